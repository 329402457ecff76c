//! Rendering's compositing on the device (`composite.wgsl`): rays keep their running colour,
//! depth and transmittance across waves of samples, as `render_image` keeps them on the CPU,
//! and finish over the background into pixels (rgb, opacity, depth).

use super::{
    GpuContext, GpuError, GpuResult, buffer_entry, device_buffer, shared_layout_pipelines,
};
use wgpu::util::DeviceExt;

const COMPOSITE_WGSL: &str = include_str!("composite.wgsl");
const WORKGROUP: u32 = 64;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct CompositeParams {
    n_rays: u32,
    row_width: u32,
    min_transmittance: f32,
    _pad: u32,
    background: [f32; 4],
}

/// The running state of `n_rays` rays and their pixels, on the device.
pub struct RayState {
    n_rays: u32,
    /// Per ray: Σ w·c (rgb), Σ w·t (vec4).
    pub acc: wgpu::Buffer,
    /// Per ray: transmittance (f32), 1 at the start.
    pub trans: wgpu::Buffer,
    /// Per ray after [`CompositeKernel::encode_finish`]: rgb over the background, opacity.
    pub pixel_rgba: wgpu::Buffer,
    /// Per ray: expected distance of what it hit (0 where it hit nothing).
    pub pixel_depth: wgpu::Buffer,
}

/// One wave's samples: ray r's are `wave[r].0 .. wave[r].0 + wave[r].1` (u32 pairs) of
/// `raw` (vec4: raw rgb, log-density), `dt` and `dist` (f32).
#[derive(Clone, Copy)]
pub struct WaveSamples<'a> {
    pub wave: &'a wgpu::Buffer,
    pub raw: &'a wgpu::Buffer,
    pub dt: &'a wgpu::Buffer,
    pub dist: &'a wgpu::Buffer,
}

pub struct CompositeKernel {
    composite: wgpu::ComputePipeline,
    finish: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    dummy: wgpu::Buffer,
}

impl CompositeKernel {
    pub fn new(ctx: &GpuContext) -> GpuResult<CompositeKernel> {
        ctx.scoped("composite kernel", || {
            let (layout, p) = shared_layout_pipelines(
                ctx,
                "composite.wgsl",
                COMPOSITE_WGSL,
                8,
                |b| (2..6).contains(&b),
                false,
                &["composite_main", "finish_main"],
            );
            let [composite, finish] =
                <[wgpu::ComputePipeline; 2]>::try_from(p).expect("two entry points");
            CompositeKernel {
                composite,
                finish,
                layout,
                dummy: device_buffer(ctx, "composite unused", 16),
            }
        })
    }

    /// Fresh state for `n_rays` rays: nothing accumulated, transmittance 1.
    pub fn state(&self, ctx: &GpuContext, n_rays: u32) -> GpuResult<RayState> {
        if n_rays == 0 {
            return Err(GpuError::Input("composite: 0 rays".into()));
        }
        let n = n_rays as u64;
        ctx.scoped("composite state", || RayState {
            n_rays,
            acc: device_buffer(ctx, "ray colour", 16 * n),
            trans: ctx
                .device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some("ray transmittance"),
                    contents: bytemuck::cast_slice(&vec![1.0f32; n_rays as usize]),
                    usage: wgpu::BufferUsages::STORAGE
                        | wgpu::BufferUsages::COPY_SRC
                        | wgpu::BufferUsages::COPY_DST,
                }),
            pixel_rgba: device_buffer(ctx, "pixel rgba", 16 * n),
            pixel_depth: device_buffer(ctx, "pixel depth", 4 * n),
        })
    }

    #[allow(clippy::too_many_arguments)]
    fn encode(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        pipeline: &wgpu::ComputePipeline,
        state: &RayState,
        samples: [&wgpu::Buffer; 4],
        min_transmittance: f32,
        background: [f32; 3],
    ) -> GpuResult<()> {
        let max_dim = ctx.device.limits().max_compute_workgroups_per_dimension;
        let groups = state.n_rays.div_ceil(WORKGROUP);
        let gx = groups.min(max_dim);
        let params = CompositeParams {
            n_rays: state.n_rays,
            row_width: gx * WORKGROUP,
            min_transmittance,
            _pad: 0,
            background: [background[0], background[1], background[2], 0.0],
        };
        ctx.scoped("composite", || {
            // A uniform of its own per pass: several waves go into one submission.
            let uniform = ctx
                .device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some("composite params"),
                    contents: bytemuck::bytes_of(&params),
                    usage: wgpu::BufferUsages::UNIFORM,
                });
            let [wave, raw, dt, dist] = samples;
            let bg = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("composite"),
                layout: &self.layout,
                entries: &[
                    buffer_entry(0, &state.acc),
                    buffer_entry(1, &state.trans),
                    buffer_entry(2, wave),
                    buffer_entry(3, raw),
                    buffer_entry(4, dt),
                    buffer_entry(5, dist),
                    buffer_entry(6, &state.pixel_rgba),
                    buffer_entry(7, &state.pixel_depth),
                    buffer_entry(8, &uniform),
                ],
            });
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(gx, groups.div_ceil(gx), 1);
        })
    }

    /// Records one wave: ray r composites its samples of the wave from its running state,
    /// and stops below `min_transmittance`.
    pub fn encode_wave(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        state: &RayState,
        samples: &WaveSamples,
        min_transmittance: f32,
    ) -> GpuResult<()> {
        let WaveSamples {
            wave,
            raw,
            dt,
            dist,
        } = *samples;
        if wave.size() < 8 * state.n_rays as u64 {
            return Err(GpuError::Input(format!(
                "composite: {} bytes of wave records for {} rays",
                wave.size(),
                state.n_rays
            )));
        }
        self.encode(
            ctx,
            encoder,
            &self.composite,
            state,
            [wave, raw, dt, dist],
            min_transmittance,
            [0.0; 3],
        )
    }

    /// Records the pixels: what each ray accumulated over `background`.
    pub fn encode_finish(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        state: &RayState,
        background: [f32; 3],
    ) -> GpuResult<()> {
        let d = &self.dummy;
        self.encode(
            ctx,
            encoder,
            &self.finish,
            state,
            [d, d, d, d],
            0.0,
            background,
        )
    }

    /// (rgb + opacity, depth) of the first `n_rays` rays, read back with one wait.
    #[allow(clippy::type_complexity)]
    pub fn read(
        &self,
        ctx: &GpuContext,
        state: &RayState,
        n_rays: u32,
    ) -> GpuResult<(Vec<[f32; 4]>, Vec<f32>)> {
        if n_rays > state.n_rays {
            return Err(GpuError::Input(format!(
                "composite: {n_rays} rays read of {}",
                state.n_rays
            )));
        }
        let n = n_rays as u64;
        let [rgba, depth]: [Vec<u8>; 2] = ctx
            .read_buffers(&[(&state.pixel_rgba, 16 * n), (&state.pixel_depth, 4 * n)])?
            .try_into()
            .map_err(|_| GpuError::Device {
                what: "composite",
                msg: "a read of two buffers gave another count".into(),
            })?;
        Ok((
            bytemuck::pod_collect_to_vec(&rgba),
            bytemuck::pod_collect_to_vec(&depth),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_context;
    use ngp::render::composite::composite;
    use ngp::rng::Pcg32;

    /// 2000 rays of 0 to 40 samples, from empty to opaque, composited in waves of up to 8
    /// samples (all waves in one submission) against the CPU renderer's loop over
    /// `composite`: colour and opacity within 2e-6, depth within 5e-5 relative (the CPU
    /// sums a wave before adding it to the ray; the device adds sample by sample, and exp
    /// and division are not correctly rounded).
    #[test]
    fn waves_match_the_cpu_renderer() {
        let Some(ctx) = test_context() else { return };
        let mut r = Pcg32::new(12, 1);
        let n_rays = 2000usize;
        let (mut raw, mut dt, mut dist) = (Vec::new(), Vec::new(), Vec::new());
        let mut rays = Vec::new(); // (start, n)
        for _ in 0..n_rays {
            let n = r.below(41) as usize;
            let opacity = r.next_f32() * 8.0 - 5.0;
            rays.push((raw.len(), n));
            let mut t = 0.5 + r.next_f32();
            for _ in 0..n {
                let step = 0.002 + r.next_f32() * 0.03;
                raw.push([
                    r.next_f32() * 6.0 - 3.0,
                    r.next_f32() * 6.0 - 3.0,
                    r.next_f32() * 6.0 - 3.0,
                    opacity + r.next_f32() * 4.0 - 2.0,
                ]);
                dt.push(step);
                dist.push(t);
                t += step;
            }
        }
        let (min_t, bg) = (1e-4f32, [0.2f32, 0.5, 1.0]);
        let upload = |label: &str, bytes: &[u8]| {
            ctx.device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents: bytes,
                    usage: wgpu::BufferUsages::STORAGE,
                })
        };
        let (b_raw, b_dt, b_dist) = (
            upload("raw", bytemuck::cast_slice(&raw)),
            upload("dt", bytemuck::cast_slice(&dt)),
            upload("dist", bytemuck::cast_slice(&dist)),
        );
        let k = CompositeKernel::new(ctx).unwrap();
        let state = k.state(ctx, n_rays as u32).unwrap();
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        let mut cpu = vec![([0.0f32; 3], 0.0f32, 1.0f32); n_rays];
        let mut waves = Vec::new();
        for w in 0..5 {
            let records: Vec<[u32; 2]> = rays
                .iter()
                .map(|&(start, n)| {
                    let a = (8 * w).min(n);
                    [(start + a) as u32, ((8 * (w + 1)).min(n) - a) as u32]
                })
                .collect();
            for (ray, rec) in cpu.iter_mut().zip(&records) {
                let s = rec[0] as usize..(rec[0] + rec[1]) as usize;
                let c = composite(&raw[s.clone()], &dt[s.clone()], &dist[s], ray.2, min_t);
                for ch in 0..3 {
                    ray.0[ch] += c.rgb[ch];
                }
                ray.1 += c.depth;
                ray.2 = c.transmittance;
            }
            let wave = upload("wave", bytemuck::cast_slice(&records));
            let samples = WaveSamples {
                wave: &wave,
                raw: &b_raw,
                dt: &b_dt,
                dist: &b_dist,
            };
            k.encode_wave(ctx, &mut encoder, &state, &samples, min_t)
                .unwrap();
            waves.push(wave);
        }
        k.encode_finish(ctx, &mut encoder, &state, bg).unwrap();
        ctx.queue.submit([encoder.finish()]);
        let (rgba, depth) = k.read(ctx, &state, state.n_rays).unwrap();
        let mut stopped = 0;
        for (i, &(rgb, d, tr)) in cpu.iter().enumerate() {
            let a = 1.0 - tr;
            for ch in 0..3 {
                let want = rgb[ch] + tr * bg[ch];
                assert!(
                    (rgba[i][ch] - want).abs() <= 2e-6,
                    "ray {i} channel {ch}: {} vs {want}",
                    rgba[i][ch]
                );
            }
            assert!((rgba[i][3] - a).abs() <= 2e-6, "ray {i} opacity");
            let want = if a > 0.0 { d / a } else { 0.0 };
            // Depth is a sum over the ray divided by its opacity: its error grows as 1/a.
            assert!(
                (depth[i] - want).abs() <= 5e-5 * want.abs() + 2e-6 / a.max(1e-6),
                "ray {i} depth {} vs {want} (opacity {a})",
                depth[i]
            );
            stopped += (tr < min_t) as u32;
        }
        assert!(stopped > 50, "{stopped} rays became opaque");
    }

    #[test]
    fn bad_inputs_are_errors() {
        let Some(ctx) = test_context() else { return };
        let k = CompositeKernel::new(ctx).unwrap();
        assert!(k.state(ctx, 0).is_err());
        let state = k.state(ctx, 100).unwrap();
        let short = device_buffer(ctx, "short", 16);
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        let s = &short;
        let samples = WaveSamples {
            wave: s,
            raw: s,
            dt: s,
            dist: s,
        };
        let r = k.encode_wave(ctx, &mut encoder, &state, &samples, 1e-4);
        assert!(matches!(r, Err(GpuError::Input(_))));
    }
}
