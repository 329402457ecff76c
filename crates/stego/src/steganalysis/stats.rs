//! The numbers an analyst computes from one model file: per-level hash-table statistics
//! split by the stored occupancy grid's reach, MLP weight moments, and summaries.

use ngp::encoding::layout::GridLayout;
use ngp::encoding::reach::EntrySet;
use ngp::network::NerfLayout;
use ngp::network::layout::{DENSITY_OUT, SH_DIMS};
use rayon::prelude::*;
use serde::Serialize;

/// Largest magnitude an entry can have and still be at its initial value as a file stores
/// it. Entries start uniform in ±1e-4 (`NerfNetwork::init_params`, as tiny-cuda-nn); an
/// untouched entry's debiased EMA equals its weight up to a few f32 ulps, and the file
/// rounds it to fp16. Near 1e-4 fp16 numbers are normal (≥ 2^-14) with a step of 2^-24,
/// so the largest stored initial value is fp16(1e-4) = 1678·2^-24 ≈ 1.000166e-4 and the
/// next fp16 value, 1679·2^-24, is already a moved entry. The bound 1e-4·(1 + 2^-11)
/// (≈ 1678.5·2^-24, 2^-11 being fp16's relative rounding error) lies between the two, so
/// the test is exact for fp16 files and keeps f32 files' EMA rounding (~1e-11) inside. A
/// trained entry lands in this box in all F features only by chance: Adam's first steps
/// alone move it by about its learning rate (1e-2).
pub const INIT_BOUND: f32 = 1e-4 * (1.0 + 1.0 / 2048.0);

/// Mean, median, 90th percentile and maximum of a sample; quantiles are nearest-rank (the
/// smallest value with at least ⌈p·n⌉ values at or below it), so they are values of the
/// sample. All zero for an empty sample.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Summary {
    pub mean: f64,
    pub median: f64,
    pub p90: f64,
    pub max: f64,
}

impl Summary {
    /// Reorders `v` (selection, not a full sort: O(n)).
    pub fn of(v: &mut [f32]) -> Summary {
        if v.is_empty() {
            return Summary::default();
        }
        let n = v.len();
        let mean = v.iter().map(|&x| x as f64).sum::<f64>() / n as f64;
        let max = v.iter().copied().fold(f32::NEG_INFINITY, f32::max) as f64;
        let mut rank = |p: f64| {
            let k = ((p * n as f64).ceil() as usize).clamp(1, n) - 1;
            *v.select_nth_unstable_by(k, f32::total_cmp).1 as f64
        };
        let median = rank(0.5);
        let p90 = rank(0.9);
        Summary {
            mean,
            median,
            p90,
            max,
        }
    }
}

/// One set of a level's entries (those the stored grid reaches, or the others).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct SetStats {
    pub count: u32,
    /// Fraction of the set's entries still at initialisation (0 for an empty set).
    pub init_frac: f64,
    /// Entry magnitude: the largest |feature| of the entry (see the module docs).
    pub magnitude: Summary,
}

/// Statistics of one level of the hash grid.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct LevelStats {
    pub level: u32,
    pub resolution: u32,
    pub entries: u32,
    /// Dense levels index every grid vertex directly; the others hash.
    pub dense: bool,
    /// Fraction of all the level's entries still at initialisation.
    pub init_frac: f64,
    /// Fraction of the entries the stored occupancy grid reaches under the standard index.
    pub reachable_frac: f64,
    pub reachable: SetStats,
    pub unreachable: SetStats,
}

/// The largest |feature| of each entry of a level: the same norm the at-initialisation test
/// uses, so "at init" is exactly "magnitude ≤ INIT_BOUND".
fn magnitudes(table: &[f32], nf: usize) -> Vec<f32> {
    table
        .chunks_exact(nf)
        .map(|e| e.iter().fold(0.0f32, |m, v| m.max(v.abs())))
        .collect()
}

fn set_stats(mut mags: Vec<f32>) -> SetStats {
    let count = mags.len();
    let init = mags.iter().filter(|&&m| m <= INIT_BOUND).count();
    SetStats {
        count: count as u32,
        init_frac: if count == 0 {
            0.0
        } else {
            init as f64 / count as f64
        },
        magnitude: Summary::of(&mut mags),
    }
}

/// Per-level statistics of the grid parameters `grid_params` (the grid block of the
/// parameter vector) with the reachable sets of each level (`None`: every entry counts as
/// reachable, for a file without a stored occupancy grid).
pub fn level_stats(
    layout: &GridLayout,
    grid_params: &[f32],
    reach: Option<&[EntrySet]>,
) -> Vec<LevelStats> {
    let nf = layout.config.n_features as usize;
    layout
        .levels
        .par_iter()
        .enumerate()
        .map(|(li, level)| {
            let start = level.offset as usize * nf;
            let table = &grid_params[start..start + level.size as usize * nf];
            let mags = magnitudes(table, nf);
            let all_init = mags.iter().filter(|&&m| m <= INIT_BOUND).count();
            let (mut inside, mut outside) = (Vec::new(), Vec::new());
            match reach.map(|r| &r[li]) {
                Some(set) => {
                    inside.reserve(set.len() as usize);
                    outside.reserve((level.size - set.len()) as usize);
                    for (i, &m) in mags.iter().enumerate() {
                        if set.contains(i as u32) {
                            inside.push(m);
                        } else {
                            outside.push(m);
                        }
                    }
                }
                None => inside = mags,
            }
            let reachable = set_stats(inside);
            LevelStats {
                level: level.level,
                resolution: level.resolution,
                entries: level.size,
                dense: level.dense,
                init_frac: all_init as f64 / level.size.max(1) as f64,
                reachable_frac: reachable.count as f64 / level.size.max(1) as f64,
                reachable,
                unreachable: set_stats(outside),
            }
        })
        .collect()
}

/// Moments of one MLP weight matrix.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct MatrixStats {
    /// "density" or "color".
    pub network: String,
    /// 0 = input layer.
    pub layer: usize,
    /// Rows (outputs) and columns (inputs) counted: tcnn's padding rows and columns are
    /// left out, since no gradient ever reaches them and they keep their initial values
    /// in every model.
    pub rows: usize,
    pub cols: usize,
    pub mean: f64,
    pub std: f64,
    pub mean_abs: f64,
    pub max_abs: f64,
    /// m4/m2² − 3 (population moments); 0 for a Gaussian, −1.2 for a uniform
    /// initialisation, larger when training grows heavy tails.
    pub excess_kurtosis: f64,
}

fn matrix_stats(
    network: &str,
    layer: usize,
    w: &[f32],
    cols_stored: usize,
    rows: usize,
    cols: usize,
) -> MatrixStats {
    let vals = || {
        (0..rows).flat_map(move |r| {
            w[r * cols_stored..r * cols_stored + cols]
                .iter()
                .map(|&v| v as f64)
        })
    };
    let n = (rows * cols).max(1) as f64;
    let mean = vals().sum::<f64>() / n;
    let (mut m2, mut m4, mut abs, mut max_abs) = (0.0, 0.0, 0.0, 0.0f64);
    for v in vals() {
        let d = v - mean;
        let d2 = d * d;
        m2 += d2;
        m4 += d2 * d2;
        abs += v.abs();
        max_abs = max_abs.max(v.abs());
    }
    let (m2, m4) = (m2 / n, m4 / n);
    MatrixStats {
        network: network.to_string(),
        layer,
        rows,
        cols,
        mean,
        std: m2.sqrt(),
        mean_abs: abs / n,
        max_abs,
        excess_kurtosis: if m2 > 0.0 { m4 / (m2 * m2) - 3.0 } else { 0.0 },
    }
}

/// Where one MLP weight matrix lies in the parameter vector (row-major, `cols_stored` a row)
/// and the part of it that counts: tcnn's padding rows and columns are left out, since no
/// gradient ever reaches them and they keep their initial values in every model.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MatrixSpan {
    /// "density" or "color".
    pub network: &'static str,
    /// 0 = input layer.
    pub layer: usize,
    pub offset: usize,
    pub cols_stored: usize,
    pub rows: usize,
    pub cols: usize,
}

impl MatrixSpan {
    /// Parameter indices of the counted weights, row by row.
    pub fn indices(&self) -> impl Iterator<Item = usize> + '_ {
        (0..self.rows).flat_map(move |r| {
            let row = self.offset + r * self.cols_stored;
            row..row + self.cols
        })
    }
}

/// Every weight matrix of the density and colour MLPs, input layer first.
pub fn mlp_matrices(layout: &NerfLayout) -> Vec<MatrixSpan> {
    let mut out = Vec::new();
    let nets = [
        (
            "density",
            layout.density_mlp,
            layout.density_offset,
            layout.config.grid.n_output_dims(),
            DENSITY_OUT,
        ),
        (
            "color",
            layout.color_mlp,
            layout.color_offset,
            DENSITY_OUT + SH_DIMS,
            3,
        ),
    ];
    for (network, shape, offset, n_in, n_out) in nets {
        let mats: Vec<_> = shape.matrices().collect();
        let last = mats.len() - 1;
        let mut at = offset;
        for (layer, &(rows, cols)) in mats.iter().enumerate() {
            out.push(MatrixSpan {
                network,
                layer,
                offset: at,
                cols_stored: cols,
                rows: if layer == last { n_out.min(rows) } else { rows },
                cols: if layer == 0 { n_in.min(cols) } else { cols },
            });
            at += rows * cols;
        }
    }
    out
}

/// Statistics of every weight matrix of the density and colour MLPs, input layer first.
pub fn mlp_stats(layout: &NerfLayout, params: &[f32]) -> Vec<MatrixStats> {
    mlp_matrices(layout)
        .iter()
        .map(|m| {
            matrix_stats(
                m.network,
                m.layer,
                &params[m.offset..],
                m.cols_stored,
                m.rows,
                m.cols,
            )
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn summaries_are_nearest_rank() {
        let mut v: Vec<f32> = (1..=10).rev().map(|i| i as f32).collect();
        let s = Summary::of(&mut v);
        assert_eq!(s.mean, 5.5);
        // ⌈0.5·10⌉ = 5th smallest, ⌈0.9·10⌉ = 9th smallest.
        assert_eq!(s.median, 5.0);
        assert_eq!(s.p90, 9.0);
        assert_eq!(s.max, 10.0);
        let mut one = vec![3.0f32];
        let s = Summary::of(&mut one);
        assert_eq!((s.median, s.p90, s.max), (3.0, 3.0, 3.0));
        assert_eq!(Summary::of(&mut []), Summary::default());
    }

    #[test]
    fn every_initial_value_is_within_the_bound_after_fp16_rounding() {
        // The extremes of the initialisation and their fp16 images.
        for v in [1e-4f32, -1e-4, 9.99e-5, 6.1e-5, 3e-5, 0.0] {
            let stored = half::f16::from_f32(v).to_f32();
            assert!(stored.abs() <= INIT_BOUND, "{v} → {stored}");
        }
        // One fp16 step above fp16(1e-4) is outside: the bound is no wider than rounding.
        let above = half::f16::from_bits(half::f16::from_f32(1e-4).to_bits() + 1).to_f32();
        assert!(above > INIT_BOUND, "{above}");
    }

    #[test]
    fn moments_of_a_known_matrix() {
        // 2 × 3 stored with one padding column (cols_stored 4) that must be skipped.
        let w = [1.0f32, -1.0, 1.0, 99.0, -1.0, 1.0, -1.0, 99.0];
        let m = matrix_stats("density", 0, &w, 4, 2, 3);
        assert_eq!(m.mean, 0.0);
        assert_eq!(m.std, 1.0);
        assert_eq!(m.mean_abs, 1.0);
        assert_eq!(m.max_abs, 1.0);
        // ±1 with equal weight: m4/m2² = 1, excess −2.
        assert_eq!(m.excess_kurtosis, -2.0);
    }
}
