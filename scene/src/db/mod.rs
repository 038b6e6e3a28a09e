//! The voxel database on disk: a directory with `manifest.dray` (see
//! [`manifest`]) and `voxels.dray`, the voxel blobs back to back. A shard
//! of one ([`shard`]) also has `shard.dray` and only its voxels' blobs.
//!
//! [`Database`] opens one, reads blobs by id without loading the rest,
//! answers reference ray queries, verifies it and summarizes it.

pub mod info;
pub mod manifest;
pub mod shard;
pub mod verify;

use crate::geometry::{Aabb, Hit, Ray};
use crate::voxel::{Voxel, VoxelError};
use manifest::{BspNode, Manifest, ManifestError, VoxelEntry, MANIFEST_FILE, VOXELS_FILE};
use shard::ShardOf;
use std::fs::File;
use std::io::Read;
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum DbError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: {source}")]
    Manifest {
        path: PathBuf,
        source: ManifestError,
    },
    #[error("{path}: {message}")]
    Layout { path: PathBuf, message: String },
    #[error("voxel {id}: {source}")]
    Voxel { id: u32, source: VoxelError },
    #[error("voxel {id}: {message}")]
    Entry { id: u32, message: String },
}

/// An open voxel database, whole or a shard of one ([`shard`]).
pub struct Database {
    dir: PathBuf,
    pub manifest: Manifest,
    voxels: File,
    /// A shard's residue class and each held blob's offset in its file.
    shard: Option<(ShardOf, Vec<u64>)>,
}

impl Database {
    pub fn open(dir: &Path) -> Result<Database, DbError> {
        if !dir.is_dir() {
            return Err(DbError::Layout {
                path: dir.to_path_buf(),
                message: if dir.exists() {
                    "not a directory (a dray database is a directory)".into()
                } else {
                    "no such database".into()
                },
            });
        }
        let manifest_path = dir.join(MANIFEST_FILE);
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |source| DbError::Io { path, source }
        };
        let mut file = File::open(&manifest_path).map_err(io(&manifest_path))?;
        let mut header = [0u8; 28];
        let mut got = 0;
        while got < header.len() {
            match file.read(&mut header[got..]).map_err(io(&manifest_path))? {
                0 => break,
                n => got += n,
            }
        }
        let bad_manifest = |source| DbError::Manifest {
            path: manifest_path.clone(),
            source,
        };
        let len = Manifest::announced_len(&header[..got]).map_err(bad_manifest)?;
        let on_disk = file.metadata().map_err(io(&manifest_path))?.len();
        if on_disk != 28 + len {
            return Err(bad_manifest(ManifestError::Truncated {
                what: format!(
                    "header announces {} bytes in all, the file has {on_disk}",
                    28 + len
                ),
            }));
        }
        let mut bytes = header[..got].to_vec();
        file.read_to_end(&mut bytes).map_err(io(&manifest_path))?;
        let manifest = Manifest::decode(&bytes).map_err(bad_manifest)?;

        let shard = shard::read_shard_file(dir)?.map(|s| (s, shard::local_offsets(&manifest, s)));
        let expected = match &shard {
            Some((_, (_, len))) => *len,
            None => manifest.voxel_bytes(),
        };
        let voxels_path = dir.join(VOXELS_FILE);
        let voxels = File::open(&voxels_path).map_err(io(&voxels_path))?;
        let len = voxels.metadata().map_err(io(&voxels_path))?.len();
        if len != expected {
            let of = match &shard {
                Some((s, _)) => format!(" for shard {s}"),
                None => String::new(),
            };
            return Err(DbError::Layout {
                path: voxels_path,
                message: format!("{len} bytes, the manifest expects {expected}{of}"),
            });
        }
        Ok(Database {
            dir: dir.to_path_buf(),
            manifest,
            voxels,
            shard: shard.map(|(s, (offsets, _))| (s, offsets)),
        })
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Which shard this database is, if it is one.
    pub fn shard(&self) -> Option<ShardOf> {
        self.shard.as_ref().map(|(s, _)| *s)
    }

    /// Whether this database holds voxel `id`'s blob (a shard holds some).
    pub fn holds(&self, id: u32) -> bool {
        (id as usize) < self.manifest.voxels.len() && self.shard().is_none_or(|s| s.holds(id))
    }

    pub fn entry(&self, id: u32) -> Result<&VoxelEntry, DbError> {
        self.manifest
            .voxels
            .get(id as usize)
            .ok_or_else(|| DbError::Entry {
                id,
                message: format!("no such voxel ({} voxels)", self.manifest.voxels.len()),
            })
    }

    /// The compressed blob of voxel `id`, checked against the manifest's
    /// length and checksum.
    pub fn read_blob(&self, id: u32) -> Result<Vec<u8>, DbError> {
        let blob = self.read_unchecked(id)?;
        if crate::voxel::checksum(&blob) != self.entry(id)?.checksum {
            return Err(corrupt(id));
        }
        Ok(blob)
    }

    /// The manifest's length of bytes at voxel `id`'s offset.
    fn read_unchecked(&self, id: u32) -> Result<Vec<u8>, DbError> {
        let entry = self.entry(id)?;
        let offset = match &self.shard {
            None => entry.offset,
            Some((s, _)) if !s.holds(id) => {
                return Err(DbError::Entry {
                    id,
                    message: format!(
                        "not in this database: {} is shard {s} (voxels whose id is {} modulo {})",
                        self.dir.display(),
                        s.index,
                        s.count
                    ),
                })
            }
            Some((s, offsets)) => offsets[(id / s.count) as usize],
        };
        let mut blob = vec![0u8; entry.compressed_bytes as usize];
        read_exact_at(&self.voxels, &mut blob, offset).map_err(|source| DbError::Io {
            path: self.dir.join(VOXELS_FILE),
            source,
        })?;
        Ok(blob)
    }

    /// Reads and decodes voxel `id`, checked against the manifest. The
    /// content is hashed once: decoding checks it against the header's
    /// checksum, which must be the manifest's.
    pub fn load_voxel(&self, id: u32) -> Result<Voxel, DbError> {
        let blob = self.read_unchecked(id)?;
        if crate::voxel::stored_checksum(&blob) != Some(self.entry(id)?.checksum) {
            return Err(corrupt(id));
        }
        Voxel::decode(&blob).map_err(|source| match source {
            crate::voxel::VoxelError::ChecksumMismatch { .. } => corrupt(id),
            other => DbError::Voxel { id, source: other },
        })
    }

    /// Every voxel of the database, decoded (for tests and small models).
    pub fn load_all(&self) -> Result<Vec<Voxel>, DbError> {
        (0..self.manifest.voxels.len() as u32)
            .map(|id| self.load_voxel(id))
            .collect()
    }
}

#[cfg(unix)]
fn read_exact_at(file: &File, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
    std::os::unix::fs::FileExt::read_exact_at(file, buf, offset)
}

#[cfg(windows)]
fn read_exact_at(file: &File, mut buf: &mut [u8], mut offset: u64) -> std::io::Result<()> {
    use std::os::windows::fs::FileExt;
    while !buf.is_empty() {
        match file.seek_read(buf, offset)? {
            0 => return Err(std::io::ErrorKind::UnexpectedEof.into()),
            n => {
                buf = &mut buf[n..];
                offset += n as u64;
            }
        }
    }
    Ok(())
}

/// The reference two-level ray query: the high-level BSP front to back,
/// then each voxel's BVH, stopping once the nearest hit lies before the next
/// cell. `voxel(id)` supplies decoded voxels. The fast kernel lives in
/// `dray-trace`; this one is the yardstick its tests and ours compare with.
pub fn intersect<'v>(
    manifest: &Manifest,
    ray: &Ray,
    tmax: f32,
    voxel: &mut dyn FnMut(u32) -> &'v Voxel,
) -> Option<Hit> {
    let (t0, t1) = manifest.root_bounds.ray_interval(ray, 0.0, tmax)?;
    let mut best: Option<Hit> = None;
    // Stack of (node, cell, t_enter, t_exit), popped front to back.
    let mut stack: Vec<(u32, Aabb, f32, f32)> = vec![(0, manifest.root_bounds, t0, t1)];
    while let Some((node, cell, enter, _exit)) = stack.pop() {
        if best.is_some_and(|b| b.t < enter) {
            continue;
        }
        match manifest.nodes[node as usize] {
            BspNode::Leaf { voxel: None } => {}
            BspNode::Leaf { voxel: Some(id) } => {
                let limit = best.map_or(tmax, |b| b.t.min(tmax));
                // `limit` is inclusive for ties: ask slightly beyond, then
                // let `closer` decide with the id rule.
                if let Some(h) = voxel(id).intersect(ray, 0.0, next_up(limit)) {
                    if best.is_none_or(|b| b.is_beaten_by(h.t, h.id)) {
                        best = Some(h);
                    }
                }
            }
            BspNode::Split {
                axis,
                pos,
                left,
                right,
            } => {
                let (lc, rc) = cell.split(axis as usize, pos);
                let l = lc
                    .ray_interval(ray, 0.0, tmax)
                    .map(|(a, b)| (left, lc, a, b));
                let r = rc
                    .ray_interval(ray, 0.0, tmax)
                    .map(|(a, b)| (right, rc, a, b));
                // Push the far child first so the near one is popped first.
                let (near, far) = match (l, r) {
                    (Some(x), Some(y)) if y.2 < x.2 => (Some(y), Some(x)),
                    (x, y) => (x, y),
                };
                stack.extend(far);
                stack.extend(near);
            }
        }
    }
    best
}

fn next_up(x: f32) -> f32 {
    if x.is_finite() {
        f32::from_bits(if x >= 0.0 {
            x.to_bits() + 1
        } else {
            x.to_bits() - 1
        })
    } else {
        x
    }
}

/// A blob whose bytes do not match the manifest's checksum.
fn corrupt(id: u32) -> DbError {
    DbError::Entry {
        id,
        message: "checksum mismatch: the blob on disk is corrupt".into(),
    }
}
