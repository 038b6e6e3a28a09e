//! What the kernel traverses: the high-level BSP (from the manifest) and
//! voxels in the kernel's layout, supplied by a [`VoxelSource`].

use dray_scene::db::manifest::{BspNode, Manifest};
use dray_scene::db::{Database, DbError};
use dray_scene::voxel::{decode_normal, BvhNode, Voxel};
use dray_scene::{Aabb, Ray};
use glam::Vec3;
use std::sync::Arc;

/// A node of the high-level BSP in traversal form.
#[derive(Clone, Copy, Debug)]
pub enum TopNode {
    Split {
        axis: u8,
        pos: f32,
        left: u32,
        right: u32,
    },
    Leaf {
        voxel: Option<u32>,
    },
}

/// The high-level BSP: everything the kernel needs before any voxel.
#[derive(Clone, Debug)]
pub struct TopLevel {
    pub nodes: Vec<TopNode>,
    /// Per node, the bounds of the geometry below it (each voxel's content
    /// box, united upwards; empty for empty space): the kernel walks the
    /// BSP as a hierarchy of these boxes, so rays through the empty part
    /// of a cell skip it.
    pub boxes: Vec<Aabb>,
    /// Voxels of the model (ids are below this).
    pub voxel_count: usize,
}

impl TopLevel {
    pub fn from_manifest(m: &Manifest) -> TopLevel {
        TopLevel {
            boxes: content_boxes(m),
            voxel_count: m.voxels.len(),
            nodes: m
                .nodes
                .iter()
                .map(|n| match *n {
                    BspNode::Split {
                        axis,
                        pos,
                        left,
                        right,
                    } => TopNode::Split {
                        axis,
                        pos,
                        left,
                        right,
                    },
                    BspNode::Leaf { voxel } => TopNode::Leaf { voxel },
                })
                .collect(),
        }
    }
}

impl TopLevel {
    /// The voxel whose cell holds point `p` (a point on a split plane
    /// goes right); `None` for empty space or a point outside the model.
    /// Unlike the voxel a hit was found in (a triangle that straddles a
    /// split is in several), this depends on the point only.
    pub fn voxel_at(&self, p: Vec3) -> Option<u32> {
        let mut node = 0usize;
        // A tree is at most as deep as it has nodes.
        for _ in 0..self.nodes.len() {
            match *self.nodes.get(node)? {
                TopNode::Leaf { voxel } => return voxel,
                TopNode::Split {
                    axis,
                    pos,
                    left,
                    right,
                } => {
                    node = if p[axis as usize] < pos { left } else { right } as usize;
                }
            }
        }
        None
    }
}

impl TopLevel {
    /// Walks the BSP front to back along `ray` and appends to `out` the
    /// first `max` voxels whose content box the ray enters (one ray, no
    /// SIMD: for sampling a view coarsely, as the prefetcher does).
    /// `stack` is scratch space.
    pub fn voxels_along(&self, ray: &Ray, max: usize, stack: &mut Vec<u32>, out: &mut Vec<u32>) {
        stack.clear();
        stack.push(0);
        let mut found = 0;
        while let Some(n) = stack.pop() {
            let n = n as usize;
            let (Some(node), Some(b)) = (self.nodes.get(n), self.boxes.get(n)) else {
                continue;
            };
            if b.is_empty() || b.ray_interval(ray, 0.0, f32::INFINITY).is_none() {
                continue;
            }
            match *node {
                TopNode::Leaf { voxel: Some(v) } => {
                    out.push(v);
                    found += 1;
                    if found >= max {
                        return;
                    }
                }
                TopNode::Leaf { voxel: None } => {}
                TopNode::Split {
                    axis,
                    pos,
                    left,
                    right,
                } => {
                    // The manifest's check keeps axis under 3.
                    let a = axis as usize;
                    let (o, d) = (ray.origin[a], ray.dir[a]);
                    let left_first = o < pos || (o == pos && d <= 0.0);
                    let (near, far) = if left_first {
                        (left, right)
                    } else {
                        (right, left)
                    };
                    stack.push(far);
                    stack.push(near);
                }
            }
        }
    }
}

/// Asks the CPU to start loading the cache line at `p` (a hint: it never
/// faults, whatever `p` is).
#[inline(always)]
pub(crate) fn prefetch(p: *const u8) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: prefetching reads nothing and cannot fault, for any address.
    unsafe {
        std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(p as *const i8);
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = p;
}

/// Each node's content box, children before parents (an explicit
/// post-order walk: the manifest is trusted to be a tree, not to be in any
/// particular order).
fn content_boxes(m: &Manifest) -> Vec<Aabb> {
    let mut boxes = vec![Aabb::EMPTY; m.nodes.len()];
    let mut stack = vec![(0usize, false)];
    while let Some((i, children_done)) = stack.pop() {
        match m.nodes[i] {
            BspNode::Leaf { voxel: Some(v) } => boxes[i] = m.voxels[v as usize].content,
            BspNode::Leaf { voxel: None } => {}
            BspNode::Split { left, right, .. } if children_done => {
                boxes[i] = boxes[left as usize].union(&boxes[right as usize]);
            }
            BspNode::Split { left, right, .. } => {
                stack.push((i, true));
                stack.push((left as usize, false));
                stack.push((right as usize, false));
            }
        }
    }
    boxes
}

/// The voxel's BVH with its boxes clipped to the voxel's cell: each leaf
/// the union of its triangles' bounds, each intersected with the cell (min
/// and max alone: nothing rounds), each interior node the union of its
/// children.
///
/// A triangle is stored in every voxel whose cell it reaches, and a voxel
/// only has to find the hits within its cell: each lane searches it only
/// within the voxel's content box (which lies in the cell), and a hit
/// outside is found in the voxel there. Unclipped, long triangles (many
/// in the plants) would take a voxel's boxes, and its frame, far out of
/// its cell; the preprocessor's SAH build bins the clipped bounds too
/// (measured by `scripts/bench-kernel`). A leaf none of whose triangles
/// reaches into the cell (never built by the preprocessor) keeps its whole
/// box.
fn clipped_to_cell(v: &Voxel) -> Vec<BvhNode> {
    let mut nodes = v.bvh.clone();
    for i in (0..nodes.len()).rev() {
        let n = nodes[i];
        nodes[i].bounds = if n.is_leaf() {
            let mut b = Aabb::EMPTY;
            for t in &v.triangles[n.first as usize..(n.first + n.count) as usize] {
                let mut tb = Aabb::EMPTY;
                for &k in t {
                    tb.grow(Vec3::from_array(v.positions[k as usize]));
                }
                let c = tb.intersection(&v.bounds);
                if !c.is_empty() {
                    b = b.union(&c);
                }
            }
            if b.is_empty() {
                n.bounds
            } else {
                b
            }
        } else {
            nodes[i + 1].bounds.union(&nodes[n.first as usize].bounds)
        };
    }
    nodes
}

/// A node of the kernel's 4-wide BVH in one cache line: the boxes of up to
/// four children side by side (one node load tests all of them against a
/// packet) in 16-bit fixed point within the voxel's [`Frame`], and for each
/// child either an interior node index or a leaf's triangle range.
///
/// Quantized rather than in floats (two lines), as loads from memory are a
/// large part of a far view's time, and the voxels take less memory
/// (`scripts/bench-kernel`). The boxes are rounded outwards, so a
/// dequantized box always holds the exact one: rounding costs a few extra
/// box hits, never a hit.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
pub struct WideNode {
    /// `qmin[axis][child]`, `qmax[axis][child]`: quanta of the frame.
    pub qmin: [[u16; 4]; 3],
    pub qmax: [[u16; 4]; 3],
    /// Per child, the kind in the top bits (0 for an interior node, a
    /// leaf's triangle count, or [`WideNode::EMPTY`] past the last child)
    /// and below them the interior node's index or the leaf's first
    /// triangle.
    pub child: [u32; 4],
}

impl WideNode {
    pub const KIND_SHIFT: u32 = 29;
    /// The kind of a slot past the last child.
    pub const EMPTY: u32 = 7;
    pub const INDEX_MASK: u32 = (1 << Self::KIND_SHIFT) - 1;

    /// 0 for an interior node, a leaf's triangle count, or `EMPTY`.
    #[inline(always)]
    pub fn kind(&self, c: usize) -> u32 {
        self.child[c] >> Self::KIND_SHIFT
    }

    /// An interior child's node index, or a leaf's first triangle.
    #[inline(always)]
    pub fn index(&self, c: usize) -> u32 {
        self.child[c] & Self::INDEX_MASK
    }
}

/// The fixed-point frame of a voxel's node boxes: quantum `q` of axis `a`
/// is the plane `origin[a] + q * scale[a]`, computed in `f32` by
/// [`Frame::plane`], the same at build and at traversal time.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Frame {
    pub origin: [f32; 3],
    pub scale: [f32; 3],
}

impl Frame {
    /// The largest quantum.
    pub const TOP: u16 = u16::MAX;

    /// The frame of a voxel without nodes.
    pub const EMPTY: Frame = Frame {
        origin: [0.0; 3],
        scale: [0.0; 3],
    };

    /// A frame covering `b` (non-empty, finite): quantum 0 is `b.min`, the
    /// top quantum at or beyond `b.max`.
    pub fn covering(b: &Aabb) -> Frame {
        let mut scale = [0.0f32; 3];
        for (a, scale) in scale.iter_mut().enumerate() {
            let (lo, hi) = (b.min[a], b.max[a]);
            // A span beyond f32's range overflows: the largest finite
            // scale then takes the top plane to +inf, which bounds it.
            let mut s = ((hi - lo) / Self::TOP as f32).min(f32::MAX);
            // Rounding may leave the top plane short of `hi`: step up.
            while lo + Self::TOP as f32 * s < hi {
                s = next_up(s);
            }
            *scale = s;
        }
        Frame {
            origin: b.min,
            scale,
        }
    }

    #[inline(always)]
    pub fn plane(&self, axis: usize, q: u16) -> f32 {
        self.origin[axis] + q as f32 * self.scale[axis]
    }

    /// The largest quantum whose plane is at or below `x` (`x` at or
    /// above the origin). Planes grow with the quantum, so the search only
    /// corrects the estimate's rounding.
    fn floor(&self, axis: usize, x: f32) -> u16 {
        // The estimate is in [0, TOP], so the cast truncates it down: the
        // floor, without a call into libm (baseline x86-64 has no rounding
        // instruction), which is dear in a voxel's preparation
        // (`trace/examples/prepare.rs`).
        let mut q = self.estimate(axis, x) as u16;
        while q > 0 && self.plane(axis, q) > x {
            q -= 1;
        }
        while q < Self::TOP && self.plane(axis, q + 1) <= x {
            q += 1;
        }
        q
    }

    /// The smallest quantum whose plane is at or above `x` (`x` at or
    /// below the top plane).
    fn ceil(&self, axis: usize, x: f32) -> u16 {
        // Truncated as in `floor`: the first loop steps it up.
        let mut q = self.estimate(axis, x) as u16;
        while q < Self::TOP && self.plane(axis, q) < x {
            q += 1;
        }
        while q > 0 && self.plane(axis, q - 1) >= x {
            q -= 1;
        }
        q
    }

    /// [`Self::floor`] of four values at once: each estimate moved by one
    /// quantum where its plane or the next says so, then checked, without
    /// branches (the four are independent, where `floor`'s searches ended
    /// in branches that each waited for a plane). Should the check fail
    /// (the estimate is off by under a hundredth of a quantum, so only in
    /// degenerate frames), `floor`'s search decides: the same answers
    /// always. Widening a voxel's BVH quantizes its child boxes this way.
    fn floor4(&self, axis: usize, x: [f32; 4]) -> [u16; 4] {
        let plane = |k: [u16; 4]| k.map(|k| self.plane(axis, k));
        let mut k = x.map(|x| self.estimate(axis, x) as u16);
        let at = plane(k);
        let next = plane(k.map(|k| k.saturating_add(1)));
        for i in 0..4 {
            k[i] -= u16::from((k[i] > 0) & (at[i] > x[i]));
            k[i] += u16::from((k[i] < Self::TOP) & (next[i] <= x[i]) & (at[i] <= x[i]));
        }
        let (at, next) = (plane(k), plane(k.map(|k| k.saturating_add(1))));
        let mut exact = true;
        for i in 0..4 {
            exact &= ((k[i] == 0) | (at[i] <= x[i])) & ((k[i] == Self::TOP) | (next[i] > x[i]));
        }
        if exact {
            k
        } else {
            x.map(|x| self.floor(axis, x))
        }
    }

    /// [`Self::ceil`] of four values at once, as [`Self::floor4`].
    fn ceil4(&self, axis: usize, x: [f32; 4]) -> [u16; 4] {
        let plane = |k: [u16; 4]| k.map(|k| self.plane(axis, k));
        let mut k = x.map(|x| self.estimate(axis, x) as u16);
        let at = plane(k);
        for i in 0..4 {
            // Truncated, the estimate's plane is mostly short of x.
            k[i] += u16::from((k[i] < Self::TOP) & (at[i] < x[i]));
        }
        let (at, below) = (plane(k), plane(k.map(|k| k.saturating_sub(1))));
        let mut exact = true;
        for i in 0..4 {
            exact &= ((k[i] == Self::TOP) | (at[i] >= x[i])) & ((k[i] == 0) | (below[i] < x[i]));
        }
        if exact {
            k
        } else {
            x.map(|x| self.ceil(axis, x))
        }
    }

    /// Where `x` falls in quanta, clamped to the frame.
    fn estimate(&self, axis: usize, x: f32) -> f32 {
        let s = self.scale[axis];
        let q = if s > 0.0 {
            (x - self.origin[axis]) / s
        } else {
            0.0
        };
        if q.is_nan() {
            0.0
        } else {
            q.clamp(0.0, Self::TOP as f32)
        }
    }
}

/// The next larger `f32` after a finite, non-negative `x`.
fn next_up(x: f32) -> f32 {
    f32::from_bits(x.to_bits() + 1)
}

/// Collapses the voxel's binary BVH into a 4-wide one: each wide node takes
/// the two children of a binary node and keeps opening its interior child
/// of largest surface area until it has four. Halves the chain of
/// dependent node loads a ray walks. Boxes are quantized within `frame`,
/// which covers the root's box (every box below lies within it).
fn widen(bvh: &[BvhNode], frame: &Frame) -> Vec<WideNode> {
    fn is_leaf(bvh: &[BvhNode], i: usize) -> bool {
        bvh[i].count > 0
    }
    fn children(bvh: &[BvhNode], i: usize) -> [usize; 2] {
        [i + 1, bvh[i].first as usize]
    }
    fn emit(bvh: &[BvhNode], frame: &Frame, kids: &[usize], out: &mut Vec<WideNode>) -> u32 {
        let me = out.len();
        out.push(WideNode {
            qmin: [[0; 4]; 3],
            qmax: [[0; 4]; 3],
            child: [WideNode::EMPTY << WideNode::KIND_SHIFT; 4],
        });
        // Slots without a child quantize the frame's origin (and are
        // left empty).
        let mut min = frame.origin.map(|o| [o; 4]);
        let mut max = min;
        let mut child = [0; 4];
        for (slot, &k) in kids.iter().enumerate() {
            // Leaves hold at most MAX_LEAF_TRIANGLES (checked when a voxel
            // is decoded), and a voxel's nodes and triangles number under
            // 2^29 (its raw size is bounded): both fit their bits.
            child[slot] = if is_leaf(bvh, k) {
                (bvh[k].count << WideNode::KIND_SHIFT) | bvh[k].first
            } else {
                let (kids, n) = open(bvh, k);
                emit(bvh, frame, &kids[..n], out)
            };
            for a in 0..3 {
                min[a][slot] = bvh[k].bounds.min[a];
                max[a][slot] = bvh[k].bounds.max[a];
            }
        }
        let node = &mut out[me];
        for a in 0..3 {
            let (qmin, qmax) = (frame.floor4(a, min[a]), frame.ceil4(a, max[a]));
            let n = kids.len();
            node.qmin[a][..n].copy_from_slice(&qmin[..n]);
            node.qmax[a][..n].copy_from_slice(&qmax[..n]);
        }
        node.child[..kids.len()].copy_from_slice(&child[..kids.len()]);
        me as u32
    }
    /// Up to four descendants of interior node `i` that cover it, and how
    /// many (in an array: a `Vec` for each wide node would allocate in a
    /// voxel's preparation, `trace/examples/prepare.rs`).
    fn open(bvh: &[BvhNode], i: usize) -> ([usize; 4], usize) {
        let [a, b] = children(bvh, i);
        let (mut kids, mut n) = ([a, b, 0, 0], 2);
        while n < 4 {
            let widest = kids[..n]
                .iter()
                .enumerate()
                .filter(|(_, &k)| !is_leaf(bvh, k))
                .max_by(|a, b| bvh[*a.1].bounds.area().total_cmp(&bvh[*b.1].bounds.area()))
                .map(|(slot, _)| slot);
            let Some(slot) = widest else { break };
            // The widest makes way for the last (as `Vec::swap_remove`),
            // and its two children go at the end.
            let k = kids[slot];
            kids[slot] = kids[n - 1];
            kids[n - 1..n + 1].copy_from_slice(&children(bvh, k));
            n += 1;
        }
        (kids, n)
    }
    let mut out = Vec::new();
    if bvh.is_empty() {
        return out;
    }
    // The root itself is the only child of a one-leaf voxel.
    let (top, n) = if is_leaf(bvh, 0) {
        ([0; 4], 1)
    } else {
        open(bvh, 0)
    };
    emit(bvh, frame, &top[..n], &mut out);
    out
}

/// A voxel in the kernel's layout: BVH nodes, each triangle's corners
/// gathered in leaf order (one cache line and a half per triangle, no
/// index indirection in the inner loop), and what shading needs.
#[derive(Debug)]
pub struct PreparedVoxel {
    pub id: u32,
    /// The 4-wide BVH; node 0 is the root (empty without triangles).
    pub nodes: Vec<WideNode>,
    /// The fixed-point frame of the nodes' boxes.
    pub frame: Frame,
    /// Corner positions of triangle i: `corners[i]` = [a, b, c].
    pub corners: Vec<[[f32; 3]; 3]>,
    /// ORIGINAL triangle id of triangle i.
    pub ids: Vec<u32>,
    /// Local vertex indices, for normals and colors.
    pub triangles: Vec<[u32; 3]>,
    pub normals: Vec<Vec3>,
    pub colors: Vec<[u8; 4]>,
    /// Decoded size, for cache accounting.
    pub bytes: usize,
}

impl PreparedVoxel {
    /// Starts loading the root node and the two after it (in depth-first
    /// order its first child and grandchild) into the cache: the first
    /// loads of a packet that enters the voxel, which otherwise wait on
    /// memory with nothing else to do (far views, `scripts/bench-kernel`).
    #[inline(always)]
    pub fn prefetch_root(&self) {
        let root = self.nodes.as_ptr() as *const u8;
        for line in 0..3 {
            prefetch(root.wrapping_add(64 * line));
        }
    }

    pub fn new(id: u32, v: &Voxel) -> PreparedVoxel {
        // The frame covers the root's box, clipped to the cell (see
        // `clipped_to_cell`).
        let bvh = clipped_to_cell(v);
        let frame = bvh
            .first()
            .map_or(Frame::EMPTY, |root| Frame::covering(&root.bounds));
        let nodes = widen(&bvh, &frame);
        let corners: Vec<[[f32; 3]; 3]> = v
            .triangles
            .iter()
            .map(|t| t.map(|i| v.positions[i as usize]))
            .collect();
        let normals: Vec<Vec3> = v.normals.iter().map(|&n| decode_normal(n)).collect();
        let bytes = nodes.len() * std::mem::size_of::<WideNode>()
            + corners.len() * 36
            + v.triangle_ids.len() * 4
            + v.triangles.len() * 12
            + normals.len() * 12
            + v.colors.len() * 4;
        PreparedVoxel {
            id,
            nodes,
            frame,
            corners,
            ids: v.triangle_ids.clone(),
            triangles: v.triangles.clone(),
            normals,
            colors: v.colors.clone(),
            bytes,
        }
    }

    /// Starts loading local triangle `tri`'s vertex indices, the first
    /// link of [`Self::prefetch_surface`]'s chain.
    #[inline(always)]
    pub fn prefetch_indices(&self, tri: u32) {
        prefetch(self.triangles.as_ptr().wrapping_add(tri as usize) as *const u8);
    }

    /// Starts loading what shading reads of local triangle `tri`: its
    /// vertex indices are read now, its corners' normals and colors
    /// prefetched. A packet's hits are looked up one lane after
    /// another, and each lookup is a chain of misses (indices, then
    /// normals and colors) in a voxel that traversal did not read;
    /// starting every lane's chain first lets them wait on memory together.
    #[inline(always)]
    pub fn prefetch_surface(&self, tri: u32) {
        let Some(&corners) = self.triangles.get(tri as usize) else {
            return;
        };
        for i in corners {
            prefetch(self.normals.as_ptr().wrapping_add(i as usize) as *const u8);
            prefetch(self.colors.as_ptr().wrapping_add(i as usize) as *const u8);
        }
    }
}

/// Where the kernel gets voxels. `None` means "not resident": the packet
/// that asked is suspended until the voxel arrives.
pub trait VoxelSource: Sync {
    fn voxel(&self, id: u32) -> Option<VoxelRef<'_>>;

    /// A hint that the kernel may soon enter voxel `id`: a source that
    /// finds it without locks or counting starts loading the voxel's
    /// first nodes into the cache ([`PreparedVoxel::prefetch_root`]).
    /// Never counts as a use: nothing is recorded, nothing is marked
    /// recently used. By default, nothing.
    #[inline(always)]
    fn prefetch(&self, _id: u32) {}
}

/// A voxel as a source hands it to the kernel: borrowed where the source
/// keeps it for at least as long as the borrow (every voxel of a
/// [`ResidentSource`], a voxel a job holds), or shared where a cache may
/// evict it meanwhile. A packet enters a voxel many times a frame, and a
/// reference count taken each time costs two atomic operations on a cache
/// line that every render thread touches (`scripts/bench-kernel`).
pub enum VoxelRef<'a> {
    Borrowed(&'a PreparedVoxel),
    Shared(Arc<PreparedVoxel>),
}

impl std::ops::Deref for VoxelRef<'_> {
    type Target = PreparedVoxel;

    #[inline(always)]
    fn deref(&self) -> &PreparedVoxel {
        match self {
            VoxelRef::Borrowed(v) => v,
            VoxelRef::Shared(v) => v,
        }
    }
}

/// Every voxel of a database, loaded up front (for `dray render`).
pub struct ResidentSource {
    voxels: Vec<Arc<PreparedVoxel>>,
}

impl ResidentSource {
    /// Every voxel of `db`, read, decoded and prepared on every core (one
    /// thread's rate: `trace/examples/prepare.rs`). A bad voxel is an
    /// error naming it: the first bad one by id, as in one pass in order
    /// (ids are handed out in order, and every id below a failed one is
    /// finished before the threads stop).
    pub fn load(db: &Database) -> Result<ResidentSource, DbError> {
        let count = db.manifest.voxels.len();
        let threads = std::thread::available_parallelism()
            .map_or(1, |n| n.get())
            .min(count.max(1));
        let next = std::sync::atomic::AtomicUsize::new(0);
        let failed = std::sync::atomic::AtomicBool::new(false);
        let work = || {
            let mut done = Vec::new();
            while !failed.load(std::sync::atomic::Ordering::Relaxed) {
                let id = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                if id >= count {
                    break;
                }
                let voxel = db
                    .load_voxel(id as u32)
                    .map(|v| Arc::new(PreparedVoxel::new(id as u32, &v)));
                failed.fetch_or(voxel.is_err(), std::sync::atomic::Ordering::Relaxed);
                done.push((id, voxel));
            }
            done
        };
        let mut loaded: Vec<(usize, Result<Arc<PreparedVoxel>, DbError>)> =
            std::thread::scope(|s| {
                let helpers: Vec<_> = (1..threads).map(|_| s.spawn(work)).collect();
                let mut all = work();
                for h in helpers {
                    all.extend(h.join().unwrap_or_else(|p| std::panic::resume_unwind(p)));
                }
                all
            });
        loaded.sort_by_key(|(id, _)| *id);
        let voxels = loaded
            .into_iter()
            .map(|(_, v)| v)
            .collect::<Result<Vec<_>, DbError>>()?;
        Ok(ResidentSource { voxels })
    }

    pub fn bytes(&self) -> usize {
        self.voxels.iter().map(|v| v.bytes).sum()
    }

    pub fn voxel_count(&self) -> usize {
        self.voxels.len()
    }

    /// Voxel `id`, as a handle of its own.
    pub fn shared(&self, id: u32) -> Option<Arc<PreparedVoxel>> {
        self.voxels.get(id as usize).cloned()
    }
}

impl VoxelSource for ResidentSource {
    #[inline]
    fn voxel(&self, id: u32) -> Option<VoxelRef<'_>> {
        self.voxels.get(id as usize).map(|v| VoxelRef::Borrowed(v))
    }

    #[inline]
    fn prefetch(&self, id: u32) {
        if let Some(v) = self.voxels.get(id as usize) {
            v.prefetch_root();
        }
    }
}

/// A source that records which voxels the kernel enters: the working set
/// of what it renders (the paper's "visible geometry"), in the same bytes
/// as a client's cache counts. `dray render --path --working-set` reports
/// it per frame; the affinity benchmark sizes the clients' caches by it.
pub struct RecordingSource<'a, S> {
    inner: &'a S,
    /// Per voxel id: whether it was entered since the last [`Self::take`].
    entered: Vec<std::sync::atomic::AtomicBool>,
}

impl<'a, S: VoxelSource> RecordingSource<'a, S> {
    pub fn new(inner: &'a S, voxels: usize) -> Self {
        RecordingSource {
            inner,
            entered: (0..voxels)
                .map(|_| std::sync::atomic::AtomicBool::new(false))
                .collect(),
        }
    }

    /// The voxels entered since the last call, and clears the record.
    pub fn take(&mut self) -> Vec<u32> {
        self.entered
            .iter_mut()
            .enumerate()
            .filter_map(|(id, e)| std::mem::take(e.get_mut()).then_some(id as u32))
            .collect()
    }
}

impl<S: VoxelSource> VoxelSource for RecordingSource<'_, S> {
    fn prefetch(&self, id: u32) {
        // A prefetched voxel may never be entered: not recorded.
        self.inner.prefetch(id);
    }

    fn voxel(&self, id: u32) -> Option<VoxelRef<'_>> {
        let v = self.inner.voxel(id)?;
        if let Some(e) = self.entered.get(id as usize) {
            // Read first: after its first entry a voxel's flag is only
            // read, so the render threads do not fight over its line.
            if !e.load(std::sync::atomic::Ordering::Relaxed) {
                e.store(true, std::sync::atomic::Ordering::Relaxed);
            }
        }
        Some(v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dray_scene::mesh::Triangle;
    use proptest::prelude::*;

    /// A float of any sign and magnitude within `±2^exp_max`.
    fn arb_coord(exp_max: i32) -> impl Strategy<Value = f32> {
        (any::<bool>(), -30..exp_max, 0.0f32..1.0).prop_map(|(neg, e, m)| {
            let x = (1.0 + m) * 2f32.powi(e);
            if neg {
                -x
            } else {
                x
            }
        })
    }

    fn arb_box(exp_max: i32) -> impl Strategy<Value = Aabb> {
        proptest::collection::vec(arb_coord(exp_max), 6).prop_map(|c| {
            let mut b = Aabb::EMPTY;
            b.grow(Vec3::new(c[0], c[1], c[2]));
            b.grow(Vec3::new(c[3], c[4], c[5]));
            b
        })
    }

    proptest! {
        #![proptest_config(ProptestConfig {
            cases: 2000,
            failure_persistence: None,
            ..ProptestConfig::default()
        })]

        /// Quanta round outwards and are the tightest that do: the plane of
        /// a box's low quantum is at or below its minimum and the next one
        /// above it, and the other way round for the maximum, for boxes of
        /// any size and place, up to spans that overflow `f32`.
        #[test]
        fn quanta_hold_their_box_tightly(
            frame_box in arb_box(127),
            t in proptest::collection::vec(0.0f32..=1.0, 6),
        ) {
            let f = Frame::covering(&frame_box);
            for a in 0..3 {
                let (lo, hi) = (frame_box.min[a], frame_box.max[a]);
                prop_assert_eq!(f.plane(a, 0), lo);
                prop_assert!(f.plane(a, Frame::TOP) >= hi);
                prop_assert!(f.scale[a].is_finite());
                // A box inside the frame (a point of the span, as f32).
                let at = |s: f32| (lo as f64 + (hi as f64 - lo as f64) * s as f64) as f32;
                let (x0, x1) = (at(t[a].min(t[a + 3])), at(t[a].max(t[a + 3])));
                let (x0, x1) = (x0.clamp(lo, hi), x1.clamp(lo, hi));
                let q0 = f.floor(a, x0);
                prop_assert!(f.plane(a, q0) <= x0);
                prop_assert!(q0 == Frame::TOP || f.plane(a, q0 + 1) > x0);
                let q1 = f.ceil(a, x1);
                prop_assert!(f.plane(a, q1) >= x1);
                prop_assert!(q1 == 0 || f.plane(a, q1 - 1) < x1);
            }
        }
    }

    proptest! {
        /// Four bounds quantized at once give exactly what one after
        /// another do: inside the frame, out of it on either side, at its
        /// planes, far away, infinite or NaN, in frames of any size.
        #[test]
        fn four_at_once_quantize_as_one_at_a_time(
            frame_box in arb_box(127),
            picks in proptest::collection::vec((0u8..6, 0.0f32..=1.0, arb_coord(127)), 12),
        ) {
            let f = Frame::covering(&frame_box);
            for a in 0..3 {
                let (lo, hi) = (frame_box.min[a], frame_box.max[a]);
                let x: [f32; 4] = std::array::from_fn(|i| {
                    let (kind, t, far) = picks[4 * a + i];
                    match kind {
                        0 => (lo as f64 + (hi as f64 - lo as f64) * t as f64) as f32,
                        1 => f.plane(a, (t * Frame::TOP as f32) as u16),
                        2 => far,
                        3 => [f32::INFINITY, f32::NEG_INFINITY, f32::NAN][(t * 2.99) as usize],
                        4 => lo,
                        _ => hi,
                    }
                });
                prop_assert_eq!(f.floor4(a, x), x.map(|x| f.floor(a, x)), "floor of {:?}", x);
                prop_assert_eq!(f.ceil4(a, x), x.map(|x| f.ceil(a, x)), "ceil of {:?}", x);
            }
        }
    }

    /// Every child box of the wide BVH, out of the frame's fixed point,
    /// holds the part within the voxel's cell of every triangle below it
    /// (small triangles far from the frame's origin, coarse quanta against
    /// them, and long ones across it and out of the cell), and no box
    /// reaches out of the cell by more than a quantum.
    #[test]
    fn dequantized_boxes_hold_their_triangles() {
        let mut r = dray_scene::rng::Rng::new(7);
        let mut tris = Vec::new();
        for i in 0..3000u32 {
            // Every triangle reaches into the cell (its first corner),
            // as the preprocessor's do.
            let base = Vec3::new(
                r.range(1000.0, 1050.0),
                r.range(0.0, 50.0),
                r.range(-2000.0, -1950.0),
            );
            let size = if i % 100 == 0 { 200.0 } else { 0.01 };
            let p = [0, 1, 2].map(|k| {
                let offset = Vec3::new(r.unit(), r.unit(), r.unit()) * size;
                if k == 0 {
                    base
                } else {
                    base + offset
                }
            });
            tris.push(Triangle {
                positions: p,
                normals: [Vec3::Y; 3],
                colors: [[255; 4]; 3],
                id: i,
            });
        }
        let cell = Aabb::new(
            Vec3::new(1000.0, 0.0, -2000.0),
            Vec3::splat(50.0) + Vec3::new(1000.0, 0.0, -2000.0),
        );
        let v = Voxel::build(cell, &tris);
        let p = PreparedVoxel::new(0, &v);
        let dequantized = |n: &WideNode, c: usize| {
            let min = [0, 1, 2].map(|a| p.frame.plane(a, n.qmin[a][c]));
            let max = [0, 1, 2].map(|a| p.frame.plane(a, n.qmax[a][c]));
            Aabb { min, max }
        };
        // (node, the box it must lie in)
        let mut stack = vec![(0u32, None::<Aabb>)];
        let mut leaves = 0;
        while let Some((i, within)) = stack.pop() {
            let n = &p.nodes[i as usize];
            for c in 0..4 {
                let kind = n.kind(c);
                if kind == WideNode::EMPTY {
                    continue;
                }
                let b = dequantized(n, c);
                for a in 0..3 {
                    let quantum = p.frame.scale[a];
                    assert!(b.min[a] >= cell.min[a] - quantum, "{b:?} out of {cell:?}");
                    assert!(b.max[a] <= cell.max[a] + quantum, "{b:?} out of {cell:?}");
                }
                if let Some(w) = within {
                    assert!(
                        w.contains_box(&b),
                        "node {i} child {c}: {b:?} outside {w:?}"
                    );
                }
                if kind == 0 {
                    stack.push((n.index(c), Some(b)));
                    continue;
                }
                leaves += 1;
                for k in n.index(c)..n.index(c) + kind {
                    let tb = Aabb::from_points(&p.corners[k as usize].map(Vec3::from));
                    let tb = tb.intersection(&cell);
                    assert!(b.contains_box(&tb), "leaf {k}: {tb:?} outside {b:?}");
                }
            }
        }
        assert!(leaves >= 3000 / 4);
    }
}
