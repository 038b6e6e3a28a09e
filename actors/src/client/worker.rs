//! Render threads: dedicated OS threads (tracing is CPU bound), each
//! running a small executor over its tiles' futures; in the virtual
//! engine, tasks on the virtual clock that charge their tracing to it
//! ([`Meter::Model`]). In suspend mode a
//! thread keeps up to `tiles_in_progress` tiles going, so that while every
//! packet of one tile waits for voxels it traces another; in block mode it
//! renders one tile at a time and stalls on each miss.

use super::loader::{Fetched, Shared, TileLoader};
use crate::costs::CostModel;
use dray_protocol::TileRect;
use dray_trace::accel::TopLevel;
use dray_trace::camera::Camera;
use dray_trace::render::{PacketChooser, Packets, RenderSettings};
use dray_trace::tile::{render_tile_sample, LoadError, MissMode, Rect, TileImage};
use futures::future::{select, Either};
use futures::stream::{FuturesUnordered, StreamExt};
use std::cell::Cell;
use std::rc::Rc;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use tokio::sync::mpsc;
use tokio::time::Instant;

/// One tile to render.
#[derive(Debug)]
pub(crate) struct TileJob {
    pub frame: u64,
    pub tile: TileRect,
    pub camera: Camera,
    /// Which sample of the camera the frame is (where in each pixel the
    /// rays pass).
    pub sample: u32,
    pub settings: Arc<RenderSettings>,
    pub want_depth: bool,
    pub want_prim_ids: bool,
    /// When the assignment arrived.
    pub assigned: Instant,
}

/// A finished (or failed) tile.
pub(crate) struct TileResult {
    pub thread: usize,
    pub job: TileJob,
    pub image: Result<TileImage, LoadError>,
    /// Voxel bytes fetched on this tile's behalf.
    pub fetched: Fetched,
    /// The thread's stall time charged to this tile: time the thread
    /// waited while every tile it had in progress waited for voxels, since
    /// its previous tile finished. Summed over tiles it is the thread's
    /// stall time (tiles in progress together are not counted twice).
    pub stall: std::time::Duration,
    /// How long the thread sat with no tile at all since its previous tile
    /// finished (from its first tile on): it ran out of work.
    pub idle: std::time::Duration,
}

/// What a render thread needs.
pub(crate) struct WorkerCtx {
    pub top: Arc<TopLevel>,
    pub shared: Arc<Shared>,
    pub mode: MissMode,
    /// Tiles a thread keeps going at once in suspend mode: one and those
    /// the client asks ahead (the actor changes it with them).
    pub tiles_in_progress: Arc<AtomicUsize>,
    pub stop: Arc<AtomicBool>,
    /// Finished tiles go to the client's actor task in groups: one wakeup
    /// of the actor per group instead of one per tile ([`super::batch`]).
    pub results: mpsc::UnboundedSender<Vec<TileResult>>,
    /// Finished tiles a group holds before it is sent; a group also leaves
    /// once this thread renders no other tile of one of its frames. The
    /// actor changes it as the tiles it asks ahead change.
    pub group: Arc<AtomicUsize>,
    /// On the virtual clock, the cores every simulated client shares
    /// where they model one host ([`crate::costs::VirtualClock::cores`]).
    pub cores: Option<Arc<tokio::sync::Semaphore>>,
}

async fn run_job(
    ctx: &WorkerCtx,
    index: usize,
    job: TileJob,
    chooser: Rc<Cell<PacketChooser>>,
) -> TileResult {
    let loader = TileLoader {
        shared: &ctx.shared,
        bytes: AtomicU64::new(0),
        bytes_raw: AtomicU64::new(0),
    };
    let rect = Rect {
        x0: job.tile.x,
        y0: job.tile.y,
        width: job.tile.w,
        height: job.tile.h,
    };
    // The packet width this thread's earlier tiles suggest (as `render`
    // chooses it), unless the settings fix it.
    let settings = RenderSettings {
        packets: match job.settings.packets {
            Packets::Auto => chooser.get().next(),
            fixed => fixed,
        },
        ..(*job.settings).clone()
    };
    let image = render_tile_sample(
        &ctx.top,
        &loader,
        &job.camera,
        job.sample,
        rect,
        &settings,
        ctx.mode,
    )
    .await;
    if let Ok(image) = &image {
        let mut c = chooser.get();
        c.learn(
            settings.isa,
            image.stats.child_hits,
            image.stats.child_lanes,
        );
        chooser.set(c);
    }
    TileResult {
        thread: index,
        job,
        image,
        fetched: Fetched {
            compressed: loader.bytes.load(Ordering::Relaxed),
            raw: loader.bytes_raw.load(Ordering::Relaxed),
        },
        stall: std::time::Duration::ZERO,
        idle: std::time::Duration::ZERO,
    }
}

/// How a render thread's tracing time is known.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Meter {
    /// Measured: an OS thread, on the wall clock.
    Wall,
    /// Charged from the work each poll of a tile did: a task on the
    /// virtual clock, which then waits that long before it does anything
    /// else, as a thread busy tracing would.
    Model(CostModel),
}

/// A tile's future that adds the time spent polling it (tracing) to a
/// counter of its thread, so that the thread can tell its waits from its
/// work.
struct Timed<F> {
    /// The tile's frame.
    frame: u64,
    inner: std::pin::Pin<Box<F>>,
    traced: Rc<Cell<std::time::Duration>>,
    meter: Meter,
}

impl<F: std::future::Future> std::future::Future for Timed<F> {
    type Output = F::Output;

    fn poll(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<F::Output> {
        let (r, spent) = match self.meter {
            Meter::Wall => {
                let start = std::time::Instant::now();
                let r = self.inner.as_mut().poll(cx);
                (r, start.elapsed())
            }
            Meter::Model(cost) => {
                let before = dray_trace::work::done();
                let r = self.inner.as_mut().poll(cx);
                (r, cost.trace(dray_trace::work::done().since(before)))
            }
        };
        self.traced.set(self.traced.get() + spent);
        r
    }
}

/// Spends `work` of a thread's time on the virtual clock, on one of the
/// host's `cores` where they are shared. Tokio's timers fire on whole
/// milliseconds: what a sleep overshoots is kept in `overslept` and taken
/// off the next charges, so that a thread's busy time is the sum of its
/// charges, not each rounded up.
pub(crate) async fn charge(
    work: std::time::Duration,
    overslept: &mut std::time::Duration,
    cores: Option<&tokio::sync::Semaphore>,
) {
    let due = work.saturating_sub(*overslept);
    *overslept = overslept.saturating_sub(work);
    if due.is_zero() {
        return;
    }
    let _core = match cores {
        Some(c) => c.acquire().await.ok(),
        None => None,
    };
    let until = Instant::now() + due;
    tokio::time::sleep_until(until).await;
    *overslept += Instant::now().saturating_duration_since(until);
}

/// The body of render thread `index`: renders the tiles it receives until
/// its channel closes or the client stops.
/// Returns the CPU time the thread used.
pub(crate) fn render_thread(
    ctx: WorkerCtx,
    index: usize,
    tiles: mpsc::UnboundedReceiver<TileJob>,
) -> std::time::Duration {
    dray_runtime::process::lower_this_thread_priority(
        dray_runtime::process::RENDER_THREAD_NICENESS,
    );
    futures::executor::block_on(render_loop(ctx, index, tiles, Meter::Wall));
    crate::costs::cpu_time(libc::CLOCK_THREAD_CPUTIME_ID)
}

/// A render thread's loop, on its own thread ([`render_thread`]) or as a
/// task on the virtual clock (with [`Meter::Model`]).
pub(crate) async fn render_loop(
    ctx: WorkerCtx,
    index: usize,
    mut tiles: mpsc::UnboundedReceiver<TileJob>,
    meter: Meter,
) {
    let limit = || match ctx.mode {
        MissMode::Block => 1,
        MissMode::Suspend => ctx.tiles_in_progress.load(Ordering::Relaxed).max(1),
    };
    let ctx = &ctx;
    let mut running = FuturesUnordered::new();
    let mut open = true;
    // Stall: waiting with tiles in progress (all of them blocked on
    // voxels); waiting with none is idleness, not stall.
    let mut stalled = std::time::Duration::ZERO;
    let mut charged = std::time::Duration::ZERO;
    let traced = Rc::new(Cell::new(std::time::Duration::ZERO));
    // On the virtual clock: time slept past a charge's end.
    let mut overslept = std::time::Duration::ZERO;
    let (mut traced_total, mut idle) = (std::time::Duration::ZERO, std::time::Duration::ZERO);
    // Idleness charged to tiles so far; `None` until the first tile
    // arrives (waiting for it is not running out of work).
    let mut idle_charged: Option<std::time::Duration> = None;
    let chooser = Rc::new(Cell::new(PacketChooser::new(Packets::Auto)));
    let start_job = |job: TileJob| Timed {
        frame: job.frame,
        inner: Box::pin(run_job(ctx, index, job, chooser.clone())),
        traced: traced.clone(),
        meter,
    };
    // Finished tiles not yet sent to the actor.
    let mut unsent: Vec<TileResult> = Vec::new();
    loop {
        // Take what is waiting, up to the limit.
        while open && running.len() < limit() {
            match tiles.try_recv() {
                Ok(job) => {
                    idle_charged.get_or_insert(idle);
                    running.push(start_job(job))
                }
                Err(mpsc::error::TryRecvError::Empty) => break,
                Err(mpsc::error::TryRecvError::Disconnected) => open = false,
            }
        }
        if ctx.stop.load(Ordering::Relaxed) {
            open = false;
        }
        enum Event {
            // Boxed: a result is larger than the other variants, and
            // one allocation a tile is nothing beside the tile.
            Done(Box<TileResult>),
            Job(Option<TileJob>),
            Idle,
        }
        let busy = !running.is_empty();
        let waited = Instant::now();
        traced.set(std::time::Duration::ZERO);
        let event = if running.is_empty() {
            if !open {
                break;
            }
            Event::Job(tiles.recv().await)
        } else if open && running.len() < limit() {
            let recv = tiles.recv();
            futures::pin_mut!(recv);
            match select(running.next(), recv).await {
                Either::Left((Some(r), _)) => Event::Done(Box::new(r)),
                Either::Left((None, _)) => Event::Idle,
                Either::Right((job, _)) => Event::Job(job),
            }
        } else {
            match running.next().await {
                Some(r) => Event::Done(Box::new(r)),
                None => Event::Idle,
            }
        };
        let spent = traced.take();
        traced_total += spent;
        // Polling the tiles traces their ready packets; what is left of
        // the wait is time with nothing runnable. On the virtual clock
        // polls take no time: the thread is charged for them now.
        let waited = match meter {
            Meter::Wall => waited.elapsed().saturating_sub(spent),
            Meter::Model(_) => {
                let w = waited.elapsed();
                charge(spent, &mut overslept, ctx.cores.as_deref()).await;
                w
            }
        };
        if busy {
            stalled += waited;
        } else {
            idle += waited;
        }
        match event {
            Event::Done(mut r) => {
                r.stall = stalled - charged;
                charged = stalled;
                if let Some(c) = idle_charged.as_mut() {
                    r.idle = idle - *c;
                    *c = idle;
                }
                unsent.push(*r);
                let frame_over = |f: u64| !running.iter().any(|t| t.frame == f);
                let group = ctx.group.load(Ordering::Relaxed);
                if unsent.len() >= group || unsent.iter().any(|r| frame_over(r.job.frame)) {
                    let _ = ctx.results.send(std::mem::take(&mut unsent));
                }
            }
            Event::Job(Some(job)) => {
                idle_charged.get_or_insert(idle);
                running.push(start_job(job))
            }
            Event::Job(None) => open = false,
            Event::Idle => {}
        }
    }
    if !unsent.is_empty() {
        let _ = ctx.results.send(unsent);
    }
    tracing::info!(
        thread = index,
        traced_s = traced_total.as_secs_f64(),
        stalled_s = stalled.as_secs_f64(),
        idle_s = idle.as_secs_f64(),
        "render thread done"
    );
}
