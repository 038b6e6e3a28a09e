//! Finished tiles leave in batches: a tile of 32 × 32 primary rays traces
//! in about a tenth of a millisecond, less than the messages around it cost
//! (its pixels to the display, the display's report to the scheduler, the
//! request for the next tile and the assignment back), which each wake a
//! process and cost a QUIC packet or more. A client that holds tiles ahead
//! therefore sends a finished tile's pixels, and asks for more tiles, only
//! once a batch of them is done: the pixels leave together, the display's
//! reports follow together, one request asks for the whole batch, and the
//! scheduler's assignments go out together (each hop flushes what is
//! queued at once), so the fixed cost of a wakeup and a packet is shared.
//!
//! A batch is half the tiles asked for ahead (one tile when one is asked
//! ahead: no batching), so the render threads keep the other half while
//! the next batch comes. Held tiles leave early when this client renders
//! no other tile of their frame (a frame never waits for a batch to fill),
//! and so when the client has nothing else to render.
//!
//! The render threads hand their finished tiles to the actor task in
//! groups by the same rule (their share of a batch, or a frame with no
//! other tile on that thread), so the actor task too wakes once a group
//! rather than once a tile (`worker.rs`).

use dray_protocol::Message;
use std::collections::HashMap;

/// Finished tiles not sent yet, and the tiles being rendered per frame.
#[derive(Debug)]
pub(crate) struct TileBatch {
    size: usize,
    /// Finished tiles' messages (pixels), with their frames.
    held: Vec<(u64, Option<Message>)>,
    /// Tiles assigned, not finished, per frame.
    rendering: HashMap<u64, usize>,
}

impl TileBatch {
    /// Batches for a client that asks for `tiles_ahead` tiles beyond those
    /// its threads render.
    pub fn new(tiles_ahead: usize) -> TileBatch {
        TileBatch {
            size: tiles_ahead.div_ceil(2).max(1),
            held: Vec::new(),
            rendering: HashMap::new(),
        }
    }

    /// The client now asks for `tiles_ahead` tiles ahead
    /// ([`super::ahead`]): batches of half that from now on.
    pub fn set_ahead(&mut self, tiles_ahead: usize) {
        self.size = tiles_ahead.div_ceil(2).max(1);
    }

    /// Tiles a batch holds.
    pub fn size(&self) -> usize {
        self.size
    }

    /// A tile of `frame` was assigned.
    pub fn assigned(&mut self, frame: u64) {
        *self.rendering.entry(frame).or_default() += 1;
    }

    /// A tile of `frame` finished; `pixels` is its [`Message::TileDone`]
    /// (none for a tile that failed: its slot is freed all the same).
    pub fn finished(&mut self, frame: u64, pixels: Option<Message>) {
        if let Some(n) = self.rendering.get_mut(&frame) {
            *n -= 1;
            if *n == 0 {
                self.rendering.remove(&frame);
            }
        }
        self.held.push((frame, pixels));
    }

    /// Whether the held tiles should leave now: a full batch, or a tile
    /// whose frame this client renders no more of.
    pub fn ready(&self) -> bool {
        self.held.len() >= self.size
            || self
                .held
                .iter()
                .any(|(f, _)| !self.rendering.contains_key(f))
    }

    /// Takes the held tiles: their messages in the order they finished,
    /// and how many slots they free.
    pub fn take(&mut self) -> (Vec<Message>, usize) {
        let freed = self.held.len();
        let msgs = self.held.drain(..).filter_map(|(_, m)| m).collect();
        (msgs, freed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dray_protocol::Ping;

    fn msg() -> Option<Message> {
        Some(Message::Ping(Ping { seq: 0 }))
    }

    #[test]
    fn one_tile_ahead_sends_every_tile_at_once() {
        let mut b = TileBatch::new(1);
        b.assigned(0);
        b.assigned(0);
        b.finished(0, msg());
        assert!(b.ready());
        assert_eq!(b.take().1, 1);
        assert!(!b.ready());
    }

    #[test]
    fn tiles_wait_for_a_full_batch_while_their_frame_goes_on() {
        let mut b = TileBatch::new(16);
        for _ in 0..17 {
            b.assigned(3);
        }
        for i in 0..8 {
            assert!(!b.ready(), "after {i} tiles");
            b.finished(3, if i == 2 { None } else { msg() });
        }
        assert!(b.ready());
        let (msgs, freed) = b.take();
        assert_eq!((msgs.len(), freed), (7, 8), "a failed tile frees its slot");
        assert!(!b.ready());
    }

    #[test]
    fn the_last_tile_of_a_frame_leaves_at_once() {
        let mut b = TileBatch::new(16);
        b.assigned(1);
        b.assigned(2);
        b.assigned(2);
        b.finished(2, msg());
        assert!(!b.ready(), "frame 2 has a tile left");
        b.finished(1, msg());
        assert!(b.ready(), "frame 1 has none");
        assert_eq!(b.take().1, 2);
        b.finished(2, msg());
        assert!(b.ready(), "nothing left to render");
    }
}
