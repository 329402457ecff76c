//! Small 3-vector and rotation algebra on plain arrays, in `f32` or `f64`: the one copy that
//! the engine's cameras, the meshes, the capture import, the generated scenes, the camera
//! paths and the tests share. Each function evaluates in the order written, so a caller's
//! numbers are the ones its own copy gave (no fused multiply-add, no reassociation).

use std::ops::{Add, Div, Mul, Sub};

/// `f32` or `f64`.
pub trait Real:
    Copy
    + PartialOrd
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
{
    const ZERO: Self;
    const ONE: Self;
    const TWO: Self;
    fn sqrt(self) -> Self;
}

impl Real for f32 {
    const ZERO: f32 = 0.0;
    const ONE: f32 = 1.0;
    const TWO: f32 = 2.0;
    #[inline]
    fn sqrt(self) -> f32 {
        f32::sqrt(self)
    }
}

impl Real for f64 {
    const ZERO: f64 = 0.0;
    const ONE: f64 = 1.0;
    const TWO: f64 = 2.0;
    #[inline]
    fn sqrt(self) -> f64 {
        f64::sqrt(self)
    }
}

#[inline]
pub fn add<T: Real>(a: [T; 3], b: [T; 3]) -> [T; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

#[inline]
pub fn sub<T: Real>(a: [T; 3], b: [T; 3]) -> [T; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[inline]
pub fn scale<T: Real>(a: [T; 3], s: T) -> [T; 3] {
    [a[0] * s, a[1] * s, a[2] * s]
}

#[inline]
pub fn dot<T: Real>(a: [T; 3], b: [T; 3]) -> T {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline]
pub fn cross<T: Real>(a: [T; 3], b: [T; 3]) -> [T; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// The Euclidean length.
#[inline]
pub fn norm<T: Real>(a: [T; 3]) -> T {
    dot(a, a).sqrt()
}

#[inline]
pub fn dist<T: Real>(a: [T; 3], b: [T; 3]) -> T {
    norm(sub(a, b))
}

/// `a` over its length (each component divided by it); a zero vector stays as it is.
#[inline]
pub fn normalize<T: Real>(a: [T; 3]) -> [T; 3] {
    let n = norm(a);
    if n > T::ZERO {
        [a[0] / n, a[1] / n, a[2] / n]
    } else {
        a
    }
}

/// `a` times the reciprocal of its length (one division, three products: it rounds
/// differently from [`normalize`]); a zero vector stays as it is. The generated scenes and
/// the camera paths were made with it, so their images stay the bytes they were.
#[inline]
pub fn normalize_by_reciprocal<T: Real>(a: [T; 3]) -> [T; 3] {
    let n = norm(a);
    if n > T::ZERO { scale(a, T::ONE / n) } else { a }
}

/// The rotation matrix of a unit quaternion (w, x, y, z), written as COLMAP's
/// `qvec2rotmat` (the capture import's poses depend on its rounding).
pub fn quat_to_rotation<T: Real>(q: [T; 4]) -> [[T; 3]; 3] {
    let [w, x, y, z] = q;
    let two = T::TWO;
    [
        [
            T::ONE - two * y * y - two * z * z,
            two * x * y - two * w * z,
            two * z * x + two * w * y,
        ],
        [
            two * x * y + two * w * z,
            T::ONE - two * x * x - two * z * z,
            two * y * z - two * w * x,
        ],
        [
            two * z * x - two * w * y,
            two * y * z + two * w * x,
            T::ONE - two * x * x - two * y * y,
        ],
    ]
}

/// `v` turned by the rotation vector `w` (axis `w/|w|`, angle `|w|` radians), by
/// Rodrigues' formula; `v` itself, to the bit, when `w` is zero.
pub fn rotate_by_vector(w: [f32; 3], v: [f32; 3]) -> [f32; 3] {
    let angle = norm(w);
    if angle == 0.0 {
        return v;
    }
    let k = scale(w, 1.0 / angle);
    let (sin, cos) = angle.sin_cos();
    let kv = cross(k, v);
    let along = dot(k, v) * (1.0 - cos);
    [0, 1, 2].map(|i| v[i] * cos + kv[i] * sin + k[i] * along)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn products_by_hand() {
        assert_eq!(dot([1.0f32, 2.0, 3.0], [4.0, -5.0, 6.0]), 12.0);
        assert_eq!(cross([1.0f64, 0.0, 0.0], [0.0, 1.0, 0.0]), [0.0, 0.0, 1.0]);
        assert_eq!(cross([0.0f32, 1.0, 0.0], [1.0, 0.0, 0.0]), [0.0, 0.0, -1.0]);
        assert_eq!(normalize([3.0f32, 0.0, 4.0]), [0.6, 0.0, 0.8]);
        assert_eq!(normalize([0.0f64; 3]), [0.0; 3], "zero stays zero");
        assert_eq!(dist([1.0f32, 1.0, 1.0], [1.0, 4.0, 5.0]), 5.0);
    }

    /// A quarter turn about z takes x to y; the identity quaternion is the identity.
    #[test]
    fn quaternions_by_hand() {
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let r = quat_to_rotation([h, 0.0, 0.0, h]);
        let x = [r[0][0], r[1][0], r[2][0]];
        assert!(dist(x, [0.0, 1.0, 0.0]) < 1e-12, "{r:?}");
        assert_eq!(
            quat_to_rotation([1.0f32, 0.0, 0.0, 0.0]),
            [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
        );
    }

    /// A quarter turn about z takes x to y, as the quaternion does; no turn is no change.
    #[test]
    fn rotation_vectors_by_hand() {
        let q = std::f32::consts::FRAC_PI_2;
        assert!(
            dist(
                rotate_by_vector([0.0, 0.0, q], [1.0, 0.0, 0.0]),
                [0.0, 1.0, 0.0]
            ) < 1e-6
        );
        assert!(
            dist(
                rotate_by_vector([q, 0.0, 0.0], [0.0, 1.0, 0.0]),
                [0.0, 0.0, 1.0]
            ) < 1e-6
        );
        let v = [0.3f32, -0.7, 0.2];
        assert_eq!(rotate_by_vector([0.0; 3], v), v);
        let w = [0.1f32, -0.2, 0.3];
        let turned = rotate_by_vector(w, v);
        assert!(
            (norm(turned) - norm(v)).abs() < 1e-6,
            "a turn keeps the length"
        );
        assert!(
            dist(rotate_by_vector(scale(w, -1.0), turned), v) < 1e-6,
            "and undoes"
        );
    }
}
