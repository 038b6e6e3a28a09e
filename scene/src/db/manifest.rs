//! The manifest: what a voxel database holds and where.
//!
//! File layout of `manifest.dray` (little-endian):
//!
//! | bytes | field |
//! |---|---|
//! | 0..8 | magic `DRAYMANI` |
//! | 8..12 | format version (u32) |
//! | 12..20 | payload length in bytes (u64) |
//! | 20..28 | xxh3-64 of the payload |
//! | 28.. | payload: [`Manifest`] encoded with postcard |

use crate::geometry::Aabb;
use serde::{Deserialize, Serialize};

pub const MANIFEST_FILE: &str = "manifest.dray";
pub const VOXELS_FILE: &str = "voxels.dray";
pub const MAGIC: &[u8; 8] = b"DRAYMANI";
/// Version of the database format (manifest and voxel blobs together).
pub const FORMAT_VERSION: u32 = 2;
const HEADER_BYTES: usize = 28;
/// A manifest larger than this is refused before reading it (a 100 M
/// triangle model has about 100 k voxels, a few MB of manifest).
pub const MAX_MANIFEST_BYTES: u64 = 1 << 30;

/// The parameters a database was built with.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BuildParams {
    pub inputs: Vec<InputModel>,
    pub max_triangles: u32,
    pub max_depth: u32,
    pub copies: [u32; 3],
    pub spacing: f32,
    pub zstd_level: i32,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct InputModel {
    pub path: String,
    pub triangles: u64,
    pub vertices: u64,
}

/// A node of the high-level BSP. Node 0 is the root; its cell is
/// [`Manifest::root_bounds`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum BspNode {
    /// `left` covers coordinates below `pos` on `axis`, `right` those above.
    Split {
        axis: u8,
        pos: f32,
        left: u32,
        right: u32,
    },
    /// A cell with its voxel, or `None` for empty space.
    Leaf { voxel: Option<u32> },
}

/// One voxel's entry: where its blob is and what it holds.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct VoxelEntry {
    /// The BSP cell the voxel covers.
    pub bounds: Aabb,
    /// The bounds of the parts of its triangles inside the cell: a ray
    /// that misses this box misses the voxel, so traversal can skip the
    /// empty space of a cell without fetching anything.
    pub content: Aabb,
    pub triangles: u32,
    pub vertices: u32,
    /// Decoded size in memory.
    pub raw_bytes: u64,
    /// Size of the blob in `voxels.dray`.
    pub compressed_bytes: u64,
    pub offset: u64,
    /// xxh3-64 of the whole blob.
    pub checksum: u64,
    /// Depth of its leaf in the BSP (root = 0).
    pub depth: u32,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub format_version: u32,
    /// Bounds of all triangles (copies included).
    pub model_bounds: Aabb,
    /// The root cell of the BSP.
    pub root_bounds: Aabb,
    /// Triangles in the input (copies included).
    pub input_triangles: u64,
    /// Triangles stored in voxels (replicas included).
    pub stored_triangles: u64,
    pub build: BuildParams,
    pub nodes: Vec<BspNode>,
    pub voxels: Vec<VoxelEntry>,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ManifestError {
    #[error("not a dray manifest (bad magic)")]
    BadMagic,
    #[error("format version {found} is not supported (this dray reads version {FORMAT_VERSION})")]
    Version { found: u32 },
    #[error("truncated: {what}")]
    Truncated { what: String },
    #[error("manifest payload of {0} bytes exceeds the limit")]
    TooLarge(u64),
    #[error("checksum mismatch: the manifest is corrupt")]
    Checksum,
    #[error("cannot decode the manifest: {0}")]
    Decode(String),
    #[error("inconsistent manifest: {0}")]
    Inconsistent(String),
}

impl Manifest {
    /// Stored triangles per input triangle: how often the BSP copied a
    /// triangle into more than one voxel.
    pub fn replication_factor(&self) -> f64 {
        self.stored_triangles as f64 / self.input_triangles.max(1) as f64
    }

    pub fn encode(&self) -> Vec<u8> {
        let payload = postcard::to_allocvec(self).expect("in-memory manifest encodes");
        let mut out = Vec::with_capacity(HEADER_BYTES + payload.len());
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        out.extend_from_slice(&(payload.len() as u64).to_le_bytes());
        out.extend_from_slice(&xxhash_rust::xxh3::xxh3_64(&payload).to_le_bytes());
        out.extend_from_slice(&payload);
        out
    }

    /// Reads the header only: the payload length it announces, so a reader
    /// can refuse a huge or truncated file before reading it all.
    pub fn announced_len(header: &[u8]) -> Result<u64, ManifestError> {
        if header.len() < HEADER_BYTES {
            return Err(ManifestError::Truncated {
                what: format!("{} bytes, the header alone is {HEADER_BYTES}", header.len()),
            });
        }
        if &header[0..8] != MAGIC {
            return Err(ManifestError::BadMagic);
        }
        let version = u32::from_le_bytes(header[8..12].try_into().expect("4 bytes"));
        if version != FORMAT_VERSION {
            return Err(ManifestError::Version { found: version });
        }
        let len = u64::from_le_bytes(header[12..20].try_into().expect("8 bytes"));
        if len > MAX_MANIFEST_BYTES {
            return Err(ManifestError::TooLarge(len));
        }
        Ok(len)
    }

    pub fn decode(bytes: &[u8]) -> Result<Manifest, ManifestError> {
        let len = Self::announced_len(bytes)?;
        let payload = &bytes[HEADER_BYTES..];
        if (payload.len() as u64) < len {
            return Err(ManifestError::Truncated {
                what: format!(
                    "header announces {len} payload bytes, the file has {}",
                    payload.len()
                ),
            });
        }
        if payload.len() as u64 > len {
            return Err(ManifestError::Inconsistent(format!(
                "{} bytes after the {len}-byte payload",
                payload.len() as u64 - len
            )));
        }
        let sum = u64::from_le_bytes(bytes[20..28].try_into().expect("8 bytes"));
        if xxhash_rust::xxh3::xxh3_64(payload) != sum {
            return Err(ManifestError::Checksum);
        }
        let m: Manifest =
            postcard::from_bytes(payload).map_err(|e| ManifestError::Decode(e.to_string()))?;
        m.check_structure()?;
        Ok(m)
    }

    /// The BSP is a tree over `nodes` rooted at 0 in which every voxel is
    /// referenced by exactly one leaf; voxel blobs do not overlap.
    pub fn check_structure(&self) -> Result<(), ManifestError> {
        let bad = |m: String| Err(ManifestError::Inconsistent(m));
        if self.nodes.is_empty() {
            return bad("the BSP has no nodes".into());
        }
        let mut seen_node = vec![false; self.nodes.len()];
        let mut seen_voxel = vec![false; self.voxels.len()];
        let mut stack = vec![0u32];
        while let Some(i) = stack.pop() {
            let Some(node) = self.nodes.get(i as usize) else {
                return bad(format!("BSP child {i} out of range"));
            };
            if std::mem::replace(&mut seen_node[i as usize], true) {
                return bad(format!("BSP node {i} is reachable twice"));
            }
            match *node {
                BspNode::Split {
                    axis,
                    left,
                    right,
                    pos,
                } => {
                    if axis > 2 || !pos.is_finite() {
                        return bad(format!("BSP node {i} has a bad plane"));
                    }
                    stack.push(left);
                    stack.push(right);
                }
                BspNode::Leaf { voxel: Some(v) } => match seen_voxel.get_mut(v as usize) {
                    None => return bad(format!("BSP leaf {i} names voxel {v}, out of range")),
                    Some(s) if *s => return bad(format!("voxel {v} is in two leaves")),
                    Some(s) => *s = true,
                },
                BspNode::Leaf { voxel: None } => {}
            }
        }
        if let Some(i) = seen_node.iter().position(|s| !s) {
            return bad(format!("BSP node {i} is unreachable"));
        }
        if let Some(v) = seen_voxel.iter().position(|s| !s) {
            return bad(format!("voxel {v} is in no leaf"));
        }
        let mut spans: Vec<(u64, u64)> = self
            .voxels
            .iter()
            .map(|v| (v.offset, v.offset.saturating_add(v.compressed_bytes)))
            .collect();
        spans.sort_unstable();
        if spans.windows(2).any(|w| w[0].1 > w[1].0) {
            return bad("voxel blobs overlap".into());
        }
        Ok(())
    }

    /// Bytes the voxels file must have.
    pub fn voxel_bytes(&self) -> u64 {
        self.voxels
            .iter()
            .map(|v| v.offset.saturating_add(v.compressed_bytes))
            .max()
            .unwrap_or(0)
    }

    /// Depth of the deepest leaf.
    pub fn depth(&self) -> u32 {
        let mut deepest = 0;
        let mut stack = vec![(0u32, 0u32)];
        while let Some((i, d)) = stack.pop() {
            deepest = deepest.max(d);
            if let Some(BspNode::Split { left, right, .. }) = self.nodes.get(i as usize) {
                stack.push((*left, d + 1));
                stack.push((*right, d + 1));
            }
        }
        deepest
    }
}
