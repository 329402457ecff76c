//! The GPU training step past its warm-up, phase by phase: a scene trained on the device
//! with the trainer's warm-up cut to `WARMUP` steps and `SETTLE` more steps for the batch
//! to grow out of the first steps' fog, then, over `STEPS` steps: steps/s, trained
//! samples/s, marched, network and trained samples a step, and the device's time per
//! phase (timestamps on one step in `PROFILE_EVERY`). Occupancy updates take 1/128 of the
//! reference's samples (a software adapter's update would take seconds). For setting two
//! builds of the trainer side by side on one adapter.
//!
//! cargo run --release --example bench_gpu_train_pass -- DATA [DOWNSCALE] [LOG2_BATCH]
//!     [STEPS] [WARMUP] [SETTLE] [PROFILE_EVERY] [auto|software|any]
//! (defaults: 8, 14, 60, 8, 40, 4, any)

use std::sync::Arc;
use std::time::Instant;
use stegongp::dataset::LoadOptions;
use stegongp::gpu::{GpuContext, GpuTrainer};
use stegongp::ngp::data::Split;
use stegongp::ngp::encoding::reference_indices;
use stegongp::ngp::network::{ModelConfig, NerfLayout};
use stegongp::ngp::train::{SceneSpec, TrainConfig};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let arg = |i: usize, d: u32| args.get(i).map_or(d, |s| s.parse().expect("a number"));
    let data = args.get(1).expect("DATA: a dataset folder");
    let (downscale, log2_batch, steps) = (arg(2, 8), arg(3, 14), arg(4, 60));
    let (warmup, settle, every) = (arg(5, 8), arg(6, 40), arg(7, 4));
    let ctx = GpuContext::from_arg(args.get(8).map(String::as_str)).expect("an adapter");
    let opts = LoadOptions {
        downscale,
        ..Default::default()
    };
    let train =
        Arc::new(stegongp::dataset::load(data.as_ref(), Split::Train, &opts).expect("the dataset"));
    let model = ModelConfig {
        aabb_scale: train.aabb_scale,
        ..Default::default()
    };
    let layout = NerfLayout::new(model).expect("a layout");
    let config = TrainConfig {
        seed: 1,
        batch_samples: 1 << log2_batch,
        occupancy_fraction: 1.0 / 128.0,
        ..Default::default()
    };
    let scenes = vec![SceneSpec {
        dataset: train,
        indices: reference_indices(&layout.grid),
    }];
    let mut t = GpuTrainer::new(&ctx, model, scenes, config).expect("a trainer");
    t.set_warmup(warmup);
    for _ in 0..warmup + settle {
        t.train_step().expect("a step");
    }
    t.profile_device(every);
    let (mut trained, mut marched, mut network) = (0u64, 0u64, 0u64);
    let t0 = Instant::now();
    for _ in 0..steps {
        let s = t.train_step().expect("a step");
        trained += s.n_samples;
        marched += s.n_marched;
        network += s.n_network;
    }
    let s = t.flush_stats().expect("the last measurements");
    (trained, marched, network) = (
        trained + s.n_samples,
        marched + s.n_marched,
        network + s.n_network,
    );
    let secs = t0.elapsed().as_secs_f64();
    println!("adapter: {}", ctx.report());
    println!(
        "{steps} steps after {} ({warmup} of warm-up): {:.3} steps/s, {:.0} trained samples/s; \
         per step {:.0} trained, {:.0} marched, {:.0} through the whole network",
        warmup + settle,
        steps as f64 / secs,
        trained as f64 / secs,
        trained as f64 / steps as f64,
        marched as f64 / steps as f64,
        network as f64 / steps as f64
    );
    let phases = t.device_profile();
    let total: f64 = phases.iter().map(|(_, ms)| ms).sum();
    for (name, ms) in &phases {
        println!("  {name:<34} {ms:9.3} ms");
    }
    println!("  {:<34} {total:9.3} ms", "sum");
}
