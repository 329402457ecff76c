//! Stealth: hidden scenes confined to the table entries the cover itself trains.
//!
//! A plain model's table records where its training went: entries the cover's samples never
//! reach stay at their initialisation, entries reached only before the occupancy grid pruned
//! empty space freeze where Adam left them. A hidden scene indexed across the whole table
//! trains those entries to the end, and an analyst can count that from the file alone
//! (`stegongp detect`). Stealth training maps every hidden-scene index into the cover's
//! *reachable set*: the entries that the cover's occupancy grid lets training reach under the
//! reference index ([`reachable_entries`]).
//!
//! The set depends only on the cover's occupancy grid, which the published file stores, so a
//! key holder recomputes it exactly and nothing is added to the file. During training it is
//! recomputed after every update of the cover's grid, from the grid as the file will store it
//! (fp16), so the mapping of the last steps is the one a key holder rebuilds.
//!
//! The mapping (per level, public, keyless): slots are visited in a fixed pseudo-random order
//! (`i ↦ a·i + c mod size`); a keyed index that lands on an unreachable slot moves to the next
//! reachable slot in that order. When the grid gains or loses a cell, only the indices whose
//! slot run crosses a changed slot move, so the hidden scene keeps what it learnt.

use super::keys::Key;
use crate::ngp::encoding::reach::{EntrySet, reachable_entries};
use crate::ngp::encoding::{GridLayout, LevelIndex, LevelIndices, reference_indices};
use crate::ngp::occupancy::OccupancyGrid;
use crate::ngp::train::IndexRefresh;
use std::sync::Arc;

/// A level's keyed index followed by the public map into the cover's reachable entries.
pub struct ConfinedIndex {
    inner: Arc<dyn LevelIndex>,
    map: Arc<[u32]>,
}

impl LevelIndex for ConfinedIndex {
    #[inline]
    fn index(&self, x: u32, y: u32, z: u32) -> u32 {
        self.map[self.inner.index(x, y, z) as usize]
    }

    fn corners(&self, cell: [u32; 3], out: &mut [u32; 8]) {
        self.inner.corners(cell, out);
        for o in out.iter_mut() {
            *o = self.map[*o as usize];
        }
    }
}

/// An odd-ish stride coprime to `size` near `size / φ`: visits every slot once.
fn stride(size: u32) -> u32 {
    let gcd = |mut a: u64, mut b: u64| {
        while b != 0 {
            (a, b) = (b, a % b);
        }
        a
    };
    let mut a = ((size as f64 * 0.618_033_988_75) as u32).max(1);
    while gcd(a as u64, size as u64) != 1 {
        a += 1;
    }
    a
}

/// The level map: reachable slots map to themselves, the others to the next reachable slot
/// in the visiting order. With nothing reachable, the identity (no confinement possible).
pub fn confinement_map(set: &EntrySet) -> Vec<u32> {
    let size = set.size();
    let mut map: Vec<u32> = (0..size).collect();
    if set.is_empty() || set.is_full() {
        return map;
    }
    let a = stride(size) as u64;
    let c = (size / 3) as u64;
    let slot = |i: u64| ((a * i + c) % size as u64) as u32;
    // Two passes backwards round the cycle: the second fills the run before the first
    // reachable slot in order.
    let mut next = u32::MAX;
    for k in (0..2 * size as u64).rev() {
        let s = slot(k % size as u64);
        if set.contains(s) {
            next = s;
        } else if next != u32::MAX {
            map[s as usize] = next;
        }
    }
    map
}

/// The cover's reachable entries as a key holder computes them from the stored grid: the
/// grid's values rounded to fp16 first (what the file holds), so training and reading agree
/// bit for bit.
pub fn cover_reachable(
    layout: &GridLayout,
    grid: &OccupancyGrid,
    aabb_scale: u32,
) -> Vec<EntrySet> {
    let stored: Vec<f32> = grid
        .density
        .iter()
        .map(|&v| half::f16::from_f32(v).to_f32())
        .collect();
    let stored = OccupancyGrid::from_density(stored).unwrap_or_else(|| grid.clone());
    reachable_entries(layout, &stored, aabb_scale, &reference_indices(layout))
}

/// The level maps of a cover grid (shared by every hidden scene).
pub fn confinement_maps(
    layout: &GridLayout,
    grid: &OccupancyGrid,
    aabb_scale: u32,
) -> Vec<Arc<[u32]>> {
    cover_reachable(layout, grid, aabb_scale)
        .iter()
        .map(|s| Arc::from(confinement_map(s)))
        .collect()
}

/// `key`'s index functions confined by `maps`.
pub fn confine(key: &Key, layout: &GridLayout, maps: &[Arc<[u32]>]) -> LevelIndices {
    key.level_indices(layout)
        .into_iter()
        .zip(maps)
        .map(|(inner, map)| {
            Arc::new(ConfinedIndex {
                inner,
                map: map.clone(),
            }) as Arc<dyn LevelIndex>
        })
        .collect()
}

/// The index functions a key holder renders a hidden scene with: the key's, confined to the
/// reachable entries of the model's stored grid when the model was trained with stealth.
pub fn hidden_indices(
    key: &Key,
    layout: &GridLayout,
    cover_grid: &OccupancyGrid,
    aabb_scale: u32,
    stealth: bool,
) -> LevelIndices {
    if stealth && !key.is_reference() {
        confine(
            key,
            layout,
            &confinement_maps(layout, cover_grid, aabb_scale),
        )
    } else {
        key.level_indices(layout)
    }
}

/// The trainer hook of stealth training: after every update of the cover's grid, the hidden
/// scenes (scenes 1..) get their keys' indices confined to the new reachable set.
pub struct StealthRefresh {
    layout: GridLayout,
    aabb_scale: u32,
    keys: Vec<Key>,
}

impl StealthRefresh {
    /// `keys[i]` is the key of scene `i + 1`.
    pub fn new(layout: GridLayout, aabb_scale: u32, keys: Vec<Key>) -> Self {
        StealthRefresh {
            layout,
            aabb_scale,
            keys,
        }
    }
}

impl IndexRefresh for StealthRefresh {
    fn refresh(&self, cover_grid: &OccupancyGrid) -> Vec<(usize, LevelIndices)> {
        let maps = confinement_maps(&self.layout, cover_grid, self.aabb_scale);
        self.keys
            .iter()
            .enumerate()
            .map(|(i, k)| (i + 1, confine(k, &self.layout, &maps)))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn strides_visit_every_slot() {
        for size in [1u32, 2, 8, 12_168, 205_384, 1 << 14, 1 << 19] {
            let a = stride(size) as u64;
            let mut seen = vec![false; size as usize];
            for i in 0..size as u64 {
                seen[((a * i + 7) % size as u64) as usize] = true;
            }
            assert!(seen.iter().all(|&s| s), "size {size}");
        }
    }

    #[test]
    fn the_map_lands_only_on_reachable_slots_and_keeps_them() {
        let mut set = EntrySet::new(1000);
        for s in [3u32, 500, 999, 42, 77] {
            set.insert(s);
        }
        let map = confinement_map(&set);
        for (s, &m) in map.iter().enumerate() {
            assert!(set.contains(m), "slot {s} maps to unreachable {m}");
            if set.contains(s as u32) {
                assert_eq!(m, s as u32);
            }
        }
        // Every reachable slot takes the run of unreachable slots before it: all used.
        let mut used = std::collections::BTreeSet::new();
        used.extend(map.iter().copied());
        assert_eq!(used.len(), 5);
    }

    #[test]
    fn one_more_reachable_slot_moves_only_its_run() {
        let size = 4096u32;
        let mut set = EntrySet::new(size);
        for s in (0..size).step_by(10) {
            set.insert(s);
        }
        let before = confinement_map(&set);
        set.insert(1235);
        let after = confinement_map(&set);
        let moved = before.iter().zip(&after).filter(|(a, b)| a != b).count();
        // The new slot captures at most the run before it (about 10 slots), and itself.
        assert!((1..=40).contains(&moved), "{moved} slots moved");
        assert_eq!(after[1235], 1235);
    }

    #[test]
    fn empty_and_full_sets_leave_the_index_alone() {
        let id: Vec<u32> = (0..64).collect();
        assert_eq!(confinement_map(&EntrySet::new(64)), id);
        assert_eq!(confinement_map(&EntrySet::full(64)), id);
    }
}
