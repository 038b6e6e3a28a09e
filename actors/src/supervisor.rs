//! `dray cluster`: every node of a config as a process on this machine,
//! supervised.
//!
//! Nodes start in dependency order (stores, scheduler, display, clients);
//! each prints `ready NODE` once its connections are up, and the display
//! only does so when every client has joined, so "all ready" means the
//! whole cluster is up. Then the display runs the camera path, prints
//! `summary JSON` and tells every node to stop. An interactive display
//! (no camera path, a web viewer) runs until Ctrl-C: the terminal's
//! SIGINT reaches the nodes too, the display ends with its summary, and
//! the supervisor waits for it (up to `STOP_TIMEOUT`; a second Ctrl-C
//! stops everything at once). SIGTERM and SIGHUP count as Ctrl-C (the
//! supervisor passes them on to the nodes as SIGINT, which a terminal
//! would have sent them). Every node dies with the supervisor, however
//! it ends ([`dray_runtime::process::die_with_parent`]).
//!
//! A node that dies while the cluster comes up ends the startup at once,
//! named with its last log lines (a store is restarted instead). A node
//! that exits with [`EXIT_NO_RESTART`] (its address is taken) ends the run
//! at once whatever its role: starting it again would fail the same way.
//!
//! Faults while running: a client that dies is reported and the others
//! take its tiles (the scheduler reassigns them); a store that dies is
//! restarted (clients re-send their fetches when it is back); the
//! scheduler or the display dying ends the run with an error naming the
//! node, its exit status and its last log lines.

use dray_config::Config;
use std::collections::VecDeque;
use std::path::Path;
use std::process::{ExitStatus, Stdio};
use std::time::Duration;
use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::{Child, Command};
use tokio::sync::mpsc;

/// How long the whole cluster may take to come up.
const STARTUP_TIMEOUT: Duration = Duration::from_secs(120);
/// How long nodes may take to stop once told to.
const STOP_TIMEOUT: Duration = Duration::from_secs(10);
/// Times a store is restarted before the run gives up.
const STORE_RESTARTS: u32 = 3;
/// Log lines kept per node, to say why it died.
const LOG_TAIL: usize = 12;
/// The exit code of a node that would fail the same way if started again
/// (its address is taken): the run ends at once, nothing is restarted.
pub const EXIT_NO_RESTART: u8 = 3;

/// Why `dray cluster` failed.
#[derive(Debug, thiserror::Error)]
pub enum LaunchError {
    /// A node process could not be started.
    #[error("cannot start {node}: {source}")]
    Spawn {
        /// The node.
        node: String,
        /// What the OS said.
        source: std::io::Error,
    },
    /// A node died where the run cannot go on without it.
    #[error("{node} died ({status}){log}")]
    Died {
        /// The node.
        node: String,
        /// Its exit status.
        status: String,
        /// Its last log lines.
        log: String,
    },
    /// A node cannot run, and starting it again would not help.
    #[error("{node} cannot run{log}")]
    Refused {
        /// The node.
        node: String,
        /// Its last log lines (which say why).
        log: String,
    },
    /// Nodes did not come up in time.
    #[error("the cluster did not come up within {}s; waiting for {waiting}", STARTUP_TIMEOUT.as_secs())]
    Startup {
        /// The nodes not ready.
        waiting: String,
    },
    /// Ctrl-C.
    #[error("interrupted; every node was stopped")]
    Interrupted,
    /// Certificates could not be made.
    #[error("certificates: {0}")]
    Certs(String),
    /// The stop signals could not be caught.
    #[error("cannot catch SIGINT, SIGTERM and SIGHUP: {0}")]
    Signals(std::io::Error),
    /// No random token for the web viewer.
    #[error("cannot make the web viewer's token: {0}")]
    Token(std::io::Error),
    /// An address of the config cannot be resolved.
    #[error(transparent)]
    Config(#[from] dray_config::ConfigError),
}

/// What a supervised run produced.
#[derive(Debug)]
pub struct ClusterReport {
    /// The display's summary (its `summary` line).
    pub summary: serde_json::Value,
    /// What happened along the way (deaths, restarts), in order.
    pub events: Vec<String>,
}

#[derive(Debug)]
enum Event {
    Line { node: usize, line: String },
    Log { node: usize, line: String },
}

struct Proc {
    name: String,
    args: Vec<String>,
    /// Environment variables it gets besides ours.
    env: Vec<(&'static str, String)>,
    child: Option<Child>,
    tail: VecDeque<String>,
    ready: bool,
    restarts: u32,
    done: bool,
}

/// Waits for every node to exit (at most [`STOP_TIMEOUT`] in all) when the
/// run ended well, and kills those still running.
async fn stop_all(procs: &mut [Proc], wait: bool, events: &mut Vec<String>) {
    let deadline = tokio::time::Instant::now() + STOP_TIMEOUT;
    for p in procs.iter_mut() {
        if let Some(c) = p.child.as_mut() {
            if wait {
                let left = deadline.saturating_duration_since(tokio::time::Instant::now());
                if tokio::time::timeout(left, c.wait()).await.is_ok() {
                    continue;
                }
                events.push(format!("{} did not stop in time and was killed", p.name));
            }
            let _ = c.kill().await;
        }
    }
}

fn status_text(s: &ExitStatus) -> String {
    #[cfg(unix)]
    {
        use std::os::unix::process::ExitStatusExt;
        if let Some(sig) = s.signal() {
            return format!("killed by signal {sig}");
        }
    }
    match s.code() {
        Some(c) => format!("exit code {c}"),
        None => "unknown status".into(),
    }
}

fn tail_text(p: &Proc) -> String {
    if p.tail.is_empty() {
        String::new()
    } else {
        let lines: Vec<&str> = p.tail.iter().map(String::as_str).collect();
        format!("; its last log lines:\n  {}", lines.join("\n  "))
    }
}

/// Sends each line a child writes to `from` as an event.
fn forward_lines(
    from: impl tokio::io::AsyncRead + Unpin + Send + 'static,
    tx: mpsc::Sender<Event>,
    event: impl Fn(String) -> Event + Send + 'static,
) {
    tokio::spawn(async move {
        let mut lines = BufReader::new(from).lines();
        while let Ok(Some(line)) = lines.next_line().await {
            let _ = tx.send(event(line)).await;
        }
    });
}

fn spawn(
    exe: &Path,
    p: &mut Proc,
    idx: usize,
    tx: &mpsc::Sender<Event>,
) -> Result<(), LaunchError> {
    let mut cmd = Command::new(exe);
    dray_runtime::process::die_with_parent(&mut cmd);
    if std::env::var_os("RUST_LOG").is_none() {
        // The nodes' routine info lines would drown the summary.
        cmd.env("RUST_LOG", "warn");
    }
    let mut child = cmd
        .args(&p.args)
        .envs(p.env.iter().map(|(k, v)| (k, v)))
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .map_err(|source| LaunchError::Spawn {
            node: p.name.clone(),
            source,
        })?;
    if let Some(out) = child.stdout.take() {
        forward_lines(out, tx.clone(), move |line| Event::Line { node: idx, line });
    }
    if let Some(err) = child.stderr.take() {
        forward_lines(err, tx.clone(), move |line| Event::Log { node: idx, line });
    }
    println!(
        "started {} (pid {})",
        p.name,
        child.id().map_or("?".into(), |i| i.to_string())
    );
    p.child = Some(child);
    p.ready = false;
    p.done = false;
    Ok(())
}

/// Makes the cluster's certificates when `certs.dir` has none yet (a
/// cluster on one machine needs nothing else).
pub fn ensure_certs(cfg: &Config) -> Result<bool, LaunchError> {
    if cfg.certs.dir.join("ca.pem").exists() {
        return Ok(false);
    }
    let names = cfg.node_names();
    let refs: Vec<&str> = names.iter().map(String::as_str).collect();
    dray_runtime::certs::init_cluster(&cfg.certs.dir, &refs)
        .map_err(|e| LaunchError::Certs(e.to_string()))?;
    Ok(true)
}

/// Runs every node of the config at `config_path` as a process of `exe`
/// (the `dray` binary: `exe node --config … --role … --index …`), until the
/// display is done; `extra` is appended to every node's arguments.
pub async fn cluster(
    exe: &Path,
    config_path: &Path,
    cfg: &Config,
    extra: &[String],
) -> Result<ClusterReport, LaunchError> {
    let clients = cfg.clients.count as usize;
    let mut signals = crate::signals::StopSignals::new().map_err(LaunchError::Signals)?;
    if ensure_certs(cfg)? {
        println!(
            "made the cluster certificates in {}",
            cfg.certs.dir.display()
        );
    }
    let proc_for = |role: &str, index: Option<usize>| {
        let name = match index {
            Some(i) => format!("{role}-{i}"),
            None => role.to_string(),
        };
        let mut args = vec![
            "node".to_string(),
            "--config".into(),
            config_path.display().to_string(),
            "--role".into(),
            role.into(),
        ];
        if let Some(i) = index {
            args.extend(["--index".into(), i.to_string()]);
        }
        args.extend(extra.iter().cloned());
        Proc {
            name,
            args,
            env: Vec::new(),
            child: None,
            tail: VecDeque::new(),
            ready: false,
            restarts: 0,
            done: false,
        }
    };
    let mut procs: Vec<Proc> = Vec::new();
    for i in 0..cfg.stores.len() {
        procs.push(proc_for("store", Some(i)));
    }
    procs.push(proc_for("scheduler", None));
    let display = procs.len();
    procs.push(proc_for("display", None));
    // The viewer's token is made here, so that its address can be printed.
    let viewer_url = match cfg.web_addr()? {
        Some(addr) => {
            let token = crate::display::web::wire::new_token().map_err(LaunchError::Token)?;
            procs[display]
                .env
                .push((crate::nodes::WEB_TOKEN_ENV, token.clone()));
            Some(format!("http://{addr}/?token={token}"))
        }
        None => None,
    };
    for i in 0..clients {
        procs.push(proc_for("client", Some(i)));
    }
    // Start in stages, each once the one before is ready, so that nobody
    // dials a node that is not listening yet: the stores, the scheduler
    // (which dials the stores), then the display and the clients (the
    // display is ready once every client has joined).
    let mut stages: VecDeque<Vec<usize>> = VecDeque::from([
        (0..cfg.stores.len()).collect(),
        vec![display - 1],
        (display..procs.len()).collect(),
    ]);
    let (tx, mut rx) = mpsc::channel::<Event>(1024);
    let mut current = stages.pop_front().unwrap_or_default();
    for &i in &current {
        spawn(exe, &mut procs[i], i, &tx)?;
    }
    let mut events = Vec::new();
    let mut summary = None;
    let started = tokio::time::Instant::now();
    let mut all_ready = false;
    // An interactive display runs until Ctrl-C: the first one (which the
    // nodes get too, from the terminal) waits for the display's summary,
    // a second one or STOP_TIMEOUT stops everything at once.
    let interactive = crate::nodes::interactive(cfg);
    let mut interrupted: Option<tokio::time::Instant> = None;
    let mut tick = tokio::time::interval(Duration::from_millis(50));
    // The node whose death ended the run, to name its last log lines.
    let mut died = None;
    let mut outcome: Result<(), LaunchError> = loop {
        tokio::select! {
            ev = rx.recv() => match ev {
                Some(Event::Line { node, line }) => {
                    if line.starts_with("ready ") {
                        procs[node].ready = true;
                        while current.iter().all(|&i| procs[i].ready) {
                            let Some(next) = stages.pop_front() else { break };
                            for &i in &next {
                                spawn(exe, &mut procs[i], i, &tx)?;
                            }
                            current = next;
                        }
                        if !all_ready && procs.iter().all(|p| p.ready) {
                            all_ready = true;
                            println!("all {} nodes joined", procs.len());
                            if let Some(url) = &viewer_url {
                                println!("viewer: {url}");
                            }
                        }
                    } else if let Some(json) = line.strip_prefix("summary ") {
                        summary = serde_json::from_str(json).ok();
                    } else {
                        println!("[{}] {line}", procs[node].name);
                    }
                }
                Some(Event::Log { node, line }) => {
                    eprintln!("[{}] {line}", procs[node].name);
                    let t = &mut procs[node].tail;
                    if t.len() == LOG_TAIL {
                        t.pop_front();
                    }
                    t.push_back(line);
                }
                None => {}
            },
            _ = tick.tick() => {
                if interrupted.is_some_and(|t| t.elapsed() > STOP_TIMEOUT) {
                    break Err(LaunchError::Interrupted);
                }
                if !all_ready && started.elapsed() > STARTUP_TIMEOUT {
                    let waiting: Vec<&str> = procs.iter().filter(|p| !p.ready).map(|p| p.name.as_str()).collect();
                    break Err(LaunchError::Startup { waiting: waiting.join(", ") });
                }
                let mut fatal = None;
                for i in 0..procs.len() {
                    if procs[i].done {
                        continue;
                    }
                    let exited = match procs[i].child.as_mut() {
                        Some(c) => c.try_wait().ok().flatten(),
                        None => None,
                    };
                    let Some(status) = exited else { continue };
                    procs[i].done = true;
                    let name = procs[i].name.clone();
                    // Exiting cleanly is what a node does when the display
                    // tells it the run is over.
                    if status.success() {
                        continue;
                    }
                    let what = status_text(&status);
                    if status.code() == Some(i32::from(EXIT_NO_RESTART)) {
                        died = Some(i);
                        fatal = Some(LaunchError::Refused { node: name, log: tail_text(&procs[i]) });
                    } else if summary.is_some() {
                        events.push(format!("{name} ended with {what} after the run"));
                    } else if !all_ready && !name.starts_with("store-") {
                        // The display waits for every client before it is
                        // ready: without this node the cluster never comes
                        // up, and waiting out STARTUP_TIMEOUT says less.
                        died = Some(i);
                        fatal = Some(LaunchError::Died {
                            node: name,
                            status: format!("{what}, before the cluster came up"),
                            log: tail_text(&procs[i]),
                        });
                    } else if name.starts_with("client-") {
                        let alive = procs.iter().filter(|p| p.name.starts_with("client-") && !p.done).count();
                        let e = format!("{name} died ({what}); {alive} clients go on and take its tiles");
                        eprintln!("cluster: {e}");
                        events.push(e);
                        if alive == 0 {
                            died = Some(i);
                            fatal = Some(LaunchError::Died { node: "every client".into(), status: what, log: tail_text(&procs[i]) });
                        }
                    } else if name.starts_with("store-") && procs[i].restarts < STORE_RESTARTS {
                        procs[i].restarts += 1;
                        let e = format!("{name} died ({what}); restarting it (restart {})", procs[i].restarts);
                        eprintln!("cluster: {e}");
                        events.push(e);
                        if let Err(err) = spawn(exe, &mut procs[i], i, &tx) {
                            fatal = Some(err);
                        }
                    } else {
                        died = Some(i);
                        fatal = Some(LaunchError::Died { node: name, status: what, log: tail_text(&procs[i]) });
                    }
                }
                if let Some(f) = fatal {
                    break Err(f);
                }
                if procs[display].done {
                    let status = procs[display].child.as_mut().and_then(|c| c.try_wait().ok().flatten());
                    match status {
                        Some(s) if !s.success() => {
                            died = Some(display);
                            break Err(LaunchError::Died { node: "display".into(), status: status_text(&s), log: tail_text(&procs[display]) });
                        }
                        _ => break Ok(()),
                    }
                }
            }
            name = signals.next() => {
                // Passed on even for SIGINT: a Ctrl-C at a terminal reaches
                // the nodes too (a node takes the first and ignores the
                // rest), but a `kill -INT` of this process alone does not.
                for p in &procs {
                    if let Some(pid) = p.child.as_ref().and_then(Child::id) {
                        let _ = dray_runtime::process::interrupt(pid);
                    }
                }
                if interactive && all_ready && interrupted.is_none() {
                    eprintln!("cluster: interrupted; waiting for the display's summary (Ctrl-C again to stop at once)");
                    events.push(format!("interrupted ({name}): the interactive run ended"));
                    interrupted = Some(tokio::time::Instant::now());
                    continue;
                }
                break Err(LaunchError::Interrupted);
            }
        }
    };
    // The display told everyone to stop: wait for them while reading what
    // they print last (the summary may be among it, and a node blocked on
    // a full pipe could not exit), then read their output to its end.
    drop(tx);
    let mut late_logs = Vec::new();
    {
        let mut summary_from = |ev: Event| match ev {
            Event::Line { line, .. } => {
                if let Some(json) = line.strip_prefix("summary ") {
                    summary = serde_json::from_str(json).ok();
                }
            }
            Event::Log { node, line } => late_logs.push((node, line)),
        };
        let stopping = stop_all(&mut procs, outcome.is_ok(), &mut events);
        tokio::pin!(stopping);
        loop {
            tokio::select! {
                _ = &mut stopping => break,
                Some(ev) = rx.recv() => summary_from(ev),
            }
        }
        // Every forwarder ends at its pipe's end, now that the nodes are
        // gone.
        while let Ok(Some(ev)) = tokio::time::timeout(STOP_TIMEOUT, rx.recv()).await {
            summary_from(ev);
        }
    }
    // A node that died has usually said why on its last line, which may
    // have been read only now.
    for (node, line) in late_logs {
        eprintln!("[{}] {line}", procs[node].name);
        let t = &mut procs[node].tail;
        if t.len() == LOG_TAIL {
            t.pop_front();
        }
        t.push_back(line);
    }
    if let (Err(LaunchError::Died { log, .. } | LaunchError::Refused { log, .. }), Some(i)) =
        (&mut outcome, died)
    {
        *log = tail_text(&procs[i]);
    }
    outcome?;
    let summary = summary.ok_or_else(|| LaunchError::Died {
        node: "display".into(),
        status: "exited without a summary".into(),
        log: tail_text(&procs[display]),
    })?;
    Ok(ClusterReport { summary, events })
}
