//! The model and the camera path every run uses: a generated plant
//! preprocessed once into the model cache (kept for later runs), and the
//! walk written into the results directory.

use crate::error::ExperimentError;
use crate::results::write_atomic;
use crate::spec::{Model, Route, Walk};
use dray_actors::display::CameraPath;
use dray_scene::db::Database;
use dray_scene::generate::{generate_plant, PlantParams};
use dray_scene::preprocess::{preprocess, PreprocessOptions};
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
    let progress = Progress::auto();
    progress.stage("generating plant", triangles);
    let mut last = 0;
    generate_plant(&PlantParams { triangles, seed }, &ply, &mut |done| {
        progress.advance(done - last);
        last = done;
    })
    .map_err(|e| fail(&e))?;
    progress.finish();
    let built = preprocess(
        &PreprocessOptions::new(vec![ply.clone()], db.clone()),
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

/// Writes the walk's camera path to `out` (the path file as given, or the
/// walkthrough of the database; `quick` keeps a tenth of its frames) and
/// returns its frame count.
pub(crate) fn write_walk(
    file: &Path,
    walk: &Walk,
    db: &Path,
    quick: bool,
    out: &Path,
) -> Result<u32, ExperimentError> {
    let path = match &walk.route {
        Route::File(p) => CameraPath::load(p)
            .map_err(|e| ExperimentError::invalid(file, "walk.camera_path", e))?,
        Route::Frames(n) => {
            let db =
                Database::open(db).map_err(|e| ExperimentError::invalid(file, "walk.frames", e))?;
            CameraPath::walkthrough(&db.manifest.model_bounds, *n)
        }
    };
    let path = if quick {
        CameraPath::new(quick_frames(path.frames), path.keyframes)
            .map_err(|(key, e)| ExperimentError::invalid(file, format!("walk: {key}"), e))?
    } else {
        path
    };
    write_atomic(out, path.to_toml().as_bytes())?;
    Ok(path.frames)
}
