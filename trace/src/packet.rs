//! Ray packets and the suspendable two-level traversal.
//!
//! A [`Packet`] holds `N` rays in structure-of-arrays form. Every loop over
//! its lanes is a plain `for i in 0..N` over fixed-size arrays, written
//! without branches, so that LLVM turns it into SIMD: the render entry
//! points (`render.rs`) instantiate this code inside functions compiled for
//! AVX-512 or AVX2 (16 or 32 lanes), chosen at run time, with a portable
//! fallback (8 lanes). Hand-written intrinsics would tie the kernel to one
//! ISA; the generated code was checked (objdump) to do its arithmetic on
//! full-width vector registers. The exceptions are where a vector holds
//! several lanes against a node's four children at once, which LLVM does
//! not emit from lane loops: sparse 16-lane packets (`crate::quad`, with a
//! lane-by-lane twin a test compares them with), and shadow subtrees handed
//! over to groups of lanes (`group` for AVX-512, `group_avx2`; tests
//! compare the packets that hand over with brute force).
//!
//! [`Traversal`] walks the high-level BSP front to back as a hierarchy of
//! content boxes, then each voxel's 4-wide BVH, culling per lane against
//! the lane's nearest hit so far and the lane's interval inside the
//! voxel's content box. When it reaches a voxel the source does
//! not hold, it stops and returns [`Step::Missing`]: its whole state (the
//! stack and the packet's hits) stays in the `Traversal`, and calling
//! [`Traversal::run`] again later resumes exactly there. The nearest hit is
//! the minimum over all triangles of (distance, original id), so any order of
//! voxels, and any pattern of suspensions, gives bit-identical results.

// Lane loops index several arrays in lockstep on purpose: that is the
// shape LLVM vectorizes.
#![allow(clippy::needless_range_loop)]

#[cfg(target_arch = "x86_64")]
mod group;
#[cfg(target_arch = "x86_64")]
mod group_avx2;
#[cfg(target_arch = "x86_64")]
mod subtree;

use crate::accel::{prefetch, Frame, PreparedVoxel, TopLevel, TopNode, VoxelSource, WideNode};
use crate::quad;
use crate::render::Isa;
use glam::Vec3;

/// Relative widening of every culling interval: slab tests round, and a
/// box or cell must never be culled because of it.
const WIDEN: f32 = 1.0 / 65536.0;
/// The margin of [`FrameRays`]' intervals, relative to the largest
/// magnitude in their sums: 16 units in the last place, where the
/// rounding of the planes, of the box test and of the triangle test's
/// distances adds up to at most a few.
const MARGIN: f32 = 1.0 / 1_048_576.0;
/// Stand-in for a zero direction component in the reciprocal (never in the
/// triangle test), so that no NaN reaches the interval arithmetic. Slab
/// tests do not use it for such a lane: a ray exactly in the plane of a
/// box's face would exit there at 0 (`0 * 1e30`), before its `tmin`, and
/// miss a triangle through that face's edge ([`Sign::WithZero`]).
const TINY: f32 = 1e-30;

/// The sign of one direction component across a packet's lanes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Sign {
    /// Every lane's reciprocal is positive: the min plane is near.
    Positive,
    /// Every lane's reciprocal is negative: the max plane is near.
    Negative,
    Mixed,
    /// Some lane's component is exactly zero: that lane is inside the slab
    /// for every `t` or for none, as its origin is. (With light
    /// `0,1,0`, shadow rays from points exactly on a box's face missed
    /// triangles through its edge.)
    WithZero,
}

/// N rays and what they found.
///
/// Aligned to cache lines, so that each lane array of a 16-lane packet
/// is one AVX-512 register's load, never split across two lines (measured
/// by `scripts/bench-kernel`).
#[derive(Clone, Debug)]
#[repr(align(64))]
pub struct Packet<const N: usize> {
    /// Origins and directions, per axis.
    pub org: [[f32; N]; 3],
    pub dir: [[f32; N]; 3],
    inv: [[f32; N]; 3],
    /// Per axis, whether every lane's direction has the same sign: the
    /// slab test then knows which plane is near without comparing.
    signs: [Sign; 3],
    /// Hits count only in `(tmin, t)`: `t` starts at the ray's far limit.
    pub tmin: f32,
    pub t: [f32; N],
    /// ORIGINAL triangle id of the nearest hit, `u32::MAX` for none.
    pub id: [u32; N],
    /// Voxel and voxel-local triangle of the hit, and the barycentric
    /// weights of its second and third corners (for shading; a shadow
    /// packet leaves them as they were: nothing shades its hits).
    pub voxel: [u32; N],
    pub tri: [u32; N],
    pub u: [f32; N],
    pub v: [f32; N],
    /// Any-hit query (shadow rays): a lane stops at its first hit and its
    /// `t` becomes `-inf`.
    pub any_hit: bool,
    /// Whether to count, at every child box of the voxels' BVHs that some
    /// lane enters, how many do (`child_hits`, `child_lanes`): how
    /// coherent the packet is ([`crate::render::PacketChooser`]). Counting
    /// is not free, so only a sample of the packets does it.
    pub count_lanes: bool,
    pub child_hits: u32,
    pub child_lanes: u32,
    /// Whether the packet may use AVX-512 intrinsics (`crate::quad`):
    /// set only where the CPU has AVX-512F and BMI2, and used only with 16
    /// lanes.
    pub(crate) quad: bool,
    /// Whether a shadow packet hands the subtrees of a voxel's BVH that
    /// few of its lanes enter over to those lanes, and how
    /// ([`Packet::hand_off_sparse_subtrees`]).
    pub(crate) groups: Groups,
    /// Subtrees handed over so far (the tests check that hand-overs
    /// happen).
    pub group_searches: u32,
}

/// How a shadow packet's sparse subtrees are searched: by the whole packet,
/// or handed over to the few lanes that enter them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Groups {
    /// Every subtree searched by the whole packet.
    Off,
    /// Up to four lanes at a time in one AVX-512 vector (`group`): 16-lane
    /// packets where the CPU has AVX-512F and BMI2.
    Avx512,
    /// Up to four lanes at a time in two AVX2 vectors (`group_avx2`):
    /// packets of up to 16 lanes where the CPU has AVX2, in voxels where
    /// their lanes agree on every direction sign (the box test in the
    /// voxel's frame, [`FrameRays`]).
    Avx2,
}

/// A triangle that blocked a shadow ray: its corners and ORIGINAL id
/// (a shadow packet's lanes need nothing else of their hits).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Occluder {
    pub corners: [[f32; 3]; 3],
    pub id: u32,
}

impl<const N: usize> Packet<N> {
    /// A packet of rays from `origins` along unit `dirs`, far limit `tmax`.
    #[inline(always)]
    pub fn new(origins: &[Vec3; N], dirs: &[Vec3; N], tmin: f32, tmax: f32) -> Packet<N> {
        let org = [0, 1, 2].map(|a| std::array::from_fn(|i| origins[i][a]));
        let dir = [0, 1, 2].map(|a| std::array::from_fn(|i| dirs[i][a]));
        Packet::from_axes(&org, &dir, tmin, tmax)
    }

    /// [`Self::new`] from origins and directions given axis by axis
    /// (`org[axis][lane]`).
    #[inline(always)]
    pub fn from_axes(org: &[[f32; N]; 3], dir: &[[f32; N]; 3], tmin: f32, tmax: f32) -> Packet<N> {
        let mut p = Packet {
            org: [[0.0; N]; 3],
            dir: [[0.0; N]; 3],
            inv: [[0.0; N]; 3],
            signs: [Sign::Mixed; 3],
            tmin,
            t: [tmax; N],
            id: [u32::MAX; N],
            voxel: [u32::MAX; N],
            tri: [u32::MAX; N],
            u: [0.0; N],
            v: [0.0; N],
            any_hit: false,
            count_lanes: false,
            child_hits: 0,
            child_lanes: 0,
            quad: false,
            groups: Groups::Off,
            group_searches: 0,
        };
        p.aim(org, dir, tmin, tmax);
        p
    }

    /// Makes this packet the one [`Packet::from_axes`] builds, in place: a
    /// packet is about a kilobyte at 16 lanes, and one built and then
    /// moved into a job is copied through the stack every time.
    #[inline(always)]
    pub fn aim(&mut self, org: &[[f32; N]; 3], dir: &[[f32; N]; 3], tmin: f32, tmax: f32) {
        for a in 0..3 {
            for i in 0..N {
                let d = dir[a][i];
                let guarded = if d == 0.0 { TINY.copysign(d) } else { d };
                self.inv[a][i] = 1.0 / guarded;
            }
        }
        let inv = &self.inv;
        // `array::map`, unlike the kernel's other per-packet loops: as a
        // loop this was faster with AVX2 but slower with AVX-512.
        self.signs = [0, 1, 2].map(|a| {
            let mut positive = true;
            let mut negative = true;
            let mut zero = false;
            for i in 0..N {
                positive &= inv[a][i] > 0.0;
                negative &= inv[a][i] < 0.0;
                zero |= dir[a][i] == 0.0;
            }
            match (zero, positive, negative) {
                (true, _, _) => Sign::WithZero,
                (_, true, _) => Sign::Positive,
                (_, _, true) => Sign::Negative,
                _ => Sign::Mixed,
            }
        });
        self.org = *org;
        self.dir = *dir;
        self.tmin = tmin;
        self.t = [tmax; N];
        self.id = [u32::MAX; N];
        self.voxel = [u32::MAX; N];
        self.tri = [u32::MAX; N];
        self.u = [0.0; N];
        self.v = [0.0; N];
        self.any_hit = false;
        self.count_lanes = false;
        self.child_hits = 0;
        self.child_lanes = 0;
        self.quad = false;
        self.groups = Groups::Off;
        self.group_searches = 0;
    }

    /// Lets a shadow packet (`any_hit`, `tmin` not negative, every lane
    /// with the same axis order in the triangle test, as a distant light's
    /// rays have) search each subtree of a voxel's BVH that few of its
    /// lanes enter (at most four) with those lanes alone, in the code of
    /// `isa`; whether it will. With AVX-512, in one vector (`group`), where
    /// the packet has 16 lanes and the CPU has AVX-512F and BMI2. With
    /// AVX2, in one vector for two lanes or two for four (`group_avx2`),
    /// where the packet has up to 16 lanes and the CPU has AVX2, in the
    /// voxels where its lanes agree on every direction sign. Other packets
    /// ignore it. The answers are the same either way.
    ///
    /// Far from the model a shadow packet's lanes part ways inside each
    /// voxel, and a node visit of the whole packet costs the same for 3
    /// lanes as for 16. Handed over, a node costs a group one vector's box
    /// test for all four children, and a leaf one triangle test for all
    /// its triangles. Where the lanes stay together, the lane masks of
    /// every entered child and the groups at the fringes cost more than
    /// they save: `render` turns hand-overs off for such tiles (measured
    /// by `scripts/bench-kernel`).
    pub fn hand_off_sparse_subtrees(&mut self, isa: Isa) -> bool {
        self.groups = match isa {
            Isa::Avx512 if N == 16 && quad::available() => Groups::Avx512,
            Isa::Avx2 if N <= 16 && avx2_groups_available() => Groups::Avx2,
            _ => Groups::Off,
        };
        self.groups != Groups::Off
    }

    /// Whether some lane's direction has a component exactly zero: the
    /// box tests of `crate::quad`, which do not handle it, are left to
    /// [`Self::slab_within`].
    #[inline(always)]
    fn any_zero_component(&self) -> bool {
        self.signs.contains(&Sign::WithZero)
    }

    /// Whether every lane of a shadow packet is blocked (or was never
    /// live): nothing is left to trace.
    #[inline(always)]
    fn all_blocked(&self) -> bool {
        let mut all = true;
        for i in 0..N {
            all &= self.t[i] == f32::NEG_INFINITY;
        }
        all
    }

    /// Blocks every lane of a shadow packet that `occluder` blocks,
    /// before any traversal; whether every lane is now blocked.
    ///
    /// Neighbouring shadow rays are often blocked by the same triangle, so
    /// a shadow packet first tries the one that blocked a lane of the
    /// packet before. Whatever it blocks, traversal would have found
    /// blocked too: it is a triangle of the model, tested and accepted
    /// exactly as in a voxel's leaf, and a shadow ray's answer is only
    /// whether something lies in `(tmin, inf)`. Where it blocks every
    /// lane, the traversal is skipped.
    #[inline(always)]
    pub fn occlude_with(&mut self, occluder: &Occluder) -> bool {
        let o = occluder;
        // No voxel or voxel-local triangle: shadow lanes need neither.
        match AnyShear::new(self) {
            AnyShear::Uniform(s) => {
                self.triangle::<_, true>(&s, &o.corners, o.id, u32::MAX, u32::MAX)
            }
            AnyShear::Mixed(s) => {
                self.triangle::<_, true>(&s, &o.corners, o.id, u32::MAX, u32::MAX)
            }
        }
        self.all_blocked()
    }

    pub fn hit(&self, lane: usize) -> bool {
        self.id[lane] != u32::MAX
    }

    /// Whether lane `i` of a shadow packet is blocked.
    pub fn occluded(&self, lane: usize) -> bool {
        self.t[lane] == f32::NEG_INFINITY
    }

    /// Per-lane interval of the rays inside the box, widened; empty
    /// (`t0 > t1`) where a ray misses or its current hit is nearer.
    #[inline(always)]
    fn slab(&self, min: [f32; 3], max: [f32; 3]) -> ([f32; N], [f32; N]) {
        self.slab_within(min, max, &[self.tmin; N], &[f32::INFINITY; N])
    }

    /// [`Self::slab`] with each lane's interval also limited to
    /// `[lo, hi]`.
    #[inline(always)]
    fn slab_within(
        &self,
        min: [f32; 3],
        max: [f32; 3],
        lo: &[f32; N],
        hi: &[f32; N],
    ) -> ([f32; N], [f32; N]) {
        let mut t0 = *lo;
        let mut exit = [f32::INFINITY; N];
        for a in 0..3 {
            // Where every lane agrees on the sign (nearly always), the near
            // plane is known: two multiplies and a max/min per lane. The
            // values are those the comparison would pick, so both paths
            // cull alike.
            let (near_plane, far_plane) = match self.signs[a] {
                Sign::Positive => (min[a], max[a]),
                Sign::Negative => (max[a], min[a]),
                Sign::Mixed => {
                    for i in 0..N {
                        let near = (min[a] - self.org[a][i]) * self.inv[a][i];
                        let far = (max[a] - self.org[a][i]) * self.inv[a][i];
                        let (lo, hi) = if near < far { (near, far) } else { (far, near) };
                        t0[i] = if lo > t0[i] { lo } else { t0[i] };
                        exit[i] = if hi < exit[i] { hi } else { exit[i] };
                    }
                    continue;
                }
                Sign::WithZero => {
                    // As `Mixed`, except for lanes without a component on
                    // this axis: no limit where the origin is in the slab,
                    // an empty interval where it is not (finite, so that
                    // widening makes no NaN).
                    for i in 0..N {
                        let near = (min[a] - self.org[a][i]) * self.inv[a][i];
                        let far = (max[a] - self.org[a][i]) * self.inv[a][i];
                        let (lo, hi) = if near < far { (near, far) } else { (far, near) };
                        let o = self.org[a][i];
                        let inside = (min[a] <= o) & (o <= max[a]);
                        let flat = self.dir[a][i] == 0.0;
                        let (lo, hi) = match (flat, inside) {
                            (false, _) => (lo, hi),
                            (true, true) => (-f32::MAX, f32::MAX),
                            (true, false) => (f32::MAX, -f32::MAX),
                        };
                        t0[i] = if lo > t0[i] { lo } else { t0[i] };
                        exit[i] = if hi < exit[i] { hi } else { exit[i] };
                    }
                    continue;
                }
            };
            for i in 0..N {
                let lo = (near_plane - self.org[a][i]) * self.inv[a][i];
                let hi = (far_plane - self.org[a][i]) * self.inv[a][i];
                t0[i] = if lo > t0[i] { lo } else { t0[i] };
                exit[i] = if hi < exit[i] { hi } else { exit[i] };
            }
        }
        // Widening is monotonic, so widening the nearest exit once equals
        // taking the nearest of the widened exits.
        let mut t1 = self.t;
        for i in 0..N {
            t0[i] -= t0[i].abs() * WIDEN;
            let exit = exit[i] + exit[i].abs() * WIDEN;
            let limit = if hi[i] < t1[i] { hi[i] } else { t1[i] };
            t1[i] = if exit < limit { exit } else { limit };
        }
        (t0, t1)
    }

    /// Keeps, per lane, the better of the current hit and the candidate
    /// whose scaled barycentrics are (`u`, `v`, `w`) and distance `tt`. A
    /// shadow packet (`ANY`, [`Self::any_hit`]) blocks the lane and keeps no
    /// barycentrics: one division a lane less in its every triangle test.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn accept<const ANY: bool>(
        &mut self,
        u: &[f32; N],
        v: &[f32; N],
        w: &[f32; N],
        tt: &[f32; N],
        id: u32,
        voxel: u32,
        tri: u32,
    ) {
        for i in 0..N {
            let neg = (u[i] < 0.0) | (v[i] < 0.0) | (w[i] < 0.0);
            let pos = (u[i] > 0.0) | (v[i] > 0.0) | (w[i] > 0.0);
            let det = u[i] + v[i] + w[i];
            let t = tt[i];
            let inside = !(neg & pos) & (det != 0.0) & (t > self.tmin) & t.is_finite();
            let better = (t < self.t[i]) | ((t == self.t[i]) & (id < self.id[i]));
            let take = inside & better;
            let t_new = if ANY { f32::NEG_INFINITY } else { t };
            self.t[i] = if take { t_new } else { self.t[i] };
            self.id[i] = if take { id } else { self.id[i] };
            self.voxel[i] = if take { voxel } else { self.voxel[i] };
            self.tri[i] = if take { tri } else { self.tri[i] };
            if !ANY {
                let inv_det = 1.0 / det;
                self.u[i] = if take { v[i] * inv_det } else { self.u[i] };
                self.v[i] = if take { w[i] * inv_det } else { self.v[i] };
            }
        }
    }

    /// Every lane against one triangle (`corners`, ORIGINAL id `id`,
    /// voxel-local `tri` of voxel `voxel`): tested, and kept where it is
    /// the better hit.
    #[inline(always)]
    fn triangle<S: TriangleTest<N>, const ANY: bool>(
        &mut self,
        shear: &S,
        corners: &[[f32; 3]; 3],
        id: u32,
        voxel: u32,
        tri: u32,
    ) {
        let (u, v, w, t) = shear.test(self, corners);
        self.accept::<ANY>(&u, &v, &w, &t, id, voxel, tri);
    }

    /// Nearest hits (or occlusion) of every lane in one voxel's BVH,
    /// searched only within each lane's interval `seg` (the lane's part of
    /// the voxel's content box). `ANY` is [`Self::any_hit`], fixed at
    /// compile time so that the shadow packets' search is code of its own.
    #[inline(always)]
    fn voxel<S: TriangleTest<N>, const ANY: bool>(
        &mut self,
        shear: &S,
        vox: &PreparedVoxel,
        seg: (&[f32; N], &[f32; N]),
    ) {
        if vox.nodes.is_empty() {
            return;
        }
        // Sparse packets (16 lanes, AVX-512 and BMI2) keep each entry's
        // lanes and test boxes as planes, which `crate::quad` reads.
        // 32-lane nearest-hit packets keep the slab test too: their frame
        // set-up and its registers cost more than they save; 32-lane
        // shadow packets, whose lanes part more, gain from the frame
        // (`docs/benchmarks.md`).
        let sparse = N == 16 && self.quad;
        let frame = if sparse || (N > 16 && !ANY) {
            None
        } else {
            FrameRays::new(self, &vox.frame)
        };
        let frame = frame.as_ref();
        // Only shadow packets hand subtrees over.
        let groups = ANY && self.groups != Groups::Off;
        if groups {
            let lanes = entering(self, seg.0, seg.1);
            if self.hand_off(shear, frame, vox, seg, lanes, 0) {
                return;
            }
        }
        // The searches that keep lanes, and those that hand subtrees over,
        // are code of their own, as keeping the lanes slows every other
        // packet down, and the hand-over's tests would cost the other
        // packets too (`scripts/bench-kernel`).
        match (sparse, groups) {
            (true, true) => self.search::<S, LaneMask, true, ANY>(shear, frame, vox, seg),
            (true, false) => self.search::<S, LaneMask, false, ANY>(shear, frame, vox, seg),
            (false, true) => self.search::<S, AllLanes, true, ANY>(shear, frame, vox, seg),
            (false, false) => self.search::<S, AllLanes, false, ANY>(shear, frame, vox, seg),
        }
    }

    /// The search of one voxel's BVH, with `L` the lanes each stack entry
    /// stands for, and its boxes tested in the voxel's `frame` where there
    /// is one.
    #[inline(always)]
    fn search<S: TriangleTest<N>, L: EntryLanes<N>, const HAND_OFF: bool, const ANY: bool>(
        &mut self,
        shear: &S,
        frame: Option<&FrameRays<N>>,
        vox: &PreparedVoxel,
        seg: (&[f32; N], &[f32; N]),
    ) {
        // Each wide level pushes at most 4 entries and the BVH is at most
        // 64 binary levels deep: 4 * 64 + 4 entries always fit.
        // Uninitialised: zeroing 1 KiB on every voxel a packet enters
        // showed in profiles, and only written slots are read.
        let mut stack = [std::mem::MaybeUninit::<(u32, L)>::uninit(); 260];
        let mut top = 0usize;
        // The entry to visit next without a trip through the stack: the
        // nearest child a node pushes would be popped at once, and the store
        // and load would sit on the path from one node load to the next.
        let mut next = (0u32, L::root(self, seg));
        let dir0 = [self.dir[0][0], self.dir[1][0], self.dir[2][0]];
        loop {
            let (entry, lanes) = if next.0 != NONE {
                next
            } else if top > 0 {
                top -= 1;
                // SAFETY: slots below `top` were all written.
                unsafe { stack[top].assume_init() }
            } else {
                break;
            };
            next.0 = NONE;
            if entry & LEAF != 0 {
                if self.leaf::<S, ANY>(shear, vox, entry) {
                    return;
                }
                continue;
            }
            let node = &vox.nodes[entry as usize];
            prefetch_children::<N>(vox, node);
            let boxes = match frame {
                Some(f) => Boxes::Frame(f.node(self, node, seg)),
                None => Boxes::Planes(dequantize(vox, node)),
            };
            let tested = L::node(self, lanes, node, &boxes, seg);
            if ANY {
                if self.any_children::<S, L, HAND_OFF>(
                    shear, frame, vox, seg, node, lanes, &tested, &boxes, &mut stack, &mut top,
                ) {
                    return;
                }
                continue;
            }
            // Test every child box; order the hit ones by where the first
            // ray meets their centres.
            let mut hits = [(0.0f32, (0u32, lanes)); 4];
            let mut n = 0;
            for c in 0..4 {
                if node.kind(c) == WideNode::EMPTY {
                    break;
                }
                let Some(child_lanes) = L::child(self, lanes, &tested, c, &boxes, seg) else {
                    continue;
                };
                if let Some(e) = self.child_entry::<S>(shear, vox, node, c) {
                    hits[n] = (boxes.key(c, dir0), (e, child_lanes));
                    n += 1;
                }
            }
            sort_far_first(&mut hits[..n]);
            if n > 0 {
                for &(_, e) in &hits[..n - 1] {
                    stack[top].write(e);
                    top += 1;
                }
                next = hits[n - 1].1;
            }
        }
    }

    /// A shadow packet's children of `node`, which `lanes` entered: each
    /// child that few enough lanes enter handed over to them (`HAND_OFF`),
    /// every other child some lane enters pushed onto `stack` in stored
    /// order, the last on top. Whether the packet is now wholly blocked.
    ///
    /// Every slot is tested, and written to the stack and kept where some
    /// lane enters it: which children a shadow packet's rays enter is data
    /// the branch predictor does not learn (`scripts/bench-kernel`).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn any_children<S: TriangleTest<N>, L: EntryLanes<N>, const HAND_OFF: bool>(
        &mut self,
        shear: &S,
        frame: Option<&FrameRays<N>>,
        vox: &PreparedVoxel,
        seg: (&[f32; N], &[f32; N]),
        node: &WideNode,
        lanes: L,
        tested: &L::Tested,
        boxes: &Boxes<'_, N>,
        stack: &mut [std::mem::MaybeUninit<(u32, L)>],
        top: &mut usize,
    ) -> bool {
        let mut entered = [(lanes, 0u32); 4];
        for c in 0..4 {
            let (child_lanes, mask) = L::child_mask(self, lanes, tested, c, boxes, seg, HAND_OFF);
            let mask = if node.kind(c) == WideNode::EMPTY {
                0
            } else {
                mask
            };
            entered[c] = (child_lanes, mask);
        }
        let mut handed = 0u32;
        if HAND_OFF {
            for c in 0..4 {
                let mask = entered[c].1;
                if (1..=4).contains(&mask.count_ones())
                    && self.hand_off(shear, frame, vox, seg, mask, node.child[c])
                {
                    if self.all_blocked() {
                        return true;
                    }
                    handed |= 1 << c;
                }
            }
        }
        for c in 0..4 {
            let (kind, first) = (node.kind(c), node.index(c));
            let (child_lanes, mask) = entered[c];
            let live = (mask != 0) & (handed & (1 << c) == 0);
            let entry = stack_entry(kind, first);
            // The index first: it is never that large, a branch that is
            // always predicted, where `kind` is not.
            if first > 0x00FF_FFFF && kind != 0 {
                // A leaf past what an entry can name (never built): tested
                // at once, as `child_entry` does.
                if live && kind != WideNode::EMPTY {
                    self.triangles::<S, true>(shear, vox, first, kind);
                }
                continue;
            }
            stack[*top].write((entry, child_lanes));
            *top += live as usize;
        }
        false
    }

    /// Where this is a shadow packet that hands sparse subtrees over to
    /// groups of lanes (`groups`) and few enough lanes (`lanes`, a bit
    /// each) enter `root` (a child slot of a node, 0 for the voxel's root):
    /// searches it for them ([`group::subtree`], or
    /// [`group_avx2::subtree`] with the box test of `frame`); whether it
    /// did.
    #[inline(always)]
    fn hand_off<S: TriangleTest<N>>(
        &mut self,
        shear: &S,
        frame: Option<&FrameRays<N>>,
        vox: &PreparedVoxel,
        seg: (&[f32; N], &[f32; N]),
        lanes: u32,
        root: u32,
    ) -> bool {
        #[cfg(target_arch = "x86_64")]
        if let (true, Some(shear)) = (
            self.any_hit && (1..=4).contains(&lanes.count_ones()),
            shear.uniform(),
        ) {
            match (self.groups, frame) {
                (Groups::Avx512, _) if N == 16 && self.tmin >= 0.0 => {
                    // SAFETY: `Groups::Avx512` only where the CPU has
                    // AVX-512F and BMI2; N is 16, so the types are the same.
                    unsafe {
                        let p = &mut *(self as *mut Packet<N> as *mut Packet<16>);
                        let shear = &*(shear as *const Shear<N> as *const Shear<16>);
                        group::subtree(p, shear, vox, (as16(seg.0), as16(seg.1)), lanes, root);
                    }
                }
                (Groups::Avx2, Some(frame)) => {
                    // SAFETY: `Groups::Avx2` only where the CPU has AVX2 and FMA.
                    unsafe { group_avx2::subtree(self, shear, frame, vox, seg, lanes, root) };
                }
                _ => return false,
            }
            self.group_searches = self.group_searches.wrapping_add(1);
            return true;
        }
        // (Off x86_64 nothing is handed over and the arguments go unused.)
        let _ = (shear, frame, vox, seg, lanes, root);
        false
    }

    /// Every lane against the triangles of the leaf `entry`; whether a
    /// shadow packet is now wholly blocked (nothing left to search).
    #[inline(always)]
    fn leaf<S: TriangleTest<N>, const ANY: bool>(
        &mut self,
        shear: &S,
        vox: &PreparedVoxel,
        entry: u32,
    ) -> bool {
        self.triangles::<S, ANY>(shear, vox, entry & 0x00FF_FFFF, (entry >> 24) & 0x7F);
        ANY && self.all_blocked()
    }

    /// Every lane against the voxel's triangles `first..first + count`.
    #[inline(always)]
    fn triangles<S: TriangleTest<N>, const ANY: bool>(
        &mut self,
        shear: &S,
        vox: &PreparedVoxel,
        first: u32,
        count: u32,
    ) {
        for k in first..first + count {
            let (corners, id) = (&vox.corners[k as usize], vox.ids[k as usize]);
            self.triangle::<S, ANY>(shear, corners, id, vox.id, k);
        }
    }

    /// The stack entry of child `c` of `node`, which some lane of a
    /// nearest-hit packet enters: its node index, or its leaf. A leaf past
    /// what an entry can name (voxels of over 16 M triangles; never built,
    /// kept exact) is tested at once instead.
    #[inline(always)]
    fn child_entry<S: TriangleTest<N>>(
        &mut self,
        shear: &S,
        vox: &PreparedVoxel,
        node: &WideNode,
        c: usize,
    ) -> Option<u32> {
        let (kind, first) = (node.kind(c), node.index(c));
        if kind == 0 || first <= 0x00FF_FFFF {
            Some(stack_entry(kind, first))
        } else {
            self.triangles::<S, false>(shear, vox, first, kind);
            None
        }
    }

    /// Counts a child box entered by `lanes` lanes (`count_lanes`).
    #[inline(always)]
    fn count_child(&mut self, lanes: u32) {
        self.child_hits = self.child_hits.wrapping_add(1);
        self.child_lanes = self.child_lanes.wrapping_add(lanes);
    }
}

/// Which lanes an entry of a voxel's search stands for, and how a node's
/// children are tested for them.
trait EntryLanes<const N: usize>: Copy {
    /// What a node works out before its children are tested one by one.
    type Tested;
    /// The lanes of the voxel's root: those whose interval `seg` is not
    /// empty.
    fn root(p: &Packet<N>, seg: (&[f32; N], &[f32; N])) -> Self;
    #[allow(clippy::type_complexity)]
    fn node(
        p: &Packet<N>,
        lanes: Self,
        node: &WideNode,
        boxes: &Boxes<'_, N>,
        seg: (&[f32; N], &[f32; N]),
    ) -> Self::Tested;
    /// The lanes of `lanes` that enter child `c` of `boxes`, if any,
    /// counted where the packet counts its lanes: a nearest-hit packet's
    /// children.
    fn child(
        p: &mut Packet<N>,
        lanes: Self,
        tested: &Self::Tested,
        c: usize,
        boxes: &Boxes<'_, N>,
        seg: (&[f32; N], &[f32; N]),
    ) -> Option<Self>;
    /// The lanes of `lanes` that enter child `c` of `boxes`, and a bit for
    /// each of them where `masks` asks or the entries keep their lanes
    /// anyway (`LaneMask`), else `u32::MAX`; 0 where none does. Not
    /// counted: a shadow packet's children.
    fn child_mask(
        p: &Packet<N>,
        lanes: Self,
        tested: &Self::Tested,
        c: usize,
        boxes: &Boxes<'_, N>,
        seg: (&[f32; N], &[f32; N]),
        masks: bool,
    ) -> (Self, u32);
}

/// Every lane takes part in every entry (no lanes kept).
#[derive(Clone, Copy)]
struct AllLanes;

impl<const N: usize> EntryLanes<N> for AllLanes {
    type Tested = ();

    #[inline(always)]
    fn root(_: &Packet<N>, _: (&[f32; N], &[f32; N])) -> Self {
        AllLanes
    }

    #[inline(always)]
    fn node(_: &Packet<N>, _: Self, _: &WideNode, _: &Boxes<'_, N>, _: (&[f32; N], &[f32; N])) {}

    #[inline(always)]
    fn child(
        p: &mut Packet<N>,
        _: Self,
        _: &(),
        c: usize,
        boxes: &Boxes<'_, N>,
        seg: (&[f32; N], &[f32; N]),
    ) -> Option<Self> {
        let (t0, t1) = boxes.interval(p, c, seg);
        if lanes_entering(p, &t0, &t1, false) == 0 {
            return None;
        }
        if p.count_lanes {
            let mut lanes = 0u32;
            for i in 0..N {
                lanes += (t0[i] <= t1[i]) as u32;
            }
            p.count_child(lanes);
        }
        Some(AllLanes)
    }

    #[inline(always)]
    fn child_mask(
        p: &Packet<N>,
        _: Self,
        _: &(),
        c: usize,
        boxes: &Boxes<'_, N>,
        seg: (&[f32; N], &[f32; N]),
        masks: bool,
    ) -> (Self, u32) {
        let (t0, t1) = boxes.interval(p, c, seg);
        (AllLanes, lanes_entering(p, &t0, &t1, masks))
    }
}

/// The lanes where `t0 <= t1`, a bit each where `masks` asks, else
/// `u32::MAX` where any lane enters; 0 where none does. Packets that hand
/// nothing over need only whether any lane enters: a mask of 32 lanes
/// costs more than the box test.
#[inline(always)]
fn lanes_entering<const N: usize>(p: &Packet<N>, t0: &[f32; N], t1: &[f32; N], masks: bool) -> u32 {
    if masks {
        return entering(p, t0, t1);
    }
    let mut any = false;
    for i in 0..N {
        any |= t0[i] <= t1[i];
    }
    if any {
        u32::MAX
    } else {
        0
    }
}

/// The lanes that entered an entry's box, a bit each (sparse packets: 16
/// lanes, AVX-512 and BMI2). A lane left out could not enter anything
/// below it, as its hit only comes nearer; a node that at most four lanes
/// entered tests its children for them at once (`crate::quad`).
#[derive(Clone, Copy)]
struct LaneMask(u32);

// SAFETY (every intrinsic in this impl): a packet is sparse only where the
// CPU has AVX-512F and BMI2, and only with 16 lanes.
impl<const N: usize> EntryLanes<N> for LaneMask {
    /// The lanes entering each child where at most four entered the node.
    type Tested = Option<[u32; 4]>;

    #[inline(always)]
    fn root(_: &Packet<N>, seg: (&[f32; N], &[f32; N])) -> Self {
        LaneMask(unsafe { lanes_le16(as16(seg.0), as16(seg.1)) })
    }

    #[inline(always)]
    fn node(
        p: &Packet<N>,
        lanes: Self,
        node: &WideNode,
        boxes: &Boxes<'_, N>,
        seg: (&[f32; N], &[f32; N]),
    ) -> Option<[u32; 4]> {
        let Boxes::Planes((bmin, bmax)) = boxes else {
            return None;
        };
        if lanes.0.count_ones() > 4 || p.any_zero_component() {
            return None;
        }
        let mut slots = 0;
        for c in 0..4 {
            slots |= ((node.kind(c) != WideNode::EMPTY) as u32) << c;
        }
        let rays = quad::Rays {
            org: as16x3(&p.org),
            inv: as16x3(&p.inv),
            lo: as16(seg.0),
            hi: as16(seg.1),
            t: as16(&p.t),
        };
        Some(unsafe { children16(&rays, bmin, bmax, lanes.0, slots) })
    }

    #[inline(always)]
    fn child(
        p: &mut Packet<N>,
        lanes: Self,
        tested: &Option<[u32; 4]>,
        c: usize,
        boxes: &Boxes<'_, N>,
        seg: (&[f32; N], &[f32; N]),
    ) -> Option<Self> {
        let (lanes, entered) = Self::child_mask(p, lanes, tested, c, boxes, seg, true);
        if entered == 0 {
            return None;
        }
        if p.count_lanes {
            p.count_child(entered.count_ones());
        }
        Some(lanes)
    }

    #[inline(always)]
    fn child_mask(
        p: &Packet<N>,
        lanes: Self,
        tested: &Option<[u32; 4]>,
        c: usize,
        boxes: &Boxes<'_, N>,
        seg: (&[f32; N], &[f32; N]),
        _: bool,
    ) -> (Self, u32) {
        let entered = match tested {
            Some(entered) => entered[c],
            None => {
                let (t0, t1) = boxes.interval(p, c, seg);
                unsafe { lanes_le16(as16(&t0), as16(&t1)) & lanes.0 }
            }
        };
        (LaneMask(entered), entered)
    }
}

/// A node's child boxes, ready for a packet's box tests.
enum Boxes<'a, const N: usize> {
    /// Dequantized: `(min, max)`, each per axis and child.
    Planes(([[f32; 4]; 3], [[f32; 4]; 3])),
    /// In the voxel's frame, for a packet whose lanes agree on every
    /// direction sign ([`FrameRays`]).
    Frame(FrameNode<'a, N>),
}

impl<const N: usize> Boxes<'_, N> {
    /// Per lane, the interval of the ray inside child `c`, limited to
    /// `seg` and the lane's current hit, widened; empty (`t0 > t1`) where
    /// the ray misses it.
    #[inline(always)]
    fn interval(
        &self,
        p: &Packet<N>,
        c: usize,
        seg: (&[f32; N], &[f32; N]),
    ) -> ([f32; N], [f32; N]) {
        match self {
            Boxes::Planes((bmin, bmax)) => {
                let min = [bmin[0][c], bmin[1][c], bmin[2][c]];
                let max = [bmax[0][c], bmax[1][c], bmax[2][c]];
                p.slab_within(min, max, seg.0, seg.1)
            }
            Boxes::Frame(f) => f.interval(c, seg),
        }
    }

    /// The order of a nearest-hit packet's children: where the first ray
    /// (direction `dir0`) meets the centre of child `c`, up to a constant
    /// of the voxel.
    #[inline(always)]
    fn key(&self, c: usize, dir0: [f32; 3]) -> f32 {
        match self {
            Boxes::Planes((min, max)) => {
                (min[0][c] + max[0][c]) * dir0[0]
                    + (min[1][c] + max[1][c]) * dir0[1]
                    + (min[2][c] + max[2][c]) * dir0[2]
            }
            Boxes::Frame(f) => {
                (f.near[0][c] + f.far[0][c]) * f.rays.key[0]
                    + (f.near[1][c] + f.far[1][c]) * f.rays.key[1]
                    + (f.near[2][c] + f.far[2][c]) * f.rays.key[2]
            }
        }
    }
}

/// The box test of a packet whose lanes agree on the sign of every
/// direction component, in one voxel's fixed-point frame: along axis `a`,
/// lane `i` meets the plane of quantum `q` at `q * scale[a][i] +
/// offset`, one multiply and one add per plane (fused where the kernel
/// has FMA, [`fused_planes`]) instead of dequantizing the node and a
/// subtract, a multiply and the widening per plane.
///
/// `near` and `far` are the offsets lowered and raised by [`MARGIN`] of
/// the largest magnitude in the sum (the voxel's origin, the ray's origin
/// and the frame's extent, over the direction): it bounds the rounding of
/// this form, of `Frame::plane` (which the boxes are conservative in) and
/// of the triangle test's distances, so a box is culled only where the
/// ray misses it. Unlike [`Packet::slab_within`]'s widening it does not
/// grow with the distance, which culls more boxes far from the eye.
///
/// The top level's boxes are tested the same way in world coordinates
/// ([`FrameRays::world`]), once per packet.
struct FrameRays<const N: usize> {
    scale: [[f32; N]; 3],
    near: [[f32; N]; 3],
    far: [[f32; N]; 3],
    /// Per axis, whether the near plane is a child's max (lanes going
    /// towards smaller coordinates).
    near_is_max: [bool; 3],
    /// The first ray's direction scaled by the frame (child order).
    key: [f32; 3],
}

impl<const N: usize> FrameRays<N> {
    /// For the boxes of a voxel's nodes, in its frame; `None` where some
    /// axis has lanes of both signs or a zero component.
    #[inline(always)]
    fn new(p: &Packet<N>, frame: &Frame) -> Option<FrameRays<N>> {
        let mut top = frame.scale;
        for a in 0..3 {
            top[a] *= Frame::TOP as f32;
        }
        Self::with(p, frame.origin, frame.scale, top)
    }

    /// For boxes in world coordinates, every coordinate at most `extent`
    /// in magnitude, per axis.
    #[inline(always)]
    fn world(p: &Packet<N>, extent: [f32; 3]) -> Option<FrameRays<N>> {
        Self::with(p, [0.0; 3], [1.0; 3], extent)
    }

    /// Planes `origin + q * scale`, with `q * scale` at most `extent` in
    /// magnitude.
    #[inline(always)]
    fn with(
        p: &Packet<N>,
        origin: [f32; 3],
        scale: [f32; 3],
        extent: [f32; 3],
    ) -> Option<FrameRays<N>> {
        let mut near_is_max = [false; 3];
        for a in 0..3 {
            near_is_max[a] = match p.signs[a] {
                Sign::Positive => false,
                Sign::Negative => true,
                Sign::Mixed | Sign::WithZero => return None,
            };
        }
        let mut r = FrameRays {
            scale: [[0.0; N]; 3],
            near: [[0.0; N]; 3],
            far: [[0.0; N]; 3],
            near_is_max,
            key: [0.0; 3],
        };
        for a in 0..3 {
            let (origin, scale, top) = (origin[a], scale[a], extent[a]);
            for i in 0..N {
                let inv = p.inv[a][i];
                let offset = (origin - p.org[a][i]) * inv;
                let margin = (origin.abs() + p.org[a][i].abs() + top) * inv.abs() * MARGIN;
                r.scale[a][i] = scale * inv;
                r.near[a][i] = offset - margin;
                r.far[a][i] = offset + margin;
            }
            r.key[a] = scale * p.dir[a][0];
        }
        Some(r)
    }

    /// Per lane, the interval of the ray inside the box `min`..`max` (in
    /// the planes' own units) before its current hit, widened; empty
    /// (`t0 > t1`) where the ray misses it.
    #[inline(always)]
    fn interval(&self, p: &Packet<N>, min: [f32; 3], max: [f32; 3]) -> ([f32; N], [f32; N]) {
        let (mut t0, mut t1) = ([p.tmin; N], p.t);
        let mut near = min;
        let mut far = max;
        for a in 0..3 {
            if self.near_is_max[a] {
                (near[a], far[a]) = (max[a], min[a]);
            }
        }
        self.clip(near, far, &mut t0, &mut t1);
        (t0, t1)
    }

    /// Narrows each lane's `t0`..`t1` to where it is between the `near`
    /// and `far` planes of every axis (quanta, or world coordinates).
    #[inline(always)]
    fn clip(&self, near: [f32; 3], far: [f32; 3], t0: &mut [f32; N], t1: &mut [f32; N]) {
        for a in 0..3 {
            for i in 0..N {
                let (lo, hi) = if fused_planes::<N>() {
                    (
                        near[a].mul_add(self.scale[a][i], self.near[a][i]),
                        far[a].mul_add(self.scale[a][i], self.far[a][i]),
                    )
                } else {
                    (
                        near[a] * self.scale[a][i] + self.near[a][i],
                        far[a] * self.scale[a][i] + self.far[a][i],
                    )
                };
                t0[i] = if lo > t0[i] { lo } else { t0[i] };
                t1[i] = if hi < t1[i] { hi } else { t1[i] };
            }
        }
    }

    /// The quanta of `node`'s near and far planes, per axis and child,
    /// and each lane's limit.
    #[inline(always)]
    fn node<'a>(
        &'a self,
        p: &Packet<N>,
        node: &WideNode,
        seg: (&[f32; N], &[f32; N]),
    ) -> FrameNode<'a, N> {
        let mut near = [[0.0f32; 4]; 3];
        let mut far = [[0.0f32; 4]; 3];
        for a in 0..3 {
            let (n, f) = if self.near_is_max[a] {
                (&node.qmax[a], &node.qmin[a])
            } else {
                (&node.qmin[a], &node.qmax[a])
            };
            for c in 0..4 {
                near[a][c] = n[c] as f32;
                far[a][c] = f[c] as f32;
            }
        }
        let mut limit = p.t;
        for i in 0..N {
            limit[i] = if seg.1[i] < limit[i] {
                seg.1[i]
            } else {
                limit[i]
            };
        }
        FrameNode {
            rays: self,
            near,
            far,
            limit,
        }
    }
}

/// One node's boxes for [`FrameRays`].
struct FrameNode<'a, const N: usize> {
    rays: &'a FrameRays<N>,
    /// Quanta of each child's near and far planes, per axis and child.
    near: [[f32; 4]; 3],
    far: [[f32; 4]; 3],
    /// Per lane, the nearer of the lane's segment end and its current hit
    /// when the node was reached (a hit found since only narrows it).
    limit: [f32; N],
}

impl<const N: usize> FrameNode<'_, N> {
    #[inline(always)]
    fn interval(&self, c: usize, seg: (&[f32; N], &[f32; N])) -> ([f32; N], [f32; N]) {
        let (mut t0, mut t1) = (*seg.0, self.limit);
        let near = [0, 1, 2].map(|a| self.near[a][c]);
        let far = [0, 1, 2].map(|a| self.far[a][c]);
        self.rays.clip(near, far, &mut t0, &mut t1);
        (t0, t1)
    }
}

/// Whether [`FrameRays::clip`] computes its planes with fused
/// multiply-adds: one instruction in place of two in the hottest loop
/// (`scripts/bench-kernel`). Packets of more than 8 lanes run only in the
/// AVX2 and AVX-512 kernels, whose CPUs have FMA ([`crate::render::Isa`]);
/// the portable kernel's 8 would call the C library's `fmaf`. The margin of
/// [`FrameRays`] bounds the rounding of either form.
const fn fused_planes<const N: usize>() -> bool {
    N > 8
}

/// Stack entries of a voxel's search: a wide node index, or a leaf as
/// LEAF | count << 24 | first (counts are at most 4, so first has 24 bits;
/// a leaf past that, in a voxel of over 16 M triangles, is tested where its
/// parent finds it).
const LEAF: u32 = 1 << 31;
/// The stack entry of a child of `kind` (0 for an interior node, else a
/// leaf's triangle count) at `first`, which names it ([`LEAF`]).
#[inline(always)]
fn stack_entry(kind: u32, first: u32) -> u32 {
    if kind == 0 {
        first
    } else {
        LEAF | (kind << 24) | first
    }
}

/// No entry to visit next.
const NONE: u32 = u32::MAX;

/// Starts loading every child of `node` before the box tests decide which
/// are needed: these dependent loads are a large part of the traversal's
/// time on far views, and the box tests hide part of their latency.
/// Prefetching only the children that were hit, once sorted, comes too
/// late on far views, where the nearest child is visited at once.
///
/// An interior child: its node and the two after it (in depth-first order
/// its first child and grandchild). A leaf: its corners (4 triangles span
/// 144 bytes, three lines, or four where they start in a line's last 16
/// bytes) and its ids. Packets of up to 16 lanes, the incoherent ones, do
/// it without branches: when each node is visited once, which children
/// are leaves is data the branch predictor cannot learn (32-lane packets,
/// the coherent ones, branch). An interior child's line is then asked for
/// twice, and an empty slot prefetches the voxel's first corners.
/// (Prefetches never fault: `wrapping_add` of any index is fine.) Measured
/// by `scripts/bench-kernel`.
#[inline(always)]
fn prefetch_children<const N: usize>(vox: &PreparedVoxel, node: &WideNode) {
    for c in 0..4 {
        let (kind, first) = (node.kind(c), node.index(c) as usize);
        let n = vox.nodes.as_ptr().wrapping_add(first) as *const u8;
        let t = vox.corners.as_ptr().wrapping_add(first) as *const u8;
        let ids = vox.ids.as_ptr().wrapping_add(first) as *const u8;
        if N <= 16 {
            let p = if kind == 0 { n } else { t };
            prefetch(p);
            prefetch(p.wrapping_add(64));
            prefetch(p.wrapping_add(128));
            prefetch(p.wrapping_add(143));
            prefetch(if kind == 0 { n } else { ids });
        } else if kind == 0 {
            prefetch(n);
            prefetch(n.wrapping_add(64));
            prefetch(n.wrapping_add(128));
        } else if kind != WideNode::EMPTY {
            prefetch(t);
            prefetch(t.wrapping_add(64));
            prefetch(t.wrapping_add(128));
            prefetch(t.wrapping_add(143));
            prefetch(ids);
        }
    }
}

/// The boxes of `node`'s children, out of the frame's fixed point:
/// `(min, max)`, each per axis and child.
#[inline(always)]
#[allow(clippy::type_complexity)]
fn dequantize(vox: &PreparedVoxel, node: &WideNode) -> ([[f32; 4]; 3], [[f32; 4]; 3]) {
    let mut bmin = [[0.0f32; 4]; 3];
    let mut bmax = [[0.0f32; 4]; 3];
    for a in 0..3 {
        for c in 0..4 {
            bmin[a][c] = vox.frame.plane(a, node.qmin[a][c]);
            bmax[a][c] = vox.frame.plane(a, node.qmax[a][c]);
        }
    }
    (bmin, bmax)
}

/// Far first, so that the nearest is popped next: an insertion sort by the
/// key (a library sort of four costs more than the node's box tests). A
/// shadow packet needs any hit, not the nearest: its children stay in their
/// stored order, the last popped first ([`Packet::any_children`]): a shadow
/// ray starts on a surface, and the nearest boxes hold that surface, which
/// cannot block it (near first and largest first are both slower in
/// `scripts/bench-kernel`).
#[inline(always)]
fn sort_far_first<T: Copy>(hits: &mut [(f32, T)]) {
    for j in 1..hits.len() {
        let x = hits[j];
        let mut k = j;
        while k > 0 && hits[k - 1].0 < x.0 {
            hits[k] = hits[k - 1];
            k -= 1;
        }
        hits[k] = x;
    }
}

/// Whether this CPU has what `group_avx2` needs: AVX2, and FMA for its
/// box test.
fn avx2_groups_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    return is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma");
    #[cfg(not(target_arch = "x86_64"))]
    return false;
}

/// The lanes where `t0 <= t1`, a bit each (up to 32 lanes): the AVX-512
/// intrinsic where the packet's groups run on AVX-512, else a lane loop
/// (which LLVM turns into comparisons and a mask move).
#[inline(always)]
fn entering<const N: usize>(p: &Packet<N>, t0: &[f32; N], t1: &[f32; N]) -> u32 {
    if N == 16 && p.groups == Groups::Avx512 {
        // SAFETY: `Groups::Avx512` only where the CPU has AVX-512F.
        return unsafe { lanes_le16(as16(t0), as16(t1)) };
    }
    (0..N).fold(0, |m, i| m | (((t0[i] <= t1[i]) as u32) << i))
}

/// [`quad::lanes_le`] where it exists (elsewhere `quad` is never set).
///
/// # Safety
/// As [`quad::lanes_le`].
#[inline(always)]
unsafe fn lanes_le16(t0: &[f32; 16], t1: &[f32; 16]) -> u32 {
    #[cfg(target_arch = "x86_64")]
    return quad::lanes_le(t0, t1);
    #[cfg(not(target_arch = "x86_64"))]
    return (0..16).fold(0, |m, i| m | (((t0[i] <= t1[i]) as u32) << i));
}

/// [`quad::children`] where it exists.
///
/// # Safety
/// As [`quad::children`].
#[inline(always)]
unsafe fn children16(
    rays: &quad::Rays,
    bmin: &[[f32; 4]; 3],
    bmax: &[[f32; 4]; 3],
    lanes: u32,
    slots: u32,
) -> [u32; 4] {
    #[cfg(target_arch = "x86_64")]
    return quad::children(rays, bmin, bmax, lanes, slots);
    #[cfg(not(target_arch = "x86_64"))]
    return quad::children_by_lane(rays, bmin, bmax, lanes, slots);
}

/// A packet's lane array as the 16 lanes it is where `N` is 16.
#[inline(always)]
fn as16<const N: usize>(v: &[f32; N]) -> &[f32; 16] {
    assert_eq!(N, 16);
    // SAFETY: the same type, as N is 16.
    unsafe { &*(v as *const [f32; N] as *const [f32; 16]) }
}

#[inline(always)]
fn as16x3<const N: usize>(v: &[[f32; N]; 3]) -> &[[f32; 16]; 3] {
    assert_eq!(N, 16);
    // SAFETY: as `as16`.
    unsafe { &*(v as *const [[f32; N]; 3] as *const [[f32; 16]; 3]) }
}

/// The watertight test (`dray_scene::geometry::intersect_triangle`,
/// operation for operation, so distances are bit-identical to the
/// reference) for every lane of a packet against one triangle: scaled
/// barycentrics u, v, w and distances.
pub trait TriangleTest<const N: usize> {
    #[allow(clippy::type_complexity)]
    fn test(
        &self,
        p: &Packet<N>,
        corners: &[[f32; 3]; 3],
    ) -> ([f32; N], [f32; N], [f32; N], [f32; N]);

    /// The shear itself where every lane shares one axis order.
    fn uniform(&self) -> Option<&Shear<N>> {
        None
    }
}

/// The per-lane shear of the watertight test, for a packet whose lanes all
/// share one axis permutation (nearly every coherent packet).
#[derive(Clone, Copy, Debug)]
pub struct Shear<const N: usize> {
    kx: usize,
    ky: usize,
    kz: usize,
    sx: [f32; N],
    sy: [f32; N],
    sz: [f32; N],
}

/// The shear for a packet whose lanes need different permutations
/// (reflection rays, packets across a diagonal): each lane picks its
/// components with bit masks, still in SIMD.
#[derive(Clone, Copy, Debug)]
pub struct MixedShear<const N: usize> {
    /// `pick[slot][axis][i]`: all ones where lane `i`'s permutation puts
    /// `axis` in `slot`, else zero. Masks rather than a per-lane index:
    /// LLVM turns an indexed pick into a gather of scalar loads, which
    /// made these packets' triangle tests several times slower.
    pick: [[[u32; N]; 3]; 3],
    /// The origin's components in each lane's permuted order.
    o: [[f32; N]; 3],
    sx: [f32; N],
    sy: [f32; N],
    sz: [f32; N],
}

/// The permutation the reference test uses for one direction.
fn permutation(d: [f32; 3]) -> (usize, usize, usize) {
    let ad = [d[0].abs(), d[1].abs(), d[2].abs()];
    let kz = if ad[0] >= ad[1] && ad[0] >= ad[2] {
        0
    } else if ad[1] >= ad[2] {
        1
    } else {
        2
    };
    let mut kx = (kz + 1) % 3;
    let mut ky = (kx + 1) % 3;
    if d[kz] < 0.0 {
        std::mem::swap(&mut kx, &mut ky);
    }
    (kx, ky, kz)
}

/// The packet's shear: uniform when all lanes agree.
enum AnyShear<const N: usize> {
    Uniform(Shear<N>),
    Mixed(MixedShear<N>),
}

impl<const N: usize> AnyShear<N> {
    #[inline(always)]
    fn new(p: &Packet<N>) -> AnyShear<N> {
        let lane = |i: usize| [p.dir[0][i], p.dir[1][i], p.dir[2][i]];
        // Whether every lane picks lane 0's permutation: the same tests as
        // `permutation`, lane by lane without branches (this runs for every
        // packet; the per-lane version showed in profiles).
        let (kx, ky, kz) = permutation(lane(0));
        let negative = p.dir[kz][0] < 0.0;
        let mut uniform = true;
        for i in 0..N {
            let ad = [p.dir[0][i].abs(), p.dir[1][i].abs(), p.dir[2][i].abs()];
            let x_major = (ad[0] >= ad[1]) & (ad[0] >= ad[2]);
            let y_over_z = ad[1] >= ad[2];
            let same_axis = match kz {
                0 => x_major,
                1 => !x_major & y_over_z,
                _ => !x_major & !y_over_z,
            };
            uniform &= same_axis & ((p.dir[kz][i] < 0.0) == negative);
        }
        if uniform {
            let mut s = Shear {
                kx,
                ky,
                kz,
                sx: [0.0; N],
                sy: [0.0; N],
                sz: [0.0; N],
            };
            for i in 0..N {
                s.sz[i] = 1.0 / p.dir[kz][i];
                s.sx[i] = p.dir[kx][i] * s.sz[i];
                s.sy[i] = p.dir[ky][i] * s.sz[i];
            }
            return AnyShear::Uniform(s);
        }
        let mut m = MixedShear {
            pick: [[[0; N]; 3]; 3],
            o: [[0.0; N]; 3],
            sx: [0.0; N],
            sy: [0.0; N],
            sz: [0.0; N],
        };
        for i in 0..N {
            let (kx, ky, kz) = permutation(lane(i));
            for (slot, k) in [kx, ky, kz].into_iter().enumerate() {
                m.pick[slot][k][i] = u32::MAX;
                m.o[slot][i] = p.org[k][i];
            }
            m.sz[i] = 1.0 / p.dir[kz][i];
            m.sx[i] = p.dir[kx][i] * m.sz[i];
            m.sy[i] = p.dir[ky][i] * m.sz[i];
        }
        AnyShear::Mixed(m)
    }
}

/// The reference's double-precision redo for a lane exactly on an edge.
#[inline(never)]
#[allow(clippy::too_many_arguments)]
fn edge_lane(c: [[f32; 3]; 3], shear: (f32, f32, f32)) -> (f32, f32, f32, f32) {
    // c[corner] = [x, y, z] of the corner relative to the origin, already
    // permuted to (kx, ky, kz).
    let (sx, sy, sz) = shear;
    let ax = (c[0][0] - sx * c[0][2]) as f64;
    let ay = (c[0][1] - sy * c[0][2]) as f64;
    let bx = (c[1][0] - sx * c[1][2]) as f64;
    let by = (c[1][1] - sy * c[1][2]) as f64;
    let cx = (c[2][0] - sx * c[2][2]) as f64;
    let cy = (c[2][1] - sy * c[2][2]) as f64;
    let u = (cx * by - cy * bx) as f32;
    let v = (ax * cy - ay * cx) as f32;
    let w = (bx * ay - by * ax) as f32;
    let det = u + v + w;
    let t = (u * (sz * c[0][2]) + v * (sz * c[1][2]) + w * (sz * c[2][2])) / det;
    (u, v, w, t)
}

/// The single-precision core shared by both shears: corner components
/// relative to the origin, permuted, per lane.
#[inline(always)]
#[allow(clippy::type_complexity)]
fn core<const N: usize>(
    rel: impl Fn(usize, usize, usize) -> f32,
    sx: &[f32; N],
    sy: &[f32; N],
    sz: &[f32; N],
) -> ([f32; N], [f32; N], [f32; N], [f32; N]) {
    let mut u = [0.0f32; N];
    let mut v = [0.0f32; N];
    let mut w = [0.0f32; N];
    let mut tt = [0.0f32; N];
    let mut any_edge = false;
    for i in 0..N {
        // rel(i, corner, slot): slot 0, 1, 2 = kx, ky, kz.
        let (az, bz, cz) = (rel(i, 0, 2), rel(i, 1, 2), rel(i, 2, 2));
        let ax = rel(i, 0, 0) - sx[i] * az;
        let ay = rel(i, 0, 1) - sy[i] * az;
        let bx = rel(i, 1, 0) - sx[i] * bz;
        let by = rel(i, 1, 1) - sy[i] * bz;
        let cx = rel(i, 2, 0) - sx[i] * cz;
        let cy = rel(i, 2, 1) - sy[i] * cz;
        u[i] = cx * by - cy * bx;
        v[i] = ax * cy - ay * cx;
        w[i] = bx * ay - by * ax;
        any_edge |= (u[i] == 0.0) | (v[i] == 0.0) | (w[i] == 0.0);
        let det = u[i] + v[i] + w[i];
        tt[i] = (u[i] * (sz[i] * az) + v[i] * (sz[i] * bz) + w[i] * (sz[i] * cz)) / det;
    }
    if any_edge {
        for i in 0..N {
            if u[i] == 0.0 || v[i] == 0.0 || w[i] == 0.0 {
                let c = [0, 1, 2].map(|corner| [0, 1, 2].map(|slot| rel(i, corner, slot)));
                (u[i], v[i], w[i], tt[i]) = edge_lane(c, (sx[i], sy[i], sz[i]));
            }
        }
    }
    (u, v, w, tt)
}

impl<const N: usize> TriangleTest<N> for Shear<N> {
    #[inline(always)]
    fn uniform(&self) -> Option<&Shear<N>> {
        Some(self)
    }

    #[inline(always)]
    fn test(&self, p: &Packet<N>, c: &[[f32; 3]; 3]) -> ([f32; N], [f32; N], [f32; N], [f32; N]) {
        let k = [self.kx, self.ky, self.kz];
        core(
            |i, corner, slot| c[corner][k[slot]] - p.org[k[slot]][i],
            &self.sx,
            &self.sy,
            &self.sz,
        )
    }
}

impl<const N: usize> TriangleTest<N> for MixedShear<N> {
    #[inline(always)]
    fn test(&self, _p: &Packet<N>, c: &[[f32; 3]; 3]) -> ([f32; N], [f32; N], [f32; N], [f32; N]) {
        // Exactly one mask of the three is set: the component itself.
        let pick = |corner: usize, slot: usize, i: usize| {
            let [x, y, z] = c[corner].map(f32::to_bits);
            let m = &self.pick[slot];
            f32::from_bits((x & m[0][i]) | (y & m[1][i]) | (z & m[2][i]))
        };
        core(
            |i, corner, slot| pick(corner, slot, i) - self.o[slot][i],
            &self.sx,
            &self.sy,
            &self.sz,
        )
    }
}

/// What [`Traversal::run`] stopped at.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Step {
    /// Every lane has its final answer.
    Done,
    /// The packet needs this voxel; call `run` again once it is resident.
    Missing(u32),
}

/// The resumable state of one packet's traversal: the BSP nodes still to
/// visit, nearest on top.
#[derive(Clone, Debug)]
pub struct Traversal<const N: usize> {
    stack: Vec<u32>,
    started: bool,
    /// Voxels entered (for statistics).
    pub voxels_visited: u32,
}

impl<const N: usize> Default for Traversal<N> {
    fn default() -> Self {
        Traversal {
            stack: Vec::with_capacity(64),
            started: false,
            voxels_visited: 0,
        }
    }
}

impl<const N: usize> Traversal<N> {
    /// Forgets everything, to trace a new packet.
    pub fn reset(&mut self) {
        self.stack.clear();
        self.started = false;
        self.voxels_visited = 0;
    }

    /// Traverses until the packet is done or needs a voxel `source` lacks.
    #[inline(always)]
    pub fn run(
        &mut self,
        packet: &mut Packet<N>,
        top: &TopLevel,
        source: &dyn VoxelSource,
    ) -> Step {
        // Set up at the first voxel: a packet that meets none (sky) never
        // needs it.
        let mut shear: Option<AnyShear<N>> = None;
        // The top level's boxes tested as a voxel's are, in world
        // coordinates, where the packet's lanes agree on every sign.
        let root = &top.boxes[0];
        let world = if root.is_empty() {
            None
        } else {
            // A loop: through `array::map` LLVM called a closure per packet.
            let mut extent = [0.0; 3];
            for a in 0..3 {
                extent[a] = root.min[a].abs().max(root.max[a].abs());
            }
            FrameRays::world(packet, extent)
        };
        if !self.started {
            self.started = true;
            self.stack.push(0);
        }
        while let Some(node) = self.stack.pop() {
            // Every node is a box of the geometry below it: a lane goes on
            // where its ray meets the box before its current hit.
            let b = &top.boxes[node as usize];
            if b.is_empty() {
                continue;
            }
            let (t0, t1) = match &world {
                Some(w) => w.interval(packet, b.min, b.max),
                None => packet.slab(b.min, b.max),
            };
            let mut live = false;
            for i in 0..N {
                live |= t0[i] <= t1[i];
            }
            if !live {
                continue;
            }
            match top.nodes[node as usize] {
                TopNode::Leaf { voxel: None } => {}
                TopNode::Leaf { voxel: Some(id) } => {
                    let Some(vox) = source.voxel(id) else {
                        self.stack.push(node);
                        return Step::Missing(id);
                    };
                    self.voxels_visited += 1;
                    // Each lane searches the voxel only where it crosses
                    // the voxel's content box: a triangle is stored in
                    // every cell it reaches, and each hit point lies in a
                    // content box the ray enters, so the parts of
                    // replicated triangles outside this cell are left to
                    // their own voxels (the nearest hit is a minimum over
                    // all of them either way).
                    if shear.is_none() {
                        shear = Some(AnyShear::new(packet));
                    }
                    match shear.as_ref().expect("just set") {
                        AnyShear::Uniform(s) if packet.any_hit => {
                            packet.voxel::<_, true>(s, &vox, (&t0, &t1))
                        }
                        AnyShear::Uniform(s) => packet.voxel::<_, false>(s, &vox, (&t0, &t1)),
                        AnyShear::Mixed(s) if packet.any_hit => {
                            packet.voxel::<_, true>(s, &vox, (&t0, &t1))
                        }
                        AnyShear::Mixed(s) => packet.voxel::<_, false>(s, &vox, (&t0, &t1)),
                    }
                    if packet.any_hit && packet.all_blocked() {
                        self.stack.clear();
                        break;
                    }
                }
                TopNode::Split {
                    axis, left, right, ..
                } => {
                    // A child that is a voxel: its first nodes start
                    // loading now, while the packet tests the boxes
                    // before it.
                    for child in [left, right] {
                        if let TopNode::Leaf { voxel: Some(id) } = top.nodes[child as usize] {
                            source.prefetch(id);
                        }
                    }
                    // Near child on top: forward rays meet the left cell
                    // first. A shadow packet (any hit will do) takes the
                    // far child first instead: it starts on a surface, and
                    // what blocks it is more often what encloses it (a
                    // ceiling, a wall, the far side of a closed object)
                    // than the clutter around where it starts (measured by
                    // `scripts/bench-kernel`, the living room the most).
                    let left_first = packet.dir[axis as usize][0] >= 0.0;
                    if left_first != packet.any_hit {
                        self.stack.push(right);
                        self.stack.push(left);
                    } else {
                        self.stack.push(left);
                        self.stack.push(right);
                    }
                }
            }
        }
        Step::Done
    }
}
