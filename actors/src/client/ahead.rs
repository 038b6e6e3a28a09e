//! How many tiles a client asks for ahead of those its threads render.
//!
//! A render thread that finishes its last tile before the next assignment
//! arrives sits idle for what is left of the round trip to the scheduler.
//! How many tiles cover that round trip depends on how fast tiles trace: a
//! 32 × 32 tile of primary rays takes about a tenth of a millisecond, the
//! same tile with shadows and a reflection several times that, and a tile
//! waiting for voxels far longer. So a client starts at `tiles_ahead` and
//! grows it by half whenever a thread sat idle before a tile for up to
//! about a round trip (up to `max_tiles_ahead`, 32 unless configured), and
//! gives one back after a long calm stretch (every thread busy through
//! eight times as many tiles as it asks ahead), so that it holds no more
//! tiles than keep its threads busy: tiles a client holds are tiles the
//! scheduler cannot give to another client.
//!
//! A longer wait is not the round trip but the scheduler having no tile
//! to give (the display is waiting for a frame that another client's
//! tiles hold up, say), which more tiles ahead would not shorten: growing
//! then only makes each client take tiles from the other's part of the
//! image, and fetch their voxels (`experiments/latency-hiding.toml`). The
//! round trip is the quickest answer to a request lately ([`RoundTrips`]).
//!
//! Holding more tiles must not cost affinity: the scheduler lets a client
//! take others' tiles only once it holds at most one of its own
//! (`experiments/affinity-inside.toml`).

use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// Idle time before a tile that counts as a thread having run dry (less is
/// the ordinary hand-over from one tile to the next).
pub(crate) const IDLE_MIN: Duration = Duration::from_micros(50);
/// Tiles finished without idling, per tile asked ahead, before one fewer
/// is asked for.
const CALM_PER_TILE: usize = 8;
/// Idleness up to the round trip times this (plus [`SLACK`]) is taken
/// for waiting on the round trip.
const ROUND_TRIPS: u32 = 2;
const SLACK: Duration = Duration::from_micros(500);

/// The number of tiles asked for ahead, between a floor and a ceiling.
#[derive(Clone, Debug)]
pub(crate) struct Ahead {
    floor: usize,
    ceiling: usize,
    current: usize,
    /// Tiles finished without idling since the last change.
    calm: usize,
}

impl Ahead {
    /// Starts at `floor`; never goes past `ceiling` (at least `floor`).
    pub fn new(floor: usize, ceiling: usize) -> Ahead {
        Ahead {
            floor,
            ceiling: ceiling.max(floor),
            current: floor,
            calm: 0,
        }
    }

    pub fn current(&self) -> usize {
        self.current
    }

    /// A tile finished; its thread was idle for `idle` (with no tile at
    /// all) since its previous tile, and the scheduler answers requests
    /// in `round_trip` (none measured yet: any idleness counts). Returns
    /// whether [`Self::current`] changed.
    pub fn tile_finished(&mut self, idle: Duration, round_trip: Option<Duration>) -> bool {
        let before = self.current;
        let waited_for_work = round_trip.is_some_and(|rt| idle > rt * ROUND_TRIPS + SLACK);
        if idle >= IDLE_MIN && !waited_for_work {
            self.calm = 0;
            self.current = (self.current + self.current / 2)
                .max(self.current + 1)
                .min(self.ceiling);
        } else {
            self.calm += 1;
            if self.calm >= CALM_PER_TILE * self.current.max(1) && self.current > self.floor {
                self.current -= 1;
                self.calm = 0;
            }
        }
        self.current != before
    }
}

/// How quickly the scheduler answers a request for tiles: the time from
/// a request to the first tile assigned after it, the least of the last
/// [`RoundTrips::WINDOW`] (answers delayed because the scheduler had no
/// tile are longer, and drop out).
#[derive(Debug, Default)]
pub(crate) struct RoundTrips {
    /// Requests not yet filled: when sent, slots still unfilled, and
    /// whether its first tile has come (and timed it).
    pending: VecDeque<(Instant, usize, bool)>,
    recent: VecDeque<Duration>,
}

impl RoundTrips {
    const WINDOW: usize = 16;

    /// The scheduler was asked for `slots` tiles at `at`.
    pub fn asked(&mut self, at: Instant, slots: usize) {
        if slots > 0 {
            self.pending.push_back((at, slots, false));
        }
    }

    /// A tile was assigned at `at`: it fills the oldest request's slot,
    /// and the first one filled times that request.
    pub fn assigned(&mut self, at: Instant) {
        let Some((sent, left, timed)) = self.pending.front_mut() else {
            return;
        };
        if !*timed {
            *timed = true;
            if self.recent.len() == Self::WINDOW {
                self.recent.pop_front();
            }
            self.recent.push_back(at.saturating_duration_since(*sent));
        }
        *left -= 1;
        if *left == 0 {
            self.pending.pop_front();
        }
    }

    /// Every unanswered request is void (a new scheduler).
    pub fn forget_requests(&mut self) {
        self.pending.clear();
    }

    /// The quickest recent answer, if any.
    pub fn round_trip(&self) -> Option<Duration> {
        self.recent.iter().min().copied()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const IDLE: Duration = Duration::from_millis(1);

    #[test]
    fn idle_threads_grow_it_by_half_up_to_the_ceiling() {
        let mut a = Ahead::new(1, 32);
        let mut seen = vec![a.current()];
        while a.tile_finished(IDLE, None) {
            seen.push(a.current());
        }
        assert_eq!(seen, [1, 2, 3, 4, 6, 9, 13, 19, 28, 32]);
        assert!(!a.tile_finished(IDLE, None), "stays at the ceiling");
    }

    #[test]
    fn a_calm_stretch_gives_one_back_down_to_the_floor() {
        let mut a = Ahead::new(2, 8);
        for _ in 0..3 {
            a.tile_finished(IDLE, None);
        }
        assert_eq!(a.current(), 6);
        // Short hand-overs are not idleness.
        for _ in 0..CALM_PER_TILE * 6 - 1 {
            assert!(!a.tile_finished(IDLE_MIN / 2, None));
        }
        assert!(a.tile_finished(Duration::ZERO, None));
        assert_eq!(a.current(), 5);
        for _ in 0..1000 {
            a.tile_finished(Duration::ZERO, None);
        }
        assert_eq!(a.current(), 2, "never below the configured floor");
    }

    #[test]
    fn an_idle_tile_restarts_the_calm_count() {
        let mut a = Ahead::new(1, 2);
        a.tile_finished(IDLE, None);
        assert_eq!(a.current(), 2);
        for _ in 0..CALM_PER_TILE * 2 - 1 {
            a.tile_finished(Duration::ZERO, None);
        }
        a.tile_finished(IDLE, None);
        for _ in 0..CALM_PER_TILE * 2 - 1 {
            a.tile_finished(Duration::ZERO, None);
        }
        assert_eq!(a.current(), 2);
    }

    #[test]
    fn a_ceiling_at_the_floor_fixes_it() {
        let mut a = Ahead::new(4, 4);
        assert!(!a.tile_finished(IDLE, None));
        assert_eq!(a.current(), 4);
    }

    #[test]
    fn waiting_longer_than_a_round_trip_is_no_reason_to_grow() {
        let mut a = Ahead::new(1, 32);
        let rt = Some(Duration::from_micros(300));
        // Waiting about a round trip: the scheduler's answer was the wait.
        assert!(a.tile_finished(Duration::from_micros(900), rt));
        assert_eq!(a.current(), 2);
        // Waiting far longer: the scheduler had no tile to give.
        assert!(!a.tile_finished(Duration::from_millis(30), rt));
        assert_eq!(a.current(), 2);
    }

    #[test]
    fn the_round_trip_is_the_quickest_recent_answer() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let mut r = RoundTrips::default();
        assert_eq!(r.round_trip(), None);
        r.asked(t0, 2);
        r.asked(t0 + ms(1), 1);
        // The first request's first tile times it; its second does not.
        r.assigned(t0 + ms(3));
        r.assigned(t0 + ms(4));
        assert_eq!(r.round_trip(), Some(ms(3)));
        // The second request is answered in 1 ms.
        r.assigned(t0 + ms(2));
        assert_eq!(r.round_trip(), Some(ms(1)));
        // Slow answers (no tile to give) do not hide the quick ones...
        r.asked(t0 + ms(10), 1);
        r.assigned(t0 + ms(60));
        assert_eq!(r.round_trip(), Some(ms(1)));
        // ...until they are all that is left of the window.
        for i in 0..RoundTrips::WINDOW as u64 {
            r.asked(t0 + ms(100 * i), 1);
            r.assigned(t0 + ms(100 * i + 20));
        }
        assert_eq!(r.round_trip(), Some(ms(20)));
        // A tile nobody asked for (after a scheduler restart) is ignored.
        r.forget_requests();
        r.assigned(t0 + ms(5000));
        assert_eq!(r.round_trip(), Some(ms(20)));
    }
}
