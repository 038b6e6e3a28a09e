//! The runner end to end on the in-process engine: a 2 × 2 sweep on a tiny
//! plant, a sweep of the walkthrough's frames with a plot over the frames,
//! resuming an interrupted run, and the errors of bad files.

use dray_experiments::{run, ExperimentError, Options, FRAMES_CSV, POINTS_CSV};
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).to_path_buf()
}

fn tiny() -> PathBuf {
    repo().join("tiny.toml")
}

fn options(tmp: &Path) -> Options {
    Options {
        out: Some(tmp.join("out")),
        models: tmp.join("models"),
        ..Options::default()
    }
}

fn csv_rows(path: &Path) -> Vec<Vec<String>> {
    let mut r = csv::ReaderBuilder::new()
        .has_headers(false)
        .from_path(path)
        .unwrap();
    r.records()
        .map(|rec| rec.unwrap().iter().map(str::to_string).collect())
        .collect()
}

/// (swept values, repeat) of every row of points.csv.
fn runs(points_csv: &Path) -> BTreeSet<Vec<String>> {
    csv_rows(points_csv)
        .into_iter()
        .skip(1)
        .map(|row| row[..3].to_vec())
        .collect()
}

const MEASURED: [&str; 16] = [
    "fps",
    "frame_ms_p50",
    "frame_ms_p95",
    "frame_ms_max",
    "mrays_per_s",
    "stall_ms",
    "voxel_mb",
    "voxel_mb_raw",
    "link_mb_client_store",
    "link_mb_client_scheduler",
    "link_mb_display",
    "link_mb_store_uplink",
    "link_mb_client_downlink",
    "cache_hit_rate",
    "tiles_reassigned",
    "wall_s",
];

#[test]
fn a_sweep_writes_every_output() {
    let tmp = tempfile::tempdir().unwrap();
    let report = run(&tiny(), &options(tmp.path())).unwrap();
    let dir = tmp.path().join("out");
    assert_eq!(report.dir, dir);
    assert_eq!((report.runs_total, report.runs_done), (8, 8));
    assert!(!report.interrupted);

    // points.csv: the swept keys (in key order), repeat, the measures.
    let points = csv_rows(&dir.join(POINTS_CSV));
    let mut header = vec![
        "clients.miss_mode",
        "links.client_store.latency_ms",
        "repeat",
    ];
    header.extend(MEASURED);
    assert_eq!(points[0], header);
    assert_eq!(points.len(), 1 + 8);
    let mut expected = BTreeSet::new();
    for mode in ["suspend", "block"] {
        for latency in ["0", "2"] {
            for repeat in ["0", "1"] {
                expected.insert(vec![
                    mode.to_string(),
                    latency.to_string(),
                    repeat.to_string(),
                ]);
            }
        }
    }
    assert_eq!(runs(&dir.join(POINTS_CSV)), expected);
    for row in &points[1..] {
        assert_eq!(row.len(), header.len());
        let value = |name: &str| -> f64 {
            let i = header.iter().position(|h| *h == name).unwrap();
            row[i]
                .parse()
                .unwrap_or_else(|_| panic!("{name} = {:?}", row[i]))
        };
        assert!(value("fps") > 0.0);
        assert!(value("frame_ms_p50") <= value("frame_ms_p95"));
        assert!(value("frame_ms_p95") <= value("frame_ms_max"));
        assert!(value("mrays_per_s") > 0.0);
        // Cold caches: every run fetches, and decompressed is larger.
        assert!(value("voxel_mb") > 0.0);
        assert!(value("voxel_mb_raw") > value("voxel_mb"));
        // Links carry the voxels with their envelopes and the requests for
        // them, the tiles and their pixels, and the frames' messages.
        assert!(value("link_mb_client_store") > value("voxel_mb"));
        assert!(value("link_mb_store_uplink") > value("voxel_mb"));
        assert!(value("link_mb_client_store") > value("link_mb_store_uplink"));
        assert!(value("link_mb_client_downlink") > value("link_mb_store_uplink"));
        assert!(value("link_mb_client_scheduler") > 0.0);
        assert!(value("link_mb_display") > 0.0);
        assert!((0.0..=1.0).contains(&value("cache_hit_rate")));
        assert!(value("wall_s") > 0.0);
    }

    // frames.csv: every frame of every run (4 frames each): the display's
    // columns, then the per-frame rates.
    let frames = csv_rows(&dir.join(FRAMES_CSV));
    let mut frame_columns: Vec<&str> = dray_actors::display::CSV_HEADER.split(',').collect();
    frame_columns.extend([
        "frame_ms_window",
        "fps_window",
        "voxel_mb_per_s",
        "voxel_mb_raw_per_s",
    ]);
    assert_eq!(frames[0][..3], header[..3]);
    assert_eq!(frames[0][3..], frame_columns[..]);
    assert_eq!(frames.len(), 1 + 8 * 4);
    assert!(frames[1..].iter().all(|r| r.len() == frames[0].len()));

    // Each run's config and the display's metrics.
    let run0 = dir.join("runs/p000-r0");
    assert!(run0.join("config.toml").is_file());
    assert!(run0.join("metrics.csv").is_file());
    dray_config::Config::load(&run0.join("config.toml")).unwrap();

    // The plot, as SVG and as PNG.
    let svg = std::fs::read_to_string(dir.join("plot1-fps-by-latency_ms.svg")).unwrap();
    assert!(svg.starts_with("<svg"), "{}", &svg[..40]);
    assert!(svg.trim_end().ends_with("</svg>"));
    assert!(svg.contains("clients.miss_mode=suspend"));
    let png = std::fs::File::open(dir.join("plot1-fps-by-latency_ms.png")).unwrap();
    let mut reader = png::Decoder::new(png).read_info().unwrap();
    let mut pixels = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut pixels).unwrap();
    assert_eq!((info.width, info.height), (900, 560));
    // Not a blank image: the lines and the text drew something dark.
    assert!(pixels.iter().any(|&b| b < 64));

    let summary = std::fs::read_to_string(dir.join("summary.md")).unwrap();
    for part in [
        "# tiny",
        "## Medians",
        "plot1-fps-by-latency_ms.png",
        "| commit |",
        "| machine |",
    ] {
        assert!(
            summary.contains(part),
            "summary.md lacks {part}:\n{summary}"
        );
    }
    assert!(dir.join("experiment.toml").is_file());
    assert!(dir.join("walk.toml").is_file());
}

/// Writes an experiment file in `dir` from `body`, based on
/// `config/examples/local.toml` and the tiny plant at 64 × 48 pixels.
fn tiny_experiment(dir: &Path, name: &str, body: &str) -> PathBuf {
    let file = dir.join(format!("{name}.toml"));
    let config = repo().join("../config/examples/local.toml");
    let text = format!(
        "name = {name:?}\nconfig = {:?}\nengine = \"sim\"\n\
         [model]\ngenerate = \"plant\"\ntriangles = 20_000\nseed = 3\n\
         [set]\n\"clients.count\" = 2\n\"clients.threads\" = 1\n\"clients.cache_mb\" = 16\n\
         \"render.width\" = 64\n\"render.height\" = 48\n\"render.shadows\" = false\n\
         \"render.reflection_depth\" = 0\n{body}",
        config.display().to_string()
    );
    std::fs::write(&file, text).unwrap();
    file
}

fn assert_valid_plot(dir: &Path, stem: &str, texts: &[&str]) {
    let svg = std::fs::read_to_string(dir.join(format!("{stem}.svg"))).unwrap();
    assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
    for text in texts {
        assert!(svg.contains(text), "{stem}.svg lacks {text:?}");
    }
    let png = std::fs::File::open(dir.join(format!("{stem}.png"))).unwrap();
    let mut reader = png::Decoder::new(png).read_info().unwrap();
    let mut pixels = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut pixels).unwrap();
    assert_eq!((info.width, info.height), (900, 560));
    assert!(pixels.iter().any(|&b| b < 64));
}

#[test]
fn a_walk_frames_sweep_and_a_plot_over_the_frames() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tiny_experiment(
        tmp.path(),
        "walks",
        "[sweep]\n\"walk.frames\" = [6, 3]\n\
         [[plot]]\nx = \"frame\"\ny = [\"fps_window\", \"voxel_mb_raw_per_s\"]\n\
         [[plot]]\nx = \"walk.frames\"\ny = \"voxel_mb_raw\"\n",
    );
    let report = run(&file, &options(tmp.path())).unwrap();
    assert_eq!((report.runs_total, report.runs_done), (2, 2));
    let dir = tmp.path().join("out");

    // One walk per point, with the point's frames, and no walk.toml.
    for n in [6, 3] {
        let walk = dir.join(format!("walks/frames-{n}.toml"));
        let path = dray_actors::display::CameraPath::load(&walk).unwrap();
        assert_eq!(path.frames, n);
        let config = dir.join(format!(
            "runs/p00{}-r0/config.toml",
            if n == 6 { 0 } else { 1 }
        ));
        let config = dray_config::Config::load(&config).unwrap();
        assert_eq!(config.render.camera_path.as_deref(), Some(walk.as_path()));
    }
    assert!(!dir.join("walk.toml").exists());

    // Every frame has its decompressed bytes, and the run's sum is the
    // point's voxel_mb_raw.
    let frames = csv_rows(&dir.join(FRAMES_CSV));
    assert_eq!(frames.len(), 1 + 6 + 3);
    let col = |name: &str| frames[0].iter().position(|h| h == name).unwrap();
    let points = csv_rows(&dir.join(POINTS_CSV));
    let pcol = |name: &str| points[0].iter().position(|h| h == name).unwrap();
    for point in &points[1..] {
        let mine = frames[1..]
            .iter()
            .filter(|f| f[col("walk.frames")] == point[pcol("walk.frames")]);
        let raw: u64 = mine
            .clone()
            .map(|f| f[col("bytes_raw")].parse::<u64>().unwrap())
            .sum();
        let fetched: u64 = mine
            .map(|f| f[col("bytes_fetched")].parse::<u64>().unwrap())
            .sum();
        assert!(raw > fetched, "decompressed {raw} <= compressed {fetched}");
        let mb_raw: f64 = point[pcol("voxel_mb_raw")].parse().unwrap();
        assert!(
            (mb_raw - raw as f64 / 1e6).abs() < 1e-5,
            "{mb_raw} against {raw}"
        );
    }
    // The per-frame rates are taken over the 5 frames around each frame
    // of its run.
    for point in &points[1..] {
        let mine: Vec<&Vec<String>> = frames[1..]
            .iter()
            .filter(|f| f[col("walk.frames")] == point[pcol("walk.frames")])
            .collect();
        let num = |f: &Vec<String>, c: &str| f[col(c)].parse::<f64>().unwrap();
        for (i, f) in mine.iter().enumerate() {
            let around = &mine[i.saturating_sub(2)..(i + 3).min(mine.len())];
            let ms: f64 = around.iter().map(|g| num(g, "frame_ms")).sum();
            let raw: f64 = around.iter().map(|g| num(g, "bytes_raw")).sum();
            let expected = raw / 1e6 / (ms / 1e3);
            let rate = num(f, "voxel_mb_raw_per_s");
            assert!(
                (rate - expected).abs() <= 1e-3 * expected.max(1.0),
                "{rate} against {expected}"
            );
            let fps = num(f, "fps_window");
            assert!((fps - 1e3 * around.len() as f64 / ms).abs() <= 1e-3 * fps);
        }
    }

    // Two units: the rate on a right-hand axis.
    assert_valid_plot(
        &dir,
        "plot1-fps_window-voxel_mb_raw_per_s-by-frame",
        &[
            "fps_window (frames/s)",
            "voxel_mb_raw_per_s (MB/s)",
            "walk.frames=6",
        ],
    );
    assert_valid_plot(&dir, "plot2-voxel_mb_raw-by-frames", &["faster camera"]);
    let summary = std::fs::read_to_string(dir.join("summary.md")).unwrap();
    assert!(summary.contains("walks/"), "{summary}");
}

#[test]
fn resume_runs_only_the_missing_points() {
    let tmp = tempfile::tempdir().unwrap();
    let opts = options(tmp.path());
    run(&tiny(), &opts).unwrap();
    let dir = tmp.path().join("out");
    let points_csv = dir.join(POINTS_CSV);
    let uninterrupted = runs(&points_csv);

    // An interrupted run: 3 runs recorded, a fourth row cut short, and
    // frames.csv holding the frames of runs not recorded.
    let text = std::fs::read_to_string(&points_csv).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    let kept = format!("{}\n{}", lines[..4].join("\n"), &lines[4][..10]);
    std::fs::write(&points_csv, kept).unwrap();

    let report = run(
        &tiny(),
        &Options {
            out: None,
            resume: Some(dir.clone()),
            ..opts
        },
    )
    .unwrap();
    assert_eq!((report.runs_resumed, report.runs_done), (3, 5));
    assert_eq!(runs(&points_csv), uninterrupted);
    assert_eq!(csv_rows(&points_csv).len(), 1 + 8);
    // Each run's frames once.
    let frames = csv_rows(&dir.join(FRAMES_CSV));
    assert_eq!(frames.len(), 1 + 8 * 4);
    let frame_runs: BTreeSet<Vec<String>> = frames[1..].iter().map(|r| r[..3].to_vec()).collect();
    assert_eq!(frame_runs, uninterrupted);

    // Nothing left to do.
    let again = run(
        &tiny(),
        &Options {
            out: None,
            resume: Some(dir.clone()),
            models: tmp.path().join("models"),
            ..Options::default()
        },
    )
    .unwrap();
    assert_eq!((again.runs_resumed, again.runs_done), (8, 0));
}

/// Writes an experiment based on `config/examples/local.toml` with `body`
/// after its first lines, runs it, and returns the error.
fn error_of(name: &str, head: &str, body: &str) -> String {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join(name);
    let config = repo().join("../config/examples/local.toml");
    let text = format!(
        "name = \"bad\"\nconfig = {:?}\n{head}\n[model]\ngenerate = \"plant\"\ntriangles = 20_000\n{body}\n",
        config.display().to_string()
    );
    std::fs::write(&file, text).unwrap();
    let err: ExperimentError = run(&file, &options(tmp.path())).unwrap_err();
    // Nothing was made for a file with a mistake.
    assert!(!tmp.path().join("out").exists());
    assert!(!tmp.path().join("models").exists());
    let message = err.to_string();
    assert!(message.contains(name), "{message}");
    message
}

#[test]
fn a_bad_key_is_named() {
    let e = error_of(
        "badkey.toml",
        "engine = \"sim\"",
        "[set]\n\"clients.thread\" = 2\n",
    );
    assert!(e.contains("[set] clients.thread"), "{e}");
    assert!(e.contains("unknown field `thread`"), "{e}");

    let e = error_of("badtop.toml", "engine = \"sim\"\nrepeats = 3", "");
    assert!(e.contains("repeats"), "{e}");

    let e = error_of(
        "badplot.toml",
        "engine = \"sim\"",
        "[sweep]\n\"clients.count\" = [1, 2]\n[[plot]]\nx = \"clients.count\"\ny = \"speed\"\n",
    );
    assert!(e.contains("plot[0].y"), "{e}");

    // A plot over the frames draws columns of frames.csv.
    let e = error_of(
        "badframes.toml",
        "engine = \"sim\"",
        "[[plot]]\nx = \"frame\"\ny = [\"fps\", \"voxel_mb\"]\n",
    );
    assert!(e.contains("plot[0].y") && e.contains("\"voxel_mb\""), "{e}");
    assert!(e.contains("frames.csv"), "{e}");

    let e = error_of(
        "threeunits.toml",
        "engine = \"sim\"",
        "[[plot]]\nx = \"frame\"\ny = [\"fps\", \"stall_ms\", \"bytes_raw\"]\n",
    );
    assert!(e.contains("plot[0].y") && e.contains("3 units"), "{e}");
}

#[test]
fn a_bad_value_is_named() {
    let e = error_of(
        "badvalue.toml",
        "engine = \"sim\"",
        "[sweep]\n\"clients.cache_mb\" = [16, 0]\n",
    );
    assert!(e.contains("[sweep] clients.cache_mb = 0"), "{e}");
    assert!(e.contains("a cache must hold at least one voxel"), "{e}");

    let e = error_of(
        "badtype.toml",
        "engine = \"sim\"",
        "[set]\n\"clients.count\" = \"two\"\n",
    );
    assert!(e.contains("[set] clients.count"), "{e}");

    let e = error_of("badrepeat.toml", "engine = \"sim\"\nrepeat = 0", "");
    assert!(e.contains("repeat: 0 is not in"), "{e}");

    let e = error_of(
        "badframes.toml",
        "engine = \"sim\"",
        "[sweep]\n\"walk.frames\" = [10, 0]\n",
    );
    assert!(e.contains("[sweep] walk.frames = 0"), "{e}");
    // The sweep gives the walkthrough's frames: [walk] cannot as well.
    let e = error_of(
        "twoframes.toml",
        "engine = \"sim\"",
        "[walk]\nframes = 10\n[sweep]\n\"walk.frames\" = [10, 5]\n",
    );
    assert!(e.contains("walk.frames") && e.contains("[sweep]"), "{e}");
}

#[test]
fn a_missing_model_is_named() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("nomodel.toml");
    let config = repo().join("../config/examples/local.toml");
    let text = format!(
        "name = \"bad\"\nconfig = {:?}\nengine = \"sim\"\n[model]\ndatabase = \"nowhere.vdb\"\n",
        config.display().to_string()
    );
    std::fs::write(&file, text).unwrap();
    let e = run(&file, &options(tmp.path())).unwrap_err().to_string();
    assert!(
        e.contains("nomodel.toml") && e.contains("model.database"),
        "{e}"
    );
    assert!(e.contains("nowhere.vdb"), "{e}");
    assert!(!tmp.path().join("out").exists());
}

#[test]
fn an_unknown_engine_is_named() {
    let e = error_of("engine.toml", "engine = \"gpu\"", "");
    assert!(e.contains("engine") && e.contains("gpu"), "{e}");
    // The cluster engine starts dray processes: without the binary, it
    // cannot run, swept or not.
    let e = error_of("cluster.toml", "engine = \"cluster\"", "");
    assert!(e.contains("engine"), "{e}");
    let swept = "[walk]\nframes = 2\n[sweep]\nengine = [\"sim\", \"cluster\"]";
    let e = error_of("swept.toml", "engine = \"sim\"", swept);
    assert!(e.contains("engine") && e.contains("cluster"), "{e}");
    let e = error_of(
        "gpu.toml",
        "engine = \"sim\"",
        "[walk]\nframes = 2\n[sweep]\nengine = [\"sim\", \"gpu\"]",
    );
    assert!(e.contains("[sweep] engine") && e.contains("gpu"), "{e}");
}

/// The engine swept like a config key: the same frames from the cluster
/// in this process and from one process with the whole model loaded.
#[test]
fn the_engine_can_be_swept() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tiny_experiment(
        tmp.path(),
        "engines",
        "[walk]\nframes = 3\n[sweep]\nengine = [\"sim\", \"render\"]\n\
         \"clients.max_tiles_ahead\" = [1, 8]\n\
         [[plot]]\nx = \"clients.max_tiles_ahead\"\ny = \"fps\"\nseries = \"engine\"\n",
    );
    let report = run(&file, &options(tmp.path())).unwrap();
    assert_eq!(report.runs_done, 4);
    let rows = csv_rows(&report.dir.join(POINTS_CSV));
    let header = &rows[0];
    let col = |n: &str| header.iter().position(|h| h == n).unwrap();
    let mut engines = BTreeSet::new();
    for row in &rows[1..] {
        let value = |n: &str| row[col(n)].parse::<f64>().unwrap();
        assert!(value("fps") > 0.0 && value("mrays_per_s") > 0.0);
        engines.insert(row[col("engine")].clone());
        if row[col("engine")] == "render" {
            // Every voxel is loaded: nothing fetched, no link crossed.
            assert_eq!(value("voxel_mb"), 0.0);
            assert_eq!(value("link_mb_client_store"), 0.0);
        } else {
            assert!(value("voxel_mb") > 0.0);
        }
    }
    assert_eq!(engines, BTreeSet::from(["render".into(), "sim".into()]));
    // Both engines traced the same rays for the same frames.
    let frames = csv_rows(&report.dir.join(FRAMES_CSV));
    let fcol = |n: &str| frames[0].iter().position(|h| h == n).unwrap();
    let rays = |engine: &str| -> Vec<String> {
        frames[1..]
            .iter()
            .filter(|f| f[fcol("engine")] == engine && f[fcol("clients.max_tiles_ahead")] == "1")
            .map(|f| f[fcol("rays")].clone())
            .collect()
    };
    assert_eq!(rays("sim").len(), 3);
    assert_eq!(rays("sim"), rays("render"));
    assert_valid_plot(
        &report.dir,
        "plot1-fps-by-max_tiles_ahead",
        &["render", "sim"],
    );
}

/// The virtual engine with a fixed cost model: twice the same experiment
/// gives the same `points.csv` in every measured column but `wall_s`; a
/// labelled sweep value shows its label and configures its value; a log
/// axis draws.
#[test]
fn a_virtual_experiment_repeats_exactly() {
    let tmp = tempfile::tempdir().unwrap();
    let stores = |n: u32| -> String {
        let list: Vec<String> = (0..n)
            .map(|i| {
                format!(
                    "{{ address = \"127.0.0.1:{}\", shard = \"{i}/{n}\" }}",
                    7410 + i
                )
            })
            .collect();
        format!("{{ label = {n}, value = [{}] }}", list.join(", "))
    };
    let file = tiny_experiment(
        tmp.path(),
        "virtual",
        &format!(
            "\"clients.speed\" = 0.5\n\
             \"links.client_store.latency_ms\" = 2.0\n\
             [walk]\nframes = 3\n\
             [virtual]\ncost = {{ ns_per_tile = 5000.0, ns_per_primary_ray = 200.0, \
             ns_per_secondary_ray = 100.0, ns_per_voxel_visit = 300.0, ns_per_decoded_byte = 2.0 }}\n\
             [sweep]\n\"clients.max_tiles_ahead\" = [1, 8]\nstores = [{}, {}]\n\
             [[plot]]\nx = \"clients.max_tiles_ahead\"\nx_scale = \"log\"\ny = \"fps\"\n\
             series = \"stores\"\n",
            stores(1),
            stores(2)
        ),
    )
    .to_path_buf();
    let text = std::fs::read_to_string(&file)
        .unwrap()
        .replace("engine = \"sim\"", "engine = \"virtual\"");
    std::fs::write(&file, text).unwrap();
    let measured = |out: &str| -> Vec<Vec<String>> {
        let opts = Options {
            out: Some(tmp.path().join(out)),
            models: tmp.path().join("models"),
            ..Options::default()
        };
        let report = run(&file, &opts).unwrap();
        assert_eq!(report.runs_done, 4);
        assert_valid_plot(
            &report.dir,
            "plot1-fps-by-max_tiles_ahead",
            &["stores=1", "stores=2"],
        );
        let rows = csv_rows(&report.dir.join(POINTS_CSV));
        let wall = rows[0].iter().position(|h| h == "wall_s").unwrap();
        // The stores are shown by their label.
        let stores = rows[0].iter().position(|h| h == "stores").unwrap();
        assert_eq!(
            rows[1..]
                .iter()
                .map(|r| r[stores].as_str())
                .collect::<BTreeSet<_>>(),
            BTreeSet::from(["1", "2"])
        );
        rows.into_iter()
            .map(|mut r| {
                r.remove(wall);
                r
            })
            .collect()
    };
    let first = measured("a");
    let second = measured("b");
    assert_eq!(first, second);
    // Both stores served: the shards reached the config.
    let fps = first[0].iter().position(|h| h == "fps").unwrap();
    assert!(first[1..]
        .iter()
        .all(|r| r[fps].parse::<f64>().unwrap() > 0.0));
}
