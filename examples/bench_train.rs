//! Training speed and time-to-PSNR on any device: trains a scene (a generated one by
//! default) with `--device`'s backend, scoring held-out views every `eval-every` steps
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
use stegongp::ngp::data::{Dataset, LoadOptions, Split};
use stegongp::ngp::encoding::reference_indices;
use stegongp::ngp::eval::{evaluate_on, spread_views};
use stegongp::ngp::network::{ModelConfig, NerfLayout};
use stegongp::ngp::render::image::RenderOptions;
use stegongp::ngp::train::{SceneSpec, TrainConfig};
use stegongp::synth::{SceneKind, SynthOptions, generate};

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
            },
            &dir,
        )?;
        dir
    } else {
        PathBuf::from(&scene)
    };
    let opts = LoadOptions::default();
    let train = Dataset::load(&dir, Split::Train, &opts)?;
    let test = Dataset::load(&dir, Split::Test, &opts)?;
    let config = ModelConfig {
        aabb_scale: train.aabb_scale,
        ..Default::default()
    };
    let layout = NerfLayout::new(config)?;
    let device = Device::open(device)?;
    eprintln!(
        "device: {}; {} training images of {}×{}",
        device.report(),
        train.frames.len(),
        train.width,
        train.height
    );
    let cfg = TrainConfig {
        batch_samples: 1 << log2_batch,
        occupancy_fraction,
        ..Default::default()
    };
    let scenes = vec![SceneSpec {
        dataset: Arc::new(train),
        indices: reference_indices(&layout.grid),
    }];
    let mut trainer = device.trainer(config, scenes, cfg)?;
    let which = spread_views(test.frames.len(), 8);
    let ropts = RenderOptions::default();
    let (mut secs, mut samples) = (0.0f64, 0u64);
    let mut loss = 0.0f32;
    let mut evals = Vec::new();
    let mut reached: Vec<Option<f64>> = vec![None; targets.len()];
    while trainer.step() < steps {
        let st = trainer.train_step()?;
        secs += st.seconds;
        samples += st.n_samples;
        loss = st.cover_loss.unwrap_or(loss);
        if trainer.step() % eval_every == 0 || trainer.step() == steps {
            let model = trainer.model(loss)?;
            let idx = reference_indices(&layout.grid);
            let mut r = device.renderer(&model, &idx, &model.grid)?;
            let e = evaluate_on(r.as_mut(), &test, &ropts, Some(&which), None, |_, _, _| {})?;
            eprintln!(
                "step {:5}: {:7.1} s, {:8.0} k samples/s, test PSNR {:.2} dB",
                trainer.step(),
                secs,
                samples as f64 / secs / 1e3,
                e.psnr
            );
            for (t, at) in targets.iter().zip(reached.iter_mut()) {
                if at.is_none() && e.psnr >= *t {
                    *at = Some(secs);
                }
            }
            evals.push(json!({"step": trainer.step(), "seconds": secs, "psnr": e.psnr}));
        }
    }
    let out = json!({
        "device": device.report(),
        "scene": scene,
        "steps": trainer.step(),
        "batch_samples": 1u64 << log2_batch,
        "occupancy_fraction": occupancy_fraction,
        "train_seconds": secs,
        "samples_per_second": samples as f64 / secs,
        "steps_per_second": trainer.step() as f64 / secs,
        "evaluations": evals,
        "time_to_psnr": targets.iter().zip(&reached)
            .map(|(t, s)| json!({"psnr": t, "seconds": s}))
            .collect::<Vec<_>>(),
    });
    println!("{}", serde_json::to_string_pretty(&out)?);
    Ok(())
}
