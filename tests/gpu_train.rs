//! The whole training step on the device (`crates/gpu/src/trainer.rs`) against the CPU trainer: a
//! generated scene trained on both with the same configuration, seed and steps; the GPU
//! model, saved as a snapshot, loads and renders on the CPU.
#![cfg(feature = "gpu")]

use std::sync::Arc;
use std::time::Instant;
use stegongp::gpu::{GpuContext, GpuTrainer, test_context};
use stegongp::ngp::data::Dataset;
use stegongp::ngp::encoding::reference_indices;
use stegongp::ngp::model::Model;
use stegongp::ngp::network::{ModelConfig, NerfLayout};
use stegongp::ngp::render::image::RenderOptions;
use stegongp::ngp::train::{SceneSpec, TrainConfig, Trainer};
use stegongp::score::eval::{evaluate, spread_views};
use stegongp::synth::SceneKind;
use testkit::scenes::generated;

/// Steps both backends train. Not e2e_train's budget (250 steps of 2^15 samples, ~22 dB):
/// llvmpipe runs the network's forward + backward at ~12 500 samples/s (benchmarks/gpu.md, 76×
/// slower than one CPU core), so 2^15-sample steps take 5–7 s each there and that budget
/// would take half an hour. 100 steps of 2^12 samples (about 6 500 marched a step) take
/// about a minute on llvmpipe, and the CPU reaches ~17.5 dB with them from the untrained
/// 8.2 dB (measured): both clearly learn, and the comparison still holds GPU to CPU
/// within 0.5 dB.
const STEPS: u32 = 100;

/// e2e_train's model: the paper's grid with a 2^16 table.
fn model_config() -> ModelConfig {
    let mut c = ModelConfig::default();
    c.grid.log2_hashmap_size = 16;
    c
}

fn scene(dir: &std::path::Path) -> (Dataset, Dataset) {
    generated(dir, SceneKind::Object, 40, 40, 4, 3).pair()
}

fn config() -> TrainConfig {
    TrainConfig {
        seed: 7,
        batch_samples: 1 << 12,
        // Occupancy updates run ~53 times in 100 steps; at a 128th of the reference's
        // samples (16 384 a cascade) each costs ~0.15 s on llvmpipe instead of ~1 s.
        occupancy_fraction: 1.0 / 128.0,
        ..Default::default()
    }
}

fn psnr_of(model: &Model, test: &Dataset) -> f64 {
    let layout = NerfLayout::new(model.config).unwrap();
    let indices = reference_indices(&layout.grid);
    let view = model.view(&indices, &model.grid);
    let which = spread_views(test.frames.len(), 4);
    evaluate(
        &view,
        test,
        &RenderOptions::default(),
        Some(&which),
        |_, _, _| {},
    )
    .psnr
}

/// A GPU trainer of `train` with the test's model and configuration.
fn gpu_trainer(ctx: &'static GpuContext, train: &Arc<Dataset>) -> GpuTrainer<'static> {
    let cfg = model_config();
    let layout = NerfLayout::new(cfg).unwrap();
    GpuTrainer::new(
        ctx,
        cfg,
        vec![SceneSpec {
            dataset: train.clone(),
            indices: reference_indices(&layout.grid),
        }],
        config(),
    )
    .unwrap()
}

fn train_gpu(train: &Arc<Dataset>) -> Option<Model> {
    let ctx = test_context()?;
    let mut t = gpu_trainer(ctx, train);
    let t0 = Instant::now();
    let mut last = None;
    for _ in 0..STEPS {
        last = Some(t.train_step().unwrap());
    }
    let s = last.unwrap();
    eprintln!(
        "GPU: {STEPS} steps in {:.1} s; last step loss {:.5}, {} rays, \
         {} trained / {} marched samples (budget {})",
        t0.elapsed().as_secs_f64(),
        s.loss,
        s.n_rays,
        s.n_samples,
        s.n_marched,
        t.sample_budget()
    );
    assert!(
        s.n_marched < t.sample_budget() as u64,
        "the marching budget bound: the GPU step trained fewer rays than the CPU's"
    );
    Some(t.model(s.loss).unwrap())
}

#[test]
fn gpu_training_matches_cpu_and_its_snapshot_renders_on_cpu() {
    if test_context().is_none() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (train, test) = scene(dir.path());
    let train = Arc::new(train);
    let cfg = model_config();
    let layout = NerfLayout::new(cfg).unwrap();

    let t0 = Instant::now();
    let mut cpu = Trainer::new(
        cfg,
        vec![SceneSpec {
            dataset: train.clone(),
            indices: reference_indices(&layout.grid),
        }],
        config(),
    )
    .unwrap();
    let untrained = psnr_of(&Model::from_trainer(&cpu, 0.0), &test);
    for _ in 0..STEPS {
        cpu.train_step().unwrap();
    }
    let p_cpu = psnr_of(&Model::from_trainer(&cpu, 0.0), &test);
    eprintln!(
        "CPU: {STEPS} steps in {:.1} s, counters {:?}",
        t0.elapsed().as_secs_f64(),
        cpu.batch_counters(0)
    );

    let gpu = train_gpu(&train).unwrap();
    let p_gpu = psnr_of(&gpu, &test);
    eprintln!(
        "untrained {untrained:.2} dB, CPU {p_cpu:.2} dB, GPU {p_gpu:.2} dB (counters {:?})",
        gpu.batch_counters
    );
    // Both learn far beyond an untrained model (8.2 dB here; the CPU reaches ~17.5).
    assert!(p_cpu > untrained + 7.0, "CPU trained to {p_cpu:.2} dB");
    assert!(p_gpu > untrained + 7.0, "GPU trained to {p_gpu:.2} dB");
    assert!(
        (p_gpu - p_cpu).abs() <= 0.5,
        "GPU {p_gpu:.2} dB vs CPU {p_cpu:.2} dB"
    );

    // Saved, loaded and rendered on the CPU: the same model.
    let path = dir.path().join("gpu.ingp");
    gpu.save(&path).unwrap();
    let loaded = Model::load(&path).unwrap();
    assert_eq!(loaded.training_step, STEPS);
    let p_loaded = psnr_of(&loaded, &test);
    eprintln!("GPU model from its snapshot: {p_loaded:.2} dB");
    // fp16 weights in the file.
    assert!(
        (p_loaded - p_gpu).abs() < 0.3,
        "{p_loaded:.2} vs {p_gpu:.2} dB"
    );
}

/// The training pass in chunks of a small workspace gives the step a single pass gives:
/// the same loss and the same weights after it, to the rounding of the device's atomic
/// sums; and no ray is dropped for it.
#[test]
fn a_batch_past_the_workspace_trains_in_chunks_like_one_pass() {
    let Some(ctx) = test_context() else { return };
    let dir = tempfile::tempdir().unwrap();
    let (train, _) = scene(dir.path());
    let train = Arc::new(train);
    let mut one = gpu_trainer(ctx, &train);
    let mut chunked = gpu_trainer(ctx, &train);
    chunked.set_workspace_capacity(256).unwrap();
    assert!(chunked.set_workspace_capacity(500).is_err());
    for step in 0..4 {
        let (a, b) = (one.train_step().unwrap(), chunked.train_step().unwrap());
        // Several chunks: the first steps' batches train a thousand samples or more.
        assert!(
            b.n_samples > 3 * 256,
            "step {step}: {} trained",
            b.n_samples
        );
        assert_eq!(a.n_samples, b.n_samples, "step {step}");
        assert_eq!((a.dropped_rays, b.dropped_rays), (0, 0), "step {step}");
        assert!(
            (a.loss - b.loss).abs() <= 1e-5 * a.loss,
            "step {step}: loss {} in one pass, {} in chunks",
            a.loss,
            b.loss
        );
    }
    // Measured: at most 2e-5 to 1.2e-4 apart (the device's atomic sums run in another
    // order).
    assert_same_step(&one.params().unwrap(), &chunked.params().unwrap());
}

/// Weights two trainers reached by the same steps: a wrong chunk moves most weights it
/// touches by Adam's step, 1e-2; a weight whose gradient is near zero can flip its step's
/// sign on the device's summing order alone, so this counts the weights more than a tenth
/// of a step apart (at most 1 in 10 000) instead of taking the largest gap.
fn assert_same_step(p1: &[f32], p2: &[f32]) {
    let far = p1
        .iter()
        .zip(p2)
        .filter(|(a, b)| (*a - *b).abs() > 1e-3)
        .count();
    eprintln!("{far} of {} weights more than 1e-3 apart", p1.len());
    assert!(
        far * 10_000 <= p1.len(),
        "{far} of {} weights apart",
        p1.len()
    );
}

/// A run that reads its measurements two steps late (as `train --device gpu` does past its
/// warm-up, which these runs skip): every step is one submission (and one per occupancy
/// update) that the host never waits for inside the step; the measurements of each step
/// arrive two steps later and the last two with `flush_stats`; it learns as the run that
/// reads each step at its end does, to the noise of the device's sums. That run waits once
/// a step, at its end, and submits once too.
///
/// With the grid's fp16 copy (`set_half_grid`, `train --half-grid`) the training forwards
/// read the table rounded to fp16, refreshed in the step's own submission: that run, read
/// at each step's end, learns as the f32 one does on weights of its own (the copy was
/// read), still in one submission a step. The three runs share this test so that the plain
/// run, the comparison for both, trains once.
#[test]
fn a_pipelined_run_and_the_fp16_grid_copy_learn_as_the_plain_run_does() {
    let Some(ctx) = test_context() else { return };
    let dir = tempfile::tempdir().unwrap();
    let (train, test) = scene(dir.path());
    let train = Arc::new(train);
    const N: u32 = 40;
    let mut runs = Vec::new();
    for (lag, half) in [
        (0, false),
        (stegongp::gpu::trainer::MAX_LAG, false),
        (0, true),
    ] {
        let mut t = gpu_trainer(ctx, &train);
        t.set_read_lag(lag).unwrap();
        t.set_warmup(0);
        t.set_half_grid(half).unwrap();
        assert_eq!(t.half_grid(), half);
        let mut measured = 0;
        let mut samples = 0u64;
        for step in 0..N {
            let s = t.train_step().unwrap();
            assert_eq!(
                s.submissions,
                1 + s.occupancy_updates,
                "lag {lag}, half {half}, step {step}"
            );
            // Read at its end, a step waits for the device unless the device was already
            // done; read late, never.
            assert!(
                s.host_waits <= u32::from(lag == 0),
                "lag {lag}, step {step}"
            );
            // A step reports what was measured `lag` steps before it.
            assert_eq!(
                s.primary_loss.is_some(),
                step >= lag,
                "lag {lag}, step {step}"
            );
            measured += s.primary_loss.is_some() as u32;
            samples += s.n_samples;
        }
        let rest = t.flush_stats().unwrap();
        assert_eq!(rest.primary_loss.is_some(), lag > 0);
        assert!(t.flush_stats().unwrap().primary_loss.is_none());
        eprintln!(
            "lag {lag}, half {half}: {measured} steps reported in the run, {samples} trained \
             samples, {} in the flush",
            rest.n_samples
        );
        assert_eq!(measured + lag, N);
        assert!(rest.n_samples > 0 || lag == 0);
        let model = t.model(rest.loss).unwrap();
        runs.push((psnr_of(&model, &test), model.params().to_vec()));
    }
    let [plain, late, half] = [0, 1, 2].map(|i| runs[i].0);
    eprintln!(
        "PSNR after {N} steps: read in step {plain:.2} dB, two steps late {late:.2} dB, \
         fp16 grid copy {half:.2} dB"
    );
    assert!(plain > 11.0, "{plain:.2} dB: did not learn");
    assert!(
        (plain - late).abs() < 0.5,
        "read late: {late:.2} against {plain:.2} dB"
    );
    assert!(
        half > 11.0,
        "{half:.2} dB: the fp16 copy's run did not learn"
    );
    assert!(
        (plain - half).abs() < 0.5,
        "fp16 copy: {half:.2} against {plain:.2} dB"
    );
    assert_ne!(
        runs[0].1, runs[2].1,
        "the fp16 copy changed nothing: not read"
    );
}

/// Past the warm-up the training pass records only the chunks the measured batches call
/// for (half as much again as a batch is expected to ask for): with a small workspace,
/// several chunks a batch out of 64, 8 steps train exactly what recording all 64 trains,
/// with no ray dropped, while the batches still grow out of the first steps' fog; and so
/// does a workspace where one chunk holds a batch and the loss reads the training
/// forward's outputs instead of a forward of its own (the steady state on a GPU).
#[test]
fn recording_the_chunks_a_batch_needs_trains_what_all_chunks_train() {
    let Some(ctx) = test_context() else { return };
    let dir = tempfile::tempdir().unwrap();
    let (train, _) = scene(dir.path());
    let train = Arc::new(train);
    let mut all = gpu_trainer(ctx, &train);
    let mut some = gpu_trainer(ctx, &train);
    for t in [&mut all, &mut some] {
        t.set_workspace_capacity(1024).unwrap();
    }
    all.set_warmup(u32::MAX);
    some.set_warmup(2);
    // A workspace of the whole marching budget holds any batch in one chunk after the
    // warm-up: forward, loss, backward, with no forward for the loss before.
    let mut one = gpu_trainer(ctx, &train);
    one.set_workspace_capacity(one.sample_budget()).unwrap();
    one.set_warmup(2);
    let mut single = 0;
    for step in 0..8 {
        let (a, b, c) = (
            all.train_step().unwrap(),
            some.train_step().unwrap(),
            one.train_step().unwrap(),
        );
        assert_eq!(
            (a.dropped_rays, b.dropped_rays, c.dropped_rays),
            (0, 0, 0),
            "step {step}"
        );
        assert_eq!(a.n_samples, b.n_samples, "step {step}");
        assert_eq!(a.n_samples, c.n_samples, "step {step}");
        for (what, x) in [("those needed", &b), ("one chunk", &c)] {
            assert!(
                (a.loss - x.loss).abs() <= 1e-5 * a.loss,
                "step {step}: loss {} with every chunk, {} with {what}",
                a.loss,
                x.loss
            );
        }
        // The one submission of each step: recording fewer chunks is not a second one.
        assert_eq!(a.submissions, b.submissions, "step {step}");
        assert_eq!(a.submissions, c.submissions, "step {step}");
        // The whole network runs on the compacted samples alone (the density network on
        // the marched ones): twice where they take several chunks, once where one holds
        // them.
        assert_eq!(a.n_network, 2 * a.n_samples, "step {step}");
        assert_eq!(b.n_network, 2 * b.n_samples, "step {step}");
        assert!(
            c.n_network == c.n_samples || (step < 3 && c.n_network == 2 * c.n_samples),
            "step {step}: {} network samples, {} trained",
            c.n_network,
            c.n_samples
        );
        single += (c.n_network == c.n_samples) as u32;
    }
    assert!(single >= 5, "one chunk in {single} of 8 steps");
    assert_same_step(&all.params().unwrap(), &some.params().unwrap());
    assert_same_step(&all.params().unwrap(), &one.params().unwrap());
}

/// The coarse march is the CPU's aid: a GPU trainer asked for it refuses, naming it, and
/// keeps the reference's march (its default configuration has none).
#[test]
fn a_gpu_refuses_the_cpus_coarse_march() {
    let Some(ctx) = test_context() else {
        eprintln!("skipped: no GPU adapter");
        return;
    };
    let d = tempfile::tempdir().unwrap();
    let (train, _) = generated(d.path(), SceneKind::Object, 16, 4, 1, 3).pair();
    let train = Arc::new(train);
    let cfg = model_config();
    let layout = NerfLayout::new(cfg).unwrap();
    let spec = || SceneSpec {
        dataset: train.clone(),
        indices: reference_indices(&layout.grid),
    };
    let asked = TrainConfig {
        coarse_march: Some(64),
        ..config()
    };
    let err = GpuTrainer::new(ctx, cfg, vec![spec()], asked)
        .err()
        .expect("refused");
    assert!(err.to_string().contains("coarse march"), "{err}");
    assert!(GpuTrainer::new(ctx, cfg, vec![spec()], config()).is_ok());
}
