//! The Client actor: voxel cache, loader and render threads.
