//! Spill files: triangles in fixed-size records on disk, so preprocessing
//! never holds the whole model in memory.

use crate::geometry::Aabb;
use crate::mesh::Triangle;
use glam::Vec3;
use std::fs::File;
use std::io::{self, BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

/// Bytes of one record: 9 position floats, 9 normal floats, 12 color bytes,
/// the u32 id. Normals stay f32 here so the voxel builder encodes them once.
pub const RECORD_BYTES: usize = 88;

const BUFFER_BYTES: usize = 1 << 20;

pub fn encode(t: &Triangle, out: &mut [u8; RECORD_BYTES]) {
    let mut o = 0;
    for v in t.positions.iter().chain(t.normals.iter()) {
        for c in v.to_array() {
            out[o..o + 4].copy_from_slice(&c.to_le_bytes());
            o += 4;
        }
    }
    for c in &t.colors {
        out[o..o + 4].copy_from_slice(c);
        o += 4;
    }
    out[o..o + 4].copy_from_slice(&t.id.to_le_bytes());
}

pub fn decode(rec: &[u8]) -> Triangle {
    let f = |i: usize| f32::from_le_bytes([rec[i], rec[i + 1], rec[i + 2], rec[i + 3]]);
    let v = |i: usize| Vec3::new(f(i), f(i + 4), f(i + 8));
    let c = |i: usize| [rec[i], rec[i + 1], rec[i + 2], rec[i + 3]];
    Triangle {
        positions: [v(0), v(12), v(24)],
        normals: [v(36), v(48), v(60)],
        colors: [c(72), c(76), c(80)],
        id: u32::from_le_bytes([rec[84], rec[85], rec[86], rec[87]]),
    }
}

/// Appends triangles to a spill file and counts them.
pub struct SpillWriter {
    path: PathBuf,
    out: BufWriter<File>,
    pub count: u64,
    pub bounds: Aabb,
}

impl SpillWriter {
    pub fn create(path: &Path) -> io::Result<SpillWriter> {
        Ok(SpillWriter {
            path: path.to_path_buf(),
            out: BufWriter::with_capacity(BUFFER_BYTES, File::create(path)?),
            count: 0,
            bounds: Aabb::EMPTY,
        })
    }

    pub fn push(&mut self, t: &Triangle) -> io::Result<()> {
        let mut rec = [0u8; RECORD_BYTES];
        encode(t, &mut rec);
        self.out.write_all(&rec)?;
        self.count += 1;
        self.bounds = self.bounds.union(&t.bounds());
        Ok(())
    }

    /// Flushes and returns the finished file.
    pub fn finish(mut self) -> io::Result<SpillFile> {
        self.out.flush()?;
        Ok(SpillFile {
            path: self.path,
            count: self.count,
            bounds: self.bounds,
        })
    }
}

/// A finished spill file.
#[derive(Clone, Debug)]
pub struct SpillFile {
    pub path: PathBuf,
    pub count: u64,
    pub bounds: Aabb,
}

impl SpillFile {
    /// Calls `f` for every triangle in file order, reading in large blocks.
    pub fn for_each<E: From<io::Error>>(
        &self,
        mut f: impl FnMut(Triangle) -> Result<(), E>,
    ) -> Result<(), E> {
        let mut input = BufReader::with_capacity(BUFFER_BYTES, File::open(&self.path)?);
        let mut block = vec![0u8; RECORD_BYTES * 4096];
        let mut left = self.count;
        while left > 0 {
            let n = left.min(4096) as usize;
            let bytes = &mut block[..n * RECORD_BYTES];
            input.read_exact(bytes)?;
            for rec in bytes.chunks_exact(RECORD_BYTES) {
                f(decode(rec))?;
            }
            left -= n as u64;
        }
        Ok(())
    }

    pub fn remove(self) {
        // Best effort: the whole spill directory is removed at the end anyway.
        let _ = std::fs::remove_file(&self.path);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn records_round_trip() {
        let t = Triangle {
            positions: [Vec3::new(1.0, -2.0, 3.5), Vec3::ZERO, Vec3::splat(f32::MAX)],
            normals: [Vec3::X, Vec3::Y, Vec3::Z],
            colors: [[1, 2, 3, 255], [4, 5, 6, 255], [7, 8, 9, 255]],
            id: 0xDEAD_BEEF,
        };
        let mut rec = [0u8; RECORD_BYTES];
        encode(&t, &mut rec);
        assert_eq!(decode(&rec), t);

        let dir = tempfile::tempdir().unwrap();
        let mut w = SpillWriter::create(&dir.path().join("s")).unwrap();
        for i in 0..5000 {
            w.push(&Triangle { id: i, ..t }).unwrap();
        }
        let f = w.finish().unwrap();
        let mut all = Vec::new();
        f.for_each(|t| {
            all.push(t);
            Ok::<(), io::Error>(())
        })
        .unwrap();
        assert_eq!(all.len(), 5000);
        assert!(all.iter().enumerate().all(|(i, x)| x.id == i as u32));
    }
}
