//! Whether the adapter's `fma` is fused, as the CPU's `mul_add` is.
//!
//! The grid chooses each sample's cell from `fma(scale, x, 0.5)`, and the index must stay
//! bit-identical to the CPU's; WGSL promises `fma` only the accuracy of a multiply and an
//! add, and llvmpipe rounds twice. So `grid.wgsl` computes that one fma exactly in
//! integers (some fifty operations a coordinate) unless this probe shows the adapter's
//! `fma` fused: it runs the builtin on grid-like inputs (scales of the levels' range,
//! positions in [0, 1)) chosen where rounding twice gives another float than rounding once,
//! and on random ones, and compares every result's bits with the CPU's `mul_add`. An
//! adapter that rounded the product first would miss every one of the first kind.

use super::{GpuContext, GpuResult, auto_layout_pipelines, buffer_entry};
use ngp::rng::Pcg32;
use wgpu::util::DeviceExt;

const PROBE_WGSL: &str = "
@group(0) @binding(0) var<storage, read_write> cases: array<u32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= arrayLength(&cases) / 3u) {
        return;
    }
    let s = bitcast<f32>(cases[3u * i]);
    let x = bitcast<f32>(cases[3u * i + 1u]);
    cases[3u * i + 2u] = bitcast<u32>(fma(s, x, 0.5));
}
";

/// Cases of each kind.
const CASES: usize = 1024;

/// The probe's inputs: `(scale, x)` pairs where `RN(RN(s·x) + 0.5) ≠ RN(s·x + 0.5)`, then
/// random ones. Scales span a grid's levels (resolution − 1 from 15 to 2048 × a box of
/// 128); deterministic.
pub fn probe_cases() -> Vec<(f32, f32)> {
    let mut rng = Pcg32::new(0x0066_6d61, 1);
    let mut apart = Vec::with_capacity(CASES);
    let mut random = Vec::with_capacity(CASES);
    while apart.len() < CASES || random.len() < CASES {
        let s = (15.0f32 * (rng.next_f32() * 14.0).exp2()).floor();
        let x = rng.next_f32();
        if s.mul_add(x, 0.5) != s * x + 0.5 {
            if apart.len() < CASES {
                apart.push((s, x));
            }
        } else if random.len() < CASES {
            random.push((s, x));
        }
    }
    apart.extend(random);
    apart
}

/// Runs the probe on `ctx`: true when every case's `fma(s, x, 0.5)` has the bits of the
/// CPU's `s.mul_add(x, 0.5)`.
pub fn fma_is_fused(ctx: &GpuContext) -> GpuResult<bool> {
    let cases = probe_cases();
    let words: Vec<u32> = cases
        .iter()
        .flat_map(|&(s, x)| [s.to_bits(), x.to_bits(), 0])
        .collect();
    let buffer = ctx.scoped("fma probe", || {
        let [pipeline] = auto_layout_pipelines(ctx, "fma probe", PROBE_WGSL, ["main"]);
        let buffer = ctx
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("fma probe cases"),
                contents: bytemuck::cast_slice(&words),
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            });
        let bind_group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("fma probe"),
            layout: &pipeline.get_bind_group_layout(0),
            entries: &[buffer_entry(0, &buffer)],
        });
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&pipeline);
            pass.set_bind_group(0, &bind_group, &[]);
            pass.dispatch_workgroups((cases.len() as u32).div_ceil(64), 1, 1);
        }
        ctx.queue.submit([encoder.finish()]);
        buffer
    })?;
    let got: Vec<u32> = ctx.read_buffer(&buffer, 4 * words.len() as u64)?;
    Ok(cases
        .iter()
        .enumerate()
        .all(|(i, &(s, x))| got[3 * i + 2] == s.mul_add(x, 0.5).to_bits()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cases_tell_one_rounding_from_two() {
        let cases = probe_cases();
        assert_eq!(cases.len(), 2 * CASES);
        let apart = cases[..CASES]
            .iter()
            .filter(|&&(s, x)| s.mul_add(x, 0.5) != s * x + 0.5)
            .count();
        assert_eq!(apart, CASES);
        assert!(
            cases
                .iter()
                .all(|&(s, x)| (15.0..=2048.0 * 128.0).contains(&s) && (0.0..1.0).contains(&x))
        );
    }

    /// The context keeps the probe's answer and the grid compiles its cells from it
    /// (`grid::tests::the_cell_fma_is_rounded_once` checks the cells on either path).
    #[test]
    fn the_grid_takes_the_probes_answer() {
        let Some(ctx) = crate::test_context() else {
            return;
        };
        let fused = fma_is_fused(ctx).unwrap();
        eprintln!("{}: fma fused: {fused}", ctx.report());
        assert_eq!(ctx.fma_fused().unwrap(), fused);
        let layout = ngp::encoding::GridLayout::new(Default::default(), 1).unwrap();
        let g = crate::GridEncoding::new(ctx, &layout, crate::GradAtomics::Auto).unwrap();
        assert_eq!(g.hardware_fma(), fused);
        if ctx.report().software {
            // llvmpipe rounds the product first (Mesa 22.3): CI runs the exact emulation.
            assert!(!fused);
        }
    }
}
