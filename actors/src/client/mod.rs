//! The Client actor: voxel cache, loader and render threads.
//!
//! At start the client asks a store for the manifest (the high-level BSP
//! and the voxel table), then asks the scheduler for `threads +
//! tiles_ahead` tiles. Each [`AssignTile`] goes to the least busy render
//! thread ([`worker`]); finished tiles go to the display ([`TileDone`]),
//! which reports them to the scheduler, and the scheduler is asked for as
//! many more tiles: one at a time, or in batches when several tiles are
//! asked for ahead ([`batch`]). Where a render thread runs out of tiles
//! before the next one comes, the client asks for more ahead, up to
//! `max_tiles_ahead` ([`ahead`]).
//! Voxels come through the [`loader`] into the [`cache`], shared by every
//! render thread.
//!
//! The actor task itself only does bookkeeping: messages go out through
//! sender tasks, blobs are decoded on tokio's blocking pool, and tracing
//! runs on the render threads, so the mailbox is always served promptly.

mod ahead;
mod batch;
pub mod cache;
mod loader;
mod worker;

pub use loader::{FETCH_TIMEOUT, MAX_TRIES, RETRY_DELAY};

use crate::names::StoreRoutes;
use crate::settings::{kernel_camera, kernel_settings};
use crate::ActorError;
use ahead::{Ahead, RoundTrips};
use batch::TileBatch;
use cache::VoxelCache;
use dray_protocol::{
    Address, AssignTile, BoundedVec, Compression, FetchManifest, Message, PackedF32, PackedU32,
    RequestWork, TileDone, TilePixels, TileStats, MAX_REPORT_HITS,
};
use dray_runtime::{ActorRef, Delivery, LinkMeter, Mailbox};
use dray_scene::db::manifest::Manifest;
use dray_trace::scene::TopLevel;
use dray_trace::tile::MissMode;
use loader::{Fetched, Loader, LostPolicy, Shared};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use tokio::sync::mpsc;
use tokio::time::{timeout, timeout_at, Duration, Instant};
use tracing::{debug, info, warn};
use worker::{render_thread, TileJob, TileResult, WorkerCtx};

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
    /// `tiles_ahead` while its threads run out of work ([`ahead`]; suspend
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
}

/// Sends messages in order from a task of their own, so that the actor
/// loop never waits on a slow peer; failures are logged.
fn sender(me: ActorRef, what: &'static str) -> mpsc::UnboundedSender<(Address, Message)> {
    let (tx, mut rx) = mpsc::unbounded_channel::<(Address, Message)>();
    tokio::spawn(async move {
        while let Some((to, msg)) = rx.recv().await {
            let kind = msg.kind().name();
            if let Err(e) = me.send(&to, msg).await {
                warn!(%to, kind, error = %e, "{what}: sending failed");
            }
        }
    });
    tx
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

/// A request for `n` more tiles, saying whether `cache` holds the whole
/// model (so that the scheduler may send blocks of any tiles).
fn request_work(n: usize, cache: &VoxelCache) -> Message {
    Message::RequestWork(RequestWork {
        slots: n.min(u16::MAX as usize) as u16,
        holds_model: cache.holds_all(),
    })
}

/// Runs a client until it gets [`Message::Shutdown`] or its mailbox
/// closes.
pub async fn run_client(mut mb: Mailbox, opts: ClientOptions) -> Result<ClientSummary, ActorError> {
    let actor = mb.address().to_string();
    let mut summary = ClientSummary::default();
    let manifest = match fetch_manifest(&mut mb, &opts, &actor).await? {
        Start::Ready(m) => Arc::new(m),
        Start::Stop => return Ok(summary),
    };
    let top = Arc::new(TopLevel::from_manifest(&manifest));
    let diagonal = manifest.model_bounds.diagonal();
    if let Start::Stop = wait_for_scheduler(&mut mb, &opts).await {
        return Ok(summary);
    }

    let me = mb.handle();
    let mut links = LinkMeter::new(me.bus().clone());
    let fetches = sender(me.clone(), "voxel fetch");
    // Finished tiles' pixels and the request for as many new tiles go out
    // in this order in one queue, a batch at a time ([`batch`]): the
    // scheduler counts a tile done only once its pixels have left (a client
    // that dies with pixels still queued has the tile reassigned instead of
    // lost), and it never sees more tiles asked for than the client holds.
    // A display slow to take tiles therefore slows the requests too, which
    // also bounds the queue. Other control messages (the first request,
    // pongs) go in their own.
    let results = sender(me.clone(), "control message");
    let pixels = sender(me.clone(), "finished tile");
    let cache = Arc::new(VoxelCache::new(manifest.voxels.len(), opts.cache_bytes));
    let (req_tx, mut req_rx) = mpsc::unbounded_channel();
    let (decoded_tx, mut decoded_rx) = mpsc::unbounded_channel();
    let (done_tx, mut done_rx) = mpsc::unbounded_channel::<Vec<TileResult>>();
    let mut loader = Loader::new(
        manifest.clone(),
        cache.clone(),
        opts.stores.clone(),
        opts.max_inflight_fetches,
        fetches,
        decoded_tx,
        LostPolicy {
            mode: opts.corrupt_voxel,
            report_to: opts.display.clone(),
            out: results.clone(),
        },
    );
    let shared = Arc::new(Shared {
        cache: cache.clone(),
        requests: req_tx,
    });
    let stop = Arc::new(AtomicBool::new(false));
    let threads = opts.threads.max(1);
    // A blocked thread renders one tile at a time whatever it holds: in
    // block mode (the demand-paging baseline) the client holds exactly
    // `tiles_ahead`, as such a client would.
    let most_ahead = match opts.miss_mode {
        MissMode::Suspend => opts.max_tiles_ahead,
        MissMode::Block => opts.tiles_ahead,
    };
    let mut ahead = Ahead::new(opts.tiles_ahead, most_ahead);
    let mut round_trips = RoundTrips::default();
    let mut batch = TileBatch::new(ahead.current());
    // Each thread's share of a batch.
    let group = Arc::new(AtomicUsize::new((batch.size() / threads).max(1)));
    let in_progress = Arc::new(AtomicUsize::new(1 + ahead.current()));
    let mut queues = Vec::with_capacity(threads);
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
        };
        let h = std::thread::Builder::new()
            .name(format!("render-{i}"))
            .spawn(move || render_thread(ctx, i, rx))
            .map_err(|source| ActorError::Io {
                actor: actor.clone(),
                path: format!("render thread {i}"),
                source,
            })?;
        queues.push(tx);
        handles.push(h);
    }
    drop((shared, done_tx));
    // Tiles to hold: one per thread and those asked ahead.
    let capacity = |ahead: &Ahead| threads + ahead.current();
    let mut busy = vec![0usize; threads];
    // Tiles assigned whose slots are not asked for again yet (being
    // rendered, queued, or finished and held for a batch).
    let mut outstanding = 0usize;
    // Slots asked for that the scheduler has not filled yet.
    let mut owed = 0usize;
    let mut scheduler_up = true;
    // Work is asked for once the preload (if any) is over.
    let mut asked_for_work = false;
    let preload_start = Instant::now();
    if opts.preload {
        loader.preload();
    }
    info!(%actor, threads, mode = ?opts.miss_mode, cache_bytes = opts.cache_bytes, "client ready");

    let mut tick = tokio::time::interval(TICK);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        if !asked_for_work && !loader.preloading() {
            asked_for_work = true;
            if opts.preload {
                // What the preload fetched is charged to no frame.
                let bytes = loader.take_unattributed().compressed;
                info!(%actor, voxels = loader.stats.preloaded, mb = bytes as f64 / 1e6,
                    seconds = preload_start.elapsed().as_secs_f64(), "preloaded");
            }
            if scheduler_up {
                owed = capacity(&ahead);
                round_trips.asked(Instant::now().into_std(), owed);
                let _ = results.send((opts.scheduler.clone(), request_work(owed, &cache)));
            }
        }
        tokio::select! {
            d = mb.recv() => match d {
                None => break,
                Some(Delivery::Message { from, msg }) => match msg {
                    Message::AssignTile(a) => {
                        let t = (0..threads).min_by_key(|&t| busy[t]).unwrap_or(0);
                        busy[t] += 1;
                        outstanding += 1;
                        owed = owed.saturating_sub(1);
                        round_trips.assigned(Instant::now().into_std());
                        batch.assigned(a.frame);
                        let _ = queues[t].send(job(a, diagonal, opts.isa));
                    }
                    Message::VoxelLoaded(v) => loader.loaded(from, v.id, v.data.0),
                    Message::VoxelError(e) => loader.refused(from, e),
                    Message::PrefetchHint(h) => loader.hint(&h.voxels.0),
                    Message::Ping(p) => {
                        let _ = results.send((from, Message::Pong(p)));
                    }
                    Message::Shutdown(s) => {
                        info!(%actor, reason = %s.reason, "client stopping");
                        break;
                    }
                    other => debug!(%actor, kind = other.kind().name(), %from, "ignored"),
                },
                Some(Delivery::PeerUp { node, .. }) => {
                    if node == opts.scheduler.node && !scheduler_up {
                        scheduler_up = true;
                        let free = capacity(&ahead).saturating_sub(outstanding);
                        // A new scheduler owes nothing; before the preload
                        // is over, work is not asked for yet.
                        owed = 0;
                        round_trips.forget_requests();
                        if asked_for_work && free > 0 {
                            owed = free;
                            round_trips.asked(Instant::now().into_std(), free);
                            info!(%actor, free, "scheduler is back: asking for work again");
                            let _ = results.send((
                                opts.scheduler.clone(),
                                request_work(free, &cache),
                            ));
                        }
                    }
                    loader.peer_up(&node);
                }
                Some(Delivery::PeerDown { node, reason }) => {
                    if node == opts.scheduler.node {
                        if reason.starts_with("closed") {
                            info!(%actor, %reason, "the scheduler stopped");
                        } else {
                            warn!(%actor, %reason, "lost the scheduler");
                        }
                        scheduler_up = false;
                    }
                }
            },
            Some(req) = req_rx.recv() => loader.request(req),
            Some(d) = decoded_rx.recv() => loader.decoded(d),
            Some(tiles) = done_rx.recv() => {
                let mut resized = false;
                for r in tiles {
                    busy[r.thread] = busy[r.thread].saturating_sub(1);
                    resized |= ahead.tile_finished(r.idle, round_trips.round_trip());
                    let prefetched = loader.take_unattributed();
                    let frame = r.job.frame;
                    batch.finished(
                        frame,
                        finish_tile(r, prefetched, opts.pixel_compression, &mut links, &mut summary),
                    );
                }
                if resized {
                    batch.set_ahead(ahead.current());
                    group.store((batch.size() / threads).max(1), Ordering::Relaxed);
                    in_progress.store(1 + ahead.current(), Ordering::Relaxed);
                    debug!(%actor, tiles_ahead = ahead.current(), "tiles asked ahead");
                }
                let freed = if batch.ready() {
                    let (done, freed) = batch.take();
                    outstanding = outstanding.saturating_sub(freed);
                    for msg in done {
                        let _ = pixels.send((opts.display.clone(), msg));
                    }
                    freed
                } else {
                    0
                };
                // Ask for what the freed slots, and a grown capacity,
                // leave unasked (after a shrink, fewer than were freed).
                let ask = capacity(&ahead).saturating_sub(outstanding + owed);
                if (freed > 0 || resized) && ask > 0 && scheduler_up {
                    owed += ask;
                    round_trips.asked(Instant::now().into_std(), ask);
                    let _ = pixels.send((
                        opts.scheduler.clone(),
                        request_work(ask, &cache),
                    ));
                }
            }
            _ = tick.tick() => loader.tick(),
        }
    }

    // Stop: no new tiles, every waiting packet gets an error, the threads
    // finish what they are doing and exit.
    stop.store(true, Ordering::Relaxed);
    loader.stop();
    drop(queues);
    drop(req_rx);
    drop(done_rx);
    let joined = tokio::task::spawn_blocking(move || {
        handles
            .into_iter()
            .map(|h| h.join().is_ok())
            .collect::<Vec<bool>>()
            .into_iter()
            .all(|ok| ok)
    })
    .await;
    if !matches!(joined, Ok(true)) {
        warn!(%actor, "a render thread panicked");
    }
    let s = &loader.stats;
    summary.fetched = s.fetched;
    summary.bytes_fetched = s.bytes_fetched;
    summary.bytes_raw = s.bytes_raw;
    summary.refetched = s.refetched;
    summary.prefetched = s.prefetched;
    summary.preloaded = s.preloaded;
    summary.voxels_lost = s.lost;
    summary.evicted = cache.evicted();
    summary.peak_cache_bytes = cache.peak_bytes();
    info!(%actor, ?summary, retries = s.retries, "client stopped");
    Ok(summary)
}

fn job(a: AssignTile, diagonal: f32, isa: dray_trace::render::Isa) -> TileJob {
    TileJob {
        frame: a.frame,
        tile: a.tile,
        camera: kernel_camera(&a.camera, a.width, a.height),
        settings: Arc::new(kernel_settings(&a.settings, diagonal, 1, isa)),
        want_depth: a.settings.want_depth,
        want_prim_ids: a.settings.want_prim_ids,
        assigned: std::time::Instant::now(),
    }
}

/// A finished tile's pixels for the display (none if it failed);
/// `prefetched` bytes (fetched by hints, asked for by no tile) are charged
/// to it so that frames count every byte fetched, and so is what the
/// client's links carried since its previous finished tile.
fn finish_tile(
    r: TileResult,
    prefetched: Fetched,
    compression: Compression,
    links: &mut LinkMeter,
    summary: &mut ClientSummary,
) -> Option<Message> {
    let TileResult {
        job,
        image,
        mut fetched,
        stall,
        ..
    } = r;
    fetched += prefetched;
    match image {
        Ok(img) => {
            let st = &img.stats;
            let rays = st.primary_rays + st.shadow_rays + st.reflection_rays;
            summary.tiles += 1;
            summary.rays += rays;
            summary.misses += st.misses;
            let stats = TileStats {
                rays,
                time_us: job.assigned.elapsed().as_micros() as u64,
                voxels_touched: st.voxels_touched,
                // Voxels, not packets: the display's hit rate divides
                // this by `voxels_touched`.
                misses: st.voxels_missed,
                bytes_fetched: fetched.compressed,
                bytes_raw: fetched.raw,
                stall_us: stall.as_micros() as u64,
                link: links.take(),
            };
            // One sample per 16 × 16 pixels (2 × 2 in a 32-pixel tile, 8 × 8
            // in a block of 4 × 4 such tiles): enough for the scheduler to
            // tell whose content the next frame's tiles show. Each sample
            // is handled about ten times on its way (sampled, sent, passed
            // on by the display, placed, projected into the next cameras,
            // sent to the prefetcher), and denser samples cost the nodes
            // time without fetching less (`experiments/affinity-inside.toml`).
            let side = job.tile.w.max(job.tile.h);
            let hits: Vec<[f32; 3]> = img
                .sample_hits(
                    &job.camera,
                    side.div_ceil(HIT_SPACING).clamp(1, HIT_GRID_MAX),
                )
                .iter()
                .map(|p| p.to_array())
                .collect();
            let done = TileDone {
                frame: job.frame,
                tile: job.tile,
                pixels: TilePixels::encode_with(&img.rgba, compression),
                depth: job.want_depth.then_some(PackedF32(img.depth)),
                prim_ids: job.want_prim_ids.then_some(PackedU32(img.primid)),
                stats,
                hits: BoundedVec::new(hits).unwrap_or_default(),
            };
            // The display reports the tile to the scheduler once it has
            // the pixels: a tile whose pixels die with this client is
            // reassigned, never counted done.
            Some(Message::TileDone(done))
        }
        Err(e) => {
            warn!(frame = job.frame, tile = ?job.tile, error = %e, "tile failed");
            None
        }
    }
}
