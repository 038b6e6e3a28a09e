//! The Scheduler, FrameAssigner and Prefetcher actors (node `scheduler`).
//!
//! - [`run_assigner`]: takes the display's [`CameraUpdate`]s (the `seq` is
//!   the frame number), queues at most [`MAX_QUEUED_FRAMES`] of them and
//!   releases one frame at a time to the scheduler ([`FrameStart`]): the
//!   next as soon as the scheduler reports the previous one fully handed out
//!   ([`FrameAssigned`]), so the clients start on the next frame while the
//!   last tiles of the previous one finish (double buffering; how many
//!   frames are outstanding in all is the display's `frames_ahead`).
//! - [`run_scheduler`]: cuts each frame into [`TileGrid`] tiles and gives
//!   them to clients as they ask ([`RequestWork`] credits), oldest frame
//!   first, in the order of the configured [`TilePolicy`] (`affinity`:
//!   each client first the tiles its cache holds, costliest first, in
//!   blocks early in a frame; `random`: the baseline; one file each
//!   under `policy/`). Tiles of a lost client, or outstanding past
//!   `max(tile_deadline, 8 × median tile time)`, go to another client (the
//!   first report wins). A complete frame yields [`FrameDone`] for the
//!   display and [`TileOwners`] for the prefetcher.
//! - [`run_prefetcher`]: fetches the manifest from a store, predicts the
//!   next camera from the last two, samples it coarsely through the
//!   high-level BSP and sends each client a [`PrefetchHint`] with the voxels
//!   of the tiles it will probably render, by the policy's own prediction
//!   (`policy::predict_owners`, which the scheduler's queues follow).
//!
//! [`CameraUpdate`]: dray_protocol::CameraUpdate
//! [`FrameStart`]: dray_protocol::FrameStart
//! [`FrameAssigned`]: dray_protocol::FrameAssigned
//! [`RequestWork`]: dray_protocol::RequestWork
//! [`FrameDone`]: dray_protocol::FrameDone
//! [`TileOwners`]: dray_protocol::TileOwners
//! [`PrefetchHint`]: dray_protocol::PrefetchHint

mod assigner;
mod policy;
mod prefetch;
mod tiles;
mod tiles_in_flight;

pub use assigner::{run_assigner, AssignerOptions, MAX_QUEUED_FRAMES};
pub use policy::TilePolicy;
pub use prefetch::{
    plans_frame, run_prefetcher, PrefetcherOptions, PrefetcherSummary, WARM_AFTER, WARM_STRIDE,
};
pub use tiles::TileGrid;
pub use tiles_in_flight::{run_scheduler, SchedulerOptions, SchedulerSummary};
