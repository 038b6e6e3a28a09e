//! A shadow packet's sparse subtrees searched by their lanes alone, four
//! at a time, with AVX-512 intrinsics ([`Packet::hand_off_sparse_subtrees`]).
//!
//! Where at most four of a 16-lane packet's lanes enter a child box of a
//! voxel's BVH, those lanes (a group) search the subtree below it on their
//! own, with every vector full: position `4 * r + c` of a 16-lane vector
//! is the group's r-th lane against child c of a node, or against triangle
//! c of a leaf. The rays' data is gathered into those positions once per
//! subtree, not once per node as [`crate::quad`] does, and a leaf's
//! triangles are tested in one pass instead of one pass each.
//!
//! The arithmetic of every (lane, box) and (lane, triangle) pair gives the
//! packet's own results (`Packet::slab_within`, `core`, `Packet::accept`),
//! so the same boxes are entered and the same triangles block the same
//! lanes. A lane's answer, blocked or not, does not depend on the order
//! triangles are tested in; which blocking triangle a lane records may.
//!
//! What a node visit costs here is mostly the path from its load to its
//! children's lane masks, even with every load an L1 hit. Node boxes kept
//! in floats would cut that path but double the nodes' memory, which costs
//! more with cold caches (`scripts/bench-kernel`); the box test's last
//! steps take the shortest exact forms instead (see
//! [`GroupRays::children`]).

use super::subtree::{block_lanes, lane_order, redo_edges, walk, GroupTests};
use super::{Packet, Shear, WIDEN};
use crate::accel::{PreparedVoxel, WideNode};
use std::arch::x86_64::*;

/// Blocks every lane of `group` (at most four of the shadow packet `p`'s
/// lanes) that a triangle below `root` blocks: a child slot of a node of
/// `vox` (`WideNode::child`), or 0 for the voxel's root. Each lane is
/// searched only within its interval `seg`.
///
/// # Safety
/// The CPU must have AVX-512F and BMI2.
#[inline]
#[target_feature(enable = "avx512f,bmi2")]
pub(super) unsafe fn subtree(
    p: &mut Packet<16>,
    shear: &Shear<16>,
    vox: &PreparedVoxel,
    seg: (&[f32; 16], &[f32; 16]),
    group: u32,
    root: u32,
) {
    debug_assert!(group.count_ones() <= 4 && p.tmin >= 0.0);
    // Position 4r + c takes the r-th lane of the group (positions of lanes
    // past the group's last repeat its first and are masked off).
    let iota = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    let live = _mm512_maskz_compress_epi32(group as u16, iota);
    let spread = _mm512_setr_epi32(0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3);
    let index = _mm512_permutexvar_epi32(spread, live);
    let gather = |v: &[f32; 16]| _mm512_permutexvar_ps(index, _mm512_loadu_ps(v.as_ptr()));
    let rays = GroupRays {
        org: [gather(&p.org[0]), gather(&p.org[1]), gather(&p.org[2])],
        inv: [gather(&p.inv[0]), gather(&p.inv[1]), gather(&p.inv[2])],
        lo: gather(seg.0),
        t: gather(&p.t),
        limit: _mm512_min_ps(gather(seg.1), gather(&p.t)),
        tmin: _mm512_set1_ps(p.tmin),
        k: [shear.kx, shear.ky, shear.kz],
        sx: gather(&shear.sx),
        sy: gather(&shear.sy),
        sz: gather(&shear.sz),
        flat: [0, 1, 2]
            .map(|a| _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(gather(&p.dir[a]), _mm512_setzero_ps())),
    };
    let tests = Avx512Group {
        rays,
        frame: Dequantizer::new(vox),
        lane_of: lane_order(group),
    };
    walk(p, &tests, vox, group.count_ones(), root);
}

/// A group's rays and the voxel's frame, with AVX-512.
struct Avx512Group {
    rays: GroupRays,
    frame: Dequantizer,
    lane_of: [usize; 4],
}

// SAFETY (every method): `subtree`'s callers run with AVX-512F and BMI2.
impl GroupTests<16> for Avx512Group {
    #[inline(always)]
    unsafe fn children(&self, node: &WideNode, lanes: u32) -> u32 {
        self.rays.children(&self.frame, node) & spread_lanes(lanes)
    }

    #[inline(always)]
    unsafe fn leaf(
        &self,
        p: &mut Packet<16>,
        vox: &PreparedVoxel,
        first: u32,
        count: u32,
        lanes: u32,
    ) -> u32 {
        leaf(p, &self.rays, vox, first, count, lanes, &self.lane_of)
    }

    #[inline(always)]
    unsafe fn child_lanes(hit: u32, c: usize) -> u32 {
        _pext_u32(hit, 0x1111 << c)
    }
}

/// Bit `4r + c` for every c, from bit r of `lanes`.
#[inline(always)]
fn spread_lanes(lanes: u32) -> u32 {
    // SAFETY: callers run with BMI2.
    unsafe { _pdep_u32(lanes, 0x1111) * 0xF }
}

/// A group's rays, each of its lanes at four positions.
struct GroupRays {
    org: [__m512; 3],
    inv: [__m512; 3],
    /// The lane's interval in the voxel (`seg`): entry at or after `lo`,
    /// exit at or before `limit` (`seg`'s end, or the lane's `t`).
    lo: __m512,
    t: __m512,
    limit: __m512,
    tmin: __m512,
    /// The shear's axis order, and its per-lane factors.
    k: [usize; 3],
    sx: __m512,
    sy: __m512,
    sz: __m512,
    /// Per axis, the positions whose lane's direction has no component on
    /// it (a light straight along an axis).
    flat: [__mmask16; 3],
}

/// A voxel's frame as vectors: the planes of a node's quanta.
struct Dequantizer {
    /// For a node's first 16 quanta (qmin x, y, z, then qmax x) and its
    /// last 8 (qmax y, z).
    origin_lo: __m512,
    scale_lo: __m512,
    origin_hi: __m256,
    scale_hi: __m256,
}

impl Dequantizer {
    #[inline]
    #[target_feature(enable = "avx512f")]
    unsafe fn new(vox: &PreparedVoxel) -> Dequantizer {
        let (o, s) = (vox.frame.origin, vox.frame.scale);
        let per_axis = |v: [f32; 3], axes: [usize; 4]| {
            let mut out = [0f32; 16];
            for (block, &a) in axes.iter().enumerate() {
                out[4 * block..4 * block + 4].fill(v[a]);
            }
            out
        };
        let o_lo = per_axis(o, [0, 1, 2, 0]);
        let s_lo = per_axis(s, [0, 1, 2, 0]);
        let o_hi = per_axis(o, [1, 2, 1, 2]);
        let s_hi = per_axis(s, [1, 2, 1, 2]);
        Dequantizer {
            origin_lo: _mm512_loadu_ps(o_lo.as_ptr()),
            scale_lo: _mm512_loadu_ps(s_lo.as_ptr()),
            origin_hi: _mm256_loadu_ps(o_hi.as_ptr()),
            scale_hi: _mm256_loadu_ps(s_hi.as_ptr()),
        }
    }
}

impl GroupRays {
    /// Bit `4r + c`: lane r enters child c of `node` (slots past the last
    /// child never).
    #[inline]
    #[target_feature(enable = "avx512f")]
    unsafe fn children(&self, frame: &Dequantizer, node: &WideNode) -> u32 {
        // `Frame::plane` for all 24 quanta: origin + q * scale.
        let q = node.qmin.as_ptr() as *const u8;
        let q_lo = _mm512_cvtepu16_epi32(_mm256_loadu_si256(q as *const __m256i));
        let q_hi = _mm256_cvtepu16_epi32(_mm_loadu_si128(q.add(32) as *const __m128i));
        let planes_lo = _mm512_add_ps(
            frame.origin_lo,
            _mm512_mul_ps(_mm512_cvtepi32_ps(q_lo), frame.scale_lo),
        );
        let planes_hi = _mm512_castps256_ps512(_mm256_add_ps(
            frame.origin_hi,
            _mm256_mul_ps(_mm256_cvtepi32_ps(q_hi), frame.scale_hi),
        ));
        // Block b of 4 floats in every 128-bit quarter.
        let min = [
            _mm512_shuffle_f32x4::<0x00>(planes_lo, planes_lo),
            _mm512_shuffle_f32x4::<0x55>(planes_lo, planes_lo),
            _mm512_shuffle_f32x4::<0xAA>(planes_lo, planes_lo),
        ];
        let max = [
            _mm512_shuffle_f32x4::<0xFF>(planes_lo, planes_lo),
            _mm512_shuffle_f32x4::<0x00>(planes_hi, planes_hi),
            _mm512_shuffle_f32x4::<0x55>(planes_hi, planes_hi),
        ];
        let mut lo = [_mm512_setzero_ps(); 3];
        let mut hi = [_mm512_setzero_ps(); 3];
        for a in 0..3 {
            let near = _mm512_mul_ps(_mm512_sub_ps(min[a], self.org[a]), self.inv[a]);
            let far = _mm512_mul_ps(_mm512_sub_ps(max[a], self.org[a]), self.inv[a]);
            lo[a] = _mm512_min_ps(near, far);
            hi[a] = _mm512_max_ps(far, near);
            if self.flat[a] != 0 {
                // `Sign::WithZero`: a lane without a component on this
                // axis is in the slab for every t, or for none.
                let inside = _mm512_cmp_ps_mask::<_CMP_LE_OQ>(min[a], self.org[a])
                    & _mm512_cmp_ps_mask::<_CMP_LE_OQ>(self.org[a], max[a]);
                let (big, small) = (_mm512_set1_ps(f32::MAX), _mm512_set1_ps(-f32::MAX));
                let flat_lo = _mm512_mask_blend_ps(inside, big, small);
                let flat_hi = _mm512_mask_blend_ps(inside, small, big);
                lo[a] = _mm512_mask_blend_ps(self.flat[a], lo[a], flat_lo);
                hi[a] = _mm512_mask_blend_ps(self.flat[a], hi[a], flat_hi);
            }
        }
        // Maxima and minima in pairs (exact in any order). Widening: with
        // W a power of two, t - |t| * W is t * (1 - W) for t >= 0, and
        // t + |t| * W is t * (1 + W): one rounding of the same value. Entry
        // is never negative here (`seg`'s entry is at least `tmin`, and
        // `tmin >= 0`); an exit below zero stays below zero either way, so
        // the decision is the same.
        let t0 = _mm512_max_ps(_mm512_max_ps(lo[0], lo[1]), _mm512_max_ps(lo[2], self.lo));
        let exit = _mm512_min_ps(_mm512_min_ps(hi[0], hi[1]), hi[2]);
        let t0 = _mm512_mul_ps(t0, _mm512_set1_ps(1.0 - WIDEN));
        let exit = _mm512_mul_ps(exit, _mm512_set1_ps(1.0 + WIDEN));
        let t1 = _mm512_min_ps(exit, self.limit);
        let mut slots = 0u32;
        for c in 0..4 {
            slots |= ((node.kind(c) != WideNode::EMPTY) as u32) << c;
        }
        u32::from(_mm512_cmp_ps_mask::<_CMP_LE_OQ>(t0, t1)) & (slots * 0x1111)
    }
}

#[inline(always)]
fn abs(v: __m512) -> __m512 {
    // SAFETY: callers run with AVX-512F.
    unsafe {
        _mm512_castsi512_ps(_mm512_and_si512(
            _mm512_castps_si512(v),
            _mm512_set1_epi32(0x7FFF_FFFF),
        ))
    }
}

/// The group's lanes `lanes` against the `count` (1-4) triangles of a leaf
/// from `first`: blocks the packet's lanes they block; the group's bits of
/// those lanes.
#[inline]
#[target_feature(enable = "avx512f,bmi2")]
unsafe fn leaf(
    p: &mut Packet<16>,
    rays: &GroupRays,
    vox: &PreparedVoxel,
    first: u32,
    count: u32,
    lanes: u32,
    lane_of: &[usize; 4],
) -> u32 {
    let (first, count) = (first as usize, count as usize);
    debug_assert!((1..=4).contains(&count) && first + count <= vox.corners.len());
    // The leaf's corners, 9 floats a triangle, in three registers; masked
    // loads read nothing past the last triangle. A leaf holds 1-4 of the
    // voxel's triangles: decoding checks every leaf's range and count
    // (`Voxel::validate_tree`, `MAX_LEAF_TRIANGLES`), and the wide nodes
    // are built from those leaves.
    let base = vox.corners.as_ptr().wrapping_add(first) as *const f32;
    let floats = 9 * count;
    let load = |at: usize| {
        let n = floats.saturating_sub(at).min(16);
        _mm512_maskz_loadu_ps(((1u32 << n) - 1) as u16, base.wrapping_add(at))
    };
    let (v0, v1, v2) = (load(0), load(16), load(32));
    // Position 4r + j takes triangle j: its float at 9j + 3 * corner + axis.
    let nine = _mm512_setr_epi32(0, 9, 18, 27, 0, 9, 18, 27, 0, 9, 18, 27, 0, 9, 18, 27);
    let k = rays.k;
    // Corner `corner`'s component on the shear's axis `slot`, relative to
    // each lane's origin.
    let rel = |corner: usize, slot: usize| {
        let at = _mm512_add_epi32(nine, _mm512_set1_epi32((3 * corner + k[slot]) as i32));
        let low = _mm512_permutex2var_ps(v0, at, v1);
        let high = _mm512_cmpge_epi32_mask(at, _mm512_set1_epi32(32));
        let c = _mm512_mask_permutexvar_ps(low, high, at, v2);
        _mm512_sub_ps(c, rays.org[k[slot]])
    };
    let (az, bz, cz) = (rel(0, 2), rel(1, 2), rel(2, 2));
    let ax = _mm512_sub_ps(rel(0, 0), _mm512_mul_ps(rays.sx, az));
    let ay = _mm512_sub_ps(rel(0, 1), _mm512_mul_ps(rays.sy, az));
    let bx = _mm512_sub_ps(rel(1, 0), _mm512_mul_ps(rays.sx, bz));
    let by = _mm512_sub_ps(rel(1, 1), _mm512_mul_ps(rays.sy, bz));
    let cx = _mm512_sub_ps(rel(2, 0), _mm512_mul_ps(rays.sx, cz));
    let cy = _mm512_sub_ps(rel(2, 1), _mm512_mul_ps(rays.sy, cz));
    let mut u = _mm512_sub_ps(_mm512_mul_ps(cx, by), _mm512_mul_ps(cy, bx));
    let mut v = _mm512_sub_ps(_mm512_mul_ps(ax, cy), _mm512_mul_ps(ay, cx));
    let mut w = _mm512_sub_ps(_mm512_mul_ps(bx, ay), _mm512_mul_ps(by, ax));
    let mut det = _mm512_add_ps(_mm512_add_ps(u, v), w);
    let mut t = _mm512_div_ps(
        _mm512_add_ps(
            _mm512_add_ps(
                _mm512_mul_ps(u, _mm512_mul_ps(rays.sz, az)),
                _mm512_mul_ps(v, _mm512_mul_ps(rays.sz, bz)),
            ),
            _mm512_mul_ps(w, _mm512_mul_ps(rays.sz, cz)),
        ),
        det,
    );
    let valid = spread_lanes(lanes) & (((1u32 << count) - 1) * 0x1111);
    let zero = _mm512_setzero_ps();
    let edge = u32::from(
        _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(u, zero)
            | _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(v, zero)
            | _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(w, zero),
    ) & valid;
    if edge != 0 {
        // The reference's double-precision redo, position by position.
        let store = |x: __m512| {
            let mut a = [0f32; 16];
            _mm512_storeu_ps(a.as_mut_ptr(), x);
            a
        };
        let corners = [
            [store(rel(0, 0)), store(rel(0, 1)), store(az)],
            [store(rel(1, 0)), store(rel(1, 1)), store(bz)],
            [store(rel(2, 0)), store(rel(2, 1)), store(cz)],
        ];
        let (sx, sy, sz) = (store(rays.sx), store(rays.sy), store(rays.sz));
        let (mut uu, mut vv, mut ww, mut tt) = (store(u), store(v), store(w), store(t));
        let mut dd = store(det);
        redo_edges(
            edge,
            &corners,
            [&sx, &sy, &sz],
            [&mut uu, &mut vv, &mut ww, &mut tt, &mut dd],
        );
        let load = |a: &[f32; 16]| _mm512_loadu_ps(a.as_ptr());
        (u, v, w, t, det) = (load(&uu), load(&vv), load(&ww), load(&tt), load(&dd));
    }
    // `Packet::accept` for a lane still unblocked.
    let neg = _mm512_cmp_ps_mask::<_CMP_LT_OQ>(u, zero)
        | _mm512_cmp_ps_mask::<_CMP_LT_OQ>(v, zero)
        | _mm512_cmp_ps_mask::<_CMP_LT_OQ>(w, zero);
    let pos = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(u, zero)
        | _mm512_cmp_ps_mask::<_CMP_GT_OQ>(v, zero)
        | _mm512_cmp_ps_mask::<_CMP_GT_OQ>(w, zero);
    let inside = !(neg & pos)
        & _mm512_cmp_ps_mask::<_CMP_NEQ_UQ>(det, zero)
        & _mm512_cmp_ps_mask::<_CMP_GT_OQ>(t, rays.tmin)
        & _mm512_cmp_ps_mask::<_CMP_LT_OQ>(abs(t), _mm512_set1_ps(f32::INFINITY))
        & _mm512_cmp_ps_mask::<_CMP_LT_OQ>(t, rays.t);
    let take = u32::from(inside) & valid;
    if take == 0 {
        return 0;
    }
    block_lanes(p, vox, first, lane_of, take)
}
