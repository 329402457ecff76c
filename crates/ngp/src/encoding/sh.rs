//! Degree-4 real spherical harmonics of the view direction (16 coefficients, bands 0..3),
//! with tiny-cuda-nn's polynomials and constants (spec §2.3). No trainable parameters: NeRF
//! training never needs dL/d(direction), but tcnn's encoding has that backward (for inputs
//! that are themselves optimised, e.g. camera refinement), so it is provided and checked.

/// Number of coefficients of degree 4 (bands l = 0..3).
pub const SH4_DIMS: usize = 16;

/// The direction tcnn's SH encoder actually sees: instant-ngp feeds `(d + 1) / 2` and the
/// encoder maps it back with `x·2 − 1`, both in f32. The round trip is not the identity in
/// float (it drops the low bits of small components), so it is reproduced here.
#[inline(always)]
pub fn reference_direction(d: [f32; 3]) -> [f32; 3] {
    d.map(|v| ((v + 1.0) * 0.5) * 2.0 - 1.0)
}

/// tcnn's SH constants, rounded to f32 by the compiler exactly as nvcc rounds them; the
/// forward and its backward share them.
#[allow(clippy::excessive_precision)]
mod constants {
    pub const C0: f32 = 0.28209479177387814;
    pub const C1: f32 = 0.48860251190291987;
    pub const C2: f32 = 1.0925484305920792;
    pub const C3: f32 = 0.94617469575755997;
    pub const C4: f32 = 0.31539156525251999;
    pub const C5: f32 = 0.54627421529603959;
    pub const C6: f32 = 0.59004358992664352;
    pub const C7: f32 = 2.8906114426405538;
    pub const C8: f32 = 0.45704579946446572;
    pub const C9: f32 = 0.3731763325901154;
    pub const C10: f32 = 1.4453057213202769;
}
use constants::*;

/// The 16 SH basis functions at `(x, y, z)` (a unit vector), tcnn ordering and signs.
#[inline(always)]
pub fn sh4(x: f32, y: f32, z: f32) -> [f32; SH4_DIMS] {
    let (xy, xz, yz) = (x * y, x * z, y * z);
    let (x2, y2, z2) = (x * x, y * y, z * z);
    [
        C0,
        -C1 * y,
        C1 * z,
        -C1 * x,
        C2 * xy,
        -C2 * yz,
        C3 * z2 - C4,
        -C2 * xz,
        C5 * x2 - C5 * y2,
        C6 * y * (-3.0 * x2 + y2),
        C7 * xy * z,
        C8 * y * (1.0 - 5.0 * z2),
        C9 * z * (5.0 * z2 - 3.0),
        C8 * x * (1.0 - 5.0 * z2),
        C10 * z * (x2 - y2),
        C6 * x * (-x2 + 3.0 * y2),
    ]
}

/// Encodes `dirs` (unit view directions, not warped) feature-major: coefficient `k` of
/// sample `s` goes to `out[k·ld + s]`.
pub fn encode(dirs: &[[f32; 3]], out: &mut [f32], ld: usize) {
    assert!(dirs.len() <= ld && out.len() >= SH4_DIMS * ld);
    for (s, d) in dirs.iter().enumerate() {
        let [x, y, z] = reference_direction(*d);
        let v = sh4(x, y, z);
        for (k, &val) in v.iter().enumerate() {
            out[k * ld + s] = val;
        }
    }
}

/// Vector-Jacobian product of [`sh4`]: given `d_out` = dL/d(basis), returns dL/d(x, y, z).
/// The polynomials are differentiated as written, off the unit sphere too (no
/// renormalisation is differentiated, as in tcnn).
#[inline(always)]
pub fn sh4_backward(x: f32, y: f32, z: f32, d_out: &[f32; SH4_DIMS]) -> [f32; 3] {
    let (x2, y2, z2) = (x * x, y * y, z * z);
    let g = d_out;
    // Each row: (d/dx, d/dy, d/dz) of basis k.
    let jac: [[f32; 3]; SH4_DIMS] = [
        [0.0, 0.0, 0.0],
        [0.0, -C1, 0.0],
        [0.0, 0.0, C1],
        [-C1, 0.0, 0.0],
        [C2 * y, C2 * x, 0.0],
        [0.0, -C2 * z, -C2 * y],
        [0.0, 0.0, 2.0 * C3 * z],
        [-C2 * z, 0.0, -C2 * x],
        [2.0 * C5 * x, -2.0 * C5 * y, 0.0],
        [-6.0 * C6 * x * y, 3.0 * C6 * (y2 - x2), 0.0],
        [C7 * y * z, C7 * x * z, C7 * x * y],
        [0.0, C8 * (1.0 - 5.0 * z2), -10.0 * C8 * y * z],
        [0.0, 0.0, C9 * (15.0 * z2 - 3.0)],
        [C8 * (1.0 - 5.0 * z2), 0.0, -10.0 * C8 * x * z],
        [2.0 * C10 * x * z, -2.0 * C10 * y * z, C10 * (x2 - y2)],
        [3.0 * C6 * (y2 - x2), 6.0 * C6 * x * y, 0.0],
    ];
    let mut d = [0.0f32; 3];
    for (row, &gk) in jac.iter().zip(g) {
        for c in 0..3 {
            d[c] += row[c] * gk;
        }
    }
    d
}

/// Backward of [`encode`]: accumulates dL/d(direction) into `d_dirs` from the feature-major
/// gradient `d_out` (coefficient `k` of sample `s` at `d_out[k·ld + s]`). The warp round
/// trip of [`reference_direction`] has derivative 1.
pub fn encode_backward(dirs: &[[f32; 3]], d_out: &[f32], ld: usize, d_dirs: &mut [[f32; 3]]) {
    assert!(dirs.len() <= ld && d_out.len() >= SH4_DIMS * ld && d_dirs.len() >= dirs.len());
    for (s, (d, acc)) in dirs.iter().zip(d_dirs.iter_mut()).enumerate() {
        let [x, y, z] = reference_direction(*d);
        let g: [f32; SH4_DIMS] = std::array::from_fn(|k| d_out[k * ld + s]);
        let v = sh4_backward(x, y, z, &g);
        for c in 0..3 {
            acc[c] += v[c];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// dL/d(direction) against central differences of L = Σ_k g_k·sh_k, in f64 around f32
    /// evaluations: a wrong coefficient or sign in any of the 48 partials moves the result
    /// by far more than the tolerance.
    #[test]
    fn backward_matches_finite_differences() {
        let mut rng = crate::rng::Pcg32::new(5, 17);
        for trial in 0..200 {
            let mut u = [0.0f32; 3];
            for c in &mut u {
                *c = rng.next_f32() * 2.0 - 1.0;
            }
            // Unit directions and a few off the sphere (the polynomials don't care).
            if trial % 4 != 0 {
                let n = (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]).sqrt().max(1e-3);
                u = u.map(|c| c / n);
            }
            let g: [f32; SH4_DIMS] = std::array::from_fn(|_| rng.next_f32() * 2.0 - 1.0);
            let loss = |p: [f32; 3]| -> f64 {
                let v = sh4(p[0], p[1], p[2]);
                v.iter().zip(&g).map(|(&a, &b)| a as f64 * b as f64).sum()
            };
            let got = sh4_backward(u[0], u[1], u[2], &g);
            let eps = 1e-2f32;
            for c in 0..3 {
                let (mut p, mut m) = (u, u);
                p[c] += eps;
                m[c] -= eps;
                let fd = (loss(p) - loss(m)) / ((p[c] - m[c]) as f64);
                // Central differences of a cubic: error eps²·|f'''|/6 ≲ 1e-3 here.
                assert!(
                    (got[c] as f64 - fd).abs() < 2e-3 * (1.0 + fd.abs()),
                    "trial {trial} component {c}: analytic {} vs fd {fd}",
                    got[c]
                );
            }
        }
        // encode_backward is the per-sample product over the feature-major layout.
        let dirs = [[0.6f32, 0.0, 0.8], [0.0, -1.0, 0.0]];
        let ld = 3;
        let d_out: Vec<f32> = (0..SH4_DIMS * ld)
            .map(|i| (i as f32 * 0.37).sin())
            .collect();
        let mut d_dirs = [[1.0f32; 3]; 2];
        encode_backward(&dirs, &d_out, ld, &mut d_dirs);
        for (s, d) in dirs.iter().enumerate() {
            let g: [f32; SH4_DIMS] = std::array::from_fn(|k| d_out[k * ld + s]);
            let [x, y, z] = reference_direction(*d);
            let want = sh4_backward(x, y, z, &g);
            for c in 0..3 {
                assert_eq!(d_dirs[s][c], 1.0 + want[c], "accumulates");
            }
        }
    }

    fn close(a: f32, b: f64) -> bool {
        ((a as f64) - b).abs() < 1e-6
    }

    #[test]
    fn hand_worked_directions() {
        // +z: only the zonal (m = 0) functions survive.
        let v = sh4(0.0, 0.0, 1.0);
        let c0 = 1.0 / (2.0 * std::f64::consts::PI.sqrt());
        let want_z = {
            let mut w = [0.0f64; 16];
            w[0] = c0;
            w[2] = 3f64.sqrt() * c0; // sqrt(3)/(2 sqrt(pi))
            w[6] = 5f64.sqrt() * 2.0 / (4.0 * std::f64::consts::PI.sqrt()); // sqrt5 (3-1)/(4 sqrt pi)
            w[12] = 7f64.sqrt() * 2.0 / (4.0 * std::f64::consts::PI.sqrt()); // sqrt7 (5-3)/(4 sqrt pi)
            w
        };
        for k in 0..16 {
            assert!(close(v[k], want_z[k]), "z k={k} {} vs {}", v[k], want_z[k]);
        }
        // +x.
        let v = sh4(1.0, 0.0, 0.0);
        let sp = std::f64::consts::PI.sqrt();
        let mut w = [0.0f64; 16];
        w[0] = c0;
        w[3] = -(3f64.sqrt()) / (2.0 * sp);
        w[6] = -(5f64.sqrt()) / (4.0 * sp);
        w[8] = 15f64.sqrt() / (4.0 * sp);
        w[13] = 42f64.sqrt() / (8.0 * sp);
        w[15] = -(70f64.sqrt()) / (8.0 * sp);
        for k in 0..16 {
            assert!(close(v[k], w[k]), "x k={k} {} vs {}", v[k], w[k]);
        }
        // A generic direction, (1, 2, 2)/3, against the formulas evaluated in f64.
        let (x, y, z) = (1.0f64 / 3.0, 2.0 / 3.0, 2.0 / 3.0);
        let v = sh4(x as f32, y as f32, z as f32);
        let want = [
            c0,
            -(3f64.sqrt()) / (2.0 * sp) * y,
            3f64.sqrt() / (2.0 * sp) * z,
            -(3f64.sqrt()) / (2.0 * sp) * x,
            15f64.sqrt() / (2.0 * sp) * x * y,
            -(15f64.sqrt()) / (2.0 * sp) * y * z,
            5f64.sqrt() * (3.0 * z * z - 1.0) / (4.0 * sp),
            -(15f64.sqrt()) / (2.0 * sp) * x * z,
            15f64.sqrt() * (x * x - y * y) / (4.0 * sp),
            70f64.sqrt() * y * (-3.0 * x * x + y * y) / (8.0 * sp),
            105f64.sqrt() * x * y * z / (2.0 * sp),
            42f64.sqrt() * y * (1.0 - 5.0 * z * z) / (8.0 * sp),
            7f64.sqrt() * z * (5.0 * z * z - 3.0) / (4.0 * sp),
            42f64.sqrt() * x * (1.0 - 5.0 * z * z) / (8.0 * sp),
            105f64.sqrt() * z * (x * x - y * y) / (4.0 * sp),
            70f64.sqrt() * x * (-x * x + 3.0 * y * y) / (8.0 * sp),
        ];
        for k in 0..16 {
            assert!(close(v[k], want[k]), "g k={k} {} vs {}", v[k], want[k]);
        }
    }

    /// The basis must be orthonormal on the sphere; a wrong constant or sign-less typo in
    /// any polynomial breaks this. Fibonacci-sphere quadrature with 20 000 points is exact
    /// to ~1e-4 for these low-degree products.
    #[test]
    fn orthonormal_on_sphere() {
        let n = 20_000;
        let mut gram = [[0.0f64; 16]; 16];
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        for i in 0..n {
            let z = 1.0 - (2.0 * i as f64 + 1.0) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = golden * i as f64;
            let v = sh4((r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32);
            for a in 0..16 {
                for b in 0..16 {
                    gram[a][b] += v[a] as f64 * v[b] as f64;
                }
            }
        }
        let area = 4.0 * std::f64::consts::PI / n as f64;
        for (a, row) in gram.iter().enumerate() {
            for (b, &g) in row.iter().enumerate() {
                let want = if a == b { 1.0 } else { 0.0 };
                let got = g * area;
                assert!((got - want).abs() < 2e-3, "gram[{a}][{b}] = {got}");
            }
        }
    }

    #[test]
    fn encode_is_feature_major_and_uses_the_warp_round_trip() {
        let dirs = [[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [1e-9, 0.0, -1.0]];
        let ld = 5;
        let mut out = vec![f32::NAN; SH4_DIMS * ld];
        encode(&dirs, &mut out, ld);
        for (s, d) in dirs.iter().enumerate() {
            let [x, y, z] = reference_direction(*d);
            let v = sh4(x, y, z);
            for k in 0..16 {
                assert_eq!(out[k * ld + s], v[k]);
            }
        }
        // 1e-9 is lost in (x + 1) − 1, as in the reference.
        assert_eq!(reference_direction([1e-9, 0.0, 0.0])[0], 0.0);
        assert!(out[4].is_nan(), "padding columns untouched");
    }
}
