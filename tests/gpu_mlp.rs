//! The GPU network after the grid (SH, density MLP, colour MLP; `crates/gpu/src/mlp.rs`) against
//! the CPU engine's `NerfNetwork`, on random encodings, directions, weights and output
//! gradients: forward, density only, weight gradients and the encoding's gradient.
//!
//! The GPU starts from the encoding the CPU's own `grid::forward` computes for random
//! positions (bit-identical input), so the CPU reference is `NerfNetwork` itself on those
//! positions, unchanged. Runs on whatever adapter `test_context` finds (lavapipe in CI).
//!
//! Tolerances: the kernels and the CPU (gemm) sum the same products in different orders and
//! with different fused multiply-adds, so results agree to f32 rounding of the sums, not
//! bit for bit. A dot product of k terms in f32 is off by at most ~k·2^-24 of Σ|terms| and
//! typically √k·2^-24; the network's outputs are O(1) with terms of similar size, so
//! forward outputs must agree to 1e-5·(1 + |cpu|) (64-term sums: ≤ 4e-6 worst case, per
//! layer, and three layers deep). Weight gradients sum 1000 samples' products: they must
//! agree to 1e-4 of the matrix's largest gradient (√1000·2^-24 ≈ 2e-6 of the summed
//! magnitudes, which here exceed the largest entry by up to ~20×). What is measured is
//! printed; a wrong index, transpose, mask or missing term is off by O(1) relative.

#![cfg(feature = "gpu")]

use stegongp::gpu::mlp::{upload, zeroed};
use stegongp::gpu::{EncodedBatch, GpuContext, GpuError, MlpKernels, test_context};
use stegongp::ngp::encoding::grid::{self, GridCache};
use stegongp::ngp::encoding::{GridConfig, reference_indices, sh};
use stegongp::ngp::network::ModelConfig;
use stegongp::ngp::network::mlp::{self, matrix_offset};
use stegongp::ngp::network::nerf::{CHUNK, NerfNetwork};
use stegongp::rng::Pcg32;

/// Samples: not a multiple of any tile (16/32/64) nor of the CPU's chunk (512) or the GPU's
/// gradient chunk (512), so every partial tile and chunk is exercised.
const N: usize = 1000;
/// The encoding's leading dimension, past N as a grid kernel's capacity would be.
const LD: usize = 1031;

/// A random problem and the CPU's view of it.
struct Case {
    net: NerfNetwork,
    params: Vec<f32>,
    pos: Vec<[f32; 3]>,
    dir: Vec<[f32; 3]>,
    /// `grid::forward` of `pos`: `n_enc` rows of `LD`.
    enc: Vec<f32>,
    cache: GridCache,
    d_out: Vec<[f32; 4]>,
}

fn small_config() -> ModelConfig {
    // 6 features, padded to 16 MLP inputs: the padding columns and a d_enc row count that
    // is not a multiple of 16.
    ModelConfig {
        grid: GridConfig {
            n_levels: 3,
            n_features: 2,
            log2_hashmap_size: 10,
            base_resolution: 4,
        },
        aabb_scale: 1,
    }
}

fn case(config: ModelConfig, seed: u64) -> Case {
    let net = NerfNetwork::new(config).unwrap();
    let l = &net.layout;
    let mut params = net.init_params(seed);
    let mut r = Pcg32::new(seed, 99);
    // Xavier weights moved by up to ±0.1 (their scale is 0.2–0.3), so that ReLUs are on and
    // off in every layer and nothing depends on the initialisation's symmetry; a grid of
    // ±1 makes the encoding O(1), where the network is far from linear.
    for v in &mut params[..l.grid_offset] {
        *v += (r.next_f32() * 2.0 - 1.0) * 0.1;
    }
    for v in &mut params[l.grid_offset..] {
        *v = r.next_f32() * 2.0 - 1.0;
    }
    let pos: Vec<[f32; 3]> = (0..N)
        .map(|_| [r.next_f32(), r.next_f32(), r.next_f32()])
        .collect();
    let dir: Vec<[f32; 3]> = (0..N)
        .map(|_| {
            loop {
                let v = [0; 3].map(|_: u8| r.next_f32() * 2.0 - 1.0);
                let n2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
                if n2 > 1e-3 && n2 <= 1.0 {
                    break v.map(|c| c / n2.sqrt());
                }
            }
        })
        .collect();
    let mut d_out: Vec<[f32; 4]> = (0..N)
        .map(|_| [0; 4].map(|_: u8| r.next_f32() * 2.0 - 1.0))
        .collect();
    let n_enc = l.grid.config.n_output_dims();
    let mut enc = vec![0f32; n_enc * LD];
    let mut cache = GridCache::new(&l.grid, N);
    let indices = reference_indices(&l.grid);
    grid::forward(
        &l.grid,
        &params[l.grid_offset..],
        &indices,
        &pos,
        &mut cache,
        &mut enc,
        LD,
    );
    // No gradient from samples at a ReLU kink: there the gradient jumps, and which side a
    // pre-activation within rounding of 0 lands on depends on the summation order (seen:
    // 9.3e-10 on llvmpipe, 0 on the CPU, one hidden unit of one sample, which moved a whole
    // row of a weight gradient by 3 %). Both sides then see the same zero gradient there.
    let near = near_kinks(&net, &params, &enc, &dir, 1e-5);
    let n_near = near.iter().filter(|&&k| k).count();
    eprintln!("{n_near} of {N} samples within 1e-5 of a ReLU kink: no gradient from them");
    assert!(n_near < N / 20, "{n_near} samples near a kink");
    for (d, _) in d_out.iter_mut().zip(&near).filter(|(_, k)| **k) {
        *d = [0.0; 4];
    }
    Case {
        net,
        params,
        pos,
        dir,
        enc,
        cache,
        d_out,
    }
}

/// Samples with a hidden pre-activation within `eps` of 0 in either MLP, from the CPU
/// engine's layers run without their ReLU (pre-activations are not kept by `forward`).
/// The GPU's pre-activations differ from these by ~1e-7 (f32 rounding of sums of O(1)
/// terms; the forward outputs agree to 2e-7), so `eps` = 1e-5 leaves a 100× margin.
fn near_kinks(
    net: &NerfNetwork,
    params: &[f32],
    enc: &[f32],
    dir: &[[f32; 3]],
    eps: f32,
) -> Vec<bool> {
    let l = &net.layout;
    let (dm, cm) = (l.density_mlp, l.color_mlp);
    let wd = &params[l.density_offset..l.color_offset];
    let wc = &params[l.color_offset..l.grid_offset];
    let n_enc = l.grid.config.n_output_dims();
    let mut x = vec![0f32; dm.n_in * N];
    for f in 0..n_enc {
        x[f * N..(f + 1) * N].copy_from_slice(&enc[f * LD..f * LD + N]);
    }
    let relu = |v: &[f32]| v.iter().map(|a| a.max(0.0)).collect::<Vec<f32>>();
    let mut pre_d = vec![0f32; 64 * N];
    mlp::layer_forward(wd, dm.n_in, 64, &x, &mut pre_d, N, N, false);
    let mut cin = vec![0f32; 32 * N];
    let w_d1 = &wd[matrix_offset(&dm, 1)..];
    mlp::layer_forward(w_d1, 64, 16, &relu(&pre_d), &mut cin, N, N, false);
    sh::encode(dir, &mut cin[16 * N..], N);
    let mut pre_1 = vec![0f32; 64 * N];
    mlp::layer_forward(wc, 32, 64, &cin, &mut pre_1, N, N, false);
    let mut pre_2 = vec![0f32; 64 * N];
    let w_c1 = &wc[matrix_offset(&cm, 1)..];
    mlp::layer_forward(w_c1, 64, 64, &relu(&pre_1), &mut pre_2, N, N, false);
    (0..N)
        .map(|s| {
            [&pre_d, &pre_1, &pre_2]
                .iter()
                .any(|pre| (0..64).any(|j| pre[j * N + s].abs() < eps))
        })
        .collect()
}

impl Case {
    /// `NerfNetwork::forward` (and, with `grad`, `backward` right after each chunk).
    fn cpu_forward(&self, mut grad: Option<&mut [f32]>) -> Vec<[f32; 4]> {
        let idx = reference_indices(&self.net.layout.grid);
        let mut ws = self.net.workspace();
        let mut out = vec![[0f32; 4]; N];
        for c in (0..N).step_by(CHUNK) {
            let e = (c + CHUNK).min(N);
            self.net.forward(
                &self.params,
                &idx,
                &self.pos[c..e],
                &self.dir[c..e],
                &mut ws,
                &mut out[c..e],
            );
            if let Some(g) = grad.as_deref_mut() {
                self.net
                    .backward(&self.params, &idx, &self.d_out[c..e], &mut ws, g);
            }
        }
        out
    }

    fn cpu_density(&self) -> Vec<f32> {
        let idx = reference_indices(&self.net.layout.grid);
        let mut ws = self.net.workspace();
        let mut out = vec![0f32; N];
        for c in (0..N).step_by(CHUNK) {
            let e = (c + CHUNK).min(N);
            self.net
                .density(&self.params, &idx, &self.pos[c..e], &mut ws, &mut out[c..e]);
        }
        out
    }
}

/// The case's buffers on the device.
struct Device {
    kernels: MlpKernels,
    params: wgpu::Buffer,
    enc: wgpu::Buffer,
    dirs: wgpu::Buffer,
}

impl Device {
    fn new(ctx: &GpuContext, c: &Case) -> Device {
        let flat_dirs: Vec<f32> = c.dir.iter().flatten().copied().collect();
        Device {
            kernels: MlpKernels::new(ctx, &c.net.layout).unwrap(),
            params: upload(ctx, "params", &c.params).unwrap(),
            enc: upload(ctx, "enc", &c.enc).unwrap(),
            dirs: upload(ctx, "dirs", &flat_dirs).unwrap(),
        }
    }

    fn batch(&self) -> EncodedBatch<'_> {
        EncodedBatch {
            params: &self.params,
            enc: &self.enc,
            ld: LD as u32,
            n: N as u32,
        }
    }
}

fn read(ctx: &GpuContext, b: &wgpu::Buffer, floats: usize) -> Vec<f32> {
    ctx.read_buffer(b, 4 * floats as u64).unwrap()
}

/// max over i of |got − want| / (1 + |want|).
fn max_rel(got: &[f32], want: &[f32]) -> f32 {
    assert_eq!(got.len(), want.len());
    got.iter()
        .zip(want)
        .map(|(g, w)| (g - w).abs() / (1.0 + w.abs()))
        .fold(0.0, f32::max)
}

#[test]
fn forward_matches_the_cpu_network() {
    let Some(ctx) = test_context() else { return };
    for (name, config) in [("default", ModelConfig::default()), ("3×2", small_config())] {
        let c = case(config, 1);
        let want: Vec<f32> = c.cpu_forward(None).into_iter().flatten().collect();
        let d = Device::new(ctx, &c);
        let ws = d.kernels.workspace(ctx, N as u32).unwrap();
        // Rendering (nothing kept) and training (activations kept) give the same outputs.
        for keep in [None, Some(&ws)] {
            let out = zeroed(ctx, "out", 4 * N as u64).unwrap();
            d.kernels
                .forward(ctx, &d.batch(), &d.dirs, &out, keep)
                .unwrap();
            let got = read(ctx, &out, 4 * N);
            let err = max_rel(&got, &want);
            eprintln!(
                "{name} (tile {}) forward, keep {}: max |Δ|/(1+|cpu|) = {err:.2e}",
                d.kernels.tile(),
                keep.is_some()
            );
            assert!(err <= 1e-5, "{name}: forward off by {err}");
            // The outputs are not trivially small, and both halves of every ReLU layer are
            // exercised (a network that only passes zeros would agree as well).
            assert!(want.iter().map(|v| v.abs()).fold(0.0, f32::max) > 0.3);
        }
    }
}

#[test]
fn density_matches_the_cpu_network() {
    let Some(ctx) = test_context() else { return };
    let c = case(ModelConfig::default(), 2);
    let want = c.cpu_density();
    let d = Device::new(ctx, &c);
    let out = zeroed(ctx, "density", N as u64).unwrap();
    d.kernels.density(ctx, &d.batch(), &out).unwrap();
    let got = read(ctx, &out, N);
    let err = max_rel(&got, &want);
    eprintln!("density: max |Δ|/(1+|cpu|) = {err:.2e}");
    assert!(err <= 1e-5, "density off by {err}");
}

#[test]
fn backward_matches_the_cpu_network() {
    let Some(ctx) = test_context() else { return };
    for (name, config) in [("default", ModelConfig::default()), ("3×2", small_config())] {
        let c = case(config, 3);
        let l = &c.net.layout;
        let n_mlp = l.grid_offset;
        // Gradients accumulate: both start from the same non-zero vector.
        let mut r = Pcg32::new(4, 4);
        let start: Vec<f32> = (0..l.n_params).map(|_| r.next_f32() - 0.5).collect();
        let mut want = start.clone();
        c.cpu_forward(Some(&mut want[..]));

        let d = Device::new(ctx, &c);
        let ws = d.kernels.workspace(ctx, N as u32 + 7).unwrap();
        let out = zeroed(ctx, "out", 4 * N as u64).unwrap();
        let flat_d_out: Vec<f32> = c.d_out.iter().flatten().copied().collect();
        let d_out = upload(ctx, "d_out", &flat_d_out).unwrap();
        let n_enc = l.grid.config.n_output_dims();
        let mut got = Vec::new();
        let mut d_enc = Vec::new();
        // Twice: the gradient reduction has a fixed order, so the result is bit for bit
        // the same every run.
        for _ in 0..2 {
            let grad = upload(ctx, "grad", &start[..n_mlp]).unwrap();
            let d_enc_buf = zeroed(ctx, "d_enc", (n_enc * LD) as u64).unwrap();
            d.kernels
                .forward(ctx, &d.batch(), &d.dirs, &out, Some(&ws))
                .unwrap();
            d.kernels
                .backward(ctx, &d.batch(), &d_out, &ws, &grad, &d_enc_buf)
                .unwrap();
            let g = read(ctx, &grad, n_mlp);
            let e = read(ctx, &d_enc_buf, n_enc * LD);
            if !got.is_empty() {
                assert!(g == got && e == d_enc, "{name}: backward not reproducible");
            }
            (got, d_enc) = (g, e);
        }

        // Weight gradients, matrix by matrix (the gradient added, so the start cancels).
        let (dm, cm) = (l.density_mlp, l.color_mlp);
        let mats = [
            (
                "density 0",
                l.density_offset + matrix_offset(&dm, 0),
                64 * dm.n_in,
            ),
            (
                "density 1",
                l.density_offset + matrix_offset(&dm, 1),
                16 * 64,
            ),
            ("colour 0", l.color_offset + matrix_offset(&cm, 0), 64 * 32),
            ("colour 1", l.color_offset + matrix_offset(&cm, 1), 64 * 64),
            ("colour 2", l.color_offset + matrix_offset(&cm, 2), 16 * 64),
        ];
        for (what, off, len) in mats {
            let g: Vec<f32> = (off..off + len).map(|i| got[i] - start[i]).collect();
            let w: Vec<f32> = (off..off + len).map(|i| want[i] - start[i]).collect();
            let scale = w.iter().map(|v| v.abs()).fold(0.0, f32::max);
            let err = g
                .iter()
                .zip(&w)
                .map(|(g, w)| (g - w).abs())
                .fold(0.0, f32::max);
            eprintln!("{name} {what}: max |Δ| = {err:.2e} of max |grad| {scale:.3e}");
            assert!(scale > 1e-3, "{name} {what}: no gradient to compare");
            assert!(
                err <= 1e-4 * scale,
                "{name} {what}: off by {err} (scale {scale})"
            );
        }
        // The colour MLP's padded output rows 3..16 get no gradient at all, as on the CPU.
        let pad = l.color_offset + matrix_offset(&cm, 2) + 3 * 64..l.grid_offset;
        assert_eq!(got[pad.clone()], want[pad], "{name}: padded rows touched");

        // d_enc through the CPU grid's backward: the grid gradient it gives must be the
        // one NerfNetwork::backward accumulated, entry by entry. On the fine levels an
        // entry is read by one sample or two, so this checks d_enc sample by sample; each
        // entry is held to 1e-4 of the summed magnitudes reaching it (the same scatter of
        // |d_enc|) plus 1e-6 absolute.
        let grid_n = l.grid.n_params();
        let mut g_grid = vec![0f32; grid_n];
        grid::backward(&l.grid, &c.cache, &d_enc, LD, &mut g_grid);
        let abs: Vec<f32> = d_enc.iter().map(|v| v.abs()).collect();
        let mut mag = vec![0f32; grid_n];
        grid::backward(&l.grid, &c.cache, &abs, LD, &mut mag);
        // The largest share of its tolerance any entry uses.
        let (mut worst, mut touched) = (0f32, 0);
        for i in 0..grid_n {
            let w = want[l.grid_offset + i] - start[l.grid_offset + i];
            let err = (g_grid[i] - w).abs();
            touched += (mag[i] > 0.0) as usize;
            worst = worst.max(err / (1e-4 * mag[i] + 1e-6));
            assert!(
                err <= 1e-4 * mag[i] + 1e-6,
                "{name}: grid entry {i}: {} via GPU d_enc, CPU {w} (magnitude {})",
                g_grid[i],
                mag[i]
            );
        }
        eprintln!("{name} d_enc: {touched} grid entries, at most {worst:.3} of the tolerance");
        assert!(touched > N, "{name}: d_enc reached too few entries");
    }
}

#[test]
fn wrong_sizes_are_input_errors() {
    let Some(ctx) = test_context() else { return };
    let c = case(small_config(), 5);
    let d = Device::new(ctx, &c);
    let out = zeroed(ctx, "out", 4 * N as u64).unwrap();
    let input = |r: Result<(), GpuError>| matches!(r, Err(GpuError::Input(_)));
    let short = zeroed(ctx, "short", 10).unwrap();
    let mut b = d.batch();
    b.enc = &short;
    assert!(input(d.kernels.forward(ctx, &b, &d.dirs, &out, None)));
    assert!(input(d.kernels.density(ctx, &b, &short)));
    let mut b = d.batch();
    b.params = &short;
    assert!(input(d.kernels.forward(ctx, &b, &d.dirs, &out, None)));
    let mut b = d.batch();
    b.n = LD as u32 + 1;
    assert!(input(d.kernels.forward(ctx, &b, &d.dirs, &out, None)));
    assert!(input(d.kernels.forward(
        ctx,
        &d.batch(),
        &short,
        &out,
        None
    )));
    assert!(input(d.kernels.forward(
        ctx,
        &d.batch(),
        &d.dirs,
        &short,
        None
    )));
    assert!(input(d.kernels.workspace(ctx, 0).map(|_| ())));
    // A workspace too small for the batch (capacities round up to a multiple of 4), and a
    // backward with no forward kept.
    let small = d.kernels.workspace(ctx, N as u32 - 4).unwrap();
    assert!(input(d.kernels.forward(
        ctx,
        &d.batch(),
        &d.dirs,
        &out,
        Some(&small)
    )));
    let ws = d.kernels.workspace(ctx, N as u32).unwrap();
    let grad = zeroed(ctx, "grad", c.net.layout.grid_offset as u64).unwrap();
    let d_enc = zeroed(ctx, "d_enc", (6 * LD) as u64).unwrap();
    assert!(input(d.kernels.backward(
        ctx,
        &d.batch(),
        &out,
        &ws,
        &grad,
        &d_enc
    )));
    d.kernels
        .forward(ctx, &d.batch(), &d.dirs, &out, Some(&ws))
        .unwrap();
    assert!(input(d.kernels.backward(
        ctx,
        &d.batch(),
        &out,
        &ws,
        &short,
        &d_enc
    )));
    assert!(input(d.kernels.backward(
        ctx,
        &d.batch(),
        &out,
        &ws,
        &grad,
        &short
    )));
    d.kernels
        .backward(ctx, &d.batch(), &out, &ws, &grad, &d_enc)
        .unwrap();
    // A grid wider than one 64-input layer is refused, not miscomputed.
    let wide = NerfNetwork::new(ModelConfig {
        grid: GridConfig {
            n_levels: 16,
            n_features: 8,
            log2_hashmap_size: 10,
            base_resolution: 4,
        },
        aabb_scale: 1,
    })
    .unwrap();
    assert!(matches!(
        MlpKernels::new(ctx, &wide.layout),
        Err(GpuError::Input(_))
    ));
}
