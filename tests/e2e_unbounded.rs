//! End to end on capture-like generated scenes: the object inside a room, cameras inside the
//! room and inside the scene's box, the walls a far background, at `aabb_scale` 4 (3
//! cascades) and 16 (5 cascades, exponential steps reaching the coarsest). Plus marching and
//! rendering from cameras anywhere — inside, outside, on the box's faces, looking along its
//! axes — at every aabb_scale up to 128, which must never panic.

use std::sync::Arc;
use stegongp::dataset::LoadOptions;
use stegongp::ngp::camera::Camera;
use stegongp::ngp::data::{Dataset, Split, aabb_for_scale};
use stegongp::ngp::encoding::reference_indices;
use stegongp::ngp::model::Model;
use stegongp::ngp::network::nerf::NerfNetwork;
use stegongp::ngp::network::{ModelConfig, NerfLayout};
use stegongp::ngp::occupancy::OccupancyGrid;
use stegongp::ngp::render::image::{RenderOptions, SceneView, render_image};
use stegongp::ngp::render::march::Marcher;
use stegongp::ngp::train::{SceneSpec, TrainConfig, Trainer};
use stegongp::rng::Pcg32;
use stegongp::score::eval::evaluate;
use stegongp::stego::occupancy::rebuild_occupancy;
use stegongp::synth::{SceneKind, SynthOptions, generate};

fn model_config(aabb_scale: u32) -> ModelConfig {
    let mut c = ModelConfig::default();
    c.grid.log2_hashmap_size = 16;
    c.aabb_scale = aabb_scale;
    c
}

fn room(dir: &std::path::Path, aabb_scale: u32) -> (Dataset, Dataset) {
    generate(
        &SynthOptions {
            scene: SceneKind::Room,
            resolution: 64,
            n_train: 40,
            n_val: 0,
            n_test: 8,
            seed: 5,
            aabb_scale,
            ..Default::default()
        },
        dir,
    )
    .unwrap();
    let o = LoadOptions {
        downscale: 1,
        ..Default::default()
    };
    (
        stegongp::dataset::load(dir, Split::Train, &o).unwrap(),
        stegongp::dataset::load(dir, Split::Test, &o).unwrap(),
    )
}

/// Mean PSNR over every held-out view, on black (the views are opaque).
fn psnr(model: &Model, test: &Dataset) -> f64 {
    let idx = reference_indices(&model.net.layout.grid);
    let view = model.view(&idx, &model.grid);
    let opts = RenderOptions {
        background: [0.0; 3],
        ..Default::default()
    };
    evaluate(&view, test, &opts, None, |_, _, _| {}).psnr
}

/// What a room training gave: the model, its PSNR before and after, and the densities its
/// occupancy updates evaluated.
struct RoomRun {
    model: Model,
    untrained: f64,
    psnr: f64,
    evaluations: u64,
    updates: u32,
}

fn train_room(aabb_scale: u32, steps: u32, occupancy_budget: Option<f32>) -> RoomRun {
    let dir = tempfile::tempdir().unwrap();
    let (train, test) = room(dir.path(), aabb_scale);
    assert_eq!(train.aabb_scale, aabb_scale);
    // The premise: every camera is inside the box, and the walls are far beyond the object.
    let (lo, hi) = aabb_for_scale(aabb_scale);
    for f in &train.frames {
        let p = f.camera.position();
        assert!(
            (0..3).all(|d| p[d] > lo[d] && p[d] < hi[d]),
            "camera at {p:?}"
        );
    }
    assert!(test.frames.len() >= 5);
    let cfg = model_config(aabb_scale);
    let layout = NerfLayout::new(cfg).unwrap();
    let mut t = Trainer::new(
        cfg,
        vec![SceneSpec {
            dataset: Arc::new(train),
            indices: reference_indices(&layout.grid),
        }],
        TrainConfig {
            seed: 7,
            batch_samples: 1 << 15,
            occupancy_fraction: 1.0 / 32.0,
            occupancy_budget,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(t.grid(0).n_cascades, aabb_scale.ilog2() as usize + 1);
    let untrained = psnr(&Model::from_trainer(&t, 0.0), &test);
    let (mut evaluations, mut updates) = (0, 0);
    for _ in 0..steps {
        let st = t.train_step().unwrap();
        evaluations += st.occupancy_evaluations;
        updates += st.occupancy_updates;
    }
    let model = Model::from_trainer(&t, 0.0);
    let psnr = psnr(&model, &test);
    eprintln!(
        "aabb_scale {aabb_scale}, budget {occupancy_budget:?}: untrained {untrained:.2} dB, \
         {steps} steps {psnr:.2} dB, {updates} occupancy updates, {evaluations} densities"
    );
    RoomRun {
        model,
        untrained,
        psnr,
        evaluations,
        updates,
    }
}

fn trains_room(aabb_scale: u32, steps: u32, floor: f64) -> RoomRun {
    let r = train_room(aabb_scale, steps, None);
    assert!(
        r.psnr > floor,
        "aabb_scale {aabb_scale}: {:.2} dB after {steps} steps",
        r.psnr
    );
    assert!(
        r.psnr > r.untrained + 6.0,
        "{:.2} dB vs untrained {:.2} dB",
        r.psnr,
        r.untrained
    );
    r
}

// Thresholds: an untrained model scores 5–6 dB on these views, one that learned only the
// walls' mean colour ~11 dB. Measured after 300 steps: 20.98 dB at aabb_scale 4, 19.31 dB at
// 16 (600 steps of the same scene at 16 reach 21.7 dB). The floors sit 2.5 and 1.8 dB
// under: run-to-run noise is nil on one machine (deterministic), and across machines of
// this kind small; a broken cascade, cone step or background would cost far more.

#[test]
fn room_at_aabb_scale_4_reaches_threshold() {
    trains_room(4, 300, 18.5);
}

/// Five cascades, on the reference's occupancy schedule and on the CPU's budget (each of
/// the reference's updates drawing the share of its cells one density per trained sample
/// pays for). At equal steps the budget keeps the quality from far fewer densities
/// (measured: 18.89 dB against 19.15 from 39 % of them; spacing out whole updates instead
/// gave 17.32 dB). The trained model also renders the same image whatever the waves' sizes.
#[test]
fn room_at_aabb_scale_16_reaches_threshold() {
    let reference = trains_room(16, 300, 17.5);
    let budget = train_room(16, 300, Some(1.0));
    assert!(
        budget.psnr > reference.psnr - 1.0 && budget.psnr > 17.5,
        "budget {:.2} dB against the reference's {:.2} dB",
        budget.psnr,
        reference.psnr
    );
    // 300 steps of 2^15 samples pay for 9.8 M densities (and the first, whole update for
    // 0.33 M); the reference's 67 warm-up updates alone evaluate 22 M. The updates come on
    // the reference's steps.
    assert!(
        budget.evaluations as f64 <= 300.0 * (1u64 << 15) as f64 * 1.1,
        "{} densities",
        budget.evaluations
    );
    assert!(
        budget.evaluations * 2 < reference.evaluations && budget.updates == reference.updates,
        "budget {} densities in {} updates, reference {} in {}",
        budget.evaluations,
        budget.updates,
        reference.evaluations,
        reference.updates
    );
    renders_alike_in_any_waves(&budget.model);
}

/// One sample per ray per wave is the plain front-to-back renderer; waves of several samples
/// must give the same image, evaluating only a few samples past a ray's end.
fn renders_alike_in_any_waves(model: &Model) {
    let idx = reference_indices(&model.net.layout.grid);
    let view = model.view(&idx, &model.grid);
    let dir = tempfile::tempdir().unwrap();
    let (_, test) = room(dir.path(), 16);
    let cam = &test.frames[0].camera;
    let one = render_image(
        &view,
        cam,
        &RenderOptions {
            samples_per_wave: 1,
            ..Default::default()
        },
    );
    let waves = render_image(&view, cam, &RenderOptions::default());
    let worst = one
        .rgb
        .iter()
        .zip(&waves.rgb)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(worst < 1e-4, "pixels differ by {worst}");
    assert!(waves.n_samples >= one.n_samples);
    assert!(
        waves.n_samples <= one.n_samples + 7 * one.profile.n_rays,
        "{} samples in waves against {} one by one",
        waves.n_samples,
        one.n_samples
    );
    assert_eq!(waves.profile.n_rays, one.profile.n_rays);
    assert!(one.profile.n_rays > 0 && one.profile.n_waves > waves.profile.n_waves);
}

/// Cameras everywhere: far outside, on a face, inside near a corner, at the centre, looking
/// along an axis (rays parallel to four slab faces) and away from the box.
fn cameras_everywhere(aabb_scale: u32) -> Vec<Camera> {
    let (lo, hi) = aabb_for_scale(aabb_scale);
    let h = hi[0];
    let positions = [
        [0.5, 0.5, 0.5],
        [lo[0] + 1e-3, lo[1] + 1e-3, lo[2] + 1e-3],
        [hi[0], 0.5, 0.5],
        [h * 3.0, h * 2.0, -h * 4.0],
        [0.5, 0.5, lo[2] - 50.0],
        [1e6, 0.5, 0.5],
    ];
    let rotations = [
        // Identity: looks down +z (ngp cameras look along their third column).
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        // Looks down −x.
        [[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]],
        // Oblique.
        [[0.8, -0.36, 0.48], [0.0, 0.8, 0.6], [-0.6, -0.48, 0.64]],
    ];
    let mut cams = Vec::new();
    for p in positions {
        for r in rotations {
            cams.push(Camera {
                c2w: [
                    [r[0][0], r[0][1], r[0][2], p[0]],
                    [r[1][0], r[1][1], r[1][2], p[1]],
                    [r[2][0], r[2][1], r[2][2], p[2]],
                ],
                fx: 5.0,
                fy: 5.0,
                // Pixel 4's centre is the principal point: its ray runs exactly along the
                // camera's axis, parallel to four faces of the box.
                cx: 4.5,
                cy: 4.5,
                width: 8,
                height: 8,
                distortion: None,
            });
        }
    }
    cams
}

#[test]
fn marching_and_rendering_never_panic_at_any_aabb_scale() {
    for aabb_scale in [1u32, 2, 4, 16, 128] {
        let mut cfg = model_config(aabb_scale);
        cfg.grid.log2_hashmap_size = 12;
        let net = NerfNetwork::new(cfg).unwrap();
        let params = net.init_params(3);
        let idx = reference_indices(&net.layout.grid);
        // Every cell occupied (rays march the whole box), and a sparse random grid (rays
        // skip from cell to cell through every cascade).
        let full = OccupancyGrid::new(aabb_scale);
        let mut rng = Pcg32::new(aabb_scale as u64, 1);
        let sparse = OccupancyGrid::from_density(
            (0..full.density.len())
                .map(|_| if rng.next_f32() < 0.02 { 1.0 } else { 0.0 })
                .collect(),
        )
        .unwrap();
        for grid in [&full, &sparse] {
            let view = SceneView {
                net: &net,
                params: &params,
                grid_f16: None,
                indices: &idx,
                grid,
                marcher: Marcher::new(aabb_scale),
            };
            for cam in cameras_everywhere(aabb_scale) {
                let img = render_image(&view, &cam, &RenderOptions::default());
                assert!(img.rgb.iter().all(|v| v.is_finite()));
                let bad: Vec<&f32> = img
                    .opacity
                    .iter()
                    .filter(|v| !(0.0..=1.0).contains(*v))
                    .collect();
                assert!(
                    bad.is_empty(),
                    "aabb {aabb_scale} cam {:?}: opacity {bad:?}",
                    cam.c2w
                );
            }
        }
    }
}

/// A key holder's grid rebuild and training steps at a large box: cameras inside the box, the
/// marching of training rays through 5 cascades, the occupancy update over all of them.
#[test]
fn key_holder_rebuild_and_training_steps_at_aabb_scale_16() {
    let dir = tempfile::tempdir().unwrap();
    generate(
        &SynthOptions {
            scene: SceneKind::Room,
            resolution: 8,
            n_train: 9,
            n_val: 0,
            n_test: 1,
            seed: 1,
            aabb_scale: 16,
            ..Default::default()
        },
        dir.path(),
    )
    .unwrap();
    let data = stegongp::dataset::load(dir.path(), Split::Train, &LoadOptions::default()).unwrap();
    let mut cfg = model_config(16);
    cfg.grid.log2_hashmap_size = 12;
    let layout = NerfLayout::new(cfg).unwrap();
    let mut t = Trainer::new(
        cfg,
        vec![SceneSpec {
            dataset: Arc::new(data),
            indices: reference_indices(&layout.grid),
        }],
        TrainConfig {
            batch_samples: 1 << 12,
            occupancy_fraction: 1.0 / 64.0,
            ..Default::default()
        },
    )
    .unwrap();
    for _ in 0..3 {
        let s = t.train_step().unwrap();
        assert!(s.loss.is_finite() && s.n_samples > 0);
    }
    let model = Model::from_trainer(&t, 0.0);
    let idx = reference_indices(&model.net.layout.grid);
    let rebuilt = rebuild_occupancy(&model.net, model.params(), &idx, 16, 1, 0);
    assert_eq!(rebuilt.n_cascades, 5);
    let view = model.view(&idx, &rebuilt);
    for cam in cameras_everywhere(16) {
        let img = render_image(&view, &cam, &RenderOptions::default());
        assert!(img.rgb.iter().all(|v| v.is_finite()));
    }
}

/// A hidden text (its own box: aabb 1) in a capture-like cover at aabb 4, under a key whose
/// box is its own: it trains in the cover's whole box, the key holder's grid is cut to the
/// unit cube and recovers it, and a wrong key — tried in the same box — renders close to an
/// empty image, while over the cover's whole box its grid finds the cover's trained
/// entries everywhere.
#[test]
fn hidden_scene_confined_to_its_box_in_a_large_cover() {
    use stegongp::stego::{Key, generate_prf, open_scene};
    let dir = tempfile::tempdir().unwrap();
    let (cover, mut room_test) = room(&dir.path().join("room"), 4);
    let hdir = dir.path().join("text");
    generate(
        &SynthOptions {
            scene: SceneKind::Text("HI".into()),
            resolution: 48,
            n_train: 40,
            n_val: 0,
            n_test: 3,
            seed: 3,
            aabb_scale: 1,
            ..Default::default()
        },
        &hdir,
    )
    .unwrap();
    let o = LoadOptions::default();
    let mut hidden = stegongp::dataset::load(&hdir, Split::Train, &o).unwrap();
    let mut hidden_test = stegongp::dataset::load(&hdir, Split::Test, &o).unwrap();
    let key = generate_prf(2).unwrap().with_scene_box(Some(1)).unwrap();
    // A key's box smaller than its scene is refused, naming the scene and the fix.
    let err = room_test.fit_into_box(16, Some(1)).unwrap_err().to_string();
    assert!(
        err.contains("room") && err.contains("keygen --aabb-scale 4"),
        "{err}"
    );
    hidden.fit_into_box(4, key.scene_box()).unwrap();
    hidden_test.fit_into_box(4, key.scene_box()).unwrap();
    assert_eq!(hidden.aabb_scale, 4);

    let cfg = model_config(4);
    let layout = NerfLayout::new(cfg).unwrap();
    let mut t = Trainer::new(
        cfg,
        vec![
            SceneSpec {
                dataset: Arc::new(cover),
                indices: reference_indices(&layout.grid),
            },
            SceneSpec {
                dataset: Arc::new(hidden),
                indices: key.level_indices(&layout.grid),
            },
        ],
        TrainConfig {
            seed: 3,
            batch_samples: 1 << 14,
            occupancy_fraction: 1.0 / 128.0,
            ..Default::default()
        },
    )
    .unwrap();
    let outside = |g: &OccupancyGrid| -> usize {
        (1..g.n_cascades as u32)
            .map(|c| {
                g.occupied_cells(c)
                    .iter()
                    .filter(|p| {
                        // Cell centre in ngp space, outside the unit cube.
                        let s = (c as f32).exp2();
                        p.iter().any(|&i| {
                            ((i as f32 + 0.5) / 128.0 - 0.5) * s + 0.5 > 1.0
                                || ((i as f32 + 0.5) / 128.0 - 0.5) * s + 0.5 < 0.0
                        })
                    })
                    .count()
            })
            .sum()
    };
    for _ in 0..100 {
        t.train_step().unwrap();
    }
    assert!(
        t.grid(0).n_cascades == 3 && outside(t.grid(0)) > 0,
        "the cover fills its box"
    );
    let model = Model::from_trainer(&t, 0.0);
    let white = RenderOptions::default();
    let score = |k: &Key| {
        let opened = open_scene(&model, Some(k), false, 0);
        let r = evaluate(
            &opened.view(&model),
            &hidden_test,
            &white,
            None,
            |_, _, _| {},
        );
        (r.psnr, r.blank_psnr, outside(opened.grid(&model)))
    };
    let (right, blank, right_out) = score(&key);
    let wrong = Key::wrong(11, &key);
    let (in_box, _, wrong_out) = score(&wrong);
    let (whole_box, _, haze) = score(&wrong.clone().with_scene_box(None).unwrap());
    eprintln!(
        "hidden with its key {right:.2} dB; wrong key in its box {in_box:.2}, over the whole box {whole_box:.2} ({haze} occupied cells outside the box); empty image {blank:.2}"
    );
    assert_eq!((right_out, wrong_out), (0, 0));
    // What the box removes: outside it a wrong key meets the cover's trained entries.
    assert!(haze > 1000, "{haze} cells");
    assert!(
        right > blank + 4.0,
        "key holder: {right:.2} dB, empty {blank:.2}"
    );
    // Measured 10.21 against 9.90 (whole box 10.55): at this size the cover's entries met
    // at random are still faint; on fox the whole box costs 4 dB (benchmarks/stego.md).
    assert!(
        (in_box - blank).abs() < 1.5,
        "wrong key in the box: {in_box:.2} dB, empty {blank:.2}"
    );
}
