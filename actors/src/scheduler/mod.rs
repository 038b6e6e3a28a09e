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
//!   first. With affinity a client gets first its own tiles: while the
//!   image streams from a point in view (the camera travels roughly the
//!   way it looks), those of its sector around the image's centre, else
//!   those that show what it rendered in the last completed frame (its
//!   hit samples reprojected into the new camera); costliest first by that
//!   frame's times. Then the tiles of others that show most of its content
//!   or border its region (only for a client holding at most one tile);
//!   without affinity, a random tile. Early in a frame a tile of the
//!   client's own queue goes out with the rest of its aligned block (up to
//!   `max_block_px` a side) where the last frame rendered those tiles
//!   without a miss: one message each way for up to 16 tiles. After a cut
//!   (the camera turned by more than half the field of view, or moved
//!   beyond everything the last frame showed) the last frame is no guide:
//!   each client keeps its part of the screen, and the tiles go one by
//!   one. Tiles of a lost client, or outstanding past `max(tile_deadline, 8 × median tile time)`, go to
//!   another client (the first report wins). A complete frame yields
//!   [`FrameDone`] for the display and [`TileOwners`] for the prefetcher.
//! - [`run_prefetcher`]: fetches the manifest from a store, predicts the
//!   next camera from the last two, samples it coarsely through the
//!   high-level BSP and sends each client a [`PrefetchHint`] with the voxels
//!   of the tiles it will probably render (by the same reprojection).
//!
//! [`CameraUpdate`]: dray_protocol::CameraUpdate
//! [`FrameStart`]: dray_protocol::FrameStart
//! [`FrameAssigned`]: dray_protocol::FrameAssigned
//! [`RequestWork`]: dray_protocol::RequestWork
//! [`FrameDone`]: dray_protocol::FrameDone
//! [`TileOwners`]: dray_protocol::TileOwners
//! [`PrefetchHint`]: dray_protocol::PrefetchHint

mod assigner;
mod prefetch;
mod reproject;
mod sched;
mod sectors;
mod tiles;

pub use assigner::{run_assigner, AssignerOptions, MAX_QUEUED_FRAMES};
pub use prefetch::{
    plans_frame, run_prefetcher, PrefetcherOptions, PrefetcherSummary, WARM_AFTER, WARM_STRIDE,
};
pub use sched::{run_scheduler, SchedulerOptions, SchedulerSummary};
pub use tiles::TileGrid;
