//! A whole cluster started by a real Slurm: `deploy/slurm/dray.sbatch` runs
//! every node as one task of one `srun` step, each taking its node from
//! `SLURM_PROCID` and its hosts from the step's node list (`{host:0}`),
//! two stores serving shards made by `dray shard`; every frame equals
//! `dray render`'s. A step with the wrong number of tasks fails naming the
//! counts. Needs a running Slurm (`deploy/slurm/local-slurm start`); where
//! there is none the test says so and passes, unless DRAY_REQUIRE_SLURM=1
//! (CI) makes that a failure.

mod common;

use common::*;
use dray_actors::nodes::frame_cameras;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

const FRAMES: u32 = 10;

fn dray() -> &'static str {
    env!("CARGO_BIN_EXE_dray")
}

fn repo() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// Whether a Slurm controller answers here; why not, if it does not.
fn slurm_missing() -> Option<String> {
    match Command::new("scontrol").arg("ping").output() {
        Err(e) => Some(format!("scontrol: {e} (is slurm-wlm installed?)")),
        Ok(o) if !String::from_utf8_lossy(&o.stdout).contains("is UP") => Some(format!(
            "no Slurm controller is up (`scontrol ping`: {}); start one with deploy/slurm/local-slurm start",
            String::from_utf8_lossy(&o.stdout).trim()
        )),
        Ok(_) => None,
    }
}

/// Runs `cmd` to its end or kills it after `limit`, naming `what`.
fn run_within(mut cmd: Command, limit: Duration, what: &str) -> Output {
    let child = cmd
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("{what}: {e}"));
    let pid = child.id();
    let done = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let watch = done.clone();
    let what_owned = what.to_string();
    std::thread::spawn(move || {
        let deadline = Instant::now() + limit;
        while Instant::now() < deadline {
            if watch.load(std::sync::atomic::Ordering::Relaxed) {
                return;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        eprintln!("{what_owned}: still running after {limit:?}; killing it");
        let _ = Command::new("kill").arg(pid.to_string()).status();
    });
    let out = child.wait_with_output().unwrap();
    done.store(true, std::sync::atomic::Ordering::Relaxed);
    out
}

/// A cluster of 2 stores (each on its own shard) and 2 clients, every
/// address on the first host of the Slurm step.
fn setup(dir: &Path) -> PathBuf {
    let db = plant_db(dir, 20_000);
    let out = Command::new(dray())
        .args(["shard", db.to_str().unwrap(), "--of", "2", "--out"])
        .arg(dir.join("shards"))
        .output()
        .unwrap();
    assert!(out.status.success(), "dray shard: {out:?}");
    write_path(&db, &dir.join("path.toml"), FRAMES);
    let [p0, p1, p2, p3] = free_ports::<4>();
    let text = format!(
        r#"
[scene]
database = "{db}"

[render]
width = 96
height = 64
tile_size = 16
shadows = true
depth_and_ids = true
camera_path = "path.toml"

[render.camera]
eye = [0.0, 5.0, -30.0]
look = [0.0, 2.0, 0.0]

[scheduler]
address = "{{host:0}}:{p0}"

[display]
address = "{{host:0}}:{p1}"
output = "out"

[[stores]]
address = "{{host:0}}:{p2}"
database = "shards/shard-0"

[[stores]]
address = "{{host:0}}:{p3}"
database = "shards/shard-1"

[clients]
count = 2
threads = 1
cache_mb = 0.5

[certs]
dir = "certs"
"#,
        db = db.display()
    );
    let config = dir.join("cluster.toml");
    std::fs::write(&config, text).unwrap();
    let out = Command::new(dray())
        .args(["certs", "init"])
        .arg(dir.join("certs"))
        .arg("--config")
        .arg(&config)
        .output()
        .unwrap();
    assert!(out.status.success(), "dray certs init: {out:?}");
    config
}

/// The JSON summary a rank printed: srun's `--label` cuts long lines into
/// pieces of about 1 KiB, each labelled, so the pieces are joined until
/// they parse.
fn rank_summary(log: &str, rank: u32) -> Option<serde_json::Value> {
    let label = format!("{rank}: ");
    let mut pieces = log
        .lines()
        .filter_map(|l| l.strip_prefix(&label))
        .skip_while(|l| !l.starts_with("summary "));
    let mut text = pieces.next()?.strip_prefix("summary ")?.to_string();
    loop {
        if let Ok(v) = serde_json::from_str(&text) {
            return Some(v);
        }
        text.push_str(pieces.next()?);
    }
}

#[test]
fn sbatch_runs_a_sharded_cluster_whose_frames_equal_dray_render() {
    if let Some(why) = slurm_missing() {
        assert!(
            std::env::var("DRAY_REQUIRE_SLURM").as_deref() != Ok("1"),
            "DRAY_REQUIRE_SLURM=1 but {why}"
        );
        eprintln!("skipped: {why}");
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let config = setup(dir);

    // Too few tasks: every one of them says so, and the step fails.
    let mut few = Command::new("srun");
    few.args([
        "--ntasks=5",
        "--overcommit",
        "--time=1",
        "--kill-on-bad-exit=1",
    ])
    .arg(format!("--chdir={}", dir.display()))
    .args([dray(), "node", "--config", "cluster.toml"]);
    let out = run_within(few, Duration::from_secs(60), "srun with 5 tasks");
    let text = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{text}");
    assert!(
        text.contains("Slurm started 5 processes (SLURM_NTASKS), but the config has 6 ranks"),
        "{text}"
    );

    let mut job = Command::new("sbatch");
    job.args(["--wait", "--ntasks=6", "--time=3"])
        .arg(format!("--chdir={}", dir.display()))
        .arg(format!("--output={}", dir.join("job.out").display()))
        .arg(repo().join("deploy/slurm/dray.sbatch"))
        .arg("cluster.toml")
        .env("DRAY", dray())
        .env("RUST_LOG", "warn");
    let out = run_within(job, Duration::from_secs(240), "sbatch");
    let log = std::fs::read_to_string(dir.join("job.out")).unwrap_or_default();
    assert!(out.status.success(), "sbatch: {out:?}\n{log}");

    // The display is rank 1: its summary says every frame was shown whole.
    let summary = rank_summary(&log, 1)
        .unwrap_or_else(|| panic!("no summary from rank 1 (the display):\n{log}"));
    assert_eq!(summary["complete"], true, "{summary}");
    assert_eq!(summary["frames_shown"], FRAMES, "{summary}");
    assert_eq!(summary["missing_pixels"], 0, "{summary}");

    let cfg = dray_config::Config::load(&config).unwrap();
    for (k, cam) in frame_cameras(&cfg).unwrap().iter().enumerate() {
        let png = dir.join(format!("out/frames/frame-{k:05}.png"));
        let bytes = std::fs::read(&png).unwrap_or_else(|e| panic!("{}: {e}", png.display()));
        let (_, _, rgba) = dray_trace::image::decode_png(&bytes).unwrap();
        let (want, _, _) = reference(&cfg, cam);
        assert!(rgba == want, "frame {k} differs from dray render's");
    }
}
