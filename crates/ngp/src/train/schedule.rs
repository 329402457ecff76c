//! The schedule both trainers follow, so that the CPU engine and the GPU backend draw the
//! same rays and train the same scenes for a seed: which scenes a step trains, how rays
//! per batch adapt (the reference's), each scene's starting occupancy grid, and the seed
//! mixer every stream of a step derives from.

use crate::data::Dataset;
use crate::occupancy::OccupancyGrid;
use crate::rng::Pcg32;

/// How the scenes of a multi-scene model share the steps.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Schedule {
    /// Every batch mixes rays of all scenes (our default).
    Mixed,
    /// One scene per step, drawn at random (the StegoNGP paper's Algorithm 1).
    RandomScene,
}

impl Schedule {
    /// The name `train --schedule` takes and reports print.
    pub fn name(self) -> &'static str {
        match self {
            Schedule::Mixed => "mixed",
            Schedule::RandomScene => "random-scene",
        }
    }
}

impl crate::choice::Choice for Schedule {
    const ALL: &'static [Self] = &[Schedule::Mixed, Schedule::RandomScene];
    fn name(self) -> &'static str {
        Schedule::name(self)
    }
    fn help(self) -> &'static str {
        match self {
            Schedule::Mixed => "every batch mixes rays of all scenes (our default)",
            Schedule::RandomScene => {
                "one scene per step, drawn at random (the StegoNGP paper's Algorithm 1)"
            }
        }
    }
}

impl std::fmt::Display for Schedule {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The reference adapts rays per batch in multiples of this (`BATCH_SIZE_GRANULARITY`).
const RAY_GRANULARITY: u32 = 256;
/// Most rays per batch (the reference's cap; the GPU's too).
pub const MAX_RAYS_PER_BATCH: u32 = 1 << 18;
/// Rays of the first step: the reference starts at 4096 rays for its 2^18-sample target, i.e.
/// 64 samples a ray; a smaller target starts at the same ratio.
pub fn initial_rays_per_batch(batch_samples: u32) -> u32 {
    let rays = (4096u64 * batch_samples as u64) >> 18;
    (rays as u32)
        .div_ceil(RAY_GRANULARITY)
        .max(1)
        .saturating_mul(RAY_GRANULARITY)
        .min(MAX_RAYS_PER_BATCH)
}

/// The reference's `update_after_training`: scale the ray count by target / measured samples,
/// round up to a multiple of 256, cap at 2^18.
pub fn next_rays_per_batch(rays: u32, batch_samples: u32, measured: u64) -> u32 {
    let r = (rays as f64 * batch_samples as f64 / measured.max(1) as f64) as u64;
    (r.div_ceil(RAY_GRANULARITY as u64).max(1) * RAY_GRANULARITY as u64)
        .min(MAX_RAYS_PER_BATCH as u64) as u32
}

/// A scene's occupancy grid before its first step (the GPU trainer's too): every cell no
/// training camera sees culled, as the reference does. A hidden scene in a larger cover box
/// keeps the whole box: trained empty outside its own content under its key, the network
/// learns that features met at random are empty space — what makes a wrong key, whose grid
/// is cut to the scene's box like the key holder's, render close to an empty image
/// (measured on fox + text, benchmarks/stego.md, "The key's box"; confining training to the box loses it).
pub fn starting_grid(aabb_scale: u32, data: &Dataset) -> OccupancyGrid {
    let mut grid = OccupancyGrid::new(aabb_scale);
    let cams: Vec<_> = data.frames.iter().map(|f| f.camera.clone()).collect();
    grid.mark_untrained(&cams);
    grid
}

/// Also the GPU trainer's seeds, so both backends draw the same rays for a seed.
pub fn mix(a: u64, b: u64) -> u64 {
    // splitmix64 of a combination: decorrelates (seed, step, scene) streams.
    let mut z = a
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(b)
        .wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The scenes step `step` of a trainer seeded `seed` trains, in order: scene 0 alone for
/// its first `solo_steps` steps, then all of them (mixed) or one drawn for the step (random
/// scene). Also the GPU trainer's, so both backends train the same scenes.
pub fn step_scenes(
    schedule: Schedule,
    solo_steps: u32,
    seed: u64,
    step: u32,
    n_scenes: usize,
) -> Vec<usize> {
    if step < solo_steps {
        return vec![0];
    }
    match schedule {
        Schedule::Mixed => (0..n_scenes).collect(),
        Schedule::RandomScene => {
            let mut r = Pcg32::new(mix(seed, step as u64), 0x5ce7e);
            vec![r.below(n_scenes as u32) as usize]
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rays_per_batch_follow_the_reference() {
        // 2^18 target: the reference's 4096 start.
        assert_eq!(initial_rays_per_batch(1 << 18), 4096);
        assert_eq!(initial_rays_per_batch(1 << 16), 1024);
        // Small targets still start at one granule.
        assert_eq!(initial_rays_per_batch(1000), 256);
        // 4096 rays gave 2^17 samples for a 2^18 target: twice the rays.
        assert_eq!(next_rays_per_batch(4096, 1 << 18, 1 << 17), 8192);
        // 1000 × 65536 / 70000 = 936.2 → 936 → next multiple of 256 = 1024.
        assert_eq!(next_rays_per_batch(1000, 65536, 70000), 1024);
        // Capped at 2^18, never below one granule.
        assert_eq!(next_rays_per_batch(1 << 17, 1 << 18, 1), 1 << 18);
        assert_eq!(next_rays_per_batch(256, 1, 1 << 20), 256);
    }
}
