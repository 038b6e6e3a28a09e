//! Box tests for 16-lane packets with AVX-512 intrinsics: lane masks, and
//! a node's four children tested at once for up to four lanes.
//!
//! Far from the model most of a packet's lanes part ways: from outside the
//! plants a child box that some lane enters is entered by only a few of
//! the 16. Testing a node's four children one after another costs four
//! 16-lane slab tests whatever the number of lanes; with at most four
//! lanes left, one 16-lane vector holds every (lane, child) pair instead:
//! position `4 * r + c` is the r-th live lane against child c. The
//! arithmetic of each pair is the packet's, so the same boxes are entered.
//!
//! The lane masks need the comparison's mask register as an integer,
//! which LLVM builds bit by bit from a comparison of lane arrays; the
//! intrinsics read it in one instruction. Callers must run on a CPU with
//! AVX-512F and BMI2 ([`crate::render::Isa::Avx512`] checked). Other
//! processors never take this path; [`children_by_lane`] is the same test
//! written out lane by lane (the reference the tests compare with).

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::*;

/// Relative widening of every culling interval (as `packet::WIDEN`).
const WIDEN: f32 = 1.0 / 65536.0;

/// Whether this CPU has what [`lanes_le`] and [`children`] need.
pub(crate) fn available() -> bool {
    #[cfg(target_arch = "x86_64")]
    return is_x86_feature_detected!("avx512f") && is_x86_feature_detected!("bmi2");
    #[cfg(not(target_arch = "x86_64"))]
    return false;
}

/// The lanes where `t0 <= t1`, one bit each.
///
/// # Safety
/// The CPU must have AVX-512F.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx512f")]
pub(crate) unsafe fn lanes_le(t0: &[f32; 16], t1: &[f32; 16]) -> u32 {
    let a = _mm512_loadu_ps(t0.as_ptr());
    let b = _mm512_loadu_ps(t1.as_ptr());
    u32::from(_mm512_cmp_ps_mask::<_CMP_LE_OQ>(a, b))
}

/// What a packet's box test needs of its rays, per lane.
pub(crate) struct Rays<'a> {
    pub org: &'a [[f32; 16]; 3],
    pub inv: &'a [[f32; 16]; 3],
    /// The lane's interval: entry at or after `lo`, exit at or before the
    /// nearer of `hi` and `t`.
    pub lo: &'a [f32; 16],
    pub hi: &'a [f32; 16],
    pub t: &'a [f32; 16],
}

/// For each of a node's four children (boxes `bmin`, `bmax`, per axis
/// and child; slots not in `slots` are skipped), the lanes of `lanes` (at
/// most four) that enter it.
///
/// # Safety
/// The CPU must have AVX-512F and BMI2.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx512f,bmi2")]
pub(crate) unsafe fn children(
    rays: &Rays,
    bmin: &[[f32; 4]; 3],
    bmax: &[[f32; 4]; 3],
    lanes: u32,
    slots: u32,
) -> [u32; 4] {
    debug_assert!(lanes.count_ones() <= 4);
    // Position 4r + c takes the r-th lane of `lanes` (positions of rays
    // past the last lane repeat lane 0 and are masked off below).
    let iota = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    let live = _mm512_maskz_compress_epi32(lanes as u16, iota);
    let spread = _mm512_setr_epi32(0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3);
    let index = _mm512_permutexvar_epi32(spread, live);
    let gather = |v: &[f32; 16]| _mm512_permutexvar_ps(index, _mm512_loadu_ps(v.as_ptr()));
    let mut t0 = gather(rays.lo);
    let mut exit = _mm512_set1_ps(f32::INFINITY);
    for a in 0..3 {
        let org = gather(&rays.org[a]);
        let inv = gather(&rays.inv[a]);
        // Child c at positions c, 4 + c, 8 + c, 12 + c.
        let min = _mm512_broadcast_f32x4(_mm_loadu_ps(bmin[a].as_ptr()));
        let max = _mm512_broadcast_f32x4(_mm_loadu_ps(bmax[a].as_ptr()));
        let near = _mm512_mul_ps(_mm512_sub_ps(min, org), inv);
        let far = _mm512_mul_ps(_mm512_sub_ps(max, org), inv);
        // The packet's slab test for lanes of mixed signs, selection for
        // selection: lo = near < far ? near : far, hi the other; then
        // t0 = lo > t0 ? lo : t0 and exit = hi < exit ? hi : exit.
        let lo = _mm512_min_ps(near, far);
        let hi = _mm512_max_ps(far, near);
        t0 = _mm512_max_ps(lo, t0);
        exit = _mm512_min_ps(hi, exit);
    }
    let abs = |v: __m512| {
        _mm512_castsi512_ps(_mm512_and_si512(
            _mm512_castps_si512(v),
            _mm512_set1_epi32(0x7FFF_FFFF),
        ))
    };
    let widen = _mm512_set1_ps(WIDEN);
    t0 = _mm512_sub_ps(t0, _mm512_mul_ps(abs(t0), widen));
    let exit = _mm512_add_ps(exit, _mm512_mul_ps(abs(exit), widen));
    // limit = hi < t ? hi : t; t1 = exit < limit ? exit : limit.
    let limit = _mm512_min_ps(gather(rays.hi), gather(rays.t));
    let t1 = _mm512_min_ps(exit, limit);
    let rays_live = (1u32 << (4 * lanes.count_ones())) - 1;
    let hit = u32::from(_mm512_cmp_ps_mask::<_CMP_LE_OQ>(t0, t1)) & rays_live & (slots * 0x1111);
    [0, 1, 2, 3].map(|c| _pdep_u32(_pext_u32(hit, 0x1111 << c), lanes))
}

/// [`children`] lane by lane, with the packet's arithmetic.
#[cfg(any(test, not(target_arch = "x86_64")))]
pub(crate) fn children_by_lane(
    rays: &Rays,
    bmin: &[[f32; 4]; 3],
    bmax: &[[f32; 4]; 3],
    lanes: u32,
    slots: u32,
) -> [u32; 4] {
    [0, 1, 2, 3].map(|c| {
        let mut entered = 0u32;
        if slots & (1 << c) == 0 {
            return 0;
        }
        for i in 0..16 {
            if lanes & (1 << i) == 0 {
                continue;
            }
            let (mut t0, mut exit) = (rays.lo[i], f32::INFINITY);
            for a in 0..3 {
                let near = (bmin[a][c] - rays.org[a][i]) * rays.inv[a][i];
                let far = (bmax[a][c] - rays.org[a][i]) * rays.inv[a][i];
                let (lo, hi) = if near < far { (near, far) } else { (far, near) };
                t0 = if lo > t0 { lo } else { t0 };
                exit = if hi < exit { hi } else { exit };
            }
            t0 -= t0.abs() * WIDEN;
            let exit = exit + exit.abs() * WIDEN;
            let limit = if rays.hi[i] < rays.t[i] {
                rays.hi[i]
            } else {
                rays.t[i]
            };
            let t1 = if exit < limit { exit } else { limit };
            entered |= ((t0 <= t1) as u32) << i;
        }
        entered
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Against the packet's own test written out lane by lane: every
    /// (lane, child) pair, for random boxes, rays and lane sets.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn children_match_lane_by_lane_tests() {
        if !(is_x86_feature_detected!("avx512f") && is_x86_feature_detected!("bmi2")) {
            return;
        }
        let mut r = dray_scene::rng::Rng::new(3);
        for _ in 0..2000 {
            let mut org = [[0f32; 16]; 3];
            let mut inv = [[0f32; 16]; 3];
            let (mut lo, mut hi, mut t) = ([0f32; 16], [0f32; 16], [0f32; 16]);
            for i in 0..16 {
                for a in 0..3 {
                    org[a][i] = r.range(-2.0, 2.0);
                    let d: f32 = r.range(-1.0, 1.0);
                    inv[a][i] = 1.0 / if d == 0.0 { 1e-30 } else { d };
                }
                lo[i] = r.range(0.0, 1.0);
                hi[i] = r.range(0.0, 8.0);
                t[i] = if r.below(4) == 0 {
                    f32::INFINITY
                } else {
                    r.range(0.0, 8.0)
                };
            }
            let mut bmin = [[0f32; 4]; 3];
            let mut bmax = [[0f32; 4]; 3];
            for a in 0..3 {
                for c in 0..4 {
                    let (x, y) = (r.range(-1.5, 1.5), r.range(-1.5, 1.5));
                    bmin[a][c] = x.min(y);
                    bmax[a][c] = x.max(y);
                }
            }
            let mut lanes = 0u32;
            for _ in 0..r.int(1, 4) {
                lanes |= 1 << r.below(16);
            }
            let slots = r.int(1, 15);
            let rays = Rays {
                org: &org,
                inv: &inv,
                lo: &lo,
                hi: &hi,
                t: &t,
            };
            // SAFETY: checked above.
            let got = unsafe { children(&rays, &bmin, &bmax, lanes, slots) };
            let want = children_by_lane(&rays, &bmin, &bmax, lanes, slots);
            assert_eq!(got, want, "lanes {lanes:#x}, slots {slots:#x}");
        }
    }
}
