//! What the kernel traverses: the high-level BSP (from the manifest) and
//! voxels in the kernel's layout, supplied by a [`VoxelSource`].

use dray_scene::db::manifest::{BspNode, Manifest};
use dray_scene::db::{Database, DbError};
use dray_scene::voxel::{decode_normal, Voxel};
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

/// A node of the kernel's 4-wide BVH: the boxes of up to four children
/// side by side (one node load tests all of them against a packet), and
/// for each child either an interior node index (`count == 0`) or a leaf's
/// triangle range. Slots past the last child have `count == EMPTY`.
/// 128 bytes, two cache lines.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
pub struct WideNode {
    /// `min[axis][child]`, `max[axis][child]`.
    pub min: [[f32; 4]; 3],
    pub max: [[f32; 4]; 3],
    pub child: [u32; 4],
    pub count: [u32; 4],
}

impl WideNode {
    pub const EMPTY: u32 = u32::MAX;
}

/// Collapses the voxel's binary BVH into a 4-wide one: each wide node takes
/// the two children of a binary node and keeps opening its interior child
/// of largest surface area until it has four. Halves the chain of
/// dependent node loads a ray walks.
fn widen(bvh: &[dray_scene::voxel::BvhNode]) -> Vec<WideNode> {
    fn is_leaf(bvh: &[dray_scene::voxel::BvhNode], i: usize) -> bool {
        bvh[i].count > 0
    }
    fn children(bvh: &[dray_scene::voxel::BvhNode], i: usize) -> [usize; 2] {
        [i + 1, bvh[i].first as usize]
    }
    fn emit(bvh: &[dray_scene::voxel::BvhNode], kids: Vec<usize>, out: &mut Vec<WideNode>) -> u32 {
        let me = out.len();
        out.push(WideNode {
            min: [[f32::INFINITY; 4]; 3],
            max: [[f32::NEG_INFINITY; 4]; 3],
            child: [0; 4],
            count: [WideNode::EMPTY; 4],
        });
        for (slot, &k) in kids.iter().enumerate() {
            let (child, count) = if is_leaf(bvh, k) {
                (bvh[k].first, bvh[k].count)
            } else {
                (emit(bvh, open(bvh, k), out), 0)
            };
            let node = &mut out[me];
            for a in 0..3 {
                node.min[a][slot] = bvh[k].bounds.min[a];
                node.max[a][slot] = bvh[k].bounds.max[a];
            }
            node.child[slot] = child;
            node.count[slot] = count;
        }
        me as u32
    }
    /// Up to four descendants of interior node `i` that cover it.
    fn open(bvh: &[dray_scene::voxel::BvhNode], i: usize) -> Vec<usize> {
        let mut kids = children(bvh, i).to_vec();
        while kids.len() < 4 {
            let widest = kids
                .iter()
                .enumerate()
                .filter(|(_, &k)| !is_leaf(bvh, k))
                .max_by(|a, b| bvh[*a.1].bounds.area().total_cmp(&bvh[*b.1].bounds.area()))
                .map(|(slot, _)| slot);
            let Some(slot) = widest else { break };
            let k = kids.swap_remove(slot);
            kids.extend(children(bvh, k));
        }
        kids
    }
    let mut out = Vec::new();
    if bvh.is_empty() {
        return out;
    }
    // The root itself is the only child of a one-leaf voxel.
    let top = if is_leaf(bvh, 0) {
        vec![0]
    } else {
        open(bvh, 0)
    };
    emit(bvh, top, &mut out);
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
    pub fn new(id: u32, v: &Voxel) -> PreparedVoxel {
        let nodes = widen(&v.bvh);
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
            corners,
            ids: v.triangle_ids.clone(),
            triangles: v.triangles.clone(),
            normals,
            colors: v.colors.clone(),
            bytes,
        }
    }

    /// Interpolated unit shading normal and color of local triangle `tri`
    /// at barycentrics (u, v) (weights of corners b and c).
    pub fn surface(&self, tri: u32, u: f32, v: f32) -> (Vec3, [f32; 3]) {
        let [a, b, c] = self.triangles[tri as usize];
        let w = 1.0 - u - v;
        let n = self.normals[a as usize] * w
            + self.normals[b as usize] * u
            + self.normals[c as usize] * v;
        let col = |i: u32| {
            let c = self.colors[i as usize];
            Vec3::new(c[0] as f32, c[1] as f32, c[2] as f32) / 255.0
        };
        let color = col(a) * w + col(b) * u + col(c) * v;
        (n.normalize_or(Vec3::Y), color.to_array())
    }
}

/// Where the kernel gets voxels. `None` means "not resident": the packet
/// that asked is suspended until the voxel arrives.
pub trait VoxelSource: Sync {
    fn voxel(&self, id: u32) -> Option<VoxelRef<'_>>;
}

/// A voxel as a source hands it to the kernel: borrowed where the source
/// keeps it for at least as long as the borrow (every voxel of a
/// [`ResidentSource`], a voxel a job holds), or shared where a cache may
/// evict it meanwhile. A packet enters a voxel many times a frame; taking
/// a reference count each time (two atomic operations, on a cache line
/// that every render thread touches) made shadow rays inside the 12.5 M
/// plant 2-8 % slower.
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
    pub fn load(db: &Database) -> Result<ResidentSource, DbError> {
        let voxels = (0..db.manifest.voxels.len() as u32)
            .map(|id| Ok(Arc::new(PreparedVoxel::new(id, &db.load_voxel(id)?))))
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
