//! The occupancy (density) grid that lets ray marching skip empty space: 128³ cells per
//! cascade in Morton order, optical-thickness values with a 0.95 max-decay, a bitfield at
//! `min(0.01, mean)` and OR-pooled mips — as instant-ngp keeps it (spec §3.5).
//!
//! The grid is per scene: the stego layer keeps one per scene it trains and rebuilds a
//! hidden scene's grid from the network when rendering with a key.

use crate::camera::Camera;
use crate::rng::Pcg32;
use half::slice::HalfFloatSliceExt;
use rayon::prelude::*;

pub const GRID_SIZE: u32 = 128;
pub const N_CELLS: usize = (GRID_SIZE * GRID_SIZE * GRID_SIZE) as usize;
/// Cells below this optical thickness count as empty.
pub const MIN_OPTICAL_THICKNESS: f32 = 0.01;
pub const DECAY: f32 = 0.95;
/// `sqrt(3) / 1024`: the finest marching step, in units of the unit cube.
pub const MIN_CONE_STEPSIZE: f32 = 1.732_050_8 / 1024.0;

/// Spreads the low 10 bits of `v` to every third bit.
#[inline]
fn expand_bits(mut v: u32) -> u32 {
    v &= 0x3ff;
    v = (v | (v << 16)) & 0x0300_00ff;
    v = (v | (v << 8)) & 0x0300_f00f;
    v = (v | (v << 4)) & 0x030c_30c3;
    v = (v | (v << 2)) & 0x0924_9249;
    v
}

/// Morton index with x in bit 0 (instant-ngp's `morton3D`).
#[inline]
pub fn morton3d(x: u32, y: u32, z: u32) -> u32 {
    expand_bits(x) | (expand_bits(y) << 1) | (expand_bits(z) << 2)
}

/// Inverse of [`morton3d`] for one axis: pass `idx >> axis`.
#[inline]
pub fn morton3d_invert(mut x: u32) -> u32 {
    x &= 0x0924_9249;
    x = (x | (x >> 2)) & 0x030c_30c3;
    x = (x | (x >> 4)) & 0x0300_f00f;
    x = (x | (x >> 8)) & 0x0300_00ff;
    x = (x | (x >> 16)) & 0x0000_03ff;
    x
}

/// Number of cascades for an aabb scale: `log2(aabb_scale) + 1`.
pub fn n_cascades(aabb_scale: u32) -> usize {
    (aabb_scale.max(1).ilog2() + 1) as usize
}

/// Which cascade a position falls in (`mip_from_pos`).
#[inline]
pub fn mip_from_pos(pos: [f32; 3], max_cascade: u32) -> u32 {
    let m = (pos[0] - 0.5)
        .abs()
        .max((pos[1] - 0.5).abs())
        .max((pos[2] - 0.5).abs());
    mip_from_distance(m, max_cascade)
}

/// [`mip_from_pos`] of a position whose largest distance from the centre along an axis is
/// `m`.
#[inline]
pub fn mip_from_distance(m: f32, max_cascade: u32) -> u32 {
    // frexp exponent of m: m = f·2^e with f in [0.5, 1).
    let e = if m == 0.0 {
        0
    } else {
        ((m.to_bits() >> 23) & 0xff) as i32 - 126
    };
    (e + 1).clamp(0, max_cascade as i32) as u32
}

/// Cascade for a step of size `dt` at `pos` (`mip_from_dt`): big steps read coarse mips.
#[inline]
pub fn mip_from_dt(dt: f32, pos: [f32; 3], max_cascade: u32) -> u32 {
    let mip = mip_from_pos(pos, max_cascade);
    let d = dt * 2.0 * GRID_SIZE as f32;
    if d < 1.0 {
        return mip;
    }
    let e = ((d.to_bits() >> 23) & 0xff) as i32 - 126;
    // glm's clamp(mip, e, max) is min(max(mip, e), max): a step coarser than the coarsest
    // cascade reads the coarsest one (`Ord::clamp` would panic when e > max).
    (mip as i32).max(e).min(max_cascade as i32) as u32
}

/// `2^k` for a normal float's exponent (`-126 ..= 127`), built from its bits: the value
/// `exp2f(k)` gives (a test checks every cascade's), without a libm call on every marched
/// step.
#[inline]
pub fn pow2(k: i32) -> f32 {
    debug_assert!((-126..=127).contains(&k), "2^{k} is not a normal f32");
    f32::from_bits(((k + 127) as u32) << 23)
}

/// Morton cell of `pos` in cascade `mip`, or `None` outside it.
#[inline]
pub fn cell_at(pos: [f32; 3], mip: u32) -> Option<u32> {
    let s = pow2(-(mip as i32));
    let i = [
        cell_along(pos[0], s)?,
        cell_along(pos[1], s)?,
        cell_along(pos[2], s)?,
    ];
    Some(morton3d(i[0], i[1], i[2]))
}

/// [`cell_at`] along one axis: the cell holding coordinate `p` in the cascade whose scale is
/// `s` (`2^-mip`), or `None` outside it.
#[inline]
pub fn cell_along(p: f32, s: f32) -> Option<u32> {
    let u = (p - 0.5) * s + 0.5;
    // `as i32` truncates toward zero like the reference's ivec3 conversion.
    let i = (u * GRID_SIZE as f32) as i32;
    if !(0..GRID_SIZE as i32).contains(&i) || u < 0.0 {
        return None;
    }
    Some(i as u32)
}

/// The distance along `d` (`idir` its reciprocal) from `pos` to the far side of its cell of
/// level `mip` when that cell's bit is clear, or `None` when it is set or `pos` is outside
/// the level. The cell is found as [`cell_at`] finds it, so a point that rounding puts on
/// the other side of a face gets the far side of the cell that was read (a distance ≤ 0 if
/// the ray is leaving it).
#[inline]
pub fn empty_cell_exit(
    grid: &OccupancyGrid,
    pos: [f32; 3],
    d: [f32; 3],
    idir: [f32; 3],
    mip: u32,
) -> Option<f32> {
    let s = pow2(-(mip as i32));
    let g = GRID_SIZE as f32;
    let mut i = [0u32; 3];
    for k in 0..3 {
        let u = ((pos[k] - 0.5) * s + 0.5) * g;
        if !(0.0..g).contains(&u) {
            return None;
        }
        i[k] = u as u32;
    }
    let bit = morton3d(i[0], i[1], i[2]) as usize + mip as usize * N_CELLS;
    if grid.bitfield[bit / 8] & (1 << (bit % 8)) != 0 {
        return None;
    }
    let mut far = f32::INFINITY;
    for k in 0..3 {
        if d[k] == 0.0 {
            continue;
        }
        let face = i[k] as f32 + if d[k] > 0.0 { 1.0 } else { 0.0 };
        // The face in world units: the inverse of the cell's index map.
        let w = (face / g - 0.5) / s + 0.5;
        far = far.min((w - pos[k]) * idir[k]);
    }
    far.is_finite().then_some(far)
}

/// Most passes of [`OccupancyGrid::refine_near_occupied`]: each reaches one cell further
/// along a surface the first rounds missed.
pub const REFINE_PASSES: usize = 16;

/// What [`OccupancyGrid::refine_near_occupied`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RefineReport {
    pub passes: u32,
    /// Cells sampled again, over all passes (each once).
    pub cells: u64,
}

/// Cell `c` (cascade offset included) and its 26 neighbours inside its cascade.
fn neighbourhood(c: u32) -> impl Iterator<Item = u32> {
    let n = N_CELLS as u32;
    let (base, m) = (c / n * n, c % n);
    let at = [
        morton3d_invert(m) as i32,
        morton3d_invert(m >> 1) as i32,
        morton3d_invert(m >> 2) as i32,
    ];
    let g = GRID_SIZE as i32;
    (0..27).filter_map(move |k| {
        let q = [at[0] + k % 3 - 1, at[1] + k / 3 % 3 - 1, at[2] + k / 9 - 1];
        q.iter()
            .all(|&v| (0..g).contains(&v))
            .then(|| base + morton3d(q[0] as u32, q[1] as u32, q[2] as u32))
    })
}

/// The octant of every cell that round `r` of [`OccupancyGrid::rebuild`] samples is
/// `REBUILD_OCTANTS[r % 8]` (seed `seed + r`): opposite octants come first, so that any
/// number of rounds spreads over the cell.
pub const REBUILD_OCTANTS: [u32; 8] = [0, 7, 3, 4, 5, 2, 6, 1];

/// The occupancy grid of one scene.
#[derive(Clone, Debug, PartialEq)]
pub struct OccupancyGrid {
    pub n_cascades: usize,
    /// Optical thickness per cell, `N_CELLS` per cascade, Morton order; −1 = never seen.
    pub density: Vec<f32>,
    /// One bit per cell per mip (mips ≥ 1 also hold the OR-pooled finer mip).
    bitfield: Vec<u8>,
    /// Mean of cascade 0, clamped at 0 per cell.
    pub mean: f32,
    /// Number of updates so far (seeds the reference's cell-selection hash).
    pub ema_step: u32,
}

impl OccupancyGrid {
    /// All cells marked seen with density 0 and every bit set, so the first update's
    /// marching is unrestricted.
    pub fn new(aabb_scale: u32) -> Self {
        let nc = n_cascades(aabb_scale);
        OccupancyGrid {
            n_cascades: nc,
            density: crate::pages::zeroed(N_CELLS * nc),
            bitfield: vec![0xff; N_CELLS / 8 * nc],
            mean: 0.0,
            ema_step: 0,
        }
    }

    /// A grid from stored values (e.g. a snapshot's `density_grid_binary`).
    pub fn from_density(density: Vec<f32>) -> Option<Self> {
        if density.is_empty() || !density.len().is_multiple_of(N_CELLS) {
            return None;
        }
        let nc = density.len() / N_CELLS;
        let mut g = OccupancyGrid {
            n_cascades: nc,
            density,
            bitfield: vec![0; N_CELLS / 8 * nc],
            mean: 0.0,
            ema_step: 0,
        };
        g.update_bitfield();
        Some(g)
    }

    /// This grid as a reader of a published model rebuilds it: the densities rounded to
    /// fp16 (a snapshot's storage), then the mean, the threshold and the bits recomputed.
    /// Rounding moves cells near the threshold (and the mean with it) across it, so a
    /// policy that must agree with what a reader of the file finds (stealth's left
    /// entries) reads this grid, not the trainer's.
    pub fn as_stored(&self) -> OccupancyGrid {
        let mut h = vec![half::f16::ZERO; self.density.len()];
        h.convert_from_f32_slice(&self.density);
        let mut density = vec![0.0f32; h.len()];
        h.convert_to_f32_slice(&mut density);
        let mut g = OccupancyGrid {
            n_cascades: self.n_cascades,
            density,
            bitfield: vec![0; self.bitfield.len()],
            mean: 0.0,
            ema_step: self.ema_step,
        };
        g.update_bitfield();
        g
    }

    /// A grid from all its parts (another backend's copy): `None` unless the sizes agree.
    pub fn from_parts(
        density: Vec<f32>,
        bitfield: Vec<u8>,
        mean: f32,
        ema_step: u32,
    ) -> Option<Self> {
        if density.is_empty()
            || !density.len().is_multiple_of(N_CELLS)
            || bitfield.len() * 8 != density.len()
        {
            return None;
        }
        Some(OccupancyGrid {
            n_cascades: density.len() / N_CELLS,
            density,
            bitfield,
            mean,
            ema_step,
        })
    }

    /// One bit per cell (bit j of byte i: cell 8i + j), cascade after cascade, each coarser
    /// one OR-pooling the finer.
    pub fn bitfield(&self) -> &[u8] {
        &self.bitfield
    }

    pub fn max_cascade(&self) -> u32 {
        self.n_cascades as u32 - 1
    }

    /// Lower corner of the Morton cell `idx` of cascade `c`, in ngp space, plus the voxel size.
    fn cell_origin(idx: u32, c: usize) -> ([f32; 3], f32) {
        let s = (c as f32).exp2();
        let g = GRID_SIZE as f32;
        let p = [
            morton3d_invert(idx) as f32,
            morton3d_invert(idx >> 1) as f32,
            morton3d_invert(idx >> 2) as f32,
        ];
        (
            [
                (p[0] / g - 0.5) * s + 0.5,
                (p[1] / g - 0.5) * s + 0.5,
                (p[2] / g - 0.5) * s + 0.5,
            ],
            s / g,
        )
    }

    /// Marks every cell that no training camera sees (no corner projects inside an image,
    /// in front of the camera) with −1, and the others 0 (`mark_untrained_density_grid`).
    /// Neighbouring cells share corners, so each cascade's 129³ corners are tested once (a
    /// capture's five cascades: 10 M corners instead of 84 M, seconds instead of a quarter
    /// of a minute on two cores).
    pub fn mark_untrained(&mut self, cameras: &[Camera]) {
        const SIDE: usize = GRID_SIZE as usize + 1;
        let g = GRID_SIZE as f32;
        for c in 0..self.n_cascades {
            let s = (c as f32).exp2();
            let at = |i: usize| (i as f32 / g - 0.5) * s + 0.5;
            // seen[(z·SIDE + y)·SIDE + x]: whether corner (x, y, z) of the cascade is seen.
            let mut seen = vec![false; SIDE * SIDE * SIDE];
            seen.par_chunks_mut(SIDE).enumerate().for_each(|(zy, row)| {
                let (y, z) = (at(zy % SIDE), at(zy / SIDE));
                for (x, v) in row.iter_mut().enumerate() {
                    let p = [at(x), y, z];
                    *v = cameras.iter().any(|cam| {
                        // Without distortion the projection is injective: skip the
                        // reference's ray round trip, which only guards distortion.
                        if cam.distortion.is_some() {
                            cam.sees(p)
                        } else {
                            projects_inside(cam, p)
                        }
                    });
                }
            });
            let cascade = &mut self.density[c * N_CELLS..(c + 1) * N_CELLS];
            cascade.par_iter_mut().enumerate().for_each(|(idx, v)| {
                let idx = idx as u32;
                let (x, y, z) = (
                    morton3d_invert(idx) as usize,
                    morton3d_invert(idx >> 1) as usize,
                    morton3d_invert(idx >> 2) as usize,
                );
                let any = (0..8).any(|corner| {
                    let (dx, dy, dz) = (corner & 1, (corner >> 1) & 1, (corner >> 2) & 1);
                    seen[((z + dz) * SIDE + y + dy) * SIDE + x + dx]
                });
                *v = if any { 0.0 } else { -1.0 };
            });
        }
        self.update_bitfield();
    }

    /// Culls for good (−1) every cell whose centre lies outside the box of `aabb_scale`
    /// (centred on the same point as the model's): the grid of a scene whose content fills a
    /// smaller box than the model's, e.g. an object in a capture's large box. Rays then skip
    /// the rest of the model's box, where another index function's features are
    /// meaningless.
    pub fn confine_to_box(&mut self, aabb_scale: u32) {
        let h = 0.5 * aabb_scale as f32;
        for c in 0..self.n_cascades {
            // Cascade c spans 2^c: it lies inside a box at least as large.
            if (1u64 << c) <= aabb_scale as u64 {
                continue;
            }
            let cascade = &mut self.density[c * N_CELLS..(c + 1) * N_CELLS];
            for (idx, d) in cascade.iter_mut().enumerate() {
                let (o, vs) = Self::cell_origin(idx as u32, c);
                if !(0..3).all(|k| (o[k] + 0.5 * vs - 0.5).abs() < h) {
                    *d = -1.0;
                }
            }
        }
        self.update_bitfield();
    }

    /// One of training's updates at `step` (the reference's `update_density_grid_nerf`):
    /// draws the step's cells and positions, asks `log_density` for the field's raw
    /// log-density at each position (ngp space, in order) and folds them in. The grid does not
    /// know what answers: the CPU network, another backend, or a test's analytic field.
    /// Returns the number of positions evaluated.
    ///
    /// A position the reference draws in a culled cell (its uniform draw gives up after ten
    /// tries) is not evaluated: the fold leaves culled cells as they are, so its density
    /// would be thrown away. Where most of a capture's box is outside every camera's view,
    /// that is most of the work.
    pub fn update(
        &mut self,
        step: u32,
        fraction: f32,
        seed: u64,
        log_density: impl FnOnce(&[[f32; 3]]) -> Vec<f32>,
    ) -> usize {
        self.update_share(step, fraction, 1.0, seed, log_density)
    }

    /// [`Self::update`] drawing a share `share` ∈ (0, 1] of its cells and decaying the grid
    /// by `0.95^share`: between two of its samples a cell decays as in the reference's grid
    /// ([`GridUpdates`](crate::train::GridUpdates)).
    pub fn update_share(
        &mut self,
        step: u32,
        fraction: f32,
        share: f32,
        seed: u64,
        log_density: impl FnOnce(&[[f32; 3]]) -> Vec<f32>,
    ) -> usize {
        let (nu, nn) = self.update_sample_counts(step, fraction * share);
        let (mut pos, mut cells) = self.sample_positions(nu, nn, seed);
        let density = &self.density;
        let mut keep = 0;
        for i in 0..cells.len() {
            if density[cells[i] as usize] >= 0.0 {
                pos[keep] = pos[i];
                cells[keep] = cells[i];
                keep += 1;
            }
        }
        pos.truncate(keep);
        cells.truncate(keep);
        // The fold is a maximum per cell, so the order of evaluation is free: neighbouring
        // points share table entries, and in block order they are evaluated together (1.5×
        // the densities per second of the order drawn, benchmarks/engine.md).
        let (pos, cells) = in_block_order(&pos, &cells);
        let dens = log_density(&pos);
        assert_eq!(dens.len(), pos.len(), "one log-density per position");
        let decay = if share == 1.0 {
            DECAY
        } else {
            DECAY.powf(share)
        };
        self.splat_decaying(&cells, &dens, decay);
        keep
    }

    /// How many densities [`Self::update`] at `step` evaluates, in expectation: a draw picks
    /// a cascade at random and tries ten cells of it, a uniform draw for one a camera sees, a
    /// non-uniform one for an occupied one, keeping the last tried if none is; only draws that
    /// end in a cell a camera sees are evaluated.
    pub fn expected_update_cost(&self, step: u32, fraction: f32) -> u64 {
        let (nu, nn) = self.update_sample_counts(step, fraction);
        let (mut uniform, mut nonuniform) = (0.0f64, 0.0f64);
        for c in 0..self.n_cascades {
            let cells = &self.density[c * N_CELLS..(c + 1) * N_CELLS];
            let (live, occupied) = cells
                .par_iter()
                .map(|&d| ((d >= 0.0) as usize, (d > MIN_OPTICAL_THICKNESS) as usize))
                .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
            let f = live as f64 / N_CELLS as f64;
            let o = occupied as f64 / N_CELLS as f64;
            uniform += 1.0 - (1.0 - f).powi(10);
            let miss = (1.0 - o).powi(10);
            let live_unoccupied = if o < 1.0 { (f - o) / (1.0 - o) } else { 0.0 };
            nonuniform += 1.0 - miss + miss * live_unoccupied;
        }
        let nc = self.n_cascades as f64;
        (nu as f64 * uniform / nc + nn as f64 * nonuniform / nc).round() as u64
    }

    /// A grid rebuilt from a field alone (for index functions whose grid is never
    /// stored): `samples_per_cell` stratified random points in every cell of
    /// every cascade, max-splatted, then thresholded as usual. `log_density` answers as for
    /// [`Self::update`].
    pub fn rebuild(
        aabb_scale: u32,
        samples_per_cell: usize,
        seed: u64,
        log_density: impl FnMut(&[[f32; 3]]) -> Vec<f32>,
    ) -> OccupancyGrid {
        Self::rebuild_in_box(aabb_scale, None, samples_per_cell, seed, log_density)
    }

    /// [`Self::rebuild`] of a scene confined to the box of `scene_box` (its key's): only
    /// the cells inside are sampled, and those outside culled ([`Self::confine_to_box`]).
    /// The same grid as a whole rebuild then confined, for a fraction of the field's work.
    pub fn rebuild_in_box(
        aabb_scale: u32,
        scene_box: Option<u32>,
        samples_per_cell: usize,
        seed: u64,
        mut log_density: impl FnMut(&[[f32; 3]]) -> Vec<f32>,
    ) -> OccupancyGrid {
        let mut grid = OccupancyGrid::new(aabb_scale);
        grid.density.iter_mut().for_each(|d| *d = 0.0);
        let scene_box = scene_box.filter(|&b| b < aabb_scale);
        if let Some(b) = scene_box {
            grid.confine_to_box(b);
        }
        let cells: Vec<u32> = (0..(N_CELLS * grid.n_cascades) as u32)
            .filter(|&c| grid.density[c as usize] >= 0.0)
            .collect();
        for round in 0..samples_per_cell {
            // Every cell once per round, at a random point of one of its octants.
            let pos = grid.points_in_cell_octant(
                &cells,
                REBUILD_OCTANTS[round % 8],
                seed.wrapping_add(round as u64),
            );
            let dens = log_density(&pos);
            assert_eq!(dens.len(), pos.len(), "one log-density per position");
            // No decay between rounds: each round only raises a cell's maximum.
            grid.splat_max(&cells, &dens);
        }
        grid.update_bitfield();
        grid
    }

    /// More points for the cells a rebuild's rounds may have got wrong: `rounds` more in every
    /// cell next to an occupied one (its 26 neighbours in the same cascade, and itself), then
    /// in the neighbours of the cells that this made occupied, until no cell changes (at most
    /// [`REFINE_PASSES`] times). A thin surface that a few points per cell miss in one cell
    /// is hit in the next one along it, so the cells it crosses are all found at the cost of
    /// the cells near a surface, not of the whole grid. A pass that would take the cells
    /// sampled again past a quarter of the unculled cells is not made: that is fog, where
    /// more points find little and cost up to seven rebuilds. Round `r` (from
    /// `first_round`) takes the octant and seed a rebuild's round `r` would.
    pub fn refine_near_occupied(
        &mut self,
        rounds: usize,
        first_round: usize,
        seed: u64,
        mut log_density: impl FnMut(&[[f32; 3]]) -> Vec<f32>,
    ) -> RefineReport {
        let mut report = RefineReport::default();
        if rounds == 0 {
            return report;
        }
        let mut visited = vec![false; self.density.len()];
        let limit = self.density.iter().filter(|&&d| d >= 0.0).count() as u64 / 4;
        let thresh = self.threshold();
        let mut frontier: Vec<u32> = (0..self.density.len() as u32)
            .filter(|&c| self.density[c as usize] > thresh)
            .collect();
        for _ in 0..REFINE_PASSES {
            let mut cells = Vec::new();
            for &c in &frontier {
                for n in neighbourhood(c) {
                    if !visited[n as usize] && self.density[n as usize] >= 0.0 {
                        visited[n as usize] = true;
                        cells.push(n);
                    }
                }
            }
            // Near surfaces the neighbourhoods are a few per cent of the grid; a pass past
            // a quarter of it is refining fog (an early model), at up to seven rebuilds' cost.
            if cells.is_empty() || report.cells + cells.len() as u64 > limit {
                break;
            }
            // Morton order: neighbouring cells together for the network's table reads.
            cells.sort_unstable();
            for r in first_round..first_round + rounds {
                let pos = self.points_in_cell_octant(
                    &cells,
                    REBUILD_OCTANTS[r % 8],
                    seed.wrapping_add(r as u64),
                );
                let dens = log_density(&pos);
                assert_eq!(dens.len(), pos.len(), "one log-density per position");
                self.splat_max(&cells, &dens);
            }
            report.passes += 1;
            report.cells += cells.len() as u64;
            let thresh = self.threshold();
            frontier = cells
                .into_iter()
                .filter(|&c| self.density[c as usize] > thresh)
                .collect();
        }
        if report.passes > 0 {
            self.update_bitfield();
        }
        report
    }

    /// The occupancy threshold `min(0.01, mean of cascade 0)`, as [`Self::update_bitfield`]
    /// computes it.
    pub fn threshold(&self) -> f32 {
        MIN_OPTICAL_THICKNESS.min(self.cascade0_mean())
    }

    /// Mean of cascade 0, each cell clamped at 0.
    fn cascade0_mean(&self) -> f32 {
        // Fixed chunks summed in order: the same mean, to the bit, for any thread count, so
        // a reader of the stored grid thresholds exactly as the writer did.
        let partial: Vec<f64> = self.density[..N_CELLS]
            .par_chunks(1 << 14)
            .map(|c| c.iter().map(|&v| v.max(0.0) as f64).sum())
            .collect();
        let sum: f64 = partial.iter().sum();
        (sum / N_CELLS as f64) as f32
    }

    /// Cells to sample in one update at `step` (the reference's counts, times `fraction`).
    pub fn update_sample_counts(&self, step: u32, fraction: f32) -> (usize, usize) {
        Self::sample_counts(self.n_cascades, step, fraction)
    }

    /// [`Self::update_sample_counts`] of a grid of `nc` cascades (for a grid that lives
    /// elsewhere, e.g. on the GPU).
    pub fn sample_counts(nc: usize, step: u32, fraction: f32) -> (usize, usize) {
        let scale = |n: usize| ((n as f32 * fraction).round() as usize).max(1024);
        if step < 256 {
            (scale(N_CELLS * nc), 0)
        } else {
            (scale(N_CELLS / 4 * nc), scale(N_CELLS / 4 * nc))
        }
    }

    /// Picks the cells and random positions of one update (`generate_grid_samples_nerf_nonuniform`):
    /// `n_uniform` among non-culled cells, `n_nonuniform` among occupied cells. Returns
    /// (ngp-space positions, cell indices including the cascade offset).
    pub fn sample_positions(
        &self,
        n_uniform: usize,
        n_nonuniform: usize,
        seed: u64,
    ) -> (Vec<[f32; 3]>, Vec<u32>) {
        let nc = self.n_cascades;
        let step = self.ema_step;
        let draw = |n: usize, thresh: f32, stream: u64| -> Vec<([f32; 3], u32)> {
            (0..n)
                .into_par_iter()
                .map(|i| {
                    let mut rng = Pcg32::new(
                        seed ^ ((step as u64) << 32),
                        stream * 0x1_0000_0000 + i as u64,
                    );
                    let level = (rng.next_f32() * nc as f32) as usize % nc;
                    let mut idx = 0u32;
                    for j in 0..10u32 {
                        idx = ((i as u32).wrapping_add(step.wrapping_mul(n as u32)))
                            .wrapping_mul(56924617)
                            .wrapping_add(j.wrapping_mul(19349663))
                            .wrapping_add(96925573)
                            % N_CELLS as u32;
                        if self.density[idx as usize + level * N_CELLS] > thresh {
                            break;
                        }
                    }
                    let (o, vs) = Self::cell_origin(idx, level);
                    let p = [
                        o[0] + vs * rng.next_f32(),
                        o[1] + vs * rng.next_f32(),
                        o[2] + vs * rng.next_f32(),
                    ];
                    (p, idx + (level * N_CELLS) as u32)
                })
                .collect()
        };
        let mut all = draw(n_uniform, -0.01, 1);
        all.extend(draw(n_nonuniform, MIN_OPTICAL_THICKNESS, 2));
        all.into_iter().unzip()
    }

    /// Folds new density estimates in: each cell takes `max(old·0.95, max σ·Δt_min of its
    /// samples)`, culled cells stay −1; then the mean and bitfield are recomputed.
    pub fn splat(&mut self, cells: &[u32], log_density: &[f32]) {
        self.splat_decaying(cells, log_density, DECAY)
    }

    fn splat_decaying(&mut self, cells: &[u32], log_density: &[f32], decay: f32) {
        // The reference folds a buffer of fresh maxima into the decayed grid,
        // max(old·decay, max(0, samples)). A maximum does not care about order, so decaying
        // in place and then raising each drawn cell gives the same values without a second
        // grid-sized buffer (42 MB for a capture's five cascades, zeroed and faulted in at
        // every update).
        self.density.par_iter_mut().for_each(|d| {
            if *d >= 0.0 {
                *d = (*d * decay).max(0.0);
            }
        });
        self.splat_max(cells, log_density);
        self.ema_step += 1;
        self.update_bitfield();
    }

    /// A uniformly random point inside each given cell (index including the cascade offset).
    pub fn points_in_cells(cells: &[u32], seed: u64) -> Vec<[f32; 3]> {
        Self::points_in_sub_boxes(cells, [0.0; 3], 1.0, seed, |i, _| i as u64)
    }

    /// Like [`Self::points_in_cells`], but each point lies in octant `octant` (bit d set =
    /// upper half along axis d) of its cell: rounds over different octants stratify the
    /// samples, so a few rounds cover a cell far better than as many independent points.
    /// A cell's point comes from the stream of its own number (not its place in `cells`),
    /// so a rebuild of part of the grid draws what the whole one draws there.
    pub fn points_in_cell_octant(&self, cells: &[u32], octant: u32, seed: u64) -> Vec<[f32; 3]> {
        let lo = std::array::from_fn(|d| 0.5 * ((octant >> d) & 1) as f32);
        Self::points_in_sub_boxes(cells, lo, 0.5, seed, |_, c| c as u64)
    }

    /// A random point per cell in the sub-box `[lo, lo + extent]³` of the cell (fractions
    /// of the cell's side), the i-th cell `c` drawn from the stream `stream(i, c)`.
    fn points_in_sub_boxes(
        cells: &[u32],
        lo: [f32; 3],
        extent: f32,
        seed: u64,
        stream: impl Fn(usize, u32) -> u64 + Sync,
    ) -> Vec<[f32; 3]> {
        cells
            .par_iter()
            .enumerate()
            .map(|(i, &c)| {
                let mut rng = Pcg32::new(seed, stream(i, c));
                let (o, vs) = Self::cell_origin(c % N_CELLS as u32, c as usize / N_CELLS);
                std::array::from_fn(|d| o[d] + vs * (lo[d] + extent * rng.next_f32()))
            })
            .collect()
    }

    /// Raises cells to the optical thickness of their samples, without decay and without
    /// recomputing the bitfield (call [`Self::update_bitfield`] when done).
    pub fn splat_max(&mut self, cells: &[u32], log_density: &[f32]) {
        for (&c, &ld) in cells.iter().zip(log_density) {
            let t = ld.exp() * MIN_CONE_STEPSIZE;
            let d = &mut self.density[c as usize];
            if *d >= 0.0 && t > *d {
                *d = t;
            }
        }
    }

    /// Threshold `min(0.01, mean)`, bit per cell, then OR-pool each mip into the next.
    pub fn update_bitfield(&mut self) {
        self.mean = self.cascade0_mean();
        let thresh = MIN_OPTICAL_THICKNESS.min(self.mean);
        let density = &self.density;
        self.bitfield.par_iter_mut().enumerate().for_each(|(i, b)| {
            let mut bits = 0u8;
            for j in 0..8 {
                if density[i * 8 + j] > thresh {
                    bits |= 1 << j;
                }
            }
            *b = bits;
        });
        let per_mip = N_CELLS / 8;
        for level in 1..self.n_cascades {
            let (fine, coarse) = self.bitfield.split_at_mut(level * per_mip);
            let prev = &fine[(level - 1) * per_mip..];
            let next = &mut coarse[..per_mip];
            for i in 0..N_CELLS / 64 {
                let mut bits = 0u8;
                for j in 0..8 {
                    if prev[i * 8 + j] != 0 {
                        bits |= 1 << j;
                    }
                }
                let q = GRID_SIZE / 8;
                let x = morton3d_invert(i as u32) + q;
                let y = morton3d_invert(i as u32 >> 1) + q;
                let z = morton3d_invert(i as u32 >> 2) + q;
                next[morton3d(x, y, z) as usize] |= bits;
            }
        }
    }

    #[inline]
    pub fn is_occupied(&self, pos: [f32; 3], mip: u32) -> bool {
        match cell_at(pos, mip) {
            Some(idx) => {
                let i = idx as usize + mip as usize * N_CELLS;
                self.bitfield[i / 8] & (1 << (i % 8)) != 0
            }
            None => false,
        }
    }

    /// Integer coordinates of the occupied cells of cascade `mip`, in Morton order.
    pub fn occupied_cells(&self, mip: u32) -> Vec<[u32; 3]> {
        let base = mip as usize * N_CELLS;
        let bytes = &self.bitfield[base / 8..(base + N_CELLS) / 8];
        let mut out = Vec::new();
        for (i, &b) in bytes.iter().enumerate() {
            let mut b = b;
            while b != 0 {
                let m = (i * 8) as u32 + b.trailing_zeros();
                b &= b - 1;
                out.push([
                    morton3d_invert(m),
                    morton3d_invert(m >> 1),
                    morton3d_invert(m >> 2),
                ]);
            }
        }
        out
    }

    /// Fraction of cascade-0 cells that are occupied.
    pub fn occupied_fraction(&self) -> f64 {
        self.occupied_fraction_in(0)
    }

    /// Fraction of the cells of `cascade` whose bit is set (a cascade above 0 includes the
    /// pooled bits of the finer one at its centre); 0 for a cascade the grid does not have.
    pub fn occupied_fraction_in(&self, cascade: usize) -> f64 {
        let per = N_CELLS / 8;
        let Some(bytes) = self.bitfield.get(cascade * per..(cascade + 1) * per) else {
            return 0.0;
        };
        let n: u32 = bytes.iter().map(|b| b.count_ones()).sum();
        n as f64 / N_CELLS as f64
    }
}

/// Draws regrouped by blocks of 8³ cells (512 consecutive Morton indices, cascade after
/// cascade), in a counting sort: the draws of one block stay in the order drawn.
pub fn in_block_order(pos: &[[f32; 3]], cells: &[u32]) -> (Vec<[f32; 3]>, Vec<u32>) {
    let n_blocks = cells
        .iter()
        .map(|&c| (c >> 9) as usize + 1)
        .max()
        .unwrap_or(0);
    let mut start = vec![0usize; n_blocks + 1];
    for &c in cells {
        start[(c >> 9) as usize + 1] += 1;
    }
    for b in 0..n_blocks {
        start[b + 1] += start[b];
    }
    let mut out_pos = vec![[0.0f32; 3]; pos.len()];
    let mut out_cells = vec![0u32; cells.len()];
    for (p, &c) in pos.iter().zip(cells) {
        let k = &mut start[(c >> 9) as usize];
        out_pos[*k] = *p;
        out_cells[*k] = c;
        *k += 1;
    }
    (out_pos, out_cells)
}

/// Whether ngp-space point `p` is in front of `cam` and projects strictly inside its image.
fn projects_inside(cam: &Camera, p: [f32; 3]) -> bool {
    let m = &cam.c2w;
    let d = [p[0] - m[0][3], p[1] - m[1][3], p[2] - m[2][3]];
    // Camera-space coordinates: the rotation's transpose applied to d.
    let x = m[0][0] * d[0] + m[1][0] * d[1] + m[2][0] * d[2];
    let y = m[0][1] * d[0] + m[1][1] * d[1] + m[2][1] * d[2];
    let z = m[0][2] * d[0] + m[1][2] * d[1] + m[2][2] * d[2];
    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    if n == 0.0 || z / n < 1e-4 {
        return false;
    }
    let u = (x / z * cam.fx + cam.cx) / cam.width as f32;
    let v = (y / z * cam.fy + cam.cy) / cam.height as f32;
    u > 0.0 && v > 0.0 && u < 1.0 && v < 1.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_stored_grid_is_what_a_reader_of_the_file_rebuilds() {
        // Threshold 0.01 (the mean is 0.02); 0.009999 is below it in f32, but its nearest
        // fp16 is 0.0100021: empty to the trainer, occupied in the file.
        let bit = |g: &OccupancyGrid, i: usize| g.bitfield()[i / 8] & (1 << (i % 8)) != 0;
        let mut d = vec![0.02f32; N_CELLS];
        let near = morton3d(3, 5, 7) as usize;
        d[near] = 0.009999;
        d[morton3d(1, 1, 1) as usize] = -1.0;
        let trainer = OccupancyGrid::from_density(d).unwrap();
        assert!(!bit(&trainer, near));

        let bytes = crate::snapshot::write::fp16_bytes(&trainer.density);
        let read: Vec<f32> = bytes
            .chunks_exact(2)
            .map(|c| half::f16::from_le_bytes([c[0], c[1]]).to_f32())
            .collect();
        let reader = OccupancyGrid::from_density(read).unwrap();
        let stored = trainer.as_stored();
        assert!(bit(&stored, near));
        assert_eq!(stored.bitfield(), reader.bitfield());
        assert_eq!(stored.mean.to_bits(), reader.mean.to_bits());
        assert_eq!(stored.density, reader.density);
    }

    #[test]
    fn occupied_fractions_per_cascade() {
        // Cascade 0 empty (nothing pooled into cascade 1), 5 cells of cascade 1 set.
        let mut d = vec![0.0f32; 2 * N_CELLS];
        for x in 0..5 {
            d[N_CELLS + morton3d(x, 3, 7) as usize] = 1.0;
        }
        let g = OccupancyGrid::from_density(d).unwrap();
        assert_eq!(g.occupied_fraction_in(0), 0.0);
        assert_eq!(g.occupied_fraction_in(1), 5.0 / N_CELLS as f64);
        assert_eq!(g.occupied_fraction_in(2), 0.0, "a cascade the grid lacks");
        // One cascade, 12 cells above the threshold (the mean of their densities).
        let mut d = vec![0.0f32; N_CELLS];
        for x in 0..12 {
            d[morton3d(x, 100, 9) as usize] = 0.5;
        }
        let g = OccupancyGrid::from_density(d).unwrap();
        assert_eq!(g.occupied_fraction(), 12.0 / N_CELLS as f64);
        assert_eq!(g.occupied_fraction_in(0), g.occupied_fraction());
    }

    #[test]
    fn morton_by_hand() {
        assert_eq!(morton3d(1, 0, 0), 1);
        assert_eq!(morton3d(0, 1, 0), 2);
        assert_eq!(morton3d(0, 0, 1), 4);
        assert_eq!(morton3d(3, 0, 0), 0b1001);
        assert_eq!(morton3d(127, 127, 127), N_CELLS as u32 - 1);
        for &(x, y, z) in &[(5u32, 17u32, 99u32), (127, 0, 64)] {
            let m = morton3d(x, y, z);
            assert_eq!(morton3d_invert(m), x);
            assert_eq!(morton3d_invert(m >> 1), y);
            assert_eq!(morton3d_invert(m >> 2), z);
        }
    }

    #[test]
    fn mips_and_cells() {
        // frexp(0) has exponent 0, so the exact centre reads mip 1 (a reference quirk).
        assert_eq!(mip_from_pos([0.5, 0.5, 0.5], 7), 1);
        assert_eq!(mip_from_pos([0.5, 0.5, 0.5], 0), 0);
        assert_eq!(mip_from_pos([0.501, 0.5, 0.5], 7), 0);
        assert_eq!(mip_from_pos([0.9, 0.5, 0.5], 7), 0); // |0.4| < 0.5
        assert_eq!(mip_from_pos([1.2, 0.5, 0.5], 7), 1); // 0.7 in [0.5, 1)
        assert_eq!(mip_from_pos([2.4, 0.5, 0.5], 7), 2); // 1.9 ≤ 2
        assert_eq!(mip_from_pos([2.6, 0.5, 0.5], 7), 3); // 2.1 > 2
        assert_eq!(mip_from_pos([2.6, 0.5, 0.5], 1), 1);
        assert_eq!(mip_from_dt(MIN_CONE_STEPSIZE, [0.6, 0.5, 0.5], 7), 0);
        assert_eq!(mip_from_dt(4.0 / 128.0, [0.6, 0.5, 0.5], 7), 4); // dt·256 = 8 = 0.5·2^4
        // A step coarser than the coarsest cascade reads the coarsest (fox crashed here).
        assert_eq!(mip_from_dt(4.0 / 128.0, [0.6, 0.5, 0.5], 2), 2);
        assert_eq!(mip_from_dt(1.7, [0.6, 0.5, 0.5], 0), 0);
        assert_eq!(mip_from_dt(1.7, [9.0, 0.5, 0.5], 7), 7);
        assert_eq!(cell_at([0.0, 0.0, 0.0], 0), Some(0));
        assert_eq!(cell_at([0.999, 0.0, 0.0], 0), Some(morton3d(127, 0, 0)));
        assert_eq!(cell_at([1.0001, 0.5, 0.5], 0), None);
        assert_eq!(cell_at([-0.001, 0.5, 0.5], 0), None);
        // Cascade 1 covers [0, 1] ∪ … = [-0.5, 1.5]: the cube's centre is its cell 64.
        assert_eq!(cell_at([0.5, 0.5, 0.5], 1), Some(morton3d(64, 64, 64)));
        assert_eq!(cell_at([-0.49, 0.5, 0.5], 1), Some(morton3d(0, 64, 64)));
    }

    #[test]
    fn confine_to_box_keeps_the_inner_box_and_culls_the_rest() {
        // aabb 4 (cascades 0, 1, 2) confined to box 1: cascade 0 is the box and stays; of
        // cascade 1 (side 2) the central half per axis stays, 1/8 of its cells; of cascade 2
        // (side 4) a quarter per axis, 1/64.
        fn kept(g: &OccupancyGrid, c: usize) -> usize {
            g.density[c * N_CELLS..(c + 1) * N_CELLS]
                .iter()
                .filter(|&&d| d >= 0.0)
                .count()
        }
        let mut g = OccupancyGrid::new(4);
        g.density[5] = -1.0; // a cell no camera sees stays culled
        g.confine_to_box(1);
        assert_eq!(kept(&g, 0), N_CELLS - 1);
        assert_eq!(kept(&g, 1), N_CELLS / 8);
        assert_eq!(kept(&g, 2), N_CELLS / 64);
        // With every kept cell dense: inside the unit cube every mip is occupied, just
        // outside it none is; far outside, cascade 2 is empty too.
        g.density
            .iter_mut()
            .filter(|d| **d >= 0.0)
            .for_each(|d| *d = 1.0);
        g.update_bitfield();
        assert!(g.is_occupied([0.99, 0.5, 0.5], 1));
        assert!(g.is_occupied([0.99, 0.5, 0.5], 2));
        assert!(!g.is_occupied([1.01, 0.5, 0.5], 1));
        assert!(!g.is_occupied([-0.01, 0.5, 0.5], 2));
        assert!(!g.is_occupied([2.4, 2.4, -1.4], 2));
        // A box as large as the grid changes nothing.
        let mut h = OccupancyGrid::new(4);
        h.confine_to_box(4);
        assert_eq!(h.density, OccupancyGrid::new(4).density);
        // Box 2 in aabb 8: cascades 0 and 1 whole, a half of cascade 2 per axis.
        let mut e = OccupancyGrid::new(8);
        e.confine_to_box(2);
        assert_eq!((kept(&e, 0), kept(&e, 1)), (N_CELLS, N_CELLS));
        assert_eq!((kept(&e, 2), kept(&e, 3)), (N_CELLS / 8, N_CELLS / 64));
    }

    /// A thin wall (x in [0.5010, 0.5040], inside the lower half of the cells at x index 64):
    /// one point a cell finds most of its cells, not all; the refinement finds every one of
    /// them, samples nothing more than a cell away from the wall, and leaves a grid with
    /// nothing occupied as it was.
    #[test]
    fn refinement_finds_a_thin_wall_the_rebuild_missed_and_stays_near_it() {
        let wall = |pos: &[[f32; 3]]| -> Vec<f32> {
            pos.iter()
                .map(|p| {
                    if (0.5010..0.5040).contains(&p[0]) {
                        (1.0 / MIN_CONE_STEPSIZE).ln()
                    } else {
                        -20.0
                    }
                })
                .collect()
        };
        let in_wall = |c: u32| morton3d_invert(c) == 64;
        let found = |g: &OccupancyGrid| {
            (0..N_CELLS as u32)
                .filter(|&c| in_wall(c) && g.bitfield()[c as usize / 8] >> (c % 8) & 1 == 1)
                .count()
        };
        let mut g = OccupancyGrid::rebuild(1, 1, 3, wall);
        let base = found(&g);
        let wall_cells = (GRID_SIZE * GRID_SIZE) as usize;
        assert!(
            base > wall_cells / 2 && base < wall_cells * 9 / 10,
            "one point a cell found {base} of {wall_cells}"
        );
        let report = g.refine_near_occupied(28, 1, 3, wall);
        assert_eq!(found(&g), wall_cells, "after {report:?}");
        // Only the wall's column of cells and its two neighbours are sampled again.
        assert!(report.cells <= 3 * wall_cells as u64, "{report:?}");
        assert!(report.passes >= 1, "{report:?}");
        let occupied = (0..N_CELLS as u32)
            .filter(|&c| g.bitfield()[c as usize / 8] >> (c % 8) & 1 == 1)
            .count();
        assert_eq!(occupied, wall_cells, "nothing outside the wall is occupied");

        // From one occupied cell of the wall, each pass reaches one cell further along it,
        // up to REFINE_PASSES cells away.
        let mut empty = OccupancyGrid::rebuild(1, 1, 3, |p| vec![-20.0; p.len()]);
        let mut one = empty.clone();
        one.density[morton3d(64, 10, 10) as usize] = 1.0;
        let report = one.refine_near_occupied(28, 1, 3, wall);
        assert_eq!(report.passes as usize, REFINE_PASSES);
        let reach = (10 + REFINE_PASSES + 1).min(GRID_SIZE as usize);
        assert_eq!(found(&one), reach * reach, "{report:?}");

        // Fog everywhere: every cell occupied, the first pass would sample them all again.
        let mut fog = OccupancyGrid::rebuild(1, 1, 3, |pos| {
            pos.iter()
                .map(|p| if p[0] > 0.3 { 0.0 } else { -20.0 })
                .collect()
        });
        assert!(fog.bitfield().iter().map(|b| b.count_ones()).sum::<u32>() > N_CELLS as u32 / 2);
        let before = fog.clone();
        assert_eq!(
            fog.refine_near_occupied(28, 1, 3, |_| unreachable!()),
            RefineReport::default()
        );
        assert_eq!(fog, before);

        let before = empty.clone();
        let report = empty.refine_near_occupied(28, 1, 3, |_| unreachable!());
        assert_eq!(report, RefineReport::default());
        assert_eq!(empty, before);
    }

    /// The in-place fold against the reference's two buffers written out here, bit for bit:
    /// culled cells, cells drawn several times, log-densities of NaN, ±∞ and underflow.
    #[test]
    fn the_in_place_fold_is_the_two_buffer_fold() {
        let mut r = crate::rng::Pcg32::new(9, 2);
        let n = 2 * N_CELLS;
        let mut g = OccupancyGrid::new(2);
        for d in g.density.iter_mut() {
            *d = match r.next_u32() % 8 {
                0 => -1.0,
                1 => 0.0,
                _ => r.next_f32() * 0.05,
            };
        }
        let cells: Vec<u32> = (0..50_000).map(|_| r.next_u32() % n as u32).collect();
        let lds: Vec<f32> = (0..cells.len())
            .map(|i| match i % 97 {
                0 => f32::NAN,
                1 => f32::INFINITY,
                2 => f32::NEG_INFINITY,
                3 => -200.0,
                _ => r.next_f32() * 8.0 - 4.0,
            })
            .collect();
        for decay in [DECAY, DECAY.powf(0.3)] {
            let mut want = g.density.clone();
            let mut fresh = vec![0.0f32; n];
            for (&c, &ld) in cells.iter().zip(&lds) {
                let t = ld.exp() * MIN_CONE_STEPSIZE;
                if t > fresh[c as usize] {
                    fresh[c as usize] = t;
                }
            }
            for (d, &f) in want.iter_mut().zip(&fresh) {
                if *d >= 0.0 {
                    *d = (*d * decay).max(f);
                }
            }
            let mut got = g.clone();
            got.splat_decaying(&cells, &lds, decay);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert!(bits(&got.density) == bits(&want), "decay {decay}");
        }
    }

    #[test]
    fn splat_max_decay_and_bitfield() {
        let mut g = OccupancyGrid::new(1);
        g.density.iter_mut().for_each(|d| *d = 0.0);
        g.density[7] = -1.0;
        g.density[3] = 1.0;
        let ln = |t: f32| (t / MIN_CONE_STEPSIZE).ln();
        g.splat(&[5, 7, 3, 5], &[ln(0.5), ln(9.0), ln(0.1), ln(0.2)]);
        assert!((g.density[5] - 0.5).abs() < 1e-5); // max of its two samples
        assert_eq!(g.density[7], -1.0); // culled stays culled
        assert!((g.density[3] - 0.95).abs() < 1e-6); // decay beats the smaller sample
        assert!(g.mean > 0.0 && g.mean < 1e-5);
        // threshold = mean (< 0.01): cells 3 and 5 occupied, an empty one not.
        let p = |idx: u32| {
            let (o, vs) = OccupancyGrid::cell_origin(idx, 0);
            [o[0] + vs / 2.0, o[1] + vs / 2.0, o[2] + vs / 2.0]
        };
        assert!(g.is_occupied(p(5), 0));
        assert!(g.is_occupied(p(3), 0));
        assert!(!g.is_occupied(p(6), 0));
        assert!(!g.is_occupied(p(7), 0));
    }

    #[test]
    fn cascades_pool_finer_bits() {
        let mut g = OccupancyGrid::new(4);
        assert_eq!(g.n_cascades, 3);
        g.density.iter_mut().for_each(|d| *d = 0.0);
        let c = morton3d(10, 20, 30) as usize;
        g.density[c] = 1.0;
        g.update_bitfield();
        let pos = [(10.5) / 128.0, 20.5 / 128.0, 30.5 / 128.0];
        assert!(g.is_occupied(pos, 0));
        assert!(
            g.is_occupied(pos, 1),
            "mip 1 must contain the pooled fine bit"
        );
        assert!(g.is_occupied(pos, 2));
        assert!(!g.is_occupied([0.9, 0.9, 0.9], 1));
    }

    #[test]
    fn sampling_is_deterministic_and_in_cells() {
        let g = OccupancyGrid::new(1);
        let (p1, c1) = g.sample_positions(1000, 0, 3);
        let (p2, c2) = g.sample_positions(1000, 0, 3);
        assert_eq!(c1, c2);
        assert_eq!(p1, p2);
        for (p, &c) in p1.iter().zip(&c1) {
            assert_eq!(cell_at(*p, 0), Some(c));
        }
    }

    #[test]
    fn octant_points_stay_in_their_cell_and_octant() {
        let g = OccupancyGrid::new(4);
        // Cells of cascades 0 and 2, spread over the grid.
        let cells: Vec<u32> = (0..500u32)
            .map(|i| i * 4099 % N_CELLS as u32)
            .chain((0..500u32).map(|i| 2 * N_CELLS as u32 + i * 7919 % N_CELLS as u32))
            .collect();
        for octant in 0..8u32 {
            let pts = g.points_in_cell_octant(&cells, octant, 11);
            assert_eq!(pts, g.points_in_cell_octant(&cells, octant, 11));
            for (p, &c) in pts.iter().zip(&cells) {
                let cascade = c as usize / N_CELLS;
                assert_eq!(
                    cell_at(*p, cascade as u32),
                    Some(c % N_CELLS as u32),
                    "octant {octant}"
                );
                let (o, vs) = OccupancyGrid::cell_origin(c % N_CELLS as u32, cascade);
                for d in 0..3 {
                    let upper = p[d] >= o[d] + 0.5 * vs;
                    assert_eq!(upper, (octant >> d) & 1 == 1, "octant {octant} axis {d}");
                }
            }
        }
    }

    /// A ball of radius 0.15 at (0.3, 0.5, 0.5), dense inside and empty outside: after a
    /// rebuild, every cell wholly inside is occupied on cascade 0 and every cell wholly outside
    /// is not; training updates with the same field reach the same verdict on those cells.
    #[test]
    fn rebuild_and_update_from_an_analytic_field() {
        let centre = [0.3f32, 0.5, 0.5];
        let dist = |p: [f32; 3]| {
            (0..3)
                .map(|d| (p[d] - centre[d]).powi(2))
                .sum::<f32>()
                .sqrt()
        };
        let field = |pos: &[[f32; 3]]| -> Vec<f32> {
            pos.iter()
                .map(|&p| if dist(p) < 0.15 { 5.0 } else { -20.0 })
                .collect()
        };
        let half_diag = 3f32.sqrt() / 2.0 / GRID_SIZE as f32;
        let check = |g: &OccupancyGrid, what: &str| {
            let (mut inside, mut outside) = (0, 0);
            for idx in (0..N_CELLS as u32).step_by(61) {
                let (o, vs) = OccupancyGrid::cell_origin(idx, 0);
                let c = [o[0] + vs / 2.0, o[1] + vs / 2.0, o[2] + vs / 2.0];
                let r = dist(c);
                if r < 0.15 - half_diag {
                    assert!(
                        g.is_occupied(c, 0),
                        "{what}: cell at r = {r} inside the ball"
                    );
                    inside += 1;
                } else if r > 0.15 + half_diag {
                    assert!(!g.is_occupied(c, 0), "{what}: cell at r = {r} outside");
                    outside += 1;
                }
            }
            assert!(
                inside > 100 && outside > 10_000,
                "{what}: {inside} / {outside}"
            );
        };
        let rebuilt = OccupancyGrid::rebuild(1, 2, 5, field);
        check(&rebuilt, "rebuild");
        assert_eq!(rebuilt, OccupancyGrid::rebuild(1, 2, 5, field));
        // In a box: the whole rebuild confined afterwards, from a third of the samples.
        let mut whole = OccupancyGrid::rebuild(4, 2, 5, field);
        whole.confine_to_box(1);
        let mut asked = 0;
        let boxed = OccupancyGrid::rebuild_in_box(4, Some(1), 2, 5, |p: &[[f32; 3]]| {
            asked += p.len();
            field(p)
        });
        assert_eq!(boxed, whole);
        assert_eq!(asked, 2 * (N_CELLS + N_CELLS / 8 + N_CELLS / 64));
        check(&boxed, "rebuild in a box");
        // A box as large as the model's is no box.
        assert_eq!(
            OccupancyGrid::rebuild_in_box(1, Some(4), 2, 5, field),
            rebuilt
        );

        let mut trained = OccupancyGrid::new(1);
        let mut calls = 0;
        for step in 0..4 {
            trained.update(step, 1.0, 9, |pos| {
                calls += 1;
                field(pos)
            });
        }
        assert_eq!((calls, trained.ema_step), (4, 4));
        check(&trained, "updates");
    }

    /// An update skips the culled cells' draws and folds in exactly what evaluating every
    /// draw would (the reference's update, spelt out here).
    #[test]
    fn an_update_skips_culled_draws_and_gives_the_reference_grid() {
        let field = |pos: &[[f32; 3]]| -> Vec<f32> {
            pos.iter()
                .map(|p| 3.0 * (9.0 * p[0]).sin() + 2.0 * (7.0 * p[1] * p[2]).cos())
                .collect()
        };
        let mut g = OccupancyGrid::new(4);
        // Cull most of the grid, as cameras that see little of a capture's box do.
        for (i, d) in g.density.iter_mut().enumerate() {
            // One cell in eight kept, at random (a pattern in step with the reference's hash
            // of the ten tries would skew how often they find one).
            if !crate::train::schedule::mix(3, i as u64).is_multiple_of(8) {
                *d = -1.0;
            }
        }
        g.update_bitfield();
        let mut reference = g.clone();
        for step in [0u32, 1, 300] {
            let (nu, nn) = reference.update_sample_counts(step, 0.1);
            let (pos, cells) = reference.sample_positions(nu, nn, 5);
            reference.splat(&cells, &field(&pos));
            let expected = g.expected_update_cost(step, 0.1) as f64;
            let mut asked = 0;
            let evaluated = g.update(step, 0.1, 5, |p| {
                asked += p.len();
                field(p)
            });
            assert_eq!(g, reference, "step {step}");
            assert_eq!(asked, evaluated);
            // The ten tries find a live cell for about 1 − (7/8)^10 = 74 % of the uniform draws.
            assert!(
                evaluated < pos.len() && evaluated > nu / 2,
                "{evaluated} of {}",
                pos.len()
            );
            // The expectation: 1 − (7/8)^10 of the uniform draws, and so on.
            assert!(
                (expected / evaluated as f64 - 1.0).abs() < 0.02,
                "expected {expected}, evaluated {evaluated}"
            );
        }
    }

    /// The corner lattice culls exactly the cells whose eight corners no camera sees,
    /// each corner tested on its own as the reference does (checked cell by cell here).
    #[test]
    fn mark_untrained_culls_the_cells_no_camera_sees() {
        // Two cameras looking along +z and −x from outside the unit cube, narrow views.
        let cam = |c2w: [[f32; 4]; 3]| Camera {
            c2w,
            fx: 60.0,
            fy: 60.0,
            cx: 16.0,
            cy: 12.0,
            width: 32,
            height: 24,
            distortion: None,
        };
        let cams = [
            cam([
                [1.0, 0.0, 0.0, 0.5],
                [0.0, 1.0, 0.0, 0.5],
                [0.0, 0.0, 1.0, -1.5],
            ]),
            cam([
                [0.0, 0.0, -1.0, 3.0],
                [0.0, 1.0, 0.0, 0.3],
                [1.0, 0.0, 0.0, 0.6],
            ]),
        ];
        let mut g = OccupancyGrid::new(4);
        g.mark_untrained(&cams);
        let gs = GRID_SIZE as f32;
        let (mut seen, mut culled) = (0, 0);
        for i in (0..g.density.len()).step_by(97) {
            let (c, idx) = (i / N_CELLS, (i % N_CELLS) as u32);
            let s = (c as f32).exp2();
            let at = |k: u32| (k as f32 / gs - 0.5) * s + 0.5;
            let xyz = [
                morton3d_invert(idx),
                morton3d_invert(idx >> 1),
                morton3d_invert(idx >> 2),
            ];
            let any = (0..8u32).any(|corner| {
                let p: [f32; 3] = std::array::from_fn(|d| at(xyz[d] + ((corner >> d) & 1)));
                cams.iter().any(|cam| projects_inside(cam, p))
            });
            assert_eq!(g.density[i], if any { 0.0 } else { -1.0 }, "cell {i}");
            if any {
                seen += 1;
            } else {
                culled += 1;
            }
        }
        assert!(seen > 1000 && culled > 1000, "{seen} seen, {culled} culled");
    }
}
