//! Attacks on a published model: what whoever downloads a file can do to it, blind to any
//! key. Each takes a [`Model`] as read from a snapshot and gives one back, so that an
//! attacked file is an ordinary snapshot every tool reads (`eval`, `render`, `detect`,
//! `view`, `mesh`). They read only what the file holds (weights, the stored occupancy
//! grid, the stored training cameras) and, for fine-tuning, the cover's own photos.
//!
//! - weight edits ([`weights`]): Gaussian noise, random and magnitude pruning of table
//!   entries, int8 / int4 quantisation;
//! - purification ([`purify`]): resetting the entries the cover cannot reach, or barely
//!   uses, to the initialisation's range;
//! - re-training ([`refit`]): fine-tuning on the cover's photos or on renders of it, the
//!   MLPs re-fitted on renders, and a fresh model distilled from renders.
//!
//! Every attack is deterministic for a seed.

pub mod purify;
pub mod refit;
pub mod spec;
pub mod views;
pub mod weights;

pub use spec::Attack;

use dataset::LoadOptions;
use ngp::error::Result;
use ngp::model::Model;
use serde::Serialize;
use std::path::PathBuf;
use std::time::Instant;

/// What attacks may need beyond the model.
#[derive(Clone, Debug)]
pub struct AttackContext {
    /// Seeds every random draw (each attack of a chain draws from its own stream).
    pub seed: u64,
    /// The cover's photos, for `finetune` (a user refining the model they downloaded).
    pub data: Option<PathBuf>,
    /// How to read them (downscale, image folder, box), as `train` read them.
    pub load: LoadOptions,
    /// The long side of the cover's renders that `finetune-renders`, `refit-mlp`,
    /// `purify-mlp` and `redistil` train on (at most the stored cameras' own size).
    pub render_side: u32,
    /// Views (at most) rendered of the stored cameras for those attacks.
    pub render_views: usize,
    /// Samples a training step of those attacks trains (the recipe's 2^18 by default: a
    /// user fine-tunes as they would train).
    pub batch: u32,
}

impl AttackContext {
    /// The context of the `i`-th attack of a chain: its own random stream.
    pub fn for_attack(&self, i: usize) -> AttackContext {
        AttackContext {
            seed: ngp::train::schedule::mix(self.seed, 0x6174_7461 + i as u64),
            ..self.clone()
        }
    }
}

impl Default for AttackContext {
    fn default() -> Self {
        AttackContext {
            seed: 0,
            data: None,
            load: LoadOptions::default(),
            render_side: 200,
            render_views: 64,
            batch: 1 << 18,
        }
    }
}

/// What one attack did, for a report.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Applied {
    /// As written on the command line (`noise=0.001`).
    pub attack: String,
    /// Weights whose value changed (the stored fp16 may hide the smallest changes).
    pub params_changed: u64,
    /// Grid table entries (feature vectors) touched: zeroed, reset or trained.
    pub entries_changed: u64,
    /// Entries of the table in all.
    pub entries_total: u64,
    /// Training steps the attack ran (fine-tuning, re-fitting, re-distilling).
    pub steps: u32,
    pub seconds: f64,
}

/// Applies `attacks` left to right, each with its own random stream
/// ([`AttackContext::for_attack`]), after checking them all; `each` hears of every attack
/// as it is done (a command's progress). The report of each.
pub fn apply_all(
    mut model: Model,
    attacks: &[Attack],
    ctx: &AttackContext,
    mut each: impl FnMut(&Applied),
) -> Result<(Model, Vec<Applied>)> {
    for a in attacks {
        a.check(ctx)?;
    }
    let mut reports = Vec::with_capacity(attacks.len());
    for (i, a) in attacks.iter().enumerate() {
        let (m, r) = apply(model, a, &ctx.for_attack(i))
            .map_err(|e| ngp::error::Error::Other(format!("attack `{a}`: {e}")))?;
        model = m;
        each(&r);
        reports.push(r);
    }
    Ok((model, reports))
}

/// Applies one attack.
pub fn apply(model: Model, attack: &Attack, ctx: &AttackContext) -> Result<(Model, Applied)> {
    attack.check(ctx)?;
    let t0 = Instant::now();
    let before = model.params().to_vec();
    let layout = model.net.layout.clone();
    let (model, steps, touched) = match *attack {
        Attack::Noise { sigma } => {
            let p = weights::noise(&before, sigma, ctx.seed);
            (model.with_params(p)?, 0, None)
        }
        Attack::Prune { fraction } => {
            let (p, n) = weights::prune_random(&layout, &before, fraction, ctx.seed);
            (model.with_params(p)?, 0, Some(n))
        }
        Attack::PruneMagnitude { fraction } => {
            let (p, n) = weights::prune_magnitude(&layout, &before, fraction);
            (model.with_params(p)?, 0, Some(n))
        }
        Attack::Quantise { bits } => {
            let p = weights::quantise(&layout, &before, bits);
            (model.with_params(p)?, 0, None)
        }
        Attack::Purify => {
            let (p, n) = purify::purify_unreachable(&model, ctx.seed);
            (model.with_params(p)?, 0, Some(n))
        }
        Attack::PurifyContribution { epsilon } => {
            let (p, n) = purify::purify_by_contribution(&model, epsilon, ctx)?;
            (model.with_params(p)?, 0, Some(n))
        }
        Attack::PurifyMlp { steps } => {
            let (p, n) = purify::purify_unreachable(&model, ctx.seed);
            let m = refit::refit_mlp(model.with_params(p)?, steps, ctx)?;
            (m, steps, Some(n))
        }
        Attack::RefitMlp { steps } => (refit::refit_mlp(model, steps, ctx)?, steps, None),
        Attack::Finetune { steps } => (refit::finetune_photos(model, steps, ctx)?, steps, None),
        Attack::FinetuneRenders { steps } => {
            (refit::finetune_renders(model, steps, ctx)?, steps, None)
        }
        Attack::Redistil { steps } => (refit::redistil(model, steps, ctx)?, steps, None),
    };
    let after = model.params();
    let params_changed = before
        .iter()
        .zip(after)
        .filter(|(a, b)| a.to_bits() != b.to_bits())
        .count() as u64;
    let g = layout.grid_offset;
    let nf = layout.grid.config.n_features as usize;
    let entries_changed = touched.unwrap_or_else(|| {
        before[g..]
            .chunks(nf)
            .zip(after[g..].chunks(nf))
            .filter(|(a, b)| {
                a.iter()
                    .zip(b.iter())
                    .any(|(x, y)| x.to_bits() != y.to_bits())
            })
            .count() as u64
    });
    Ok((
        model,
        Applied {
            attack: attack.to_string(),
            params_changed,
            entries_changed,
            entries_total: layout.grid.n_entries as u64,
            steps,
            seconds: t0.elapsed().as_secs_f64(),
        },
    ))
}

#[cfg(test)]
mod tests;
