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
//! With [`DisplayOptions::samples`] above 1, each camera goes out that many
//! times, one sample a frame, and what is shown, saved and kept per camera
//! is the mean of its samples (`samples.rs`); every frame still gets its
//! metrics row.
//!
//! In interactive mode ([`DisplayOptions::interactive`]) a person at the
//! web viewer flies the camera instead: the display starts from the first
//! camera and applies the [`ViewInput`]s the page sends ([`view`] has the
//! controls). While the view changes it keeps `frames_ahead` frames in
//! flight; once it stands still, each next frame is another jittered
//! sample of the same image, accumulated here, up to `max_samples`; then
//! it sends nothing until the next input, so an idle viewer leaves the
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
//! Shape: `state::Display` owns what the display decides (the frames
//! outstanding, the cameras sent and the interactive camera, the clocks
//! of the run, the summary); its handlers (a tile, a frame done, a voxel
//! lost, a Shutdown, a ping, the viewer's moves, the deadline, the stop
//! future, and the loop's word that a camera left or did not) push
//! effects (`state::Out`: send a camera, report a tile to the scheduler,
//! answer a ping, show a frame, end the run); [`run_display_with_viewer`]
//! receives, calls the handler and carries the effects out: sends, the
//! viewer, `metrics.csv`, and the frame files, written off the loop at
//! most `MAX_PENDING_WRITES` at once, and hands a shown image back for
//! the summary or the next frame's pixels.
//!
//! [`CameraUpdate`]: dray_protocol::CameraUpdate
//! [`TileDone`]: dray_protocol::TileDone
//! [`FrameDone`]: dray_protocol::FrameDone
//! [`VoxelLost`]: dray_protocol::VoxelLost

mod frames;
mod metrics;
pub mod path;
pub mod record;
mod samples;
mod state;
pub mod view;
pub mod web;

pub use frames::{FrameImage, TileRejected};
pub use metrics::{DisplaySummary, FrameMetrics, CSV_HEADER};
pub use path::{CameraPath, Keyframe, PathError};
pub use view::{Picked, View, ViewInput};
pub use web::{PageEvent, ShownFrame, WebOptions, WebViewer};

use crate::ActorError;
use dray_protocol::{Address, Message, RenderSettings};
use dray_runtime::{Delivery, LinkMeter, Mailbox, SendError};
use metrics::CsvLog;
use state::{Display, End, Out};
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

/// Interactive mode: samples per pixel a still view is refined to, unless
/// the options say otherwise; about a second of frames at this machine's
/// rates for a small cluster.
pub const DEFAULT_MAX_SAMPLES: u32 = 32;

/// How long the viewer's pages have to hear that the run ended.
const ENDED_NOTICE: Duration = Duration::from_millis(300);

/// What the display does.
#[derive(Clone, Debug)]
pub struct DisplayOptions {
    /// The frame assigner, which gets the camera updates.
    pub assigner: Address,
    /// The scheduler, which hears from here of each tile whose pixels
    /// arrived.
    pub scheduler: Address,
    /// Image width (interactive: at the 1× scale).
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Shading, as the assigner has it from the config (interactive: what
    /// the viewer's toggles start from).
    pub settings: RenderSettings,
    /// Interactive: samples per pixel a still view is refined to.
    pub max_samples: u32,
    /// The web viewer's token; `None`: a fresh random one.
    pub web_token: Option<String>,
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
    /// Keep each frame's metrics in the summary (its run-wide figures are
    /// always there; with an `output`, so is each frame's row in
    /// `metrics.csv`).
    pub keep_metrics: bool,
    /// Serve the live web viewer there.
    pub web: Option<std::net::SocketAddr>,
    /// Samples per camera (`render.samples`; 0 counts as 1): each camera
    /// is sent as this many frames, samples 0 to `samples - 1`, and its
    /// image is their mean. Interactive mode renders sample 0 only.
    pub samples: u32,
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
        self.pending.push_back(crate::spawn_blocking(move || {
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
        Some(addr) => {
            let web = WebOptions {
                interactive: opts.interactive,
                token: opts.web_token.clone(),
            };
            Some(
                WebViewer::start(addr, web)
                    .await
                    .map_err(|e| web_err(addr, e))?,
            )
        }
        None => None,
    };
    run_display_with_viewer(mb, opts, viewer, stop).await
}

/// [`run_display_until`] serving a web viewer already listening (started
/// with [`WebViewer::start`], interactive with its inputs): a caller that
/// lets the system pick the port knows it before the display runs.
/// `opts.web` is then only checked to be set.
pub async fn run_display_with_viewer(
    mut mb: Mailbox,
    opts: DisplayOptions,
    viewer: Option<(WebViewer, Option<tokio::sync::mpsc::Receiver<ViewInput>>)>,
    stop: impl Future<Output = ()>,
) -> Result<DisplaySummary, ActorError> {
    tokio::pin!(stop);
    check_options(&opts)?;
    let output = opts
        .output
        .as_deref()
        .map(|dir| Output::create(dir, opts.save_frames))
        .transpose()?;
    let (viewer, mut inputs) = match viewer {
        Some((v, inputs)) => (Some(v), inputs),
        None => (None, None),
    };
    if opts.interactive && inputs.is_none() {
        return Err(ActorError::Peer {
            actor: ACTOR.into(),
            message: "interactive mode needs an interactive web viewer".into(),
        });
    }
    let mut links = LinkMeter::new(mb.handle().bus().clone());
    let mut sink = Sink {
        assigner: opts.assigner.clone(),
        scheduler: opts.scheduler.clone(),
        output,
        viewer,
    };
    let mut d = Display::new(opts, Box::new(move || links.take().display));
    if let Some(v) = &sink.viewer {
        let view = d.view();
        let choices = d.choices();
        v.set_status(|s| {
            s.choices = choices;
            s.home_distance = view.map_or(1.0, |v| v.home_distance());
            s.max_samples = view.map_or(1, |v| v.max_samples());
        });
    }
    if d.opts().cameras.is_empty() {
        return Ok(d.finish(None));
    }
    let mut out = Vec::new();

    // Wait for the assigner's node, still answering a Shutdown.
    let bus = mb.handle().bus().clone();
    let node = sink.assigner.node.clone();
    if node != *bus.node() && !bus.is_connected(&node) {
        info!("waiting for {node}");
        let wait = bus.wait_for_peer(&node);
        tokio::pin!(wait);
        loop {
            tokio::select! {
                biased;
                _ = &mut wait => break,
                _ = &mut stop => d.interrupted(&mut out),
                delivery = mb.recv() => match delivery {
                    None => return Err(ActorError::BusClosed(ACTOR.into())),
                    Some(Delivery::Message { msg: Message::Shutdown(s), .. }) => {
                        d.shutdown(&s.reason, &mut out);
                    }
                    Some(Delivery::Message { from, msg: Message::Ping(p) }) => {
                        d.ping(from, p, &mut out);
                    }
                    Some(other) => debug!("before the assigner is up: {other:?}"),
                },
            }
            if let Some(end) = sink.carry(&mut d, &mut out, &mb).await? {
                return sink.end(d, end).await;
            }
        }
    }

    d.advance(&mut out);
    loop {
        if let Some(end) = sink.carry(&mut d, &mut out, &mb).await? {
            return sink.end(d, end).await;
        }
        let deadline = d.deadline();
        tokio::select! {
            biased;
            delivery = mb.recv() => {
                let now = Instant::now();
                match delivery {
                    None => return Err(ActorError::BusClosed(ACTOR.into())),
                    Some(Delivery::Message { from, msg }) => match msg {
                        Message::TileDone(t) => d.tile_done(&from, t, now, &mut out),
                        Message::FrameDone(f) => d.frame_done(&from, f, now),
                        Message::VoxelLost(l) => d.voxel_lost(&from, l, &mut out),
                        Message::Shutdown(s) => d.shutdown(&s.reason, &mut out),
                        Message::Ping(p) => d.ping(from, p, &mut out),
                        other => debug!(from = %from, "ignored {:?}", other.kind()),
                    },
                    Some(Delivery::PeerDown { node, reason }) => {
                        if node == sink.assigner.node {
                            warn!("{node} is down: {reason}");
                        }
                    }
                    Some(Delivery::PeerUp { node, .. }) => debug!("{node} is up"),
                }
                d.advance(&mut out);
            }
            _ = &mut stop => d.interrupted(&mut out),
            i = next_input(&mut inputs) => match i {
                Some(i) => {
                    // Every input already waiting goes into the same frame.
                    let mut all = vec![i];
                    while let Some(i) = inputs.as_mut().and_then(|rx| rx.try_recv().ok()) {
                        all.push(i);
                    }
                    d.input(all, Instant::now(), &mut out);
                }
                None => inputs = None,
            },
            _ = crate::sleep_until_opt(deadline) => d.tick(Instant::now(), &mut out),
        }
    }
}

/// Where the display's effects go: the mailbox's peers, the files and the
/// web viewer.
struct Sink {
    assigner: Address,
    scheduler: Address,
    output: Option<Output>,
    viewer: Option<WebViewer>,
}

impl Sink {
    /// Carries out the effects in `out`, and those the display pushes
    /// while told how they went; the run's end, if one came.
    async fn carry(
        &mut self,
        d: &mut Display,
        out: &mut Vec<Out>,
        mb: &Mailbox,
    ) -> Result<Option<End>, ActorError> {
        while !out.is_empty() {
            for o in std::mem::take(out) {
                match o {
                    Out::Camera(u) => {
                        let seq = u.seq;
                        match mb.send(&self.assigner, Message::CameraUpdate(u)).await {
                            Ok(()) => {
                                debug!(frame = seq, "camera sent");
                                d.camera_sent(Instant::now(), out);
                            }
                            Err(SendError::Protocol(e)) => {
                                return Err(ActorError::Send {
                                    actor: ACTOR.into(),
                                    to: self.assigner.to_string(),
                                    source: SendError::Protocol(e),
                                })
                            }
                            Err(e) => {
                                warn!(frame = seq, "camera not sent, will retry: {e}");
                                d.camera_failed(Instant::now());
                            }
                        }
                    }
                    Out::Report(report) => {
                        let frame = report.frame;
                        if let Err(e) = mb.send(&self.scheduler, Message::TileReport(report)).await
                        {
                            debug!(frame, "cannot report a tile to the scheduler: {e}");
                        }
                    }
                    Out::Pong { to, ping } => {
                        let _ = mb.send(&to, Message::Pong(ping)).await;
                    }
                    Out::Show {
                        image,
                        metrics,
                        shown,
                    } => {
                        let keep = d.keeps_frames();
                        if let Some(image) = self.show(image, &metrics, shown, keep).await? {
                            d.shown(image);
                        }
                    }
                    Out::Metrics(metrics) => self.log(&metrics)?,
                    Out::Choices(c) => {
                        if let Some(v) = &self.viewer {
                            v.set_status(|s| s.choices = Some(c));
                        }
                    }
                    Out::Picked(p) => {
                        if let Some(v) = &self.viewer {
                            v.tell(PageEvent::Picked(p));
                        }
                    }
                    Out::Recorded(r) => {
                        if let Err(why) = &r {
                            warn!("recording the flight: {why}");
                        }
                        if let Some(v) = &self.viewer {
                            v.tell(PageEvent::Recorded(r));
                        }
                    }
                    Out::End(end) => return Ok(Some(end)),
                }
            }
        }
        Ok(None)
    }

    /// Publishes a frame, appends its metrics row and starts writing its
    /// files (a copy when `keep` holds the image for the summary); the
    /// image unless the writer took it.
    async fn show(
        &mut self,
        image: FrameImage,
        metrics: &FrameMetrics,
        shown: state::Shown,
        keep: bool,
    ) -> Result<Option<FrameImage>, ActorError> {
        let (w, h) = (image.width, image.height);
        if let Some(v) = &self.viewer {
            v.publish(ShownFrame::new(
                image.frame,
                (w, h),
                std::sync::Arc::new(image.rgba.clone()),
                (shown.samples, shown.view, shown.still, shown.path),
                metrics.clone(),
            ));
        }
        let Some(out) = &mut self.output else {
            return Ok(Some(image));
        };
        let path = out.csv.path().to_path_buf();
        out.csv.append(metrics).map_err(|e| io_err(&path, e))?;
        if !out.saves_frames() {
            return Ok(Some(image));
        }
        if keep {
            out.write(w, h, image.clone()).await?;
            Ok(Some(image))
        } else {
            out.write(w, h, image).await?;
            Ok(None)
        }
    }

    /// Appends a frame's row to `metrics.csv`, if one is written.
    fn log(&mut self, metrics: &FrameMetrics) -> Result<(), ActorError> {
        if let Some(out) = &mut self.output {
            let path = out.csv.path().to_path_buf();
            out.csv.append(metrics).map_err(|e| io_err(&path, e))?;
        }
        Ok(())
    }

    /// Ends the run: waits for the frame files (a failure only fails a
    /// complete run; a stopped one is ending anyway) and sums it up.
    async fn end(&mut self, d: Display, end: End) -> Result<DisplaySummary, ActorError> {
        if let Some(v) = &self.viewer {
            let why = match &end {
                End::Complete => "every frame is shown".to_string(),
                End::Stopped(why) | End::Failed(why) => why.clone(),
            };
            v.set_status(|s| s.ended = Some(why));
            tokio::time::sleep(ENDED_NOTICE).await;
        }
        match end {
            End::Complete => {
                if let Some(out) = &mut self.output {
                    out.flush().await?;
                }
                Ok(d.finish(None))
            }
            End::Stopped(why) => {
                self.flush_anyway().await;
                Ok(d.finish(Some(why)))
            }
            End::Failed(message) => {
                self.flush_anyway().await;
                Err(ActorError::Peer {
                    actor: ACTOR.into(),
                    message,
                })
            }
        }
    }

    /// Waits for the frame files being written; a failure is logged.
    async fn flush_anyway(&mut self) {
        if let Some(out) = &mut self.output {
            if let Err(e) = out.flush().await {
                warn!("writing the last frames: {e}");
            }
        }
    }
}

/// The next input; never when there is no viewer taking them.
async fn next_input(rx: &mut Option<tokio::sync::mpsc::Receiver<ViewInput>>) -> Option<ViewInput> {
    match rx {
        Some(rx) => rx.recv().await,
        None => std::future::pending().await,
    }
}
