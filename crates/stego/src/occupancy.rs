//! The key holder's occupancy grid. A hidden scene's grid is never stored (the model's is
//! the cover's), so whoever holds its key rebuilds one from the network under the key's
//! indices: [`KEY_HOLDER_SAMPLES_PER_CELL`] points in every cell (cut to the key's box),
//! then [`KEY_HOLDER_REFINE_SAMPLES`] more near the occupied cells. [`crate::view`] does it
//! on any device (`backend::Device`); the functions here are the CPU engine's, on the
//! engine's primitives ([`OccupancyGrid::rebuild_in_box`],
//! [`OccupancyGrid::refine_near_occupied`], and the network's density, [`log_density_at`]).

use ngp::encoding::LevelIndices;
use ngp::network::nerf::NerfNetwork;
use ngp::occupancy::{OccupancyGrid, RefineReport};
use ngp::render::march::log_density_at;

/// Density samples per cell when a key holder rebuilds a hidden scene's grid. Measured on
/// a plain model of a 200 px text scene (12 views, benchmarks/stego.md, "The key holder's occupancy grid"): against the grid stored
/// by training (33.07 dB), one random point per cell gives 30.25 dB (thin strokes fall
/// between samples and get culled), 4 stratified points 32.92 dB, 8 points 32.97 dB.
pub const KEY_HOLDER_SAMPLES_PER_CELL: usize = 4;

/// Points more per cell, after the rebuild's [`KEY_HOLDER_SAMPLES_PER_CELL`], in the cells
/// next to occupied ones ([`OccupancyGrid::refine_near_occupied`]): 32 in all there. A 800 px
/// text model rendered through its stored grid scores 36.01 dB; through a grid rebuilt with
/// 4 points a cell 32.53 dB (strokes between the points culled), with 32 in every cell 35.72
/// dB in 21 s, with 4 and these near the occupied cells 35.80 dB in 3.9 s, 3.5 % of the
/// cells sampled again (benchmarks/stego.md, "The key holder's grid at 800 px").
pub const KEY_HOLDER_REFINE_SAMPLES: usize = 28;

/// [`OccupancyGrid::refine_near_occupied`] of a rebuilt `grid` with the CPU network's
/// densities under `indices`: the rounds after the first `first_round`.
#[allow(clippy::too_many_arguments)]
pub fn refine_occupancy(
    net: &NerfNetwork,
    params: &[f32],
    indices: &LevelIndices,
    grid: &mut OccupancyGrid,
    aabb_scale: u32,
    rounds: usize,
    first_round: usize,
    seed: u64,
) -> RefineReport {
    grid.refine_near_occupied(
        rounds,
        first_round,
        seed,
        log_density_at(net, params, indices, aabb_scale),
    )
}

/// [`OccupancyGrid::rebuild`] from the CPU network under `indices` (how a key holder
/// recovers a hidden scene's grid, which is never stored).
pub fn rebuild_occupancy(
    net: &NerfNetwork,
    params: &[f32],
    indices: &LevelIndices,
    aabb_scale: u32,
    samples_per_cell: usize,
    seed: u64,
) -> OccupancyGrid {
    rebuild_occupancy_in_box(
        net,
        params,
        indices,
        aabb_scale,
        None,
        samples_per_cell,
        seed,
    )
}

/// [`rebuild_occupancy`] of a scene confined to the box of `scene_box` (its key's box,
/// [`OccupancyGrid::rebuild_in_box`]).
pub fn rebuild_occupancy_in_box(
    net: &NerfNetwork,
    params: &[f32],
    indices: &LevelIndices,
    aabb_scale: u32,
    scene_box: Option<u32>,
    samples_per_cell: usize,
    seed: u64,
) -> OccupancyGrid {
    OccupancyGrid::rebuild_in_box(
        aabb_scale,
        scene_box,
        samples_per_cell,
        seed,
        log_density_at(net, params, indices, aabb_scale),
    )
}
