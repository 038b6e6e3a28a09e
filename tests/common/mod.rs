//! Shared by the cluster tests: a small generated plant preprocessed into
//! a database, configs on free loopback ports (one sharded, for launchers),
//! the reference render and the check of the frames a display wrote.

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
/// loopback ports with two stores; `extra_clients` is appended inside
/// `[clients]`, `links` after it.
pub fn config_text(
    db: &Path,
    path: &Path,
    dir: &Path,
    clients: u32,
    cache_mb: f64,
    extra_clients: &str,
    links: &str,
) -> String {
    let [p0, p1, p2, p3] = free_ports::<4>();
    let at = |port: u16| format!("127.0.0.1:{port}");
    let layout = Layout {
        scheduler: at(p0),
        display: at(p1),
        stores: vec![
            format!("address = \"{}\"", at(p2)),
            format!("address = \"{}\"", at(p3)),
        ],
        tile_deadline_ms: Some(3000),
    };
    config_text_with(
        db,
        path,
        dir,
        &layout,
        clients,
        cache_mb,
        extra_clients,
        links,
    )
}

/// Where a config's nodes listen: the scheduler's and the display's
/// addresses, and each store's table (its address, and its shard or
/// database where it has its own); the scheduler's tile deadline, if not
/// its default.
pub struct Layout {
    pub scheduler: String,
    pub display: String,
    pub stores: Vec<String>,
    pub tile_deadline_ms: Option<u32>,
}

/// [`config_text`] with the nodes where `layout` puts them; `tail` goes
/// after `[clients]` (link shaping, `[launch]`).
#[allow(clippy::too_many_arguments)]
pub fn config_text_with(
    db: &Path,
    path: &Path,
    dir: &Path,
    layout: &Layout,
    clients: u32,
    cache_mb: f64,
    extra_clients: &str,
    tail: &str,
) -> String {
    let deadline = layout
        .tile_deadline_ms
        .map_or(String::new(), |ms| format!("tile_deadline_ms = {ms}\n"));
    let stores: String = layout
        .stores
        .iter()
        .map(|body| format!("[[stores]]\n{body}\n\n"))
        .collect();
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
address = "{scheduler}"
{deadline}
[display]
address = "{display}"
output = "{out}"

{stores}[clients]
count = {clients}
threads = 1
cache_mb = {cache_mb}
{extra_clients}

{tail}

[certs]
dir = "{certs}"
"#,
        db = db.display(),
        path = path.display(),
        out = dir.join("out").display(),
        certs = dir.join("certs").display(),
        scheduler = layout.scheduler,
        display = layout.display,
    )
}

/// `dray shard DB --of N --out OUT`, which must succeed.
pub fn shard(db: &Path, n: u32, out: &Path) {
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_dray"))
        .args([
            "shard",
            db.to_str().unwrap(),
            "--of",
            &n.to_string(),
            "--out",
        ])
        .arg(out)
        .output()
        .unwrap();
    assert!(o.status.success(), "dray shard: {o:?}");
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

/// Every frame the display wrote under `frames` (`frame-K.png`, and with
/// `render.depth_and_ids` its `.pfm` and `.primid`) against `dray render`'s
/// image of the config's K-th camera.
pub fn assert_saved_frames_equal_reference(cfg: &Config, frames: &Path) {
    let cameras = dray_actors::nodes::frame_cameras(cfg).unwrap();
    for (k, camera) in cameras.iter().enumerate() {
        let stem = frames.join(format!("frame-{k:05}"));
        let file = |ext: &str| stem.with_extension(ext);
        let (rgba, depth, primid) = reference(cfg, camera);
        let png =
            std::fs::read(file("png")).unwrap_or_else(|e| panic!("{}: {e}", file("png").display()));
        let (w, h, pixels) = dray_trace::image::decode_png(&png).unwrap();
        assert_eq!(
            (w, h),
            (cfg.render.width, cfg.render.height),
            "frame {k}: size"
        );
        assert!(pixels == rgba, "frame {k}: colours differ from dray render");
        if !cfg.render.depth_and_ids {
            continue;
        }
        let (_, _, d) = dray_trace::image::read_pfm(&file("pfm")).unwrap();
        assert!(
            d.len() == depth.len()
                && d.iter()
                    .zip(&depth)
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
            "frame {k}: depth differs from dray render"
        );
        let ids = dray_trace::image::read_u32(&file("primid")).unwrap();
        assert!(
            ids == primid,
            "frame {k}: triangle ids differ from dray render"
        );
    }
}

/// A cluster for a launcher to start (`tests/slurm.rs`, `tests/mpi.rs`):
/// a 20 k plant cut into 2 shards, 2 stores each reading its own, 2
/// clients, a walk of `frames`; every address `{host:0}:PORT` on free
/// ports, `launch` appended (e.g. a `[launch]` table). Writes
/// `dir/cluster.toml` and its certificates; returns the config's path.
pub fn launcher_cluster(dir: &Path, frames: u32, launch: &str) -> PathBuf {
    let db = plant_db(dir, 20_000);
    shard(&db, 2, &dir.join("shards"));
    let path = dir.join("path.toml");
    write_path(&db, &path, frames);
    let [p0, p1, p2, p3] = free_ports::<4>();
    let store = |port: u16, i: u32| {
        let shard = dir.join(format!("shards/shard-{i}"));
        format!(
            "address = \"{{host:0}}:{port}\"\ndatabase = \"{}\"",
            shard.display()
        )
    };
    let layout = Layout {
        scheduler: format!("{{host:0}}:{p0}"),
        display: format!("{{host:0}}:{p1}"),
        stores: vec![store(p2, 0), store(p3, 1)],
        tile_deadline_ms: None,
    };
    let text = config_text_with(&db, &path, dir, &layout, 2, 0.5, "", launch);
    let config = dir.join("cluster.toml");
    std::fs::write(&config, text).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_dray"))
        .args(["certs", "init"])
        .arg(dir.join("certs"))
        .arg("--config")
        .arg(&config)
        .output()
        .unwrap();
    assert!(out.status.success(), "dray certs init: {out:?}");
    config
}

/// Runs `cmd` to its end, or kills it after `limit` (naming `what`).
pub fn run_within(
    mut cmd: std::process::Command,
    limit: std::time::Duration,
    what: &str,
) -> std::process::Output {
    use std::sync::atomic::{AtomicBool, Ordering};
    let child = cmd
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("{what}: {e}"));
    let pid = child.id();
    let done = std::sync::Arc::new(AtomicBool::new(false));
    let watch = done.clone();
    let what_owned = what.to_string();
    std::thread::spawn(move || {
        let deadline = std::time::Instant::now() + limit;
        while std::time::Instant::now() < deadline {
            if watch.load(Ordering::Relaxed) {
                return;
            }
            std::thread::sleep(std::time::Duration::from_millis(100));
        }
        eprintln!("{what_owned}: still running after {limit:?}; killing it");
        let _ = std::process::Command::new("kill")
            .arg(pid.to_string())
            .status();
    });
    let out = child.wait_with_output().unwrap();
    done.store(true, Ordering::Relaxed);
    out
}
