//! `experiment detectability`: how well an analyst who holds only model files tells stego
//! models from plain ones, measured on a population instead of asserted.
//!
//! The population is paired: model pair `i` shares one generated cover (a random
//! arrangement of primitives, so the occupied region, and with it the reachable part of the
//! hashed levels, differs between covers), one hidden scene (3D text or another random
//! object), one training seed and one key. Arms: `plain` (the cover alone), `stego` (cover +
//! hidden, the default training) and optionally `stealth` (the same with stealth training).
//! Stego models cycle through the four combinations of key scheme (`prf`, `primes`) and
//! schedule (mixed batches, the paper's random scene per step), so the detector is measured
//! against every way we train. A `control` arm (plain models of the same covers, trained
//! from another seed) is scored as if it hid something: what the statistics and the
//! detector make of it is chance at this population's size, the floor against which the
//! other arms read (with 53 statistics on 20 + 20 models the largest AUC of two plain arms
//! is about 0.7, so no arm can show every statistic at 0.5).
//!
//! Every model is saved as an `.ingp` and analysed from the file alone
//! ([`stego::steganalysis::analyse_file`]). Per statistic the report gives the ROC AUC of
//! the statistic itself over all models; the combined detector (a logistic regression,
//! [`Detector`]) is fitted on the first half of the pairs and scored on the other half, so
//! its AUC is measured on covers it never saw.
//!
//! Models are written under `OUT/models/` with a sidecar JSON holding the configuration
//! they were trained with and their scores; a rerun reuses every model whose sidecar
//! matches, so an interrupted run resumes.

use super::jobs::{Action, PlannedModel};
use super::report::{Report, Table};
use super::setup::{ExpConfig, Experiment, train_pair};
use super::store::{read_stored, reuse_or_train};
use ngp::data::save_png_rgb;
use ngp::error::{Error, Result};
use ngp::rng::Pcg32;
use ngp::train::Schedule;
use ngp::util::write_atomic;
use serde_json::{Value, json};
use std::path::{Path, PathBuf};
use std::time::Instant;
use stego::SchemeKind;
use stego::stealth::StealthOptions;
use stego::steganalysis::{
    Detector, analyse_file, auc_p_value, directed_auc_p_value, feature_matrix, roc_auc,
};
use synth::scene::{Material, Object, Scene, Shape, V3, text_scene};
use synth::{CAMERA_ANGLE_X, CAMERA_RADIUS, layout_text, look_at, render_view};
use training::recipe::HiddenOptions;

/// What the detectability experiment adds to [`ExpConfig`].
#[derive(Clone, Debug)]
pub struct DetectOptions {
    /// Models per arm (pairs of cover and hidden scene).
    pub models: usize,
    /// Train the stealth arm as well.
    pub stealth_arm: bool,
    /// Width and height of the generated scenes' views.
    pub res: u32,
    pub n_train_views: usize,
    pub n_test_views: usize,
    /// Train the control arm (plain models from another seed) as well.
    pub control_arm: bool,
}

impl Default for DetectOptions {
    fn default() -> Self {
        DetectOptions {
            models: 20,
            stealth_arm: true,
            res: 32,
            n_train_views: 40,
            n_test_views: 8,
            control_arm: true,
        }
    }
}

/// Bump when a change makes earlier model files no longer what this code would train.
const MODEL_FORMAT: u32 = 1;
/// Bump when stealth training changes (the stealth arm alone is trained again).
const STEALTH_FORMAT: u32 = 5;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Arm {
    Plain,
    Stego,
    Stealth,
    /// Plain models of the same covers from another training seed: the null hypothesis.
    Control,
}

impl Arm {
    fn name(self) -> &'static str {
        match self {
            Arm::Plain => "plain",
            Arm::Stego => "stego",
            Arm::Stealth => "stealth",
            Arm::Control => "control",
        }
    }

    fn hides(self) -> bool {
        matches!(self, Arm::Stego | Arm::Stealth)
    }

    /// The training seed of this arm's model of pair `pair_seed`: the control arm's differs
    /// from the plain model's (same scenes, another initialisation and sample order).
    fn training_seed(self, pair_seed: u64) -> u64 {
        match self {
            Arm::Control => pair_seed ^ 0xc0_17_c0_17,
            _ => pair_seed,
        }
    }
}

/// Pair `i`'s key scheme and schedule: consecutive pairs cover all four combinations, so
/// both halves of the population (fit and scored) hold every one.
fn combination(i: usize) -> (SchemeKind, Schedule) {
    let scheme = if i.is_multiple_of(2) {
        SchemeKind::Prf
    } else {
        SchemeKind::Primes
    };
    let schedule = if (i / 2).is_multiple_of(2) {
        Schedule::Mixed
    } else {
        Schedule::RandomScene
    };
    (scheme, schedule)
}

/// Pair `i`'s seed: scenes, training and key all follow from it.
fn pair_seed(seed: u64, i: usize) -> u64 {
    seed.wrapping_mul(1_000_003).wrapping_add(i as u64)
}

/// One trained (or reused) model.
struct ModelRecord {
    arm: Arm,
    index: usize,
    scheme: Option<SchemeKind>,
    schedule: Schedule,
    hidden_kind: String,
    cover_psnr: f64,
    hidden_psnr: Option<f64>,
    /// LPIPS (None when not scored: `--no-lpips`, or a model trained before LPIPS existed).
    cover_lpips: Option<f64>,
    hidden_lpips: Option<f64>,
    train_s: f64,
    eval_s: f64,
    analyse_s: f64,
    features: Vec<(String, f64)>,
}

// ---------------------------------------------------------------------------------------
// Generated scenes

fn uni(rng: &mut Pcg32, lo: f32, hi: f32) -> f32 {
    lo + (hi - lo) * rng.next_f32()
}

fn colour(rng: &mut Pcg32) -> V3 {
    [
        uni(rng, 0.1, 0.95),
        uni(rng, 0.1, 0.95),
        uni(rng, 0.1, 0.95),
    ]
}

fn material(rng: &mut Pcg32) -> Material {
    match rng.below(5) {
        0 => Material::Solid(colour(rng)),
        1 => Material::Checker(colour(rng), colour(rng), uni(rng, 0.06, 0.2)),
        2 => Material::HueStripes(uni(rng, 1.0, 4.0)),
        3 => Material::Helix,
        _ => Material::Grid(colour(rng), colour(rng), uni(rng, 0.08, 0.2)),
    }
}

/// A random tabletop: a platform and 3–6 primitives standing on it, inside the unit box's
/// scene (|x|, |y| ≤ 1.2, −0.75 ≤ z ≤ 0.7, where the fixed object scene lives too). Covers
/// that differ in where they are occupied give the statistics their natural spread; one
/// fixed cover would make every plain model alike and the detector's task artificially easy.
fn random_object_scene(seed: u64) -> Scene {
    let mut rng = Pcg32::new(seed, 0x0b1e);
    const TOP: f32 = -0.62;
    let pr = uni(&mut rng, 0.8, 1.15);
    let mut objs = vec![Object {
        shape: if rng.below(2) == 0 {
            Shape::Cylinder {
                c: [0.0, 0.0, 0.0],
                r: pr,
                z0: -0.75,
                z1: TOP,
            }
        } else {
            let h = pr * 0.85;
            Shape::Box {
                lo: [-h, -h, -0.75],
                hi: [h, h, TOP],
            }
        },
        material: Material::Checker(colour(&mut rng), colour(&mut rng), uni(&mut rng, 0.12, 0.3)),
        specular: 0.0,
    }];
    let n = 3 + rng.below(4) as usize;
    for _ in 0..n {
        let a = uni(&mut rng, 0.0, std::f32::consts::TAU);
        let d = 0.7 * pr * rng.next_f32().sqrt();
        let (x, y) = (d * a.cos(), d * a.sin());
        let shape = match rng.below(3) {
            0 => {
                let r = uni(&mut rng, 0.12, 0.4);
                Shape::Sphere {
                    c: [x, y, TOP + r * uni(&mut rng, 0.6, 1.0)],
                    r,
                }
            }
            1 => {
                let (hx, hy) = (uni(&mut rng, 0.08, 0.3), uni(&mut rng, 0.08, 0.3));
                let h = uni(&mut rng, 0.1, 0.7);
                Shape::Box {
                    lo: [x - hx, y - hy, TOP],
                    hi: [x + hx, y + hy, TOP + h],
                }
            }
            _ => Shape::Cylinder {
                c: [x, y, 0.0],
                r: uni(&mut rng, 0.08, 0.25),
                z0: TOP,
                z1: TOP + uni(&mut rng, 0.2, 1.2),
            },
        };
        let m = material(&mut rng);
        let specular = if rng.below(2) == 0 {
            0.0
        } else {
            uni(&mut rng, 0.3, 0.8)
        };
        objs.push(Object {
            shape,
            material: m,
            specular,
        });
    }
    let light = [
        uni(&mut rng, -1.0, 1.0),
        uni(&mut rng, -1.0, 1.0),
        uni(&mut rng, 0.5, 1.0),
    ];
    Scene::new(objs, light)
}

const WORDS: [&str; 10] = [
    "SECRET", "HIDDEN", "KEY", "STEGO", "NERF", "VAULT", "ECHO", "NOTE", "CIPHER", "MAP",
];

/// Pair `i`'s hidden scene: 3D text or another random tabletop (hidden scenes need not be
/// text, and the two occupy the box very differently), alternating out of step with the key
/// scheme so that, every 8 pairs, each scheme and schedule hides both kinds.
fn hidden_scene(seed: u64, i: usize) -> Result<(Scene, String)> {
    if (i + i / 4).is_multiple_of(2) {
        let mut rng = Pcg32::new(seed, 0x7e47);
        let msg = format!("{} {}", WORDS[rng.below(WORDS.len() as u32) as usize], i);
        Ok((text_scene(&layout_text(&msg)?), format!("text {msg:?}")))
    } else {
        Ok((random_object_scene(seed ^ 0x5eed_0b1e), "object".into()))
    }
}

/// Camera-to-world poses as `synth` places them: train views uniform over the cap between
/// 8° and 80° of elevation, test views rings at 30°, 15° and 50°.
fn poses(n: usize, train: bool, seed: u64) -> Vec<[[f32; 4]; 4]> {
    let mut rng = Pcg32::new(seed, if train { 1 } else { 3 });
    let at = |az: f32, el: f32| {
        look_at([
            CAMERA_RADIUS * el.cos() * az.cos(),
            CAMERA_RADIUS * el.cos() * az.sin(),
            CAMERA_RADIUS * el.sin(),
        ])
    };
    (0..n)
        .map(|i| {
            if train {
                let (lo, hi) = (8f32.to_radians().sin(), 80f32.to_radians().sin());
                let z = lo + rng.next_f32() * (hi - lo);
                at(rng.next_f32() * std::f32::consts::TAU, z.asin())
            } else {
                let el = [30.0f32, 15.0, 50.0][i % 3].to_radians();
                at(i as f32 / n as f32 * std::f32::consts::TAU, el)
            }
        })
        .collect()
}

fn encode_rgba_png(path: &Path, res: u32, rgba: &[u8]) -> Result<()> {
    let bytes = ngp::data::png_bytes(res, res, 4, rgba, false)
        .map_err(|e| Error::format(path, e.to_string()))?;
    write_atomic(path, &bytes)
}

/// Writes `scene` as a NeRF-synthetic dataset (train and test splits) unless it is there:
/// images first, the JSON files last, so an interrupted run never looks complete.
fn write_dataset(scene: &Scene, dir: &Path, opts: &DetectOptions, seed: u64) -> Result<()> {
    if dir.join("transforms_test.json").exists() && dir.join("transforms_train.json").exists() {
        return Ok(());
    }
    for (split, n, train) in [
        ("train", opts.n_train_views, true),
        ("test", opts.n_test_views, false),
    ] {
        let sub = dir.join(split);
        std::fs::create_dir_all(&sub).map_err(|e| Error::io(&sub, e))?;
        let ps = poses(n, train, seed);
        let mut frames = Vec::new();
        for (k, p) in ps.iter().enumerate() {
            let rgba = render_view(scene, p, opts.res);
            encode_rgba_png(&sub.join(format!("r_{k}.png")), opts.res, &rgba)?;
            frames.push(json!({"file_path": format!("./{split}/r_{k}"), "transform_matrix": p}));
        }
        let doc = json!({"camera_angle_x": CAMERA_ANGLE_X, "frames": frames});
        let text = serde_json::to_string_pretty(&doc).map_err(|e| Error::Other(e.to_string()))?;
        write_atomic(
            &dir.join(format!("transforms_{split}.json")),
            text.as_bytes(),
        )?;
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------
// Training, resumable

/// Everything a model file depends on: a sidecar with the same value means the file is
/// what this run would train.
fn model_config(
    cfg: &ExpConfig,
    arm: Arm,
    scenes: (&Path, &Path),
    seed: u64,
    combo: (SchemeKind, Schedule),
) -> Value {
    let g = &cfg.grid;
    // Relative to the output folder, so a moved folder still resumes.
    let rel = |p: &Path| p.strip_prefix(&cfg.out).unwrap_or(p).to_path_buf();
    let mut v = json!({
        "format": MODEL_FORMAT, "arm": arm.name(), "cover": rel(scenes.0),
        "hidden": if arm.hides() { json!(rel(scenes.1)) } else { Value::Null },
        "seed": seed, "scheme": if arm.hides() { json!(combo.0.name()) } else { Value::Null },
        "schedule": if arm.hides() { json!(combo.1.name()) } else { Value::Null },
        // A string: serde_json's float parsing does not round-trip every f64 exactly, and a
        // sidecar must compare equal to what wrote it.
        "steps": cfg.steps, "batch": cfg.batch, "occupancy_fraction": cfg.occupancy_fraction.to_string(),
        "levels": g.n_levels, "features": g.n_features, "log2_t": g.log2_hashmap_size,
        "base_resolution": g.base_resolution, "eval_views": cfg.eval_views,
        "downscale": cfg.downscale, "hidden_downscale": cfg.hidden_downscale,
    });
    if arm.hides() {
        cfg.record_hidden_options(&mut v);
    }
    if arm == Arm::Stealth {
        // Only this arm's key, so that plain and default stego files stay reusable.
        v["stealth"] = json!(STEALTH_FORMAT);
        cfg.record_density_cap(&mut v);
        if cfg.training.stealth.cover_only_mlp {
            v["cover_only_mlp"] = json!(true);
        }
    }
    v
}

/// Trains (or reuses) one model and analyses its file, as the run's
/// [`JobMode`](crate::JobMode) says: `None` where this run scores nothing, or where a
/// partial report lacks the model.
fn model(
    cfg: &ExpConfig,
    arm: Arm,
    i: usize,
    scenes: (&Path, &Path),
    hidden_kind: &str,
    models_dir: &Path,
) -> Result<Option<ModelRecord>> {
    let seed = arm.training_seed(pair_seed(cfg.seed, i));
    let combo = combination(i);
    let config = model_config(cfg, arm, scenes, seed, combo);
    let stem = format!("{}_{i:02}", arm.name());
    let path = models_dir.join(format!("{stem}.ingp"));
    let n_scenes = if arm.hides() { 2 } else { 1 };
    let planned = PlannedModel {
        id: format!("detectability-{stem}"),
        label: format!("{} model of pair {i}", arm.name()),
        output: path.clone(),
        inputs: if arm.hides() {
            vec![scenes.0.to_path_buf(), scenes.1.to_path_buf()]
        } else {
            vec![scenes.0.to_path_buf()]
        },
        after: Vec::new(),
        steps: Some(cfg.steps as u64 * n_scenes),
        samples: Some(cfg.steps as u64 * n_scenes * cfg.batch as u64),
        seconds: None,
    };
    let id = planned.id.clone();
    let info = match cfg.jobs.action(planned) {
        Action::Train => Some(train_model(cfg, arm, i, scenes, &path, &config)?),
        Action::PassOver => None,
        Action::Read => {
            let v = read_stored(&path, &config);
            if v.is_none() {
                cfg.jobs.missing(&id, &path)?;
            }
            v
        }
    };
    let Some(info) = info.filter(|_| cfg.jobs.scores()) else {
        return Ok(None);
    };
    let t0 = Instant::now();
    let analysis = analyse_file(&path)?;
    let features = analysis.features();
    Ok(Some(ModelRecord {
        arm,
        index: i,
        scheme: arm.hides().then_some(combo.0),
        schedule: combo.1,
        hidden_kind: hidden_kind.into(),
        cover_psnr: info["cover_psnr"].as_f64().unwrap_or(f64::NAN),
        hidden_psnr: info["hidden_psnr"].as_f64(),
        cover_lpips: info["cover_lpips"].as_f64(),
        hidden_lpips: info["hidden_lpips"].as_f64(),
        train_s: info["train_s"].as_f64().unwrap_or(f64::NAN),
        eval_s: info["eval_s"].as_f64().unwrap_or(f64::NAN),
        analyse_s: t0.elapsed().as_secs_f64(),
        features,
    }))
}

/// Trains (or reuses) the model of `arm` on pair `i` and records its scores beside it.
fn train_model(
    cfg: &ExpConfig,
    arm: Arm,
    i: usize,
    scenes: (&Path, &Path),
    path: &Path,
    config: &Value,
) -> Result<Value> {
    let seed = arm.training_seed(pair_seed(cfg.seed, i));
    let combo = combination(i);
    let stem = format!("{}_{i:02}", arm.name());
    let (info, _) = reuse_or_train(path, config, cfg.verbose, cfg.save_every, |state| {
        let mcfg = ExpConfig {
            cover: scenes.0.to_path_buf(),
            hidden: vec![scenes.1.to_path_buf()],
            seed,
            scheme: combo.0,
            training: HiddenOptions {
                schedule: if arm.hides() {
                    combo.1
                } else {
                    Schedule::Mixed
                },
                stealth: StealthOptions {
                    enabled: arm == Arm::Stealth,
                    ..cfg.training.stealth
                },
                ..cfg.training
            },
            ..cfg.clone()
        };
        // Key number i under the pair's seed: stego and stealth pair i share their key.
        let key = arm.hides().then_some(i as u64);
        let run = train_pair(&mcfg, key, &stem, state)?;
        let fields = json!({
            "train_s": run.train_seconds, "eval_s": run.eval_seconds,
            "cover_psnr": run.cover.psnr,
            "hidden_psnr": run.hidden.as_ref().map(|h| h.psnr),
            "cover_lpips": run.cover.lpips,
            "hidden_lpips": run.hidden.as_ref().and_then(|h| h.lpips),
        });
        Ok((run.model, fields.as_object().cloned().unwrap_or_default()))
    })?;
    Ok(info)
}

// ---------------------------------------------------------------------------------------
// Statistics

/// ROC curve of scores where higher means positive: (false positive rate, true positive
/// rate) from (0, 0) to (1, 1), tied scores taken together (a diagonal step).
pub fn roc_points(pos: &[f64], neg: &[f64]) -> Vec<(f64, f64)> {
    let mut all: Vec<(f64, bool)> = pos
        .iter()
        .map(|&s| (s, true))
        .chain(neg.iter().map(|&s| (s, false)))
        .collect();
    all.sort_by(|a, b| b.0.total_cmp(&a.0));
    let (np, nn) = (pos.len().max(1) as f64, neg.len().max(1) as f64);
    let (mut tp, mut fp) = (0usize, 0usize);
    let mut out = vec![(0.0, 0.0)];
    let mut k = 0;
    while k < all.len() {
        let mut j = k;
        while j < all.len() && all[j].0 == all[k].0 {
            if all[j].1 {
                tp += 1;
            } else {
                fp += 1;
            }
            j += 1;
        }
        out.push((fp as f64 / nn, tp as f64 / np));
        k = j;
    }
    out
}

/// AUC of one statistic with the direction an analyst would pick from the data:
/// (max(AUC, 1 − AUC), true if larger values mean stego, the two-sided p-value of that
/// AUC). NaN values are left out.
fn directed_auc(pos: &[f64], neg: &[f64]) -> (f64, bool, f64) {
    let p: Vec<f64> = pos.iter().copied().filter(|v| v.is_finite()).collect();
    let n: Vec<f64> = neg.iter().copied().filter(|v| v.is_finite()).collect();
    let auc = roc_auc(&p, &n);
    if auc.is_nan() {
        return (f64::NAN, true, f64::NAN);
    }
    let (auc, up) = if auc >= 0.5 {
        (auc, true)
    } else {
        (1.0 - auc, false)
    };
    (auc, up, directed_auc_p_value(auc, p.len(), n.len()))
}

fn mean(v: impl IntoIterator<Item = f64>) -> f64 {
    let (mut s, mut n) = (0.0, 0usize);
    for x in v {
        if x.is_finite() {
            s += x;
            n += 1;
        }
    }
    if n == 0 { f64::NAN } else { s / n as f64 }
}

/// JSON for a number that may be NaN (JSON has none: null).
fn num(x: f64) -> Value {
    if x.is_finite() { json!(x) } else { Value::Null }
}

/// Which half of the pairs a combined detector is fitted on; it is scored on the other.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Fold {
    /// Pairs `0..n_fit`: the detector the report draws and saves.
    First,
    /// Pairs `n_fit..`: with [`Fold::First`], every model is scored once by a detector that
    /// never saw it (cross-fitting), twice the held-out models of one fold.
    Second,
}

impl Fold {
    fn fits(self, pair: usize, n_fit: usize) -> bool {
        (pair < n_fit) == (self == Fold::First)
    }
}

/// A combined detector for plain vs `arm`, fitted on one fold and scored on the other.
struct Combined {
    detector: Detector,
    /// Held-out scores: (stego models, plain models).
    held_out: (Vec<f64>, Vec<f64>),
    auc: f64,
}

fn fit_combined(models: &[ModelRecord], arm: Arm, n_fit: usize, fold: Fold) -> Result<Combined> {
    let fit: Vec<&ModelRecord> = models
        .iter()
        .filter(|m| fold.fits(m.index, n_fit) && (m.arm == Arm::Plain || m.arm == arm))
        .collect();
    let samples: Vec<Vec<(String, f64)>> = fit.iter().map(|m| m.features.clone()).collect();
    let (names, rows) = feature_matrix(&samples);
    let labels: Vec<bool> = fit.iter().map(|m| m.arm == arm).collect();
    let mut detector = Detector::fit(&names, &rows, &labels)?;
    let pairs = match fold {
        Fold::First => format!("0..{n_fit}"),
        Fold::Second => format!("{n_fit}.."),
    };
    detector.fitted_on = format!(
        "{} plain and {} {} models (pairs {pairs}) of the detectability experiment",
        labels.iter().filter(|l| !**l).count(),
        labels.iter().filter(|l| **l).count(),
        arm.name()
    );
    let held_out = score_held_out(&detector, models, arm, n_fit, fold);
    let auc = roc_auc(&held_out.0, &held_out.1);
    Ok(Combined {
        detector,
        held_out,
        auc,
    })
}

fn score_held_out(
    d: &Detector,
    models: &[ModelRecord],
    arm: Arm,
    n_fit: usize,
    fitted_on: Fold,
) -> (Vec<f64>, Vec<f64>) {
    let scores = |a: Arm| {
        models
            .iter()
            .filter(|m| !fitted_on.fits(m.index, n_fit) && m.arm == a)
            .map(|m| d.score(&m.features))
            .collect::<Vec<f64>>()
    };
    (scores(arm), scores(Arm::Plain))
}

// ---------------------------------------------------------------------------------------
// The ROC figure

const PLOT: u32 = 400;
const MARGIN: u32 = 24;

/// Curve colours, in the order the report's legend lists them.
const COLOURS: [(&str, [f32; 3]); 7] = [
    ("red", [0.85, 0.1, 0.1]),
    ("blue", [0.1, 0.25, 0.9]),
    ("orange", [1.0, 0.6, 0.0]),
    ("cyan", [0.0, 0.75, 0.8]),
    ("green", [0.1, 0.6, 0.15]),
    ("magenta", [0.8, 0.1, 0.75]),
    ("brown", [0.5, 0.3, 0.1]),
];

struct Canvas {
    w: u32,
    h: u32,
    rgb: Vec<f32>,
}

impl Canvas {
    fn new(w: u32, h: u32) -> Self {
        Canvas {
            w,
            h,
            rgb: vec![1.0; (w * h * 3) as usize],
        }
    }

    fn dot(&mut self, x: f64, y: f64, r: f64, c: [f32; 3]) {
        let (x0, x1) = ((x - r).floor().max(0.0) as u32, (x + r).ceil() as u32);
        let (y0, y1) = ((y - r).floor().max(0.0) as u32, (y + r).ceil() as u32);
        for py in y0..=y1.min(self.h - 1) {
            for px in x0..=x1.min(self.w - 1) {
                let (dx, dy) = (px as f64 - x, py as f64 - y);
                if dx * dx + dy * dy <= r * r {
                    let k = ((py * self.w + px) * 3) as usize;
                    self.rgb[k..k + 3].copy_from_slice(&c);
                }
            }
        }
    }

    /// A line of radius `r`; `dash` > 0 draws only every other `dash` pixels of it.
    fn line(&mut self, a: (f64, f64), b: (f64, f64), r: f64, c: [f32; 3], dash: f64) {
        let len = ((b.0 - a.0).powi(2) + (b.1 - a.1).powi(2)).sqrt();
        let n = (len * 2.0).ceil().max(1.0) as usize;
        for k in 0..=n {
            let t = k as f64 / n as f64;
            if dash > 0.0 && ((t * len / dash) as u64) % 2 == 1 {
                continue;
            }
            self.dot(a.0 + t * (b.0 - a.0), a.1 + t * (b.1 - a.1), r, c);
        }
    }
}

/// Plot coordinates of a (false positive rate, true positive rate) point.
fn px(p: (f64, f64)) -> (f64, f64) {
    let s = (PLOT - 1) as f64;
    (MARGIN as f64 + p.0 * s, MARGIN as f64 + (1.0 - p.1) * s)
}

/// Draws ROC curves: light grid every 0.1, axes box, dashed chance diagonal, one coloured
/// curve each (colours from [`COLOURS`], in order; at most as many curves as colours). No
/// text: the legend is the report's.
fn draw_roc(path: &Path, curves: &[Vec<(f64, f64)>]) -> Result<()> {
    let size = PLOT + 2 * MARGIN;
    let mut c = Canvas::new(size, size);
    for k in 1..10 {
        let t = k as f64 / 10.0;
        c.line(px((t, 0.0)), px((t, 1.0)), 0.5, [0.88; 3], 0.0);
        c.line(px((0.0, t)), px((1.0, t)), 0.5, [0.88; 3], 0.0);
    }
    c.line(px((0.0, 0.0)), px((1.0, 1.0)), 1.0, [0.55; 3], 6.0);
    let corners = [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0), (0.0, 0.0)];
    for w in corners.windows(2) {
        c.line(px(w[0]), px(w[1]), 1.0, [0.0; 3], 0.0);
    }
    // Ticks every 0.25 outside the box, so the scale reads without labels.
    for k in 0..=4 {
        let t = k as f64 / 4.0;
        let (x, y0) = px((t, 0.0));
        c.line((x, y0), (x, y0 + 6.0), 1.0, [0.0; 3], 0.0);
        let (x0, y) = px((0.0, t));
        c.line((x0 - 6.0, y), (x0, y), 1.0, [0.0; 3], 0.0);
    }
    // Over the box, each curve thinner than the one before: curves that coincide (every
    // perfect detector runs up the left edge and along the top) still all show, as stripes.
    let n = curves.len().min(COLOURS.len());
    for (k, (curve, (_, col))) in curves.iter().zip(COLOURS).enumerate() {
        let r = 1.2 + 0.7 * (n - 1 - k) as f64;
        for w in curve.windows(2) {
            c.line(px(w[0]), px(w[1]), r, col, 0.0);
        }
    }
    save_png_rgb(path, size, size, &c.rgb)
}

// ---------------------------------------------------------------------------------------
// The experiment

/// Runs the experiment into `cfg.out` (scenes under `scenes/`, models under `models/`,
/// `report.md`, `report.json`, `features.json`, `roc.png`, the fitted detectors).
/// `cfg.cover`, `cfg.hidden`, `cfg.scheme`, `cfg.schedule` and `cfg.stealth` are not used:
/// the experiment generates its scenes and cycles through the schemes and schedules itself.
pub fn run_detectability(cfg: &ExpConfig, opts: &DetectOptions) -> Result<Report> {
    check_options(opts)?;
    let out = &cfg.out;
    let models_dir = out.join("models");
    std::fs::create_dir_all(&models_dir).map_err(|e| Error::io(&models_dir, e))?;
    let arms = arms(opts);
    let t_all = Instant::now();
    let models = train_population(cfg, opts, &arms, &models_dir)?;
    if !cfg.jobs.scores() {
        return Ok(Report::default());
    }
    let wall = t_all.elapsed().as_secs_f64();
    let pop = Population::new(arms, models, opts.models.div_ceil(2));
    let mut report = Report {
        name: Experiment::Detectability.to_string(),
        setup: setup(cfg, opts, &pop),
        ..Default::default()
    };
    report.tables.push(fidelity_table(&pop));
    let stats = per_statistic(&pop);
    let control_max = stats.control_max(&pop.arms);
    let summary = summary_table(&pop, &stats, control_max);
    // Writes detector_<arm>.json; a detector that cannot be fitted is a note, not an error.
    let detectors = combined_detectors(out, &pop, opts.stealth_arm, &mut report.notes)?;
    let (curves, legend) = roc_curves(&pop, &stats, &detectors);
    let stego_detector = detectors.stego();
    let per_model = per_model_table(&pop, stego_detector);
    report
        .notes
        .extend(closing_notes(opts, &pop, control_max, stego_detector));
    // The report's order: fidelity (above), detectors, arms, statistics, models.
    report.tables.push(detectors.table);
    report.tables.push(summary);
    report.tables.push(stats.table);
    report.tables.push(per_model);
    report.figures.push(roc_figure(out, &curves, &legend)?);
    report.run_notes.push(timing_note(&pop, wall));
    write_features(out, &pop.models)?;
    report.missing_jobs = cfg.jobs.missing_jobs();
    report.write(out)?;
    Ok(report)
}

fn check_options(opts: &DetectOptions) -> Result<()> {
    if opts.models < 2 {
        return Err(Error::Config(format!(
            "detectability needs at least 2 models per arm (one to fit the detector on, one to score), got {}",
            opts.models
        )));
    }
    if opts.n_train_views == 0 || opts.n_test_views == 0 {
        return Err(Error::Config(
            "detectability needs train and test views".into(),
        ));
    }
    Ok(())
}

/// The arms `opts` asks for, plain first: every comparison is plain against another arm.
fn arms(opts: &DetectOptions) -> Vec<Arm> {
    let mut arms = vec![Arm::Plain, Arm::Stego];
    if opts.stealth_arm {
        arms.push(Arm::Stealth);
    }
    if opts.control_arm {
        arms.push(Arm::Control);
    }
    arms
}

/// Generates every pair's scenes and trains (or reuses) each arm's model of it, pair by
/// pair.
fn train_population(
    cfg: &ExpConfig,
    opts: &DetectOptions,
    arms: &[Arm],
    models_dir: &Path,
) -> Result<Vec<ModelRecord>> {
    let scenes_dir = cfg.out.join("scenes").join(format!(
        "s{}_r{}_v{}-{}",
        cfg.seed, opts.res, opts.n_train_views, opts.n_test_views
    ));
    let mut models: Vec<ModelRecord> = Vec::new();
    for i in 0..opts.models {
        let seed = pair_seed(cfg.seed, i);
        let cover_dir: PathBuf = scenes_dir.join(format!("cover_{i:02}"));
        let hidden_dir: PathBuf = scenes_dir.join(format!("hidden_{i:02}"));
        write_dataset(&random_object_scene(seed), &cover_dir, opts, seed)?;
        let (hs, hidden_kind) = hidden_scene(seed, i)?;
        write_dataset(&hs, &hidden_dir, opts, seed ^ 0x4d)?;
        if cfg.verbose {
            let (s, sc) = combination(i);
            eprintln!(
                "detectability: pair {}/{} ({} key, {} schedule, hidden {hidden_kind})",
                i + 1,
                opts.models,
                s.name(),
                sc.name()
            );
        }
        for &arm in arms {
            let scenes = (cover_dir.as_path(), hidden_dir.as_path());
            models.extend(model(cfg, arm, i, scenes, &hidden_kind, models_dir)?);
        }
    }
    Ok(models)
}

/// The scored population: its models and their statistics as one matrix.
struct Population {
    arms: Vec<Arm>,
    models: Vec<ModelRecord>,
    /// Pairs `0..n_fit` fit the reported detectors; the rest score them.
    n_fit: usize,
    /// The statistics' names, and per model (in `models`' order) its value of each.
    names: Vec<String>,
    rows: Vec<Vec<f64>>,
}

impl Population {
    fn new(arms: Vec<Arm>, models: Vec<ModelRecord>, n_fit: usize) -> Self {
        let samples: Vec<Vec<(String, f64)>> = models.iter().map(|m| m.features.clone()).collect();
        let (names, rows) = feature_matrix(&samples);
        Population {
            arms,
            models,
            n_fit,
            names,
            rows,
        }
    }

    /// The models of arm `a`.
    fn of(&self, a: Arm) -> impl Iterator<Item = &ModelRecord> {
        self.models.iter().filter(move |m| m.arm == a)
    }

    /// Statistic `j` over the models of arm `a`.
    fn column(&self, j: usize, a: Arm) -> Vec<f64> {
        self.models
            .iter()
            .zip(&self.rows)
            .filter(|(m, _)| m.arm == a)
            .map(|(_, r)| r[j])
            .collect()
    }
}

fn setup(cfg: &ExpConfig, opts: &DetectOptions, pop: &Population) -> Value {
    json!({
        "models_per_arm": opts.models, "stealth_mlp": if cfg.training.stealth.cover_only_mlp { "the cover's alone" } else { "shared" }, "hidden_from_step": cfg.training.hidden_from, "hidden_loss_weight": cfg.training.hidden_weight, "density_cap": cfg.training.stealth.density_cap, "arms": pop.arms.iter().map(|a| a.name()).collect::<Vec<_>>(),
        "scene_res": opts.res, "train_views": opts.n_train_views, "test_views": opts.n_test_views,
        "steps": cfg.steps, "batch_samples_per_scene": cfg.batch, "seed": cfg.seed,
        "eval_views": cfg.eval_views, "occupancy_fraction": cfg.occupancy_fraction,
        "levels": cfg.grid.n_levels, "features": cfg.grid.n_features,
        "log2_hashmap_size": cfg.grid.log2_hashmap_size,
        "combinations": "pair i: key prf if i even else primes; schedule mixed if (i/2) even else random-scene",
        "detector": "logistic regression on standardised features (L2 = 1, Newton/IRLS)",
        "fit_pairs": pop.n_fit, "scored_pairs": opts.models - pop.n_fit,
    })
}

/// Fidelity per arm: what the stego and stealth models cost the scenes.
fn fidelity_table(pop: &Population) -> Table {
    let mut fid = Table::new(
        "Fidelity per arm: mean PSNR (dB) and LPIPS on held-out views, the cover without a key and the hidden scene with its key",
    );
    for &a in &pop.arms {
        let mut row = json!({
            "arm": a.name(), "models": pop.of(a).count(),
            "cover_psnr": num(mean(pop.of(a).map(|m| m.cover_psnr))),
            "cover_lpips": num(mean(pop.of(a).filter_map(|m| m.cover_lpips))),
        });
        if a.hides() {
            row["hidden_psnr"] = num(mean(pop.of(a).filter_map(|m| m.hidden_psnr)));
            row["hidden_lpips"] = num(mean(pop.of(a).filter_map(|m| m.hidden_lpips)));
        }
        fid.push(row);
    }
    fid
}

/// Every statistic on its own, plain against each other arm over all models.
struct StatScan {
    /// One row per statistic.
    table: Table,
    /// Per arm (as `Population::arms`): the largest AUC, its statistic and whether it is
    /// higher in the arm; NaN where no statistic has an AUC (always so for plain).
    best: Vec<(f64, usize, bool)>,
    /// Per arm: (AUC, p, statistic) of every statistic defined on both sides.
    per_arm: Vec<Vec<(f64, f64, usize)>>,
}

impl StatScan {
    /// The control arm's largest AUC: what chance gives the largest of this many statistics
    /// on this many models.
    fn control_max(&self, arms: &[Arm]) -> Option<f64> {
        arms.iter()
            .position(|&a| a == Arm::Control)
            .map(|k| self.best[k].0)
            .filter(|c| c.is_finite())
    }
}

fn direction(up: bool) -> &'static str {
    if up {
        "higher in stego"
    } else {
        "lower in stego"
    }
}

/// Per statistic, over all models of each arm.
fn per_statistic(pop: &Population) -> StatScan {
    let arms = &pop.arms;
    let mut table = Table::new(
        "Per statistic: ROC AUC of plain vs each arm over all models, as max(AUC, 1 − AUC) with the direction that gives it",
    );
    let mut best: Vec<(f64, usize, bool)> = vec![(f64::NAN, 0, true); arms.len()];
    let mut per_arm: Vec<Vec<(f64, f64, usize)>> = vec![Vec::new(); arms.len()];
    for (j, name) in pop.names.iter().enumerate() {
        let plain = pop.column(j, Arm::Plain);
        let mut row = serde_json::Map::new();
        row.insert("statistic".into(), json!(name));
        row.insert("plain_mean".into(), num(mean(plain.iter().copied())));
        for (k, &a) in arms.iter().enumerate().skip(1) {
            let vals = pop.column(j, a);
            let (auc, up, p) = directed_auc(&vals, &plain);
            row.insert(
                format!("{}_mean", a.name()),
                num(mean(vals.iter().copied())),
            );
            row.insert(format!("{}_auc", a.name()), num(auc));
            row.insert(format!("{}_p", a.name()), num(p));
            if auc.is_finite() {
                per_arm[k].push((auc, p, j));
            }
            row.insert(format!("{}_direction", a.name()), json!(direction(up)));
            if auc.is_finite() && (best[k].0.is_nan() || auc > best[k].0) {
                best[k] = (auc, j, up);
            }
        }
        table.push(Value::Object(row));
    }
    StatScan {
        table,
        best,
        per_arm,
    }
}

/// Per arm, what the statistics add up to, read against the control arm's largest AUC
/// where there is one.
fn summary_table(pop: &Population, stats: &StatScan, control_max: Option<f64>) -> Table {
    let mut summary = Table::new(
        "Statistics per arm (plain vs the arm, all models): the largest AUC, how many statistics reach at most 0.6, their mean AUC, how many are significant after a Bonferroni correction (two-sided p < 0.05 / statistics) and, with a control arm, how many lie above its largest AUC",
    );
    for (k, &a) in pop.arms.iter().enumerate().skip(1) {
        let arm_stats = &stats.per_arm[k];
        let n = arm_stats.len();
        let (largest, j, _) = stats.best[k];
        let mut row = json!({
            "arm": a.name(), "statistics": n,
            "largest_auc": num(largest),
            "largest_statistic": if largest.is_finite() { pop.names[j].as_str() } else { "-" },
            "at_most_0_6": arm_stats.iter().filter(|x| x.0 <= 0.6).count(),
            "mean_auc": num(mean(arm_stats.iter().map(|x| x.0))),
            "significant": arm_stats.iter().filter(|x| x.1 < 0.05 / n.max(1) as f64).count(),
        });
        if let Some(c) = control_max {
            row["above_control_max"] = json!(arm_stats.iter().filter(|x| x.0 > c).count());
        }
        summary.push(row);
    }
    summary
}

/// The combined detectors, one per arm against plain.
struct Detectors {
    table: Table,
    fitted: Vec<(Arm, Combined)>,
    /// With a stealth arm: the plain vs stego detector's held-out scores on plain vs
    /// stealth models, (stealth, plain).
    stego_on_stealth: Option<(Vec<f64>, Vec<f64>)>,
}

impl Detectors {
    /// The plain vs stego detector, when it could be fitted.
    fn stego(&self) -> Option<&Detector> {
        self.fitted
            .iter()
            .find(|(a, _)| *a == Arm::Stego)
            .map(|(_, c)| &c.detector)
    }
}

/// Combined detectors, fitted on the first half of the pairs, scored on the rest, each
/// saved as `out/detector_<arm>.json`; one that cannot be fitted is said in `notes`.
fn combined_detectors(
    out: &Path,
    pop: &Population,
    stealth_arm: bool,
    notes: &mut Vec<String>,
) -> Result<Detectors> {
    let (models, n_fit) = (&pop.models, pop.n_fit);
    let mut table = Table::new(
        "Combined detector (logistic regression): fitted on pairs 0..n_fit, ROC AUC on the held-out pairs; auc_second_fold: fitted on the held-out pairs, scored on the first; auc_cross_fitted: every model scored by the detector fitted on the other half",
    );
    let mut fitted: Vec<(Arm, Combined)> = Vec::new();
    for &a in pop.arms.iter().skip(1) {
        match fit_combined(models, a, n_fit, Fold::First) {
            Ok(c) => {
                let path = out.join(format!("detector_{}.json", a.name()));
                c.detector.save(&path)?;
                table.push(combined_row(models, a, n_fit, &c));
                fitted.push((a, c));
            }
            Err(e) => notes.push(format!(
                "The plain vs {} detector could not be fitted: {e}.",
                a.name()
            )),
        }
    }
    let mut detectors = Detectors {
        table,
        fitted,
        stego_on_stealth: None,
    };
    // An analyst who only knows default stego models, facing stealth ones.
    if let Some(d) = detectors.stego().filter(|_| stealth_arm) {
        let (p, n) = score_held_out(d, models, Arm::Stealth, n_fit, Fold::First);
        let auc = roc_auc(&p, &n);
        let row = json!({
            "fitted_on": "plain vs stego", "scored": "plain vs stealth",
            "auc": num(auc), "p": num(auc_p_value(auc, p.len(), n.len())),
            "scored_models": p.len() + n.len(),
            "features_used": d.features.len(),
        });
        detectors.table.push(row);
        detectors.stego_on_stealth = Some((p, n));
    }
    Ok(detectors)
}

/// The row of the detector `c` fitted on the first fold for plain vs `a`.
fn combined_row(models: &[ModelRecord], a: Arm, n_fit: usize, c: &Combined) -> Value {
    let mut row = json!({
        "fitted_on": format!("plain vs {}", a.name()), "scored": format!("plain vs {}", a.name()),
        "auc": num(c.auc), "p": num(auc_p_value(c.auc, c.held_out.0.len(), c.held_out.1.len())),
        "scored_models": c.held_out.0.len() + c.held_out.1.len(),
        "features_used": c.detector.features.len(),
    });
    // The other fold, and every model scored by the detector that did not see it.
    if let Ok(c2) = fit_combined(models, a, n_fit, Fold::Second) {
        let pos: Vec<f64> = c.held_out.0.iter().chain(&c2.held_out.0).copied().collect();
        let neg: Vec<f64> = c.held_out.1.iter().chain(&c2.held_out.1).copied().collect();
        let cross = roc_auc(&pos, &neg);
        row["auc_second_fold"] = num(c2.auc);
        row["auc_cross_fitted"] = num(cross);
        row["p_cross_fitted"] = num(auc_p_value(cross, pos.len(), neg.len()));
    }
    row
}

/// The ROC figure's curves and their legends, in drawing order: the combined detectors,
/// each arm's best single statistic, the stego detector on stealth models.
fn roc_curves(
    pop: &Population,
    stats: &StatScan,
    detectors: &Detectors,
) -> (Vec<Vec<(f64, f64)>>, Vec<String>) {
    let mut curves: Vec<Vec<(f64, f64)>> = Vec::new();
    let mut legend: Vec<String> = Vec::new();
    for (a, c) in &detectors.fitted {
        curves.push(roc_points(&c.held_out.0, &c.held_out.1));
        legend.push(format!(
            "combined detector, plain vs {} (held-out pairs, AUC {:.3})",
            a.name(),
            c.auc
        ));
    }
    for (k, &a) in pop.arms.iter().enumerate().skip(1) {
        let (auc, j, up) = stats.best[k];
        if auc.is_finite() {
            // Oriented so that the arm scores higher: the curve runs above the diagonal.
            let sign = if up { 1.0 } else { -1.0 };
            let oriented = |arm: Arm| -> Vec<f64> {
                pop.column(j, arm)
                    .iter()
                    .map(|v| sign * v)
                    .filter(|v| v.is_finite())
                    .collect()
            };
            curves.push(roc_points(&oriented(a), &oriented(Arm::Plain)));
            legend.push(format!(
                "best single statistic for {}: {} ({}, all models, AUC {auc:.3})",
                a.name(),
                pop.names[j],
                direction(up)
            ));
        }
    }
    if let Some((p, n)) = &detectors.stego_on_stealth {
        curves.push(roc_points(p, n));
        legend.push(format!(
            "stego-fitted detector scored on plain vs stealth (held-out pairs, AUC {:.3})",
            roc_auc(p, n)
        ));
    }
    (curves, legend)
}

/// Per model, for inspection.
fn per_model_table(pop: &Population, stego_detector: Option<&Detector>) -> Table {
    let mut per_model = Table::new("Models");
    for m in &pop.models {
        per_model.push(json!({
            "arm": m.arm.name(), "pair": m.index, "key": m.scheme.map(SchemeKind::name).unwrap_or("-"),
            "schedule": if m.arm.hides() { m.schedule.name() } else { "-" },
            "hidden": if m.arm.hides() { m.hidden_kind.as_str() } else { "-" },
            "cover_psnr": num(m.cover_psnr), "hidden_psnr": m.hidden_psnr.map(num).unwrap_or(json!("-")),
            "half": if m.index < pop.n_fit { "fit" } else { "scored" },
            "stego_detector_score": stego_detector.map(|d| num(d.score(&m.features))).unwrap_or(Value::Null),
        }));
    }
    per_model
}

/// Draws `out/roc.png` and returns the report's figure entry for it.
fn roc_figure(
    out: &Path,
    curves: &[Vec<(f64, f64)>],
    legend: &[String],
) -> Result<(String, String)> {
    draw_roc(&out.join("roc.png"), curves)?;
    let legend_text: Vec<String> = legend
        .iter()
        .zip(COLOURS)
        .map(|(l, (c, _))| format!("{c}: {l}"))
        .collect();
    Ok((
        "roc.png".into(),
        format!(
            "ROC curves (x: false positive rate, y: true positive rate, grid every 0.1, ticks every 0.25; dashed grey: chance). {}",
            legend_text.join("; ")
        ),
    ))
}

/// The report's notes after the detectors': the population, how to read the figures, the
/// control arm, the cost of stealth and the stego detector's largest weights.
fn closing_notes(
    opts: &DetectOptions,
    pop: &Population,
    control_max: Option<f64>,
    stego_detector: Option<&Detector>,
) -> Vec<String> {
    let mut notes = vec![format!(
        "{} pairs of generated scenes; each pair is one cover (a random tabletop of primitives) and one hidden scene (3D text or another random tabletop, alternating), with one seed and one key, shared by its plain, stego{} models{}. Stego pairs cycle through the key schemes (prf, primes) and schedules (mixed, random-scene). Every model is analysed from its .ingp file alone.",
        opts.models,
        if opts.stealth_arm { " and stealth" } else { "" },
        if opts.control_arm {
            " (the control models: the same cover, another training seed)"
        } else {
            ""
        }
    )];
    notes.push(
        "Per-statistic AUC is max(AUC, 1 − AUC) over all models, with the direction (larger or smaller in stego models) that gives it: an analyst picks the direction from data, so a statistic that separates the classes either way counts, and 0.5 is the floor. This is optimistic for the statistic (the direction is chosen on the same models it is scored on); its p-value (`<arm>_p`) is two-sided for that reason, exact (Mann–Whitney). The combined detector is honest: fitted on the first half of the pairs, its AUC is measured on the second half, covers and hidden scenes it never saw; its p is the chance that a detector that knows nothing scores at least that AUC on those models. The detectors are saved as detector_<arm>.json.".into(),
    );
    if opts.control_arm {
        notes.push(format!(
            "The control arm is plain models of the same covers trained from another seed, scored as if they hid something: every figure it gets is chance at this population's size{}. Read the other arms against it, not against 0.5.",
            control_max
                .map(|c| format!(" (its largest statistic reaches AUC {c:.3})"))
                .unwrap_or_default()
        ));
    }
    if opts.stealth_arm {
        let m = |a: Arm, hidden: bool| {
            mean(pop.of(a).filter_map(|x| {
                if hidden {
                    x.hidden_psnr
                } else {
                    Some(x.cover_psnr)
                }
            }))
        };
        notes.push(format!(
            "Cost of stealth: cover {:+.2} dB (stealth − stego; stego − plain {:+.2} dB), hidden {:+.2} dB (stealth − stego).",
            m(Arm::Stealth, false) - m(Arm::Stego, false),
            m(Arm::Stego, false) - m(Arm::Plain, false),
            m(Arm::Stealth, true) - m(Arm::Stego, true),
        ));
    }
    if let Some(d) = stego_detector {
        let mut w: Vec<_> = d.features.iter().collect();
        w.sort_by(|a, b| b.weight.abs().total_cmp(&a.weight.abs()));
        let top: Vec<String> = w
            .iter()
            .take(5)
            .map(|f| format!("{} {:+.2}", f.name, f.weight))
            .collect();
        notes.push(format!(
            "Largest weights of the plain vs stego detector (standardised units): {}.",
            top.join(", ")
        ));
    }
    notes
}

/// The run note of mean times per model; `wall`: this run's seconds.
fn timing_note(pop: &Population, wall: f64) -> String {
    let timing: Vec<String> = pop
        .arms
        .iter()
        .map(|&a| {
            format!(
                "{} {:.1} s training, {:.1} s scoring, {:.2} s analysis",
                a.name(),
                mean(pop.of(a).map(|m| m.train_s)),
                mean(pop.of(a).map(|m| m.eval_s)),
                mean(pop.of(a).map(|m| m.analyse_s))
            )
        })
        .collect();
    format!(
        "Mean per model (training time as recorded when the model was trained): {}. This run: {wall:.0} s for {} models, {} threads.",
        timing.join("; "),
        pop.models.len(),
        rayon::current_num_threads()
    )
}

/// `out/features.json`: every model's statistics.
fn write_features(out: &Path, models: &[ModelRecord]) -> Result<()> {
    let feats: Vec<Value> = models
        .iter()
        .map(|m| {
            let f: serde_json::Map<String, Value> = m
                .features
                .iter()
                .map(|(n, v)| (n.clone(), num(*v)))
                .collect();
            json!({"arm": m.arm.name(), "pair": m.index, "features": f})
        })
        .collect();
    let text = serde_json::to_string_pretty(&feats).map_err(|e| Error::Other(e.to_string()))?;
    write_atomic(&out.join("features.json"), text.as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;
    use backend::Device;
    use ngp::encoding::GridConfig;

    /// A reused model's scores come from its sidecar: they must read back as the run that
    /// trained it had them, or a rerun's report differs in the last digit (serde_json's
    /// default float parser is off by an ulp on some inputs; `float_roundtrip` is exact).
    #[test]
    fn a_sidecars_numbers_read_back_to_the_bit() {
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        for k in 0..20_000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            // PSNR-like values, then any finite double.
            let v = if k % 2 == 0 {
                10.0 + (x >> 11) as f64 / (1u64 << 53) as f64 * 40.0
            } else {
                f64::from_bits(x)
            };
            if !v.is_finite() {
                continue;
            }
            let text = serde_json::to_string(&json!({ "cover_psnr": v })).unwrap();
            let back: serde_json::Value = serde_json::from_str(&text).unwrap();
            assert_eq!(
                back["cover_psnr"].as_f64().unwrap().to_bits(),
                v.to_bits(),
                "{text}"
            );
        }
    }

    fn exp_config(hidden_from_step: u32, hidden_loss_weight: f32) -> ExpConfig {
        ExpConfig {
            out: "out".into(),
            cover: PathBuf::new(),
            hidden: Vec::new(),
            downscale: 1,
            hidden_downscale: 1,
            steps: 200,
            batch: 4096,
            seed: 0,
            eval_views: 8,
            occupancy_fraction: 0.03,
            grid: GridConfig {
                n_levels: 16,
                n_features: 2,
                log2_hashmap_size: 14,
                base_resolution: 16,
            },
            scheme: SchemeKind::Prf,
            training: HiddenOptions {
                hidden_from: hidden_from_step,
                hidden_weight: hidden_loss_weight,
                ..HiddenOptions::default()
            },
            lpips: false,
            verbose: false,
            device: std::sync::Arc::new(Device::default()),
            save_every: None,
            jobs: Default::default(),
        }
    }

    /// A model's sidecar changes with what changes its training, and only then: the
    /// warm-up and the hidden weight change the models with a hidden scene, not the plain
    /// ones, and at their defaults they leave every sidecar as it was before they existed.
    #[test]
    fn sidecars_record_the_warm_up_and_the_hidden_weight_where_they_apply() {
        let scenes = (Path::new("out/scenes/c"), Path::new("out/scenes/h"));
        let combo = combination(0);
        let config = |c: &ExpConfig, arm| model_config(c, arm, scenes, 7, combo);
        let base = exp_config(0, 1.0);
        for arm in [Arm::Plain, Arm::Stego, Arm::Stealth] {
            let v = config(&base, arm);
            assert!(v.get("hidden_from_step").is_none() && v.get("hidden_loss_weight").is_none());
        }
        for changed in [exp_config(50, 1.0), exp_config(0, 0.25)] {
            assert_eq!(config(&changed, Arm::Plain), config(&base, Arm::Plain));
            for arm in [Arm::Stego, Arm::Stealth] {
                assert_ne!(config(&changed, arm), config(&base, arm), "{arm:?}");
            }
        }
        assert_eq!(
            config(&exp_config(0, 0.25), Arm::Stego)["hidden_loss_weight"],
            "0.25"
        );
    }

    /// Stealth's density cap, when not the default, changes the stealth arm's sidecar and
    /// no other.
    #[test]
    fn a_density_cap_changes_the_stealth_sidecar_alone() {
        let scenes = (Path::new("out/scenes/c"), Path::new("out/scenes/h"));
        let combo = combination(0);
        let config = |c: &ExpConfig, arm| model_config(c, arm, scenes, 7, combo);
        let base = exp_config(0, 1.0);
        let mut capped = exp_config(0, 1.0);
        capped.training.stealth.density_cap = Some(10.0);
        assert!(config(&base, Arm::Stealth).get("density_cap").is_none());
        for arm in [Arm::Plain, Arm::Stego] {
            assert_eq!(config(&capped, arm), config(&base, arm), "{arm:?}");
        }
        assert_eq!(config(&capped, Arm::Stealth)["density_cap"], "10");
    }

    /// The control arm is the plain model of the same cover from another seed: its sidecar
    /// is the plain one's but for the arm and the seed, and the options that change the
    /// models with a hidden scene leave it alone.
    #[test]
    fn the_control_arm_is_a_plain_model_from_another_seed() {
        let scenes = (Path::new("out/scenes/c"), Path::new("out/scenes/h"));
        let combo = combination(1);
        let seed = pair_seed(0, 1);
        let config =
            |c: &ExpConfig, arm: Arm| model_config(c, arm, scenes, arm.training_seed(seed), combo);
        let base = exp_config(0, 1.0);
        let (plain, control) = (config(&base, Arm::Plain), config(&base, Arm::Control));
        assert_eq!(plain["seed"], seed);
        assert_ne!(control["seed"], plain["seed"]);
        assert_eq!(control["arm"], "control");
        let mut relabelled = control.clone();
        relabelled["arm"] = plain["arm"].clone();
        relabelled["seed"] = plain["seed"].clone();
        assert_eq!(relabelled, plain);
        let mut hidden_options = exp_config(50, 0.25);
        hidden_options.training.stealth.density_cap = Some(10.0);
        assert_eq!(config(&hidden_options, Arm::Control), control);
        assert!(!Arm::Control.hides() && !Arm::Plain.hides());
        assert!(Arm::Stego.hides() && Arm::Stealth.hides());
    }

    #[test]
    fn the_two_folds_split_the_pairs() {
        for pair in 0..5 {
            assert_eq!(Fold::First.fits(pair, 3), pair < 3);
            assert_ne!(Fold::First.fits(pair, 3), Fold::Second.fits(pair, 3));
        }
    }

    #[test]
    fn roc_points_by_hand() {
        // Perfect separation: straight up, then across.
        assert_eq!(
            roc_points(&[3.0, 4.0], &[1.0, 2.0]),
            vec![(0.0, 0.0), (0.0, 0.5), (0.0, 1.0), (0.5, 1.0), (1.0, 1.0)]
        );
        // All tied: one diagonal step.
        assert_eq!(
            roc_points(&[1.0, 1.0], &[1.0]),
            vec![(0.0, 0.0), (1.0, 1.0)]
        );
    }

    #[test]
    fn directed_auc_picks_the_direction() {
        // Two of each: 1 order in 6 separates them one way, 1 the other.
        assert_eq!(
            directed_auc(&[3.0, 4.0], &[1.0, 2.0]),
            (1.0, true, 1.0 / 3.0)
        );
        assert_eq!(
            directed_auc(&[1.0, 2.0], &[3.0, 4.0]),
            (1.0, false, 1.0 / 3.0)
        );
        // The NaN is left out: two against two, U = 3 of 4, P(U ≥ 3) = 2/6, twice.
        let (a, _, p) = directed_auc(&[2.0, 4.0, f64::NAN], &[1.0, 3.0]);
        assert_eq!((a, p), (0.75, 2.0 / 3.0));
        assert!(directed_auc(&[f64::NAN], &[1.0]).0.is_nan());
    }

    #[test]
    fn pairs_cycle_through_all_four_combinations() {
        let c: Vec<_> = (0..4).map(combination).collect();
        for s in [SchemeKind::Prf, SchemeKind::Primes] {
            for sc in [Schedule::Mixed, Schedule::RandomScene] {
                assert_eq!(c.iter().filter(|x| **x == (s, sc)).count(), 1);
            }
        }
    }

    #[test]
    fn random_covers_differ_and_fit_the_box() {
        let a = random_object_scene(1);
        let b = random_object_scene(2);
        assert!(a.lo != b.lo || a.hi != b.hi || a.objects.len() != b.objects.len());
        for s in [&a, &b] {
            assert!(s.lo.iter().all(|&v| v >= -1.3) && s.hi.iter().all(|&v| v <= 1.3));
        }
        // Same seed, same scene.
        let c = random_object_scene(1);
        assert_eq!((a.lo, a.hi, a.objects.len()), (c.lo, c.hi, c.objects.len()));
    }
}
