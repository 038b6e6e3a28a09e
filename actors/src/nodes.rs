//! Starting the actors of one config: every node in this process over the
//! in-process transport ([`sim`]), or one node over QUIC ([`node`]). The
//! process supervisor of `dray cluster` is in [`crate::supervisor`].
//!
//! Which node runs what, and who dials whom (the bus convention: the
//! dialer redials when a connection is lost):
//!
//! | node | actors | dials |
//! |---|---|---|
//! | `scheduler` | scheduler, assigner, prefetcher | the stores (manifest for the prefetcher) |
//! | `store-I` | store | — |
//! | `display` | display | the scheduler, the stores |
//! | `client-I` | client | the scheduler, the display, the stores |
//!
//! Shaped links (`[links]`) go through a UDP relay that the dialing node
//! starts on its own machine; in-process they are shaped by the network.
//! A node link (a store's uplink, a client's downlink) is one shaper that
//! every connection of that node crosses: in-process the network's
//! [`NodeLink`]; over QUIC a relay the store runs in front of its own
//! socket (every peer enters through it), and for a client one shaper that
//! all the relays of its dials share (it dials every peer). Either way the
//! shared state lives in the process that owns the link, so separate
//! processes need no coordination.

use crate::client::{run_client, ClientOptions, ClientSummary};
use crate::display::{path::CameraPath, run_display_until, DisplayOptions, DisplaySummary};
use crate::names::{self, StoreRoutes};
use crate::scheduler::{
    run_assigner, run_prefetcher, run_scheduler, AssignerOptions, PrefetcherOptions,
    SchedulerOptions, SchedulerSummary,
};
use crate::settings::{wire_camera, wire_settings};
use crate::signals::StopSignals;
use crate::store::{run_store, StoreDisk, StoreOptions, StoreSummary};
use crate::{ActorError, Shard};
use dray_config::{Config, LinkConfig, Listener};
use dray_protocol::{Address, Camera, Message, Name, Role, Shutdown};
use dray_runtime::certs::NodeIdentity;
use dray_runtime::quic::{DialTarget, QuicError, QuicTransport};
use dray_runtime::relay::{shared_link, RelayShaping, UdpRelay};
use dray_runtime::shaping::SharedShaper;
use dray_runtime::{Bus, InProcNet, LinkShape, Mailbox, NodeLink};
use dray_trace::render::Isa;
use std::net::SocketAddr;
use std::time::Duration;
use tokio::task::JoinHandle;
use tracing::{info, warn};

/// Undelivered messages an actor's mailbox holds before senders wait.
pub(crate) const MAILBOX: usize = 4096;

/// Why a run could not start or finish.
#[derive(Debug, thiserror::Error)]
pub enum ClusterError {
    /// The config is unusable.
    #[error(transparent)]
    Config(#[from] dray_config::ConfigError),
    /// The camera path is unusable.
    #[error("render.camera_path: {0}")]
    CameraPath(String),
    /// An actor failed.
    #[error(transparent)]
    Actor(#[from] ActorError),
    /// A node's address is taken by another process: starting it again
    /// fails the same way.
    #[error("node {node}: cannot listen on {addr}: the address is in use (another dray running? stop it, or change {key} in the config)")]
    AddressInUse {
        /// The node.
        node: String,
        /// Its address.
        addr: SocketAddr,
        /// The config key that sets it.
        key: String,
    },
    /// A node could not start (certificates, sockets, names).
    #[error("node {node}: {message}")]
    Node {
        /// The node.
        node: String,
        /// What went wrong.
        message: String,
    },
}

fn node_err(node: &Name, e: impl std::fmt::Display) -> ClusterError {
    ClusterError::Node {
        node: node.to_string(),
        message: e.to_string(),
    }
}

/// Choices a command makes on top of the config.
#[derive(Clone, Debug)]
pub struct RunOptions {
    /// Number of clients instead of `clients.count`.
    pub clients: Option<u32>,
    /// Keep every frame's image in the summary (tests compare them).
    pub keep_frames: bool,
    /// Keep every frame's metrics in the summary (the default; experiments
    /// read them). Interactive runs never do: they last as long as someone
    /// flies.
    pub keep_frame_metrics: bool,
    /// The kernel's instruction set (default: the best this CPU runs).
    pub isa: Option<Isa>,
    /// Show only this many of the run's first frames.
    pub max_frames: Option<usize>,
    /// Run on the virtual clock: [`sim_virtual`] sets it.
    pub virtual_clock: Option<crate::costs::VirtualRun>,
}

impl Default for RunOptions {
    fn default() -> RunOptions {
        RunOptions {
            clients: None,
            keep_frames: false,
            keep_frame_metrics: true,
            isa: None,
            max_frames: None,
            virtual_clock: None,
        }
    }
}

/// What a whole run did.
#[derive(Debug)]
pub struct RunSummary {
    /// Frames, metrics and (when kept) images.
    pub display: DisplaySummary,
    /// The scheduler's counts.
    pub scheduler: SchedulerSummary,
    /// Per client, in order.
    pub clients: Vec<ClientSummary>,
    /// Per store, in order.
    pub stores: Vec<StoreSummary>,
}

impl RunSummary {
    /// `dray sim`'s report: the display's summary with each client's
    /// counts under `clients`.
    pub fn to_json(&self) -> serde_json::Value {
        let mut summary = self.display.to_json();
        summary["clients"] = self.clients.iter().map(client_json).collect();
        summary
    }
}

/// A client's counts in a run's report.
fn client_json(c: &ClientSummary) -> serde_json::Value {
    serde_json::json!({
        "tiles": c.tiles,
        "rays": c.rays,
        "misses": c.misses,
        "fetched": c.fetched,
        "bytes_fetched": c.bytes_fetched,
        "bytes_raw": c.bytes_raw,
        "refetched": c.refetched,
        "evicted": c.evicted,
        "peak_cache_bytes": c.peak_cache_bytes,
        "prefetched": c.prefetched,
        "voxels_lost": c.voxels_lost,
    })
}

fn name(s: &str) -> Name {
    Name::new(s).expect("fixed node names are valid")
}

fn shape(l: &LinkConfig) -> LinkShape {
    LinkShape {
        latency: l.latency(),
        jitter: l.jitter(),
        bandwidth_bps: l.bandwidth_bps(),
        loss: l.loss,
    }
}

/// Each store's modelled disk (`links.store_disk`).
fn store_disk(cfg: &Config) -> StoreDisk {
    StoreDisk {
        access_time: cfg.links.store_disk.access_time(),
        bandwidth_bps: cfg.links.store_disk.bandwidth_bps(),
    }
}

/// Where each voxel is fetched, from the config's shards.
pub fn store_routes(cfg: &Config) -> Result<StoreRoutes, ClusterError> {
    let stores = cfg
        .shards()?
        .into_iter()
        .enumerate()
        .map(|(i, (index, count))| (Shard { index, count }, names::store(i)))
        .collect();
    StoreRoutes::new(stores).map_err(|problem| {
        ClusterError::Config(dray_config::ConfigError::Invalid {
            key: "stores".into(),
            problem,
        })
    })
}

/// Whether the display runs interactively: no `render.camera_path` and a
/// web viewer (`display.web`), whose page then sends the camera moves.
pub fn interactive(cfg: &Config) -> bool {
    cfg.render.camera_path.is_none() && cfg.display.web.is_some()
}

/// The camera of every frame: the camera path's, `render.loops` times, or
/// the fixed camera `render.frames` times; interactive ([`interactive`]):
/// the fixed camera once, where the user starts.
pub fn frame_cameras(cfg: &Config) -> Result<Vec<Camera>, ClusterError> {
    if interactive(cfg) {
        return Ok(vec![wire_camera(&cfg.render.camera)]);
    }
    match &cfg.render.camera_path {
        Some(p) => {
            let once = CameraPath::load(p)
                .map_err(|e| ClusterError::CameraPath(e.to_string()))?
                .cameras();
            Ok(once.repeat(cfg.render.loops as usize))
        }
        None => Ok(vec![
            wire_camera(&cfg.render.camera);
            cfg.render.frames as usize
        ]),
    }
}

/// Checks what the config points at before anything starts, so that a
/// mistake stops startup with the key's name: each store's database (and
/// that it holds the store's shard) and the camera path (the display's).
/// `node` None: every node of the config; else (role, index).
pub fn preflight(cfg: &Config, node: Option<(Role, usize)>) -> Result<(), ClusterError> {
    let stores = match node {
        None => 0..cfg.stores.len(),
        Some((Role::Store, i)) => i..i + 1,
        Some(_) => 0..0,
    };
    let shards = cfg.shards()?;
    // Stores often share a database: each is opened once.
    let mut opened: std::collections::HashMap<&std::path::Path, dray_scene::db::Database> =
        std::collections::HashMap::new();
    for i in stores {
        let key = match cfg.stores.get(i).and_then(|s| s.database.as_ref()) {
            Some(_) => format!("stores[{i}].database"),
            None => "scene.database".into(),
        };
        let Some(&(index, count)) = shards.get(i) else {
            continue;
        };
        let bad = |problem| {
            ClusterError::Config(dray_config::ConfigError::Invalid {
                key: key.clone(),
                problem,
            })
        };
        let path = cfg.store_database(i);
        let db = match opened.entry(path) {
            std::collections::hash_map::Entry::Occupied(e) => e.into_mut(),
            std::collections::hash_map::Entry::Vacant(e) => {
                e.insert(dray_scene::db::Database::open(path).map_err(|e| bad(e.to_string()))?)
            }
        };
        crate::store::check_holds(db, Shard { index, count }).map_err(bad)?;
    }
    if matches!(node, None | Some((Role::Display, _))) {
        frame_cameras(cfg)?;
    }
    Ok(())
}

fn client_options(cfg: &Config, opts: &RunOptions) -> Result<ClientOptions, ClusterError> {
    let c = &cfg.clients;
    Ok(ClientOptions {
        threads: c.threads as usize,
        cache_bytes: cfg.cache_bytes(),
        miss_mode: match c.miss_mode {
            dray_config::MissMode::Suspend => dray_trace::tile::MissMode::Suspend,
            dray_config::MissMode::Block => dray_trace::tile::MissMode::Block,
        },
        max_inflight_fetches: c.max_inflight_fetches as usize,
        tiles_ahead: c.tiles_ahead as usize,
        max_tiles_ahead: c.most_tiles_ahead() as usize,
        preload: c.preload,
        pixel_compression: c.pixel_compression,
        corrupt_voxel: c.corrupt_voxel,
        isa: opts.isa.unwrap_or_else(Isa::detect),
        stores: store_routes(cfg)?,
        scheduler: names::scheduler(),
        display: names::display(),
        virtual_clock: opts.virtual_clock.map(|v| crate::costs::VirtualClock {
            cost: v.cost.scaled(c.speed, c.decode_speed),
            voxels: crate::client::shared_voxels::DecodedVoxels::new(),
            cores: v
                .host_cores
                .map(|n| std::sync::Arc::new(tokio::sync::Semaphore::new(n as usize))),
        }),
    })
}

/// The environment variable that gives a display node its web viewer's
/// token (`dray cluster` sets it, to print the viewer's address).
pub const WEB_TOKEN_ENV: &str = "DRAY_WEB_TOKEN";

pub(crate) fn display_options(
    cfg: &Config,
    opts: &RunOptions,
) -> Result<DisplayOptions, ClusterError> {
    let web = cfg.web_addr()?;
    Ok(DisplayOptions {
        assigner: names::assigner(),
        scheduler: names::scheduler(),
        width: cfg.render.width,
        height: cfg.render.height,
        cameras: {
            let mut cameras = frame_cameras(cfg)?;
            cameras.truncate(opts.max_frames.unwrap_or(usize::MAX).max(1));
            cameras
        },
        settings: crate::settings::wire_settings(&cfg.render),
        max_samples: cfg.display.max_samples,
        web_token: std::env::var(WEB_TOKEN_ENV).ok(),
        interactive: interactive(cfg),
        frames_ahead: cfg.display.frames_ahead as usize,
        output: cfg.display.output.clone(),
        // An interactive run writes its metrics, not a file per frame.
        save_frames: cfg.display.save_frames && !interactive(cfg),
        keep_frames: opts.keep_frames,
        keep_metrics: opts.keep_frame_metrics && !interactive(cfg),
        web,
        samples: cfg.render.samples,
    })
}

/// The scheduler node's three actors.
pub(crate) struct SchedulerTasks {
    pub(crate) scheduler: JoinHandle<Result<SchedulerSummary, ActorError>>,
    pub(crate) assigner: JoinHandle<Result<(), ActorError>>,
    prefetcher: Option<JoinHandle<Result<crate::scheduler::PrefetcherSummary, ActorError>>>,
}

/// Actor `actor`'s mailbox on `bus`, holding `capacity` messages.
pub(crate) fn open_mailbox(
    bus: &Bus,
    actor: &str,
    capacity: usize,
) -> Result<Mailbox, ClusterError> {
    bus.mailbox(name(actor), capacity)
        .map_err(|e| node_err(bus.node(), e))
}

pub(crate) fn scheduler_mailboxes(bus: &Bus) -> Result<[Mailbox; 3], ClusterError> {
    Ok([
        open_mailbox(bus, names::SCHEDULER, MAILBOX)?,
        open_mailbox(bus, names::ASSIGNER, MAILBOX)?,
        open_mailbox(bus, names::PREFETCHER, MAILBOX)?,
    ])
}

pub(crate) fn spawn_scheduler(
    cfg: &Config,
    boxes: [Mailbox; 3],
) -> Result<SchedulerTasks, ClusterError> {
    let [sched, assign, prefetch] = boxes;
    let prefetcher = cfg.prefetch.enabled.then(names::prefetcher);
    let scheduler = tokio::spawn(run_scheduler(
        sched,
        SchedulerOptions {
            tile_size: cfg.render.tile_size,
            policy: cfg.scheduler.policy,
            costliest_first: cfg.scheduler.costliest_first,
            max_block_px: cfg.scheduler.max_block_px,
            tile_deadline: Duration::from_millis(cfg.scheduler.tile_deadline_ms),
            display: names::display(),
            assigner: names::assigner(),
            prefetcher: prefetcher.clone(),
            seed: 0x5eed,
        },
    ));
    let assigner = tokio::spawn(run_assigner(
        assign,
        AssignerOptions {
            scheduler: names::scheduler(),
            prefetcher: prefetcher.clone(),
            width: cfg.render.width,
            height: cfg.render.height,
            settings: wire_settings(&cfg.render),
        },
    ));
    let prefetcher = if cfg.prefetch.enabled {
        Some(tokio::spawn(run_prefetcher(
            prefetch,
            PrefetcherOptions {
                stores: store_routes(cfg)?,
                step: cfg.prefetch.step,
                voxels_per_ray: cfg.prefetch.voxels_per_ray,
                width: cfg.render.width,
                height: cfg.render.height,
                policy: cfg.scheduler.policy,
            },
        )))
    } else {
        None
    };
    Ok(SchedulerTasks {
        scheduler,
        assigner,
        prefetcher,
    })
}

fn store_options(cfg: &Config, i: usize) -> Result<StoreOptions, ClusterError> {
    let (index, count) = cfg.shards()?[i];
    Ok(StoreOptions {
        database: cfg.store_database(i).to_path_buf(),
        shard: Shard { index, count },
        max_concurrent: cfg.stores[i].max_concurrent as usize,
        disk: store_disk(cfg),
    })
}

/// Every actor of every node, to tell them all to stop.
fn every_actor(cfg: &Config, clients: u32) -> Vec<Address> {
    let mut v = vec![names::scheduler(), names::assigner(), names::prefetcher()];
    v.extend((0..cfg.stores.len()).map(names::store));
    v.extend((0..clients as usize).map(names::client));
    v
}

async fn shutdown_all(mb: &Mailbox, to: &[Address], reason: &str) {
    for a in to {
        let msg = Message::Shutdown(Shutdown {
            reason: reason.into(),
        });
        if let Err(e) = mb.send(a, msg).await {
            // A node that is already gone needs no telling.
            tracing::debug!(to = %a, error = %e, "shutdown not delivered");
        }
    }
}

pub(crate) async fn joined<T>(
    what: &str,
    h: JoinHandle<Result<T, ActorError>>,
) -> Result<T, ClusterError> {
    match h.await {
        Ok(r) => Ok(r?),
        Err(e) => Err(ClusterError::Node {
            node: what.into(),
            message: format!("actor task failed: {e}"),
        }),
    }
}

/// Runs every node of `cfg` in this process over the in-process transport,
/// with the config's link shaping, until the display has every frame.
pub async fn sim(cfg: &Config, opts: &RunOptions) -> Result<RunSummary, ClusterError> {
    preflight(cfg, None)?;
    let clients = opts.clients.unwrap_or(cfg.clients.count);
    let net = InProcNet::new();
    let add = |n: Name, role: Role| net.add_node(n.clone(), role).map_err(|e| node_err(&n, e));
    let sched_bus = add(name("scheduler"), Role::Scheduler)?;
    let display_bus = add(name("display"), Role::Display)?;
    let store_buses = (0..cfg.stores.len())
        .map(|i| add(names::store_node(i), Role::Store))
        .collect::<Result<Vec<_>, _>>()?;
    let client_buses = (0..clients as usize)
        .map(|i| add(names::client_node(i), Role::Client))
        .collect::<Result<Vec<_>, _>>()?;
    let links = &cfg.links;
    let set = |a: &Bus, b: &Bus, l: &LinkConfig| {
        if l.is_shaped() {
            net.set_shape(a.node(), b.node(), shape(l))
                .map_err(|e| node_err(a.node(), e))
        } else {
            Ok(())
        }
    };
    for c in &client_buses {
        for s in &store_buses {
            set(c, s, &links.client_store)?;
        }
        set(c, &sched_bus, &links.client_scheduler)?;
        set(c, &display_bus, &links.client_scheduler)?;
    }
    set(&display_bus, &sched_bus, &links.display)?;
    let set_node = |bus: &Bus, side: NodeLink, l: &LinkConfig| {
        if l.is_shaped() {
            net.set_node_link(bus.node(), side, shape(l))
                .map_err(|e| node_err(bus.node(), e))
        } else {
            Ok(())
        }
    };
    for s in &store_buses {
        set_node(s, NodeLink::Uplink, &links.store_uplink)?;
    }
    for c in &client_buses {
        set_node(c, NodeLink::Downlink, &links.client_downlink)?;
    }

    // Every mailbox exists before any actor sends.
    let sched_boxes = scheduler_mailboxes(&sched_bus)?;
    let display_box = open_mailbox(&display_bus, names::DISPLAY, MAILBOX)?;
    let control = open_mailbox(&display_bus, "sim", 16)?;
    let store_boxes = store_buses
        .iter()
        .map(|b| open_mailbox(b, names::STORE, MAILBOX))
        .collect::<Result<Vec<_>, _>>()?;
    let client_boxes = client_buses
        .iter()
        .map(|b| open_mailbox(b, names::CLIENT, MAILBOX))
        .collect::<Result<Vec<_>, _>>()?;

    let stores: Vec<_> = store_boxes
        .into_iter()
        .enumerate()
        .map(|(i, mb)| {
            let opts = store_options(cfg, i)?;
            Ok(tokio::spawn(run_store(mb, opts)))
        })
        .collect::<Result<_, ClusterError>>()?;
    let sched = spawn_scheduler(cfg, sched_boxes)?;
    let copts = client_options(cfg, opts)?;
    // On the virtual clock a client's render threads are tasks of its own
    // thread (`spawn_local`), so the client is one too.
    let client_tasks: Vec<_> = client_boxes
        .into_iter()
        .map(|mb| match copts.virtual_clock {
            Some(_) => tokio::task::spawn_local(run_client(mb, copts.clone())),
            None => tokio::spawn(run_client(mb, copts.clone())),
        })
        .collect();
    info!(clients, stores = stores.len(), "simulated cluster started");
    // A stop signal ends the display (an interactive run has no other end
    // here) with the summary of what it showed; the others are then stopped.
    let mut signals = StopSignals::new().map_err(|e| ClusterError::Node {
        node: "sim".into(),
        message: format!("cannot catch SIGINT, SIGTERM and SIGHUP: {e}"),
    })?;
    let stop = async {
        signals.next().await;
    };
    let display = run_display_until(display_box, display_options(cfg, opts)?, stop).await;
    shutdown_all(&control, &every_actor(cfg, clients), "the run is over").await;
    let display = display?;
    let scheduler = joined("scheduler", sched.scheduler).await?;
    joined("assigner", sched.assigner).await?;
    if let Some(p) = sched.prefetcher {
        joined("prefetcher", p).await?;
    }
    let mut client_summaries = Vec::new();
    for (i, t) in client_tasks.into_iter().enumerate() {
        client_summaries.push(joined(&format!("client-{i}"), t).await?);
    }
    let mut store_summaries = Vec::new();
    for (i, t) in stores.into_iter().enumerate() {
        store_summaries.push(joined(&format!("store-{i}"), t).await?);
    }
    drop((sched_bus, client_buses, store_buses, display_bus, net));
    Ok(RunSummary {
        display,
        scheduler,
        clients: client_summaries,
        stores: store_summaries,
    })
}

/// [`sim`] on the virtual clock: a fresh single-threaded runtime whose
/// clock is paused, so that time moves only by the cost model's charges,
/// the links' and disks' models and the actors' own timers; waiting for
/// real work (a blocking read, a decode) never moves it. Every client's
/// rendering is real, and all of it runs on the calling thread. Errors as
/// [`sim`]'s.
pub fn sim_virtual(
    cfg: &Config,
    opts: &RunOptions,
    run: crate::costs::VirtualRun,
) -> Result<RunSummary, ClusterError> {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .start_paused(true)
        .build()
        .map_err(|e| ClusterError::Node {
            node: "sim".into(),
            message: format!("cannot start the virtual runtime: {e}"),
        })?;
    let opts = RunOptions {
        virtual_clock: Some(run),
        ..opts.clone()
    };
    let _virtual = crate::on_virtual_clock();
    tokio::task::LocalSet::new().block_on(&rt, sim(cfg, &opts))
}

/// The node a role and index name.
pub fn node_name(role: Role, index: usize) -> Result<Name, String> {
    match role {
        Role::Scheduler => Ok(name("scheduler")),
        Role::Display => Ok(name("display")),
        Role::Store => Ok(names::store_node(index)),
        Role::Client => Ok(names::client_node(index)),
        Role::Tool => Err("a tool is not a node of the cluster".into()),
    }
}

/// What one node did, for its process to print.
#[derive(Debug)]
pub enum NodeOutcome {
    /// The display's run.
    Display(Box<DisplaySummary>),
    /// Another node stopped when told to.
    Stopped,
}

/// Port 0 on the loopback address of `addr`'s family: for a socket that
/// only a relay on this machine talks to.
fn loopback_like(addr: SocketAddr) -> SocketAddr {
    let ip: std::net::IpAddr = if addr.is_ipv4() {
        std::net::Ipv4Addr::LOCALHOST.into()
    } else {
        std::net::Ipv6Addr::LOCALHOST.into()
    };
    SocketAddr::new(ip, 0)
}

/// How long a node waits for its own address's host name to resolve.
const LOOKUP_PATIENCE: Duration = Duration::from_secs(120);

/// Looks `target` up, again and again for up to [`LOOKUP_PATIENCE`],
/// saying every 10 s that it is still waiting; `key` names it.
async fn resolve_waiting(target: &DialTarget, key: &str) -> Result<SocketAddr, String> {
    let start = tokio::time::Instant::now();
    let mut said = start;
    loop {
        match target.resolve().await {
            Ok(a) => return Ok(a),
            Err(e) if start.elapsed() >= LOOKUP_PATIENCE => {
                return Err(format!(
                    "{key}: {e} (waited {}s)",
                    LOOKUP_PATIENCE.as_secs()
                ))
            }
            Err(e) => {
                if said.elapsed() >= Duration::from_secs(10) {
                    warn!(%key, error = %e, waited_s = start.elapsed().as_secs(), "still waiting for the name to resolve");
                    said = tokio::time::Instant::now();
                }
                tokio::time::sleep(Duration::from_millis(500)).await;
            }
        }
    }
}

/// A QUIC transport and the relays its shaped dials go through.
struct Links {
    transport: std::sync::Arc<QuicTransport>,
    _relays: Vec<UdpRelay>,
    dialed: Vec<Name>,
    /// This node's downlink, shared by the relays of all its dials.
    downlink: Option<SharedShaper>,
}

impl Links {
    async fn dial(&mut self, peer: Name, target: DialTarget, l: &LinkConfig) -> Result<(), String> {
        let target = if l.is_shaped() || self.downlink.is_some() {
            // A relay forwards to one address: the name is looked up once.
            let addr = target
                .resolve()
                .await
                .map_err(|e| format!("relay to {peer}: {e}"))?;
            // The relay runs on this machine, whatever the peer's.
            let shaping = RelayShaping {
                to_upstream: shape(l),
                to_client: shape(l),
                shared_to_client: self.downlink.clone(),
                ..RelayShaping::default()
            };
            let relay = UdpRelay::start_shaped(loopback_like(addr), addr, shaping)
                .await
                .map_err(|e| format!("relay to {peer}: {e}"))?;
            let a = relay.local_addr();
            self._relays.push(relay);
            DialTarget::Addr(a)
        } else {
            target
        };
        self.transport.connect(peer.clone(), target);
        self.dialed.push(peer);
        Ok(())
    }
}

/// Runs one node of `cfg` over QUIC until it is told to stop (or, for the
/// display, until every frame is in; it then stops the others). Prints
/// `ready NODE` on stdout once its connections are up, which
/// `dray cluster` waits for.
pub async fn node(
    cfg: &Config,
    role: Role,
    index: usize,
    opts: &RunOptions,
) -> Result<NodeOutcome, ClusterError> {
    let clients = opts.clients.unwrap_or(cfg.clients.count);
    let me = node_name(role, index).map_err(|m| ClusterError::Node {
        node: role.to_string(),
        message: m,
    })?;
    // Caught from the start: a launcher may stop a node still waiting for
    // its peers.
    let mut signals = StopSignals::new()
        .map_err(|e| node_err(&me, format!("cannot catch SIGINT, SIGTERM and SIGHUP: {e}")))?;
    match role {
        Role::Store if index >= cfg.stores.len() => {
            return Err(node_err(
                &me,
                format!("the config has {} stores", cfg.stores.len()),
            ))
        }
        Role::Client if index >= clients as usize => {
            return Err(node_err(&me, format!("the config has {clients} clients")))
        }
        _ => {}
    }
    preflight(cfg, Some((role, index)))?;
    let bus = Bus::new(me.clone(), role);
    let identity = NodeIdentity::load(&cfg.certs.dir, &me).map_err(|e| {
        node_err(
            &me,
            format!(
                "certs.dir {}: {e} (make them with `dray certs init DIR --config CONFIG`)",
                cfg.certs.dir.display()
            ),
        )
    })?;
    let listen_key = match role {
        Role::Scheduler => "scheduler.address".to_string(),
        Role::Display => "display.address".to_string(),
        Role::Store => format!("stores[{index}].address"),
        _ => "clients.bind".to_string(),
    };
    let bind_err = |addr: SocketAddr,
                    what: &str,
                    e: &dyn std::fmt::Display,
                    io: Option<&std::io::Error>| {
        if io.is_some_and(|io| io.kind() == std::io::ErrorKind::AddrInUse) {
            ClusterError::AddressInUse {
                node: me.to_string(),
                addr,
                key: listen_key.clone(),
            }
        } else if io.is_some_and(|io| io.kind() == std::io::ErrorKind::AddrNotAvailable) {
            node_err(
                    &me,
                    format!("{what} {addr}: {e}: the address is not this host's (change {listen_key} in the config, or start this node on its host)"),
                )
        } else {
            node_err(&me, format!("{what} {addr}: {e}"))
        }
    };
    // A host name may not resolve yet where a launcher starts every node
    // at once (a Kubernetes pod's name appears once the pod runs); a
    // client looks the scheduler up to bind the same address family.
    let own = match role {
        Role::Display => Listener::Display,
        Role::Store => Listener::Store(index),
        _ => Listener::Scheduler,
    };
    let (host, port) = cfg.host_port(own)?;
    let (own_target, own_key) = (DialTarget::new(&host, port), own.key());
    let resolved = tokio::select! {
        r = resolve_waiting(&own_target, &own_key) => {
            r.map_err(|m| node_err(&me, m))?
        }
        signal = signals.next() => {
            warn!(node = %me, signal, "stopped while starting");
            return Ok(NodeOutcome::Stopped);
        }
    };
    let listen = match role {
        Role::Scheduler | Role::Display | Role::Store => resolved,
        _ => SocketAddr::new(cfg.client_bind(resolved)?, 0),
    };
    // Mailboxes before the transport: nothing may arrive for an actor that
    // does not exist yet.
    let boxes = match role {
        Role::Scheduler => RoleBoxes::Scheduler(scheduler_mailboxes(&bus)?),
        _ => {
            let actor = match role {
                Role::Store => names::STORE,
                Role::Client => names::CLIENT,
                _ => names::DISPLAY,
            };
            RoleBoxes::One(open_mailbox(&bus, actor, MAILBOX)?)
        }
    };
    // A store with a shaped uplink listens behind a relay of its own on its
    // address, so that every peer's traffic crosses the one shared link.
    let uplink = (role == Role::Store && cfg.links.store_uplink.is_shaped())
        .then(|| shared_link(shape(&cfg.links.store_uplink), index as u64 + 1));
    let quic_listen = if uplink.is_some() {
        loopback_like(listen)
    } else {
        listen
    };
    let transport = QuicTransport::start(&bus, &identity, quic_listen)
        .await
        .map_err(|e| {
            let io = match &e {
                QuicError::Io(io) => Some(io),
                _ => None,
            };
            bind_err(quic_listen, "listening on", &e, io)
        })?;
    let mut links = Links {
        transport: transport.clone(),
        _relays: Vec::new(),
        dialed: Vec::new(),
        downlink: (role == Role::Client && cfg.links.client_downlink.is_shaped())
            .then(|| shared_link(shape(&cfg.links.client_downlink), index as u64 + 1)),
    };
    if let Some(uplink) = uplink {
        let node = transport.local_addr().map_err(|e| node_err(&me, e))?;
        let shaping = RelayShaping {
            shared_to_client: Some(uplink),
            ..RelayShaping::default()
        };
        let relay = UdpRelay::start_shaped(listen, node, shaping)
            .await
            .map_err(|e| bind_err(listen, "uplink relay on", &e, Some(&e)))?;
        links._relays.push(relay);
    }
    let unshaped = LinkConfig::default();
    let dial_stores = |l: &LinkConfig| {
        (0..cfg.stores.len())
            .map(|i| (names::store_node(i), Listener::Store(i), *l))
            .collect::<Vec<_>>()
    };
    let dials: Vec<(Name, Listener, LinkConfig)> = match role {
        Role::Scheduler => dial_stores(&unshaped),
        Role::Display => {
            let mut v = vec![(name("scheduler"), Listener::Scheduler, cfg.links.display)];
            v.extend(dial_stores(&unshaped));
            v
        }
        Role::Client => {
            let mut v = vec![
                (
                    name("scheduler"),
                    Listener::Scheduler,
                    cfg.links.client_scheduler,
                ),
                (
                    name("display"),
                    Listener::Display,
                    cfg.links.client_scheduler,
                ),
            ];
            v.extend(dial_stores(&cfg.links.client_store));
            v
        }
        _ => Vec::new(),
    };
    let connected = async {
        for (peer, listener, l) in dials {
            let (host, port) = cfg.host_port(listener)?;
            links
                .dial(peer, DialTarget::new(&host, port), &l)
                .await
                .map_err(|m| node_err(&me, m))?;
        }
        for peer in links.dialed.clone() {
            wait_logged(&transport, &bus, &peer)
                .await
                .map_err(|e| node_err(&me, e))?;
        }
        if role == Role::Display {
            // The walk starts once every client has joined.
            wait_for_clients(&bus, clients as usize).await;
        }
        Ok::<(), ClusterError>(())
    };
    tokio::select! {
        r = connected => r?,
        signal = signals.next() => {
            warn!(node = %me, signal, "stopped while starting");
            transport.shutdown().await;
            return Ok(NodeOutcome::Stopped);
        }
    }
    println!("ready {me}");
    use std::io::Write;
    let _ = std::io::stdout().flush();

    let outcome = if role == Role::Display {
        // The display ends cleanly on a stop signal (see run_role).
        let stop = async {
            let signal = signals.next().await;
            info!(node = %me, signal, "stopping");
        };
        run_role(cfg, opts, &bus, boxes, index, clients, stop).await
    } else {
        tokio::select! {
            r = run_role(cfg, opts, &bus, boxes, index, clients, std::future::pending()) => r,
            signal = signals.next() => {
                warn!(node = %me, signal, "stopped");
                Ok(NodeOutcome::Stopped)
            }
        }
    };
    transport.shutdown().await;
    outcome
}

/// The mailboxes of one node's actors.
enum RoleBoxes {
    Scheduler([Mailbox; 3]),
    One(Mailbox),
}

/// Waits for the connection to `peer`, saying every few seconds why the
/// last dial failed; fails at once when the certificates do not match
/// (another CA), which waiting cannot mend.
async fn wait_logged(transport: &QuicTransport, bus: &Bus, peer: &Name) -> Result<(), String> {
    let mut waited = 0u32;
    loop {
        match tokio::time::timeout(Duration::from_secs(5), transport.wait_connected(peer)).await {
            Ok(r) => return r.map_err(|e| e.to_string()),
            Err(_) => {
                waited += 5;
                let last = transport.dial_error(peer).unwrap_or_default();
                warn!(node = %bus.node(), %peer, seconds = waited, last_error = %last, "still waiting for a connection");
            }
        }
    }
}

async fn wait_for_clients(bus: &Bus, n: usize) {
    let mut last = usize::MAX;
    loop {
        let have = bus
            .peers()
            .iter()
            .filter(|(_, r)| *r == Role::Client)
            .count();
        if have >= n {
            return;
        }
        if have != last {
            info!(joined = have, expected = n, "waiting for clients");
            last = have;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Runs the node's actors; `stop` ends the display cleanly.
async fn run_role(
    cfg: &Config,
    opts: &RunOptions,
    bus: &Bus,
    boxes: RoleBoxes,
    index: usize,
    clients: u32,
    stop: impl std::future::Future<Output = ()>,
) -> Result<NodeOutcome, ClusterError> {
    match (bus.role(), boxes) {
        (Role::Scheduler, RoleBoxes::Scheduler(b)) => {
            let t = spawn_scheduler(cfg, b)?;
            joined("scheduler", t.scheduler).await?;
            joined("assigner", t.assigner).await?;
            if let Some(p) = t.prefetcher {
                joined("prefetcher", p).await?;
            }
            Ok(NodeOutcome::Stopped)
        }
        (Role::Store, RoleBoxes::One(mb)) => {
            run_store(mb, store_options(cfg, index)?).await?;
            Ok(NodeOutcome::Stopped)
        }
        (Role::Client, RoleBoxes::One(mb)) => {
            run_client(mb, client_options(cfg, opts)?).await?;
            Ok(NodeOutcome::Stopped)
        }
        (Role::Display, RoleBoxes::One(mb)) => {
            let control = open_mailbox(bus, "control", 16)?;
            // A stop signal ends the display cleanly (it is how an
            // interactive run ends): the others are stopped and the summary
            // printed.
            let summary = run_display_until(mb, display_options(cfg, opts)?, stop).await;
            shutdown_all(&control, &every_actor(cfg, clients), "the run is over").await;
            // Give the shutdown messages time to leave before the
            // transport closes.
            tokio::time::sleep(Duration::from_millis(200)).await;
            Ok(NodeOutcome::Display(Box::new(summary?)))
        }
        (role, _) => Err(ClusterError::Node {
            node: bus.node().to_string(),
            message: format!("no actors for role {role}"),
        }),
    }
}

#[cfg(test)]
mod report_tests {
    use super::*;

    #[test]
    fn a_clients_report_names_each_count() {
        let c = ClientSummary {
            tiles: 3,
            bytes_raw: 4096,
            voxels_lost: 1,
            ..ClientSummary::default()
        };
        let j = client_json(&c);
        assert_eq!(j["tiles"], 3);
        assert_eq!(j["bytes_raw"], 4096);
        assert_eq!(j["voxels_lost"], 1);
        assert_eq!(j.as_object().unwrap().len(), 11);
    }
}
