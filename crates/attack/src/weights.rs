//! Edits of the weights alone: noise, pruning, quantisation. The table's *entries* are its
//! feature vectors (one per slot of a level); the MLPs' *matrices* are the layout's.

use ngp::network::NerfLayout;
use ngp::rng::Pcg32;
use std::ops::Range;

/// `w + σ·N(0,1)` on every weight, the normal draws from the seed's stream (Box–Muller).
pub fn noise(params: &[f32], sigma: f32, seed: u64) -> Vec<f32> {
    if sigma == 0.0 {
        return params.to_vec();
    }
    let mut r = Pcg32::new(seed, 0x6e6f_6973);
    let mut out = params.to_vec();
    for pair in out.chunks_mut(2) {
        // u1 in (0, 1]: ln never sees 0.
        let u1 = 1.0 - r.next_f32() as f64;
        let u2 = r.next_f32() as f64;
        let rad = (-2.0 * u1.ln()).sqrt();
        let (s, c) = (std::f64::consts::TAU * u2).sin_cos();
        pair[0] += sigma * (rad * c) as f32;
        if let Some(w) = pair.get_mut(1) {
            *w += sigma * (rad * s) as f32;
        }
    }
    out
}

/// A uniform draw in [0, 1) with 53 bits (an f32's 24 would bias a choice among millions).
fn unit_f64(r: &mut Pcg32) -> f64 {
    let bits = ((r.next_u32() as u64) << 21) ^ (r.next_u32() as u64 >> 11);
    bits as f64 / (1u64 << 53) as f64
}

/// The number of entries a fraction of `n` stands for, rounded to the nearest.
fn count_of(fraction: f32, n: u64) -> u64 {
    ((fraction as f64 * n as f64).round() as u64).min(n)
}

/// Zeroes `round(F·N)` of the table's N entries, drawn uniformly without replacement
/// (selection sampling: one pass, no index list). Returns the weights and the count.
pub fn prune_random(
    layout: &NerfLayout,
    params: &[f32],
    fraction: f32,
    seed: u64,
) -> (Vec<f32>, u64) {
    let n = layout.grid.n_entries as u64;
    let k = count_of(fraction, n);
    let nf = layout.grid.config.n_features as usize;
    let mut out = params.to_vec();
    let mut r = Pcg32::new(seed, 0x7072_756e);
    let mut left = k;
    for (i, e) in out[layout.grid_offset..].chunks_mut(nf).enumerate() {
        if left == 0 {
            break;
        }
        // Entry i is chosen with probability left / (entries still to visit).
        let remaining = n - i as u64;
        if unit_f64(&mut r) * (remaining as f64) < left as f64 {
            e.fill(0.0);
            left -= 1;
        }
    }
    (out, k - left)
}

/// Zeroes the `round(F·N)` entries of smallest feature-vector norm over the whole table
/// (ties: the lower index first).
pub fn prune_magnitude(layout: &NerfLayout, params: &[f32], fraction: f32) -> (Vec<f32>, u64) {
    let n = layout.grid.n_entries as usize;
    let k = count_of(fraction, n as u64) as usize;
    let nf = layout.grid.config.n_features as usize;
    let mut out = params.to_vec();
    if k == 0 {
        return (out, 0);
    }
    let table = &params[layout.grid_offset..];
    let mut norms: Vec<(f32, u32)> = table
        .chunks(nf)
        .enumerate()
        .map(|(i, e)| (e.iter().map(|x| x * x).sum::<f32>(), i as u32))
        .collect();
    let order = |a: &(f32, u32), b: &(f32, u32)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
    if k < n {
        norms.select_nth_unstable_by(k, order);
    }
    let out_table = &mut out[layout.grid_offset..];
    for &(_, i) in &norms[..k] {
        out_table[i as usize * nf..][..nf].fill(0.0);
    }
    (out, k as u64)
}

/// The spans quantisation scales apart: each MLP weight matrix, then each grid level.
pub fn quantisation_blocks(layout: &NerfLayout) -> Vec<Range<usize>> {
    let mut blocks = Vec::new();
    for (offset, shape) in [
        (layout.density_offset, layout.density_mlp),
        (layout.color_offset, layout.color_mlp),
    ] {
        let mut at = offset;
        for (rows, cols) in shape.matrices() {
            blocks.push(at..at + rows * cols);
            at += rows * cols;
        }
    }
    let nf = layout.grid.config.n_features as usize;
    for level in &layout.grid.levels {
        let start = layout.grid_offset + level.offset as usize * nf;
        blocks.push(start..start + level.size as usize * nf);
    }
    blocks
}

/// Every block to `bits`-bit signed integers, symmetric with the block's absolute maximum
/// as full scale (`q = round(w / s)`, `|q| ≤ 2^(bits−1) − 1`), and back to `q·s`.
pub fn quantise(layout: &NerfLayout, params: &[f32], bits: u32) -> Vec<f32> {
    let q_max = ((1u32 << (bits - 1)) - 1) as f32;
    let mut out = params.to_vec();
    for block in quantisation_blocks(layout) {
        let w = &mut out[block];
        let absmax = w.iter().fold(0.0f32, |m, x| m.max(x.abs()));
        if absmax == 0.0 {
            continue;
        }
        let s = absmax / q_max;
        for x in w.iter_mut() {
            *x = (*x / s).round().clamp(-q_max, q_max) * s;
        }
    }
    out
}
