//! Per-level index functions: where a grid vertex lives in its level's table.
//!
//! The engine only sees the [`LevelIndex`] trait. [`ReferenceIndex`] is tiny-cuda-nn's
//! (dense `x + y·res + z·res²` where the level fits, else the coherent-prime hash, both in
//! wrapping u32 and taken modulo the level size — spec §1.3–1.4). Keyed indices live in
//! `crate::stego` and implement the same trait.

use super::layout::{GridLayout, LevelInfo};
use std::sync::Arc;

/// tiny-cuda-nn's CoherentPrime constants for 3-D inputs.
pub const REFERENCE_PRIMES: [u32; 3] = [1, 2654435761, 805459861];

/// The index function of one grid level.
pub trait LevelIndex: Send + Sync {
    /// Table entry of vertex `(x, y, z)`, in `[0, level size)`.
    fn index(&self, x: u32, y: u32, z: u32) -> u32;

    /// The 8 corners of a cell; corner bit `d` selects `cell[d] + 1` (x is bit 0), as the
    /// reference interpolation does. One dynamic call per (sample, level).
    fn corners(&self, cell: [u32; 3], out: &mut [u32; 8]) {
        for (c, o) in out.iter_mut().enumerate() {
            *o = self.index(
                cell[0] + (c as u32 & 1),
                cell[1] + ((c as u32 >> 1) & 1),
                cell[2] + ((c as u32 >> 2) & 1),
            );
        }
    }
}

/// One index function per level, in level order.
pub type LevelIndices = Vec<Arc<dyn LevelIndex>>;

/// The reference (tiny-cuda-nn) index of one level.
#[derive(Clone, Copy, Debug)]
pub struct ReferenceIndex {
    resolution: u32,
    size: u32,
    dense: bool,
}

impl ReferenceIndex {
    pub fn new(level: &LevelInfo) -> Self {
        ReferenceIndex {
            resolution: level.resolution,
            size: level.size,
            dense: level.dense,
        }
    }
}

/// `x·π1 ⊕ y·π2 ⊕ z·π3` in wrapping u32 (tcnn `lcg_hash`).
#[inline(always)]
pub fn coherent_prime_hash(x: u32, y: u32, z: u32, primes: [u32; 3]) -> u32 {
    x.wrapping_mul(primes[0]) ^ y.wrapping_mul(primes[1]) ^ z.wrapping_mul(primes[2])
}

impl LevelIndex for ReferenceIndex {
    #[inline(always)]
    fn index(&self, x: u32, y: u32, z: u32) -> u32 {
        if self.dense {
            let r = self.resolution;
            x.wrapping_add(y.wrapping_mul(r))
                .wrapping_add(z.wrapping_mul(r.wrapping_mul(r)))
                % self.size
        } else if self.size.is_power_of_two() {
            coherent_prime_hash(x, y, z, REFERENCE_PRIMES) & (self.size - 1)
        } else {
            coherent_prime_hash(x, y, z, REFERENCE_PRIMES) % self.size
        }
    }

    fn corners(&self, cell: [u32; 3], out: &mut [u32; 8]) {
        if self.dense {
            let r = self.resolution;
            let base = cell[0]
                .wrapping_add(cell[1].wrapping_mul(r))
                .wrapping_add(cell[2].wrapping_mul(r.wrapping_mul(r)));
            let steps = [0, 1, r, r + 1, r * r, r * r + 1, r * r + r, r * r + r + 1];
            for c in 0..8 {
                out[c] = base.wrapping_add(steps[c]) % self.size;
            }
        } else {
            let hx = [cell[0], cell[0] + 1];
            let hy = [
                cell[1].wrapping_mul(REFERENCE_PRIMES[1]),
                (cell[1] + 1).wrapping_mul(REFERENCE_PRIMES[1]),
            ];
            let hz = [
                cell[2].wrapping_mul(REFERENCE_PRIMES[2]),
                (cell[2] + 1).wrapping_mul(REFERENCE_PRIMES[2]),
            ];
            let mask = self.size.wrapping_sub(1);
            let pow2 = self.size.is_power_of_two();
            for c in 0..8 {
                let h = hx[c & 1] ^ hy[(c >> 1) & 1] ^ hz[(c >> 2) & 1];
                out[c] = if pow2 { h & mask } else { h % self.size };
            }
        }
    }
}

/// The reference index for every level of `layout`.
pub fn reference_indices(layout: &GridLayout) -> LevelIndices {
    layout
        .levels
        .iter()
        .map(|l| Arc::new(ReferenceIndex::new(l)) as Arc<dyn LevelIndex>)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ngp::encoding::layout::{GridConfig, GridLayout};

    fn layout() -> GridLayout {
        GridLayout::new(GridConfig::default(), 1).unwrap()
    }

    #[test]
    fn dense_level_by_hand() {
        let g = layout();
        // Level 1: res 23, size 12168 = next_multiple(23³ = 12167, 8).
        let idx = ReferenceIndex::new(&g.levels[1]);
        assert_eq!(idx.index(0, 0, 0), 0);
        assert_eq!(idx.index(5, 7, 11), 5 + 7 * 23 + 11 * 529); // 5985
        assert_eq!(idx.index(22, 22, 22), 12166);
        // The upper corner may equal res and wraps into the next row / past the end.
        assert_eq!(idx.index(23, 22, 22), 12167);
        assert_eq!(idx.index(23, 23, 22), (23 + 23 * 23 + 22 * 529) % 12168); // 1
        assert_eq!(idx.index(23, 23, 23), (23 + 23 * 23 + 23 * 529) % 12168); // 530
    }

    #[test]
    fn hashed_level_by_hand() {
        let g = layout();
        let idx = ReferenceIndex::new(&g.levels[15]);
        // Worked out from the formula: 2·2654435761 mod 2^32 = 1013904226,
        // 3·805459861 mod 2^32 = 2416379583, 1 ^ 1013904226 ^ 2416379583 = 2892625372,
        // and 2892625372 mod 2^19 = 128476.
        assert_eq!(idx.index(1, 2, 3), 128476);
        assert_eq!(idx.index(0, 0, 0), 0);
        assert_eq!(idx.index(7, 0, 0), 7); // π1 = 1 leaves x unscrambled
        assert_eq!(idx.index(0, 1, 0), 489905); // 2654435761 mod 2^19
        // Level 5 (res 81) is the first hashed level of the paper config.
        let idx5 = ReferenceIndex::new(&g.levels[5]);
        assert_eq!(idx5.index(1, 2, 3), 128476);
    }

    #[test]
    fn corners_agree_with_index() {
        let g = layout();
        for l in [0usize, 3, 4, 5, 9, 15] {
            let idx = ReferenceIndex::new(&g.levels[l]);
            let r = g.levels[l].resolution;
            for cell in [[0, 0, 0], [r - 1, r - 1, r - 1], [3, r / 2, 1]] {
                let mut out = [0u32; 8];
                idx.corners(cell, &mut out);
                for (c, &o) in out.iter().enumerate() {
                    let want = idx.index(
                        cell[0] + (c as u32 & 1),
                        cell[1] + ((c as u32 >> 1) & 1),
                        cell[2] + ((c as u32 >> 2) & 1),
                    );
                    assert_eq!(o, want, "level {l} cell {cell:?} corner {c}");
                    assert!(o < g.levels[l].size);
                }
            }
        }
    }
}
