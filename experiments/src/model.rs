//! The model and the camera path every run uses: a generated plant
//! preprocessed once into the model cache (kept for later runs), and the
//! walk written into the results directory.

use crate::error::ExperimentError;
use crate::results::write_atomic;
use crate::spec::{Model, Route, Walk};
use dray_actors::display::CameraPath;
use dray_scene::db::Database;
use dray_scene::generate::PlantParams;
use dray_scene::preprocess::{plant_database, PreprocessOptions};
use dray_scene::progress::Progress;
use std::path::{Path, PathBuf};

/// Where a model's database is (or will be, for a plant not made yet).
pub(crate) fn database_path(model: &Model, cache: &Path) -> PathBuf {
    match model {
        Model::Database(db) => db.clone(),
        Model::Plant { triangles, seed } => cache.join(format!("plant-{triangles}-seed{seed}.vdb")),
    }
}

/// Makes the plant's database in the cache unless an earlier run did.
pub(crate) fn prepare(model: &Model, cache: &Path) -> Result<PathBuf, ExperimentError> {
    let db = database_path(model, cache);
    let Model::Plant { triangles, seed } = *model else {
        return Ok(db);
    };
    if Database::open(&db).is_ok() {
        return Ok(db);
    }
    let fail = |e: &dyn std::fmt::Display| ExperimentError::Model {
        path: db.clone(),
        message: e.to_string(),
    };
    std::fs::create_dir_all(cache).map_err(|e| fail(&e))?;
    let ply = db.with_extension("ply");
    let built = plant_database(
        &PlantParams { triangles, seed },
        &ply,
        &PreprocessOptions::new(Vec::new(), db.clone()),
        &Progress::auto(),
    );
    // The PLY is only the preprocessor's input: the database is what is kept.
    let _ = std::fs::remove_file(&ply);
    built.map_err(|e| fail(&e))?;
    Ok(db)
}

/// Frames of a quick run: a tenth, at least 2 (or all, if fewer).
pub(crate) fn quick_frames(frames: u32) -> u32 {
    (frames / 10).max(2).min(frames)
}

/// The file of a run's camera path in the results directory `dir`:
/// `walk.toml`, or for a point of a swept walkthrough
/// (`swept_frames`, as the sweep gives them) `walks/frames-N.toml`.
pub(crate) fn walk_file(dir: &Path, swept_frames: Option<u32>) -> PathBuf {
    match swept_frames {
        None => dir.join("walk.toml"),
        Some(n) => dir.join(WALKS).join(format!("frames-{n}.toml")),
    }
}

/// The directory of the walks of a swept walkthrough.
const WALKS: &str = "walks";

/// Writes the camera paths of the runs into the results directory `dir`
/// (see [`walk_file`]): the path file as given, or the walkthrough of the
/// database, one per value of `swept_frames` when the sweep gives its
/// frames; `quick` keeps a tenth of the frames of each. Returns the
/// frames of the path when every run flies the same one.
pub(crate) fn write_walks(
    file: &Path,
    walk: &Walk,
    swept_frames: &[u32],
    db: &Path,
    quick: bool,
    dir: &Path,
) -> Result<Option<u32>, ExperimentError> {
    match &walk.route {
        Route::File(p) => {
            let path = CameraPath::load(p)
                .map_err(|e| ExperimentError::invalid(file, "walk.camera_path", e))?;
            write_walk(file, path, quick, &walk_file(dir, None)).map(Some)
        }
        Route::Frames(n) => {
            let path = walkthrough(file, db, *n, walk.inside)?;
            write_walk(file, path, quick, &walk_file(dir, None)).map(Some)
        }
        Route::SweptFrames => {
            let walks = dir.join(WALKS);
            std::fs::create_dir_all(&walks).map_err(|e| ExperimentError::output(&walks, e))?;
            for &n in swept_frames {
                let path = walkthrough(file, db, n, walk.inside)?;
                write_walk(file, path, quick, &walk_file(dir, Some(n)))?;
            }
            Ok(None)
        }
    }
}

/// The walkthrough of `dray walkthrough` through the database's model;
/// `inside`: only its last stretch (its last two keyframes), a person
/// walking among the structures, over all `frames`.
fn walkthrough(
    file: &Path,
    db: &Path,
    frames: u32,
    inside: bool,
) -> Result<CameraPath, ExperimentError> {
    let db = Database::open(db).map_err(|e| ExperimentError::invalid(file, "walk.frames", e))?;
    let mut path = CameraPath::walkthrough(&db.manifest.model_bounds, frames);
    if inside && path.keyframes.len() > 2 {
        path.keyframes.drain(..path.keyframes.len() - 2);
    }
    Ok(path)
}

/// Writes `path` to `out` (`quick`: a tenth of its frames, along the same
/// keyframes) and returns its frame count.
fn write_walk(
    file: &Path,
    path: CameraPath,
    quick: bool,
    out: &Path,
) -> Result<u32, ExperimentError> {
    let path = if quick {
        CameraPath::new(quick_frames(path.frames), path.keyframes)
            .map_err(|(key, e)| ExperimentError::invalid(file, format!("walk: {key}"), e))?
    } else {
        path
    };
    write_atomic(out, path.to_toml().as_bytes())?;
    Ok(path.frames)
}
