//! The trainer: one shared set of weights, one or more scenes, each with its own per-level
//! index functions and its own occupancy grid. With one scene and the reference index this
//! is plain Instant-NGP training; the stego layer chooses the scenes and indices, and may
//! install a [`TrainPolicy`] (its stealth) that acts through the hooks of [`super::hooks`].
//!
//! A step: refresh the occupancy grids on the reference schedule, draw rays (equal chunks per
//! image, uniform pixels at their centres, random background for RGBA data), march them,
//! run the network, composite, take the Huber loss, backpropagate, one Adam step. Rays are
//! split into one fixed range per worker, each with its own gradient buffer, summed in a
//! fixed order: the result is deterministic for a seed and worker count.

use super::cameras::{self, CameraRefinement, CameraRefiner};
use super::coarse;
use super::grid_updates::GridUpdates;
use super::held::{HoldBack, KeptMlp};
use super::hooks::{PolicyOps, StepInfo, TableBounds, TrainPolicy};
use super::loss::{DENSITY_PULL_UP, ray_loss};
use super::optimizer::{Optimizer, OptimizerConfig, Touched};
use super::schedule::{
    Schedule, initial_rays_per_batch, mix, next_rays_per_batch, starting_grid, step_scenes,
};
use super::worker::{RayRec, Worker};
use crate::data::Dataset;
use crate::encoding::{LevelIndices, check_indices};
use crate::error::{Error, Result};
use crate::model::Model;
use crate::network::ModelConfig;
use crate::network::nerf::{CHUNK, NerfNetwork, Workspace};
use crate::occupancy::{MIN_OPTICAL_THICKNESS, OccupancyGrid};
use crate::render::composite::TRAIN_MIN_TRANSMITTANCE;
use crate::render::march::{MAX_SAMPLES_PER_RAY, Marcher};
use crate::rng::Pcg32;
use rayon::prelude::*;
use std::sync::Arc;

/// The fewest samples a step aims to train of a scene after the first (1/16 of the
/// reference's batch), so that a small [`TrainConfig::others_batch`] still trains rays.
pub const MIN_SCENE_BATCH: u32 = 1 << 14;

#[derive(Clone, Debug)]
pub struct TrainConfig {
    pub seed: u64,
    /// Target number of trained (compacted) samples per step, per scene in a mixed batch.
    pub batch_samples: u32,
    /// Fraction of the reference's occupancy-update sample count (1 = reference).
    pub occupancy_fraction: f32,
    /// Density evaluations per trained sample the occupancy updates may spend, which spaces
    /// them out ([`GridUpdates`]); `None` for the reference's schedule.
    pub occupancy_budget: Option<f32>,
    /// The samples a ray should reach the loss with, at most twice over, before a step
    /// marches coarser ([`super::coarse`]); `None` for the reference's step throughout.
    pub coarse_march: Option<u32>,
    /// How the scenes share the steps.
    pub schedule: Schedule,
    /// Loss weight of every scene after the first, relative to scene 0's 1. Shared table
    /// entries settle where the scenes' gradients balance.
    pub others_weight: f32,
    /// The samples a step trains of every scene after the first, as a fraction of
    /// `batch_samples` (scene 0 trains all of them). A scene that needs less than the first
    /// (a hidden text beside a 360° capture) then costs the step less of its time.
    pub others_batch: f32,
    /// Steps scene 0 trains alone before the others join (0: all from the start).
    pub solo_steps: u32,
    pub optimizer: OptimizerConfig,
    /// Worker count (gradient partitions); 0 = one per core; at most
    /// [`MAX_WORKERS`](super::memory::MAX_WORKERS), within the memory available.
    pub workers: usize,
}

impl TrainConfig {
    /// The samples a step aims to train of scene `si` (at least one granule of rays' worth).
    pub fn scene_batch(&self, si: usize) -> u32 {
        if si == 0 || self.others_batch >= 1.0 {
            return self.batch_samples;
        }
        let b = (self.batch_samples as f64 * self.others_batch.max(0.0) as f64).round() as u32;
        b.clamp(self.batch_samples.min(MIN_SCENE_BATCH), self.batch_samples)
    }

    /// The scenes step `step` trains ([`step_scenes`]).
    pub fn step_scenes(&self, step: u32, n_scenes: usize) -> Vec<usize> {
        step_scenes(self.schedule, self.solo_steps, self.seed, step, n_scenes)
    }
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            seed: 0,
            batch_samples: 1 << 18,
            occupancy_fraction: 1.0,
            occupancy_budget: None,
            coarse_march: None,
            schedule: Schedule::Mixed,
            others_weight: 1.0,
            others_batch: 1.0,
            solo_steps: 0,
            optimizer: OptimizerConfig::default(),
            workers: 0,
        }
    }
}

/// A scene to train: its training images and the index functions it is stored under.
pub struct SceneSpec {
    pub dataset: Arc<Dataset>,
    pub indices: LevelIndices,
}

pub(super) struct SceneState {
    data: Arc<Dataset>,
    indices: LevelIndices,
    grid: OccupancyGrid,
    marcher: Marcher,
    loss_weight: f32,
    rays_per_batch: u32,
    measured_samples: u32,
    measured_marched: u32,
    /// The reference's steps a training sample stands for ([`super::coarse`]).
    stride: u32,
    /// The training cameras' offsets, where they are refined ([`super::cameras`]).
    cameras: Option<CameraRefiner>,
}

impl SceneState {
    /// Training image `img`'s ray through pixel (x, y)'s centre, from its refined camera
    /// where the cameras are refined.
    fn ray(&self, img: usize, x: u32, y: u32) -> crate::camera::Ray {
        let ray = self.data.frames[img]
            .camera
            .ray(x as f32 + 0.5, y as f32 + 0.5);
        match &self.cameras {
            Some(c) => c.ray(img, ray),
            None => ray,
        }
    }
}

/// What one step did.
#[derive(Clone, Copy, Debug, Default)]
pub struct StepStats {
    pub step: u32,
    /// Mean loss per ray (summed over the scenes trained this step).
    pub loss: f32,
    /// Scene 0's mean loss per ray (what a model file stores), `None` if the step did not
    /// train it.
    pub primary_loss: Option<f32>,
    pub n_rays: u64,
    /// Samples that contributed to the loss (the reference's compacted samples).
    pub n_samples: u64,
    /// Samples marched (≥ n_samples).
    pub n_marched: u64,
    /// Samples run through the whole network (density and colour), each forward pass
    /// counted: this engine runs it on the used samples only (density-only waves find where
    /// rays stop); a backend that first runs an inference pass over the marched samples, as
    /// instant-ngp does, counts those too.
    pub n_network: u64,
    /// Rays drawn that trained nothing because a backend's batch buffer was full; 0 here.
    pub dropped_rays: u64,
    /// Times the host waited for a separate device in this step, and the command
    /// submissions it made (0 here).
    pub host_waits: u32,
    pub submissions: u32,
    /// Points where a policy's extra density loss ([`PolicyOps::density_loss`]) had a
    /// gradient this step.
    pub penalised: u32,
    pub seconds: f64,
    /// Time spent refreshing occupancy grids, in rays (march + network + loss), and in the
    /// optimizer, within `seconds`. On a device backend these are the host's times between
    /// those points of the step (recording, submitting, and any wait a submission makes),
    /// not the device's: its phases are in the device profile (`--profile-every`).
    pub occupancy_seconds: f64,
    pub rays_seconds: f64,
    pub optimizer_seconds: f64,
    /// Time within `seconds` the host spent waiting for a separate device to finish
    /// earlier work (a GPU's late measurements), outside the three phases above; 0 here.
    pub wait_seconds: f64,
    /// Occupancy-grid updates this step made (0 or 1) and the densities they evaluated.
    pub occupancy_updates: u32,
    pub occupancy_evaluations: u64,
}

/// Samples a worker marches before running the network on them.
const GROUP_SAMPLES: usize = 4 * CHUNK;

pub struct Trainer {
    pub net: NerfNetwork,
    pub params: Vec<f32>,
    pub optimizer: Optimizer,
    pub config: TrainConfig,
    scenes: Vec<SceneState>,
    workers: Vec<Worker>,
    policy: Option<Box<dyn TrainPolicy>>,
    mech: Mechanisms,
    grid_updates: GridUpdates,
    /// Steps taken, updating the weights or not: the schedule's and the rays' clock.
    pub step: u32,
    /// Steps that updated the weights (every step unless a policy's clock says otherwise):
    /// the optimizer's and the occupancy grids' clock, and the step count a model file
    /// records.
    pub weight_steps: u32,
}

/// The state of the hooks' mechanisms, made when a policy first uses them.
#[derive(Default)]
struct Mechanisms {
    hold: Option<HoldBack>,
    kept: Option<KeptMlp>,
    bounds: Option<TableBounds>,
}

impl Trainer {
    pub fn new(model: ModelConfig, scenes: Vec<SceneSpec>, config: TrainConfig) -> Result<Self> {
        if scenes.is_empty() {
            return Err(Error::Config("no scene to train".into()));
        }
        if !(config.others_batch > 0.0 && config.others_batch <= 1.0) {
            return Err(Error::Config(format!(
                "the other scenes' batch fraction must be in (0, 1], not {}",
                config.others_batch
            )));
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
            let rays = initial_rays_per_batch(config.scene_batch(states.len()));
            states.push(SceneState {
                data: s.dataset,
                indices: s.indices,
                grid,
                marcher: Marcher::new(model.aabb_scale),
                loss_weight: if states.is_empty() {
                    1.0
                } else {
                    config.others_weight
                },
                rays_per_batch: rays,
                measured_samples: 0,
                measured_marched: 0,
                stride: 1,
                cameras: None,
            });
        }
        let n_workers = if config.workers == 0 {
            rayon::current_num_threads()
        } else {
            config.workers
        };
        super::memory::check(
            net.layout.n_params,
            n_workers,
            super::memory::available_bytes(),
        )?;
        let params = net.init_params(config.seed);
        let workers = (0..n_workers).map(|_| Worker::new(params.len())).collect();
        let optimizer = Optimizer::new(config.optimizer, params.len(), net.layout.n_mlp_params());
        let grid_updates = GridUpdates::new(config.occupancy_budget, states.len());
        Ok(Trainer {
            net,
            params,
            optimizer,
            config,
            scenes: states,
            workers,
            policy: None,
            mech: Mechanisms::default(),
            grid_updates,
            step: 0,
            weight_steps: 0,
        })
    }

    /// Starts from published weights instead of the seed's initialisation, before the first
    /// step: `params` become the weights (the optimizer fresh, its EMA of them as they are:
    /// an entry no step moves publishes as given), and scene 0 marches through `grid` where
    /// one is given (a published model's stored grid, refreshed from there as training goes
    /// on). What fine-tuning a downloaded model is.
    pub fn start_from(&mut self, params: &[f32], grid: Option<OccupancyGrid>) -> Result<()> {
        if self.step != 0 {
            return Err(Error::Config(
                "a trainer starts from given weights only before its first step".into(),
            ));
        }
        if params.len() != self.params.len() {
            return Err(Error::Config(format!(
                "{} parameters for a {}-parameter network",
                params.len(),
                self.params.len()
            )));
        }
        self.params.copy_from_slice(params);
        if let Some(g) = grid {
            if g.n_cascades != self.scenes[0].grid.n_cascades {
                return Err(Error::Config(format!(
                    "an occupancy grid of {} cascades for a model of {}",
                    g.n_cascades, self.scenes[0].grid.n_cascades
                )));
            }
            self.scenes[0].grid = g;
        }
        Ok(())
    }

    pub fn n_scenes(&self) -> usize {
        self.scenes.len()
    }

    /// The occupancy grid of scene `i` (0: the one a model publishes).
    pub fn grid(&self, i: usize) -> &OccupancyGrid {
        &self.scenes[i].grid
    }

    /// The training images of scene `i`.
    pub fn dataset(&self, i: usize) -> &Dataset {
        &self.scenes[i].data
    }

    /// Scene `i`'s (rays per batch, trained samples, marched samples) of the last step.
    pub fn batch_counters(&self, i: usize) -> (u32, u32, u32) {
        let s = &self.scenes[i];
        (s.rays_per_batch, s.measured_samples, s.measured_marched)
    }

    /// Refines scene 0's training cameras as it trains ([`super::cameras`]), from the first
    /// step; the other scenes' cameras (generated, exact) stay as given.
    pub fn refine_cameras(&mut self, config: CameraRefinement) -> Result<()> {
        if self.step != 0 {
            return Err(Error::Config(
                "camera refinement starts before the first step".into(),
            ));
        }
        let scene = &mut self.scenes[0];
        let side = scene.marcher.aabb_max[0] - scene.marcher.aabb_min[0];
        scene.cameras = Some(CameraRefiner::new(scene.data.frames.len(), side, config)?);
        Ok(())
    }

    /// Scene 0's refined cameras, where they are refined.
    pub fn cameras(&self) -> Option<&CameraRefiner> {
        self.scenes[0].cameras.as_ref()
    }

    /// The reference's steps a training sample of scene `i` stands for at the next step
    /// ([`super::coarse`]).
    pub fn march_stride(&self, i: usize) -> u32 {
        self.scenes[i].stride
    }

    /// The table's bounds, once a policy has set them ([`PolicyOps::update_bounds`]).
    pub fn table_bounds(&self) -> Option<&TableBounds> {
        self.mech.bounds.as_ref()
    }

    /// The gradient waiting in the buffers, summed over the workers (between steps: what a
    /// step that did not update the weights left for the next one; zero otherwise).
    pub fn gradient(&self) -> Vec<f32> {
        let mut g = vec![0.0f32; self.params.len()];
        for w in &self.workers {
            for (s, x) in g.iter_mut().zip(&w.grad) {
                *s += x;
            }
        }
        g
    }

    /// The table gradients a gate holds back ([`PolicyOps::hold_back`]), once used.
    pub fn held_back(&self) -> Option<&[f32]> {
        self.mech.hold.as_ref().map(|h| h.pending())
    }

    /// Index functions of scene `i` as trained now.
    pub fn indices(&self, i: usize) -> &LevelIndices {
        &self.scenes[i].indices
    }

    /// Installs a training policy, before the first step, and applies its index functions
    /// to scene 0's starting grid.
    pub fn set_policy(&mut self, policy: Box<dyn TrainPolicy>) -> Result<()> {
        if self.step > 0 {
            return Err(Error::Config(
                "a training policy is installed before the first step".into(),
            ));
        }
        let reads = policy.reads();
        self.policy = Some(policy);
        if reads.published {
            let published = self.optimizer.ema_params(&self.params);
            let fresh = self.policy_indices(&published);
            self.set_indices(fresh)?;
        }
        Ok(())
    }

    fn policy_indices(&mut self, published: &[f32]) -> Vec<(usize, LevelIndices)> {
        match &mut self.policy {
            Some(p) => p.indices(&self.scenes[0].grid, published),
            None => Vec::new(),
        }
    }

    /// Index functions for the scenes named, all checked before any is used.
    fn set_indices(&mut self, fresh: Vec<(usize, LevelIndices)>) -> Result<()> {
        let n_levels = self.net.layout.grid.levels.len();
        for (i, indices) in &fresh {
            if *i == 0 || *i >= self.scenes.len() || indices.len() != n_levels {
                return Err(Error::Config(format!(
                    "index refresh for scene {i} with {} levels ({} scenes, {n_levels} levels; scene 0 is never refreshed)",
                    indices.len(),
                    self.scenes.len()
                )));
            }
            check_indices(indices, &self.net.layout.grid)?;
        }
        for (i, indices) in fresh {
            self.scenes[i].indices = indices;
        }
        Ok(())
    }

    /// The parts of a training a saved state must share with the trainer it goes back into,
    /// by name. Never the index functions: a state's errors may be printed, and a key must
    /// not be (the program re-derives them from the same key files).
    fn fingerprint(&self) -> Vec<(String, String)> {
        let mut options = self.config.clone();
        options.workers = self.workers.len();
        let mut out = super::state::fingerprint(
            None,
            &self.net.layout.config,
            &options,
            self.policy.is_some(),
            self.scenes.iter().map(|s| s.data.as_ref()),
        );
        // Only where refined, so that the states of runs without it keep their fingerprint.
        if let Some(c) = self.cameras() {
            out.push((super::state::CAMERAS.to_string(), format!("{:?}", c.config)));
        }
        out
    }

    /// The whole training state between two steps ([`super::state`]): restored into a
    /// trainer built the same way (its policy too), training goes on as if it had never
    /// stopped. With a policy: its own state, the mechanisms' (held-back gradients, table
    /// bounds) and the gradients a step that did not update the weights left waiting in
    /// the workers' buffers.
    pub fn save_state(&self) -> Result<Vec<u8>> {
        Ok(super::state::encode(&self.save_state_doc()?))
    }

    /// [`save_state`](Self::save_state) as a document, for a caller that nests it.
    pub fn save_state_doc(&self) -> Result<rmpv::Value> {
        use super::state::{self, Sparse};
        use std::borrow::Cow::Borrowed;
        let (since, updates) = self.grid_updates.clock();
        let scenes = self.scenes.iter().map(|s| state::Scene {
            grid: Borrowed(&s.grid),
            rays_per_batch: s.rays_per_batch,
            measured_samples: s.measured_samples,
            measured_marched: s.measured_marched,
            march_stride: s.stride,
        });
        let workers = self.workers.iter().map(|w| state::Worker {
            grad: Sparse::of(&w.grad),
            touched: Borrowed(w.touched.words()),
        });
        let policy = match &self.policy {
            Some(p) => p.save_state()?.map(Into::into),
            None => None,
        };
        let doc = state::TrainerState {
            fingerprint: self.fingerprint(),
            step: self.step,
            weight_steps: self.weight_steps,
            params: Borrowed(&self.params),
            optimizer: self.optimizer.state(&self.params),
            occupancy_clock: Some(state::OccupancyClock {
                since: Borrowed(since),
                updates,
            }),
            scenes: scenes.collect(),
            mechanisms: Some(state::Mechanisms {
                held: self.mech.hold.as_ref().map(|h| Sparse::of(h.pending())),
                bounds: self.mech.bounds.as_ref().map(Borrowed),
            }),
            waiting: state::Waiting::Workers(workers.collect()),
            policy,
            cameras: self.cameras().map(CameraRefiner::save),
        };
        Ok(doc.to_value())
    }

    /// Takes back a [`save_state`](Self::save_state) into this trainer, which must be fresh
    /// (no step taken) and built from the same scenes, layout, options and worker count;
    /// `origin` names the state in errors. Every field is read and checked before any is
    /// taken; after an error, drop the trainer.
    pub fn restore_state(&mut self, bytes: &[u8], origin: &std::path::Path) -> Result<()> {
        self.restore_state_doc(&super::state::open(origin, bytes)?, origin)
    }

    /// [`restore_state`](Self::restore_state) from the document.
    pub fn restore_state_doc(&mut self, doc: &rmpv::Value, origin: &std::path::Path) -> Result<()> {
        use super::state::{self, TrainerState, Waiting};
        if self.step != 0 {
            return Err(Error::Config(
                "a training state goes into a trainer that has not stepped".into(),
            ));
        }
        let (n, n_matrix) = (self.params.len(), self.net.layout.n_mlp_params());
        let n_features = self.net.layout.config.grid.n_features as usize;
        let expect = state::Expect {
            fingerprint: &self.fingerprint(),
            device: state::Device::Cpu {
                workers: self.workers.len(),
                touched_words: self.workers.first().map_or(0, |w| w.touched.words().len()),
                ema_groups: self.optimizer.ema_groups(),
            },
            optimizer: self.optimizer.config,
            n_params: n,
            n_matrix,
            n_entries: (n - self.net.layout.grid_offset) / n_features,
            n_features,
            scene_cells: self.scenes.iter().map(|s| s.grid.density.len()).collect(),
            policy: self.policy.is_some(),
            refined_images: self.cameras().map(|c| c.offsets().len()),
        };
        let saved = TrainerState::read(origin, doc, &expect)?;
        self.params.copy_from_slice(&saved.params);
        self.optimizer.restore(saved.optimizer);
        let clock = saved.occupancy_clock.expect("read for the CPU");
        self.grid_updates.set_clock(&clock.since, clock.updates);
        for (s, saved) in self.scenes.iter_mut().zip(saved.scenes) {
            s.grid = saved.grid.into_owned();
            s.rays_per_batch = saved.rays_per_batch;
            s.measured_samples = saved.measured_samples;
            s.measured_marched = saved.measured_marched;
            s.stride = saved.march_stride;
        }
        let mech = saved.mechanisms.expect("read for the CPU");
        self.mech.hold = mech.held.map(|held| {
            let mut hold = HoldBack::new(n, n_matrix);
            held.scatter_into(hold.pending_mut());
            hold
        });
        self.mech.bounds = mech.bounds.map(std::borrow::Cow::into_owned);
        let Waiting::Workers(workers) = saved.waiting else {
            unreachable!("read for the CPU")
        };
        for (w, saved) in self.workers.iter_mut().zip(workers) {
            saved.grad.scatter_into(&mut w.grad);
            w.touched.words_mut().copy_from_slice(&saved.touched);
        }
        // The fingerprint has checked that a policy is installed here iff one saved.
        if let Some(p) = &mut self.policy {
            let fresh = p.restore_state(saved.policy.as_deref(), origin)?;
            self.set_indices(fresh)?;
        }
        if let (Some(c), Some(saved)) = (&mut self.scenes[0].cameras, &saved.cameras) {
            c.restore(saved).ok_or_else(|| {
                Error::format(origin, "the camera offsets are not one per training image")
            })?;
        }
        self.step = saved.step;
        self.weight_steps = saved.weight_steps;
        Ok(())
    }

    /// Weights to render with and to publish: the debiased EMA.
    pub fn inference_params(&self) -> Vec<f32> {
        self.optimizer.ema_params(&self.params)
    }

    /// Refreshes every scene's occupancy grid when an update is due ([`GridUpdates`]);
    /// `trained` are the scenes this step trains. Returns the densities evaluated, `None`
    /// when no update was due; an error where the training policy failed.
    fn update_occupancy(&mut self, trained: &[usize]) -> Result<Option<u64>> {
        let step = self.weight_steps;
        let fraction = self.config.occupancy_fraction;
        let n = self.scenes.len();
        let mut samples = vec![0u64; n];
        for &si in trained {
            samples[si] = self.config.scene_batch(si) as u64;
        }
        let mut shares = vec![0f32; n];
        let scenes = &self.scenes;
        let due = self.grid_updates.due(
            step,
            &samples,
            &mut shares,
            |si| scenes[si].grid.ema_step == 0,
            |si| scenes[si].grid.expected_update_cost(step, fraction),
        );
        if !due {
            return Ok(None);
        }
        let seed = self.config.seed;
        let mut evaluated = 0;
        for (si, &share) in shares.iter().enumerate() {
            if share == 0.0 {
                continue;
            }
            let SceneState {
                grid,
                marcher,
                indices,
                ..
            } = &mut self.scenes[si];
            let (net, params) = (&self.net, &self.params);
            let seed = mix(seed, 0x6772_6964 + si as u64);
            // A grid's first update draws every cell, as the reference's first steps do,
            // even for a scene that joins late (a hidden scene after the cover's warm-up).
            let at = if grid.ema_step == 0 { 0 } else { step };
            evaluated += grid.update_share(at, fraction, share, seed, |pos| {
                let warped: Vec<[f32; 3]> = pos.iter().map(|&p| marcher.warp(p)).collect();
                net.density_batch(params, indices, &warped)
            });
            // The policy's indices take effect before the other scenes' grids are updated.
            if si == 0 && self.policy.is_some() {
                self.primary_grid_updated()?;
            }
        }
        Ok(Some(evaluated as u64))
    }

    /// The policy's hooks after an update of scene 0's grid.
    fn primary_grid_updated(&mut self) -> Result<()> {
        let Some(policy) = &mut self.policy else {
            return Ok(());
        };
        let reads = policy.reads();
        let published = reads
            .published
            .then(|| self.optimizer.ema_params(&self.params));
        let grid = &self.scenes[0].grid;
        let mut ops = CpuOps {
            net: &self.net,
            params: &self.params,
            scenes: &self.scenes,
            workers: &mut self.workers,
            mech: &mut self.mech,
            penalised: 0,
        };
        policy
            .grid_updated(reads.grid.then_some(grid), published.as_deref(), &mut ops)
            .map_err(policy_failed)?;
        let fresh = match &published {
            Some(p) => policy.indices(grid, p),
            None => Vec::new(),
        };
        self.set_indices(fresh).map_err(|e| {
            Error::Other(format!(
                "the training policy gave invalid index functions: {e}"
            ))
        })
    }

    /// Runs a policy hook on the CPU's mechanisms; returns the points its extra loss
    /// penalised.
    fn with_policy(
        &mut self,
        hook: impl FnOnce(&mut dyn TrainPolicy, &mut dyn PolicyOps) -> Result<()>,
    ) -> Result<u32> {
        let Some(policy) = &mut self.policy else {
            return Ok(0);
        };
        let mut ops = CpuOps {
            net: &self.net,
            params: &self.params,
            scenes: &self.scenes,
            workers: &mut self.workers,
            mech: &mut self.mech,
            penalised: 0,
        };
        hook(policy.as_mut(), &mut ops).map_err(policy_failed)?;
        Ok(ops.penalised)
    }

    fn step_info(&self) -> StepInfo {
        StepInfo {
            seed: self.config.seed,
            step: self.step,
            weight_steps: self.weight_steps,
        }
    }

    /// One training step; an error where the training policy failed (the step's weights
    /// are then not updated).
    pub fn train_step(&mut self) -> Result<StepStats> {
        let t0 = std::time::Instant::now();
        let step = self.step;
        let info = self.step_info();
        let scene_ids = self.config.step_scenes(step, self.scenes.len());
        let update = self
            .policy
            .as_ref()
            .is_none_or(|p| p.updates_weights(&scene_ids));
        let occupancy = if update {
            self.update_occupancy(&scene_ids)?
        } else {
            None
        };
        let t_occ = t0.elapsed().as_secs_f64();
        let mut stats = StepStats {
            step,
            occupancy_updates: occupancy.is_some() as u32,
            occupancy_evaluations: occupancy.unwrap_or(0),
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
                    if let Some(c) = &scene.cameras {
                        worker.cam_grad.clear();
                        worker.cam_grad.resize(c.offsets().len(), [0.0; 6]);
                    }
                    train_rays(net, params, scene, seed, r0..r1, n_rays, worker);
                });
            if let Some(c) = &mut self.scenes[si].cameras {
                c.add_step(self.workers.iter().map(|w| w.cam_grad.as_slice()));
            }
            let mut loss = 0.0;
            let (mut used, mut marched, mut rays) = (0, 0, 0);
            for w in &self.workers {
                loss += w.loss;
                used += w.n_samples;
                marched += w.n_marched;
                rays += w.n_rays;
            }
            stats.n_rays += rays;
            stats.n_marched += marched;
            let scene_loss = (loss / n_rays as f64) as f32;
            stats.loss += scene_loss;
            if si == 0 {
                stats.primary_loss = Some(scene_loss);
            }
            stats.n_samples += used;
            stats.n_network += used;
            let scene = &mut self.scenes[si];
            scene.measured_samples = used as u32;
            scene.measured_marched = marched as u32;
            let stride = coarse::next_stride(self.config.coarse_march, scene.stride, rays, used);
            // The reference keeps its ray count when nothing was trained.
            if used > 0 {
                let expected = coarse::at_stride(used, scene.stride, stride);
                scene.rays_per_batch =
                    next_rays_per_batch(n_rays as u32, self.config.scene_batch(si), expected);
            }
            scene.stride = stride;
            stats.penalised += self.with_policy(|p, ops| p.after_scene(si, info, ops))?;
        }
        stats.penalised += self.with_policy(|p, ops| p.before_update(info, ops))?;
        let t_rays = t0.elapsed().as_secs_f64();
        // Without the update, the gradients left in the workers' buffers wait there for the
        // next step that updates the weights (a gate's held-back ones in its own sum).
        if update {
            self.update_weights();
            self.weight_steps += 1;
        }
        self.step += 1;
        stats.seconds = t0.elapsed().as_secs_f64();
        stats.occupancy_seconds = t_occ;
        stats.rays_seconds = t_rays - t_occ;
        stats.optimizer_seconds = stats.seconds - t_rays;
        Ok(stats)
    }

    /// One optimizer step on the summed gradients of the workers, which it leaves zeroed;
    /// then the table's bounds.
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
        if let Some(b) = &self.mech.bounds {
            b.clamp(&mut self.params[self.net.layout.grid_offset..]);
        }
        for ((w, g), mut t) in self.workers.iter_mut().zip(grads).zip(touched) {
            w.grad = g;
            t.clear();
            w.touched = t;
        }
    }
}

impl Model {
    /// The model a CPU trainer would publish now, with `loss` as its stored loss.
    pub fn from_trainer(t: &Trainer, loss: f32) -> Self {
        Model::from_parts(
            t.net.layout.config,
            t.inference_params(),
            t.grid(0).clone(),
            t.weight_steps,
            loss,
            t.dataset(0),
            t.batch_counters(0),
        )
        .expect("a trainer's config and parameters are consistent")
    }
}

/// The CPU's side of [`PolicyOps`]: the mechanisms act on the workers' partial gradients.
struct CpuOps<'a> {
    net: &'a NerfNetwork,
    params: &'a [f32],
    scenes: &'a [SceneState],
    workers: &'a mut [Worker],
    mech: &'a mut Mechanisms,
    penalised: u32,
}

impl CpuOps<'_> {
    /// The gate (made on first use), the table's bounds and the workers it acts on.
    fn held(&mut self) -> (&mut HoldBack, Option<&TableBounds>, &mut [Worker]) {
        let (n, n_matrix) = (self.params.len(), self.net.layout.n_mlp_params());
        let Mechanisms { hold, bounds, .. } = &mut *self.mech;
        let hold = hold.get_or_insert_with(|| HoldBack::new(n, n_matrix));
        (hold, bounds.as_ref(), self.workers)
    }

    /// The kept MLP gradient (made on first use) and the workers it acts on.
    fn kept(&mut self) -> (&mut KeptMlp, &mut [Worker]) {
        let (n_workers, n_matrix) = (self.workers.len(), self.net.layout.n_mlp_params());
        let kept = self
            .mech
            .kept
            .get_or_insert_with(|| KeptMlp::new(n_workers, n_matrix));
        (kept, self.workers)
    }
}

impl PolicyOps for CpuOps<'_> {
    fn density_loss(
        &mut self,
        scene: usize,
        points: &[[f32; 3]],
        d_loss: &(dyn Fn(f32) -> f32 + Sync),
    ) -> Result<u32> {
        let Some(s) = self.scenes.get(scene) else {
            return Err(Error::Config(format!(
                "a density loss on scene {scene} of {}",
                self.scenes.len()
            )));
        };
        let n = density_loss(self.net, self.params, s, self.workers, points, d_loss);
        self.penalised += n;
        Ok(n)
    }

    fn open_gate(&mut self) -> Result<()> {
        let (hold, _, workers) = self.held();
        hold.open_gate(workers);
        Ok(())
    }

    fn hold_back(&mut self) -> Result<()> {
        let (hold, bounds, workers) = self.held();
        hold.hold_back(workers, bounds);
        Ok(())
    }

    fn keep_mlp(&mut self) -> Result<()> {
        let (kept, workers) = self.kept();
        kept.keep(workers);
        Ok(())
    }

    fn restore_mlp(&mut self) -> Result<()> {
        let (kept, workers) = self.kept();
        kept.restore(workers);
        Ok(())
    }

    fn update_bounds(&mut self, update: &mut dyn FnMut(&mut TableBounds)) -> Result<()> {
        let grid = &self.net.layout.grid;
        let (n_entries, f) = (grid.n_entries as usize, grid.config.n_features as usize);
        update(
            self.mech
                .bounds
                .get_or_insert_with(|| TableBounds::new(n_entries, f)),
        );
        Ok(())
    }
}

/// [`PolicyOps::density_loss`] on the CPU: the points split over the workers as rays are,
/// each worker's through the network forward and back into its own gradient.
fn density_loss(
    net: &NerfNetwork,
    params: &[f32],
    scene: &SceneState,
    workers: &mut [Worker],
    points: &[[f32; 3]],
    d_loss: &(dyn Fn(f32) -> f32 + Sync),
) -> u32 {
    let pos: Vec<[f32; 3]> = points.iter().map(|&p| scene.marcher.warp(p)).collect();
    let n = pos.len();
    if n == 0 {
        return 0;
    }
    let n_workers = workers.len();
    let grid_offset = net.layout.grid_offset;
    let n_levels = net.layout.grid.levels.len();
    workers
        .par_iter_mut()
        .enumerate()
        .map(|(w, worker)| {
            let range = n * w / n_workers..n * (w + 1) / n_workers;
            if worker.ws.is_empty() {
                worker.ws.push(net.workspace());
            }
            let mut active = 0;
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
                    &scene.indices,
                    chunk,
                    &worker.dir,
                    ws,
                    &mut worker.raw,
                );
                for (d, r) in worker.d_raw.iter_mut().zip(&worker.raw) {
                    let g = d_loss(r[3]);
                    active += (g != 0.0) as u32;
                    *d = [0.0, 0.0, 0.0, g];
                }
                net.backward(params, &scene.indices, &worker.d_raw, ws, &mut worker.grad);
                mark_corners(ws, n_levels, grid_offset, &mut worker.touched);
            }
            active
        })
        .sum()
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
    let stride = scene.stride as f32;
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
            let ray = scene.ray(img, x, y);
            let Some((tmin, _)) = scene.marcher.intersect(ray.o, ray.d) else {
                continue;
            };
            // The start is jittered over the whole stride, so that coarse samples cover
            // the ray as densely as the reference's do.
            let t = scene.marcher.advance(tmin, stride * rng.next_f32());
            let start = w.pos.len();
            scene.marcher.march_strided(
                &scene.grid,
                ray.o,
                ray.d,
                t,
                MAX_SAMPLES_PER_RAY,
                stride,
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
                image: img,
                o: ray.o,
                d: ray.d,
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
        if scene.cameras.is_some() {
            camera_gradients(net, params, scene, n_chunks, w);
        }
    }
}

/// Adds the camera offsets' gradient of every ray of the worker's group (whose backward
/// has just run) into its image's row of `w.cam_grad`.
fn camera_gradients(
    net: &NerfNetwork,
    params: &[f32],
    scene: &SceneState,
    n_chunks: usize,
    w: &mut Worker,
) {
    let total = w.pos.len();
    w.d_pos.clear();
    w.d_pos.resize(total, [0.0; 3]);
    for k in 0..n_chunks {
        let r = k * CHUNK..((k + 1) * CHUNK).min(total);
        net.position_gradient(params, &w.pos[r.clone()], &w.ws[k], &mut w.d_pos[r]);
    }
    let m = &scene.marcher;
    let size = [0, 1, 2].map(|k| m.aabb_max[k] - m.aabb_min[k]);
    for ray in &w.rays {
        let r = ray.start..ray.start + ray.n;
        let g = cameras::ray_gradient(
            ray.o,
            ray.d,
            m.aabb_min,
            size,
            &w.pos[r.clone()],
            &w.d_pos[r],
        );
        let row = &mut w.cam_grad[ray.image];
        for k in 0..6 {
            row[k] += g[k];
        }
    }
}

/// A policy hook's error, saying where it came from.
fn policy_failed(e: Error) -> Error {
    Error::Other(format!("the training policy failed on the CPU: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::Split;
    use crate::encoding::{GridConfig, reference_indices};
    use crate::network::NerfLayout;

    /// A small NeRF-synthetic scene made in memory: `n` views of 16×16 noise on a ring of
    /// cameras looking at the origin, as the loader would read them from PNGs and a
    /// `transforms_train.json` with `camera_angle_x` 0.7 (`dir` is only its root).
    fn tiny_scene(dir: &std::path::Path, n: usize) -> Arc<Dataset> {
        let mut rng = Pcg32::new(4, 4);
        let fl = (0.5 * 16.0 / (0.5 * 0.7f64).tan()) as f32;
        let mut frames = Vec::new();
        for i in 0..n {
            let a = i as f32 * std::f32::consts::TAU / n as f32;
            let (s, c) = a.sin_cos();
            // Camera at (4c, 4s, 1) looking at the origin (OpenGL: −z forward, +y up).
            let pos = [4.0 * c, 4.0 * s, 1.0f32];
            let len = (pos[0] * pos[0] + pos[1] * pos[1] + pos[2] * pos[2]).sqrt();
            let z = pos.map(|p| p / len);
            let x = [-s, c, 0.0];
            let y = [
                z[1] * x[2] - z[2] * x[1],
                z[2] * x[0] - z[0] * x[2],
                z[0] * x[1] - z[1] * x[0],
            ];
            let pose = [
                [x[0], y[0], z[0], pos[0]],
                [x[1], y[1], z[1], pos[1]],
                [x[2], y[2], z[2], pos[2]],
            ];
            let rgb: Vec<f32> = (0..16 * 16 * 3).map(|_| rng.next_f32()).collect();
            // What an 8-bit RGB PNG of `rgb` decodes to.
            let rgba: Vec<u8> = rgb
                .chunks_exact(3)
                .flat_map(|p| {
                    let q = p.iter().map(|&v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8);
                    q.chain(std::iter::once(255))
                })
                .collect();
            frames.push(crate::data::Frame {
                camera: crate::camera::Camera {
                    c2w: crate::camera::nerf_to_ngp(&pose, 0.33, [0.5; 3]),
                    fx: fl,
                    fy: fl,
                    cx: 8.0,
                    cy: 8.0,
                    width: 16,
                    height: 16,
                    distortion: None,
                },
                image: crate::data::Image::from_rgba8(16, 16, rgba).unwrap(),
                file_path: format!("./train/r_{i}"),
            });
        }
        Arc::new(Dataset {
            root: dir.to_path_buf(),
            split: Split::Train,
            width: 16,
            height: 16,
            frames,
            aabb_scale: 1,
            scale: 0.33,
            offset: [0.5; 3],
            has_alpha: false,
            format: crate::data::DatasetFormat::NerfSynthetic,
        })
    }

    /// 4 levels of 2^10 entries: a step in milliseconds.
    fn tiny_model() -> ModelConfig {
        ModelConfig {
            grid: GridConfig {
                n_levels: 4,
                n_features: 2,
                log2_hashmap_size: 10,
                base_resolution: 16,
            },
            aabb_scale: 1,
        }
    }

    fn two_scene_trainer(dir: &std::path::Path, seed: u64) -> Trainer {
        let a = tiny_scene(&dir.join("a"), 6);
        let b = tiny_scene(&dir.join("b"), 5);
        // A coarse march, so that the state's strides are restored too.
        tiny_trainer(vec![a, b], seed, Some(16), 1 << 11)
    }

    fn tiny_trainer(
        datasets: Vec<Arc<Dataset>>,
        seed: u64,
        coarse_march: Option<u32>,
        batch_samples: u32,
    ) -> Trainer {
        let model = tiny_model();
        let layout = NerfLayout::new(model).unwrap();
        let scenes = datasets
            .into_iter()
            .map(|dataset| SceneSpec {
                dataset,
                indices: reference_indices(&layout.grid),
            })
            .collect();
        let tc = TrainConfig {
            seed,
            batch_samples,
            occupancy_fraction: 0.05,
            coarse_march,
            workers: 2,
            ..Default::default()
        };
        Trainer::new(model, scenes, tc).unwrap()
    }

    /// A policy whose hook fails makes the step an error naming it, not a panic, and the
    /// weights are left as they were (the optimizer never ran).
    #[test]
    fn a_failing_policy_is_an_error_not_a_panic() {
        struct Failing;
        impl TrainPolicy for Failing {
            fn before_update(&mut self, _: StepInfo, _: &mut dyn PolicyOps) -> Result<()> {
                Err(Error::Other("no room for the hold-back".into()))
            }
        }
        let dir = tempfile::tempdir().unwrap();
        let a = tiny_scene(&dir.path().join("a"), 4);
        let mut t = tiny_trainer(vec![a], 3, None, 1 << 10);
        t.set_policy(Box::new(Failing)).unwrap();
        let before = t.params.clone();
        let e = t.train_step().unwrap_err().to_string();
        assert!(
            e.contains("training policy failed") && e.contains("no room for the hold-back"),
            "{e}"
        );
        assert_eq!(t.params, before, "a failed step updated the weights");
    }

    #[test]
    fn the_other_scenes_batch_is_a_fraction_of_the_first_scenes() {
        let tc = |f| TrainConfig {
            others_batch: f,
            ..Default::default()
        };
        assert_eq!(tc(0.25).scene_batch(0), 1 << 18);
        assert_eq!(tc(0.25).scene_batch(1), 1 << 16);
        assert_eq!(tc(1.0).scene_batch(2), 1 << 18);
        assert_eq!(
            tc(0.001).scene_batch(1),
            MIN_SCENE_BATCH,
            "at least the floor"
        );
        let small = TrainConfig {
            batch_samples: 1000,
            others_batch: 0.5,
            ..Default::default()
        };
        assert_eq!(
            small.scene_batch(1),
            1000,
            "never above the first scene's batch"
        );
    }

    /// The same scene twice, the second at a quarter of the batch and from the third step:
    /// it trains about a quarter of the samples a step (its rays adapt to its own target),
    /// its grid is first updated when it joins, and a fraction outside (0, 1] is refused.
    #[test]
    fn a_smaller_batch_for_the_other_scenes_trains_fewer_of_their_samples() {
        let dir = tempfile::tempdir().unwrap();
        let data = tiny_scene(&dir.path().join("a"), 6);
        let model = tiny_model();
        let layout = NerfLayout::new(model).unwrap();
        let specs = || {
            (0..2)
                .map(|_| SceneSpec {
                    dataset: data.clone(),
                    indices: reference_indices(&layout.grid),
                })
                .collect::<Vec<_>>()
        };
        let tc = |f| TrainConfig {
            seed: 3,
            // Enough samples that neither scene's rays sit at the floor of 256.
            batch_samples: 1 << 17,
            occupancy_fraction: 0.05,
            occupancy_budget: Some(1.0),
            others_batch: f,
            solo_steps: 2,
            workers: 2,
            ..Default::default()
        };
        for bad in [0.0, -1.0, 1.5, f32::NAN] {
            assert!(Trainer::new(model, specs(), tc(bad)).is_err(), "{bad}");
        }
        let mut t = Trainer::new(model, specs(), tc(0.25)).unwrap();
        let (mut first, mut other) = (0u64, 0u64);
        for step in 0..8 {
            t.train_step().unwrap();
            // A grid is paid for by its own scene's samples: none while the first trains
            // alone.
            let updates = t.scenes[1].grid.ema_step;
            assert_eq!(updates == 0, step < 2, "step {step}: {updates} updates");
            if step >= 3 {
                first += t.scenes[0].measured_samples as u64;
                other += t.scenes[1].measured_samples as u64;
            }
        }
        let ratio = other as f64 / first as f64;
        assert!(
            (0.18..0.4).contains(&ratio),
            "samples: {other} of the second scene against {first} ({ratio:.3})"
        );
    }

    /// While rays are long (the noise views of the tiny scene are fog at first) the coarse
    /// march strides over them and trains several times the rays a step, and it steps back
    /// towards the reference's step as they shorten; without it the stride stays 1.
    #[test]
    fn a_coarse_march_trains_more_rays_while_rays_are_long() {
        let dir = tempfile::tempdir().unwrap();
        let data = tiny_scene(&dir.path().join("a"), 6);
        // A batch of many rays (not the floor of 256 a tiny batch stays at).
        let mut reference = tiny_trainer(vec![data.clone()], 5, None, 1 << 15);
        let mut coarse = tiny_trainer(vec![data], 5, Some(16), 1 << 15);
        let (mut rays_ref, mut rays_coarse, mut strides) = (0, 0, Vec::new());
        for step in 0..30 {
            let (a, b) = (
                reference.train_step().unwrap(),
                coarse.train_step().unwrap(),
            );
            assert_eq!(reference.march_stride(0), 1);
            strides.push(coarse.march_stride(0));
            if (3..20).contains(&step) {
                rays_ref += a.n_rays;
                rays_coarse += b.n_rays;
            }
        }
        assert_eq!(
            strides[0], 1,
            "the first step's rays are short: {strides:?}"
        );
        assert_eq!(
            *strides.iter().max().unwrap(),
            8,
            "long rays, the coarsest stride: {strides:?}"
        );
        assert!(
            rays_coarse as f64 > 2.5 * rays_ref as f64,
            "rays in steps 3..20: {rays_coarse} coarse, {rays_ref} at the reference's step"
        );
        assert!(
            strides.windows(2).any(|w| w[1] < w[0]),
            "the stride falls as the grid empties: {strides:?}"
        );
    }

    fn bits(v: &[f32]) -> Vec<u32> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    /// A run saved at step 12 and restored into a fresh trainer ends bit for bit where the
    /// uninterrupted run does at step 30: weights, published (EMA) weights and both scenes'
    /// grids; saving does not disturb the run that saved.
    #[test]
    fn a_restored_state_goes_on_bit_for_bit() {
        let dir = tempfile::tempdir().unwrap();
        let mut whole = two_scene_trainer(dir.path(), 3);
        for _ in 0..30 {
            whole.train_step().unwrap();
        }
        let mut first = two_scene_trainer(dir.path(), 3);
        for _ in 0..12 {
            first.train_step().unwrap();
        }
        let saved = first.save_state().unwrap();
        let mut resumed = two_scene_trainer(dir.path(), 3);
        resumed
            .restore_state(&saved, std::path::Path::new("state"))
            .unwrap();
        assert_eq!(resumed.step, 12);
        for _ in 12..30 {
            first.train_step().unwrap();
            resumed.train_step().unwrap();
        }
        for t in [&first, &resumed] {
            assert_eq!(t.step, whole.step);
            assert!(bits(&t.params) == bits(&whole.params), "weights differ");
            assert!(
                bits(&t.inference_params()) == bits(&whole.inference_params()),
                "published weights differ"
            );
            for i in 0..2 {
                assert!(
                    bits(&t.grid(i).density) == bits(&whole.grid(i).density),
                    "grid {i}"
                );
                assert_eq!(t.grid(i).bitfield(), whole.grid(i).bitfield());
                assert_eq!(t.batch_counters(i), whole.batch_counters(i));
                assert_eq!(t.march_stride(i), whole.march_stride(i));
            }
        }
        // The state really moves the run: a fresh trainer without it differs.
        let mut fresh = two_scene_trainer(dir.path(), 3);
        for _ in 12..30 {
            fresh.train_step().unwrap();
        }
        assert!(bits(&fresh.params) != bits(&whole.params));
    }

    /// Camera refinement's offsets and optimiser travel in the state: a resumed refining run
    /// goes on bit for bit, cameras included; a state with refinement and one without do
    /// not go into each other's trainers.
    #[test]
    fn refined_cameras_resume_bit_for_bit_and_plain_states_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let refine = CameraRefinement {
            steps_per_update: 3,
            ..CameraRefinement::default()
        };
        let refining = |seed| {
            let mut t = two_scene_trainer(dir.path(), seed);
            t.refine_cameras(refine).unwrap();
            t
        };
        let mut whole = refining(5);
        for _ in 0..20 {
            whole.train_step().unwrap();
        }
        let mut first = refining(5);
        for _ in 0..10 {
            first.train_step().unwrap();
        }
        let saved = first.save_state().unwrap();
        let mut resumed = refining(5);
        resumed
            .restore_state(&saved, std::path::Path::new("state"))
            .unwrap();
        for _ in 10..20 {
            resumed.train_step().unwrap();
        }
        let cams = |t: &Trainer| -> Vec<u32> {
            let c = t.cameras().unwrap();
            c.offsets().iter().flatten().map(|v| v.to_bits()).collect()
        };
        assert!(
            bits(&resumed.params) == bits(&whole.params),
            "weights differ"
        );
        assert_eq!(cams(&resumed), cams(&whole), "camera offsets differ");
        assert_eq!(whole.cameras().unwrap().updates(), 6);
        assert!(
            whole
                .cameras()
                .unwrap()
                .offsets()
                .iter()
                .flatten()
                .any(|&v| v != 0.0),
            "the cameras never moved"
        );
        // The hidden scene's cameras are not refined: the state has one image set only.
        assert_eq!(
            whole.cameras().unwrap().offsets().len(),
            whole.dataset(0).frames.len()
        );
        let plain_state = two_scene_trainer(dir.path(), 5).save_state().unwrap();
        let e = refining(5)
            .restore_state(&plain_state, std::path::Path::new("plain"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("plain") && e.contains("cameras"), "{e}");
        let e = two_scene_trainer(dir.path(), 5)
            .restore_state(&saved, std::path::Path::new("refined"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("refined") && e.contains("cameras"), "{e}");
        // Refinement starts with the run or not at all.
        assert!(first.refine_cameras(refine).is_err());
    }

    #[test]
    fn a_state_from_another_training_or_damaged_is_refused_naming_the_field() {
        let dir = tempfile::tempdir().unwrap();
        let mut t = two_scene_trainer(dir.path(), 3);
        for _ in 0..3 {
            t.train_step().unwrap();
        }
        let saved = t.save_state().unwrap();
        let origin = std::path::Path::new("run.state");
        let err = |r: Result<()>| r.unwrap_err().to_string();
        // Another seed: the options differ.
        let e = err(two_scene_trainer(dir.path(), 4).restore_state(&saved, origin));
        assert!(
            e.contains("run.state") && e.contains("fingerprint") && e.contains("options"),
            "{e}"
        );
        // Truncated, and not msgpack at all.
        let e =
            err(two_scene_trainer(dir.path(), 3).restore_state(&saved[..saved.len() / 2], origin));
        assert!(e.contains("run.state") && e.contains("msgpack"), "{e}");
        let e = err(two_scene_trainer(dir.path(), 3).restore_state(b"{}", origin));
        assert!(e.contains("run.state"), "{e}");
        // A trainer that has stepped.
        let e = err(t.restore_state(&saved, origin));
        assert!(e.contains("not stepped"), "{e}");
        // The weights of a smaller table: the length is checked, nothing copied.
        let mut doc = rmpv::decode::read_value(&mut saved.as_slice()).unwrap();
        if let rmpv::Value::Map(m) = &mut doc {
            for (k, v) in m.iter_mut() {
                if k.as_str() == Some("params") {
                    *v = rmpv::Value::Binary(vec![0; 16]);
                }
            }
        }
        let mut forged = Vec::new();
        rmpv::encode::write_value(&mut forged, &doc).unwrap();
        let e = err(two_scene_trainer(dir.path(), 3).restore_state(&forged, origin));
        assert!(e.contains("field params") && e.contains("16 bytes"), "{e}");
        // A forged step count: refused before the optimizer's tables are grown to it.
        // (Adam's count, two maps down as tiny-cuda-nn nests it.)
        fn find<'a>(v: &'a mut rmpv::Value, path: &[&str]) -> &'a mut rmpv::Value {
            let Some((first, rest)) = path.split_first() else {
                return v;
            };
            let rmpv::Value::Map(m) = v else {
                panic!("not a map at {first}")
            };
            let (_, inner) = m
                .iter_mut()
                .find(|(k, _)| k.as_str() == Some(first))
                .unwrap_or_else(|| panic!("no {first}"));
            find(inner, rest)
        }
        let mut doc = rmpv::decode::read_value(&mut saved.as_slice()).unwrap();
        *find(&mut doc, &["optimizer", "nested", "nested", "current_step"]) =
            rmpv::Value::from(u32::MAX);
        let mut forged = Vec::new();
        rmpv::encode::write_value(&mut forged, &doc).unwrap();
        let e = err(two_scene_trainer(dir.path(), 3).restore_state(&forged, origin));
        assert!(
            e.contains("optimizer.nested.nested.current_step") && e.contains("at most"),
            "{e}"
        );
    }

    /// [`PolicyOps::density_loss`]'s gradient through the network and the grid equals
    /// finite differences of its loss, on the table entries and MLP weights it moves most.
    /// The loss is the stego layer's density cap: a hinge on the raw log-density,
    /// `w/n · max(0, ld − c)²`, with the cap below the untrained field's so that most
    /// points lie above it.
    #[test]
    fn a_density_losss_gradient_matches_finite_differences() {
        let dir = tempfile::tempdir().unwrap();
        let data = tiny_scene(dir.path(), 6);
        let model = tiny_model();
        let layout = NerfLayout::new(model).unwrap();
        let spec = SceneSpec {
            dataset: data,
            indices: reference_indices(&layout.grid),
        };
        let tc = TrainConfig {
            seed: 2,
            batch_samples: 1 << 11,
            occupancy_fraction: 0.05,
            workers: 2,
            ..Default::default()
        };
        let mut t = Trainer::new(model, vec![spec], tc).unwrap();
        for _ in 0..20 {
            t.train_step().unwrap();
        }
        for w in &mut t.workers {
            w.grad.fill(0.0);
        }
        // ln(0.0015 / (√3/1024)): the cap's 0.0015 per finest step as a raw log-density.
        let (cap, weight) = ((0.0015f32 / (3f32.sqrt() / 1024.0)).ln(), 1.0f32);
        let mut rng = Pcg32::new(9, 1);
        let points: Vec<[f32; 3]> = (0..512)
            .map(|_| [0.3, 0.3, 0.3].map(|c: f32| c + 0.4 * rng.next_f32()))
            .collect();
        let n = points.len();
        let hinge = |ld: f32| {
            let excess = ld - cap;
            let w = weight / n as f32;
            if excess > 0.0 {
                (2.0 * w * excess, w * excess * excess)
            } else {
                (0.0, 0.0)
            }
        };
        let active = density_loss(
            &t.net,
            &t.params,
            &t.scenes[0],
            &mut t.workers,
            &points,
            &|ld| hinge(ld).0,
        );
        let grad: Vec<f64> = t.gradient().iter().map(|&g| g as f64).collect();
        let scene = &t.scenes[0];
        let pos: Vec<[f32; 3]> = points.iter().map(|&p| scene.marcher.warp(p)).collect();
        assert!(
            active as usize > n / 4,
            "{active} of {n} points above the cap"
        );
        let loss = |params: &[f32]| -> f64 {
            t.net
                .density_batch(params, &scene.indices, &pos)
                .iter()
                .map(|&ld| hinge(ld).1 as f64)
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
}
