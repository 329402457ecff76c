use super::common::{DeviceArg, check_model_path, progress};
use anyhow::{Context, Result, bail};
use serde::Serialize;
use std::path::PathBuf;
use stegongp::backend::DeviceReport;
use stegongp::ngp::data::{Dataset, LoadOptions, Split};
use stegongp::ngp::encoding::GridConfig;
use stegongp::ngp::encoding::reference_indices;
use stegongp::ngp::eval::{evaluate_on, spread_views};
use stegongp::ngp::lpips::Lpips;
use stegongp::ngp::network::{ModelConfig, NerfLayout};
use stegongp::ngp::render::image::{Background, RenderOptions};
use stegongp::ngp::train::{DensityCap, SceneSpec, Schedule, TrainConfig};
use stegongp::stego::stealth::StealthRefresh;

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
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Target trained samples per step (the reference's 2^18 by default).
    #[arg(long, default_value_t = 1 << 18)]
    pub batch: u32,
    /// Fraction of the reference's occupancy-grid update samples.
    #[arg(long, default_value_t = 1.0)]
    pub occupancy_fraction: f32,
    /// Worker threads (gradient partitions); 0 = one per core.
    #[arg(long, default_value_t = 0)]
    pub workers: usize,
    /// Hash-grid levels.
    #[arg(long, default_value_t = 16)]
    pub levels: u32,
    /// Features per level.
    #[arg(long, default_value_t = 2)]
    pub features: u32,
    /// log2 of the hash table size T.
    #[arg(long, default_value_t = 19)]
    pub log2_t: u32,
    /// Hidden scene directory (repeat for several; each needs its own --key).
    #[arg(long)]
    pub hidden: Vec<PathBuf>,
    /// Key file of the matching --hidden scene.
    #[arg(long)]
    pub key: Vec<PathBuf>,
    #[arg(long, value_enum, default_value_t = Schedule::Mixed)]
    pub schedule: Schedule,
    /// Loss weight of each hidden scene relative to the cover's 1: where the scenes share
    /// table entries, a larger weight moves quality from the cover to the hidden scenes.
    #[arg(long, default_value_t = 1.0)]
    pub hidden_weight: f32,
    /// Steps the cover trains alone before the hidden scenes join (they train for the
    /// remaining steps). A real capture's first steps settle its occupancy grid and its
    /// background; a few hundred steps of it alone keep most of the quality a hidden scene
    /// otherwise costs it (fox: −0.3 dB against −2.1 dB at 600 steps; BENCHMARKS.md).
    #[arg(long, default_value_t = 0, requires = "hidden")]
    pub hidden_from: u32,
    /// Stealth: confine the hidden scenes to the table entries the cover itself trained
    /// (those off their initial value in the file), so that the file's statistics look like
    /// a plain model's (see `stegongp detect`); an entry the cover's occupancy grid still
    /// reaches moves only in steps where the cover's own gradient reaches it, one the grid
    /// has left keeps at most the magnitude it had then. Render and evaluate the hidden
    /// scenes with `--stealth` too.
    #[arg(long)]
    pub stealth: bool,
    /// With --stealth: the MLP learns from the cover alone, the hidden scenes train their
    /// keyed table entries only and are decoded by the cover's MLP. Fewer statistics tell
    /// the file from a plain one and the cover keeps more of its quality; the hidden scenes
    /// lose more (BENCHMARKS.md, "Stealth with the cover's own MLP").
    #[arg(long, requires = "stealth")]
    pub cover_only_mlp: bool,
    /// With --stealth: the cap on the cover's optical thickness per finest marching step
    /// (the occupancy grid's unit), 0 for none. Hidden scenes sharing the cover's entries
    /// make its network decode dense cells inside opaque objects, where no cover ray looks,
    /// and the stored grid shows them; a penalty pulls the cover's density above the cap
    /// back down (BENCHMARKS.md, "Capping the cover's density"). [default: 2]
    #[arg(long, requires = "stealth")]
    pub density_cap: Option<f32>,
    /// Evaluate the cover's test PSNR at these elapsed minutes (e.g. 2,5,10,20).
    #[arg(long, value_delimiter = ',')]
    pub checkpoints: Vec<f64>,
    /// Test views used at checkpoints.
    #[arg(long, default_value_t = 25)]
    pub eval_views: usize,
    #[arg(long, value_enum, default_value_t = Background::White)]
    pub background: Background,
    #[command(flatten)]
    pub device: DeviceArg,
    /// Print a JSON summary on stdout.
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct Checkpoint {
    minutes: f64,
    step: u32,
    psnr: f64,
    ssim: f64,
}

#[derive(Serialize)]
struct Summary {
    model: PathBuf,
    device: DeviceReport,
    steps: u32,
    train_seconds: f64,
    /// The cover's loss (what the file stores).
    final_loss: f32,
    samples_per_second: f64,
    marched_samples_per_second: f64,
    steps_per_second: f64,
    occupancy_seconds: f64,
    rays_seconds: f64,
    optimizer_seconds: f64,
    checkpoints: Vec<Checkpoint>,
}

pub fn run(a: Args) -> Result<()> {
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
    if !(a.hidden_weight.is_finite() && a.hidden_weight > 0.0) {
        bail!("--hidden-weight must be a positive number");
    }
    if let Some(c) = a.density_cap
        && !(c.is_finite() && c >= 0.0)
    {
        bail!("--density-cap must be a number ≥ 0 (0: no cap)");
    }
    if let Some(steps) = a.steps
        && a.hidden_from >= steps
    {
        bail!(
            "--hidden-from {} leaves the hidden scenes no step of the {steps} to train",
            a.hidden_from
        );
    }
    let opts = LoadOptions {
        downscale: a.downscale,
        images: a.images.clone(),
        aabb_scale: a.aabb_scale,
    };
    let cover = Dataset::load(&a.scene, Split::Train, &opts)?;
    let config = ModelConfig {
        grid: GridConfig {
            n_levels: a.levels,
            n_features: a.features,
            log2_hashmap_size: a.log2_t,
            base_resolution: 16,
        },
        aabb_scale: cover.aabb_scale,
    };
    let layout = NerfLayout::new(config)?;
    let mut scenes = vec![SceneSpec {
        dataset: std::sync::Arc::new(cover),
        indices: reference_indices(&layout.grid),
    }];
    let (hidden_scenes, hidden_keys) = super::stego_scenes(
        &a.hidden,
        &a.key,
        &layout,
        &LoadOptions {
            downscale: a.hidden_downscale,
            ..Default::default()
        },
        config.aabb_scale,
    )?;
    scenes.extend(hidden_scenes);
    if a.stealth && hidden_keys.is_empty() {
        bail!("--stealth needs at least one --hidden scene");
    }
    let eval_data = if a.checkpoints.is_empty() {
        None
    } else {
        Some(
            Dataset::load(&a.scene, Split::Test, &opts)
                .context("loading test views for --checkpoints")?,
        )
    };
    let density_cap = stealth_density_cap(&a);
    let cfg = TrainConfig {
        seed: a.seed,
        batch_samples: a.batch,
        occupancy_fraction: a.occupancy_fraction,
        schedule: a.schedule,
        hidden_loss_weight: a.hidden_weight,
        cover_paced_table: a.stealth,
        bounded_left_entries: a.stealth,
        cover_only_mlp: a.cover_only_mlp,
        density_cap,
        hidden_from_step: a.hidden_from,
        workers: a.workers,
        ..Default::default()
    };
    let device = a.device.open()?;
    let mut trainer = device.trainer(config, scenes, cfg)?;
    if a.stealth {
        trainer.set_index_refresh(Box::new(StealthRefresh::new(layout.clone(), hidden_keys)))?;
    }
    if !a.json {
        eprintln!("device: {}", device.report());
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
        if a.stealth {
            eprintln!(
                "stealth: hidden scenes confined to the entries the cover moved, those its \
                 grid reaches paced on the cover, those it left bounded, the MLP {}, {}",
                if a.cover_only_mlp {
                    "learnt from the cover alone"
                } else {
                    "shared"
                },
                match density_cap {
                    Some(c) => format!(
                        "the cover's optical thickness capped at {}",
                        c.max_optical_thickness
                    ),
                    None => "the cover's density uncapped".into(),
                }
            );
        }
    }
    let budget_s = a.minutes.map(|m| m * 60.0);
    let steps = a
        .steps
        .unwrap_or(if budget_s.is_some() { u32::MAX } else { 1000 });
    let pb = if let Some(s) = budget_s {
        progress(
            s.ceil() as u64,
            "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len}s {msg}",
        )
    } else {
        progress(
            steps as u64,
            "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} steps {msg}",
        )
    };
    let mut train_s = 0.0;
    let (mut samples, mut marched) = (0u64, 0u64);
    // The progress line shows the loss of every scene; the file stores the cover's alone,
    // as a plain model's would.
    let mut loss_ema = 0.0f32;
    let mut cover_ema: Option<f32> = None;
    let mut phase = [0.0f64; 3];
    let mut checkpoints = Vec::new();
    let mut pending: Vec<f64> = a.checkpoints.clone();
    pending.sort_by(|x, y| x.total_cmp(y));
    while trainer.step() < steps && budget_s.is_none_or(|b| train_s < b) {
        let st = trainer.train_step()?;
        train_s += st.seconds;
        samples += st.n_samples;
        marched += st.n_marched;
        phase[0] += st.occupancy_seconds;
        phase[1] += st.rays_seconds;
        phase[2] += st.optimizer_seconds;
        loss_ema = if trainer.step() == 1 {
            st.loss
        } else {
            0.95 * loss_ema + 0.05 * st.loss
        };
        if let Some(c) = st.cover_loss {
            cover_ema = Some(cover_ema.map_or(c, |e| 0.95 * e + 0.05 * c));
        }
        if budget_s.is_some() {
            pb.set_position(train_s as u64);
        } else {
            pb.set_position(trainer.step() as u64);
        }
        pb.set_message(format!(
            "step {} loss {:.5} {:.2} steps/s {:.0}k samples/s",
            trainer.step(),
            loss_ema,
            trainer.step() as f64 / train_s,
            samples as f64 / train_s / 1e3
        ));
        while let Some(&m) = pending.first() {
            if train_s < m * 60.0 {
                break;
            }
            pending.remove(0);
            let data = eval_data.as_ref().expect("loaded with checkpoints");
            let model = trainer.model(cover_ema.unwrap_or(0.0))?;
            let idx = reference_indices(&layout.grid);
            let mut renderer = device.renderer(&model, &idx, &model.grid)?;
            let opts = RenderOptions {
                background: a.background.rgb(),
                ..Default::default()
            };
            let which = spread_views(data.frames.len(), a.eval_views);
            let r = evaluate_on(
                renderer.as_mut(),
                data,
                &opts,
                Some(&which),
                Some(Lpips::embedded()),
                |_, _, _| {},
            )?;
            let line = format!(
                "checkpoint {m} min: step {} test PSNR {:.2} dB SSIM {:.4} ({} views)",
                trainer.step(),
                r.psnr,
                r.ssim,
                r.n_views
            );
            // A hidden bar (no terminal) swallows println: write the line ourselves.
            if pb.is_hidden() {
                eprintln!("{line}");
            } else {
                pb.println(line);
            }
            checkpoints.push(Checkpoint {
                minutes: m,
                step: trainer.step(),
                psnr: r.psnr,
                ssim: r.ssim,
            });
        }
    }
    pb.finish_and_clear();
    // A --minutes budget can end before --hidden-from: the file would hold the cover alone.
    if trainer.n_scenes() > 1 && trainer.step() <= a.hidden_from {
        bail!(
            "training stopped at step {} with --hidden-from {}: the hidden scenes never \
             trained; nothing written (give more --minutes or a smaller --hidden-from)",
            trainer.step(),
            a.hidden_from
        );
    }
    let model = trainer.model(cover_ema.unwrap_or(0.0))?;
    model.save(&a.out)?;
    let summary = Summary {
        model: a.out.clone(),
        device: device.report(),
        steps: trainer.step(),
        train_seconds: train_s,
        final_loss: cover_ema.unwrap_or(0.0),
        samples_per_second: samples as f64 / train_s,
        marched_samples_per_second: marched as f64 / train_s,
        steps_per_second: trainer.step() as f64 / train_s,
        occupancy_seconds: phase[0],
        rays_seconds: phase[1],
        optimizer_seconds: phase[2],
        checkpoints,
    };
    if a.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        eprintln!(
            "trained {} steps on the {} in {:.1} s ({:.2} steps/s, {:.0} k samples/s), loss {:.5}; wrote {}",
            summary.steps,
            summary.device.kind,
            summary.train_seconds,
            summary.steps_per_second,
            summary.samples_per_second / 1e3,
            summary.final_loss,
            a.out.display()
        );
    }
    Ok(())
}

/// The cover's density cap: stealth's, at `--density-cap` if given (0: none).
fn stealth_density_cap(a: &Args) -> Option<DensityCap> {
    if !a.stealth {
        return None;
    }
    DensityCap::stealth(a.density_cap)
}
