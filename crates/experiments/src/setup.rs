//! What every experiment shares: the experiments' names, their configuration, the scenes
//! they load, their keys, and training and scoring one model through the one recipe
//! ([`training::recipe`]).

use super::jobs::{Action, JobMode, PlannedModel, is_placeholder, no_scores, placeholder, slug};
use super::report::save_grid;
use super::store::{read_stored, reuse_or_train_exact};
use backend::Device;
use dataset::LoadOptions;
use ngp::data::{Dataset, Split};
use ngp::encoding::GridConfig;
use ngp::error::{Error, Result};
use ngp::model::Model;
use ngp::network::ModelConfig;
use ngp::render::image::RenderOptions;
use ngp::rng::Pcg32;
use score::eval::{EvalResult, evaluate_on, spread_views};
use score::lpips::Lpips;
use serde_json::json;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use stego::{Key, SchemeKind, generate_with, open_scene_on};
pub use training::recipe::Budget;
use training::recipe::{HiddenOptions, HiddenScene, Recipe, StepOptions, StoredLoss};
use training::run::{Event, ResumeFrom, Resumed, Run, RunOptions};
use training::state::{SaveEvery, StateSaver};

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
    Robustness,
}

impl Experiment {
    /// Every experiment, in the order the CLI lists them.
    pub const ALL: [Experiment; 9] = [
        Experiment::Fidelity,
        Experiment::KeySensitivity,
        Experiment::PartialKeys,
        Experiment::MultiHidden,
        Experiment::TableSize,
        Experiment::KeyStrength,
        Experiment::Detectability,
        Experiment::Pairs,
        Experiment::Robustness,
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
            Experiment::Robustness => "robustness",
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
pub(crate) fn experiment_key(
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
    /// How every model with hidden scenes trains them: schedule, weight, the cover's
    /// warm-up, stealth (models without hidden scenes train plain; see
    /// [`HiddenOptions::applied`]). Detectability's stealth options are its stealth arm's.
    pub training: HiddenOptions,
    /// Score LPIPS beside PSNR and SSIM (the `--no-lpips` flag turns it off).
    pub lpips: bool,
    /// Progress lines on stderr.
    pub verbose: bool,
    /// Where every model trains and renders (shared: one device for the whole run).
    pub device: Arc<Device>,
    /// How often a model of the experiments that keep their models (detectability, pairs)
    /// saves its training state, so that a rerun goes on inside it; `None`: never.
    pub save_every: Option<SaveEvery>,
    /// Train every model here, plan them as jobs, train one, or read them all back
    /// ([`JobMode`]); shared by the clones of this configuration a run makes.
    pub jobs: Arc<JobMode>,
}

impl ExpConfig {
    /// Whether this configuration's models learn their MLP from the cover alone: only
    /// stealth training does.
    pub fn trains_cover_only_mlp(&self) -> bool {
        self.training.stealth.enabled && self.training.stealth.cover_only_mlp
    }

    /// Whether the models with hidden scenes train with stealth.
    pub fn stealth(&self) -> bool {
        self.training.stealth.enabled
    }

    /// Adds to a model-with-hidden-scenes sidecar config the training options that are not
    /// at their defaults (warm-up, hidden weight, hidden batch), and nothing else: a model trained before
    /// an option existed keeps a sidecar that still matches, and is reused.
    pub(crate) fn record_hidden_options(&self, config: &mut serde_json::Value) {
        if self.training.hidden_from > 0 {
            config["hidden_from_step"] = json!(self.training.hidden_from);
        }
        if self.training.hidden_weight != 1.0 {
            // A string: serde_json's float parsing does not round-trip every f64 exactly.
            config["hidden_loss_weight"] = json!(self.training.hidden_weight.to_string());
        }
        if self.training.hidden_batch != 1.0 {
            config["hidden_batch"] = json!(self.training.hidden_batch.to_string());
        }
        if self.training.robust {
            config["robust"] = json!(true);
        }
    }

    /// Adds a stealth model's cap to its sidecar when not the default (so that models
    /// trained at the default stay reusable).
    pub(crate) fn record_density_cap(&self, config: &mut serde_json::Value) {
        if let Some(c) = self.training.stealth.density_cap {
            config["density_cap"] = json!(c.to_string());
        }
    }
}

pub(crate) struct Scene {
    /// The folder it was read from.
    pub dir: PathBuf,
    pub train: Arc<Dataset>,
    pub test: Dataset,
    pub name: String,
    /// The scene's own box (its aabb_scale as loaded, before it took the cover's).
    pub own_box: u32,
}

/// Loads a scene's splits, placed in the box of `aabb_scale` when given (hidden scenes take
/// the cover's: every model of an experiment shares the cover's box).
pub(crate) fn load_scene(dir: &Path, downscale: u32, aabb_scale: Option<u32>) -> Result<Scene> {
    let opts = LoadOptions {
        downscale,
        ..Default::default()
    };
    let mut train = dataset::load(dir, Split::Train, &opts)?;
    let mut test = dataset::load(dir, Split::Test, &opts)?;
    let own_box = train.aabb_scale;
    if let Some(a) = aabb_scale {
        train.fit_into_box(a, None)?;
        test.fit_into_box(a, None)?;
    }
    Ok(Scene {
        dir: dir.to_path_buf(),
        train: Arc::new(train),
        test,
        name: dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| dir.display().to_string()),
        own_box,
    })
}

/// An experiment's loaded scenes, and what it does with them.
pub(crate) struct Ctx<'a> {
    pub(crate) cfg: &'a ExpConfig,
    /// The experiment (its models' job ids begin with its name).
    pub(crate) name: Experiment,
    pub(crate) cover: Scene,
    pub(crate) hidden: Vec<Scene>,
}

/// A trained model and how long its training took.
pub(crate) struct Trained {
    pub model: Model,
    pub seconds: f64,
    pub samples_per_s: f64,
    /// Steps per scene (a random-scene schedule ran this many times the scene count).
    pub steps: u32,
}

/// Trains one model of `config` on `scenes` (dataset, key; the cover first, under the
/// reference key) with the experiment's batch, seed and training options, through the one
/// recipe. `Budget::Steps(n)` gives every scene n steps, whatever the schedule.
pub(crate) fn train_scenes(
    cfg: &ExpConfig,
    config: ModelConfig,
    scenes: &[(&Scene, &Key)],
    budget: Budget,
    label: &str,
    state: Option<StateSaver>,
) -> Result<Trained> {
    let Some(((cover, _), hidden)) = scenes.split_first() else {
        return Err(Error::Config(format!("{label}: no scene to train")));
    };
    let options = cfg.training.applied(hidden.len());
    let n_scenes = scenes.len();
    let per_round = options.steps_per_round(n_scenes);
    let recipe = Recipe {
        model: config,
        cover: cover.train.clone(),
        hidden: hidden
            .iter()
            .map(|(s, k)| HiddenScene {
                dataset: s.train.clone(),
                key: (*k).clone(),
                key_name: format!("the key of {}", s.name),
            })
            .collect(),
        steps: StepOptions::reference_schedule(cfg.seed, cfg.batch, cfg.occupancy_fraction),
        options,
        budget: match budget {
            Budget::Steps(n) => Budget::Steps(options.steps_for(n, n_scenes)),
            b => b,
        },
        stored_loss: StoredLoss::Last,
    };
    let in_label = |e: Error| Error::Other(format!("{label}: {e}"));
    let opts = RunOptions {
        resume: state.as_ref().map(|_| ResumeFrom::OwnState),
        save: state,
        checkpoints: None,
    };
    let recipe = recipe.check().map_err(in_label)?;
    let mut run = Run::start(&recipe, &cfg.device, opts).map_err(in_label)?;
    if cfg.verbose {
        match run.resumed() {
            Resumed::From {
                from,
                step,
                trained_seconds,
                ..
            } => eprintln!(
                "  resumed {} at step {step} ({trained_seconds:.1} s trained)",
                from.display()
            ),
            Resumed::StaleRemoved(p) => {
                eprintln!("  {}: left by another configuration, removed", p.display());
            }
            Resumed::Fresh => {}
        }
    }
    run.run(|event| {
        if let Event::StateOff { why } = event {
            eprintln!("  no training state for this model: {why}");
        }
        Ok(())
    })?;
    let trained = run.finish().map_err(in_label)?.trained;
    let t = trained.totals;
    if cfg.verbose {
        eprintln!(
            "  trained {label}: {} steps in {:.1} s ({:.0} k samples/s), loss {:.5}",
            t.steps,
            t.seconds,
            t.samples_per_second() / 1e3,
            trained.model.loss
        );
    }
    Ok(Trained {
        model: trained.model,
        seconds: t.seconds,
        samples_per_s: t.samples_per_second(),
        steps: t.steps / per_round,
    })
}

impl Ctx<'_> {
    pub(crate) fn model_config(&self, grid: GridConfig) -> ModelConfig {
        ModelConfig {
            grid,
            aabb_scale: self.cover.train.aabb_scale,
        }
    }

    pub(crate) fn log(&self, msg: &str) {
        if self.cfg.verbose {
            eprintln!("{msg}");
        }
    }

    /// Trains one model on `scenes` (dataset, key) for `cfg.steps` steps per scene — the
    /// cover uses the reference key — as the run's [`JobMode`] says: here and kept in
    /// memory (the single-machine run), as a job that stores it at full precision
    /// ([`Model::save_exact`], so that the report scores what this process would have), or
    /// read back from that job's file. A model this run passes over is a placeholder.
    pub(crate) fn train(
        &self,
        grid: GridConfig,
        scenes: &[(&Scene, &Key)],
        label: &str,
    ) -> Result<Trained> {
        let name = slug(label);
        let path = self.cfg.out.join("models").join(format!("{name}.ingp"));
        let planned = PlannedModel {
            id: format!("{}-{name}", self.name),
            label: label.to_string(),
            output: path.clone(),
            inputs: scenes.iter().map(|(s, _)| s.dir.clone()).collect(),
            after: Vec::new(),
            steps: Some(self.cfg.steps as u64 * scenes.len() as u64),
            samples: Some(self.cfg.steps as u64 * scenes.len() as u64 * self.cfg.batch as u64),
            seconds: None,
        };
        let id = planned.id.clone();
        let config = self.model_config(grid);
        let action = self.cfg.jobs.action(planned);
        let train = |state: Option<StateSaver>| {
            let budget = Budget::Steps(self.cfg.steps);
            train_scenes(self.cfg, config, scenes, budget, label, state)
        };
        if self.cfg.jobs.in_process() {
            return train(None);
        }
        let sidecar = json!({"format": 1, "experiment": self.name.name(), "model": label,
            "setup": reproducible_setup(self.cfg), "levels": grid.n_levels,
            "features": grid.n_features, "log2_t": grid.log2_hashmap_size});
        let stored = match action {
            Action::PassOver => None,
            Action::Train => {
                std::fs::create_dir_all(self.cfg.out.join("models"))
                    .map_err(|e| Error::io(&self.cfg.out, e))?;
                let every = self.cfg.save_every;
                reuse_or_train_exact(&path, &sidecar, self.cfg.verbose, every, |st| {
                    let t = train(st)?;
                    let fields = json!({"train_s": t.seconds, "samples_per_s": t.samples_per_s, "steps": t.steps});
                    Ok((t.model, fields.as_object().cloned().unwrap_or_default()))
                })?;
                // A job scores nothing: the report is written from the file.
                None
            }
            Action::Read => match read_stored(&path, &sidecar) {
                Some(v) => Some((Model::load(&path)?, v)),
                None => {
                    self.cfg.jobs.missing(&id, &path)?;
                    None
                }
            },
        };
        Ok(match stored {
            Some((model, v)) => Trained {
                model,
                seconds: v["train_s"].as_f64().unwrap_or(f64::NAN),
                samples_per_s: v["samples_per_s"].as_f64().unwrap_or(f64::NAN),
                steps: v["steps"].as_u64().unwrap_or(0) as u32,
            },
            None => Trained {
                model: placeholder(config, &self.cover.train)?,
                seconds: f64::NAN,
                samples_per_s: f64::NAN,
                steps: 0,
            },
        })
    }

    /// Writes an image grid of the report, unless this run writes no report.
    pub(crate) fn save_grid(
        &self,
        file: &str,
        tiles: &[Vec<f32>],
        w: u32,
        h: u32,
        cols: usize,
    ) -> Result<()> {
        if !self.cfg.jobs.scores() {
            return Ok(());
        }
        save_grid(&self.cfg.out.join(file), tiles, w, h, cols)
    }

    pub(crate) fn render_opts(&self) -> RenderOptions {
        RenderOptions::default()
    }

    /// Scores `model` seen through `key` on `scene`'s held-out views; the occupancy grid is
    /// the stored one for the reference key, otherwise rebuilt from the network with the key
    /// (what a key holder — or an attacker trying a key — does). Returns the scores and the
    /// rendering of the first evaluated view.
    pub(crate) fn score(
        &self,
        model: &Model,
        key: &Key,
        scene: &Scene,
    ) -> Result<(EvalResult, Vec<f32>)> {
        if is_placeholder(model) {
            return Ok((no_scores(), Vec::new()));
        }
        let device = &self.cfg.device;
        let opened = open_scene_on(device, model, Some(key), self.cfg.stealth(), self.cfg.seed)?;
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

    pub(crate) fn gt(&self, scene: &Scene) -> Vec<f32> {
        let which = spread_views(scene.test.frames.len(), self.cfg.eval_views);
        score::eval::ground_truth(&scene.test, which[0], [1.0; 3])
    }

    pub(crate) fn size(&self) -> (u32, u32) {
        (self.cover.test.width, self.cover.test.height)
    }

    pub(crate) fn hidden(&self, i: usize) -> &Scene {
        &self.hidden[i % self.hidden.len()]
    }
}

/// The configuration without what depends on the machine (threads, device): what a
/// model's training depends on, on the CPU.
pub(crate) fn reproducible_setup(cfg: &ExpConfig) -> serde_json::Value {
    let mut v = setup_json(cfg);
    if let Some(o) = v.as_object_mut() {
        for k in HOST_FIELDS {
            o.remove(*k);
        }
    }
    v
}

/// The setup's fields that name the machine a report was written on.
pub(crate) const HOST_FIELDS: &[&str] = &["threads", "device"];

/// The report's record of the configuration.
pub(crate) fn setup_json(cfg: &ExpConfig) -> serde_json::Value {
    let mut v = json!({
        "cover": cfg.cover, "hidden": cfg.hidden, "downscale": cfg.downscale, "hidden_downscale": cfg.hidden_downscale,
        "steps": cfg.steps, "batch_samples_per_scene": cfg.batch, "seed": cfg.seed,
        "eval_views": cfg.eval_views, "occupancy_fraction": cfg.occupancy_fraction,
        "levels": cfg.grid.n_levels, "features": cfg.grid.n_features,
        "log2_hashmap_size": cfg.grid.log2_hashmap_size, "scheme": cfg.scheme.name(),
        "schedule": format!("{:?}", cfg.training.schedule), "stealth": cfg.stealth(),
        "cover_only_mlp": cfg.trains_cover_only_mlp(), "hidden_from_step": cfg.training.hidden_from,
        "hidden_loss_weight": cfg.training.hidden_weight, "density_cap": cfg.training.stealth.density_cap, "lpips": cfg.lpips,
        "threads": rayon::current_num_threads(), "device": cfg.device.report(),
    });
    // Only when set, so that the sidecars of models trained before it existed still match.
    if cfg.training.robust {
        v["robust"] = json!(true);
    }
    v
}

/// One model of an experiment that trains many scene pairs (detectability), with its
/// held-out scores.
pub(crate) struct PairRun {
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
pub(crate) fn train_pair(
    cfg: &ExpConfig,
    key: Option<u64>,
    label: &str,
    state: Option<StateSaver>,
) -> Result<PairRun> {
    let cover = load_scene(&cfg.cover, cfg.downscale, None)?;
    let box_scale = Some(cover.train.aabb_scale);
    let hidden = match (key, cfg.hidden.first()) {
        (None, _) => Vec::new(),
        (Some(_), Some(h)) => vec![load_scene(h, cfg.hidden_downscale, box_scale)?],
        (Some(_), None) => {
            return Err(Error::Config("a stego model needs a hidden scene".into()));
        }
    };
    let ctx = Ctx {
        cfg,
        name: Experiment::Detectability,
        cover,
        hidden,
    };
    let pi = Key::reference();
    let key = key
        .map(|which| experiment_key(cfg.scheme, 1, cfg.seed, which, &ctx.hidden[0]))
        .transpose()?;
    let mut scenes = vec![(&ctx.cover, &pi)];
    if let Some(k) = &key {
        scenes.push((&ctx.hidden[0], k));
    }
    let trained = train_scenes(
        cfg,
        ctx.model_config(cfg.grid),
        &scenes,
        Budget::Steps(cfg.steps),
        label,
        state,
    )?;
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
    use stego::SchemeKind;
    use synth::{SceneKind, SynthOptions, generate};

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
                    ..Default::default()
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
                "pairs",
                "robustness"
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
