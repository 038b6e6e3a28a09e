//! The tile policies: which fresh tile of a frame goes to a client that
//! asks, and which client will probably render each tile of the next frame.
//!
//! The closed set is [`TilePolicy`], chosen by name with `scheduler.policy`;
//! [`of`] gives each name its implementation, one file each:
//!
//! - [`affinity`] (the default): each tile to the client whose cache holds
//!   what it shows, by sectors ([`sectors`]) while the camera travels the
//!   way it looks, else by reprojection ([`reproject`]), else to its last
//!   client; costliest first, in blocks early in a frame.
//! - [`random`]: a uniformly random fresh tile to whoever asks (the
//!   baseline).
//!
//! [`predict_owners`] is the one rule for "who will render this tile": the
//! scheduler's queues are built from it, and the prefetcher sends its hints
//! by it, so the two cannot disagree.
//!
//! Adding a policy: a file here with a [`Policy`] and its per-frame
//! [`Queues`], its variant in `dray_config::TilePolicy` (with its name and
//! in `ALL`), its arm in [`of`], and unit tests in its file.

mod affinity;
mod random;
pub(super) mod reproject;
pub(super) mod sectors;

use super::tiles::TileGrid;
use super::tiles_in_flight::{SchedulerOptions, Tile};
use crate::settings::kernel_camera;
use dray_protocol::{Camera, Name};
use dray_scene::rng::Rng;
use dray_trace::camera::CameraBasis;
use glam::Vec3;
use std::collections::BTreeMap;

pub use dray_config::TilePolicy;

/// The implementation of `policy`.
pub(super) fn of(policy: TilePolicy) -> &'static dyn Policy {
    match policy {
        TilePolicy::Affinity => &affinity::Affinity,
        TilePolicy::Random => &random::Random,
    }
}

/// Per tile of a frame on `grid` seen through `now`, the client that
/// `policy` will give it, judged from the last frame: what the scheduler
/// sorts a frame's fresh tiles by and the prefetcher sends its hints by.
pub(super) fn predict_owners(
    policy: TilePolicy,
    grid: &TileGrid,
    now: &CameraBasis,
    last: &LastFrame<'_>,
) -> Prediction {
    of(policy).predict(grid, now, last)
}

/// A tile policy.
pub(super) trait Policy: Sync {
    /// Per tile of a frame on `grid` seen through `now`, the client
    /// predicted to render it, judged from `last`.
    fn predict(&self, grid: &TileGrid, now: &CameraBasis, last: &LastFrame<'_>) -> Prediction;

    /// Whether tiles belong to clients: a client then takes its own tiles
    /// first, in the oldest frame that has some, takes another's only when
    /// about to run dry, and lets the next frame start once out of its own.
    fn claims_tiles(&self) -> bool;

    /// The empty queues of a frame on `grid`.
    fn queues(&self, grid: &TileGrid) -> Box<dyn Queues>;
}

/// A frame's fresh tiles, queued as its policy hands them out. The frame
/// keeps the tiles' states and the retry queue; a policy sees them through
/// a [`FrameView`].
pub(super) trait Queues: Send {
    /// Sorts the fresh tiles into queues, judged from the last completed
    /// frame (`prev`), or while none has completed from the frame's
    /// `first_guide`.
    fn sort(&mut self, frame: &FrameView<'_>, prev: Option<&Previous>, opts: &SchedulerOptions);

    /// The fresh tile client `c` should render next, taken out of its
    /// queue.
    fn pick(&mut self, c: &Name, rng: &mut Rng) -> Option<usize>;

    /// Whether client `c` has fresh tiles of its own, or tiles nobody has.
    fn has_own(&self, c: &Name) -> bool;

    /// Tile `i`, just picked for client `c`, with the tiles that go out
    /// with it in one assignment (row by row, `i` among them), taken out
    /// of their queues; `clients` ask for work.
    fn block(
        &mut self,
        i: usize,
        c: &Name,
        frame: &FrameView<'_>,
        clients: usize,
        opts: &SchedulerOptions,
        holds_model: bool,
    ) -> Vec<usize>;

    /// Tile `i` went out to client `c`.
    fn handed_out(&mut self, c: &Name, i: usize);

    /// Per tile, the client predicted to render it when the queues were
    /// last sorted (empty: no prediction).
    fn predicted(&self) -> &[Option<Name>];
}

/// What a policy sees of a frame in flight.
pub(super) struct FrameView<'a> {
    /// The frame's grid.
    pub grid: &'a TileGrid,
    /// The frame's camera.
    pub camera: &'a Camera,
    /// Its tiles.
    pub tiles: &'a [Tile],
    /// Per tile, the client that rendered it so far.
    pub owners: &'a [Option<Name>],
    /// Tiles never assigned yet.
    pub fresh_left: usize,
    /// While no frame has completed: per tile, its client in the frame
    /// that was in flight when this one started.
    pub first_guide: Option<&'a [Option<Name>]>,
}

/// The last completed frame: what a policy goes by.
pub(super) struct Previous {
    /// Its number.
    pub number: u64,
    /// Its camera.
    pub camera: Camera,
    /// Its grid.
    pub grid: TileGrid,
    /// Per tile, its time, µs.
    pub costs: Vec<u64>,
    /// Per tile, the client that rendered it.
    pub owners: Vec<Option<Name>>,
    /// Per tile, the world positions of some of its hits.
    pub hits: Vec<Vec<Vec3>>,
    /// Per tile, whether its packets met a voxel their client lacked.
    pub missed: Vec<bool>,
}

impl Previous {
    /// The frame as a prediction reads it.
    pub fn last_frame(&self) -> LastFrame<'_> {
        LastFrame {
            camera: Some(kernel_camera(&self.camera, self.grid.width, self.grid.height).basis()),
            grid: self.grid,
            owners: &self.owners,
            hits: &self.hits,
        }
    }
}

/// The frame a prediction is judged from: the scheduler's last completed
/// frame, or the prefetcher's view of it from its [`TileOwners`].
///
/// [`TileOwners`]: dray_protocol::TileOwners
pub(super) struct LastFrame<'a> {
    /// Its camera on its grid, where known (the prefetcher may have lost
    /// it): without it no cut and no sectors can be seen.
    pub camera: Option<CameraBasis>,
    /// Its grid.
    pub grid: TileGrid,
    /// Per tile, the client that rendered it.
    pub owners: &'a [Option<Name>],
    /// Per tile, the world positions of some of its hits.
    pub hits: &'a [Vec<Vec3>],
}

impl LastFrame<'_> {
    /// Tile `i`'s client, if the frame is on `grid` (tile indices mean the
    /// same tiles only on the same grid).
    fn owner_on(&self, grid: &TileGrid, i: usize) -> Option<&Name> {
        if self.grid == *grid {
            self.owners.get(i)?.as_ref()
        } else {
            None
        }
    }
}

/// A policy's prediction for a frame.
pub(super) struct Prediction {
    /// Per tile, the client predicted to render it.
    pub owners: Vec<Option<Name>>,
    /// Per tile, how many of the last frame's hit samples of each client
    /// land in it (empty where the policy does not go by them).
    pub votes: Vec<BTreeMap<Name, u32>>,
    /// Whether the last frame guides this one: the camera moved on from it
    /// rather than cut to another view, so its costs and misses apply.
    pub guides: bool,
}

impl Prediction {
    /// No client for any of `n` tiles.
    pub fn none(n: usize) -> Prediction {
        Prediction {
            owners: vec![None; n],
            votes: vec![BTreeMap::new(); n],
            guides: false,
        }
    }
}

/// What the policies' tests share.
#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use crate::scheduler::tiles_in_flight::State;
    use std::time::Duration;

    /// Affinity, costliest first, blocks of up to 4 × 4 tiles of 32.
    pub fn options() -> SchedulerOptions {
        SchedulerOptions {
            tile_size: 32,
            policy: TilePolicy::Affinity,
            costliest_first: true,
            max_block_px: 128,
            tile_deadline: Duration::from_secs(10),
            display: crate::names::display(),
            assigner: crate::names::assigner(),
            prefetcher: None,
            seed: 1,
        }
    }

    /// `n` tiles never handed out.
    pub fn fresh_tiles(n: usize) -> Vec<Tile> {
        (0..n)
            .map(|_| Tile {
                state: State::Fresh,
                outstanding: Vec::new(),
            })
            .collect()
    }

    /// A frame on `grid` through `camera` with `tiles`, rendered by
    /// `owners` so far, before any frame completed.
    pub fn view<'a>(
        grid: &'a TileGrid,
        camera: &'a Camera,
        tiles: &'a [Tile],
        owners: &'a [Option<Name>],
    ) -> FrameView<'a> {
        FrameView {
            grid,
            camera,
            tiles,
            owners,
            fresh_left: tiles.iter().filter(|t| t.state == State::Fresh).count(),
            first_guide: None,
        }
    }

    /// A camera `z` units up the z axis, looking at the origin.
    pub fn walk_camera(z: f32) -> Camera {
        Camera {
            eye: [0.0, 0.0, z],
            look: [0.0, 0.0, 0.0],
            up: [0.0, 1.0, 0.0],
            fov_y_deg: 50.0,
        }
    }
}
