//! The Scheduler, FrameAssigner and Prefetcher actors (node `scheduler`).
