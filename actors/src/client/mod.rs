//! The Client actor: voxel cache, loader and render threads.
//!
//! At start the client asks a store for the manifest (the high-level BSP
//! and the voxel table), then asks the scheduler for `threads +
//! tiles_ahead` tiles. Each `AssignTile` goes to the least busy render
//! thread (`worker`); finished tiles go to the display (`TileDone`),
//! which reports them to the scheduler, and the scheduler is asked for as
//! many more tiles: one at a time, or in batches when several tiles are
//! asked for ahead (`batch`). Where a render thread runs out of tiles
//! before the next one comes, the client asks for more ahead, up to
//! `max_tiles_ahead` (`ahead`).
//! Voxels come through the `loader` into the [`cache`], shared by every
//! render thread.
//!
//! The actor task itself only does bookkeeping: messages go out through
//! sender tasks, blobs are decoded on tokio's blocking pool, and tracing
//! runs on the render threads, so the mailbox is always served promptly.
//!
//! Shape: once it has the manifest and the scheduler is connected,
//! `state::Client` owns the client's state (the loader, the tiles held
//! and asked for, the batch); its handlers (a tile assigned, a voxel wanted,
//! arrived, decoded or refused, a hint, a ping, a peer up or down, tiles
//! finished, the retry tick) push effects (`state::Out`: send a message on
//! one of the ordered queues, fetch a voxel, decode a blob, hand a thread a
//! tile, resize the threads' groups); [`run_client`] receives, calls the
//! handler and carries the effects out.

mod ahead;
mod batch;
pub mod cache;
mod loader;
pub mod shared_voxels;
mod state;
mod worker;

pub use loader::{FETCH_TIMEOUT, MAX_TRIES, RETRY_DELAY};

use crate::costs::VirtualClock;
use crate::names::StoreRoutes;
use crate::ActorError;
use cache::VoxelCache;
use dray_protocol::{Address, Compression, FetchManifest, FetchVoxel, Message, MAX_REPORT_HITS};
use dray_runtime::{ActorRef, Delivery, LinkMeter, Mailbox};
use dray_scene::db::manifest::Manifest;
use dray_trace::accel::TopLevel;
use dray_trace::tile::MissMode;
use loader::{Decoded, Shared};
use state::{Client, Out};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use tokio::sync::mpsc;
use tokio::time::{timeout, timeout_at, Duration, Instant};
use tracing::{debug, info, warn};
use worker::{render_loop, render_thread, Meter, TileJob, TileResult, WorkerCtx};

/// How long to wait for a store's manifest before asking another store.
pub const MANIFEST_TIMEOUT: Duration = Duration::from_secs(5);
/// How often retries and fetch timeouts are looked at.
const TICK: Duration = Duration::from_millis(20);
/// Pixels between a tile's hit samples, along x and y.
const HIT_SPACING: u32 = 16;
/// Most hit samples along a side: the largest grid a report carries.
const HIT_GRID_MAX: u32 = 16;
const _: () = assert!((HIT_GRID_MAX * HIT_GRID_MAX) as usize <= MAX_REPORT_HITS);

/// How a client runs.
#[derive(Clone, Debug)]
pub struct ClientOptions {
    /// Render threads.
    pub threads: usize,
    /// Voxel cache budget in bytes (of prepared voxels).
    pub cache_bytes: u64,
    /// Suspend packets on a miss, or block the thread (the baseline).
    pub miss_mode: MissMode,
    /// Most voxel fetches in flight or being decoded at once.
    pub max_inflight_fetches: usize,
    /// Tiles asked for beyond one per thread (latency hiding), at first
    /// and at least.
    pub tiles_ahead: usize,
    /// Most tiles asked for ahead: the client asks for more than
    /// `tiles_ahead` while its threads run out of work (`ahead`; suspend
    /// mode only); equal to `tiles_ahead`, it asks for exactly that many.
    pub max_tiles_ahead: usize,
    /// Fetch every voxel that fits the cache before asking for tiles.
    pub preload: bool,
    /// How finished tiles' pixels are compressed (where that makes them
    /// smaller).
    pub pixel_compression: Compression,
    /// The tracing kernel.
    pub isa: dray_trace::render::Isa,
    /// Where voxels come from.
    pub stores: StoreRoutes,
    /// The scheduler's address.
    pub scheduler: Address,
    /// The display's address.
    pub display: Address,
    /// A voxel no store serves intact: fail its tiles (the display ends
    /// the run) or render it as empty.
    pub corrupt_voxel: dray_config::CorruptVoxel,
    /// Run on the virtual clock: render threads are tasks charged by the
    /// cost model, and decodes share their voxels with the process's
    /// other clients ([`crate::costs`]).
    pub virtual_clock: Option<VirtualClock>,
}

/// Checks a blob against its manifest entry, decodes and prepares it, as
/// the client does (for calibrating what that costs).
pub fn decode_voxel(
    id: u32,
    entry: &dray_scene::db::manifest::VoxelEntry,
    blob: &[u8],
) -> Result<std::sync::Arc<dray_trace::accel::PreparedVoxel>, String> {
    loader::decode(id, entry, blob)
}

/// What a client did, returned when it stops.
#[derive(Clone, Debug, Default)]
pub struct ClientSummary {
    /// Tiles rendered.
    pub tiles: u64,
    /// Rays traced (primary, shadow, reflection).
    pub rays: u64,
    /// Times a packet met a missing voxel.
    pub misses: u64,
    /// Voxels fetched (and verified).
    pub fetched: u64,
    /// Compressed bytes of those voxels.
    pub bytes_fetched: u64,
    /// The same voxels' bytes after decompression (the blobs' raw sizes).
    pub bytes_raw: u64,
    /// Voxels fetched again after they had been evicted.
    pub refetched: u64,
    /// Voxels evicted from the cache.
    pub evicted: u64,
    /// The most bytes the cache held at once.
    pub peak_cache_bytes: u64,
    /// Voxels fetched because of a prefetch hint.
    pub prefetched: u64,
    /// Voxels fetched by the preload, before the first tile.
    pub preloaded: u64,
    /// Voxels no store served intact (rendered as empty when
    /// `clients.corrupt_voxel` is "skip").
    pub voxels_lost: u64,
    /// CPU time of the render threads (OS threads only; none on the
    /// virtual clock), seconds.
    pub render_cpu_s: f64,
}

/// Sends messages in order from a task of their own, so that the actor
/// loop never waits on a slow peer; failures are logged, the first to a
/// peer as a warning and the rest until a send there succeeds again at
/// debug level (a run that ends leaves many tiles with no one to take
/// them).
fn sender(me: ActorRef, what: &'static str) -> mpsc::UnboundedSender<(Address, Message)> {
    let (tx, mut rx) = mpsc::unbounded_channel::<(Address, Message)>();
    tokio::spawn(async move {
        let mut failing = std::collections::HashSet::new();
        while let Some((to, msg)) = rx.recv().await {
            let kind = msg.kind().name();
            match me.send(&to, msg).await {
                Ok(()) => {
                    failing.remove(&to);
                }
                Err(e) if failing.contains(&to) => {
                    debug!(%to, kind, error = %e, "{what}: sending failed again");
                }
                Err(e) => {
                    warn!(%to, kind, error = %e, "{what}: sending failed (more to this peer at debug level)");
                    failing.insert(to);
                }
            }
        }
    });
    tx
}

/// Where the client's effects go: three ordered send queues, the
/// decoders on the blocking pool, and the render threads.
struct Outlets {
    /// Control messages: the first requests for work, pongs, lost voxels.
    control: mpsc::UnboundedSender<(Address, Message)>,
    /// Finished tiles' pixels and then the request for as many new tiles,
    /// a batch at a time ([`batch`]): a client that dies with pixels still
    /// queued has the tile reassigned instead of lost, and a display slow
    /// to take tiles slows the requests too, which bounds the queue.
    tiles: mpsc::UnboundedSender<(Address, Message)>,
    fetches: mpsc::UnboundedSender<(Address, Message)>,
    decoded: mpsc::UnboundedSender<Decoded>,
    /// Each render thread's queue of tiles.
    threads: Vec<mpsc::UnboundedSender<TileJob>>,
    /// On the virtual clock: the client's work beside its render threads.
    virtual_lane: Option<VirtualLane>,
    group: Arc<AtomicUsize>,
    in_progress: Arc<AtomicUsize>,
}

/// On the virtual clock, what a client's machine does beside tracing,
/// charged in order on one lane: decoding a voxel (delivered when done),
/// and where the clients share one host, what its other actors spend on
/// finished tiles. One lane, not a timer each, so that tokio's
/// whole-millisecond timers round its total once, not every item.
enum Background {
    Decode(Duration, Decoded),
    Host(Duration),
}

/// The virtual clock's model and the lane that charges what it prices.
struct VirtualLane {
    clock: VirtualClock,
    work: mpsc::UnboundedSender<Background>,
}

async fn background_lane(
    mut work: mpsc::UnboundedReceiver<Background>,
    decoded: mpsc::UnboundedSender<Decoded>,
    cores: Option<Arc<tokio::sync::Semaphore>>,
) {
    let mut overslept = Duration::ZERO;
    while let Some(w) = work.recv().await {
        match w {
            Background::Decode(cost, d) => {
                worker::charge(cost, &mut overslept, cores.as_deref()).await;
                let _ = decoded.send(d);
            }
            Background::Host(cost) => worker::charge(cost, &mut overslept, cores.as_deref()).await,
        }
    }
}

impl Outlets {
    /// Carries out one effect; nothing here waits.
    fn carry(&self, o: Out) {
        match o {
            Out::Control(to, msg) => {
                let _ = self.control.send((to, msg));
            }
            Out::Tile(to, msg) => {
                let _ = self.tiles.send((to, msg));
            }
            Out::Fetch { to, id } => {
                let _ = self
                    .fetches
                    .send((to, Message::FetchVoxel(FetchVoxel { id })));
            }
            Out::Decode {
                id,
                store,
                entry,
                blob,
            } => {
                if let Some(lane) = &self.virtual_lane {
                    // Decoded here, shared, and delivered when the cost
                    // model says a decoder would be done.
                    let v = &lane.clock;
                    let decoded = Decoded {
                        id,
                        store,
                        bytes: blob.len() as u64,
                        result: v.voxels.get_or_decode(id, &entry, &blob),
                    };
                    let cost = v.cost.decode(entry.raw_bytes);
                    let _ = lane.work.send(Background::Decode(cost, decoded));
                    return;
                }
                let tx = self.decoded.clone();
                tokio::task::spawn_blocking(move || {
                    let result = loader::decode(id, &entry, &blob);
                    let bytes = blob.len() as u64;
                    let _ = tx.send(Decoded {
                        id,
                        store,
                        bytes,
                        result,
                    });
                });
            }
            Out::Render { thread, job } => {
                let _ = self.threads[thread].send(job);
            }
            Out::Ahead { group, in_progress } => {
                self.group.store(group, Ordering::Relaxed);
                self.in_progress.store(in_progress, Ordering::Relaxed);
            }
        }
    }
}

/// A render thread: an OS thread, or a task on the virtual clock.
enum RenderThread {
    Os(std::thread::JoinHandle<Duration>),
    Virtual(tokio::task::JoinHandle<()>),
}

enum Start<T> {
    Ready(T),
    Stop,
}

/// Asks the stores for the manifest until one answers.
async fn fetch_manifest(
    mb: &mut Mailbox,
    opts: &ClientOptions,
    actor: &str,
) -> Result<Start<Manifest>, ActorError> {
    let bus = mb.handle().bus().clone();
    let stores: Vec<Address> = opts.stores.all().cloned().collect();
    let mut next = 0;
    // Manifests that did not decode: another store is asked, until each
    // has sent a bad one twice.
    let mut unusable = 0;
    loop {
        let pick = (0..stores.len())
            .map(|k| (next + k) % stores.len())
            .find(|&i| bus.is_connected(&stores[i].node));
        let Some(i) = pick else {
            // No store connected: wait for one (or a shutdown).
            match timeout(Duration::from_millis(250), mb.recv()).await {
                Ok(None) => return Ok(Start::Stop),
                Ok(Some(Delivery::Message {
                    msg: Message::Shutdown(_),
                    ..
                })) => return Ok(Start::Stop),
                _ => continue,
            }
        };
        next = i + 1;
        let store = &stores[i];
        if let Err(e) = mb
            .send(store, Message::FetchManifest(FetchManifest {}))
            .await
        {
            warn!(%actor, %store, error = %e, "cannot ask for the manifest");
            tokio::time::sleep(Duration::from_millis(100)).await;
            continue;
        }
        let deadline = Instant::now() + MANIFEST_TIMEOUT;
        loop {
            match timeout_at(deadline, mb.recv()).await {
                Err(_) => {
                    warn!(%actor, %store, "no manifest in time; asking again");
                    break;
                }
                Ok(None) => return Ok(Start::Stop),
                Ok(Some(Delivery::Message { from, msg })) => match msg {
                    Message::ManifestData(m) => match Manifest::decode(&m.data.0) {
                        Ok(manifest) => {
                            info!(%actor, %from, voxels = manifest.voxels.len(), "manifest received");
                            return Ok(Start::Ready(manifest));
                        }
                        Err(e) => {
                            unusable += 1;
                            if unusable >= 2 * stores.len() {
                                return Err(ActorError::Peer {
                                    actor: actor.into(),
                                    message: format!("the manifest from {from} is unusable: {e}"),
                                });
                            }
                            warn!(%actor, %from, error = %e, "unusable manifest; asking another store");
                            break;
                        }
                    },
                    Message::Shutdown(_) => return Ok(Start::Stop),
                    other => debug!(%actor, kind = other.kind().name(), "ignored while starting"),
                },
                Ok(Some(Delivery::PeerDown { node, .. })) if node == store.node => break,
                Ok(Some(_)) => {}
            }
        }
    }
}

/// Waits until the scheduler is connected.
async fn wait_for_scheduler(mb: &mut Mailbox, opts: &ClientOptions) -> Start<()> {
    let bus = mb.handle().bus().clone();
    loop {
        if bus.is_connected(&opts.scheduler.node) {
            return Start::Ready(());
        }
        match timeout(Duration::from_millis(250), mb.recv()).await {
            Ok(None) => return Start::Stop,
            Ok(Some(Delivery::Message {
                msg: Message::Shutdown(_),
                ..
            })) => return Start::Stop,
            _ => {}
        }
    }
}

/// Runs a client until it gets [`Message::Shutdown`] or its mailbox
/// closes.
pub async fn run_client(mut mb: Mailbox, opts: ClientOptions) -> Result<ClientSummary, ActorError> {
    let actor = mb.address().to_string();
    let manifest = match fetch_manifest(&mut mb, &opts, &actor).await? {
        Start::Ready(m) => Arc::new(m),
        Start::Stop => return Ok(ClientSummary::default()),
    };
    let top = Arc::new(TopLevel::from_manifest(&manifest));
    if let Start::Stop = wait_for_scheduler(&mut mb, &opts).await {
        return Ok(ClientSummary::default());
    }

    let me = mb.handle();
    let mut links = LinkMeter::new(me.bus().clone());
    let cache = Arc::new(match &opts.virtual_clock {
        Some(v) => VoxelCache::sharing(manifest.voxels.len(), opts.cache_bytes, v.voxels.clone()),
        None => VoxelCache::new(manifest.voxels.len(), opts.cache_bytes),
    });
    let (req_tx, mut req_rx) = mpsc::unbounded_channel();
    let (decoded_tx, mut decoded_rx) = mpsc::unbounded_channel();
    let (done_tx, mut done_rx) = mpsc::unbounded_channel::<Vec<TileResult>>();
    let shared = Arc::new(Shared {
        cache: cache.clone(),
        requests: req_tx,
    });
    let mut out = Vec::new();
    let mut c = Client::new(actor.clone(), &opts, manifest, cache, &mut out);
    let stop = Arc::new(AtomicBool::new(false));
    let threads = opts.threads.max(1);
    let group = Arc::new(AtomicUsize::new(c.group()));
    let in_progress = Arc::new(AtomicUsize::new(c.in_progress()));
    let mut outlets = Outlets {
        control: sender(me.clone(), "control message"),
        tiles: sender(me.clone(), "finished tile"),
        fetches: sender(me.clone(), "voxel fetch"),
        virtual_lane: opts.virtual_clock.as_ref().map(|v| {
            let (work, rx) = mpsc::unbounded_channel();
            tokio::spawn(background_lane(rx, decoded_tx.clone(), v.cores.clone()));
            VirtualLane {
                clock: v.clone(),
                work,
            }
        }),
        decoded: decoded_tx,
        threads: Vec::with_capacity(threads),
        group: group.clone(),
        in_progress: in_progress.clone(),
    };
    let mut handles = Vec::with_capacity(threads);
    for i in 0..threads {
        let (tx, rx) = mpsc::unbounded_channel();
        let ctx = WorkerCtx {
            top: top.clone(),
            shared: shared.clone(),
            mode: opts.miss_mode,
            tiles_in_progress: in_progress.clone(),
            stop: stop.clone(),
            results: done_tx.clone(),
            group: group.clone(),
            cores: opts.virtual_clock.as_ref().and_then(|v| v.cores.clone()),
        };
        let h = match &opts.virtual_clock {
            Some(v) => RenderThread::Virtual(tokio::task::spawn_local(render_loop(
                ctx,
                i,
                rx,
                Meter::Model(v.cost),
            ))),
            None => RenderThread::Os(
                std::thread::Builder::new()
                    .name(format!("render-{i}"))
                    .spawn(move || render_thread(ctx, i, rx))
                    .map_err(|source| ActorError::Io {
                        actor: actor.clone(),
                        path: format!("render thread {i}"),
                        source,
                    })?,
            ),
        };
        outlets.threads.push(tx);
        handles.push(h);
    }
    drop((shared, done_tx));
    info!(%actor, threads, mode = ?opts.miss_mode, cache_bytes = opts.cache_bytes, "client ready");

    let mut link = || links.take();
    let mut tick = tokio::time::interval(TICK);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        c.ask_once_preloaded(&mut out);
        // Effects leave in the order the handlers pushed them.
        for o in out.drain(..) {
            outlets.carry(o);
        }
        tokio::select! {
            biased;
            d = mb.recv() => match d {
                None => break,
                Some(Delivery::Message { from, msg }) => match msg {
                    Message::AssignTile(a) => c.assign_tile(a, &mut out),
                    Message::VoxelLoaded(v) => c.voxel_loaded(from, v.id, v.data.0, &mut out),
                    Message::VoxelError(e) => c.voxel_refused(from, e, &mut out),
                    Message::PrefetchHint(h) => c.hint(&h.voxels.0, &mut out),
                    Message::Ping(p) => c.ping(from, p, &mut out),
                    Message::Shutdown(s) => {
                        info!(%actor, reason = %s.reason, "client stopping");
                        break;
                    }
                    other => debug!(%actor, kind = other.kind().name(), %from, "ignored"),
                },
                Some(Delivery::PeerUp { node, .. }) => c.peer_up(&node, &mut out),
                Some(Delivery::PeerDown { node, reason }) => c.peer_down(&node, &reason, &mut out),
            },
            Some(req) = req_rx.recv() => c.voxel_wanted(req, &mut out),
            Some(d) = decoded_rx.recv() => c.decoded(d, &mut out),
            Some(tiles) = done_rx.recv() => {
                let one_host = outlets.virtual_lane.as_ref().filter(|l| l.clock.cores.is_some());
                if let Some(lane) = one_host {
                    // What the host's other actors spend on these tiles
                    // takes its cores too.
                    let pixels = tiles.iter().map(|t| u64::from(t.job.tile.w) * u64::from(t.job.tile.h)).sum();
                    let _ = lane.work.send(Background::Host(lane.clock.cost.host(pixels)));
                }
                c.tiles_finished(tiles, &mut link, &mut out)
            }
            _ = tick.tick() => c.tick(&mut out),
        }
    }

    // Stop: no new tiles, every waiting packet gets an error, the threads
    // finish what they are doing and exit.
    stop.store(true, Ordering::Relaxed);
    c.stop();
    drop(outlets);
    drop(req_rx);
    drop(done_rx);
    let mut all_ok = true;
    let mut render_cpu = Duration::ZERO;
    for h in handles {
        all_ok &= match h {
            RenderThread::Os(h) => match tokio::task::spawn_blocking(move || h.join()).await {
                Ok(Ok(cpu)) => {
                    render_cpu += cpu;
                    true
                }
                _ => false,
            },
            RenderThread::Virtual(h) => h.await.is_ok(),
        };
    }
    if !all_ok {
        warn!(%actor, "a render thread panicked");
    }
    let summary = ClientSummary {
        render_cpu_s: render_cpu.as_secs_f64(),
        ..c.summary()
    };
    info!(%actor, ?summary, retries = c.retries(), "client stopped");
    Ok(summary)
}
