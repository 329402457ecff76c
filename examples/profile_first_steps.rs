//! Where a capture's first minutes go, step by step: trains a plain model of a dataset with
//! `train`'s CPU defaults (or the options given) for a time or a number of steps, and prints
//! one JSON line per step: its seconds and their split (occupancy update, rays, optimizer),
//! the rays it trained, the samples that reached the loss and those marched, the march's
//! stride, the densities its occupancy update evaluated; every `--grid-every` steps also
//! the occupancy threshold and the share of each cascade's cells occupied.
//!
//! cargo run --release --example profile_first_steps -- DATASET [--downscale N]
//!     [--images DIR] [--seconds S | --steps N] [--coarse-march S] [--occupancy-budget R]
//!     [--grid-every K]
//!
//! The model's grid is read through `Training::model` (a copy of the weights): with
//! `--grid-every 1` that copy is part of every step's wall time, never of its measured
//! seconds.

use anyhow::{Context, bail};
use serde_json::json;
use std::path::PathBuf;
use std::sync::Arc;
use stegongp::backend::{Device, DeviceRequest};
use stegongp::dataset::LoadOptions;
use stegongp::ngp::data::Split;
use stegongp::ngp::network::ModelConfig;
use stegongp::training::recipe::{Budget, Recipe, StepOptions};

struct Args {
    data: PathBuf,
    load: LoadOptions,
    budget: Budget,
    steps: StepOptions,
    grid_every: u32,
}

fn parse() -> anyhow::Result<Args> {
    let mut it = std::env::args().skip(1);
    let data = PathBuf::from(it.next().context("DATASET missing")?);
    let mut a = Args {
        data,
        load: LoadOptions::default(),
        budget: Budget::Seconds(60.0),
        steps: StepOptions::default(),
        grid_every: 10,
    };
    while let Some(flag) = it.next() {
        let v = it.next().with_context(|| format!("{flag} needs a value"))?;
        match flag.as_str() {
            "--downscale" => a.load.downscale = v.parse()?,
            "--images" => a.load.images = Some(v),
            "--seconds" => a.budget = Budget::Seconds(v.parse()?),
            "--steps" => a.budget = Budget::Steps(v.parse()?),
            "--coarse-march" => a.steps.coarse_march = Some(v.parse()?),
            "--occupancy-budget" => a.steps.occupancy_budget = Some(v.parse()?),
            "--grid-every" => a.grid_every = v.parse::<u32>()?.max(1),
            _ => bail!("unknown option {flag}"),
        }
    }
    Ok(a)
}

fn main() -> anyhow::Result<()> {
    let a = parse()?;
    let train = stegongp::dataset::load(&a.data, Split::Train, &a.load)?;
    let model = ModelConfig {
        aabb_scale: train.aabb_scale,
        ..Default::default()
    };
    let device = Device::open(DeviceRequest::Cpu)?;
    let recipe = Recipe::plain(model, Arc::new(train), a.steps, a.budget);
    eprintln!(
        "{}: coarse march {:?}, occupancy budget {:?}",
        a.data.display(),
        recipe.coarse_march(&device),
        recipe.occupancy_budget(&device)
    );
    let recipe = recipe.check()?;
    let mut training = recipe.start(&device)?;
    while let Some(st) = training.step()? {
        let t = *training.totals();
        let mut line = json!({
            "step": st.step,
            "seconds": st.seconds,
            "elapsed": t.seconds,
            "occupancy_seconds": st.occupancy_seconds,
            "rays_seconds": st.rays_seconds,
            "optimizer_seconds": st.optimizer_seconds,
            "rays": st.n_rays,
            "samples": st.n_samples,
            "marched": st.n_marched,
            "occupancy_evaluations": st.occupancy_evaluations,
            "stride": training.trainer().march_stride(0),
        });
        if t.steps.is_multiple_of(a.grid_every) {
            let grid = training.model()?.grid;
            line["threshold"] = json!(grid.threshold());
            line["occupied_per_cascade"] = json!(
                (0..grid.n_cascades)
                    .map(|c| grid.occupied_fraction_in(c))
                    .collect::<Vec<_>>()
            );
        }
        println!("{line}");
    }
    Ok(())
}
