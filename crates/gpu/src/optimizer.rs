//! Adam + EMA on the device (`optimizer.wgsl`): the CPU [`Optimizer`]'s update for weights
//! and gradients that live in GPU buffers, so a training step needs no host round trip of
//! the 12 M-float parameter vector. The learning-rate schedule and Adam's bias correction
//! come from the same [`OptimizerConfig`] functions the CPU uses, evaluated on the host.
//!
//! [`Optimizer`]: ngp::train::optimizer::Optimizer

use super::{
    GpuContext, GpuError, GpuResult, buffer_entry as entry, check_binding, device_buffer as storage,
};
use ngp::train::optimizer::OptimizerConfig;
use wgpu::util::DeviceExt;

const OPTIMIZER_WGSL: &str = include_str!("optimizer.wgsl");
const WORKGROUP: u32 = 256;
/// Steps the first correction table covers (small in tests, so they regrow it).
const FIRST_CORRECTION_CAPACITY: u32 = if cfg!(test) { 8 } else { 1024 };

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct AdamParams {
    n: u32,
    n_matrix: u32,
    row_width: u32,
    _pad0: u32,
    lr: f32,
    beta1: f32,
    beta2: f32,
    epsilon: f32,
    l2_reg: f32,
    ema_decay: f32,
    _pad1: [f32; 2],
}

/// The optimizer state of `n` parameters on the device (moments, per-parameter step counts,
/// the EMA), and the kernel that updates them.
pub struct GpuOptimizer {
    pub config: OptimizerConfig,
    n: u32,
    n_matrix: u32,
    m: wgpu::Buffer,
    v: wgpu::Buffer,
    steps: wgpu::Buffer,
    ema: wgpu::Buffer,
    /// `correction[t]` for t = 0..=step; regrown (doubling) as steps pass its capacity.
    correction: wgpu::Buffer,
    correction_cap: u32,
    uniform: wgpu::Buffer,
    pipeline: wgpu::ComputePipeline,
    groups: [u32; 2],
    /// Updates so far.
    pub step: u32,
}

impl GpuOptimizer {
    /// State for `n_params` parameters, the first `n_matrix` of them MLP weights.
    pub fn new(
        ctx: &GpuContext,
        config: OptimizerConfig,
        n_params: usize,
        n_matrix: usize,
    ) -> GpuResult<GpuOptimizer> {
        let n = u32::try_from(n_params)
            .ok()
            .filter(|&n| n > 0)
            .ok_or_else(|| GpuError::Input(format!("{n_params} parameters")))?;
        if n_matrix > n_params {
            return Err(GpuError::Input(format!(
                "{n_matrix} matrix parameters of {n_params}"
            )));
        }
        let bytes = 4 * n as u64;
        check_binding(ctx, &format!("{n} parameters"), bytes)?;
        let limits = ctx.device.limits();
        let n_groups = n.div_ceil(WORKGROUP);
        let gx = n_groups.min(limits.max_compute_workgroups_per_dimension);
        let groups = [gx, n_groups.div_ceil(gx)];
        let correction_cap = FIRST_CORRECTION_CAPACITY;
        ctx.scoped("optimizer state", || {
            let module = ctx
                .device
                .create_shader_module(wgpu::ShaderModuleDescriptor {
                    label: Some("optimizer.wgsl"),
                    source: wgpu::ShaderSource::Wgsl(OPTIMIZER_WGSL.into()),
                });
            let pipeline = ctx
                .device
                .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some("adam"),
                    layout: None,
                    module: &module,
                    entry_point: Some("adam_main"),
                    compilation_options: Default::default(),
                    cache: None,
                });
            let uniform = ctx.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("adam params"),
                size: std::mem::size_of::<AdamParams>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            GpuOptimizer {
                config,
                n,
                n_matrix: n_matrix as u32,
                m: storage(ctx, "adam m", bytes),
                v: storage(ctx, "adam v", bytes),
                steps: storage(ctx, "adam steps", bytes),
                ema: storage(ctx, "ema", bytes),
                correction: correction_table(ctx, &config, correction_cap),
                correction_cap,
                uniform,
                pipeline,
                groups,
                step: 0,
            }
        })
    }

    pub fn len(&self) -> usize {
        self.n as usize
    }

    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// Records one update into `encoder`: `weights` take an Adam step from `grad`, which is
    /// zeroed, and the EMA follows. Both buffers hold the optimizer's `n` floats
    /// (`STORAGE`). Nothing runs until the encoder is submitted.
    pub fn encode_step(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        weights: &wgpu::Buffer,
        grad: &wgpu::Buffer,
    ) -> GpuResult<()> {
        let bytes = 4 * self.n as u64;
        for (what, b) in [("weights", weights), ("gradient", grad)] {
            if b.size() < bytes {
                return Err(GpuError::Input(format!(
                    "{what} buffer of {} bytes for {} parameters",
                    b.size(),
                    self.n
                )));
            }
        }
        let c = self.config;
        let lr = c.learning_rate(self.step);
        self.step += 1;
        if self.step >= self.correction_cap {
            let cap = (self.step + 1).next_power_of_two();
            self.correction =
                ctx.scoped("optimizer correction", || correction_table(ctx, &c, cap))?;
            self.correction_cap = cap;
        }
        let params = AdamParams {
            n: self.n,
            n_matrix: self.n_matrix,
            row_width: self.groups[0] * WORKGROUP,
            _pad0: 0,
            lr,
            beta1: c.beta1,
            beta2: c.beta2,
            epsilon: c.epsilon,
            l2_reg: c.l2_reg,
            ema_decay: c.ema_decay,
            _pad1: [0.0; 2],
        };
        ctx.scoped("optimizer step", || {
            ctx.queue
                .write_buffer(&self.uniform, 0, bytemuck::bytes_of(&params));
            let bind_group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("adam"),
                layout: &self.pipeline.get_bind_group_layout(0),
                entries: &[
                    entry(0, weights),
                    entry(1, grad),
                    entry(2, &self.m),
                    entry(3, &self.v),
                    entry(4, &self.steps),
                    entry(5, &self.ema),
                    entry(6, &self.correction),
                    entry(7, &self.uniform),
                ],
            });
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &bind_group, &[]);
            pass.dispatch_workgroups(self.groups[0], self.groups[1], 1);
        })
    }

    /// One update, submitted and waited for.
    pub fn step(
        &mut self,
        ctx: &GpuContext,
        weights: &wgpu::Buffer,
        grad: &wgpu::Buffer,
    ) -> GpuResult<()> {
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        self.encode_step(ctx, &mut encoder, weights, grad)?;
        ctx.queue.submit([encoder.finish()]);
        ctx.wait()
    }

    /// The debiased EMA of the weights (what renders and what a snapshot stores), read back;
    /// before any update, the weights themselves, as on the CPU.
    pub fn ema_params(&self, ctx: &GpuContext, weights: &wgpu::Buffer) -> GpuResult<Vec<f32>> {
        let bytes = 4 * self.n as u64;
        if self.step == 0 {
            return ctx.read_buffer(weights, bytes);
        }
        let debias = 1.0 - (self.config.ema_decay as f64).powi(self.step as i32);
        let k = (1.0 / debias) as f32;
        let mut ema: Vec<f32> = ctx.read_buffer(&self.ema, bytes)?;
        ema.iter_mut().for_each(|e| *e *= k);
        Ok(ema)
    }

    /// (first moments, second moments, per-parameter update counts), read back.
    pub fn moments(&self, ctx: &GpuContext) -> GpuResult<(Vec<f32>, Vec<f32>, Vec<u32>)> {
        let bytes = 4 * self.n as u64;
        Ok((
            ctx.read_buffer(&self.m, bytes)?,
            ctx.read_buffer(&self.v, bytes)?,
            ctx.read_buffer(&self.steps, bytes)?,
        ))
    }

    /// The EMA as the kernel keeps it (not debiased), read back: with the moments and
    /// [`Self::step`], what a training state saves.
    pub fn raw_ema(&self, ctx: &GpuContext) -> GpuResult<Vec<f32>> {
        ctx.read_buffer(&self.ema, 4 * self.n as u64)
    }

    /// Takes back a saved state: `step` updates taken, the moments, per-parameter update
    /// counts and the raw EMA ([`Self::moments`], [`Self::raw_ema`]), uploaded. The
    /// bias-correction table regrows to `step` on the next update, as it would have.
    pub fn restore(
        &mut self,
        ctx: &GpuContext,
        step: u32,
        m: &[f32],
        v: &[f32],
        steps: &[u32],
        ema: &[f32],
    ) -> GpuResult<()> {
        let n = self.n as usize;
        if [m.len(), v.len(), steps.len(), ema.len()] != [n; 4] {
            return Err(GpuError::Input(format!(
                "optimizer state of {}/{}/{}/{} values for {n} parameters",
                m.len(),
                v.len(),
                steps.len(),
                ema.len()
            )));
        }
        ctx.scoped("optimizer restore", || {
            ctx.queue.write_buffer(&self.m, 0, bytemuck::cast_slice(m));
            ctx.queue.write_buffer(&self.v, 0, bytemuck::cast_slice(v));
            ctx.queue
                .write_buffer(&self.steps, 0, bytemuck::cast_slice(steps));
            ctx.queue
                .write_buffer(&self.ema, 0, bytemuck::cast_slice(ema));
        })?;
        self.step = step;
        Ok(())
    }
}

fn correction_table(ctx: &GpuContext, config: &OptimizerConfig, cap: u32) -> wgpu::Buffer {
    let table: Vec<f32> = (0..cap).map(|t| config.adam_correction(t)).collect();
    ctx.device
        .create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("adam correction"),
            contents: bytemuck::cast_slice(&table),
            usage: wgpu::BufferUsages::STORAGE,
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_context;
    use ngp::rng::Pcg32;
    use ngp::train::optimizer::{Optimizer, Touched};

    fn upload(ctx: &GpuContext, label: &str, data: &[f32]) -> wgpu::Buffer {
        ctx.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytemuck::cast_slice(data),
                usage: wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_SRC
                    | wgpu::BufferUsages::COPY_DST,
            })
    }

    fn close(what: &str, got: &[f32], want: &[f32], abs: f32, rel: f32) {
        assert_eq!(got.len(), want.len(), "{what}: length");
        for (i, (&g, &w)) in got.iter().zip(want).enumerate() {
            assert!(
                (g - w).abs() <= abs + rel * w.abs(),
                "{what}[{i}]: GPU {g} vs CPU {w}"
            );
        }
    }

    /// 40 updates of 3000 parameters (700 MLP weights, the rest grid entries with sparse
    /// gradients, some never touched, the learning rate decaying from step 10) against the
    /// CPU optimizer, which gets the touched-group bitmap the trainer gives it.
    ///
    /// Step counts must match exactly (they decide which parameters Adam moved); moments
    /// and weights within 1e-6 relative: the same f32 operations in the same order, but a
    /// GPU compiler may fuse a multiply-add and Vulkan's sqrt and division are not
    /// correctly rounded. The EMA within 1e-5: the CPU catches untouched groups up in
    /// closed form, the GPU step by step.
    #[test]
    fn adam_and_ema_match_the_cpu_optimizer() {
        let Some(ctx) = test_context() else { return };
        let (n, n_matrix) = (3000usize, 700usize);
        let config = OptimizerConfig {
            decay_start: 10,
            decay_interval: 8,
            ..Default::default()
        };
        let mut rng = Pcg32::new(5, 1);
        let mut w: Vec<f32> = (0..n).map(|_| rng.next_f32() * 2.0 - 1.0).collect();
        let weights = upload(ctx, "weights", &w);
        let grad = upload(ctx, "grad", &vec![0.0; n]);
        let mut cpu = Optimizer::new(config, n, n_matrix);
        let mut gpu = GpuOptimizer::new(ctx, config, n, n_matrix).unwrap();
        for step in 0..40 {
            let mut g = vec![0.0f32; n];
            let mut touched = Touched::new(n);
            for (i, gi) in g.iter_mut().enumerate() {
                // Grid entries past 2800 never get a gradient; of the others ~30 % do.
                let live = i < n_matrix || (i < 2800 && rng.next_f32() < 0.3);
                if live {
                    *gi = (rng.next_f32() - 0.5) * 0.1;
                    touched.mark(i);
                }
            }
            if step == 3 {
                g[n_matrix] = 0.0; // touched, yet exactly zero: Adam must skip it
            }
            ctx.queue.write_buffer(&grad, 0, bytemuck::cast_slice(&g));
            gpu.step(ctx, &weights, &grad).unwrap();
            cpu.step(&mut w, &mut [g], Some(&[touched]));
        }
        assert_eq!(gpu.step, cpu.step);
        let (m, v, steps) = gpu.moments(ctx).unwrap();
        let (cm, cv, csteps) = cpu.moments();
        assert_eq!(steps, csteps, "per-parameter update counts");
        assert!(steps[2900] == 0 && steps[0] == 40 && steps[900] > 0 && steps[900] < 40);
        close("m", &m, cm, 1e-9, 1e-6);
        close("v", &v, cv, 1e-12, 1e-6);
        let got_w: Vec<f32> = ctx.read_buffer(&weights, 4 * n as u64).unwrap();
        close("weights", &got_w, &w, 1e-7, 1e-6);
        close(
            "published EMA",
            &gpu.ema_params(ctx, &weights).unwrap(),
            &cpu.ema_params(&w),
            1e-6,
            1e-5,
        );
        let zeroed: Vec<f32> = ctx.read_buffer(&grad, 4 * n as u64).unwrap();
        assert!(zeroed.iter().all(|&x| x == 0.0), "gradient left non-zero");
    }

    #[test]
    fn ema_before_any_step_is_the_weights() {
        let Some(ctx) = test_context() else { return };
        let w = [0.5f32, -2.0, 3.0];
        let weights = upload(ctx, "weights", &w);
        let opt = GpuOptimizer::new(ctx, OptimizerConfig::default(), 3, 1).unwrap();
        assert_eq!(opt.ema_params(ctx, &weights).unwrap(), w);
    }

    #[test]
    fn bad_sizes_are_errors() {
        let Some(ctx) = test_context() else { return };
        let c = OptimizerConfig::default();
        assert!(GpuOptimizer::new(ctx, c, 0, 0).is_err());
        assert!(GpuOptimizer::new(ctx, c, 10, 11).is_err());
        let mut opt = GpuOptimizer::new(ctx, c, 10, 2).unwrap();
        let small = upload(ctx, "small", &[0.0; 9]);
        let ok = upload(ctx, "ok", &[0.0; 10]);
        assert!(opt.step(ctx, &small, &ok).is_err());
        assert!(opt.step(ctx, &ok, &small).is_err());
        assert_eq!(opt.step, 0, "a refused update does not count");
        opt.step(ctx, &ok, &ok).unwrap();
        assert_eq!(opt.step, 1);
    }
}
