//! Tracing work counted on this thread: what a cost model charges a
//! virtual clock for ([`crate::tile::render_tile_sample`] adds to it
//! whenever it stops, before each wait and at the end, so that the work
//! of one poll of a tile is the difference across that poll).

use crate::render::FrameStats;
use std::cell::Cell;

/// Counts of tracing work.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Work {
    /// Tiles started.
    pub tiles: u64,
    /// Primary rays traced.
    pub primary_rays: u64,
    /// Shadow and reflection rays traced.
    pub secondary_rays: u64,
    /// Voxels entered by packets (each packet's entries counted).
    pub voxel_visits: u64,
}

impl Work {
    /// The work done between `earlier` and `self`.
    pub fn since(self, earlier: Work) -> Work {
        Work {
            tiles: self.tiles.wrapping_sub(earlier.tiles),
            primary_rays: self.primary_rays.wrapping_sub(earlier.primary_rays),
            secondary_rays: self.secondary_rays.wrapping_sub(earlier.secondary_rays),
            voxel_visits: self.voxel_visits.wrapping_sub(earlier.voxel_visits),
        }
    }

    fn of(s: &FrameStats) -> Work {
        Work {
            tiles: 0,
            primary_rays: s.primary_rays,
            secondary_rays: s.shadow_rays + s.reflection_rays,
            voxel_visits: s.voxels_visited,
        }
    }
}

thread_local! {
    static DONE: Cell<Work> = const { Cell::new(Work { tiles: 0, primary_rays: 0, secondary_rays: 0, voxel_visits: 0 }) };
}

/// The work this thread has done so far.
pub fn done() -> Work {
    DONE.with(Cell::get)
}

/// Adds a tile's counts since `flushed` to this thread's, and remembers
/// them as flushed.
pub(crate) fn flush(stats: &FrameStats, flushed: &mut Work) {
    let now = Work::of(stats);
    let delta = now.since(*flushed);
    *flushed = now;
    DONE.with(|d| {
        let w = d.get();
        d.set(Work {
            tiles: w.tiles,
            primary_rays: w.primary_rays + delta.primary_rays,
            secondary_rays: w.secondary_rays + delta.secondary_rays,
            voxel_visits: w.voxel_visits + delta.voxel_visits,
        })
    });
}

/// Counts a tile started on this thread.
pub(crate) fn tile_started() {
    DONE.with(|d| {
        let mut w = d.get();
        w.tiles += 1;
        d.set(w)
    });
}
