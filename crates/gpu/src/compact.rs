//! Compaction of a training batch to the samples that reach the loss (`compact.wgsl`), so
//! that the colour network, the loss and the backward run on those alone. instant-ngp runs
//! the whole network over every marched sample and compacts in its loss kernel; where a
//! ray's transmittance stops depends on the densities alone, so here the density network
//! runs over the marched samples, this kernel finds each ray's stop from them and compacts,
//! and the training pass's forward gives the loss its colours: the same samples and the
//! same gradient, without the colour network on the samples past the stops (three of four
//! on lego at 800 px).
//!
//! The compacted order is the order in which the device's invocations reach the counter;
//! every sample keeps its own values, so the gradient is the same sum in another order.

use super::{GpuContext, GpuError, GpuResult, auto_layout_pipelines, buffer_entry, device_buffer};
use ngp::render::composite::TRAIN_MIN_TRANSMITTANCE;
use wgpu::util::DeviceExt;

const COMPACT_WGSL: &str = include_str!("compact.wgsl");
const WORKGROUP: u32 = 64;

/// `GpuRay::n` of a ray that did not fit the capacity: the loss leaves its `(0, used)`.
pub const SKIP: u32 = u32::MAX;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct CompactParams {
    n_rays: u32,
    row_width: u32,
    capacity: u32,
    min_transmittance: f32,
}

/// What the compaction reads: the batch's rays (`GpuRay`), the marched samples'
/// log-densities, steps, distances and positions, the rays as drawn (`GenRay`, 16 words a
/// ray: the direction at words 4..7, which every compacted sample of the ray gets); and
/// where it writes each ray's `(0, used)` (the loss fills in the loss).
pub struct CompactInputs<'a> {
    pub rays: &'a wgpu::Buffer,
    pub log_density: &'a wgpu::Buffer,
    pub dt: &'a wgpu::Buffer,
    pub dist: &'a wgpu::Buffer,
    pub pos: &'a wgpu::Buffer,
    pub drawn: &'a wgpu::Buffer,
    pub ray_out: &'a wgpu::Buffer,
}

/// The compacted samples (positions, directions, steps, distances, marched indices; `d_raw`
/// for the loss's gradient), each ray's compacted range (`rays`, a `GpuRay` a ray: `n` is
/// [`SKIP`] for a ray that did not fit), and the counters: `[0]` slots asked for, `[1]`
/// samples written, `[2]` rays that did not fit, `[3]` the whole network's forward passes
/// over the compacted samples ([`Self::record_forward_passes`]).
pub struct Compacted {
    pub pos: wgpu::Buffer,
    pub dirs: wgpu::Buffer,
    pub dt: wgpu::Buffer,
    pub dist: wgpu::Buffer,
    /// Each compacted sample's index among the marched ones (u32).
    pub from: wgpu::Buffer,
    pub d_raw: wgpu::Buffer,
    pub rays: wgpu::Buffer,
    pub counters: wgpu::Buffer,
    /// 1 and 2, for [`Self::record_forward_passes`].
    pass_counts: wgpu::Buffer,
    capacity: u32,
    max_rays: u32,
    pipeline: wgpu::ComputePipeline,
    uniform: wgpu::Buffer,
}

impl Compacted {
    /// Buffers for `capacity` compacted samples of up to `max_rays` rays.
    pub fn new(ctx: &GpuContext, capacity: u32, max_rays: u32) -> GpuResult<Compacted> {
        let c = capacity as u64;
        super::check_binding(ctx, "compacted gradients", 16 * c)?;
        ctx.scoped("compaction", || {
            let [pipeline] =
                auto_layout_pipelines(ctx, "compact.wgsl", COMPACT_WGSL, ["compact_main"]);
            Compacted {
                pos: device_buffer(ctx, "compacted positions", 12 * c),
                dirs: device_buffer(ctx, "compacted directions", 12 * c),
                dt: device_buffer(ctx, "compacted steps", 4 * c),
                dist: device_buffer(ctx, "compacted distances", 4 * c),
                from: device_buffer(ctx, "compacted samples' marched indices", 4 * c),
                d_raw: device_buffer(ctx, "compacted gradients", 16 * c),
                rays: device_buffer(ctx, "compacted rays", 32 * max_rays.max(1) as u64),
                counters: device_buffer(ctx, "compaction counters", 16),
                pass_counts: ctx
                    .device
                    .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                        label: Some("forward passes"),
                        contents: bytemuck::cast_slice(&[1u32, 2]),
                        usage: wgpu::BufferUsages::COPY_SRC,
                    }),
                capacity,
                max_rays,
                pipeline,
                uniform: ctx.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("compaction params"),
                    size: std::mem::size_of::<CompactParams>() as u64,
                    usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                }),
            }
        })
    }

    pub fn capacity(&self) -> u32 {
        self.capacity
    }

    /// Records, after the compaction, that the whole network runs `passes` (1 or 2) forward
    /// passes over the compacted samples: counter `[3]`, read back with the others.
    pub fn record_forward_passes(&self, encoder: &mut wgpu::CommandEncoder, passes: u32) {
        let at = 4 * (passes.clamp(1, 2) - 1) as u64;
        encoder.copy_buffer_to_buffer(&self.pass_counts, at, &self.counters, 12, 4);
    }

    /// Records the compaction of `n_rays` rays into `encoder` (the counters cleared first).
    /// The uniform is written at once: one compaction per submission.
    pub fn encode(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        inputs: &CompactInputs,
        n_rays: u32,
    ) -> GpuResult<()> {
        self.encode_within(ctx, encoder, inputs, n_rays, self.capacity)
    }

    /// [`Self::encode`] into the first `capacity` slots (at most the buffers'): a ray whose
    /// samples would end past them trains nothing and is counted.
    pub fn encode_within(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        inputs: &CompactInputs,
        n_rays: u32,
        capacity: u32,
    ) -> GpuResult<()> {
        if capacity > self.capacity {
            return Err(GpuError::Input(format!(
                "compaction into {capacity} slots of {}",
                self.capacity
            )));
        }
        if n_rays > self.max_rays
            || inputs.rays.size() < 32 * n_rays as u64
            || inputs.drawn.size() < 64 * n_rays as u64
            || inputs.ray_out.size() < 8 * n_rays as u64
        {
            return Err(GpuError::Input(format!(
                "compaction of {n_rays} rays (at most {}): ray buffers of {}, {} and {} bytes",
                self.max_rays,
                inputs.rays.size(),
                inputs.drawn.size(),
                inputs.ray_out.size()
            )));
        }
        encoder.clear_buffer(&self.counters, 0, None);
        if n_rays == 0 {
            return Ok(());
        }
        let max_dim = ctx.device.limits().max_compute_workgroups_per_dimension;
        let groups = n_rays.div_ceil(WORKGROUP);
        let gx = groups.min(max_dim);
        let params = CompactParams {
            n_rays,
            row_width: gx * WORKGROUP,
            capacity,
            min_transmittance: TRAIN_MIN_TRANSMITTANCE,
        };
        ctx.scoped("compaction dispatch", || {
            ctx.queue
                .write_buffer(&self.uniform, 0, bytemuck::bytes_of(&params));
            let bg = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("compaction"),
                layout: &self.pipeline.get_bind_group_layout(0),
                entries: &[
                    buffer_entry(0, inputs.rays),
                    buffer_entry(1, inputs.log_density),
                    buffer_entry(2, inputs.dt),
                    buffer_entry(3, inputs.dist),
                    buffer_entry(4, inputs.pos),
                    buffer_entry(5, inputs.drawn),
                    buffer_entry(6, &self.rays),
                    buffer_entry(7, inputs.ray_out),
                    buffer_entry(8, &self.pos),
                    buffer_entry(9, &self.dirs),
                    buffer_entry(10, &self.dt),
                    buffer_entry(11, &self.dist),
                    buffer_entry(12, &self.counters),
                    buffer_entry(13, &self.uniform),
                    buffer_entry(14, &self.from),
                ],
            });
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(gx, groups.div_ceil(gx), 1);
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::loss::GpuRay;
    use crate::mlp::upload;

    /// Every used sample, and only those, lands in the compacted buffers with its own
    /// values, and each ray's compacted range holds exactly its used samples; a ray's stop
    /// is found from the log-densities alone (a sample thick enough to end the ray is the
    /// ray's last used one); a ray past the capacity is counted, marked, not cut.
    #[test]
    fn compaction_keeps_exactly_the_used_samples() {
        let Some(ctx) = crate::test_context() else {
            return;
        };
        let mut rng = ngp::rng::Pcg32::new(5, 1);
        let (mut rays, mut used) = (Vec::new(), Vec::new());
        let (mut log_density, mut dt) = (Vec::new(), Vec::new());
        let mut start = 0u32;
        for r in 0..300u32 {
            let n = rng.next_u32() % 12;
            // The ray stops after sample u - 1 (u = n: it never does).
            let u = if n == 0 { 0 } else { 1 + rng.next_u32() % n };
            for j in 0..n {
                // Thin (alpha ~ 1e-9) until the stop, opaque there, anything after.
                let thick = j + 1 == u && u < n;
                log_density.push(if thick {
                    8.0
                } else if j < u {
                    -20.0
                } else {
                    3.0
                });
                dt.push(0.01 + 0.01 * rng.next_f32());
            }
            rays.push(GpuRay {
                start,
                n,
                bg: [r as f32, 0.5, 0.25],
                target: [0.1, 0.2, r as f32],
            });
            used.push(u);
            start += n;
        }
        let n_samples = start as usize;
        let vals: Vec<f32> = (0..n_samples * 4).map(|_| rng.next_f32()).collect();
        let pos: Vec<f32> = vals[..3 * n_samples].to_vec();
        let dist: Vec<f32> = vals[3 * n_samples..].to_vec();
        // The rays as drawn (GenRay, 16 words): only the direction, words 4..7, is read.
        let drawn: Vec<f32> = (0..16 * rays.len()).map(|_| rng.next_f32()).collect();
        let want: u32 = used.iter().sum();
        for capacity in [want, want / 2] {
            let rays_b = ctx
                .device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: None,
                    contents: bytemuck::cast_slice(&rays),
                    usage: wgpu::BufferUsages::STORAGE,
                });
            let out_b = upload(ctx, "ray_out", &vec![7.0; 2 * rays.len()]).unwrap();
            let ld_b = upload(ctx, "log_density", &log_density).unwrap();
            let dt_b = upload(ctx, "dt", &dt).unwrap();
            let dist_b = upload(ctx, "dist", &dist).unwrap();
            let pos_b = upload(ctx, "pos", &pos).unwrap();
            let drawn_b = upload(ctx, "drawn", &drawn).unwrap();
            let c = Compacted::new(ctx, capacity, rays.len() as u32).unwrap();
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            let inputs = CompactInputs {
                rays: &rays_b,
                log_density: &ld_b,
                dt: &dt_b,
                dist: &dist_b,
                pos: &pos_b,
                drawn: &drawn_b,
                ray_out: &out_b,
            };
            c.encode(ctx, &mut enc, &inputs, rays.len() as u32).unwrap();
            ctx.queue.submit([enc.finish()]);
            let counters: Vec<u32> = ctx.read_buffer(&c.counters, 16).unwrap();
            let written = counters[1] as usize;
            assert_eq!(counters[0], want);
            let ray_out: Vec<[f32; 2]> = ctx.read_buffer(&out_b, 8 * rays.len() as u64).unwrap();
            let rays_c: Vec<GpuRay> = ctx.read_buffer(&c.rays, 32 * rays.len() as u64).unwrap();
            let got_pos: Vec<f32> = ctx.read_buffer(&c.pos, 12 * written as u64).unwrap();
            let got_dirs: Vec<f32> = ctx.read_buffer(&c.dirs, 12 * written as u64).unwrap();
            let got_dt: Vec<f32> = ctx.read_buffer(&c.dt, 4 * written as u64).unwrap();
            let got_dist: Vec<f32> = ctx.read_buffer(&c.dist, 4 * written as u64).unwrap();
            let mut seen = vec![false; written];
            let mut unfit = 0;
            for (r, ray) in rays.iter().enumerate() {
                let u = used[r];
                assert_eq!(ray_out[r], [0.0, f32::from_bits(u)], "ray {r}");
                let rc = rays_c[r];
                assert_eq!((rc.bg, rc.target), (ray.bg, ray.target), "ray {r}");
                if rc.n == SKIP {
                    unfit += 1;
                    assert!(u > 0 && capacity < want, "ray {r}");
                    continue;
                }
                assert_eq!(rc.n, u, "ray {r}");
                for j in 0..u as usize {
                    let (s, c) = (ray.start as usize + j, rc.start as usize + j);
                    assert!(c < written && !seen[c], "ray {r}: slot {c}");
                    seen[c] = true;
                    assert_eq!(got_pos[3 * c..3 * c + 3], pos[3 * s..3 * s + 3]);
                    assert_eq!(got_dirs[3 * c..3 * c + 3], drawn[16 * r + 4..16 * r + 7]);
                    assert_eq!((got_dt[c], got_dist[c]), (dt[s], dist[s]));
                }
            }
            assert!(
                seen.iter().all(|&s| s),
                "every written slot belongs to a ray"
            );
            assert_eq!(counters[2], unfit);
            if capacity == want {
                assert_eq!(unfit, 0);
            } else {
                assert!(unfit > 0 && written <= capacity as usize, "{counters:?}");
            }
        }
    }
}
