//! The paper's main tables over cover/hidden pairs: for every pair, a plain model of the
//! cover, a plain model of the hidden scene and a stego model of both, at the same budget
//! per scene, scored on held-out views against ground truth (Table 1: PSNR, SSIM, LPIPS) and
//! against the plain models' renders (the imperceptibility protocol of watermarking papers:
//! how far does hiding move what the published model shows?).
//!
//! Budget: `--steps N` gives every scene N steps (a stego model of two scenes trains both,
//! N steps each); `--minutes M` trains each cover's plain model for M minutes and gives
//! every model of its pairs the number of steps that reached, so stego and plain models see
//! the same number of samples per scene whatever the machine was doing meanwhile.
//!
//! Models live under `OUT/models/` (`OUT` is the experiment's folder), each with a sidecar
//! JSON of everything the file depends on; a rerun with the same settings reuses every model
//! whose sidecar matches, so rerunning the report trains nothing. A scene used by several
//! pairs is trained once (per box and budget).

use super::jobs::{Action, PlannedModel, is_placeholder, placeholder};
use super::report::{Report, Table, save_grid};
use super::setup::{
    Budget, ExpConfig, Experiment, Scene, experiment_key, load_scene, train_scenes,
};
use super::store::{read_stored, reuse_or_train};
use ngp::error::{Error, Result};
use ngp::model::Model;
use ngp::network::ModelConfig;
use ngp::render::image::RenderOptions;
use score::eval::{ground_truth, spread_views};
use score::lpips::Lpips;
use score::metrics::{psnr, ssim};
use serde_json::{Value, json};
use std::path::{Path, PathBuf};
use stego::{Key, open_scene_on};
use training::state::StateSaver;

/// Bumped when what a model file depends on changes meaning.
const MODEL_FORMAT: u32 = 1;

/// One cover/hidden pair.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PairSpec {
    pub cover: PathBuf,
    pub hidden: PathBuf,
}

impl std::str::FromStr for PairSpec {
    type Err = Error;
    /// `COVER:HIDDEN`, split at the last ':' that leaves two non-empty paths (so a Windows
    /// drive letter in COVER still parses).
    fn from_str(s: &str) -> Result<Self> {
        let bad = || {
            Error::Config(format!(
                "pair '{s}': expected COVER:HIDDEN (two dataset folders)"
            ))
        };
        let i = s.rfind(':').ok_or_else(bad)?;
        let (c, h) = (&s[..i], &s[i + 1..]);
        if c.is_empty() || h.is_empty() {
            return Err(bad());
        }
        Ok(PairSpec {
            cover: c.into(),
            hidden: h.into(),
        })
    }
}

/// `cover` with each of `hidden`: the pairs of a run given `--cover` and `--hidden`.
pub fn cover_with_each(cover: &Path, hidden: &[PathBuf]) -> Vec<PairSpec> {
    hidden
        .iter()
        .map(|h| PairSpec {
            cover: cover.to_path_buf(),
            hidden: h.clone(),
        })
        .collect()
}

/// Reads a pairs file: JSON, either a list of `"COVER:HIDDEN"` strings or of
/// `{"cover": …, "hidden": …}` objects, or an object `{"pairs": [ … ]}`. Relative paths are
/// taken relative to the file's folder.
pub fn read_pairs_file(path: &Path) -> Result<Vec<PairSpec>> {
    let bad = |what: String| Error::Config(format!("{}: {what}", path.display()));
    // Ten thousand pairs are well under a megabyte; anything this large is not a pairs
    // file, and is refused before it is read.
    const MAX_BYTES: u64 = 16 << 20;
    let len = std::fs::metadata(path)
        .map_err(|e| Error::io(path, e))?
        .len();
    if len > MAX_BYTES {
        return Err(bad(format!(
            "{len} bytes: too large for a pairs file (at most {MAX_BYTES})"
        )));
    }
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let v: Value = serde_json::from_slice(&bytes).map_err(|e| bad(format!("not JSON: {e}")))?;
    let list = match &v {
        Value::Array(a) => a,
        Value::Object(o) => match o.get("pairs") {
            Some(Value::Array(a)) => a,
            _ => return Err(bad("expected a list of pairs or {\"pairs\": [...]}".into())),
        },
        _ => return Err(bad("expected a list of pairs or {\"pairs\": [...]}".into())),
    };
    let base = path.parent().unwrap_or(Path::new(""));
    let mut out = Vec::new();
    for (i, item) in list.iter().enumerate() {
        let p = match item {
            Value::String(s) => s
                .parse::<PairSpec>()
                .map_err(|e| bad(format!("pair {i}: {e}")))?,
            Value::Object(o) => {
                let field = |k: &str| {
                    o.get(k)
                        .and_then(Value::as_str)
                        .map(PathBuf::from)
                        .ok_or_else(|| bad(format!("pair {i}: missing string field '{k}'")))
                };
                PairSpec {
                    cover: field("cover")?,
                    hidden: field("hidden")?,
                }
            }
            _ => {
                return Err(bad(format!(
                    "pair {i}: expected \"COVER:HIDDEN\" or an object"
                )));
            }
        };
        out.push(PairSpec {
            cover: base.join(p.cover),
            hidden: base.join(p.hidden),
        });
    }
    if out.is_empty() {
        return Err(bad("no pairs".into()));
    }
    Ok(out)
}

/// What `experiment pairs` adds to the shared configuration.
#[derive(Clone, Debug, Default)]
pub struct PairsOptions {
    pub pairs: Vec<PairSpec>,
    /// Train each cover's plain model this long and use its steps as the budget (instead of
    /// `ExpConfig::steps`).
    pub minutes: Option<f64>,
    /// Score LPIPS (the slowest metric) as well as PSNR and SSIM.
    pub lpips: bool,
}

/// Mean PSNR / SSIM / LPIPS over views.
#[derive(Clone, Copy, Debug, Default)]
struct Scores {
    psnr: f64,
    ssim: f64,
    lpips: f64,
    /// Views with an LPIPS value (too small an image has none).
    n_lpips: usize,
    n: usize,
}

impl Scores {
    /// One view: `lpips` is its LPIPS when there is one.
    fn add(&mut self, pred: &[f32], reference: &[f32], w: usize, h: usize, lpips: Option<f64>) {
        self.push(psnr(pred, reference), ssim(pred, reference, w, h), lpips);
    }

    fn push(&mut self, psnr: f64, ssim: f64, lpips: Option<f64>) {
        self.psnr += psnr;
        self.ssim += ssim;
        if let Some(d) = lpips {
            self.lpips += d;
            self.n_lpips += 1;
        }
        self.n += 1;
    }

    /// Adds `other`'s means as one item (Table 1 averages pairs, each its views' mean).
    fn push_means(&mut self, other: &Scores) {
        let n = other.n.max(1) as f64;
        let lpips = (other.n_lpips > 0).then(|| other.lpips / other.n_lpips as f64);
        self.push(other.psnr / n, other.ssim / n, lpips);
    }

    fn mean(&self) -> Value {
        let n = self.n.max(1) as f64;
        json!({
            "psnr": round(self.psnr / n, 3),
            "ssim": round(self.ssim / n, 4),
            "lpips": (self.n_lpips > 0).then(|| round(self.lpips / self.n_lpips as f64, 4)),
        })
    }
}

fn round(x: f64, digits: i32) -> f64 {
    let p = 10f64.powi(digits);
    (x * p).round() / p
}

/// FNV-1a: a stable name for a configuration (file names, key numbers), not a secret.
fn fnv64(s: &str) -> u64 {
    s.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

fn canonical(p: &Path) -> Result<PathBuf> {
    std::fs::canonicalize(p).map_err(|e| Error::io(p, e))
}

fn scene_label(p: &Path) -> String {
    let name: String = p
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "scene".into())
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect();
    name
}

struct Models<'a> {
    cfg: &'a ExpConfig,
    dir: PathBuf,
    /// The current pair's model configuration and cover's training set (placeholders
    /// take their size and cameras).
    current: Option<(ModelConfig, std::sync::Arc<ngp::data::Dataset>)>,
    trained: usize,
    reused: usize,
}

/// A model file and what its sidecar says about its training.
struct Stored {
    model: Model,
    steps: u32,
    train_s: f64,
    reused: bool,
}

impl Models<'_> {
    /// Everything a model depends on besides its scenes and budget.
    fn base_config(&self, box_scale: u32) -> Value {
        let c = self.cfg;
        let g = &c.grid;
        json!({
            "format": MODEL_FORMAT, "batch": c.batch,
            "occupancy_fraction": c.occupancy_fraction.to_string(), "seed": c.seed,
            "levels": g.n_levels, "features": g.n_features, "log2_t": g.log2_hashmap_size,
            "base_resolution": g.base_resolution, "aabb_scale": box_scale,
            "downscale": c.downscale, "hidden_downscale": c.hidden_downscale,
        })
    }

    /// Reuses the model whose sidecar holds `config`, or trains it with `train` and stores
    /// it (model first, sidecar last: a model without its sidecar is trained again) — as
    /// the run's [`JobMode`](crate::JobMode) says. Its job's id is `stem` and a tag of
    /// `id_key`, what names the model before its budget is known (a `--minutes` budget is
    /// the steps another job reaches, `after`).
    fn get(
        &mut self,
        job: PairJob,
        config: Value,
        train: impl FnOnce(Option<StateSaver>) -> Result<(Model, u32, f64)>,
    ) -> Result<Stored> {
        let tag = format!("{:016x}", fnv64(&config.to_string()));
        let path = self.dir.join(format!("{}-{}.ingp", job.stem, &tag[..8]));
        let id = job.id();
        let planned = PlannedModel {
            id: id.clone(),
            label: job.label,
            // A budget another job measures names the file only once it is measured.
            output: if job.after.is_empty() {
                path.clone()
            } else {
                self.dir.join(format!("{}-*.ingp", job.stem))
            },
            inputs: job.inputs,
            after: job.after,
            steps: job.steps,
            samples: job.steps.map(|s| s * self.cfg.batch as u64),
            seconds: job.seconds,
        };
        let action = self.cfg.jobs.action(planned);
        if action != Action::Train {
            return self.not_trained(&id, &path, &config, action, job.steps_per_scene);
        }
        let every = self.cfg.save_every;
        let (v, reused) = reuse_or_train(&path, &config, self.cfg.verbose, every, |state| {
            let (model, steps, train_s) = train(state)?;
            let fields = json!({"steps": steps, "train_s": train_s});
            Ok((model, fields.as_object().cloned().unwrap_or_default()))
        })?;
        if reused {
            self.reused += 1;
        } else {
            self.trained += 1;
        }
        let model = if self.cfg.jobs.scores() {
            // Score what the file holds (half-precision weights), as a rerun does.
            Model::load(&path)?
        } else {
            self.stand_in()?
        };
        Ok(Stored {
            model,
            steps: v["steps"].as_u64().unwrap_or(0) as u32,
            train_s: v["train_s"].as_f64().unwrap_or(f64::NAN),
            reused,
        })
    }

    fn stand_in(&self) -> Result<Model> {
        match &self.current {
            Some((config, dataset)) => placeholder(*config, dataset),
            None => Err(Error::Other("pairs: no pair loaded".into())),
        }
    }

    /// A model this run does not train: read from its job's file (collect), or a
    /// placeholder with the steps its sidecar records, when there is one (a job whose
    /// budget another job measured reads it there).
    fn not_trained(
        &mut self,
        id: &str,
        path: &Path,
        config: &Value,
        action: Action,
        steps_per_scene: Option<u32>,
    ) -> Result<Stored> {
        let side = read_stored(path, config);
        let model = match (&side, action) {
            (Some(_), Action::Read) => {
                self.reused += 1;
                Model::load(path)?
            }
            (None, Action::Read) => {
                self.cfg.jobs.missing(id, path)?;
                self.stand_in()?
            }
            _ => self.stand_in()?,
        };
        let v = side.unwrap_or(Value::Null);
        Ok(Stored {
            model,
            // Without its sidecar: the budget in steps, or where the budget is a time not
            // yet measured, one step (a job that needs it waits for the model's job).
            steps: v["steps"]
                .as_u64()
                .map_or(steps_per_scene.unwrap_or(1), |s| s as u32),
            train_s: v["train_s"].as_f64().unwrap_or(f64::NAN),
            reused: true,
        })
    }
}

/// A model of a pair as a job.
struct PairJob {
    stem: String,
    /// What names the model before its budget is known.
    id_key: Value,
    label: String,
    inputs: Vec<PathBuf>,
    after: Vec<String>,
    steps: Option<u64>,
    /// The steps a scene, where the budget is steps.
    steps_per_scene: Option<u32>,
    seconds: Option<f64>,
}

impl PairJob {
    fn id(&self) -> String {
        let tag = format!("{:016x}", fnv64(&self.id_key.to_string()));
        format!("pairs-{}-{}", self.stem, &tag[..8])
    }
}

/// The renders and scores of one scene of a pair: plain model and stego model, each against
/// ground truth, and the stego model against the plain one.
struct SceneScores {
    plain: Scores,
    /// The plain model through the grid a key holder rebuilds (hidden scenes only): the
    /// stego model's hidden scene is scored through such a grid, never its trained one.
    plain_rebuilt: Scores,
    stego: Scores,
    stego_vs_plain: Scores,
    /// First evaluated view: ground truth, plain, stego.
    tiles: Vec<Vec<f32>>,
    size: (u32, u32),
}

fn score_scene(
    cfg: &ExpConfig,
    scene: &Scene,
    plain: &Model,
    stego: &Model,
    stego_key: &Key,
    lp: Option<&Lpips>,
) -> Result<SceneScores> {
    let pi = Key::reference();
    // The plain model is a one-scene model: its own stored grid. The stego model is opened
    // as its user would: the cover from the file, a hidden scene through its key.
    let device = &cfg.device;
    let p_open = open_scene_on(device, plain, Some(&pi), false, cfg.seed)?;
    let s_open = open_scene_on(device, stego, Some(stego_key), cfg.stealth(), cfg.seed)?;
    // A hidden scene's grid is rebuilt from the network; so is the plain model's here, so
    // that the two can also be compared on equal terms.
    let r_open = if stego_key.is_reference() {
        None
    } else {
        Some(
            open_scene_on(device, plain, Some(&pi), false, cfg.seed)?
                .with_rebuilt_grid(device, plain, cfg.seed)?,
        )
    };
    let mut p_render = p_open.renderer(device, plain)?;
    let mut s_render = s_open.renderer(device, stego)?;
    let mut r_render = match &r_open {
        Some(o) => Some(o.renderer(device, plain)?),
        None => None,
    };
    let opts = RenderOptions::default();
    let which = spread_views(scene.test.frames.len(), cfg.eval_views);
    let mut out = SceneScores {
        plain: Scores::default(),
        plain_rebuilt: Scores::default(),
        stego: Scores::default(),
        stego_vs_plain: Scores::default(),
        tiles: Vec::new(),
        size: (0, 0),
    };
    for &i in &which {
        let cam = &scene.test.frames[i].camera;
        let a = p_render.render(cam, &opts)?;
        let b = s_render.render(cam, &opts)?;
        let gt = ground_truth(&scene.test, i, opts.background);
        let (w, h) = (a.width as usize, a.height as usize);
        // Each image goes through the LPIPS network once for its three comparisons.
        let feats = lp.map(|l| {
            let (fg, (fa, fb)) = rayon::join(
                || l.features(&gt, w, h),
                || rayon::join(|| l.features(&a.rgb, w, h), || l.features(&b.rgb, w, h)),
            );
            (l, fg, fa, fb)
        });
        let d = |x: usize, y: usize| {
            let (l, fg, fa, fb) = feats.as_ref()?;
            let f = [fg, fa, fb];
            Some(l.distance_features(f[x].as_ref()?, f[y].as_ref()?))
        };
        out.plain.add(&a.rgb, &gt, w, h, d(1, 0));
        out.stego.add(&b.rgb, &gt, w, h, d(2, 0));
        if let Some(r) = r_render.as_mut() {
            let c = r.render(cam, &opts)?;
            let l = feats.as_ref().and_then(|(l, fg, _, _)| {
                Some(l.distance_features(&l.features(&c.rgb, w, h)?, fg.as_ref()?))
            });
            out.plain_rebuilt.add(&c.rgb, &gt, w, h, l);
        }
        out.stego_vs_plain.add(&b.rgb, &a.rgb, w, h, d(2, 1));
        if out.tiles.is_empty() {
            out.size = (a.width, a.height);
            out.tiles = vec![gt, a.rgb, b.rgb];
        }
    }
    Ok(out)
}

/// Runs the pairs experiment and writes its report into `cfg.out`.
pub fn run_pairs(cfg: &ExpConfig, opts: &PairsOptions) -> Result<Report> {
    let pairs = checked_pairs(opts)?;
    let models_dir = cfg.out.join("models");
    std::fs::create_dir_all(&models_dir).map_err(|e| Error::io(&models_dir, e))?;
    let lp = opts.lpips.then(Lpips::embedded);
    let mut models = Models {
        cfg,
        dir: models_dir,
        current: None,
        trained: 0,
        reused: 0,
    };
    let mut tally = Tally::new();
    let mut report = Report {
        name: Experiment::Pairs.to_string(),
        ..Default::default()
    };
    let t_all = std::time::Instant::now();
    for (k, (cover_dir, hidden_dir)) in pairs.iter().enumerate() {
        let which = (k, pairs.len());
        let pair = Pair::load(cfg, opts, &mut models, which, cover_dir, hidden_dir)?;
        let trained = pair.train(&mut models)?;
        if !cfg.jobs.scores() {
            continue;
        }
        if [&trained.plain_c, &trained.plain_h, &trained.stego]
            .iter()
            .any(|m| is_placeholder(&m.model))
        {
            // A partial report: this pair's models are not all there.
            continue;
        }
        pair.score(k, &trained, lp, &mut tally, &mut report.figures)?;
    }
    if !cfg.jobs.scores() {
        return Ok(report);
    }
    let t1 = tally.table1();
    let seconds = t_all.elapsed().as_secs_f64();
    report.setup = setup(cfg, opts, &pairs, &models, seconds);
    report.notes.push(budget_note(cfg, opts));
    report.run_notes.push(format!(
        "This run: {} models trained, {} reused.",
        models.trained, models.reused
    ));
    report.wall_clock = [
        "train s",
        "reused",
        "models_trained",
        "models_reused",
        "seconds",
        "threads",
    ]
    .map(String::from)
    .to_vec();
    report.missing_jobs = cfg.jobs.missing_jobs();
    report.tables = vec![t1, tally.per_pair, tally.imperceptibility, tally.budgets];
    report.write(&cfg.out)?;
    Ok(report)
}

/// The pairs' scene folders, canonical: every scene must exist before hours of training
/// start.
fn checked_pairs(opts: &PairsOptions) -> Result<Vec<(PathBuf, PathBuf)>> {
    if opts.pairs.is_empty() {
        return Err(Error::Config("pairs: no cover/hidden pair given".into()));
    }
    if let Some(m) = opts.minutes
        && !(m > 0.0 && m.is_finite())
    {
        return Err(Error::Config(format!(
            "--minutes must be positive, not {m}"
        )));
    }
    opts.pairs
        .iter()
        .map(|p| Ok((canonical(&p.cover)?, canonical(&p.hidden)?)))
        .collect()
}

/// One pair: its scenes and what configures and names its three models.
struct Pair<'a> {
    cfg: &'a ExpConfig,
    opts: &'a PairsOptions,
    cover_dir: &'a Path,
    hidden_dir: &'a Path,
    /// The scenes' labels in file names and tables.
    cl: String,
    hl: String,
    cover: Scene,
    hidden: Scene,
    config: ModelConfig,
    /// [`Models::base_config`] in the cover's box.
    base: Value,
    /// The budget as the models' configurations record it.
    budget_json: Value,
    /// The key of the cover (and of a plain model's only scene).
    pi: Key,
}

/// A pair's three models and the stego model's key of the hidden scene.
struct PairModels {
    plain_c: Stored,
    plain_h: Stored,
    stego: Stored,
    key: Key,
}

impl<'a> Pair<'a> {
    /// Loads the pair's scenes (the hidden scene in the cover's box) and makes the cover's
    /// the one `models` takes placeholders' size and cameras from; `which` is the pair's
    /// index and the number of pairs, for the progress line.
    fn load(
        cfg: &'a ExpConfig,
        opts: &'a PairsOptions,
        models: &mut Models,
        which: (usize, usize),
        cover_dir: &'a Path,
        hidden_dir: &'a Path,
    ) -> Result<Self> {
        let (cl, hl) = (scene_label(cover_dir), scene_label(hidden_dir));
        if cfg.verbose {
            eprintln!("pair {}/{}: {cl} : {hl}", which.0 + 1, which.1);
        }
        let cover = load_scene(cover_dir, cfg.downscale, None)?;
        let box_scale = cover.train.aabb_scale;
        let hidden = load_scene(hidden_dir, cfg.hidden_downscale, Some(box_scale))?;
        let config = ModelConfig {
            grid: cfg.grid,
            aabb_scale: box_scale,
        };
        models.current = Some((config, cover.train.clone()));
        let base = models.base_config(box_scale);
        let budget_json = match opts.minutes {
            Some(m) => json!({"minutes": m.to_string()}),
            None => json!({"steps": cfg.steps}),
        };
        Ok(Pair {
            cfg,
            opts,
            cover_dir,
            hidden_dir,
            cl,
            hl,
            cover,
            hidden,
            config,
            base,
            budget_json,
            pi: Key::reference(),
        })
    }

    /// Trains (or reuses) the plain cover, then the plain hidden scene and the stego model
    /// at the steps the cover's model took.
    fn train(&self, models: &mut Models) -> Result<PairModels> {
        let (plain_c, after) = self.plain_cover(models)?;
        let steps = plain_c.steps;
        if steps == 0 {
            return Err(Error::Other(format!(
                "the plain model of {} has no recorded step count; delete it to retrain",
                self.cover_dir.display()
            )));
        }
        let plain_h = self.plain_hidden(models, steps, after.clone())?;
        let (stego, key) = self.stego(models, steps, after)?;
        Ok(PairModels {
            plain_c,
            plain_h,
            stego,
            key,
        })
    }

    /// One of the pair's models as a job; `scenes`: how many it trains.
    fn job(
        &self,
        stem: String,
        id_key: Value,
        label: String,
        inputs: Vec<PathBuf>,
        after: Vec<String>,
        scenes: u64,
    ) -> PairJob {
        let (cfg, minutes) = (self.cfg, self.opts.minutes);
        PairJob {
            stem,
            id_key,
            label,
            inputs,
            after,
            steps: minutes.is_none().then_some(cfg.steps as u64 * scenes),
            steps_per_scene: minutes.is_none().then_some(cfg.steps),
            seconds: minutes.map(|m| m * 60.0 * scenes as f64),
        }
    }

    /// Trains a model of `scenes` (the first its cover) in the pair's box.
    fn train_model(
        &self,
        scenes: &[(&Scene, &Key)],
        budget: Budget,
        label: &str,
        state: Option<StateSaver>,
    ) -> Result<(Model, u32, f64)> {
        let t = train_scenes(self.cfg, self.config, scenes, budget, label, state)?;
        Ok((t.model, t.steps, t.seconds))
    }

    /// The plain model of the cover, and the jobs the pair's other models wait for.
    fn plain_cover(&self, models: &mut Models) -> Result<(Stored, Vec<String>)> {
        let (cfg, minutes, cl) = (self.cfg, self.opts.minutes, &self.cl);
        let config = json!({"base": self.base, "role": "plain", "scene": self.cover_dir, "downscale": cfg.downscale, "budget": self.budget_json});
        let job = self.job(
            format!("plain-{cl}"),
            config.clone(),
            format!("plain {cl}"),
            vec![self.cover_dir.to_path_buf()],
            vec![],
            1,
        );
        // A --minutes budget is the steps the plain cover reaches: its pair's other models
        // wait for it.
        let after: Vec<String> = minutes.map(|_| job.id()).into_iter().collect();
        let stored = models.get(job, config, |state| {
            let budget = match minutes {
                Some(m) => Budget::Seconds(m * 60.0),
                None => Budget::Steps(cfg.steps),
            };
            let scenes = [(&self.cover, &self.pi)];
            self.train_model(&scenes, budget, &format!("plain {cl}"), state)
        })?;
        Ok((stored, after))
    }

    /// The plain model of the hidden scene, `steps` steps.
    fn plain_hidden(&self, models: &mut Models, steps: u32, after: Vec<String>) -> Result<Stored> {
        let hl = &self.hl;
        let config = json!({"base": self.base, "role": "plain", "scene": self.hidden_dir, "downscale": self.cfg.hidden_downscale, "steps": steps});
        // Named by its budget, never by a measured step count (which a job that passes over
        // the cover's model does not have).
        let mut id_key = config.clone();
        id_key["steps"] = match self.opts.minutes {
            // Its steps are those the cover reaches: a model per cover.
            Some(_) => json!({"budget": self.budget_json, "of": self.cover_dir}),
            None => json!({"budget": self.budget_json}),
        };
        let job = self.job(
            format!("plain-{hl}"),
            id_key,
            format!("plain {hl}"),
            vec![self.hidden_dir.to_path_buf()],
            after,
            1,
        );
        models.get(job, config, |state| {
            let scenes = [(&self.hidden, &self.pi)];
            self.train_model(&scenes, Budget::Steps(steps), &format!("plain {hl}"), state)
        })
    }

    /// The stego model of both scenes, `steps` steps each, and its key of the hidden scene.
    fn stego(&self, models: &mut Models, steps: u32, after: Vec<String>) -> Result<(Stored, Key)> {
        let (cfg, cl, hl) = (self.cfg, &self.cl, &self.hl);
        // The key is a function of the pair and the seed, so reordering pairs reuses models.
        let which = fnv64(&format!(
            "{}\0{}",
            self.cover_dir.display(),
            self.hidden_dir.display()
        ));
        let key = experiment_key(cfg.scheme, 1, cfg.seed, which, &self.hidden)?;
        let config = self.stego_config(steps, which);
        let mut id_key = config.clone();
        id_key["steps"] = json!({"budget": self.budget_json});
        let job = self.job(
            format!("stego-{cl}-{hl}"),
            id_key,
            format!("stego {cl} + {hl}"),
            vec![self.cover_dir.to_path_buf(), self.hidden_dir.to_path_buf()],
            after,
            2,
        );
        let stored = models.get(job, config, |state| {
            let scenes = [(&self.cover, &self.pi), (&self.hidden, &key)];
            let label = format!("stego {cl} + {hl}");
            self.train_model(&scenes, Budget::Steps(steps), &label, state)
        })?;
        Ok((stored, key))
    }

    /// What the stego model depends on; `which`: its key's number.
    fn stego_config(&self, steps: u32, which: u64) -> Value {
        let cfg = self.cfg;
        let mut config = json!({"base": self.base, "role": "stego", "cover": self.cover_dir, "hidden": self.hidden_dir,
        "steps": steps, "scheme": cfg.scheme.name(), "key": which,
        "schedule": format!("{:?}", cfg.training.schedule),
        // A stealth model trained before stealth paced the table, before its optimizer
        // kept the cover's clock, or before the cover's density was capped, is not reused.
        "stealth": match (cfg.stealth(), cfg.trains_cover_only_mlp()) {
            (false, _) => json!(false),
            (true, false) => json!("paced on the cover's clock, density capped, left entries bounded"),
            (true, true) => json!(
                "paced on the cover's clock, density capped, left entries bounded, cover-only MLP"
            ),
        }});
        cfg.record_hidden_options(&mut config);
        if cfg.stealth() {
            cfg.record_density_cap(&mut config);
        }
        config
    }

    /// Scores pair `k`'s models into `tally` and saves its image grids (`figures`).
    fn score(
        &self,
        k: usize,
        m: &PairModels,
        lp: Option<&Lpips>,
        tally: &mut Tally,
        figures: &mut Vec<(String, String)>,
    ) -> Result<()> {
        let (cfg, cl, hl) = (self.cfg, &self.cl, &self.hl);
        let t_eval = std::time::Instant::now();
        let sc = score_scene(
            cfg,
            &self.cover,
            &m.plain_c.model,
            &m.stego.model,
            &self.pi,
            lp,
        )?;
        let sh = score_scene(
            cfg,
            &self.hidden,
            &m.plain_h.model,
            &m.stego.model,
            &m.key,
            lp,
        )?;
        let eval_s = t_eval.elapsed().as_secs_f64();
        tally.add(&format!("{cl} : {hl}"), &sc, &sh, m, eval_s);
        for (scene, s) in [("cover", &sc), ("hidden", &sh)] {
            let file = format!("pair{}_{scene}.png", k + 1);
            save_grid(&cfg.out.join(&file), &s.tiles, s.size.0, s.size.1, 3)?;
            figures.push((
                file,
                format!(
                    "pair {} ({cl} : {hl}), {scene}: ground truth | plain | stego",
                    k + 1
                ),
            ));
        }
        Ok(())
    }
}

/// The report's tables as the pairs fill them.
struct Tally {
    per_pair: Table,
    imperceptibility: Table,
    budgets: Table,
    /// Sums for Table 1: [plain cover, stego cover, plain hidden, stego hidden, plain
    /// hidden through a key holder's grid].
    table1: [Scores; 5],
}

impl Tally {
    fn new() -> Self {
        Tally {
            per_pair: Table::new("Per pair: held-out views against ground truth"),
            imperceptibility: Table::new(
                "Stego against plain: the stego model's renders scored against the plain model's",
            ),
            budgets: Table::new("Budget and training time per model"),
            table1: [Scores::default(); 5],
        }
    }

    /// Pair `pair`'s scores of its cover (`sc`) and hidden scene (`sh`), its models'
    /// budgets, and `eval_s`, the seconds scoring took.
    fn add(&mut self, pair: &str, sc: &SceneScores, sh: &SceneScores, m: &PairModels, eval_s: f64) {
        for (acc, s) in self.table1.iter_mut().zip([
            &sc.plain,
            &sc.stego,
            &sh.plain,
            &sh.stego,
            &sh.plain_rebuilt,
        ]) {
            acc.push_means(s);
        }
        let row = |label: &str, s: &Scores| {
            let m = s.mean();
            json!({"pair": pair, "scene": label,
                   "PSNR": m["psnr"], "SSIM": m["ssim"], "LPIPS": m["lpips"], "views": s.n})
        };
        self.per_pair.push(row("cover, plain", &sc.plain));
        self.per_pair.push(row("cover, stego", &sc.stego));
        self.per_pair.push(row("hidden, plain", &sh.plain));
        self.per_pair
            .push(row("hidden, plain, key holder's grid", &sh.plain_rebuilt));
        self.per_pair.push(row("hidden, stego", &sh.stego));
        self.imperceptibility.push(row("cover", &sc.stego_vs_plain));
        self.imperceptibility
            .push(row("hidden", &sh.stego_vs_plain));
        for (label, s) in [
            ("plain cover", &m.plain_c),
            ("plain hidden", &m.plain_h),
            ("stego", &m.stego),
        ] {
            self.budgets.push(json!({"pair": pair, "model": label,
                "steps per scene": s.steps, "train s": round(s.train_s, 1),
                "reused": s.reused}));
        }
        self.budgets
            .push(json!({"pair": pair, "model": "scoring (all four scenes)",
            "train s": round(eval_s, 1)}));
    }

    /// Table 1: the pairs' averages.
    fn table1(&self) -> Table {
        let t = &self.table1;
        let mut t1 =
            Table::new("Table 1: averages over pairs (held-out views, against ground truth)");
        for (method, c, h) in [
            ("Instant-NGP (plain)", Some(&t[0]), &t[2]),
            (
                "Instant-NGP (plain), hidden through a key holder's grid",
                None,
                &t[4],
            ),
            ("StegoNGP", Some(&t[1]), &t[3]),
        ] {
            // The cover is never rebuilt: that row has no cover of its own.
            let cm = c.map_or(
                json!({"psnr": null, "ssim": null, "lpips": null}),
                Scores::mean,
            );
            let hm = h.mean();
            t1.push(json!({"method": method,
                "cover PSNR": cm["psnr"], "cover SSIM": cm["ssim"], "cover LPIPS": cm["lpips"],
                "hidden PSNR": hm["psnr"], "hidden SSIM": hm["ssim"], "hidden LPIPS": hm["lpips"],
                "pairs": h.n}));
        }
        t1
    }
}

/// The report's setup; `seconds`: the run's so far.
fn setup(
    cfg: &ExpConfig,
    opts: &PairsOptions,
    pairs: &[(PathBuf, PathBuf)],
    models: &Models,
    seconds: f64,
) -> Value {
    json!({
        "pairs": pairs.iter().map(|(c, h)| json!({"cover": c, "hidden": h})).collect::<Vec<_>>(),
        "budget": match opts.minutes { Some(m) => json!({"minutes_of_plain_cover": m}), None => json!({"steps_per_scene": cfg.steps}) },
        "batch_samples_per_scene": cfg.batch, "seed": cfg.seed, "eval_views": cfg.eval_views,
        "occupancy_fraction": cfg.occupancy_fraction, "levels": cfg.grid.n_levels,
        "features": cfg.grid.n_features, "log2_hashmap_size": cfg.grid.log2_hashmap_size,
        "scheme": cfg.scheme.name(), "schedule": format!("{:?}", cfg.training.schedule),
        "stealth": cfg.stealth(), "hidden_from_step": cfg.training.hidden_from,
        "hidden_loss_weight": cfg.training.hidden_weight, "lpips": opts.lpips,
        "models_trained": models.trained, "models_reused": models.reused,
        "seconds": round(seconds, 1),
        "threads": rayon::current_num_threads(),
    })
}

/// The note on what every pair trains and how it is scored.
fn budget_note(cfg: &ExpConfig, opts: &PairsOptions) -> String {
    format!(
        "Every pair: a plain model of the cover, a plain model of the hidden scene (in the \
         cover's box) and a stego model of both, {} per scene; the cover is scored without a \
         key, the hidden scene through its key ({} m = 1, occupancy grid rebuilt as a key \
         holder does). The plain hidden model is scored through its stored grid and, in the \
         middle row of Table 1, through a grid rebuilt as the key holder's is: the stego \
         model's hidden scene against the latter is the price of sharing the table alone. \
         LPIPS: AlexNet, v0.1 linear layers.",
        match opts.minutes {
            Some(m) => format!("the steps the plain cover reached in {m} min"),
            None => format!("{} steps", cfg.steps),
        },
        cfg.scheme.name(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pair_specs_parse_at_the_last_colon() {
        let p: PairSpec = "a/lego:b/text".parse().unwrap();
        assert_eq!(p.cover, PathBuf::from("a/lego"));
        assert_eq!(p.hidden, PathBuf::from("b/text"));
        let p: PairSpec = "C:/data/lego:text".parse().unwrap();
        assert_eq!(p.cover, PathBuf::from("C:/data/lego"));
        assert!("lego".parse::<PairSpec>().is_err());
        assert!("lego:".parse::<PairSpec>().is_err());
        assert!(":text".parse::<PairSpec>().is_err());
    }

    #[test]
    fn pairs_files_take_strings_objects_and_relative_paths() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("pairs.json");
        std::fs::write(
            &f,
            r#"{"pairs": ["lego:text", {"cover": "/abs/fox", "hidden": "logo"}]}"#,
        )
        .unwrap();
        let p = read_pairs_file(&f).unwrap();
        assert_eq!(p.len(), 2);
        assert_eq!(p[0].cover, dir.path().join("lego"));
        assert_eq!(p[0].hidden, dir.path().join("text"));
        assert_eq!(p[1].cover, PathBuf::from("/abs/fox"));
        for bad in [
            "[]",
            "{\"x\": 1}",
            "[{\"cover\": \"a\"}]",
            "[3]",
            "not json",
        ] {
            std::fs::write(&f, bad).unwrap();
            let e = read_pairs_file(&f).unwrap_err().to_string();
            assert!(e.contains("pairs.json"), "{bad}: {e}");
        }
    }

    #[test]
    fn fnv_is_the_published_function() {
        // FNV-1a 64 test vectors (Fowler/Noll/Vo): "" and "a".
        assert_eq!(fnv64(""), 0xcbf2_9ce4_8422_2325);
        assert_eq!(fnv64("a"), 0xaf63_dc4c_8601_ec8c);
    }
}
