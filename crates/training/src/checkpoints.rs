//! `--checkpoints`: the cover's test views scored at given minutes of training, on the
//! training's device, as the model would be published then, with how the rays marched
//! since the previous checkpoint. The evaluation's time is not the training's.

use crate::steps::{Totals, Training};
use backend::Device;
use ngp::data::Dataset;
use ngp::encoding::{GridLayout, reference_indices};
use ngp::error::Result;
use ngp::network::{ModelConfig, NerfLayout};
use ngp::occupancy::OccupancyGrid;
use ngp::render::image::{Background, RenderOptions};
use score::eval::{Protocol, evaluate_under, spread_views};
use score::lpips::Lpips;
use serde::Serialize;

/// What to score, and when.
pub struct CheckpointPlan {
    /// The elapsed minutes of training to score at.
    pub minutes: Vec<f64>,
    /// The cover's test views.
    pub data: Dataset,
    /// How many of them (spread over the split).
    pub views: usize,
    /// The background views are scored on (`Protocol::StegoNgp` only).
    pub background: Background,
    pub protocol: Protocol,
}

/// One scored checkpoint, as `train --json` reports it.
#[derive(Serialize)]
pub struct Checkpoint {
    pub minutes: f64,
    /// The rules its views were scored under (`--eval-protocol`).
    pub protocol: Protocol,
    pub step: u32,
    pub psnr: f64,
    pub ssim: f64,
    /// AlexNet LPIPS (v0.1); none where the views are smaller than the network takes.
    pub lpips: Option<f64>,
    /// The training so far: its time, the samples that reached the loss and those marched
    /// (differences between checkpoints give the steady rates).
    pub train_seconds: f64,
    pub samples: u64,
    pub marched: u64,
    pub network: u64,
    /// Rays trained so far.
    pub rays: u64,
    /// Since the previous checkpoint (or the start): rays a step, and the samples a ray
    /// that reached the loss and that were marched.
    pub rays_per_step: f64,
    pub samples_per_ray: f64,
    pub marched_per_ray: f64,
    /// The cover's occupancy grid: the share of each cascade's cells occupied (its bit set),
    /// and the optical thickness above which a cell is occupied (`min(0.01, cascade 0's
    /// mean)`: below 0.01 while the middle of the box is still nearly empty, when faint fog
    /// counts as occupied).
    pub occupied_per_cascade: Vec<f64>,
    pub occupancy_threshold: f32,
    /// The reference's steps a cover sample stands for at the next step (the coarse march;
    /// 1: the reference's step).
    pub march_stride: u32,
    /// The training so far: its phase times (cumulative), to split a run by step range.
    #[serde(flatten)]
    pub phases: PhaseTotals,
    /// How long this checkpoint's evaluation took (not counted in the training's time).
    pub eval_seconds: f64,
    /// Seconds per evaluated view, and the network samples a ray its views took (0 where
    /// the renderer does not count them: a GPU's).
    pub seconds_per_view: f64,
    pub eval_samples_per_ray: f64,
    /// The line a front end shows for it.
    #[serde(skip)]
    pub line: String,
}

/// The training's phase times and occupancy work (cumulative), as a checkpoint and a
/// run's summary report them, in their place among the other fields.
#[derive(Serialize)]
pub struct PhaseTotals {
    pub occupancy_seconds: f64,
    pub rays_seconds: f64,
    pub optimizer_seconds: f64,
    /// Waiting for a GPU that runs ahead of the host (0 on the CPU).
    pub wait_seconds: f64,
    /// Occupancy-grid updates made and the densities they evaluated.
    pub occupancy_updates: u32,
    pub occupancy_evaluations: u64,
}

impl PhaseTotals {
    pub fn of(t: &Totals) -> Self {
        PhaseTotals {
            occupancy_seconds: t.occupancy_seconds,
            rays_seconds: t.rays_seconds,
            optimizer_seconds: t.optimizer_seconds,
            wait_seconds: t.wait_seconds,
            occupancy_updates: t.occupancy_updates,
            occupancy_evaluations: t.occupancy_evaluations,
        }
    }
}

/// How the rays marched since the previous checkpoint, and how full the grid is now.
struct MarchSince {
    rays_per_step: f64,
    samples_per_ray: f64,
    marched_per_ray: f64,
    occupied: Vec<f64>,
    threshold: f32,
    stride: u32,
}

impl MarchSince {
    fn new(now: &Totals, before: Option<&Totals>, grid: &OccupancyGrid, stride: u32) -> Self {
        let zero = Totals::default();
        let b = before.unwrap_or(&zero);
        let rays = now.rays.saturating_sub(b.rays).max(1) as f64;
        MarchSince {
            rays_per_step: rays / now.steps.saturating_sub(b.steps).max(1) as f64,
            samples_per_ray: now.samples.saturating_sub(b.samples) as f64 / rays,
            marched_per_ray: now.marched.saturating_sub(b.marched) as f64 / rays,
            occupied: (0..grid.n_cascades)
                .map(|c| grid.occupied_fraction_in(c))
                .collect(),
            threshold: grid.threshold(),
            stride,
        }
    }

    fn note(&self) -> String {
        let occ: Vec<String> = self
            .occupied
            .iter()
            .map(|f| format!("{:.0}%", 100.0 * f))
            .collect();
        let stride = if self.stride > 1 {
            format!(", marching {} steps a sample", self.stride)
        } else {
            String::new()
        };
        format!(
            "{:.0} rays a step, {:.0} samples a ray ({:.0} marched), occupied {} above {:.4}{stride}",
            self.rays_per_step,
            self.samples_per_ray,
            self.marched_per_ray,
            occ.join("/"),
            self.threshold
        )
    }
}

/// Scores the cover at the minutes of a [`CheckpointPlan`] as the training reaches them.
pub struct CheckpointScorer {
    plan: CheckpointPlan,
    /// The minutes still ahead, soonest first (a resumed run scores only those).
    pending: Vec<f64>,
    grid: GridLayout,
    last: Option<Totals>,
    pub done: Vec<Checkpoint>,
}

impl CheckpointScorer {
    /// The scorer of `plan` for a model of `model`, the training being at `training`'s
    /// time (a resumed run's checkpoints already passed are not scored).
    pub fn new(plan: CheckpointPlan, model: ModelConfig, training: &Training) -> Result<Self> {
        let done_seconds = training.totals().seconds;
        let mut pending: Vec<f64> = plan
            .minutes
            .iter()
            .copied()
            .filter(|m| m * 60.0 > done_seconds)
            .collect();
        pending.sort_by(|x, y| x.total_cmp(y));
        Ok(CheckpointScorer {
            plan,
            pending,
            grid: NerfLayout::new(model)?.grid,
            last: None,
            done: Vec::new(),
        })
    }

    /// Scores the next checkpoint the run's time has reached, if any; call until `None`.
    pub fn next_due(
        &mut self,
        training: &Training,
        device: &Device,
    ) -> Result<Option<&Checkpoint>> {
        match self.pending.first() {
            Some(&m) if training.totals().seconds >= m * 60.0 => {
                self.pending.remove(0);
                let c = self.score(m, training, device)?;
                self.done.push(c);
                Ok(self.done.last())
            }
            _ => Ok(None),
        }
    }

    /// Scores the checkpoint at `m` minutes.
    fn score(&mut self, m: f64, training: &Training, device: &Device) -> Result<Checkpoint> {
        let t = *training.totals();
        let data = &self.plan.data;
        let t_eval = std::time::Instant::now();
        let model = training.model()?;
        let idx = reference_indices(&self.grid);
        let mut renderer = device.renderer(&model, &idx, &model.grid)?;
        let opts = RenderOptions {
            background: self.plan.background.rgb(),
            ..Default::default()
        };
        let which = spread_views(data.frames.len(), self.plan.views);
        let r = evaluate_under(
            self.plan.protocol,
            renderer.as_mut(),
            data,
            &opts,
            Some(&which),
            Some(Lpips::embedded()),
            |_, _, _| {},
        )?;
        let eval_seconds = t_eval.elapsed().as_secs_f64();
        let seconds_per_view = eval_seconds / r.n_views.max(1) as f64;
        let eval_samples_per_ray =
            r.views.iter().map(|v| v.samples_per_ray).sum::<f64>() / r.n_views.max(1) as f64;
        let lpips = r.lpips.map_or(String::new(), |l| format!(" LPIPS {l:.4}"));
        let stride = training.trainer().march_stride(0);
        let march = MarchSince::new(&t, self.last.as_ref(), &model.grid, stride);
        let line = format!(
            "checkpoint {m} min: step {} test PSNR ({}) {:.2} dB SSIM {:.4}{lpips} ({} views, {:.2} s and {:.0} samples a ray a view); {}; {}",
            t.steps,
            r.protocol,
            r.psnr,
            r.ssim,
            r.n_views,
            seconds_per_view,
            eval_samples_per_ray,
            t.phase_split(),
            march.note()
        );
        self.last = Some(t);
        Ok(Checkpoint {
            minutes: m,
            protocol: r.protocol,
            step: t.steps,
            psnr: r.psnr,
            ssim: r.ssim,
            lpips: r.lpips,
            train_seconds: t.seconds,
            samples: t.samples,
            marched: t.marched,
            network: t.network,
            rays: t.rays,
            rays_per_step: march.rays_per_step,
            samples_per_ray: march.samples_per_ray,
            marched_per_ray: march.marched_per_ray,
            occupied_per_cascade: march.occupied,
            occupancy_threshold: march.threshold,
            march_stride: stride,
            phases: PhaseTotals::of(&t),
            eval_seconds,
            seconds_per_view,
            eval_samples_per_ray,
            line,
        })
    }
}
