//! StegoNGP: 3D cryptographic steganography in Instant-NGP neural radiance fields.
//!
//! The program and a facade over the workspace's layers, each its own crate (README.md,
//! "Layout"): [`ngp`] the engine (knows nothing of keys or devices), [`gpu`] its wgpu
//! backend, [`backend`] the device boundary (`--device`), [`synth`] generated scenes,
//! [`stego`] keys, the training recipe, stealth and [`steganalysis`], and
//! [`experiments`] the paper's experiments and their plans of jobs, [`viewer`] camera paths,
//! video and the web viewer, [`mesh`] meshes out of a model's density, [`score`] metrics, LPIPS
//! and evaluation protocols.

pub use attack;
pub use backend;
pub use capture;
pub use dataset;
pub use experiments;
pub use mesh;
pub use ngp;
pub use ngp::{Error, Result, error, rng, util};
pub use score;
pub use stego;
pub use stego::steganalysis;
pub use synth;
pub use training;
pub use viewer;

#[cfg(feature = "gpu")]
pub use gpu;
