//! Training's per-ray loss on the device (`loss.wgsl`): compositing, instant-ngp's Huber
//! loss and its gradient to every sample's raw outputs, with the reference's density
//! regularisers, exactly as [`ray_loss`] defines them on the CPU.
//!
//! [`ray_loss`]: ngp::train::loss::ray_loss

use super::{GpuContext, GpuError, GpuResult, buffer_entry as entry};
use ngp::render::composite::TRAIN_MIN_TRANSMITTANCE;
use ngp::render::march::Marcher;
use ngp::train::loss::{NEAR_DISTANCE, NEAR_PUSH_DOWN};
use wgpu::util::DeviceExt;

const LOSS_WGSL: &str = include_str!("loss.wgsl");
const WORKGROUP: u32 = 64;

/// One training ray as the device reads it (`struct Ray` in `loss.wgsl`): its samples are
/// `start..start + n` of the compacted sample buffers.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct GpuRay {
    pub start: u32,
    pub n: u32,
    pub bg: [f32; 3],
    pub target: [f32; 3],
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct LossParams {
    n_rays: u32,
    row_width: u32,
    loss_norm: f32,
    pull_up: f32,
    aabb_min: [f32; 3],
    min_transmittance: f32,
    aabb_max: [f32; 3],
    near_distance: f32,
    near_push_down: f32,
    mean_gate: u32,
    mean_below: f32,
    _pad: u32,
}

/// What one batch's loss depends on beyond its samples.
#[derive(Clone, Copy, Debug)]
pub struct LossConfig {
    /// Scales the loss gradient: scene weight / rays in the batch.
    pub loss_norm: f32,
    /// `DENSITY_PULL_UP` while the scene's grid mean is below 0.01, else 0 (or
    /// `DENSITY_PULL_UP` gated on the device by `pull_up_below_mean`).
    pub pull_up: f32,
    /// `Some(t)`: the pull-up applies only while the occupancy grid's mean, read on the
    /// device from [`LossBuffers::grid_mean`], is below `t`.
    pub pull_up_below_mean: Option<f32>,
    /// The scene's box in ngp space (where cascade 0 lies in warped coordinates).
    pub aabb_min: [f32; 3],
    pub aabb_max: [f32; 3],
}

impl LossConfig {
    pub fn new(marcher: &Marcher, loss_norm: f32, pull_up: f32) -> LossConfig {
        LossConfig {
            loss_norm,
            pull_up,
            pull_up_below_mean: None,
            aabb_min: marcher.aabb_min,
            aabb_max: marcher.aabb_max,
        }
    }
}

/// A batch's buffers on the device. Per sample: `raw` and `d_raw` 4 floats, `dt` and
/// `dist` 1, `pos` 3 (warped); per ray: `rays` one [`GpuRay`], `ray_out` (loss, samples
/// used as u32 bits).
pub struct LossBuffers<'a> {
    pub rays: &'a wgpu::Buffer,
    pub raw: &'a wgpu::Buffer,
    pub dt: &'a wgpu::Buffer,
    pub dist: &'a wgpu::Buffer,
    pub pos: &'a wgpu::Buffer,
    pub d_raw: &'a wgpu::Buffer,
    pub ray_out: &'a wgpu::Buffer,
    /// The occupancy grid's mean (the f32 at byte 0), for a gated pull-up.
    pub grid_mean: Option<&'a wgpu::Buffer>,
}

/// A batch in host memory (see [`LossBuffers`] for the layout).
#[derive(Clone, Copy)]
pub struct HostBatch<'a> {
    pub rays: &'a [GpuRay],
    pub raw: &'a [[f32; 4]],
    pub dt: &'a [f32],
    pub dist: &'a [f32],
    pub pos: &'a [[f32; 3]],
}

pub struct LossKernel {
    pipeline: wgpu::ComputePipeline,
    /// Bound as the grid mean when the pull-up is not gated.
    no_mean: wgpu::Buffer,
}

impl LossKernel {
    pub fn new(ctx: &GpuContext) -> GpuResult<LossKernel> {
        ctx.scoped("loss kernel", || {
            let module = ctx
                .device
                .create_shader_module(wgpu::ShaderModuleDescriptor {
                    label: Some("loss.wgsl"),
                    source: wgpu::ShaderSource::Wgsl(LOSS_WGSL.into()),
                });
            let pipeline = ctx
                .device
                .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some("loss"),
                    layout: None,
                    module: &module,
                    entry_point: Some("loss_main"),
                    compilation_options: Default::default(),
                    cache: None,
                });
            let no_mean = ctx.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("loss no grid mean"),
                size: 16,
                usage: wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            });
            LossKernel { pipeline, no_mean }
        })
    }

    /// Records the loss of `n_rays` rays over `n_samples` samples into `encoder`. The
    /// uniform is written at once, so one kernel serves one batch per submission.
    pub fn encode(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        bufs: &LossBuffers,
        n_rays: u32,
        n_samples: u32,
        cfg: &LossConfig,
    ) -> GpuResult<()> {
        if n_rays == 0 {
            return Ok(());
        }
        let (r, s) = (n_rays as u64, n_samples as u64);
        for (what, b, need) in [
            ("rays", bufs.rays, 32 * r),
            ("ray_out", bufs.ray_out, 8 * r),
            ("raw", bufs.raw, 16 * s),
            ("d_raw", bufs.d_raw, 16 * s),
            ("dt", bufs.dt, 4 * s),
            ("dist", bufs.dist, 4 * s),
            ("pos", bufs.pos, 12 * s),
        ] {
            if b.size() < need {
                return Err(GpuError::Input(format!(
                    "loss: {what} buffer of {} bytes, {need} needed",
                    b.size()
                )));
            }
        }
        let max_dim = ctx.device.limits().max_compute_workgroups_per_dimension;
        let n_groups = n_rays.div_ceil(WORKGROUP);
        let gx = n_groups.min(max_dim);
        let params = LossParams {
            n_rays,
            row_width: gx * WORKGROUP,
            loss_norm: cfg.loss_norm,
            pull_up: cfg.pull_up,
            aabb_min: cfg.aabb_min,
            min_transmittance: TRAIN_MIN_TRANSMITTANCE,
            aabb_max: cfg.aabb_max,
            near_distance: NEAR_DISTANCE,
            near_push_down: NEAR_PUSH_DOWN,
            mean_gate: cfg.pull_up_below_mean.is_some() as u32,
            mean_below: cfg.pull_up_below_mean.unwrap_or(0.0),
            _pad: 0,
        };
        let grid_mean = match (cfg.pull_up_below_mean, bufs.grid_mean) {
            (Some(_), Some(b)) => b,
            (Some(_), None) => {
                return Err(GpuError::Input(
                    "loss: a pull-up gated by the grid mean without the mean".into(),
                ));
            }
            (None, _) => &self.no_mean,
        };
        ctx.scoped("loss dispatch", || {
            // Its own parameters: several scenes' losses may be recorded before a submit.
            let uniform = ctx
                .device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some("loss params"),
                    contents: bytemuck::bytes_of(&params),
                    usage: wgpu::BufferUsages::UNIFORM,
                });
            let bind_group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("loss"),
                layout: &self.pipeline.get_bind_group_layout(0),
                entries: &[
                    entry(0, bufs.rays),
                    entry(1, bufs.raw),
                    entry(2, bufs.dt),
                    entry(3, bufs.dist),
                    entry(4, bufs.pos),
                    entry(5, bufs.d_raw),
                    entry(6, bufs.ray_out),
                    entry(7, &uniform),
                    entry(8, grid_mean),
                ],
            });
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &bind_group, &[]);
            pass.dispatch_workgroups(gx, n_groups.div_ceil(gx), 1);
        })
    }

    /// Uploads a batch, runs it and reads back (per sample d_raw; per ray loss and samples
    /// used): for tests and benchmarks.
    #[allow(clippy::type_complexity)]
    pub fn run_host(
        &self,
        ctx: &GpuContext,
        batch: &HostBatch,
        cfg: &LossConfig,
    ) -> GpuResult<(Vec<[f32; 4]>, Vec<(f32, u32)>)> {
        let HostBatch {
            rays,
            raw,
            dt,
            dist,
            pos,
        } = *batch;
        let n = raw.len();
        if dt.len() != n || dist.len() != n || pos.len() != n {
            return Err(GpuError::Input(
                "loss: per-sample inputs differ in length".into(),
            ));
        }
        if let Some(r) = rays.iter().find(|r| r.start as usize + r.n as usize > n) {
            return Err(GpuError::Input(format!(
                "loss: ray {r:?} reads past the {n} samples"
            )));
        }
        let n_rays = u32::try_from(rays.len())
            .map_err(|_| GpuError::Input("loss: more than 2^32 rays".into()))?;
        let n_samples = u32::try_from(n.max(1))
            .map_err(|_| GpuError::Input("loss: more than 2^32 samples".into()))?;
        let init = |label: &str, bytes: &[u8]| {
            // A binding cannot be empty.
            let bytes: &[u8] = if bytes.is_empty() { &[0; 16] } else { bytes };
            ctx.device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents: bytes,
                    usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                })
        };
        let out = |label: &str, bytes: u64| {
            ctx.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: bytes.max(16),
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            })
        };
        let (b_rays, b_raw, b_dt, b_dist, b_pos, b_draw, b_out) =
            ctx.scoped("loss buffers", || {
                (
                    init("rays", bytemuck::cast_slice(rays)),
                    init("raw", bytemuck::cast_slice(raw)),
                    init("dt", bytemuck::cast_slice(dt)),
                    init("dist", bytemuck::cast_slice(dist)),
                    init("pos", bytemuck::cast_slice(pos)),
                    out("d_raw", 16 * n_samples as u64),
                    out("ray_out", 8 * rays.len() as u64),
                )
            })?;
        let bufs = LossBuffers {
            rays: &b_rays,
            raw: &b_raw,
            dt: &b_dt,
            dist: &b_dist,
            pos: &b_pos,
            d_raw: &b_draw,
            ray_out: &b_out,
            grid_mean: None,
        };
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        self.encode(ctx, &mut encoder, &bufs, n_rays, n as u32, cfg)?;
        ctx.queue.submit([encoder.finish()]);
        ctx.wait()?;
        let d_raw: Vec<[f32; 4]> = ctx.read_buffer(&b_draw, 16 * n as u64)?;
        let per_ray: Vec<[u32; 2]> = ctx.read_buffer(&b_out, 8 * rays.len() as u64)?;
        Ok((
            d_raw,
            per_ray
                .into_iter()
                .map(|[l, n]| (f32::from_bits(l), n))
                .collect(),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_context;
    use ngp::rng::Pcg32;
    use ngp::train::loss::{DENSITY_PULL_UP, ray_loss};

    struct Batch {
        rays: Vec<GpuRay>,
        raw: Vec<[f32; 4]>,
        dt: Vec<f32>,
        dist: Vec<f32>,
        pos: Vec<[f32; 3]>,
    }

    /// Rays of 0 to 60 samples: densities from empty to opaque (so some rays stop early,
    /// some pass through), distances that start inside the near distance, warped positions
    /// inside and outside cascade 0 of an aabb-4 box.
    fn batch(n_rays: usize, seed: u64) -> Batch {
        let mut r = Pcg32::new(seed, 3);
        let mut b = Batch {
            rays: Vec::new(),
            raw: Vec::new(),
            dt: Vec::new(),
            dist: Vec::new(),
            pos: Vec::new(),
        };
        for i in 0..n_rays {
            let n = if i % 17 == 0 { 0 } else { r.below(61) };
            let opacity = r.next_f32() * 8.0 - 5.0;
            let mut t = r.next_f32() * 0.2;
            b.rays.push(GpuRay {
                start: b.raw.len() as u32,
                n,
                bg: [r.next_f32(), r.next_f32(), r.next_f32()],
                target: [r.next_f32(), r.next_f32(), r.next_f32()],
            });
            for _ in 0..n {
                let dt = 0.002 + r.next_f32() * 0.03;
                b.raw.push([
                    r.next_f32() * 6.0 - 3.0,
                    r.next_f32() * 6.0 - 3.0,
                    r.next_f32() * 6.0 - 3.0,
                    opacity + r.next_f32() * 4.0 - 2.0,
                ]);
                b.dt.push(dt);
                b.dist.push(t);
                t += dt;
                b.pos.push([r.next_f32(), r.next_f32(), r.next_f32()]);
            }
        }
        b
    }

    /// Against the CPU's `ray_loss` on 3000 rays: samples used exactly, loss within 1e-5
    /// relative plus 2e-7, each d_raw within 1e-4 of the ray's largest component (exp, sigmoid and
    /// division are not correctly rounded on GPUs, and the density gradient subtracts the
    /// remaining colour from a running sum, which turns ulps into relative error where the
    /// two nearly cancel).
    #[test]
    fn loss_and_gradients_match_the_cpu() {
        let Some(ctx) = test_context() else { return };
        let b = batch(3000, 1);
        let marcher = Marcher::new(4);
        let cfg = LossConfig::new(&marcher, 1.0 / 3000.0 * 0.7, DENSITY_PULL_UP);
        let k = LossKernel::new(ctx).unwrap();
        let host = HostBatch {
            rays: &b.rays,
            raw: &b.raw,
            dt: &b.dt,
            dist: &b.dist,
            pos: &b.pos,
        };
        let (d_raw, per_ray) = k.run_host(ctx, &host, &cfg).unwrap();
        let mut want = vec![[0.0f32; 4]; b.raw.len()];
        let (mut stopped, mut pulled, mut pushed) = (0, 0, 0);
        for (ray, &(loss, n_used)) in b.rays.iter().zip(&per_ray) {
            let r = ray.start as usize..(ray.start + ray.n) as usize;
            let pos = &b.pos[r.clone()];
            let c = ray_loss(
                &b.raw[r.clone()],
                &b.dt[r.clone()],
                &b.dist[r.clone()],
                |j| marcher.in_cascade0(pos[j]),
                ray.bg,
                ray.target,
                cfg.loss_norm,
                cfg.pull_up,
                &mut want[r.clone()],
            );
            assert_eq!(n_used as usize, c.n_used, "ray {ray:?}");
            // The predicted colour agrees to ~1e-6 and the loss's slope is at most 1/5 per
            // channel, so a small loss may differ by ~2e-7 in absolute terms.
            assert!(
                (loss - c.loss).abs() <= 1e-5 * c.loss.abs() + 2e-7,
                "loss {loss} vs {}",
                c.loss
            );
            stopped += (c.n_used < ray.n as usize) as u32;
            let scale = want[r.clone()]
                .iter()
                .flatten()
                .fold(0.0f32, |m, &v| m.max(v.abs()));
            for j in r {
                for ch in 0..4 {
                    let (g, w) = (d_raw[j][ch], want[j][ch]);
                    assert!(
                        (g - w).abs() <= 1e-4 * scale + 1e-12,
                        "sample {j} channel {ch}: GPU {g} vs CPU {w} (ray scale {scale})"
                    );
                }
                if j < ray.start as usize + c.n_used {
                    let outside = !marcher.in_cascade0(b.pos[j]);
                    pulled += (b.raw[j][3] < 0.0 && !outside) as u32;
                    pushed += (b.raw[j][3] > -10.0 && b.dist[j] < NEAR_DISTANCE) as u32;
                }
            }
        }
        // The batch reaches every branch.
        assert!(
            stopped > 100 && pulled > 100 && pushed > 100,
            "{stopped} {pulled} {pushed}"
        );
    }

    #[test]
    fn bad_batches_are_errors() {
        let Some(ctx) = test_context() else { return };
        let k = LossKernel::new(ctx).unwrap();
        let cfg = LossConfig::new(&Marcher::new(1), 1.0, 0.0);
        let ray = GpuRay {
            start: 1,
            n: 2,
            bg: [0.0; 3],
            target: [0.0; 3],
        };
        let (raw, dist, pos) = ([[0.0f32; 4]; 2], [0.1f32; 2], [[0.5f32; 3]; 2]);
        let past = [ray];
        let r = k.run_host(
            ctx,
            &HostBatch {
                rays: &past,
                raw: &raw,
                dt: &dist,
                dist: &dist,
                pos: &pos,
            },
            &cfg,
        );
        assert!(
            matches!(r, Err(GpuError::Input(_))),
            "a ray past the samples"
        );
        let r = k.run_host(
            ctx,
            &HostBatch {
                rays: &[],
                raw: &raw,
                dt: &dist[..1],
                dist: &dist,
                pos: &pos,
            },
            &cfg,
        );
        assert!(matches!(r, Err(GpuError::Input(_))), "lengths differ");
        let empty = HostBatch {
            rays: &[],
            raw: &[],
            dt: &[],
            dist: &[],
            pos: &[],
        };
        let (d, per_ray) = k.run_host(ctx, &empty, &cfg).unwrap();
        assert!(d.is_empty() && per_ray.is_empty());
    }
}
