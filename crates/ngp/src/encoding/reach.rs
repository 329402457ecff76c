//! Which table entries an occupancy grid lets training reach.
//!
//! Training samples only in occupied cells, and a sample at position `p` reads the
//! occupancy bit of cascade `max(mip_from_pos(p), mip_from_dt(dt))`. Every cascade above 0
//! also holds the OR-pooled bits of the finer one, so a bit set at any cascade that covers
//! `p` implies the bit of the coarsest cascade at `p`: the positions a training sample can
//! ever take are exactly those in the coarsest cascade's occupied cells (clipped to the
//! box). For aabb_scale 1 that is cascade 0 itself; for larger boxes it is a superset of
//! what cone-stepped rays sample in practice.
//!
//! An entry of a level is *reachable* if some grid vertex of a level cell that intersects
//! such a position maps to it under the level's index function. An analyst can compute
//! this from a published file alone (its stored grid, with the reference index); so can a
//! trainer, which is what tells stealth training which entries the cover has left
//! ([`crate::train::left_entries`]).

use super::index::{Kernel, LevelIndices, WithKernel};
use super::layout::{GridLayout, LevelInfo};
use crate::occupancy::{GRID_SIZE, OccupancyGrid};
use crate::render::march::Marcher;
use rayon::prelude::*;

/// A set of entries `[0, size)` of one level, as a bitmap.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct EntrySet {
    size: u32,
    count: u32,
    bits: Vec<u64>,
}

impl EntrySet {
    pub fn new(size: u32) -> Self {
        EntrySet {
            size,
            count: 0,
            bits: vec![0; (size as usize).div_ceil(64)],
        }
    }

    /// Every entry of the level.
    pub fn full(size: u32) -> Self {
        let mut s = EntrySet::new(size);
        for i in 0..size {
            s.insert(i);
        }
        s
    }

    /// Adds entry `i`; true if it was not there.
    #[inline]
    pub fn insert(&mut self, i: u32) -> bool {
        let (w, b) = ((i / 64) as usize, i % 64);
        let new = self.bits[w] >> b & 1 == 0;
        self.bits[w] |= 1 << b;
        self.count += new as u32;
        new
    }

    #[inline]
    pub fn contains(&self, i: u32) -> bool {
        i < self.size && self.bits[(i / 64) as usize] >> (i % 64) & 1 != 0
    }

    /// Number of entries in the set.
    pub fn len(&self) -> u32 {
        self.count
    }

    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// Number of entries of the level.
    pub fn size(&self) -> u32 {
        self.size
    }

    pub fn is_full(&self) -> bool {
        self.count == self.size
    }

    pub fn fraction(&self) -> f64 {
        self.count as f64 / self.size.max(1) as f64
    }

    /// The set's bits, 64 entries a word (what a training state saves).
    pub fn words(&self) -> &[u64] {
        &self.bits
    }

    /// A set of `size` entries from its [`Self::words`]; `None` when their count does not
    /// fit `size` or a bit past the last entry is set.
    pub fn from_words(size: u32, bits: Vec<u64>) -> Option<Self> {
        if bits.len() != (size as usize).div_ceil(64) {
            return None;
        }
        if !size.is_multiple_of(64)
            && let Some(&last) = bits.last()
            && last >> (size % 64) != 0
        {
            return None;
        }
        let count = bits.iter().map(|w| w.count_ones()).sum();
        Some(EntrySet { size, count, bits })
    }
}

/// [`reachable_entries`] through the reference index: the entries the standard (keyless)
/// index reaches from `grid`'s occupied cells, what an analyst computes from a file.
pub fn reference_reachable(
    layout: &GridLayout,
    grid: &OccupancyGrid,
    aabb_scale: u32,
) -> Vec<EntrySet> {
    reachable_entries(
        layout,
        grid,
        aabb_scale,
        &super::index::reference_indices(layout),
    )
}

/// Network-space (`[0,1]³`) boxes of the coarsest cascade's occupied cells, clipped to the
/// box; empty when no cell is occupied.
pub fn occupied_boxes(grid: &OccupancyGrid, aabb_scale: u32) -> Vec<([f32; 3], [f32; 3])> {
    let bounds = axis_bounds(grid, aabb_scale);
    grid.occupied_cells(grid.max_cascade())
        .into_iter()
        .map(|cell| {
            let lo = [0, 1, 2].map(|d| bounds[d][cell[d] as usize].0);
            let hi = [0, 1, 2].map(|d| bounds[d][cell[d] as usize].1);
            (lo, hi)
        })
        .collect()
}

/// The vertices of `level` (first and last, inclusive) along one axis of a network-space
/// span: exactly as the encoding takes cells (`fma(scale, x, 0.5)`, floor), plus the far
/// corner.
fn vertex_range(level: &LevelInfo, (lo, hi): (f32, f32)) -> (u32, u32) {
    let a = level.scale.mul_add(lo, 0.5).floor() as i32 as u32;
    let b = level.scale.mul_add(hi, 0.5).floor() as i32 as u32 + 1;
    (a, b)
}

/// The entries of every level of `layout` that training can reach through `indices` given
/// the occupancy `grid` (see the module docs). Deterministic: the cover's trainer and a key
/// holder reading the stored grid compute the same sets.
///
/// The vertex range of a cell along an axis depends on its coordinate on that axis alone,
/// and on a coarse level many neighbouring cells share it: cells are first reduced to the
/// distinct triples of axis ranges, so each vertex block is hashed once, not once per cell
/// in it (early in training every cell is occupied and each refresh of a stealth model
/// rebuilt the dense levels from two million boxes).
pub fn reachable_entries(
    layout: &GridLayout,
    grid: &OccupancyGrid,
    aabb_scale: u32,
    indices: &LevelIndices,
) -> Vec<EntrySet> {
    let cells = grid.occupied_cells(grid.max_cascade());
    let bounds = axis_bounds(grid, aabb_scale);
    layout
        .levels
        .par_iter()
        .zip(indices.par_iter())
        .map(|(level, index)| {
            let axes: [AxisClasses; 3] = std::array::from_fn(|d| {
                AxisClasses::new(bounds[d].iter().map(|&span| vertex_range(level, span)))
            });
            let n = [0, 1, 2].map(|d| axes[d].ranges.len());
            let mut marked = vec![false; n[0] * n[1] * n[2]];
            for c in &cells {
                let k = [0, 1, 2].map(|d| axes[d].class[c[d] as usize] as usize);
                marked[(k[2] * n[1] + k[1]) * n[0] + k[0]] = true;
            }
            index.with_kernel(InsertBlocks {
                set: EntrySet::new(level.size),
                axes: &axes,
                marked: &marked,
            })
        })
        .collect()
}

/// Network-space `(lo, hi)` of every cell coordinate of the coarsest cascade, per axis,
/// clipped to the box: a cell's box is its three coordinates' spans ([`occupied_boxes`]).
fn axis_bounds(grid: &OccupancyGrid, aabb_scale: u32) -> [Vec<(f32, f32)>; 3] {
    let marcher = Marcher::new(aabb_scale);
    let s = (grid.max_cascade() as f32).exp2();
    let g = GRID_SIZE as f32;
    let mut out: [Vec<(f32, f32)>; 3] = Default::default();
    for c in 0..GRID_SIZE {
        let lo = marcher.warp([(c as f32 / g - 0.5) * s + 0.5; 3]);
        let hi = marcher.warp([((c + 1) as f32 / g - 0.5) * s + 0.5; 3]);
        for d in 0..3 {
            out[d].push((lo[d].clamp(0.0, 1.0), hi[d].clamp(0.0, 1.0)));
        }
    }
    out
}

/// One axis of a level: the distinct vertex ranges of the cell coordinates (in order: the
/// ranges grow with the coordinate, so equal ones are neighbours) and each coordinate's.
struct AxisClasses {
    ranges: Vec<(u32, u32)>,
    class: Vec<u32>,
}

impl AxisClasses {
    fn new(per_cell: impl Iterator<Item = (u32, u32)>) -> Self {
        let mut ranges: Vec<(u32, u32)> = Vec::new();
        let mut class = Vec::new();
        for r in per_cell {
            if ranges.last() != Some(&r) {
                ranges.push(r);
            }
            class.push(ranges.len() as u32 - 1);
        }
        AxisClasses { ranges, class }
    }
}

/// Inserts the vertex block of every marked triple of axis ranges, with the level's kernel
/// taken once.
struct InsertBlocks<'a> {
    set: EntrySet,
    axes: &'a [AxisClasses; 3],
    marked: &'a [bool],
}

impl WithKernel for InsertBlocks<'_> {
    type Output = EntrySet;

    fn run<K: Kernel>(self, index: K) -> EntrySet {
        let InsertBlocks {
            mut set,
            axes,
            marked,
        } = self;
        let [ax, ay, az] = axes;
        let blocks = az.ranges.iter().flat_map(|&z| {
            ay.ranges
                .iter()
                .flat_map(move |&y| ax.ranges.iter().map(move |&x| [x, y, z]))
        });
        for (block, _) in blocks.zip(marked).filter(|(_, m)| **m) {
            insert_block(&mut set, &index, block);
            if set.is_full() {
                break;
            }
        }
        set
    }
}

/// Every vertex of a block given by its (first, last) vertex per axis.
fn insert_block<K: Kernel>(set: &mut EntrySet, index: &K, [x, y, z]: [(u32, u32); 3]) {
    for vz in z.0..=z.1 {
        for vy in y.0..=y.1 {
            for vx in x.0..=x.1 {
                set.insert(index.index(vx, vy, vz));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::encoding::{GridConfig, LevelIndex, reference_indices};
    use crate::occupancy::N_CELLS;

    fn grid_with(cells: &[[u32; 3]], n_cascades: usize) -> OccupancyGrid {
        let mut density = vec![0.0f32; N_CELLS * n_cascades];
        for c in cells {
            density[crate::occupancy::morton3d(c[0], c[1], c[2]) as usize] = 1.0;
        }
        OccupancyGrid::from_density(density).unwrap()
    }

    fn small_layout() -> GridLayout {
        let cfg = GridConfig {
            n_levels: 4,
            n_features: 2,
            log2_hashmap_size: 12,
            base_resolution: 16,
        };
        GridLayout::new(cfg, 1).unwrap()
    }

    #[test]
    fn one_cell_reaches_the_vertices_around_it() {
        // Cell (64, 64, 64) of a 1-cascade grid spans [0.5, 0.5 + 1/128]³. At level 0
        // (scale 15) that is x·15 + 0.5 ∈ [8.0, 8.117]: vertices 8..=9 on each axis.
        let layout = small_layout();
        let grid = grid_with(&[[64, 64, 64]], 1);
        let idx = reference_indices(&layout);
        let sets = reachable_entries(&layout, &grid, 1, &idx);
        let l0 = layout.levels[0];
        assert_eq!(l0.scale, 15.0);
        assert!(l0.dense);
        let mut want = EntrySet::new(l0.size);
        let r = LevelIndex::reference(&l0);
        for z in 8..=9 {
            for y in 8..=9 {
                for x in 8..=9 {
                    want.insert(r.index(x, y, z));
                }
            }
        }
        assert_eq!(sets[0], want);
        assert_eq!(sets[0].len(), 8);
        // The dense index by hand: 8 + 8·16 + 8·256 is one of them.
        assert!(sets[0].contains(8 + 8 * 16 + 8 * 256));
        assert!(!sets[0].contains(0));
    }

    #[test]
    fn an_empty_grid_reaches_nothing_and_a_full_one_everything() {
        let layout = small_layout();
        let idx = reference_indices(&layout);
        let empty = grid_with(&[], 1);
        for s in reachable_entries(&layout, &empty, 1, &idx) {
            assert!(s.is_empty());
        }
        let full = OccupancyGrid::from_density(vec![1.0; N_CELLS]).unwrap();
        for (s, l) in reachable_entries(&layout, &full, 1, &idx)
            .iter()
            .zip(&layout.levels)
        {
            // Hashed levels: the coherent-prime hash of the whole vertex lattice covers the
            // table; dense levels: every vertex is its own entry.
            assert_eq!(s.len(), l.size, "level {}", l.level);
        }
    }

    #[test]
    fn the_coarsest_cascade_decides_for_larger_boxes() {
        // aabb_scale 2: two cascades. A cell occupied only in cascade 0 is pooled into
        // cascade 1, whose cell (twice as large in each axis) is what counts.
        let layout = GridLayout::new(small_layout().config, 2).unwrap();
        let idx = reference_indices(&layout);
        let grid = grid_with(&[[64, 64, 64]], 2);
        let boxes = occupied_boxes(&grid, 2);
        assert_eq!(boxes.len(), 1);
        // Cascade-0 cell 64 pools into cascade-1 cell 32 + 64/2 = 64: world
        // [0.5, 0.5 + 2/128], which is network-space [0.5, 0.5 + 1/128] in the box [−0.5, 1.5].
        let (lo, hi) = boxes[0];
        assert_eq!(lo, [0.5; 3]);
        assert!((hi[0] - (0.5 + 1.0 / 128.0)).abs() < 1e-6);
        let sets = reachable_entries(&layout, &grid, 2, &idx);
        assert!(sets.iter().all(|s| !s.is_empty()));
    }

    /// Every occupied box's vertices, one box at a time: what the blocks must equal.
    fn reachable_box_by_box(
        layout: &GridLayout,
        grid: &OccupancyGrid,
        aabb_scale: u32,
        indices: &LevelIndices,
    ) -> Vec<EntrySet> {
        let boxes = occupied_boxes(grid, aabb_scale);
        layout
            .levels
            .iter()
            .zip(indices)
            .map(|(level, index)| {
                let mut set = EntrySet::new(level.size);
                for (lo, hi) in &boxes {
                    let block = [0, 1, 2].map(|d| vertex_range(level, (lo[d], hi[d])));
                    index.with_kernel(InsertBlock(&mut set, block));
                }
                set
            })
            .collect()
    }

    /// One block through [`insert_block`], the level's kernel taken per block.
    struct InsertBlock<'a>(&'a mut EntrySet, [(u32, u32); 3]);

    impl WithKernel for InsertBlock<'_> {
        type Output = ();
        fn run<K: Kernel>(self, index: K) {
            insert_block(self.0, &index, self.1)
        }
    }

    #[test]
    fn blocks_reach_what_the_boxes_reach() {
        use crate::encoding::IndexFn;
        use crate::rng::Pcg32;
        let mut r = Pcg32::new(11, 3);
        for (aabb_scale, n_cascades, occupied) in [(1, 1, 0.002), (4, 3, 0.0005), (1, 1, 0.02)] {
            let cfg = GridConfig {
                n_levels: 8,
                log2_hashmap_size: 16,
                ..small_layout().config
            };
            let layout = GridLayout::new(cfg, aabb_scale).unwrap();
            let density: Vec<f32> = (0..N_CELLS * n_cascades)
                .map(|_| (r.next_f32() < occupied) as u32 as f32)
                .collect();
            let grid = OccupancyGrid::from_density(density).unwrap();
            let keyed: LevelIndices = layout
                .levels
                .iter()
                .map(|lv| {
                    let map: Vec<u32> = (0..lv.size).map(|e| (e * 7 + 3) % lv.size).collect();
                    LevelIndex::new(lv, IndexFn::Primes([5, 9, 1 << 20])).with_table(map)
                })
                .collect();
            for idx in [reference_indices(&layout), keyed] {
                let got = reachable_entries(&layout, &grid, aabb_scale, &idx);
                let want = reachable_box_by_box(&layout, &grid, aabb_scale, &idx);
                for (l, (g, w)) in got.iter().zip(&want).enumerate() {
                    assert_eq!(g, w, "aabb {aabb_scale}, occupied {occupied}, level {l}");
                    assert!(!w.is_empty());
                }
                // Some level is left partly unreached: the comparison means something.
                assert!(
                    want.iter().any(|w| !w.is_full()),
                    "aabb {aabb_scale}, occupied {occupied}: every level full"
                );
            }
        }
    }

    #[test]
    fn entry_sets_count() {
        let mut s = EntrySet::new(100);
        assert!(s.insert(99));
        assert!(!s.insert(99));
        assert!(s.insert(0));
        assert_eq!(s.len(), 2);
        assert!(s.contains(99) && !s.contains(98) && !s.contains(100));
        assert!(EntrySet::full(70).is_full());
    }
}
