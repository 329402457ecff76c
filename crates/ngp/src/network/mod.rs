//! Bias-free MLPs (tiny-cuda-nn FullyFusedMLP semantics) and the NeRF network built from
//! them: hash grid → density MLP → [density outputs, SH] → colour MLP.

pub mod layout;
pub mod mlp;
pub mod nerf;

pub use layout::{MlpShape, ModelConfig, NerfLayout};
