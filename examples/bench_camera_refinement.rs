//! Camera refinement against cameras made wrong on purpose (issue 66's stand-in): a scene
//! trained three ways with the CPU's default recipe — on its true cameras, on perturbed
//! cameras as given, and on the perturbed cameras refined (`--refine-cameras`) — each scored
//! on the held-out views (their true cameras) at each checkpoint, with the training cameras'
//! error against the truth before and after refinement.
//!
//! cargo run --release --example bench_camera_refinement -- [SCENE] [MINUTES] [DEGREES]
//!     [SHIFT] [RES]
//! SCENE: `room` (default: the generated 360° room, aabb_scale 4, cameras inside it),
//! `object`, or a dataset folder; MINUTES: comma-separated checkpoints (default 1,2,5);
//! DEGREES: the turn's range, `lo-hi` (default 0.5-2); SHIFT: the shift's range as a share of
//! the box's side (default 0.01-0.03); RES: a generated scene's size (default 100).
//!
//! With `ONLY_REFINED=1` only the refined arm trains (the other two print empty lists).
//!
//! Output: one JSON object on stdout; progress on stderr.

use serde_json::json;
use std::path::PathBuf;
use std::sync::Arc;
use stegongp::backend::{Device, DeviceRequest};
use stegongp::dataset::LoadOptions;
use stegongp::ngp::data::{Dataset, Split};
use stegongp::ngp::encoding::reference_indices;
use stegongp::ngp::network::{ModelConfig, NerfLayout};
use stegongp::ngp::render::image::RenderOptions;
use stegongp::ngp::train::cameras::Offset;
use stegongp::score::eval::{evaluate_on, spread_views};
use stegongp::synth::{SceneKind, SynthOptions, generate};
use stegongp::training::recipe::{Budget, Recipe, StepOptions};
use testkit::cameras::{Perturbation, perturb, pose_error};

fn arg(i: usize, default: &str) -> String {
    std::env::args()
        .nth(i)
        .unwrap_or_else(|| default.to_string())
}

fn range(s: &str) -> anyhow::Result<(f32, f32)> {
    let (a, b) = s.split_once('-').unwrap_or((s, s));
    Ok((a.parse()?, b.parse()?))
}

/// What an arm gave: the PSNR at each checkpoint, the refined offsets, seconds a step.
#[derive(Default)]
struct Arm {
    psnr: Vec<f64>,
    offsets: Option<Vec<Offset>>,
    seconds_per_step: f64,
}

/// Trains `train` to the last checkpoint, scoring `test` at each.
fn arm(
    name: &str,
    device: &Device,
    train: Arc<Dataset>,
    test: &Dataset,
    minutes: &[f64],
    refine: bool,
) -> anyhow::Result<Arm> {
    let model = ModelConfig {
        aabb_scale: train.aabb_scale,
        ..Default::default()
    };
    let grid = NerfLayout::new(model)?.grid;
    let steps = StepOptions {
        refine_cameras: refine,
        ..Default::default()
    };
    let last = minutes.iter().copied().fold(0.0, f64::max);
    let recipe = Recipe::plain(model, train, steps, Budget::Seconds(last * 60.0)).check()?;
    let mut training = recipe.start(device)?;
    let which = spread_views(test.frames.len(), 8);
    let opts = RenderOptions::default();
    let mut psnrs = Vec::new();
    let mut next = 0;
    while next < minutes.len() {
        let more = training.step()?.is_some();
        let t = *training.totals();
        if t.seconds >= minutes[next] * 60.0 || !more {
            let m = training.model()?;
            let idx = reference_indices(&grid);
            let mut r = device.renderer(&m, &idx, &m.grid)?;
            let e = evaluate_on(r.as_mut(), test, &opts, Some(&which), None, |_, _, _| {})?;
            eprintln!(
                "{name}: {:.1} min, step {}, test PSNR {:.2} dB",
                t.seconds / 60.0,
                t.steps,
                e.psnr
            );
            psnrs.push(e.psnr);
            next += 1;
        }
        if !more {
            break;
        }
    }
    let t = *training.totals();
    Ok(Arm {
        psnr: psnrs,
        offsets: training.trainer().cameras().map(|c| c.offsets().to_vec()),
        seconds_per_step: t.seconds / t.steps.max(1) as f64,
    })
}

fn main() -> anyhow::Result<()> {
    let scene = arg(1, "room");
    let minutes: Vec<f64> = arg(2, "1,2,5")
        .split(',')
        .map(|m| m.trim().parse())
        .collect::<Result<_, _>>()?;
    let degrees = range(&arg(3, "0.5-2"))?;
    let shift_share = range(&arg(4, "0.01-0.03"))?;
    let res: u32 = arg(5, "100").parse()?;

    let tmp = tempfile::tempdir()?;
    let dir = match scene.as_str() {
        "room" | "object" => {
            let dir = tmp.path().join(&scene);
            let room = scene == "room";
            generate(
                &SynthOptions {
                    scene: if room {
                        SceneKind::Room
                    } else {
                        SceneKind::Object
                    },
                    resolution: res,
                    n_train: 100,
                    n_val: 0,
                    n_test: 16,
                    seed: 1,
                    aabb_scale: if room { 4 } else { 1 },
                    ..Default::default()
                },
                &dir,
            )?;
            dir
        }
        other => PathBuf::from(other),
    };
    let opts = LoadOptions::default();
    let truth = stegongp::dataset::load(&dir, Split::Train, &opts)?;
    let test = stegongp::dataset::load(&dir, Split::Test, &opts)?;
    let side = truth.aabb_scale as f32;
    let p = Perturbation {
        degrees,
        shift: (shift_share.0 * side, shift_share.1 * side),
        seed: 7,
    };
    let mut wrong = stegongp::dataset::load(&dir, Split::Train, &opts)?;
    let true_cams = perturb(&mut wrong, &p);
    let given: Vec<_> = wrong.frames.iter().map(|f| f.camera.clone()).collect();
    let before = pose_error(&true_cams, &given, None);
    let device = Device::open(DeviceRequest::Cpu)?;
    eprintln!(
        "{} training images of {}×{}, aabb {}; perturbed by {:?}° and {:?}: mean error {:.3}°, {:.4}",
        truth.frames.len(),
        truth.width,
        truth.height,
        truth.aabb_scale,
        p.degrees,
        p.shift,
        before.degrees,
        before.shift
    );
    let (n_images, size, aabb) = (truth.frames.len(), [truth.width, truth.height], side);
    let wrong = Arc::new(wrong);
    let only_refined = std::env::var("ONLY_REFINED").is_ok();
    let true_arm = match only_refined {
        true => Arm::default(),
        false => arm(
            "true cameras",
            &device,
            Arc::new(truth),
            &test,
            &minutes,
            false,
        )?,
    };
    let given_arm = match only_refined {
        true => Arm::default(),
        false => arm("perturbed", &device, wrong.clone(), &test, &minutes, false)?,
    };
    let refined = arm("perturbed, refined", &device, wrong, &test, &minutes, true)?;
    let after = pose_error(&true_cams, &given, refined.offsets.as_deref());
    eprintln!(
        "pose error: {:.3}° / {:.4} given, {:.3}° / {:.4} refined",
        before.degrees, before.shift, after.degrees, after.shift
    );
    let out = json!({
        "scene": scene,
        "images": n_images,
        "resolution": size,
        "aabb_scale": aabb,
        "perturbation": {"degrees": [p.degrees.0, p.degrees.1], "shift": [p.shift.0, p.shift.1]},
        "minutes": minutes,
        "psnr": {"true": true_arm.psnr, "perturbed": given_arm.psnr, "refined": refined.psnr},
        "seconds_per_step": {
            "true": true_arm.seconds_per_step,
            "perturbed": given_arm.seconds_per_step,
            "refined": refined.seconds_per_step,
        },
        "pose_error": {
            "given": {"degrees": before.degrees, "shift": before.shift},
            "refined": {"degrees": after.degrees, "shift": after.shift},
        },
    });
    println!("{}", serde_json::to_string_pretty(&out)?);
    Ok(())
}
