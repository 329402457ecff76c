//! Cameras made a little wrong on purpose, as an ordinary calibration leaves them, and how far
//! a refinement brought them back: camera refinement's test and benchmark share these.

use crate::geometry::rotation_angle_deg;
use ngp::camera::Camera;
use ngp::data::Dataset;
use ngp::geometry::{add, dist, dot, normalize, rotate_by_vector, scale};
use ngp::rng::Pcg32;
use ngp::train::cameras::Offset;

/// How wrong each camera is made: a turn about its centre by an angle drawn uniformly in
/// `degrees` (a random axis), and a shift of its centre by a length drawn in `shift` (a
/// random direction, scene units).
#[derive(Clone, Copy, Debug)]
pub struct Perturbation {
    pub degrees: (f32, f32),
    pub shift: (f32, f32),
    pub seed: u64,
}

/// A random unit vector.
fn direction(rng: &mut Pcg32) -> [f32; 3] {
    loop {
        let v = [0; 3].map(|_: i32| rng.next_f32() * 2.0 - 1.0);
        let n = dot(v, v);
        if n > 1e-4 && n <= 1.0 {
            return normalize(v);
        }
    }
}

/// `c` turned by the rotation vector `w` about its centre and shifted by `t`.
fn moved(c: &Camera, w: [f32; 3], t: [f32; 3]) -> Camera {
    let mut out = c.clone();
    for k in 0..3 {
        let axis = [c.c2w[0][k], c.c2w[1][k], c.c2w[2][k]];
        let turned = rotate_by_vector(w, axis);
        for (r, v) in turned.iter().enumerate() {
            out.c2w[r][k] = *v;
        }
    }
    let p = add(c.position(), t);
    for (r, v) in p.iter().enumerate() {
        out.c2w[r][3] = *v;
    }
    out
}

/// Makes every training camera of `data` wrong by `p`; returns the true cameras.
pub fn perturb(data: &mut Dataset, p: &Perturbation) -> Vec<Camera> {
    let mut rng = Pcg32::new(p.seed, 91);
    let lerp = |(a, b): (f32, f32), u: f32| a + (b - a) * u;
    data.frames
        .iter_mut()
        .map(|f| {
            let truth = f.camera.clone();
            let angle = lerp(p.degrees, rng.next_f32()).to_radians();
            let w = scale(direction(&mut rng), angle);
            let t = scale(direction(&mut rng), lerp(p.shift, rng.next_f32()));
            f.camera = moved(&truth, w, t);
            truth
        })
        .collect()
}

/// The angle between two cameras' orientations, in degrees.
fn angle_between(a: &Camera, b: &Camera) -> f32 {
    // Columns: the cameras' unit axes.
    let rotation = |c: &Camera| {
        let axes = [0, 1, 2].map(|k| c.axis(k));
        [0, 1, 2].map(|r| [0, 1, 2].map(|k| axes[k][r] as f64))
    };
    rotation_angle_deg(&rotation(a), &rotation(b)) as f32
}

/// How far cameras are from the truth: mean turn (degrees) and mean shift (scene units).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseError {
    pub degrees: f32,
    pub shift: f32,
}

/// The error of `given` cameras moved by refinement `offsets` (none: as given) against `truth`.
pub fn pose_error(truth: &[Camera], given: &[Camera], offsets: Option<&[Offset]>) -> PoseError {
    let (mut deg, mut shift) = (0f32, 0f32);
    for (i, (t, g)) in truth.iter().zip(given).enumerate() {
        let refined = match offsets {
            Some(o) => moved(g, [o[i][0], o[i][1], o[i][2]], [o[i][3], o[i][4], o[i][5]]),
            None => g.clone(),
        };
        deg += angle_between(t, &refined);
        shift += dist(t.position(), refined.position());
    }
    let n = truth.len().max(1) as f32;
    PoseError {
        degrees: deg / n,
        shift: shift / n,
    }
}
