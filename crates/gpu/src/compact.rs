//! Compaction of a training batch to the samples that reach the loss (`compact.wgsl`), so
//! that the training pass runs on those alone, as instant-ngp trains: marching, then an
//! inference pass of the network over every marched sample, the loss (which finds where
//! each ray's transmittance stops and the gradient of the samples before), then this
//! kernel, then the grid and network forward keeping activations, and the backward, over
//! the compacted samples only.
//!
//! The compacted order is the order in which the device's invocations reach the counter;
//! every sample keeps its own values, so the gradient is the same sum in another order.

use super::{GpuContext, GpuError, GpuResult, auto_layout_pipelines, buffer_entry, device_buffer};

const COMPACT_WGSL: &str = include_str!("compact.wgsl");
const WORKGROUP: u32 = 64;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct CompactParams {
    n_rays: u32,
    row_width: u32,
    capacity: u32,
    _pad: u32,
}

/// What the compaction reads: the batch's rays (`GpuRay`), the loss kernel's per-ray
/// `(loss, used)` and per-sample gradient, and the marched samples' positions and
/// directions.
pub struct CompactInputs<'a> {
    pub rays: &'a wgpu::Buffer,
    pub ray_out: &'a wgpu::Buffer,
    pub pos: &'a wgpu::Buffer,
    pub dirs: &'a wgpu::Buffer,
    pub d_raw: &'a wgpu::Buffer,
}

/// The compacted samples (positions, directions, raw-output gradients) and the counters:
/// `[0]` slots asked for, `[1]` samples written, `[2]` rays that did not fit.
pub struct Compacted {
    pub pos: wgpu::Buffer,
    pub dirs: wgpu::Buffer,
    pub d_raw: wgpu::Buffer,
    pub counters: wgpu::Buffer,
    capacity: u32,
    pipeline: wgpu::ComputePipeline,
    uniform: wgpu::Buffer,
}

impl Compacted {
    /// Buffers for `capacity` compacted samples.
    pub fn new(ctx: &GpuContext, capacity: u32) -> GpuResult<Compacted> {
        let c = capacity as u64;
        super::check_binding(ctx, "compacted gradients", 16 * c)?;
        ctx.scoped("compaction", || {
            let [pipeline] =
                auto_layout_pipelines(ctx, "compact.wgsl", COMPACT_WGSL, ["compact_main"]);
            Compacted {
                pos: device_buffer(ctx, "compacted positions", 12 * c),
                dirs: device_buffer(ctx, "compacted directions", 12 * c),
                d_raw: device_buffer(ctx, "compacted gradients", 16 * c),
                counters: device_buffer(ctx, "compaction counters", 16),
                capacity,
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
        if inputs.rays.size() < 32 * n_rays as u64 || inputs.ray_out.size() < 8 * n_rays as u64 {
            return Err(GpuError::Input(format!(
                "compaction of {n_rays} rays: ray buffers of {} and {} bytes",
                inputs.rays.size(),
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
            _pad: 0,
        };
        ctx.scoped("compaction dispatch", || {
            ctx.queue
                .write_buffer(&self.uniform, 0, bytemuck::bytes_of(&params));
            let bg = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("compaction"),
                layout: &self.pipeline.get_bind_group_layout(0),
                entries: &[
                    buffer_entry(0, inputs.rays),
                    buffer_entry(1, inputs.ray_out),
                    buffer_entry(2, inputs.pos),
                    buffer_entry(3, inputs.dirs),
                    buffer_entry(4, inputs.d_raw),
                    buffer_entry(5, &self.pos),
                    buffer_entry(6, &self.dirs),
                    buffer_entry(7, &self.d_raw),
                    buffer_entry(8, &self.counters),
                    buffer_entry(9, &self.uniform),
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
    use wgpu::util::DeviceExt;

    /// Every used sample, and only those, lands in the compacted buffers with its own
    /// values; a ray past the capacity is counted, not cut.
    #[test]
    fn compaction_keeps_exactly_the_used_samples() {
        let Some(ctx) = crate::test_context() else {
            return;
        };
        let mut rng = ngp::rng::Pcg32::new(5, 1);
        let mut rays = Vec::new();
        let mut used = Vec::new();
        let mut start = 0u32;
        for _ in 0..300 {
            let n = rng.next_u32() % 12;
            let u = if n == 0 { 0 } else { rng.next_u32() % (n + 1) };
            rays.push(GpuRay {
                start,
                n,
                bg: [0.0; 3],
                target: [0.0; 3],
            });
            used.push([0.5f32, f32::from_bits(u)]);
            start += n;
        }
        let n_samples = start as usize;
        let vals: Vec<f32> = (0..n_samples * 10).map(|_| rng.next_f32()).collect();
        let pos: Vec<f32> = vals[..3 * n_samples].to_vec();
        let dirs: Vec<f32> = vals[3 * n_samples..6 * n_samples].to_vec();
        let d_raw: Vec<f32> = vals[6 * n_samples..].to_vec();
        let want: u32 = used.iter().map(|u| u[1].to_bits()).sum();
        for capacity in [want, want / 2] {
            let rays_b = ctx
                .device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: None,
                    contents: bytemuck::cast_slice(&rays),
                    usage: wgpu::BufferUsages::STORAGE,
                });
            let out_b = upload(ctx, "ray_out", bytemuck::cast_slice(&used)).unwrap();
            let pos_b = upload(ctx, "pos", &pos).unwrap();
            let dirs_b = upload(ctx, "dirs", &dirs).unwrap();
            let d_b = upload(ctx, "d_raw", &d_raw).unwrap();
            let c = Compacted::new(ctx, capacity).unwrap();
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            let inputs = CompactInputs {
                rays: &rays_b,
                ray_out: &out_b,
                pos: &pos_b,
                dirs: &dirs_b,
                d_raw: &d_b,
            };
            c.encode(ctx, &mut enc, &inputs, rays.len() as u32).unwrap();
            ctx.queue.submit([enc.finish()]);
            let counters: Vec<u32> = ctx.read_buffer(&c.counters, 16).unwrap();
            let written = counters[1] as usize;
            assert_eq!(counters[0], want);
            let got_pos: Vec<f32> = ctx.read_buffer(&c.pos, 12 * written as u64).unwrap();
            let got_dirs: Vec<f32> = ctx.read_buffer(&c.dirs, 12 * written as u64).unwrap();
            let got_d: Vec<f32> = ctx.read_buffer(&c.d_raw, 16 * written as u64).unwrap();
            let key = |p: &[f32], d: &[f32], g: &[f32]| {
                let mut k: Vec<u32> = p.iter().chain(d).chain(g).map(|x| x.to_bits()).collect();
                k.shrink_to_fit();
                k
            };
            let mut got: Vec<Vec<u32>> = (0..written)
                .map(|i| {
                    key(
                        &got_pos[3 * i..3 * i + 3],
                        &got_dirs[3 * i..3 * i + 3],
                        &got_d[4 * i..4 * i + 4],
                    )
                })
                .collect();
            // The used samples of every ray (the rays that fit, when the capacity binds).
            let mut all: Vec<Vec<u32>> = Vec::new();
            for (ray, u) in rays.iter().zip(&used) {
                for j in 0..u[1].to_bits() {
                    let s = (ray.start + j) as usize;
                    all.push(key(
                        &pos[3 * s..3 * s + 3],
                        &dirs[3 * s..3 * s + 3],
                        &d_raw[4 * s..4 * s + 4],
                    ));
                }
            }
            got.sort();
            all.sort();
            if capacity == want {
                assert_eq!(counters[2], 0);
                assert_eq!(got, all);
            } else {
                assert!(counters[2] > 0, "{counters:?}");
                assert!(written <= capacity as usize);
                // Whole rays: every compacted sample is a used one, none twice.
                got.dedup();
                assert_eq!(got.len(), written);
                assert!(got.iter().all(|k| all.binary_search(k).is_ok()));
            }
        }
    }
}
