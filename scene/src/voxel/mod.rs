//! One voxel: a leaf of the high-level BSP, self-contained, with its
//! de-duplicated vertices, its triangles (with their ORIGINAL ids), its
//! low-level BVH, and its compressed, checksummed blob format.
//!
//! - [`Voxel::build`] turns triangles into a voxel (binned SAH BVH, leaf
//!   order, vertices by first use).
//! - [`Voxel::encode`] / [`Voxel::decode`]: the blob (layout in [`codec`]).
//! - [`Voxel::validate`]: the structural check every decoded voxel passes.
//! - [`Voxel::intersect`]: nearest hit through the BVH, identical to brute
//!   force over all triangles.

pub mod bvh;
pub mod codec;
mod normal;

pub use bvh::{BvhNode, BvhStats, MAX_BVH_DEPTH, MAX_LEAF_TRIANGLES};
pub use codec::{
    checksum, stored_checksum, DEFAULT_ZSTD_LEVEL, FORMAT_VERSION, HEADER_LEN, MAGIC,
    MAX_VOXEL_RAW_BYTES,
};
pub use normal::{decode_normal, encode_normal};

use crate::geometry::{closer, intersect_triangle, Aabb, Hit, Ray};
use crate::mesh::Triangle;
use glam::Vec3;
use std::collections::HashMap;

/// One voxel, decoded. Arrays are in locality order: triangles in BVH leaf
/// order, vertices in order of first use by the triangles.
#[derive(Clone, Debug, PartialEq)]
pub struct Voxel {
    /// The BSP cell this voxel covers (triangles may stick out of it).
    pub bounds: Aabb,
    /// Unique vertex positions, exact copies of the input.
    pub positions: Vec<[f32; 3]>,
    /// Unit vertex normals, octahedral 2×16 bit ([`encode_normal`]).
    pub normals: Vec<u32>,
    pub colors: Vec<[u8; 4]>,
    /// Local vertex indices per triangle, in BVH leaf order.
    pub triangles: Vec<[u32; 3]>,
    /// ORIGINAL id of each triangle.
    pub triangle_ids: Vec<u32>,
    /// Low-level BVH over `triangles` (layout in [`BvhNode`]); empty iff
    /// there are no triangles.
    pub bvh: Vec<BvhNode>,
}

/// What is wrong with a blob or a voxel.
#[derive(Debug, thiserror::Error)]
pub enum VoxelError {
    #[error("truncated: {0}")]
    Truncated(String),
    #[error("bad magic {found:02x?}: not a dray voxel blob")]
    BadMagic { found: [u8; 8] },
    #[error("unsupported voxel format version {found} (this build reads {supported})")]
    UnsupportedVersion { found: u32, supported: u32 },
    #[error("checksum mismatch: header says {stored:#018x}, content hashes to {computed:#018x}")]
    ChecksumMismatch { stored: u64, computed: u64 },
    #[error("voxel too large: {what} needs {bytes} bytes, limit is {limit}")]
    TooLarge {
        what: String,
        bytes: u64,
        limit: u64,
    },
    #[error("size mismatch: {0}")]
    SizeMismatch(String),
    #[error("corrupt compressed payload: {0}")]
    Decompress(String),
    #[error("triangle {triangle} vertex index {index} out of range ({vertices} vertices)")]
    IndexOutOfRange {
        triangle: usize,
        index: u32,
        vertices: usize,
    },
    #[error("non-finite {0}")]
    NonFinite(String),
    #[error("malformed BVH: {0}")]
    BadTree(String),
    #[error("inconsistent arrays: {0}")]
    Inconsistent(String),
}

impl Voxel {
    /// Builds the voxel of cell `bounds` from triangles: binned SAH BVH
    /// ([`bvh::SAH_BINS`] bins over the triangles' bounds clipped to the
    /// cell, leaves of at most [`MAX_LEAF_TRIANGLES`]), triangles in leaf order,
    /// vertices de-duplicated (same position, encoded normal and color bits)
    /// and numbered by first use.
    ///
    /// Triangles with a non-finite coordinate can never be hit and would
    /// poison the BVH: they are left out (with a warning).
    pub fn build(bounds: Aabb, triangles: &[Triangle]) -> Voxel {
        let finite: Vec<&Triangle> = triangles
            .iter()
            .filter(|t| t.positions.iter().all(|p| p.is_finite()))
            .collect();
        if finite.len() != triangles.len() {
            tracing::warn!(
                dropped = triangles.len() - finite.len(),
                "voxel build: dropped triangles with non-finite coordinates"
            );
        }
        // Each triangle's bounds within the cell: that is all of it the
        // voxel's BVH needs to find (hits outside the cell are found in the
        // voxels there), and the kernel clips the boxes so.
        let prim_bounds: Vec<Aabb> = finite
            .iter()
            .map(|t| {
                let clipped = t.bounds().intersection(&bounds);
                if clipped.is_empty() {
                    t.bounds()
                } else {
                    clipped
                }
            })
            .collect();
        let (mut nodes, order) = bvh::build(&prim_bounds);

        let mut v = Voxel {
            bounds,
            positions: Vec::new(),
            normals: Vec::new(),
            colors: Vec::new(),
            triangles: Vec::with_capacity(order.len()),
            triangle_ids: Vec::with_capacity(order.len()),
            bvh: Vec::new(),
        };
        let mut unique: HashMap<([u32; 3], u32, [u8; 4]), u32> = HashMap::new();
        for &o in &order {
            let t = finite[o as usize];
            let mut idx = [0u32; 3];
            for (k, slot) in idx.iter_mut().enumerate() {
                let p = t.positions[k].to_array();
                let n = encode_normal(t.normals[k]);
                let c = t.colors[k];
                let key = (p.map(f32::to_bits), n, c);
                let next = v.positions.len() as u32;
                *slot = *unique.entry(key).or_insert_with(|| {
                    v.positions.push(p);
                    v.normals.push(n);
                    v.colors.push(c);
                    next
                });
            }
            v.triangles.push(idx);
            v.triangle_ids.push(t.id);
        }
        bvh::refit(&mut nodes, &v.triangles, &v.positions);
        v.bvh = nodes;
        v
    }

    /// Bytes of the decoded in-memory arrays (what a cache holds).
    pub fn raw_size(&self) -> usize {
        raw_size_of(
            self.positions.len() as u64,
            self.triangles.len() as u64,
            self.bvh.len() as u64,
        ) as usize
    }

    /// The self-contained blob (layout in [`codec`]).
    pub fn encode(&self, zstd_level: i32) -> Vec<u8> {
        codec::encode(self, zstd_level)
    }

    /// Parses and checks a blob from untrusted bytes: magic, version,
    /// checksum, sizes (at most [`MAX_VOXEL_RAW_BYTES`]), then what
    /// [`validate`] checks (the node bounds, not stored, are recomputed
    /// and hold by construction).
    ///
    /// [`validate`]: Voxel::validate
    pub fn decode(blob: &[u8]) -> Result<Voxel, VoxelError> {
        codec::decode(blob)
    }

    /// Checks that the voxel is well formed: consistent array lengths,
    /// indices in range, finite coordinates, and a BVH in depth-first
    /// pre-order whose leaves cover every triangle exactly once, in order,
    /// with bounds that contain their children and triangles.
    pub fn validate(&self) -> Result<(), VoxelError> {
        self.validate_structure()?;
        self.validate_bounds()
    }

    /// Everything but the node bounds: what [`bvh::refit`] relies on.
    pub(crate) fn validate_structure(&self) -> Result<(), VoxelError> {
        let nv = self.positions.len();
        let nt = self.triangles.len();
        if self.normals.len() != nv || self.colors.len() != nv {
            return Err(VoxelError::Inconsistent(format!(
                "{nv} positions but {} normals and {} colors",
                self.normals.len(),
                self.colors.len()
            )));
        }
        if self.triangle_ids.len() != nt {
            return Err(VoxelError::Inconsistent(format!(
                "{nt} triangles but {} triangle ids",
                self.triangle_ids.len()
            )));
        }
        if nv > u32::MAX as usize || nt > u32::MAX as usize || self.bvh.len() > u32::MAX as usize {
            return Err(VoxelError::Inconsistent("more than 2^32 elements".into()));
        }
        if self
            .bounds
            .min
            .iter()
            .chain(&self.bounds.max)
            .any(|x| x.is_nan())
        {
            return Err(VoxelError::NonFinite(format!(
                "voxel bounds {:?}",
                self.bounds
            )));
        }
        if let Some(i) = self
            .positions
            .iter()
            .position(|p| !p.iter().all(|x| x.is_finite()))
        {
            return Err(VoxelError::NonFinite(format!(
                "vertex {i} position {:?}",
                self.positions[i]
            )));
        }
        for (t, tri) in self.triangles.iter().enumerate() {
            for &index in tri {
                if index as usize >= nv {
                    return Err(VoxelError::IndexOutOfRange {
                        triangle: t,
                        index,
                        vertices: nv,
                    });
                }
            }
        }
        self.validate_tree()
    }

    fn validate_tree(&self) -> Result<(), VoxelError> {
        let nodes = &self.bvh;
        let nt = self.triangles.len();
        if nt == 0 {
            return if nodes.is_empty() {
                Ok(())
            } else {
                Err(VoxelError::BadTree(format!(
                    "{} nodes but no triangles",
                    nodes.len()
                )))
            };
        }
        if nodes.is_empty() {
            return Err(VoxelError::BadTree(format!("no nodes for {nt} triangles")));
        }
        // Walk in pre-order: the i-th node visited must be node i, so every
        // node is reached exactly once and children follow their parents
        // (no cycles); leaves must cover the triangles contiguously.
        let mut stack: Vec<(usize, usize)> = vec![(0, 0)];
        let mut expected = 0usize;
        let mut next_triangle = 0usize;
        while let Some((i, depth)) = stack.pop() {
            if i != expected {
                return Err(VoxelError::BadTree(format!(
                    "node {expected} expected next in depth-first order, found a link to node {i}"
                )));
            }
            if depth > MAX_BVH_DEPTH {
                return Err(VoxelError::BadTree(format!(
                    "node {i} at depth {depth}, deeper than {MAX_BVH_DEPTH}"
                )));
            }
            expected += 1;
            let n = &nodes[i];
            if n.is_leaf() {
                // The kernel's layout names a leaf's count in a few bits.
                if n.count as usize > MAX_LEAF_TRIANGLES {
                    return Err(VoxelError::BadTree(format!(
                        "leaf {i} holds {} triangles, more than {MAX_LEAF_TRIANGLES}",
                        n.count
                    )));
                }
                if n.first as usize != next_triangle {
                    return Err(VoxelError::BadTree(format!(
                        "leaf {i} starts at triangle {}, expected {next_triangle}",
                        n.first
                    )));
                }
                next_triangle += n.count as usize;
                if next_triangle > nt {
                    return Err(VoxelError::BadTree(format!(
                        "leaf {i} covers triangles {}..{next_triangle}, only {nt} exist",
                        n.first
                    )));
                }
            } else {
                let right = n.first as usize;
                if i + 1 >= nodes.len() || right <= i + 1 || right >= nodes.len() {
                    return Err(VoxelError::BadTree(format!(
                        "interior node {i} has children {} and {right}, {} nodes",
                        i + 1,
                        nodes.len()
                    )));
                }
                stack.push((right, depth + 1));
                stack.push((i + 1, depth + 1));
            }
        }
        if expected != nodes.len() {
            return Err(VoxelError::BadTree(format!(
                "{} nodes but only {expected} reachable from the root",
                nodes.len()
            )));
        }
        if next_triangle != nt {
            return Err(VoxelError::BadTree(format!(
                "leaves cover {next_triangle} of {nt} triangles"
            )));
        }
        Ok(())
    }

    fn validate_bounds(&self) -> Result<(), VoxelError> {
        for (i, n) in self.bvh.iter().enumerate() {
            if n.bounds.is_empty()
                || !n
                    .bounds
                    .min
                    .iter()
                    .chain(&n.bounds.max)
                    .all(|x| x.is_finite())
            {
                return Err(VoxelError::BadTree(format!(
                    "node {i} has empty or non-finite bounds {:?}",
                    n.bounds
                )));
            }
            if n.is_leaf() {
                for t in n.first as usize..(n.first + n.count) as usize {
                    let tb = self.triangle_bounds(t);
                    if !n.bounds.contains_box(&tb) {
                        return Err(VoxelError::BadTree(format!(
                            "leaf {i} bounds {:?} do not contain triangle {t} {:?}",
                            n.bounds, tb
                        )));
                    }
                }
            } else {
                for c in [i + 1, n.first as usize] {
                    if !n.bounds.contains_box(&self.bvh[c].bounds) {
                        return Err(VoxelError::BadTree(format!(
                            "node {i} bounds {:?} do not contain child {c} {:?}",
                            n.bounds, self.bvh[c].bounds
                        )));
                    }
                }
            }
        }
        Ok(())
    }

    fn corners(&self, t: usize) -> [Vec3; 3] {
        self.triangles[t].map(|v| Vec3::from_array(self.positions[v as usize]))
    }

    fn triangle_bounds(&self, t: usize) -> Aabb {
        Aabb::from_points(&self.corners(t))
    }

    /// Nearest hit with `t` in `(tmin, tmax)` through the BVH; ties in `t`
    /// go to the smaller ORIGINAL id, exactly as brute force over all
    /// triangles with [`intersect_triangle`] and [`closer`].
    ///
    /// The voxel must be valid (as built or decoded).
    pub fn intersect(&self, ray: &Ray, tmin: f32, tmax: f32) -> Option<Hit> {
        if self.bvh.is_empty() {
            return None;
        }
        // Box tests are culling only: widen their interval a little so that
        // rounding in the box test can never drop a triangle the exact test
        // hits (hits on box faces are common in CAD data).
        let widen = |t: f32| t + t.abs() * (1.0 / 4096.0);
        let box_tmin = tmin - tmin.abs() * (1.0 / 4096.0);
        let mut best: Option<Hit> = None;
        let mut stack = [(0u32, 0f32); MAX_BVH_DEPTH + 2];
        let mut sp = 0usize;
        let root = &self.bvh[0];
        let (t0, _) = root.bounds.ray_interval(ray, box_tmin, widen(tmax))?;
        stack[sp] = (0, t0);
        sp += 1;
        while sp > 0 {
            sp -= 1;
            let (mut i, entry) = stack[sp];
            let mut limit = widen(best.map_or(tmax, |h| h.t));
            if entry > limit {
                continue;
            }
            loop {
                let n = &self.bvh[i as usize];
                if n.is_leaf() {
                    for t in n.first..n.first + n.count {
                        let p = self.corners(t as usize);
                        if let Some(th) = intersect_triangle(ray, &p, tmin, tmax) {
                            best = closer(best, th, self.triangle_ids[t as usize]);
                        }
                    }
                    break;
                }
                limit = widen(best.map_or(tmax, |h| h.t));
                let (l, r) = (i + 1, n.first);
                let hl = self.bvh[l as usize]
                    .bounds
                    .ray_interval(ray, box_tmin, limit);
                let hr = self.bvh[r as usize]
                    .bounds
                    .ray_interval(ray, box_tmin, limit);
                match (hl, hr) {
                    (Some((tl, _)), Some((tr, _))) => {
                        let (near, far, tfar) = if tl <= tr { (l, r, tr) } else { (r, l, tl) };
                        if sp < stack.len() {
                            stack[sp] = (far, tfar);
                            sp += 1;
                        }
                        i = near;
                    }
                    (Some(_), None) => i = l,
                    (None, Some(_)) => i = r,
                    (None, None) => break,
                }
            }
        }
        best
    }

    /// Reassembles triangle `i` (normals decoded from their 2×16-bit form).
    ///
    /// Panics when `i` is out of range.
    pub fn triangle(&self, i: usize) -> Triangle {
        let [a, b, c] = self.triangles[i].map(|v| v as usize);
        Triangle {
            positions: [a, b, c].map(|v| Vec3::from_array(self.positions[v])),
            normals: [a, b, c].map(|v| decode_normal(self.normals[v])),
            colors: [a, b, c].map(|v| self.colors[v]),
            id: self.triangle_ids[i],
        }
    }

    /// Shape statistics of the BVH (leaf sizes, depth, SAH cost).
    pub fn bvh_stats(&self) -> BvhStats {
        bvh::stats(&self.bvh)
    }
}

/// Bytes of the in-memory arrays for the given counts.
pub(crate) fn raw_size_of(vertices: u64, triangles: u64, nodes: u64) -> u64 {
    vertices * (12 + 4 + 4) + triangles * (12 + 4) + nodes * std::mem::size_of::<BvhNode>() as u64
}
