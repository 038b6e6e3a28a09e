//! The display's state and handlers: which cameras go out and when, which
//! tiles and reports count, which frames are shown in what order and with
//! what metrics, and when the run ends. Nothing here touches the network,
//! the disk or the web viewer: the handlers push [`Out`] effects that the
//! run loop carries out.

use super::frames::{Frames, ReadyFrame};
use super::samples::{Added, Samples};
use super::{
    moves, DisplayOptions, DisplaySummary, FrameImage, FrameMetrics, Move, IDLE_FRAMES,
    MISSING_PIXELS_GRACE, SEND_RETRY,
};
use dray_protocol::{
    Address, Camera, CameraUpdate, FrameDone, Ping, TileDone, TileReport, VoxelLost,
};
use std::time::Duration;
use tokio::time::Instant;
use tracing::{debug, info, warn};

/// What the display's handlers ask the run loop to do, in order.
#[derive(Debug)]
pub(super) enum Out {
    /// Send the assigner this camera; the loop calls
    /// [`Display::camera_sent`] once it left, or [`Display::camera_failed`].
    Camera(CameraUpdate),
    /// Tell the scheduler that a tile's pixels arrived.
    Report(TileReport),
    /// Answer a ping.
    Pong { to: Address, ping: Ping },
    /// Show a frame: publish it to the viewer, append its metrics row and
    /// write its files; the loop hands the image back with
    /// [`Display::shown`] unless it went to the file writer.
    Show {
        image: FrameImage,
        metrics: FrameMetrics,
    },
    /// A frame that added a sample to a camera whose image is not
    /// complete yet: only its metrics row.
    Metrics(FrameMetrics),
    /// The run is over; nothing follows.
    End(End),
}

/// How a run ends.
#[derive(Debug, PartialEq)]
pub(super) enum End {
    /// Every camera's frame was shown: the files must all be written.
    Complete,
    /// A Shutdown or the stop future, with why.
    Stopped(String),
    /// The run cannot go on: the error's message.
    Failed(String),
}

/// The display's own link since the last frame shown, in bytes.
pub(super) type LinkTake = Box<dyn FnMut() -> u64 + Send>;

/// A display's state: the frames outstanding, the cameras sent, the
/// interactive camera, the clocks of the run and what it showed so far.
pub(super) struct Display {
    opts: DisplayOptions,
    frames: Frames,
    /// Cameras sent so far.
    sent: u64,
    /// A camera is out and its send has not been reported yet.
    sending: bool,
    /// An [`Out::End`] went out: nothing else does.
    ended: bool,
    summary: DisplaySummary,
    /// When the first camera went out.
    started: Option<Instant>,
    /// When the last frame was shown.
    last_shown: Option<Instant>,
    /// When to try sending cameras again after a failed send.
    retry_at: Option<Instant>,
    /// Interactive: the user's camera now.
    current: Camera,
    /// Interactive: the step of a translation ([`moves::step_for`]).
    step: f32,
    /// Interactive: cameras sent since the last move (or the start).
    since_move: u64,
    /// Interactive: time spent waiting for a move with nothing in flight,
    /// left out of the frame times and the run's time.
    idle: Duration,
    /// The display's own link, charged to each frame shown.
    link: LinkTake,
    /// The samples of the camera being shown, averaged into its image.
    samples: Samples,
}

impl Display {
    pub fn new(opts: DisplayOptions, link: LinkTake) -> Display {
        let current = opts.cameras.first().copied().unwrap_or(Camera {
            eye: [0.0; 3],
            look: [0.0, 0.0, 1.0],
            up: [0.0, 1.0, 0.0],
            fov_y_deg: 45.0,
        });
        let samples = Samples::new(
            if opts.interactive { 1 } else { opts.samples },
            opts.width,
            opts.height,
        );
        let requested = if opts.interactive {
            0
        } else {
            opts.cameras.len() * samples.per_camera() as usize
        };
        Display {
            frames: Frames::new(opts.width, opts.height),
            summary: DisplaySummary::new(opts.width, opts.height, requested),
            opts,
            sent: 0,
            sending: false,
            ended: false,
            started: None,
            last_shown: None,
            retry_at: None,
            step: moves::step_for(&current),
            current,
            since_move: 0,
            idle: Duration::ZERO,
            link,
            samples,
        }
    }

    pub fn opts(&self) -> &DisplayOptions {
        &self.opts
    }

    fn ahead(&self) -> usize {
        self.opts.frames_ahead.max(1)
    }

    /// Frames of the run: every camera's samples.
    fn total(&self) -> u64 {
        self.opts.cameras.len() as u64 * u64::from(self.samples.per_camera())
    }

    /// Whether another camera is due (ignoring `frames_ahead`).
    fn more(&self) -> bool {
        if self.opts.interactive {
            self.since_move < IDLE_FRAMES.max(self.ahead() as u64)
        } else {
            self.sent < self.total()
        }
    }

    /// When the loop must call [`Display::tick`]: a frame whose report came
    /// but whose pixels do not is shown anyway after a grace time; a camera
    /// that could not be sent is retried.
    pub fn deadline(&self) -> Option<Instant> {
        let stuck = self.frames.stuck_next().map(|at| at + MISSING_PIXELS_GRACE);
        match (stuck, self.retry_at) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    /// Something arrived (or the run starts): frames ready are shown, the
    /// run ends once every camera's frame is, and cameras due go out.
    pub fn advance(&mut self, out: &mut Vec<Out>) {
        self.show_ready(None, out);
        self.end_or_send(out);
    }

    /// The deadline passed: a frame stuck beyond its grace time is shown
    /// with its gaps black, and cameras are sent again.
    pub fn tick(&mut self, now: Instant, out: &mut Vec<Out>) {
        if self.ended {
            return;
        }
        let stuck = self.frames.stuck_next().map(|at| at + MISSING_PIXELS_GRACE);
        if stuck.is_some_and(|t| t <= now) {
            if let Some(ready) = self.frames.force_next(now) {
                self.show_ready(Some(ready), out);
            }
        }
        self.end_or_send(out);
    }

    fn end_or_send(&mut self, out: &mut Vec<Out>) {
        if self.ended {
            return;
        }
        if !self.opts.interactive && self.frames.next_out() >= self.total() {
            self.ended = true;
            out.push(Out::End(End::Complete));
            return;
        }
        self.send_camera(out);
    }

    /// A tile from `from`: its pixels go in place and, if it brought any,
    /// the scheduler hears of it; a duplicate or a bad tile is counted.
    pub fn tile_done(&mut self, from: &Address, t: TileDone, now: Instant, out: &mut Vec<Out>) {
        match self.frames.add_tile(&t, now) {
            Ok(0) => self.summary.duplicate_tiles += 1,
            // Now the tile is done: the scheduler hears it from here, so a
            // tile lost on its way never counts.
            Ok(_) => out.push(Out::Report(TileReport {
                client: from.node.clone(),
                frame: t.frame,
                tile: t.tile,
                stats: t.stats,
                hits: t.hits,
            })),
            Err(why) => {
                warn!(from = %from, frame = t.frame, "tile ignored: {why}");
                self.summary.tiles_ignored += 1;
            }
        }
    }

    /// The scheduler reports every tile of a frame.
    pub fn frame_done(&mut self, from: &Address, f: FrameDone, now: Instant) {
        if !self.frames.frame_done(f.frame, f.stats, now) {
            warn!(from = %from, frame = f.frame, "FrameDone for a frame not outstanding ignored");
        }
    }

    /// A voxel no store serves intact: counted once when the clients
    /// render it as empty, else the end of the run.
    pub fn voxel_lost(&mut self, from: &Address, l: VoxelLost, out: &mut Vec<Out>) {
        if l.skipped {
            if self.summary.voxel_missing(l.id) {
                warn!(voxel = l.id, store = %l.store, client = %from.node, reason = %l.reason,
                    "no store serves this voxel intact: the frames show it as empty");
            }
            return;
        }
        self.end(
            End::Failed(format!(
                "voxel {} cannot be served intact by {}: {} (reported by {}); the frames cannot complete (clients.corrupt_voxel = \"skip\" renders them without it)",
                l.id, l.store, l.reason, from.node
            )),
            out,
        );
    }

    /// A Shutdown: the run stops.
    pub fn shutdown(&mut self, reason: &str, out: &mut Vec<Out>) {
        info!("shutdown: {reason}");
        self.end(End::Stopped(format!("shutdown: {reason}")), out);
    }

    /// The stop future completed (Ctrl-C): the run stops.
    pub fn interrupted(&mut self, out: &mut Vec<Out>) {
        info!("interrupted");
        self.end(End::Stopped("interrupted".into()), out);
    }

    fn end(&mut self, end: End, out: &mut Vec<Out>) {
        if !self.ended {
            self.ended = true;
            out.push(Out::End(end));
        }
    }

    /// `from` pings.
    pub fn ping(&mut self, from: Address, ping: Ping, out: &mut Vec<Out>) {
        out.push(Out::Pong { to: from, ping });
    }

    /// Interactive: the viewer's moves, oldest first, make the next camera.
    pub fn moved(&mut self, moves: &[Move], out: &mut Vec<Out>) {
        for mv in moves {
            self.current = mv.apply(&self.current, self.step);
        }
        debug!(moves = moves.len(), camera = ?self.current, "camera moved");
        self.since_move = 0;
        self.end_or_send(out);
    }

    /// Pushes the next camera if one is due, none is being sent, and
    /// fewer than `frames_ahead` frames are outstanding; the loop reports
    /// back, and each camera sent makes room to check for the next.
    fn send_camera(&mut self, out: &mut Vec<Out>) {
        if self.ended || self.sending || !self.more() || self.frames.outstanding() >= self.ahead() {
            return;
        }
        let seq = self.sent;
        let (camera, sample) = if self.opts.interactive {
            (self.current, 0)
        } else {
            let (camera, sample) = self.samples.of(seq);
            (self.opts.cameras[camera as usize], sample)
        };
        self.sending = true;
        out.push(Out::Camera(CameraUpdate {
            seq,
            camera,
            sample,
            format: None,
        }));
    }

    /// The camera pushed last has left: its frame is outstanding, and the
    /// next camera goes out if due.
    pub fn camera_sent(&mut self, now: Instant, out: &mut Vec<Out>) {
        self.sending = false;
        self.retry_at = None;
        if self.opts.interactive && self.frames.outstanding() == 0 {
            // Resuming after an idle pause: the next frame's time counts
            // from now, not from the last frame shown.
            if let Some(last) = self.last_shown {
                self.idle += now.saturating_duration_since(last);
                self.last_shown = Some(now);
            }
        }
        self.frames.open(self.sent);
        if self.started.is_none() {
            self.started = Some(now);
        }
        self.sent += 1;
        self.since_move += 1;
        self.send_camera(out);
    }

    /// The camera pushed last could not be sent now (the assigner not
    /// reachable): it is retried on the next event or after [`SEND_RETRY`].
    pub fn camera_failed(&mut self, now: Instant) {
        self.sending = false;
        self.retry_at = Some(now + SEND_RETRY);
    }

    /// Shows every frame that is ready, in order, after `first` if given.
    fn show_ready(&mut self, first: Option<ReadyFrame>, out: &mut Vec<Out>) {
        if self.ended {
            return;
        }
        let mut group: Vec<ReadyFrame> = first.into_iter().collect();
        while let Some(ready) = self.frames.pop_ready() {
            group.push(ready);
        }
        let Some(latest) = group.iter().map(|r| r.completed_at).max() else {
            return;
        };
        // Shown when complete, but never before the frame before it; frames
        // shown together share the time since the last one shown.
        let since = self.last_shown.or(self.started).unwrap_or(latest);
        let shown = latest.max(since);
        let frame_ms = (shown - since).as_secs_f64() * 1e3 / group.len() as f64;
        self.last_shown = Some(shown);
        for ready in group {
            self.show(ready, frame_ms, out);
        }
    }

    fn show(&mut self, ready: ReadyFrame, frame_ms: f64, out: &mut Vec<Out>) {
        let ReadyFrame {
            image,
            mut stats,
            missing_pixels,
            ..
        } = ready;
        stats.link.display = (self.link)();
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
        match self.samples.add(image) {
            Added::Camera(image) => out.push(Out::Show {
                image,
                metrics: m.clone(),
            }),
            Added::Pending(rgba) => {
                self.frames.recycle(rgba);
                out.push(Out::Metrics(m.clone()));
            }
        }
        self.summary.push(m);
    }

    /// A shown frame's image is back from the loop: kept for the summary
    /// (`keep_frames`) or its pixels reused for a later frame.
    pub fn shown(&mut self, image: FrameImage) {
        if self.opts.keep_frames {
            self.summary.images.push(image);
        } else {
            self.frames.recycle(image.rgba);
        }
    }

    /// Whether the summary keeps the images (the writer then gets a copy).
    pub fn keeps_frames(&self) -> bool {
        self.opts.keep_frames
    }

    /// The summary of the run; `stopped` says why it stopped, if it did.
    pub fn finish(mut self, stopped: Option<String>) -> DisplaySummary {
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
            self.summary.complete = self.summary.frames.len() as u64 == self.total();
        }
        if !self.summary.complete {
            self.summary.stopped_early = stopped.or(Some("stopped".into()));
        }
        self.summary.finish(seconds);
        self.summary
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dray_protocol::{Blob, FrameStats, TilePixels, TileRect, TileStats};

    const W: u32 = 4;
    const H: u32 = 2;

    fn camera(i: usize) -> Camera {
        Camera {
            eye: [i as f32, 0.0, -5.0],
            look: [i as f32, 0.0, 0.0],
            up: [0.0, 1.0, 0.0],
            fov_y_deg: 45.0,
        }
    }

    fn opts(cameras: usize, frames_ahead: usize) -> DisplayOptions {
        DisplayOptions {
            assigner: crate::names::assigner(),
            scheduler: crate::names::scheduler(),
            width: W,
            height: H,
            cameras: (0..cameras).map(camera).collect(),
            interactive: false,
            frames_ahead,
            output: None,
            save_frames: false,
            keep_frames: false,
            web: None,
            samples: 1,
        }
    }

    fn display(opts: DisplayOptions) -> Display {
        Display::new(opts, Box::new(|| 7))
    }

    fn tile(frame: u64, x: u32, w: u32) -> TileDone {
        TileDone {
            frame,
            tile: TileRect { x, y: 0, w, h: H },
            pixels: TilePixels::Rgba(Blob(vec![frame as u8; (w * H * 4) as usize])),
            depth: None,
            prim_ids: None,
            stats: TileStats::default(),
            hits: Default::default(),
        }
    }

    fn done(frame: u64, rays: u64) -> FrameDone {
        FrameDone {
            frame,
            stats: FrameStats {
                rays,
                ..FrameStats::default()
            },
        }
    }

    /// Every pixel of `frame` and its report arrive, then the display
    /// moves on.
    fn complete(d: &mut Display, frame: u64, out: &mut Vec<Out>) {
        let now = Instant::now();
        d.tile_done(&crate::names::client(0), tile(frame, 0, W), now, out);
        d.frame_done(&crate::names::scheduler(), done(frame, 100 + frame), now);
        d.advance(out);
    }

    /// The frames of the cameras pushed, each reported sent at once (and
    /// the next one it makes due).
    fn send_all(d: &mut Display, out: &mut Vec<Out>) -> Vec<u64> {
        let mut sent = Vec::new();
        while let Some(i) = out.iter().position(|o| matches!(o, Out::Camera(_))) {
            let Out::Camera(u) = out.remove(i) else {
                unreachable!()
            };
            sent.push(u.seq);
            d.camera_sent(Instant::now(), out);
        }
        sent
    }

    /// The image of the first frame shown, taken out of `out`.
    fn take_shown_image(out: &mut Vec<Out>) -> FrameImage {
        match out
            .iter()
            .position(|o| matches!(o, Out::Show { .. }))
            .map(|i| out.remove(i))
        {
            Some(Out::Show { image, .. }) => image,
            _ => panic!("no frame shown: {out:?}"),
        }
    }

    fn shown(out: &mut Vec<Out>) -> Vec<u64> {
        let mut frames = Vec::new();
        out.retain(|o| match o {
            Out::Show { image, metrics } => {
                assert_eq!(image.frame, metrics.frame);
                frames.push(image.frame);
                false
            }
            Out::Report(_) => false,
            _ => true,
        });
        frames
    }

    #[test]
    fn cameras_go_out_one_at_a_time_and_frames_ahead_ahead() {
        let mut d = display(opts(5, 2));
        let mut out = Vec::new();
        d.advance(&mut out);
        assert!(
            matches!(&out[..], [Out::Camera(CameraUpdate { seq: 0, camera: c, sample: 0, format: None })] if *c == camera(0)),
            "{out:?}"
        );
        d.advance(&mut out);
        assert_eq!(out.len(), 1, "the next waits until the first has left");
        assert_eq!(send_all(&mut d, &mut out), [0, 1]);
        assert!(out.is_empty(), "two frames outstanding: {out:?}");
        complete(&mut d, 0, &mut out);
        assert_eq!(shown(&mut out), [0]);
        assert_eq!(send_all(&mut d, &mut out), [2]);
        assert!(out.is_empty(), "{out:?}");
    }

    #[test]
    fn frames_are_shown_in_order_and_their_metrics_pushed() {
        let mut d = display(opts(3, 3));
        let mut out = Vec::new();
        d.advance(&mut out);
        assert_eq!(send_all(&mut d, &mut out), [0, 1, 2]);
        complete(&mut d, 1, &mut out);
        assert_eq!(shown(&mut out), [] as [u64; 0], "frame 1 waits for frame 0");
        assert!(d.summary.frames.is_empty());
        complete(&mut d, 0, &mut out);
        assert_eq!(shown(&mut out), [0, 1]);
        let m: Vec<(u64, u64, u64)> = d
            .summary
            .frames
            .iter()
            .map(|m| (m.frame, m.rays, m.link_display))
            .collect();
        assert_eq!(m, [(0, 100, 7), (1, 101, 7)], "the display's link charged");
        assert_eq!(d.summary.total_rays, 201);
    }

    #[test]
    fn tiles_report_once_and_bad_or_late_tiles_are_counted() {
        let mut d = display(opts(2, 1));
        let mut out = Vec::new();
        d.advance(&mut out);
        send_all(&mut d, &mut out);
        let now = Instant::now();
        let client = crate::names::client(1);
        d.tile_done(&client, tile(0, 0, 2), now, &mut out);
        assert!(
            matches!(&out[..], [Out::Report(r)] if r.frame == 0 && r.client == client.node),
            "{out:?}"
        );
        out.clear();
        d.tile_done(&client, tile(0, 0, 2), now, &mut out);
        d.tile_done(&client, tile(1, 0, 2), now, &mut out);
        d.tile_done(&client, tile(0, 3, 2), now, &mut out);
        assert!(out.is_empty(), "nothing reported: {out:?}");
        assert_eq!(d.summary.duplicate_tiles, 1);
        assert_eq!(
            d.summary.tiles_ignored, 2,
            "frame 1 not outstanding, outside"
        );
        d.frame_done(&crate::names::scheduler(), done(5, 0), now);
        d.advance(&mut out);
        assert!(out.is_empty(), "a report for frame 5 changes nothing");
    }

    #[test]
    fn a_voxel_rendered_empty_counts_once_and_one_that_cannot_be_ends_the_run() {
        let mut d = display(opts(2, 1));
        let mut out = Vec::new();
        let lost = |skipped| VoxelLost {
            id: 3,
            store: crate::names::store_node(1),
            reason: "checksum".into(),
            skipped,
        };
        let client = crate::names::client(0);
        d.voxel_lost(&client, lost(true), &mut out);
        d.voxel_lost(&crate::names::client(1), lost(true), &mut out);
        assert!(out.is_empty(), "{out:?}");
        assert_eq!(d.summary.voxels_missing.len(), 1);
        d.voxel_lost(&client, lost(false), &mut out);
        assert!(
            matches!(&out[..], [Out::End(End::Failed(m))] if m.starts_with("voxel 3 cannot be served intact by store-1: checksum")),
            "{out:?}"
        );
        out.clear();
        d.advance(&mut out);
        d.shutdown("late", &mut out);
        assert!(out.is_empty(), "nothing after the end: {out:?}");
    }

    #[test]
    fn the_run_ends_once_every_cameras_frame_is_shown() {
        let mut d = display(opts(2, 2));
        let mut out = Vec::new();
        d.advance(&mut out);
        send_all(&mut d, &mut out);
        complete(&mut d, 0, &mut out);
        assert_eq!(shown(&mut out), [0]);
        assert!(out.is_empty(), "{out:?}");
        complete(&mut d, 1, &mut out);
        assert_eq!(shown(&mut out), [1]);
        assert!(matches!(&out[..], [Out::End(End::Complete)]), "{out:?}");
        let s = d.finish(None);
        assert!(s.complete && s.stopped_early.is_none());
        assert_eq!(s.frames.len(), 2);
    }

    #[test]
    fn each_camera_goes_out_once_per_sample_and_shows_their_mean() {
        let mut d = display(DisplayOptions {
            samples: 2,
            ..opts(2, 2)
        });
        let mut out = Vec::new();
        let mut updates = Vec::new();
        let mut shown_images = Vec::new();
        let mut rows = 0;
        d.advance(&mut out);
        for frame in 0..4 {
            while let Some(i) = out.iter().position(|o| matches!(o, Out::Camera(_))) {
                let Out::Camera(u) = out.remove(i) else {
                    unreachable!()
                };
                updates.push((u.seq, u.camera, u.sample));
                d.camera_sent(Instant::now(), &mut out);
            }
            complete(&mut d, frame, &mut out);
            for o in std::mem::take(&mut out) {
                match o {
                    Out::Show { image, metrics } => {
                        assert_eq!(metrics.frame, frame, "the last sample's row");
                        shown_images.push(image);
                        rows += 1;
                    }
                    Out::Metrics(m) => {
                        assert_eq!(m.frame, frame);
                        rows += 1;
                    }
                    Out::End(End::Complete) => assert_eq!(frame, 3, "ends after the last"),
                    Out::Camera(_) => out.push(o),
                    Out::Report(_) => {}
                    other => panic!("{other:?}"),
                }
            }
        }
        assert_eq!(
            updates,
            [
                (0, camera(0), 0),
                (1, camera(0), 1),
                (2, camera(1), 0),
                (3, camera(1), 1)
            ]
        );
        assert_eq!(rows, 4, "a metrics row per frame");
        // Frame k's pixels are all k: the cameras' means, rounded half up.
        let images: Vec<(u64, [u8; 4])> =
            shown_images.iter().map(|i| (i.frame, i.rgba[0])).collect();
        assert_eq!(images, [(0, [1, 1, 1, 255]), (1, [3, 3, 3, 255])]);
        let s = d.finish(None);
        assert!(s.complete, "{:?}", s.stopped_early);
        assert_eq!((s.frames.len(), s.frames_requested), (4, 4));
    }

    #[test]
    fn a_shutdown_stops_the_run_short() {
        let mut d = display(opts(3, 1));
        let mut out = Vec::new();
        d.advance(&mut out);
        send_all(&mut d, &mut out);
        d.shutdown("operator", &mut out);
        assert!(
            matches!(&out[..], [Out::End(End::Stopped(why))] if why == "shutdown: operator"),
            "{out:?}"
        );
        let s = d.finish(Some("shutdown: operator".into()));
        assert!(!s.complete);
        assert_eq!(s.stopped_early.as_deref(), Some("shutdown: operator"));
    }

    #[test]
    fn a_move_in_interactive_mode_becomes_the_next_camera() {
        let mut o = opts(1, 1);
        o.interactive = true;
        o.web = Some(([127, 0, 0, 1], 0).into());
        let mut d = display(o);
        let mut out = Vec::new();
        d.advance(&mut out);
        let mut frames = Vec::new();
        loop {
            let cams: Vec<Camera> = out
                .iter()
                .filter_map(|o| match o {
                    Out::Camera(u) => Some(u.camera),
                    _ => None,
                })
                .collect();
            assert!(cams.iter().all(|c| *c == camera(0)), "{cams:?}");
            let sent = send_all(&mut d, &mut out);
            if sent.is_empty() {
                break;
            }
            frames.extend(sent.iter().copied());
            for f in sent {
                complete(&mut d, f, &mut out);
            }
            shown(&mut out);
        }
        assert_eq!(frames.len() as u64, IDLE_FRAMES, "then it waits for a move");
        d.moved(&[Move::Forward, Move::Forward], &mut out);
        let step = moves::step_for(&camera(0));
        let want = Move::Forward.apply(&Move::Forward.apply(&camera(0), step), step);
        assert!(
            matches!(&out[..], [Out::Camera(u)] if u.seq == IDLE_FRAMES && u.camera == want),
            "{out:?}"
        );
        let s = d.finish(Some("interrupted".into()));
        assert!(s.complete, "stopping is how an interactive run ends");
        assert_eq!(s.frames_requested, IDLE_FRAMES as usize);
    }

    #[test]
    fn a_camera_not_sent_is_tried_again_at_the_deadline() {
        let mut d = display(opts(2, 2));
        let mut out = Vec::new();
        d.advance(&mut out);
        out.clear();
        let now = Instant::now();
        d.camera_failed(now);
        assert_eq!(d.deadline(), Some(now + SEND_RETRY));
        d.tick(now + SEND_RETRY, &mut out);
        assert!(
            matches!(&out[..], [Out::Camera(CameraUpdate { seq: 0, .. })]),
            "{out:?}"
        );
        d.camera_sent(now + SEND_RETRY, &mut out);
        assert_eq!(d.deadline(), None);
    }

    #[test]
    fn a_frame_missing_pixels_is_shown_after_the_grace_time() {
        let mut d = display(opts(2, 2));
        let mut out = Vec::new();
        d.advance(&mut out);
        send_all(&mut d, &mut out);
        let now = Instant::now();
        d.tile_done(&crate::names::client(0), tile(0, 0, 1), now, &mut out);
        d.frame_done(&crate::names::scheduler(), done(0, 1), now);
        d.advance(&mut out);
        assert_eq!(shown(&mut out), [] as [u64; 0]);
        assert_eq!(d.deadline(), Some(now + MISSING_PIXELS_GRACE));
        d.tick(now + MISSING_PIXELS_GRACE / 2, &mut out);
        assert!(out.is_empty(), "{out:?}");
        d.tick(now + MISSING_PIXELS_GRACE, &mut out);
        assert_eq!(shown(&mut out), [0]);
        assert_eq!(d.summary.missing_pixels, u64::from((W - 1) * H));
    }

    #[test]
    fn a_shown_image_is_kept_or_its_pixels_reused() {
        let mut o = opts(2, 1);
        o.keep_frames = true;
        let mut d = display(o);
        let mut out = Vec::new();
        d.advance(&mut out);
        send_all(&mut d, &mut out);
        complete(&mut d, 0, &mut out);
        let image = take_shown_image(&mut out);
        let pixels = image.rgba.as_ptr();
        d.shown(image);
        assert_eq!(d.summary.images.len(), 1);
        assert_eq!(
            d.summary.images[0].rgba.as_ptr(),
            pixels,
            "the image itself, not a copy"
        );

        let mut d = display(opts(2, 1));
        d.advance(&mut out);
        out.clear();
        d.camera_sent(Instant::now(), &mut out);
        complete(&mut d, 0, &mut out);
        let image = take_shown_image(&mut out);
        let pixels = image.rgba.as_ptr();
        d.shown(image);
        assert!(d.summary.images.is_empty());
        send_all(&mut d, &mut out);
        assert_eq!(
            d.frames.pending_rgba(1).map(<[_]>::as_ptr),
            Some(pixels),
            "frame 1 is assembled in frame 0's pixels"
        );
    }
}
