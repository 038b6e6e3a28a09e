//! Render threads: dedicated OS threads (tracing is CPU bound), each
//! running a small executor over its tiles' futures. In suspend mode a
//! thread keeps up to `tiles_in_progress` tiles going, so that while every
//! packet of one tile waits for voxels it traces another; in block mode it
//! renders one tile at a time and stalls on each miss.

use super::loader::{Shared, TileLoader};
use dray_protocol::TileRect;
use dray_trace::camera::Camera;
use dray_trace::render::RenderSettings;
use dray_trace::scene::TopLevel;
use dray_trace::tile::{render_tile, LoadError, MissMode, Rect, TileImage};
use futures::future::{select, Either};
use futures::stream::{FuturesUnordered, StreamExt};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Instant;
use tokio::sync::mpsc;

/// One tile to render.
pub(crate) struct TileJob {
    pub frame: u64,
    pub tile: TileRect,
    pub camera: Camera,
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
    /// Compressed voxel bytes fetched on this tile's behalf.
    pub bytes_fetched: u64,
}

/// What a render thread needs.
pub(crate) struct WorkerCtx {
    pub top: Arc<TopLevel>,
    pub shared: Arc<Shared>,
    pub mode: MissMode,
    pub tiles_in_progress: usize,
    pub stop: Arc<AtomicBool>,
    pub results: mpsc::UnboundedSender<TileResult>,
}

async fn run_job(ctx: &WorkerCtx, index: usize, job: TileJob) -> TileResult {
    let loader = TileLoader {
        shared: &ctx.shared,
        bytes: AtomicU64::new(0),
    };
    let rect = Rect {
        x0: job.tile.x,
        y0: job.tile.y,
        width: job.tile.w,
        height: job.tile.h,
    };
    let image = render_tile(
        &ctx.top,
        &loader,
        &job.camera,
        rect,
        &job.settings,
        ctx.mode,
    )
    .await;
    TileResult {
        thread: index,
        job,
        image,
        bytes_fetched: loader.bytes.load(Ordering::Relaxed),
    }
}

/// The body of render thread `index`: renders the tiles it receives until
/// its channel closes or the client stops.
pub(crate) fn render_thread(
    ctx: WorkerCtx,
    index: usize,
    mut tiles: mpsc::UnboundedReceiver<TileJob>,
) {
    let limit = match ctx.mode {
        MissMode::Block => 1,
        MissMode::Suspend => ctx.tiles_in_progress.max(1),
    };
    let ctx = &ctx;
    futures::executor::block_on(async move {
        let mut running = FuturesUnordered::new();
        let mut open = true;
        loop {
            // Take what is waiting, up to the limit.
            while open && running.len() < limit {
                match tiles.try_recv() {
                    Ok(job) => running.push(run_job(ctx, index, job)),
                    Err(mpsc::error::TryRecvError::Empty) => break,
                    Err(mpsc::error::TryRecvError::Disconnected) => open = false,
                }
            }
            if ctx.stop.load(Ordering::Relaxed) {
                open = false;
            }
            enum Event {
                Done(TileResult),
                Job(Option<TileJob>),
                Idle,
            }
            let event = if running.is_empty() {
                if !open {
                    break;
                }
                Event::Job(tiles.recv().await)
            } else if open && running.len() < limit {
                let recv = tiles.recv();
                futures::pin_mut!(recv);
                match select(running.next(), recv).await {
                    Either::Left((Some(r), _)) => Event::Done(r),
                    Either::Left((None, _)) => Event::Idle,
                    Either::Right((job, _)) => Event::Job(job),
                }
            } else {
                match running.next().await {
                    Some(r) => Event::Done(r),
                    None => Event::Idle,
                }
            };
            match event {
                Event::Done(r) => {
                    let _ = ctx.results.send(r);
                }
                Event::Job(Some(job)) => running.push(run_job(ctx, index, job)),
                Event::Job(None) => open = false,
                Event::Idle => {}
            }
        }
    });
}
