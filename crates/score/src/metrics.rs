//! Image quality metrics as the NeRF literature computes them.

/// PSNR cap: identical images would give +∞, which poisons means over a test set.
pub const PSNR_MAX_DB: f64 = 100.0;

/// Mean squared error of `pred` clipped to [0,1] against `gt`.
pub fn mse(pred: &[f32], gt: &[f32]) -> f64 {
    assert_eq!(pred.len(), gt.len(), "mse: length mismatch");
    if pred.is_empty() {
        return 0.0;
    }
    let s: f64 = pred
        .iter()
        .zip(gt)
        .map(|(&p, &g)| {
            let d = p.clamp(0.0, 1.0) as f64 - g as f64;
            d * d
        })
        .sum();
    s / pred.len() as f64
}

/// PSNR in dB of values in [0,1]: `10·log10(1/MSE)` with `pred` clipped to [0,1] (as the
/// reference's `run.py`). Capped at [`PSNR_MAX_DB`] (100 dB) when MSE ≤ 1e-10, so it is
/// never infinite. Panics if the lengths differ.
pub fn psnr(pred: &[f32], gt: &[f32]) -> f64 {
    let m = mse(pred, gt);
    if m <= 1e-10 {
        PSNR_MAX_DB
    } else {
        (-10.0 * m.log10()).min(PSNR_MAX_DB)
    }
}

use rayon::prelude::*;

const SSIM_SIZE: usize = 11;
const SSIM_SIGMA: f64 = 1.5;
const SSIM_C1: f64 = 0.01 * 0.01;
const SSIM_C2: f64 = 0.03 * 0.03;

/// Normalised 1-D Gaussian taps at offsets −5..=5 (σ = 1.5): the separable factor of the
/// 11×11 window of Wang et al. (MATLAB `fspecial`), skimage and the NeRF/mip-NeRF code.
fn gaussian_taps() -> [f64; SSIM_SIZE] {
    let mut t = [0.0; SSIM_SIZE];
    let h = (SSIM_SIZE / 2) as f64;
    for (i, v) in t.iter_mut().enumerate() {
        let x = (i as f64 - h) / SSIM_SIGMA;
        *v = (-0.5 * x * x).exp();
    }
    let s: f64 = t.iter().sum();
    t.map(|v| v / s)
}

/// Output rows of the SSIM map one task computes: its horizontal pass (the band and the
/// window's 10 rows below it, five planes) stays in the core's cache (≈ 0.8 MB at 800 px).
const SSIM_BAND: usize = 16;

/// One channel's SSIM map for output rows `y0..y0 + out.len() / ow`: the five window
/// statistics (means, second moments and the cross moment) filtered horizontally, then
/// vertically, then combined. Each filtered value sums its taps in order from zero and
/// each map value is the same expression, whatever the band, so the map does not depend
/// on how it was split; the tap loops are outside the pixel loops so that those vectorise.
fn ssim_band(
    pred: &[f32],
    gt: &[f32],
    c: usize,
    width: usize,
    y0: usize,
    out: &mut [f64],
    taps: &[f64; SSIM_SIZE],
) {
    let ow = width - SSIM_SIZE + 1;
    let rows_out = out.len() / ow;
    let rows_in = rows_out + SSIM_SIZE - 1;
    let (mut xs, mut ys) = (vec![0.0f64; width], vec![0.0f64; width]);
    // Five planes of rows_in × ow: x, y, x², y², xy filtered along the row.
    let mut hz = vec![0.0f64; 5 * rows_in * ow];
    let plane = rows_in * ow;
    for r in 0..rows_in {
        let base = (y0 + r) * width;
        for (x, (a, b)) in xs.iter_mut().zip(ys.iter_mut()).enumerate() {
            let i = 3 * (base + x) + c;
            *a = pred[i].clamp(0.0, 1.0) as f64;
            *b = gt[i] as f64;
        }
        let (hx, rest) = hz.split_at_mut(plane);
        let (hy, rest) = rest.split_at_mut(plane);
        let (hxx, rest) = rest.split_at_mut(plane);
        let (hyy, hxy) = rest.split_at_mut(plane);
        let row = r * ow..(r + 1) * ow;
        let (hx, hy) = (&mut hx[row.clone()], &mut hy[row.clone()]);
        let (hxx, hyy, hxy) = (&mut hxx[row.clone()], &mut hyy[row.clone()], &mut hxy[row]);
        for (k, &t) in taps.iter().enumerate() {
            let (a, b) = (&xs[k..k + ow], &ys[k..k + ow]);
            for x in 0..ow {
                let (a, b) = (a[x], b[x]);
                hx[x] += t * a;
                hy[x] += t * b;
                hxx[x] += t * (a * a);
                hyy[x] += t * (b * b);
                hxy[x] += t * (a * b);
            }
        }
    }
    let mut v = vec![0.0f64; 5 * ow];
    for (r, o) in out.chunks_exact_mut(ow).enumerate() {
        v.fill(0.0);
        let (mx, rest) = v.split_at_mut(ow);
        let (my, rest) = rest.split_at_mut(ow);
        let (sxx, rest) = rest.split_at_mut(ow);
        let (syy, sxy) = rest.split_at_mut(ow);
        for (k, &t) in taps.iter().enumerate() {
            let at = |p: usize| &hz[p * plane + (r + k) * ow..p * plane + (r + k + 1) * ow];
            let (hx, hy, hxx, hyy, hxy) = (at(0), at(1), at(2), at(3), at(4));
            for x in 0..ow {
                mx[x] += t * hx[x];
                my[x] += t * hy[x];
                sxx[x] += t * hxx[x];
                syy[x] += t * hyy[x];
                sxy[x] += t * hxy[x];
            }
        }
        for x in 0..ow {
            let (a, b) = (mx[x], my[x]);
            // Rounding can make a variance slightly negative; clamp like mip-NeRF does.
            let vx = (sxx[x] - a * a).max(0.0);
            let vy = (syy[x] - b * b).max(0.0);
            let cov = sxy[x] - a * b;
            o[x] = ((2.0 * a * b + SSIM_C1) * (2.0 * cov + SSIM_C2))
                / ((a * a + b * b + SSIM_C1) * (vx + vy + SSIM_C2));
        }
    }
}

/// SSIM of interleaved RGB images (`3·width·height` values; `pred` clipped to [0,1]):
/// 11×11 Gaussian window σ = 1.5, K1 = 0.01, K2 = 0.03, L = 1, population (not sample)
/// statistics, mean over the 'valid' region (windows fully inside the image) of each
/// channel, then over channels. Returns NaN for images smaller than 11×11. Panics if the
/// lengths do not match `width·height`. Bands of rows run in parallel (rayon) and the
/// means are summed in order, so the value is the same on any number of threads.
pub fn ssim(pred: &[f32], gt: &[f32], width: usize, height: usize) -> f64 {
    assert_eq!(pred.len(), 3 * width * height, "ssim: pred length");
    assert_eq!(gt.len(), 3 * width * height, "ssim: gt length");
    if width < SSIM_SIZE || height < SSIM_SIZE {
        return f64::NAN;
    }
    let taps = gaussian_taps();
    let (ow, oh) = (width - SSIM_SIZE + 1, height - SSIM_SIZE + 1);
    let channel = |c: usize| {
        let mut map = vec![0.0f64; ow * oh];
        map.par_chunks_mut(ow * SSIM_BAND)
            .enumerate()
            .for_each(|(b, out)| ssim_band(pred, gt, c, width, b * SSIM_BAND, out, &taps));
        map.iter().sum::<f64>() / map.len() as f64
    };
    let means: Vec<f64> = (0..3).into_par_iter().map(channel).collect();
    means.iter().sum::<f64>() / 3.0
}

/// The 5-tap blur instant-ngp's SSIM filters with (`scripts/common.py`), in each direction.
const INGP_SSIM_TAPS: [f64; 5] = [0.120078, 0.233881, 0.292082, 0.233881, 0.120078];

/// Index `i` (which may lie up to a few pixels outside `0..n`) folded back into the image
/// the way scipy's `convolve1d` does by default (mode "reflect": the edge pixel repeats,
/// `d c b a | a b c d | d c b a`), for any `n ≥ 1`.
fn reflect_index(i: isize, n: usize) -> usize {
    if (0..n as isize).contains(&i) {
        return i as usize;
    }
    let period = 2 * n as isize;
    let k = i.rem_euclid(period) as usize;
    if k < n { k } else { 2 * n - 1 - k }
}

/// One direction of the 5-tap blur over a `w × h` plane: along x when `along_x`, else y.
fn ingp_blur_pass(src: &[f64], w: usize, h: usize, along_x: bool) -> Vec<f64> {
    let mut out = vec![0.0; w * h];
    for y in 0..h {
        for x in 0..w {
            let mut acc = 0.0;
            for (k, &t) in INGP_SSIM_TAPS.iter().enumerate() {
                let d = k as isize - 2;
                let (sx, sy) = if along_x {
                    (reflect_index(x as isize + d, w), y)
                } else {
                    (x, reflect_index(y as isize + d, h))
                };
                acc += t * src[sy * w + sx];
            }
            out[y * w + x] = acc;
        }
    }
    out
}

fn ingp_blur(src: &[f64], w: usize, h: usize) -> Vec<f64> {
    ingp_blur_pass(&ingp_blur_pass(src, w, h, false), w, h, true)
}

/// The SSIM instant-ngp's `scripts/run.py` reports (`common.py`'s `SSIM`), which is not the
/// literature's: both images clipped to [0, 1] and reduced to Rec. 709 luminance
/// (0.2126 R + 0.7152 G + 0.0722 B), local statistics from a separable 5-tap blur
/// ([`INGP_SSIM_TAPS`], edges reflected as scipy's "reflect" mode), K1 = 0.01, K2 = 0.03,
/// no clamping of the variances, and the map's mean over every pixel (borders included;
/// non-finite values count as 0). In f64 (the script works in float32). Panics if the
/// lengths do not match `width·height`.
pub fn ssim_instant_ngp(pred: &[f32], gt: &[f32], width: usize, height: usize) -> f64 {
    assert_eq!(pred.len(), 3 * width * height, "ssim: pred length");
    assert_eq!(gt.len(), 3 * width * height, "ssim: gt length");
    if width == 0 || height == 0 {
        return f64::NAN;
    }
    let lum = |img: &[f32]| -> Vec<f64> {
        img.chunks_exact(3)
            .map(|p| {
                let c = |v: f32| v.clamp(0.0, 1.0) as f64;
                0.2126 * c(p[0]) + 0.7152 * c(p[1]) + 0.0722 * c(p[2])
            })
            .collect()
    };
    let (a, b) = (lum(pred), lum(gt));
    let prod = |x: &[f64], y: &[f64]| -> Vec<f64> { x.iter().zip(y).map(|(p, q)| p * q).collect() };
    let (w, h) = (width, height);
    let (ma, mb) = (ingp_blur(&a, w, h), ingp_blur(&b, w, h));
    let (aa, bb, ab) = (
        ingp_blur(&prod(&a, &a), w, h),
        ingp_blur(&prod(&b, &b), w, h),
        ingp_blur(&prod(&a, &b), w, h),
    );
    let mut total = 0.0;
    for i in 0..w * h {
        let (sa, sb, sab) = (
            aa[i] - ma[i] * ma[i],
            bb[i] - mb[i] * mb[i],
            ab[i] - ma[i] * mb[i],
        );
        let p1 = (2.0 * ma[i] * mb[i] + SSIM_C1) / (ma[i] * ma[i] + mb[i] * mb[i] + SSIM_C1);
        let p2 = (2.0 * sab + SSIM_C2) / (sa + sb + SSIM_C2);
        let v = p1 * p2;
        total += if v.is_finite() { v } else { 0.0 };
    }
    total / (w * h) as f64
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;
    use ngp::rng::Pcg32;

    fn random_image(w: usize, h: usize, seed: u64) -> Vec<f32> {
        let mut r = Pcg32::new(seed, 1);
        (0..3 * w * h).map(|_| r.next_f32()).collect()
    }

    #[test]
    fn psnr_of_known_mse() {
        // Every value off by 0.1: MSE 0.01 → 20 dB.
        let gt = vec![0.5f32; 30];
        let pred = vec![0.6f32; 30];
        assert!((psnr(&pred, &gt) - 20.0).abs() < 1e-5);
        // Half the values off by 0.2: MSE 0.02 → 10·log10(50).
        let pred: Vec<f32> = (0..30)
            .map(|i| if i % 2 == 0 { 0.7 } else { 0.5 })
            .collect();
        assert!((psnr(&pred, &gt) - 10.0 * 50f64.log10()).abs() < 1e-5);
        // Prediction is clipped: 1.5 counts as 1.0.
        let one = vec![1.0f32; 4];
        assert_eq!(psnr(&[1.5; 4], &one), PSNR_MAX_DB);
        assert_eq!(psnr(&gt, &gt), PSNR_MAX_DB);
        assert!((psnr(&[0.0; 4], &one) - 0.0).abs() < 1e-12);
    }

    #[test]
    fn ssim_identity_and_symmetry() {
        let (w, h) = (17, 13);
        let a = random_image(w, h, 1);
        let b = random_image(w, h, 2);
        assert!((ssim(&a, &a, w, h) - 1.0).abs() < 1e-12);
        let ab = ssim(&a, &b, w, h);
        assert!((ab - ssim(&b, &a, w, h)).abs() < 1e-12);
        assert!(ab < 0.2, "independent noise should score low: {ab}");
        assert!(ssim(&a[..300], &b[..300], 10, 10).is_nan());
    }

    #[test]
    fn ssim_of_constant_images() {
        // All statistics vanish but the means: SSIM = (2ab + C1) / (a² + b² + C1).
        let (w, h) = (12, 11);
        let a = vec![0.3f32; 3 * w * h];
        let b = vec![0.5f32; 3 * w * h];
        let (x, y) = (0.3f32 as f64, 0.5f32 as f64);
        let expect = (2.0 * x * y + SSIM_C1) / (x * x + y * y + SSIM_C1);
        assert!((ssim(&a, &b, w, h) - expect).abs() < 1e-9);
    }

    #[test]
    fn ssim_of_shifted_ramp() {
        // x = ramp along the row, y = x + c. Variances and covariance are equal, so the
        // contrast-structure term is 1, and the symmetric window's mean of a linear ramp is
        // the centre value m: each window scores (2m(m+c) + C1) / (m² + (m+c)² + C1).
        let (w, h, c) = (20usize, 12usize, 0.1f64);
        let val = |x: usize| 0.1 + 0.03 * x as f64;
        let mut a = Vec::new();
        let mut b = Vec::new();
        for _y in 0..h {
            for x in 0..w {
                for _ in 0..3 {
                    a.push(val(x) as f32);
                    b.push((val(x) + c) as f32);
                }
            }
        }
        let mut expect = 0.0;
        let centres = 5..w - 5;
        for x in centres.clone() {
            let m = val(x);
            expect += (2.0 * m * (m + c) + SSIM_C1) / (m * m + (m + c) * (m + c) + SSIM_C1);
        }
        expect /= centres.len() as f64;
        let got = ssim(&b, &a, w, h);
        assert!((got - expect).abs() < 1e-6, "{got} vs {expect}");
    }

    /// SSIM with the explicit 2-D Gaussian kernel exp(−(dx²+dy²)/(2σ²)) / Σ over every
    /// valid window of every channel, with no separable filtering.
    fn direct_ssim(a: &[f32], b: &[f32], w: usize, h: usize) -> f64 {
        let mut kern = [[0.0f64; 11]; 11];
        let mut s = 0.0;
        for (dy, row) in kern.iter_mut().enumerate() {
            for (dx, k) in row.iter_mut().enumerate() {
                let (fx, fy) = (dx as f64 - 5.0, dy as f64 - 5.0);
                *k = (-(fx * fx + fy * fy) / (2.0 * 1.5 * 1.5)).exp();
                s += *k;
            }
        }
        let (ow, oh) = (w - 10, h - 10);
        let mut total = 0.0;
        for c in 0..3 {
            for y0 in 0..oh {
                for x0 in 0..ow {
                    let (mut mx, mut my, mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
                    for dy in 0..11 {
                        for dx in 0..11 {
                            let k = kern[dy][dx] / s;
                            let i = 3 * ((y0 + dy) * w + x0 + dx) + c;
                            let (p, q) = (a[i].clamp(0.0, 1.0) as f64, b[i] as f64);
                            mx += k * p;
                            my += k * q;
                            sxx += k * p * p;
                            syy += k * q * q;
                            sxy += k * p * q;
                        }
                    }
                    let (vx, vy, cv) = (sxx - mx * mx, syy - my * my, sxy - mx * my);
                    total += ((2.0 * mx * my + SSIM_C1) * (2.0 * cv + SSIM_C2))
                        / ((mx * mx + my * my + SSIM_C1) * (vx + vy + SSIM_C2));
                }
            }
        }
        total / (3 * ow * oh) as f64
    }

    fn dimmed(a: &[f32]) -> Vec<f32> {
        a.iter()
            .enumerate()
            .map(|(i, v)| 0.8 * v + 0.1 * ((i % 5) as f32) / 5.0)
            .collect()
    }

    #[test]
    fn ssim_matches_direct_2d_window() {
        // A 12×11 image has exactly two valid windows.
        let (w, h) = (12, 11);
        let a = random_image(w, h, 7);
        let b = dimmed(&a);
        let expect = direct_ssim(&a, &b, w, h);
        assert!((ssim(&a, &b, w, h) - expect).abs() < 1e-9);
        assert!(expect < 0.999 && expect > 0.5);
    }

    #[test]
    fn ssim_split_into_bands_is_the_direct_window_on_any_thread_count() {
        // 37 output rows: two whole bands and a part one; 13 output columns.
        let (w, h) = (23, 2 * SSIM_BAND + 15);
        let a = random_image(w, h, 11);
        let b = dimmed(&a);
        let expect = direct_ssim(&a, &b, w, h);
        let on = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| ssim(&a, &b, w, h))
        };
        let one = on(1);
        assert!((one - expect).abs() < 1e-9, "{one} against {expect}");
        for threads in [2, 3, 8] {
            assert_eq!(on(threads).to_bits(), one.to_bits(), "{threads} threads");
        }
        // A prediction out of [0, 1] is clipped, as the reference's metrics clip it.
        let over: Vec<f32> = a.iter().map(|v| v * 1.6 - 0.3).collect();
        let clipped = direct_ssim(&over, &b, w, h);
        assert!((ssim(&over, &b, w, h) - clipped).abs() < 1e-9);
    }

    /// instant-ngp's SSIM by its definition, written out in 2-D: luminance, the 5×5 kernel
    /// k[i]·k[j] with each tap's row and column folded back by scipy's "reflect" rule,
    /// every pixel's value averaged.
    fn direct_ssim_instant_ngp(a: &[f32], b: &[f32], w: usize, h: usize) -> f64 {
        let k = INGP_SSIM_TAPS;
        let lum = |img: &[f32], i: usize| {
            let c = |v: f32| v.clamp(0.0, 1.0) as f64;
            0.2126 * c(img[3 * i]) + 0.7152 * c(img[3 * i + 1]) + 0.0722 * c(img[3 * i + 2])
        };
        // Half-sample symmetric: −1 → 0, −2 → 1, n → n − 1, n + 1 → n − 2.
        let fold = |i: isize, n: usize| -> usize {
            let n = n as isize;
            let mut i = i;
            while i < 0 || i >= n {
                i = if i < 0 { -i - 1 } else { 2 * n - 1 - i };
            }
            i as usize
        };
        let mut total = 0.0;
        for y in 0..h {
            for x in 0..w {
                let (mut ma, mut mb, mut aa, mut bb, mut ab) = (0.0, 0.0, 0.0, 0.0, 0.0);
                for dy in 0..5 {
                    for dx in 0..5 {
                        let sy = fold(y as isize + dy as isize - 2, h);
                        let sx = fold(x as isize + dx as isize - 2, w);
                        let t = k[dy] * k[dx];
                        let (p, q) = (lum(a, sy * w + sx), lum(b, sy * w + sx));
                        ma += t * p;
                        mb += t * q;
                        aa += t * p * p;
                        bb += t * q * q;
                        ab += t * p * q;
                    }
                }
                let (sa, sb, sab) = (aa - ma * ma, bb - mb * mb, ab - ma * mb);
                total += (2.0 * ma * mb + SSIM_C1) / (ma * ma + mb * mb + SSIM_C1)
                    * ((2.0 * sab + SSIM_C2) / (sa + sb + SSIM_C2));
            }
        }
        total / (w * h) as f64
    }

    #[test]
    fn instant_ngp_ssim_matches_its_definition_borders_included() {
        // 7×6 (every pixel within two of an edge on some side) and 3×2 (taps folded twice).
        for (w, h) in [(7, 6), (3, 2), (1, 1)] {
            let a = random_image(w, h, 21);
            let b = dimmed(&a);
            let want = direct_ssim_instant_ngp(&a, &b, w, h);
            let got = ssim_instant_ngp(&a, &b, w, h);
            assert!((got - want).abs() < 1e-12, "{w}×{h}: {got} against {want}");
            assert!((ssim_instant_ngp(&a, &a, w, h) - 1.0).abs() < 1e-12);
        }
        // The five taps sum to 1, so constant images keep only the means' term; grey 0.5
        // against 0.25: (2·0.125 + C1) / (0.25 + 0.0625 + C1).
        let (w, h) = (6, 5);
        let (a, b) = (vec![0.5f32; 3 * w * h], vec![0.25f32; 3 * w * h]);
        let want = (0.25 + SSIM_C1) / (0.3125 + SSIM_C1);
        assert!((ssim_instant_ngp(&a, &b, w, h) - want).abs() < 1e-9);
        // Luminance, not channels: pure blue 1 against black differs by 0.0722 only.
        let blue: Vec<f32> = (0..3 * w * h).map(|i| (i % 3 == 2) as u8 as f32).collect();
        let black = vec![0.0f32; 3 * w * h];
        let want = SSIM_C1 / (0.0722 * 0.0722 + SSIM_C1);
        assert!((ssim_instant_ngp(&blue, &black, w, h) - want).abs() < 1e-6);
        // Both images are clipped (the literature's SSIM above clips the prediction only).
        let over: Vec<f32> = a.iter().map(|v| v * 3.0).collect();
        let ones = vec![1.0f32; 3 * w * h];
        assert!((ssim_instant_ngp(&over, &ones, w, h) - 1.0).abs() < 1e-12);
        assert!((ssim_instant_ngp(&ones, &over, w, h) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn instant_ngp_ssim_matches_scipy() {
        // Values scipy gives (scripts/ingp_driver.py's ssim_luminance: numpy and
        // scipy.ndimage.convolve1d, which run.py's common.py uses) for these 9×7 images:
        // 0.11397102376495324, and 0.19514291733777958 with the first scaled by 1.3, less 0.1,
        // and clipped.
        let (w, h) = (9usize, 7usize);
        let img = |s: usize| -> Vec<f32> {
            let mut v = Vec::new();
            for y in 0..h {
                for x in 0..w {
                    for c in 0..3 {
                        v.push(((x * 7 + y * 13 + c * 5 + s) % 17) as f32 / 16.0);
                    }
                }
            }
            v
        };
        let (a, b) = (img(0), img(3));
        assert!((ssim_instant_ngp(&a, &b, w, h) - 0.113_971_023_764_953_24).abs() < 1e-9);
        let a2: Vec<f32> = a.iter().map(|v| v * 1.3 - 0.1).collect();
        assert!((ssim_instant_ngp(&a2, &b, w, h) - 0.195_142_917_337_779_58).abs() < 1e-6);
    }
}
