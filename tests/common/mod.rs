//! Shared by the cluster tests: a small generated plant preprocessed into
//! a database, configs on free loopback ports, and the reference render.

#![allow(dead_code)]

use dray_actors::settings::{kernel_camera, kernel_settings, wire_settings};
use dray_config::Config;
use dray_protocol::Camera;
use dray_scene::db::Database;
use dray_scene::generate::suggested_views;
use dray_trace::accel::{ResidentSource, TopLevel};
use dray_trace::render::{render, Isa};
use std::path::{Path, PathBuf};

pub use dray_testkit::free_ports;

/// A plant of `triangles` in `dir/plant.vdb`, with small voxels so that a
/// small image touches many of them.
pub fn plant_db(dir: &Path, triangles: u64) -> PathBuf {
    dray_testkit::plant_db_in(dir, triangles, 3, 256)
}

/// A walkthrough of `frames` cameras from outside the model to inside.
pub fn write_path(db: &Path, out: &Path, frames: u32) {
    let db = Database::open(db).unwrap();
    let views = suggested_views(&db.manifest.model_bounds);
    let mut text = format!("frames = {frames}\n");
    for (eye, look) in views.iter().take(3) {
        text += &format!(
            "[[keyframe]]\neye = [{}, {}, {}]\nlook = [{}, {}, {}]\nfov_y_deg = 60.0\n",
            eye.x, eye.y, eye.z, look.x, look.y, look.z
        );
    }
    std::fs::write(out, text).unwrap();
}

/// The text of a cluster config over `db` with a camera path, on free
/// ports; `extra` is appended inside `[clients]`.
pub fn config_text(
    db: &Path,
    path: &Path,
    dir: &Path,
    clients: u32,
    cache_mb: f64,
    extra_clients: &str,
    links: &str,
) -> String {
    let ports = free_ports::<4>();
    format!(
        r#"
[scene]
database = "{db}"

[render]
width = 96
height = 64
tile_size = 16
shadows = true
reflection_depth = 1
depth_and_ids = true
camera_path = "{path}"

[render.camera]
eye = [0.0, 5.0, -30.0]
look = [0.0, 2.0, 0.0]

[scheduler]
address = "127.0.0.1:{p0}"
tile_deadline_ms = 3000

[display]
address = "127.0.0.1:{p1}"
output = "{out}"

[[stores]]
address = "127.0.0.1:{p2}"

[[stores]]
address = "127.0.0.1:{p3}"

[clients]
count = {clients}
threads = 1
cache_mb = {cache_mb}
{extra_clients}

{links}

[certs]
dir = "{certs}"
"#,
        db = db.display(),
        path = path.display(),
        out = dir.join("out").display(),
        certs = dir.join("certs").display(),
        p0 = ports[0],
        p1 = ports[1],
        p2 = ports[2],
        p3 = ports[3],
    )
}

/// Writes a config and loads it back.
pub fn config(dir: &Path, text: &str) -> (PathBuf, Config) {
    let p = dir.join("cluster.toml");
    std::fs::write(&p, text).unwrap();
    let cfg = Config::load(&p).unwrap();
    (p, cfg)
}

/// What `dray render` makes of one camera of the config, on one thread:
/// (rgba, depth, primid).
pub fn reference(cfg: &Config, camera: &Camera) -> (Vec<[u8; 4]>, Vec<f32>, Vec<u32>) {
    let db = Database::open(&cfg.scene.database).unwrap();
    let top = TopLevel::from_manifest(&db.manifest);
    let source = ResidentSource::load(&db).unwrap();
    let settings = kernel_settings(
        &wire_settings(&cfg.render),
        db.manifest.model_bounds.diagonal(),
        1,
        Isa::detect(),
    );
    let cam = kernel_camera(camera, cfg.render.width, cfg.render.height);
    let f = render(&top, &source, &cam, &settings).unwrap();
    (f.rgba, f.depth, f.primid)
}

/// A two-worker runtime for running clusters in a test.
pub fn rt() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap()
}
