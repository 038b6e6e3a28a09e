//! dray-actors: Scheduler, FrameAssigner, Prefetcher, VoxelStore, Client and
//! Display (DESIGN.md). They arrive with the distributed renderer issue.
