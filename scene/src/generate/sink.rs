//! Streams objects into a binary little-endian PLY without holding the model.
//!
//! Vertices go straight into the temporary output file, after a region
//! reserved for the header; faces go to a second temporary file. At the end
//! the faces are appended, the header (whose vertex count is only known now)
//! is written into the reserved region, padded by a comment line, and the
//! temporary file is renamed onto the output path. Both temporaries live in
//! the output's directory and are deleted when generation fails.

use super::mesh::Part;
use super::GenerateError;
use crate::geometry::Aabb;
use glam::Vec3;
use std::fs::File;
use std::io::{Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use tempfile::NamedTempFile;

/// Bytes reserved for the header at the start of the file.
const HEADER_RESERVE: u64 = 1024;
/// Bytes buffered before each write to disk.
const CHUNK: usize = 1 << 20;
/// `progress` is called every this many triangles.
const PROGRESS_STEP: u64 = 1 << 16;

pub(crate) const VERTEX_BYTES: usize = 27;
pub(crate) const FACE_BYTES: usize = 13;

pub(crate) struct Sink<'a> {
    out_path: PathBuf,
    out: NamedTempFile,
    faces: NamedTempFile,
    vbuf: Vec<u8>,
    fbuf: Vec<u8>,
    pub vertices: u64,
    pub triangles: u64,
    /// Triangles may be committed up to this count (the current unit's end).
    pub limit: u64,
    lo: Vec3,
    hi: Vec3,
    next_progress: u64,
    progress: &'a mut dyn FnMut(u64),
    /// The largest scratch buffer seen, in bytes (memory test).
    pub peak_scratch: usize,
}

fn io_err<'p>(
    path: &'p Path,
    action: &'static str,
) -> impl FnOnce(std::io::Error) -> GenerateError + 'p {
    move |source| GenerateError::Io {
        path: path.to_path_buf(),
        action,
        source,
    }
}

impl<'a> Sink<'a> {
    pub fn create(out: &Path, progress: &'a mut dyn FnMut(u64)) -> Result<Sink<'a>, GenerateError> {
        let dir = match out.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let tmp = |suffix: &str| {
            let mut builder = tempfile::Builder::new();
            builder.prefix(".dray-plant-").suffix(suffix);
            // The finished file is an ordinary output: readable by others
            // (as the umask allows), not tempfile's private 0600.
            #[cfg(unix)]
            builder.permissions(std::os::unix::fs::PermissionsExt::from_mode(0o644));
            builder
                .tempfile_in(&dir)
                .map_err(io_err(out, "create a temporary file next to"))
        };
        let mut out_tmp = tmp(".ply.tmp")?;
        let faces = tmp(".faces.tmp")?;
        out_tmp
            .as_file_mut()
            .seek(SeekFrom::Start(HEADER_RESERVE))
            .map_err(io_err(out, "write"))?;
        Ok(Sink {
            out_path: out.to_path_buf(),
            out: out_tmp,
            faces,
            vbuf: Vec::with_capacity(CHUNK + 4096),
            fbuf: Vec::with_capacity(CHUNK + 4096),
            vertices: 0,
            triangles: 0,
            limit: 0,
            lo: Vec3::splat(f32::INFINITY),
            hi: Vec3::splat(f32::NEG_INFINITY),
            next_progress: PROGRESS_STEP,
            progress,
            peak_scratch: 0,
        })
    }

    pub fn remaining(&self) -> u64 {
        self.limit.saturating_sub(self.triangles)
    }

    /// Writes the whole part if its triangles fit under `limit`; returns
    /// whether it did (nothing is written otherwise).
    pub fn commit(&mut self, part: &Part) -> Result<bool, GenerateError> {
        self.peak_scratch = self.peak_scratch.max(part.capacity_bytes());
        let n = part.tris.len() as u64;
        if n == 0 || n > self.remaining() {
            return Ok(false);
        }
        let base = self.vertices;
        for v in &part.verts {
            self.lo = self.lo.min(v.p);
            self.hi = self.hi.max(v.p);
            for x in [v.p.x, v.p.y, v.p.z, v.n.x, v.n.y, v.n.z] {
                self.vbuf.extend_from_slice(&x.to_le_bytes());
            }
            self.vbuf.extend_from_slice(&v.c);
            if self.vbuf.len() >= CHUNK {
                self.flush_vertices()?;
            }
        }
        for t in &part.tris {
            self.fbuf.push(3);
            for &i in t {
                self.fbuf
                    .extend_from_slice(&((base + i as u64) as u32).to_le_bytes());
            }
            if self.fbuf.len() >= CHUNK {
                self.flush_faces()?;
            }
        }
        self.vertices += part.verts.len() as u64;
        self.triangles += n;
        if self.triangles >= self.next_progress {
            (self.progress)(self.triangles);
            self.next_progress = (self.triangles / PROGRESS_STEP + 1) * PROGRESS_STEP;
        }
        Ok(true)
    }

    fn flush_vertices(&mut self) -> Result<(), GenerateError> {
        self.out
            .as_file_mut()
            .write_all(&self.vbuf)
            .map_err(io_err(&self.out_path, "write"))?;
        self.vbuf.clear();
        Ok(())
    }

    fn flush_faces(&mut self) -> Result<(), GenerateError> {
        let path = self.faces.path().to_path_buf();
        self.faces
            .as_file_mut()
            .write_all(&self.fbuf)
            .map_err(io_err(&path, "write"))?;
        self.fbuf.clear();
        Ok(())
    }

    pub fn bounds(&self) -> Aabb {
        Aabb::new(self.lo, self.hi)
    }

    /// Appends the faces, writes the header and renames the file onto the
    /// output path.
    pub fn finish(mut self, comment: &str) -> Result<(u64, u64, Aabb), GenerateError> {
        self.flush_vertices()?;
        self.flush_faces()?;
        let out_path = self.out_path.clone();
        let faces_path = self.faces.path().to_path_buf();
        let faces: &mut File = self.faces.as_file_mut();
        faces
            .seek(SeekFrom::Start(0))
            .map_err(io_err(&faces_path, "read"))?;
        let out: &mut File = self.out.as_file_mut();
        std::io::copy(faces, out).map_err(io_err(&out_path, "write"))?;
        let header = header(self.vertices, self.triangles, comment);
        out.seek(SeekFrom::Start(0))
            .map_err(io_err(&out_path, "write"))?;
        out.write_all(&header).map_err(io_err(&out_path, "write"))?;
        out.flush().map_err(io_err(&out_path, "write"))?;
        (self.progress)(self.triangles);
        let bounds = self.bounds();
        let (v, t) = (self.vertices, self.triangles);
        self.out.persist(&out_path).map_err(|e| GenerateError::Io {
            path: out_path.clone(),
            action: "rename the finished file to",
            source: e.error,
        })?;
        Ok((v, t, bounds))
    }
}

/// The PLY header, padded to exactly `HEADER_RESERVE` bytes.
fn header(vertices: u64, faces: u64, comment: &str) -> Vec<u8> {
    let body = format!(
        "element vertex {vertices}\n\
         property float x\nproperty float y\nproperty float z\n\
         property float nx\nproperty float ny\nproperty float nz\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\n\
         element face {faces}\n\
         property list uchar uint vertex_indices\n\
         end_header\n"
    );
    let head = format!("ply\nformat binary_little_endian 1.0\ncomment {comment}\n");
    let pad_line = "comment padding\n".len();
    let pad = HEADER_RESERVE as usize - head.len() - body.len() - pad_line;
    let mut s = head;
    s.push_str("comment padding");
    s.push_str(&".".repeat(pad));
    s.push('\n');
    s.push_str(&body);
    debug_assert_eq!(s.len() as u64, HEADER_RESERVE);
    s.into_bytes()
}
