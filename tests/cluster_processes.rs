//! `dray cluster`: every node a process over QUIC with mutual TLS. Killing
//! a client mid-walkthrough loses no tile, a store that dies is restarted
//! and survived, a stranger whose certificate is not from the cluster CA
//! is refused while the cluster goes on, as are a second connection under
//! a client's name and a client's Shutdown; a node with another CA's
//! certificate stops the cluster at once, saying why.

mod common;

use common::*;
use dray_protocol::{Name, Role};
use dray_runtime::certs::{add_nodes, init_cluster, NodeIdentity};
use dray_runtime::quic::QuicTransport;
use dray_runtime::Bus;
use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// A running `dray cluster`, stopped (with its nodes) when dropped, so a
/// failing test leaves no processes behind.
struct ClusterProcess(Child);

impl Drop for ClusterProcess {
    fn drop(&mut self) {
        if matches!(self.0.try_wait(), Ok(None)) {
            // SIGTERM lets the supervisor stop its nodes.
            let _ = Command::new("kill").arg(self.0.id().to_string()).status();
            let deadline = Instant::now() + Duration::from_secs(20);
            while matches!(self.0.try_wait(), Ok(None)) && Instant::now() < deadline {
                std::thread::sleep(Duration::from_millis(50));
            }
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
}

/// Starts `dray cluster CONFIG --json`; stdout lines arrive on the channel.
fn start_cluster(config: &std::path::Path) -> (ClusterProcess, mpsc::Receiver<String>) {
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
    (ClusterProcess(child), rx)
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

/// Waits (at most 5 minutes) for the cluster to exit successfully; returns
/// its summary and the rest of its output.
fn finish(
    mut cluster: ClusterProcess,
    rx: &mpsc::Receiver<String>,
) -> (serde_json::Value, Vec<String>) {
    let deadline = Instant::now() + Duration::from_secs(300);
    let status = loop {
        if let Some(status) = cluster.0.try_wait().unwrap() {
            break status;
        }
        assert!(
            Instant::now() < deadline,
            "dray cluster still runs after 5 minutes"
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    // Everything it printed, up to the end of its stdout (the summary is
    // the last line, and may still be in the pipe when it exits).
    let mut lines = Vec::new();
    while let Ok(line) = rx.recv_timeout(Duration::from_secs(30)) {
        lines.push(line);
    }
    assert!(status.success(), "dray cluster failed: {lines:#?}");
    let json = lines
        .iter()
        .rev()
        .find(|l| l.starts_with('{'))
        .unwrap_or_else(|| panic!("no summary in {lines:#?}"));
    (serde_json::from_str(json).unwrap(), lines)
}

/// Waits until the display has shown `frames` frames (its metrics file
/// grows a line a frame), so that what happens next is mid-walk.
fn wait_for_frames(dir: &std::path::Path, frames: usize) {
    let csv = dir.join("out").join("metrics.csv");
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let shown =
            std::fs::read_to_string(&csv).map_or(0, |t| t.lines().count().saturating_sub(1));
        if shown >= frames {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "only {shown} frames shown after 2 minutes"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Every frame of the walk shown, whole.
fn assert_complete(summary: &serde_json::Value, frames: usize) {
    assert_eq!(frames_done(summary), frames, "{summary:#}");
    assert_eq!(summary["complete"], true, "{summary:#}");
    assert_eq!(summary["missing_pixels"], 0, "{summary:#}");
}

/// Starts a walk of `frames` frames with `clients` clients, kills `node`
/// once two frames are shown, and returns the summary, the pid killed and
/// the cluster's output.
fn kill_mid_walk(frames: u32, clients: u32, node: &str) -> (serde_json::Value, u32, Vec<String>) {
    let (dir, config) = setup(frames, clients);
    let (cluster, rx) = start_cluster(&config);
    let mut lines = until(&rx, |l| {
        l.starts_with("all ") && l.ends_with("nodes joined")
    });
    wait_for_frames(dir.path(), 2);
    let pid = pid_of(&lines, node);
    kill(pid);
    let (summary, rest) = finish(cluster, &rx);
    lines.extend(rest);
    (summary, pid, lines)
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
    let (summary, _, _) = kill_mid_walk(60, 3, "client-1");
    assert_complete(&summary, 60);
    let frames = summary["frames"].as_array().unwrap();
    for f in frames {
        assert_eq!(f["tiles"], 12 * 8, "{f}");
    }
    // It rendered before it died, and the others finished the walk.
    let by = |f: &serde_json::Value| f["tiles_per_client"].as_str().unwrap().to_string();
    assert!(by(&frames[0]).contains("client-1"), "{}", by(&frames[0]));
    assert!(!by(&frames[59]).contains("client-1"), "{}", by(&frames[59]));
}

#[test]
fn a_store_that_dies_is_restarted_and_the_walk_completes() {
    let (summary, killed, lines) = kill_mid_walk(60, 2, "store-0");
    assert_complete(&summary, 60);
    // A new store-0 process was started.
    assert_ne!(pid_of(&lines, "store-0"), killed, "{lines:#?}");
}

#[test]
fn a_stranger_certificate_is_refused_and_the_cluster_goes_on() {
    let (dir, config) = setup(40, 2);
    let cfg = dray_config::Config::load(&config).unwrap();
    let scheduler = cfg.scheduler_addr().unwrap();
    let (cluster, rx) = start_cluster(&config);
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
    let (summary, _) = finish(cluster, &rx);
    assert_complete(&summary, 40);
}

#[test]
fn a_node_that_dies_while_the_cluster_comes_up_stops_it_at_once_naming_the_node() {
    let (dir, config) = setup(10, 2);
    let cfg = dray_config::Config::load(&config).unwrap();
    // Certificates for every node but client-1, which therefore exits
    // before it joins: the display would wait for it forever.
    let names: Vec<String> = cfg
        .node_names()
        .into_iter()
        .filter(|n| n != "client-1")
        .collect();
    let refs: Vec<&str> = names.iter().map(String::as_str).collect();
    init_cluster(&cfg.certs.dir, &refs).unwrap();
    let started = Instant::now();
    let out = Command::new(env!("CARGO_BIN_EXE_dray"))
        .args(["cluster", config.to_str().unwrap()])
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    let elapsed = started.elapsed();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "the cluster ran without client-1");
    assert!(
        stderr.contains("client-1 died (exit code 1, before the cluster came up)"),
        "{stderr}"
    );
    // Its own words on why, from its last log lines.
    assert!(stderr.contains("client-1.pem"), "{stderr}");
    // Well before the 120 s startup timeout.
    assert!(elapsed < Duration::from_secs(60), "took {elapsed:?}");
    drop(dir);
}

#[test]
fn a_twin_of_a_client_and_a_clients_shutdown_change_nothing() {
    let frames = 60;
    let (dir, config) = setup(frames, 2);
    let cfg = dray_config::Config::load(&config).unwrap();
    let scheduler = cfg.scheduler_addr().unwrap();
    let display = cfg.display_addr().unwrap();
    let store = cfg.store_addrs().unwrap()[0];
    let (cluster, rx) = start_cluster(&config);
    until(&rx, |l| {
        l.starts_with("all ") && l.ends_with("nodes joined")
    });
    wait_for_frames(dir.path(), 2);
    // A node added to the running cluster's CA, which the nodes have
    // never heard of, gets in (as a client).
    add_nodes(&cfg.certs.dir, None, &["client-9"]).unwrap();
    let n = |s: &str| Name::new(s).unwrap();
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let guard = Duration::from_secs(60);
        // client-0 started a second time (the same --index on two hosts):
        // refused by the scheduler and the display, which keep the first.
        let twin_bus = Bus::new(n("client-0"), Role::Client);
        let id = NodeIdentity::load(&cfg.certs.dir, &n("client-0")).unwrap();
        let twin = QuicTransport::start(&twin_bus, &id, "127.0.0.1:0".parse().unwrap())
            .await
            .unwrap();
        twin.connect(n("scheduler"), scheduler);
        twin.connect(n("display"), display);
        for peer in ["scheduler", "display"] {
            let why = tokio::time::timeout(guard, async {
                loop {
                    if let Some(e) = twin.dial_error(&n(peer)) {
                        break e;
                    }
                    tokio::time::sleep(Duration::from_millis(20)).await;
                }
            })
            .await
            .expect("the twin's dial neither failed nor succeeded");
            assert!(why.contains("already connected"), "{peer}: {why}");
        }
        assert!(twin_bus.peers().is_empty());
        twin.shutdown().await;

        // A client tells the scheduler's actors and a store to stop.
        let bus = Bus::new(n("client-9"), Role::Client);
        let id = NodeIdentity::load(&cfg.certs.dir, &n("client-9")).unwrap();
        let t = QuicTransport::start(&bus, &id, "127.0.0.1:0".parse().unwrap())
            .await
            .unwrap();
        t.connect(n("scheduler"), scheduler);
        t.connect(n("store-0"), store);
        for peer in ["scheduler", "store-0"] {
            tokio::time::timeout(guard, t.wait_connected(&n(peer)))
                .await
                .expect("an added node did not connect")
                .unwrap();
        }
        let mut mb = bus.mailbox(n("rogue"), 16).unwrap();
        let stop = || {
            dray_protocol::Message::Shutdown(dray_protocol::Shutdown {
                reason: "a client says so".into(),
            })
        };
        use dray_actors::names;
        for to in [
            names::scheduler(),
            names::assigner(),
            names::prefetcher(),
            names::store(0),
        ] {
            mb.send(&to, stop()).await.unwrap();
        }
        // The store answers a ping sent behind the shutdown on the same
        // stream: it has read (and refused) the shutdown.
        let ping = dray_protocol::Message::Ping(dray_protocol::Ping { seq: 1 });
        mb.send(&names::store(0), ping).await.unwrap();
        let pong = tokio::time::timeout(guard, mb.recv_message())
            .await
            .expect("the store did not answer");
        assert!(
            matches!(pong, Some((_, dray_protocol::Message::Pong(_)))),
            "{pong:?}"
        );
        t.shutdown().await;
    });
    let shown_when_told = std::fs::read_to_string(dir.path().join("out").join("metrics.csv"))
        .map_or(0, |t| t.lines().count().saturating_sub(1));
    assert!(
        shown_when_told < frames as usize,
        "the walk ended before the test could disturb it"
    );
    let (summary, _) = finish(cluster, &rx);
    assert_complete(&summary, frames as usize);
    // Both real clients rendered to the end.
    let last = &summary["frames"].as_array().unwrap()[frames as usize - 1];
    let by = last["tiles_per_client"].as_str().unwrap();
    assert!(by.contains("client-0") && by.contains("client-1"), "{by}");
}

#[test]
fn a_node_with_another_cas_certificate_stops_the_cluster_saying_why() {
    let (dir, config) = setup(10, 2);
    let cfg = dray_config::Config::load(&config).unwrap();
    let names = cfg.node_names();
    let refs: Vec<&str> = names.iter().map(String::as_str).collect();
    init_cluster(&cfg.certs.dir, &refs).unwrap();
    // client-1's certificate and key from another CA (next to the
    // cluster's ca.pem).
    let other = dir.path().join("other-ca");
    init_cluster(&other, &["client-1"]).unwrap();
    for f in ["client-1.pem", "client-1.key"] {
        std::fs::copy(other.join(f), cfg.certs.dir.join(f)).unwrap();
    }
    let out = Command::new(env!("CARGO_BIN_EXE_dray"))
        .args(["cluster", config.to_str().unwrap()])
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success(),
        "the cluster ran with a foreign client"
    );
    assert!(
        stderr.contains("client-1 died (exit code 1, before the cluster came up)"),
        "{stderr}"
    );
    assert!(stderr.contains("unknown issuer"), "{stderr}");
    assert!(
        stderr.contains("refused the certificate of client-1"),
        "{stderr}"
    );
    assert!(!stderr.contains("did not come up"), "{stderr}");
}

/// Whether process `pid` still runs (a zombie, dead but not yet reaped by
/// whoever inherited it, does not).
#[cfg(target_os = "linux")]
fn running(pid: u32) -> bool {
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        // The state follows the command name in parentheses.
        Ok(stat) => stat
            .rsplit_once(") ")
            .is_some_and(|(_, rest)| !rest.starts_with('Z') && !rest.starts_with('X')),
        Err(_) => false,
    }
}

/// Starts a long walk, sends `signal` to `dray cluster` once every node
/// has joined, and checks that no node process is left (polling for at
/// most 10 s).
#[cfg(target_os = "linux")]
fn no_node_outlives(signal: &str) {
    let (dir, config) = setup(100_000, 2);
    let (mut cluster, rx) = start_cluster(&config);
    let lines = until(&rx, |l| {
        l.starts_with("all ") && l.ends_with("nodes joined")
    });
    let nodes = [
        "store-0",
        "store-1",
        "scheduler",
        "display",
        "client-0",
        "client-1",
    ];
    let pids: Vec<(&str, u32)> = nodes.iter().map(|&n| (n, pid_of(&lines, n))).collect();
    assert!(pids.iter().all(|&(_, p)| running(p)), "{pids:?}");
    let ok = Command::new("kill")
        .args([signal, &cluster.0.id().to_string()])
        .status()
        .unwrap()
        .success();
    assert!(ok, "kill {signal}");
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let left: Vec<_> = pids.iter().filter(|&&(_, p)| running(p)).collect();
        if left.is_empty() {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "after {signal} to dray cluster these nodes still run: {left:?}"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    // The supervisor itself ended too.
    let deadline = Instant::now() + Duration::from_secs(10);
    while cluster.0.try_wait().unwrap().is_none() {
        assert!(Instant::now() < deadline, "dray cluster still runs");
        std::thread::sleep(Duration::from_millis(20));
    }
    drop(dir);
}

#[cfg(target_os = "linux")]
#[test]
fn sigterm_to_dray_cluster_leaves_no_node_running() {
    no_node_outlives("-TERM");
}

#[cfg(target_os = "linux")]
#[test]
fn sigkill_to_dray_cluster_leaves_no_node_running() {
    no_node_outlives("-KILL");
}

#[cfg(target_os = "linux")]
#[test]
fn sighup_to_dray_cluster_leaves_no_node_running() {
    no_node_outlives("-HUP");
}

/// A store whose port another process holds is not restarted: the run
/// ends at once, naming the node, the address and the config key.
#[test]
fn a_port_in_use_fails_once_naming_the_node_the_address_and_the_key() {
    let (dir, config) = setup(10, 1);
    let cfg = dray_config::Config::load(&config).unwrap();
    let addr = cfg.store_addrs().unwrap()[0];
    let _holder = std::net::UdpSocket::bind(addr).unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_dray"))
        .args(["cluster", config.to_str().unwrap()])
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut err = child.stderr.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = std::io::Read::read_to_string(&mut err, &mut s);
        s
    });
    let deadline = Instant::now() + Duration::from_secs(120);
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!("dray cluster with a store's port taken never ended");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let stderr = reader.join().unwrap();
    assert!(!status.success(), "{stderr}");
    assert!(!stderr.contains("restarting"), "{stderr}");
    assert!(stderr.contains("\nerror: store-0 cannot run"), "{stderr}");
    let why = format!(
        "node store-0: cannot listen on {addr}: the address is in use (another dray running? stop it, or change stores[0].address in the config)"
    );
    assert!(stderr.contains(&why), "{stderr}");
    drop(dir);
}

/// `dray node` stops cleanly on SIGTERM and SIGHUP, as launchers and
/// container runtimes stop it (a node that is PID 1 of a container would
/// otherwise ignore SIGTERM), whether it is still waiting for its peers or
/// running: it exits 0, saying which signal stopped it.
#[test]
fn a_node_stops_cleanly_on_sigterm_and_sighup_starting_or_running() {
    let (dir, config) = setup(10, 1);
    let certs = dir.path().join("certs");
    let cfg = dray_config::Config::load(&config).unwrap();
    let names = cfg.node_names();
    let refs: Vec<&str> = names.iter().map(String::as_str).collect();
    init_cluster(&certs, &refs).unwrap();
    let start = |role: &str| {
        let mut child = Command::new(env!("CARGO_BIN_EXE_dray"))
            .args(["node", "--config", config.to_str().unwrap(), "--role", role])
            .env("RUST_LOG", "info")
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let out = BufReader::new(child.stdout.take().unwrap());
        (child, out)
    };
    let stop = |mut child: Child, signal: &str| {
        let ok = Command::new("kill")
            .args([&format!("-{signal}"), &child.id().to_string()])
            .status()
            .unwrap()
            .success();
        assert!(ok, "kill -{signal}");
        let deadline = Instant::now() + Duration::from_secs(15);
        while matches!(child.try_wait(), Ok(None)) {
            if Instant::now() > deadline {
                let _ = child.kill();
                panic!("the node still runs 15 s after {signal}");
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let out = child.wait_with_output().unwrap();
        let log = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(out.status.success(), "{signal}: {:?}\n{log}", out.status);
        log
    };
    // A store dials nobody: it is ready at once, then runs.
    let (store, mut out) = start("store");
    let mut line = String::new();
    out.read_line(&mut line).unwrap();
    assert_eq!(line.trim(), "ready store-0");
    let log = stop(store, "TERM");
    assert!(log.contains("stopped") && log.contains("SIGTERM"), "{log}");
    // The display waits for a scheduler that never comes.
    let (display, _out) = start("display");
    std::thread::sleep(Duration::from_millis(500));
    let log = stop(display, "HUP");
    assert!(
        log.contains("stopped while starting") && log.contains("SIGHUP"),
        "{log}"
    );
}
