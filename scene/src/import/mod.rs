//! Streaming PLY and OBJ importers.
//!
//! [`import_model`] streams every triangle of a model file to a sink, in file
//! order, with the original ids of docs/design.md ("Conventions"): polygons are
//! fan-triangulated and ids count the resulting triangles. Vertices live in
//! memory (bounded by [`ImportOptions::max_vertex_bytes`]); faces are streamed,
//! twice when vertex normals must be computed, so memory is proportional to
//! the vertex count only.

mod error;
mod input;
mod obj;
mod ply;

pub use error::ImportError;

use crate::mesh::{Triangle, DEFAULT_COLOR};
use glam::Vec3;
use input::Input;
use std::path::Path;

/// Limits for an import.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ImportOptions {
    /// Memory budget, in bytes, for the in-memory vertex table (positions,
    /// normals, colors). A model whose vertices need more is refused with a
    /// clear error before anything big is allocated.
    pub max_vertex_bytes: u64,
}

impl Default for ImportOptions {
    fn default() -> Self {
        ImportOptions {
            max_vertex_bytes: 1 << 30,
        }
    }
}

/// What an import produced.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImportSummary {
    /// Vertices in the model.
    pub vertices: u64,
    /// Triangles sent to the sink (after fan triangulation).
    pub triangles: u64,
    /// The model carried vertex normals (else they were computed).
    pub has_normals: bool,
    /// The model carried vertex colors (else [`DEFAULT_COLOR`]).
    pub has_colors: bool,
}

/// A model file format.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ModelFormat {
    Ply,
    Obj,
}

/// A cheap look at a model: its format and its declared (PLY) or counted
/// (OBJ) vertices and faces (faces are polygons, before triangulation).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ModelProbe {
    pub format: ModelFormat,
    pub vertices: u64,
    pub faces: u64,
}

/// Streams every triangle of the model at `path` to `sink`, in file order,
/// fan-triangulating polygons, with ids `first_id`, `first_id + 1`, ...
/// (an error if they would overflow `u32`).
///
/// The format is detected by content: a file starting with the `ply` magic
/// line is PLY, else a file named `*.obj` is OBJ.
pub fn import_model(
    path: &Path,
    first_id: u32,
    opts: &ImportOptions,
    sink: &mut dyn FnMut(&Triangle) -> std::io::Result<()>,
) -> Result<ImportSummary, ImportError> {
    let (format, input) = open_model(path)?;
    match format {
        ModelFormat::Ply => ply::import(input, first_id, opts, sink),
        ModelFormat::Obj => obj::import(input, first_id, opts, sink),
    }
}

/// A cheap look at the model at `path`: the format and the declared counts
/// from a PLY header, or counts from a quick scan of an OBJ file.
pub fn probe_model(path: &Path) -> Result<ModelProbe, ImportError> {
    let (format, input) = open_model(path)?;
    match format {
        ModelFormat::Ply => ply::probe(input),
        ModelFormat::Obj => obj::probe(input),
    }
}

/// Opens `path` and detects its format by content (PLY magic), else by the
/// `.obj` extension.
fn open_model(path: &Path) -> Result<(ModelFormat, Input), ImportError> {
    let meta = std::fs::metadata(path)
        .map_err(|e| ImportError::file(path, format!("cannot open: {e}")))?;
    if meta.is_dir() {
        return Err(ImportError::file(path, "is a directory, not a model file"));
    }
    if !meta.is_file() {
        return Err(ImportError::file(path, "is not a regular file"));
    }
    let mut input = Input::open(path)?;
    if input.len() == 0 {
        return Err(ImportError::file(path, "empty file"));
    }
    let head = input.peek(5)?;
    let is_ply = head.starts_with(b"ply\n") || head.starts_with(b"ply\r\n");
    if is_ply {
        return Ok((ModelFormat::Ply, input));
    }
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("");
    if ext.eq_ignore_ascii_case("obj") {
        Ok((ModelFormat::Obj, input))
    } else if ext.eq_ignore_ascii_case("ply") {
        Err(ImportError::at_byte(
            path,
            0,
            "not a PLY file: it does not start with the 'ply' magic line",
        ))
    } else {
        Err(ImportError::file(
            path,
            "unknown model format: no 'ply' magic line and the extension is not .obj",
        ))
    }
}

/// The in-memory vertex table shared by the importers.
pub(crate) struct VertexTable {
    pub positions: Vec<Vec3>,
    /// Unit normals (input or computed); zero where none is usable.
    pub normals: Vec<Vec3>,
    pub colors: Option<Vec<[u8; 4]>>,
}

impl VertexTable {
    /// Bytes per vertex held in memory.
    pub fn bytes_per_vertex(colors: bool) -> u64 {
        24 + if colors { 4 } else { 0 }
    }

    /// Adds the geometric normal of triangle `idx` (area-weighted: the
    /// unnormalized cross product) to its corners' normals.
    #[inline]
    pub fn accumulate(&mut self, idx: [u32; 3]) {
        let [i, j, k] = idx.map(|i| i as usize);
        let p = &self.positions;
        let n = (p[j] - p[i]).cross(p[k] - p[i]);
        self.normals[i] += n;
        self.normals[j] += n;
        self.normals[k] += n;
    }

    /// Turns accumulated (or input) normals into unit normals, zero where the
    /// sum is zero or not finite.
    pub fn normalize(&mut self) {
        for n in &mut self.normals {
            *n = n.normalize_or_zero();
        }
    }

    /// The triangle `idx` with id `id`; `normals` are the corners' unit
    /// normals (zero where none is usable: replaced by the geometric normal).
    #[inline]
    pub fn triangle(&self, idx: [u32; 3], normals: [Vec3; 3], id: u32) -> Triangle {
        let [a, b, c] = idx.map(|i| i as usize);
        let positions = [self.positions[a], self.positions[b], self.positions[c]];
        let colors = match &self.colors {
            Some(col) => [col[a], col[b], col[c]],
            None => [DEFAULT_COLOR; 3],
        };
        Triangle {
            positions,
            normals: fix_normals(&positions, normals),
            colors,
            id,
        }
    }

    #[inline]
    pub fn vertex_normals(&self, idx: [u32; 3]) -> [Vec3; 3] {
        let n = &self.normals;
        [n[idx[0] as usize], n[idx[1] as usize], n[idx[2] as usize]]
    }
}

/// Replaces zero normals by the triangle's unit geometric normal, or +Z for a
/// degenerate triangle.
#[inline]
fn fix_normals(p: &[Vec3; 3], mut n: [Vec3; 3]) -> [Vec3; 3] {
    if n.contains(&Vec3::ZERO) {
        let g = (p[1] - p[0]).cross(p[2] - p[0]).normalize_or_zero();
        let g = if g == Vec3::ZERO { Vec3::Z } else { g };
        for v in &mut n {
            if *v == Vec3::ZERO {
                *v = g;
            }
        }
    }
    n
}

/// Hands out triangle ids, refusing to overflow `u32`.
pub(crate) struct Ids {
    next: u64,
}

impl Ids {
    pub fn new(first: u32) -> Self {
        Ids { next: first as u64 }
    }

    #[inline]
    pub fn next(&mut self, path: &Path) -> Result<u32, ImportError> {
        let id = self.next;
        if id > u32::MAX as u64 {
            return Err(overflow(path));
        }
        self.next += 1;
        Ok(id as u32)
    }

    /// Checks up front that `count` more ids fit.
    pub fn check(&self, path: &Path, count: u64) -> Result<(), ImportError> {
        if count > 0 && self.next + (count - 1) > u32::MAX as u64 {
            return Err(overflow(path));
        }
        Ok(())
    }
}

fn overflow(path: &Path) -> ImportError {
    ImportError::file(path, "triangle ids would overflow u32")
}

/// Converts a color channel to u8: float types hold 0..1, integer types
/// 0..255 (both clamped).
#[inline]
pub(crate) fn color_channel(v: f64, float: bool) -> u8 {
    let v = if float { v * 255.0 } else { v };
    v.round().clamp(0.0, 255.0) as u8
}
