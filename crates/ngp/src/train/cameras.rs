//! Camera refinement: per-image rotation and translation offsets of a scene's training
//! cameras, learned from the photometric loss with their own Adam while the field trains,
//! so that poses a little wrong (an ordinary COLMAP run) do not train to fog.
//!
//! A refined ray starts at the camera's centre moved by the image's translation `τ`, and its
//! direction is turned by the image's rotation vector `ω` about that centre. A sample at
//! distance `t` along the ray sits at `o + t·d`, so its position's gradient `g` (from
//! [`NerfNetwork::position_gradient`](crate::network::nerf::NerfNetwork::position_gradient))
//! gives the ray `∂L/∂o = Σ g` and `∂L/∂d = Σ t·g`; a small turn `δ` moves `d` by `δ × d`,
//! so `∂L/∂ω = d × ∂L/∂d`. The view-dependent colour's own part is left out.
//!
//! The optimiser follows instant-ngp's `optimize_extrinsics` (read for its facts): each
//! image's gradient scaled as if it had the whole batch, an L2 pull of the offsets towards
//! zero, and a step size that falls by a third every 128 updates down to a floor; it sums
//! the gradients of several steps into an update, which is an option here. Ours besides:
//! the offsets' mean is taken off after every update (the scene's frame stays the given
//! cameras'), and the translation's step is the rotation's times the box's side
//! (benchmarks/engine.md, "Camera refinement").

use crate::camera::Ray;
use crate::error::{Error, Result};
use crate::geometry::{add, cross, dot, rotate_by_vector, sub};

/// How the cameras learn.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraRefinement {
    /// Adam's step size at the start (radians for the rotation; for the translation, times
    /// the box's side in scene units).
    pub learning_rate: f32,
    /// The lowest the step size falls to.
    pub min_learning_rate: f32,
    /// The L2 weight pulling every offset back to zero.
    pub l2: f32,
    /// Steps whose gradients are summed into one update.
    pub steps_per_update: u32,
}

impl Default for CameraRefinement {
    /// instant-ngp's step size (1e-3, falling to a thousandth of the field's 1e-2) and L2
    /// (1e-4), but an update every step, not every 16: a CPU takes about two steps a
    /// second, and in the noise-bound regime Adam's own averaging beats summing steps
    /// (a generated 64 px object, 1.25° off on average: a minute took 0.12° off with an
    /// update every 16 steps, 0.50° with one every step).
    fn default() -> Self {
        CameraRefinement {
            learning_rate: 1e-3,
            min_learning_rate: 1e-5,
            l2: 1e-4,
            steps_per_update: 1,
        }
    }
}

const BETA1: f32 = 0.9;
const BETA2: f32 = 0.99;
const EPSILON: f32 = 1e-8;
/// Updates between two falls of the step size, and the fall.
const DECAY_UPDATES: u32 = 128;
const DECAY: f32 = 0.33;

/// An image's offsets: the rotation vector (radians) then the translation (scene units).
pub type Offset = [f32; 6];

/// The offsets of one scene's training cameras and their optimiser.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraRefiner {
    pub config: CameraRefinement,
    /// The side of the scene's box: the translation's step size is the rotation's times it,
    /// so that a step moves a camera by the same share of any scene.
    box_side: f32,
    offsets: Vec<Offset>,
    m: Vec<Offset>,
    v: Vec<Offset>,
    updates: u32,
    /// Gradients summed since the last update, and the steps they came from.
    pending: Vec<[f64; 6]>,
    pending_steps: u32,
}

impl CameraRefiner {
    pub fn new(n_images: usize, box_side: f32, config: CameraRefinement) -> Result<Self> {
        if !(config.learning_rate > 0.0
            && config.min_learning_rate >= 0.0
            && config.l2 >= 0.0
            && config.steps_per_update > 0)
        {
            return Err(Error::Config(format!(
                "camera refinement needs a positive learning rate and update interval, a \
                 non-negative floor and L2; got {config:?}"
            )));
        }
        Ok(CameraRefiner {
            config,
            box_side,
            offsets: vec![[0.0; 6]; n_images],
            m: vec![[0.0; 6]; n_images],
            v: vec![[0.0; 6]; n_images],
            updates: 0,
            pending: vec![[0.0; 6]; n_images],
            pending_steps: 0,
        })
    }

    /// Every image's offsets, in the dataset's order.
    pub fn offsets(&self) -> &[Offset] {
        &self.offsets
    }

    /// Updates made so far.
    pub fn updates(&self) -> u32 {
        self.updates
    }

    /// Image `image`'s ray as its refined camera sees it.
    pub fn ray(&self, image: usize, ray: Ray) -> Ray {
        let o = &self.offsets[image];
        Ray {
            o: add(ray.o, [o[3], o[4], o[5]]),
            d: rotate_by_vector([o[0], o[1], o[2]], ray.d),
        }
    }

    /// Adds one step's gradients (per image, as [`ray_gradient`] sums them), and updates the
    /// offsets when the interval is full.
    pub fn add_step<'a>(&mut self, grads: impl IntoIterator<Item = &'a [[f64; 6]]>) {
        for g in grads {
            for (p, gi) in self.pending.iter_mut().zip(g) {
                for k in 0..6 {
                    p[k] += gi[k];
                }
            }
        }
        self.pending_steps += 1;
        if self.pending_steps >= self.config.steps_per_update {
            self.update();
        }
    }

    /// One Adam step of every image's offsets on the pending gradients.
    fn update(&mut self) {
        let c = self.config;
        let n_images = self.offsets.len() as f64;
        let scale = n_images / self.pending_steps as f64;
        let lr = (c.learning_rate * DECAY.powi((self.updates / DECAY_UPDATES) as i32))
            .max(c.min_learning_rate);
        self.updates += 1;
        let t = self.updates as i32;
        let (b1, b2) = (1.0 - BETA1.powi(t), 1.0 - BETA2.powi(t));
        for i in 0..self.offsets.len() {
            for k in 0..6 {
                let g = (self.pending[i][k] * scale) as f32 + c.l2 * self.offsets[i][k];
                let m = BETA1 * self.m[i][k] + (1.0 - BETA1) * g;
                let v = BETA2 * self.v[i][k] + (1.0 - BETA2) * g * g;
                self.m[i][k] = m;
                self.v[i][k] = v;
                let lr = if k < 3 { lr } else { lr * self.box_side };
                self.offsets[i][k] -= lr * (m / b1) / ((v / b2).sqrt() + EPSILON);
            }
            self.pending[i] = [0.0; 6];
        }
        self.pending_steps = 0;
        self.recentre();
    }

    /// Takes the offsets' mean off every image's: all the cameras turning or moving
    /// together is the scene's frame moving, which the photos cannot see and which the
    /// held-out views, scored with their given cameras, would pay for.
    fn recentre(&mut self) {
        let n = self.offsets.len() as f64;
        let mut mean = [0f64; 6];
        for o in &self.offsets {
            for k in 0..6 {
                mean[k] += o[k] as f64 / n;
            }
        }
        for o in &mut self.offsets {
            for k in 0..6 {
                o[k] -= mean[k] as f32;
            }
        }
    }

    /// The refiner's whole state, for a training state ([`super::state`]).
    pub fn save(&self) -> RefinerState {
        let flat = |v: &[Offset]| v.iter().flatten().copied().collect();
        RefinerState {
            offsets: flat(&self.offsets),
            m: flat(&self.m),
            v: flat(&self.v),
            updates: self.updates,
            pending: self.pending.iter().flatten().map(|g| g.to_bits()).collect(),
            pending_steps: self.pending_steps,
        }
    }

    /// Takes back a [`save`](Self::save) of a refiner of as many images; `None` where the
    /// lengths differ.
    pub fn restore(&mut self, s: &RefinerState) -> Option<()> {
        let n = self.offsets.len() * 6;
        if [s.offsets.len(), s.m.len(), s.v.len(), s.pending.len()] != [n; 4] {
            return None;
        }
        let unflat = |from: &[f32], to: &mut [Offset]| {
            for (t, f) in to.iter_mut().zip(from.chunks_exact(6)) {
                t.copy_from_slice(f);
            }
        };
        unflat(&s.offsets, &mut self.offsets);
        unflat(&s.m, &mut self.m);
        unflat(&s.v, &mut self.v);
        for (t, f) in self.pending.iter_mut().zip(s.pending.chunks_exact(6)) {
            for k in 0..6 {
                t[k] = f64::from_bits(f[k]);
            }
        }
        self.updates = s.updates;
        self.pending_steps = s.pending_steps;
        Some(())
    }
}

/// A [`CameraRefiner`]'s state, flat: per image six values of each.
#[derive(Clone, Debug, PartialEq)]
pub struct RefinerState {
    pub offsets: Vec<f32>,
    pub m: Vec<f32>,
    pub v: Vec<f32>,
    pub updates: u32,
    /// The pending gradients' f64 bits.
    pub pending: Vec<u64>,
    pub pending_steps: u32,
}

/// The gradient of one refined ray's loss against its camera's offsets (`[ω, τ]`), from its
/// samples' positions `pos` in the unit cube of a box `[lo, lo + size]` and their gradients
/// `d_pos` there. `o` and `d` are the ray as marched.
pub fn ray_gradient(
    o: [f32; 3],
    d: [f32; 3],
    lo: [f32; 3],
    size: [f32; 3],
    pos: &[[f32; 3]],
    d_pos: &[[f32; 3]],
) -> [f64; 6] {
    let (mut g_o, mut g_d) = ([0f32; 3], [0f32; 3]);
    for (p, gp) in pos.iter().zip(d_pos) {
        let mut world = [0f32; 3];
        let mut g = [0f32; 3];
        for k in 0..3 {
            world[k] = lo[k] + p[k] * size[k];
            g[k] = gp[k] / size[k];
        }
        let t = dot(sub(world, o), d);
        for k in 0..3 {
            g_o[k] += g[k];
            g_d[k] += t * g[k];
        }
    }
    let r = cross(d, g_d);
    [r[0], r[1], r[2], g_o[0], g_o[1], g_o[2]].map(f64::from)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::normalize;

    /// A loss that is a smooth function of where a ray's samples fall: the analytic
    /// offsets' gradient against central differences of the offsets themselves.
    #[test]
    fn ray_gradient_matches_finite_differences_of_the_offsets() {
        let (lo, size) = ([-1.5f32; 3], [4.0f32; 3]);
        // L = Σ_j φ(p_j), φ(p) = sin(3x)·y + z², samples at fixed distances along the ray.
        let phi_grad = |p: [f32; 3]| -> [f32; 3] {
            [
                3.0 * (3.0 * p[0]).cos() * p[1],
                (3.0 * p[0]).sin(),
                2.0 * p[2],
            ]
        };
        let ts = [0.5f32, 0.9, 1.4, 2.0];
        let base = Ray {
            o: [0.2, -0.1, 0.3],
            d: normalize([0.3f32, 0.8, -0.5]),
        };
        let unit = |w: [f32; 3]| [0, 1, 2].map(|k| (w[k] - lo[k]) / size[k]);
        let loss = |off: Offset| -> f64 {
            let mut r = CameraRefiner::new(1, 1.0, CameraRefinement::default()).unwrap();
            r.offsets[0] = off;
            let ray = r.ray(0, base);
            ts.iter()
                .map(|&t| {
                    let p = unit(add(ray.o, ray.d.map(|c| c * t)));
                    ((3.0 * p[0] as f64).sin() * p[1] as f64) + (p[2] as f64).powi(2)
                })
                .sum()
        };
        let off0: Offset = [0.01, -0.02, 0.015, 0.03, -0.01, 0.02];
        let mut r = CameraRefiner::new(1, 1.0, CameraRefinement::default()).unwrap();
        r.offsets[0] = off0;
        let ray = r.ray(0, base);
        let pos: Vec<[f32; 3]> = ts
            .iter()
            .map(|&t| unit(add(ray.o, ray.d.map(|c| c * t))))
            .collect();
        let d_pos: Vec<[f32; 3]> = pos.iter().map(|&p| phi_grad(p)).collect();
        let g = ray_gradient(ray.o, ray.d, lo, size, &pos, &d_pos);
        let h = 1e-3f32;
        for k in 0..6 {
            let (mut p, mut m) = (off0, off0);
            p[k] += h;
            m[k] -= h;
            let fd = (loss(p) - loss(m)) / (2.0 * h as f64);
            // The rotation's gradient is the left perturbation's, exact at ω = 0 and off
            // by O(|ω|) elsewhere: a few per cent at these offsets.
            let tol = if k < 3 {
                0.05 * fd.abs() + 1e-3
            } else {
                1e-2 * fd.abs() + 1e-4
            };
            assert!(
                (fd - g[k]).abs() <= tol,
                "offset {k}: fd {fd} vs analytic {}",
                g[k]
            );
            assert!(g[k].abs() > 1e-3, "offset {k}: no gradient");
        }
    }

    /// On a loss whose minimum is a known offset, the updates find it; the offsets' mean
    /// stays at zero.
    #[test]
    fn adam_moves_the_offsets_to_the_loss_minimum() {
        let cfg = CameraRefinement {
            l2: 0.0,
            steps_per_update: 2,
            ..Default::default()
        };
        let mut r = CameraRefiner::new(2, 1.0, cfg).unwrap();
        // Zero-mean targets: the refiner keeps the offsets' mean at zero.
        let t0: Offset = [0.02, -0.01, 0.005, 0.03, 0.0, -0.02];
        let target: [Offset; 2] = [t0, t0.map(|v| -v)];
        for _ in 0..2 * 300 {
            // L = Σ ½ (x − target)², per image; the refiner scales by its image count.
            let g: Vec<[f64; 6]> = (0..2)
                .map(|i| [0, 1, 2, 3, 4, 5].map(|k| (r.offsets[i][k] - target[i][k]) as f64 / 2.0))
                .collect();
            r.add_step([g.as_slice()]);
        }
        assert_eq!(r.updates(), 300);
        for k in 0..6 {
            assert!(
                (r.offsets[0][k] + r.offsets[1][k]).abs() < 1e-7,
                "mean off zero"
            );
        }
        for (i, (got, want)) in r.offsets.iter().zip(&target).enumerate() {
            for (k, (g, w)) in got.iter().zip(want).enumerate() {
                assert!(
                    (g - w).abs() < 2e-3,
                    "image {i}, offset {k}: {g} against {w}"
                );
            }
        }
        // Saved and restored, the state is the same to the bit.
        let mut back = CameraRefiner::new(2, 1.0, cfg).unwrap();
        back.restore(&r.save()).unwrap();
        assert_eq!(back, r);
        assert!(
            CameraRefiner::new(3, 1.0, cfg)
                .unwrap()
                .restore(&r.save())
                .is_none()
        );
    }

    #[test]
    fn a_zero_offset_leaves_the_ray_and_bad_settings_are_refused() {
        let r = CameraRefiner::new(1, 1.0, CameraRefinement::default()).unwrap();
        let ray = Ray {
            o: [1.0, 2.0, 3.0],
            d: normalize([0.0f32, 0.6, 0.8]),
        };
        let same = r.ray(0, ray);
        assert_eq!((same.o, same.d), (ray.o, ray.d));
        for bad in [
            CameraRefinement {
                learning_rate: 0.0,
                ..Default::default()
            },
            CameraRefinement {
                steps_per_update: 0,
                ..Default::default()
            },
            CameraRefinement {
                l2: -1.0,
                ..Default::default()
            },
        ] {
            assert!(CameraRefiner::new(1, 1.0, bad).is_err(), "{bad:?}");
        }
    }
}
