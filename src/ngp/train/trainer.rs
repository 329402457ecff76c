//! The trainer: one shared set of weights, one or more scenes, each with its own per-level
//! index functions and its own occupancy grid. With one scene and the reference index this
//! is plain Instant-NGP training; the stego layer only chooses the scenes and indices.
//!
//! A step: refresh the occupancy grids on the reference schedule, draw rays (equal chunks per
//! image, uniform pixels at their centres, random background for RGBA data), march them,
//! run the network, composite, take the Huber loss, backpropagate, one Adam step. Rays are
//! split into one fixed range per worker, each with its own gradient buffer, summed in a
//! fixed order: the result is deterministic for a seed and worker count.

use super::density_cap::{DensityCap, cap_gradient};
use super::left_entries::LeftEntries;
use super::loss::{DENSITY_PULL_UP, ray_loss};
use super::optimizer::{Optimizer, OptimizerConfig, Touched};
use super::pacing::{CoverOnlyMlp, Pacing};
use crate::error::{Error, Result};
use crate::ngp::data::Dataset;
use crate::ngp::encoding::{LevelIndices, check_indices};
use crate::ngp::network::ModelConfig;
use crate::ngp::network::nerf::{CHUNK, NerfNetwork, Workspace};
use crate::ngp::occupancy::{MIN_OPTICAL_THICKNESS, OccupancyGrid};
use crate::ngp::render::composite::TRAIN_MIN_TRANSMITTANCE;
use crate::ngp::render::march::{MAX_SAMPLES_PER_RAY, Marcher, advance_n_steps};
use crate::rng::Pcg32;
use rayon::prelude::*;
use std::sync::Arc;

/// How the scenes of a multi-scene model share the steps.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum Schedule {
    /// Every batch mixes rays of all scenes.
    ///
    /// Our default.
    Mixed,
    /// One scene per step (the StegoNGP paper's Algorithm 1).
    ///
    /// The scene is drawn at random.
    RandomScene,
}

impl Schedule {
    /// The name `train --schedule` takes and reports print.
    pub fn name(self) -> &'static str {
        match self {
            Schedule::Mixed => "mixed",
            Schedule::RandomScene => "random-scene",
        }
    }
}

#[derive(Clone, Debug)]
pub struct TrainConfig {
    pub seed: u64,
    /// Target number of trained (compacted) samples per step, per scene in a mixed batch.
    pub batch_samples: u32,
    /// Fraction of the reference's occupancy-update sample count (1 = reference).
    pub occupancy_fraction: f32,
    pub schedule: Schedule,
    /// Loss weight of every scene after the first (the hidden scenes of a stego model), relative
    /// to the first scene's 1. Shared table entries settle where the scenes' gradients balance.
    pub hidden_loss_weight: f32,
    /// Table entries move only in steps where the cover's (scene 0's) own gradient reaches
    /// them; the other scenes' gradients on an entry wait, summed, for the cover's next
    /// touch. Each entry then takes as many Adam steps as the cover alone gives it. Adam
    /// moves an entry by about the learning rate per step whatever the gradient's size, so a
    /// table whose entries took extra steps for another scene is measurably larger than a
    /// plain model's (stealth training sets this; see `stego::stealth`).
    ///
    /// It also keeps the optimizer on the cover's clock: a step that does not train the
    /// cover (the random-scene schedule's hidden-scene steps) updates no weight and no
    /// occupancy grid, its gradients waiting for the next step that trains the cover. A
    /// plain model's MLP takes one Adam, L2 and EMA step per cover step; one that took the
    /// hidden scenes' steps as well ends with other weight moments, which gave paced
    /// stealth models away under that schedule at any hidden weight (BENCHMARKS.md).
    pub cover_paced_table: bool,
    /// The MLP learns from the cover (scene 0) alone: the other scenes' gradients reach the
    /// table only, and a step without the cover gives the MLP a zero gradient. A plain
    /// model's MLP is what its cover made it; one that also decodes hidden scenes drifts
    /// measurably from it (its first density layer's spread gave the paced stealth models
    /// away, BENCHMARKS.md). `train --stealth --cover-only-mlp` sets this.
    pub cover_only_mlp: bool,
    /// Table entries the cover's occupancy grid no longer lets training reach keep at most
    /// the magnitude they had (in the published weights) when it stopped reaching them, and
    /// with [`Self::cover_paced_table`] the other scenes move them at their own pace (no
    /// cover gradient will reach them again). Stealth training sets it: a hidden scene then
    /// shares the entries the cover left, most of the coarse levels, without making them
    /// larger than a plain model leaves them (see [`LeftEntries`]).
    pub bounded_left_entries: bool,
    /// Steps the cover (scene 0) trains alone before the other scenes join (0: all from the
    /// start). The first steps decide a capture's occupancy grid (every cell is updated at
    /// every step while step < 256) and where its background settles; a hidden scene moving
    /// shared entries meanwhile costs a real capture's cover lasting quality (fox: 2 dB at
    /// 600 steps; BENCHMARKS.md, "A cover warm-up").
    pub hidden_from_step: u32,
    /// A penalty on the cover's density above a cap, in the cells its grid holds above half
    /// of it, added to the cover's loss in the steps that train it (stealth training sets
    /// it; see [`DensityCap`]).
    pub density_cap: Option<DensityCap>,
    pub optimizer: OptimizerConfig,
    /// Worker count (gradient partitions); 0 = one per core.
    pub workers: usize,
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            seed: 0,
            batch_samples: 1 << 18,
            occupancy_fraction: 1.0,
            schedule: Schedule::Mixed,
            hidden_loss_weight: 1.0,
            cover_paced_table: false,
            cover_only_mlp: false,
            bounded_left_entries: false,
            hidden_from_step: 0,
            density_cap: None,
            optimizer: OptimizerConfig::default(),
            workers: 0,
        }
    }
}

/// Index functions that follow the cover's occupancy grid: called with the cover's grid and
/// the weights as they would be published (the EMA) at the start and after every update of
/// the grid, returns new index functions for the scenes it names (never scene 0). The
/// engine does not know why (stealth training uses it to keep hidden scenes inside the
/// entries the cover trains).
pub trait IndexRefresh: Send + Sync {
    fn refresh(&self, cover_grid: &OccupancyGrid, params: &[f32]) -> Vec<(usize, LevelIndices)>;
}

/// A scene to train: its training images and the index functions it is stored under.
pub struct SceneSpec {
    pub dataset: Arc<Dataset>,
    pub indices: LevelIndices,
}

struct SceneState {
    data: Arc<Dataset>,
    indices: LevelIndices,
    grid: OccupancyGrid,
    marcher: Marcher,
    loss_weight: f32,
    rays_per_batch: u32,
    measured_samples: u32,
    measured_marched: u32,
}

/// What one step did.
#[derive(Clone, Copy, Debug, Default)]
pub struct StepStats {
    pub step: u32,
    /// Mean loss per ray (summed over the scenes trained this step).
    pub loss: f32,
    /// The cover's (scene 0's) mean loss per ray, `None` if the step did not train it.
    pub cover_loss: Option<f32>,
    pub n_rays: u64,
    /// Samples that contributed to the loss (the reference's compacted samples).
    pub n_samples: u64,
    /// Samples marched and run through the network (≥ n_samples).
    pub n_marched: u64,
    /// Points of the cover's [`DensityCap`] above the cap this step (of `samples`).
    pub capped: u32,
    pub seconds: f64,
    /// Time spent refreshing occupancy grids, in rays (march + network + loss), and in the
    /// optimizer, within `seconds`.
    pub occupancy_seconds: f64,
    pub rays_seconds: f64,
    pub optimizer_seconds: f64,
}

/// Per-worker scratch, allocated once and reused every step.
pub(super) struct Worker {
    pub(super) grad: Vec<f32>,
    pub(super) touched: Touched,
    ws: Vec<Workspace>,
    pos: Vec<[f32; 3]>,
    dir: Vec<[f32; 3]>,
    dt: Vec<f32>,
    dist: Vec<f32>,
    raw: Vec<[f32; 4]>,
    d_raw: Vec<[f32; 4]>,
    rays: Vec<RayRec>,
    wave_pos: Vec<[f32; 3]>,
    wave_owner: Vec<(usize, usize)>,
    wave_dens: Vec<f32>,
    ray_state: Vec<(f32, usize, bool)>,
    loss: f64,
    n_samples: u64,
    n_marched: u64,
    n_rays: u64,
}

impl Worker {
    pub(super) fn new(n_params: usize) -> Self {
        Worker {
            grad: vec![0.0; n_params],
            touched: Touched::new(n_params),
            ws: Vec::new(),
            pos: Vec::new(),
            dir: Vec::new(),
            dt: Vec::new(),
            dist: Vec::new(),
            raw: Vec::new(),
            d_raw: Vec::new(),
            rays: Vec::new(),
            wave_pos: Vec::new(),
            wave_owner: Vec::new(),
            wave_dens: Vec::new(),
            ray_state: Vec::new(),
            loss: 0.0,
            n_samples: 0,
            n_marched: 0,
            n_rays: 0,
        }
    }
}

#[derive(Clone, Copy)]
struct RayRec {
    start: usize,
    n: usize,
    bg: [f32; 3],
    target: [f32; 3],
}

/// Samples a worker marches before running the network on them.
const GROUP_SAMPLES: usize = 4 * CHUNK;

/// The reference adapts rays per batch in multiples of this (`BATCH_SIZE_GRANULARITY`).
const RAY_GRANULARITY: u32 = 256;
/// Most rays per batch (the reference's cap).
const MAX_RAYS_PER_BATCH: u32 = 1 << 18;
/// Rays of the first step: the reference starts at 4096 rays for its 2^18-sample target, i.e.
/// 64 samples a ray; a smaller target starts at the same ratio.
pub(crate) fn initial_rays_per_batch(batch_samples: u32) -> u32 {
    let rays = (4096u64 * batch_samples as u64) >> 18;
    (rays as u32)
        .div_ceil(RAY_GRANULARITY)
        .max(1)
        .saturating_mul(RAY_GRANULARITY)
        .min(MAX_RAYS_PER_BATCH)
}

/// The reference's `update_after_training`: scale the ray count by target / measured samples,
/// round up to a multiple of 256, cap at 2^18.
pub(crate) fn next_rays_per_batch(rays: u32, batch_samples: u32, measured: u64) -> u32 {
    let r = (rays as f64 * batch_samples as f64 / measured.max(1) as f64) as u64;
    (r.div_ceil(RAY_GRANULARITY as u64).max(1) * RAY_GRANULARITY as u64)
        .min(MAX_RAYS_PER_BATCH as u64) as u32
}

pub struct Trainer {
    pub net: NerfNetwork,
    pub params: Vec<f32>,
    pub optimizer: Optimizer,
    pub config: TrainConfig,
    scenes: Vec<SceneState>,
    workers: Vec<Worker>,
    refresh: Option<Box<dyn IndexRefresh>>,
    pace: Option<Pacing>,
    cover_mlp: Option<CoverOnlyMlp>,
    left: Option<LeftEntries>,
    /// The cells the density cap draws from, as of the cover's last grid update.
    cap_cells: Vec<u32>,
    /// Steps taken, the cover's or not: the schedule's and the rays' clock.
    pub step: u32,
    /// Steps that updated the weights: every step, or with
    /// [`TrainConfig::cover_paced_table`] those that trained the cover. The optimizer's
    /// and the occupancy grids' clock, and the step count a model file records.
    pub cover_steps: u32,
}

/// A scene's occupancy grid before its first step (the GPU trainer's too): every cell no
/// training camera sees culled, as the reference does. A hidden scene in a larger cover box
/// keeps the whole box: trained empty outside its own content under its key, the network
/// learns that features met at random are empty space — what makes a wrong key, whose grid
/// is cut to the scene's box like the key holder's, render close to an empty image
/// (measured on fox + text, BENCHMARKS.md; confining training to the box loses it).
pub(crate) fn starting_grid(aabb_scale: u32, data: &Dataset) -> OccupancyGrid {
    let mut grid = OccupancyGrid::new(aabb_scale);
    let cams: Vec<_> = data.frames.iter().map(|f| f.camera.clone()).collect();
    grid.mark_untrained(&cams);
    grid
}

/// Also the GPU trainer's seeds, so both backends draw the same rays for a seed.
pub(crate) fn mix(a: u64, b: u64) -> u64 {
    // splitmix64 of a combination: decorrelates (seed, step, scene) streams.
    let mut z = a
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(b)
        .wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The scenes step `step` trains, in order: the cover alone before
/// [`TrainConfig::hidden_from_step`], then all of them (mixed) or one drawn for the step
/// (random scene). Also the GPU trainer's, so both backends train the same scenes.
pub(crate) fn step_scenes(config: &TrainConfig, step: u32, n_scenes: usize) -> Vec<usize> {
    if step < config.hidden_from_step {
        return vec![0];
    }
    match config.schedule {
        Schedule::Mixed => (0..n_scenes).collect(),
        Schedule::RandomScene => {
            let mut r = Pcg32::new(mix(config.seed, step as u64), 0x5ce7e);
            vec![r.below(n_scenes as u32) as usize]
        }
    }
}

/// Whether a step that trains `scene_ids` updates the weights and the grids: always, or
/// under [`TrainConfig::cover_paced_table`] only when it trains the cover (see
/// [`Trainer::cover_steps`]). Also the GPU trainer's rule.
pub(crate) fn updates_weights(config: &TrainConfig, scene_ids: &[usize]) -> bool {
    !config.cover_paced_table || scene_ids.contains(&0)
}

impl Trainer {
    pub fn new(model: ModelConfig, scenes: Vec<SceneSpec>, config: TrainConfig) -> Result<Self> {
        if scenes.is_empty() {
            return Err(Error::Config("no scene to train".into()));
        }
        if config.bounded_left_entries && !config.cover_paced_table {
            return Err(Error::Config(
                "bounded left entries need the cover-paced table".into(),
            ));
        }
        let net = NerfNetwork::new(model)?;
        let n_levels = net.layout.grid.levels.len();
        let mut states = Vec::new();
        for s in scenes {
            if s.indices.len() != n_levels {
                return Err(Error::Config(format!(
                    "{} index functions for {} grid levels",
                    s.indices.len(),
                    n_levels
                )));
            }
            check_indices(&s.indices, &net.layout.grid)?;
            if s.dataset.frames.is_empty() {
                return Err(Error::format(&s.dataset.root, "no training images"));
            }
            if s.dataset.aabb_scale != model.aabb_scale {
                return Err(Error::Config(format!(
                    "{}: aabb_scale {} differs from the model's {}",
                    s.dataset.root.display(),
                    s.dataset.aabb_scale,
                    model.aabb_scale
                )));
            }
            let grid = starting_grid(model.aabb_scale, &s.dataset);
            let rays = initial_rays_per_batch(config.batch_samples);
            states.push(SceneState {
                data: s.dataset,
                indices: s.indices,
                grid,
                marcher: Marcher::new(model.aabb_scale),
                loss_weight: if states.is_empty() {
                    1.0
                } else {
                    config.hidden_loss_weight
                },
                rays_per_batch: rays,
                measured_samples: 0,
                measured_marched: 0,
            });
        }
        let params = net.init_params(config.seed);
        let n_workers = if config.workers == 0 {
            rayon::current_num_threads()
        } else {
            config.workers
        };
        let workers = (0..n_workers).map(|_| Worker::new(params.len())).collect();
        let pace = config
            .cover_paced_table
            .then(|| Pacing::new(params.len(), net.layout.n_mlp_params()));
        let cover_mlp = config
            .cover_only_mlp
            .then(|| CoverOnlyMlp::new(n_workers, net.layout.n_mlp_params()));
        let optimizer = Optimizer::new(config.optimizer, params.len(), net.layout.n_mlp_params());
        let left = config
            .bounded_left_entries
            .then(|| LeftEntries::new(&net.layout.grid));
        Ok(Trainer {
            left,
            net,
            params,
            optimizer,
            config,
            scenes: states,
            workers,
            refresh: None,
            pace,
            cover_mlp,
            cap_cells: Vec::new(),
            step: 0,
            cover_steps: 0,
        })
    }

    pub fn n_scenes(&self) -> usize {
        self.scenes.len()
    }

    /// The occupancy grid of scene `i` (0 = the cover).
    pub fn grid(&self, i: usize) -> &OccupancyGrid {
        &self.scenes[i].grid
    }

    /// The training images of scene `i` (0 = the cover).
    pub fn dataset(&self, i: usize) -> &Dataset {
        &self.scenes[i].data
    }

    /// Scene `i`'s (rays per batch, trained samples, marched samples) of the last step.
    pub fn batch_counters(&self, i: usize) -> (u32, u32, u32) {
        let s = &self.scenes[i];
        (s.rays_per_batch, s.measured_samples, s.measured_marched)
    }

    /// [`TrainConfig::bounded_left_entries`]' bounds, as of the cover's last grid update.
    pub fn left_entries(&self) -> Option<&LeftEntries> {
        self.left.as_ref()
    }

    /// Index functions of scene `i` as trained now.
    pub fn indices(&self, i: usize) -> &LevelIndices {
        &self.scenes[i].indices
    }

    /// Installs an [`IndexRefresh`] and applies it to the cover's current grid.
    pub fn set_index_refresh(&mut self, refresh: Box<dyn IndexRefresh>) -> Result<()> {
        self.refresh = Some(refresh);
        self.apply_refresh()
    }

    fn apply_refresh(&mut self) -> Result<()> {
        if self.refresh.is_none() {
            return Ok(());
        }
        let published = self.optimizer.ema_params(&self.params);
        self.apply_refresh_with(&published)
    }

    /// [`Self::apply_refresh`] with the published weights already computed.
    fn apply_refresh_with(&mut self, published: &[f32]) -> Result<()> {
        let Some(r) = &self.refresh else {
            return Ok(());
        };
        let n_levels = self.net.layout.grid.levels.len();
        for (i, indices) in r.refresh(&self.scenes[0].grid, published) {
            if i == 0 || i >= self.scenes.len() || indices.len() != n_levels {
                return Err(Error::Config(format!(
                    "index refresh for scene {i} with {} levels ({} scenes, {n_levels} levels; scene 0 is never refreshed)",
                    indices.len(),
                    self.scenes.len()
                )));
            }
            check_indices(&indices, &self.net.layout.grid)?;
            self.scenes[i].indices = indices;
        }
        Ok(())
    }

    /// Weights to render with and to publish: the debiased EMA.
    pub fn inference_params(&self) -> Vec<f32> {
        self.optimizer.ema_params(&self.params)
    }

    fn update_occupancy(&mut self) {
        let step = self.cover_steps;
        let interval = (step / 16).clamp(1, 16);
        if !step.is_multiple_of(interval) {
            return;
        }
        let fraction = self.config.occupancy_fraction;
        let seed = self.config.seed;
        for si in 0..self.scenes.len() {
            let SceneState {
                grid,
                marcher,
                indices,
                ..
            } = &mut self.scenes[si];
            let (net, params) = (&self.net, &self.params);
            grid.update(step, fraction, mix(seed, 0x6772_6964 + si as u64), |pos| {
                let warped: Vec<[f32; 3]> = pos.iter().map(|&p| marcher.warp(p)).collect();
                net.density_batch(params, indices, &warped)
            });
            if si == 0 {
                if let Some(cap) = &self.config.density_cap {
                    self.cap_cells = cap.cells(&self.scenes[0].grid);
                }
                let published = (self.refresh.is_some() || self.left.is_some())
                    .then(|| self.optimizer.ema_params(&self.params));
                if let (Some(l), Some(p)) = (&mut self.left, &published) {
                    let layout = &self.net.layout;
                    l.update(
                        &layout.grid,
                        &self.scenes[0].grid,
                        layout.config.aabb_scale,
                        &p[layout.grid_offset..],
                    );
                }
                // Refreshed indices take effect before the other scenes' grids are updated.
                if let Some(p) = &published {
                    self.apply_refresh_with(p)
                        .expect("index refresh was checked when it was installed");
                }
            }
        }
    }

    /// One training step.
    pub fn train_step(&mut self) -> StepStats {
        let t0 = std::time::Instant::now();
        let step = self.step;
        let scene_ids = step_scenes(&self.config, step, self.scenes.len());
        let update = updates_weights(&self.config, &scene_ids);
        if update {
            self.update_occupancy();
        }
        let t_occ = t0.elapsed().as_secs_f64();
        let mut stats = StepStats {
            step,
            ..Default::default()
        };
        for &si in &scene_ids {
            let scene = &self.scenes[si];
            let n_rays = scene.rays_per_batch as usize;
            let n_workers = self.workers.len();
            let seed = mix(mix(self.config.seed, step as u64), si as u64 + 1);
            let net = &self.net;
            let params = &self.params;
            self.workers
                .par_iter_mut()
                .enumerate()
                .for_each(|(w, worker)| {
                    let r0 = n_rays * w / n_workers;
                    let r1 = n_rays * (w + 1) / n_workers;
                    worker.loss = 0.0;
                    worker.n_samples = 0;
                    worker.n_marched = 0;
                    worker.n_rays = 0;
                    train_rays(net, params, scene, seed, r0..r1, n_rays, worker);
                });
            let mut loss = 0.0;
            let (mut used, mut marched) = (0, 0);
            for w in &self.workers {
                loss += w.loss;
                used += w.n_samples;
                marched += w.n_marched;
                stats.n_rays += w.n_rays;
            }
            stats.n_marched += marched;
            let scene_loss = (loss / n_rays as f64) as f32;
            stats.loss += scene_loss;
            if si == 0 {
                stats.cover_loss = Some(scene_loss);
                stats.capped = self.cap_density();
                if let Some(p) = &mut self.pace {
                    p.open_gate(&self.workers);
                }
                if let Some(m) = &mut self.cover_mlp {
                    m.keep(&self.workers);
                }
            }
            stats.n_samples += used;
            let scene = &mut self.scenes[si];
            scene.measured_samples = used as u32;
            scene.measured_marched = marched as u32;
            // The reference keeps its ray count when nothing was trained.
            if used > 0 {
                scene.rays_per_batch =
                    next_rays_per_batch(n_rays as u32, self.config.batch_samples, used);
            }
        }
        if let Some(p) = &mut self.pace {
            let f = self.net.layout.config.grid.n_features as usize;
            p.hold_back(&mut self.workers, self.left.as_ref().map(|l| (l, f)));
        }
        if let Some(m) = &mut self.cover_mlp {
            m.restore(&mut self.workers);
        }
        let t_rays = t0.elapsed().as_secs_f64();
        // Without the update, the gradients the hold-back left in the workers' buffers (the
        // MLP's) wait there for the next step that trains the cover; the table's wait in
        // `pending`.
        if update {
            self.update_weights();
            self.cover_steps += 1;
        }
        self.step += 1;
        stats.seconds = t0.elapsed().as_secs_f64();
        stats.occupancy_seconds = t_occ;
        stats.rays_seconds = t_rays - t_occ;
        stats.optimizer_seconds = stats.seconds - t_rays;
        stats
    }

    /// The cover's [`DensityCap`] term, backpropagated into the workers' gradients as part
    /// of the cover's: points split over the workers as rays are. Returns the points above
    /// the cap.
    fn cap_density(&mut self) -> u32 {
        let Some(cap) = self.config.density_cap else {
            return 0;
        };
        let cover = &self.scenes[0];
        let pos: Vec<[f32; 3]> = cap
            .points(&self.cap_cells, self.config.seed, self.cover_steps)
            .into_iter()
            .map(|p| cover.marcher.warp(p))
            .collect();
        let n = pos.len();
        if n == 0 {
            return 0;
        }
        let n_workers = self.workers.len();
        let (net, params) = (&self.net, &self.params);
        let grid_offset = net.layout.grid_offset;
        let n_levels = net.layout.grid.levels.len();
        self.workers
            .par_iter_mut()
            .enumerate()
            .map(|(w, worker)| {
                let range = n * w / n_workers..n * (w + 1) / n_workers;
                if worker.ws.is_empty() {
                    worker.ws.push(net.workspace());
                }
                let mut above = 0;
                for chunk in pos[range].chunks(CHUNK) {
                    let m = chunk.len();
                    // The colour's gradient is zero: any direction does.
                    worker.dir.clear();
                    worker.dir.resize(m, [0.0, 0.0, 1.0]);
                    worker.raw.resize(m, [0.0; 4]);
                    worker.d_raw.resize(m, [0.0; 4]);
                    let ws = &mut worker.ws[0];
                    net.forward(
                        params,
                        &cover.indices,
                        chunk,
                        &worker.dir,
                        ws,
                        &mut worker.raw,
                    );
                    for (d, r) in worker.d_raw.iter_mut().zip(&worker.raw) {
                        let (g, _) = cap_gradient(&cap, r[3], n);
                        above += (g > 0.0) as u32;
                        *d = [0.0, 0.0, 0.0, g];
                    }
                    net.backward(params, &cover.indices, &worker.d_raw, ws, &mut worker.grad);
                    mark_corners(ws, n_levels, grid_offset, &mut worker.touched);
                }
                above
            })
            .sum()
    }

    /// One optimizer step on the summed gradients of the workers, which it leaves zeroed.
    fn update_weights(&mut self) {
        let mut grads: Vec<Vec<f32>> = self
            .workers
            .iter_mut()
            .map(|w| std::mem::take(&mut w.grad))
            .collect();
        let touched: Vec<Touched> = self
            .workers
            .iter_mut()
            .map(|w| std::mem::take(&mut w.touched))
            .collect();
        self.optimizer
            .step(&mut self.params, &mut grads, Some(&touched));
        if let Some(l) = &self.left {
            l.clamp(&mut self.params[self.net.layout.grid_offset..]);
        }
        for ((w, g), mut t) in self.workers.iter_mut().zip(grads).zip(touched) {
            w.grad = g;
            t.clear();
            w.touched = t;
        }
    }
}

/// Tells the optimizer which grid entries the last backward on `ws` may have given a
/// gradient: every corner its samples read.
fn mark_corners(ws: &Workspace, n_levels: usize, grid_offset: usize, touched: &mut Touched) {
    for level in 0..n_levels {
        for smp in 0..ws.len() {
            for &off in ws.grid_corner_offsets(level, smp) {
                touched.mark(grid_offset + off as usize);
            }
        }
    }
}

/// Samples evaluated per live ray per density wave.
const WAVE: usize = 12;

/// Finds where each ray of the group stops (transmittance < 1e-4) with density-only
/// evaluations in waves along the rays, so that the full network forward and backward run
/// only on samples that reach the loss — the reference's compaction, without evaluating
/// every marched sample. Leaves the number of used samples in `ray_state[r].1`.
fn find_termination(net: &NerfNetwork, params: &[f32], scene: &SceneState, w: &mut Worker) {
    w.ray_state.clear();
    w.ray_state
        .extend(w.rays.iter().map(|_| (1.0f32, 0usize, false)));
    if w.ws.is_empty() {
        w.ws.push(net.workspace());
    }
    loop {
        w.wave_pos.clear();
        w.wave_owner.clear();
        for (r, ray) in w.rays.iter().enumerate() {
            let (_, next, done) = w.ray_state[r];
            if done {
                continue;
            }
            let m = WAVE.min(ray.n - next);
            let s = ray.start + next;
            w.wave_pos.extend_from_slice(&w.pos[s..s + m]);
            w.wave_owner.push((r, m));
        }
        if w.wave_pos.is_empty() {
            break;
        }
        w.wave_dens.resize(w.wave_pos.len(), 0.0);
        for (k, chunk) in w.wave_pos.chunks(CHUNK).enumerate() {
            let o = k * CHUNK;
            net.density(
                params,
                &scene.indices,
                chunk,
                &mut w.ws[0],
                &mut w.wave_dens[o..o + chunk.len()],
            );
        }
        let mut at = 0;
        for &(r, m) in &w.wave_owner {
            let ray = w.rays[r];
            let st = &mut w.ray_state[r];
            for j in 0..m {
                let sigma = w.wave_dens[at + j].exp();
                let alpha = 1.0 - (-sigma * w.dt[ray.start + st.1]).exp();
                st.0 *= 1.0 - alpha;
                st.1 += 1;
                if st.0 < TRAIN_MIN_TRANSMITTANCE {
                    st.2 = true;
                    break;
                }
            }
            if st.1 == ray.n {
                st.2 = true;
            }
            at += m;
        }
    }
}

/// Keeps only each ray's used samples, moving them down in place.
fn compact(w: &mut Worker) {
    let mut out = 0;
    for (r, ray) in w.rays.iter_mut().enumerate() {
        let used = w.ray_state[r].1;
        for j in 0..used {
            let (from, to) = (ray.start + j, out + j);
            w.pos[to] = w.pos[from];
            w.dir[to] = w.dir[from];
            w.dt[to] = w.dt[from];
            w.dist[to] = w.dist[from];
        }
        ray.start = out;
        ray.n = used;
        out += used;
    }
    w.pos.truncate(out);
    w.dir.truncate(out);
    w.dt.truncate(out);
    w.dist.truncate(out);
}

/// Marches, evaluates and backpropagates rays `range` of a batch of `n_rays` into the
/// worker's gradient buffer.
fn train_rays(
    net: &NerfNetwork,
    params: &[f32],
    scene: &SceneState,
    seed: u64,
    range: std::ops::Range<usize>,
    n_rays: usize,
    w: &mut Worker,
) {
    let n_images = scene.data.frames.len();
    let n_levels = net.layout.grid.levels.len();
    let grid_offset = net.layout.grid_offset;
    // The reference differentiates the per-channel loss summed over channels (the reported
    // loss is their mean), divided by the ray count.
    let loss_norm = scene.loss_weight / n_rays as f32;
    let pull_up = if scene.grid.mean < MIN_OPTICAL_THICKNESS {
        DENSITY_PULL_UP
    } else {
        0.0
    };
    let mut next = range.start;
    while next < range.end {
        w.pos.clear();
        w.dir.clear();
        w.dt.clear();
        w.dist.clear();
        w.rays.clear();
        while next < range.end && w.pos.len() < GROUP_SAMPLES {
            let i = next;
            next += 1;
            let mut rng = Pcg32::new(seed, i as u64);
            let img = i * n_images / n_rays;
            let frame = &scene.data.frames[img];
            let (wd, ht) = (frame.image.width, frame.image.height);
            let x = rng.below(wd);
            let y = rng.below(ht);
            // A random background for every dataset, as the reference: on opaque images it
            // is the target of nothing, which teaches rays to end (T → 0) where the photo
            // shows something, instead of leaning on a fixed colour behind the scene.
            let bg = [rng.next_f32(), rng.next_f32(), rng.next_f32()];
            let ray = frame.camera.ray(x as f32 + 0.5, y as f32 + 0.5);
            let Some((tmin, _)) = scene.marcher.intersect(ray.o, ray.d) else {
                continue;
            };
            let t = advance_n_steps(tmin, scene.marcher.cone_angle, rng.next_f32());
            let start = w.pos.len();
            scene.marcher.march(
                &scene.grid,
                ray.o,
                ray.d,
                t,
                MAX_SAMPLES_PER_RAY,
                &mut w.pos,
                &mut w.dt,
                &mut w.dist,
            );
            let n = w.pos.len() - start;
            if n == 0 {
                continue;
            }
            w.dir.extend(std::iter::repeat_n(ray.d, n));
            let target = frame.image.target_on(x, y, bg);
            w.rays.push(RayRec {
                start,
                n,
                bg,
                target,
            });
        }
        if w.pos.is_empty() {
            continue;
        }
        let marched = w.pos.len();
        find_termination(net, params, scene, w);
        compact(w);
        w.n_marched += marched as u64;
        let total = w.pos.len();
        let n_chunks = total.div_ceil(CHUNK);
        while w.ws.len() < n_chunks {
            w.ws.push(net.workspace());
        }
        w.raw.resize(total, [0.0; 4]);
        w.d_raw.resize(total, [0.0; 4]);
        for k in 0..n_chunks {
            let r = k * CHUNK..((k + 1) * CHUNK).min(total);
            net.forward(
                params,
                &scene.indices,
                &w.pos[r.clone()],
                &w.dir[r.clone()],
                &mut w.ws[k],
                &mut w.raw[r],
            );
        }
        for ray in &w.rays {
            let r = ray.start..ray.start + ray.n;
            let pos = &w.pos[r.clone()];
            let c = ray_loss(
                &w.raw[r.clone()],
                &w.dt[r.clone()],
                &w.dist[r.clone()],
                |j| scene.marcher.in_cascade0(pos[j]),
                ray.bg,
                ray.target,
                loss_norm,
                pull_up,
                &mut w.d_raw[r],
            );
            w.loss += c.loss as f64;
            w.n_samples += c.n_used as u64;
            w.n_rays += 1;
        }
        for k in 0..n_chunks {
            let r = k * CHUNK..((k + 1) * CHUNK).min(total);
            net.backward(
                params,
                &scene.indices,
                &w.d_raw[r],
                &mut w.ws[k],
                &mut w.grad,
            );
            mark_corners(&w.ws[k], n_levels, grid_offset, &mut w.touched);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ngp::data::{LoadOptions, Split};
    use crate::ngp::encoding::{GridConfig, reference_indices};
    use crate::ngp::model::Model;
    use crate::ngp::network::NerfLayout;
    use crate::synth::{SceneKind, SynthOptions, generate};

    /// Under pacing (stealth) a random-scene step that does not train the cover updates
    /// nothing: no weight, no occupancy grid, no optimizer clock. The hidden scene's MLP
    /// gradient stays in the buffers for the next step that trains the cover, and a model
    /// file records the cover's steps. Without pacing the same steps move the weights.
    #[test]
    fn paced_steps_without_the_cover_wait_for_it() {
        let dir = tempfile::tempdir().unwrap();
        let load = |name: &str, scene: SceneKind, seed: u64| {
            let d = dir.path().join(name);
            let opts = SynthOptions {
                scene,
                resolution: 16,
                n_train: 4,
                n_val: 0,
                n_test: 1,
                seed,
                aabb_scale: 1,
            };
            generate(&opts, &d).unwrap();
            Arc::new(Dataset::load(&d, Split::Train, &LoadOptions::default()).unwrap())
        };
        let cover = load("cover", SceneKind::Object, 1);
        let hidden = load("hidden", SceneKind::Text("HI".into()), 2);
        let model = ModelConfig {
            grid: GridConfig {
                n_levels: 4,
                n_features: 2,
                log2_hashmap_size: 10,
                base_resolution: 16,
            },
            aabb_scale: 1,
        };
        let layout = NerfLayout::new(model).unwrap();
        let n_mlp = layout.n_mlp_params();
        let specs = || {
            [cover.clone(), hidden.clone()]
                .into_iter()
                .map(|dataset| SceneSpec {
                    dataset,
                    indices: reference_indices(&layout.grid),
                })
                .collect::<Vec<_>>()
        };
        for paced in [true, false] {
            let tc = TrainConfig {
                seed: 3,
                batch_samples: 1 << 10,
                occupancy_fraction: 0.01,
                schedule: Schedule::RandomScene,
                cover_paced_table: paced,
                ..Default::default()
            };
            let mut t = Trainer::new(model, specs(), tc).unwrap();
            let (mut with_cover, mut without) = (0, 0);
            let mut held_any = false;
            for step in 0..12 {
                let params = t.params.clone();
                let grid = t.grid(0).density.clone();
                let clock = t.optimizer.step;
                if t.train_step().cover_loss.is_some() {
                    with_cover += 1;
                    continue;
                }
                without += 1;
                if !paced {
                    assert_ne!(t.params, params, "step {step}: unpaced, nothing moved");
                    continue;
                }
                assert!(t.params == params, "step {step}: a weight moved");
                assert!(t.grid(0).density == grid, "step {step}: the grid moved");
                assert_eq!(t.optimizer.step, clock, "step {step}");
                let held: usize = t
                    .workers
                    .iter()
                    .map(|w| w.grad[..n_mlp].iter().filter(|&&g| g != 0.0).count())
                    .sum();
                // Grids update on the cover's steps only: before the first, the hidden
                // scene's grid is still empty and its rays find no sample.
                assert!(
                    with_cover == 0 || held > 0,
                    "step {step}: the hidden MLP gradient was dropped"
                );
                held_any |= held > 0;
            }
            assert!(!paced || held_any, "no hidden-only step after a cover step");
            assert!(with_cover > 0 && without > 0, "{with_cover} / {without}");
            let recorded = if paced { with_cover } else { 12 };
            assert_eq!(t.cover_steps, recorded);
            assert_eq!(Model::from_trainer(&t, 0.0).training_step, recorded);
        }
    }

    /// A one-scene trainer on a generated object, the cover of the density-cap tests.
    fn cap_trainer(cap: Option<DensityCap>, dir: &std::path::Path) -> Trainer {
        let opts = SynthOptions {
            scene: SceneKind::Object,
            resolution: 16,
            n_train: 6,
            n_val: 0,
            n_test: 1,
            seed: 5,
            aabb_scale: 1,
        };
        generate(&opts, dir).unwrap();
        let data = Arc::new(Dataset::load(dir, Split::Train, &LoadOptions::default()).unwrap());
        let model = ModelConfig {
            grid: GridConfig {
                n_levels: 4,
                n_features: 2,
                log2_hashmap_size: 10,
                base_resolution: 16,
            },
            aabb_scale: 1,
        };
        let layout = NerfLayout::new(model).unwrap();
        let spec = SceneSpec {
            dataset: data,
            indices: reference_indices(&layout.grid),
        };
        let tc = TrainConfig {
            seed: 2,
            batch_samples: 1 << 11,
            occupancy_fraction: 0.05,
            density_cap: cap,
            workers: 2,
            ..Default::default()
        };
        Trainer::new(model, vec![spec], tc).unwrap()
    }

    /// The cap's gradient through the network and the grid equals finite differences of
    /// its loss, on the table entries and MLP weights it moves most.
    #[test]
    fn the_density_caps_gradient_matches_finite_differences() {
        let dir = tempfile::tempdir().unwrap();
        // A cap below the untrained field's (τ ≈ Δt_min · e^0 = 0.0017): most drawn points
        // lie above it.
        let cap = DensityCap {
            max_optical_thickness: 0.0015,
            weight: 1.0,
            samples: 512,
        };
        let mut t = cap_trainer(Some(cap), dir.path());
        for _ in 0..20 {
            t.train_step();
        }
        for w in &mut t.workers {
            w.grad.fill(0.0);
        }
        let capped = t.cap_density();
        let mut grad = vec![0.0f64; t.params.len()];
        for w in &t.workers {
            for (g, &x) in grad.iter_mut().zip(&w.grad) {
                *g += x as f64;
            }
        }
        let cover = &t.scenes[0];
        let pos: Vec<[f32; 3]> = cap
            .points(&t.cap_cells, t.config.seed, t.cover_steps)
            .into_iter()
            .map(|p| cover.marcher.warp(p))
            .collect();
        assert!(
            capped as usize > pos.len() / 4,
            "{capped} of {} points above the cap",
            pos.len()
        );
        let loss = |params: &[f32]| -> f64 {
            t.net
                .density_batch(params, &cover.indices, &pos)
                .iter()
                .map(|&ld| cap_gradient(&cap, ld, pos.len()).1 as f64)
                .sum()
        };
        let grid_offset = t.net.layout.grid_offset;
        let top = |range: std::ops::Range<usize>| {
            let mut ids: Vec<usize> = range.collect();
            ids.sort_by(|&a, &b| grad[b].abs().total_cmp(&grad[a].abs()));
            ids.truncate(4);
            ids
        };
        let mut checked = top(grid_offset..t.params.len());
        checked.extend(top(0..grid_offset));
        for i in checked {
            let h = 1e-3 * t.params[i].abs().max(1e-1);
            let mut p = t.params.clone();
            p[i] += h;
            let up = loss(&p);
            p[i] -= 2.0 * h;
            let down = loss(&p);
            let fd = (up - down) / (2.0 * h as f64);
            assert!(
                (fd - grad[i]).abs() <= 0.03 * grad[i].abs() + 1e-7,
                "parameter {i}: finite differences {fd}, gradient {}",
                grad[i]
            );
        }
    }

    /// Training under a low cap keeps the cover's grid below an uncapped one's, which the
    /// same seed otherwise reproduces exactly; without cells above it the cap costs nothing.
    #[test]
    fn a_density_cap_holds_the_covers_grid_down() {
        let dir = tempfile::tempdir().unwrap();
        // The uncapped cover reaches 0.012 in these 40 steps; a heavier weight than
        // stealth's, whose covers train for hundreds of steps.
        let cap = DensityCap {
            max_optical_thickness: 0.003,
            weight: 1.0,
            samples: 4096,
        };
        let run = |cap: Option<DensityCap>| {
            let mut t = cap_trainer(cap, dir.path());
            let mut capped = 0;
            for _ in 0..40 {
                capped += t.train_step().capped;
            }
            let max = t.grid(0).density.iter().copied().fold(0.0f32, f32::max);
            (max, capped, t.params)
        };
        let (free, none, free_params) = run(None);
        let (held, capped, _) = run(Some(cap));
        assert_eq!(none, 0);
        assert!(capped > 0, "no point above the cap");
        assert!(
            held < 0.5 * free,
            "largest optical thickness {held} capped against {free} free"
        );
        // A cap above anything the cover reaches changes no weight.
        let high = DensityCap {
            max_optical_thickness: 1e6,
            ..DensityCap::STEALTH
        };
        let (_, capped, params) = run(Some(high));
        assert_eq!(capped, 0);
        assert!(params == free_params, "an idle cap moved the weights");
    }

    #[test]
    fn rays_per_batch_follow_the_reference() {
        // 2^18 target: the reference's 4096 start.
        assert_eq!(initial_rays_per_batch(1 << 18), 4096);
        assert_eq!(initial_rays_per_batch(1 << 16), 1024);
        // Small targets still start at one granule.
        assert_eq!(initial_rays_per_batch(1000), 256);
        // 4096 rays gave 2^17 samples for a 2^18 target: twice the rays.
        assert_eq!(next_rays_per_batch(4096, 1 << 18, 1 << 17), 8192);
        // 1000 × 65536 / 70000 = 936.2 → 936 → next multiple of 256 = 1024.
        assert_eq!(next_rays_per_batch(1000, 65536, 70000), 1024);
        // Capped at 2^18, never below one granule.
        assert_eq!(next_rays_per_batch(1 << 17, 1 << 18, 1), 1 << 18);
        assert_eq!(next_rays_per_batch(256, 1, 1 << 20), 256);
    }
}
