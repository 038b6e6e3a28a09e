//! A generated plant preprocessed into a database: the model of the demo's
//! and the experiments' runs and of the tests' fixtures, made one way.

use super::{preprocess, PreprocessError, PreprocessOptions, PreprocessReport};
use crate::generate::{generate_plant, PlantParams};
use crate::progress::Progress;
use std::path::Path;

/// Generates `plant` as the PLY file `ply` and preprocesses it into
/// `opts.out` (`opts.inputs` are replaced by `ply`). The PLY stays: the
/// caller removes it when only the database is wanted.
pub fn plant_database(
    plant: &PlantParams,
    ply: &Path,
    opts: &PreprocessOptions,
    progress: &Progress,
) -> Result<PreprocessReport, PreprocessError> {
    progress.stage("generating plant", plant.triangles);
    let mut last = 0;
    generate_plant(plant, ply, &mut |done| {
        progress.advance(done - last);
        last = done;
    })?;
    progress.finish();
    let opts = PreprocessOptions {
        inputs: vec![ply.to_path_buf()],
        ..opts.clone()
    };
    preprocess(&opts, progress)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::db::Database;

    #[test]
    fn the_database_holds_the_generated_plant() {
        let dir = tempfile::tempdir().unwrap();
        let ply = dir.path().join("plant.ply");
        let db = dir.path().join("plant.vdb");
        let plant = PlantParams {
            triangles: 20_000,
            seed: 7,
        };
        let report = plant_database(
            &plant,
            &ply,
            &PreprocessOptions::new(Vec::new(), db.clone()),
            &Progress::hidden(),
        )
        .unwrap();
        assert_eq!(report.manifest.input_triangles, 20_000);
        assert!(ply.exists());
        let opened = Database::open(&db).unwrap();
        assert_eq!(opened.manifest.input_triangles, 20_000);
    }

    #[test]
    fn a_bad_triangle_count_is_an_error_and_writes_no_database() {
        let dir = tempfile::tempdir().unwrap();
        let db = dir.path().join("plant.vdb");
        let e = plant_database(
            &PlantParams {
                triangles: 0,
                seed: 1,
            },
            &dir.path().join("plant.ply"),
            &PreprocessOptions::new(Vec::new(), db.clone()),
            &Progress::hidden(),
        )
        .unwrap_err();
        assert!(matches!(e, PreprocessError::Generate(_)), "{e}");
        assert!(!db.exists());
    }
}
