//! Pinhole cameras with optional OpenCV radial-tangential distortion, in ngp space.
//!
//! Pixel coordinates are continuous: pixel (i, j) covers [i, i+1)×[j, j+1) and its centre is
//! (i+0.5, j+0.5). This is the reference's `uv · resolution` convention, so the principal
//! point and focal lengths scale exactly by 1/n when an image is downscaled n times.

use crate::geometry::{dot, normalize};

/// OpenCV lens distortion (k1, k2 radial; p1, p2 tangential) on normalised image coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Distortion {
    pub k1: f32,
    pub k2: f32,
    pub p1: f32,
    pub p2: f32,
}

impl Distortion {
    /// Forward model offset (du, dv) at undistorted normalised coordinates (u, v), as the
    /// reference's `opencv_lens_distortion_delta`.
    #[inline]
    pub fn delta(&self, u: f32, v: f32) -> (f32, f32) {
        let (u2, uv, v2) = (u * u, u * v, v * v);
        let r2 = u2 + v2;
        let radial = self.k1 * r2 + self.k2 * r2 * r2;
        (
            u * radial + 2.0 * self.p1 * uv + self.p2 * (r2 + 2.0 * u2),
            v * radial + 2.0 * self.p2 * uv + self.p1 * (r2 + 2.0 * v2),
        )
    }

    /// Distorted coordinates of undistorted (u, v).
    #[inline]
    pub fn distort(&self, u: f32, v: f32) -> (f32, f32) {
        let (du, dv) = self.delta(u, v);
        (u + du, v + dv)
    }

    /// Inverse of [`distort`](Self::distort): Newton iterations with a central-difference
    /// Jacobian, the reference's `iterative_lens_undistortion` (100 iterations at most,
    /// stop when the squared step < 1e-10, relative difference step 1e-6).
    pub fn undistort(&self, u: f32, v: f32) -> (f32, f32) {
        let x0 = [u, v];
        let mut x = [u, v];
        for _ in 0..100 {
            let s0 = f32::EPSILON.max((1e-6 * x[0]).abs());
            let s1 = f32::EPSILON.max((1e-6 * x[1]).abs());
            let d = self.delta(x[0], x[1]);
            let d0b = self.delta(x[0] - s0, x[1]);
            let d0f = self.delta(x[0] + s0, x[1]);
            let d1b = self.delta(x[0], x[1] - s1);
            let d1f = self.delta(x[0], x[1] + s1);
            // J[row][col] = ∂(x + delta)_row / ∂x_col.
            let j00 = 1.0 + (d0f.0 - d0b.0) / (2.0 * s0);
            let j01 = (d1f.0 - d1b.0) / (2.0 * s1);
            let j10 = (d0f.1 - d0b.1) / (2.0 * s0);
            let j11 = 1.0 + (d1f.1 - d1b.1) / (2.0 * s1);
            let r = [x[0] + d.0 - x0[0], x[1] + d.1 - x0[1]];
            let det = j00 * j11 - j01 * j10;
            if det == 0.0 || !det.is_finite() {
                break;
            }
            let step = [
                (j11 * r[0] - j01 * r[1]) / det,
                (-j10 * r[0] + j00 * r[1]) / det,
            ];
            x[0] -= step[0];
            x[1] -= step[1];
            if step[0] * step[0] + step[1] * step[1] < 1e-10 {
                break;
            }
        }
        (x[0], x[1])
    }
}

/// A ray in ngp space; `d` has unit length.
#[derive(Clone, Copy, Debug)]
pub struct Ray {
    pub o: [f32; 3],
    pub d: [f32; 3],
}

#[derive(Clone, Debug)]
pub struct Camera {
    /// ngp space, row-major 3×4. Columns 0, 1, 2: camera right, down, forward axes;
    /// column 3: position.
    pub c2w: [[f32; 4]; 3],
    /// Pixels of the (possibly downscaled) image.
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub width: u32,
    pub height: u32,
    pub distortion: Option<Distortion>,
}

impl Camera {
    /// Camera position in ngp space.
    pub fn position(&self) -> [f32; 3] {
        [self.c2w[0][3], self.c2w[1][3], self.c2w[2][3]]
    }

    /// Unit-length camera axis `k` (0 right, 1 down, 2 forward) in ngp space.
    pub fn axis(&self, k: usize) -> [f32; 3] {
        normalize([self.c2w[0][k], self.c2w[1][k], self.c2w[2][k]])
    }

    /// Ray through continuous pixel coordinates (px, py); pixel (i, j)'s centre is
    /// (i+0.5, j+0.5). Lens distortion, when present, is inverted iteratively as the reference
    /// does. The direction is normalised after the rotation (the reference's training rays are
    /// normalised too before marching).
    pub fn ray(&self, px: f32, py: f32) -> Ray {
        let mut u = (px - self.cx) / self.fx;
        let mut v = (py - self.cy) / self.fy;
        if let Some(dist) = &self.distortion {
            (u, v) = dist.undistort(u, v);
        }
        let m = &self.c2w;
        let d = [
            m[0][0] * u + m[0][1] * v + m[0][2],
            m[1][0] * u + m[1][1] * v + m[1][2],
            m[2][0] * u + m[2][1] * v + m[2][2],
        ];
        Ray {
            o: self.position(),
            d: normalize(d),
        }
    }

    /// Continuous pixel coordinates of ngp-space point `p` (with forward distortion), or None
    /// when `p` is not in front of the camera. As the reference's `pos_to_uv`, the rotation is
    /// inverted by a general 3×3 inverse (poses may be slightly non-orthonormal).
    pub fn project(&self, p: [f32; 3]) -> Option<[f32; 2]> {
        let m = &self.c2w;
        let rel = [p[0] - m[0][3], p[1] - m[1][3], p[2] - m[2][3]];
        let c = inverse3_mul(m, rel)?;
        if c[2] <= 0.0 {
            return None;
        }
        let (mut u, mut v) = (c[0] / c[2], c[1] / c[2]);
        if let Some(dist) = &self.distortion {
            (u, v) = dist.distort(u, v);
        }
        Some([u * self.fx + self.cx, v * self.fy + self.cy])
    }

    /// The reference's "does this training view see point p" test used to cull the occupancy
    /// grid at step 0 (`mark_untrained_density_grid`): p in front (direction · forward ≥ 1e-4),
    /// projecting strictly inside the image, and the ray back through that pixel pointing at
    /// p within 1e-3 (distortion is not injective outside the image).
    pub fn sees(&self, p: [f32; 3]) -> bool {
        let o = self.position();
        let dir = normalize([p[0] - o[0], p[1] - o[1], p[2] - o[2]]);
        let fwd = [self.c2w[0][2], self.c2w[1][2], self.c2w[2][2]];
        if dot(dir, fwd) < 1e-4 {
            return false;
        }
        let Some([px, py]) = self.project(p) else {
            return false;
        };
        let (w, h) = (self.width as f32, self.height as f32);
        if !(px > 0.0 && py > 0.0 && px < w && py < h) {
            return false;
        }
        let r = self.ray(px, py);
        let e = [r.d[0] - dir[0], r.d[1] - dir[1], r.d[2] - dir[2]];
        dot(e, e).sqrt() < 1e-3
    }
}

/// Solves R·c = rel for the 3×3 part R of `m` (Cramer's rule).
fn inverse3_mul(m: &[[f32; 4]; 3], r: [f32; 3]) -> Option<[f32; 3]> {
    let col = |k: usize| [m[0][k], m[1][k], m[2][k]];
    let (a, b, c) = (col(0), col(1), col(2));
    let cross = |x: [f32; 3], y: [f32; 3]| {
        [
            x[1] * y[2] - x[2] * y[1],
            x[2] * y[0] - x[0] * y[2],
            x[0] * y[1] - x[1] * y[0],
        ]
    };
    let det = dot(a, cross(b, c));
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    Some([
        dot(r, cross(b, c)) / det,
        dot(a, cross(r, c)) / det,
        dot(a, cross(b, r)) / det,
    ])
}

/// The reference's `nerf_matrix_to_ngp`: negate camera columns 1 and 2 (OpenGL y up, z back →
/// y down, z forward), translation · scale + offset, then cycle rows: ngp (x,y,z) = nerf (y,z,x).
pub fn nerf_to_ngp(m: &[[f32; 4]; 3], scale: f32, offset: [f32; 3]) -> [[f32; 4]; 3] {
    let mut r = *m;
    for row in r.iter_mut() {
        row[1] = -row[1];
        row[2] = -row[2];
    }
    for (i, row) in r.iter_mut().enumerate() {
        row[3] = row[3] * scale + offset[i];
    }
    [r[1], r[2], r[0]]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam(distortion: Option<Distortion>) -> Camera {
        // Right = ngp +y, down = ngp −z, forward = ngp +x (a proper rotation, det +1).
        Camera {
            c2w: [
                [0.0, 0.0, 1.0, 0.1],
                [1.0, 0.0, 0.0, 0.2],
                [0.0, -1.0, 0.0, 0.3],
            ],
            fx: 100.0,
            fy: 120.0,
            cx: 32.0,
            cy: 20.0,
            width: 64,
            height: 48,
            distortion,
        }
    }

    #[test]
    fn principal_point_ray_is_forward_axis() {
        let c = cam(None);
        let r = c.ray(32.0, 20.0);
        assert_eq!(r.o, [0.1, 0.2, 0.3]);
        assert_eq!(r.d, [1.0, 0.0, 0.0]);
        // One focal length right of the principal point: 45° towards camera right (+y).
        let r = c.ray(132.0, 20.0);
        let s = std::f32::consts::FRAC_1_SQRT_2;
        assert!((r.d[0] - s).abs() < 1e-6 && (r.d[1] - s).abs() < 1e-6 && r.d[2] == 0.0);
        // Below the principal point: camera down = ngp −z.
        let r = c.ray(32.0, 140.0);
        assert!(r.d[2] < -0.7);
    }

    #[test]
    fn project_inverts_ray() {
        for dist in [
            None,
            Some(Distortion {
                k1: 0.0578,
                k2: -0.0805,
                p1: -0.00098,
                p2: 0.000156,
            }),
        ] {
            let c = cam(dist);
            for &(px, py) in &[(0.5, 0.5), (10.3, 40.2), (63.5, 47.5), (32.0, 20.0)] {
                let r = c.ray(px, py);
                let p = [
                    r.o[0] + 2.0 * r.d[0],
                    r.o[1] + 2.0 * r.d[1],
                    r.o[2] + 2.0 * r.d[2],
                ];
                let q = c.project(p).unwrap();
                assert!(
                    (q[0] - px).abs() < 2e-3 && (q[1] - py).abs() < 2e-3,
                    "{q:?}"
                );
                assert!(c.sees(p));
            }
            // Behind the camera.
            assert!(c.project([-1.0, 0.2, 0.3]).is_none());
            assert!(!c.sees([-1.0, 0.2, 0.3]));
            // In front but outside the image.
            assert!(!c.sees([1.1, 5.0, 0.3]));
        }
    }

    #[test]
    fn undistort_inverts_distort() {
        // Strong distortion, still invertible over the range tested.
        let d = Distortion {
            k1: -0.2,
            k2: 0.05,
            p1: 0.01,
            p2: -0.02,
        };
        for i in -5..=5 {
            for j in -5..=5 {
                let (u, v) = (i as f32 * 0.1, j as f32 * 0.08);
                let (du, dv) = d.distort(u, v);
                // Distortion must really move points for this to test anything.
                if i != 0 || j != 0 {
                    assert!((du - u).abs() + (dv - v).abs() > 1e-4);
                }
                let (uu, vv) = d.undistort(du, dv);
                assert!((uu - u).abs() < 1e-5 && (vv - v).abs() < 1e-5, "{u},{v}");
            }
        }
        // Hand value of the forward model: u=0.5, v=0: r2=0.25, radial=-0.05+0.003125,
        // du = 0.5·radial + p2·(0.25+0.5), dv = p1·0.25.
        let (du, dv) = d.delta(0.5, 0.0);
        assert!((du - (0.5 * (-0.046875) + (-0.02) * 0.75)).abs() < 1e-7);
        assert!((dv - 0.01 * 0.25).abs() < 1e-8);
    }

    #[test]
    fn distorted_ray_matches_forward_model() {
        let dist = Distortion {
            k1: 0.1,
            k2: -0.03,
            p1: 0.002,
            p2: -0.001,
        };
        let c = cam(Some(dist));
        let r = c.ray(50.0, 5.0);
        // Back to camera coordinates (the rotation is orthonormal: transpose).
        let m = &c.c2w;
        let cc = [0, 1, 2].map(|k| m[0][k] * r.d[0] + m[1][k] * r.d[1] + m[2][k] * r.d[2]);
        let (u, v) = dist.distort(cc[0] / cc[2], cc[1] / cc[2]);
        assert!((u - 18.0 / 100.0).abs() < 1e-5);
        assert!((v + 15.0 / 120.0).abs() < 1e-5);
    }

    #[test]
    fn pose_conversion_by_hand() {
        // nerf pose: identity rotation, position (1, 2, 3).
        let m = [
            [1.0, 0.0, 0.0, 1.0],
            [0.0, 1.0, 0.0, 2.0],
            [0.0, 0.0, 1.0, 3.0],
        ];
        let g = nerf_to_ngp(&m, 0.5, [0.1, 0.2, 0.3]);
        // After column negation rows are (1,0,0 | 0.6), (0,-1,0 | 1.2), (0,0,-1 | 1.8);
        // cycled: ngp rows = nerf rows 1, 2, 0.
        assert_eq!(
            g,
            [
                [0.0, -1.0, 0.0, 1.2],
                [0.0, 0.0, -1.0, 1.8],
                [1.0, 0.0, 0.0, 0.6],
            ]
        );
    }
}
