//! Bias-free MLPs with tiny-cuda-nn FullyFusedMLP semantics (spec §2.2, §2.5): ReLU hidden
//! layers, linear output, row-major `out × in` weight matrices, input layer first.
//!
//! Activations are feature-major over a chunk: feature `i` of sample `s` is at `i·ld + s`,
//! so every layer is one gemm over the whole chunk with the samples as the long, contiguous
//! dimension (what gemm's micro-kernels prefer). Callers may ask for only the first rows of
//! the output (the colour MLP's padded rows 3..15 are never computed, and get no gradient).

use super::layout::MlpShape;

/// Can a strided `rows × cols` matrix at the start of a slice of `len` elements be read?
fn fits(len: usize, rows: usize, cols: usize, rs: usize, cs: usize) -> bool {
    rows == 0 || cols == 0 || (rows - 1) * rs + (cols - 1) * cs < len
}

/// `c (m×n) = [c +] a (m×k) · b (k×n)`; element (r, j) of each matrix at `ptr[r·rs + j·cs]`.
///
/// # Safety
/// Every element addressed by the three views must be inside its allocation, and `c` must
/// not overlap `a` or `b`.
#[allow(clippy::too_many_arguments)]
unsafe fn matmul(
    m: usize,
    n: usize,
    k: usize,
    c: (*mut f32, usize, usize),
    accumulate: bool,
    a: (*const f32, usize, usize),
    b: (*const f32, usize, usize),
) {
    if m == 0 || n == 0 {
        return;
    }
    // SAFETY: forwarded from the caller; gemm's argument order is (ptr, col stride, row stride).
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            c.0,
            c.2 as isize,
            c.1 as isize,
            accumulate,
            a.0,
            a.2 as isize,
            a.1 as isize,
            b.0,
            b.2 as isize,
            b.1 as isize,
            1.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

/// `y[o·ld + s] = act(Σ_i w[o·n_in + i] · x[i·ld + s])` for `o < n_out`, `s < n`.
#[allow(clippy::too_many_arguments)]
pub fn layer_forward(
    w: &[f32],
    n_in: usize,
    n_out: usize,
    x: &[f32],
    y: &mut [f32],
    n: usize,
    ld: usize,
    relu: bool,
) {
    assert!(n <= ld && w.len() >= n_out * n_in);
    assert!(fits(x.len(), n, n_in, 1, ld) && fits(y.len(), n, n_out, 1, ld));
    // SAFETY: extents checked above; y is a distinct &mut.
    unsafe {
        matmul(
            n,
            n_out,
            n_in,
            (y.as_mut_ptr(), 1, ld),
            false,
            (x.as_ptr(), 1, ld),
            (w.as_ptr(), 1, n_in),
        );
    }
    if relu {
        for o in 0..n_out {
            for v in &mut y[o * ld..o * ld + n] {
                *v = v.max(0.0);
            }
        }
    }
}

/// `gw[o·n_in + i] += Σ_s dy[o·ld + s] · x[i·ld + s]` for `o < n_out`.
pub fn layer_grad_weights(
    dy: &[f32],
    n_out: usize,
    x: &[f32],
    n_in: usize,
    n: usize,
    ld: usize,
    gw: &mut [f32],
) {
    assert!(n <= ld && gw.len() >= n_out * n_in);
    assert!(fits(dy.len(), n_out, n, ld, 1) && fits(x.len(), n, n_in, 1, ld));
    if n == 0 {
        return;
    }
    // SAFETY: extents checked above; gw is a distinct &mut.
    unsafe {
        matmul(
            n_out,
            n_in,
            n,
            (gw.as_mut_ptr(), n_in, 1),
            true,
            (dy.as_ptr(), ld, 1),
            (x.as_ptr(), 1, ld),
        );
    }
}

/// `dx[i·ld + s] = Σ_{o < n_out} dy[o·ld + s] · w[o·n_in + i]` for `i < n_in_used`, zeroed
/// where `relu_of[i·ld + s] <= 0` (the layer below is a ReLU whose output was `relu_of`).
#[allow(clippy::too_many_arguments)]
pub fn layer_grad_input(
    w: &[f32],
    n_in: usize,
    n_out: usize,
    n_in_used: usize,
    dy: &[f32],
    dx: &mut [f32],
    n: usize,
    ld: usize,
    relu_of: Option<&[f32]>,
) {
    assert!(n <= ld && n_in_used <= n_in && w.len() >= n_out * n_in);
    assert!(fits(dy.len(), n, n_out, 1, ld) && fits(dx.len(), n, n_in_used, 1, ld));
    // SAFETY: extents checked above; dx is a distinct &mut.
    unsafe {
        matmul(
            n,
            n_in_used,
            n_out,
            (dx.as_mut_ptr(), 1, ld),
            false,
            (dy.as_ptr(), 1, ld),
            (w.as_ptr(), n_in, 1),
        );
    }
    if let Some(h) = relu_of {
        assert!(fits(h.len(), n, n_in_used, 1, ld));
        for i in 0..n_in_used {
            let (d, h) = (&mut dx[i * ld..i * ld + n], &h[i * ld..i * ld + n]);
            for (d, &h) in d.iter_mut().zip(h) {
                if h <= 0.0 {
                    *d = 0.0;
                }
            }
        }
    }
}

/// Offset of matrix `layer` (0 = input layer, `n_hidden_layers` = output layer) in the
/// MLP's weights, without allocating.
pub fn matrix_offset(shape: &MlpShape, layer: usize) -> usize {
    if layer == 0 {
        0
    } else {
        shape.width * shape.n_in + (layer - 1) * shape.width * shape.width
    }
}

/// Scratch sizes for a chunk of leading dimension `ld`.
pub fn hidden_len(shape: &MlpShape, ld: usize) -> usize {
    shape.n_hidden_layers * shape.width * ld
}

/// Forward pass: `x` (n_in × ld) → `hidden` (all hidden activations, kept for backward) →
/// the first `n_out_used` rows of the output into `out`.
#[allow(clippy::too_many_arguments)]
pub fn forward(
    shape: &MlpShape,
    w: &[f32],
    x: &[f32],
    hidden: &mut [f32],
    out: &mut [f32],
    n_out_used: usize,
    n: usize,
    ld: usize,
) {
    assert!(w.len() == shape.n_params() && n_out_used <= shape.n_out_padded);
    assert!(hidden.len() >= hidden_len(shape, ld));
    let wd = shape.width;
    let hl = wd * ld;
    layer_forward(w, shape.n_in, wd, x, &mut hidden[..hl], n, ld, true);
    for j in 1..shape.n_hidden_layers {
        let (prev, cur) = hidden.split_at_mut(j * hl);
        let wj = &w[matrix_offset(shape, j)..];
        layer_forward(
            wj,
            wd,
            wd,
            &prev[(j - 1) * hl..],
            &mut cur[..hl],
            n,
            ld,
            true,
        );
    }
    let last = shape.n_hidden_layers;
    let h = &hidden[(last - 1) * hl..last * hl];
    layer_forward(
        &w[matrix_offset(shape, last)..],
        wd,
        n_out_used,
        h,
        out,
        n,
        ld,
        false,
    );
}

/// Backward of [`forward`] given `d_out` (n_out_used × ld). Accumulates weight gradients
/// into `gw` (padded output rows untouched) and, if asked, writes `dL/dx` for the first
/// `n_in_used` inputs. `d_hidden` is scratch of `2·width·ld`.
#[allow(clippy::too_many_arguments)]
pub fn backward(
    shape: &MlpShape,
    w: &[f32],
    x: &[f32],
    hidden: &[f32],
    d_out: &[f32],
    n_out_used: usize,
    n: usize,
    ld: usize,
    gw: &mut [f32],
    d_hidden: &mut [f32],
    d_x: Option<(&mut [f32], usize)>,
) {
    assert!(w.len() == shape.n_params() && gw.len() == shape.n_params());
    assert!(n_out_used <= shape.n_out_padded && d_hidden.len() >= 2 * shape.width * ld);
    let wd = shape.width;
    let hl = wd * ld;
    let last = shape.n_hidden_layers;
    let (mut cur, mut next) = d_hidden.split_at_mut(hl);
    let mo = matrix_offset(shape, last);
    let h_last = &hidden[(last - 1) * hl..last * hl];
    layer_grad_weights(d_out, n_out_used, h_last, wd, n, ld, &mut gw[mo..]);
    layer_grad_input(
        &w[mo..],
        wd,
        n_out_used,
        wd,
        d_out,
        cur,
        n,
        ld,
        Some(h_last),
    );
    for j in (1..last).rev() {
        let mo = matrix_offset(shape, j);
        let h_prev = &hidden[(j - 1) * hl..j * hl];
        layer_grad_weights(cur, wd, h_prev, wd, n, ld, &mut gw[mo..]);
        layer_grad_input(&w[mo..], wd, wd, wd, cur, next, n, ld, Some(h_prev));
        std::mem::swap(&mut cur, &mut next);
    }
    layer_grad_weights(cur, wd, x, shape.n_in, n, ld, &mut gw[..wd * shape.n_in]);
    if let Some((dx, n_in_used)) = d_x {
        layer_grad_input(w, shape.n_in, wd, n_in_used, cur, dx, n, ld, None);
    }
}

/// Per-sample scalar forward (all padded outputs included), the reference for tests.
#[cfg(test)]
pub(crate) fn naive_forward(shape: &MlpShape, w: &[f32], x: &[f32]) -> Vec<f32> {
    let mut a = x.to_vec();
    let mut off = 0;
    for (k, (rows, cols)) in shape.matrices().enumerate() {
        let mut y = vec![0f32; rows];
        for o in 0..rows {
            let mut acc = 0f32;
            for i in 0..cols {
                acc += w[off + o * cols + i] * a[i];
            }
            y[o] = if k < shape.n_hidden_layers {
                acc.max(0.0)
            } else {
                acc
            };
        }
        off += rows * cols;
        a = y;
    }
    a
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Pcg32;

    fn uniform(n: usize, scale: f32, seed: u64) -> Vec<f32> {
        let mut r = Pcg32::new(seed, 3);
        (0..n).map(|_| (r.next_f32() * 2.0 - 1.0) * scale).collect()
    }

    #[test]
    fn matrix_offsets_match_shape() {
        let s = MlpShape::new(32, 64, 2, 3);
        let m: Vec<_> = s.matrices().collect();
        assert_eq!(matrix_offset(&s, 0), 0);
        assert_eq!(matrix_offset(&s, 1), m[0].0 * m[0].1);
        assert_eq!(matrix_offset(&s, 2), m[0].0 * m[0].1 + m[1].0 * m[1].1);
        assert_eq!(matrix_offset(&s, 2) + 16 * 64, s.n_params());
    }

    #[test]
    fn forward_matches_naive() {
        for shape in [MlpShape::new(32, 64, 1, 16), MlpShape::new(32, 64, 2, 3)] {
            let w = uniform(shape.n_params(), 0.3, 1);
            let n = 37;
            let ld = 40;
            let x = uniform(shape.n_in * ld, 1.0, 2);
            let mut hidden = vec![0f32; hidden_len(&shape, ld)];
            let mut out = vec![0f32; shape.n_out_padded * ld];
            forward(&shape, &w, &x, &mut hidden, &mut out, shape.n_out, n, ld);
            for s in 0..n {
                let xs: Vec<f32> = (0..shape.n_in).map(|i| x[i * ld + s]).collect();
                let want = naive_forward(&shape, &w, &xs);
                for o in 0..shape.n_out {
                    let got = out[o * ld + s];
                    assert!((got - want[o]).abs() <= 1e-5 * (1.0 + want[o].abs()));
                }
            }
        }
    }

    /// Central differences of `L = Σ c ⊙ out` (accumulated in f64). The MLP is piecewise
    /// linear (ReLU), so inside a linear piece the difference is exact up to f32 rounding:
    /// outputs O(1) carry ~1e-6 absolute error, over 2h = 2e-2 that is ~1e-4, hence the
    /// 2e-3 relative + 1e-3 absolute tolerance. The loss is piecewise linear in any single
    /// weight or input, so a kink within ±h shows as unequal one-sided differences; such
    /// steps are skipped (a 1e-2 step moves a weight's pre-activation in all 19 samples, so
    /// up to ~15 % may be).
    #[test]
    fn gradients_match_finite_differences() {
        for (shape, n_out_used, n_in_used) in [
            (MlpShape::new(32, 64, 1, 16), 16, 32),
            (MlpShape::new(32, 64, 2, 3), 3, 16),
        ] {
            let mut w = uniform(shape.n_params(), 0.4, 11);
            let n = 19;
            let ld = 24;
            let mut x = uniform(shape.n_in * ld, 1.0, 12);
            let c = uniform(n_out_used * ld, 1.0, 13);
            let mut hidden = vec![0f32; hidden_len(&shape, ld)];
            let mut out = vec![0f32; n_out_used * ld];
            let mut loss = |w: &[f32], x: &[f32], hidden: &mut [f32]| -> f64 {
                forward(&shape, w, x, hidden, &mut out, n_out_used, n, ld);
                let mut l = 0f64;
                for o in 0..n_out_used {
                    for s in 0..n {
                        l += c[o * ld + s] as f64 * out[o * ld + s] as f64;
                    }
                }
                l
            };
            loss(&w, &x, &mut hidden);
            let mut gw = vec![0f32; shape.n_params()];
            let mut dh = vec![0f32; 2 * shape.width * ld];
            let mut dx = vec![0f32; shape.n_in * ld];
            backward(
                &shape,
                &w,
                &x,
                &hidden,
                &c,
                n_out_used,
                n,
                ld,
                &mut gw,
                &mut dh,
                Some((&mut dx, n_in_used)),
            );
            // Returns (central difference, one-sided differences disagree = kink in range).
            let fd = |v: &mut Vec<f32>, p: usize, h: f32, f: &mut dyn FnMut(&[f32]) -> f64| {
                let o = v[p];
                let l0 = f(v);
                v[p] = o + h;
                let lp = f(v);
                v[p] = o - h;
                let lm = f(v);
                v[p] = o;
                let (fwd, bwd) = ((lp - l0) / h as f64, (l0 - lm) / h as f64);
                (
                    (lp - lm) / (2.0 * h as f64),
                    (fwd - bwd).abs() > 1e-3 * (1.0 + fwd.abs()),
                )
            };
            let h = 1e-2f32;
            let (mut checked, mut skipped) = (0, 0);
            let mut check = |(fd, kink): (f64, bool), an: f32, what: &str| {
                if kink {
                    skipped += 1;
                    return;
                }
                checked += 1;
                assert!(
                    (fd - an as f64).abs() <= 2e-3 * fd.abs() + 1e-3,
                    "{what}: fd {fd} vs analytic {an}"
                );
            };
            let mut r = Pcg32::new(99, 1);
            for _ in 0..300 {
                let p = r.below(shape.n_params() as u32) as usize;
                let x2 = x.clone();
                let mut f = |w: &[f32]| loss(w, &x2, &mut hidden);
                check(fd(&mut w, p, h, &mut f), gw[p], &format!("weight {p}"));
            }
            // Padded output rows: no gradient at all.
            let mo = matrix_offset(&shape, shape.n_hidden_layers);
            assert!(
                gw[mo + n_out_used * shape.width..]
                    .iter()
                    .all(|&g| g == 0.0)
            );
            for _ in 0..100 {
                let i = r.below(n_in_used as u32) as usize;
                let s = r.below(n as u32) as usize;
                let p = i * ld + s;
                let w2 = w.clone();
                let mut f = |x: &[f32]| loss(&w2, x, &mut hidden);
                check(
                    fd(&mut x, p, h, &mut f),
                    dx[p],
                    &format!("input {i} sample {s}"),
                );
            }
            assert!(
                checked >= 340 && skipped <= 60,
                "checked {checked} skipped {skipped}"
            );
        }
    }
}
