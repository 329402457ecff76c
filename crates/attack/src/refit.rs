//! Attacks that train: fine-tuning the downloaded weights on the cover's photos or on
//! renders of it, re-fitting the MLPs alone, and distilling a fresh model from renders.
//! Each trains plain (the reference index, no hidden scene) with the recipe's defaults for
//! the CPU (its batch, learning rate and occupancy schedule) and a fresh Adam.

use crate::AttackContext;
use crate::views::{cover_renders, stored_cameras};
use backend::Device;
use ngp::data::{Dataset, Split};
use ngp::encoding::reference_indices;
use ngp::error::{Error, Result};
use ngp::model::Model;
use ngp::train::{SceneSpec, Trainer};
use std::sync::Arc;
use training::recipe::{Budget, Recipe, StepOptions};

/// What a re-training starts from.
enum Start<'a> {
    /// The published weights and stored grid.
    Weights(&'a Model),
    /// The seed's initialisation (a new model of the same architecture).
    Fresh,
}

/// Trains `steps` plain steps of `data` from `start`; with `freeze_table` the grid table
/// stays as `start` had it (only the MLPs learn). The published cameras and step count
/// are `like`'s, the step count advanced by the steps trained.
fn train_plain(
    like: &Model,
    start: Start,
    data: Dataset,
    steps: u32,
    freeze_table: bool,
    ctx: &AttackContext,
) -> Result<Model> {
    if data.aabb_scale != like.config.aabb_scale {
        return Err(Error::Config(format!(
            "{}: aabb_scale {} differs from the model's {} (give --aabb-scale {})",
            data.root.display(),
            data.aabb_scale,
            like.config.aabb_scale,
            like.config.aabb_scale
        )));
    }
    let data = Arc::new(data);
    let step_options = StepOptions {
        seed: ctx.seed,
        batch: ctx.batch,
        ..StepOptions::default()
    };
    let recipe = Recipe::plain(
        like.config,
        data.clone(),
        step_options,
        Budget::Steps(steps),
    );
    let recipe = recipe.check()?;
    let config = recipe.train_config(&Device::default());
    let layout = &like.net.layout;
    let scenes = vec![SceneSpec {
        dataset: data,
        indices: reference_indices(&layout.grid),
    }];
    let mut trainer = Trainer::new(like.config, scenes, config)?;
    let table_from = match start {
        Start::Weights(m) => {
            trainer.start_from(m.params(), Some(m.grid.clone()))?;
            m.params()[layout.grid_offset..].to_vec()
        }
        Start::Fresh => trainer.params[layout.grid_offset..].to_vec(),
    };
    let mut loss = 0.0;
    for _ in 0..steps {
        loss = trainer.train_step()?.loss;
        if freeze_table {
            trainer.params[layout.grid_offset..].copy_from_slice(&table_from);
        }
    }
    let mut params = trainer.inference_params();
    if freeze_table {
        // The EMA saw each step's moved table before it was put back.
        params[layout.grid_offset..].copy_from_slice(&table_from);
    }
    let mut trained = Model::from_trainer(&trainer, loss).with_params(params)?;
    trained.dataset = like.dataset.clone();
    trained.training_step = match start {
        Start::Weights(_) => like.training_step.saturating_add(steps),
        Start::Fresh => steps,
    };
    Ok(trained)
}

/// Renders of the cover from the file's cameras, as `ctx` sizes them.
fn renders(model: &Model, ctx: &AttackContext) -> Result<Dataset> {
    let cams = stored_cameras(model, ctx.render_side, ctx.render_views)?;
    cover_renders(model, &cams)
}

/// `finetune=N`: N steps on the cover's photos (`ctx.data`), from the published weights.
pub fn finetune_photos(model: Model, steps: u32, ctx: &AttackContext) -> Result<Model> {
    let dir = ctx.data.as_ref().ok_or_else(|| {
        Error::Config("finetune trains on the cover's photos: give them with --data DIR".into())
    })?;
    let mut load = ctx.load.clone();
    if load.aabb_scale.is_none() {
        load.aabb_scale = Some(model.config.aabb_scale);
    }
    let data = dataset::load(dir, Split::Train, &load)?;
    train_plain(&model, Start::Weights(&model), data, steps, false, ctx)
}

/// `finetune-renders=N`: N steps on renders of the cover, from the published weights.
pub fn finetune_renders(model: Model, steps: u32, ctx: &AttackContext) -> Result<Model> {
    let data = renders(&model, ctx)?;
    train_plain(&model, Start::Weights(&model), data, steps, false, ctx)
}

/// `refit-mlp=N`: the MLPs trained N steps on renders of the cover, the table frozen.
pub fn refit_mlp(model: Model, steps: u32, ctx: &AttackContext) -> Result<Model> {
    let data = renders(&model, ctx)?;
    train_plain(&model, Start::Weights(&model), data, steps, true, ctx)
}

/// `redistil=N`: a fresh model of the same architecture trained N steps on renders of the
/// cover (what any analyst can always do: re-make the cover and drop the file).
pub fn redistil(model: Model, steps: u32, ctx: &AttackContext) -> Result<Model> {
    let data = renders(&model, ctx)?;
    train_plain(&model, Start::Fresh, data, steps, false, ctx)
}
