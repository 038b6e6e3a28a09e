//! A database with one corrupt voxel (a flipped byte in `voxels.dray`,
//! in a voxel the walk shows): the run ends with an error naming the voxel
//! and the store, in one process and over processes; with
//! `clients.corrupt_voxel = "skip"` every frame completes and the voxel is
//! counted as missing.

mod common;

use common::*;
use dray_actors::nodes::{frame_cameras, sim, RunOptions};
use dray_actors::settings::{kernel_camera, kernel_settings, wire_settings};
use dray_scene::db::manifest::VOXELS_FILE;
use dray_scene::db::Database;
use dray_trace::accel::{RecordingSource, ResidentSource, TopLevel};
use dray_trace::render::{render, Isa};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// A walk over a plant whose database has one voxel, shown by the first
/// frame, with its middle byte flipped; returns the directory, the config
/// path and the voxel.
fn corrupt_setup(extra_clients: &str) -> (tempfile::TempDir, PathBuf, u32) {
    let dir = tempfile::tempdir().unwrap();
    let db = plant_db(dir.path(), 30_000);
    let path = dir.path().join("walk.toml");
    write_path(&db, &path, 4);
    let text = config_text(&db, &path, dir.path(), 2, 64.0, extra_clients, "");
    let (config_path, cfg) = config(dir.path(), &text);
    let id = shown_voxel(&cfg);
    flip_middle_byte(&db, id);
    (dir, config_path, id)
}

/// A voxel the first frame's rays enter.
fn shown_voxel(cfg: &dray_config::Config) -> u32 {
    let db = Database::open(&cfg.scene.database).unwrap();
    let top = TopLevel::from_manifest(&db.manifest);
    let source = ResidentSource::load(&db).unwrap();
    let mut rec = RecordingSource::new(&source, db.manifest.voxels.len());
    let settings = kernel_settings(
        &wire_settings(&cfg.render),
        db.manifest.model_bounds.diagonal(),
        1,
        Isa::detect(),
    );
    let camera = frame_cameras(cfg).unwrap()[0];
    let cam = kernel_camera(&camera, cfg.render.width, cfg.render.height);
    render(&top, &rec, &cam, &settings).unwrap();
    let entered = rec.take();
    // The middle one: not the first or last of the file.
    entered[entered.len() / 2]
}

fn flip_middle_byte(db: &Path, id: u32) {
    let entry = Database::open(db).unwrap().manifest.voxels[id as usize];
    let at = entry.offset + entry.compressed_bytes / 2;
    let mut f = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(db.join(VOXELS_FILE))
        .unwrap();
    let mut b = [0u8];
    f.seek(SeekFrom::Start(at)).unwrap();
    f.read_exact(&mut b).unwrap();
    f.seek(SeekFrom::Start(at)).unwrap();
    f.write_all(&[b[0] ^ 0xff]).unwrap();
}

/// `sim`, which must end: a run that hangs fails the test after a
/// generous bound instead of hanging it.
fn sim_to_end(
    cfg: &dray_config::Config,
) -> Result<dray_actors::nodes::RunSummary, dray_actors::nodes::ClusterError> {
    rt().block_on(async {
        tokio::time::timeout(Duration::from_secs(120), sim(cfg, &RunOptions::default()))
            .await
            .expect("the run with a corrupt voxel never ended")
    })
}

#[test]
fn sim_with_a_corrupt_voxel_ends_with_an_error_naming_it() {
    let (dir, config_path, id) = corrupt_setup("");
    let cfg = dray_config::Config::load(&config_path).unwrap();
    let err = sim_to_end(&cfg).expect_err("a run with a corrupt voxel succeeded");
    let text = err.to_string();
    assert!(text.contains(&format!("voxel {id} ")), "{text}");
    assert!(text.contains("store-"), "{text}");
    assert!(text.contains("checksum mismatch"), "{text}");
    drop(dir);
}

#[test]
fn sim_skipping_a_corrupt_voxel_completes_every_frame_and_counts_it() {
    let (dir, config_path, id) = corrupt_setup("corrupt_voxel = \"skip\"");
    let cfg = dray_config::Config::load(&config_path).unwrap();
    let run = sim_to_end(&cfg).expect("the run skipping a corrupt voxel failed");
    let d = &run.display;
    assert!(d.complete, "{}", d.print_text());
    assert_eq!(d.frames.len(), 4);
    assert_eq!(
        d.voxels_missing.iter().copied().collect::<Vec<_>>(),
        [id],
        "{}",
        d.print_text()
    );
    assert!(
        d.print_text().contains("voxels missing"),
        "{}",
        d.print_text()
    );
    assert_eq!(d.to_json()["voxels_missing"], serde_json::json!([id]));
    let lost: u64 = run.clients.iter().map(|c| c.voxels_lost).sum();
    assert!(lost >= 1, "{:?}", run.clients);
    drop(dir);
}

#[test]
fn dray_cluster_with_a_corrupt_voxel_exits_with_an_error_naming_it() {
    let (dir, config_path, id) = corrupt_setup("");
    let mut child = Command::new(env!("CARGO_BIN_EXE_dray"))
        .args(["cluster", config_path.to_str().unwrap()])
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stderr = child.stderr.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = stderr.read_to_string(&mut s);
        s
    });
    let deadline = Instant::now() + Duration::from_secs(180);
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if Instant::now() > deadline {
            let _ = Command::new("kill").arg(child.id().to_string()).status();
            let _ = child.wait();
            panic!("dray cluster with a corrupt voxel never ended");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let stderr = reader.join().unwrap();
    assert!(!status.success(), "{stderr}");
    let named = stderr
        .lines()
        .any(|l| l.contains(&format!("voxel {id} cannot be served intact by store-")));
    assert!(named, "{stderr}");
    drop(dir);
}
