//! A whole training step on the device (issue 10), composed from the tested kernels: the
//! occupancy update on the CPU trainer's schedule with the field on the device, a batch of
//! rays drawn, marched and compacted ([`RayKernels`]), the grid forward, the network forward
//! keeping its activations, the loss, the network and grid backward, and Adam + EMA. One
//! scene (plain Instant-NGP under any [`LevelIndices`]); the CPU [`Trainer`] is the oracle:
//! same initial weights, same seeds (`mix`), same ray draws, same rays-per-batch adaptation,
//! same loss normalisation and density pull-up.
//!
//! Host round trips per step: the batch's three counters (the network kernels take their
//! sample count from the host, so the step submits twice: rays, then the rest), the per-ray
//! (loss, samples used) pairs that the rays-per-batch adaptation and the reported loss need,
//! and the occupancy grid's mean after an update (it switches the pull-up). Samples and
//! weights never leave the device.
//!
//! Differences from the CPU step, by design of this first version: the network runs (and
//! keeps activations) on every marched sample, where the CPU first finds where each ray's
//! transmittance ends with density-only waves and runs the full network on the used samples
//! only; the loss kernel gives the samples past termination a zero gradient, so the update
//! is the same, only slower by marched / used. Marching is bounded by a sample budget
//! ([`GpuTrainer::sample_budget`]); rays past it train nothing this step, as in instant-ngp.
//!
//! [`Trainer`]: crate::ngp::train::Trainer

use super::field::{DensityScratch, GpuField};
use super::grid::GridShape;
use super::loss::{LossBuffers, LossConfig, LossKernel};
use super::mlp::{ACT_ROWS, EncodedBatch, MlpWorkspace};
use super::occupancy::GpuOccupancy;
use super::optimizer::GpuOptimizer;
use super::rays::{RayBatch, RayKernels};
use super::{GpuContext, GpuError, GpuResult, buffer_entry, device_buffer};
use crate::ngp::data::Dataset;
use crate::ngp::encoding::LevelIndices;
use crate::ngp::model::Model;
use crate::ngp::network::ModelConfig;
use crate::ngp::network::nerf::NerfNetwork;
use crate::ngp::occupancy::{MIN_OPTICAL_THICKNESS, OccupancyGrid};
use crate::ngp::render::march::Marcher;
use crate::ngp::train::StepStats;
use crate::ngp::train::TrainConfig;
use crate::ngp::train::loss::DENSITY_PULL_UP;
use crate::ngp::train::trainer::{initial_rays_per_batch, mix, next_rays_per_batch};
use std::sync::Arc;
use std::time::Instant;

const DIRS_WGSL: &str = include_str!("dirs.wgsl");
const DIRS_WORKGROUP: u32 = 64;
/// Most rays per batch: the CPU trainer's (and the reference's) cap.
const MAX_RAYS: u32 = 1 << 18;
/// Marched samples the device holds per batch, as a multiple of the trained-sample target.
/// Marched samples exceed the trained ones (the generated test scene: about 1.5×), and a
/// budget that binds drops rays from the step; 4× leaves room at the cost of 1.7 KiB of
/// network workspace per budgeted sample. The device's largest storage binding caps it
/// (the network's kept activations, `ACT_ROWS` floats a sample, are the largest buffer).
const BUDGET_FACTOR: u32 = 4;
/// The encoding's leading dimension is the sample count rounded up to this, so the kernels'
/// padding work stays small while a bind is valid for a range of counts.
const LD_GRANULE: u32 = 256;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct DirsParams {
    n_rays: u32,
    row_width: u32,
    _pad: [u32; 2],
}

/// One scene trained on the device.
pub struct GpuTrainer<'c> {
    ctx: &'c GpuContext,
    pub config: TrainConfig,
    model: ModelConfig,
    dataset: Arc<Dataset>,
    marcher: Marcher,
    field: GpuField,
    occupancy: GpuOccupancy,
    density_scratch: DensityScratch,
    rays: RayKernels,
    batch: RayBatch,
    loss: LossKernel,
    optimizer: GpuOptimizer,
    ws: MlpWorkspace,
    dirs: wgpu::Buffer,
    raw: wgpu::Buffer,
    d_raw: wgpu::Buffer,
    enc: wgpu::Buffer,
    d_enc: wgpu::Buffer,
    grad: wgpu::Buffer,
    ray_out: wgpu::Buffer,
    dirs_pipeline: wgpu::ComputePipeline,
    dirs_uniform: wgpu::Buffer,
    grid_mean: f32,
    rays_per_batch: u32,
    measured_samples: u32,
    measured_marched: u32,
    /// Steps taken.
    pub step: u32,
}

fn input<T>(msg: String) -> GpuResult<T> {
    Err(GpuError::Input(msg))
}

impl<'c> GpuTrainer<'c> {
    /// A trainer of `dataset` under `indices` with `model`'s architecture, starting from the
    /// weights and occupancy grid the CPU [`Trainer`](crate::ngp::train::Trainer) starts
    /// from for `config.seed`. `config.schedule` and `hidden_loss_weight` do not apply (one
    /// scene), nor does `workers`.
    pub fn new(
        ctx: &'c GpuContext,
        model: ModelConfig,
        dataset: Arc<Dataset>,
        indices: LevelIndices,
        config: TrainConfig,
    ) -> GpuResult<Self> {
        let net = NerfNetwork::new(model).map_err(|e| GpuError::Input(e.to_string()))?;
        let layout = net.layout.clone();
        let n_levels = layout.grid.levels.len();
        if indices.len() != n_levels {
            return input(format!(
                "{} index functions for {n_levels} grid levels",
                indices.len()
            ));
        }
        if dataset.frames.is_empty() {
            return input(format!("{}: no training images", dataset.root.display()));
        }
        if dataset.aabb_scale != model.aabb_scale {
            return input(format!(
                "{}: aabb_scale {} differs from the model's {}",
                dataset.root.display(),
                dataset.aabb_scale,
                model.aabb_scale
            ));
        }
        if config.batch_samples == 0 {
            return input("a batch of 0 samples".into());
        }
        let limits = ctx.device.limits();
        let max = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        let fits = (max / (4 * ACT_ROWS)).min(u32::MAX as u64) as u32 / LD_GRANULE * LD_GRANULE;
        let budget = config.batch_samples.saturating_mul(BUDGET_FACTOR).min(fits);
        if budget < config.batch_samples {
            return input(format!(
                "{} samples per batch: the device's {max}-byte bindings hold {fits}",
                config.batch_samples
            ));
        }
        let params = net.init_params(config.seed);
        let field = GpuField::new(ctx, &layout, &params, &indices)?;
        let marcher = Marcher::new(model.aabb_scale);
        // The CPU trainer's starting grid: every cell seen by no camera culled.
        let mut grid = OccupancyGrid::new(model.aabb_scale);
        let cams: Vec<_> = dataset.frames.iter().map(|f| f.camera.clone()).collect();
        grid.mark_untrained(&cams);
        let grid_mean = grid.mean;
        let occupancy = GpuOccupancy::upload(ctx, &grid, &marcher)?;
        let rays = RayKernels::new(ctx, &dataset.frames, &marcher)?;
        let batch = RayBatch::new(ctx, MAX_RAYS, budget)?;
        let loss = LossKernel::new(ctx)?;
        let optimizer = GpuOptimizer::new(
            ctx,
            config.optimizer,
            layout.n_params,
            layout.n_mlp_params(),
        )?;
        let ws = field.mlp().workspace(ctx, budget)?;
        let width = layout.grid.config.n_output_dims() as u64;
        let b = budget as u64;
        if 4 * width * b > max {
            return input(format!(
                "a budget of {budget} samples needs a {}-byte encoding, past the device's \
                 {max}-byte binding",
                4 * width * b
            ));
        }
        let (dirs, raw, d_raw, enc, d_enc, grad, ray_out) =
            ctx.scoped("trainer buffers", || {
                (
                    device_buffer(ctx, "trainer dirs", 12 * b),
                    device_buffer(ctx, "trainer raw", 16 * b),
                    device_buffer(ctx, "trainer d_raw", 16 * b),
                    device_buffer(ctx, "trainer encoding", 4 * width * b),
                    device_buffer(ctx, "trainer encoding gradient", 4 * width * b),
                    device_buffer(ctx, "trainer gradient", 4 * layout.n_params as u64),
                    device_buffer(ctx, "trainer ray losses", 8 * MAX_RAYS as u64),
                )
            })?;
        let (dirs_pipeline, dirs_uniform) = ctx.scoped("trainer dirs kernel", || {
            let module = ctx
                .device
                .create_shader_module(wgpu::ShaderModuleDescriptor {
                    label: Some("dirs.wgsl"),
                    source: wgpu::ShaderSource::Wgsl(DIRS_WGSL.into()),
                });
            let pipeline = ctx
                .device
                .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some("dirs"),
                    layout: None,
                    module: &module,
                    entry_point: Some("dirs_main"),
                    compilation_options: Default::default(),
                    cache: None,
                });
            let uniform = ctx.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("dirs params"),
                size: std::mem::size_of::<DirsParams>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            (pipeline, uniform)
        })?;
        Ok(GpuTrainer {
            ctx,
            rays_per_batch: initial_rays_per_batch(config.batch_samples),
            config,
            model,
            dataset,
            marcher,
            field,
            occupancy,
            density_scratch: DensityScratch::default(),
            rays,
            batch,
            loss,
            optimizer,
            ws,
            dirs,
            raw,
            d_raw,
            enc,
            d_enc,
            grad,
            ray_out,
            dirs_pipeline,
            dirs_uniform,
            grid_mean,
            measured_samples: 0,
            measured_marched: 0,
            step: 0,
        })
    }

    /// Marched samples a batch may hold.
    pub fn sample_budget(&self) -> u32 {
        self.batch.sample_budget()
    }

    /// (rays per batch, trained samples, marched samples) of the last step, as
    /// [`Trainer::batch_counters`](crate::ngp::train::Trainer::batch_counters).
    pub fn batch_counters(&self) -> (u32, u32, u32) {
        (
            self.rays_per_batch,
            self.measured_samples,
            self.measured_marched,
        )
    }

    /// The occupancy grid's cascade-0 mean after the last update.
    pub fn grid_mean(&self) -> f32 {
        self.grid_mean
    }

    /// The CPU trainer's occupancy schedule: every step for the first 16, then every
    /// `step / 16` steps up to every 16th; the update runs on the current weights.
    fn update_occupancy(&mut self) -> GpuResult<()> {
        let step = self.step;
        let interval = (step / 16).clamp(1, 16);
        if !step.is_multiple_of(interval) {
            return Ok(());
        }
        let (nu, nn) = OccupancyGrid::sample_counts(
            self.occupancy.n_cascades as usize,
            step,
            self.config.occupancy_fraction,
        );
        let (nu, nn) = match (u32::try_from(nu), u32::try_from(nn)) {
            (Ok(a), Ok(b)) => (a, b),
            _ => return input(format!("occupancy: {nu} + {nn} samples")),
        };
        let ctx = self.ctx;
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        // Scene 0's update seed on the CPU.
        let seed = mix(self.config.seed, 0x6772_6964);
        self.occupancy.encode_update(
            ctx,
            &mut encoder,
            &self.field,
            &mut self.density_scratch,
            nu,
            nn,
            seed,
        )?;
        ctx.scoped("occupancy update", || ctx.queue.submit([encoder.finish()]))?;
        self.grid_mean = self.occupancy.read_mean(ctx)?;
        Ok(())
    }

    /// One training step.
    pub fn train_step(&mut self) -> GpuResult<StepStats> {
        let t0 = Instant::now();
        self.update_occupancy()?;
        let t_occ = t0.elapsed().as_secs_f64();
        let ctx = self.ctx;
        let step = self.step;
        let n_rays = self.rays_per_batch;
        // Scene 0's batch seed on the CPU.
        let seed = mix(mix(self.config.seed, step as u64), 1);

        // 1. Rays: draw, march, compact; then the counts the network kernels need.
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        self.rays.encode(
            ctx,
            &mut encoder,
            &self.batch,
            &self.occupancy.bitfield,
            n_rays,
            seed,
        )?;
        ctx.scoped("training rays", || ctx.queue.submit([encoder.finish()]))?;
        let (_asked, written, with_samples) = self.batch.read_counters(ctx)?;
        let n = written.min(self.batch.sample_budget());

        // 2. Network, loss, backward and the optimizer in one submission.
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        let loss_norm = 1.0 / n_rays as f32;
        let pull_up = if self.grid_mean < MIN_OPTICAL_THICKNESS {
            DENSITY_PULL_UP
        } else {
            0.0
        };
        if n > 0 {
            self.encode_samples(&mut encoder, n_rays, n, loss_norm, pull_up)?;
        }
        // The CPU steps the optimizer even when nothing was trained (its MLP weights still
        // take L2 and momentum).
        self.optimizer
            .encode_step(ctx, &mut encoder, &self.field.params, &self.grad)?;
        ctx.scoped("training step", || ctx.queue.submit([encoder.finish()]))?;
        let (loss, used) = if n > 0 {
            let out: Vec<[f32; 2]> = ctx.read_buffer(&self.ray_out, 8 * n_rays as u64)?;
            out.iter().fold((0.0f64, 0u64), |(l, u), o| {
                (l + o[0] as f64, u + o[1].to_bits() as u64)
            })
        } else {
            ctx.wait()?;
            (0.0, 0)
        };
        let scene_loss = (loss / n_rays as f64) as f32;
        self.measured_samples = used as u32;
        self.measured_marched = n;
        // The reference keeps its ray count when nothing was trained.
        if used > 0 {
            self.rays_per_batch = next_rays_per_batch(n_rays, self.config.batch_samples, used);
        }
        self.step += 1;
        let seconds = t0.elapsed().as_secs_f64();
        Ok(StepStats {
            step,
            loss: scene_loss,
            cover_loss: Some(scene_loss),
            n_rays: with_samples as u64,
            n_samples: used,
            n_marched: n as u64,
            seconds,
            occupancy_seconds: t_occ,
            rays_seconds: seconds - t_occ,
            optimizer_seconds: 0.0,
        })
    }

    /// Records directions, grid forward, network forward, loss, network backward and grid
    /// backward over the batch's `n` compacted samples.
    fn encode_samples(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        n_rays: u32,
        n: u32,
        loss_norm: f32,
        pull_up: f32,
    ) -> GpuResult<()> {
        let ctx = self.ctx;
        let layout = self.field.layout();
        let width = layout.grid.config.n_output_dims() as u64;
        let (g0, g1) = (4 * layout.grid_offset as u64, 4 * layout.n_params as u64);
        let ld = n
            .div_ceil(LD_GRANULE)
            .saturating_mul(LD_GRANULE)
            .min(self.batch.sample_budget());
        let shape = GridShape { n_samples: n, ld };
        let (pos_bytes, enc_bytes) = (12 * ld as u64, 4 * width * ld as u64);

        // Per-sample directions.
        let max_dim = ctx.device.limits().max_compute_workgroups_per_dimension;
        let groups = n_rays.div_ceil(DIRS_WORKGROUP).max(1);
        let gx = groups.min(max_dim);
        let params = DirsParams {
            n_rays,
            row_width: gx * DIRS_WORKGROUP,
            _pad: [0; 2],
        };
        ctx.scoped("trainer dirs", || {
            ctx.queue
                .write_buffer(&self.dirs_uniform, 0, bytemuck::bytes_of(&params));
            let bg = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("dirs"),
                layout: &self.dirs_pipeline.get_bind_group_layout(0),
                entries: &[
                    buffer_entry(0, &self.batch.drawn),
                    buffer_entry(1, &self.batch.rays),
                    buffer_entry(2, &self.dirs),
                    buffer_entry(3, &self.dirs_uniform),
                ],
            });
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.dirs_pipeline);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(gx, groups.div_ceil(gx), 1);
        })?;

        // Grid forward.
        let grid = self.field.grid();
        let index = self.field.index();
        let forward = grid.bind_forward(
            ctx,
            index,
            self.batch.pos.slice(..pos_bytes),
            self.field.params.slice(g0..g1),
            self.enc.slice(..enc_bytes),
            shape,
        )?;
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            forward.record(&mut pass);
        }

        // Network forward, keeping activations for the backward.
        let eb = EncodedBatch {
            params: &self.field.params,
            enc: &self.enc,
            ld,
            n,
        };
        let mlp = self.field.mlp();
        mlp.encode_forward(ctx, encoder, &eb, &self.dirs, &self.raw, Some(&self.ws))?;

        // Loss and its gradient to the raw outputs.
        let bufs = LossBuffers {
            rays: &self.batch.rays,
            raw: &self.raw,
            dt: &self.batch.dt,
            dist: &self.batch.dist,
            pos: &self.batch.pos,
            d_raw: &self.d_raw,
            ray_out: &self.ray_out,
        };
        let cfg = LossConfig::new(&self.marcher, loss_norm, pull_up);
        self.loss.encode(ctx, encoder, &bufs, n_rays, n, &cfg)?;

        // Network backward: MLP weight gradients into `grad`, dL/d(enc) into `d_enc`.
        mlp.encode_backward(
            ctx,
            encoder,
            &eb,
            &self.d_raw,
            &self.ws,
            &self.grad,
            &self.d_enc,
        )?;

        // Grid backward into the grid block of `grad`.
        let backward = grid.bind_backward(
            ctx,
            index,
            self.batch.pos.slice(..pos_bytes),
            self.d_enc.slice(..enc_bytes),
            self.grad.slice(g0..g1),
            shape,
        )?;
        let mut pass = encoder.begin_compute_pass(&Default::default());
        backward.record(&mut pass);
        Ok(())
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

    /// The occupancy grid, read back.
    pub fn grid(&self) -> GpuResult<OccupancyGrid> {
        self.occupancy.download(self.ctx)
    }

    /// The model as published (what [`Model::from_trainer`] makes of a CPU trainer).
    pub fn model(&self, loss: f32) -> GpuResult<Model> {
        Model::from_parts(
            self.model,
            self.inference_params()?,
            self.grid()?,
            self.step,
            loss,
            &self.dataset,
            self.batch_counters(),
        )
        .map_err(|e| GpuError::Input(e.to_string()))
    }
}
