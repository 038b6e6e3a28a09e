//! Out-of-core preprocessing: model files in, a voxel database out.
//!
//! 1. **Import** every input into one spill file of fixed-size triangle
//!    records (the importers keep only the vertex table in memory).
//! 2. **Build** the high-level BSP with SAH-placed axis-aligned planes. When
//!    the triangles (with the copies) do not fit the memory budget, a sample
//!    places the top planes, one streaming pass distributes the triangles to
//!    chunk files (replicating those that straddle a plane), and each chunk is
//!    built the same way; a chunk that fits is built in memory on all threads.
//!    A node becomes a voxel when it holds at most `max_triangles` or reaches
//!    `max_depth`; each voxel is built (vertices, low-level BVH), compressed
//!    and appended to the voxels file as soon as its leaf is known.
//! 3. **Commit**: the manifest is written last, and the finished directory
//!    is renamed over the target, so an interrupted run leaves nothing that
//!    looks like a database and never damages an existing one.

mod build;
mod plant;
pub mod spill;
pub mod split;

pub use plant::plant_database;

use crate::db::manifest::{
    BspNode, BuildParams, InputModel, Manifest, VoxelEntry, FORMAT_VERSION, MANIFEST_FILE,
    VOXELS_FILE,
};
use crate::geometry::Aabb;
use crate::import::{import_model, probe_model, ImportError, ImportOptions};
use crate::mesh::Triangle;
use crate::progress::Progress;
use build::{build_stream, BuildContext, BuildNode, TriangleStream, VoxelSink};
use glam::Vec3;
use spill::{SpillFile, SpillWriter};
use std::io;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicU64;
use std::time::Instant;

/// Default largest triangle count of a voxel (measured by `cargo bench -p
/// dray-scene --bench max_triangles`; docs/benchmarks.md has the table).
pub const DEFAULT_MAX_TRIANGLES: u32 = 4096;
/// Default deepest level of the high-level BSP.
pub const DEFAULT_MAX_DEPTH: u32 = 40;
pub const DEFAULT_MEMORY_MB: u64 = 2048;
pub const DEFAULT_ZSTD_LEVEL: i32 = 3;
/// Bytes per triangle that an in-memory build needs: the triangle (88),
/// its references with clipped bounds in the parent and both children
/// (3 × 28), the voxel being built. Measured peak RSS stays below this.
const BUILD_BYTES_PER_TRIANGLE: u64 = 220;

#[derive(Clone, Debug)]
pub struct PreprocessOptions {
    pub inputs: Vec<PathBuf>,
    pub out: PathBuf,
    pub max_triangles: u32,
    pub max_depth: u32,
    /// Copies of the whole input along x, y and z.
    pub copies: [u32; 3],
    /// Distance between copies as a multiple of the input's extent on each
    /// axis (1.0: copies touch; 1.2: a gap of a fifth of the model).
    pub spacing: f32,
    /// Worker threads; 0 means every core.
    pub threads: usize,
    pub memory_mb: u64,
    pub zstd_level: i32,
    /// Largest number of triangles built in memory at once; `None` derives
    /// it from `memory_mb`. Tests set it low to exercise the out-of-core path.
    pub chunk_triangles: Option<u64>,
}

impl PreprocessOptions {
    pub fn new(inputs: Vec<PathBuf>, out: PathBuf) -> PreprocessOptions {
        PreprocessOptions {
            inputs,
            out,
            max_triangles: DEFAULT_MAX_TRIANGLES,
            max_depth: DEFAULT_MAX_DEPTH,
            copies: [1, 1, 1],
            spacing: 1.1,
            threads: 0,
            memory_mb: DEFAULT_MEMORY_MB,
            zstd_level: DEFAULT_ZSTD_LEVEL,
            chunk_triangles: None,
        }
    }

    fn validate(&self) -> Result<(), PreprocessError> {
        let bad = |m: &str| Err(PreprocessError::Options(m.to_string()));
        if self.inputs.is_empty() {
            return bad("no input model given");
        }
        if self.max_triangles == 0 {
            return bad("--max-triangles must be at least 1");
        }
        if self.max_depth == 0 || self.max_depth > 64 {
            return bad("--max-depth must be between 1 and 64");
        }
        if self.copies.contains(&0) {
            return bad("--copies needs at least one copy on each axis");
        }
        if !(self.spacing.is_finite() && self.spacing > 0.0) {
            return bad("--spacing must be a positive number");
        }
        if self.memory_mb < 64 {
            return bad("--memory-mb must be at least 64");
        }
        if !(1..=22).contains(&self.zstd_level) {
            return bad("the zstd level must be between 1 and 22");
        }
        Ok(())
    }
}

#[derive(Debug, thiserror::Error)]
pub enum PreprocessError {
    #[error(transparent)]
    Import(#[from] ImportError),
    /// Generating the plant that [`plant_database`] preprocesses failed.
    #[error(transparent)]
    Generate(#[from] crate::generate::GenerateError),
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: io::Error },
    /// Reading or writing the temporary spill files failed (disk full...).
    #[error("temporary spill file: {0}")]
    Spill(String),
    #[error("{0}")]
    Options(String),
    #[error("{0}")]
    Model(String),
    #[error("cancelled; nothing was written")]
    Cancelled,
    #[error("{path}: exists and is not a dray database; refusing to replace it")]
    NotADatabase { path: PathBuf },
}

impl PreprocessError {
    pub(crate) fn io(path: &Path, source: io::Error) -> PreprocessError {
        PreprocessError::Io {
            path: path.to_path_buf(),
            source,
        }
    }
}

impl From<io::Error> for PreprocessError {
    fn from(e: io::Error) -> Self {
        PreprocessError::Spill(e.to_string())
    }
}

/// What a finished run did.
#[derive(Clone, Debug)]
pub struct PreprocessReport {
    pub manifest: Manifest,
    pub seconds: f64,
    pub import_seconds: f64,
}

impl PreprocessReport {
    /// Input triangles per second over the whole build.
    pub fn triangles_per_second(&self) -> f64 {
        self.manifest.input_triangles as f64 / self.seconds
    }

    /// The line `dray preprocess` prints about the database built at `out`.
    pub fn summary(&self, out: &Path) -> String {
        let m = &self.manifest;
        format!(
            "{}: {} triangles -> {} voxels in {:.1} s ({:.2} M triangles/s), replication {:.3}",
            out.display(),
            m.input_triangles,
            m.voxels.len(),
            self.seconds,
            self.triangles_per_second() / 1e6,
            m.replication_factor()
        )
    }
}

/// The input spill file, repeated on the copy grid.
struct CopiedInput {
    spill: SpillFile,
    copies: [u32; 3],
    step: Vec3,
}

impl CopiedInput {
    fn offsets(&self) -> impl Iterator<Item = (u32, Vec3)> + '_ {
        let [a, b, c] = self.copies;
        (0..c)
            .flat_map(move |z| (0..b).flat_map(move |y| (0..a).map(move |x| (x, y, z))))
            .enumerate()
            .map(move |(i, (x, y, z))| {
                (
                    i as u32,
                    Vec3::new(x as f32, y as f32, z as f32) * self.step,
                )
            })
    }

    fn bounds(&self) -> Aabb {
        self.offsets().fold(Aabb::EMPTY, |b, (_, o)| {
            b.union(&Aabb::new(
                self.spill.bounds.lo() + o,
                self.spill.bounds.hi() + o,
            ))
        })
    }
}

impl TriangleStream for CopiedInput {
    fn count(&self) -> u64 {
        self.spill.count * self.copies.iter().map(|&c| c as u64).product::<u64>()
    }

    fn for_each(
        &self,
        f: &mut dyn FnMut(Triangle) -> Result<(), PreprocessError>,
    ) -> Result<(), PreprocessError> {
        for (copy, offset) in self.offsets() {
            let id_base = copy as u64 * self.spill.count;
            self.spill.for_each(|mut t| {
                if copy > 0 {
                    for p in &mut t.positions {
                        *p += offset;
                    }
                    t.id = (t.id as u64 + id_base) as u32;
                }
                f(t)
            })?;
        }
        Ok(())
    }
}

/// Builds the database `opts.out` from `opts.inputs`.
pub fn preprocess(
    opts: &PreprocessOptions,
    progress: &Progress,
) -> Result<PreprocessReport, PreprocessError> {
    opts.validate()?;
    let start = Instant::now();
    let out = &opts.out;
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    if out.exists() && !out.join(MANIFEST_FILE).is_file() {
        return Err(PreprocessError::NotADatabase { path: out.clone() });
    }
    let name = out
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "db".into());
    remove_stale_builds(&parent);
    let prefix = building_prefix(&name, std::process::id());
    let mut builder = tempfile::Builder::new();
    builder.prefix(&prefix);
    // Becomes the database: an ordinary directory, not tempfile's 0700.
    #[cfg(unix)]
    builder.permissions(std::os::unix::fs::PermissionsExt::from_mode(0o755));
    let work = builder
        .tempdir_in(&parent)
        .map_err(|e| PreprocessError::io(&parent, e))?;
    let spill_dir = work.path().join("spill");
    std::fs::create_dir(&spill_dir).map_err(|e| PreprocessError::io(&spill_dir, e))?;
    let budget = opts.memory_mb * 1024 * 1024;

    // 1. Import.
    let input_path = spill_dir.join("input.spill");
    let mut writer =
        SpillWriter::create(&input_path).map_err(|e| PreprocessError::io(&input_path, e))?;
    let mut inputs = Vec::new();
    for path in &opts.inputs {
        let probe = probe_model(path)?;
        progress.stage(
            &format!("importing {}", short_name(path)),
            probe.faces.max(1),
        );
        let first_id = u32::try_from(writer.count)
            .map_err(|_| PreprocessError::Model("more than 2^32 triangles in the inputs".into()))?;
        let mut pending = 0u64;
        let summary = import_model(
            path,
            first_id,
            &ImportOptions {
                max_vertex_bytes: budget / 2,
            },
            &mut |t| {
                if progress.is_cancelled() {
                    return Err(io::Error::other("cancelled"));
                }
                pending += 1;
                if pending == 4096 {
                    progress.advance(pending);
                    pending = 0;
                }
                writer.push(t)
            },
        )
        .map_err(|e| {
            if progress.is_cancelled() {
                PreprocessError::Cancelled
            } else {
                e.into()
            }
        })?;
        progress.advance(pending);
        inputs.push(InputModel {
            path: path.display().to_string(),
            triangles: summary.triangles,
            vertices: summary.vertices,
        });
    }
    let spill = writer.finish()?;
    let import_seconds = start.elapsed().as_secs_f64();
    if spill.count == 0 {
        return Err(PreprocessError::Model(
            "the inputs hold no triangles".into(),
        ));
    }

    // 2. Copies.
    let extent = spill.bounds.extent();
    let source = CopiedInput {
        step: extent * opts.spacing,
        copies: opts.copies,
        spill,
    };
    if source.count() > u32::MAX as u64 {
        return Err(PreprocessError::Model(format!(
            "{} triangles with the copies: triangle ids must fit 32 bits",
            source.count()
        )));
    }
    let model_bounds = source.bounds();

    // 3. Build.
    let sink_path = work.path().join(VOXELS_FILE);
    let sink = VoxelSink::create(&sink_path)?;
    let ctx = BuildContext {
        max_triangles: opts.max_triangles,
        max_depth: opts.max_depth,
        zstd_level: opts.zstd_level,
        chunk_triangles: opts
            .chunk_triangles
            .unwrap_or(budget / 2 / BUILD_BYTES_PER_TRIANGLE)
            .max(1),
        spill_dir: &spill_dir,
        sink: &sink,
        progress,
        chunk_counter: AtomicU64::new(0),
    };
    let mut pool = rayon::ThreadPoolBuilder::new();
    if opts.threads > 0 {
        pool = pool.num_threads(opts.threads);
    }
    let pool = pool
        .build()
        .map_err(|e| PreprocessError::Options(format!("cannot start threads: {e}")))?;
    let tree = pool.install(|| build_stream(&ctx, &source, model_bounds, 0))?;
    sink.finish()?;
    progress.finish();

    // 4. Manifest, then commit.
    let mut manifest = Manifest {
        format_version: FORMAT_VERSION,
        model_bounds,
        root_bounds: model_bounds,
        input_triangles: source.count(),
        stored_triangles: 0,
        build: BuildParams {
            inputs,
            max_triangles: opts.max_triangles,
            max_depth: opts.max_depth,
            copies: opts.copies,
            spacing: opts.spacing,
            zstd_level: opts.zstd_level,
        },
        nodes: Vec::new(),
        voxels: Vec::new(),
    };
    flatten(tree, &mut manifest.nodes, &mut manifest.voxels);
    manifest.stored_triangles = manifest.voxels.iter().map(|v| v.triangles as u64).sum();
    drop(source);
    std::fs::remove_dir_all(&spill_dir).map_err(|e| PreprocessError::io(&spill_dir, e))?;
    let manifest_path = work.path().join(MANIFEST_FILE);
    write_synced(&manifest_path, &manifest.encode())?;
    commit(work.keep(), out)?;
    Ok(PreprocessReport {
        manifest,
        seconds: start.elapsed().as_secs_f64(),
        import_seconds,
    })
}

/// This machine's name, as the kernel has it ("" where unknown).
fn host_name() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|h| h.trim().to_string())
        .unwrap_or_default()
}

/// The start of the hidden folder in which process `pid` of this machine
/// builds database `name`: `.NAME.building-HOST.PID-` (tempfile adds a
/// random tag), so a later run can tell whether its builder still lives.
pub fn building_prefix(name: &str, pid: u32) -> String {
    format!(".{name}.building-{}.{pid}-", host_name())
}

/// The builder of a hidden build folder's name (host, pid), if it is one.
fn building_owner(file_name: &str) -> Option<(&str, u32)> {
    let rest = file_name.strip_prefix('.')?;
    let (_, rest) = rest.split_once(".building-")?;
    let (owner, _tag) = rest.rsplit_once('-')?;
    let (host, pid) = owner.rsplit_once('.')?;
    Some((host, pid.parse().ok()?))
}

/// Whether process `pid` of this machine runs (a zombie does not); where
/// that cannot be known, it is taken to run.
fn process_runs(pid: u32) -> bool {
    if !cfg!(target_os = "linux") {
        return true;
    }
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        // The state follows the command name in parentheses.
        Ok(stat) => !matches!(
            stat.rsplit_once(") "),
            Some((_, rest)) if rest.starts_with(['Z', 'X'])
        ),
        Err(_) => false,
    }
}

/// Removes the build folders in `parent` whose builder on this machine is
/// gone (a killed run's); a live run's, another machine's and those that
/// name no builder are left alone.
fn remove_stale_builds(parent: &Path) {
    let Ok(entries) = std::fs::read_dir(parent) else {
        return;
    };
    let host = host_name();
    for entry in entries.flatten() {
        let file_name = entry.file_name();
        let Some(name) = file_name.to_str() else {
            continue;
        };
        if !name.starts_with('.') || !name.contains(".building-") {
            continue;
        }
        let path = entry.path();
        match building_owner(name) {
            Some((h, pid)) if h == host && !process_runs(pid) => {
                match std::fs::remove_dir_all(&path) {
                    Ok(()) => tracing::info!(folder = %path.display(), pid,
                        "removed the build folder of a run that is gone"),
                    Err(e) => tracing::warn!(folder = %path.display(), error = %e,
                        "cannot remove the build folder of a run that is gone"),
                }
            }
            Some(_) => {}
            None => tracing::warn!(folder = %path.display(),
                "a build folder that names no builder: remove it by hand if no preprocess runs"),
        }
    }
}

fn short_name(path: &Path) -> String {
    path.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| path.display().to_string())
}

/// Depth-first: a split's children follow it, voxel ids in leaf order.
fn flatten(node: BuildNode, nodes: &mut Vec<BspNode>, voxels: &mut Vec<VoxelEntry>) -> u32 {
    let me = nodes.len() as u32;
    match node {
        BuildNode::Leaf(entry) => {
            let voxel = entry.map(|e| {
                voxels.push(e);
                voxels.len() as u32 - 1
            });
            nodes.push(BspNode::Leaf { voxel });
        }
        BuildNode::Split { plane, children } => {
            nodes.push(BspNode::Leaf { voxel: None });
            let [l, r] = *children;
            let left = flatten(l, nodes, voxels);
            let right = flatten(r, nodes, voxels);
            nodes[me as usize] = BspNode::Split {
                axis: plane.axis as u8,
                pos: plane.pos,
                left,
                right,
            };
        }
    }
    me
}

fn write_synced(path: &Path, bytes: &[u8]) -> Result<(), PreprocessError> {
    use std::io::Write;
    let mut f = std::fs::File::create(path).map_err(|e| PreprocessError::io(path, e))?;
    f.write_all(bytes)
        .and_then(|_| f.sync_all())
        .map_err(|e| PreprocessError::io(path, e))
}

/// Moves the finished directory to `out`. An existing database is first
/// renamed aside and removed only once the new one is in place.
fn commit(built: PathBuf, out: &Path) -> Result<(), PreprocessError> {
    let fail = |e| {
        let _ = std::fs::remove_dir_all(&built);
        PreprocessError::io(out, e)
    };
    if out.exists() {
        let aside = out.with_file_name(format!(
            ".{}.old-{}",
            out.file_name()
                .map(|n| n.to_string_lossy())
                .unwrap_or_default(),
            std::process::id()
        ));
        std::fs::rename(out, &aside).map_err(fail)?;
        std::fs::rename(&built, out).map_err(|e| {
            let _ = std::fs::rename(&aside, out);
            fail(e)
        })?;
        let _ = std::fs::remove_dir_all(&aside);
    } else {
        std::fs::rename(&built, out).map_err(fail)?;
    }
    Ok(())
}

#[cfg(test)]
mod report_tests {
    use super::*;
    use crate::generate::{generate_plant, PlantParams};

    #[test]
    fn the_summary_gives_the_rate_and_the_replication() {
        let dir = tempfile::tempdir().unwrap();
        let ply = dir.path().join("plant.ply");
        let params = PlantParams {
            triangles: crate::generate::MIN_TRIANGLES,
            seed: 1,
        };
        generate_plant(&params, &ply, &mut |_| {}).unwrap();
        let out = dir.path().join("plant.vdb");
        let opts = PreprocessOptions::new(vec![ply], out.clone());
        let report = preprocess(&opts, &Progress::hidden()).unwrap();
        let m = &report.manifest;
        assert!(m.replication_factor() >= 1.0);
        assert_eq!(
            m.replication_factor(),
            m.stored_triangles as f64 / m.input_triangles as f64
        );
        let rate = m.input_triangles as f64 / report.seconds;
        assert_eq!(report.triangles_per_second(), rate);
        let line = report.summary(&out);
        assert!(
            line.starts_with(&format!(
                "{}: {} triangles -> {} voxels in ",
                out.display(),
                m.input_triangles,
                m.voxels.len()
            )),
            "{line}"
        );
        assert!(
            line.ends_with(&format!("replication {:.3}", m.replication_factor())),
            "{line}"
        );
    }
}
