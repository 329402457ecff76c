//! `stegongp experiment`: the options of the experiments, their defaults, and what they
//! print; the experiments themselves, their plans of jobs and Slurm's scripts are
//! [`stegongp::experiments`]'.

mod plan;

use super::common::{DeviceArg, ensure_locked_dir};
use anyhow::{Result, bail};
use std::path::PathBuf;
use std::sync::Arc;
use stegongp::backend::Device;
use stegongp::experiments::paper;
use stegongp::experiments::report::Report;
use stegongp::experiments::{
    DetectOptions, ExpConfig, Experiment, JobMode, Mode, PairSpec, PairsOptions, RobustnessOptions,
    cover_with_each, default_attacks, read_pairs_file, run_detectability, run_experiment,
    run_pairs, run_robustness,
};
use stegongp::ngp::choice::Choice;
use stegongp::ngp::encoding::GridConfig;
use stegongp::ngp::train::Schedule;
use stegongp::stego::SchemeKind;
use stegongp::stego::options::choice;
use stegongp::synth::{SceneKind, SynthOptions, generate};
use stegongp::training::recipe::HiddenOptions;
use stegongp::training::state::SaveEvery;

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(flatten)]
    pub device: DeviceArg,
    /// fidelity | key-sensitivity | partial-keys | multi-hidden | table-size | key-strength |
    /// detectability | pairs | robustness; or `run-job DIR ID` (one job of a plan) or `collect DIR` (a
    /// plan's report from its finished jobs).
    pub name: String,
    /// run-job: the plan's folder and the job's id; collect: the plan's folder.
    #[arg(value_name = "DIR [ID]", num_args = 0..=2)]
    pub operands: Vec<PathBuf>,
    #[command(flatten)]
    pub plan: plan::PlanArgs,
    /// Output directory: the report goes to OUT/NAME/ (report.md, report.json, PNG grids),
    /// generated scenes to OUT/data/ (detectability: its scenes and models to
    /// OUT/detectability/{scenes,models}/, reused by a rerun with the same settings).
    #[arg(long, default_value = "out/experiments")]
    pub out: PathBuf,
    /// Cover scene (default: a generated object scene).
    #[arg(long)]
    pub cover: Option<PathBuf>,
    /// Hidden scene(s) (default: generated 3D text scenes).
    #[arg(long)]
    pub hidden: Vec<PathBuf>,
    /// Downscale factor of the cover's images.
    #[arg(long, default_value_t = 1)]
    pub downscale: u32,
    /// Downscale factor of the hidden scenes' images.
    #[arg(long, default_value_t = 1)]
    pub hidden_downscale: u32,
    /// Training steps per model [default: 300; detectability: 200].
    #[arg(long)]
    pub steps: Option<u32>,
    /// Samples per scene per step [default: 32768; detectability: 4096].
    #[arg(long)]
    pub batch: Option<u32>,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Held-out views evaluated per scene.
    #[arg(long, default_value_t = 8)]
    pub eval_views: usize,
    /// Fraction of the reference's occupancy-update samples [default: 0.125; detectability:
    /// 0.03].
    #[arg(long)]
    pub occupancy_fraction: Option<f32>,
    #[arg(long, default_value_t = 16)]
    pub levels: u32,
    #[arg(long, default_value_t = 2)]
    pub features: u32,
    /// log2 of the hash table size per level [default: 19; detectability: 14].
    #[arg(long)]
    pub log2_t: Option<u32>,
    /// Key scheme of the hidden scenes (key-sensitivity and partial-keys always run both).
    #[arg(long, value_enum, default_value_t = SchemeKind::Prf)]
    pub scheme: SchemeKind,
    /// How every model with hidden scenes trains them, as `train` does (models without one
    /// train plain); detectability's stealth options are its stealth arm's.
    #[command(flatten)]
    pub training: HiddenOptions,
    /// The paper's one-scene-per-step schedule: `--schedule random-scene`.
    #[arg(long, hide = true, conflicts_with = "schedule")]
    pub random_scene: bool,
    /// Resolution of generated scenes [default: 64; detectability: 32].
    #[arg(long)]
    pub res: Option<u32>,
    /// detectability: models per arm (plain, stego, stealth), each on its own pair of
    /// generated cover and hidden scene.
    #[arg(long, default_value_t = 20)]
    pub models: usize,
    /// detectability: leave out the stealth arm (plain and default stego models only).
    #[arg(long)]
    pub no_stealth_arm: bool,
    /// detectability: leave out the control arm (plain models of the same covers from
    /// another seed, scored as if they hid something: chance at this population's size).
    #[arg(long)]
    pub no_control_arm: bool,
    /// pairs, robustness: a cover/hidden pair of dataset folders, COVER:HIDDEN (repeatable)
    /// [default: --cover with each --hidden; without those, a generated object cover with a
    /// generated text (and, for pairs, a generated logo)].
    #[arg(long = "pair", value_name = "COVER:HIDDEN")]
    pub pairs: Vec<PairSpec>,
    /// pairs: a JSON file of pairs (a list of "COVER:HIDDEN" strings or {"cover", "hidden"}
    /// objects, paths relative to the file), added to --pair.
    #[arg(long = "pairs", value_name = "FILE")]
    pub pairs_file: Option<PathBuf>,
    /// pairs: train each cover's plain model this many minutes and give every model of its
    /// pairs the steps it reached (instead of --steps).
    #[arg(long)]
    pub minutes: Option<f64>,
    /// pairs: the paper's Table 1 at its scale, with --cover ROOT the NeRF-synthetic folder
    /// (chair, drums, ficus, hotdog, lego, materials, mic, ship): two generated 800 px logo
    /// scenes as its Google and Twitter, its pairing, 50 000 steps of 2^18 samples a scene,
    /// every test view scored. 18 models: make it a plan (--plan DIR --slurm).
    #[arg(long)]
    pub paper_scale: bool,
    /// robustness: an attack at one strength, as `stegongp attack` takes it (repeatable)
    /// [default: every attack at the field's strengths: noise σ 0.0005–0.01, pruning
    /// 5–50 %, int8 and int4, purify, purify-contribution 1e-8–1e-6, purify-mlp=100,
    /// finetune and finetune-renders 100/500/2000 steps, redistil=2000].
    #[arg(long = "attack", value_name = "ATTACK", value_parser = crate::cli::attack::parse_attack)]
    pub attacks: Vec<stegongp::attack::Attack>,
    /// robustness: the modes compared (comma-separated) [default: plain,default,stealth,robust].
    #[arg(long, value_delimiter = ',', value_parser = choice::<Mode>())]
    pub modes: Vec<Mode>,
    /// robustness: the long side of the cover's renders that finetune-renders, purify-mlp,
    /// redistil and purify-contribution use.
    #[arg(long, default_value_t = 200)]
    pub render_side: u32,
    /// Skip LPIPS (PSNR and SSIM only).
    #[arg(long)]
    pub no_lpips: bool,
    /// detectability and pairs, which keep their models: each model in training saves its
    /// state every N steps or M minutes (`Mm`) beside it (`MODEL.ingp.state`, owner-only,
    /// removed once the model is written), so that a rerun after an interruption goes on
    /// inside the model it was training; `off` for never.
    #[arg(long, value_name = "N|Mm|off", default_value = "10m", value_parser = parse_state_every)]
    pub save_every: StateEvery,
}

/// `--save-every`: how often, or never.
#[derive(Clone, Copy, Debug)]
pub struct StateEvery(Option<SaveEvery>);

fn parse_state_every(s: &str) -> std::result::Result<StateEvery, String> {
    if s.trim() == "off" {
        return Ok(StateEvery(None));
    }
    s.parse()
        .map(|e| StateEvery(Some(e)))
        .map_err(|e: String| format!("{e}, or off"))
}

/// detectability's defaults: 16 levels, so the hashed levels the statistics read are there;
/// covers still recognisable (about 24 dB); 60 models (3 arms × 20) in about 20 minutes
/// on 2 cores. Below 256 rays a step (the trainer's floor) a smaller batch saves nothing,
/// and fewer steps mostly cost quality: the first steps' occupancy updates and, for stego
/// models, rebuilding the hidden scene's grid to score it are fixed costs.
const DETECT_STEPS: u32 = 200;
const DETECT_BATCH: u32 = 1 << 12;
const DETECT_LOG2_T: u32 = 14;
const DETECT_RES: u32 = 32;
/// At these sizes the occupancy updates of the first 256 steps (every cell, dozens of
/// times) would cost more than the training itself; 0.03 still gives the grid its shape
/// (occupied fraction within a few tenths of a percent of 0.125's).
const DETECT_OCCUPANCY: f32 = 0.03;

pub fn run(a: Args) -> Result<()> {
    match a.name.as_str() {
        "run-job" => plan::run_job(a),
        "collect" => plan::collect(a),
        _ if a.plan.plan.is_some() => plan::make(a),
        _ => {
            if !a.operands.is_empty() {
                bail!(
                    "`experiment {}` takes no folder or job id (those belong to run-job and collect)",
                    a.name
                );
            }
            a.plan.refuse_without_plan()?;
            let (cfg, report) = experiment(a, Arc::new(JobMode::All), true)?;
            for t in &report.tables {
                println!("{}", t.markdown());
            }
            for n in &report.notes {
                println!("{n}\n");
            }
            println!("report: {}", cfg.out.join("report.md").display());
            Ok(())
        }
    }
}

/// Runs experiment `a.name` as `jobs` says (every model here, a plan, one job, or the
/// report from stored models): the options checked, the shared scenes generated, the
/// device opened. `lock`: hold the output folder for the run (a job does not: many run at
/// once in one plan's folder, each writing its own files).
fn experiment(mut a: Args, jobs: Arc<JobMode>, lock: bool) -> Result<(ExpConfig, Report)> {
    let name: Experiment = a.name.parse()?;
    if a.paper_scale {
        paper_scale(&mut a)?;
    }
    if a.random_scene {
        a.training.schedule = Schedule::RandomScene;
    }
    check_scope(&a, name)?;
    let steps = checked_steps(&a, name)?;
    let detect = name == Experiment::Detectability;
    let res = a.res.unwrap_or(if detect { DETECT_RES } else { 64 });
    // Held until the run ends: its scenes (OUT/data), models and reports would otherwise be
    // interleaved with another run's into the same folder.
    let _lock = if lock {
        Some(ensure_locked_dir(&a.out)?)
    } else {
        None
    };
    if a.paper_scale {
        paper::generate_logos(&a.out)?;
    }
    let (cover, hidden) = scenes(&a, name, res)?;
    // A plan trains nothing: it is made on whatever machine submits it, GPU or not.
    let device = if matches!(*jobs, JobMode::Plan(_)) {
        Device::open(stegongp::backend::DeviceRequest::Cpu)?
    } else {
        a.device.open()?
    };
    eprintln!("device: {}", device.report());
    let cfg = exp_config(&a, name, steps, (cover, hidden), device, jobs);
    let report = run_named(name, &a, &cfg, res)?;
    Ok((cfg, report))
}

/// Turns `--paper-scale --cover ROOT` into the paper's pairs and budget
/// ([`stegongp::experiments::paper`]), or refuses what does not fit it.
fn paper_scale(a: &mut Args) -> Result<()> {
    use paper::{BATCH, RES, STEPS};
    if a.name != "pairs" {
        bail!(
            "--paper-scale is the paper's Table 1: `experiment pairs --paper-scale --cover ROOT`"
        );
    }
    if !a.pairs.is_empty() || a.pairs_file.is_some() || !a.hidden.is_empty() {
        bail!("--paper-scale makes its own pairs: leave out --pair, --pairs and --hidden");
    }
    if a.steps.is_some() || a.minutes.is_some() || a.batch.is_some() || a.res.is_some() {
        bail!(
            "--paper-scale sets the budget ({STEPS} steps of {BATCH} samples a scene) and the logos' size ({RES} px): leave out --steps, --minutes, --batch and --res"
        );
    }
    let Some(root) = a.cover.take() else {
        bail!(
            "--paper-scale needs --cover ROOT: the NeRF-synthetic folder holding {}",
            paper::scene_names()
        );
    };
    let missing = paper::missing_scenes(&root);
    if !missing.is_empty() {
        bail!(
            "{}: --paper-scale needs the eight NeRF-synthetic scenes there ({}); missing: {}",
            root.display(),
            paper::scene_names(),
            missing.join(", ")
        );
    }
    let root = std::fs::canonicalize(&root)?;
    let data = std::path::absolute(a.out.join("data"))?;
    a.pairs = paper::pairs(&root, &data);
    a.steps = Some(STEPS);
    a.batch = Some(BATCH);
    // Every test view, as the paper scores them (unless fewer are asked for).
    if a.eval_views == 8 {
        a.eval_views = paper::TEST_VIEWS;
    }
    Ok(())
}

impl Args {
    /// Whether the scenes come as --pair / --pairs.
    fn explicit_pairs(&self) -> bool {
        !self.pairs.is_empty() || self.pairs_file.is_some()
    }
}

/// Refuses options that do not belong to experiment `name`, or contradict each other.
fn check_scope(a: &Args, name: Experiment) -> Result<()> {
    let detect = name == Experiment::Detectability;
    let pairs_exp = name == Experiment::Pairs;
    let robust_exp = name == Experiment::Robustness;
    let explicit_pairs = a.explicit_pairs();
    if !pairs_exp && a.minutes.is_some() {
        bail!("--minutes belongs to `experiment pairs`");
    }
    if !pairs_exp && !robust_exp && explicit_pairs {
        bail!("--pair and --pairs belong to `experiment pairs` and `experiment robustness`");
    }
    if !robust_exp && (!a.attacks.is_empty() || !a.modes.is_empty()) {
        bail!("--attack and --modes belong to `experiment robustness`");
    }
    if robust_exp && (a.training.stealth.enabled || a.training.robust) {
        bail!(
            "robustness trains plain, default, --stealth and --robust models itself (--modes picks them): leave out --stealth and --robust"
        );
    }
    if explicit_pairs && (a.cover.is_some() || !a.hidden.is_empty()) {
        bail!("give the scenes either as --pair/--pairs or as --cover/--hidden, not both");
    }
    if a.minutes.is_some() && a.steps.is_some() {
        bail!("--minutes and --steps both set the budget: give one");
    }
    let stealth = &a.training.stealth;
    if detect
        && (a.cover.is_some()
            || !a.hidden.is_empty()
            || stealth.enabled
            || a.training.schedule != Schedule::Mixed)
    {
        bail!(
            "detectability generates its own scenes and trains every scheme, schedule and \
             stealth itself: --cover, --hidden, --stealth and --schedule do not apply \
             (--no-stealth-arm leaves the stealth models out)"
        );
    }
    if detect && a.no_stealth_arm && (stealth.cover_only_mlp || stealth.density_cap.is_some()) {
        bail!(
            "--cover-only-mlp and --density-cap change the stealth arm, which \
             --no-stealth-arm leaves out"
        );
    }
    Ok(())
}

/// The training options checked as the recipe checks them, and the steps per model.
fn checked_steps(a: &Args, name: Experiment) -> Result<u32> {
    let detect = name == Experiment::Detectability;
    // Detectability's stealth options are its stealth arm's.
    let mut checked = a.training;
    checked.stealth.enabled |= detect;
    checked.check()?;
    let steps = a.steps.unwrap_or(if detect { DETECT_STEPS } else { 300 });
    if a.training.hidden_from > 0 && name == Experiment::KeyStrength {
        bail!("--hidden-from changes training, and key-strength trains no model");
    }
    if a.minutes.is_none() {
        a.training.check_steps(steps)?;
    }
    Ok(steps)
}

/// The cover and hidden scenes: as given, else generated under OUT/data where `name`
/// needs them (detectability makes its own; pairs given as --pair need none).
fn scenes(a: &Args, name: Experiment, res: u32) -> Result<(PathBuf, Vec<PathBuf>)> {
    let data = a.out.join("data");
    let gen_scene = |name: &str, kind: SceneKind, seed: u64| -> Result<PathBuf> {
        let dir = data.join(name);
        if !dir.join("transforms_train.json").exists() {
            let opts = SynthOptions {
                scene: kind,
                resolution: res,
                n_train: 60,
                n_val: 0,
                n_test: 10,
                seed,
                aabb_scale: 1,
                ..Default::default()
            };
            eprintln!("generating {} ({res} px)", dir.display());
            generate(&opts, &dir)?;
        }
        Ok(dir)
    };
    let needs_scenes =
        name != Experiment::KeyStrength && name != Experiment::Detectability && !a.explicit_pairs();
    let cover = match &a.cover {
        Some(c) => c.clone(),
        None if needs_scenes => gen_scene("cover_object", SceneKind::Object, 1)?,
        None => PathBuf::new(),
    };
    let mut hidden = a.hidden.clone();
    if hidden.is_empty() && needs_scenes {
        let n = if name == Experiment::MultiHidden {
            4
        } else {
            1
        };
        for i in 0..n {
            let text = ["(c) StegoNGP", "SECRET 2", "HIDDEN #3", "KEY 4 ONLY"][i];
            hidden.push(gen_scene(
                &format!("hidden_text_{}", i + 1),
                SceneKind::Text(text.into()),
                10 + i as u64,
            )?);
        }
        if name == Experiment::Pairs {
            // The paper hides two different logos; ours: a text and a logo.
            hidden.push(gen_scene("hidden_logo_1", SceneKind::Logo, 20)?);
        }
    }
    Ok((cover, hidden))
}

/// The configuration `a` asks for, with the defaults of experiment `name`.
fn exp_config(
    a: &Args,
    name: Experiment,
    steps: u32,
    (cover, hidden): (PathBuf, Vec<PathBuf>),
    device: Device,
    jobs: Arc<JobMode>,
) -> ExpConfig {
    let detect = name == Experiment::Detectability;
    ExpConfig {
        out: a.out.join(name.name()),
        cover,
        hidden,
        downscale: a.downscale,
        hidden_downscale: a.hidden_downscale,
        steps,
        batch: a
            .batch
            .unwrap_or(if detect { DETECT_BATCH } else { 1 << 15 }),
        seed: a.seed,
        eval_views: a.eval_views,
        occupancy_fraction: a.occupancy_fraction.unwrap_or(if detect {
            DETECT_OCCUPANCY
        } else {
            0.125
        }),
        grid: GridConfig {
            n_levels: a.levels,
            n_features: a.features,
            log2_hashmap_size: a.log2_t.unwrap_or(if detect { DETECT_LOG2_T } else { 19 }),
            base_resolution: 16,
        },
        scheme: a.scheme,
        training: a.training,
        lpips: !a.no_lpips,
        verbose: true,
        device: Arc::new(device),
        save_every: a.save_every.0,
        jobs,
    }
}

/// Runs experiment `name` on `cfg`, with the options of its own that `a` gives.
fn run_named(name: Experiment, a: &Args, cfg: &ExpConfig, res: u32) -> Result<Report> {
    Ok(match name {
        Experiment::Pairs => run_pairs(
            cfg,
            &PairsOptions {
                pairs: pair_specs(a, cfg)?,
                minutes: a.minutes,
                lpips: cfg.lpips,
            },
        )?,
        Experiment::Robustness => {
            let opts = RobustnessOptions {
                pairs: pair_specs(a, cfg)?,
                attacks: if a.attacks.is_empty() {
                    default_attacks()
                } else {
                    a.attacks.clone()
                },
                modes: if a.modes.is_empty() {
                    Mode::ALL.to_vec()
                } else {
                    a.modes.clone()
                },
                render_side: a.render_side,
            };
            run_robustness(cfg, &opts)?
        }
        Experiment::Detectability => {
            let opts = DetectOptions {
                models: a.models,
                stealth_arm: !a.no_stealth_arm,
                control_arm: !a.no_control_arm,
                res,
                ..DetectOptions::default()
            };
            run_detectability(cfg, &opts)?
        }
        _ => run_experiment(name, cfg)?,
    })
}

/// The pairs of pairs and robustness: --pair, then --pairs' file; without either, the
/// cover with each hidden scene.
fn pair_specs(a: &Args, cfg: &ExpConfig) -> Result<Vec<PairSpec>> {
    let mut pairs = a.pairs.clone();
    if let Some(f) = &a.pairs_file {
        pairs.extend(read_pairs_file(f)?);
    }
    if pairs.is_empty() {
        pairs = cover_with_each(&cfg.cover, &cfg.hidden);
    }
    Ok(pairs)
}
