//! dray-protocol: the typed messages nodes exchange (postcard encoded).
//!
//! This crate grows with the message bus issue; today it holds the
//! identifiers that the voxel database already shares with the wire.

/// Identifies one voxel of a database: its index in the manifest.
pub type VoxelId = u32;
