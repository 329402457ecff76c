//! A cap on the cover's optical thickness: a penalty on the cover's (scene 0's) density at
//! points of the cells its occupancy grid holds above the cap, added to the cover's loss
//! through the engine's extra-loss hook ([`ngp::train::PolicyOps::density_loss`]).
//!
//! No training ray constrains the density inside an opaque object: its rays end at the
//! surface. A plain model's interior keeps whatever the surface's features interpolate to
//! (an optical thickness of at most ~6 per finest step in our generated scenes, measured).
//! When other scenes train entries that the cover's interior also reads (stealth confines
//! hidden scenes to the cover's own entries), the cover's network decodes their features
//! there as densities of 20–900: the stored grid then shows cells far denser than a plain
//! model's, its mean (the occupancy threshold) rises, and a quarter to two thirds of the
//! cells a plain model keeps fall below it (benchmarks/steganalysis.md, "What stealth changes in the
//! cover's grid"). The cap adds to the cover's loss, at points drawn in the cells the grid
//! holds above half the cap,
//!
//! `weight · mean over points of max(0, ln τ(x) − ln cap)²`,  τ = σ(x) · Δt_min,
//!
//! the grid's own unit (optical thickness per finest marching step). The hinge leaves every
//! density below the cap alone, so it changes nothing where a cover has no such cells; the
//! log keeps a cell of 900 from swamping the step. Both backends draw the same points for a
//! step from the same grid, and take the gradient from [`cap_gradient`].

use ngp::occupancy::{MIN_CONE_STEPSIZE, OccupancyGrid};
use ngp::rng::Pcg32;

/// The penalty's settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DensityCap {
    /// Optical thickness per finest marching step (the occupancy grid's unit) above which
    /// the cover's density is pulled down. 2 lets a single finest step absorb 86 % of the
    /// light, and an opaque surface needs no more; plain models' grids reach 1–23, median
    /// 3.5, in their densest cell.
    pub max_optical_thickness: f32,
    /// Weight of the penalty against the photometric loss (whose gradient is per ray).
    pub weight: f32,
    /// Points drawn per step.
    pub samples: u32,
}

impl DensityCap {
    /// What stealth training uses (measured on the 20-pair population, benchmarks/steganalysis.md).
    pub const STEALTH: DensityCap = DensityCap {
        max_optical_thickness: 2.0,
        weight: 0.01,
        samples: 4096,
    };

    /// Stealth's cap at `max_optical_thickness` when given (0: none), else
    /// [`Self::STEALTH`]: what `--density-cap` selects.
    pub fn stealth(max_optical_thickness: Option<f32>) -> Option<DensityCap> {
        match max_optical_thickness {
            None => Some(Self::STEALTH),
            Some(c) if c <= 0.0 => None,
            Some(c) => Some(DensityCap {
                max_optical_thickness: c,
                ..Self::STEALTH
            }),
        }
    }

    /// The cap as a raw log-density (the network's density output).
    pub fn log_density_cap(&self) -> f32 {
        self.max_optical_thickness.ln() - MIN_CONE_STEPSIZE.ln()
    }

    /// The cells (cascade offset included) the penalty draws its points from: those the
    /// grid holds above half the cap. Computed at each update of the cover's grid.
    pub fn cells(&self, grid: &OccupancyGrid) -> Vec<u32> {
        let floor = 0.5 * self.max_optical_thickness;
        grid.density
            .iter()
            .enumerate()
            .filter(|&(_, &d)| d > floor)
            .map(|(i, _)| i as u32)
            .collect()
    }

    /// Step `step`'s points in ngp space: `samples` cells drawn at random (with repeats)
    /// from `cells`, a uniform point in each. Empty when there is no cell.
    pub fn points(&self, cells: &[u32], seed: u64, step: u32) -> Vec<[f32; 3]> {
        if cells.is_empty() || self.samples == 0 {
            return Vec::new();
        }
        let stream = ngp::train::schedule::mix(seed, 0x6361_7000 + step as u64);
        let mut r = Pcg32::new(stream, 0x0063_6170);
        let pick: Vec<u32> = (0..self.samples)
            .map(|_| cells[r.below(cells.len() as u32) as usize])
            .collect();
        OccupancyGrid::points_in_cells(&pick, stream)
    }
}

/// The penalty's gradient with respect to one point's raw log-density, for `n` points
/// (zero below the cap), and the point's term of the loss.
pub fn cap_gradient(cap: &DensityCap, log_density: f32, n: usize) -> (f32, f32) {
    let excess = log_density - cap.log_density_cap();
    if excess > 0.0 && n > 0 {
        let w = cap.weight / n as f32;
        (2.0 * w * excess, w * excess * excess)
    } else {
        (0.0, 0.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cap_is_the_grids_unit_and_the_gradient_is_the_hinges() {
        let cap = DensityCap {
            max_optical_thickness: 2.0,
            weight: 0.5,
            samples: 4,
        };
        // τ = e^ld · √3/1024 = 2 ⇔ ld = ln(2048/√3) = 7.0753…
        assert!((cap.log_density_cap() - 7.075_34).abs() < 1e-4);
        assert_eq!(cap_gradient(&cap, 7.0, 4), (0.0, 0.0));
        let ld = cap.log_density_cap() + 3.0;
        let (g, l) = cap_gradient(&cap, ld, 4);
        // weight / n · excess² and its derivative, 0.125 · 9 and 0.25 · 3.
        assert!((l - 1.125).abs() < 1e-5, "{l}");
        assert!((g - 0.75).abs() < 1e-5, "{g}");
        // The derivative of the loss, by central differences.
        let h = 1e-2;
        let fd = (cap_gradient(&cap, ld + h, 4).1 - cap_gradient(&cap, ld - h, 4).1) / (2.0 * h);
        assert!((fd - g).abs() < 1e-3, "{fd} vs {g}");
    }

    #[test]
    fn points_come_from_the_cells_above_half_the_cap() {
        let cap = DensityCap {
            max_optical_thickness: 2.0,
            weight: 0.01,
            samples: 64,
        };
        let mut grid = OccupancyGrid::new(1);
        grid.density.iter_mut().for_each(|d| *d = 0.5);
        // Cell 0 (the corner at the origin) and cell 7 (x, y, z = 1) above 1.
        grid.density[0] = 1.5;
        grid.density[7] = 40.0;
        let cells = cap.cells(&grid);
        assert_eq!(cells, vec![0, 7]);
        let pts = cap.points(&cells, 9, 3);
        assert_eq!(pts.len(), 64);
        let side = 1.0 / 128.0;
        let (mut in0, mut in7) = (0, 0);
        for p in &pts {
            if p.iter().all(|&c| (0.0..side).contains(&c)) {
                in0 += 1;
            } else if p.iter().all(|&c| (side..2.0 * side).contains(&c)) {
                in7 += 1;
            }
        }
        assert_eq!(in0 + in7, 64, "a point outside both cells");
        assert!(in0 > 10 && in7 > 10, "{in0} / {in7}");
        // The same step draws the same points; another step others.
        assert_eq!(pts, cap.points(&cells, 9, 3));
        assert_ne!(pts, cap.points(&cells, 9, 4));
        assert!(cap.points(&[], 9, 3).is_empty());
    }
}
