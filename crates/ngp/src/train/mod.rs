//! Training: the Adam + EMA optimizer, the schedule both backends follow, the hooks a
//! training policy acts through, and the trainer that ties rays, marching, the network and
//! compositing together for one or more scenes sharing one set of weights.

pub mod cameras;
pub mod coarse;
pub mod grid_updates;
mod held;
pub mod hooks;
pub mod loss;
pub mod memory;
pub mod optimizer;
pub mod schedule;
pub mod state;
pub mod trainer;
mod worker;

pub use grid_updates::GridUpdates;
pub use hooks::{PolicyOps, PolicyReads, StepInfo, TableBounds, TrainPolicy};
pub use optimizer::{Optimizer, OptimizerConfig};
pub use schedule::Schedule;
pub use trainer::{SceneSpec, StepStats, TrainConfig, Trainer};

use crate::data::Dataset;
use crate::error::Result;
use crate::model::Model;

/// What a training loop needs from a trainer, whichever device runs it (the CPU
/// [`Trainer`], or the wgpu backend's).
pub trait TrainBackend {
    /// One training step.
    fn train_step(&mut self) -> Result<StepStats>;
    /// Steps taken.
    fn step(&self) -> u32;
    fn n_scenes(&self) -> usize;
    /// The training images of scene `i` (0: the one the model publishes).
    fn dataset(&self, i: usize) -> &Dataset;
    /// Installs a [`TrainPolicy`], before the first step.
    fn set_policy(&mut self, policy: Box<dyn TrainPolicy>) -> Result<()>;
    /// The model as it would be published now, with `loss` as its stored loss.
    fn model(&self, loss: f32) -> Result<Model>;
    /// The whole training state between two steps ([`state`]), as a document (a caller
    /// nests it: the run's state, a checkpoint snapshot), to go on from later; an error
    /// where this backend cannot save one.
    fn save_state(&self) -> Result<state::Value>;
    /// Takes back a [`save_state`](Self::save_state) before the first step; `origin`
    /// names it in errors.
    fn restore_state(&mut self, doc: &state::Value, origin: &std::path::Path) -> Result<()>;
    /// The measurements of steps taken that no step's stats reported yet (a backend that
    /// reads them late, as a GPU does), for a run's totals once it ends; none here.
    fn flush_stats(&mut self) -> Result<StepStats> {
        Ok(StepStats::default())
    }
    /// Times the device's phases on one step in `every` (a GPU that can write timestamps);
    /// false where this backend cannot.
    fn profile_device(&mut self, _every: u32) -> bool {
        false
    }
    /// Has the training forwards read an fp16 copy of the grid table (a GPU's option,
    /// tiny-cuda-nn's way); an error where this backend or model cannot.
    fn half_grid(&mut self) -> Result<()> {
        Err(crate::error::Error::Config(
            "an fp16 copy of the grid is a GPU option (the CPU reads the f32 table)".into(),
        ))
    }
    /// The reference's steps a training sample of scene `i` stands for at the next step
    /// ([`coarse`]); 1 where this backend marches the reference's step.
    fn march_stride(&self, _i: usize) -> u32 {
        1
    }
    /// Milliseconds per profiled step by phase, in the order they ran (empty unless
    /// profiling).
    fn device_profile(&self) -> Vec<(String, f64)> {
        Vec::new()
    }
    /// Refines scene 0's training cameras as it trains ([`cameras`]), from the first step;
    /// an error where this backend cannot.
    fn refine_cameras(&mut self, _config: cameras::CameraRefinement) -> Result<()> {
        Err(crate::error::Error::Config(
            "camera refinement runs on the CPU trainer only (the GPU's is not written yet)".into(),
        ))
    }
    /// Scene 0's refined cameras, where they are refined.
    fn cameras(&self) -> Option<&cameras::CameraRefiner> {
        None
    }
}

impl TrainBackend for Trainer {
    fn train_step(&mut self) -> Result<StepStats> {
        Trainer::train_step(self)
    }
    fn step(&self) -> u32 {
        self.step
    }
    fn n_scenes(&self) -> usize {
        Trainer::n_scenes(self)
    }
    fn dataset(&self, i: usize) -> &Dataset {
        Trainer::dataset(self, i)
    }
    fn set_policy(&mut self, policy: Box<dyn TrainPolicy>) -> Result<()> {
        Trainer::set_policy(self, policy)
    }
    fn model(&self, loss: f32) -> Result<Model> {
        Ok(Model::from_trainer(self, loss))
    }
    fn save_state(&self) -> Result<state::Value> {
        Trainer::save_state_doc(self)
    }
    fn march_stride(&self, i: usize) -> u32 {
        Trainer::march_stride(self, i)
    }
    fn restore_state(&mut self, doc: &state::Value, origin: &std::path::Path) -> Result<()> {
        Trainer::restore_state_doc(self, doc, origin)
    }
    fn refine_cameras(&mut self, config: cameras::CameraRefinement) -> Result<()> {
        Trainer::refine_cameras(self, config)
    }
    fn cameras(&self) -> Option<&cameras::CameraRefiner> {
        Trainer::cameras(self)
    }
}
