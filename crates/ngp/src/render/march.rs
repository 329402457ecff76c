//! Ray marching as instant-ngp does it: fixed steps of `sqrt(3)/1024` inside the unit cube
//! (exponential steps with cone angle 1/256 for larger aabb scales), samples only in occupied
//! occupancy-grid cells, empty cells skipped to the next voxel boundary (spec §3.2).

use crate::encoding::LevelIndices;
use crate::network::nerf::NerfNetwork;
use crate::occupancy::{GRID_SIZE, MIN_CONE_STEPSIZE, OccupancyGrid, mip_from_dt, pow2};

/// Most samples along one training ray (`NERF_STEPS`).
pub const MAX_SAMPLES_PER_RAY: usize = 1024;
/// The coarsest step: the width of the coarsest cascade's cell.
pub const MAX_CONE_STEPSIZE: f32 = MIN_CONE_STEPSIZE * 1024.0;

/// Marching parameters of a scene.
#[derive(Clone, Copy, Debug)]
pub struct Marcher {
    pub aabb_min: [f32; 3],
    pub aabb_max: [f32; 3],
    /// The cone angle's stepping (0 for aabb_scale 1, fixed steps; 1/256 otherwise).
    stepping: Stepping,
    pub max_cascade: u32,
}

impl Marcher {
    pub fn new(aabb_scale: u32) -> Self {
        let s = aabb_scale.clamp(1, 128) as f32;
        Marcher {
            aabb_min: [0.5 - s / 2.0; 3],
            aabb_max: [0.5 + s / 2.0; 3],
            stepping: Stepping::new(if aabb_scale <= 1 { 0.0 } else { 1.0 / 256.0 }),
            max_cascade: crate::occupancy::n_cascades(aabb_scale) as u32 - 1,
        }
    }

    /// 0 for aabb_scale 1 (fixed steps), 1/256 otherwise.
    pub fn cone_angle(&self) -> f32 {
        self.stepping.cone_angle
    }

    /// The stepping space's constants `[ln(1 + cone angle), a, b, at, bt]`, for a device
    /// that steps as this marcher does (the GPU's ray kernels).
    pub fn stepping_constants(&self) -> [f32; 5] {
        let Stepping {
            l, a, b, at, bt, ..
        } = self.stepping;
        [l, a, b, at, bt]
    }

    /// `t` advanced by `n` (possibly fractional) steps: [`advance_n_steps`] with this
    /// marcher's constants.
    #[inline]
    pub fn advance(&self, t: f32, n: f32) -> f32 {
        self.stepping.advance(t, n)
    }

    /// Maps an ngp-space position to the network's [0,1]³ input (`warp_position`).
    #[inline]
    pub fn warp(&self, p: [f32; 3]) -> [f32; 3] {
        let mut w = [0.0; 3];
        for d in 0..3 {
            w[d] = (p[d] - self.aabb_min[d]) / (self.aabb_max[d] - self.aabb_min[d]);
        }
        w
    }

    /// Whether a warped position (the network's input) lies in occupancy cascade 0, the
    /// unit cube of ngp space: the region over which the grid's mean density is measured.
    #[inline]
    pub fn in_cascade0(&self, w: [f32; 3]) -> bool {
        (0..3).all(|d| {
            let p = self.aabb_min[d] + w[d] * (self.aabb_max[d] - self.aabb_min[d]);
            (0.0..=1.0).contains(&p)
        })
    }

    #[inline]
    fn contains(&self, p: [f32; 3]) -> bool {
        (0..3).all(|d| p[d] >= self.aabb_min[d] && p[d] <= self.aabb_max[d])
    }

    /// Entry and exit distances of a ray through the AABB (slab test), `None` if missed.
    pub fn intersect(&self, o: [f32; 3], d: [f32; 3]) -> Option<(f32, f32)> {
        let mut t0 = f32::NEG_INFINITY;
        let mut t1 = f32::INFINITY;
        for k in 0..3 {
            let inv = 1.0 / d[k];
            let mut a = (self.aabb_min[k] - o[k]) * inv;
            let mut b = (self.aabb_max[k] - o[k]) * inv;
            if a > b {
                std::mem::swap(&mut a, &mut b);
            }
            if a.is_nan() || b.is_nan() {
                // Ray parallel to the slab: inside it or not.
                if o[k] < self.aabb_min[k] || o[k] > self.aabb_max[k] {
                    return None;
                }
                continue;
            }
            t0 = t0.max(a);
            t1 = t1.min(b);
        }
        if t0 > t1 || t1 < 0.0 {
            None
        } else {
            Some((t0.max(0.0), t1))
        }
    }

    /// One step from `t`. Never negative: far from the camera, rounding in stepping space
    /// can put `t` one step on *before* `t` (a negative step would make α < 0 and the
    /// transmittance grow past 1).
    #[inline]
    pub fn calc_dt(&self, t: f32) -> f32 {
        self.stepping.dt_from(t, self.stepping.steps_at(t))
    }

    /// Marches from `t` and appends at most `max_samples` samples (network position, dt,
    /// distance). Returns the distance to resume from, or `None` once the ray left the box.
    #[allow(clippy::too_many_arguments)]
    pub fn march(
        &self,
        grid: &OccupancyGrid,
        o: [f32; 3],
        d: [f32; 3],
        t: f32,
        max_samples: usize,
        pos: &mut Vec<[f32; 3]>,
        dts: &mut Vec<f32>,
        ts: &mut Vec<f32>,
    ) -> Option<f32> {
        self.march_strided(grid, o, d, t, max_samples, 1.0, pos, dts, ts)
    }

    /// [`Self::march`] taking `stride` of the reference's steps at a time where a sample is
    /// taken (its `dt` that many steps long): training's coarse march while a grid is still
    /// full of fog ([`next_stride`](crate::train::coarse::next_stride)). Occupancy is
    /// read at the cascade the reference's step reads and empty cells are skipped as the
    /// reference skips them, so a stride of 1 is [`Self::march`] to the bit.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    pub fn march_strided(
        &self,
        grid: &OccupancyGrid,
        o: [f32; 3],
        d: [f32; 3],
        mut t: f32,
        max_samples: usize,
        stride: f32,
        pos: &mut Vec<[f32; 3]>,
        dts: &mut Vec<f32>,
        ts: &mut Vec<f32>,
    ) -> Option<f32> {
        let idir = [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]];
        let mut n = 0;
        loop {
            let p = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
            if !self.contains(p) {
                return None;
            }
            if n >= max_samples {
                return Some(t);
            }
            // `t` in stepping space, once for the step and the skip (a logarithm each).
            let st = self.stepping.steps_at(t);
            let dt = self.stepping.dt_from(t, st);
            let mip = mip_from_dt(dt, p, self.max_cascade);
            let next = if grid.is_occupied(p, mip) {
                let dt = if stride == 1.0 {
                    dt
                } else {
                    self.stepping.dt_over(t, st, stride)
                };
                pos.push(self.warp(p));
                dts.push(dt);
                ts.push(t);
                n += 1;
                t + dt
            } else {
                #[cfg(test)]
                tests::EMPTY_VISITS.with(|v| v.set(v.get() + 1));
                // The reference skips the empty cell of its step's level; past an empty
                // coarser cell around it where there is one.
                let cell = t + distance_to_next_voxel(p, d, idir, voxels_across(mip));
                let far = self.empty_coarse_cell_exit(grid, t, p, d, idir, mip);
                self.stepping.past(st, far.map_or(cell, |f| f.max(cell)))
            };
            // Far from the camera a step can be smaller than the spacing of floats at t
            // (a camera 10^6 away from a unit box): step to the next float instead of
            // marching in place for ever.
            t = if next > t { next } else { t.next_up() };
        }
    }
}

impl Marcher {
    /// Where the ray leaves the coarsest empty cell around `p` that the reference's walk
    /// would cross without a sample, when one is coarser than the step's level `mip`: the
    /// walk may leave it at once. `None` where the next level's cell is occupied.
    ///
    /// Every level ORs the finer one into its cells, so an empty cell of level `c` holds only
    /// empty cells of the finer levels; the reference, skipping one cell of its step's level
    /// at a time, takes no sample inside it and lands on the first step past its far side,
    /// which is where one skip of the whole cell lands. Its step's level grows with the
    /// distance, so a level serves only if the step at the cell's far side still reads no
    /// coarser one (with a margin for rounding). The far side is measured from the cell whose
    /// bit was read (a point on a face belongs to one cell for both), so that rounding cannot
    /// read one cell and skip the next. A ray across a 360° capture's five cascades visits
    /// about a hundred cells of each level one by one, a logarithm and an exponential each;
    /// the empty room is now crossed in a few coarse cells.
    #[inline]
    fn empty_coarse_cell_exit(
        &self,
        grid: &OccupancyGrid,
        t: f32,
        p: [f32; 3],
        d: [f32; 3],
        idir: [f32; 3],
        mip: u32,
    ) -> Option<f32> {
        let mut exit = None;
        for c in mip + 1..=self.max_cascade {
            let Some(far) = crate::occupancy::empty_cell_exit(grid, p, d, idir, c) else {
                break;
            };
            let at = t + far;
            if mip_from_dt(self.calc_dt(at) * (1.0 + 1e-3), p, self.max_cascade) > c {
                break;
            }
            exit = Some(at);
        }
        exit
    }
}

/// The stepping space of a cone angle: a step is 1 there. Linear below the finest step and
/// above the coarsest, logarithmic between (the reference's `to_stepping_space`). Its
/// constants are the reference's expressions, evaluated once per marcher instead of in every
/// call (three logarithms and two exponentials a call, one to three calls a marched step):
/// the same bits, fewer libm calls.
#[derive(Clone, Copy, Debug)]
struct Stepping {
    cone_angle: f32,
    /// ln(1 + cone angle).
    l: f32,
    /// The stepping-space positions of the finest and the coarsest step's ends...
    a: f32,
    b: f32,
    /// ...and their distances.
    at: f32,
    bt: f32,
}

impl Stepping {
    fn new(cone_angle: f32) -> Self {
        let l = (1.0 + cone_angle).ln();
        let a = (MIN_CONE_STEPSIZE.ln() - l.ln()) / l;
        let b = (MAX_CONE_STEPSIZE.ln() - l.ln()) / l;
        Stepping {
            cone_angle,
            l,
            a,
            b,
            at: (a * l).exp(),
            bt: (b * l).exp(),
        }
    }

    fn fixed(&self) -> bool {
        self.cone_angle <= 1e-5
    }

    #[inline]
    fn steps_at(&self, t: f32) -> f32 {
        let Stepping {
            l, a, b, at, bt, ..
        } = *self;
        if self.fixed() {
            t / MIN_CONE_STEPSIZE
        } else if t <= at {
            (t - at) / MIN_CONE_STEPSIZE + a
        } else if t <= bt {
            t.ln() / l
        } else {
            (t - bt) / MAX_CONE_STEPSIZE + b
        }
    }

    #[inline]
    fn distance_at(&self, n: f32) -> f32 {
        let Stepping {
            l, a, b, at, bt, ..
        } = *self;
        if self.fixed() {
            n * MIN_CONE_STEPSIZE
        } else if n <= a {
            (n - a) * MIN_CONE_STEPSIZE + at
        } else if n <= b {
            (n * l).exp()
        } else {
            (n - b) * MAX_CONE_STEPSIZE + bt
        }
    }

    #[inline]
    fn advance(&self, t: f32, n: f32) -> f32 {
        self.distance_at(self.steps_at(t) + n)
    }

    /// One step from `t`, given `st = steps_at(t)`: `advance(t, 1) - t`, never negative.
    #[inline]
    fn dt_from(&self, t: f32, st: f32) -> f32 {
        (self.distance_at(st + 1.0) - t).max(0.0)
    }

    /// `n` steps from `t`, given `st = steps_at(t)`: `advance(t, n) - t`, never negative.
    #[inline]
    fn dt_over(&self, t: f32, st: f32, n: f32) -> f32 {
        (self.distance_at(st + n) - t).max(0.0)
    }

    /// The first step on the lattice through `ts` (a position in stepping space) at or past
    /// `target`, at least half a step on: where a skip to `target` lands.
    #[inline]
    fn past(&self, ts: f32, target: f32) -> f32 {
        let tt = self.steps_at(target);
        self.distance_at(ts + (tt - ts).max(0.5).ceil())
    }
}

/// `t` advanced by `n` (possibly fractional) steps.
pub fn advance_n_steps(t: f32, cone_angle: f32, n: f32) -> f32 {
    Stepping::new(cone_angle).advance(t, n)
}

/// Cells across cascade `mip`'s unit: the reference's `GRID_SIZE / exp2(mip)` (dividing by
/// a power of two is exact).
#[inline]
fn voxels_across(mip: u32) -> f32 {
    GRID_SIZE as f32 * pow2(-(mip as i32))
}

fn distance_to_next_voxel(p: [f32; 3], d: [f32; 3], idir: [f32; 3], res: f32) -> f32 {
    let mut tmin = f32::INFINITY;
    for k in 0..3 {
        let q = res * (p[k] - 0.5);
        let s = if d[k] > 0.0 {
            1.0
        } else if d[k] < 0.0 {
            -1.0
        } else {
            0.0
        };
        let tk = ((q + 0.5 + 0.5 * s).floor() - q) * idir[k];
        // A zero direction component gives ±inf or NaN; it never bounds the step.
        if tk.is_finite() || tk == f32::INFINITY {
            tmin = tmin.min(tk);
        }
    }
    (tmin / res).max(0.0)
}

/// The CPU network's log-density (the raw density output) under `indices` at ngp-space
/// points, warped as the marcher warps them: the density an occupancy grid's rebuild
/// ([`OccupancyGrid::rebuild_in_box`]) and refinement
/// ([`OccupancyGrid::refine_near_occupied`]) sample.
pub fn log_density_at<'a>(
    net: &'a NerfNetwork,
    params: &'a [f32],
    indices: &'a LevelIndices,
    aabb_scale: u32,
) -> impl FnMut(&[[f32; 3]]) -> Vec<f32> + 'a {
    let marcher = Marcher::new(aabb_scale);
    move |pos| {
        let warped: Vec<[f32; 3]> = pos.iter().map(|&p| marcher.warp(p)).collect();
        net.density_batch(params, indices, &warped)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::normalize;
    use crate::occupancy::N_CELLS;
    use std::cell::Cell;

    thread_local! {
        /// Empty cells [`Marcher::march_strided`] stepped past on this thread.
        pub(super) static EMPTY_VISITS: Cell<u64> = const { Cell::new(0) };
    }

    #[test]
    fn fixed_steps_in_unit_cube() {
        let m = Marcher::new(1);
        assert_eq!(m.cone_angle(), 0.0);
        assert!((m.calc_dt(0.3) - MIN_CONE_STEPSIZE).abs() < 1e-7);
        let grid = OccupancyGrid::new(1); // all occupied
        let (mut p, mut dt, mut ts) = (vec![], vec![], vec![]);
        // Along +x through the centre: the cube is 1 long, so 1/step ≈ 591 samples.
        let (t0, _) = m.intersect([-1.0, 0.5, 0.5], [1.0, 0.0, 0.0]).unwrap();
        assert!((t0 - 1.0).abs() < 1e-6);
        let r = m.march(
            &grid,
            [-1.0, 0.5, 0.5],
            [1.0, 0.0, 0.0],
            t0,
            2000,
            &mut p,
            &mut dt,
            &mut ts,
        );
        assert!(r.is_none());
        assert_eq!(p.len(), (1.0 / MIN_CONE_STEPSIZE).floor() as usize + 1);
        assert!(p.iter().all(|q| (0.0..=1.0).contains(&q[0])));
        // The sample budget is honoured and marching resumes where it stopped.
        let (mut p2, mut dt2, mut ts2) = (vec![], vec![], vec![]);
        let r = m.march(
            &grid,
            [-1.0, 0.5, 0.5],
            [1.0, 0.0, 0.0],
            t0,
            10,
            &mut p2,
            &mut dt2,
            &mut ts2,
        );
        assert_eq!(p2.len(), 10);
        assert!((r.unwrap() - (t0 + 10.0 * MIN_CONE_STEPSIZE)).abs() < 1e-5);
    }

    /// A stride of k takes every k-th of the reference's samples with k steps of `dt`: the
    /// same ray covered by a k-th of the samples, fixed steps (aabb 1) and cone steps alike.
    #[test]
    fn a_strided_march_takes_every_kth_step() {
        for aabb in [1u32, 16] {
            let m = Marcher::new(aabb);
            let grid = OccupancyGrid::new(aabb); // all occupied
            let (o, d) = ([0.5, 0.45, 0.52], [0.6f32, 0.64, 0.48]);
            let march = |stride: f32| {
                let (mut p, mut dt, mut ts) = (vec![], vec![], vec![]);
                m.march_strided(&grid, o, d, 0.01, 4096, stride, &mut p, &mut dt, &mut ts);
                (dt, ts)
            };
            let (fine_dt, fine_t) = march(1.0);
            for k in [2usize, 4, 8] {
                let (dt, ts) = march(k as f32);
                assert_eq!(
                    ts.len(),
                    fine_t.len().div_ceil(k),
                    "aabb {aabb}, stride {k}"
                );
                for (j, (&t, &step)) in ts.iter().zip(&dt).enumerate() {
                    let (want_t, want_dt): (f32, f32) = (
                        fine_t[j * k],
                        fine_dt[j * k..(j * k + k).min(fine_dt.len())].iter().sum(),
                    );
                    assert!(
                        (t - want_t).abs() <= 1e-4 * want_t.max(1.0),
                        "t {t} vs {want_t}"
                    );
                    if j * k + k <= fine_dt.len() {
                        assert!(
                            (step - want_dt).abs() <= 1e-3 * want_dt,
                            "dt {step} vs {want_dt}"
                        );
                    }
                }
            }
            // A stride of 1 is the reference's march.
            let (mut p, mut dt, mut ts) = (vec![], vec![], vec![]);
            m.march(&grid, o, d, 0.01, 4096, &mut p, &mut dt, &mut ts);
            assert_eq!(
                ts.iter().map(|t| t.to_bits()).collect::<Vec<_>>(),
                fine_t.iter().map(|t| t.to_bits()).collect::<Vec<_>>()
            );
        }
    }

    /// The reference's walk: one cell of the step's level at a time (instant-ngp's
    /// `march_ray`), which [`Marcher::march`] must reproduce while it crosses empty coarse
    /// cells at once.
    /// Returns the samples' distances and the empty cells visited.
    fn cellwise(
        m: &Marcher,
        grid: &OccupancyGrid,
        o: [f32; 3],
        d: [f32; 3],
        t0: f32,
    ) -> (Vec<f32>, u64) {
        let idir = [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]];
        let (mut t, mut ts, mut visits) = (t0, Vec::new(), 0);
        loop {
            let p = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
            if !m.contains(p) || ts.len() >= 4096 {
                return (ts, visits);
            }
            let st = m.stepping.steps_at(t);
            let dt = m.stepping.dt_from(t, st);
            let mip = mip_from_dt(dt, p, m.max_cascade);
            let next = if grid.is_occupied(p, mip) {
                ts.push(t);
                t + dt
            } else {
                visits += 1;
                let res = GRID_SIZE as f32 * pow2(-(mip as i32));
                let tt = m
                    .stepping
                    .steps_at(t + distance_to_next_voxel(p, d, idir, res));
                m.stepping.distance_at(st + (tt - st).max(0.5).ceil())
            };
            t = if next > t { next } else { t.next_up() };
        }
    }

    /// A room-like grid: a box of `aabb`, occupied in a blob at the centre and a thin shell
    /// (walls) in the outer cascade, empty between; rays from inside in every direction.
    /// Each ray's samples are the cell-by-cell walk's, but where rounding at a cell's face
    /// moves a step (a few rays in a thousand, each by a step's rounding or one cell).
    #[test]
    fn empty_coarse_cells_are_crossed_as_the_reference_crosses_their_cells() {
        let aabb = 16;
        let m = Marcher::new(aabb);
        let mut grid = OccupancyGrid::new(aabb);
        for c in 0..grid.n_cascades {
            let s = (c as f32).exp2();
            for idx in 0..N_CELLS as u32 {
                let q = [idx, idx >> 1, idx >> 2]
                    .map(|v| (crate::occupancy::morton3d_invert(v) as f32 + 0.5) / 128.0 - 0.5);
                let r = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt() * s;
                let wall = c == grid.n_cascades - 1 && (5.5..5.8).contains(&r);
                grid.density[c * N_CELLS + idx as usize] = if r < 0.3 || wall { 1.0 } else { 0.0 };
            }
        }
        grid.update_bitfield();
        let mut rng = crate::rng::Pcg32::new(7, 1);
        let (mut differ, mut samples, n) = (0, 0, 3000);
        let (mut visits, mut reference_visits) = (0, 0);
        for _ in 0..n {
            let mut u = || rng.next_f32() * 2.0 - 1.0;
            let o = [0.5 + 2.0 * u(), 0.5 + 2.0 * u(), 0.5 + 2.0 * u()];
            let d = normalize([u(), u(), u()]);
            let t0 = m.advance(0.05, rng.next_f32());
            let (want, skips) = cellwise(&m, &grid, o, d, t0);
            reference_visits += skips;
            let (mut p, mut dt, mut ts) = (vec![], vec![], vec![]);
            let before = EMPTY_VISITS.with(Cell::get);
            m.march(&grid, o, d, t0, 4096, &mut p, &mut dt, &mut ts);
            visits += EMPTY_VISITS.with(Cell::get) - before;
            samples += want.len();
            let same = ts.len() == want.len()
                && ts
                    .iter()
                    .zip(&want)
                    .all(|(a, b)| (a - b).abs() <= 1e-5 * b.max(1.0));
            differ += !same as usize;
        }
        eprintln!(
            "{differ} of {n} rays differ, {samples} samples; empty cells visited \
             {visits} against the reference's {reference_visits}"
        );
        // Rays from the middle cross the inner cascades' empty shells in their outer
        // cascades' cells (a half to a sixteenth of the visits) and the outer cascade, where
        // no coarser level exists, cell by cell: about half of the visits in all.
        assert!(
            visits * 3 < reference_visits * 2,
            "{visits} empty cells visited against the reference's {reference_visits}"
        );
        assert!(
            samples > 10 * n,
            "{samples} samples: the rays must meet the blob and walls"
        );
        assert!(
            differ * 200 <= n,
            "{differ} of {n} rays differ from the reference's walk"
        );
    }

    /// Empty space is skipped, at the reference's step and at a coarse training stride: every
    /// sample lands in the one occupied cell.
    #[test]
    fn empty_space_is_skipped() {
        let m = Marcher::new(1);
        let mut grid = OccupancyGrid::new(1);
        grid.density.iter_mut().for_each(|d| *d = 0.0);
        // One occupied cell at x ∈ [64/128, 65/128) on the ray's path.
        let cell = crate::occupancy::morton3d(64, 64, 64) as usize;
        grid.density[cell] = 1.0;
        grid.update_bitfield();
        // 1/128 / step = 4.6 → 4 or 5 samples, all inside the cell; at a stride of 2, 2 or 3.
        for (stride, n) in [(1.0, 4..=5), (2.0, 2..=3)] {
            let (mut p, mut dt, mut ts) = (vec![], vec![], vec![]);
            m.march_strided(
                &grid,
                [-1.0, 0.502, 0.502],
                [1.0, 0.0, 0.0],
                1.0,
                2000,
                stride,
                &mut p,
                &mut dt,
                &mut ts,
            );
            assert!(n.contains(&p.len()), "stride {stride}: {} samples", p.len());
            assert!(p.iter().all(|q| q[0] >= 0.5 && q[0] < 65.0 / 128.0));
        }
    }

    #[test]
    fn exponential_steps_grow() {
        let m = Marcher::new(16);
        assert!(m.cone_angle() > 0.0);
        let near = m.calc_dt(0.01);
        let far = m.calc_dt(5.0);
        assert!((near - MIN_CONE_STEPSIZE).abs() < 1e-6);
        assert!((far - 5.0 / 256.0).abs() / (5.0 / 256.0) < 0.01, "{far}");
        // Stepping space round-trips.
        for &t in &[0.001f32, 0.3, 2.0, 50.0, 900.0] {
            let st = Stepping::new(m.cone_angle());
            let back = st.distance_at(st.steps_at(t));
            assert!((back - t).abs() / t < 1e-3, "{t} -> {back}");
        }
    }

    /// The reference's `to_stepping_space` / `from_stepping_space`, each constant computed
    /// where the reference computes it, in the call.
    fn reference_advance(t: f32, cone_angle: f32, n: f32) -> f32 {
        let l = (1.0 + cone_angle).ln();
        let a = (MIN_CONE_STEPSIZE.ln() - l.ln()) / l;
        let b = (MAX_CONE_STEPSIZE.ln() - l.ln()) / l;
        let (at, bt) = ((a * l).exp(), (b * l).exp());
        let to = |t: f32| {
            if cone_angle <= 1e-5 {
                t / MIN_CONE_STEPSIZE
            } else if t <= at {
                (t - at) / MIN_CONE_STEPSIZE + a
            } else if t <= bt {
                t.ln() / l
            } else {
                (t - bt) / MAX_CONE_STEPSIZE + b
            }
        };
        let from = |n: f32| {
            if cone_angle <= 1e-5 {
                n * MIN_CONE_STEPSIZE
            } else if n <= a {
                (n - a) * MIN_CONE_STEPSIZE + at
            } else if n <= b {
                (n * l).exp()
            } else {
                (n - b) * MAX_CONE_STEPSIZE + bt
            }
        };
        from(to(t) + n)
    }

    #[test]
    fn stepping_with_constants_made_once_is_the_references_to_the_bit() {
        let mut r = crate::rng::Pcg32::new(3, 4);
        for aabb in [1, 2, 16, 128] {
            let m = Marcher::new(aabb);
            // Every region: below the finest step's end, the logarithmic part, past the
            // coarsest step's start.
            for k in 0..20_000 {
                let t = (r.next_f32() * 30.0 - 12.0).exp2();
                let n = [1.0, 0.5, r.next_f32() * 40.0][k % 3];
                let want = reference_advance(t, m.cone_angle(), n);
                assert_eq!(
                    m.advance(t, n).to_bits(),
                    want.to_bits(),
                    "aabb {aabb}, t {t}"
                );
                assert_eq!(
                    advance_n_steps(t, m.cone_angle(), n).to_bits(),
                    want.to_bits()
                );
                let dt = (reference_advance(t, m.cone_angle(), 1.0) - t).max(0.0);
                assert_eq!(m.calc_dt(t).to_bits(), dt.to_bits());
            }
        }
    }

    /// The march as the reference writes it: `calc_dt` and the skip each from `t` (the
    /// skip's `to_stepping_space(t)` computed again), the cell and the voxel size through
    /// `exp2`.
    #[allow(clippy::too_many_arguments)]
    fn reference_march(
        m: &Marcher,
        grid: &OccupancyGrid,
        o: [f32; 3],
        d: [f32; 3],
        mut t: f32,
        max_samples: usize,
        out: &mut Vec<([f32; 3], f32, f32)>,
    ) -> Option<f32> {
        let c = m.cone_angle();
        let stepping = Stepping::new(c);
        let idir = [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]];
        loop {
            let p = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
            if !m.contains(p) {
                return None;
            }
            if out.len() >= max_samples {
                return Some(t);
            }
            let dt = (reference_advance(t, c, 1.0) - t).max(0.0);
            let mip = mip_from_dt(dt, p, m.max_cascade);
            let next = if reference_is_occupied(grid, p, mip) {
                out.push((m.warp(p), dt, t));
                t + dt
            } else {
                let res = GRID_SIZE as f32 / (mip as f32).exp2();
                let target = t + distance_to_next_voxel(p, d, idir, res);
                let (ts, tt) = (stepping.steps_at(t), stepping.steps_at(target));
                stepping.distance_at(ts + (tt - ts).max(0.5).ceil())
            };
            t = if next > t { next } else { t.next_up() };
        }
    }

    /// `density_grid_occupied_at`, the cascade's scale through `exp2`.
    fn reference_is_occupied(grid: &OccupancyGrid, p: [f32; 3], mip: u32) -> bool {
        let s = (-(mip as i32) as f32).exp2();
        let mut i = [0u32; 3];
        for k in 0..3 {
            let u = (p[k] - 0.5) * s + 0.5;
            let g = (u * GRID_SIZE as f32) as i32;
            if u < 0.0 || !(0..GRID_SIZE as i32).contains(&g) {
                return false;
            }
            i[k] = g as u32;
        }
        let cell = crate::occupancy::morton3d(i[0], i[1], i[2]) as usize
            + mip as usize * crate::occupancy::N_CELLS;
        grid.bitfield()[cell / 8] & (1 << (cell % 8)) != 0
    }

    #[test]
    fn powers_of_two_from_bits_are_exp2s() {
        for k in -126..=127 {
            assert_eq!(pow2(k).to_bits(), (k as f32).exp2().to_bits(), "2^{k}");
        }
    }

    /// One stepping-space logarithm a marched step (shared by the step and the skip) and
    /// powers of two from their bits march the reference's samples: random occupancy grids,
    /// every cascade count, rays from inside and outside the box. To the bit where every
    /// coarse cell is occupied (90 %); where an empty coarse cell is crossed at once, its
    /// landing step is reached in fewer roundings, so within a few units of the last place,
    /// and where a step lies on a cell's face that rounding can move the ray by a step.
    #[test]
    fn marching_is_the_reference_form_to_the_bit() {
        let mut r = crate::rng::Pcg32::new(11, 5);
        for aabb in [1, 4, 16, 128] {
            for occupied in [0.02f32, 0.3, 0.9] {
                let m = Marcher::new(aabb);
                let mut grid = OccupancyGrid::new(aabb);
                grid.density
                    .iter_mut()
                    .for_each(|v| *v = if r.next_f32() < occupied { 1.0 } else { 0.0 });
                grid.update_bitfield();
                let (mut total, mut moved) = (0, 0);
                for ray in 0..300 {
                    let span = aabb as f32 * 1.5;
                    let o = [0, 1, 2].map(|_| 0.5 + (r.next_f32() - 0.5) * span);
                    let d = [0, 1, 2].map(|_| r.next_f32() - 0.5);
                    let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                    let d = d.map(|x| x / len);
                    let Some((t0, _)) = m.intersect(o, d) else {
                        continue;
                    };
                    let cap = [7, 64, 4096][ray % 3];
                    let mut want = Vec::new();
                    let want_t = reference_march(&m, &grid, o, d, t0, cap, &mut want);
                    let (mut p, mut dt, mut ts) = (vec![], vec![], vec![]);
                    let got_t = m.march(&grid, o, d, t0, cap, &mut p, &mut dt, &mut ts);
                    total += want.len();
                    if occupied > 0.5 {
                        assert_eq!(got_t.map(f32::to_bits), want_t.map(f32::to_bits));
                        assert_eq!(p.len(), want.len(), "aabb {aabb}, {occupied}");
                        for (k, (wp, wdt, wt)) in want.iter().enumerate() {
                            assert_eq!(p[k].map(f32::to_bits), wp.map(f32::to_bits));
                            assert_eq!(
                                (dt[k].to_bits(), ts[k].to_bits()),
                                (wdt.to_bits(), wt.to_bits())
                            );
                        }
                        continue;
                    }
                    let near = |a: f32, b: f32| (a - b).abs() <= 1e-5 * b.abs().max(1.0);
                    let same = got_t.is_some() == want_t.is_some()
                        && p.len() == want.len()
                        && want.iter().enumerate().all(|(k, (wp, wdt, wt))| {
                            (0..3).all(|i| near(p[k][i], wp[i]))
                                && near(dt[k], *wdt)
                                && near(ts[k], *wt)
                        });
                    moved += !same as usize;
                }
                assert!(total > 0, "aabb {aabb}, {occupied}: no sample to compare");
                assert!(
                    moved <= 3,
                    "aabb {aabb}, {occupied}: {moved} of 300 rays moved"
                );
            }
        }
    }

    #[test]
    fn marching_from_far_away_terminates() {
        // At t ≈ 1e6 the fixed step (1.7e-3) is below the float spacing (0.0625): marching
        // must still advance and leave the box.
        let m = Marcher::new(1);
        let grid = OccupancyGrid::new(1);
        let o = [1.0e6, 0.5, 0.5];
        let d = [-1.0, 0.0, 0.0];
        let (t0, _) = m.intersect(o, d).unwrap();
        let (mut p, mut dt, mut ts) = (vec![], vec![], vec![]);
        let r = m.march(&grid, o, d, t0, 100_000, &mut p, &mut dt, &mut ts);
        assert!(r.is_none());
        assert!(!p.is_empty() && p.len() < 100, "{} samples", p.len());
        assert!(ts.windows(2).all(|w| w[1] > w[0]));
        assert!(dt.iter().all(|&x| x >= 0.0));
    }

    #[test]
    fn cascade0_is_the_unit_cube_after_warping() {
        // aabb 4: the box is [-1.5, 2.5]^3, so ngp 0 and 1 warp to 0.375 and 0.625.
        let m = Marcher::new(4);
        assert!(m.in_cascade0(m.warp([0.5, 0.5, 0.5])));
        assert!(m.in_cascade0([0.375, 0.625, 0.5]));
        assert!(!m.in_cascade0([0.37, 0.5, 0.5]));
        assert!(!m.in_cascade0([0.5, 0.5, 0.63]));
        assert!(!m.in_cascade0(m.warp([1.1, 0.5, 0.5])));
        assert!(!m.in_cascade0(m.warp([0.5, -0.1, 0.5])));
        // aabb 1: the box is cascade 0, so every sample is in it.
        let m = Marcher::new(1);
        assert!(
            [[0.0; 3], [1.0; 3], [0.3, 0.9, 0.01]]
                .iter()
                .all(|&w| m.in_cascade0(w))
        );
    }

    #[test]
    fn aabb_intersection() {
        let m = Marcher::new(1);
        assert!(m.intersect([2.0, 2.0, 2.0], [1.0, 0.0, 0.0]).is_none());
        let (a, b) = m.intersect([0.5, 0.5, 0.5], [0.0, 0.0, 1.0]).unwrap();
        assert_eq!(a, 0.0);
        assert!((b - 0.5).abs() < 1e-6);
    }
}
