//! What the kernel traverses: the high-level BSP (from the manifest) and
//! voxels in the kernel's layout, supplied by a [`VoxelSource`].

use dray_scene::db::manifest::{BspNode, Manifest};
use dray_scene::db::{Database, DbError};
use dray_scene::voxel::{decode_normal, Voxel};
use dray_scene::Aabb;
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
    pub root: Aabb,
    pub nodes: Vec<TopNode>,
    /// Per node, the bounds of the geometry below it (each voxel's content
    /// box, united upwards; empty for empty space): the kernel walks the
    /// BSP as a hierarchy of these boxes, so rays through the empty part
    /// of a cell skip it.
    pub boxes: Vec<Aabb>,
    pub voxel_count: u32,
}

impl TopLevel {
    pub fn from_manifest(m: &Manifest) -> TopLevel {
        TopLevel {
            root: m.root_bounds,
            boxes: content_boxes(m),
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
            voxel_count: m.voxels.len() as u32,
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

/// A node of the kernel's 4-wide BVH, one cache line: the boxes of up to
/// four children, quantized to 8 bits per coordinate inside the node's own
/// box (rounded outwards, so they only ever grow), side by side so one load
/// tests all four against a packet; and for each child an interior node
/// index or a leaf entry ([`WideNode::leaf`]).
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
pub struct WideNode {
    pub origin: [f32; 3],
    pub scale: [f32; 3],
    /// `qmin[axis][child]`, `qmax[axis][child]`.
    pub qmin: [[u8; 4]; 3],
    pub qmax: [[u8; 4]; 3],
    pub child: [u32; 4],
}

impl WideNode {
    /// Marks a leaf entry: `LEAF | count << 24 | first`.
    pub const LEAF: u32 = 1 << 31;
    /// An unused child slot (a leaf of no triangles).
    pub const EMPTY: u32 = WideNode::LEAF;

    /// The entry of a leaf of `count` triangles from `first`, if it fits.
    pub fn leaf(first: u32, count: u32) -> Option<u32> {
        (count > 0 && count <= 0x7F && first <= 0x00FF_FFFF)
            .then_some(WideNode::LEAF | (count << 24) | first)
    }

    /// The (conservative) box of child `c`.
    #[inline(always)]
    pub fn child_box(&self, c: usize) -> ([f32; 3], [f32; 3]) {
        let mut min = [0.0; 3];
        let mut max = [0.0; 3];
        for a in 0..3 {
            min[a] = self.origin[a] + self.qmin[a][c] as f32 * self.scale[a];
            max[a] = self.origin[a] + self.qmax[a][c] as f32 * self.scale[a];
        }
        (min, max)
    }
}

/// Quantizes child boxes inside their union so every dequantized box
/// contains the exact one.
fn quantize(boxes: &[Aabb], child: [u32; 4]) -> WideNode {
    let union = boxes.iter().fold(Aabb::EMPTY, |u, b| u.union(b));
    let mut node = WideNode {
        origin: union.min,
        scale: [0.0; 3],
        qmin: [[0; 4]; 3],
        qmax: [[0; 4]; 3],
        child,
    };
    for a in 0..3 {
        let extent = union.max[a] - union.min[a];
        let mut scale = extent / 255.0 * (1.0 + 1.0 / 65536.0);
        'fit: loop {
            node.scale[a] = scale;
            for (c, b) in boxes.iter().enumerate() {
                let at = |q: u8| union.min[a] + q as f32 * scale;
                let q_of = |x: f32| {
                    if scale > 0.0 {
                        ((x - union.min[a]) / scale).clamp(0.0, 255.0)
                    } else {
                        0.0
                    }
                };
                let mut lo = q_of(b.min[a]).floor() as u8;
                while lo > 0 && at(lo) > b.min[a] {
                    lo -= 1;
                }
                let mut hi = q_of(b.max[a]).ceil() as u8;
                while hi < 255 && at(hi) < b.max[a] {
                    hi += 1;
                }
                if at(lo) > b.min[a] || at(hi) < b.max[a] {
                    // Rounding left the box uncovered: a coarser grid.
                    scale = if scale > 0.0 {
                        scale * 2.0
                    } else {
                        f32::MIN_POSITIVE
                    };
                    continue 'fit;
                }
                node.qmin[a][c] = lo;
                node.qmax[a][c] = hi;
            }
            break;
        }
    }
    node
}

/// Collapses the voxel's binary BVH into a 4-wide one: each wide node takes
/// the two children of a binary node and keeps opening its interior child
/// of largest surface area until it has four. Halves the chain of
/// dependent node loads a ray walks. Fails on a leaf the entry format
/// cannot hold (more than 127 triangles, or beyond triangle 2^24), which the
/// preprocessor never builds.
fn widen(bvh: &[dray_scene::voxel::BvhNode]) -> Result<Vec<WideNode>, String> {
    type Bvh = [dray_scene::voxel::BvhNode];
    fn is_leaf(bvh: &Bvh, i: usize) -> bool {
        bvh[i].count > 0
    }
    fn children(bvh: &Bvh, i: usize) -> [usize; 2] {
        [i + 1, bvh[i].first as usize]
    }
    fn emit(bvh: &Bvh, kids: Vec<usize>, out: &mut Vec<WideNode>) -> Result<u32, String> {
        let me = out.len();
        out.push(quantize(&[], [WideNode::EMPTY; 4]));
        let mut child = [WideNode::EMPTY; 4];
        let mut boxes = Vec::with_capacity(4);
        for (slot, &k) in kids.iter().enumerate() {
            child[slot] = if is_leaf(bvh, k) {
                WideNode::leaf(bvh[k].first, bvh[k].count).ok_or_else(|| {
                    format!(
                        "BVH leaf of {} triangles from {} is beyond the kernel's limits",
                        bvh[k].count, bvh[k].first
                    )
                })?
            } else {
                emit(bvh, open(bvh, k), out)?
            };
            boxes.push(bvh[k].bounds);
        }
        out[me] = quantize(&boxes, child);
        Ok(me as u32)
    }
    /// Up to four descendants of interior node `i` that cover it.
    fn open(bvh: &Bvh, i: usize) -> Vec<usize> {
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
        return Ok(out);
    }
    // The root itself is the only child of a one-leaf voxel.
    let top = if is_leaf(bvh, 0) {
        vec![0]
    } else {
        open(bvh, 0)
    };
    emit(bvh, top, &mut out)?;
    Ok(out)
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
    /// The kernel's layout of a (validated) voxel; fails only on a BVH leaf
    /// beyond the kernel's limits (see `widen`).
    pub fn new(id: u32, v: &Voxel) -> Result<PreparedVoxel, String> {
        let nodes = widen(&v.bvh)?;
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
        Ok(PreparedVoxel {
            id,
            nodes,
            corners,
            ids: v.triangle_ids.clone(),
            triangles: v.triangles.clone(),
            normals,
            colors: v.colors.clone(),
            bytes,
        })
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
    fn voxel(&self, id: u32) -> Option<Arc<PreparedVoxel>>;
}

/// Every voxel of a database, loaded up front (for `dray render`).
pub struct ResidentSource {
    voxels: Vec<Arc<PreparedVoxel>>,
}

impl ResidentSource {
    pub fn load(db: &Database) -> Result<ResidentSource, DbError> {
        let voxels = (0..db.manifest.voxels.len() as u32)
            .map(|id| {
                let voxel = db.load_voxel(id)?;
                let prepared = PreparedVoxel::new(id, &voxel)
                    .map_err(|message| DbError::Entry { id, message })?;
                Ok(Arc::new(prepared))
            })
            .collect::<Result<Vec<_>, DbError>>()?;
        Ok(ResidentSource { voxels })
    }

    pub fn from_voxels(voxels: Vec<PreparedVoxel>) -> ResidentSource {
        ResidentSource {
            voxels: voxels.into_iter().map(Arc::new).collect(),
        }
    }

    pub fn bytes(&self) -> usize {
        self.voxels.iter().map(|v| v.bytes).sum()
    }
}

impl VoxelSource for ResidentSource {
    fn voxel(&self, id: u32) -> Option<Arc<PreparedVoxel>> {
        self.voxels.get(id as usize).cloned()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn arb_box() -> impl Strategy<Value = Aabb> {
        // Far from the origin and tiny, or flat: where rounding bites.
        (
            prop::array::uniform3(-1e4f32..1e4),
            prop::array::uniform3(prop_oneof![Just(0.0f32), 1e-6f32..1e-2, 0.0f32..50.0]),
        )
            .prop_map(|(lo, ext)| Aabb {
                min: lo,
                max: [lo[0] + ext[0], lo[1] + ext[1], lo[2] + ext[2]],
            })
    }

    proptest! {
        #[test]
        fn quantized_child_boxes_contain_the_exact_ones(boxes in prop::collection::vec(arb_box(), 1..=4)) {
            let node = quantize(&boxes, [0; 4]);
            for (c, b) in boxes.iter().enumerate() {
                let (min, max) = node.child_box(c);
                for a in 0..3 {
                    prop_assert!(min[a] <= b.min[a], "axis {a} min {} > {}", min[a], b.min[a]);
                    prop_assert!(max[a] >= b.max[a], "axis {a} max {} < {}", max[a], b.max[a]);
                }
            }
        }
    }
}
