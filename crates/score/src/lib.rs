//! Scoring of renders against their ground truth: image metrics as the NeRF literature
//! computes them ([`metrics`]: MSE, PSNR, SSIM), LPIPS with the shipped AlexNet v0.1
//! weights ([`lpips`]), and held-out evaluation ([`eval`]): every camera of a split
//! rendered by the engine (or any `RenderBackend`) and scored under a [`eval::Protocol`],
//! ours or instant-ngp's `scripts/run.py`.
//!
//! It reads the engine (`ngp`) and nothing else of ours: it knows nothing of keys, devices
//! or command lines, and the engine knows nothing of it.

pub mod eval;
pub mod lpips;
pub mod metrics;
