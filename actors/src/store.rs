//! The VoxelStore actor: serves compressed voxel blobs by id from a database
//! on disk (one shard of it).
