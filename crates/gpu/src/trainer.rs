//! A whole training step on the device (issue 10), composed from the tested kernels: the
//! occupancy updates on the CPU trainer's schedule with the field on the device, a batch of
//! rays drawn, marched and compacted ([`RayKernels`]), the grid forward, the network forward
//! keeping its activations, the loss, the network and grid backward, and Adam + EMA. One
//! or more scenes on one set of weights, as the CPU [`Trainer`], which is the oracle: same
//! initial weights, same seeds (`mix`, per scene), same ray draws, same rays-per-batch
//! adaptation per scene, same loss normalisation (scene weight / rays) and density
//! pull-up, same schedules ([`Schedule::Mixed`]: every scene every step, their gradients
//! summed into one Adam step; [`Schedule::RandomScene`]: one scene a step, drawn as the CPU
//! draws it), and the same [`TrainPolicy`] hooks at the same points of the step, with the
//! mechanisms behind [`PolicyOps`] in device kernels (`held.rs`).
//!
//! Each scene has its own index functions on the device ([`GpuIndex`]: the grid kernels
//! bind one per dispatch), its own occupancy grid ([`GpuOccupancy`]), its own frames
//! ([`RayKernels`]) and counters. The sample buffers, the network workspace and the
//! gradient are shared: the scenes of a step run one after another, each in its own
//! submissions, and both backward passes ADD into the gradient (the network's reduction
//! adds its chunk sums, the grid's atomics add), which only the optimizer's kernel zeroes,
//! after it has read it. So a mixed step's gradient is the sum of its scenes' gradients
//! when the one Adam step runs, as the CPU sums its workers' partials (in another order:
//! the sums agree to rounding, not bit for bit).
//!
//! Each scene's batch is trained on the samples that reach the loss, as instant-ngp trains
//! (`testbed_nerf.cu`): rays drawn and marched into a budget of 16× the target samples;
//! the grid and the density network over every marched sample, which is all a ray's stop
//! depends on; each ray's stop found and the samples before it compacted ([`Compacted`]);
//! then the grid and the whole network forward keeping activations over the compacted
//! samples alone, the loss on those outputs, and the backward. instant-ngp runs the whole
//! network over the marched samples and its loss kernel compacts; the colour network on
//! the samples past the stops (three of four on lego at 800 px) changed nothing there.
//! The gradient is the same: the samples past a ray's end had a zero gradient. Where the
//! compacted samples need more than one chunk of the workspace (the warm-up), a forward
//! without activations over all of them gives the loss its outputs first.
//!
//! Nothing is read back inside a step: every pass after the draw takes its sample count
//! from the device ([`DeviceCount`]: the marching and compaction counters turned into
//! uniforms and indirect dispatches), the density pull-up reads the grid mean there, and a
//! scene's measurements (counters, summed loss and used samples, grid mean) go to a ring
//! of mappable buffers ([`StepReadback`]) that the host reads at the step's end, or
//! [`GpuTrainer::set_read_lag`] steps later once the warm-up is over, when the device is
//! long done with them; one submission a step without a policy (and one per occupancy
//! update). `StepStats` counts the host waits and submissions.
//! With a [`TrainPolicy`] installed that reads them, every update of scene 0's grid (and
//! the installation itself) also reads back that grid and the EMA weights, calls the policy
//! on the host and uploads the indices and bounds it returns, before the other scenes'
//! grids update: the weights' whole vector crosses the bus once per update. A policy's
//! extra density loss reads its raw outputs back to take the loss's derivative on the host.
//! Otherwise samples and weights never leave the device.
//!
//! Rays whose samples do not fit the marching budget train nothing that step, as in
//! instant-ngp; they are counted (`StepStats::dropped_rays`), and the rays-per-batch
//! adaptation leaves them out of the count it scales, so that a budget that binds shrinks
//! the next batch (it used to grow it until every step filled its budget). The training
//! pass runs in chunks of the network workspace's capacity (2× the target), each counted
//! on the device: all of the marching budget's through the warm-up, then as many as the
//! measured batches call for (`chunks_for`), with rays past them dropped and counted.
//!
//! [`Trainer`]: ngp::train::Trainer
//! [`Schedule::Mixed`]: ngp::train::Schedule::Mixed
//! [`Schedule::RandomScene`]: ngp::train::Schedule::RandomScene

use super::compact::{CompactInputs, Compacted};
use super::count::{CountKernel, DeviceCount};
use super::field::{DensityScratch, GpuField};
use super::grid::{GridShape, HalfTable};
use super::held::{GpuHoldBack, GpuKeptMlp};
use super::loss::{LossBuffers, LossConfig, LossKernel};
use super::mlp::{ACT_ROWS, EncodedBatch, MlpWorkspace};
use super::occupancy::GpuOccupancy;
use super::optimizer::GpuOptimizer;
use super::profile::StepProfiler;
use super::rays::{RayBatch, RayKernels};
use super::readback::StepReadback;
use super::{GpuContext, GpuError, GpuIndex, GpuResult, device_buffer};
use ngp::data::Dataset;
use ngp::encoding::{LevelIndices, check_indices};
use ngp::model::Model;
use ngp::network::nerf::NerfNetwork;
use ngp::network::{ModelConfig, NerfLayout};
use ngp::occupancy::{MIN_OPTICAL_THICKNESS, N_CELLS, OccupancyGrid};
use ngp::render::march::Marcher;
use ngp::train::hooks::{PolicyOps, StepInfo, TableBounds, TrainPolicy};
use ngp::train::loss::DENSITY_PULL_UP;
use ngp::train::schedule::{
    MAX_RAYS_PER_BATCH, initial_rays_per_batch, mix, next_rays_per_batch, starting_grid,
};
use ngp::train::state;
use ngp::train::{GridUpdates, SceneSpec, StepStats, TrainConfig};
use std::cell::RefCell;
use std::sync::Arc;
use std::time::Instant;

/// Most rays per batch: the CPU trainer's (and the reference's) cap.
const MAX_RAYS: u32 = MAX_RAYS_PER_BATCH;
/// Marched samples the device holds per batch, as a multiple of the trained-sample target:
/// instant-ngp's 16. A budget that binds drops rays from the step (counted in
/// [`StepStats::dropped_rays`]); marched samples cost 4 B per encoding feature and 60 B
/// besides (the network's activations are kept for the trained samples only), so 2^18
/// trained samples march into 2^22 slots, 0.8 GiB. The device's largest storage binding
/// caps it (the encoding is the largest per-sample buffer).
const BUDGET_FACTOR: u32 = 16;
/// Trained samples (those that reach the loss) the network's workspace holds, as a multiple
/// of the target: each costs its kept activations, `ACT_ROWS` floats. Rays-per-batch
/// adaptation keeps a batch near the target; one with more (the first steps' fog, where
/// rays cross the whole box before they stop) trains in chunks of this many, so that no
/// ray is dropped for it.
const CAPACITY_FACTOR: u32 = 2;
/// The encoding's leading dimension is the sample count rounded up to this, so the kernels'
/// padding work stays small while a bind is valid for a range of counts.
const LD_GRANULE: u32 = 256;
/// The most steps a measurement may be read late ([`GpuTrainer::set_read_lag`]): 2 keeps
/// the device one whole step ahead of the host.
pub const MAX_LAG: u32 = 2;
/// Weight steps of the warm-up ([`GpuTrainer::set_warmup`]), through which each step's
/// measurements are read at its end and the training pass records every chunk: the
/// reference's occupancy warm-up (an update every step or two until step 256), when a
/// batch's demand per ray changes fastest. About 3 seconds of an H200's run.
const WARMUP: u32 = 256;

/// Chunks of `capacity` samples (at most `all`) for a batch expected to ask for
/// `expected` compacted slots, with half as much again to spare.
fn chunks_needed(expected: f32, capacity: u32, all: usize) -> usize {
    let want = (1.5 * expected as f64).ceil().max(1.0);
    ((want / capacity as f64).ceil() as usize).clamp(1, all)
}

/// One chunk of the training pass: the compacted samples `first ..< first + ld`, as many
/// of them as the compaction wrote (counted on the device; none past the count).
struct TrainChunk {
    first: u32,
    ld: u32,
    count: DeviceCount,
}

impl TrainChunk {
    /// The chunk's grid shape, first sample and length (samples).
    fn span(&self) -> (GridShape, u64, u64) {
        let shape = GridShape {
            n_samples: self.ld,
            ld: self.ld,
        };
        (shape, self.first as u64, self.ld as u64)
    }

    /// Chunks of `capacity` samples covering a compaction of `budget` samples, their counts
    /// read from `counters` (word 1: samples written).
    fn all(
        ctx: &GpuContext,
        kernel: &CountKernel,
        field: &GpuField,
        counters: &wgpu::Buffer,
        budget: u32,
        capacity: u32,
    ) -> GpuResult<Vec<TrainChunk>> {
        let mut chunks = Vec::new();
        let mut first = 0u32;
        while first < budget {
            let ld = capacity.min(budget - first);
            let grid = field.grid().count_slot(ctx, ld)?;
            let [tiles, wchunks, reduce] = field.mlp().count_slots(ctx, ld)?;
            let slots = [grid, tiles, wchunks, reduce];
            let count = DeviceCount::new(ctx, kernel, counters, 1, first, ld, &slots)?;
            chunks.push(TrainChunk { first, ld, count });
            first += ld;
        }
        Ok(chunks)
    }
}

/// Where a training pass's grid encodings come from.
enum GridInput<'a> {
    /// The grid forward at these positions (3 f32 a sample).
    Positions(wgpu::BufferSlice<'a>),
    /// A copy of the marched pass's encodings, still in the trainer's `enc`: each sample's
    /// marched index (u32), as the compaction wrote it.
    Copied(wgpu::BufferSlice<'a>),
}

/// One scene's state on the device (and the host copies the API hands out).
struct GpuScene {
    dataset: Arc<Dataset>,
    /// The index functions as trained now (host copy of `index`).
    indices: LevelIndices,
    index: GpuIndex,
    occupancy: GpuOccupancy,
    rays: RayKernels,
    loss_weight: f32,
    grid_mean: f32,
    rays_per_batch: u32,
    measured_samples: u32,
    measured_marched: u32,
    /// Compacted slots per ray drawn of the scene's last two measured batches, or `None`
    /// before any: how many chunks its training pass records.
    recent_asked: Option<[f32; 2]>,
}

/// One or more scenes trained on the device on one set of weights (scene 0: the one a model
/// publishes).
pub struct GpuTrainer<'c> {
    ctx: &'c GpuContext,
    pub config: TrainConfig,
    model: ModelConfig,
    marcher: Marcher,
    field: GpuField,
    scenes: Vec<GpuScene>,
    policy: Option<Box<dyn TrainPolicy>>,
    density_scratch: DensityScratch,
    batch: RayBatch,
    /// The samples of a batch that reach the loss, which the training pass runs on.
    compacted: Compacted,
    /// The kernel of the device's counts.
    counter: CountKernel,
    /// The batch's marched samples, counted on the device.
    marched: DeviceCount,
    /// All the compacted samples, counted on the device (the loss's forward when the
    /// training pass takes more than one chunk).
    compacted_all: DeviceCount,
    /// The training pass's chunks of the compacted samples, each counted on the device.
    chunks: Vec<TrainChunk>,
    /// Each step's measurements, read back late.
    readback: StepReadback,
    /// Steps a measurement is read after the step that made it (0: at the end of that
    /// step, as the CPU trainer adapts; see [`Self::set_read_lag`]).
    lag: u32,
    /// Measurements read and not yet reported in a step's stats.
    unreported: StepStats,
    /// Weight steps through which measurements are read in step and the training pass
    /// records all its chunks.
    warmup: u32,
    loss: LossKernel,
    optimizer: GpuOptimizer,
    /// The gate with hold-back and the table's bounds on the device, once a policy uses
    /// them.
    hold: Option<GpuHoldBack>,
    /// The kept MLP gradient, once a policy uses it.
    kept: Option<GpuKeptMlp>,
    /// The table's bounds, kept on the host (a policy sets them from what it reads back)
    /// and uploaded to the hold-back kernels.
    bounds: Option<TableBounds>,
    ws: MlpWorkspace,
    /// The step's sample buffers and the gradient.
    samples: SampleBuffers,
    /// Occupancy updates submitted (each with its read-back) in this step so far.
    occupancy_submissions: u32,
    /// Device timestamps between the step's phases, when asked for.
    profiler: RefCell<Option<StepProfiler>>,
    /// The grid table's fp16 copy the training forwards read, when asked for
    /// ([`Self::set_half_grid`]).
    half: Option<HalfTable>,
    /// Steps taken, updating the weights or not: the schedule's and the rays' clock.
    pub step: u32,
    /// Steps that updated the weights (the CPU trainer's `weight_steps`): the optimizer's
    /// and the occupancy grids' clock, and the step count a model file records.
    pub weight_steps: u32,
}

fn input<T>(msg: String) -> GpuResult<T> {
    Err(GpuError::Input(msg))
}

/// [`GpuTrainer::new`]'s checks of its scenes against the model, and of the batch.
fn check_inputs(
    scenes: &[SceneSpec],
    layout: &NerfLayout,
    model: ModelConfig,
    config: &TrainConfig,
) -> GpuResult<()> {
    let n_levels = layout.grid.levels.len();
    for s in scenes {
        if s.indices.len() != n_levels {
            return input(format!(
                "{} index functions for {n_levels} grid levels",
                s.indices.len()
            ));
        }
        check_indices(&s.indices, &layout.grid).map_err(|e| GpuError::Input(e.to_string()))?;
        if s.dataset.frames.is_empty() {
            return input(format!("{}: no training images", s.dataset.root.display()));
        }
        if s.dataset.aabb_scale != model.aabb_scale {
            return input(format!(
                "{}: aabb_scale {} differs from the model's {}",
                s.dataset.root.display(),
                s.dataset.aabb_scale,
                model.aabb_scale
            ));
        }
    }
    if config.batch_samples == 0 {
        return input("a batch of 0 samples".into());
    }
    if !(config.others_batch > 0.0 && config.others_batch <= 1.0) {
        return input(format!(
            "the other scenes' batch fraction must be in (0, 1], not {}",
            config.others_batch
        ));
    }
    Ok(())
}

/// The CPU engine's options a GPU trainer refuses.
fn check_cpu_only(config: &TrainConfig) -> GpuResult<()> {
    if config.occupancy_budget.is_some_and(|r| r > 0.0) {
        return input(
            "an occupancy budget is for the CPU engine: a GPU keeps the reference's schedule"
                .to_string(),
        );
    }
    if config.coarse_march.is_some_and(|s| s > 0) {
        return input(
            "a coarse march is for the CPU engine: a GPU marches the reference's step".to_string(),
        );
    }
    Ok(())
}

/// How many samples the trainer's buffers hold, for a batch's target on this device.
#[derive(Clone, Copy)]
struct SampleSizes {
    /// Floats of a sample's grid encoding.
    width: u64,
    /// Marched samples a batch may hold ([`BUDGET_FACTOR`]).
    budget: u32,
    /// Trained samples the network's workspace holds ([`CAPACITY_FACTOR`]): one chunk of
    /// the training pass.
    capacity: u32,
}

impl SampleSizes {
    /// The sizes for `config`'s batch within the device's largest binding, or an error
    /// where even the batch's target does not fit.
    fn for_device(
        ctx: &GpuContext,
        layout: &NerfLayout,
        config: &TrainConfig,
    ) -> GpuResult<SampleSizes> {
        let limits = ctx.device.limits();
        let max = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        let width = layout.grid.config.n_output_dims() as u64;
        let fitting = |bytes_per_sample: u64| {
            (max / bytes_per_sample).min(u32::MAX as u64) as u32 / LD_GRANULE * LD_GRANULE
        };
        let budget = config
            .batch_samples
            .saturating_mul(BUDGET_FACTOR)
            .min(fitting(4 * width));
        // A multiple of LD_GRANULE: the training pass binds its chunks at offsets of it,
        // which the device's storage alignment (256 bytes at most) divides.
        // In u64: a batch near u32::MAX rounded up to the granule would wrap to 0.
        let most = (fitting(4 * ACT_ROWS) as u64).min((budget / LD_GRANULE * LD_GRANULE) as u64);
        let capacity = (config.batch_samples as u64 * CAPACITY_FACTOR as u64)
            .next_multiple_of(LD_GRANULE as u64)
            .min(most) as u32;
        if capacity < config.batch_samples {
            return input(format!(
                "{} samples per batch: more than this device's {max}-byte bindings hold \
                 (at most {most} samples a batch)",
                config.batch_samples
            ));
        }
        Ok(SampleSizes {
            width,
            budget,
            capacity,
        })
    }
}

/// The trainer's sample buffers and its gradient.
struct SampleBuffers {
    raw: wgpu::Buffer,
    /// The marched samples' log-densities (the density network's pass).
    log_density: wgpu::Buffer,
    enc: wgpu::Buffer,
    /// A one-chunk step's trained encodings, copied from the marched ones in `enc` (a
    /// second buffer: the copy changes the leading dimension, so in place it would race).
    enc_copied: wgpu::Buffer,
    d_enc: wgpu::Buffer,
    grad: wgpu::Buffer,
    ray_out: wgpu::Buffer,
}

impl SampleBuffers {
    fn new(ctx: &GpuContext, sizes: &SampleSizes, n_params: usize) -> GpuResult<SampleBuffers> {
        let SampleSizes {
            width,
            budget,
            capacity,
        } = *sizes;
        let b = budget as u64;
        ctx.scoped("trainer buffers", || SampleBuffers {
            raw: device_buffer(ctx, "trainer raw", 16 * b),
            log_density: device_buffer(ctx, "trainer log-densities", 4 * b),
            enc: device_buffer(ctx, "trainer encoding", 4 * width * b),
            enc_copied: device_buffer(ctx, "trainer encoding, copied", 4 * width * capacity as u64),
            d_enc: device_buffer(
                ctx,
                "trainer encoding gradient",
                4 * width * capacity as u64,
            ),
            grad: device_buffer(ctx, "trainer gradient", 4 * n_params as u64),
            ray_out: device_buffer(ctx, "trainer ray losses", 8 * MAX_RAYS as u64),
        })
    }
}

impl GpuScene {
    /// `scenes` on the device, each with the occupancy grid the CPU trainer starts it
    /// from; scene 0's loss weighs 1, the others' `config.others_weight`.
    fn upload_all(
        ctx: &GpuContext,
        field: &GpuField,
        marcher: &Marcher,
        aabb_scale: u32,
        scenes: Vec<SceneSpec>,
        config: &TrainConfig,
    ) -> GpuResult<Vec<GpuScene>> {
        let mut states = Vec::with_capacity(scenes.len());
        for s in scenes {
            let grid = starting_grid(aabb_scale, &s.dataset);
            let loss_weight = if states.is_empty() {
                1.0
            } else {
                config.others_weight
            };
            states.push(GpuScene {
                index: field.grid().upload_index(ctx, &s.indices)?,
                occupancy: GpuOccupancy::upload(ctx, &grid, marcher)?,
                rays: RayKernels::new(ctx, &s.dataset.frames, marcher)?,
                grid_mean: grid.mean,
                dataset: s.dataset,
                indices: s.indices,
                loss_weight,
                rays_per_batch: initial_rays_per_batch(config.scene_batch(states.len())),
                measured_samples: 0,
                measured_marched: 0,
                recent_asked: None,
            });
        }
        Ok(states)
    }
}

impl<'c> GpuTrainer<'c> {
    /// A trainer of `scenes` (scene 0 the one a model publishes, the others weighted by
    /// `config.others_weight`) with `model`'s architecture, starting from the weights
    /// and occupancy grids the CPU [`Trainer`](ngp::train::Trainer) starts from for
    /// `config.seed`, with its checks. `config.schedule` applies; `workers` does not.
    pub fn new(
        ctx: &'c GpuContext,
        model: ModelConfig,
        scenes: Vec<SceneSpec>,
        config: TrainConfig,
    ) -> GpuResult<Self> {
        if scenes.is_empty() {
            return input("no scene to train".into());
        }
        let net = NerfNetwork::new(model).map_err(|e| GpuError::Input(e.to_string()))?;
        let layout = net.layout.clone();
        check_inputs(&scenes, &layout, model, &config)?;
        let sizes = SampleSizes::for_device(ctx, &layout, &config)?;
        let SampleSizes {
            budget, capacity, ..
        } = sizes;
        let params = net.init_params(config.seed);
        // The field's own index is scene 0's; the trainer binds each scene's.
        let field = GpuField::new(ctx, &layout, &params, &scenes[0].indices)?;
        let marcher = Marcher::new(model.aabb_scale);
        let states =
            GpuScene::upload_all(ctx, &field, &marcher, model.aabb_scale, scenes, &config)?;
        let batch = RayBatch::new(ctx, MAX_RAYS, budget)?;
        let loss = LossKernel::new(ctx)?;
        let optimizer = GpuOptimizer::new(
            ctx,
            config.optimizer,
            layout.n_params,
            layout.n_mlp_params(),
        )?;
        let ws = field.mlp().workspace(ctx, capacity)?;
        let compacted = Compacted::new(ctx, budget, MAX_RAYS)?;
        let counter = CountKernel::new(ctx)?;
        let chunks = TrainChunk::all(ctx, &counter, &field, &compacted.counters, budget, capacity)?;
        let grid_slot = field.grid().count_slot(ctx, budget)?;
        let [tiles, ..] = field.mlp().count_slots(ctx, budget)?;
        // Word 1 of the batch's counters: samples written (within the budget).
        let slots = [grid_slot, tiles];
        let marched = DeviceCount::new(ctx, &counter, &batch.counters, 1, 0, budget, &slots)?;
        // Word 1 of the compaction's counters: samples written.
        let compacted_all =
            DeviceCount::new(ctx, &counter, &compacted.counters, 1, 0, budget, &slots)?;
        let readback = StepReadback::new(ctx, states.len(), MAX_LAG as usize + 1)?;
        let samples = SampleBuffers::new(ctx, &sizes, layout.n_params)?;
        // Refused after the allocations, where it always was: on a device that fails to
        // allocate, the device's error still comes first.
        check_cpu_only(&config)?;
        Ok(GpuTrainer {
            ctx,
            config,
            model,
            marcher,
            field,
            scenes: states,
            policy: None,
            density_scratch: DensityScratch::default(),
            batch,
            compacted,
            counter,
            marched,
            compacted_all,
            chunks,
            readback,
            lag: 0,
            unreported: StepStats::default(),
            warmup: WARMUP,
            loss,
            optimizer,
            hold: None,
            kept: None,
            bounds: None,
            ws,
            samples,
            occupancy_submissions: 0,
            profiler: RefCell::new(None),
            half: None,
            step: 0,
            weight_steps: 0,
        })
    }

    /// Marched samples a batch may hold.
    pub fn sample_budget(&self) -> u32 {
        self.batch.sample_budget()
    }

    /// Times the device's phases on one step in `every` (0: off); false where the device
    /// cannot write timestamps inside encoders.
    pub fn profile_device(&mut self, every: u32) -> bool {
        let p = StepProfiler::new(self.ctx, every);
        let on = p.is_some();
        *self.profiler.get_mut() = p;
        on
    }

    /// With `on`, the training forwards (over the marched and the trained samples) read an
    /// fp16 copy of the grid table, made from the f32 table at the start of every step, as
    /// tiny-cuda-nn's forward reads fp16 parameters while Adam keeps the f32 master: half
    /// the bytes a corner. Occupancy updates and rendering keep reading the f32 table.
    /// Refused (an input error) for an odd number of features per level.
    pub fn set_half_grid(&mut self, on: bool) -> GpuResult<()> {
        self.half = if on {
            let table = self.field.params.slice(self.field.grid_bytes());
            Some(self.field.grid().half_table(self.ctx, table)?)
        } else {
            None
        };
        Ok(())
    }

    /// Whether the training forwards read the fp16 copy ([`Self::set_half_grid`]).
    pub fn half_grid(&self) -> bool {
        self.half.is_some()
    }

    /// Milliseconds per profiled step by phase (see [`StepProfiler::report`]).
    pub fn device_profile(&self) -> Vec<(String, f64)> {
        self.profiler
            .borrow()
            .as_ref()
            .map_or_else(Vec::new, |p| p.report())
    }

    /// Marks the end of phase `label` in `encoder` when this step is profiled.
    fn mark(&self, encoder: &mut wgpu::CommandEncoder, label: &'static str) {
        if let Some(p) = self.profiler.borrow_mut().as_mut() {
            p.mark(encoder, label);
        }
    }

    /// Marks the start of a submission when this step is profiled.
    fn mark_submission(&self, encoder: &mut wgpu::CommandEncoder) {
        if let Some(p) = self.profiler.borrow_mut().as_mut() {
            p.submission(encoder);
        }
    }

    /// Sets the workspace's capacity (a multiple of 256, at most the marching budget), so
    /// that tests can make a batch train in chunks.
    pub fn set_workspace_capacity(&mut self, capacity: u32) -> GpuResult<()> {
        let budget = self.batch.sample_budget();
        if capacity == 0 || !capacity.is_multiple_of(LD_GRANULE) || capacity > budget {
            return input(format!(
                "workspace capacity {capacity}: a multiple of {LD_GRANULE} up to {budget}"
            ));
        }
        let ctx = self.ctx;
        let width = self.field.layout().grid.config.n_output_dims() as u64;
        self.ws = self.field.mlp().workspace(ctx, capacity)?;
        let counters = &self.compacted.counters;
        self.chunks = TrainChunk::all(ctx, &self.counter, &self.field, counters, budget, capacity)?;
        let bytes = 4 * width * capacity as u64;
        self.samples.d_enc = ctx.scoped("trainer encoding gradient", || {
            device_buffer(ctx, "trainer encoding gradient", bytes)
        })?;
        self.samples.enc_copied = ctx.scoped("trainer encoding, copied", || {
            device_buffer(ctx, "trainer encoding, copied", bytes)
        })?;
        Ok(())
    }

    /// Reads each step's measurements (losses, counts; the rays-per-batch adaptation's
    /// input) `lag` steps after it (at most [`MAX_LAG`]) instead of at its end, so that the
    /// host records the next steps while the device runs this one and never waits for it:
    /// each scene's batch then adapts to the measurement of `lag` steps before rather than
    /// the last (instant-ngp's own counters arrive late too), and a step's stats report
    /// the measurements read during it. 0, the default, adapts as the CPU trainer does,
    /// with one wait at the end of each step; so do the warm-up's steps whatever the lag
    /// ([`Self::set_warmup`]: adapting two steps late while the demand per ray still falls
    /// fast cost 0.5 dB at 300 steps on one of three seeds on llvmpipe). Only without a
    /// training policy, whose hooks read the step's results.
    pub fn set_read_lag(&mut self, lag: u32) -> GpuResult<()> {
        if lag > MAX_LAG || (lag > 0 && self.policy.is_some()) {
            return input(format!(
                "a read lag of {lag} steps: at most {MAX_LAG}, and 0 with a training policy"
            ));
        }
        self.lag = lag;
        Ok(())
    }

    /// The measurements of the steps taken that no step's stats have reported yet (waiting
    /// for the device where they are not there): what a run adds to its totals when it
    /// ends.
    pub fn flush_stats(&mut self) -> GpuResult<StepStats> {
        let mut stats = std::mem::take(&mut self.unreported);
        while self.readback.in_flight() > 0 {
            self.read_measure(&mut stats, self.lag)?;
        }
        Ok(stats)
    }

    pub fn n_scenes(&self) -> usize {
        self.scenes.len()
    }

    /// The training images of scene `i`. Panics if `i` is not a scene, as
    /// indexing does (and as the CPU trainer's accessors).
    pub fn dataset(&self, i: usize) -> &Dataset {
        &self.scenes[i].dataset
    }

    /// Index functions of scene `i` as trained now.
    pub fn indices(&self, i: usize) -> &LevelIndices {
        &self.scenes[i].indices
    }

    /// Scene `i`'s (rays per batch, trained samples, marched samples) of the last step that
    /// trained it, as [`Trainer::batch_counters`](ngp::train::Trainer::batch_counters).
    pub fn batch_counters(&self, i: usize) -> (u32, u32, u32) {
        let s = &self.scenes[i];
        (s.rays_per_batch, s.measured_samples, s.measured_marched)
    }

    /// Scene `i`'s occupancy grid's cascade-0 mean after its last update.
    pub fn grid_mean(&self, i: usize) -> f32 {
        self.scenes[i].grid_mean
    }

    /// Scene `i`'s occupancy grid, read back (`i` past the scenes: an input error).
    pub fn grid(&self, i: usize) -> GpuResult<OccupancyGrid> {
        match self.scenes.get(i) {
            Some(s) => s.occupancy.download(self.ctx),
            None => input(format!("scene {i} of {}", self.scenes.len())),
        }
    }

    /// Installs a training policy, before the first step, and applies its index functions
    /// to scene 0's starting grid (read back, with the EMA weights, when it reads them), as
    /// [`Trainer::set_policy`](ngp::train::Trainer::set_policy).
    pub fn set_policy(&mut self, policy: Box<dyn TrainPolicy>) -> GpuResult<()> {
        if self.step > 0 {
            return input("a training policy is installed before the first step".into());
        }
        let reads = policy.reads();
        // Its hooks read each step's results: measurements are read in step.
        self.lag = 0;
        self.policy = Some(policy);
        if reads.published {
            let grid = self.scenes[0].occupancy.download(self.ctx)?;
            let published = self.optimizer.ema_params(self.ctx, &self.field.params)?;
            self.apply_indices(&grid, &published)?;
        }
        Ok(())
    }

    /// The policy's new indices for the scenes it names, checked all before any is used
    /// (an error changes nothing), then uploaded.
    fn apply_indices(&mut self, grid: &OccupancyGrid, published: &[f32]) -> GpuResult<()> {
        let Some(policy) = &mut self.policy else {
            return Ok(());
        };
        let fresh = policy.indices(grid, published);
        self.upload_indices(fresh)
    }

    /// New indices for the scenes named, checked all before any is used (an error changes
    /// nothing), then uploaded.
    fn upload_indices(&mut self, fresh: Vec<(usize, LevelIndices)>) -> GpuResult<()> {
        let ctx = self.ctx;
        let layout = self.field.layout();
        let n_levels = layout.grid.levels.len();
        let mut uploaded = Vec::with_capacity(fresh.len());
        for (i, indices) in fresh {
            if i == 0 || i >= self.scenes.len() || indices.len() != n_levels {
                return input(format!(
                    "index refresh for scene {i} with {} levels ({} scenes, {n_levels} \
                     levels; scene 0 is never refreshed)",
                    indices.len(),
                    self.scenes.len()
                ));
            }
            let index = self.field.grid().upload_index(ctx, &indices)?;
            uploaded.push((i, indices, index));
        }
        for (i, indices, index) in uploaded {
            self.scenes[i].indices = indices;
            self.scenes[i].index = index;
        }
        Ok(())
    }

    /// The table's bounds, once a policy has set them.
    pub fn table_bounds(&self) -> Option<&TableBounds> {
        self.bounds.as_ref()
    }

    /// The reference's occupancy schedule ([`GridUpdates::reference_due`]); every scene's
    /// grid updates on the current weights under its own indices, the policy's hooks right
    /// after scene 0's. Returns the densities evaluated, `None` when no update was due.
    fn update_occupancy(&mut self) -> GpuResult<Option<u64>> {
        let step = self.weight_steps;
        // The GPU keeps the reference's schedule: whole updates, where an update costs it
        // a millisecond.
        if !GridUpdates::reference_due(step) {
            return Ok(None);
        }
        // The GPU evaluates every drawn position, culled cells' too.
        let mut evaluated = 0u64;
        let ctx = self.ctx;
        for si in 0..self.scenes.len() {
            let scene = &mut self.scenes[si];
            let (nu, nn) = OccupancyGrid::sample_counts(
                scene.occupancy.n_cascades as usize,
                step,
                self.config.occupancy_fraction,
            );
            let (nu, nn) = match (u32::try_from(nu), u32::try_from(nn)) {
                (Ok(a), Ok(b)) => (a, b),
                _ => return input(format!("occupancy: {nu} + {nn} samples")),
            };
            evaluated += nu as u64 + nn as u64;
            let mut encoder = ctx.device.create_command_encoder(&Default::default());
            if let Some(p) = self.profiler.get_mut() {
                p.submission(&mut encoder);
            }
            // Scene si's update seed on the CPU.
            let seed = mix(self.config.seed, 0x6772_6964 + si as u64);
            scene.occupancy.encode_update_under(
                ctx,
                &mut encoder,
                &self.field,
                &scene.index,
                &mut self.density_scratch,
                nu,
                nn,
                seed,
            )?;
            if let Some(p) = self.profiler.get_mut() {
                p.mark(&mut encoder, "occupancy update");
            }
            ctx.scoped("occupancy update", || ctx.queue.submit([encoder.finish()]))?;
            // The mean switches the loss's density pull-up on the device; the host's copy
            // comes with the step's measurements.
            self.occupancy_submissions += 1;
            if si == 0 {
                self.primary_grid_updated()?;
            }
        }
        Ok(Some(evaluated))
    }

    /// The policy's hooks after an update of scene 0's grid; its indices take effect
    /// before the other scenes' grids update.
    fn primary_grid_updated(&mut self) -> GpuResult<()> {
        let Some(reads) = self.policy.as_ref().map(|p| p.reads()) else {
            return Ok(());
        };
        let ctx = self.ctx;
        let grid = if reads.grid || reads.published {
            Some(self.scenes[0].occupancy.download(ctx)?)
        } else {
            None
        };
        let published = if reads.published {
            Some(self.optimizer.ema_params(ctx, &self.field.params)?)
        } else {
            None
        };
        let visible = grid.as_ref().filter(|_| reads.grid);
        self.with_policy(|p, ops| p.grid_updated(visible, published.as_deref(), ops))?;
        if let (Some(g), Some(p)) = (&grid, &published) {
            self.apply_indices(g, p)?;
        }
        Ok(())
    }

    /// Runs a policy hook (if a policy is installed) on the device's mechanisms: the points
    /// its extra loss penalised, and the encoder holding what it recorded, if anything.
    fn run_policy(
        &mut self,
        hook: impl FnOnce(&mut dyn TrainPolicy, &mut dyn PolicyOps) -> ngp::Result<()>,
    ) -> GpuResult<(u32, Option<wgpu::CommandEncoder>)> {
        let Some(mut policy) = self.policy.take() else {
            return Ok((0, None));
        };
        let mut ops = GpuOps {
            t: self,
            encoder: None,
            penalised: 0,
        };
        let run = hook(policy.as_mut(), &mut ops).map_err(|e| GpuError::Input(e.to_string()));
        let GpuOps {
            encoder, penalised, ..
        } = ops;
        self.policy = Some(policy);
        run?;
        Ok((penalised, encoder))
    }

    /// [`Self::run_policy`], submitting what the hook recorded.
    fn with_policy(
        &mut self,
        hook: impl FnOnce(&mut dyn TrainPolicy, &mut dyn PolicyOps) -> ngp::Result<()>,
    ) -> GpuResult<u32> {
        let (penalised, encoder) = self.run_policy(hook)?;
        if let Some(e) = encoder {
            let ctx = self.ctx;
            ctx.scoped("policy", || ctx.queue.submit([e.finish()]))?;
        }
        Ok(penalised)
    }

    /// One training step: the occupancy updates due, the scenes of the step's schedule one
    /// after another (their gradients summed), one Adam + EMA step. Nothing is read back
    /// inside the step: every pass takes its sample count from the device. Without a
    /// policy, the last scene and the optimizer go in one submission, which also copies
    /// the step's measurements out; they are read at the step's end (lag 0), or
    /// [`Self::set_read_lag`] steps later, when the device is long done with them.
    pub fn train_step(&mut self) -> GpuResult<StepStats> {
        let t0 = Instant::now();
        let step = self.step;
        if let Some(p) = self.profiler.get_mut() {
            p.begin_step(step);
        }
        let mut stats = StepStats {
            step,
            ..std::mem::take(&mut self.unreported)
        };
        // The measurements of the steps `lag` behind this one: the batch sizes below
        // adapt to them. Blocking here is the host waiting for the device to finish a step
        // while it still has the next one queued.
        let lag = self.lag_now();
        while self.readback.oldest().is_some_and(|s| s + lag <= step) {
            self.read_measure(&mut stats, lag)?;
        }
        let t_wait = t0.elapsed().as_secs_f64();
        let info = StepInfo {
            seed: self.config.seed,
            step,
            weight_steps: self.weight_steps,
        };
        let ids = self.config.step_scenes(step, self.scenes.len());
        let update = self.policy.as_ref().is_none_or(|p| p.updates_weights(&ids));
        let occupancy = if update {
            self.update_occupancy()?
        } else {
            None
        };
        let t_occ = t0.elapsed().as_secs_f64();
        stats.occupancy_updates = occupancy.is_some() as u32;
        stats.occupancy_evaluations = occupancy.unwrap_or(0);
        let ctx = self.ctx;
        let mut trained = Vec::with_capacity(ids.len());
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        for (i, &si) in ids.iter().enumerate() {
            self.mark_submission(&mut encoder);
            if i == 0
                && let Some(h) = &self.half
            {
                // After the last step's optimizer and any write of the weights since; before
                // the step's forwards.
                h.encode_pack(&mut encoder);
                self.mark(&mut encoder, "grid table to fp16");
            }
            trained.push((si, self.encode_scene(si, &mut encoder)?));
            // Each scene's uniforms are written at its submission: the next scene's are
            // written after it. A policy's hooks follow their scene's submission.
            if i + 1 < ids.len() || self.policy.is_some() {
                let done = std::mem::replace(
                    &mut encoder,
                    ctx.device.create_command_encoder(&Default::default()),
                );
                ctx.scoped("training step", || ctx.queue.submit([done.finish()]))?;
                stats.submissions += 1;
                stats.penalised += self.with_policy(|p, ops| p.after_scene(si, info, ops))?;
            }
        }
        let t_rays = t0.elapsed().as_secs_f64();
        // The policy's work before the update and the optimizer's go in the step's last
        // submission. The CPU steps the optimizer even when nothing was trained (its MLP
        // weights still take L2 and momentum).
        let (penalised, hooked) = self.run_policy(|p, ops| p.before_update(info, ops))?;
        stats.penalised += penalised;
        if let Some(h) = hooked {
            // Recorded after the scenes' submissions: it goes first in the next one.
            let done = std::mem::replace(&mut encoder, h);
            ctx.scoped("training step", || ctx.queue.submit([done.finish()]))?;
            stats.submissions += 1;
        }
        if self.policy.is_some() {
            self.mark_submission(&mut encoder);
        }
        if update {
            self.optimizer.encode_step(
                ctx,
                &mut encoder,
                &self.field.params,
                &self.samples.grad,
            )?;
            if let (Some(_), Some(h)) = (&self.bounds, &self.hold) {
                h.encode_clamp(ctx, &mut encoder, &self.field.params)?;
            }
            self.weight_steps += 1;
        }
        self.mark(&mut encoder, "optimizer (Adam + EMA)");
        self.readback.encode_copy(&mut encoder)?;
        let submission = ctx.scoped("training step", || ctx.queue.submit([encoder.finish()]))?;
        self.readback.submitted(step, trained, submission);
        stats.submissions += 1 + self.occupancy_submissions;
        self.occupancy_submissions = 0;
        // A profiled step reads its timestamps back: one more wait.
        if let Some(p) = self.profiler.get_mut()
            && p.is_active()
        {
            p.end_step(ctx)?;
            stats.host_waits += 1;
        }
        self.step += 1;
        let t_opt = t0.elapsed().as_secs_f64();
        if lag == 0 {
            self.read_measure(&mut stats, 0)?;
        }
        stats.seconds = t0.elapsed().as_secs_f64();
        stats.wait_seconds = t_wait + (stats.seconds - t_opt);
        stats.occupancy_seconds = t_occ - t_wait;
        stats.rays_seconds = t_rays - t_occ;
        stats.optimizer_seconds = t_opt - t_rays;
        Ok(stats)
    }

    /// Reads the oldest step's measurements into `stats` and the scenes' batch state: the
    /// losses, the counts, the grid means, and each scene's rays per batch for its next
    /// draw. A read at the end of its own step (`lag` 0) that had to wait for the device
    /// counts as a host wait.
    fn read_measure(&mut self, stats: &mut StepStats, lag: u32) -> GpuResult<()> {
        let Some((m, waited)) = self.readback.read_oldest(self.ctx)? else {
            return Ok(());
        };
        // A late read that blocks leaves the device a whole step queued: the device does
        // not idle for it, so only the in-step read (lag 0) counts as a host wait.
        stats.host_waits += (waited && lag == 0) as u32;
        let budget = self.batch.sample_budget();
        for sm in &m.scenes {
            let [_asked, written, with_samples, dropped] = sm.batch;
            let [_, trained, unfit, passes] = sm.compact;
            let n = written.min(budget);
            let scene_loss = sm.loss_sum / sm.n_rays.max(1) as f32;
            stats.loss += scene_loss;
            if sm.scene == 0 {
                stats.primary_loss = Some(scene_loss);
            }
            stats.n_rays += with_samples as u64;
            stats.n_samples += trained as u64;
            stats.n_marched += n as u64;
            stats.n_network += trained as u64 * passes.max(1) as u64;
            stats.dropped_rays += dropped as u64 + unfit as u64;
            let scene = &mut self.scenes[sm.scene];
            let asked = sm.compact[0] as f32 / sm.n_rays.max(1) as f32;
            scene.recent_asked = Some(match scene.recent_asked {
                Some([_, last]) => [last, asked],
                None => [asked, asked],
            });
            scene.measured_samples = trained;
            scene.measured_marched = n;
            scene.grid_mean = sm.grid_mean;
            // The reference keeps its ray count when nothing was trained. Rays that did
            // not fit the marching budget are left out of the count the adaptation
            // scales, so that a budget that binds shrinks the batch instead of growing it
            // (their samples are not in `used`); with none dropped this is the CPU's
            // adaptation.
            if sm.used > 0 {
                scene.rays_per_batch = next_rays_per_batch(
                    sm.n_rays.saturating_sub(dropped),
                    self.config.scene_batch(sm.scene),
                    sm.used as u64,
                );
            }
        }
        Ok(())
    }

    /// Records scene `si`'s batch into `encoder`, trained on the samples that reach the
    /// loss: rays drawn and marched; the grid and the density network over every marched
    /// sample; each ray's stop found from those densities and the samples before it
    /// compacted; the grid and network forward keeping activations over them, the loss on
    /// its outputs, and the backward, adding into the gradient (chunk by chunk of the
    /// workspace, after a forward over all of them for the loss, when one chunk does not
    /// hold them); the scene's measurements. Every count after the draw is the device's.
    /// Returns the rays drawn.
    fn encode_scene(&mut self, si: usize, encoder: &mut wgpu::CommandEncoder) -> GpuResult<u32> {
        let ctx = self.ctx;
        let step = self.step;
        let scene = &self.scenes[si];
        let n_rays = scene.rays_per_batch;
        // Scene si's batch seed on the CPU.
        let seed = mix(mix(self.config.seed, step as u64), si as u64 + 1);
        scene.rays.encode(
            ctx,
            encoder,
            &self.batch,
            &scene.occupancy.bitfield,
            n_rays,
            seed,
        )?;
        self.mark(encoder, "rays: draw and march");
        self.marched.encode(encoder);
        let loss_norm = scene.loss_weight / n_rays as f32;
        let n_chunks = self.chunks_for(si);
        let slots = self.chunks[..n_chunks].iter().map(|c| c.ld).sum();
        self.encode_density_and_compaction(encoder, si, n_rays, slots)?;
        self.compacted
            .record_forward_passes(encoder, 1 + (n_chunks > 1) as u32);
        if n_chunks == 1 {
            // The marched encodings are still in `enc`: the chunk copies its samples'.
            self.encode_chunk_forward(encoder, si, 0, true)?;
            self.encode_loss(encoder, si, n_rays, loss_norm)?;
            self.encode_chunk_backward(encoder, si, 0, true)?;
        } else {
            // The loss's forward over all compacted samples wrote over them first.
            self.encode_loss_forward(encoder, si)?;
            self.encode_loss(encoder, si, n_rays, loss_norm)?;
            for k in 0..n_chunks {
                self.encode_chunk_forward(encoder, si, k, false)?;
                self.encode_chunk_backward(encoder, si, k, false)?;
            }
        }
        let scene = &self.scenes[si];
        self.readback.encode_scene(
            ctx,
            encoder,
            si,
            &self.batch.counters,
            &self.compacted.counters,
            &self.samples.ray_out,
            n_rays,
            scene.occupancy.mean_buffer(),
        )?;
        self.mark(encoder, "measurements");
        Ok(n_rays)
    }

    /// Chunks of the training pass to record for scene `si`: all of them (the whole marching
    /// budget) through the warm-up ([`Self::set_warmup`]: the occupancy grid's first 256
    /// updates by default, while it changes every step or two) and until the
    /// scene's batches are measured; then enough for 1.5 times what the batch is expected
    /// to ask for, its rays times the larger per-ray demand of its last two measured
    /// batches (one chunk of twice the target in steady state, where the rays-per-batch
    /// adaptation keeps the demand near the target). Only the device knows a batch's
    /// count, and a chunk recorded empty still costs its dispatches and barriers (1.2 ms a
    /// step for seven on an H200); a batch that asks for more than the recorded chunks hold
    /// loses the rays past them, counted as dropped, and its measurement records more
    /// chunks for the next.
    fn chunks_for(&self, si: usize) -> usize {
        let all = self.chunks.len();
        let scene = &self.scenes[si];
        match scene.recent_asked {
            Some(asked) if self.weight_steps >= self.warmup => chunks_needed(
                asked[0].max(asked[1]) * scene.rays_per_batch as f32,
                self.chunks[0].ld,
                all,
            ),
            _ => all,
        }
    }

    /// The warm-up: until the weights have taken `steps` steps (default 256) each step's
    /// measurements are read at its end ([`Self::set_read_lag`] applies after) and the
    /// training pass records every chunk (their number adapts to the measured batches
    /// after, see `chunks_for`).
    pub fn set_warmup(&mut self, steps: u32) {
        self.warmup = steps;
    }

    /// The lag this step reads with: 0 through the warm-up.
    fn lag_now(&self) -> u32 {
        if self.weight_steps < self.warmup {
            0
        } else {
            self.lag
        }
    }

    /// Chunk `k` of the training pass over the compacted samples: the grid forward and the
    /// network forward keeping activations, on as many of the chunk's samples as the
    /// compaction wrote (none: nothing is dispatched); the outputs go to `raw` from its
    /// start (the first chunk's are the loss's when it is the only one).
    fn encode_chunk_forward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        si: usize,
        k: usize,
        copied: bool,
    ) -> GpuResult<()> {
        let chunk = &self.chunks[k];
        chunk.count.encode(encoder);
        let (shape, first, ld) = chunk.span();
        let c = &self.compacted;
        let pos = c.pos.slice(12 * first..12 * (first + ld));
        let dirs = c.dirs.slice(12 * first..12 * (first + ld));
        let grid = match copied {
            true => GridInput::Copied(c.from.slice(4 * first..4 * (first + ld))),
            false => GridInput::Positions(pos),
        };
        self.encode_network_forward(encoder, si, shape, grid, dirs, true, Some(&chunk.count))
    }

    /// The backward of chunk `k` after [`Self::encode_chunk_forward`] and the loss: network
    /// and grid backward from the loss's gradient of the chunk's samples.
    fn encode_chunk_backward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        si: usize,
        k: usize,
        copied: bool,
    ) -> GpuResult<()> {
        let chunk = &self.chunks[k];
        let (shape, first, ld) = chunk.span();
        let c = &self.compacted;
        let pos = c.pos.slice(12 * first..12 * (first + ld));
        let d_raw = c.d_raw.slice(16 * first..16 * (first + ld));
        let count = Some(&chunk.count);
        self.encode_network_backward(encoder, si, shape, pos, d_raw, count, copied)
    }

    /// The outputs of every compacted sample into `raw`, without activations, for the loss
    /// when the training pass takes more than one chunk.
    fn encode_loss_forward(&self, encoder: &mut wgpu::CommandEncoder, si: usize) -> GpuResult<()> {
        let budget = self.batch.sample_budget();
        let shape = GridShape {
            n_samples: budget,
            ld: budget,
        };
        self.compacted_all.encode(encoder);
        let c = &self.compacted;
        let (pos, dirs) = (GridInput::Positions(c.pos.slice(..)), c.dirs.slice(..));
        let count = Some(&self.compacted_all);
        self.encode_network_forward(encoder, si, shape, pos, dirs, false, count)
    }

    /// The loss of scene `si`'s `n_rays` rays on the compacted samples' outputs in `raw`,
    /// and its gradient to them; the density pull-up while the grid's mean (on the device)
    /// is below the reference's threshold.
    fn encode_loss(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        si: usize,
        n_rays: u32,
        loss_norm: f32,
    ) -> GpuResult<()> {
        let c = &self.compacted;
        let bufs = LossBuffers {
            rays: &c.rays,
            raw: &self.samples.raw,
            dt: &c.dt,
            dist: &c.dist,
            pos: &c.pos,
            d_raw: &c.d_raw,
            ray_out: &self.samples.ray_out,
            grid_mean: Some(self.scenes[si].occupancy.mean_buffer()),
        };
        let mut cfg = LossConfig::new(&self.marcher, loss_norm, DENSITY_PULL_UP);
        cfg.pull_up_below_mean = Some(MIN_OPTICAL_THICKNESS);
        let budget = self.batch.sample_budget();
        self.loss
            .encode(self.ctx, encoder, &bufs, n_rays, budget, &cfg)?;
        self.mark(encoder, "loss");
        Ok(())
    }

    /// The grid shape of `n` samples in buffers of `cap` samples: the leading dimension is
    /// `n` rounded up to [`LD_GRANULE`], within the buffers.
    fn shape(&self, n: u32, cap: u32) -> GridShape {
        let ld = n.div_ceil(LD_GRANULE).saturating_mul(LD_GRANULE).min(cap);
        GridShape { n_samples: n, ld }
    }

    /// Records the grid forward and the density network over the batch's marched samples
    /// of scene `si` (as many as the device counted), and the compaction of the samples
    /// that reach the loss into its first `slots`, each given its ray's direction there
    /// (the colour network sees only those).
    fn encode_density_and_compaction(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        si: usize,
        n_rays: u32,
        slots: u32,
    ) -> GpuResult<()> {
        let ctx = self.ctx;
        let budget = self.batch.sample_budget();
        let shape = GridShape {
            n_samples: budget,
            ld: budget,
        };

        let pos = self.batch.pos.slice(..);
        self.encode_grid_forward(encoder, si, shape, pos, Some(&self.marched))?;
        self.mark(encoder, "grid forward (marched)");
        let eb = self.encoded_batch(shape, false);
        self.field.mlp().encode_density_counted(
            ctx,
            encoder,
            &eb,
            &self.samples.log_density,
            Some(&self.marched),
        )?;
        self.mark(encoder, "density network (marched)");

        let inputs = CompactInputs {
            rays: &self.batch.rays,
            log_density: &self.samples.log_density,
            dt: &self.batch.dt,
            dist: &self.batch.dist,
            pos: &self.batch.pos,
            drawn: &self.batch.drawn,
            ray_out: &self.samples.ray_out,
        };
        self.compacted
            .encode_within(ctx, encoder, &inputs, n_rays, slots)?;
        self.mark(encoder, "compaction");
        Ok(())
    }

    /// Byte ranges of a batch of `shape`: the grid block of the parameters (and of the
    /// gradient), the positions, the encoding.
    fn batch_bytes(&self, shape: GridShape) -> (std::ops::Range<u64>, u64, u64) {
        let layout = self.field.layout();
        let width = layout.grid.config.n_output_dims() as u64;
        (
            self.field.grid_bytes(),
            12 * shape.ld as u64,
            4 * width * shape.ld as u64,
        )
    }

    /// The trainer's encoding buffer (with `copied`, the copied encodings') as a batch of
    /// `shape`.
    fn encoded_batch(&self, shape: GridShape, copied: bool) -> EncodedBatch<'_> {
        EncodedBatch {
            params: &self.field.params,
            enc: if copied {
                &self.samples.enc_copied
            } else {
                &self.samples.enc
            },
            ld: shape.ld,
            n: shape.n_samples,
        }
    }

    /// The encodings of the first `shape.n_samples` samples (or as many as `count` says, at
    /// most that): the grid forward under scene `si`'s index at `grid`'s positions, or a
    /// copy of the marched pass's; then the network forward with `dirs`, into `raw`. With
    /// `keep`, the activations stay in the workspace for [`Self::encode_network_backward`]
    /// (`shape` within its capacity).
    #[allow(clippy::too_many_arguments)]
    fn encode_network_forward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        si: usize,
        shape: GridShape,
        grid: GridInput<'_>,
        dirs: wgpu::BufferSlice<'_>,
        keep: bool,
        count: Option<&DeviceCount>,
    ) -> GpuResult<()> {
        let ctx = self.ctx;
        let copied = matches!(grid, GridInput::Copied(_));
        match grid {
            GridInput::Positions(pos) => {
                self.encode_grid_forward(encoder, si, shape, pos, count)?;
                self.mark(
                    encoder,
                    if keep {
                        "grid forward (trained)"
                    } else {
                        "grid forward (for the loss)"
                    },
                );
            }
            GridInput::Copied(from) => {
                let budget = self.batch.sample_budget();
                let width = self.field.layout().grid.config.n_output_dims() as u64;
                let copy = self.field.grid().bind_copy(
                    ctx,
                    from,
                    self.samples.enc.slice(..4 * width * budget as u64),
                    budget,
                    self.samples.enc_copied.slice(..4 * width * shape.ld as u64),
                    shape,
                )?;
                copy.record_maybe_counted(encoder, count)?;
                self.mark(encoder, "encodings copied (trained)");
            }
        }
        let eb = self.encoded_batch(shape, copied);
        let ws = keep.then_some(&self.ws);
        let mlp = self.field.mlp();
        mlp.encode_forward_slice(ctx, encoder, &eb, dirs, &self.samples.raw, ws, count)?;
        self.mark(
            encoder,
            if keep {
                "network forward (trained)"
            } else {
                "network forward (for the loss)"
            },
        );
        Ok(())
    }

    /// The grid forward under scene `si`'s index over the first `shape.n_samples` of `pos`
    /// (or as many as `count` says) into the encoding buffer, from the grid's fp16 copy
    /// when there is one.
    fn encode_grid_forward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        si: usize,
        shape: GridShape,
        pos: wgpu::BufferSlice<'_>,
        count: Option<&DeviceCount>,
    ) -> GpuResult<()> {
        let ctx = self.ctx;
        let (grid_bytes, pos_bytes, enc_bytes) = self.batch_bytes(shape);
        let grid = self.field.grid();
        let index = &self.scenes[si].index;
        let (pos, enc) = (pos.slice(..pos_bytes), self.samples.enc.slice(..enc_bytes));
        let forward = match &self.half {
            Some(h) => grid.bind_forward_half(ctx, index, pos, h, enc, shape)?,
            None => {
                let table = self.field.params.slice(grid_bytes);
                grid.bind_forward(ctx, index, pos, table, enc, shape)?
            }
        };
        forward.record_maybe_counted(encoder, count)?;
        Ok(())
    }

    /// Backward of the last [`Self::encode_network_forward`] that kept its activations
    /// (with the same `count`), from `d_raw`: MLP weight gradients added into `grad`,
    /// dL/d(enc) into `d_enc`, then the grid's gradient at `pos` added into the grid block
    /// of `grad`. With `copied`, the network reads the copied encodings, as the forward did.
    #[allow(clippy::too_many_arguments)]
    fn encode_network_backward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        si: usize,
        shape: GridShape,
        pos: wgpu::BufferSlice<'_>,
        d_raw: wgpu::BufferSlice<'_>,
        count: Option<&DeviceCount>,
        copied: bool,
    ) -> GpuResult<()> {
        let ctx = self.ctx;
        let (grid_bytes, pos_bytes, enc_bytes) = self.batch_bytes(shape);
        let eb = self.encoded_batch(shape, copied);
        let mlp = self.field.mlp();
        let (ws, grad, d_enc) = (&self.ws, &self.samples.grad, &self.samples.d_enc);
        mlp.encode_backward_slice(ctx, encoder, &eb, d_raw, ws, grad, d_enc, count)?;
        self.mark(encoder, "network backward (trained)");
        let backward = self.field.grid().bind_backward(
            ctx,
            &self.scenes[si].index,
            pos.slice(..pos_bytes),
            self.samples.d_enc.slice(..enc_bytes),
            self.samples.grad.slice(grid_bytes),
            shape,
        )?;
        backward.record_maybe_counted(encoder, count)?;
        self.mark(encoder, "grid backward (trained)");
        Ok(())
    }

    /// [`PolicyOps::density_loss`] on the device: the points, drawn on the host, go through
    /// the network in the compacted samples' buffers (the scene's rays are done with them)
    /// in chunks of their capacity; the loss's derivative is taken on the host from the raw
    /// outputs read back, and the backward pass adds into the gradient. Returns the points
    /// where the derivative is not zero.
    fn density_loss(
        &mut self,
        si: usize,
        points: &[[f32; 3]],
        d_loss: &(dyn Fn(f32) -> f32 + Sync),
    ) -> GpuResult<u32> {
        if si >= self.scenes.len() {
            return input(format!(
                "a density loss on scene {si} of {}",
                self.scenes.len()
            ));
        }
        let ctx = self.ctx;
        let pos: Vec<[f32; 3]> = points.iter().map(|&p| self.marcher.warp(p)).collect();
        let mut active = 0;
        let cap = self.ws.capacity();
        for chunk in pos.chunks(cap as usize) {
            let m = chunk.len() as u32;
            let shape = self.shape(m, cap);
            // The colour's gradient is zero: any direction does.
            let dirs = vec![[0.0f32, 0.0, 1.0]; chunk.len()];
            let c = &self.compacted;
            ctx.scoped("density loss points", || {
                ctx.queue
                    .write_buffer(&c.pos, 0, bytemuck::cast_slice(chunk));
                ctx.queue
                    .write_buffer(&c.dirs, 0, bytemuck::cast_slice(&dirs));
            })?;
            let mut encoder = ctx.device.create_command_encoder(&Default::default());
            let (pos, dirs) = (GridInput::Positions(c.pos.slice(..)), c.dirs.slice(..));
            self.encode_network_forward(&mut encoder, si, shape, pos, dirs, true, None)?;
            ctx.scoped("density loss forward", || {
                ctx.queue.submit([encoder.finish()])
            })?;
            let raw: Vec<[f32; 4]> = ctx.read_buffer(&self.samples.raw, 16 * m as u64)?;
            let d_raw: Vec<[f32; 4]> = raw
                .iter()
                .map(|r| {
                    let g = d_loss(r[3]);
                    active += (g != 0.0) as u32;
                    [0.0, 0.0, 0.0, g]
                })
                .collect();
            ctx.scoped("density loss gradient", || {
                ctx.queue
                    .write_buffer(&c.d_raw, 0, bytemuck::cast_slice(&d_raw));
            })?;
            let mut encoder = ctx.device.create_command_encoder(&Default::default());
            let (pos, d_raw) = (c.pos.slice(..), c.d_raw.slice(..));
            self.encode_network_backward(&mut encoder, si, shape, pos, d_raw, None, false)?;
            ctx.scoped("density loss backward", || {
                ctx.queue.submit([encoder.finish()])
            })?;
        }
        Ok(active)
    }

    /// Weights to render with and to publish: the debiased EMA, read back.
    pub fn inference_params(&self) -> GpuResult<Vec<f32>> {
        self.optimizer.ema_params(self.ctx, &self.field.params)
    }

    /// The training weights (not the EMA), read back.
    pub fn params(&self) -> GpuResult<Vec<f32>> {
        self.ctx
            .read_buffer(&self.field.params, 4 * self.field.layout().n_params as u64)
    }

    /// The gradient buffer, read back (for tests: between steps it holds what a step that
    /// did not update the weights left for the next one, zero otherwise).
    pub fn gradient(&self) -> GpuResult<Vec<f32>> {
        self.ctx
            .read_buffer(&self.samples.grad, 4 * self.field.layout().n_params as u64)
    }

    /// The model as published (what [`Model::from_trainer`] makes of a CPU trainer): the
    /// EMA weights with scene 0's grid, dataset and counters.
    pub fn model(&self, loss: f32) -> GpuResult<Model> {
        Model::from_parts(
            self.model,
            self.inference_params()?,
            self.grid(0)?,
            self.weight_steps,
            loss,
            &self.scenes[0].dataset,
            self.batch_counters(0),
        )
        .map_err(|e| GpuError::Input(e.to_string()))
    }

    /// The parts of a training a saved state must share with the trainer it goes back into,
    /// by name, as the CPU trainer's, with the device named (a CPU state does not go on
    /// here, nor this one on the CPU) and no worker count (the GPU has none). Never the
    /// index functions: a state's errors may be printed, and a key must not be.
    fn fingerprint(&self) -> Vec<(String, String)> {
        let mut options = self.config.clone();
        options.workers = 0;
        state::fingerprint(
            Some("gpu"),
            &self.field.layout().config,
            &options,
            self.policy.is_some(),
            self.scenes.iter().map(|s| s.dataset.as_ref()),
        )
    }

    /// The whole training state between two steps ([`ngp::train::state`]), read back from
    /// the device: the weights; Adam's moments, per-parameter update counts and step; the
    /// EMA (raw, as the kernel keeps it); every scene's occupancy grid (density, bitfield,
    /// mean, update count) and rays-per-batch counters; the step counts. Nothing else
    /// lasts from one step to the next: the seeds are functions of (seed, step, scene) and
    /// of the grid's update count, the occupancy schedule of `weight_steps`, and the
    /// gradient is zero after every update. With a training policy: its own state, the
    /// mechanisms' (held-back gradients, table bounds) and the gradient a step that did not
    /// update the weights left in the buffer, as the CPU saves them. Restored into a
    /// trainer built the same way (its policy too), training goes on with the same steps,
    /// schedule and draws, though not bit for bit (the device's float sums depend on the
    /// order threads add in).
    pub fn save_state(&self) -> ngp::Result<Vec<u8>> {
        Ok(state::encode(&self.save_state_doc()?))
    }

    /// [`save_state`](Self::save_state) as a document, for a caller that nests it.
    pub fn save_state_doc(&self) -> ngp::Result<state::Value> {
        use state::Sparse;
        use std::borrow::Cow::{Borrowed, Owned};
        let ctx = self.ctx;
        let (m, v, steps) = self.optimizer.moments(ctx)?;
        let mut scenes = Vec::with_capacity(self.scenes.len());
        for s in &self.scenes {
            scenes.push(state::Scene {
                grid: Owned(s.occupancy.download(ctx)?),
                rays_per_batch: s.rays_per_batch,
                measured_samples: s.measured_samples,
                measured_marched: s.measured_marched,
                // The GPU marches the reference's step (no coarse march).
                march_stride: 1,
            });
        }
        // Only a policy leaves anything between steps in these (read back only then).
        let (mechanisms, gradient, policy) = match &self.policy {
            None => (None, None, None),
            Some(p) => {
                // Per parameter, as the CPU's (the device holds the table's alone).
                let held = match &self.hold {
                    Some(h) => {
                        let mut all = vec![0.0f32; self.field.layout().n_mlp_params()];
                        all.extend(h.pending(ctx)?);
                        Some(Sparse::of(&all))
                    }
                    None => None,
                };
                let bounds = self.bounds.as_ref().map(Borrowed);
                (
                    Some(state::Mechanisms { held, bounds }),
                    Some(Sparse::of(&self.gradient()?)),
                    p.save_state()?.map(Owned),
                )
            }
        };
        let doc = state::TrainerState {
            fingerprint: self.fingerprint(),
            step: self.step,
            weight_steps: self.weight_steps,
            params: Owned(self.params()?),
            // As the CPU's (tiny-cuda-nn's), with the device's raw EMA for our resume.
            optimizer: state::OptimizerState {
                config: self.optimizer.config,
                step: self.optimizer.step,
                m: Owned(m),
                v: Owned(v),
                param_steps: Owned(steps),
                published: Owned(self.inference_params()?),
                ema: Owned(self.optimizer.raw_ema(ctx)?),
                ema_step: None,
            },
            occupancy_clock: None,
            scenes,
            mechanisms,
            waiting: state::Waiting::Gradient(gradient),
            policy,
            cameras: None,
        };
        Ok(doc.to_value())
    }

    /// Takes back a [`save_state`](Self::save_state) into this trainer, which must be fresh
    /// (no step taken) and built from the same scenes, layout and options; `origin` names
    /// the state in errors. Every field is read and checked before anything is uploaded.
    /// After an error, drop the trainer.
    pub fn restore_state(&mut self, bytes: &[u8], origin: &std::path::Path) -> ngp::Result<()> {
        self.restore_state_doc(&state::open(origin, bytes)?, origin)
    }

    /// [`restore_state`](Self::restore_state) from the document.
    pub fn restore_state_doc(
        &mut self,
        doc: &state::Value,
        origin: &std::path::Path,
    ) -> ngp::Result<()> {
        if self.step != 0 {
            return Err(ngp::Error::Config(
                "a training state goes into a trainer that has not stepped".into(),
            ));
        }
        let layout = self.field.layout();
        let (n, n_matrix) = (layout.n_params, layout.n_mlp_params());
        let expect = state::Expect {
            fingerprint: &self.fingerprint(),
            // Checked there: the device's ray buffers hold MAX_RAYS rays.
            device: state::Device::Gpu { max_rays: MAX_RAYS },
            optimizer: self.optimizer.config,
            n_params: n,
            n_matrix,
            n_entries: layout.grid.n_entries as usize,
            n_features: layout.config.grid.n_features as usize,
            scene_cells: (self.scenes.iter())
                .map(|s| N_CELLS * s.occupancy.n_cascades as usize)
                .collect(),
            policy: self.policy.is_some(),
            refined_images: None,
        };
        let saved = state::TrainerState::read(origin, doc, &expect)?;
        let ctx = self.ctx;
        ctx.scoped("restore parameters", || {
            ctx.queue
                .write_buffer(&self.field.params, 0, bytemuck::cast_slice(&saved.params))
        })?;
        let o = &saved.optimizer;
        self.optimizer
            .restore(ctx, o.step, &o.m, &o.v, &o.param_steps, &o.ema)?;
        for (s, saved) in self.scenes.iter_mut().zip(&saved.scenes) {
            s.occupancy.restore(ctx, &saved.grid)?;
            // The host copies the step reads: the mean switches the density pull-up.
            s.grid_mean = saved.grid.mean;
            s.rays_per_batch = saved.rays_per_batch;
            s.measured_samples = saved.measured_samples;
            s.measured_marched = saved.measured_marched;
        }
        // A policy's mechanisms and waiting gradient (the fingerprint has checked that a
        // policy is installed here iff one saved; read only then).
        let (held, bounds) = match saved.mechanisms {
            // The device holds the table's part alone.
            Some(m) => (
                m.held.map(|h| h.dense(n).split_off(n_matrix)),
                m.bounds.map(std::borrow::Cow::into_owned),
            ),
            None => (None, None),
        };
        if held.is_some() || bounds.is_some() {
            let h = self.hold_back()?;
            if let Some(pending) = &held {
                h.restore_pending(ctx, pending)?;
            }
            if let Some(b) = &bounds {
                h.upload_bounds(ctx, b)?;
            }
        }
        self.bounds = bounds;
        if let state::Waiting::Gradient(Some(g)) = &saved.waiting {
            let g = g.dense(n);
            ctx.scoped("restore gradient", || {
                ctx.queue
                    .write_buffer(&self.samples.grad, 0, bytemuck::cast_slice(&g))
            })?;
        }
        if let Some(p) = &mut self.policy {
            let fresh = p.restore_state(saved.policy.as_deref(), origin)?;
            self.upload_indices(fresh)?;
        }
        ctx.wait()?;
        self.step = saved.step;
        self.weight_steps = saved.weight_steps;
        Ok(())
    }

    /// The hold-back kernels, made on first use.
    fn hold_back(&mut self) -> GpuResult<&GpuHoldBack> {
        if self.hold.is_none() {
            let layout = self.field.layout();
            self.hold = Some(GpuHoldBack::new(
                self.ctx,
                layout.n_params,
                layout.n_mlp_params(),
                layout.config.grid.n_features as usize,
            )?);
        }
        Ok(self.hold.as_ref().expect("made above"))
    }
}

/// The device's side of [`PolicyOps`]: kernels recorded into one encoder that the trainer
/// submits when the hook returns (a density loss submits what was recorded before it, then
/// its own work).
struct GpuOps<'t, 'c> {
    t: &'t mut GpuTrainer<'c>,
    encoder: Option<wgpu::CommandEncoder>,
    penalised: u32,
}

impl GpuOps<'_, '_> {
    /// The hold-back kernels, made on first use.
    fn hold(&mut self) -> GpuResult<()> {
        self.t.hold_back().map(|_| ())
    }

    fn kept(&mut self) -> GpuResult<()> {
        if self.t.kept.is_none() {
            let n_matrix = self.t.field.layout().n_mlp_params();
            self.t.kept = Some(GpuKeptMlp::new(self.t.ctx, n_matrix)?);
        }
        Ok(())
    }

    /// Submits what was recorded so far.
    fn flush(&mut self) -> GpuResult<()> {
        if let Some(e) = self.encoder.take() {
            let ctx = self.t.ctx;
            ctx.scoped("policy", || ctx.queue.submit([e.finish()]))?;
        }
        Ok(())
    }

    /// Records `f` on the hold-back kernels (made on first use) and the gradient.
    fn record_held(
        &mut self,
        f: impl FnOnce(
            &GpuHoldBack,
            &GpuContext,
            &mut wgpu::CommandEncoder,
            &wgpu::Buffer,
        ) -> GpuResult<()>,
    ) -> ngp::Result<()> {
        self.hold()?;
        let t = &*self.t;
        let encoder = self
            .encoder
            .get_or_insert_with(|| t.ctx.device.create_command_encoder(&Default::default()));
        let h = t.hold.as_ref().expect("made above");
        Ok(f(h, t.ctx, encoder, &t.samples.grad)?)
    }

    /// Records `f` on the kept MLP gradient (made on first use) and the gradient.
    fn record_kept(
        &mut self,
        f: impl FnOnce(&mut GpuKeptMlp, &mut wgpu::CommandEncoder, &wgpu::Buffer) -> GpuResult<()>,
    ) -> ngp::Result<()> {
        self.kept()?;
        let t = &mut *self.t;
        let encoder = self
            .encoder
            .get_or_insert_with(|| t.ctx.device.create_command_encoder(&Default::default()));
        let k = t.kept.as_mut().expect("made above");
        Ok(f(k, encoder, &t.samples.grad)?)
    }
}

impl PolicyOps for GpuOps<'_, '_> {
    fn density_loss(
        &mut self,
        scene: usize,
        points: &[[f32; 3]],
        d_loss: &(dyn Fn(f32) -> f32 + Sync),
    ) -> ngp::Result<u32> {
        self.flush()?;
        let n = self.t.density_loss(scene, points, d_loss)?;
        self.penalised += n;
        Ok(n)
    }

    fn open_gate(&mut self) -> ngp::Result<()> {
        self.record_held(|h, ctx, encoder, grad| h.encode_open_gate(ctx, encoder, grad))
    }

    fn hold_back(&mut self) -> ngp::Result<()> {
        self.record_held(|h, ctx, encoder, grad| h.encode_hold_back(ctx, encoder, grad))
    }

    fn keep_mlp(&mut self) -> ngp::Result<()> {
        self.record_kept(|k, encoder, grad| k.encode_keep(encoder, grad))
    }

    fn restore_mlp(&mut self) -> ngp::Result<()> {
        self.record_kept(|k, encoder, grad| k.encode_restore(encoder, grad))
    }

    fn update_bounds(&mut self, update: &mut dyn FnMut(&mut TableBounds)) -> ngp::Result<()> {
        self.hold()?;
        let t = &mut *self.t;
        let grid = &t.field.layout().grid;
        let (n_entries, f) = (grid.n_entries as usize, grid.config.n_features as usize);
        let b = t
            .bounds
            .get_or_insert_with(|| TableBounds::new(n_entries, f));
        update(b);
        let h = t.hold.as_ref().expect("made above");
        Ok(h.upload_bounds(t.ctx, b)?)
    }
}

#[cfg(test)]
mod tests {
    use super::chunks_needed;

    #[test]
    fn chunks_cover_half_as_much_again_as_expected() {
        // Steady state: 2^18 expected, chunks of 2^19: one.
        assert_eq!(chunks_needed(262_144.0, 1 << 19, 8), 1);
        // A third more than the target still fits one; more takes two.
        assert_eq!(chunks_needed(349_000.0, 1 << 19, 8), 1);
        assert_eq!(chunks_needed(350_000.0, 1 << 19, 8), 2);
        // Nothing expected: one; past the budget: all.
        assert_eq!(chunks_needed(0.0, 1 << 19, 8), 1);
        assert_eq!(chunks_needed(1e9, 1 << 19, 8), 8);
    }
}
