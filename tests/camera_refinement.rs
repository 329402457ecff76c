//! Camera refinement (`train --refine-cameras`, issue 66): cameras made wrong on purpose come
//! back towards the truth and the model trains better on them than on the cameras as given;
//! the command says what it refined and still writes a plain snapshot.

use std::sync::Arc;
use stegongp::ngp::data::Dataset;
use stegongp::ngp::encoding::reference_indices;
use stegongp::ngp::model::Model;
use stegongp::ngp::network::{ModelConfig, NerfLayout};
use stegongp::ngp::render::image::RenderOptions;
use stegongp::ngp::train::cameras::CameraRefinement;
use stegongp::ngp::train::{SceneSpec, TrainConfig, Trainer};
use stegongp::score::eval::evaluate;
use stegongp::synth::SceneKind;
use testkit::cameras::{Perturbation, perturb, pose_error};
use testkit::cli::{run_ok, stegongp};
use testkit::scenes::generated;

const STEPS: u32 = 250;

fn model_config() -> ModelConfig {
    let mut c = ModelConfig::default();
    c.grid.log2_hashmap_size = 16;
    c
}

/// `STEPS` steps on `train`, refining its cameras or not; the test PSNR and the trainer.
fn train(train: Arc<Dataset>, test: &Dataset, refine: bool) -> (f64, Trainer) {
    let cfg = model_config();
    let layout = NerfLayout::new(cfg).unwrap();
    let mut t = Trainer::new(
        cfg,
        vec![SceneSpec {
            dataset: train,
            indices: reference_indices(&layout.grid),
        }],
        TrainConfig {
            seed: 3,
            batch_samples: 1 << 15,
            occupancy_fraction: 1.0 / 32.0,
            ..Default::default()
        },
    )
    .unwrap();
    if refine {
        t.refine_cameras(CameraRefinement::default()).unwrap();
    }
    for _ in 0..STEPS {
        t.train_step().unwrap();
    }
    let model = Model::from_trainer(&t, 0.0);
    let indices = reference_indices(&layout.grid);
    let view = model.view(&indices, &model.grid);
    let psnr = evaluate(&view, test, &RenderOptions::default(), None, |_, _, _| {}).psnr;
    (psnr, t)
}

#[test]
fn perturbed_cameras_come_back_and_train_a_better_model() {
    let dir = tempfile::tempdir().unwrap();
    let scene = generated(dir.path(), SceneKind::Object, 48, 60, 6, 2);
    let mut wrong = scene.train;
    let truth = perturb(
        &mut wrong,
        &Perturbation {
            degrees: (1.0, 2.0),
            shift: (0.01, 0.03),
            seed: 4,
        },
    );
    let given: Vec<_> = wrong.frames.iter().map(|f| f.camera.clone()).collect();
    let before = pose_error(&truth, &given, None);
    let wrong = Arc::new(wrong);
    let (given_psnr, _) = train(wrong.clone(), &scene.test, false);
    let (refined_psnr, t) = train(wrong, &scene.test, true);
    let after = pose_error(&truth, &given, Some(t.cameras().unwrap().offsets()));
    eprintln!(
        "{STEPS} steps: perturbed {given_psnr:.2} dB, refined {refined_psnr:.2} dB; pose error {:.3}° / {:.4} given, {:.3}° / {:.4} refined",
        before.degrees, before.shift, after.degrees, after.shift
    );
    // Measured (two workers): 1.567° → 1.123°, 17.57 → 18.97 dB; the true cameras reach
    // 24.04 dB in these steps (examples/bench_camera_refinement.rs for the longer runs).
    assert!(
        after.degrees < 0.8 * before.degrees,
        "turns: {:.3}° given, {:.3}° refined",
        before.degrees,
        after.degrees
    );
    assert!(
        refined_psnr > given_psnr + 0.7,
        "refined {refined_psnr:.2} dB against {given_psnr:.2} dB as given"
    );
}

#[test]
fn train_says_what_it_refined_and_writes_a_plain_snapshot() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("obj");
    let s = scene.to_str().unwrap();
    run_ok(&[
        "synth", "--scene", "object", "--res", "32", "--train", "20", "--test", "2", "--out", s,
    ]);
    let run = |out: &str, extra: &[&str]| {
        let out = dir.path().join(out);
        let mut args = vec![
            "train",
            s,
            "--out",
            out.to_str().unwrap(),
            "--steps",
            "12",
            "--batch",
            "4096",
        ];
        args.extend_from_slice(extra);
        (stegongp(&args), std::fs::read(&out).unwrap_or_default())
    };
    let (o, refined) = run("refined.ingp", &["--refine-cameras", "--json"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let doc: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let c = &doc["cameras"];
    assert_eq!(c["images"], 20, "{doc}");
    assert_eq!(c["updates"], 12, "{doc}");
    assert!(c["mean_rotation_degrees"].as_f64().unwrap() > 0.0, "{doc}");
    let (o, plain) = run("plain.ingp", &["--json"]);
    let doc: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!(doc.get("cameras").is_none(), "{doc}");
    // The published file is a plain snapshot either way: its camera offsets are the idle
    // ones instant-ngp writes for a run that refined nothing.
    let load = |bytes: &[u8]| stegongp::ngp::snapshot::from_bytes(bytes).unwrap();
    let (refined, plain) = (load(&refined), load(&plain));
    assert!(
        refined.preserved.cam_pos_offset.is_some() && refined.preserved.cam_rot_offset.is_some()
    );
    assert_eq!(
        refined.preserved.cam_pos_offset,
        plain.preserved.cam_pos_offset
    );
    assert_eq!(
        refined.preserved.cam_rot_offset,
        plain.preserved.cam_rot_offset
    );
    let (o, _) = run("said.ingp", &["--refine-cameras"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("cameras: the cover's refined")
            && err.contains("cameras: 20 refined in 12 updates"),
        "{err}"
    );
    let (o, _) = run("default.ingp", &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("cameras: as given"), "{err}");
}
