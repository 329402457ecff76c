//! A GPU training saved and resumed (`GpuTrainer::save_state` / `restore_state`, and
//! `train --save-every` / `--resume --device gpu`): everything restored reads back as saved,
//! bit for bit; the resumed run takes the steps the uninterrupted one takes and ends within
//! the device's run-to-run noise of it; a stealth run's policy and mechanisms come back
//! too; states from the other device, from another scene, cut short, or with a policy where
//! none was saved (or the reverse) are refused, naming the file.
#![cfg(feature = "gpu")]

use serde_json::Value;
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;
use stegongp::gpu::{GpuContext, GpuTrainer, test_context};
use stegongp::ngp::data::Dataset;
use stegongp::ngp::encoding::reference_indices;
use stegongp::ngp::model::Model;
use stegongp::ngp::network::{ModelConfig, NerfLayout};
use stegongp::ngp::render::image::RenderOptions;
use stegongp::ngp::train::{SceneSpec, TrainBackend, TrainConfig, TrainPolicy, Trainer};
use stegongp::score::eval::{evaluate, spread_views};
use stegongp::synth::SceneKind;
use testkit::cli::{fails_naming, stegongp};
use testkit::scenes::generated;

/// Steps before the save, and in all. gpu_train.rs's scene and configuration (2^12 samples
/// a step, about 1 s a step on 2 cores' llvmpipe); 40 steps take the model from 8 dB to ~13.
const SAVE_AT: u32 = 20;
const TOTAL: u32 = 40;

fn model_config() -> ModelConfig {
    let mut c = ModelConfig::default();
    c.grid.log2_hashmap_size = 16;
    c
}

fn config() -> TrainConfig {
    TrainConfig {
        seed: 7,
        batch_samples: 1 << 12,
        occupancy_fraction: 1.0 / 128.0,
        ..Default::default()
    }
}

fn specs(train: &Arc<Dataset>) -> Vec<SceneSpec> {
    let layout = NerfLayout::new(model_config()).unwrap();
    vec![SceneSpec {
        dataset: train.clone(),
        indices: reference_indices(&layout.grid),
    }]
}

fn gpu_trainer(ctx: &'static GpuContext, train: &Arc<Dataset>) -> GpuTrainer<'static> {
    GpuTrainer::new(ctx, model_config(), specs(train), config()).unwrap()
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

/// Root-mean-square distance between two weight vectors, relative to the first's RMS.
fn rel_distance(a: &[f32], b: &[f32]) -> f64 {
    let d: f64 = a.iter().zip(b).map(|(x, y)| ((x - y) as f64).powi(2)).sum();
    let n: f64 = a.iter().map(|x| (*x as f64).powi(2)).sum();
    (d / n).sqrt()
}

fn steps(t: &mut GpuTrainer, n: u32) -> f32 {
    let mut loss = 0.0;
    for _ in 0..n {
        loss = t.train_step().unwrap().loss;
    }
    loss
}

/// Trains to `SAVE_AT`, saves, restores into a fresh trainer and checks that everything
/// reads back as saved; then both go on to `TOTAL` beside a run that never stopped.
///
/// The tolerance is the device's run-to-run noise: two uninterrupted runs on llvmpipe
/// differ (the grid's backward adds into the gradient with float atomics, in whatever
/// order the threads come). Measured on llvmpipe (2 cores): the two uninterrupted runs and
/// the resumed one within 0.000–0.003 dB of each other, weights 0.07–0.7 % apart (RMS,
/// relative; 3 runs, two of them at 30 + 30 steps). The test allows 0.1 dB and 3 %. A
/// resume that leaves Adam's moments and EMA at zero ends 2.8 dB and 47 % away; one that
/// leaves the occupancy grid as it starts, 0.75 dB and 43 % (both measured, with the exact
/// checks below switched off).
#[test]
fn a_resumed_gpu_run_goes_on_as_the_uninterrupted_one() {
    let Some(ctx) = test_context() else { return };
    let dir = tempfile::tempdir().unwrap();
    let (train, test) = generated(dir.path(), SceneKind::Object, 40, 40, 4, 3).shared();
    let origin = dir.path().join("run.state");

    let mut whole = gpu_trainer(ctx, &train);
    steps(&mut whole, TOTAL);

    let mut first = gpu_trainer(ctx, &train);
    steps(&mut first, SAVE_AT);
    let t0 = Instant::now();
    let saved = first.save_state().unwrap();
    let save_s = t0.elapsed().as_secs_f64();

    let mut resumed = gpu_trainer(ctx, &train);
    let t0 = Instant::now();
    resumed.restore_state(&saved, &origin).unwrap();
    let restore_s = t0.elapsed().as_secs_f64();
    eprintln!(
        "state: {} bytes ({} parameters), saved in {save_s:.3} s, restored in {restore_s:.3} s",
        saved.len(),
        first.params().unwrap().len()
    );

    // Everything restored reads back as saved: the whole state again, byte for byte
    // (weights, moments, update counts, raw EMA, grids, counters, steps), and what the
    // trainer shows of it.
    assert_eq!((resumed.step, resumed.weight_steps), (SAVE_AT, SAVE_AT));
    assert!(
        resumed.save_state().unwrap() == saved,
        "the restored state reads back otherwise"
    );
    assert_eq!(resumed.params().unwrap(), first.params().unwrap());
    assert_eq!(
        resumed.inference_params().unwrap(),
        first.inference_params().unwrap()
    );
    let (g1, g2) = (first.grid(0).unwrap(), resumed.grid(0).unwrap());
    assert_eq!(g1.density, g2.density);
    assert_eq!(g1.bitfield(), g2.bitfield());
    assert_eq!((g1.mean, g1.ema_step), (g2.mean, g2.ema_step));
    assert!(g1.ema_step > 0, "the grid was updated");
    assert_eq!(first.grid_mean(0), resumed.grid_mean(0));
    assert_eq!(first.batch_counters(0), resumed.batch_counters(0));
    // Between steps the gradient is zero (the optimizer zeroes it), so it is not saved.
    for t in [&first, &resumed] {
        assert!(t.gradient().unwrap().iter().all(|&g| g == 0.0));
    }

    // The next step is the same step: the same rays through the same grid, the same loss
    // to the rounding of the device's sums.
    let (a, b) = (first.train_step().unwrap(), resumed.train_step().unwrap());
    assert_eq!(
        (a.n_rays, a.n_marched, a.n_samples, a.occupancy_updates),
        (b.n_rays, b.n_marched, b.n_samples, b.occupancy_updates),
        "step {SAVE_AT}"
    );
    assert!(
        (a.loss - b.loss).abs() <= 1e-4 * a.loss,
        "step {SAVE_AT}: loss {} uninterrupted, {} resumed",
        a.loss,
        b.loss
    );
    steps(&mut first, TOTAL - SAVE_AT - 1);
    steps(&mut resumed, TOTAL - SAVE_AT - 1);
    assert_eq!((resumed.step, resumed.weight_steps), (TOTAL, TOTAL));

    let models = [&whole, &first, &resumed].map(|t| t.model(0.0).unwrap());
    let [p_whole, p_first, p_resumed] = [0, 1, 2].map(|i| psnr_of(&models[i], &test));
    let noise_db = (p_whole - p_first).abs();
    let noise_w = rel_distance(models[0].params(), models[1].params());
    let off_db = (p_resumed - p_whole).abs().max((p_resumed - p_first).abs());
    let off_w = rel_distance(models[0].params(), models[2].params())
        .max(rel_distance(models[1].params(), models[2].params()));
    eprintln!(
        "PSNR: uninterrupted {p_whole:.3} and {p_first:.3} dB, resumed {p_resumed:.3} dB; \
         noise {noise_db:.3} dB / {:.2} % of the weights, resumed off by {off_db:.3} dB / \
         {:.2} %",
        100.0 * noise_w,
        100.0 * off_w
    );
    // Untrained: 8.2 dB; 40 steps reach ~13.
    assert!(p_whole > 11.0, "the run learns ({p_whole:.2} dB)");
    assert_eq!(models[2].training_step, TOTAL);
    assert!(off_db <= 0.1, "resumed {off_db:.3} dB off");
    assert!(off_w <= 0.03, "resumed weights {:.2} % off", 100.0 * off_w);
}

/// A policy that changes nothing and keeps no state.
struct Nop;
impl TrainPolicy for Nop {}

fn refused(r: stegongp::ngp::Result<()>, needles: &[&str]) {
    let e = r.expect_err("refused").to_string();
    for n in needles {
        assert!(e.contains(n), "{n:?} not in: {e}");
    }
}

/// `state` with the field at `path` (map keys, then array indices as numbers) replaced.
fn forged(state: &[u8], path: &[&str], value: rmpv::Value) -> Vec<u8> {
    let mut doc = rmpv::decode::read_value(&mut &state[..]).unwrap();
    let mut at = &mut doc;
    for key in path {
        at = match at {
            rmpv::Value::Map(m) => {
                &mut m
                    .iter_mut()
                    .find(|(k, _)| k.as_str() == Some(key))
                    .unwrap_or_else(|| panic!("no {key}"))
                    .1
            }
            rmpv::Value::Array(a) => &mut a[key.parse::<usize>().unwrap()],
            _ => panic!("{key}: not a map or an array"),
        };
    }
    *at = value;
    let mut out = Vec::new();
    rmpv::encode::write_value(&mut out, &doc).unwrap();
    out
}

#[test]
fn states_from_elsewhere_cut_short_or_forged_are_refused_naming_the_file() {
    let Some(ctx) = test_context() else { return };
    let dir = tempfile::tempdir().unwrap();
    let (train, _) = generated(&dir.path().join("a"), SceneKind::Object, 24, 8, 1, 3).shared();
    let (other, _) = generated(&dir.path().join("b"), SceneKind::Object, 24, 6, 1, 3).shared();
    let origin = dir.path().join("x.state");
    let file = "x.state";

    let mut g = gpu_trainer(ctx, &train);
    steps(&mut g, 2);
    let gpu_state = g.save_state().unwrap();
    let mut cpu = Trainer::new(model_config(), specs(&train), config()).unwrap();
    cpu.train_step().unwrap();
    let cpu_state = cpu.save_state().unwrap();
    // The sanity of what follows: each restores into its own kind of trainer.
    gpu_trainer(ctx, &train)
        .restore_state(&gpu_state, &origin)
        .unwrap();
    Trainer::new(model_config(), specs(&train), config())
        .unwrap()
        .restore_state(&cpu_state, &origin)
        .unwrap();

    // The other device's state, both ways.
    refused(
        gpu_trainer(ctx, &train).restore_state(&cpu_state, &origin),
        &[
            file,
            "saved by training on the CPU; this run trains on the GPU",
        ],
    );
    refused(
        Trainer::new(model_config(), specs(&train), config())
            .unwrap()
            .restore_state(&gpu_state, &origin),
        &[
            file,
            "saved by training on the GPU; this run trains on the CPU",
        ],
    );
    // Cut short, or not a state at all.
    for cut in [gpu_state.len() / 2, gpu_state.len() - 1, 7] {
        refused(
            gpu_trainer(ctx, &train).restore_state(&gpu_state[..cut], &origin),
            &[file],
        );
    }
    refused(
        gpu_trainer(ctx, &train).restore_state(b"not a state", &origin),
        &[file],
    );
    // Another scene, another seed.
    refused(
        gpu_trainer(ctx, &other).restore_state(&gpu_state, &origin),
        &[file, "scene 0 differ"],
    );
    let mut seeded = config();
    seeded.seed = 8;
    refused(
        GpuTrainer::new(ctx, model_config(), specs(&train), seeded)
            .unwrap()
            .restore_state(&gpu_state, &origin),
        &[file, "options differ"],
    );
    // A worker count is not the GPU's business.
    let mut workers = config();
    workers.workers = 5;
    GpuTrainer::new(ctx, model_config(), specs(&train), workers)
        .unwrap()
        .restore_state(&gpu_state, &origin)
        .unwrap();
    // Forged counts that would overrun the device's buffers or tables.
    let forgeries: [(&[&str], u64, &str); 4] = [
        (
            &["scenes", "0", "rays_per_batch"],
            1 << 20,
            "rays_per_batch",
        ),
        (&["scenes", "0", "rays_per_batch"], 0, "rays_per_batch"),
        (
            &["optimizer", "nested", "nested", "current_step"],
            1 << 30,
            "optimizer.nested.nested.current_step",
        ),
        (&["weight_steps"], 1, "weight_steps"),
    ];
    for (path, value, field) in forgeries {
        let bad = forged(&gpu_state, path, rmpv::Value::from(value));
        refused(
            gpu_trainer(ctx, &train).restore_state(&bad, &origin),
            &[file, field],
        );
    }
    let bad = forged(
        &gpu_state,
        &["scenes", "0", "density"],
        rmpv::Value::Binary(vec![0; 12]),
    );
    refused(
        gpu_trainer(ctx, &train).restore_state(&bad, &origin),
        &[file, "scenes[0].density"],
    );
    // Only into a trainer that has not stepped.
    refused(g.restore_state(&gpu_state, &origin), &["has not stepped"]);
    // A state goes back only where a policy is installed iff one was when it was saved.
    let mut p = gpu_trainer(ctx, &train);
    p.set_policy(Box::new(Nop)).unwrap();
    let with_policy = p.save_state().unwrap();
    refused(p.restore_state(&gpu_state, &origin), &[file, "policy"]);
    refused(
        gpu_trainer(ctx, &train).restore_state(&with_policy, &origin),
        &[file, "policy"],
    );
    let mut q = gpu_trainer(ctx, &train);
    q.set_policy(Box::new(Nop)).unwrap();
    q.restore_state(&with_policy, &origin).unwrap();
    // Through the backend trait, as the recipe calls it.
    let b: &mut dyn TrainBackend = &mut gpu_trainer(ctx, &train);
    let doc = stegongp::ngp::train::state::open(&origin, &gpu_state).unwrap();
    b.restore_state(&doc, &origin).unwrap();
    assert_eq!(b.step(), 2);
    // (Compared as bytes: a document read back holds the encoder's compact floats.)
    let again = stegongp::ngp::train::state::encode(&b.save_state().unwrap());
    assert!(again == gpu_state);
}

const RUN: &[&str] = &[
    "--batch",
    "1024",
    "--levels",
    "8",
    "--log2-t",
    "12",
    "--seed",
    "3",
    "--occupancy-fraction",
    "0.05",
    "--json",
];

fn train_json(scene: &Path, out: &Path, device: &str, extra: &[&str]) -> Value {
    let mut args = vec![
        "train",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--device",
        device,
    ];
    args.extend_from_slice(RUN);
    args.extend_from_slice(extra);
    let run = stegongp(&args);
    let stdout = testkit::cli::stdout_ok(&run);
    serde_json::from_str(&stdout).unwrap_or_else(|e| panic!("{e}: {stdout}"))
}

/// `train --device gpu --save-every` then `--resume`: the model of the whole run's step
/// count is written, the summary says where it resumed; a GPU state does not go on on the
/// CPU.
#[test]
fn the_cli_saves_and_resumes_a_gpu_run() {
    if test_context().is_none() {
        return;
    }
    let d = tempfile::tempdir().unwrap();
    let scene = d.path().join("scene");
    testkit::cli::synth(&scene, "object", 24, 8);
    let part = d.path().join("part.ingp");
    let state = d.path().join("part.checkpoint.msgpack");
    let s = state.to_str().unwrap();
    let first = train_json(
        &scene,
        &part,
        "gpu",
        &["--steps", "16", "--save-every", "8"],
    );
    assert_eq!(first["device"]["kind"], "gpu", "{first}");
    assert_eq!(first["steps"], 16, "{first}");
    // At steps 8 and 16; the end does not save twice.
    assert_eq!(first["state_saves"], 2, "{first}");
    assert!(first["resumed_at"].is_null(), "{first}");
    eprintln!(
        "GPU state: {} bytes, {:.3} s a save",
        std::fs::metadata(&state).unwrap().len(),
        first["state_save_seconds"].as_f64().unwrap() / 2.0
    );

    let resumed = d.path().join("resumed.ingp");
    let second = train_json(&scene, &resumed, "gpu", &["--steps", "30", "--resume", s]);
    assert_eq!(second["steps"], 30, "{second}");
    assert_eq!(second["resumed_at"], 16, "{second}");
    assert!(second["resume_seconds"].as_f64().unwrap() > 0.0, "{second}");
    eprintln!(
        "resumed in {:.3} s",
        second["resume_seconds"].as_f64().unwrap()
    );
    assert_eq!(Model::load(&resumed).unwrap().training_step, 30);
    assert_eq!(Model::load(&part).unwrap().training_step, 16);

    // The GPU's state on the CPU: refused by name, nothing written.
    let out = d.path().join("cpu.ingp");
    let mut args = vec![
        "train",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--device",
        "cpu",
        "--steps",
        "30",
        "--resume",
        s,
    ];
    args.extend_from_slice(RUN);
    fails_naming(
        &stegongp(&args),
        &["part.checkpoint.msgpack", "saved by training on the GPU"],
    );
    assert!(!out.exists(), "nothing written");
}

/// A stealth run on the GPU (every part, the random-scene schedule whose hidden steps update
/// nothing) saved right after a hidden-only step — its gradient waiting in the buffer, table
/// gradients held back, bounds on the entries the cover left, the confinement the policy
/// made — and restored into a fresh trainer with a fresh policy reads back the same state,
/// byte for byte, and takes the same next step.
#[test]
fn a_stealth_gpu_run_resumes_with_its_policy_and_mechanisms() {
    use stegongp::ngp::train::Schedule;
    use stegongp::stego::generate_prf;
    use stegongp::stego::stealth::{Stealth, StealthOptions};
    let Some(ctx) = test_context() else { return };
    let dir = tempfile::tempdir().unwrap();
    let (cover, _) = generated(&dir.path().join("c"), SceneKind::Object, 24, 6, 1, 3).shared();
    let (hidden, _) = generated(
        &dir.path().join("h"),
        SceneKind::Text("HI".into()),
        24,
        6,
        1,
        4,
    )
    .shared();
    let mut model = model_config();
    model.grid.n_levels = 8;
    model.grid.log2_hashmap_size = 12;
    let layout = NerfLayout::new(model).unwrap();
    let key = generate_prf(4).unwrap();
    let options = StealthOptions {
        enabled: true,
        ..Default::default()
    };
    let build = || {
        let specs = [cover.clone(), hidden.clone()]
            .into_iter()
            .map(|dataset| SceneSpec {
                dataset,
                indices: reference_indices(&layout.grid),
            })
            .collect();
        let tc = TrainConfig {
            schedule: Schedule::RandomScene,
            batch_samples: 1 << 11,
            ..config()
        };
        let mut t = GpuTrainer::new(ctx, model, specs, tc).unwrap();
        let policy = Stealth::new(layout.clone(), std::slice::from_ref(&key), &options).unwrap();
        t.set_policy(Box::new(policy)).unwrap();
        t
    };
    let mut first = build();
    let mut cover_steps = 0;
    loop {
        let trained_cover = first.train_step().unwrap().primary_loss.is_some();
        cover_steps += trained_cover as u32;
        if cover_steps >= 6 && !trained_cover {
            break;
        }
        assert!(first.step < 40, "no hidden-only step");
    }
    assert!(
        first.gradient().unwrap().iter().any(|&g| g != 0.0),
        "no gradient waits after a hidden-only step"
    );
    assert!(first.table_bounds().is_some(), "no bounds set");
    let saved = first.save_state().unwrap();
    let origin = dir.path().join("stealth.state");
    let mut resumed = build();
    assert!(
        resumed.indices(1) != first.indices(1),
        "the confinement has not moved"
    );
    resumed.restore_state(&saved, &origin).unwrap();
    assert!(
        resumed.save_state().unwrap() == saved,
        "the restored stealth state reads back otherwise"
    );
    assert!(
        resumed.indices(1) == first.indices(1),
        "the confined indices"
    );
    assert!(resumed.table_bounds() == first.table_bounds());
    assert_eq!(resumed.gradient().unwrap(), first.gradient().unwrap());
    let (a, b) = (first.train_step().unwrap(), resumed.train_step().unwrap());
    assert_eq!(
        (a.n_rays, a.n_marched, a.n_samples, a.primary_loss.is_some()),
        (b.n_rays, b.n_marched, b.n_samples, b.primary_loss.is_some())
    );
    assert!(
        (a.loss - b.loss).abs() <= 1e-4 * a.loss.max(1e-6),
        "{} vs {}",
        a.loss,
        b.loss
    );
    // Without a policy, or into a plain trainer: refused by name.
    let plain = GpuTrainer::new(
        ctx,
        model,
        [cover.clone(), hidden.clone()]
            .into_iter()
            .map(|dataset| SceneSpec {
                dataset,
                indices: reference_indices(&layout.grid),
            })
            .collect(),
        TrainConfig {
            schedule: Schedule::RandomScene,
            batch_samples: 1 << 11,
            ..config()
        },
    );
    refused(
        plain.unwrap().restore_state(&saved, &origin),
        &["stealth.state", "policy"],
    );
}
