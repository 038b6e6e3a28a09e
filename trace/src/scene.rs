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
    pub voxel_count: u32,
}

impl TopLevel {
    pub fn from_manifest(m: &Manifest) -> TopLevel {
        TopLevel {
            root: m.root_bounds,
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

/// A node of a voxel's BVH: bounds, then either a leaf's triangle range
/// (`count > 0`) or an interior node whose children are `self + 1` and
/// `first` (`count == 0`). 32 bytes, two to a cache line.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(32))]
pub struct Node {
    pub min: [f32; 3],
    pub first: u32,
    pub max: [f32; 3],
    /// Leaf: its triangle count. Interior: `INTERIOR | order`, where
    /// `order` says which child to visit first without loading either:
    /// bits 0-1 the axis along which the children's centres differ most,
    /// bit 2 set when the first child (`self + 1`) lies above the other.
    pub count: u32,
}

impl Node {
    pub const INTERIOR: u32 = 1 << 31;

    #[inline(always)]
    pub fn is_leaf(&self) -> bool {
        self.count & Node::INTERIOR == 0
    }

    /// Whether a ray with direction component `d` on the node's ordering
    /// axis meets the first child (`self + 1`) first.
    #[inline(always)]
    pub fn first_child_near(&self, dir: [f32; 3]) -> bool {
        let axis = (self.count & 3) as usize;
        let above = self.count & 4 != 0;
        (dir[axis] >= 0.0) != above
    }
}

/// A voxel in the kernel's layout: BVH nodes, each triangle's corners
/// gathered in leaf order (one cache line and a half per triangle, no
/// index indirection in the inner loop), and what shading needs.
#[derive(Debug)]
pub struct PreparedVoxel {
    pub id: u32,
    pub nodes: Vec<Node>,
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
        let centre2 = |i: usize| {
            let b = &v.bvh[i].bounds;
            [0, 1, 2].map(|a| b.min[a] + b.max[a])
        };
        let nodes: Vec<Node> = v
            .bvh
            .iter()
            .enumerate()
            .map(|(i, n)| {
                let count = if n.count > 0 {
                    n.count
                } else {
                    let (l, r) = (centre2(i + 1), centre2(n.first as usize));
                    let diff = [0, 1, 2].map(|a| l[a] - r[a]);
                    let axis = (0..3)
                        .max_by(|&a, &b| diff[a].abs().total_cmp(&diff[b].abs()))
                        .unwrap_or(0);
                    Node::INTERIOR | axis as u32 | (((diff[axis] > 0.0) as u32) << 2)
                };
                Node {
                    min: n.bounds.min,
                    first: n.first,
                    max: n.bounds.max,
                    count,
                }
            })
            .collect();
        let corners: Vec<[[f32; 3]; 3]> = v
            .triangles
            .iter()
            .map(|t| t.map(|i| v.positions[i as usize]))
            .collect();
        let normals: Vec<Vec3> = v.normals.iter().map(|&n| decode_normal(n)).collect();
        let bytes = nodes.len() * std::mem::size_of::<Node>()
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
    fn voxel(&self, id: u32) -> Option<Arc<PreparedVoxel>>;
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
