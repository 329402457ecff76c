//! The cost of keyed index functions in training: the same scene trained with the
//! reference index, a `primes` key and a `prf` key (permuted dense levels), reporting
//! trained samples per second for each, and the held-out PSNR each reaches (a keyed index
//! alone must fit a scene as well as the reference one: it is only another hash).
//!
//! cargo run --release --example bench_index_cost -- [SCENE_DIR] [STEPS] [DOWNSCALE]
//! (default: a generated 100 px object scene, 60 steps)

use std::sync::Arc;
use stegongp::dataset::LoadOptions;
use stegongp::ngp::data::Split;
use stegongp::ngp::encoding::reference_indices;
use stegongp::ngp::model::Model;
use stegongp::ngp::network::{ModelConfig, NerfLayout};
use stegongp::ngp::render::image::RenderOptions;
use stegongp::ngp::train::{SceneSpec, TrainConfig, Trainer};
use stegongp::score::eval::{evaluate, spread_views};
use stegongp::stego::{generate_prf, generate_primes};
use stegongp::synth::{SceneKind, SynthOptions, generate};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let tmp = std::env::temp_dir().join("stegongp_bench_index_scene");
    let dir = match args.get(1) {
        Some(d) => std::path::PathBuf::from(d),
        None => {
            if !tmp.join("transforms_train.json").exists() {
                let opts = SynthOptions {
                    scene: SceneKind::Object,
                    resolution: 100,
                    n_train: 50,
                    n_val: 0,
                    n_test: 2,
                    seed: 1,
                    aabb_scale: 1,
                    ..Default::default()
                };
                generate(&opts, &tmp).expect("generate scene");
            }
            tmp
        }
    };
    let steps: u32 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(60);
    let downscale: u32 = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(1);
    let opts = LoadOptions {
        downscale,
        ..Default::default()
    };
    let data = Arc::new(stegongp::dataset::load(&dir, Split::Train, &opts).expect("load"));
    let test = stegongp::dataset::load(&dir, Split::Test, &opts).expect("load test split");
    let cfg = ModelConfig {
        aabb_scale: data.aabb_scale,
        ..Default::default()
    };
    let layout = NerfLayout::new(cfg).unwrap();
    let prf = generate_prf(1).unwrap();
    let primes = generate_primes(1).unwrap();
    let mut base = 0.0;
    for (name, indices) in [
        ("reference", reference_indices(&layout.grid)),
        ("primes", primes.level_indices(&layout.grid)),
        ("prf", prf.level_indices(&layout.grid)),
    ] {
        let tc = TrainConfig {
            batch_samples: 1 << 16,
            occupancy_fraction: 0.0625,
            ..Default::default()
        };
        let mut t = Trainer::new(
            cfg,
            vec![SceneSpec {
                dataset: data.clone(),
                indices: indices.clone(),
            }],
            tc,
        )
        .unwrap();
        // Warm-up: the first steps refresh the occupancy grid every step.
        for _ in 0..32 {
            t.train_step().unwrap();
        }
        let (mut secs, mut samples) = (0.0, 0u64);
        for _ in 0..steps {
            let st = t.train_step().unwrap();
            secs += st.rays_seconds;
            samples += st.n_samples;
        }
        let sps = samples as f64 / secs;
        let model = Model::from_trainer(&t, 0.0);
        let view = model.view(&indices, t.grid(0));
        let which = spread_views(test.frames.len(), 8);
        let score = evaluate(
            &view,
            &test,
            &RenderOptions::default(),
            Some(&which),
            |_, _, _| {},
        );
        if name == "reference" {
            base = sps;
        }
        println!(
            "{name:>9}: {:>8.0} trained samples/s in the ray phase ({:+.1} % vs reference), \
             held-out PSNR {:.2} dB over {} views",
            sps,
            (sps / base - 1.0) * 100.0,
            score.psnr,
            score.n_views
        );
    }
}
