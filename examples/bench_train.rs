//! Training speed and time-to-PSNR on any device: trains a plain model of a scene (a
//! generated one by default) through the one recipe with `--device`'s backend, scoring held-out views every `eval-every` steps
//! (evaluation time excluded), and prints trained samples/s, steps/s and the training time
//! at which the test PSNR first reached each target.
//!
//! cargo run --release --example bench_train -- [DEVICE] [SCENE] [STEPS] [LOG2_BATCH]
//!     [EVAL_EVERY] [TARGETS] [OCCUPANCY_FRACTION]
//! DEVICE: auto | cpu | gpu (default auto); SCENE: a dataset folder, or `object` (default)
//! for a generated 64 px object; STEPS default 400; LOG2_BATCH default 16; EVAL_EVERY
//! default 50; TARGETS comma-separated dB (default 20,24,26); OCCUPANCY_FRACTION of the
//! reference's occupancy-update samples (default 1; small batches on a slow device want less:
//! the first 16 steps each update the whole grid).
//!
//! Output: one JSON object on stdout (device, samples/s, steps/s, evaluations,
//! time_to_psnr), progress on stderr.

use serde_json::json;
use std::path::PathBuf;
use std::sync::Arc;
use stegongp::backend::{Device, DeviceRequest};
use stegongp::dataset::LoadOptions;
use stegongp::ngp::data::Split;
use stegongp::ngp::encoding::reference_indices;
use stegongp::ngp::network::{ModelConfig, NerfLayout};
use stegongp::ngp::render::image::RenderOptions;
use stegongp::score::eval::{evaluate_on, spread_views};
use stegongp::synth::{SceneKind, SynthOptions, generate};
use stegongp::training::recipe::{Budget, Recipe, StepOptions, StoredLoss};

fn arg<T: std::str::FromStr>(i: usize, default: T) -> T {
    std::env::args()
        .nth(i)
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

fn main() -> anyhow::Result<()> {
    let device: DeviceRequest = arg(1, DeviceRequest::Auto);
    let scene: String = arg(2, "object".to_string());
    let steps: u32 = arg(3, 400);
    let log2_batch: u32 = arg(4, 16);
    let eval_every: u32 = arg(5, 50).max(1);
    let targets: Vec<f64> = arg(6, "20,24,26".to_string())
        .split(',')
        .filter_map(|t| t.trim().parse().ok())
        .collect();
    let occupancy_fraction: f32 = arg(7, 1.0);

    let tmp = tempfile::tempdir()?;
    let dir = if scene == "object" {
        let dir = tmp.path().join("object");
        generate(
            &SynthOptions {
                scene: SceneKind::Object,
                resolution: 64,
                n_train: 60,
                n_val: 0,
                n_test: 8,
                seed: 1,
                aabb_scale: 1,
                ..Default::default()
            },
            &dir,
        )?;
        dir
    } else {
        PathBuf::from(&scene)
    };
    let opts = LoadOptions::default();
    let train = stegongp::dataset::load(&dir, Split::Train, &opts)?;
    let test = stegongp::dataset::load(&dir, Split::Test, &opts)?;
    let model = ModelConfig {
        aabb_scale: train.aabb_scale,
        ..Default::default()
    };
    let grid = NerfLayout::new(model)?.grid;
    let device = Device::open(device)?;
    eprintln!(
        "device: {}; {} training images of {}×{}",
        device.report(),
        train.frames.len(),
        train.width,
        train.height
    );
    let steps_opts = StepOptions {
        batch: 1 << log2_batch,
        occupancy_fraction,
        ..Default::default()
    };
    let mut recipe = Recipe::plain(model, Arc::new(train), steps_opts, Budget::Steps(steps));
    recipe.stored_loss = StoredLoss::Last;
    let recipe = recipe.check()?;
    let mut training = recipe.start(&device)?;
    let which = spread_views(test.frames.len(), 8);
    let ropts = RenderOptions::default();
    let mut evals = Vec::new();
    let mut reached: Vec<Option<f64>> = vec![None; targets.len()];
    while training.step()?.is_some() {
        let t = *training.totals();
        if t.steps % eval_every == 0 || t.steps == steps {
            let model = training.model()?;
            let idx = reference_indices(&grid);
            let mut r = device.renderer(&model, &idx, &model.grid)?;
            let e = evaluate_on(r.as_mut(), &test, &ropts, Some(&which), None, |_, _, _| {})?;
            eprintln!(
                "step {:5}: {:7.1} s, {:8.0} k samples/s, test PSNR {:.2} dB",
                t.steps,
                t.seconds,
                t.samples_per_second() / 1e3,
                e.psnr
            );
            for (target, at) in targets.iter().zip(reached.iter_mut()) {
                if at.is_none() && e.psnr >= *target {
                    *at = Some(t.seconds);
                }
            }
            evals.push(json!({"step": t.steps, "seconds": t.seconds, "psnr": e.psnr}));
        }
    }
    let t = *training.totals();
    let out = json!({
        "device": device.report(),
        "scene": scene,
        "steps": t.steps,
        "batch_samples": 1u64 << log2_batch,
        "occupancy_fraction": occupancy_fraction,
        "train_seconds": t.seconds,
        "samples_per_second": t.samples as f64 / t.seconds,
        "steps_per_second": t.steps as f64 / t.seconds,
        "evaluations": evals,
        "time_to_psnr": targets.iter().zip(&reached)
            .map(|(t, s)| json!({"psnr": t, "seconds": s}))
            .collect::<Vec<_>>(),
    });
    println!("{}", serde_json::to_string_pretty(&out)?);
    Ok(())
}
