//! The Instant-NGP engine of StegoNGP. It knows nothing of keys, devices or command lines:
//! every consumer of the hash grid passes one index function per level (`encoding::index`),
//! and a training policy (the stego layer's stealth, say) acts through the trainer's hooks
//! (`train::hooks`).

pub mod camera;
pub mod choice;
pub mod data;
pub mod encoding;
pub mod error;
pub mod geometry;
pub mod model;
pub mod network;
pub mod occupancy;
pub mod pages;
pub mod render;
pub mod rng;
pub mod snapshot;
pub mod train;
pub mod util;

pub use error::{Error, Result};
