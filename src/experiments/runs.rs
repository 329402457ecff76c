//! The experiments themselves.

use super::report::{Report, Table, save_grid};
use crate::backend::Device;
use crate::error::{Error, Result};
use crate::ngp::data::{Dataset, LoadOptions, Split};
use crate::ngp::encoding::GridConfig;
use crate::ngp::eval::{EvalResult, evaluate_on, spread_views};
use crate::ngp::lpips::Lpips;
use crate::ngp::model::Model;
use crate::ngp::network::{ModelConfig, NerfLayout};
use crate::ngp::render::image::RenderOptions;
use crate::ngp::train::{DensityCap, SceneSpec, Schedule, TrainConfig};
use crate::rng::Pcg32;
use crate::stego::stealth::StealthRefresh;
use crate::stego::{
    Key, Mixed, SchemeKind, generate_prf, generate_primes, generate_with, key_strength,
    open_scene_on,
};
use serde_json::json;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// One of the experiments, named as `stegongp experiment NAME` takes it; the name is also
/// its report's folder and its report's `experiment` field.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Experiment {
    Fidelity,
    KeySensitivity,
    PartialKeys,
    MultiHidden,
    TableSize,
    KeyStrength,
    Detectability,
    Pairs,
}

impl Experiment {
    /// Every experiment, in the order the CLI lists them.
    pub const ALL: [Experiment; 8] = [
        Experiment::Fidelity,
        Experiment::KeySensitivity,
        Experiment::PartialKeys,
        Experiment::MultiHidden,
        Experiment::TableSize,
        Experiment::KeyStrength,
        Experiment::Detectability,
        Experiment::Pairs,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Experiment::Fidelity => "fidelity",
            Experiment::KeySensitivity => "key-sensitivity",
            Experiment::PartialKeys => "partial-keys",
            Experiment::MultiHidden => "multi-hidden",
            Experiment::TableSize => "table-size",
            Experiment::KeyStrength => "key-strength",
            Experiment::Detectability => "detectability",
            Experiment::Pairs => "pairs",
        }
    }
}

impl std::fmt::Display for Experiment {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Experiment {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        Experiment::ALL
            .into_iter()
            .find(|e| e.name() == s)
            .ok_or_else(|| {
                let names: Vec<&str> = Experiment::ALL.iter().map(|e| e.name()).collect();
                Error::Config(format!(
                    "unknown experiment '{s}' (one of: {})",
                    names.join(", ")
                ))
            })
    }
}

/// An experiment's key number `which` of `kind` for `m` groups, for `hidden`: drawn from the
/// run's seed, so a report can be reproduced exactly (these keys protect nothing). Like
/// `keygen --aabb-scale`, the key names the hidden scene's own box, so that a key holder's
/// grid (and a wrong key's) is cut to it inside a larger cover's box.
pub(super) fn experiment_key(
    kind: SchemeKind,
    m: usize,
    seed: u64,
    which: u64,
    hidden: &Scene,
) -> Result<Key> {
    let mut rng = Pcg32::new(seed ^ 0x6b65_7973, (which << 8) | m as u64);
    let next = move || Ok(((rng.next_u32() as u64) << 32) | rng.next_u32() as u64);
    generate_with(kind, m, next)?.with_scene_box(Some(hidden.own_box))
}

/// What every experiment shares.
#[derive(Clone, Debug)]
pub struct ExpConfig {
    pub out: PathBuf,
    pub cover: PathBuf,
    /// Hidden scenes; experiments that need more than given reuse them cyclically.
    pub hidden: Vec<PathBuf>,
    /// Downscale of the cover's images.
    pub downscale: u32,
    /// Downscale of the hidden scenes' images (each scene has its own native resolution).
    pub hidden_downscale: u32,
    /// Training steps of every model (a stego model trains each scene this many steps).
    pub steps: u32,
    /// Samples per scene per step.
    pub batch: u32,
    pub seed: u64,
    pub eval_views: usize,
    pub occupancy_fraction: f32,
    pub grid: GridConfig,
    pub scheme: SchemeKind,
    pub schedule: Schedule,
    /// Stealth training: hidden scenes confined to the cover's reachable entries.
    pub stealth: bool,
    /// With `stealth`: the MLP learns from the cover alone (see
    /// [`ExpConfig::trains_cover_only_mlp`]).
    pub cover_only_mlp: bool,
    /// Cover-only warm-up: a model with hidden scenes trains the cover alone for this many
    /// trainer steps first ([`TrainConfig::hidden_from_step`]); 0 trains every scene from
    /// the start.
    pub hidden_from_step: u32,
    /// Loss weight of the hidden scenes relative to the cover's 1
    /// ([`TrainConfig::hidden_loss_weight`]).
    pub hidden_loss_weight: f32,
    /// Stealth's cap on the cover's optical thickness when not the default
    /// ([`DensityCap::stealth`]; 0: none).
    pub density_cap: Option<f32>,
    /// Score LPIPS beside PSNR and SSIM (the `--no-lpips` flag turns it off).
    pub lpips: bool,
    /// Progress lines on stderr.
    pub verbose: bool,
    /// Where every model trains and renders (shared: one device for the whole run).
    pub device: Arc<Device>,
}

impl ExpConfig {
    /// Whether this configuration's models learn their MLP from the cover alone: only
    /// stealth training does.
    pub fn trains_cover_only_mlp(&self) -> bool {
        self.stealth && self.cover_only_mlp
    }

    /// Adds to a model-with-hidden-scenes sidecar config the training options that are not
    /// at their defaults (warm-up, hidden weight), and nothing else: a model trained before
    /// an option existed keeps a sidecar that still matches, and is reused.
    pub(super) fn record_hidden_options(&self, config: &mut serde_json::Value) {
        if self.hidden_from_step > 0 {
            config["hidden_from_step"] = json!(self.hidden_from_step);
        }
        if self.hidden_loss_weight != 1.0 {
            // A string: serde_json's float parsing does not round-trip every f64 exactly.
            config["hidden_loss_weight"] = json!(self.hidden_loss_weight.to_string());
        }
    }

    /// Adds a stealth model's cap to its sidecar when not the default (so that models
    /// trained at the default stay reusable).
    pub(super) fn record_density_cap(&self, config: &mut serde_json::Value) {
        if let Some(c) = self.density_cap {
            config["density_cap"] = json!(c.to_string());
        }
    }
}

pub(super) struct Scene {
    pub train: Arc<Dataset>,
    pub test: Dataset,
    pub name: String,
    /// The scene's own box (its aabb_scale as loaded, before it took the cover's).
    pub own_box: u32,
}

/// Loads a scene's splits, placed in the box of `aabb_scale` when given (hidden scenes take
/// the cover's: every model of an experiment shares the cover's box).
pub(super) fn load_scene(dir: &Path, downscale: u32, aabb_scale: Option<u32>) -> Result<Scene> {
    let opts = LoadOptions {
        downscale,
        ..Default::default()
    };
    let mut train = Dataset::load(dir, Split::Train, &opts)?;
    let mut test = Dataset::load(dir, Split::Test, &opts)?;
    let own_box = train.aabb_scale;
    if let Some(a) = aabb_scale {
        train.fit_into_box(a, None)?;
        test.fit_into_box(a, None)?;
    }
    Ok(Scene {
        train: Arc::new(train),
        test,
        name: dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| dir.display().to_string()),
        own_box,
    })
}

struct Ctx<'a> {
    cfg: &'a ExpConfig,
    cover: Scene,
    hidden: Vec<Scene>,
}

/// A trained model and how long its training took.
pub(super) struct Trained {
    pub model: Model,
    pub seconds: f64,
    pub samples_per_s: f64,
    /// Steps per scene (a random-scene schedule ran this many times the scene count).
    pub steps: u32,
}

/// How long a model trains.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Budget {
    /// Steps per scene: every scene is trained this many times, whatever the schedule.
    Steps(u32),
    /// Training seconds (step time only, not setup); the steps reached are recorded.
    Seconds(f64),
}

/// Trains one model of `config` on `scenes` (dataset, key; the cover first, under the
/// reference key) with the experiment's batch, schedule, seed and stealth.
pub(super) fn train_scenes(
    cfg: &ExpConfig,
    config: ModelConfig,
    scenes: &[(&Scene, &Key)],
    budget: Budget,
    label: &str,
) -> Result<Trained> {
    let layout = NerfLayout::new(config)?;
    let warm_up = warm_up_steps(cfg, scenes.len());
    let specs = scenes
        .iter()
        .map(|(s, k)| {
            k.validate_for(&layout.grid)?;
            Ok(SceneSpec {
                dataset: s.train.clone(),
                indices: k.level_indices(&layout.grid),
            })
        })
        .collect::<Result<Vec<_>>>()?;
    let tc = TrainConfig {
        seed: cfg.seed,
        batch_samples: cfg.batch,
        occupancy_fraction: cfg.occupancy_fraction,
        schedule: cfg.schedule,
        cover_paced_table: cfg.stealth,
        bounded_left_entries: cfg.stealth,
        density_cap: if cfg.stealth {
            DensityCap::stealth(cfg.density_cap)
        } else {
            None
        },
        cover_only_mlp: cfg.trains_cover_only_mlp(),
        hidden_from_step: warm_up,
        hidden_loss_weight: cfg.hidden_loss_weight,
        ..Default::default()
    };
    let mut t = cfg.device.trainer(config, specs, tc)?;
    if cfg.stealth && scenes.len() > 1 {
        let keys = scenes[1..].iter().map(|(_, k)| (*k).clone()).collect();
        t.set_index_refresh(Box::new(StealthRefresh::new(layout.clone(), keys)))?;
    }
    // RandomScene trains one scene per step: give each scene the same number of steps.
    let per_step = match cfg.schedule {
        Schedule::Mixed => 1,
        Schedule::RandomScene => scenes.len() as u32,
    };
    if let Budget::Steps(n) = budget
        && warm_up >= n * per_step
    {
        return Err(Error::Config(format!(
            "{label}: the cover-only warm-up ({warm_up} steps) is not shorter than the \
             training ({} steps): the hidden scenes would never train",
            n * per_step
        )));
    }
    let (mut secs, mut samples, mut loss, mut steps) = (0.0, 0u64, 0.0f32, 0u32);
    loop {
        let done = match budget {
            Budget::Steps(n) => steps >= n * per_step,
            Budget::Seconds(s) => secs >= s && steps % per_step == 0,
        };
        if done {
            break;
        }
        let st = t.train_step()?;
        secs += st.seconds;
        samples += st.n_samples;
        loss = st.cover_loss.unwrap_or(loss);
        steps += 1;
    }
    if steps <= warm_up {
        return Err(Error::Config(format!(
            "{label}: the time budget ended at step {steps}, inside the cover-only warm-up \
             ({warm_up} steps): the hidden scenes never trained"
        )));
    }
    if cfg.verbose {
        eprintln!(
            "  trained {label}: {steps} steps in {secs:.1} s ({:.0} k samples/s), loss {loss:.5}",
            samples as f64 / secs.max(1e-9) / 1e3
        );
    }
    Ok(Trained {
        model: t.model(loss)?,
        seconds: secs,
        samples_per_s: samples as f64 / secs.max(1e-9),
        steps: steps / per_step,
    })
}

/// The trainer steps a model of `n_scenes` scenes trains its cover alone.
fn warm_up_steps(cfg: &ExpConfig, n_scenes: usize) -> u32 {
    if n_scenes > 1 {
        cfg.hidden_from_step
    } else {
        0
    }
}

impl Ctx<'_> {
    fn model_config(&self, grid: GridConfig) -> ModelConfig {
        ModelConfig {
            grid,
            aabb_scale: self.cover.train.aabb_scale,
        }
    }

    fn log(&self, msg: &str) {
        if self.cfg.verbose {
            eprintln!("{msg}");
        }
    }

    /// Trains one model on `scenes` (dataset, key) for `cfg.steps` steps per scene — the
    /// cover uses the reference key.
    fn train(&self, grid: GridConfig, scenes: &[(&Scene, &Key)], label: &str) -> Result<Trained> {
        train_scenes(
            self.cfg,
            self.model_config(grid),
            scenes,
            Budget::Steps(self.cfg.steps),
            label,
        )
    }

    fn render_opts(&self) -> RenderOptions {
        RenderOptions::default()
    }

    /// Scores `model` seen through `key` on `scene`'s held-out views; the occupancy grid is
    /// the stored one for the reference key, otherwise rebuilt from the network with the key
    /// (what a key holder — or an attacker trying a key — does). Returns the scores and the
    /// rendering of the first evaluated view.
    fn score(&self, model: &Model, key: &Key, scene: &Scene) -> Result<(EvalResult, Vec<f32>)> {
        let device = &self.cfg.device;
        let opened = open_scene_on(device, model, Some(key), self.cfg.stealth, self.cfg.seed)?;
        let mut renderer = opened.renderer(device, model)?;
        let which = spread_views(scene.test.frames.len(), self.cfg.eval_views);
        let mut first = None;
        let r = evaluate_on(
            renderer.as_mut(),
            &scene.test,
            &self.render_opts(),
            Some(&which),
            self.cfg.lpips.then(Lpips::embedded),
            |_, img, _| {
                if first.is_none() {
                    first = Some(img.rgb.clone());
                }
            },
        )?;
        Ok((r, first.unwrap_or_default()))
    }

    fn gt(&self, scene: &Scene) -> Vec<f32> {
        let which = spread_views(scene.test.frames.len(), self.cfg.eval_views);
        crate::ngp::eval::ground_truth(&scene.test, which[0], [1.0; 3])
    }

    fn size(&self) -> (u32, u32) {
        (self.cover.test.width, self.cover.test.height)
    }

    fn hidden(&self, i: usize) -> &Scene {
        &self.hidden[i % self.hidden.len()]
    }
}

fn setup_json(cfg: &ExpConfig) -> serde_json::Value {
    json!({
        "cover": cfg.cover, "hidden": cfg.hidden, "downscale": cfg.downscale, "hidden_downscale": cfg.hidden_downscale,
        "steps": cfg.steps, "batch_samples_per_scene": cfg.batch, "seed": cfg.seed,
        "eval_views": cfg.eval_views, "occupancy_fraction": cfg.occupancy_fraction,
        "levels": cfg.grid.n_levels, "features": cfg.grid.n_features,
        "log2_hashmap_size": cfg.grid.log2_hashmap_size, "scheme": cfg.scheme.name(),
        "schedule": format!("{:?}", cfg.schedule), "stealth": cfg.stealth,
        "cover_only_mlp": cfg.trains_cover_only_mlp(), "hidden_from_step": cfg.hidden_from_step,
        "hidden_loss_weight": cfg.hidden_loss_weight, "density_cap": cfg.density_cap, "lpips": cfg.lpips,
        "threads": rayon::current_num_threads(), "device": cfg.device.report(),
    })
}

/// Runs experiment `name` and writes its report into `cfg.out`.
pub fn run_experiment(name: Experiment, cfg: &ExpConfig) -> Result<Report> {
    std::fs::create_dir_all(&cfg.out).map_err(|e| Error::io(&cfg.out, e))?;
    if name == Experiment::Detectability {
        // It generates its own population of scenes; the CLI passes its options directly.
        return super::detectability::run_detectability(
            cfg,
            &super::detectability::DetectOptions::default(),
        );
    }
    if name == Experiment::Pairs {
        // The cover with each hidden scene; the CLI passes its own pairs and options.
        let opts = super::pairs::PairsOptions {
            pairs: cfg
                .hidden
                .iter()
                .map(|h| super::pairs::PairSpec {
                    cover: cfg.cover.clone(),
                    hidden: h.clone(),
                })
                .collect(),
            minutes: None,
            lpips: cfg.lpips,
        };
        return super::pairs::run_pairs(cfg, &opts);
    }
    let mut report = Report {
        name: name.to_string(),
        setup: setup_json(cfg),
        ..Default::default()
    };
    if name == Experiment::KeyStrength {
        key_strength_report(cfg, &mut report)?;
        report.write(&cfg.out)?;
        return Ok(report);
    }
    if cfg.hidden.is_empty() {
        return Err(Error::Config(
            "this experiment needs at least one hidden scene".into(),
        ));
    }
    let cover = load_scene(&cfg.cover, cfg.downscale, None)?;
    let box_scale = Some(cover.train.aabb_scale);
    let ctx = Ctx {
        cfg,
        cover,
        hidden: cfg
            .hidden
            .iter()
            .map(|h| load_scene(h, cfg.hidden_downscale, box_scale))
            .collect::<Result<_>>()?,
    };
    match name {
        Experiment::Fidelity => fidelity(&ctx, &mut report)?,
        Experiment::KeySensitivity => key_sensitivity(&ctx, &mut report)?,
        Experiment::PartialKeys => partial_keys(&ctx, &mut report)?,
        Experiment::MultiHidden => multi_hidden(&ctx, &mut report)?,
        Experiment::TableSize => table_size(&ctx, &mut report)?,
        Experiment::KeyStrength | Experiment::Detectability | Experiment::Pairs => {
            unreachable!("run above")
        }
    }
    report.write(&cfg.out)?;
    Ok(report)
}

fn fidelity(ctx: &Ctx, report: &mut Report) -> Result<()> {
    let pi = Key::reference();
    let h = ctx.hidden(0);
    let key = experiment_key(ctx.cfg.scheme, 1, ctx.cfg.seed, 0, h)?;
    ctx.log("fidelity: plain cover, plain hidden, stego (cover + hidden)");
    let plain_c = ctx.train(ctx.cfg.grid, &[(&ctx.cover, &pi)], "plain cover")?;
    let plain_h = ctx.train(ctx.cfg.grid, &[(h, &pi)], "plain hidden")?;
    let stego = ctx.train(ctx.cfg.grid, &[(&ctx.cover, &pi), (h, &key)], "stego")?;
    let (pc, img_pc) = ctx.score(&plain_c.model, &pi, &ctx.cover)?;
    let (ph, img_ph) = ctx.score(&plain_h.model, &pi, h)?;
    let (sc, img_sc) = ctx.score(&stego.model, &pi, &ctx.cover)?;
    let (sh, img_sh) = ctx.score(&stego.model, &key, h)?;
    let mut t = Table::new("Fidelity at the same per-scene step and sample budget");
    for (model, scene, r, tr) in [
        ("plain", &ctx.cover.name, &pc, &plain_c),
        ("stego (no key)", &ctx.cover.name, &sc, &stego),
        ("plain", &h.name, &ph, &plain_h),
        ("stego (key)", &h.name, &sh, &stego),
    ] {
        t.push(json!({"model": model, "scene": scene, "psnr": r.psnr, "ssim": r.ssim, "lpips": r.lpips, "views": r.n_views,
            "train_s": tr.seconds, "samples_per_s": tr.samples_per_s.round()}));
    }
    report.tables.push(t);
    report.notes.push(format!(
        "Cover: stego − plain = {:+.2} dB. Hidden: stego − plain = {:+.2} dB. Key scheme {}.",
        sc.psnr - pc.psnr,
        sh.psnr - ph.psnr,
        ctx.cfg.scheme.name()
    ));
    let (w, hgt) = ctx.size();
    save_grid(
        &ctx.cfg.out.join("fidelity.png"),
        &[
            ctx.gt(&ctx.cover),
            img_pc,
            img_sc,
            ctx.gt(h),
            img_ph,
            img_sh,
        ],
        w,
        hgt,
        3,
    )?;
    report.figures.push(("fidelity.png".into(), "Rows: cover, hidden. Columns: ground truth, plain model, stego model (cover without key, hidden with key).".into()));
    Ok(())
}

fn key_sensitivity(ctx: &Ctx, report: &mut Report) -> Result<()> {
    let pi = Key::reference();
    let h = ctx.hidden(0);
    for scheme in [SchemeKind::Primes, SchemeKind::Prf] {
        let key = experiment_key(scheme, 1, ctx.cfg.seed, 0, h)?;
        ctx.log(&format!("key-sensitivity ({}): stego model", scheme.name()));
        let stego = ctx.train(ctx.cfg.grid, &[(&ctx.cover, &pi), (h, &key)], scheme.name())?;
        let variants = [
            ("default Π", pi.clone()),
            ("secret key", key.clone()),
            (
                if scheme == SchemeKind::Primes {
                    "{π1,k2,k3}"
                } else {
                    "1/3 of secret zeroed"
                },
                key.mixed(Mixed::Pi1K2K3),
            ),
            (
                if scheme == SchemeKind::Primes {
                    "{π1,π2,k3}"
                } else {
                    "2/3 of secret zeroed"
                },
                key.mixed(Mixed::Pi1Pi2K3),
            ),
            ("wrong key", Key::wrong(ctx.cfg.seed ^ 0xbad, &key)),
        ];
        let mut t = Table::new(&format!(
            "Key sensitivity, {} scheme: PSNR of each rendering against both scenes",
            scheme.name()
        ));
        let mut tiles = vec![ctx.gt(&ctx.cover), ctx.gt(h)];
        for (label, k) in &variants {
            let (vs_hidden, img) = ctx.score(&stego.model, k, h)?;
            let (vs_cover, _) = ctx.score(&stego.model, k, &ctx.cover)?;
            t.push(json!({"key": label, "psnr_vs_hidden": vs_hidden.psnr, "ssim_vs_hidden": vs_hidden.ssim, "lpips_vs_hidden": vs_hidden.lpips,
                "psnr_vs_cover": vs_cover.psnr, "empty_render_vs_hidden": vs_hidden.blank_psnr}));
            tiles.push(img);
        }
        report.tables.push(t);
        let (w, hgt) = ctx.size();
        let file = format!("key_sensitivity_{}.png", scheme.name());
        save_grid(&ctx.cfg.out.join(&file), &tiles, w, hgt, tiles.len())?;
        report.figures.push((
            file,
            format!(
                "{}: cover GT, hidden GT, then renderings with: {}",
                scheme.name(),
                variants.iter().map(|v| v.0).collect::<Vec<_>>().join(", ")
            ),
        ));
    }
    Ok(())
}

/// A way of giving part of a key: `Key::partial` or `Key::disclose_levels`.
type Disclose = fn(&Key, f64) -> Key;

fn partial_keys(ctx: &Ctx, report: &mut Report) -> Result<()> {
    let pi = Key::reference();
    let h = ctx.hidden(0);
    let fractions = [0.0, 0.25, 0.5, 0.75, 1.0];
    let mut t = Table::new(
        "Partial key disclosure: hidden-scene PSNR when the first p % of the m keys are given (the rest replaced by Π)",
    );
    let (w, hgt) = ctx.size();
    for scheme in [SchemeKind::Primes, SchemeKind::Prf] {
        for m in [4usize, 8, 16] {
            if m > ctx.cfg.grid.n_levels as usize {
                continue;
            }
            let key = experiment_key(scheme, m, ctx.cfg.seed, 0, h)?;
            ctx.log(&format!("partial-keys: {} m = {m}", scheme.name()));
            let stego = ctx.train(
                ctx.cfg.grid,
                &[(&ctx.cover, &pi), (h, &key)],
                &format!("{} m={m}", scheme.name()),
            )?;
            let (wrong, _) = ctx.score(&stego.model, &Key::wrong(ctx.cfg.seed ^ 0x77, &key), h)?;
            // prf: partial key material (all-or-nothing), then leaked level subkeys (the
            // paper's per-level substitution); primes: the two are the same.
            let variants: Vec<(&str, Disclose)> = match scheme {
                SchemeKind::Primes => vec![("keys", Key::partial)],
                SchemeKind::Prf => vec![
                    ("secret shares", Key::partial),
                    ("level subkeys", Key::disclose_levels),
                ],
            };
            for (given, disclose) in variants {
                let mut row = serde_json::Map::new();
                row.insert("scheme".into(), json!(scheme.name()));
                row.insert("m".into(), json!(m));
                row.insert("given".into(), json!(given));
                let mut tiles = vec![];
                for &p in &fractions {
                    let (r, img) = ctx.score(&stego.model, &disclose(&key, p), h)?;
                    row.insert(format!("{}%", (p * 100.0) as u32), json!(r.psnr));
                    if p == 1.0 {
                        row.insert("LPIPS 100%".into(), json!(r.lpips));
                    }
                    tiles.push(img);
                }
                row.insert("wrong key".into(), json!(wrong.psnr));
                row.insert("LPIPS wrong key".into(), json!(wrong.lpips));
                row.insert("empty render".into(), json!(wrong.blank_psnr));
                t.push(serde_json::Value::Object(row));
                let file = format!(
                    "partial_{}_{}_m{m}.png",
                    scheme.name(),
                    given.replace(' ', "_")
                );
                save_grid(&ctx.cfg.out.join(&file), &tiles, w, hgt, tiles.len())?;
                report.figures.push((
                    file,
                    format!(
                        "{} m = {m}, {given} given: 0, 25, 50, 75, 100 %",
                        scheme.name()
                    ),
                ));
            }
        }
    }
    report.tables.push(t);
    report.notes.push("`primes`: the first p % of the m prime triples are given, the rest replaced by Π (the paper's ablation). `prf`, secret shares: the first p % of the secret's m equal shares are given, the rest zero; every level's subkey depends on the whole secret, so a partial key should score like a wrong key. `prf`, level subkeys: the subkeys of the first p % of the level groups leak (a side channel the key file never offers), the other levels use Π — the paper's substitution applied to `prf`. 0 % is no key at all (the cover) in every row. `empty render` is the score of an image of background colour only: a rendering that tells nothing about the hidden scene scores near it (a wrong key renders a faint haze, so it scores near the empty render rather than near the cover, an opaque object).".into());
    Ok(())
}

fn multi_hidden(ctx: &Ctx, report: &mut Report) -> Result<()> {
    let pi = Key::reference();
    let mut t = Table::new("Several hidden scenes in one model (Φ), each with its own key");
    let (w, hgt) = ctx.size();
    let mut tiles = vec![];
    for phi in 1..=4usize {
        let keys: Vec<Key> = (0..phi)
            .map(|i| experiment_key(ctx.cfg.scheme, 1, ctx.cfg.seed, i as u64, ctx.hidden(i)))
            .collect::<Result<_>>()?;
        let mut scenes: Vec<(&Scene, &Key)> = vec![(&ctx.cover, &pi)];
        for (i, k) in keys.iter().enumerate() {
            scenes.push((ctx.hidden(i), k));
        }
        ctx.log(&format!("multi-hidden: Φ = {phi}"));
        let m = ctx.train(ctx.cfg.grid, &scenes, &format!("Φ={phi}"))?;
        let (c, img_c) = ctx.score(&m.model, &pi, &ctx.cover)?;
        let mut row = serde_json::Map::new();
        row.insert("phi".into(), json!(phi));
        row.insert("cover".into(), json!(c.psnr));
        row.insert("cover LPIPS".into(), json!(c.lpips));
        tiles.push(img_c);
        let (mut hs, mut hl) = (vec![], vec![]);
        for (i, k) in keys.iter().enumerate() {
            let (r, img) = ctx.score(&m.model, k, ctx.hidden(i))?;
            row.insert(format!("hidden {}", i + 1), json!(r.psnr));
            hs.push(r.psnr);
            hl.extend(r.lpips);
            if i == 0 {
                tiles.push(img);
            }
        }
        row.insert(
            "hidden mean".into(),
            json!(hs.iter().sum::<f64>() / hs.len() as f64),
        );
        row.insert(
            "hidden mean LPIPS".into(),
            json!((!hl.is_empty()).then(|| hl.iter().sum::<f64>() / hl.len() as f64)),
        );
        t.push(serde_json::Value::Object(row));
    }
    report.tables.push(t);
    save_grid(&ctx.cfg.out.join("multi_hidden.png"), &tiles, w, hgt, 2)?;
    report.figures.push((
        "multi_hidden.png".into(),
        "Rows Φ = 1..4: the cover without key, hidden scene 1 with its key".into(),
    ));
    Ok(())
}

fn table_size(ctx: &Ctx, report: &mut Report) -> Result<()> {
    let pi = Key::reference();
    let h = ctx.hidden(0);
    let key = experiment_key(ctx.cfg.scheme, 1, ctx.cfg.seed, 0, h)?;
    let mut t = Table::new("Hash table size T");
    for log2_t in 18..=21u32 {
        let grid = GridConfig {
            log2_hashmap_size: log2_t,
            ..ctx.cfg.grid
        };
        ctx.log(&format!("table-size: T = 2^{log2_t}"));
        let m = ctx.train(
            grid,
            &[(&ctx.cover, &pi), (h, &key)],
            &format!("T=2^{log2_t}"),
        )?;
        let (c, _) = ctx.score(&m.model, &pi, &ctx.cover)?;
        let (hs, _) = ctx.score(&m.model, &key, h)?;
        t.push(json!({"T": format!("2^{log2_t}"), "params": m.model.net.layout.n_params, "cover_psnr": c.psnr,
            "cover_lpips": c.lpips, "hidden_psnr": hs.psnr, "hidden_lpips": hs.lpips, "train_s": m.seconds}));
    }
    report.tables.push(t);
    Ok(())
}

fn key_strength_report(cfg: &ExpConfig, report: &mut Report) -> Result<()> {
    use crate::stego::strength::{
        PROBE_POINTS, brute_force_years_log10, format_pow10, key_trial_cost,
    };
    use crate::stego::{DenseMode, KeyScheme};
    let layout = NerfLayout::new(ModelConfig {
        grid: cfg.grid,
        aabb_scale: 1,
    })?;
    let levels = cfg.grid.n_levels as usize;
    // Strength depends on the scheme, m and the grid, not on the key's values.
    let legacy = |m: usize| {
        Key::new(
            KeyScheme::PrfShares {
                secret: [0x5a; 32],
                m,
            },
            DenseMode::default(),
        )
    };
    let mut t = Table::new("Effective key space, from the index arithmetic actually used");
    let mut costs = Table::new(&format!(
        "Cost of one key trial on this machine, one core ({PROBE_POINTS} probe points × {levels} levels × 8 corners; median of 7 warm runs)"
    ));
    // The paper's brute-force column (RTX 5090 at 20 FPS): a figure for the basic model
    // (m = 1), "computationally infeasible" for the multi-key one (m = 16), nothing else.
    let paper_years = |scheme: &str, m: usize| match (scheme, m) {
        ("primes", 1) => json!("7.43e16"),
        ("primes", 16) => json!("infeasible"),
        _ => json!(null),
    };
    for (label, key) in [
        ("primes m=1", generate_primes(1)?),
        ("primes m=4", generate_primes(4)?),
        ("primes m=16", generate_primes(16.min(levels))?),
        ("prf", generate_prf(1)?),
        ("prf m=16", generate_prf(16.min(levels))?),
    ] {
        let s = key_strength(&key, &layout.grid);
        let c = key_trial_cost(key.scheme().kind(), s.m, &layout.grid, PROBE_POINTS, 7, 2)?;
        let years = |bits: f64, secs: f64| brute_force_years_log10(bits, secs).map(format_pow10);
        t.push(
            json!({"key": label, "scheme": s.scheme, "m": s.m, "total_bits": s.total_bits,
            "per_level_oracle_bits": s.oracle_bits, "paper_claim_bits": s.paper_claim_bits,
            "trial_ms": round2(c.trial_seconds * 1e3),
            "brute_force_years": years(s.total_bits, c.trial_seconds),
            "paper_brute_force_years": paper_years(&s.scheme, s.m),
            "oracle_years": years(s.oracle_bits, c.trial_seconds)}),
        );
        costs.push(
            json!({"key": label, "trial_ms": round2(c.trial_seconds * 1e3),
            "derive_ms": round2(c.derive_seconds * 1e3),
            "index_ms": round2(c.index_seconds * 1e3),
            "brute_force_years": years(s.total_bits, c.trial_seconds),
            "brute_force_years_index_only": years(s.total_bits, c.index_seconds),
            "brute_force_years_log10": brute_force_years_log10(s.total_bits, c.trial_seconds)
                .map(round2)}),
        );
    }
    report.tables.push(t);
    report.tables.push(costs);
    report.notes.push(format!(
        "Brute-force time: 2^(bits−1) trials (half the space on average) × the measured seconds of one trial, in Julian years (3.156e7 s). \
         A trial derives the candidate key's index functions (per-level subkeys, the dense levels' keyed permutation tables) and indexes {PROBE_POINTS} fixed probe points on every level (8 corners each), compared with the true key's indices: the fewest points that tell a scene from noise (a few dozen rays' samples); the MLP, which a real test also needs, is left out, so a real trial costs more. \
         index_ms is the trial without the derivation (index functions already built): no trial costs less, so brute_force_years_index_only, which uses it, is a lower bound (an attacker who permutes only the probes' dense-level corners, lazily, pays between index_ms and trial_ms). \
         The figures are for one CPU core of this machine: n cores, or a GPU running n trials at once, divide them by n. \
         paper_brute_force_years: the paper's table (RTX 5090 at 20 rendered frames a second, an ideal classifier): 7.43e16 years for the basic model (86.3 bits), 'computationally infeasible' for m = 16; it has no prf. \
         oracle_years: the same trial cost at per_level_oracle_bits (each group, or level, searched on its own)."
    ));
    let mut d =
        Table::new("Bits left when j of the m keys are disclosed (worst case over which j)");
    let mut ms: Vec<usize> = [1, 4, 8, 16].into_iter().filter(|&m| m <= levels).collect();
    ms.dedup();
    for (scheme, make) in [
        ("primes", &generate_primes as &dyn Fn(usize) -> Result<Key>),
        ("prf", &generate_prf),
        ("prf v1 (old shares)", &legacy),
    ] {
        for &m in &ms {
            let s = key_strength(&make(m)?, &layout.grid);
            for x in &s.after_disclosure {
                d.push(json!({"scheme": scheme, "m": m, "disclosed": x.disclosed,
                    "left": m - x.disclosed, "brute_force_bits": round2(x.brute_force_bits),
                    "oracle_bits": round2(x.oracle_bits)}));
            }
        }
    }
    report.tables.push(d);
    report.notes.push("total_bits: brute-force work for the whole key set; per_level_oracle_bits: work when each level group can be attacked on its own (the paper's partial-key table shows PSNR rises with each correct key, which is such an oracle for `primes`).".into());
    report.notes.push(format!(
        "Disclosure table ({levels} levels, T = 2^{}): `disclosed` of the m keys are known, the worst case over which (the attacker gets the most valuable: with cyclic assignment, the first groups, which hold the dense levels 0-4). \
         primes: brute_force_bits is the product of the undisclosed triples' spaces (sum of their bits: 54 per triple where a group has only hashed levels, because only k mod 2^19 matters and primes are odd; 3·log2(454 387 932) = 86.28 where it has a dense level). \
         oracle_bits is the realistic figure for primes: a correct triple raises PSNR on its own levels, so each undisclosed group is searched separately and the work is the sum 2^b1 + 2^b2 + …, not the product (within a group: residues on a hashed level, 2^54, then the remaining 32.28 bits on a dense level). \
         prf (version 2): m independent 256-bit secrets and every level's subkey needs all of them, so any j < m leaves 256 bits (the master, or the missing secret) and partial keys give no oracle; oracle_bits = 132 is a per-level side channel (a level's 128-bit subkey recognised alone, 16 levels), independent of j. \
         prf v1 (the old layout, still readable): the m keys were shares of one secret, so j disclosed leave only the undisclosed shares' bits — 16 for m = 16, j = 15.",
        cfg.grid.log2_hashmap_size
    ));
    Ok(())
}

fn round2(x: f64) -> f64 {
    (x * 100.0).round() / 100.0
}

/// One model of an experiment that trains many scene pairs (detectability), with its
/// held-out scores.
pub(super) struct PairRun {
    pub model: Model,
    pub train_seconds: f64,
    /// Scoring both scenes (for the hidden one, rebuilding its occupancy grid first).
    pub eval_seconds: f64,
    pub cover: EvalResult,
    pub hidden: Option<EvalResult>,
}

/// Trains `cfg.cover` alone (`key: None`), or with `cfg.hidden[0]` under key number `key`
/// of `cfg.scheme` (m = 1, drawn from `cfg.seed`), and scores the cover without a key and
/// the hidden scene with its key on held-out views: the same training (schedule, stealth)
/// and viewing as every other experiment, one scene pair at a time.
pub(super) fn train_pair(cfg: &ExpConfig, key: Option<u64>, label: &str) -> Result<PairRun> {
    let cover = load_scene(&cfg.cover, cfg.downscale, None)?;
    let box_scale = Some(cover.train.aabb_scale);
    let hidden = match (key, cfg.hidden.first()) {
        (None, _) => Vec::new(),
        (Some(_), Some(h)) => vec![load_scene(h, cfg.hidden_downscale, box_scale)?],
        (Some(_), None) => {
            return Err(Error::Config("a stego model needs a hidden scene".into()));
        }
    };
    let ctx = Ctx { cfg, cover, hidden };
    let pi = Key::reference();
    let key = key
        .map(|which| experiment_key(cfg.scheme, 1, cfg.seed, which, &ctx.hidden[0]))
        .transpose()?;
    let mut scenes = vec![(&ctx.cover, &pi)];
    if let Some(k) = &key {
        scenes.push((&ctx.hidden[0], k));
    }
    let trained = ctx.train(cfg.grid, &scenes, label)?;
    let t0 = std::time::Instant::now();
    let (cover, _) = ctx.score(&trained.model, &pi, &ctx.cover)?;
    let hidden = key
        .as_ref()
        .map(|k| ctx.score(&trained.model, k, &ctx.hidden[0]).map(|r| r.0))
        .transpose()?;
    Ok(PairRun {
        model: trained.model,
        train_seconds: trained.seconds,
        eval_seconds: t0.elapsed().as_secs_f64(),
        cover,
        hidden,
    })
}

#[cfg(test)]
mod tests {
    use super::{Experiment, experiment_key, load_scene};
    use crate::stego::SchemeKind;
    use crate::synth::{SceneKind, SynthOptions, generate};

    #[test]
    fn experiment_keys_name_the_hidden_scenes_own_box() {
        let d = tempfile::tempdir().unwrap();
        for (name, aabb_scale) in [("one", 1), ("four", 4)] {
            generate(
                &SynthOptions {
                    scene: SceneKind::Object,
                    resolution: 8,
                    n_train: 2,
                    n_val: 0,
                    n_test: 1,
                    seed: 1,
                    aabb_scale,
                },
                &d.path().join(name),
            )
            .unwrap();
        }
        // In a cover's box of 8, each scene keeps its own box in its key (as `keygen
        // --aabb-scale` would write it) and the same index as a key of the same number.
        let one = load_scene(&d.path().join("one"), 1, Some(8)).unwrap();
        let four = load_scene(&d.path().join("four"), 1, Some(8)).unwrap();
        assert_eq!((one.train.aabb_scale, four.test.aabb_scale), (8, 8));
        for scheme in [SchemeKind::Prf, SchemeKind::Primes] {
            let k1 = experiment_key(scheme, 4, 3, 0, &one).unwrap();
            let k4 = experiment_key(scheme, 4, 3, 0, &four).unwrap();
            assert_eq!((k1.scene_box(), k4.scene_box()), (Some(1), Some(4)));
            assert!(k1.same_index(&k4));
            assert!(!k1.same_index(&experiment_key(scheme, 4, 3, 1, &one).unwrap()));
        }
    }

    #[test]
    fn experiment_names_read_back_and_name_the_report_folders() {
        // The names are the CLI's and the report folders' (OUT/NAME/): they must not change.
        let names: Vec<String> = Experiment::ALL.iter().map(|e| e.to_string()).collect();
        assert_eq!(
            names,
            [
                "fidelity",
                "key-sensitivity",
                "partial-keys",
                "multi-hidden",
                "table-size",
                "key-strength",
                "detectability",
                "pairs"
            ]
        );
        for e in Experiment::ALL {
            assert_eq!(e.to_string().parse::<Experiment>().unwrap(), e);
            assert_eq!(e.name(), e.to_string());
        }
        for bad in ["Fidelity", "key_strength", "", "pair"] {
            let err = bad.parse::<Experiment>().unwrap_err().to_string();
            assert!(
                err.contains(&format!("unknown experiment '{bad}'")),
                "{err}"
            );
            assert!(err.contains(&names.join(", ")), "{err}");
        }
    }
}
