//! dray-scene: everything about a model before it is rendered.
//!
//! - [`import`]: streaming PLY and OBJ readers that turn model files into
//!   [`Triangle`]s with their original ids (docs/design.md, "Conventions").
//! - [`generate`]: the deterministic synthetic power plant.
//! - [`preprocess`]: the out-of-core build of the high-level BSP and voxels.
//! - [`voxel`]: one voxel: its triangles, its low-level BVH, its codec.
//! - [`db`]: the voxel database on disk: manifest, reading, verifying.
//! - [`geometry`]: boxes, rays, the watertight ray-triangle test, clipping.

pub mod db;
pub mod generate;
pub mod geometry;
pub mod import;
pub mod mesh;
pub mod preprocess;
pub mod progress;
pub mod rng;
pub mod voxel;

pub use geometry::{Aabb, Hit, Ray};
pub use mesh::Triangle;
