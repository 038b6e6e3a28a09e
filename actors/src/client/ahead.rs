//! How many tiles a client asks for ahead of those its threads render.
//!
//! A render thread that finishes its last tile before the next assignment
//! arrives sits idle for what is left of the round trip to the scheduler.
//! How many tiles cover that round trip depends on how fast tiles trace: a
//! 32 × 32 tile of primary rays takes about a tenth of a millisecond, the
//! same tile with shadows and a reflection several times that, and a tile
//! waiting for voxels far longer. So the client starts at the configured
//! `tiles_ahead` and grows it by half whenever a thread sat idle before a
//! tile (up to `max_tiles_ahead`), and gives one back after a long calm
//! stretch (every thread busy through eight times as many tiles as it asks
//! ahead), so that it holds no more tiles than keep its threads busy: tiles
//! a client holds are tiles the scheduler cannot give to a faster one.

use std::time::Duration;

/// Idle time before a tile that counts as a thread having run dry (less is
/// the ordinary hand-over from one tile to the next).
pub(crate) const IDLE_MIN: Duration = Duration::from_micros(50);
/// Tiles finished without idling, per tile asked ahead, before one fewer
/// is asked for.
const CALM_PER_TILE: usize = 8;

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
    /// all) since its previous tile. Returns whether [`Self::current`]
    /// changed.
    pub fn tile_finished(&mut self, idle: Duration) -> bool {
        let before = self.current;
        if idle >= IDLE_MIN {
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

#[cfg(test)]
mod tests {
    use super::*;

    const IDLE: Duration = Duration::from_millis(1);

    #[test]
    fn idle_threads_grow_it_by_half_up_to_the_ceiling() {
        let mut a = Ahead::new(1, 32);
        let mut seen = vec![a.current()];
        while a.tile_finished(IDLE) {
            seen.push(a.current());
        }
        assert_eq!(seen, [1, 2, 3, 4, 6, 9, 13, 19, 28, 32]);
        assert!(!a.tile_finished(IDLE), "stays at the ceiling");
    }

    #[test]
    fn a_calm_stretch_gives_one_back_down_to_the_floor() {
        let mut a = Ahead::new(2, 8);
        for _ in 0..3 {
            a.tile_finished(IDLE);
        }
        assert_eq!(a.current(), 6);
        // Short hand-overs are not idleness.
        for _ in 0..CALM_PER_TILE * 6 - 1 {
            assert!(!a.tile_finished(IDLE_MIN / 2));
        }
        assert!(a.tile_finished(Duration::ZERO));
        assert_eq!(a.current(), 5);
        for _ in 0..1000 {
            a.tile_finished(Duration::ZERO);
        }
        assert_eq!(a.current(), 2, "never below the configured floor");
    }

    #[test]
    fn an_idle_tile_restarts_the_calm_count() {
        let mut a = Ahead::new(1, 2);
        a.tile_finished(IDLE);
        assert_eq!(a.current(), 2);
        for _ in 0..CALM_PER_TILE * 2 - 1 {
            a.tile_finished(Duration::ZERO);
        }
        a.tile_finished(IDLE);
        for _ in 0..CALM_PER_TILE * 2 - 1 {
            a.tile_finished(Duration::ZERO);
        }
        assert_eq!(a.current(), 2);
    }

    #[test]
    fn a_ceiling_at_the_floor_fixes_it() {
        let mut a = Ahead::new(4, 4);
        assert!(!a.tile_finished(IDLE));
        assert_eq!(a.current(), 4);
    }
}
