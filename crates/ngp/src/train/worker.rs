//! A worker's scratch for a training step: its share of the rays' samples and its partial
//! gradient, allocated once and reused every step. The trainer sums the partials in a fixed
//! order; the hooks' mechanisms act on them before it does.

use super::optimizer::Touched;
use crate::network::nerf::Workspace;

/// Per-worker scratch, allocated once and reused every step.
pub(super) struct Worker {
    pub(super) grad: Vec<f32>,
    pub(super) touched: Touched,
    pub(super) ws: Vec<Workspace>,
    pub(super) pos: Vec<[f32; 3]>,
    pub(super) dir: Vec<[f32; 3]>,
    pub(super) dt: Vec<f32>,
    pub(super) dist: Vec<f32>,
    pub(super) raw: Vec<[f32; 4]>,
    pub(super) d_raw: Vec<[f32; 4]>,
    pub(super) rays: Vec<RayRec>,
    pub(super) wave_pos: Vec<[f32; 3]>,
    pub(super) wave_owner: Vec<(usize, usize)>,
    pub(super) wave_dens: Vec<f32>,
    pub(super) ray_state: Vec<(f32, usize, bool)>,
    /// With camera refinement: the samples' position gradients and, per training image,
    /// the gradient of its camera's offsets summed over this worker's rays.
    pub(super) d_pos: Vec<[f32; 3]>,
    pub(super) cam_grad: Vec<[f64; 6]>,
    pub(super) loss: f64,
    pub(super) n_samples: u64,
    pub(super) n_marched: u64,
    pub(super) n_rays: u64,
}

impl Worker {
    pub(super) fn new(n_params: usize) -> Self {
        Worker {
            grad: crate::pages::zeroed(n_params),
            touched: Touched::new(n_params),
            ws: Vec::new(),
            pos: Vec::new(),
            dir: Vec::new(),
            dt: Vec::new(),
            dist: Vec::new(),
            raw: Vec::new(),
            d_raw: Vec::new(),
            rays: Vec::new(),
            wave_pos: Vec::new(),
            wave_owner: Vec::new(),
            wave_dens: Vec::new(),
            ray_state: Vec::new(),
            d_pos: Vec::new(),
            cam_grad: Vec::new(),
            loss: 0.0,
            n_samples: 0,
            n_marched: 0,
            n_rays: 0,
        }
    }
}

#[derive(Clone, Copy)]
pub(super) struct RayRec {
    pub(super) start: usize,
    pub(super) n: usize,
    pub(super) bg: [f32; 3],
    pub(super) target: [f32; 3],
    /// The training image and the ray as marched (camera refinement's gradient needs them).
    pub(super) image: usize,
    pub(super) o: [f32; 3],
    pub(super) d: [f32; 3],
}
