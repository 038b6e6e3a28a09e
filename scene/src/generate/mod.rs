//! The synthetic power plant: a deterministic stand-in for the UNC power
//! plant of the paper (12.5 M triangles of steel frames, pipes and vessels),
//! at any size from 10 thousand to 100 million triangles.
//!
//! # Layout
//!
//! The plant is a grid of **units** (building blocks) in the XZ plane, Y up,
//! metres. `N` triangles give `ceil(N / 200_000)` units on a
//! `ceil(sqrt(units))`-wide grid with a pitch of 72 m, so the plant grows in
//! area while the density per volume stays that of a real plant: 10 k
//! triangles is one small building, 12.5 M is 63 units over about
//! 580 m × 580 m. Tessellation is fixed (pipes 8–16 sides, tanks 24–32), so
//! more triangles always mean more objects, never finer ones.
//!
//! Each unit has a kind, drawn per unit from the seed (unit 0 is always a
//! process block), and a triangle share proportional to the kind's weight:
//!
//! - **process block** (weight 10): a 3–5 storey steel frame of 6 m bays
//!   (I-beam columns and beams, grating floors over ~65 % of the bays,
//!   railings on open edges, a stair tower), with vessels, pump sets and
//!   pipe runs;
//! - **dense block** (weight 16): 5–7 storeys, nearly all bays floored and the
//!   most piping: the crowded parts of the plant;
//! - **hall** (weight 6): an 18 m high open hall with 10 m bays, turbine
//!   sets, a crane on its rails and a mezzanine: big open volumes;
//! - **tank farm** (weight 6): a two-level pipe rack and a field of large
//!   tanks with roof railings, piping between them.
//!
//! Inside a unit, pipe starts and machines cluster around one "hot" corner
//! (60 %) while the rest spread uniformly, so crowded corners sit next to
//! open bays. Units are separated by roads; along each road runs a pipe rack
//! whose straight pipes line up from unit to unit across the plant. Sides
//! and roofs are open and floors are gratings of separate bars, so from
//! outside one sees deep inside.
//!
//! Objects: boxes (flat normals, unshared vertices), I-beams (three boxes),
//! pipe runs (one smooth swept surface through straight legs and torus
//! elbows, radial normals, flanges, end caps), tanks and vessels (cylinders
//! with ellipsoidal domes), pump sets (skid, motor with fins and fan hood,
//! coupling guard, pump casing, nozzles), turbine sets. Each object has one
//! color (pipes in nine colors, steel yellow/grey/blue/red per unit, green,
//! white and silver tanks, ...).
//!
//! # Exactly N triangles
//!
//! Unit `u` may write triangles up to the cumulative share
//! `N * (w_0 + ... + w_u) / (w_0 + ... + w_U-1)`. Objects are built whole
//! and written only if they fit; when pipe runs stop fitting, the rest is
//! filled with junction boxes (12 triangles), then signs (2) and at most one
//! gusset plate (1). No triangle is degenerate on purpose.
//!
//! # Memory and files
//!
//! Memory does not depend on N: one object at a time lives in a reusable
//! scratch buffer (the largest object is a few thousand triangles, see
//! [`last_peak_scratch_bytes`]), the per-unit plan is a few numbers, and
//! output goes through 1 MiB buffers. Vertices stream into a temporary file
//! next to the output after space reserved for the header, faces into a
//! second temporary file; at the end the faces are appended, the header
//! (padded by a comment) is written in front, and the file is renamed onto
//! the output path. A failed run deletes its temporaries and never leaves
//! a partial file at the output path.
//!
//! # Determinism
//!
//! Everything derives from the seed through SplitMix64 streams, one per
//! unit; there is no hashing or threading, so the same seed and N give the
//! same bytes.

mod mesh;
mod plant;
mod sink;

use crate::geometry::Aabb;
use glam::Vec3;
use std::cell::Cell;
use std::path::{Path, PathBuf};

/// Smallest triangle count accepted.
pub const MIN_TRIANGLES: u64 = 10_000;
/// Largest triangle count accepted.
pub const MAX_TRIANGLES: u64 = 100_000_000;
/// Bytes per vertex in the output (3 + 3 floats, 3 color bytes).
pub const BYTES_PER_VERTEX: u64 = sink::VERTEX_BYTES as u64;
/// Bytes per face in the output (count byte + 3 indices).
pub const BYTES_PER_FACE: u64 = sink::FACE_BYTES as u64;

/// What to generate.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PlantParams {
    /// Exact number of triangles in the output.
    pub triangles: u64,
    /// Different seeds give different plants.
    pub seed: u64,
}

/// What was written.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GenerateSummary {
    pub vertices: u64,
    pub triangles: u64,
    /// Bounds of all written vertex positions.
    pub bounds: Aabb,
}

#[derive(Debug, thiserror::Error)]
pub enum GenerateError {
    #[error(
        "cannot generate {requested} triangles: the count must be between {MIN_TRIANGLES} and {MAX_TRIANGLES}"
    )]
    TriangleCount { requested: u64 },
    #[error("cannot {action} {}: {source}", path.display())]
    Io {
        path: PathBuf,
        action: &'static str,
        #[source]
        source: std::io::Error,
    },
}

thread_local! {
    static PEAK_SCRATCH: Cell<usize> = const { Cell::new(0) };
}

/// The largest per-object scratch buffer (bytes) used by the last
/// [`generate_plant`] call on this thread: the only part of the generator's
/// memory that depends on the model, and it depends on the largest object,
/// not on N.
pub fn last_peak_scratch_bytes() -> usize {
    PEAK_SCRATCH.with(|c| c.get())
}

/// Writes the plant; `progress(triangles_written_so_far)` is called now and
/// then (for a progress bar).
pub fn generate_plant(
    params: &PlantParams,
    out: &Path,
    progress: &mut dyn FnMut(u64),
) -> Result<GenerateSummary, GenerateError> {
    let n = params.triangles;
    if !(MIN_TRIANGLES..=MAX_TRIANGLES).contains(&n) {
        return Err(GenerateError::TriangleCount { requested: n });
    }
    let mut sink = sink::Sink::create(out, progress)?;
    plant::build(&mut sink, n, params.seed)?;
    PEAK_SCRATCH.with(|c| c.set(sink.peak_scratch));
    let (units, _) = plant::grid(n);
    let comment = format!(
        "dray synthetic power plant: seed {}, {} triangles, {} units",
        params.seed, n, units
    );
    let (vertices, triangles, bounds) = sink.finish(&comment)?;
    Ok(GenerateSummary {
        vertices,
        triangles,
        bounds,
    })
}

/// Camera positions `(eye, look)` for a walkthrough of a plant with these
/// bounds: first an overview from outside showing the whole plant, then a
/// path that enters along the first road at eye height and goes deeper
/// into the frames, ending in the middle of the plant.
pub fn suggested_views(bounds: &Aabb) -> Vec<(Vec3, Vec3)> {
    let lo = bounds.lo();
    let e = bounds.extent();
    let c = bounds.center();
    let span = e.x.max(e.z).max(1.0);
    let at = |fx: f32, y: f32, fz: f32| Vec3::new(lo.x + fx * e.x, lo.y + y, lo.z + fz * e.z);
    // Height of a mid storey, bounded by the model.
    let storey = (e.y * 0.3).clamp(1.7, 12.0);
    vec![
        // Outside: from a corner, high up, looking at the centre.
        (
            Vec3::new(lo.x - 0.2 * span, lo.y + 0.5 * span, lo.z - 0.3 * span),
            c,
        ),
        // Approaching from the front at a low height.
        (at(-0.15, 1.7 + e.y * 0.15, 0.05), at(0.5, e.y * 0.2, 0.4)),
        // At the edge of the first frames, eye height.
        (at(0.02, 1.7, 0.12), at(0.6, 1.7, 0.35)),
        // Inside, on a storey, looking along the plant.
        (at(0.2, storey, 0.25), at(0.9, storey, 0.3)),
        // Deep inside, near the centre, looking towards the far corner.
        (at(0.45, storey * 0.6, 0.45), at(1.0, storey * 0.8, 1.0)),
        // The centre, looking up through the gratings.
        (at(0.5, 1.7, 0.5), at(0.55, e.y, 0.6)),
    ]
}
