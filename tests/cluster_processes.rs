//! `dray cluster`: every node a process over QUIC with mutual TLS. Killing
//! a client mid-walkthrough loses no tile, a store that dies is restarted
//! and survived, and a stranger whose certificate is not from the cluster
//! CA is refused while the cluster goes on.

mod common;

use common::*;
use dray_protocol::{Name, Role};
use dray_runtime::certs::{init_cluster, NodeIdentity};
use dray_runtime::quic::QuicTransport;
use dray_runtime::Bus;
use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

/// Starts `dray cluster CONFIG --json`; stdout lines arrive on the channel.
fn start_cluster(config: &std::path::Path) -> (Child, mpsc::Receiver<String>) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_dray"))
        .args(["cluster", config.to_str().unwrap(), "--json"])
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap();
    let out = child.stdout.take().unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(out).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    (child, rx)
}

/// Reads lines until `pred` matches one; returns every line read.
fn until(rx: &mpsc::Receiver<String>, pred: impl Fn(&str) -> bool) -> Vec<String> {
    let mut seen = Vec::new();
    loop {
        let line = rx
            .recv_timeout(Duration::from_secs(120))
            .unwrap_or_else(|_| panic!("cluster output stopped; so far: {seen:#?}"));
        let done = pred(&line);
        seen.push(line);
        if done {
            return seen;
        }
    }
}

fn pid_of(lines: &[String], node: &str) -> u32 {
    let prefix = format!("started {node} (pid ");
    lines
        .iter()
        .rev()
        .find_map(|l| l.strip_prefix(&prefix))
        .and_then(|r| r.trim_end_matches(')').parse().ok())
        .unwrap_or_else(|| panic!("no pid for {node} in {lines:#?}"))
}

fn kill(pid: u32) {
    let ok = Command::new("kill")
        .args(["-9", &pid.to_string()])
        .status()
        .unwrap()
        .success();
    assert!(ok, "kill {pid}");
}

/// Waits for the cluster to exit successfully and returns its summary.
fn finish(mut child: Child, rx: &mpsc::Receiver<String>) -> serde_json::Value {
    let status = child.wait().unwrap();
    let lines: Vec<String> = rx.try_iter().collect();
    assert!(status.success(), "dray cluster failed: {lines:#?}");
    let json = lines
        .iter()
        .rev()
        .find(|l| l.starts_with('{'))
        .unwrap_or_else(|| panic!("no summary in {lines:#?}"));
    serde_json::from_str(json).unwrap()
}

fn frames_done(summary: &serde_json::Value) -> usize {
    summary["frames"].as_array().map_or(0, |f| f.len())
}

fn setup(frames: u32, clients: u32) -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let db = plant_db(dir.path(), 30_000);
    let path = dir.path().join("walk.toml");
    write_path(&db, &path, frames);
    let links = "[links.client_store]\nlatency_ms = 2.0\n";
    let text = config_text(&db, &path, dir.path(), clients, 8.0, "", links)
        .replace("width = 96\nheight = 64", "width = 192\nheight = 128");
    let (p, _) = config(dir.path(), &text);
    (dir, p)
}

#[test]
fn killing_a_client_mid_walkthrough_loses_no_tile() {
    let (_dir, config) = setup(20, 3);
    let (child, rx) = start_cluster(&config);
    let lines = until(&rx, |l| {
        l.starts_with("all ") && l.ends_with("nodes joined")
    });
    kill(pid_of(&lines, "client-1"));
    let summary = finish(child, &rx);
    assert_eq!(frames_done(&summary), 20, "{summary:#}");
    for f in summary["frames"].as_array().unwrap() {
        assert_eq!(f["tiles"], 12 * 8, "{f}");
    }
}

#[test]
fn a_store_that_dies_is_restarted_and_the_walk_completes() {
    let (_dir, config) = setup(20, 2);
    let (child, rx) = start_cluster(&config);
    let lines = until(&rx, |l| {
        l.starts_with("all ") && l.ends_with("nodes joined")
    });
    kill(pid_of(&lines, "store-0"));
    let summary = finish(child, &rx);
    assert_eq!(frames_done(&summary), 20, "{summary:#}");
}

#[test]
fn a_stranger_certificate_is_refused_and_the_cluster_goes_on() {
    let (dir, config) = setup(40, 2);
    let cfg = dray_config::Config::load(&config).unwrap();
    let scheduler = cfg.scheduler_addr().unwrap();
    let (child, rx) = start_cluster(&config);
    until(&rx, |l| {
        l.starts_with("all ") && l.ends_with("nodes joined")
    });
    // Another CA's certificate, under the name of a real client.
    let other = dir.path().join("other-ca");
    init_cluster(&other, &["client-0"]).unwrap();
    let rt = tokio::runtime::Runtime::new().unwrap();
    let refused = rt.block_on(async {
        let name = Name::new("client-0").unwrap();
        let id = NodeIdentity::load(&other, &name).unwrap();
        let bus = Bus::new(name, Role::Client);
        let t = QuicTransport::start(&bus, &id, "127.0.0.1:0".parse().unwrap())
            .await
            .unwrap();
        t.connect(Name::new("scheduler").unwrap(), scheduler);
        let joined = tokio::time::timeout(
            Duration::from_millis(1500),
            bus.wait_for_peer(&Name::new("scheduler").unwrap()),
        )
        .await;
        t.shutdown().await;
        joined.is_err()
    });
    assert!(refused, "the scheduler accepted a stranger");
    let summary = finish(child, &rx);
    assert_eq!(frames_done(&summary), 40, "{summary:#}");
}
