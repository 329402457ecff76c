//! The layers AlexNet needs, on feature maps stored height × width × channels (NHWC with
//! N = 1, the layout of the flax checkpoint the weights come from): convolution by im2col
//! and `gemm` over tiles of output pixels (in parallel with rayon), ReLU, 3×3/2 max pooling,
//! and the per-pixel channel normalisation of LPIPS.

use rayon::prelude::*;

/// A feature map, `h × w × c`, row-major with channels fastest.
#[derive(Clone, Debug)]
pub(crate) struct Map {
    pub h: usize,
    pub w: usize,
    pub c: usize,
    pub data: Vec<f32>,
}

/// A square convolution with bias, followed by ReLU. `w` is `k·k·cin × cout` row-major: the
/// HWIO kernel of the checkpoint, which is exactly the right-hand matrix of im2col when an
/// im2col row holds one output pixel's receptive field in (ky, kx, ci) order.
#[derive(Clone, Debug)]
pub(crate) struct Conv {
    pub k: usize,
    pub stride: usize,
    pub pad: usize,
    pub cin: usize,
    pub cout: usize,
    pub w: Vec<f32>,
    pub b: Vec<f32>,
}

/// Output length along one axis of a convolution or pooling window `k` with stride `s` and
/// symmetric padding `pad` ('VALID' when 0); `None` when the window does not fit once.
pub(crate) fn out_len(n: usize, k: usize, s: usize, pad: usize) -> Option<usize> {
    (n + 2 * pad).checked_sub(k).map(|r| r / s + 1)
}

/// Output pixels per im2col/gemm tile: large enough that gemm's packing of the kernel
/// matrix is amortised, small enough that the im2col tile stays in cache and that every
/// core gets several tiles.
fn tile_pixels(total: usize, k_len: usize) -> usize {
    let threads = rayon::current_num_threads().max(1);
    let by_cache = (2 << 20) / (4 * k_len); // ≈ 2 MiB of im2col rows
    let by_threads = total.div_ceil(4 * threads);
    by_cache.min(by_threads).clamp(32, 512)
}

impl Conv {
    /// `relu(conv(x) + b)`. Panics if `x.c != cin` or the window does not fit.
    pub fn forward(&self, x: &Map) -> Map {
        assert_eq!(x.c, self.cin, "conv: channel count");
        let oh = out_len(x.h, self.k, self.stride, self.pad).expect("conv: input too small");
        let ow = out_len(x.w, self.k, self.stride, self.pad).expect("conv: input too small");
        let (k, cin, cout) = (self.k, self.cin, self.cout);
        let k_len = k * k * cin;
        debug_assert_eq!(self.w.len(), k_len * cout);
        let total = oh * ow;
        let mut out = vec![0.0f32; total * cout];
        let tile = tile_pixels(total, k_len);
        out.par_chunks_mut(tile * cout).enumerate().for_each_init(
            || vec![0.0f32; tile * k_len],
            |col, (t, dst)| {
                let p0 = t * tile;
                let n = dst.len() / cout;
                let col = &mut col[..n * k_len];
                self.im2col(x, ow, p0, n, col);
                // SAFETY: `col` is n × k_len, `self.w` is k_len × cout and `dst` is n × cout,
                // all row-major with unit column stride, in bounds and not overlapping.
                unsafe {
                    gemm::gemm(
                        n,
                        cout,
                        k_len,
                        dst.as_mut_ptr(),
                        1,
                        cout as isize,
                        false,
                        col.as_ptr(),
                        1,
                        k_len as isize,
                        self.w.as_ptr(),
                        1,
                        cout as isize,
                        0.0,
                        1.0,
                        false,
                        false,
                        false,
                        gemm::Parallelism::None,
                    );
                }
                for row in dst.chunks_exact_mut(cout) {
                    for (v, &b) in row.iter_mut().zip(&self.b) {
                        *v = (*v + b).max(0.0);
                    }
                }
            },
        );
        Map {
            h: oh,
            w: ow,
            c: cout,
            data: out,
        }
    }

    /// Rows `p0..p0+n` of the im2col matrix (output pixel p = oy·ow + ox): the receptive
    /// field in (ky, kx, ci) order, zeros where it falls in the padding. Along x the field is
    /// one contiguous run of the input row, so each (pixel, ky) is one copy.
    fn im2col(&self, x: &Map, ow: usize, p0: usize, n: usize, col: &mut [f32]) {
        let (k, s, cin) = (self.k, self.stride, self.cin);
        let pad = self.pad as isize;
        let (h, w) = (x.h as isize, x.w as isize);
        let k_len = k * k * cin;
        let run = k * cin;
        for (r, row) in col.chunks_exact_mut(k_len).enumerate().take(n) {
            let p = p0 + r;
            let (oy, ox) = ((p / ow) as isize, (p % ow) as isize);
            let iy0 = oy * s as isize - pad;
            let ix0 = ox * s as isize - pad;
            let kx_lo = (-ix0).clamp(0, k as isize) as usize;
            let kx_hi = (w - ix0).clamp(kx_lo as isize, k as isize) as usize;
            for (ky, dst) in row.chunks_exact_mut(run).enumerate() {
                let iy = iy0 + ky as isize;
                if iy < 0 || iy >= h {
                    dst.fill(0.0);
                    continue;
                }
                dst[..kx_lo * cin].fill(0.0);
                dst[kx_hi * cin..].fill(0.0);
                let src = ((iy * w + ix0) as usize + kx_lo) * cin;
                dst[kx_lo * cin..kx_hi * cin]
                    .copy_from_slice(&x.data[src..src + (kx_hi - kx_lo) * cin]);
            }
        }
    }
}

/// 3×3 max pooling with stride 2 and no padding (flax `max_pool(x, (3, 3), (2, 2))`,
/// torch `MaxPool2d(3, 2)`). Panics if the input is smaller than 3×3.
pub(crate) fn max_pool_3x2(x: &Map) -> Map {
    let oh = out_len(x.h, 3, 2, 0).expect("max_pool: input too small");
    let ow = out_len(x.w, 3, 2, 0).expect("max_pool: input too small");
    let c = x.c;
    let mut out = vec![0.0f32; oh * ow * c];
    out.par_chunks_mut(ow * c)
        .enumerate()
        .for_each(|(oy, orow)| {
            for (ox, o) in orow.chunks_exact_mut(c).enumerate() {
                o.fill(f32::NEG_INFINITY);
                for ky in 0..3 {
                    let base = ((2 * oy + ky) * x.w + 2 * ox) * c;
                    for v in x.data[base..base + 3 * c].chunks_exact(c) {
                        for (m, &a) in o.iter_mut().zip(v) {
                            *m = m.max(a);
                        }
                    }
                }
            }
        });
    Map {
        h: oh,
        w: ow,
        c,
        data: out,
    }
}

/// LPIPS's `normalize_tensor`: every pixel's channel vector divided by its Euclidean norm
/// plus 1e-10 (so an all-zero vector stays zero), in place.
pub(crate) fn normalize_channels(x: &mut Map) {
    let c = x.c;
    x.data.par_chunks_mut(c * 256).for_each(|chunk| {
        for v in chunk.chunks_exact_mut(c) {
            let ss: f64 = v.iter().map(|&a| (a as f64) * (a as f64)).sum();
            // A division, as the reference (x / (‖x‖ + eps)), not a multiplication by the
            // reciprocal.
            let d = (ss.sqrt() + 1e-10) as f32;
            v.iter_mut().for_each(|a| *a /= d);
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Direct (naive) convolution + ReLU for checking the im2col path.
    fn naive(conv: &Conv, x: &Map) -> Map {
        let oh = out_len(x.h, conv.k, conv.stride, conv.pad).unwrap();
        let ow = out_len(x.w, conv.k, conv.stride, conv.pad).unwrap();
        let mut data = vec![0.0f32; oh * ow * conv.cout];
        for oy in 0..oh {
            for ox in 0..ow {
                for co in 0..conv.cout {
                    let mut s = conv.b[co] as f64;
                    for ky in 0..conv.k {
                        for kx in 0..conv.k {
                            let iy = (oy * conv.stride + ky) as isize - conv.pad as isize;
                            let ix = (ox * conv.stride + kx) as isize - conv.pad as isize;
                            if iy < 0 || ix < 0 || iy >= x.h as isize || ix >= x.w as isize {
                                continue;
                            }
                            for ci in 0..conv.cin {
                                let xv = x.data[((iy as usize) * x.w + ix as usize) * x.c + ci];
                                let wv =
                                    conv.w[((ky * conv.k + kx) * conv.cin + ci) * conv.cout + co];
                                s += xv as f64 * wv as f64;
                            }
                        }
                    }
                    data[(oy * ow + ox) * conv.cout + co] = s.max(0.0) as f32;
                }
            }
        }
        Map {
            h: oh,
            w: ow,
            c: conv.cout,
            data,
        }
    }

    fn pseudo(n: usize, seed: u32) -> Vec<f32> {
        let mut s = seed.wrapping_mul(2654435761).wrapping_add(1);
        (0..n)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 17;
                s ^= s << 5;
                (s as f32 / u32::MAX as f32) * 2.0 - 1.0
            })
            .collect()
    }

    #[test]
    fn im2col_gemm_matches_direct_convolution() {
        for &(k, stride, pad, cin, cout, h, w) in &[
            (11, 4, 2, 3, 8, 37, 29),
            (5, 1, 2, 4, 6, 9, 7),
            (3, 1, 1, 5, 3, 6, 11),
            (3, 1, 1, 2, 2, 1, 1),
        ] {
            let conv = Conv {
                k,
                stride,
                pad,
                cin,
                cout,
                w: pseudo(k * k * cin * cout, 1),
                b: pseudo(cout, 2),
            };
            let x = Map {
                h,
                w,
                c: cin,
                data: pseudo(h * w * cin, 3),
            };
            let (a, b) = (conv.forward(&x), naive(&conv, &x));
            assert_eq!((a.h, a.w, a.c), (b.h, b.w, b.c));
            for (p, q) in a.data.iter().zip(&b.data) {
                assert!((p - q).abs() <= 1e-4 * (1.0 + q.abs()), "{p} vs {q}");
            }
        }
    }

    #[test]
    fn pooling_and_normalisation() {
        let x = Map {
            h: 5,
            w: 4,
            c: 2,
            data: (0..40).map(|i| i as f32).collect(),
        };
        let p = max_pool_3x2(&x);
        assert_eq!((p.h, p.w), (2, 1));
        // Window rows 0..3, cols 0..3: the maximum is at (2, 2).
        assert_eq!(&p.data[..2], &[(2 * 4 + 2) as f32 * 2.0, 21.0]);
        assert_eq!(&p.data[2..], &[(4 * 4 + 2) as f32 * 2.0, 37.0]);
        let mut m = Map {
            h: 1,
            w: 2,
            c: 2,
            data: vec![3.0, 4.0, 0.0, 0.0],
        };
        normalize_channels(&mut m);
        assert_eq!(m.data, vec![0.6, 0.8, 0.0, 0.0]);
        assert_eq!(out_len(30, 11, 4, 2), Some(6));
        assert_eq!(out_len(2, 3, 2, 0), None);
    }
}
