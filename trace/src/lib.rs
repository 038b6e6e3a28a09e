//! dray-trace: the ray tracing kernel.
//!
//! - [`camera`]: the pinhole camera of docs/design.md.
//! - [`accel`]: the acceleration structures the kernel traverses: the
//!   high-level BSP and voxels in the kernel's layout, and the
//!   [`accel::VoxelSource`] the kernel asks for voxels.
//! - [`packet`]: SIMD ray packets and the suspendable two-level traversal.
//! - [`render`]: frames in tiles on threads, shadows, shading.
//! - [`tile`]: one tile, fully shaded, while voxels arrive over time.
//! - [`report`]: the figures of a rendered view or camera path, as text
//!   and JSON.
//! - [`clock`]: a cheap clock for timing single packets.
//! - [`image`]: PNG, and the depth/primitive-id comparison formats.
//! - [`work`]: tracing work counted per thread, for a virtual clock's
//!   cost model.

pub mod accel;
pub mod camera;
pub mod clock;
pub mod image;
mod job;
pub mod packet;
mod quad;
pub mod render;
pub mod report;
pub mod tile;
pub mod work;
