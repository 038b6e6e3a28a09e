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
use std::path::Path;
use std::process::Command;
use std::time::Duration;

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
        dray_testkit::skip_unless_required("DRAY_REQUIRE_SLURM", &why);
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let config = launcher_cluster(dir, FRAMES, "");

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
    assert_saved_frames_equal_reference(&cfg, &dir.join("out/frames"));
}
