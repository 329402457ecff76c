//! Sample counts known only on the device (issue 29): a kernel that wrote a count (marching,
//! compaction) leaves it in a counter buffer, and the passes after it take their sample
//! count and their workgroup counts from there instead of from the host, so a training step
//! is recorded whole without reading anything back.
//!
//! A [`DeviceCount`] is one such count: `n = min(max(src[i] − base, 0), max)` (a chunk of a
//! count: the samples from `base` on, at most `max`), computed by a one-invocation kernel
//! into its own buffer, with the indirect dispatch arguments of each consumer ([`Slot`]):
//! `⌈n / divisor⌉` workgroups folded into rows of at most `max_x` (or `fixed_x` columns and
//! the count in y), `z` deep. A consumer copies `n` into its parameters with
//! [`DeviceCount::copy_n`] (the kernels keep their sample count as the first word of their
//! uniform) and dispatches with [`DeviceCount::dispatch`]: a count of 0 dispatches nothing.

use super::{GpuContext, GpuError, GpuResult, auto_layout_pipelines, buffer_entry as entry};
use wgpu::util::DeviceExt;

const COUNT_WGSL: &str = "
struct CountParams {
    src: u32,
    base: u32,
    max: u32,
    n_slots: u32,
    // Per slot: divisor, max_x, z, fixed_x (0: x from the count).
    slots: array<vec4<u32>, 4>,
}
@group(0) @binding(0) var<storage, read> src: array<u32>;
@group(0) @binding(1) var<storage, read_write> out: array<u32>;
@group(0) @binding(2) var<uniform> p: CountParams;

@compute @workgroup_size(1)
fn count_main() {
    let v = src[p.src];
    var n = 0u;
    if (v > p.base) {
        n = min(v - p.base, p.max);
    }
    out[0] = n;
    for (var j = 0u; j < p.n_slots; j++) {
        let s = p.slots[j];
        let groups = (n + s.x - 1u) / s.x;
        var x = 0u;
        var y = 0u;
        if (groups > 0u) {
            if (s.w != 0u) {
                x = s.w;
                y = groups;
            } else {
                x = min(groups, s.y);
                y = (groups + s.y - 1u) / s.y;
            }
        }
        out[4u + 4u * j] = x;
        out[5u + 4u * j] = y;
        out[6u + 4u * j] = s.z;
    }
}
";

/// One consumer's dispatch shape.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Slot {
    /// Samples per workgroup (≥ 1).
    pub divisor: u32,
    /// Workgroups per row before folding into y.
    pub max_x: u32,
    /// Workgroups in z.
    pub z: u32,
    /// If not 0: x is this and the count goes to y.
    pub fixed_x: u32,
}

const MAX_SLOTS: usize = 4;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct CountParams {
    src: u32,
    base: u32,
    max: u32,
    n_slots: u32,
    slots: [[u32; 4]; MAX_SLOTS],
}

/// The counting kernel, compiled once for every [`DeviceCount`] made from it.
pub struct CountKernel {
    pipeline: wgpu::ComputePipeline,
}

impl CountKernel {
    pub fn new(ctx: &GpuContext) -> GpuResult<CountKernel> {
        ctx.scoped("device count kernel", || {
            let [pipeline] = auto_layout_pipelines(ctx, "count", COUNT_WGSL, ["count_main"]);
            CountKernel { pipeline }
        })
    }
}

/// A count read on the device from a counter buffer (see the module).
pub struct DeviceCount {
    pipeline: wgpu::ComputePipeline,
    group: wgpu::BindGroup,
    /// `[n, _, _, _]`, then per slot `[x, y, z, _]`: STORAGE | INDIRECT | COPY_SRC.
    buffer: wgpu::Buffer,
    slots: Vec<Slot>,
    max: u32,
}

impl DeviceCount {
    /// The count `min(max(src[index] − base, 0), max)` of the u32 counter buffer `src`,
    /// with dispatch arguments for `slots` (at most 4), run by `kernel`.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        ctx: &GpuContext,
        kernel: &CountKernel,
        src: &wgpu::Buffer,
        index: u32,
        base: u32,
        max: u32,
        slots: &[Slot],
    ) -> GpuResult<DeviceCount> {
        if slots.len() > MAX_SLOTS || slots.iter().any(|s| s.divisor == 0 || s.max_x == 0) {
            return Err(GpuError::Input(format!("device count slots {slots:?}")));
        }
        if u64::from(index) * 4 + 4 > src.size() {
            return Err(GpuError::Input(format!(
                "device count: word {index} of a {}-byte buffer",
                src.size()
            )));
        }
        let mut p = CountParams {
            src: index,
            base,
            max,
            n_slots: slots.len() as u32,
            slots: [[0; 4]; MAX_SLOTS],
        };
        for (d, s) in p.slots.iter_mut().zip(slots) {
            *d = [s.divisor, s.max_x, s.z, s.fixed_x];
        }
        ctx.scoped("device count", || {
            let d = &ctx.device;
            let pipeline = kernel.pipeline.clone();
            let uniform = d.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("device count params"),
                contents: bytemuck::bytes_of(&p),
                usage: wgpu::BufferUsages::UNIFORM,
            });
            let buffer = d.create_buffer(&wgpu::BufferDescriptor {
                label: Some("device count"),
                size: 16 * (1 + MAX_SLOTS as u64),
                usage: wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::INDIRECT
                    | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            });
            let group = d.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("device count"),
                layout: &pipeline.get_bind_group_layout(0),
                entries: &[entry(0, src), entry(1, &buffer), entry(2, &uniform)],
            });
            DeviceCount {
                pipeline,
                group,
                buffer,
                slots: slots.to_vec(),
                max,
            }
        })
    }

    /// The most the count can be: what the consumers' buffers must hold.
    pub fn max(&self) -> u32 {
        self.max
    }

    /// Records the kernel that reads the counter (after the pass that wrote it).
    pub fn encode(&self, encoder: &mut wgpu::CommandEncoder) {
        let mut pass = encoder.begin_compute_pass(&Default::default());
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.group, &[]);
        pass.dispatch_workgroups(1, 1, 1);
    }

    /// Records a copy of the count into the first word of `params` (COPY_DST).
    pub fn copy_n(&self, encoder: &mut wgpu::CommandEncoder, params: &wgpu::Buffer) {
        encoder.copy_buffer_to_buffer(&self.buffer, 0, params, 0, 4);
    }

    /// The slot index of `slot` in this count.
    pub fn slot(&self, slot: Slot) -> GpuResult<usize> {
        self.slots
            .iter()
            .position(|s| *s == slot)
            .ok_or_else(|| GpuError::Input(format!("device count has no slot {slot:?}")))
    }

    /// Dispatches the bound pipeline with slot `i`'s arguments.
    pub fn dispatch(&self, pass: &mut wgpu::ComputePass<'_>, i: usize) {
        pass.dispatch_workgroups_indirect(&self.buffer, 16 * (1 + i as u64));
    }

    /// The count buffer (`n` at byte 0), to copy from.
    pub fn buffer(&self) -> &wgpu::Buffer {
        &self.buffer
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_chunks_and_dispatch_shapes() {
        let Some(ctx) = crate::test_context() else {
            return;
        };
        let src = ctx
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: None,
                contents: bytemuck::cast_slice(&[7u32, 1000]),
                usage: wgpu::BufferUsages::STORAGE,
            });
        let slots = [
            Slot {
                divisor: 128,
                max_x: 3,
                z: 16,
                fixed_x: 0,
            },
            Slot {
                divisor: 64,
                max_x: 65535,
                z: 1,
                fixed_x: 80,
            },
        ];
        let kernel = CountKernel::new(ctx).unwrap();
        // Chunks of 300 samples of 1000 from 0, 300, 900 and past the end.
        for (base, n) in [(0u32, 300u32), (300, 300), (900, 100), (1000, 0), (1200, 0)] {
            let c = DeviceCount::new(ctx, &kernel, &src, 1, base, 300, &slots).unwrap();
            let mut e = ctx.device.create_command_encoder(&Default::default());
            c.encode(&mut e);
            ctx.queue.submit([e.finish()]);
            let got: Vec<u32> = ctx.read_buffer(c.buffer(), 48).unwrap();
            let g = n.div_ceil(128);
            let want_x = if g == 0 { 0 } else { g.min(3) };
            let want_y = if g == 0 { 0 } else { g.div_ceil(3) };
            let h = n.div_ceil(64);
            let (fx, fy) = if h == 0 { (0, 0) } else { (80, h) };
            assert_eq!(
                got,
                vec![n, 0, 0, 0, want_x, want_y, 16, 0, fx, fy, 1, 0],
                "base {base}"
            );
        }
        assert!(DeviceCount::new(ctx, &kernel, &src, 2, 0, 1, &slots).is_err());
    }
}
