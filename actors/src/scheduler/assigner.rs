//! The FrameAssigner actor: double buffering. It queues the display's camera
//! updates and releases them to the scheduler one at a time, the next one as
//! soon as the scheduler says the previous one is assigned (every tile handed
//! out, or, with affinity, a client has run out of its own tiles), so that
//! the clients render frame k+1's first tiles while frame k's last ones
//! finish.

use crate::ActorError;
use dray_protocol::{Address, CameraUpdate, FrameStart, Message, RenderSettings};
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
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Shading of every frame.
    pub settings: RenderSettings,
}

/// Most camera updates waiting; beyond, the oldest is dropped (a user
/// moving fast only needs the recent views).
pub const MAX_QUEUED_FRAMES: usize = 64;
/// How soon a [`FrameStart`] the scheduler could not take is sent again.
const RETRY: Duration = Duration::from_millis(100);

/// Runs the frame assigner until [`Message::Shutdown`] (or the mailbox
/// closes). Frame numbers are the updates' `seq`; an update whose `seq` is
/// not above every one seen before is ignored.
pub async fn run_assigner(mut mb: Mailbox, opts: AssignerOptions) -> Result<(), ActorError> {
    let mut queue: VecDeque<CameraUpdate> = VecDeque::new();
    let mut newest: Option<u64> = None;
    // The frame released and not yet fully assigned.
    let mut assigning: Option<u64> = None;
    let mut dropped = 0u64;
    let mut retry_at: Option<tokio::time::Instant> = None;
    loop {
        tokio::select! {
            d = mb.recv() => match d {
                None => return Ok(()),
                Some(Delivery::Message { from, msg }) => match msg {
                    Message::CameraUpdate(u) => {
                        if newest.is_some_and(|n| u.seq <= n) {
                            debug!(seq = u.seq, "old camera update ignored");
                            continue;
                        }
                        newest = Some(u.seq);
                        if let Some(p) = &opts.prefetcher {
                            if let Err(e) = mb.send(p, Message::CameraUpdate(u.clone())).await {
                                debug!(to = %p, "cannot forward the camera to the prefetcher: {e}");
                            }
                        }
                        queue.push_back(u);
                        while queue.len() > MAX_QUEUED_FRAMES {
                            if let Some(old) = queue.pop_front() {
                                dropped += 1;
                                warn!(frame = old.seq, dropped, "camera updates arrive faster than frames: frame dropped");
                            }
                        }
                    }
                    Message::FrameAssigned(a) => {
                        if assigning == Some(a.frame) {
                            assigning = None;
                        } else {
                            debug!(frame = a.frame, ?assigning, "unexpected frame assigned");
                        }
                    }
                    Message::Shutdown(r) => {
                        info!(reason = %r.reason, "frame assigner stops");
                        return Ok(());
                    }
                    other => debug!(kind = other.kind().name(), %from, "frame assigner ignores"),
                },
                Some(_) => {}
            },
            _ = crate::sleep_until_opt(retry_at) => retry_at = None,
        }
        if assigning.is_none() && retry_at.is_none() {
            if let Some(u) = queue.pop_front() {
                let start = FrameStart {
                    frame: u.seq,
                    camera: u.camera,
                    width: opts.width,
                    height: opts.height,
                    settings: opts.settings.clone(),
                };
                match mb.send(&opts.scheduler, Message::FrameStart(start)).await {
                    Ok(()) => {
                        debug!(frame = u.seq, "frame released");
                        assigning = Some(u.seq);
                    }
                    Err(e) => {
                        warn!(frame = u.seq, to = %opts.scheduler, "cannot release the frame, retrying: {e}");
                        queue.push_front(u);
                        retry_at = Some(tokio::time::Instant::now() + RETRY);
                    }
                }
            }
        }
    }
}
