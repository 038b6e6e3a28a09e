//! The runner end to end on the in-process engine: a 2 × 2 sweep on a tiny
//! plant, resuming an interrupted run, and the errors of bad files.

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

const MEASURED: [&str; 11] = [
    "fps",
    "frame_ms_p50",
    "frame_ms_p95",
    "frame_ms_max",
    "mrays_per_s",
    "stall_ms",
    "voxel_mb",
    "voxel_mb_raw",
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
        assert!((0.0..=1.0).contains(&value("cache_hit_rate")));
        assert!(value("wall_s") > 0.0);
    }

    // frames.csv: every frame of every run (4 frames each).
    let frames = csv_rows(&dir.join(FRAMES_CSV));
    let display_columns: Vec<&str> = dray_actors::display::CSV_HEADER.split(',').collect();
    assert_eq!(frames[0][..3], header[..3]);
    assert_eq!(frames[0][3..], display_columns[..]);
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
    // cannot run.
    let e = error_of("cluster.toml", "engine = \"cluster\"", "");
    assert!(e.contains("engine"), "{e}");
}
