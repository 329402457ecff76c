//! Small trained models, made as a user's would be: through the one recipe, on the CPU.

use backend::Device;
use ngp::data::Dataset;
use ngp::model::Model;
use ngp::network::ModelConfig;
use std::sync::Arc;
use stego::Key;
use training::recipe::{Budget, HiddenOptions, HiddenScene, Recipe, StepOptions, StoredLoss};
use training::run::{Run, RunOptions};

/// A model of `cover`, with each of `hidden` under its key, trained `n_steps` steps of
/// `steps` on the CPU with the default hidden options (mixed batches, no stealth).
pub fn trained(
    model: ModelConfig,
    cover: Arc<Dataset>,
    hidden: Vec<(Arc<Dataset>, Key)>,
    steps: StepOptions,
    n_steps: u32,
) -> Model {
    let recipe = Recipe {
        model,
        cover,
        hidden: hidden
            .into_iter()
            .enumerate()
            .map(|(i, (dataset, key))| HiddenScene {
                dataset,
                key,
                key_name: format!("hidden scene {}'s key", i + 1),
            })
            .collect(),
        steps,
        options: HiddenOptions::default(),
        budget: Budget::Steps(n_steps),
        stored_loss: StoredLoss::Last,
    };
    let cpu = Device::default();
    let recipe = recipe.check().expect("a valid test recipe");
    let mut run = Run::start(&recipe, &cpu, RunOptions::default()).expect("training on the CPU");
    run.run(|_| Ok(())).expect("training on the CPU");
    run.finish().expect("a finished training").trained.model
}
