//! A shadow packet's sparse subtrees searched by their lanes alone, up to
//! four at a time, with AVX2 intrinsics ([`Packet::hand_off_sparse_subtrees`]).
//!
//! The AVX2 twin of [`super::group`]: where at most four of a packet's
//! lanes enter a child box of a voxel's BVH, those lanes (a group) search
//! the subtree below it on their own. Position `4 * r + c` of the group's
//! vectors is its r-th lane against child c of a node, or against
//! triangle c of a leaf: `H` 8-lane vectors, two lanes each, one for
//! groups of one or two lanes and two for three or four. A node then costs
//! `H` box tests for all four children instead of four tests of every
//! lane, and a leaf `H` triangle tests for all its triangles.
//!
//! Boxes are tested in the voxel's frame with the packet's own scales and
//! offsets ([`FrameRays`]), operation for operation, so a group's lanes
//! enter the boxes they would enter in the packet; triangles with the
//! packet's arithmetic (`core`, `Packet::accept`), so the same triangles
//! block the same lanes. Which blocking triangle a lane records may differ.

use super::subtree::{block_lanes, lane_order, redo_edges, walk, GroupTests};
use super::{FrameRays, Packet, Shear};
use crate::accel::{PreparedVoxel, WideNode};
use std::arch::x86_64::*;

/// Blocks every lane of `group` (one to four of the shadow packet `p`'s
/// lanes, a bit each) that a triangle below `root` blocks: a child slot of
/// a node of `vox` (`WideNode::child`), or 0 for the voxel's root. Each
/// lane is searched only within its interval `seg`; `frame` is the
/// packet's box test in `vox`'s frame.
///
/// # Safety
/// The CPU must have AVX2 and FMA.
#[inline]
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn subtree<const N: usize>(
    p: &mut Packet<N>,
    shear: &Shear<N>,
    frame: &FrameRays<N>,
    vox: &PreparedVoxel,
    seg: (&[f32; N], &[f32; N]),
    group: u32,
    root: u32,
) {
    debug_assert!((1..=4).contains(&group.count_ones()) && p.any_hit);
    if group.count_ones() <= 2 {
        search::<N, 1>(p, shear, frame, vox, seg, group, root);
    } else {
        search::<N, 2>(p, shear, frame, vox, seg, group, root);
    }
}

/// [`subtree`] with `H` vectors: at most `2 * H` lanes.
#[inline]
#[target_feature(enable = "avx2,fma")]
unsafe fn search<const N: usize, const H: usize>(
    p: &mut Packet<N>,
    shear: &Shear<N>,
    frame: &FrameRays<N>,
    vox: &PreparedVoxel,
    seg: (&[f32; N], &[f32; N]),
    group: u32,
    root: u32,
) {
    let lane_of = lane_order(group);
    let halves = |v: &[f32; N]| -> [__m256; H] {
        std::array::from_fn(|h| {
            let (a, b) = (lane_of[2 * h], lane_of[2 * h + 1]);
            _mm256_setr_m128(_mm_set1_ps(v[a]), _mm_set1_ps(v[b]))
        })
    };
    // Where a node's near and far quanta of each axis lie in it.
    let qmax = std::mem::offset_of!(WideNode, qmax);
    let plane_at = |a: usize, max: bool| (if max { qmax } else { 0 }) + 8 * a;
    let mut limit = *seg.1;
    for i in 0..N {
        limit[i] = if seg.1[i] < p.t[i] { seg.1[i] } else { p.t[i] };
    }
    // Three plain calls: through `array::map` LLVM called the closure.
    let axes = |v: &[[f32; N]; 3]| [halves(&v[0]), halves(&v[1]), halves(&v[2])];
    let rays = GroupRays::<H> {
        scale: axes(&frame.scale),
        near: axes(&frame.near),
        far: axes(&frame.far),
        near_at: [0, 1, 2].map(|a| plane_at(a, frame.near_is_max[a])),
        far_at: [0, 1, 2].map(|a| plane_at(a, !frame.near_is_max[a])),
        lo: halves(seg.0),
        limit: halves(&limit),
        org: axes(&p.org),
        t: halves(&p.t),
        tmin: _mm256_set1_ps(p.tmin),
        k: [shear.kx, shear.ky, shear.kz],
        sx: halves(&shear.sx),
        sy: halves(&shear.sy),
        sz: halves(&shear.sz),
    };
    walk(
        p,
        &Avx2Group { rays, lane_of },
        vox,
        group.count_ones(),
        root,
    );
}

/// A group's rays in `H` vectors, with AVX2.
struct Avx2Group<const H: usize> {
    rays: GroupRays<H>,
    lane_of: [usize; 4],
}

// SAFETY (every method): `subtree`'s callers run with AVX2 and FMA.
impl<const N: usize, const H: usize> GroupTests<N> for Avx2Group<H> {
    #[inline(always)]
    unsafe fn children(&self, node: &WideNode, lanes: u32) -> u32 {
        self.rays.children(node) & spread_lanes(lanes)
    }

    #[inline(always)]
    unsafe fn leaf(
        &self,
        p: &mut Packet<N>,
        vox: &PreparedVoxel,
        first: u32,
        count: u32,
        lanes: u32,
    ) -> u32 {
        leaf(p, &self.rays, vox, first, count, lanes, &self.lane_of)
    }
}

/// A group's rays, each of its lanes at four positions, and their box
/// test in one voxel's frame.
struct GroupRays<const H: usize> {
    /// Per axis, [`FrameRays`]' scale and near and far offsets.
    scale: [[__m256; H]; 3],
    near: [[__m256; H]; 3],
    far: [[__m256; H]; 3],
    /// Per axis, the byte offsets in a [`WideNode`] of the children's near
    /// and far quanta.
    near_at: [usize; 3],
    far_at: [usize; 3],
    /// The lane's interval in the voxel (`seg`): entry at or after `lo`,
    /// exit at or before `limit` (`seg`'s end, or the lane's `t`).
    lo: [__m256; H],
    limit: [__m256; H],
    org: [[__m256; H]; 3],
    t: [__m256; H],
    tmin: __m256,
    /// The shear's axis order, and its per-lane factors.
    k: [usize; 3],
    sx: [__m256; H],
    sy: [__m256; H],
    sz: [__m256; H],
}

impl<const H: usize> GroupRays<H> {
    /// Bit `4r + c`: lane r enters child c of `node` (slots past the last
    /// child never). `FrameRays::clip`'s arithmetic, with its maxima and
    /// minima taken in pairs: the same answers wherever no plane is NaN;
    /// where one is, a pair ignores it and its partner, so the group may
    /// enter a box the packet would cull, never the reverse.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn children(&self, node: &WideNode) -> u32 {
        let base = node as *const WideNode as *const u8;
        // The four children's quanta at `at`, as floats, in both halves of
        // a vector.
        let quanta = |at: usize| {
            let bits = std::ptr::read_unaligned(base.add(at) as *const i64);
            _mm256_cvtepi32_ps(_mm256_cvtepu16_epi32(_mm_set1_epi64x(bits)))
        };
        let near = [0, 1, 2].map(|a| quanta(self.near_at[a]));
        let far = [0, 1, 2].map(|a| quanta(self.far_at[a]));
        let mut slots = 0u32;
        for c in 0..4 {
            slots |= ((node.kind(c) != WideNode::EMPTY) as u32) << c;
        }
        let mut hit = 0;
        for h in 0..H {
            let plane =
                |q: __m256, scale: __m256, offset: __m256| _mm256_fmadd_ps(q, scale, offset);
            let lo = [0, 1, 2].map(|a| plane(near[a], self.scale[a][h], self.near[a][h]));
            let hi = [0, 1, 2].map(|a| plane(far[a], self.scale[a][h], self.far[a][h]));
            let t0 = _mm256_max_ps(
                _mm256_max_ps(lo[0], lo[1]),
                _mm256_max_ps(lo[2], self.lo[h]),
            );
            let t1 = _mm256_min_ps(
                _mm256_min_ps(hi[0], hi[1]),
                _mm256_min_ps(hi[2], self.limit[h]),
            );
            hit |= bits(_mm256_cmp_ps::<_CMP_LE_OQ>(t0, t1)) << (8 * h);
        }
        hit & (slots * 0x1111)
    }
}

/// Bits `4r..4r + 4` for bit r of `lanes` (r below 4).
#[inline(always)]
fn spread_lanes(lanes: u32) -> u32 {
    ((lanes & 1) * 0xF) | ((lanes & 2) * 0x78) | ((lanes & 4) * 0x3C0) | ((lanes & 8) * 0x1E00)
}

/// A bit for each position of a comparison's result, set where it holds.
#[inline]
#[target_feature(enable = "avx2,fma")]
unsafe fn bits(cmp: __m256) -> u32 {
    _mm256_movemask_ps(cmp) as u32
}

/// The group's lanes `lanes` against the `count` (1-4) triangles of a leaf
/// from `first`: blocks the packet's lanes they block; the group's bits of
/// those lanes.
#[inline]
#[target_feature(enable = "avx2,fma")]
unsafe fn leaf<const N: usize, const H: usize>(
    p: &mut Packet<N>,
    rays: &GroupRays<H>,
    vox: &PreparedVoxel,
    first: u32,
    count: u32,
    lanes: u32,
    lane_of: &[usize; 4],
) -> u32 {
    let (first, count) = (first as usize, count as usize);
    debug_assert!((1..=4).contains(&count) && first + count <= vox.corners.len());
    // The leaf's corners, 9 floats a triangle, transposed so that
    // component `3 * corner + axis` of triangle j is at positions j and
    // 4 + j. A leaf holds 1-4 of the voxel's triangles: decoding checks
    // every leaf's range and count (`Voxel::validate_tree`,
    // `MAX_LEAF_TRIANGLES`); positions past the last repeat it and are
    // masked off.
    let base = vox.corners.as_ptr().add(first) as *const f32;
    let row = |j: usize, at: usize| {
        let q = base.add(9 * j.min(count - 1) + at);
        _mm256_loadu2_m128(q, q)
    };
    let columns = |at: usize| {
        let (r0, r1, r2, r3) = (row(0, at), row(1, at), row(2, at), row(3, at));
        let (a, b) = (_mm256_unpacklo_ps(r0, r1), _mm256_unpacklo_ps(r2, r3));
        let (c, d) = (_mm256_unpackhi_ps(r0, r1), _mm256_unpackhi_ps(r2, r3));
        [
            _mm256_shuffle_ps::<0x44>(a, b),
            _mm256_shuffle_ps::<0xEE>(a, b),
            _mm256_shuffle_ps::<0x44>(c, d),
            _mm256_shuffle_ps::<0xEE>(c, d),
        ]
    };
    let [c0, c1, c2, c3] = columns(0);
    let [c4, c5, c6, c7] = columns(4);
    let [_, _, _, c8] = columns(5);
    let comp = [c0, c1, c2, c3, c4, c5, c6, c7, c8];
    let valid = spread_lanes(lanes) & (((1u32 << count) - 1) * 0x1111);
    // Half h's positions at 8h: position 4r + j of the group at bit
    // 4r + j.
    let mut take = 0;
    for h in 0..H {
        let valid = (valid >> (8 * h)) & 0xFF;
        if valid == 0 {
            continue;
        }
        take |= triangles(rays, h, &comp, valid) << (8 * h);
    }
    if take == 0 {
        return 0;
    }
    block_lanes(p, vox, first, lane_of, take)
}

/// The watertight test of half `h`'s two lanes against a leaf's
/// triangles (`comp`, transposed), positions `valid`: a bit for each
/// position whose triangle the packet would accept for its lane.
#[inline]
#[target_feature(enable = "avx2,fma")]
unsafe fn triangles<const H: usize>(
    rays: &GroupRays<H>,
    h: usize,
    comp: &[__m256; 9],
    valid: u32,
) -> u32 {
    let k = rays.k;
    let (sx, sy, sz) = (rays.sx[h], rays.sy[h], rays.sz[h]);
    // Corner `corner`'s component on the shear's axis `slot`, relative to
    // each lane's origin.
    let rel = |corner: usize, slot: usize| {
        _mm256_sub_ps(comp[3 * corner + k[slot]], rays.org[k[slot]][h])
    };
    let (az, bz, cz) = (rel(0, 2), rel(1, 2), rel(2, 2));
    let ax = _mm256_sub_ps(rel(0, 0), _mm256_mul_ps(sx, az));
    let ay = _mm256_sub_ps(rel(0, 1), _mm256_mul_ps(sy, az));
    let bx = _mm256_sub_ps(rel(1, 0), _mm256_mul_ps(sx, bz));
    let by = _mm256_sub_ps(rel(1, 1), _mm256_mul_ps(sy, bz));
    let cx = _mm256_sub_ps(rel(2, 0), _mm256_mul_ps(sx, cz));
    let cy = _mm256_sub_ps(rel(2, 1), _mm256_mul_ps(sy, cz));
    let mut u = _mm256_sub_ps(_mm256_mul_ps(cx, by), _mm256_mul_ps(cy, bx));
    let mut v = _mm256_sub_ps(_mm256_mul_ps(ax, cy), _mm256_mul_ps(ay, cx));
    let mut w = _mm256_sub_ps(_mm256_mul_ps(bx, ay), _mm256_mul_ps(by, ax));
    let mut det = _mm256_add_ps(_mm256_add_ps(u, v), w);
    let mut t = _mm256_div_ps(
        _mm256_add_ps(
            _mm256_add_ps(
                _mm256_mul_ps(u, _mm256_mul_ps(sz, az)),
                _mm256_mul_ps(v, _mm256_mul_ps(sz, bz)),
            ),
            _mm256_mul_ps(w, _mm256_mul_ps(sz, cz)),
        ),
        det,
    );
    let zero = _mm256_setzero_ps();
    let is_zero = |x: __m256| _mm256_cmp_ps::<_CMP_EQ_OQ>(x, zero);
    let edge = bits(_mm256_or_ps(
        _mm256_or_ps(is_zero(u), is_zero(v)),
        is_zero(w),
    )) & valid;
    if edge != 0 {
        // The reference's double-precision redo, position by position.
        let store = |x: __m256| {
            let mut a = [0f32; 8];
            _mm256_storeu_ps(a.as_mut_ptr(), x);
            a
        };
        let corners = [
            [store(rel(0, 0)), store(rel(0, 1)), store(az)],
            [store(rel(1, 0)), store(rel(1, 1)), store(bz)],
            [store(rel(2, 0)), store(rel(2, 1)), store(cz)],
        ];
        let (sx, sy, sz) = (store(sx), store(sy), store(sz));
        let (mut uu, mut vv, mut ww, mut tt) = (store(u), store(v), store(w), store(t));
        let mut dd = store(det);
        redo_edges(
            edge,
            &corners,
            [&sx, &sy, &sz],
            [&mut uu, &mut vv, &mut ww, &mut tt, &mut dd],
        );
        let load = |a: &[f32; 8]| _mm256_loadu_ps(a.as_ptr());
        (u, v, w, t, det) = (load(&uu), load(&vv), load(&ww), load(&tt), load(&dd));
    }
    // `Packet::accept` for a lane still unblocked.
    let below = |x: __m256| _mm256_cmp_ps::<_CMP_LT_OQ>(x, zero);
    let above = |x: __m256| _mm256_cmp_ps::<_CMP_GT_OQ>(x, zero);
    let neg = bits(_mm256_or_ps(_mm256_or_ps(below(u), below(v)), below(w)));
    let pos = bits(_mm256_or_ps(_mm256_or_ps(above(u), above(v)), above(w)));
    let abs_t = _mm256_andnot_ps(_mm256_set1_ps(-0.0), t);
    let inside = !(neg & pos)
        & bits(_mm256_cmp_ps::<_CMP_NEQ_UQ>(det, zero))
        & bits(_mm256_cmp_ps::<_CMP_GT_OQ>(t, rays.tmin))
        & bits(_mm256_cmp_ps::<_CMP_LT_OQ>(
            abs_t,
            _mm256_set1_ps(f32::INFINITY),
        ))
        & bits(_mm256_cmp_ps::<_CMP_LT_OQ>(t, rays.t[h]));
    inside & valid
}
