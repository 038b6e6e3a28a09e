//! The client's state and handlers: which render thread gets a tile, when
//! and for how many tiles the scheduler is asked, when finished tiles leave
//! ([`super::batch`]), how many tiles are asked ahead ([`super::ahead`]),
//! and the voxel [`Loader`]. Nothing here sends, spawns or waits: the
//! handlers push [`Out`] effects that the run loop carries out.

use super::ahead::{Ahead, RoundTrips};
use super::batch::TileBatch;
use super::cache::VoxelCache;
use super::loader::{Decoded, Fetched, LoadRequest, Loader, LostPolicy};
use super::worker::{TileJob, TileResult};
use super::{ClientOptions, ClientSummary, HIT_GRID_MAX, HIT_SPACING};
use crate::settings::{kernel_camera, kernel_settings};
use dray_protocol::{
    Address, AssignTile, BoundedVec, Compression, LinkBytes, Message, Name, PackedF32, PackedU32,
    Ping, RequestWork, TileDone, TilePixels, TileStats, VoxelError,
};
use dray_scene::db::manifest::{Manifest, VoxelEntry};
use dray_trace::render::Isa;
use dray_trace::tile::MissMode;
use std::sync::Arc;
use tokio::time::Instant;
use tracing::{debug, info, warn};

/// What the client's handlers ask the run loop to do, in order.
#[derive(Debug)]
pub(crate) enum Out {
    /// A control message (requests for work before any tile finished,
    /// pongs, [`dray_protocol::VoxelLost`]), sent in order on its own queue.
    Control(Address, Message),
    /// Finished tiles' pixels and then the request for as many tiles, in
    /// order on one queue: the scheduler counts a tile done only once its
    /// pixels have left, and never sees more tiles asked for than the
    /// client holds.
    Tile(Address, Message),
    /// Ask store `to` for voxel `id`.
    Fetch { to: Address, id: u32 },
    /// Verify and decode a blob off the actor task; the result comes back
    /// to [`Client::decoded`].
    Decode {
        id: u32,
        store: Address,
        entry: VoxelEntry,
        blob: Vec<u8>,
    },
    /// Hand render thread `thread` a tile.
    Render { thread: usize, job: TileJob },
    /// The tiles asked ahead changed: each thread's share of a batch, and
    /// the tiles a thread keeps in progress at once.
    Ahead { group: usize, in_progress: usize },
}

/// A client's state once it has the manifest.
pub(crate) struct Client {
    /// The client's address, for messages.
    actor: String,
    threads: usize,
    scheduler: Address,
    display: Address,
    isa: Isa,
    compression: Compression,
    preload: bool,
    /// The model's diagonal (the kernel's ray offsets scale with it).
    diagonal: f32,
    cache: Arc<VoxelCache>,
    loader: Loader,
    ahead: Ahead,
    round_trips: RoundTrips,
    batch: TileBatch,
    /// Tiles each render thread holds.
    busy: Vec<usize>,
    /// Tiles assigned whose slots are not asked for again yet (being
    /// rendered, queued, or finished and held for a batch).
    outstanding: usize,
    /// Slots asked for that the scheduler has not filled yet.
    owed: usize,
    scheduler_up: bool,
    /// Work is asked for once the preload (if any) is over.
    asked_for_work: bool,
    started: Instant,
    summary: ClientSummary,
}

impl Client {
    /// A client of `manifest`'s model whose voxels go in `cache`; with
    /// `opts.preload` the preload's fetches are the first effects.
    pub fn new(
        actor: String,
        opts: &ClientOptions,
        manifest: Arc<Manifest>,
        cache: Arc<VoxelCache>,
        out: &mut Vec<Out>,
    ) -> Client {
        let started = Instant::now();
        let threads = opts.threads.max(1);
        // A blocked thread renders one tile at a time whatever it holds: in
        // block mode (the demand-paging baseline) the client holds exactly
        // `tiles_ahead`, as such a client would.
        let most_ahead = match opts.miss_mode {
            MissMode::Suspend => opts.max_tiles_ahead,
            MissMode::Block => opts.tiles_ahead,
        };
        let ahead = Ahead::new(opts.tiles_ahead, most_ahead);
        let diagonal = manifest.model_bounds.diagonal();
        let mut loader = Loader::new(
            manifest,
            cache.clone(),
            opts.stores.clone(),
            opts.max_inflight_fetches,
            LostPolicy {
                mode: opts.corrupt_voxel,
                report_to: opts.display.clone(),
            },
        );
        if opts.preload {
            loader.preload(out);
        }
        Client {
            actor,
            threads,
            scheduler: opts.scheduler.clone(),
            display: opts.display.clone(),
            isa: opts.isa,
            compression: opts.pixel_compression,
            preload: opts.preload,
            diagonal,
            cache,
            loader,
            batch: TileBatch::new(ahead.current()),
            ahead,
            round_trips: RoundTrips::default(),
            busy: vec![0; threads],
            outstanding: 0,
            owed: 0,
            scheduler_up: true,
            asked_for_work: false,
            started,
            summary: ClientSummary::default(),
        }
    }

    /// Each thread's share of a batch of finished tiles.
    pub fn group(&self) -> usize {
        (self.batch.size() / self.threads).max(1)
    }

    /// Tiles a render thread keeps in progress at once (suspend mode).
    pub fn in_progress(&self) -> usize {
        1 + self.ahead.current()
    }

    /// Tiles to hold: one per thread and those asked ahead.
    fn capacity(&self) -> usize {
        self.threads + self.ahead.current()
    }

    fn request_work(&mut self, n: usize) -> Message {
        self.round_trips.asked(Instant::now().into_std(), n);
        Message::RequestWork(RequestWork {
            slots: n.min(u16::MAX as usize) as u16,
            holds_model: self.cache.holds_all(),
        })
    }

    /// Once the preload (if any) is over, asks the scheduler for the
    /// first tiles; the loop calls it after every handler.
    pub fn ask_once_preloaded(&mut self, out: &mut Vec<Out>) {
        if self.asked_for_work || self.loader.preloading() {
            return;
        }
        self.asked_for_work = true;
        if self.preload {
            // What the preload fetched is charged to no frame.
            let bytes = self.loader.take_unattributed().compressed;
            info!(actor = %self.actor, voxels = self.loader.stats.preloaded,
                mb = bytes as f64 / 1e6, seconds = self.started.elapsed().as_secs_f64(),
                "preloaded");
        }
        if self.scheduler_up {
            self.owed = self.capacity();
            let msg = self.request_work(self.owed);
            out.push(Out::Control(self.scheduler.clone(), msg));
        }
    }

    /// The scheduler assigned a tile: the least busy thread renders it.
    pub fn assign_tile(&mut self, a: AssignTile, out: &mut Vec<Out>) {
        let thread = (0..self.threads).min_by_key(|&t| self.busy[t]).unwrap_or(0);
        self.busy[thread] += 1;
        self.outstanding += 1;
        self.owed = self.owed.saturating_sub(1);
        self.round_trips.assigned(Instant::now().into_std());
        self.batch.assigned(a.frame);
        let job = job(a, self.diagonal, self.isa);
        out.push(Out::Render { thread, job });
    }

    /// A render thread asks for a voxel that is not in the cache.
    pub fn voxel_wanted(&mut self, req: LoadRequest, out: &mut Vec<Out>) {
        self.loader.request(req, out);
    }

    /// A store sent voxel `id`.
    pub fn voxel_loaded(&mut self, from: Address, id: u32, blob: Vec<u8>, out: &mut Vec<Out>) {
        self.loader.loaded(from, id, blob, out);
    }

    /// A blob was verified and decoded (or failed to).
    pub fn decoded(&mut self, d: Decoded, out: &mut Vec<Out>) {
        self.loader.decoded(d, out);
    }

    /// A store refused a voxel.
    pub fn voxel_refused(&mut self, from: Address, e: VoxelError, out: &mut Vec<Out>) {
        self.loader.refused(from, e, out);
    }

    /// The prefetcher hints at voxels needed soon.
    pub fn hint(&mut self, ids: &[u32], out: &mut Vec<Out>) {
        self.loader.hint(ids, out);
    }

    /// `from` pings.
    pub fn ping(&mut self, from: Address, ping: Ping, out: &mut Vec<Out>) {
        out.push(Out::Control(from, Message::Pong(ping)));
    }

    /// Retries whose delay is over, fetches that timed out.
    pub fn tick(&mut self, out: &mut Vec<Out>) {
        self.loader.tick(out);
    }

    /// A node came (back) up: a returning scheduler owes nothing and is
    /// asked for the free slots; a store gets its unanswered fetches again.
    pub fn peer_up(&mut self, node: &Name, out: &mut Vec<Out>) {
        if *node == self.scheduler.node && !self.scheduler_up {
            self.scheduler_up = true;
            let free = self.capacity().saturating_sub(self.outstanding);
            self.owed = 0;
            self.round_trips.forget_requests();
            // Before the preload is over, work is not asked for yet.
            if self.asked_for_work && free > 0 {
                self.owed = free;
                info!(actor = %self.actor, free, "scheduler is back: asking for work again");
                let msg = self.request_work(free);
                out.push(Out::Control(self.scheduler.clone(), msg));
            }
        }
        self.loader.peer_up(node, out);
    }

    /// A node went down: without the scheduler no work is asked for; a
    /// store's fetches go to another store serving their voxels.
    pub fn peer_down(&mut self, node: &Name, reason: &str, out: &mut Vec<Out>) {
        self.loader.peer_down(node, out);
        if *node == self.scheduler.node {
            if reason.starts_with("closed") {
                info!(actor = %self.actor, %reason, "the scheduler stopped");
            } else {
                warn!(actor = %self.actor, %reason, "lost the scheduler");
            }
            self.scheduler_up = false;
        }
    }

    /// Render threads finished `tiles`: they join the batch, which leaves
    /// once ready, followed by a request for the slots it frees (and any
    /// the tiles asked ahead grew by). `link` says what the client's links
    /// carried since it was last asked (charged to the next tile rendered).
    pub fn tiles_finished(
        &mut self,
        tiles: Vec<TileResult>,
        link: &mut impl FnMut() -> LinkBytes,
        out: &mut Vec<Out>,
    ) {
        let mut resized = false;
        for r in tiles {
            self.busy[r.thread] = self.busy[r.thread].saturating_sub(1);
            resized |= self
                .ahead
                .tile_finished(r.idle, self.round_trips.round_trip());
            let prefetched = self.loader.take_unattributed();
            let frame = r.job.frame;
            let pixels = finish_tile(r, prefetched, self.compression, link, &mut self.summary);
            self.batch.finished(frame, pixels);
        }
        if resized {
            self.batch.set_ahead(self.ahead.current());
            out.push(Out::Ahead {
                group: self.group(),
                in_progress: self.in_progress(),
            });
            debug!(actor = %self.actor, tiles_ahead = self.ahead.current(), "tiles asked ahead");
        }
        let freed = if self.batch.ready() {
            let (done, freed) = self.batch.take();
            self.outstanding = self.outstanding.saturating_sub(freed);
            out.extend(done.into_iter().map(|m| Out::Tile(self.display.clone(), m)));
            freed
        } else {
            0
        };
        // Ask for what the freed slots, and a grown capacity, leave
        // unasked (after a shrink, fewer than were freed).
        let ask = self.capacity().saturating_sub(self.outstanding + self.owed);
        if (freed > 0 || resized) && ask > 0 && self.scheduler_up {
            self.owed += ask;
            let msg = self.request_work(ask);
            out.push(Out::Tile(self.scheduler.clone(), msg));
        }
    }

    /// The client stops: every waiting packet gets an error.
    pub fn stop(&mut self) {
        self.loader.stop();
    }

    /// What the client did.
    pub fn summary(&self) -> ClientSummary {
        let s = &self.loader.stats;
        ClientSummary {
            fetched: s.fetched,
            bytes_fetched: s.bytes_fetched,
            bytes_raw: s.bytes_raw,
            refetched: s.refetched,
            prefetched: s.prefetched,
            preloaded: s.preloaded,
            voxels_lost: s.lost,
            evicted: self.cache.evicted(),
            peak_cache_bytes: self.cache.peak_bytes(),
            ..self.summary.clone()
        }
    }

    /// Fetches asked again (failed, refused or timed out).
    pub fn retries(&self) -> u64 {
        self.loader.stats.retries
    }
}

fn job(a: AssignTile, diagonal: f32, isa: Isa) -> TileJob {
    TileJob {
        frame: a.frame,
        tile: a.tile,
        camera: kernel_camera(&a.camera, a.width, a.height),
        sample: a.sample,
        settings: Arc::new(kernel_settings(&a.settings, diagonal, 1, isa)),
        want_depth: a.settings.want_depth,
        want_prim_ids: a.settings.want_prim_ids,
        assigned: Instant::now(),
    }
}

/// A finished tile's pixels for the display (none if it failed);
/// `prefetched` bytes (fetched by hints, asked for by no tile) are charged
/// to it so that frames count every byte fetched, and so is what the
/// client's links carried since its previous finished tile (`link`).
fn finish_tile(
    r: TileResult,
    prefetched: Fetched,
    compression: Compression,
    link: &mut impl FnMut() -> LinkBytes,
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
                link: link(),
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
                    &job.camera.sample_basis(job.sample),
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

#[cfg(test)]
mod tests {
    use super::super::loader::{empty_voxel, Answer, MAX_TRIES};
    use super::*;
    use crate::names::{self, StoreRoutes};
    use crate::Shard;
    use dray_config::CorruptVoxel;
    use dray_protocol::TileRect;
    use dray_scene::db::manifest::BuildParams;
    use dray_scene::geometry::Aabb;
    use dray_trace::accel::PreparedVoxel;
    use dray_trace::tile::{LoadError, Rect, TileImage};
    use std::time::Duration;
    use tokio::sync::oneshot;

    const VOXELS: u32 = 4;

    fn unit_box() -> Aabb {
        Aabb {
            min: [0.0; 3],
            max: [1.0; 3],
        }
    }

    /// A model of [`VOXELS`] voxels that only its table describes (the
    /// client's state never reads the BSP).
    fn manifest() -> Arc<Manifest> {
        let entry = VoxelEntry {
            bounds: unit_box(),
            content: unit_box(),
            triangles: 0,
            vertices: 0,
            raw_bytes: 1000,
            compressed_bytes: 100,
            offset: 0,
            checksum: 0,
            depth: 0,
        };
        Arc::new(Manifest {
            format_version: 1,
            model_bounds: unit_box(),
            root_bounds: unit_box(),
            input_triangles: 0,
            stored_triangles: 0,
            build: BuildParams {
                inputs: Vec::new(),
                max_triangles: 1,
                max_depth: 1,
                copies: [1; 3],
                spacing: 0.0,
                zstd_level: 1,
            },
            nodes: Vec::new(),
            voxels: vec![entry; VOXELS as usize],
        })
    }

    /// Two threads, one tile ahead (up to four), one store.
    fn options() -> ClientOptions {
        ClientOptions {
            threads: 2,
            cache_bytes: 1 << 20,
            miss_mode: MissMode::Suspend,
            max_inflight_fetches: 8,
            tiles_ahead: 1,
            max_tiles_ahead: 4,
            preload: false,
            pixel_compression: Compression::None,
            isa: Isa::Portable,
            stores: StoreRoutes::new(vec![(Shard::ALL, names::store(0))]).unwrap(),
            scheduler: names::scheduler(),
            display: names::display(),
            corrupt_voxel: CorruptVoxel::Fail,
            virtual_clock: None,
        }
    }

    fn client_with(opts: &ClientOptions, out: &mut Vec<Out>) -> Client {
        let manifest = manifest();
        let cache = Arc::new(VoxelCache::new(manifest.voxels.len(), opts.cache_bytes));
        Client::new("client-0".into(), opts, manifest, cache, out)
    }

    /// A client that has asked for its first tiles (the request is
    /// dropped from `out`).
    fn started(opts: &ClientOptions) -> Client {
        let mut out = Vec::new();
        let mut c = client_with(opts, &mut out);
        c.ask_once_preloaded(&mut out);
        assert!(matches!(&out[..], [Out::Control(..)]), "{out:?}");
        c
    }

    fn assignment(frame: u64) -> AssignTile {
        AssignTile {
            frame,
            tile: TileRect {
                x: 0,
                y: 0,
                w: 4,
                h: 4,
            },
            width: 64,
            height: 64,
            ..dray_protocol::examples::one_of_each(16)
                .into_iter()
                .find_map(|m| match m {
                    Message::AssignTile(a) => Some(a),
                    _ => None,
                })
                .expect("the examples hold an assignment")
        }
    }

    /// Assigns a tile of `frame`; returns the job as its thread got it.
    fn assign(c: &mut Client, frame: u64) -> (usize, TileJob) {
        let mut out = Vec::new();
        c.assign_tile(assignment(frame), &mut out);
        match out.pop() {
            Some(Out::Render { thread, job }) if out.is_empty() => (thread, job),
            other => panic!("not one render: {other:?} {out:?}"),
        }
    }

    /// `job` rendered by `thread` (all background), or failed.
    fn finished(thread: usize, job: TileJob, ok: bool, idle: Duration) -> TileResult {
        let n = (job.tile.w * job.tile.h) as usize;
        let image = if ok {
            Ok(TileImage {
                rect: Rect {
                    x0: job.tile.x,
                    y0: job.tile.y,
                    width: job.tile.w,
                    height: job.tile.h,
                },
                rgba: vec![[0, 0, 0, 255]; n],
                depth: vec![f32::INFINITY; n],
                primid: vec![u32::MAX; n],
                stats: Default::default(),
            })
        } else {
            Err(LoadError {
                voxel: 1,
                message: "lost".into(),
            })
        };
        TileResult {
            thread,
            job,
            image,
            fetched: Fetched::default(),
            stall: Duration::ZERO,
            idle,
        }
    }

    fn slots(msg: &Message) -> Option<u16> {
        match msg {
            Message::RequestWork(r) => Some(r.slots),
            _ => None,
        }
    }

    fn want(c: &mut Client, id: u32, out: &mut Vec<Out>) -> oneshot::Receiver<Answer> {
        let (reply, answer) = oneshot::channel();
        c.voxel_wanted(LoadRequest { id, reply }, out);
        answer
    }

    /// Voxel `id` arrives from the store and decodes to `result`; the
    /// effects in between are checked.
    fn arrives(c: &mut Client, id: u32, result: Result<PreparedVoxel, String>, out: &mut Vec<Out>) {
        c.voxel_loaded(names::store(0), id, vec![7; 100], out);
        let Some(Out::Decode {
            id: decoding, blob, ..
        }) = out.pop()
        else {
            panic!("no decode: {out:?}");
        };
        assert_eq!(
            (decoding, blob.len()),
            (id, 100),
            "the blob is decoded as it came"
        );
        let d = Decoded {
            id,
            store: names::store(0),
            bytes: 100,
            result: result.map(Arc::new),
        };
        c.decoded(d, out);
    }

    fn fetches(out: &mut Vec<Out>) -> Vec<u32> {
        out.drain(..)
            .map(|o| match o {
                Out::Fetch { to, id } if to == names::store(0) => id,
                other => panic!("not a fetch: {other:?}"),
            })
            .collect()
    }

    #[test]
    fn at_start_it_asks_once_for_a_tile_per_thread_and_those_ahead() {
        let mut out = Vec::new();
        let mut c = client_with(&options(), &mut out);
        assert!(out.is_empty(), "no preload: {out:?}");
        c.ask_once_preloaded(&mut out);
        match &out[..] {
            [Out::Control(to, msg)] => {
                assert_eq!(*to, names::scheduler());
                assert_eq!(slots(msg), Some(3), "two threads and one ahead");
            }
            other => panic!("{other:?}"),
        }
        out.clear();
        c.ask_once_preloaded(&mut out);
        assert!(out.is_empty(), "asked once: {out:?}");
    }

    #[test]
    fn with_a_preload_work_is_asked_for_once_every_voxel_is_in() {
        let opts = ClientOptions {
            preload: true,
            ..options()
        };
        let mut out = Vec::new();
        let mut c = client_with(&opts, &mut out);
        assert_eq!(fetches(&mut out), [0, 1, 2, 3], "the whole model fits");
        for id in 0..VOXELS {
            c.ask_once_preloaded(&mut out);
            assert!(out.is_empty(), "still preloading: {out:?}");
            arrives(&mut c, id, Ok(empty_voxel(id, unit_box())), &mut out);
        }
        assert!(out.is_empty(), "{out:?}");
        c.ask_once_preloaded(&mut out);
        assert!(
            matches!(&out[..], [Out::Control(_, m)] if slots(m) == Some(3)),
            "{out:?}"
        );
    }

    #[test]
    fn a_tile_goes_to_the_least_busy_thread() {
        let mut c = started(&options());
        let threads: Vec<usize> = (0..3).map(|_| assign(&mut c, 1).0).collect();
        assert_eq!(threads, [0, 1, 0]);
        let (_, job) = assign(&mut c, 1);
        assert_eq!((job.frame, job.sample), (1, assignment(1).sample));
        assert_eq!((job.camera.width, job.camera.height), (64, 64));
    }

    #[test]
    fn a_finished_tile_leaves_for_the_display_and_its_slot_is_asked_again() {
        let mut c = started(&options());
        let (thread, job) = assign(&mut c, 5);
        let mut out = Vec::new();
        let tile = finished(thread, job, true, Duration::ZERO);
        c.tiles_finished(vec![tile], &mut LinkBytes::default, &mut out);
        match &out[..] {
            [Out::Tile(display, Message::TileDone(done)), Out::Tile(scheduler, ask)] => {
                assert_eq!(*display, names::display());
                assert_eq!(done.frame, 5);
                assert_eq!(*scheduler, names::scheduler());
                assert_eq!(slots(ask), Some(1), "two slots are still owed");
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn a_failed_tile_sends_no_pixels_but_frees_its_slot() {
        let mut c = started(&options());
        let (thread, job) = assign(&mut c, 5);
        let mut out = Vec::new();
        let tile = finished(thread, job, false, Duration::ZERO);
        c.tiles_finished(vec![tile], &mut LinkBytes::default, &mut out);
        assert!(
            matches!(&out[..], [Out::Tile(_, m)] if slots(m) == Some(1)),
            "{out:?}"
        );
    }

    #[test]
    fn a_thread_left_idle_grows_the_tiles_asked_ahead() {
        let mut c = started(&options());
        let (thread, job) = assign(&mut c, 5);
        let mut out = Vec::new();
        // Idle, but for less than the scheduler takes to answer: it ran dry.
        let tile = finished(thread, job, true, Duration::from_micros(200));
        c.tiles_finished(vec![tile], &mut LinkBytes::default, &mut out);
        match &out[..] {
            [Out::Ahead { group, in_progress }, Out::Tile(_, Message::TileDone(_)), Out::Tile(_, ask)] =>
            {
                assert_eq!((*group, *in_progress), (1, 3), "two tiles ahead now");
                assert_eq!(slots(ask), Some(2), "the freed slot and the new one");
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn without_the_scheduler_no_work_is_asked_until_it_is_back() {
        let mut c = started(&options());
        let (thread, job) = assign(&mut c, 5);
        let scheduler = names::scheduler().node;
        let mut out = Vec::new();
        c.peer_down(&scheduler, "timed out", &mut out);
        assert!(out.is_empty(), "{out:?}");
        let tile = finished(thread, job, true, Duration::ZERO);
        c.tiles_finished(vec![tile], &mut LinkBytes::default, &mut out);
        assert!(
            matches!(&out[..], [Out::Tile(_, Message::TileDone(_))]),
            "the pixels still go, no request: {out:?}"
        );
        out.clear();
        c.peer_up(&scheduler, &mut out);
        assert!(
            matches!(&out[..], [Out::Control(to, m)] if *to == names::scheduler() && slots(m) == Some(3)),
            "a new scheduler owes nothing: every free slot is asked for: {out:?}"
        );
        out.clear();
        c.peer_up(&scheduler, &mut out);
        assert!(out.is_empty(), "asked once: {out:?}");
    }

    #[test]
    fn a_voxel_is_fetched_once_for_all_who_want_it_and_decoded_off_the_actor() {
        let mut c = started(&options());
        let mut out = Vec::new();
        let mut first = want(&mut c, 2, &mut out);
        let mut second = want(&mut c, 2, &mut out);
        assert_eq!(fetches(&mut out), [2]);
        arrives(&mut c, 2, Ok(empty_voxel(2, unit_box())), &mut out);
        assert!(out.is_empty(), "{out:?}");
        for answer in [&mut first, &mut second] {
            let (v, _) = answer.try_recv().unwrap().unwrap();
            assert_eq!(v.id, 2);
        }
        let mut again = want(&mut c, 2, &mut out);
        assert!(out.is_empty(), "cached: {out:?}");
        assert!(matches!(again.try_recv(), Ok(Ok(_))));
    }

    /// Voxel 1 fails verification at every try; returns the first
    /// waiter's answer and what the display was told.
    fn corrupt(mode: CorruptVoxel) -> (Client, Answer, Message) {
        let mut c = started(&ClientOptions {
            corrupt_voxel: mode,
            ..options()
        });
        let mut out = Vec::new();
        let mut answer = want(&mut c, 1, &mut out);
        for _ in 0..MAX_TRIES {
            assert_eq!(fetches(&mut out), [1], "fetched again");
            arrives(&mut c, 1, Err("checksum mismatch".into()), &mut out);
        }
        let report = match out.pop() {
            Some(Out::Control(to, msg)) if out.is_empty() && to == names::display() => msg,
            other => panic!("no report: {other:?} {out:?}"),
        };
        (c, answer.try_recv().expect("answered"), report)
    }

    #[test]
    fn a_corrupt_voxel_fails_its_tiles_when_corrupt_voxel_is_fail() {
        let (mut c, answer, report) = corrupt(CorruptVoxel::Fail);
        let Message::VoxelLost(lost) = report else {
            panic!("{report:?}");
        };
        assert_eq!((lost.id, lost.skipped), (1, false));
        assert_eq!(lost.store, names::store(0).node);
        let Err(e) = answer else {
            panic!("no error");
        };
        assert_eq!(e.voxel, 1);
        assert!(e.message.contains("checksum mismatch"), "{}", e.message);
        // Later requests fail at once, without a fetch.
        let mut out = Vec::new();
        let mut later = want(&mut c, 1, &mut out);
        assert!(out.is_empty(), "{out:?}");
        assert!(matches!(later.try_recv(), Ok(Err(_))));
        c.stop();
        assert_eq!(c.summary().voxels_lost, 1);
    }

    #[test]
    fn a_corrupt_voxel_renders_empty_when_corrupt_voxel_is_skip() {
        let (mut c, answer, report) = corrupt(CorruptVoxel::Skip);
        assert!(matches!(report, Message::VoxelLost(l) if l.id == 1 && l.skipped));
        let (v, _) = answer.expect("a stand-in");
        assert_eq!(v.id, 1);
        assert!(v.triangles.is_empty());
        let mut out = Vec::new();
        let mut later = want(&mut c, 1, &mut out);
        assert!(out.is_empty(), "{out:?}");
        assert!(matches!(later.try_recv(), Ok(Ok(_))));
        c.stop();
        assert_eq!(c.summary().voxels_lost, 1);
    }

    #[test]
    fn stopping_answers_every_waiting_packet_with_an_error() {
        let mut c = started(&options());
        let mut out = Vec::new();
        let mut waiting = want(&mut c, 3, &mut out);
        assert_eq!(fetches(&mut out), [3]);
        c.stop();
        let summary = c.summary();
        let Err(e) = waiting.try_recv().unwrap() else {
            panic!("no error");
        };
        assert_eq!(e.message, "the client is stopping");
        assert_eq!((summary.tiles, summary.fetched), (0, 0));
    }

    #[test]
    fn pings_are_answered_on_the_control_queue() {
        let mut c = started(&options());
        let mut out = Vec::new();
        c.ping(names::display(), Ping { seq: 4 }, &mut out);
        assert!(
            matches!(&out[..], [Out::Control(to, Message::Pong(p))] if *to == names::display() && p.seq == 4),
            "{out:?}"
        );
    }
}
