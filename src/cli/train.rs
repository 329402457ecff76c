use super::common::{DeviceArg, check_model_path, check_parent_dir, progress};
use super::keygen;
use anyhow::{Context, Result, bail};
use indicatif::ProgressBar;
use serde::Serialize;
use std::path::PathBuf;
use std::sync::Arc;
use stegongp::backend::{Device, DeviceReport};
use stegongp::dataset::{Capture, LoadOptions};
use stegongp::ngp::data::{Dataset, Split};
use stegongp::ngp::network::ModelConfig;
use stegongp::ngp::render::image::Background;
use stegongp::score::eval::Protocol;
use stegongp::stego::options::choice;
use stegongp::training::checkpoints::{Checkpoint, CheckpointPlan, PhaseTotals};
use stegongp::training::recipe::{
    Budget, Checked, GridOptions, HiddenOptions, HiddenScene, Recipe, StepOptions, StoredLoss,
};
use stegongp::training::run::{Event, ResumeFrom, Resumed, Run, RunOptions};
use stegongp::training::state::{SaveEvery, StateFile, StateForm, StateSaver};
use stegongp::training::steps::{Totals, Training};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Scene directory: NeRF-synthetic (transforms_*.json), instant-ngp (transforms.json),
    /// COLMAP (sparse/0 with cameras/images .bin or .txt) or LLFF (poses_bounds.npy).
    pub scene: PathBuf,
    /// Model file to write (.ingp or .msgpack).
    #[arg(long)]
    pub out: PathBuf,
    /// Integer downscale factor of the cover's images (area averaging).
    #[arg(long, default_value_t = 1)]
    pub downscale: u32,
    /// COLMAP / LLFF cover: the image folder to read (e.g. images_4); default `images/`, else
    /// the `images_N/` with the smallest N.
    #[arg(long)]
    pub images: Option<String>,
    /// The cover's box, overriding its dataset's aabb_scale (a power of two ≤ 128; COLMAP and
    /// LLFF captures default to 16). Hidden scenes are placed in the same box.
    #[arg(long)]
    pub aabb_scale: Option<u32>,
    /// Integer downscale factor of the hidden scenes' images; each scene is trained at the
    /// resolution it will be evaluated at, so the cover's --downscale does not apply.
    #[arg(long, default_value_t = 1)]
    pub hidden_downscale: u32,
    /// Training steps (default 1000 unless --minutes is given).
    #[arg(long, conflicts_with = "minutes")]
    pub steps: Option<u32>,
    /// Train for this many minutes of wall-clock time (evaluation pauses excluded).
    #[arg(long)]
    pub minutes: Option<f64>,
    #[command(flatten)]
    pub step: StepOptions,
    #[command(flatten)]
    pub grid: GridOptions,
    /// Hidden scene directory (repeat for several; each needs its own --key).
    #[arg(long)]
    pub hidden: Vec<PathBuf>,
    /// Key file of the matching --hidden scene.
    #[arg(long)]
    pub key: Vec<PathBuf>,
    #[command(flatten)]
    pub training: HiddenOptions,
    /// Evaluate the cover's test PSNR at these elapsed minutes (e.g. 2,5,10,20).
    #[arg(long, value_delimiter = ',')]
    pub checkpoints: Vec<f64>,
    /// Test views used at checkpoints.
    #[arg(long, default_value_t = 25)]
    pub eval_views: usize,
    /// The background checkpoints score on (`--eval-protocol stegongp` only).
    #[arg(long, value_parser = choice::<Background>(), default_value_t = Background::White)]
    pub background: Background,
    /// The rules checkpoints score views under, as `eval --protocol` (stegongp: ours, on
    /// --background; instant-ngp: its scripts/run.py's, on black).
    #[arg(long, value_parser = choice::<Protocol>(), default_value_t = Protocol::StegoNgp)]
    pub eval_protocol: Protocol,
    #[command(flatten)]
    pub device: DeviceArg,
    /// GPU: time the device's phases (marching, grid, network, loss, compaction,
    /// optimizer, and its idle time between submissions) with timestamps on one step in N,
    /// and report the milliseconds per step of each (one extra read-back per profiled step).
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub profile_every: u32,
    /// GPU: the training forwards read an fp16 copy of the grid table, made from the f32
    /// table at the start of every step (tiny-cuda-nn's forward reads fp16 parameters;
    /// Adam keeps the f32 master): half the bytes a corner. Off by default until measured
    /// on hardware (benchmarks/gpu.md). An error on the CPU.
    #[arg(long)]
    pub half_grid: bool,
    /// Save the whole training state every N steps, or every M minutes with `Mm` (e.g.
    /// `500`, `10m`), and at the end, to `--state`: `--resume` goes on from it, on the
    /// kind of device that saved it (CPU: exactly; GPU: the same run, within noise; with
    /// --stealth too). A plain run's is a checkpoint snapshot with its optimizer
    /// state, as instant-ngp saves one (it loads it and trains on; our tools render it); a
    /// stego run's describes its hidden scenes: a secret file, owner-only, to keep like the
    /// keys.
    #[arg(long, value_name = "N|Mm", value_parser = parse_every)]
    pub save_every: Option<SaveEvery>,
    /// Where --save-every writes. A plain run's state is a snapshot, named like a model
    /// (.ingp or .msgpack; default MODEL.checkpoint.msgpack); a stego run's defaults to the
    /// model's path with `.state` added.
    #[arg(long, value_name = "PATH")]
    pub state: Option<PathBuf>,
    /// Go on from a state --save-every wrote, with the same data, keys, options and thread
    /// count; --steps and --minutes count from the run's start, not from the resume. On the
    /// CPU the resumed run's model is the uninterrupted run's, byte for byte; on the GPU it
    /// is the same run (the same steps, schedule and draws) but not bit-identical: the
    /// device's float sums depend on the order its threads add in, so its quality matches
    /// within run-to-run noise.
    #[arg(long, value_name = "STATE")]
    pub resume: Option<PathBuf>,
    /// Print a JSON summary on stdout.
    #[arg(long)]
    pub json: bool,
}

/// `--robust`: each key file records the mode (rewritten in place, owner-only, as keygen
/// writes it), so that whoever holds the key reads the scene as it trained.
fn record_robust(keys: &[PathBuf]) -> Result<()> {
    for kp in keys {
        let key = keygen::load_key_reporting(kp)?;
        if key.robust() {
            continue;
        }
        stegongp::stego::save_key(kp, &key.with_robust(true), true)
            .with_context(|| format!("{}: cannot record the robust mode in it", kp.display()))?;
        eprintln!(
            "{}: now records the robust mode (\"robust\": true): render, eval, view and \
             mesh read the hidden scene with this key alone",
            kp.display()
        );
    }
    Ok(())
}

fn parse_every(s: &str) -> std::result::Result<SaveEvery, String> {
    s.parse()
}

/// The state's path: `--state`, else beside the model: a plain run's checkpoint snapshot
/// (`MODEL.checkpoint.msgpack`: raw msgpack, quick to write, what instant-ngp reads as
/// well as `.ingp`), a stego run's secret state (`MODEL.ingp.state`).
fn state_path(a: &Args) -> PathBuf {
    a.state.clone().unwrap_or_else(|| {
        if a.hidden.is_empty() {
            a.out.with_extension("checkpoint.msgpack")
        } else {
            let mut p = a.out.clone().into_os_string();
            p.push(".state");
            PathBuf::from(p)
        }
    })
}

#[derive(Serialize)]
struct Summary {
    model: PathBuf,
    device: DeviceReport,
    steps: u32,
    train_seconds: f64,
    /// --save-every: states written, their total seconds (outside `train_seconds`), and the
    /// seconds --resume took to read and restore one.
    state_saves: u32,
    state_save_seconds: f64,
    resume_seconds: f64,
    /// --resume: the step the run went on from (null otherwise).
    resumed_at: Option<u32>,
    /// The cover's loss (what the file stores).
    final_loss: f32,
    samples_per_second: f64,
    marched_samples_per_second: f64,
    steps_per_second: f64,
    /// Per step: samples that reached the loss (trained), marched, and run through the
    /// whole network (forward passes counted separately).
    trained_per_step: f64,
    marched_per_step: f64,
    network_per_step: f64,
    /// Rays that trained nothing because a device buffer was full (0 on the CPU).
    dropped_rays: u64,
    /// Times the host waited for the device, and command submissions, per step (0 on the
    /// CPU).
    host_waits_per_step: f64,
    submissions_per_step: f64,
    #[serde(flatten)]
    phases: PhaseTotals,
    /// The budget that sized the updates (evaluations per trained sample); null for the
    /// reference's schedule.
    occupancy_budget: Option<f32>,
    /// The coarse march's aim (samples a ray), null for the reference's step throughout.
    coarse_march: Option<u32>,
    /// Whether the training forwards read the grid's fp16 copy (--half-grid).
    half_grid: bool,
    checkpoints: Vec<Checkpoint>,
    /// With --profile-every: milliseconds per profiled step in each device phase.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    device_phases_ms: Vec<Phase>,
    /// With --refine-cameras: how far the cover's cameras moved.
    #[serde(skip_serializing_if = "Option::is_none")]
    cameras: Option<CameraMoves>,
}

/// How far refinement moved the training cameras from their given poses.
#[derive(Serialize)]
struct CameraMoves {
    images: usize,
    updates: u32,
    /// The turn of each camera, in degrees: mean and largest.
    mean_rotation_degrees: f64,
    max_rotation_degrees: f64,
    /// The shift of each camera's centre, in scene units: mean and largest.
    mean_translation: f64,
    max_translation: f64,
}

impl CameraMoves {
    fn of(c: &ngp::train::cameras::CameraRefiner) -> Self {
        use ngp::geometry::norm;
        let offsets = c.offsets();
        let rot: Vec<f64> = (offsets.iter())
            .map(|o| (norm([o[0], o[1], o[2]]) as f64).to_degrees())
            .collect();
        let pos: Vec<f64> = (offsets.iter())
            .map(|o| norm([o[3], o[4], o[5]]) as f64)
            .collect();
        let n = rot.len().max(1) as f64;
        CameraMoves {
            images: rot.len(),
            updates: c.updates(),
            mean_rotation_degrees: rot.iter().sum::<f64>() / n,
            max_rotation_degrees: rot.iter().copied().fold(0.0, f64::max),
            mean_translation: pos.iter().sum::<f64>() / n,
            max_translation: pos.iter().copied().fold(0.0, f64::max),
        }
    }
}

#[derive(Serialize)]
struct Phase {
    phase: String,
    ms: f64,
}

/// What `--resume` read before anything else: the state's bytes and the seconds reading took.
struct ResumeBytes {
    bytes: Vec<u8>,
    read_seconds: f64,
}

/// Every option that can be checked before an image is read (the recipe checks them again
/// with the scenes and keys), and the state `--resume` names, read.
fn check_args(a: &Args) -> Result<Option<ResumeBytes>> {
    check_model_path(&a.out)?;
    if a.hidden.len() != a.key.len() {
        bail!(
            "{} --hidden scene(s) but {} --key file(s): each hidden scene needs its own key",
            a.hidden.len(),
            a.key.len()
        );
    }
    if a.downscale == 0 || a.hidden_downscale == 0 {
        bail!("--downscale and --hidden-downscale must be at least 1");
    }
    a.training.check()?;
    let t_read = std::time::Instant::now();
    let resume = match &a.resume {
        Some(p) => Some(ResumeBytes {
            bytes: std::fs::read(p).with_context(|| format!("reading {}", p.display()))?,
            read_seconds: t_read.elapsed().as_secs_f64(),
        }),
        None => None,
    };
    if a.save_every.is_some() {
        let sp = state_path(a);
        if a.hidden.is_empty() {
            // A plain run's state is a snapshot: refuse a name the writer would refuse at
            // the first save, after the steps before it were spent.
            check_model_path(&sp).with_context(|| "--state: a plain run's state is a snapshot")?;
        } else {
            check_parent_dir(&sp)?;
        }
        if sp == a.out {
            bail!(
                "--state {}: the model and the state need two files",
                sp.display()
            );
        }
    }
    Ok(resume)
}

/// The recipe of the scenes and keys the options name, checked (a `--robust` run's keys
/// then record the mode), and the test views `--checkpoints` scores.
fn load_recipe(a: &Args) -> Result<(Checked, Option<Dataset>)> {
    let opts = LoadOptions {
        downscale: a.downscale,
        images: a.images.clone(),
        aabb_scale: a.aabb_scale,
    };
    // The cover's capture is imported once for its training images and its test views.
    let mut capture = Capture::new(&a.scene, &opts);
    let cover = capture.load(Split::Train)?;
    let model = ModelConfig {
        grid: a.grid.grid(),
        aabb_scale: cover.aabb_scale,
    };
    let hidden_opts = LoadOptions {
        downscale: a.hidden_downscale,
        ..Default::default()
    };
    let hidden = a
        .hidden
        .iter()
        .zip(&a.key)
        .map(|(dir, kp)| {
            let mut key = keygen::load_key_reporting(kp)?;
            if a.training.robust {
                key = key.with_robust(true);
            }
            let name = kp.display().to_string();
            Ok(HiddenScene::load(
                dir,
                key,
                &name,
                &hidden_opts,
                model.aabb_scale,
            )?)
        })
        .collect::<Result<Vec<_>>>()?;
    let budget = match (a.steps, a.minutes) {
        (_, Some(m)) => Budget::Seconds(m * 60.0),
        (steps, None) => Budget::Steps(steps.unwrap_or(1000)),
    };
    let recipe = Recipe {
        model,
        cover: Arc::new(cover),
        hidden,
        steps: a.step,
        options: a.training,
        budget,
        stored_loss: StoredLoss::Smoothed,
    };
    let recipe = recipe.check()?;
    if a.training.robust {
        record_robust(&a.key)?;
    }
    let eval_data = if a.checkpoints.is_empty() {
        None
    } else {
        Some(
            capture
                .load(Split::Test)
                .context("loading test views for --checkpoints")?,
        )
    };
    Ok((recipe, eval_data))
}

/// What the run does besides stepping: go on from `--resume`'s state, save states on
/// `--save-every`'s cadence, score `--checkpoints`.
fn run_options(a: &Args, resume: Option<ResumeBytes>, eval: Option<Dataset>) -> RunOptions {
    let resume = resume
        .zip(a.resume.clone())
        .map(|(r, origin)| ResumeFrom::Bytes {
            bytes: r.bytes,
            origin,
        });
    let save = a.save_every.map(|every| {
        let form = if a.hidden.is_empty() {
            StateForm::Snapshot
        } else {
            StateForm::Secret
        };
        let path = state_path(a);
        StateSaver::for_run(every, StateFile { path, form })
    });
    let checkpoints = eval.map(|data| CheckpointPlan {
        minutes: a.checkpoints.clone(),
        data,
        views: a.eval_views,
        background: a.background,
        protocol: a.eval_protocol,
    });
    RunOptions {
        resume,
        save,
        checkpoints,
    }
}

/// Where `--resume` went on from: the seconds it took (reading the state included) and the
/// step; said unless `--json`.
fn resumed(a: &Args, run: &Run, read_seconds: f64) -> (f64, Option<u32>) {
    let Resumed::From {
        from,
        step,
        trained_seconds,
        seconds,
    } = run.resumed()
    else {
        return (0.0, None);
    };
    if !a.json {
        eprintln!(
            "resumed from {} at step {step} ({trained_seconds:.1} s trained)",
            from.display()
        );
    }
    (seconds + read_seconds, Some(*step))
}

/// `--half-grid` and `--profile-every` on the device that trains.
fn configure_device(a: &Args, training: &mut Training, device: &Device) -> Result<()> {
    if a.half_grid {
        training.trainer_mut().half_grid()?;
    }
    if a.profile_every > 0 && !training.trainer_mut().profile_device(a.profile_every) {
        eprintln!(
            "--profile-every: {} cannot time its phases (no timestamp queries); ignored",
            device.report()
        );
    }
    Ok(())
}

/// What the run is about to do: the device, how the occupancy grid updates and rays march,
/// the scenes, and the hidden scenes' mode.
fn describe(a: &Args, recipe: &Recipe, training: &Training, device: &Device) {
    eprintln!("device: {}", device.report());
    eprintln!(
        "occupancy updates: {}",
        match (recipe.occupancy_budget(device), a.step.occupancy_budget) {
            (Some(r), None) => format!(
                "the reference's steps, each sized to {r} density evaluation(s) per trained sample (this device's default; --occupancy-budget 0 for the reference's)"
            ),
            (Some(r), Some(_)) => format!(
                "the reference's steps, each sized to {r} density evaluation(s) per trained sample"
            ),
            (None, _) => "the reference's schedule".to_string(),
        }
    );
    eprintln!(
        "training march: {}",
        match recipe.coarse_march(device) {
            Some(s) => format!(
                "coarser (2, 4 or 8 steps a sample) while rays reach the loss with ≥ {} samples at the reference's step (--coarse-march 0 for the reference's)",
                2 * s
            ),
            None => "the reference's step".to_string(),
        }
    );
    let trainer = training.trainer();
    for i in 0..trainer.n_scenes() {
        let d = trainer.dataset(i);
        let role = if i == 0 { "cover" } else { "hidden" };
        eprintln!(
            "{role}: {} images of {}×{}",
            d.frames.len(),
            d.width,
            d.height
        );
    }
    eprintln!(
        "cameras: {}",
        if trainer.cameras().is_some() {
            "the cover's refined as it trains (a rotation and a translation an image)"
        } else {
            "as given (--refine-cameras to refine them)"
        }
    );
    if a.training.stealth.enabled {
        eprintln!("{}", a.training.stealth.describe());
    }
    if a.training.robust {
        eprintln!(
            "robust: hidden scenes confined to the table entries the cover's occupancy grid reaches"
        );
    }
}

/// The bar, in seconds or steps as the budget counts.
fn progress_bar(budget: Budget) -> ProgressBar {
    match budget {
        Budget::Seconds(s) => progress(
            s.ceil() as u64,
            "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len}s {msg}",
        ),
        Budget::Steps(n) => progress(
            n as u64,
            "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} steps {msg}",
        ),
    }
}

fn show_progress(pb: &ProgressBar, budget: Budget, training: &Training) {
    let t = training.totals();
    match budget {
        Budget::Seconds(_) => pb.set_position(t.seconds as u64),
        Budget::Steps(_) => pb.set_position(t.steps as u64),
    }
    pb.set_message(format!(
        "step {} loss {:.5} {:.2} steps/s {:.0}k samples/s {}",
        t.steps,
        training.shown_loss(),
        t.steps_per_second(),
        t.samples_per_second() / 1e3,
        t.phase_split()
    ));
}

pub fn run(a: Args) -> Result<()> {
    let state = check_args(&a)?;
    let read_seconds = state.as_ref().map_or(0.0, |r| r.read_seconds);
    let (recipe, eval_data) = load_recipe(&a)?;
    let device = a.device.open()?;
    let mut run = Run::start(&recipe, &device, run_options(&a, state, eval_data))?;
    let (resume_seconds, resumed_at) = resumed(&a, &run, read_seconds);
    configure_device(&a, run.training_mut(), &device)?;
    if !a.json {
        describe(&a, &recipe, run.training(), &device);
    }
    let pb = progress_bar(recipe.budget);
    run.run(|event| {
        match event {
            Event::Step(training) => show_progress(&pb, recipe.budget, training),
            // A hidden bar (no terminal) swallows println: write the line ourselves.
            Event::Checkpoint(c) if pb.is_hidden() => eprintln!("{}", c.line),
            Event::Checkpoint(c) => pb.println(&c.line),
            Event::StateSaved { .. } | Event::StateOff { .. } => {}
        }
        Ok(())
    })?;
    pb.finish_and_clear();
    if let Some(file) = run.save_last_state()?
        && !a.json
    {
        say_state(file);
    }
    let cameras = run.training().trainer().cameras().map(CameraMoves::of);
    let device_phases_ms: Vec<Phase> = run
        .device_profile()
        .into_iter()
        .map(|(phase, ms)| Phase { phase, ms })
        .collect();
    // A --minutes budget can end before --hidden-from: the file would hold the cover alone.
    let done = run
        .finish()
        .map_err(|e| anyhow::anyhow!("{e}; nothing written"))?;
    let trained = done.trained;
    trained.model.save(&a.out)?;
    let t = trained.totals;
    let steps = t.steps.max(1) as f64;
    let summary = Summary {
        model: a.out.clone(),
        device: device.report(),
        steps: t.steps,
        train_seconds: t.seconds,
        state_saves: done.state_saves,
        state_save_seconds: done.state_save_seconds,
        resume_seconds,
        resumed_at,
        final_loss: trained.model.loss,
        samples_per_second: t.samples as f64 / t.seconds,
        marched_samples_per_second: t.marched as f64 / t.seconds,
        steps_per_second: t.steps as f64 / t.seconds,
        trained_per_step: t.samples as f64 / steps,
        marched_per_step: t.marched as f64 / steps,
        network_per_step: t.network as f64 / steps,
        dropped_rays: t.dropped_rays,
        host_waits_per_step: t.host_waits as f64 / steps,
        submissions_per_step: t.submissions as f64 / steps,
        phases: PhaseTotals::of(&t),
        occupancy_budget: recipe.occupancy_budget(&device),
        coarse_march: recipe.coarse_march(&device),
        half_grid: a.half_grid,
        checkpoints: done.checkpoints,
        device_phases_ms,
        cameras,
    };
    report(&summary, &t, &a)
}

/// Where the run's last state is, and what it is.
fn say_state(file: &StateFile) {
    if file.form == StateForm::Snapshot {
        eprintln!(
            "training state: {} (a snapshot with its optimizer state: --resume goes on from it, instant-ngp loads it)",
            file.path.display()
        );
    } else {
        eprintln!(
            "training state: {} (owner-only; --resume goes on from it; it describes the hidden scenes: keep it like the keys, delete it when done)",
            file.path.display()
        );
    }
}

fn report(summary: &Summary, t: &Totals, a: &Args) -> Result<()> {
    if a.json {
        println!("{}", serde_json::to_string_pretty(summary)?);
        return Ok(());
    }
    for p in &summary.device_phases_ms {
        eprintln!("device {:>8.3} ms a step  {}", p.ms, p.phase);
    }
    if let Some(c) = &summary.cameras {
        eprintln!(
            "cameras: {} refined in {} updates; turned {:.3}° on average ({:.3}° at most), moved {:.4} ({:.4} at most)",
            c.images,
            c.updates,
            c.mean_rotation_degrees,
            c.max_rotation_degrees,
            c.mean_translation,
            c.max_translation
        );
    }
    eprintln!(
        "trained {} steps on the {} in {:.1} s ({:.2} steps/s, {:.0} k samples/s; {}), loss {:.5}; wrote {}",
        summary.steps,
        summary.device.kind,
        summary.train_seconds,
        summary.steps_per_second,
        summary.samples_per_second / 1e3,
        t.phase_split(),
        summary.final_loss,
        a.out.display()
    );
    Ok(())
}
