//! The Instant-NGP engine. It knows nothing of keys: every consumer of the hash grid passes
//! one index function per level (`encoding::index`).

pub mod camera;
pub mod data;
pub mod encoding;
pub mod eval;
pub mod lpips;
pub mod metrics;
pub mod model;
pub mod network;
pub mod occupancy;
pub mod render;
pub mod snapshot;
pub mod train;
