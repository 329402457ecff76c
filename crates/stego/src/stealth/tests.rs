//! Stealth's parts through the CPU trainer's hooks (the GPU's are tested against these in
//! `tests/gpu_stego_train.rs`).
// A test reads as one story; the 120-line limit (clippy.toml) is the program's.
#![allow(clippy::too_many_lines)]

use super::*;
use dataset::LoadOptions;
use ngp::data::{Dataset, Split};
use ngp::encoding::{GridConfig, reference_indices};
use ngp::model::Model;
use ngp::network::{ModelConfig, NerfLayout};
use ngp::train::{SceneSpec, Schedule, TrainConfig, Trainer};
use std::sync::Arc;
use synth::{SceneKind, SynthOptions, generate};

/// A generated object (the cover) and text (the hidden scene) of 4 views at 16 px, and a
/// tiny model for both.
fn cover_and_hidden(dir: &std::path::Path) -> (Arc<Dataset>, Arc<Dataset>, ModelConfig) {
    let load = |name: &str, scene: SceneKind, seed: u64| {
        let d = dir.join(name);
        let opts = SynthOptions {
            scene,
            resolution: 16,
            n_train: 4,
            n_val: 0,
            n_test: 1,
            seed,
            aabb_scale: 1,
            ..Default::default()
        };
        generate(&opts, &d).unwrap();
        Arc::new(dataset::load(&d, Split::Train, &LoadOptions::default()).unwrap())
    };
    let model = ModelConfig {
        grid: GridConfig {
            n_levels: 4,
            n_features: 2,
            log2_hashmap_size: 10,
            base_resolution: 16,
        },
        aabb_scale: 1,
    };
    (
        load("cover", SceneKind::Object, 1),
        load("hidden", SceneKind::Text("HI".into()), 2),
        model,
    )
}

/// Under pacing (stealth) a random-scene step that does not train the cover updates
/// nothing: no weight, no occupancy grid, no optimizer clock. The hidden scene's MLP
/// gradient stays in the buffers for the next step that trains the cover, and a model
/// file records the cover's steps. Without pacing the same steps move the weights.
#[test]
fn paced_steps_without_the_cover_wait_for_it() {
    let dir = tempfile::tempdir().unwrap();
    let (cover, hidden, model) = cover_and_hidden(dir.path());
    let layout = NerfLayout::new(model).unwrap();
    let n_mlp = layout.n_mlp_params();
    let specs = || {
        [cover.clone(), hidden.clone()]
            .into_iter()
            .map(|dataset| SceneSpec {
                dataset,
                indices: reference_indices(&layout.grid),
            })
            .collect::<Vec<_>>()
    };
    for paced in [true, false] {
        let tc = TrainConfig {
            seed: 3,
            batch_samples: 1 << 10,
            occupancy_fraction: 0.01,
            schedule: Schedule::RandomScene,
            ..Default::default()
        };
        let mut t = Trainer::new(model, specs(), tc).unwrap();
        if paced {
            let parts = StealthParts {
                pace: true,
                ..StealthParts::none()
            };
            let policy = Stealth::with_parts(layout.clone(), &[], parts).unwrap();
            t.set_policy(Box::new(policy)).unwrap();
        }
        let (mut with_cover, mut without) = (0, 0);
        let mut held_any = false;
        for step in 0..12 {
            let params = t.params.clone();
            let grid = t.grid(0).density.clone();
            let clock = t.optimizer.step;
            if t.train_step().unwrap().primary_loss.is_some() {
                with_cover += 1;
                continue;
            }
            without += 1;
            if !paced {
                assert_ne!(t.params, params, "step {step}: unpaced, nothing moved");
                continue;
            }
            assert!(t.params == params, "step {step}: a weight moved");
            assert!(t.grid(0).density == grid, "step {step}: the grid moved");
            assert_eq!(t.optimizer.step, clock, "step {step}");
            let held = t.gradient()[..n_mlp].iter().filter(|&&g| g != 0.0).count();
            // Grids update on the cover's steps only: before the first, the hidden
            // scene's grid is still empty and its rays find no sample.
            assert!(
                with_cover == 0 || held > 0,
                "step {step}: the hidden MLP gradient was dropped"
            );
            held_any |= held > 0;
        }
        assert!(!paced || held_any, "no hidden-only step after a cover step");
        assert!(with_cover > 0 && without > 0, "{with_cover} / {without}");
        let recorded = if paced { with_cover } else { 12 };
        assert_eq!(t.weight_steps, recorded);
        assert_eq!(Model::from_trainer(&t, 0.0).training_step, recorded);
    }
}

/// A one-scene trainer on a generated object, the cover of the density-cap tests.
fn cap_trainer(cap: Option<DensityCap>, dir: &std::path::Path) -> Trainer {
    let opts = SynthOptions {
        scene: SceneKind::Object,
        resolution: 16,
        n_train: 6,
        n_val: 0,
        n_test: 1,
        seed: 5,
        aabb_scale: 1,
        ..Default::default()
    };
    generate(&opts, dir).unwrap();
    let data = Arc::new(dataset::load(dir, Split::Train, &LoadOptions::default()).unwrap());
    let model = ModelConfig {
        grid: GridConfig {
            n_levels: 4,
            n_features: 2,
            log2_hashmap_size: 10,
            base_resolution: 16,
        },
        aabb_scale: 1,
    };
    let layout = NerfLayout::new(model).unwrap();
    let spec = SceneSpec {
        dataset: data,
        indices: reference_indices(&layout.grid),
    };
    let tc = TrainConfig {
        seed: 2,
        batch_samples: 1 << 11,
        occupancy_fraction: 0.05,
        workers: 2,
        ..Default::default()
    };
    let mut t = Trainer::new(model, vec![spec], tc).unwrap();
    if cap.is_some() {
        let parts = StealthParts {
            density_cap: cap,
            ..StealthParts::none()
        };
        let policy = Stealth::with_parts(layout, &[], parts).unwrap();
        t.set_policy(Box::new(policy)).unwrap();
    }
    t
}

/// Training under a low cap keeps the cover's grid below an uncapped one's, which the
/// same seed otherwise reproduces exactly; without cells above it the cap costs nothing.
#[test]
fn a_density_cap_holds_the_covers_grid_down() {
    let dir = tempfile::tempdir().unwrap();
    // The uncapped cover reaches 0.012 in these 40 steps; a heavier weight than
    // stealth's, whose covers train for hundreds of steps.
    let cap = DensityCap {
        max_optical_thickness: 0.003,
        weight: 1.0,
        samples: 4096,
    };
    let run = |cap: Option<DensityCap>| {
        let mut t = cap_trainer(cap, dir.path());
        let mut capped = 0;
        for _ in 0..40 {
            capped += t.train_step().unwrap().penalised;
        }
        let max = t.grid(0).density.iter().copied().fold(0.0f32, f32::max);
        (max, capped, t.params)
    };
    let (free, none, free_params) = run(None);
    let (held, capped, _) = run(Some(cap));
    assert_eq!(none, 0);
    assert!(capped > 0, "no point above the cap");
    assert!(
        held < 0.5 * free,
        "largest optical thickness {held} capped against {free} free"
    );
    // A cap above anything the cover reaches changes no weight.
    let high = DensityCap {
        max_optical_thickness: 1e6,
        ..DensityCap::STEALTH
    };
    let (_, capped, params) = run(Some(high));
    assert_eq!(capped, 0);
    assert!(params == free_params, "an idle cap moved the weights");
}

/// A stealth run saved between two steps — with hidden-only steps' gradients waiting in the
/// buffers, held-back table gradients, bounds on the entries the cover left and confined
/// hidden indices — and restored into a fresh trainer with a fresh policy goes on bit for
/// bit as the run that never stopped (every part on, the random-scene schedule whose
/// hidden steps update nothing).
#[test]
fn a_stealth_run_restored_goes_on_bit_for_bit() {
    // With the MLP shared, a hidden-only step leaves its MLP gradient waiting; with the
    // cover's own MLP, it keeps none.
    for cover_only_mlp in [false, true] {
        stealth_restores_bit_for_bit(cover_only_mlp);
    }
}

fn stealth_restores_bit_for_bit(cover_only_mlp: bool) {
    let dir = tempfile::tempdir().unwrap();
    let (cover, hidden, model) = cover_and_hidden(dir.path());
    let layout = NerfLayout::new(model).unwrap();
    let key = crate::keys::generate_prf(4).unwrap();
    let parts = StealthParts {
        cover_only_mlp,
        // Low enough that these few steps' cover exceeds it.
        density_cap: Some(DensityCap {
            max_optical_thickness: 0.002,
            weight: 1.0,
            samples: 1024,
        }),
        ..StealthParts::of(&StealthOptions::default())
    };
    let build_with = |parts: Option<StealthParts>| {
        let specs = [cover.clone(), hidden.clone()]
            .into_iter()
            .map(|dataset| SceneSpec {
                dataset,
                indices: reference_indices(&layout.grid),
            })
            .collect();
        let tc = TrainConfig {
            seed: 3,
            batch_samples: 1 << 10,
            occupancy_fraction: 0.05,
            schedule: Schedule::RandomScene,
            workers: 2,
            ..Default::default()
        };
        let mut t = Trainer::new(model, specs, tc).unwrap();
        if let Some(parts) = parts {
            let policy =
                Stealth::with_parts(layout.clone(), std::slice::from_ref(&key), parts).unwrap();
            t.set_policy(Box::new(policy)).unwrap();
        }
        t
    };
    let build = || build_with(Some(parts));
    const END: u32 = 28;
    let mut whole = build();
    // The first hidden-only step after the cover's eighth: with the MLP shared, its
    // gradient waits in the buffers, the hardest place to stop.
    let mut first = build();
    let mut cover_steps = 0;
    loop {
        let trained_cover = first.train_step().unwrap().primary_loss.is_some();
        cover_steps += trained_cover as u32;
        if cover_steps >= 8 && !trained_cover {
            break;
        }
        assert!(first.step < END - 5, "no hidden-only step");
    }
    let waiting = first.gradient().iter().any(|&g| g != 0.0);
    assert_eq!(
        waiting, !cover_only_mlp,
        "a gradient waits iff the MLP is shared"
    );
    let stop = first.step;
    let held = first.held_back().expect("the gate was used");
    assert!(
        held.iter().any(|&g| g != 0.0),
        "nothing held back at {stop}"
    );
    let bounded = first.table_bounds().expect("bounds were set");
    assert!(
        bounded.bounds().iter().any(|&b| b >= 0.0),
        "no bound at {stop}"
    );
    let saved = first.save_state().unwrap();
    let origin = std::path::Path::new("stealth.state");
    let mut resumed = build();
    resumed.restore_state(&saved, origin).unwrap();
    assert_eq!(resumed.step, stop);
    assert!(
        resumed.gradient() == first.gradient(),
        "the waiting gradient"
    );
    assert!(
        resumed.indices(1) == first.indices(1),
        "the confined indices"
    );
    assert!(
        build().indices(1) != first.indices(1),
        "the confinement has not moved since installation: the test proves nothing"
    );
    for _ in 0..END {
        whole.train_step().unwrap();
    }
    for _ in stop..END {
        first.train_step().unwrap();
        resumed.train_step().unwrap();
    }
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    for t in [&first, &resumed] {
        assert_eq!((t.step, t.weight_steps), (whole.step, whole.weight_steps));
        assert!(bits(&t.params) == bits(&whole.params), "weights differ");
        assert!(
            bits(&t.inference_params()) == bits(&whole.inference_params()),
            "published weights differ"
        );
        for i in 0..2 {
            assert!(bits(&t.grid(i).density) == bits(&whole.grid(i).density));
        }
        assert!(t.indices(1) == whole.indices(1));
        assert!(bits(t.held_back().unwrap()) == bits(whole.held_back().unwrap()));
        assert!(t.table_bounds() == whole.table_bounds());
    }
    // A state saved with other stealth options, or none, is refused by name.
    let other = StealthParts {
        cover_only_mlp: !cover_only_mlp,
        ..parts
    };
    let e = build_with(Some(other))
        .restore_state(&saved, origin)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("stealth.state") && e.contains("stealth options"),
        "{e}"
    );
    let e = build_with(None)
        .restore_state(&saved, origin)
        .unwrap_err()
        .to_string();
    assert!(e.contains("stealth.state") && e.contains("policy"), "{e}");
}
