//! The Kubernetes deployment (deploy/k8s) and its image
//! (deploy/Containerfile) agree with each other and with dray, checked
//! without Kubernetes: the manifests are parsed, the config is dray's own
//! parser's, and the scripts and the binary run for real. Each failure
//! names the file and what disagrees.

use base64::Engine;
use dray_config::Config;
use serde_yaml_ng::Value;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

const DRAY: &str = env!("CARGO_BIN_EXE_dray");
const CONFIG_YAML: &str = "deploy/k8s/config.yaml";
const STATEFULSET_YAML: &str = "deploy/k8s/statefulset.yaml";
const SERVICES_YAML: &str = "deploy/k8s/services.yaml";
const MAKE_SECRETS: &str = "deploy/k8s/make-secrets";
const CONTAINERFILE: &str = "deploy/Containerfile";
/// The key of the ConfigMap that holds the cluster config.
const TOML_KEY: &str = "dray.toml";
/// The label a StatefulSet gives each pod, its pod's name.
const POD_NAME_LABEL: &str = "statefulset.kubernetes.io/pod-name";

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

fn read(path: &str) -> String {
    std::fs::read_to_string(repo(path)).unwrap_or_else(|e| panic!("{path}: {e}"))
}

/// The documents of a YAML stream: the text between `---` lines.
fn yaml_parts(text: &str) -> Vec<String> {
    let mut parts = vec![String::new()];
    for line in text.lines() {
        if line.trim_end() == "---" {
            parts.push(String::new());
        } else {
            let last = parts.last_mut().unwrap();
            last.push_str(line);
            last.push('\n');
        }
    }
    parts
}

/// Every YAML document of a manifest file; each must be a Kubernetes
/// object: apiVersion, kind and metadata.name.
fn documents(file: &str) -> Vec<Value> {
    let text = read(file);
    let mut docs = Vec::new();
    for (i, part) in yaml_parts(&text).iter().enumerate() {
        let doc: Value = serde_yaml_ng::from_str(part)
            .unwrap_or_else(|e| panic!("{file}: document {i} is not YAML: {e}"));
        if doc.is_null() {
            continue;
        }
        for path in [&["apiVersion"][..], &["kind"], &["metadata", "name"]] {
            let v = at(&doc, path, file);
            assert!(
                v.as_str().is_some_and(|s| !s.is_empty()),
                "{file}: document {i} has no {}",
                path.join(".")
            );
        }
        docs.push(doc);
    }
    assert!(!docs.is_empty(), "{file}: no documents");
    docs
}

/// The value at a path of mapping keys, or a panic naming the file and path.
fn at<'a>(v: &'a Value, path: &[&str], file: &str) -> &'a Value {
    let mut cur = v;
    for (i, key) in path.iter().enumerate() {
        cur = cur
            .get(*key)
            .unwrap_or_else(|| panic!("{file}: {} is missing", path[..=i].join(".")));
    }
    cur
}

fn text_at<'a>(v: &'a Value, path: &[&str], file: &str) -> &'a str {
    at(v, path, file)
        .as_str()
        .unwrap_or_else(|| panic!("{file}: {} is not a string", path.join(".")))
}

fn list_at<'a>(v: &'a Value, path: &[&str], file: &str) -> &'a [Value] {
    at(v, path, file)
        .as_sequence()
        .unwrap_or_else(|| panic!("{file}: {} is not a list", path.join(".")))
}

fn name_of(v: &Value) -> &str {
    v.get("name").and_then(Value::as_str).unwrap_or("")
}

fn strings(v: &[Value], what: &str, file: &str) -> Vec<String> {
    v.iter()
        .map(|s| {
            s.as_str()
                .unwrap_or_else(|| panic!("{file}: {what} holds a non-string"))
                .to_string()
        })
        .collect()
}

/// A container's `key` list (`command`, `args`) in the StatefulSet, as
/// strings.
fn container_list(container: &Value, key: &str) -> Vec<String> {
    strings(
        list_at(container, &[key], STATEFULSET_YAML),
        key,
        STATEFULSET_YAML,
    )
}

/// One object of a file, by kind and name.
fn object<'a>(docs: &'a [Value], kind: &str, name: &str, file: &str) -> &'a Value {
    docs.iter()
        .find(|d| {
            d.get("kind").and_then(Value::as_str) == Some(kind) && name_of(&d["metadata"]) == name
        })
        .unwrap_or_else(|| panic!("{file}: no {kind} named {name}"))
}

/// The manifests, parsed, and the config they carry.
struct Deploy {
    config_map: Value,
    sts: Value,
    headless: Value,
    viewer: Value,
    cfg: Config,
    toml: String,
}

impl Deploy {
    fn load() -> Deploy {
        let maps = documents(CONFIG_YAML);
        let sets = documents(STATEFULSET_YAML);
        let services = documents(SERVICES_YAML);
        assert!(
            maps.len() == 1 && maps[0]["kind"].as_str() == Some("ConfigMap"),
            "{CONFIG_YAML}: one ConfigMap expected"
        );
        let config_map = maps[0].clone();
        assert_eq!(
            sets.len(),
            1,
            "{STATEFULSET_YAML}: one StatefulSet expected"
        );
        let sts = object(&sets, "StatefulSet", "dray", STATEFULSET_YAML).clone();
        let service = text_at(&sts, &["spec", "serviceName"], STATEFULSET_YAML);
        let headless = object(&services, "Service", service, SERVICES_YAML).clone();
        let viewer = object(&services, "Service", "dray-viewer", SERVICES_YAML).clone();
        let toml = text_at(&config_map, &["data", TOML_KEY], CONFIG_YAML).to_string();
        let cfg = Config::parse(&toml).unwrap_or_else(|e| {
            panic!("{CONFIG_YAML}: data.{TOML_KEY} is not a valid dray config: {e}")
        });
        Deploy {
            config_map,
            sts,
            headless,
            viewer,
            cfg,
            toml,
        }
    }

    fn pod_spec(&self) -> &Value {
        at(&self.sts, &["spec", "template", "spec"], STATEFULSET_YAML)
    }

    /// The one container that runs `dray node`.
    fn main_container(&self) -> &Value {
        let containers = list_at(self.pod_spec(), &["containers"], STATEFULSET_YAML);
        assert_eq!(
            containers.len(),
            1,
            "{STATEFULSET_YAML}: one container expected, the node"
        );
        &containers[0]
    }

    fn init_container(&self, name: &str) -> &Value {
        list_at(self.pod_spec(), &["initContainers"], STATEFULSET_YAML)
            .iter()
            .find(|c| name_of(c) == name)
            .unwrap_or_else(|| panic!("{STATEFULSET_YAML}: no initContainer {name}"))
    }

    fn volume(&self, name: &str) -> &Value {
        list_at(self.pod_spec(), &["volumes"], STATEFULSET_YAML)
            .iter()
            .find(|v| name_of(v) == name)
            .unwrap_or_else(|| panic!("{STATEFULSET_YAML}: no volume {name}"))
    }

    /// Pod `R`'s name: the StatefulSet's name and its ordinal.
    fn pod(&self, rank: usize) -> String {
        format!("{}-{rank}", name_of(&self.sts["metadata"]))
    }

    /// The rank of the node named `node`.
    fn rank_of(&self, node: &str) -> usize {
        self.cfg
            .rank_nodes()
            .iter()
            .position(|n| n == node)
            .unwrap_or_else(|| panic!("{CONFIG_YAML}: node {node} has no rank"))
    }

    /// Each listening node: (node, config key, address text).
    fn listeners(&self) -> Vec<(String, String, String)> {
        let c = &self.cfg;
        let mut v = vec![
            (
                "scheduler".into(),
                "scheduler.address".into(),
                c.scheduler.address.clone(),
            ),
            (
                "display".into(),
                "display.address".into(),
                c.display.address.clone(),
            ),
        ];
        for (i, s) in c.stores.iter().enumerate() {
            v.push((
                format!("store-{i}"),
                format!("stores[{i}].address"),
                s.address.clone(),
            ));
        }
        v
    }

    fn web_port(&self) -> u16 {
        let web = self
            .cfg
            .display
            .web
            .as_deref()
            .unwrap_or_else(|| panic!("{CONFIG_YAML}: display.web is not set: no viewer"));
        host_port(web).1
    }
}

/// An address's host and port.
fn host_port(addr: &str) -> (&str, u16) {
    let (host, port) = addr
        .rsplit_once(':')
        .unwrap_or_else(|| panic!("{addr}: no port"));
    (
        host.trim_start_matches('[').trim_end_matches(']'),
        port.parse().expect("a port"),
    )
}

/// The container's environment variable `name` (a plain value).
fn env_value<'a>(c: &'a Value, name: &str) -> &'a str {
    list_at(c, &["env"], STATEFULSET_YAML)
        .iter()
        .find(|e| name_of(e) == name)
        .and_then(|e| e.get("value").and_then(Value::as_str))
        .unwrap_or_else(|| {
            panic!(
                "{STATEFULSET_YAML}: container {} has no env {name} with a value",
                name_of(c)
            )
        })
}

/// The container's mounts of volume `volume`: (mountPath, subPath, read-only).
fn mount_of<'a>(c: &'a Value, volume: &str) -> Vec<(&'a str, Option<&'a str>, bool)> {
    c.get("volumeMounts")
        .and_then(Value::as_sequence)
        .map(|m| m.as_slice())
        .unwrap_or(&[])
        .iter()
        .filter(|m| name_of(m) == volume)
        .map(|m| {
            (
                text_at(m, &["mountPath"], STATEFULSET_YAML),
                m.get("subPath").and_then(Value::as_str),
                m.get("readOnly").and_then(Value::as_bool) == Some(true),
            )
        })
        .collect()
}

/// The container's mount at `path`: (volume, subPath, read-only).
fn mount_at<'a>(c: &'a Value, path: &str) -> (&'a str, Option<&'a str>, bool) {
    list_at(c, &["volumeMounts"], STATEFULSET_YAML)
        .iter()
        .find(|m| m.get("mountPath").and_then(Value::as_str) == Some(path))
        .map(|m| {
            (
                name_of(m),
                m.get("subPath").and_then(Value::as_str),
                m.get("readOnly").and_then(Value::as_bool) == Some(true),
            )
        })
        .unwrap_or_else(|| {
            panic!(
                "{STATEFULSET_YAML}: container {} mounts nothing at {path}",
                name_of(c)
            )
        })
}

/// The container's ports of a protocol: number by name.
fn container_ports(c: &Value, protocol: &str) -> BTreeMap<String, u64> {
    list_at(c, &["ports"], STATEFULSET_YAML)
        .iter()
        .filter(|p| p.get("protocol").and_then(Value::as_str).unwrap_or("TCP") == protocol)
        .map(|p| {
            (
                name_of(p).to_string(),
                at(p, &["containerPort"], STATEFULSET_YAML)
                    .as_u64()
                    .expect("a port number"),
            )
        })
        .collect()
}

/// The container ports a Service's ports of a protocol lead to.
fn service_target_ports(
    svc: &Value,
    protocol: &str,
    pod_ports: &BTreeMap<String, u64>,
) -> BTreeSet<u64> {
    let name = name_of(&svc["metadata"]);
    list_at(svc, &["spec", "ports"], SERVICES_YAML)
        .iter()
        .filter(|p| p.get("protocol").and_then(Value::as_str).unwrap_or("TCP") == protocol)
        .map(|p| {
            let port = at(p, &["port"], SERVICES_YAML).as_u64().expect("a port number");
            match p.get("targetPort") {
                None => port,
                Some(Value::Number(n)) => n.as_u64().expect("a port number"),
                Some(t) => {
                    let t = t.as_str().unwrap_or("");
                    *pod_ports.get(t).unwrap_or_else(|| {
                        panic!("{SERVICES_YAML}: Service {name}'s targetPort {t} is no {protocol} port of the container in {STATEFULSET_YAML}")
                    })
                }
            }
        })
        .collect()
}

fn output_text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// Runs a command with a deadline, so that a node that unexpectedly
/// starts cannot hang the test.
fn run_with_deadline(cmd: &mut Command, limit: Duration) -> Output {
    let mut child = cmd
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot run {cmd:?}: {e}"));
    let start = Instant::now();
    while child.try_wait().expect("wait").is_none() {
        if start.elapsed() > limit {
            child.kill().ok();
            let out = child.wait_with_output().expect("wait");
            panic!("{cmd:?} ran past {limit:?}: {}", output_text(&out));
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().expect("output")
}

#[test]
fn every_document_is_a_named_kubernetes_object() {
    for file in [CONFIG_YAML, STATEFULSET_YAML, SERVICES_YAML] {
        documents(file);
    }
}

#[test]
fn each_pod_runs_the_node_its_address_names() {
    let d = Deploy::load();
    let nodes = d.cfg.rank_nodes();
    let replicas = at(&d.sts, &["spec", "replicas"], STATEFULSET_YAML).as_u64();
    assert_eq!(
        replicas,
        Some(nodes.len() as u64),
        "{STATEFULSET_YAML}: spec.replicas is not the {} ranks of {CONFIG_YAML} ({nodes:?})",
        nodes.len()
    );
    assert_eq!(
        text_at(&d.sts, &["spec", "podManagementPolicy"], STATEFULSET_YAML),
        "Parallel",
        "{STATEFULSET_YAML}: pods must start together, as each waits for the others"
    );
    let service = name_of(&d.headless["metadata"]);
    for (node, key, addr) in d.listeners() {
        let rank = d.rank_of(&node);
        let (host, _) = host_port(&addr);
        let pod = d.pod(rank);
        let want = format!("{pod}.{service}");
        assert!(
            host == want || host.starts_with(&format!("{want}.")),
            "{CONFIG_YAML}: {key} = {addr:?}, but {node} is rank {rank}, which runs on pod {pod}: its host is {want}"
        );
    }
}

#[test]
fn the_pods_mount_what_the_config_names() {
    let d = Deploy::load();
    let main = d.main_container();
    let args: Vec<String> = container_list(main, "args");
    let config_path = args
        .iter()
        .position(|a| a == "--config")
        .and_then(|i| args.get(i + 1))
        .unwrap_or_else(|| panic!("{STATEFULSET_YAML}: the container's args give no --config"));
    let (volume, sub, _) = mount_at(main, config_path);
    assert_eq!(
        sub,
        Some(TOML_KEY),
        "{STATEFULSET_YAML}: {config_path} is not the ConfigMap's {TOML_KEY}"
    );
    let cm = name_of(&d.config_map["metadata"]);
    assert_eq!(
        text_at(d.volume(volume), &["configMap", "name"], STATEFULSET_YAML),
        cm,
        "{STATEFULSET_YAML}: volume {volume} is not ConfigMap {cm} of {CONFIG_YAML}"
    );

    // The database: a read-only claim, holding each store's shard.
    let db = d.volume("db");
    assert_eq!(
        text_at(
            db,
            &["persistentVolumeClaim", "claimName"],
            STATEFULSET_YAML
        ),
        "dray-db",
        "{STATEFULSET_YAML}: volume db is not the claim dray-db"
    );
    assert_eq!(
        at(db, &["persistentVolumeClaim", "readOnly"], STATEFULSET_YAML).as_bool(),
        Some(true),
        "{STATEFULSET_YAML}: the claim dray-db must be mounted read-only"
    );
    let db_mounts = mount_of(main, "db");
    assert_eq!(
        db_mounts.len(),
        1,
        "{STATEFULSET_YAML}: volume db must be mounted once"
    );
    let (db_path, _, db_ro) = db_mounts[0];
    assert!(
        db_ro,
        "{STATEFULSET_YAML}: {db_path} must be mounted readOnly"
    );
    let shards = d.cfg.shards().expect("shards");
    for (i, s) in d.cfg.stores.iter().enumerate() {
        let path = s
            .database
            .as_ref()
            .unwrap_or_else(|| panic!("{CONFIG_YAML}: stores[{i}].database is not set: the store would read scene.database"));
        let (index, count) = shards[i];
        assert!(
            path.starts_with(db_path) && path.ends_with(format!("shard-{index}")),
            "{CONFIG_YAML}: stores[{i}].database = {path:?} serves shard {index}/{count}: it should be `dray shard --of {count}`'s shard-{index} on the volume at {db_path}"
        );
    }

    // The certificates: the initContainer's OUT is what the node sees as certs.dir.
    let certs_dir = d.cfg.certs.dir.to_str().unwrap();
    let (volume, sub, ro) = mount_at(main, certs_dir);
    assert!(
        ro,
        "{STATEFULSET_YAML}: certs.dir {certs_dir} should be read-only"
    );
    assert!(
        d.volume(volume).get("emptyDir").is_some(),
        "{STATEFULSET_YAML}: certs.dir {certs_dir} should be the emptyDir the initContainer certs fills"
    );
    let init = d.init_container("certs");
    let init_mounts = mount_of(init, volume);
    assert_eq!(
        init_mounts.len(),
        1,
        "{STATEFULSET_YAML}: initContainer certs must mount volume {volume}"
    );
    let want_out = match sub {
        Some(s) => format!("{}/{s}", init_mounts[0].0),
        None => init_mounts[0].0.to_string(),
    };
    assert_eq!(
        env_value(init, "OUT"),
        want_out,
        "{STATEFULSET_YAML}: initContainer certs writes elsewhere than the node's certs.dir {certs_dir}"
    );
    let all = env_value(init, "ALL_CERTS");
    let (secret_volume, _, _) = mount_at(init, all);
    assert_eq!(
        text_at(
            d.volume(secret_volume),
            &["secret", "secretName"],
            STATEFULSET_YAML
        ),
        "dray-certs",
        "{STATEFULSET_YAML}: initContainer certs reads {all}, which is not Secret dray-certs (what {MAKE_SECRETS} writes)"
    );
    assert!(
        mount_of(main, secret_volume).is_empty(),
        "{STATEFULSET_YAML}: the node's container must not mount {secret_volume}, every node's keys"
    );
    let (config_volume, config_sub, _) = mount_at(init, env_value(init, "CONFIG"));
    assert_eq!(
        (config_volume, config_sub),
        (volume_of_config(&d), Some(TOML_KEY)),
        "{STATEFULSET_YAML}: initContainer certs's CONFIG is not {CONFIG_YAML}'s data.{TOML_KEY}"
    );

    // One image for every container.
    let image = text_at(main, &["image"], STATEFULSET_YAML);
    for c in list_at(d.pod_spec(), &["initContainers"], STATEFULSET_YAML) {
        assert_eq!(
            text_at(c, &["image"], STATEFULSET_YAML),
            image,
            "{STATEFULSET_YAML}: initContainer {} runs another image than the node",
            name_of(c)
        );
    }
}

fn volume_of_config(d: &Deploy) -> &str {
    let cm = name_of(&d.config_map["metadata"]);
    list_at(d.pod_spec(), &["volumes"], STATEFULSET_YAML)
        .iter()
        .find(|v| {
            v.get("configMap")
                .and_then(|c| c.get("name"))
                .and_then(Value::as_str)
                == Some(cm)
        })
        .map(name_of)
        .unwrap_or_else(|| panic!("{STATEFULSET_YAML}: no volume of ConfigMap {cm}"))
}

#[test]
fn every_port_the_nodes_listen_on_is_open() {
    let d = Deploy::load();
    let main = d.main_container();
    let udp = container_ports(main, "UDP");
    let tcp = container_ports(main, "TCP");
    let quic: BTreeSet<u64> = d
        .listeners()
        .iter()
        .map(|(_, _, a)| u64::from(host_port(a).1))
        .collect();
    let udp_numbers: BTreeSet<u64> = udp.values().copied().collect();
    assert_eq!(
        udp_numbers, quic,
        "{STATEFULSET_YAML}: the UDP containerPorts are not the QUIC ports of {CONFIG_YAML}'s nodes"
    );
    let headless = name_of(&d.headless["metadata"]);
    assert_eq!(
        service_target_ports(&d.headless, "UDP", &udp),
        quic,
        "{SERVICES_YAML}: Service {headless}'s UDP ports are not the QUIC ports of {CONFIG_YAML}"
    );
    assert_eq!(
        d.headless["spec"]["clusterIP"].as_str(),
        Some("None"),
        "{SERVICES_YAML}: Service {headless} must be headless (clusterIP: None): each pod has a name of its own"
    );
    assert_eq!(
        d.headless["spec"]["publishNotReadyAddresses"].as_bool(),
        Some(true),
        "{SERVICES_YAML}: Service {headless} must publish pods before they are ready: the nodes look each other up while starting"
    );

    let web = u64::from(d.web_port());
    let tcp_numbers: BTreeSet<u64> = tcp.values().copied().collect();
    assert_eq!(
        tcp_numbers,
        BTreeSet::from([web]),
        "{STATEFULSET_YAML}: the TCP containerPorts are not display.web's port of {CONFIG_YAML}"
    );
    assert_eq!(
        service_target_ports(&d.viewer, "TCP", &tcp),
        BTreeSet::from([web]),
        "{SERVICES_YAML}: Service dray-viewer does not lead to display.web's port {web}"
    );
    let display_pod = d.pod(d.rank_of("display"));
    let selector = at(&d.viewer, &["spec", "selector"], SERVICES_YAML);
    assert_eq!(
        selector.get(POD_NAME_LABEL).and_then(Value::as_str),
        Some(display_pod.as_str()),
        "{SERVICES_YAML}: Service dray-viewer must select the display's pod {display_pod} ({POD_NAME_LABEL})"
    );
    let labels = at(
        &d.sts,
        &["spec", "template", "metadata", "labels"],
        STATEFULSET_YAML,
    );
    for svc in [&d.headless, &d.viewer] {
        let name = name_of(&svc["metadata"]);
        for (k, v) in at(svc, &["spec", "selector"], SERVICES_YAML)
            .as_mapping()
            .expect("a selector")
        {
            if k.as_str() == Some(POD_NAME_LABEL) {
                continue;
            }
            assert_eq!(
                labels.get(k),
                Some(v),
                "{SERVICES_YAML}: Service {name} selects {k:?}: {v:?}, which the pods of {STATEFULSET_YAML} lack"
            );
        }
    }
    // Readiness: only the display's pod serves HTTP; any other is ready.
    let probe = list_at(
        main,
        &["readinessProbe", "exec", "command"],
        STATEFULSET_YAML,
    );
    let probe = strings(probe, "readinessProbe.exec.command", STATEFULSET_YAML);
    let text = probe.join(" ");
    assert!(
        text.contains(&display_pod) && text.contains(&web.to_string()),
        "{STATEFULSET_YAML}: the readinessProbe should test the viewer's port {web} on {display_pod} only: {text}"
    );
    let client = d.pod(d.rank_of("client-0"));
    let mut cmd = Command::new(&probe[0]);
    cmd.args(&probe[1..]).env("HOSTNAME", &client);
    let o = run_with_deadline(&mut cmd, Duration::from_secs(30));
    assert!(
        o.status.success(),
        "{STATEFULSET_YAML}: the readinessProbe fails on {client}, which serves no HTTP: {}",
        output_text(&o)
    );
}

/// `make-secrets DIR`'s output, with `kubectl` as the script finds it
/// or none (`KUBECTL=`).
fn make_secrets(dir: &Path, kubectl: bool) -> Output {
    let mut cmd = Command::new(repo(MAKE_SECRETS));
    cmd.arg(dir).env_remove("DRAY_WEB_TOKEN");
    if !kubectl {
        cmd.env("KUBECTL", "");
    }
    cmd.output()
        .unwrap_or_else(|e| panic!("{MAKE_SECRETS}: cannot run it: {e}"))
}

/// The Secrets make-secrets wrote: name to (key to bytes).
fn secrets(out: &Output) -> BTreeMap<String, BTreeMap<String, Vec<u8>>> {
    assert!(
        out.status.success(),
        "{MAKE_SECRETS} failed: {}",
        output_text(out)
    );
    let text = String::from_utf8(out.stdout.clone()).expect("UTF-8 YAML");
    let mut found = BTreeMap::new();
    for (i, part) in yaml_parts(&text).iter().enumerate() {
        let doc: Value = serde_yaml_ng::from_str(part)
            .unwrap_or_else(|e| panic!("{MAKE_SECRETS}: document {i} is not YAML: {e}\n{text}"));
        assert_eq!(
            doc["kind"].as_str(),
            Some("Secret"),
            "{MAKE_SECRETS}: document {i} is not a Secret"
        );
        let name = text_at(&doc, &["metadata", "name"], MAKE_SECRETS).to_string();
        let data = at(&doc, &["data"], MAKE_SECRETS)
            .as_mapping()
            .unwrap_or_else(|| panic!("{MAKE_SECRETS}: Secret {name}'s data is not a mapping"))
            .iter()
            .map(|(k, v)| {
                let k = k.as_str().expect("a key").to_string();
                let text: String = v
                    .as_str()
                    .expect("base64 text")
                    .split_whitespace()
                    .collect();
                let bytes = base64::engine::general_purpose::STANDARD
                    .decode(text)
                    .unwrap_or_else(|e| {
                        panic!("{MAKE_SECRETS}: Secret {name}'s {k} is not base64: {e}")
                    });
                (k, bytes)
            })
            .collect();
        found.insert(name, data);
    }
    found
}

#[test]
fn each_pod_gets_its_own_nodes_certificate_and_never_the_ca_key() {
    let d = Deploy::load();
    let tmp = tempfile::tempdir().unwrap();
    let config = tmp.path().join("dray.toml");
    std::fs::write(&config, &d.toml).unwrap();
    let certs = tmp.path().join("certs");
    let init = Command::new(DRAY)
        .args(["certs", "init"])
        .arg(&certs)
        .arg("--config")
        .arg(&config)
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    assert!(
        init.status.success(),
        "dray certs init: {}",
        output_text(&init)
    );
    let ca_key =
        std::fs::read(certs.join("ca/ca.key")).expect("dray certs init keeps the CA key in ca/");

    let nodes = d.cfg.node_names();
    let mut want: BTreeSet<String> = BTreeSet::from(["ca.pem".to_string()]);
    for n in &nodes {
        want.insert(format!("{n}.pem"));
        want.insert(format!("{n}.key"));
    }
    let kubectl = Command::new("kubectl")
        .arg("version")
        .arg("--client")
        .output()
        .is_ok();
    let mut made = Vec::new();
    for with_kubectl in [false, true] {
        if with_kubectl && !kubectl {
            continue;
        }
        let how = if with_kubectl {
            "with kubectl"
        } else {
            "without kubectl"
        };
        let s = secrets(&make_secrets(&certs, with_kubectl));
        let names: BTreeSet<&str> = s.keys().map(String::as_str).collect();
        assert_eq!(
            names,
            BTreeSet::from(["dray-certs", "dray-web-token"]),
            "{MAKE_SECRETS} ({how}): Secrets"
        );
        let data = &s["dray-certs"];
        let keys: BTreeSet<String> = data.keys().cloned().collect();
        assert_eq!(keys, want, "{MAKE_SECRETS} ({how}): Secret dray-certs should hold ca.pem and each node's .pem and .key of {CONFIG_YAML}");
        for (k, v) in data {
            assert_eq!(
                v,
                &std::fs::read(certs.join(k)).unwrap(),
                "{MAKE_SECRETS} ({how}): {k} differs from the file"
            );
            assert_ne!(v, &ca_key, "{MAKE_SECRETS} ({how}): {k} is the CA key");
        }
        let token = String::from_utf8(s["dray-web-token"]["token"].clone()).expect("UTF-8 token");
        assert!(
            (16..=128).contains(&token.len()) && token.bytes().all(|b| b.is_ascii_alphanumeric()),
            "{MAKE_SECRETS} ({how}): the viewer's token {token:?} is not 16 to 128 letters and digits"
        );
        made.push(s);
    }

    // The node reads the token Secret make-secrets writes.
    let env = list_at(d.main_container(), &["env"], STATEFULSET_YAML)
        .iter()
        .find(|e| name_of(e) == dray_actors::nodes::WEB_TOKEN_ENV)
        .unwrap_or_else(|| {
            panic!(
                "{STATEFULSET_YAML}: the node's container has no {}",
                dray_actors::nodes::WEB_TOKEN_ENV
            )
        });
    let r = at(env, &["valueFrom", "secretKeyRef"], STATEFULSET_YAML);
    assert_eq!(
        (name_of(r), r["key"].as_str()),
        ("dray-web-token", Some("token")),
        "{STATEFULSET_YAML}: {} does not come from {MAKE_SECRETS}'s Secret dray-web-token, key token",
        dray_actors::nodes::WEB_TOKEN_ENV
    );

    // A CA key at the top of the directory is refused, and nothing is written.
    std::fs::copy(certs.join("ca/ca.key"), certs.join("ca.key")).unwrap();
    let refused = make_secrets(&certs, false);
    assert!(
        !refused.status.success()
            && refused.stdout.is_empty()
            && output_text(&refused).contains("ca.key"),
        "{MAKE_SECRETS}: a ca.key in the directory should be refused: {}",
        output_text(&refused)
    );
    std::fs::remove_file(certs.join("ca.key")).unwrap();

    // The Secret as the kubelet mounts it, and the initContainer certs on
    // each rank: it leaves exactly that rank's node's three files.
    let volume = tmp.path().join("secret");
    std::fs::create_dir(&volume).unwrap();
    for (k, v) in &made[0]["dray-certs"] {
        std::fs::write(volume.join(k), v).unwrap();
    }
    let script = d.init_container("certs");
    let command = container_list(script, "command");
    let args = container_list(script, "args");
    let path = format!(
        "{}:{}",
        Path::new(DRAY).parent().unwrap().display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let run_init = |rank: usize, out: &Path| {
        Command::new(&command[0])
            .args(&command[1..])
            .args(&args)
            .env("HOSTNAME", d.pod(rank))
            .env("KUBERNETES_SERVICE_HOST", "10.96.0.1")
            .env("CONFIG", &config)
            .env("ALL_CERTS", &volume)
            .env("OUT", out)
            .env("PATH", &path)
            .env("RUST_LOG", "warn")
            .output()
            .unwrap()
    };
    for (rank, node) in d.cfg.rank_nodes().iter().enumerate() {
        let out = tmp.path().join(format!("pod-{rank}/node"));
        // Twice: a restarted pod finds the files of its first start.
        for _ in 0..2 {
            let o = run_init(rank, &out);
            assert!(
                o.status.success(),
                "{STATEFULSET_YAML}: initContainer certs on pod {}: {}",
                d.pod(rank),
                output_text(&o)
            );
        }
        let got: BTreeSet<String> = std::fs::read_dir(&out)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        let mine = BTreeSet::from([
            "ca.pem".to_string(),
            format!("{node}.pem"),
            format!("{node}.key"),
        ]);
        assert_eq!(
            got,
            mine,
            "{STATEFULSET_YAML}: initContainer certs on pod {} (node {node})",
            d.pod(rank)
        );
        for f in &mine {
            assert_eq!(
                std::fs::read(out.join(f)).unwrap(),
                std::fs::read(certs.join(f)).unwrap(),
                "{f}"
            );
        }
    }
    let beyond = d.cfg.rank_nodes().len();
    let o = run_init(beyond, &tmp.path().join("pod-beyond/node"));
    assert!(
        !o.status.success() && output_text(&o).contains("has no node"),
        "{STATEFULSET_YAML}: initContainer certs on pod {}, past the last rank, should fail: {}",
        d.pod(beyond),
        output_text(&o)
    );
}

#[test]
fn the_container_runs_the_node_of_its_pod() {
    let d = Deploy::load();
    let main = d.main_container();
    let command = container_list(main, "command");
    let args = container_list(main, "args");
    assert_eq!(
        command,
        ["dray"],
        "{STATEFULSET_YAML}: the node's command should be dray"
    );
    let i = args
        .iter()
        .position(|a| a == "--config")
        .unwrap_or_else(|| panic!("{STATEFULSET_YAML}: the node's args give no --config"));
    assert!(
        !args.iter().any(|a| a == "--role" || a == "--index"),
        "{STATEFULSET_YAML}: every pod has the same args: the node must come from the pod's ordinal, not --role"
    );

    // The args parse: only the file is missing.
    let mut missing = args.clone();
    missing[i + 1] = "/nonexistent-dray-deploy-test.toml".into();
    let o = Command::new(DRAY)
        .args(&missing)
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    let text = output_text(&o);
    assert!(
        !o.status.success()
            && text.contains("/nonexistent-dray-deploy-test.toml")
            && !text.contains("Usage:"),
        "{STATEFULSET_YAML}: `dray {}` should fail on the missing file alone: {text}",
        missing.join(" ")
    );

    // On pod dray-R, `dray node` takes rank R's node from the host name. It
    // then stops, as the config's absolute paths (certificates, databases)
    // are moved under an empty folder.
    let tmp = tempfile::tempdir().unwrap();
    let config = tmp.path().join("dray.toml");
    let empty = tmp.path().join("empty");
    std::fs::write(
        &config,
        d.toml.replace("\"/", &format!("\"{}/", empty.display())),
    )
    .unwrap();
    let mut real = args.clone();
    real[i + 1] = config.to_str().unwrap().into();
    let launched = |rank: usize| {
        let mut cmd = Command::new(DRAY);
        cmd.args(&real)
            .env("KUBERNETES_SERVICE_HOST", "10.96.0.1")
            .env("HOSTNAME", d.pod(rank))
            .env("RUST_LOG", "info");
        for var in [
            "OMPI_COMM_WORLD_RANK",
            "PMIX_RANK",
            "PMI_RANK",
            "SLURM_PROCID",
            "JOB_COMPLETION_INDEX",
        ] {
            cmd.env_remove(var);
        }
        run_with_deadline(&mut cmd, Duration::from_secs(60))
    };
    for (rank, node) in d.cfg.rank_nodes().iter().enumerate() {
        let (role, index) = dray_config::node_role(node).expect("a node name");
        let o = launched(rank);
        let text = output_text(&o);
        assert!(
            text.contains(&format!("role={role} index={index}")),
            "{STATEFULSET_YAML}: pod {} should run {node} of {CONFIG_YAML}: {text}",
            d.pod(rank)
        );
    }
    let beyond = d.cfg.rank_nodes().len();
    let text = output_text(&launched(beyond));
    assert!(
        text.contains("has no node"),
        "pod {}: {text}",
        d.pod(beyond)
    );
}

/// The Containerfile's instructions: (keyword, arguments), continuation
/// lines joined and comments dropped.
fn instructions(text: &str) -> Vec<(String, String)> {
    let mut out = Vec::new();
    let mut current = String::new();
    for line in text.lines() {
        let t = line.trim();
        if t.starts_with('#') || (t.is_empty() && current.is_empty()) {
            continue;
        }
        if let Some(part) = t.strip_suffix('\\') {
            current.push_str(part);
            current.push(' ');
            continue;
        }
        current.push_str(t);
        let (k, a) = current
            .trim()
            .split_once(char::is_whitespace)
            .unwrap_or((current.trim(), ""));
        out.push((k.to_ascii_uppercase(), a.trim().to_string()));
        current.clear();
    }
    out
}

#[test]
fn the_image_holds_dray_and_exposes_the_configs_ports() {
    let d = Deploy::load();
    let steps = instructions(&read(CONTAINERFILE));
    let froms: Vec<usize> = steps
        .iter()
        .enumerate()
        .filter(|(_, (k, _))| k == "FROM")
        .map(|(i, _)| i)
        .collect();
    assert!(
        froms.len() >= 2,
        "{CONTAINERFILE}: a build stage and a runtime stage expected, found {} FROM",
        froms.len()
    );
    let last = &steps[*froms.last().unwrap()..];

    // The final stage copies dray from a stage that builds it.
    let copy = last
        .iter()
        .find(|(k, a)| k == "COPY" && a.starts_with("--from=") && a.contains("dray"))
        .unwrap_or_else(|| {
            panic!("{CONTAINERFILE}: the final stage copies no dray from a build stage")
        });
    let parts: Vec<&str> = copy.1.split_whitespace().collect();
    let stage = parts[0].trim_start_matches("--from=");
    let dest = parts.last().unwrap();
    let build = froms
        .iter()
        .position(|&i| {
            steps[i]
                .1
                .to_ascii_lowercase()
                .ends_with(&format!(" as {}", stage.to_ascii_lowercase()))
        })
        .unwrap_or_else(|| {
            panic!("{CONTAINERFILE}: COPY --from={stage}, but no stage is named {stage}")
        });
    let end = froms.get(build + 1).copied().unwrap_or(steps.len());
    assert!(
        steps[froms[build]..end]
            .iter()
            .any(|(k, a)| k == "RUN" && a.contains("cargo build --release --locked --bin dray")),
        "{CONTAINERFILE}: stage {stage} does not run `cargo build --release --locked --bin dray`"
    );
    assert!(
        dest.starts_with("/usr/local/bin/") || dest.starts_with("/usr/bin/"),
        "{CONTAINERFILE}: dray goes to {dest}, not on PATH: the manifests run `dray`"
    );

    let entry = &last
        .iter()
        .rfind(|(k, _)| k == "ENTRYPOINT")
        .unwrap_or_else(|| panic!("{CONTAINERFILE}: the final stage has no ENTRYPOINT"))
        .1;
    let entry: Vec<String> = serde_yaml_ng::from_str(entry).unwrap_or_else(|_| {
        panic!("{CONTAINERFILE}: ENTRYPOINT {entry} is not the exec form [\"dray\"]")
    });
    assert!(
        entry
            .first()
            .is_some_and(|p| p == "dray" || p.ends_with("/dray")),
        "{CONTAINERFILE}: ENTRYPOINT {entry:?} does not run dray"
    );

    // A numeric user, the pods' (runAsNonRoot checks only numbers).
    let user = &last
        .iter()
        .rfind(|(k, _)| k == "USER")
        .unwrap_or_else(|| panic!("{CONTAINERFILE}: no USER: the image runs as root"))
        .1;
    let uid = user.split(':').next().unwrap();
    let pod_uid = at(
        d.pod_spec(),
        &["securityContext", "runAsUser"],
        STATEFULSET_YAML,
    )
    .as_u64();
    assert_eq!(
        uid.parse::<u64>().ok(),
        pod_uid,
        "{CONTAINERFILE}: USER {user} is not the runAsUser of {STATEFULSET_YAML}"
    );

    // EXPOSE documents exactly the ports the config uses.
    let mut exposed = BTreeSet::new();
    for (_, a) in last.iter().filter(|(k, _)| k == "EXPOSE") {
        for p in a.split_whitespace() {
            let (n, proto) = p.split_once('/').unwrap_or((p, "tcp"));
            exposed.insert((
                n.parse::<u16>()
                    .unwrap_or_else(|_| panic!("{CONTAINERFILE}: EXPOSE {p}")),
                proto.to_ascii_lowercase(),
            ));
        }
    }
    let mut used: BTreeSet<(u16, String)> = d
        .listeners()
        .iter()
        .map(|(_, _, a)| (host_port(a).1, "udp".to_string()))
        .collect();
    used.insert((d.web_port(), "tcp".to_string()));
    assert_eq!(exposed, used, "{CONTAINERFILE}: EXPOSE is not the ports of {CONFIG_YAML} (QUIC over UDP, the viewer over TCP)");

    // The build context leaves the build's output behind.
    let ignore = read(".dockerignore");
    assert!(
        ignore
            .lines()
            .any(|l| l.trim().trim_start_matches('/').trim_end_matches('/') == "target"),
        ".dockerignore: target/ would go into the image's build context"
    );
}
