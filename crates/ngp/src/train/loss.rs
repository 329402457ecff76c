//! Training's loss on one ray, as the reference computes it: composite the ray's samples
//! over its random background, instant-ngp's Huber loss against the pixel, its gradient back
//! to every sample's raw outputs, plus the reference's two density regularisers. One
//! definition for every backend (the GPU's loss kernel is tested against it).

use crate::render::composite::{
    TRAIN_MIN_TRANSMITTANCE, composite, composite_backward, huber_loss,
};

/// The reference's loss scale: its gradients reach the optimizer multiplied by 128, which
/// the optimizer divides out. The regularisers below are added *after* that scaling, so
/// their effective size is their constant divided by 128.
pub const REFERENCE_LOSS_SCALE: f32 = 128.0;
/// Pull-up on negative raw density while the grid's mean density is below 0.01
/// (`output_l1_reg_density`): keeps an empty-looking grid from collapsing early.
///
/// Applied only to samples inside occupancy cascade 0 (the unit cube, over which that mean
/// is measured; at aabb 1 the whole box, i.e. exactly the reference). The reference pushes
/// every sample: a scene that never reaches the mean (sparse text, a logo) then keeps the
/// push all run, and in a large box it fills every cascade with fog. Measured on fox ×4 +
/// hidden text (benchmarks/stego.md, "the reference's density guard"): the confined guard keeps
/// the hidden text's thin strokes alive as the reference's does and narrows the cover gap.
pub const DENSITY_PULL_UP: f32 = 1e-4 / REFERENCE_LOSS_SCALE;
/// Push-down on density of samples closer than `NEAR_DISTANCE` to their camera (raw > −10):
/// keeps camera-specific floaters from forming right in front of the lens.
pub const NEAR_PUSH_DOWN: f32 = 1e-4 / REFERENCE_LOSS_SCALE;
/// `near_distance` (ngp units) of the reference's training.
pub const NEAR_DISTANCE: f32 = 0.1;

/// A training ray's loss (the mean over channels) and the samples it used before its
/// transmittance ran out (the others get a zero gradient).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RayLoss {
    pub loss: f32,
    pub n_used: usize,
}

/// Loss and gradient of one training ray. `raw`, `dt` and `dist` are its samples in marching
/// order; `in_cascade0(j)` says whether sample j lies in occupancy cascade 0 (where the
/// density pull-up applies); `loss_norm` scales the loss gradient (scene weight / rays in the
/// batch); `pull_up` is [`DENSITY_PULL_UP`] while the grid's mean density is below 0.01,
/// else 0. Writes `d_raw` for every sample.
#[allow(clippy::too_many_arguments)]
#[inline]
pub fn ray_loss(
    raw: &[[f32; 4]],
    dt: &[f32],
    dist: &[f32],
    in_cascade0: impl Fn(usize) -> bool,
    bg: [f32; 3],
    target: [f32; 3],
    loss_norm: f32,
    pull_up: f32,
    d_raw: &mut [[f32; 4]],
) -> RayLoss {
    let c = composite(raw, dt, dist, 1.0, TRAIN_MIN_TRANSMITTANCE);
    let pred = [
        c.rgb[0] + c.transmittance * bg[0],
        c.rgb[1] + c.transmittance * bg[1],
        c.rgb[2] + c.transmittance * bg[2],
    ];
    let (loss, g) = huber_loss(pred, target);
    let dl = [g[0] * loss_norm, g[1] * loss_norm, g[2] * loss_norm];
    composite_backward(raw, dt, bg, TRAIN_MIN_TRANSMITTANCE, dl, d_raw);
    for j in 0..c.n_used {
        let raw_density = raw[j][3];
        if raw_density < 0.0 && in_cascade0(j) {
            d_raw[j][3] -= pull_up;
        }
        if raw_density > -10.0 && dist[j] < NEAR_DISTANCE {
            d_raw[j][3] += NEAR_PUSH_DOWN;
        }
    }
    RayLoss {
        loss: loss / 3.0,
        n_used: c.n_used,
    }
}
