//! A whole cluster started by an MPI launcher (Open MPI's `mpirun`): every
//! process runs `dray node --config C`, takes its node from
//! `OMPI_COMM_WORLD_RANK` and its hosts from `launch.hosts`; two stores
//! serve shards made by `dray shard`; every frame equals `dray render`'s. A
//! launch of the wrong size fails naming the counts. Needs `mpirun`
//! (Debian's `openmpi-bin`); without it the test says so and passes,
//! unless DRAY_REQUIRE_MPI=1 (CI) makes that a failure.

mod common;

use common::*;
use std::process::Command;
use std::time::Duration;

const FRAMES: u32 = 10;

/// `mpirun` for `n` processes on this host, as root too, more processes
/// than cores.
fn mpirun(n: usize, dir: &std::path::Path) -> Command {
    let mut cmd = Command::new("mpirun");
    cmd.args([
        "--allow-run-as-root",
        "--oversubscribe",
        "-n",
        &n.to_string(),
    ])
    .args(["--wdir", dir.to_str().unwrap()])
    .args([
        env!("CARGO_BIN_EXE_dray"),
        "node",
        "--config",
        "cluster.toml",
    ])
    .env("RUST_LOG", "warn");
    cmd
}

#[test]
fn mpirun_starts_a_sharded_cluster_whose_frames_equal_dray_render() {
    if let Err(e) = Command::new("mpirun").arg("--version").output() {
        let why = format!("mpirun cannot run ({e}); apt-get install openmpi-bin");
        dray_testkit::skip_unless_required("DRAY_REQUIRE_MPI", &why);
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    // MPI gives no host list: the config names its hosts.
    let config = launcher_cluster(dir, FRAMES, "[launch]\nhosts = [\"127.0.0.1\"]\n");

    let out = run_within(mpirun(5, dir), Duration::from_secs(60), "mpirun -n 5");
    let text = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{text}");
    assert!(
        text.contains(
            "Open MPI started 5 processes (OMPI_COMM_WORLD_SIZE), but the config has 6 ranks"
        ),
        "{text}"
    );

    let out = run_within(mpirun(6, dir), Duration::from_secs(180), "mpirun -n 6");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "mpirun: {:?}\n{stdout}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    let mut ready: Vec<&str> = stdout
        .lines()
        .filter_map(|l| l.strip_prefix("ready "))
        .collect();
    ready.sort_unstable();
    assert_eq!(
        ready,
        [
            "client-0",
            "client-1",
            "display",
            "scheduler",
            "store-0",
            "store-1"
        ],
        "{stdout}"
    );
    let summary: serde_json::Value = stdout
        .lines()
        .find_map(|l| l.strip_prefix("summary "))
        .map(|j| serde_json::from_str(j).unwrap())
        .unwrap_or_else(|| panic!("no summary from the display:\n{stdout}"));
    assert_eq!(summary["complete"], true, "{summary}");
    assert_eq!(summary["frames_shown"], FRAMES, "{summary}");
    assert_eq!(summary["missing_pixels"], 0, "{summary}");

    let cfg = dray_config::Config::load(&config).unwrap();
    assert_saved_frames_equal_reference(&cfg, &dir.join("out/frames"));
}
