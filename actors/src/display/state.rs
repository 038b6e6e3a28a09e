//! The display's state and handlers: which cameras go out and when, which
//! tiles and reports count, which frames are shown in what order and with
//! what metrics, and when the run ends. Nothing here touches the network,
//! the disk or the web viewer: the handlers push [`Out`] effects that the
//! run loop carries out.

use super::frames::{Frames, ReadyFrame};
use super::record::{Recorder, Recording};
use super::samples::{Added, Samples};
use super::view::{Choices, Picked, View, ViewInput};
use super::{
    DisplayOptions, DisplaySummary, FrameImage, FrameMetrics, MISSING_PIXELS_GRACE, SEND_RETRY,
};
use dray_protocol::{
    Address, Camera, CameraUpdate, FrameDone, FrameFormat, Ping, TileDone, TileReport, VoxelLost,
};
use dray_trace::image::Accumulator;
use std::collections::BTreeMap;
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
        shown: Shown,
    },
    /// A frame that added a sample to a camera whose image is not
    /// complete yet: only its metrics row.
    Metrics(FrameMetrics),
    /// Interactive: the view's choices changed (for the viewer's page).
    Choices(Choices),
    /// Interactive: a pick's answer.
    Picked(Picked),
    /// Interactive: a recording stopped, or why it could not be made.
    Recorded(Result<Recording, String>),
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

/// What a shown frame is, besides its pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Shown {
    /// Samples per pixel in the image.
    pub samples: u32,
    /// The interactive view it shows (0 on a camera path).
    pub view: u64,
    /// No frame of this view follows for now: the view is refined (or the
    /// path ends).
    pub still: bool,
    /// Interactive, playing a path: the frame's index in it and its
    /// length.
    pub path: Option<(u32, u32)>,
}

/// A frame asked for, until it is shown.
#[derive(Clone, Debug)]
struct Asked {
    camera: Camera,
    width: u32,
    height: u32,
    view: u64,
    sample: u32,
    pick: bool,
    path: Option<(u32, u32)>,
}

/// The samples of one view added up so far.
struct Accumulation {
    view: u64,
    size: (u32, u32),
    acc: Accumulator,
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
    /// Interactive: the user's view (camera, choices, samples).
    view: Option<View>,
    /// Interactive: the flight being recorded.
    recorder: Option<Recorder>,
    /// The update being sent and what it asks for; kept on a failed send,
    /// to be sent again as it was.
    unsent: Option<(CameraUpdate, Asked)>,
    /// The size frames have now.
    size: (u32, u32),
    /// Frames sent and not shown yet: what each asked for.
    asked: BTreeMap<u64, Asked>,
    /// Interactive: the samples of the view shown last.
    accumulation: Option<Accumulation>,
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
        let samples = Samples::new(
            if opts.interactive { 1 } else { opts.samples },
            opts.width,
            opts.height,
        );
        let view = match (opts.interactive, opts.cameras.first()) {
            (true, Some(&home)) => Some(View::new(
                home,
                FrameFormat {
                    width: opts.width,
                    height: opts.height,
                    settings: opts.settings.clone(),
                },
                opts.max_samples,
            )),
            _ => None,
        };
        let requested = if opts.interactive {
            0
        } else {
            opts.cameras.len() * samples.per_camera() as usize
        };
        Display {
            frames: Frames::new(),
            summary: DisplaySummary::new(opts.width, opts.height, requested),
            size: (opts.width, opts.height),
            opts,
            sent: 0,
            sending: false,
            ended: false,
            started: None,
            last_shown: None,
            retry_at: None,
            view,
            recorder: None,
            unsent: None,
            asked: BTreeMap::new(),
            accumulation: None,
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

    /// The interactive view, for the viewer's page.
    pub fn view(&self) -> Option<&View> {
        self.view.as_ref()
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

    /// Interactive: the viewer's inputs, oldest first, arrived at `now`
    /// and make the next frame; the page hears of changed choices and of
    /// a recording that stopped.
    pub fn input(&mut self, inputs: Vec<ViewInput>, now: Instant, out: &mut Vec<Out>) {
        let before = self.choices();
        let Some(view) = &mut self.view else {
            return;
        };
        let n = inputs.len();
        for i in inputs {
            let camera = view.camera();
            match (&i, self.recorder.take()) {
                (ViewInput::Record(true), None) => {
                    self.recorder = Some(Recorder::start(now, camera));
                }
                (ViewInput::Record(false), Some(r)) => {
                    out.push(Out::Recorded(r.stop(now, camera)));
                }
                (_, Some(mut r)) => {
                    r.held(now, camera);
                    if r.full() {
                        out.push(Out::Recorded(r.stop(now, camera)));
                    } else {
                        self.recorder = Some(r);
                    }
                }
                (_, None) => {}
            }
            view.apply(i);
        }
        debug!(inputs = n, camera = ?view.camera(), "view changed");
        let after = self.choices();
        if after != before {
            if let Some(c) = after {
                out.push(Out::Choices(c));
            }
        }
        self.end_or_send(out);
    }

    /// Interactive: what the page shows as the view's choices.
    pub fn choices(&self) -> Option<Choices> {
        let mut c = self.view.as_ref()?.choices();
        c.recording = self.recorder.is_some();
        Some(c)
    }

    /// Pushes the next camera if one is due, none is being sent, and
    /// fewer than `frames_ahead` frames are outstanding (an interactive
    /// view's refining samples: none, so that a move is never queued
    /// behind them); the loop reports back, and each camera sent makes
    /// room to check for the next.
    fn send_camera(&mut self, out: &mut Vec<Out>) {
        if self.ended || self.sending {
            return;
        }
        let outstanding = self.frames.outstanding();
        let next = match self.unsent.take() {
            Some(next) => Some(next),
            None => self.next_update(outstanding),
        };
        let Some((update, asked)) = next else {
            return;
        };
        self.sending = true;
        self.unsent = Some((update.clone(), asked));
        out.push(Out::Camera(update));
    }

    /// The next frame to ask for, if one is due and there is room for it.
    fn next_update(&mut self, outstanding: usize) -> Option<(CameraUpdate, Asked)> {
        let seq = self.sent;
        if let Some(view) = &mut self.view {
            let room = match view.due()? {
                0 => self.opts.frames_ahead.max(1),
                _ => 1,
            };
            if outstanding >= room {
                return None;
            }
            let next = view.next_frame()?;
            if let Some(f) = &next.format {
                self.size = (f.width, f.height);
            }
            let asked = Asked {
                camera: next.camera,
                width: self.size.0,
                height: self.size.1,
                view: next.view,
                sample: next.sample,
                pick: next.pick,
                path: next.path,
            };
            let update = CameraUpdate {
                seq,
                camera: next.camera,
                sample: next.sample,
                format: next.format,
            };
            return Some((update, asked));
        }
        if seq >= self.total() || outstanding >= self.ahead() {
            return None;
        }
        let (index, sample) = self.samples.of(seq);
        let camera = self.opts.cameras[index as usize];
        let asked = Asked {
            camera,
            width: self.size.0,
            height: self.size.1,
            view: 0,
            sample,
            pick: false,
            path: None,
        };
        let update = CameraUpdate {
            seq,
            camera,
            sample,
            format: None,
        };
        Some((update, asked))
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
        if let Some((_, asked)) = self.unsent.take() {
            self.frames.open(self.sent, asked.width, asked.height);
            self.asked.insert(self.sent, asked);
        }
        if self.started.is_none() {
            self.started = Some(now);
        }
        self.sent += 1;
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
            mut image,
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
        let asked = self.asked.remove(&image.frame);
        if let (Some(asked), true) = (asked, self.view.is_some()) {
            if let (true, Some(view)) = (asked.pick, &mut self.view) {
                let ids = image.primid.as_deref();
                let depth = image.depth.as_deref();
                let (w, h) = (image.width, image.height);
                if let Some(p) = view.picked(&asked.camera, w, h, ids, depth) {
                    out.push(Out::Picked(p));
                }
            }
            let samples = self.accumulate(&mut image, &asked);
            let max = self.view.as_ref().map_or(1, View::max_samples);
            let shown = Shown {
                samples,
                view: asked.view,
                still: samples >= max,
                path: asked.path,
            };
            out.push(Out::Show {
                image,
                metrics: m.clone(),
                shown,
            });
        } else {
            match self.samples.add(image) {
                Added::Camera(image) => {
                    let shown = Shown {
                        samples: self.samples.per_camera(),
                        view: 0,
                        still: image.frame + 1 >= self.opts.cameras.len() as u64,
                        path: None,
                    };
                    out.push(Out::Show {
                        image,
                        metrics: m.clone(),
                        shown,
                    });
                }
                Added::Pending(rgba) => {
                    self.frames.recycle(rgba);
                    out.push(Out::Metrics(m.clone()));
                }
            }
        }
        self.summary.push(m, self.opts.keep_metrics);
    }

    /// Adds an interactive frame to the samples of its view (the first
    /// sample starts them again) and puts their mean in its place; the
    /// samples it now shows.
    fn accumulate(&mut self, image: &mut FrameImage, asked: &Asked) -> u32 {
        if asked.sample == 0 {
            self.accumulation = Some(Accumulation {
                view: asked.view,
                size: (image.width, image.height),
                acc: Accumulator::new(image.width, image.height),
            });
        }
        let Some(a) = &mut self.accumulation else {
            return 1;
        };
        let same_view = a.view == asked.view && a.size == (image.width, image.height);
        if !same_view {
            // A sample of a view whose first was never shown: alone.
            return 1;
        }
        // A sample again (a pick's frame after the last) adds nothing.
        if a.acc.samples() == asked.sample && a.acc.add(&image.rgba).is_err() {
            return 1;
        }
        if a.acc.samples() > 1 {
            image.rgba = a.acc.image();
        }
        a.acc.samples()
    }

    /// A shown frame's image is back from the loop: kept for the summary
    /// (`keep_frames`) or its pixels reused for a later frame.
    pub fn shown(&mut self, image: FrameImage) {
        if self.opts.keep_frames && self.view.is_none() {
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
            self.summary.frames_requested = self.summary.frames_shown;
            self.summary.complete = true;
        } else {
            self.summary.complete = self.summary.frames_shown as u64 == self.total();
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

    fn settings() -> dray_protocol::RenderSettings {
        dray_protocol::RenderSettings {
            shade: true,
            shadows: false,
            reflection_depth: 0,
            light_dir: [0.3, 1.0, 0.2],
            reflective: dray_protocol::Reflective::All,
            reflectance: 0.5,
            voxel_colors: false,
            want_depth: false,
            want_prim_ids: false,
        }
    }

    fn opts(cameras: usize, frames_ahead: usize) -> DisplayOptions {
        DisplayOptions {
            assigner: crate::names::assigner(),
            scheduler: crate::names::scheduler(),
            width: W,
            height: H,
            settings: settings(),
            max_samples: 3,
            web_token: None,
            cameras: (0..cameras).map(camera).collect(),
            interactive: false,
            frames_ahead,
            output: None,
            save_frames: false,
            keep_frames: false,
            keep_metrics: true,
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
            Out::Show { image, metrics, .. } => {
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
                    Out::Show { image, metrics, .. } => {
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

    /// An interactive display with a viewer (one camera, two frames ahead).
    fn interactive_display() -> Display {
        let mut o = opts(1, 2);
        o.interactive = true;
        o.web = Some(([127, 0, 0, 1], 0).into());
        display(o)
    }

    /// A step of `d` straight ahead.
    fn forward(d: f32) -> ViewInput {
        ViewInput::Fly {
            forward: d,
            right: 0.0,
            up: 0.0,
            yaw_deg: 0.0,
            pitch_deg: 0.0,
        }
    }

    #[test]
    fn a_recording_follows_the_view_and_the_page_hears_of_it() {
        let mut d = interactive_display();
        let mut out = Vec::new();
        let t0 = Instant::now();
        d.input(vec![ViewInput::Record(true)], t0, &mut out);
        assert!(
            out.iter()
                .any(|o| matches!(o, Out::Choices(c) if c.recording)),
            "{out:?}"
        );
        out.clear();
        d.input(
            vec![forward(1.0)],
            t0 + Duration::from_millis(450),
            &mut out,
        );
        out.clear();
        d.input(
            vec![ViewInput::Record(false)],
            t0 + Duration::from_millis(700),
            &mut out,
        );
        let rec = out
            .iter()
            .find_map(|o| match o {
                Out::Recorded(r) => Some(r.clone().expect("a path")),
                _ => None,
            })
            .expect("the recording");
        let zs: Vec<f32> = rec.path.keyframes.iter().map(|k| k.eye[2]).collect();
        // Still until 450 ms (keyframes at 0, 200, 400), then one step
        // closer (600), and where it stopped.
        assert_eq!(zs, [-5.0, -5.0, -5.0, -4.0, -4.0], "{zs:?}");
        assert!(out
            .iter()
            .any(|o| matches!(o, Out::Choices(c) if !c.recording)));
        assert_eq!(d.choices().map(|c| c.recording), Some(false));
    }

    #[test]
    fn an_interactive_view_is_refined_then_rests_and_an_input_starts_again() {
        let mut d = interactive_display();
        let mut out = Vec::new();
        d.advance(&mut out);
        let mut samples = Vec::new();
        let mut images = Vec::new();
        loop {
            let cams: Vec<(u32, Camera)> = out
                .iter()
                .filter_map(|o| match o {
                    Out::Camera(u) => Some((u.sample, u.camera)),
                    _ => None,
                })
                .collect();
            assert!(cams.iter().all(|c| c.1 == camera(0)), "{cams:?}");
            let sent = send_all(&mut d, &mut out);
            if sent.is_empty() {
                break;
            }
            samples.extend(cams.iter().map(|c| c.0));
            for f in sent {
                complete(&mut d, f, &mut out);
                images.push(take_shown_image(&mut out).rgba[0][0]);
                shown(&mut out);
            }
        }
        assert_eq!(samples, [0, 1, 2], "refined to max_samples, then it rests");
        // Frame k's pixels are k (see `tile`): the page sees their mean.
        assert_eq!(images, [0, 1, 1], "0, (0+1)/2, (0+1+2)/3, rounded");
        d.input(vec![forward(1.0)], Instant::now(), &mut out);
        let want = [0.0, 0.0, -4.0];
        assert!(
            matches!(&out[..], [Out::Camera(u)] if u.seq == 3 && u.sample == 0 && u.camera.eye == want),
            "{out:?}"
        );
        let s = d.finish(Some("interrupted".into()));
        assert!(s.complete, "stopping is how an interactive run ends");
        assert_eq!(s.frames_requested, 3);
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
