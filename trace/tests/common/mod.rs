//! Scenes, databases, cameras and instruction sets shared by the tests.
#![allow(dead_code)]

use dray_scene::db::Database;
use dray_scene::import::{import_model, ImportOptions};
use dray_trace::accel::{ResidentSource, TopLevel};
use dray_trace::camera::Camera;
use dray_trace::render::{Isa, RenderSettings};
use glam::Vec3;
use std::path::Path;

pub struct Model {
    pub _dir: tempfile::TempDir,
    pub tris: Vec<[Vec3; 3]>,
    pub top: TopLevel,
    pub source: ResidentSource,
    pub db: Database,
}

fn load(model: &Path, dir: tempfile::TempDir, db: Database) -> Model {
    let mut tris = Vec::new();
    import_model(model, 0, &ImportOptions::default(), &mut |t| {
        tris.push(t.positions);
        Ok(())
    })
    .unwrap();
    Model {
        _dir: dir,
        tris,
        top: TopLevel::from_manifest(&db.manifest),
        source: ResidentSource::load(&db).unwrap(),
        db,
    }
}

pub fn plant(triangles: u64) -> Model {
    let t = dray_testkit::plant_db(triangles, 5, 512);
    load(&t.model, t.dir, t.db)
}

/// A real model shipped in `tests/data/` (origins in its `SOURCES.md`).
pub fn real_model(name: &str) -> Model {
    let dir = tempfile::tempdir().unwrap();
    let model = dray_testkit::real_model(name, dir.path());
    let db = dray_testkit::preprocess_into(&model, &dir.path().join("db"), 2048);
    load(&model, dir, db)
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
