//! Confinement: every hidden index mapped into the table entries the cover moved off their
//! initialisation (a public, keyless map a key holder recomputes from the file).
//!
//! The set is read from what the published file stores (the fp16 EMA weights), so a key
//! holder recomputes it and nothing is added to the file. During training it is recomputed
//! after every update of the cover's grid; hidden scenes never move an entry outside it, so
//! an entry off its initial value is one the cover moved. The key holder's set can differ
//! from the last one used in training only by entries the cover first moved in the last
//! ≤ 16 steps, which late in training are none or a handful (their slot runs map
//! differently; nothing else does).
//!
//! The mapping (per level, public, keyless): slots are visited in a fixed pseudo-random order
//! (`i ↦ a·i + c mod size`); a keyed index that lands on a slot outside the set moves to the
//! next slot in it in that order. When the set gains or loses an entry, only the indices
//! whose slot run crosses a changed slot move, so the hidden scene keeps what it learnt.

use crate::keys::Key;
use crate::steganalysis::INIT_BOUND;
use ngp::encoding::reach::{EntrySet, reference_reachable};
use ngp::encoding::{GridLayout, LevelIndex, LevelIndices};
use ngp::network::NerfLayout;
use ngp::occupancy::OccupancyGrid;
use std::sync::Arc;

/// A level's keyed index followed by the public map into the cover's reachable entries. A
/// table the index already has (a dense level's permutation) is composed with the map here,
/// so that a corner still costs one lookup.
pub fn confined(inner: LevelIndex, map: &Arc<[u32]>) -> LevelIndex {
    let table: Arc<[u32]> = match &inner.table {
        None => map.clone(),
        // An entry outside the map (maps are made per level of the same layout, so none)
        // would give an index that the trainer's check refuses.
        Some(t) => t
            .iter()
            .map(|&e| map.get(e as usize).copied().unwrap_or(u32::MAX))
            .collect(),
    };
    inner.with_table(table)
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

/// The level map: slots in the set map to themselves, the others to the next slot in the set
/// in the visiting order. With an empty set, the identity (no confinement possible).
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

/// The entries a hidden scene may share, as a key holder computes them from the file: those
/// off their initial value in the stored (fp16) weights, i.e. those the cover moved. The
/// entries the cover still reaches move at its pace; those it has left, within the
/// magnitude they had when it left them ([`super::left_entries`]).
pub fn cover_entries(layout: &NerfLayout, params: &[f32]) -> Vec<EntrySet> {
    let f = layout.config.grid.n_features as usize;
    layout
        .grid
        .levels
        .iter()
        .map(|lv| {
            let start = layout.grid_offset + lv.offset as usize * f;
            let table = &params[start..start + lv.size as usize * f];
            let mut moved = EntrySet::new(lv.size);
            for (e, feats) in table.chunks_exact(f).enumerate() {
                let at_init = feats
                    .iter()
                    .all(|&v| half::f16::from_f32(v).to_f32().abs() <= INIT_BOUND);
                if !at_init {
                    moved.insert(e as u32);
                }
            }
            // Before the cover has moved anything (the first step), every hidden index of the
            // level goes to one entry rather than anywhere: at most one entry a level is
            // touched that the cover might not have (at the first step its grid reaches every
            // entry, so the cover's pace holds it).
            if moved.is_empty() {
                moved.insert(0);
            }
            moved
        })
        .collect()
}

/// The level maps of a cover (shared by every hidden scene).
pub fn confinement_maps(layout: &NerfLayout, params: &[f32]) -> Vec<Arc<[u32]>> {
    cover_entries(layout, params)
        .iter()
        .map(|s| Arc::from(confinement_map(s)))
        .collect()
}

/// `key`'s index functions confined by `maps`.
pub fn confine(key: &Key, layout: &GridLayout, maps: &[Arc<[u32]>]) -> LevelIndices {
    confine_indices(&key.level_indices(layout), maps)
}

/// Index functions (a key's) confined by `maps`.
pub(super) fn confine_indices(inner: &[LevelIndex], maps: &[Arc<[u32]>]) -> LevelIndices {
    inner
        .iter()
        .zip(maps)
        .map(|(inner, map)| confined(inner.clone(), map))
        .collect()
}

/// Which of the cover's entries the hidden scenes are confined to.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ConfineTo {
    /// Those the cover moved off their initialisation (`--stealth`): read from the weights,
    /// so any edit of the weights that moves an entry off it (noise) moves the map.
    #[default]
    Moved,
    /// Those the reference index reaches from the stored occupancy grid's occupied cells
    /// (`--robust`): the entries no edit can reset without the cover's own samples reading
    /// the change, and a map read from the grid alone, which weight edits leave as it is.
    Reachable,
}

impl ConfineTo {
    pub fn name(self) -> &'static str {
        match self {
            ConfineTo::Moved => "moved",
            ConfineTo::Reachable => "reachable",
        }
    }
}

/// The entries the cover's stored grid lets the reference index reach, as a key holder
/// computes them from the file (`grid` as a reader rebuilds it:
/// [`OccupancyGrid::as_stored`] in training, the loaded grid after). A level the grid
/// reaches nowhere keeps one entry, as [`cover_entries`] does before the cover moved any.
pub fn reachable_cover_entries(layout: &NerfLayout, grid: &OccupancyGrid) -> Vec<EntrySet> {
    let mut sets = reference_reachable(&layout.grid, grid, layout.config.aabb_scale);
    for set in &mut sets {
        if set.is_empty() {
            set.insert(0);
        }
    }
    sets
}

/// A robust model's hidden index for `key`: the key's indices confined to the entries the
/// stored grid reaches.
pub fn robust_indices(key: &Key, layout: &NerfLayout, grid: &OccupancyGrid) -> LevelIndices {
    let maps: Vec<Arc<[u32]>> = reachable_cover_entries(layout, grid)
        .iter()
        .map(|s| Arc::from(confinement_map(s)))
        .collect();
    confine(key, &layout.grid, &maps)
}

/// The index functions a key holder renders a hidden scene with: the key's, confined to the
/// cover's entries (from the model's stored weights) when the model was trained with
/// stealth.
pub fn hidden_indices(
    key: &Key,
    layout: &NerfLayout,
    params: &[f32],
    stealth: bool,
) -> LevelIndices {
    if stealth && !key.is_reference() {
        confine(key, &layout.grid, &confinement_maps(layout, params))
    } else {
        key.level_indices(&layout.grid)
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
