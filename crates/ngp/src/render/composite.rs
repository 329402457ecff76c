//! Front-to-back volume compositing of one ray's samples and its exact backward pass
//! (instant-ngp's classic NeRF mode, spec §3.3).
//!
//! Per sample: σ = exp(raw_density), α = 1 − exp(−σ·dt), w = α·T, T ← T·(1 − α), colour
//! c = sigmoid(raw_rgb); the ray stops once T < `min_transmittance`. The prediction is
//! Σ w·c + T·bg.

/// Transmittance below which a training ray stops (and later samples get no gradient).
pub const TRAIN_MIN_TRANSMITTANCE: f32 = 1e-4;

/// The logistic function, colour network output → colour (the compositor's, and the mesh
/// layer's vertex colours).
#[inline]
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// What a ray accumulated.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Composite {
    /// Σ w·c (without background).
    pub rgb: [f32; 3],
    /// Σ w·t (expected distance, unnormalised).
    pub depth: f32,
    /// Transmittance left after the last used sample.
    pub transmittance: f32,
    /// Samples used before the ray stopped.
    pub n_used: usize,
}

/// Composites samples in order, starting from transmittance `t_start` (1 for a new ray; a
/// renderer that marches in waves passes the running value).
pub fn composite(
    raw: &[[f32; 4]],
    dt: &[f32],
    dist: &[f32],
    t_start: f32,
    min_transmittance: f32,
) -> Composite {
    let mut c = Composite {
        transmittance: t_start,
        ..Default::default()
    };
    let mut tr = t_start;
    for j in 0..raw.len() {
        if tr < min_transmittance {
            break;
        }
        let sigma = raw[j][3].exp();
        let alpha = 1.0 - (-sigma * dt[j]).exp();
        let w = alpha * tr;
        for (acc, &r) in c.rgb.iter_mut().zip(&raw[j][..3]) {
            *acc += w * sigmoid(r);
        }
        c.depth += w * dist[j];
        tr *= 1.0 - alpha;
        c.n_used = j + 1;
    }
    c.transmittance = tr;
    c
}

/// Gradient of a loss w.r.t. every sample's raw outputs, given `dl_dpred` = dLoss/d(Σ w·c +
/// T·bg). Writes `d_raw[j]` for all samples (zero after the ray stopped).
pub fn composite_backward(
    raw: &[[f32; 4]],
    dt: &[f32],
    bg: [f32; 3],
    min_transmittance: f32,
    dl_dpred: [f32; 3],
    d_raw: &mut [[f32; 4]],
) {
    let fwd = composite(raw, dt, dt, 1.0, min_transmittance);
    let pred = [
        fwd.rgb[0] + fwd.transmittance * bg[0],
        fwd.rgb[1] + fwd.transmittance * bg[1],
        fwd.rgb[2] + fwd.transmittance * bg[2],
    ];
    let mut acc = [0.0f32; 3];
    let mut tr = 1.0f32;
    for j in 0..raw.len() {
        if j >= fwd.n_used {
            d_raw[j] = [0.0; 4];
            continue;
        }
        let sigma = raw[j][3].exp();
        let alpha = 1.0 - (-sigma * dt[j]).exp();
        let w = alpha * tr;
        let col = [sigmoid(raw[j][0]), sigmoid(raw[j][1]), sigmoid(raw[j][2])];
        for k in 0..3 {
            acc[k] += w * col[k];
        }
        tr *= 1.0 - alpha;
        // d pred / d(σ·dt) = T_after·c − (what is still to come, background included).
        let mut dtau = 0.0;
        for k in 0..3 {
            let suffix = pred[k] - acc[k];
            dtau += dl_dpred[k] * (tr * col[k] - suffix);
        }
        // The reference clamps the exponent of the density derivative to [−15, 15].
        let dsigma = raw[j][3].clamp(-15.0, 15.0).exp();
        d_raw[j] = [
            dl_dpred[0] * w * col[0] * (1.0 - col[0]),
            dl_dpred[1] * w * col[1] * (1.0 - col[1]),
            dl_dpred[2] * w * col[2] * (1.0 - col[2]),
            dtau * dt[j] * dsigma,
        ];
    }
}

/// instant-ngp's "Huber" loss: Huber with δ = 0.1, divided by 5, per channel. Returns the
/// loss summed over channels and its gradient w.r.t. the prediction.
pub fn huber_loss(pred: [f32; 3], target: [f32; 3]) -> (f32, [f32; 3]) {
    const DELTA: f32 = 0.1;
    let mut loss = 0.0;
    let mut grad = [0.0; 3];
    for k in 0..3 {
        let d = pred[k] - target[k];
        if d.abs() > DELTA {
            loss += d.abs() - 0.5 * DELTA;
            grad[k] = d.signum();
        } else {
            loss += 0.5 / DELTA * d * d;
            grad[k] = d / DELTA;
        }
        grad[k] /= 5.0;
    }
    (loss / 5.0, grad)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Pcg32;

    fn random_ray(n: usize, seed: u64) -> (Vec<[f32; 4]>, Vec<f32>) {
        let mut r = Pcg32::new(seed, 7);
        let raw = (0..n)
            .map(|_| {
                [
                    r.next_f32() * 4.0 - 2.0,
                    r.next_f32() * 4.0 - 2.0,
                    r.next_f32() * 4.0 - 2.0,
                    r.next_f32() * 8.0 - 2.0,
                ]
            })
            .collect();
        let dt = (0..n).map(|_| 0.002 + r.next_f32() * 0.05).collect();
        (raw, dt)
    }

    #[test]
    fn single_opaque_sample_by_hand() {
        // σ·dt = e^2·0.5 ≈ 3.69 → α = 1 − e^−3.69 ≈ 0.97504; colour sigmoid(0) = 0.5.
        let c = composite(&[[0.0, 0.0, 0.0, 2.0]], &[0.5], &[1.0], 1.0, 1e-4);
        let alpha = 1.0 - (-(2.0f32).exp() * 0.5).exp();
        assert!((c.rgb[0] - 0.5 * alpha).abs() < 1e-6);
        assert!((c.transmittance - (1.0 - alpha)).abs() < 1e-6);
        assert_eq!(c.n_used, 1);
        // A ray stops once T < min: the second sample is not used.
        let c = composite(
            &[[0.0, 0.0, 0.0, 10.0], [5.0; 4]],
            &[1.0, 1.0],
            &[1.0, 2.0],
            1.0,
            1e-4,
        );
        assert_eq!(c.n_used, 1);
    }

    #[test]
    fn backward_matches_finite_differences() {
        for seed in 0..4 {
            let (raw, dt) = random_ray(24, seed);
            let bg = [0.2, 0.7, 0.4];
            let target = [0.3, 0.5, 0.9];
            // Loss: Huber of the composited colour against a target, through the background.
            let loss = |raw: &[[f32; 4]]| -> f64 {
                let c = composite(raw, &dt, &dt, 1.0, 0.0);
                let p = [
                    c.rgb[0] + c.transmittance * bg[0],
                    c.rgb[1] + c.transmittance * bg[1],
                    c.rgb[2] + c.transmittance * bg[2],
                ];
                // A smooth loss (squared error) keeps central differences exact.
                (0..3).map(|k| ((p[k] - target[k]) as f64).powi(2)).sum()
            };
            let c = composite(&raw, &dt, &dt, 1.0, 0.0);
            let p: Vec<f32> = (0..3).map(|k| c.rgb[k] + c.transmittance * bg[k]).collect();
            let dl = [
                2.0 * (p[0] - target[0]),
                2.0 * (p[1] - target[1]),
                2.0 * (p[2] - target[2]),
            ];
            let mut d_raw = vec![[0.0; 4]; raw.len()];
            composite_backward(&raw, &dt, bg, 0.0, dl, &mut d_raw);
            let h = 1e-2f32;
            for j in 0..raw.len() {
                for k in 0..4 {
                    let mut a = raw.clone();
                    a[j][k] += h;
                    let mut b = raw.clone();
                    b[j][k] -= h;
                    let fd = (loss(&a) - loss(&b)) / (2.0 * h as f64);
                    let an = d_raw[j][k] as f64;
                    assert!(
                        (fd - an).abs() <= 2e-3 * fd.abs().max(an.abs()) + 2e-5,
                        "seed {seed} sample {j} comp {k}: fd {fd} vs analytic {an}"
                    );
                }
            }
        }
    }

    #[test]
    fn terminated_samples_get_no_gradient() {
        let raw = vec![[0.0, 0.0, 0.0, 12.0], [1.0, 1.0, 1.0, 1.0]];
        let mut d = vec![[9.0; 4]; 2];
        composite_backward(&raw, &[1.0, 1.0], [0.0; 3], 1e-4, [1.0; 3], &mut d);
        assert_eq!(d[1], [0.0; 4]);
        assert_ne!(d[0][0], 0.0);
    }

    #[test]
    fn huber_by_hand() {
        let (l, g) = huber_loss([0.55, 0.0, 0.0], [0.5, 0.0, 0.3]);
        // channel 0: d = 0.05 → 0.5/0.1·0.0025 = 0.0125; channel 2: |d| = 0.3 → 0.25.
        assert!((l - (0.0125 + 0.25) / 5.0).abs() < 1e-6);
        assert!((g[0] - 0.5 / 5.0).abs() < 1e-6);
        assert_eq!(g[1], 0.0);
        assert!((g[2] + 0.2).abs() < 1e-6);
    }
}
