//! Training: the Adam + EMA optimizer and the trainer that ties rays, marching, the network
//! and compositing together for one or more scenes sharing one set of weights.

pub mod density_cap;
pub mod left_entries;
pub mod loss;
pub mod optimizer;
mod pacing;
pub mod trainer;

pub use density_cap::DensityCap;
pub use optimizer::{Optimizer, OptimizerConfig};
pub use trainer::{IndexRefresh, SceneSpec, Schedule, StepStats, TrainConfig, Trainer};
