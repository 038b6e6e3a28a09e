//! The FrameAssigner actor: double buffering. It queues the display's camera
//! updates and releases them to the scheduler one at a time, the next one as
//! soon as the scheduler says the previous one is assigned (every tile handed
//! out, or, with affinity, a client has run out of its own tiles), so that
//! the clients render frame k+1's first tiles while frame k's last ones
//! finish.
//!
//! A camera update's `format` changes the size and shading of its frame and
//! of every later one; its `sample` goes with its frame.
//!
//! Shape: [`Assigner`] owns the queue and what is being assigned; its
//! handlers (a camera update, a frame assigned, a release that failed, the
//! retry timer) change it and push effects ([`Out`]: forward a camera to
//! the prefetcher, release a frame); [`run_assigner`] receives, calls the
//! handler and carries the effects out.

use crate::ActorError;
use dray_protocol::{Address, CameraUpdate, FrameFormat, FrameStart, Message, RenderSettings};
use dray_runtime::{Delivery, Mailbox};
use std::collections::VecDeque;
use std::time::Duration;
use tracing::{debug, info, warn};

/// Where the frame assigner sends frames, and their size and shading.
#[derive(Clone, Debug)]
pub struct AssignerOptions {
    /// The scheduler ([`FrameStart`] goes there).
    pub scheduler: Address,
    /// The prefetcher, which gets a copy of every camera update.
    pub prefetcher: Option<Address>,
    /// Image width, pixels, until a camera update's format changes it.
    pub width: u32,
    /// Image height, pixels, until a camera update's format changes it.
    pub height: u32,
    /// Shading of the frames, until a camera update's format changes it.
    pub settings: RenderSettings,
}

/// Most camera updates waiting; beyond, the oldest is dropped (a user
/// moving fast only needs the recent views).
pub const MAX_QUEUED_FRAMES: usize = 64;
/// How soon a [`FrameStart`] the scheduler could not take is sent again.
const RETRY: Duration = Duration::from_millis(100);

/// What the assigner's handlers ask the run loop to do, in order.
#[derive(Debug, PartialEq)]
enum Out {
    /// Send the prefetcher a copy of a camera update.
    Forward(Address, CameraUpdate),
    /// Release a frame to the scheduler; if that fails the loop calls
    /// [`Assigner::release_failed`].
    Release(FrameStart),
}

/// The frame assigner's state.
struct Assigner {
    opts: AssignerOptions,
    /// The size and shading of the frames from the newest update on.
    format: FrameFormat,
    /// Frames not released yet, oldest first, each with the format that
    /// held when its update came.
    queue: VecDeque<FrameStart>,
    /// The highest `seq` seen.
    newest: Option<u64>,
    /// The frame released and not yet fully assigned.
    assigning: Option<u64>,
    /// Updates dropped because the queue was full.
    dropped: u64,
    /// A release failed: nothing goes out until the retry timer fires.
    retrying: bool,
}

impl Assigner {
    fn new(opts: AssignerOptions) -> Assigner {
        Assigner {
            format: FrameFormat {
                width: opts.width,
                height: opts.height,
                settings: opts.settings.clone(),
            },
            opts,
            queue: VecDeque::new(),
            newest: None,
            assigning: None,
            dropped: 0,
            retrying: false,
        }
    }

    /// The display moved the camera: queue its frame (dropping the oldest
    /// beyond [`MAX_QUEUED_FRAMES`]), with the update's format from now on,
    /// and forward it to the prefetcher; an update not newer than every
    /// one seen is ignored.
    fn camera_update(&mut self, u: CameraUpdate, out: &mut Vec<Out>) {
        if self.newest.is_some_and(|n| u.seq <= n) {
            debug!(seq = u.seq, "old camera update ignored");
            return;
        }
        self.newest = Some(u.seq);
        if let Some(p) = &self.opts.prefetcher {
            out.push(Out::Forward(p.clone(), u.clone()));
        }
        if let Some(f) = u.format {
            info!(
                frame = u.seq,
                width = f.width,
                height = f.height,
                "frame format changed"
            );
            self.format = f;
        }
        self.queue.push_back(FrameStart {
            frame: u.seq,
            camera: u.camera,
            width: self.format.width,
            height: self.format.height,
            settings: self.format.settings.clone(),
            sample: u.sample,
        });
        while self.queue.len() > MAX_QUEUED_FRAMES {
            if let Some(old) = self.queue.pop_front() {
                self.dropped += 1;
                warn!(
                    frame = old.frame,
                    dropped = self.dropped,
                    "camera updates arrive faster than frames: frame dropped"
                );
            }
        }
        self.release(out);
    }

    /// The scheduler has handed out every tile of `frame`: the next one may go.
    fn frame_assigned(&mut self, frame: u64, out: &mut Vec<Out>) {
        if self.assigning == Some(frame) {
            self.assigning = None;
        } else {
            debug!(frame, assigning = ?self.assigning, "unexpected frame assigned");
        }
        self.release(out);
    }

    /// The scheduler could not be sent `start`: it goes back to the head
    /// of the queue and is sent again after [`RETRY`].
    fn release_failed(&mut self, start: FrameStart) {
        if self.assigning == Some(start.frame) {
            self.assigning = None;
        }
        self.retrying = true;
        self.queue.push_front(start);
    }

    /// The retry delay is over.
    fn retry_due(&mut self, out: &mut Vec<Out>) {
        self.retrying = false;
        self.release(out);
    }

    /// Releases the oldest queued frame if none is being assigned.
    fn release(&mut self, out: &mut Vec<Out>) {
        if self.assigning.is_some() || self.retrying {
            return;
        }
        if let Some(start) = self.queue.pop_front() {
            self.assigning = Some(start.frame);
            out.push(Out::Release(start));
        }
    }
}

/// Runs the frame assigner until [`Message::Shutdown`] (or the mailbox
/// closes). Frame numbers are the updates' `seq`; an update whose `seq` is
/// not above every one seen before is ignored.
pub async fn run_assigner(mut mb: Mailbox, opts: AssignerOptions) -> Result<(), ActorError> {
    let mut a = Assigner::new(opts);
    let mut out = Vec::new();
    let mut retry_at: Option<tokio::time::Instant> = None;
    loop {
        tokio::select! {
            biased;
            d = mb.recv() => match d {
                None => return Ok(()),
                Some(Delivery::Message { from, msg }) => match msg {
                    Message::CameraUpdate(u) => a.camera_update(u, &mut out),
                    Message::FrameAssigned(f) => a.frame_assigned(f.frame, &mut out),
                    Message::Shutdown(r) => {
                        info!(reason = %r.reason, "frame assigner stops");
                        return Ok(());
                    }
                    other => debug!(kind = other.kind().name(), %from, "frame assigner ignores"),
                },
                Some(_) => {}
            },
            _ = crate::sleep_until_opt(retry_at) => {
                retry_at = None;
                a.retry_due(&mut out);
            }
        }
        for o in out.drain(..) {
            match o {
                Out::Forward(to, u) => {
                    if let Err(e) = mb.send(&to, Message::CameraUpdate(u)).await {
                        debug!(%to, "cannot forward the camera to the prefetcher: {e}");
                    }
                }
                Out::Release(start) => {
                    let frame = start.frame;
                    let to = &a.opts.scheduler;
                    match mb.send(to, Message::FrameStart(start.clone())).await {
                        Ok(()) => debug!(frame, "frame released"),
                        Err(e) => {
                            warn!(frame, %to, "cannot release the frame, retrying: {e}");
                            a.release_failed(start);
                            retry_at = Some(tokio::time::Instant::now() + RETRY);
                        }
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The protocol's example frame: a camera and shading.
    fn example() -> FrameStart {
        dray_protocol::examples::one_of_each(16)
            .into_iter()
            .find_map(|m| match m {
                Message::FrameStart(f) => Some(f),
                _ => None,
            })
            .expect("the examples hold a frame start")
    }

    fn assigner(prefetcher: bool) -> Assigner {
        Assigner::new(AssignerOptions {
            scheduler: crate::names::scheduler(),
            prefetcher: prefetcher.then(crate::names::prefetcher),
            width: 64,
            height: 48,
            settings: example().settings,
        })
    }

    fn update(seq: u64) -> CameraUpdate {
        CameraUpdate {
            seq,
            camera: example().camera,
            sample: 0,
            format: None,
        }
    }

    fn released(out: &mut Vec<Out>) -> Vec<u64> {
        out.drain(..)
            .filter_map(|o| match o {
                Out::Release(s) => Some(s.frame),
                Out::Forward(..) => None,
            })
            .collect()
    }

    #[test]
    fn one_frame_at_a_time_the_next_once_the_last_is_assigned() {
        let mut a = assigner(false);
        let mut out = Vec::new();
        a.camera_update(update(1), &mut out);
        a.camera_update(update(2), &mut out);
        a.camera_update(update(3), &mut out);
        assert_eq!(released(&mut out), [1]);
        a.frame_assigned(2, &mut out);
        assert_eq!(
            released(&mut out),
            [0u64; 0],
            "not the frame being assigned"
        );
        a.frame_assigned(1, &mut out);
        assert_eq!(released(&mut out), [2]);
        a.frame_assigned(2, &mut out);
        assert_eq!(released(&mut out), [3]);
        a.frame_assigned(3, &mut out);
        assert_eq!(released(&mut out), [0u64; 0], "nothing queued");
        a.camera_update(update(4), &mut out);
        assert_eq!(released(&mut out), [4], "released at once when idle");
    }

    #[test]
    fn a_frame_carries_the_size_and_shading() {
        let mut a = assigner(false);
        let mut out = Vec::new();
        a.camera_update(update(7), &mut out);
        let Some(Out::Release(s)) = out.pop() else {
            panic!("no release: {out:?}");
        };
        assert_eq!((s.frame, s.width, s.height), (7, 64, 48));
        assert_eq!(s.settings, example().settings);
        assert_eq!(s.camera, example().camera);
    }

    #[test]
    fn a_format_holds_from_its_update_on_and_a_sample_goes_with_its_frame() {
        let mut a = assigner(false);
        let mut out = Vec::new();
        a.camera_update(update(1), &mut out);
        let other = RenderSettings {
            shadows: !example().settings.shadows,
            reflection_depth: 3,
            ..example().settings
        };
        a.camera_update(
            CameraUpdate {
                sample: 4,
                format: Some(FrameFormat {
                    width: 320,
                    height: 200,
                    settings: other.clone(),
                }),
                ..update(2)
            },
            &mut out,
        );
        a.camera_update(
            CameraUpdate {
                sample: 5,
                ..update(3)
            },
            &mut out,
        );
        let mut starts = Vec::new();
        for f in 1..=3 {
            for o in out.drain(..) {
                if let Out::Release(s) = o {
                    starts.push(s);
                }
            }
            a.frame_assigned(f, &mut out);
        }
        let got: Vec<_> = starts
            .iter()
            .map(|s| (s.frame, s.sample, s.width, s.height, s.settings == other))
            .collect();
        assert_eq!(
            got,
            [
                (1, 0, 64, 48, false),
                (2, 4, 320, 200, true),
                (3, 5, 320, 200, true)
            ],
            "frame 1 was queued before the format changed"
        );
        // A frame sent again after a failed release keeps its own format.
        a.camera_update(update(4), &mut out);
        let Some(Out::Release(start)) = out.pop() else {
            panic!("no release");
        };
        a.release_failed(start.clone());
        a.retry_due(&mut out);
        assert!(
            matches!(&out[..], [Out::Release(s)] if *s == start),
            "{out:?}"
        );
    }

    #[test]
    fn old_updates_are_ignored_and_the_prefetcher_gets_the_rest_first() {
        let mut a = assigner(true);
        let mut out = Vec::new();
        a.camera_update(update(5), &mut out);
        assert!(
            matches!(&out[..], [Out::Forward(to, u), Out::Release(s)]
                if *to == crate::names::prefetcher() && u.seq == 5 && s.frame == 5),
            "{out:?}"
        );
        out.clear();
        a.camera_update(update(5), &mut out);
        a.camera_update(update(3), &mut out);
        assert!(out.is_empty(), "{out:?}");
    }

    #[test]
    fn beyond_the_queue_limit_the_oldest_updates_are_dropped() {
        let mut a = assigner(false);
        let mut out = Vec::new();
        let last = MAX_QUEUED_FRAMES as u64 + 11;
        for seq in 1..=last {
            a.camera_update(update(seq), &mut out);
        }
        assert_eq!(released(&mut out), [1]);
        assert_eq!(a.dropped, 10);
        a.frame_assigned(1, &mut out);
        assert_eq!(released(&mut out), [12], "2..=11 were dropped");
    }

    #[test]
    fn a_failed_release_goes_again_after_the_retry() {
        let mut a = assigner(false);
        let mut out = Vec::new();
        a.camera_update(update(1), &mut out);
        let Some(Out::Release(start)) = out.pop() else {
            panic!("no release");
        };
        a.release_failed(start);
        a.camera_update(update(2), &mut out);
        assert_eq!(released(&mut out), [0u64; 0], "nothing before the retry");
        a.retry_due(&mut out);
        assert_eq!(released(&mut out), [1], "the failed frame first");
        a.frame_assigned(1, &mut out);
        assert_eq!(released(&mut out), [2]);
    }
}
