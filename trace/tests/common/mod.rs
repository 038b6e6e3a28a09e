//! Scenes, databases, cameras and instruction sets shared by the tests.
#![allow(dead_code)]

use dray_scene::db::Database;
use dray_scene::generate::{generate_plant, PlantParams};
use dray_scene::import::{import_model, ImportOptions};
use dray_scene::preprocess::{preprocess, PreprocessOptions};
use dray_scene::progress::Progress;
use dray_trace::camera::Camera;
use dray_trace::render::{Isa, RenderSettings};
use dray_trace::scene::{ResidentSource, TopLevel};
use glam::Vec3;
use std::path::{Path, PathBuf};

pub struct Model {
    pub _dir: tempfile::TempDir,
    pub tris: Vec<[Vec3; 3]>,
    pub top: TopLevel,
    pub source: ResidentSource,
    pub db: Database,
}

pub fn load(model: &Path, dir: tempfile::TempDir, max_triangles: u32) -> Model {
    let mut tris = Vec::new();
    import_model(model, 0, &ImportOptions::default(), &mut |t| {
        tris.push(t.positions);
        Ok(())
    })
    .unwrap();
    let db_path = dir.path().join("db");
    preprocess(
        &PreprocessOptions {
            max_triangles,
            ..PreprocessOptions::new(vec![model.to_path_buf()], db_path.clone())
        },
        &Progress::hidden(),
    )
    .unwrap();
    let db = Database::open(&db_path).unwrap();
    Model {
        _dir: dir,
        tris,
        top: TopLevel::from_manifest(&db.manifest),
        source: ResidentSource::load(&db).unwrap(),
        db,
    }
}

pub fn plant(triangles: u64) -> Model {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("plant.ply");
    generate_plant(&PlantParams { triangles, seed: 5 }, &model, &mut |_| {}).unwrap();
    load(&model, dir, 512)
}

/// A real model shipped in `tests/data/` (origins in its `SOURCES.md`).
pub fn real_model(name: &str) -> Model {
    let dir = tempfile::tempdir().unwrap();
    let src = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../tests/data")
        .join(format!("{name}.ply.zst"));
    let out = dir.path().join(format!("{name}.ply"));
    let input = std::fs::File::open(&src).unwrap_or_else(|e| panic!("{}: {e}", src.display()));
    zstd::stream::copy_decode(input, std::fs::File::create(&out).unwrap()).unwrap();
    load(&out, dir, 2048)
}

pub fn isas() -> Vec<Isa> {
    let mut v = vec![Isa::Portable];
    match Isa::detect() {
        Isa::Avx512 => v.extend([Isa::Avx2, Isa::Avx512]),
        Isa::Avx2 => v.push(Isa::Avx2),
        Isa::Portable => {}
    }
    v
}

pub fn settings(isa: Isa, m: &Model) -> RenderSettings {
    RenderSettings {
        threads: 2,
        isa,
        ..RenderSettings::primary(m.db.manifest.model_bounds.diagonal())
    }
}

pub fn cameras(m: &Model, w: u32, h: u32) -> Vec<Camera> {
    let b = m.db.manifest.model_bounds;
    let outside = Camera::default_for(&b, w, h);
    let c = b.center();
    let e = b.extent();
    vec![
        outside,
        // Close up, looking across the model from inside its box.
        Camera {
            eye: c + Vec3::new(-0.3 * e.x, 0.1 * e.y, 0.2 * e.z),
            look: c + Vec3::new(0.4 * e.x, 0.0, -0.3 * e.z),
            ..outside
        },
        // Straight down, axis-aligned rays (the watertight test's edge case).
        Camera {
            eye: c + Vec3::new(0.0, 1.2 * e.max_element(), 0.0),
            look: c,
            up: Vec3::Z,
            ..outside
        },
    ]
}
