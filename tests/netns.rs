//! A cluster across hosts: every node of the config runs as `dray node` in
//! a Linux network namespace of its own, with its own address on a bridge,
//! so nodes reach each other only over a network, as on separate machines.
//! Killing a client and a store whose shard a replica also serves, a few
//! frames into the walk, loses nothing: the display's summary says every
//! frame was shown whole, every frame written equals `dray render`'s
//! (colours, depth and triangle ids), and every node left stops when the
//! display is done.
//!
//! Needs root and iproute2; elsewhere it says why and passes, unless
//! `DRAY_REQUIRE_NETNS=1` makes that a failure. The nodes log at the level
//! `DRAY_NETNS_LOG` gives (`warn` by default); a failure names a copy of
//! every node's whole log.

mod common;

use common::*;
use dray_actors::nodes::frame_cameras;
use std::collections::{BTreeSet, HashMap};
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// Frames of the walk.
const FRAMES: u32 = 36;
/// Frames the display asks for ahead of the one it waits for (its default).
const FRAMES_AHEAD: u32 = 2;
/// The port every node listens on, each at its own host's address.
const PORT: u16 = 7400;
/// The nodes, as (name, role, index), in the order their hosts are made.
const NODES: [(&str, &str, usize); 8] = [
    ("scheduler", "scheduler", 0),
    ("display", "display", 0),
    ("store-0", "store", 0),
    ("store-1", "store", 1),
    ("store-2", "store", 2),
    ("client-0", "client", 0),
    ("client-1", "client", 1),
    ("client-2", "client", 2),
];

/// Runs `ip ARGS`; the error names the command and what ip said.
fn ip(args: &[&str]) -> Result<(), String> {
    let out = Command::new("ip")
        .args(args)
        .output()
        .map_err(|e| format!("ip {}: {e}", args.join(" ")))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "ip {}: {}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr).trim()
        ))
    }
}

/// Why network namespaces cannot be made here, if they cannot.
fn netns_unavailable() -> Option<String> {
    // SAFETY: geteuid has no preconditions.
    if unsafe { libc::geteuid() } != 0 {
        return Some("not root (network namespaces need CAP_SYS_ADMIN)".into());
    }
    if let Err(e) = Command::new("ip").arg("-V").output() {
        return Some(format!("no ip command (iproute2): {e}"));
    }
    let probe = format!("dray{}-probe", std::process::id());
    if let Err(e) = ip(&["netns", "add", &probe]) {
        return Some(e);
    }
    let _ = ip(&["netns", "del", &probe]);
    None
}

/// One network namespace per node on a bridge of their own, and the
/// processes started in them; all removed on drop, whatever happened.
struct Hosts {
    bridge: String,
    /// The root namespace's ends of the veth pairs.
    veths: Vec<String>,
    namespaces: Vec<String>,
    /// Node processes, by node name.
    processes: Vec<(String, Child)>,
}

impl Hosts {
    /// The namespace of `node`.
    fn namespace(node: &str) -> String {
        format!("dray{}-{node}", std::process::id())
    }

    /// A host per node on a bridge, each with `lo` up and `eth0` at its
    /// address on `subnet` (a /24); names carry this process's id, so
    /// parallel runs never share one.
    fn new(nodes: &[&str], subnet: &str) -> (Hosts, HashMap<String, String>) {
        let tag = std::process::id();
        let mut hosts = Hosts {
            bridge: format!("drb{tag}"),
            veths: Vec::new(),
            namespaces: Vec::new(),
            processes: Vec::new(),
        };
        let must = |r: Result<(), String>| r.unwrap_or_else(|e| panic!("making the hosts: {e}"));
        must(ip(&["link", "add", &hosts.bridge, "type", "bridge"]));
        must(ip(&["link", "set", &hosts.bridge, "up"]));
        let mut addrs = HashMap::new();
        for (k, node) in nodes.iter().enumerate() {
            let ns = Hosts::namespace(node);
            must(ip(&["netns", "add", &ns]));
            hosts.namespaces.push(ns.clone());
            // Interface names have at most 15 bytes: "dv" + pid + "-" + k.
            let (outer, inner) = (format!("dv{tag}-{k}"), format!("dn{tag}-{k}"));
            must(ip(&[
                "link", "add", &outer, "type", "veth", "peer", "name", &inner,
            ]));
            hosts.veths.push(outer.clone());
            must(ip(&["link", "set", &inner, "netns", &ns]));
            must(ip(&["link", "set", &outer, "master", &hosts.bridge, "up"]));
            let addr = format!("{subnet}.{}", k + 2);
            must(ip(&["-n", &ns, "link", "set", "lo", "up"]));
            must(ip(&["-n", &ns, "link", "set", &inner, "name", "eth0"]));
            must(ip(&[
                "-n",
                &ns,
                "addr",
                "add",
                &format!("{addr}/24"),
                "dev",
                "eth0",
            ]));
            must(ip(&["-n", &ns, "link", "set", "eth0", "up"]));
            addrs.insert(node.to_string(), addr);
        }
        (hosts, addrs)
    }

    fn process(&mut self, node: &str) -> &mut Child {
        self.processes
            .iter_mut()
            .find(|(n, _)| n == node)
            .map(|(_, c)| c)
            .unwrap_or_else(|| panic!("{node} was not started"))
    }
}

impl Drop for Hosts {
    fn drop(&mut self) {
        for (_, child) in &mut self.processes {
            let _ = child.kill();
            let _ = child.wait();
        }
        for ns in &self.namespaces {
            let _ = ip(&["netns", "del", ns]);
        }
        // Deleting a namespace deletes its veth ends; these are the rest.
        for veth in &self.veths {
            let _ = ip(&["link", "del", veth]);
        }
        let _ = ip(&["link", "del", &self.bridge]);
    }
}

/// This process's own /24, so that parallel runs never share addresses.
fn subnet() -> String {
    let pid = std::process::id();
    format!("10.{}.{}", 200 + pid % 50, pid / 50 % 250)
}

/// The cluster config: every node at its host's address, each store
/// reading only its shard, store-2 a replica of store-0's.
fn netns_config(db: &Path, path: &Path, dir: &Path, addrs: &HashMap<String, String>) -> String {
    let at = |node: &str| format!("{}:{PORT}", addrs[node]);
    let store = |i: usize, shard: u32| {
        let db = dir.join(format!("shards/shard-{shard}"));
        format!(
            "address = \"{}\"\nshard = \"{shard}/2\"\ndatabase = \"{}\"",
            at(&format!("store-{i}")),
            db.display()
        )
    };
    let layout = Layout {
        scheduler: at("scheduler"),
        display: at("display"),
        stores: vec![store(0, 0), store(1, 1), store(2, 0)],
        tile_deadline_ms: None,
    };
    config_text_with(db, path, dir, &layout, 3, 64.0, "", "")
}

/// Starts `dray node` for `node` in its namespace; its stdout lines arrive
/// on `lines` as (node, line), its log goes to `logs/NODE.log`.
fn start_node(
    hosts: &mut Hosts,
    config: &Path,
    logs: &Path,
    (node, role, index): (&str, &str, usize),
    lines: &mpsc::Sender<(String, String)>,
) {
    let log = std::fs::File::create(logs.join(format!("{node}.log"))).unwrap();
    let mut child = Command::new("ip")
        .args(["netns", "exec", &Hosts::namespace(node)])
        .arg(env!("CARGO_BIN_EXE_dray"))
        .args(["node", "--config", config.to_str().unwrap()])
        .args(["--role", role, "--index", &index.to_string()])
        .env(
            "RUST_LOG",
            std::env::var("DRAY_NETNS_LOG").unwrap_or_else(|_| "warn".into()),
        )
        .stdout(Stdio::piped())
        .stderr(log)
        .spawn()
        .unwrap_or_else(|e| panic!("starting {node}: {e}"));
    let out = child.stdout.take().unwrap();
    let (tx, name) = (lines.clone(), node.to_string());
    std::thread::spawn(move || {
        for line in BufReader::new(out).lines().map_while(Result::ok) {
            if tx.send((name.clone(), line)).is_err() {
                break;
            }
        }
    });
    hosts.processes.push((node.to_string(), child));
}

/// The last lines of every node's log, for a failure message, and where
/// a copy of the whole logs outlives the test's directory.
fn log_tails(logs: &Path) -> String {
    let kept = std::env::temp_dir().join(format!("dray-netns-logs-{}", std::process::id()));
    let _ = std::fs::create_dir_all(&kept);
    for (node, _, _) in NODES {
        let name = format!("{node}.log");
        let _ = std::fs::copy(logs.join(&name), kept.join(&name));
    }
    let mut s = format!("whole logs: {}\n", kept.display());
    for (node, _, _) in NODES {
        let text = std::fs::read_to_string(logs.join(format!("{node}.log"))).unwrap_or_default();
        let tail: Vec<&str> = text.lines().rev().take(8).collect();
        s += &format!("--- {node}.log (last lines)\n");
        for l in tail.iter().rev() {
            s += &format!("{l}\n");
        }
    }
    s
}

/// Frames the display has shown: its metrics file grows a line a frame.
fn frames_shown(out: &Path) -> usize {
    std::fs::read_to_string(out.join("metrics.csv"))
        .map_or(0, |t| t.lines().count().saturating_sub(1))
}

/// Waits for the exit status of `node`'s process until `deadline`.
fn wait_exit(hosts: &mut Hosts, node: &str, deadline: Instant) -> Option<std::process::ExitStatus> {
    let child = hosts.process(node);
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return Some(status);
        }
        if Instant::now() >= deadline {
            return None;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn a_cluster_across_network_namespaces_survives_a_dead_client_and_store() {
    if let Some(why) = netns_unavailable() {
        let why = format!("network namespaces cannot be made here: {why}");
        dray_testkit::skip_unless_required("DRAY_REQUIRE_NETNS", &why);
        return;
    }
    let started = Instant::now();
    let dir = tempfile::tempdir().unwrap();
    let db = plant_db(dir.path(), 30_000);
    shard(&db, 2, &dir.path().join("shards"));
    let path = dir.path().join("walk.toml");
    write_path(&db, &path, FRAMES);
    let names: Vec<&str> = NODES.iter().map(|n| n.0).collect();
    let (mut hosts, addrs) = Hosts::new(&names, &subnet());
    let text = netns_config(&db, &path, dir.path(), &addrs);
    let (config, cfg) = common::config(dir.path(), &text);
    let node_names = cfg.node_names();
    assert_eq!(node_names, names, "the config's nodes are the hosts'");
    let refs: Vec<&str> = node_names.iter().map(String::as_str).collect();
    dray_runtime::certs::init_cluster(&cfg.certs.dir, &refs).unwrap();

    let logs = dir.path().join("logs");
    std::fs::create_dir_all(&logs).unwrap();
    let (tx, rx) = mpsc::channel();
    for node in NODES {
        start_node(&mut hosts, &config, &logs, node, &tx);
    }
    drop(tx);

    // Every node connected to the peers it dials.
    let mut waiting: BTreeSet<&str> = names.iter().copied().collect();
    let mut display_out = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(60);
    while !waiting.is_empty() {
        match rx.recv_timeout(Duration::from_millis(200)) {
            Ok((node, line)) => {
                if let Some(ready) = line.strip_prefix("ready ") {
                    assert_eq!(ready, node, "a node says it is another");
                    waiting.remove(node.as_str());
                }
                if node == "display" {
                    display_out.push(line);
                }
            }
            Err(_) => {
                for node in &waiting {
                    if let Some(status) = hosts.process(node).try_wait().unwrap() {
                        panic!(
                            "{node} ended before it was ready: {status}\n{}",
                            log_tails(&logs)
                        );
                    }
                }
                assert!(
                    Instant::now() < deadline,
                    "not ready after 60 s: {waiting:?}\n{}",
                    log_tails(&logs)
                );
            }
        }
    }
    println!("every node ready after {:.1?}", started.elapsed());

    // A few frames in, a client and a store die without a word.
    let out = dir.path().join("out");
    let deadline = Instant::now() + Duration::from_secs(60);
    while frames_shown(&out) < 2 {
        assert!(
            Instant::now() < deadline,
            "fewer than 2 frames shown after 60 s\n{}",
            log_tails(&logs)
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    for node in ["client-1", "store-0"] {
        hosts.process(node).kill().unwrap();
    }
    let shown_at_kill = frames_shown(&out);
    println!(
        "killed client-1 and store-0 after {shown_at_kill} of {FRAMES} frames ({:.1?})",
        started.elapsed()
    );
    // Frames past those the display had asked for are wholly rendered
    // without the dead nodes.
    assert!(
        shown_at_kill + (FRAMES_AHEAD as usize) < FRAMES as usize,
        "the walk was nearly over at the kill ({shown_at_kill} frames shown)"
    );

    let status = wait_exit(
        &mut hosts,
        "display",
        Instant::now() + Duration::from_secs(120),
    )
    .unwrap_or_else(|| {
        panic!(
            "the display still runs 120 s after the kill\n{}",
            log_tails(&logs)
        )
    });
    println!("the display finished after {:.1?}", started.elapsed());
    // The display's stdout, to its end (the summary is its last line).
    while let Ok((node, line)) = rx.recv_timeout(Duration::from_secs(5)) {
        if node == "display" {
            display_out.push(line);
        }
        if display_out.iter().any(|l| l.starts_with("summary ")) {
            break;
        }
    }
    assert!(
        status.success(),
        "the display failed: {status}\n{}",
        log_tails(&logs)
    );
    let summary = display_out
        .iter()
        .find_map(|l| l.strip_prefix("summary "))
        .unwrap_or_else(|| panic!("no summary from the display: {display_out:#?}"));
    let summary: serde_json::Value = serde_json::from_str(summary).unwrap();
    println!("{}", summary["text"].as_str().unwrap_or_default());
    assert_eq!(summary["complete"], true, "{summary:#}");
    assert_eq!(summary["frames_requested"], FRAMES, "{summary:#}");
    assert_eq!(summary["frames_shown"], FRAMES, "{summary:#}");
    assert_eq!(summary["missing_pixels"], 0, "{summary:#}");
    let frames = summary["frames"].as_array().unwrap();
    assert_eq!(frames.len(), FRAMES as usize, "{summary:#}");
    // Voxels were still fetched for frames not shown at the kill (without,
    // the dead store would have tested nothing).
    let fetched_after: u64 = frames[shown_at_kill..]
        .iter()
        .map(|f| f["bytes_fetched"].as_u64().unwrap())
        .sum();
    assert!(
        fetched_after > 0,
        "no voxel was fetched after the first {shown_at_kill} frames, so store-0's death was not tested"
    );
    let by = |f: &serde_json::Value| f["tiles_per_client"].as_str().unwrap().to_string();
    assert!(
        !by(&frames[FRAMES as usize - 1]).contains("client-1"),
        "the dead client rendered the last frame: {}",
        by(&frames[FRAMES as usize - 1])
    );

    // The display stopped every node left.
    let deadline = Instant::now() + Duration::from_secs(20);
    for node in ["scheduler", "store-1", "store-2", "client-0", "client-2"] {
        let status = wait_exit(&mut hosts, node, deadline).unwrap_or_else(|| {
            panic!(
                "{node} still runs 20 s after the display finished\n{}",
                log_tails(&logs)
            )
        });
        assert!(
            status.success(),
            "{node} ended with {status}\n{}",
            log_tails(&logs)
        );
    }
    println!("every node left stopped after {:.1?}", started.elapsed());

    assert_eq!(frame_cameras(&cfg).unwrap().len(), FRAMES as usize);
    assert_saved_frames_equal_reference(&cfg, &out.join("frames"));

    // Fetches store-0 never answered went to its replica once its
    // connection was lost, none after waiting out a fetch's time out.
    let count = |what: &str| -> usize {
        ["client-0", "client-2"]
            .iter()
            .map(|c| {
                std::fs::read_to_string(logs.join(format!("{c}.log")))
                    .unwrap_or_default()
                    .lines()
                    .filter(|l| l.contains(what) && l.contains("store-0"))
                    .count()
            })
            .sum()
    };
    let (failed_over, timed_out) = (
        count("store is down: asking the others"),
        count("fetch timed out"),
    );
    println!(
        "clients that sent store-0's fetches to its replica at once: {failed_over}; fetches that timed out: {timed_out}; wall time {:.1?}",
        started.elapsed()
    );
    assert_eq!(
        timed_out,
        0,
        "a fetch waited for the dead store\n{}",
        log_tails(&logs)
    );
    drop(hosts);
    drop(dir);
}
