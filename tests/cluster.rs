//! The cluster in one process (the in-process transport): frames equal
//! `dray render` pixel for pixel whatever the number of clients, the cache
//! budget and the link shaping; 8 clients with tiny caches and 5 ms links
//! finish a walkthrough; config mistakes name their key.

mod common;

use common::*;
use dray_actors::nodes::{frame_cameras, sim, RunOptions};

fn check_frames(cfg: &dray_config::Config, clients: u32) {
    let opts = RunOptions {
        clients: Some(clients),
        keep_frames: true,
        ..RunOptions::default()
    };
    let run = rt().block_on(sim(cfg, &opts)).unwrap();
    let cameras = frame_cameras(cfg).unwrap();
    assert_eq!(run.display.images.len(), cameras.len());
    for (img, cam) in run.display.images.iter().zip(&cameras) {
        let (rgba, depth, primid) = reference(cfg, cam);
        let what = format!("frame {} with {clients} clients", img.frame);
        assert_eq!(
            img.primid.as_ref().unwrap(),
            &primid,
            "{what}: primitive ids"
        );
        let d = img.depth.as_ref().unwrap();
        assert!(
            d.iter()
                .zip(&depth)
                .all(|(a, b)| a.to_bits() == b.to_bits()),
            "{what}: depth"
        );
        assert!(img.rgba == rgba, "{what}: colors");
    }
}

#[test]
fn frames_equal_dray_render_for_any_clients_cache_and_shaping() {
    let dir = tempfile::tempdir().unwrap();
    let db = plant_db(dir.path(), 30_000);
    let path = dir.path().join("walk.toml");
    write_path(&db, &path, 3);
    // Everything fits; unshaped.
    let (_, big) = config(
        dir.path(),
        &config_text(&db, &path, dir.path(), 2, 256.0, "", ""),
    );
    for clients in [1, 2, 8] {
        check_frames(&big, clients);
    }
    // Preloaded caches, tiles sent back in batches of 4.
    let (_, batched) = config(
        dir.path(),
        &config_text(
            &db,
            &path,
            dir.path(),
            2,
            256.0,
            "tiles_ahead = 8\npreload = true",
            "",
        ),
    );
    check_frames(&batched, 2);
    // A cache of a few voxels (each is some tens of kB), shaped links, and
    // the block mode.
    let links = "[links.client_store]\nlatency_ms = 2.0\nbandwidth_mbps = 200.0\n[links.client_scheduler]\nlatency_ms = 1.0\n";
    for extra in [
        "miss_mode = \"suspend\"",
        "miss_mode = \"block\"",
        "miss_mode = \"suspend\"\ntiles_ahead = 8",
    ] {
        let (_, tiny) = config(
            dir.path(),
            &config_text(&db, &path, dir.path(), 2, 0.15, extra, links),
        );
        check_frames(&tiny, 2);
    }
}

#[test]
fn eight_clients_with_tiny_caches_and_5ms_links_finish_a_walkthrough() {
    let dir = tempfile::tempdir().unwrap();
    let db = plant_db(dir.path(), 30_000);
    let path = dir.path().join("walk.toml");
    write_path(&db, &path, 6);
    let links = "[links.client_store]\nlatency_ms = 5.0\n[links.client_scheduler]\nlatency_ms = 5.0\n[links.display]\nlatency_ms = 5.0\n";
    let (_, cfg) = config(
        dir.path(),
        &config_text(&db, &path, dir.path(), 8, 0.1, "", links),
    );
    let run = rt().block_on(sim(&cfg, &RunOptions::default())).unwrap();
    assert_eq!(run.display.frames.len(), 6);
    for m in &run.display.frames {
        assert_eq!(
            m.tiles as usize,
            (96usize / 16) * (64 / 16),
            "frame {}",
            m.frame
        );
    }
    // The caches were too small for the walk: voxels were evicted and
    // fetched again.
    assert!(run.clients.iter().map(|c| c.evicted).sum::<u64>() > 0);
    // Frames and metrics were written.
    let csv = std::fs::read_to_string(dir.path().join("out/metrics.csv")).unwrap();
    assert_eq!(csv.lines().count(), 7, "{csv}");
    assert!(dir.path().join("out/frames/frame-00005.png").exists());
}

/// With `render.samples = 4` each camera of the walk is rendered as four
/// frames (samples 0 to 3) and the display saves their mean: the PNG, the
/// depth and the ids of every camera equal, byte for byte, what `dray
/// render --spp 4` writes for that camera.
#[test]
fn a_walkthrough_with_samples_saves_dray_render_spp_images() {
    let dir = tempfile::tempdir().unwrap();
    let db = plant_db(dir.path(), 30_000);
    let path = dir.path().join("walk.toml");
    write_path(&db, &path, 3);
    let text = config_text(&db, &path, dir.path(), 2, 0.15, "", "");
    let text = text.replacen("tile_size = 16\n", "tile_size = 16\nsamples = 4\n", 1);
    let (_, cfg) = config(dir.path(), &text);
    assert_eq!(cfg.render.samples, 4);
    let run = rt().block_on(sim(&cfg, &RunOptions::default())).unwrap();
    let cameras = frame_cameras(&cfg).unwrap();
    assert_eq!(cameras.len(), 3);
    assert!(run.display.complete, "{:?}", run.display.stopped_early);
    assert_eq!(run.display.frames.len(), 12, "a metrics row per sample");
    let csv = std::fs::read_to_string(dir.path().join("out/metrics.csv")).unwrap();
    assert_eq!(csv.lines().count(), 1 + 12, "{csv}");
    let frames = dir.path().join("out/frames");
    let mut saved: Vec<String> = std::fs::read_dir(&frames)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    saved.sort();
    let mut expected: Vec<String> = (0..3)
        .flat_map(|k| ["png", "pfm", "primid"].map(|ext| format!("frame-{k:05}.{ext}")))
        .collect();
    expected.sort();
    assert_eq!(saved, expected, "one image per camera");
    let xyz = |v: [f32; 3]| format!("{},{},{}", v[0], v[1], v[2]);
    for (k, c) in cameras.iter().enumerate() {
        let stem = dir.path().join(format!("render-{k}"));
        let file = |ext: &str| stem.with_extension(ext).display().to_string();
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_dray"))
            .args(["render", &db.display().to_string()])
            .args([
                "--eye",
                &xyz(c.eye),
                "--look",
                &xyz(c.look),
                "--up",
                &xyz(c.up),
            ])
            .args(["--fov", &c.fov_y_deg.to_string()])
            .args(["--width", "96", "--height", "64", "--shadows"])
            .args(["--reflections", "1", "--threads", "1", "--spp", "4"])
            .args(["--out", &file("png"), "--depth-out", &file("pfm")])
            .args(["--primid-out", &file("primid")])
            .output()
            .unwrap();
        assert!(out.status.success(), "{out:?}");
        for ext in ["png", "pfm", "primid"] {
            let cluster = std::fs::read(frames.join(format!("frame-{k:05}.{ext}"))).unwrap();
            let render = std::fs::read(file(ext)).unwrap();
            assert!(cluster == render, "camera {k}: the .{ext} files differ");
        }
        // Four samples are not the centres' image: the edges are smoothed.
        let (rgba, _, _) = reference(&cfg, c);
        let (_, _, png) =
            dray_trace::image::decode_png(&std::fs::read(file("png")).unwrap()).unwrap();
        assert!(png != rgba, "camera {k}: the samples changed nothing");
    }
}

#[test]
fn config_mistakes_stop_startup_naming_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nothing-here.vdb");
    let path = dir.path().join("walk.toml");
    std::fs::write(
        &path,
        "frames = 2\n[[keyframe]]\neye = [0.0, 0.0, -5.0]\nlook = [0.0, 0.0, 0.0]\n[[keyframe]]\neye = [0.0, 1.0, -5.0]\nlook = [0.0, 0.0, 0.0]\n",
    )
    .unwrap();
    let (_, cfg) = config(
        dir.path(),
        &config_text(&missing, &path, dir.path(), 1, 16.0, "", ""),
    );
    let err = rt()
        .block_on(sim(&cfg, &RunOptions::default()))
        .unwrap_err()
        .to_string();
    assert!(err.contains("scene.database"), "{err}");
    assert!(err.contains("nothing-here.vdb"), "{err}");
    // A bad address is refused when the config is read.
    let text = config_text(&missing, &path, dir.path(), 1, 16.0, "", "").replacen(
        "address = \"127.0.0.1:",
        "address = \"127.0.0.1:x",
        1,
    );
    let err = dray_config::Config::parse(&text).unwrap_err().to_string();
    assert!(err.contains("scheduler.address"), "{err}");
}
