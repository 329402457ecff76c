//! Training's coarse march: while a scene's rays cross fog, each sample stands for several
//! of the reference's steps.
//!
//! A step trains a fixed number of samples (the reference's 2^18), so its rays are that
//! number over the samples a ray reaches the loss with. Early in a 360° capture the grid is
//! still full (the room's volume is fog the network has not emptied yet), every ray keeps
//! most of its ~1000 steps, and a step trains a few hundred rays: on two cores the first
//! ten minutes see about 1 % of the capture's pixels once. Marching `k` steps at a time
//! divides a ray's samples by `k` and multiplies the rays a step by `k`: the same volume
//! rendering integral on a coarser lattice, each sample's `dt` `k` steps long, the start
//! jittered over the whole stride. As the network empties the room, the rays shorten at the
//! reference's step, the stride falls back to 1 and training marches as the reference does.
//!
//! It is an aid to training only: the model, its grid and how it renders are the
//! reference's. It is counted, never timed (a seed gives the same model), and a GPU keeps
//! the reference's march, where a step costs milliseconds.

/// The coarsest stride, `2^MAX_STRIDE_LOG2` of the reference's steps.
pub const MAX_STRIDE_LOG2: u32 = 3;

/// The stride of a scene's next step: the largest power of two `k ≤ 2^MAX_STRIDE_LOG2` with
/// `k · target` at most the samples a ray would have reached the loss with at the
/// reference's step, estimated from this step (`rays` rays, `used` samples at `stride`).
/// `target` `None` (or 0) keeps the reference's step; a step that trained no ray keeps its
/// stride.
pub fn next_stride(target: Option<u32>, stride: u32, rays: u64, used: u64) -> u32 {
    let Some(target) = target.filter(|&t| t > 0) else {
        return 1;
    };
    if rays == 0 {
        return stride;
    }
    let fine = used as f64 * stride as f64 / rays as f64;
    let mut k = 1u32;
    while k < 1 << MAX_STRIDE_LOG2 && fine >= (2 * k) as f64 * target as f64 {
        k *= 2;
    }
    k
}

/// The samples `measured` (at `stride`) would have been at `next` instead: what the rays a
/// batch adapt to when the stride changes, so that the first step at a new stride is not
/// sized for the old one.
pub fn at_stride(measured: u64, stride: u32, next: u32) -> u64 {
    measured * stride as u64 / next.max(1) as u64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_stride_keeps_a_ray_between_one_and_two_targets() {
        // 1000 rays of 900 samples at the reference's step, aim 64: 900 ≥ 8·64 → 8.
        assert_eq!(next_stride(Some(64), 1, 1000, 900_000), 8);
        // The same rays at stride 8 (112.5 samples each) say the same.
        assert_eq!(next_stride(Some(64), 8, 1000, 112_500), 8);
        // 300 samples a ray: 4 (256 ≤ 300 < 512).
        assert_eq!(next_stride(Some(64), 1, 10, 3000), 4);
        // Rays of 127 samples keep the reference's step; 128 take 2.
        assert_eq!(next_stride(Some(64), 1, 1, 127), 1);
        assert_eq!(next_stride(Some(64), 1, 1, 128), 2);
        // Never past the coarsest stride.
        assert_eq!(next_stride(Some(1), 1, 1, 1 << 20), 1 << MAX_STRIDE_LOG2);
        // No aim: the reference's; no rays: unchanged.
        assert_eq!(next_stride(None, 4, 1, 1 << 20), 1);
        assert_eq!(next_stride(Some(0), 4, 1, 1 << 20), 1);
        assert_eq!(next_stride(Some(64), 4, 0, 0), 4);
    }

    #[test]
    fn samples_rescale_to_the_next_stride() {
        assert_eq!(at_stride(1000, 1, 8), 125);
        assert_eq!(at_stride(125, 8, 1), 1000);
        assert_eq!(at_stride(1000, 2, 2), 1000);
    }
}
