//! Bounded left entries: table entries the cover's occupancy grid no longer lets training
//! reach (under the reference index) keep at most the magnitude they had when it stopped
//! reaching them, and other scenes may move them within that bound (the engine's
//! [`TableBounds`]: clamped after every optimizer step, never held back).
//!
//! A plain model leaves such entries where the cover's early training (before its grid
//! pruned empty space) left them. Sharing only the entries the cover still reaches costs a
//! hidden scene most of the coarse levels (at level 0 a plain cover reaches about a third of
//! its entries); moving the others without a bound makes them measurably larger than a
//! plain model's (benchmarks/steganalysis.md, "Sharing the entries the cover left"). Within
//! the bound their magnitudes stay what the cover made them.

use ngp::encoding::reach::reachable_entries;
use ngp::encoding::{GridLayout, LevelIndices, reference_indices};
use ngp::occupancy::OccupancyGrid;
use ngp::train::hooks::{TableBounds, UNBOUNDED};

/// The rule that sets the bounds of the entries the cover has left.
pub struct LeftEntries {
    /// The cover's index functions (the reference's), made once.
    reference: LevelIndices,
}

impl LeftEntries {
    pub fn new(layout: &GridLayout) -> Self {
        LeftEntries {
            reference: reference_indices(layout),
        }
    }

    /// After an update of the cover's grid: an entry it no longer reaches takes its
    /// magnitude in `table` (the largest |feature|; the published, EMA weights of the
    /// table, entries × features) as its bound, unless it already had one; an entry it
    /// reaches again loses its bound. Before the first update every entry is unbounded (a
    /// new grid's every cell is occupied). The reach is the stored grid's
    /// ([`OccupancyGrid::as_stored`]), which a key holder and an analyst rebuild from the
    /// file: from the trainer's f32 grid, cells near the threshold left 0.15 % of a hidden
    /// scene's vertices in entries the file calls left but training had not bounded.
    pub fn update(
        &self,
        bounds: &mut TableBounds,
        layout: &GridLayout,
        grid: &OccupancyGrid,
        aabb_scale: u32,
        table: &[f32],
    ) {
        let sets = reachable_entries(layout, &grid.as_stored(), aabb_scale, &self.reference);
        let f = bounds.n_features();
        // The levels are contiguous in table order: entry g belongs to the level whose
        // range holds it, visited in order.
        let mut level = 0;
        bounds.set_each(|g, old| {
            while g as u32 >= layout.levels[level].offset + layout.levels[level].size {
                level += 1;
            }
            let e = g as u32 - layout.levels[level].offset;
            if sets[level].contains(e) {
                UNBOUNDED
            } else if old < 0.0 {
                table[g * f..(g + 1) * f]
                    .iter()
                    .fold(0.0f32, |m, v| m.max(v.abs()))
            } else {
                old
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ngp::encoding::GridConfig;
    use ngp::occupancy::{N_CELLS, morton3d};

    fn layout() -> GridLayout {
        let cfg = GridConfig {
            n_levels: 2,
            n_features: 2,
            log2_hashmap_size: 12,
            base_resolution: 16,
        };
        GridLayout::new(cfg, 1).unwrap()
    }

    /// Entry `e`'s features are `±(e + 1)/1000`, so a bound names its entry.
    fn table(layout: &GridLayout) -> Vec<f32> {
        (0..layout.n_entries as usize * 2)
            .map(|i| ((i / 2 + 1) as f32 / 1000.0) * if i % 2 == 0 { 1.0 } else { -2.0 })
            .collect()
    }

    #[test]
    fn entries_the_grid_stops_reaching_keep_their_magnitude_then() {
        let layout = layout();
        let t = table(&layout);
        let rule = LeftEntries::new(&layout);
        let mut left = TableBounds::new(layout.n_entries as usize, 2);
        // Every cell occupied: every entry reached (the reach tests cover the full grid).
        let full = OccupancyGrid::from_density(vec![1.0; N_CELLS]).unwrap();
        rule.update(&mut left, &layout, &full, 1, &t);
        assert!((0..layout.n_entries as usize).all(|e| !left.is_bounded(e)));

        // One cell, (64, 64, 64): at level 0 (dense, 16 vertices an axis) it reaches
        // vertices 8..=9 on each axis (worked out in the reach tests), entry
        // x + 16·y + 256·z; every other level-0 entry is left, its bound its largest
        // |feature| (the second, twice the first) at this update.
        let mut density = vec![0.0f32; N_CELLS];
        density[morton3d(64, 64, 64) as usize] = 1.0;
        let one = OccupancyGrid::from_density(density).unwrap();
        rule.update(&mut left, &layout, &one, 1, &t);
        let l0 = &layout.levels[0];
        assert!(l0.dense && l0.offset == 0);
        let reached = |e: usize| {
            let (x, y, z) = (e % 16, e / 16 % 16, e / 256);
            (8..=9).contains(&x) && (8..=9).contains(&y) && (8..=9).contains(&z)
        };
        for e in 0..l0.size as usize {
            if reached(e) {
                assert_eq!(left.bound(e), UNBOUNDED, "entry {e}");
            } else {
                assert_eq!(left.bound(e), 2.0 * (e + 1) as f32 / 1000.0, "entry {e}");
            }
        }
        assert_eq!(
            (0..l0.size as usize)
                .filter(|&e| !left.is_bounded(e))
                .count(),
            8
        );

        // A later update keeps the bounds the entries had when left, whatever the table
        // holds now; an entry reached again loses its bound.
        let shrunk: Vec<f32> = t.iter().map(|v| v / 10.0).collect();
        let mut density = vec![0.0f32; N_CELLS];
        density[morton3d(0, 0, 0) as usize] = 1.0;
        let corner = OccupancyGrid::from_density(density).unwrap();
        rule.update(&mut left, &layout, &corner, 1, &shrunk);
        assert_eq!(
            left.bound(0),
            UNBOUNDED,
            "vertex (0, 0, 0) is reached again"
        );
        assert_eq!(left.bound(1000), t[2001].abs());
        // Vertex (8, 8, 8), reached before, is left now with the table's value today.
        let e = 8 + 16 * 8 + 256 * 8;
        assert_eq!(left.bound(e), shrunk[2 * e + 1].abs());
    }

    #[test]
    fn the_clamp_holds_left_entries_alone() {
        let layout = layout();
        let t = table(&layout);
        let mut left = TableBounds::new(layout.n_entries as usize, 2);
        let mut density = vec![0.0f32; N_CELLS];
        density[morton3d(64, 64, 64) as usize] = 1.0;
        LeftEntries::new(&layout).update(
            &mut left,
            &layout,
            &OccupancyGrid::from_density(density).unwrap(),
            1,
            &t,
        );
        // Every feature pushed out by 1: a left entry below 999 comes back to its bound on
        // both features (the first, half the bound, is pushed past it too), a reached one
        // keeps both.
        let mut pushed: Vec<f32> = t.iter().map(|v| v + v.signum()).collect();
        left.clamp(&mut pushed);
        let reached = 8 + 16 * 8 + 256 * 8;
        for e in [0usize, 5, 900, reached] {
            let (a, b) = (pushed[2 * e], pushed[2 * e + 1]);
            if e == reached {
                assert_eq!((a, b), (t[2 * e] + 1.0, t[2 * e + 1] - 1.0));
            } else {
                let bound = left.bound(e);
                assert_eq!((a, b), (bound, -bound), "entry {e}");
            }
        }
        assert!(
            pushed
                .chunks(2)
                .enumerate()
                .all(|(e, f)| !left.is_bounded(e) || f.iter().all(|v| v.abs() <= left.bound(e)))
        );
    }
}
