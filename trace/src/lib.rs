//! dray-trace: camera, ray packets, two-level traversal and shading.
//!
//! The kernel arrives with the ray tracing kernel issue.
