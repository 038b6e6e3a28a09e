//! The Display actor: frames, metrics, camera path.
//!
//! [`run_display`] sends one [`CameraUpdate`] per frame to the frame
//! assigner, keeping at most `frames_ahead` frames outstanding, assembles
//! the [`TileDone`] pixels the clients send into images, and shows each
//! frame once it has both all its pixels and the scheduler's [`FrameDone`]:
//! frames are shown in order, a frame that completes early waits for the
//! ones before it. With an `output` directory each shown frame gets a row
//! of `metrics.csv` and, with `save_frames`, a PNG
//! (`frames/frame-NNNNN.png`, plus `.pfm` depth and `.primid` ids when the
//! tiles carry them); with a viewer, a refresh of the web page ([`web`]).
//!
//! In interactive mode ([`DisplayOptions::interactive`]) the camera comes
//! from a user instead: the display starts from the first camera and
//! applies the [`Move`]s the web viewer takes on `/move` ([`moves`] has
//! the keys and step sizes). It keeps `frames_ahead` frames in flight with
//! the current camera, so the image refreshes continuously and a move
//! shows in the next frame sent; after [`IDLE_FRAMES`] frames without a
//! move it stops sending until the next move, so an idle viewer leaves the
//! cluster idle. It runs until a Shutdown (or the stop future of
//! [`run_display_until`], Ctrl-C in the node and `dray sim`), which is its
//! normal end: the summary then counts as complete.
//!
//! Bad input never stops the display: tiles for frames that are not
//! outstanding, outside the image or of inconsistent sizes are ignored
//! with a warning and counted. A voxel that no store serves intact
//! ([`VoxelLost`]) ends the run with an error naming it, unless the
//! clients render it as empty (`clients.corrupt_voxel = "skip"`): then it
//! is logged once and counted in the summary. Memory holds only the outstanding frames
//! (and the shown images when `keep_frames`).
//!
//! [`CameraUpdate`]: dray_protocol::CameraUpdate
//! [`TileDone`]: dray_protocol::TileDone
//! [`FrameDone`]: dray_protocol::FrameDone
//! [`VoxelLost`]: dray_protocol::VoxelLost

mod frames;
mod metrics;
pub mod moves;
pub mod path;
pub mod web;

pub use frames::{FrameImage, TileRejected};
pub use metrics::{DisplaySummary, FrameMetrics, CSV_HEADER};
pub use moves::Move;
pub use path::{CameraPath, Keyframe, PathError};
pub use web::WebViewer;

use crate::ActorError;
use dray_protocol::{Address, CameraUpdate, Message, Ping, TileReport};
use dray_runtime::{Delivery, LinkMeter, Mailbox, SendError};
use frames::{Frames, ReadyFrame};
use metrics::CsvLog;
use std::future::Future;
use std::path::{Path, PathBuf};
use std::time::Duration;
use tokio::time::Instant;
use tracing::{debug, info, warn};

/// How long a frame whose [`FrameDone`](dray_protocol::FrameDone) came may
/// wait for missing pixels (a tile lost with its client after the scheduler
/// counted it) before it is shown anyway, the gaps black.
pub const MISSING_PIXELS_GRACE: Duration = Duration::from_secs(10);

/// When a camera could not be sent (the assigner unreachable), how long
/// until the next try.
pub const SEND_RETRY: Duration = Duration::from_millis(200);

/// Interactive mode: frames rendered with an unchanged camera (from the
/// start or the last move) before the display waits for the next move.
/// A few refreshes let a progressive or still-loading view settle (voxels
/// that missed the cache in the first frame are there for the next).
pub const IDLE_FRAMES: u64 = 4;

/// What the display does.
#[derive(Clone, Debug)]
pub struct DisplayOptions {
    /// The frame assigner, which gets the camera updates.
    pub assigner: Address,
    /// The scheduler, which hears from here of each tile whose pixels
    /// arrived.
    pub scheduler: Address,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// One camera per frame, in order; interactive: the first is where
    /// the user starts, the others are unused.
    pub cameras: Vec<dray_protocol::Camera>,
    /// Interactive mode: the camera follows the moves a user sends to the
    /// web viewer (`web` must be set) and frames go on until a Shutdown.
    pub interactive: bool,
    /// Cameras sent before the oldest frame is complete (2: double
    /// buffering; 0 counts as 1).
    pub frames_ahead: usize,
    /// Where `frames/frame-NNNNN.png` and `metrics.csv` go (created if
    /// missing).
    pub output: Option<PathBuf>,
    /// Write each frame's PNG (and depth and ids) under `output`; without
    /// it only `metrics.csv` is written.
    pub save_frames: bool,
    /// Keep the images in the summary.
    pub keep_frames: bool,
    /// Serve the live web viewer there.
    pub web: Option<std::net::SocketAddr>,
}

const ACTOR: &str = "display";

fn io_err(path: &Path, source: std::io::Error) -> ActorError {
    ActorError::Io {
        actor: ACTOR.into(),
        path: path.display().to_string(),
        source,
    }
}

/// Frame files being written at once; the display waits for the oldest
/// beyond this, so a slow disk slows it down instead of filling memory.
const MAX_PENDING_WRITES: usize = 4;

/// Files of a run.
struct Output {
    /// Where frame files go; `None`: only the metrics are written.
    frames_dir: Option<PathBuf>,
    csv: CsvLog,
    /// Frame files being written, oldest first. PNG encoding of a big
    /// frame takes milliseconds: it runs off the display's loop, which
    /// goes on receiving tiles meanwhile.
    pending: std::collections::VecDeque<tokio::task::JoinHandle<Result<(), ActorError>>>,
}

impl Output {
    fn create(dir: &Path, save_frames: bool) -> Result<Output, ActorError> {
        let frames_dir = if save_frames {
            let d = dir.join("frames");
            std::fs::create_dir_all(&d).map_err(|e| io_err(&d, e))?;
            Some(d)
        } else {
            std::fs::create_dir_all(dir).map_err(|e| io_err(dir, e))?;
            None
        };
        let csv_path = dir.join("metrics.csv");
        let csv = CsvLog::create(&csv_path).map_err(|e| io_err(&csv_path, e))?;
        Ok(Output {
            frames_dir,
            csv,
            pending: Default::default(),
        })
    }

    /// Whether frames are written as files (else only the metrics).
    fn saves_frames(&self) -> bool {
        self.frames_dir.is_some()
    }

    /// Starts writing a frame's files.
    async fn write(
        &mut self,
        width: u32,
        height: u32,
        image: FrameImage,
    ) -> Result<(), ActorError> {
        let Some(dir) = self.frames_dir.clone() else {
            return Ok(());
        };
        self.pending.push_back(tokio::task::spawn_blocking(move || {
            write_frame_files(&dir, width, height, &image)
        }));
        while self.pending.len() > MAX_PENDING_WRITES {
            if let Some(oldest) = self.pending.pop_front() {
                joined_write(oldest).await?;
            }
        }
        Ok(())
    }

    /// Waits for every file being written.
    async fn flush(&mut self) -> Result<(), ActorError> {
        while let Some(w) = self.pending.pop_front() {
            joined_write(w).await?;
        }
        Ok(())
    }
}

async fn joined_write(
    h: tokio::task::JoinHandle<Result<(), ActorError>>,
) -> Result<(), ActorError> {
    h.await.map_err(|e| ActorError::Peer {
        actor: ACTOR.into(),
        message: format!("writing a frame failed: {e}"),
    })?
}

/// Writes a frame's files (PNG, and depth and ids when present).
fn write_frame_files(
    dir: &Path,
    width: u32,
    height: u32,
    image: &FrameImage,
) -> Result<(), ActorError> {
    let stem = dir.join(format!("frame-{:05}", image.frame));
    let img_err = |e: dray_trace::image::ImageError| ActorError::Io {
        actor: ACTOR.into(),
        path: stem.display().to_string(),
        source: std::io::Error::other(e.to_string()),
    };
    dray_trace::image::write_png(&stem.with_extension("png"), width, height, &image.rgba)
        .map_err(img_err)?;
    if let Some(d) = &image.depth {
        dray_trace::image::write_pfm(&stem.with_extension("pfm"), width, height, d)
            .map_err(img_err)?;
    }
    if let Some(ids) = &image.primid {
        dray_trace::image::write_u32(&stem.with_extension("primid"), ids).map_err(img_err)?;
    }
    Ok(())
}

struct Display {
    opts: DisplayOptions,
    frames: Frames,
    /// Cameras sent so far.
    sent: u64,
    output: Option<Output>,
    viewer: Option<WebViewer>,
    summary: DisplaySummary,
    /// When the first camera went out.
    started: Option<Instant>,
    /// When the last frame was shown.
    last_shown: Option<Instant>,
    /// When to try sending cameras again after a failed send.
    retry_at: Option<Instant>,
    /// Interactive: the user's camera now.
    current: dray_protocol::Camera,
    /// Interactive: the step of a translation ([`moves::step_for`]).
    step: f32,
    /// Interactive: the moves the viewer takes.
    moves: Option<tokio::sync::mpsc::Receiver<Move>>,
    /// Interactive: cameras sent since the last move (or the start).
    since_move: u64,
    /// Interactive: time spent waiting for a move with nothing in flight,
    /// left out of the frame times and the run's time.
    idle: Duration,
    /// The display's own link, charged to each frame shown.
    links: LinkMeter,
}

impl Display {
    fn ahead(&self) -> usize {
        self.opts.frames_ahead.max(1)
    }

    fn total(&self) -> u64 {
        self.opts.cameras.len() as u64
    }

    /// Whether another camera is due (ignoring `frames_ahead`).
    fn more(&self) -> bool {
        if self.opts.interactive {
            self.since_move < IDLE_FRAMES.max(self.ahead() as u64)
        } else {
            self.sent < self.total()
        }
    }

    /// Applies `m` and every move already waiting behind it.
    fn take_moves(&mut self, m: Move) {
        let mut m = Some(m);
        let mut n = 0;
        while let Some(mv) = m {
            self.current = mv.apply(&self.current, self.step);
            n += 1;
            m = self.moves.as_mut().and_then(|rx| rx.try_recv().ok());
        }
        debug!(moves = n, camera = ?self.current, "camera moved");
        self.since_move = 0;
    }

    /// Sends cameras until `frames_ahead` frames are outstanding. When the
    /// assigner cannot be reached now, the camera is retried later (on its
    /// node's PeerUp, or after [`SEND_RETRY`]).
    async fn send_cameras(&mut self, mb: &Mailbox) -> Result<(), ActorError> {
        while self.more() && self.frames.outstanding() < self.ahead() {
            let seq = self.sent;
            let camera = if self.opts.interactive {
                self.current
            } else {
                self.opts.cameras[seq as usize]
            };
            let r = mb
                .send(
                    &self.opts.assigner,
                    Message::CameraUpdate(CameraUpdate { seq, camera }),
                )
                .await;
            match r {
                Ok(()) => {}
                Err(SendError::Protocol(e)) => {
                    return Err(ActorError::Send {
                        actor: ACTOR.into(),
                        to: self.opts.assigner.to_string(),
                        source: SendError::Protocol(e),
                    })
                }
                Err(e) => {
                    warn!(frame = seq, "camera not sent, will retry: {e}");
                    self.retry_at = Some(Instant::now() + SEND_RETRY);
                    return Ok(());
                }
            }
            debug!(frame = seq, "camera sent");
            self.retry_at = None;
            if self.opts.interactive && self.frames.outstanding() == 0 {
                // Resuming after an idle pause: the next frame's time
                // counts from now, not from the last frame shown.
                if let Some(last) = self.last_shown {
                    let now = Instant::now();
                    self.idle += now.saturating_duration_since(last);
                    self.last_shown = Some(now);
                }
            }
            self.frames.open(seq);
            if self.started.is_none() {
                self.started = Some(Instant::now());
            }
            self.sent += 1;
            self.since_move += 1;
        }
        Ok(())
    }

    /// Shows every frame that is ready, in order, after `first` if given.
    async fn show_ready(&mut self, first: Option<ReadyFrame>) -> Result<(), ActorError> {
        let mut group: Vec<ReadyFrame> = first.into_iter().collect();
        while let Some(ready) = self.frames.pop_ready() {
            group.push(ready);
        }
        let Some(latest) = group.iter().map(|r| r.completed_at).max() else {
            return Ok(());
        };
        // Shown when complete, but never before the frame before it; frames
        // shown together share the time since the last one shown.
        let since = self.last_shown.or(self.started).unwrap_or(latest);
        let shown = latest.max(since);
        let frame_ms = (shown - since).as_secs_f64() * 1e3 / group.len() as f64;
        self.last_shown = Some(shown);
        for ready in group {
            self.show(ready, frame_ms).await?;
        }
        Ok(())
    }

    async fn show(&mut self, ready: ReadyFrame, frame_ms: f64) -> Result<(), ActorError> {
        let ReadyFrame {
            image,
            mut stats,
            missing_pixels,
            ..
        } = ready;
        stats.link.display = self.links.take().display;
        let m = FrameMetrics::compute(image.frame, &stats, frame_ms);
        if missing_pixels > 0 {
            warn!(
                frame = image.frame,
                missing_pixels, "frame shown with pixels missing"
            );
            self.summary.missing_pixels += missing_pixels as u64;
        }
        info!(
            frame = m.frame,
            frame_ms = format!("{:.1}", m.frame_ms),
            rays = m.rays,
            misses = m.misses,
            "frame shown"
        );
        let (w, h) = (self.opts.width, self.opts.height);
        if let Some(v) = &self.viewer {
            v.publish(w, h, &image, &m);
        }
        let keep = self.opts.keep_frames;
        let mut image = image;
        if let Some(out) = &mut self.output {
            let path = out.csv.path().to_path_buf();
            out.csv.append(&m).map_err(|e| io_err(&path, e))?;
            if out.saves_frames() {
                let to_write = if keep {
                    image.clone()
                } else {
                    std::mem::replace(
                        &mut image,
                        FrameImage {
                            frame: m.frame,
                            rgba: Vec::new(),
                            depth: None,
                            primid: None,
                        },
                    )
                };
                out.write(w, h, to_write).await?;
            }
        }
        if keep {
            self.summary.images.push(image);
        } else {
            self.frames.recycle(image.rgba);
        }
        self.summary.push(m);
        Ok(())
    }

    /// Waits for the frame files being written; a failure is logged (the
    /// run is ending anyway).
    async fn flush(&mut self) {
        if let Some(out) = &mut self.output {
            if let Err(e) = out.flush().await {
                warn!("writing the last frames: {e}");
            }
        }
    }

    fn finish(mut self, stopped: Option<String>) -> DisplaySummary {
        let seconds = match (self.started, self.last_shown) {
            (Some(a), Some(b)) => (b - a).saturating_sub(self.idle).as_secs_f64(),
            _ => 0.0,
        };
        if self.opts.interactive {
            // Stopping is how an interactive run ends.
            if let Some(why) = &stopped {
                info!("interactive run over: {why}");
            }
            self.summary.frames_requested = self.summary.frames.len();
            self.summary.complete = true;
        } else {
            self.summary.complete = self.summary.frames.len() == self.opts.cameras.len();
        }
        if !self.summary.complete {
            self.summary.stopped_early = stopped.or(Some("stopped".into()));
        }
        self.summary.finish(seconds);
        self.summary
    }
}

/// Runs the display until every camera's frame is shown (or a Shutdown;
/// interactive: until a Shutdown).
pub async fn run_display(mb: Mailbox, opts: DisplayOptions) -> Result<DisplaySummary, ActorError> {
    run_display_until(mb, opts, std::future::pending()).await
}

/// What a display cannot run with.
fn check_options(opts: &DisplayOptions) -> Result<(), ActorError> {
    if opts.interactive && (opts.web.is_none() || opts.cameras.is_empty()) {
        return Err(ActorError::Peer {
            actor: ACTOR.into(),
            message: "interactive mode needs a web viewer and a first camera".into(),
        });
    }
    if opts.width == 0 || opts.height == 0 {
        return Err(ActorError::Peer {
            actor: ACTOR.into(),
            message: format!("image of {}x{} is empty", opts.width, opts.height),
        });
    }
    Ok(())
}

/// [`run_display`], which also ends, with the summary of what was shown,
/// when `stop` completes (Ctrl-C).
pub async fn run_display_until(
    mb: Mailbox,
    opts: DisplayOptions,
    stop: impl Future<Output = ()>,
) -> Result<DisplaySummary, ActorError> {
    check_options(&opts)?;
    let web_err = |addr: std::net::SocketAddr, e| ActorError::Io {
        actor: ACTOR.into(),
        path: format!("http://{addr}/"),
        source: e,
    };
    let viewer = match opts.web {
        Some(addr) if opts.interactive => {
            let (v, rx) = WebViewer::start_interactive(addr)
                .await
                .map_err(|e| web_err(addr, e))?;
            Some((v, Some(rx)))
        }
        Some(addr) => Some((
            WebViewer::start(addr).await.map_err(|e| web_err(addr, e))?,
            None,
        )),
        None => None,
    };
    run_display_with_viewer(mb, opts, viewer, stop).await
}

/// [`run_display_until`] serving a web viewer already listening (started
/// with [`WebViewer::start`], or [`WebViewer::start_interactive`] and its
/// moves): a caller that lets the system pick the port knows it before the
/// display runs. `opts.web` is then only checked to be set.
pub async fn run_display_with_viewer(
    mut mb: Mailbox,
    opts: DisplayOptions,
    viewer: Option<(WebViewer, Option<tokio::sync::mpsc::Receiver<Move>>)>,
    stop: impl Future<Output = ()>,
) -> Result<DisplaySummary, ActorError> {
    tokio::pin!(stop);
    check_options(&opts)?;
    let output = opts
        .output
        .as_deref()
        .map(|dir| Output::create(dir, opts.save_frames))
        .transpose()?;
    let (viewer, moves) = match viewer {
        Some((v, moves)) => (Some(v), moves),
        None => (None, None),
    };
    if opts.interactive && moves.is_none() {
        return Err(ActorError::Peer {
            actor: ACTOR.into(),
            message: "interactive mode needs an interactive web viewer".into(),
        });
    }
    let current = opts
        .cameras
        .first()
        .copied()
        .unwrap_or(dray_protocol::Camera {
            eye: [0.0; 3],
            look: [0.0, 0.0, 1.0],
            up: [0.0, 1.0, 0.0],
            fov_y_deg: 45.0,
        });
    let mut d = Display {
        frames: Frames::new(opts.width, opts.height),
        summary: DisplaySummary::new(
            opts.width,
            opts.height,
            if opts.interactive {
                0
            } else {
                opts.cameras.len()
            },
        ),
        opts,
        sent: 0,
        output,
        viewer,
        started: None,
        last_shown: None,
        retry_at: None,
        step: moves::step_for(&current),
        current,
        moves,
        since_move: 0,
        idle: Duration::ZERO,
        links: LinkMeter::new(mb.handle().bus().clone()),
    };
    if d.opts.cameras.is_empty() {
        return Ok(d.finish(None));
    }

    // Wait for the assigner's node, still answering a Shutdown.
    let bus = mb.handle().bus().clone();
    let node = d.opts.assigner.node.clone();
    if node != *bus.node() && !bus.is_connected(&node) {
        info!("waiting for {node}");
        let wait = bus.wait_for_peer(&node);
        tokio::pin!(wait);
        loop {
            tokio::select! {
                _ = &mut wait => break,
                _ = &mut stop => return Ok(d.finish(Some("interrupted".into()))),
                delivery = mb.recv() => match delivery {
                    None => return Err(ActorError::BusClosed(ACTOR.into())),
                    Some(Delivery::Message { msg: Message::Shutdown(s), .. }) => {
                        return Ok(d.finish(Some(format!("shutdown: {}", s.reason))));
                    }
                    Some(Delivery::Message { from, msg: Message::Ping(p) }) => {
                        let _ = mb.send(&from, Message::Pong(Ping { seq: p.seq })).await;
                    }
                    Some(other) => debug!("before the assigner is up: {other:?}"),
                },
            }
        }
    }
    d.send_cameras(&mb).await?;

    while d.opts.interactive || d.frames.next_out() < d.total() {
        // A frame whose report came but whose pixels do not is shown anyway
        // after a grace time; a camera that could not be sent is retried.
        let stuck = d.frames.stuck_next().map(|at| at + MISSING_PIXELS_GRACE);
        let deadline = match (stuck, d.retry_at) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        };
        let delivery = tokio::select! {
            delivery = mb.recv() => delivery,
            _ = &mut stop => {
                info!("interrupted");
                d.flush().await;
                return Ok(d.finish(Some("interrupted".into())));
            }
            m = next_move(&mut d.moves) => {
                match m {
                    Some(m) => {
                        d.take_moves(m);
                        d.send_cameras(&mb).await?;
                    }
                    None => d.moves = None,
                }
                continue;
            }
            _ = crate::sleep_until_opt(deadline) => {
                let now = Instant::now();
                if stuck.is_some_and(|t| t <= now) {
                    if let Some(ready) = d.frames.force_next(now) {
                        d.show_ready(Some(ready)).await?;
                    }
                }
                d.send_cameras(&mb).await?;
                continue;
            }
        };
        let now = Instant::now();
        match delivery {
            None => return Err(ActorError::BusClosed(ACTOR.into())),
            Some(Delivery::Message { from, msg }) => match msg {
                Message::TileDone(t) => match d.frames.add_tile(&t, now) {
                    Ok(0) => d.summary.duplicate_tiles += 1,
                    Ok(_) => {
                        // Now the tile is done: the scheduler hears it from
                        // here, so a tile lost on its way never counts.
                        let report = TileReport {
                            client: from.node.clone(),
                            frame: t.frame,
                            tile: t.tile,
                            stats: t.stats,
                            hits: t.hits,
                        };
                        if let Err(e) = mb
                            .send(&d.opts.scheduler, Message::TileReport(report))
                            .await
                        {
                            debug!(
                                frame = t.frame,
                                "cannot report a tile to the scheduler: {e}"
                            );
                        }
                    }
                    Err(why) => {
                        warn!(from = %from, frame = t.frame, "tile ignored: {why}");
                        d.summary.tiles_ignored += 1;
                    }
                },
                Message::FrameDone(f) => {
                    if !d.frames.frame_done(f.frame, f.stats, now) {
                        warn!(from = %from, frame = f.frame, "FrameDone for a frame not outstanding ignored");
                    }
                }
                Message::VoxelLost(l) if l.skipped => {
                    if d.summary.voxel_missing(l.id) {
                        warn!(voxel = l.id, store = %l.store, client = %from.node, reason = %l.reason,
                            "no store serves this voxel intact: the frames show it as empty");
                    }
                }
                Message::VoxelLost(l) => {
                    d.flush().await;
                    return Err(ActorError::Peer {
                        actor: ACTOR.into(),
                        message: format!(
                            "voxel {} cannot be served intact by {}: {} (reported by {}); the frames cannot complete (clients.corrupt_voxel = \"skip\" renders them without it)",
                            l.id, l.store, l.reason, from.node
                        ),
                    });
                }
                Message::Shutdown(s) => {
                    info!("shutdown: {}", s.reason);
                    d.flush().await;
                    return Ok(d.finish(Some(format!("shutdown: {}", s.reason))));
                }
                Message::Ping(p) => {
                    let _ = mb.send(&from, Message::Pong(Ping { seq: p.seq })).await;
                }
                other => debug!(from = %from, "ignored {:?}", other.kind()),
            },
            Some(Delivery::PeerDown { node, reason }) => {
                if node == d.opts.assigner.node {
                    warn!("{node} is down: {reason}");
                }
            }
            Some(Delivery::PeerUp { node, .. }) => debug!("{node} is up"),
        }
        d.show_ready(None).await?;
        d.send_cameras(&mb).await?;
    }
    if let Some(out) = &mut d.output {
        out.flush().await?;
    }
    Ok(d.finish(None))
}

/// The next move; never when there is no viewer taking them.
async fn next_move(rx: &mut Option<tokio::sync::mpsc::Receiver<Move>>) -> Option<Move> {
    match rx {
        Some(rx) => rx.recv().await,
        None => std::future::pending().await,
    }
}
