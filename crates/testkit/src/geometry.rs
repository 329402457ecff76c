//! The geometry a test needs to write a capture by hand (COLMAP stores world-to-camera
//! rotations as quaternions) and to compare recovered poses with known ones (the
//! similarity between two sets of points, the angle between two rotations).

pub use ngp::geometry::{cross, quat_to_rotation};

/// Shepperd's quaternion (w, x, y, z) of a rotation matrix, normalised.
pub fn rot_to_quat(r: &[[f64; 3]; 3]) -> [f64; 4] {
    let tr = r[0][0] + r[1][1] + r[2][2];
    let q = if tr > 0.0 {
        let s = (tr + 1.0).sqrt() * 2.0;
        [
            0.25 * s,
            (r[2][1] - r[1][2]) / s,
            (r[0][2] - r[2][0]) / s,
            (r[1][0] - r[0][1]) / s,
        ]
    } else if r[0][0] > r[1][1] && r[0][0] > r[2][2] {
        let s = (1.0 + r[0][0] - r[1][1] - r[2][2]).sqrt() * 2.0;
        [
            (r[2][1] - r[1][2]) / s,
            0.25 * s,
            (r[0][1] + r[1][0]) / s,
            (r[0][2] + r[2][0]) / s,
        ]
    } else if r[1][1] > r[2][2] {
        let s = (1.0 + r[1][1] - r[0][0] - r[2][2]).sqrt() * 2.0;
        [
            (r[0][2] - r[2][0]) / s,
            (r[0][1] + r[1][0]) / s,
            0.25 * s,
            (r[1][2] + r[2][1]) / s,
        ]
    } else {
        let s = (1.0 + r[2][2] - r[0][0] - r[1][1]).sqrt() * 2.0;
        [
            (r[1][0] - r[0][1]) / s,
            (r[0][2] + r[2][0]) / s,
            (r[1][2] + r[2][1]) / s,
            0.25 * s,
        ]
    };
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    q.map(|v| v / n)
}

/// Eigenvalues and eigenvectors (the columns of the second) of a symmetric 4×4 matrix, by
/// cyclic Jacobi rotations.
fn symmetric_eigen4(mut a: [[f64; 4]; 4]) -> ([f64; 4], [[f64; 4]; 4]) {
    let mut v = [[0.0; 4]; 4];
    for (i, row) in v.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    for _ in 0..64 {
        let off: f64 = (0..4)
            .flat_map(|i| (0..4).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| a[i][j] * a[i][j])
            .sum();
        if off < 1e-30 {
            break;
        }
        for p in 0..4 {
            for q in p + 1..4 {
                if a[p][q] == 0.0 {
                    continue;
                }
                let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let (c, s) = (1.0 / (t * t + 1.0).sqrt(), t / (t * t + 1.0).sqrt());
                for row in a.iter_mut() {
                    let (x, y) = (row[p], row[q]);
                    row[p] = c * x - s * y;
                    row[q] = s * x + c * y;
                }
                let (rp, rq) = (a[p], a[q]);
                a[p] = std::array::from_fn(|k| c * rp[k] - s * rq[k]);
                a[q] = std::array::from_fn(|k| s * rp[k] + c * rq[k]);
                for row in v.iter_mut() {
                    let (x, y) = (row[p], row[q]);
                    row[p] = c * x - s * y;
                    row[q] = s * x + c * y;
                }
            }
        }
    }
    ([a[0][0], a[1][1], a[2][2], a[3][3]], v)
}

/// The similarity that best maps the points `from` onto `to` in least squares (Umeyama's
/// problem; the rotation by Horn's quaternion method, always proper): `(s, R, t)` with
/// `to ≈ s·R·from + t`.
pub fn similarity(from: &[[f64; 3]], to: &[[f64; 3]]) -> (f64, [[f64; 3]; 3], [f64; 3]) {
    assert!(
        from.len() == to.len() && from.len() >= 3,
        "3 or more point pairs"
    );
    let n = from.len() as f64;
    let mean = |ps: &[[f64; 3]]| {
        let mut m = [0.0; 3];
        for p in ps {
            for k in 0..3 {
                m[k] += p[k] / n;
            }
        }
        m
    };
    let (ma, mb) = (mean(from), mean(to));
    let mut sm = [[0.0; 3]; 3];
    let mut var_a = 0.0;
    for (a, b) in from.iter().zip(to) {
        let (a, b) = (
            [0, 1, 2].map(|k| a[k] - ma[k]),
            [0, 1, 2].map(|k| b[k] - mb[k]),
        );
        for i in 0..3 {
            for j in 0..3 {
                sm[i][j] += a[i] * b[j];
            }
        }
        var_a += a.iter().map(|v| v * v).sum::<f64>();
    }
    let [[sxx, sxy, sxz], [syx, syy, syz], [szx, szy, szz]] = sm;
    let nm = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ];
    let (vals, vecs) = symmetric_eigen4(nm);
    let best = (0..4)
        .max_by(|&i, &j| vals[i].total_cmp(&vals[j]))
        .expect("four eigenvalues");
    let q = [0, 1, 2, 3].map(|k| vecs[k][best]);
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    let r = quat_to_rotation(q.map(|v| v / norm));
    let rot = |p: [f64; 3]| [0, 1, 2].map(|i| (0..3).map(|k| r[i][k] * p[k]).sum::<f64>());
    let mut num = 0.0;
    for (a, b) in from.iter().zip(to) {
        let ra = rot([0, 1, 2].map(|k| a[k] - ma[k]));
        num += (0..3).map(|k| ra[k] * (b[k] - mb[k])).sum::<f64>();
    }
    let s = num / var_a;
    let rm = rot(ma);
    (s, r, [0, 1, 2].map(|k| mb[k] - s * rm[k]))
}

/// The angle of the rotation taking `a` to `b`, in degrees.
pub fn rotation_angle_deg(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3]) -> f64 {
    // trace(aᵀ b) = 1 + 2 cos θ
    let tr: f64 = (0..3)
        .map(|i| (0..3).map(|k| a[k][i] * b[k][i]).sum::<f64>())
        .sum();
    ((tr - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quaternions_of_known_rotations() {
        let id = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        assert_eq!(rot_to_quat(&id), [1.0, 0.0, 0.0, 0.0]);
        // 180° about x: every branch but the first.
        let rx = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]];
        assert_eq!(rot_to_quat(&rx), [0.0, 1.0, 0.0, 0.0]);
        let ry = [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]];
        assert_eq!(rot_to_quat(&ry), [0.0, 0.0, 1.0, 0.0]);
        let rz = [[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]];
        assert_eq!(rot_to_quat(&rz), [0.0, 0.0, 0.0, 1.0]);
        // 90° about z: (cos 45°, 0, 0, sin 45°).
        let q = rot_to_quat(&[[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]);
        let h = std::f64::consts::FRAC_1_SQRT_2;
        assert!(
            q.iter()
                .zip([h, 0.0, 0.0, h])
                .all(|(a, b)| (a - b).abs() < 1e-12)
        );
        assert_eq!(cross([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]), [0.0, 0.0, 1.0]);
        for r in [rx, ry, rz] {
            let back = quat_to_rotation(rot_to_quat(&r));
            assert!(rotation_angle_deg(&r, &back) < 1e-6);
        }
    }

    #[test]
    fn a_known_similarity_is_recovered() {
        let q = [0.8f64, 0.1, -0.5, 0.3];
        let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        let r = quat_to_rotation(q.map(|v| v / n));
        let (s, t) = (2.5, [1.0, -3.0, 0.5]);
        let from: Vec<[f64; 3]> = (0..7)
            .map(|i| {
                let f = i as f64;
                [f.sin() * 3.0, (1.3 * f).cos(), 0.2 * f * f - 1.0]
            })
            .collect();
        let to: Vec<[f64; 3]> = from
            .iter()
            .map(|p| [0, 1, 2].map(|i| s * (0..3).map(|k| r[i][k] * p[k]).sum::<f64>() + t[i]))
            .collect();
        let (s2, r2, t2) = similarity(&from, &to);
        assert!((s2 - s).abs() < 1e-9, "{s2}");
        assert!(rotation_angle_deg(&r, &r2) < 1e-6);
        assert!((0..3).all(|k| (t2[k] - t[k]).abs() < 1e-9), "{t2:?}");
        // 90° about z, by hand.
        let rz90 = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
        let id = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        assert!((rotation_angle_deg(&id, &rz90) - 90.0).abs() < 1e-9);
    }
}
