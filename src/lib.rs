//! StegoNGP: 3D cryptographic steganography in Instant-NGP neural radiance fields.
//!
//! `ngp` is a CPU Instant-NGP engine that knows nothing of keys: the hash-grid encoding takes
//! one index function per level. `stego` supplies keyed index functions, key files and
//! multi-scene training. `synth` ray-traces generated scenes for tests and the demo. `gpu`
//! (feature `gpu`) is the wgpu backend, tested against the CPU engine; `backend` puts the
//! two behind one boundary (`--device auto|cpu|gpu`).

pub mod backend;
pub mod error;
pub mod experiments;
#[cfg(feature = "gpu")]
pub mod gpu;
pub mod ngp;
pub mod rng;
pub mod steganalysis;
pub mod stego;
pub mod synth;
pub mod util;

pub use error::{Error, Result};
