//! `dray node` started by a launcher: ranks map to nodes, host templates
//! fill from Slurm's node list or `launch.hosts`, per-store databases, and
//! each mistake is named.

use dray_config::{node_role, Config};
use dray_protocol::Role;
use std::collections::HashMap;
use std::path::Path;

/// A cluster of 2 stores and 2 clients whose addresses are host templates.
fn templated(extra: &str) -> String {
    format!(
        r#"
[scene]
database = "db"
[render]
width = 64
height = 48
[render.camera]
eye = [0.0, 0.0, -5.0]
look = [0.0, 0.0, 0.0]
[scheduler]
address = "{{host:0}}:7400"
[display]
address = "{{host:0}}:7401"
web = "{{host:0}}:7480"
[[stores]]
address = "{{host:1}}:7410"
[[stores]]
address = "{{host:2}}-ib:7410"
database = "shards/shard-1"
[clients]
count = 2
threads = 1
cache_mb = 8
[certs]
dir = "certs"
{extra}
"#
    )
}

fn env(vars: &[(&str, &str)]) -> impl Fn(&str) -> Option<String> {
    let m: HashMap<String, String> = vars
        .iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect();
    move |k| m.get(k).cloned()
}

#[test]
fn a_slurm_rank_picks_its_node_and_the_node_list_fills_the_templates() {
    let mut cfg = Config::parse(&templated("")).unwrap();
    let slurm = env(&[
        ("SLURM_PROCID", "3"),
        ("SLURM_NTASKS", "6"),
        ("SLURM_STEP_NODELIST", "localhost,node[1-2]"),
    ]);
    let node = cfg.node_from_launcher(&slurm).unwrap();
    assert_eq!((node.role, node.index), (Role::Store, 1));
    assert_eq!(cfg.launch.hosts, ["localhost", "node1", "node2"]);
    assert_eq!(cfg.launch.hosts_from, Some("SLURM_STEP_NODELIST"));
    assert!(cfg.scheduler_addr().unwrap().ip().is_loopback());
    assert_eq!(cfg.web_addr().unwrap().unwrap().port(), 7480);
    // node1 does not resolve here: the error names the key and the host.
    let e = cfg.store_addrs().unwrap_err().to_string();
    assert!(
        e.starts_with("stores[0].address: cannot look up host \"node1\""),
        "{e}"
    );
}

#[test]
fn ranks_follow_launch_ranks_and_the_task_count_must_match() {
    let text = templated(
        "[launch]\nranks = [\"store-0\", \"store-1\", \"scheduler\", \"display\", \"client-1\", \"client-0\"]\nhosts = [\"127.0.0.1\", \"127.0.0.2\", \"127.0.0.3\"]\n",
    );
    let mut cfg = Config::parse(&text).unwrap();
    let node = cfg
        .node_from_launcher(&env(&[
            ("OMPI_COMM_WORLD_RANK", "4"),
            ("OMPI_COMM_WORLD_SIZE", "6"),
            ("SLURM_JOB_NODELIST", "n[1-3]"),
        ]))
        .unwrap();
    assert_eq!((node.role, node.index), (Role::Client, 1));
    assert_eq!(node.launch.launcher, "Open MPI");
    // The config's hosts win over a launcher's.
    assert_eq!(cfg.launch.hosts_from, None);
    assert_eq!(
        cfg.scheduler_addr().unwrap(),
        "127.0.0.1:7400".parse().unwrap()
    );

    let e = cfg
        .node_from_launcher(&env(&[("SLURM_PROCID", "0"), ("SLURM_NTASKS", "5")]))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("Slurm started 5 processes (SLURM_NTASKS)") && e.contains("exactly 6"),
        "{e}"
    );
    let e = cfg
        .node_from_launcher(&env(&[("PMIX_RANK", "6")]))
        .unwrap_err()
        .to_string();
    assert!(e.contains("rank 6 (PMIX_RANK) has no node"), "{e}");
    let e = cfg.node_from_launcher(&env(&[])).unwrap_err().to_string();
    assert!(
        e.contains("--role") && e.contains("SLURM_PROCID") && e.contains("JOB_COMPLETION_INDEX"),
        "{e}"
    );
}

#[test]
fn launch_mistakes_are_named() {
    let bad = |extra: &str| Config::parse(&templated(extra)).unwrap_err().to_string();
    let e = bad("[launch]\nranks = [\"scheduler\", \"client-2\"]\n");
    assert!(
        e.starts_with("launch.ranks: rank 1: \"client-2\" is not a node"),
        "{e}"
    );
    let e = bad("[launch]\nranks = [\"display\", \"display\"]\n");
    assert!(e.contains("rank 1: display has another rank too"), "{e}");
    let e = bad("[launch]\nhosts = [\"a\", \"b b\"]\n");
    assert!(e.starts_with("launch.hosts[1]:"), "{e}");
    // Host 2 of a list of two.
    let e = bad("[launch]\nhosts = [\"a\", \"b\"]\n");
    assert!(
        e.starts_with("stores[1].address:") && e.contains("launch.hosts lists 2: a,b"),
        "{e}"
    );
    // Two nodes on one host and port, once the templates are filled.
    let same = templated("[launch]\nhosts = [\"a\", \"a\", \"b\"]\n")
        .replace("{host:1}:7410", "{host:1}:7400");
    let e = Config::parse(&same).unwrap_err().to_string();
    assert!(
        e.contains("stores[0].address: {host:1}:7400 is also scheduler.address"),
        "{e}"
    );
}

#[test]
fn a_template_without_hosts_is_named_when_it_is_resolved() {
    let cfg = Config::parse(&templated("")).unwrap();
    let e = cfg.scheduler_addr().unwrap_err().to_string();
    assert!(
        e.contains("scheduler.address") && e.contains("set launch.hosts"),
        "{e}"
    );
}

#[test]
fn a_store_reads_its_own_database_relative_to_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("c.toml");
    std::fs::write(&file, templated("")).unwrap();
    let cfg = Config::load(&file).unwrap();
    assert_eq!(cfg.store_database(0), dir.path().join("db"));
    assert_eq!(cfg.store_database(1), dir.path().join("shards/shard-1"));
    assert!(dray_config::is_path_key("stores[1].database"));
    assert!(!dray_config::is_path_key("stores[x].database"));
    assert_eq!(
        dray_config::path_keys(2).last().map(String::as_str),
        Some("stores[1].database")
    );
    let e = Config::parse(&templated("").replace("shards/shard-1", ""))
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("stores[1].database: is empty"), "{e}");
}

#[test]
fn clients_bind_every_interface_of_the_schedulers_family_unless_told() {
    let local = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/local.toml");
    let text = std::fs::read_to_string(local).unwrap();
    let cfg = Config::parse(&text.replace("bind = \"127.0.0.1\"", "")).unwrap();
    let v4 = cfg.scheduler_addr().unwrap();
    assert_eq!(
        cfg.client_bind(v4).unwrap(),
        std::net::Ipv4Addr::UNSPECIFIED
    );
    let v6 = "[::1]:7400".parse().unwrap();
    assert_eq!(
        cfg.client_bind(v6).unwrap(),
        std::net::Ipv6Addr::UNSPECIFIED
    );
    let set = Config::parse(&text).unwrap();
    assert_eq!(set.client_bind(v6).unwrap(), std::net::Ipv4Addr::LOCALHOST);
}

#[test]
fn node_names_read_back_as_roles() {
    assert_eq!(node_role("scheduler"), Some((Role::Scheduler, 0)));
    assert_eq!(node_role("store-12"), Some((Role::Store, 12)));
    assert_eq!(node_role("client-0"), Some((Role::Client, 0)));
    for bad in ["client-01", "client-", "store--1", "worker-1", "client-x"] {
        assert_eq!(node_role(bad), None, "{bad}");
    }
}
