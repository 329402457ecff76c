//! Keyed permutation of a dense level's slots: an unbalanced Feistel network on the
//! smallest power of two ≥ size, with cycle-walking back into `[0, size)`.
//!
//! Applied to the reference dense index `d = (x + y·res + z·res²) mod size`, it keeps the
//! dense layout's property that distinct cells of the level get distinct slots, for the
//! hidden scene as for the cover (a keyed hash mod size would collide ~37% of them).
//! Round function: `F_r(v) = SipHash-2-4(key, r ‖ v)` (both u32 LE). 8 rounds, well above
//! the 4 a Luby–Rackoff PRP needs. The permutation is tabulated once per level, so the
//! per-sample cost is one table lookup per corner.

use super::prf::{SipKey, siphash24};
use ngp::encoding::{LevelIndex, LevelInfo};

const ROUNDS: u32 = 8;

/// The Feistel permutation of `[0, 2^bits)`.
#[derive(Clone, Debug)]
pub struct Feistel {
    key: SipKey,
    bits: u32,
}

impl Feistel {
    pub fn new(key: SipKey, bits: u32) -> Self {
        Feistel {
            key,
            bits: bits.clamp(2, 32),
        }
    }

    fn f(&self, round: u32, v: u32) -> u64 {
        let mut m = [0u8; 8];
        m[..4].copy_from_slice(&round.to_le_bytes());
        m[4..].copy_from_slice(&v.to_le_bytes());
        siphash24(self.key, &m)
    }

    /// Each round maps (hi: wh bits, lo: wl bits) to (lo, hi ⊕ F(lo)), widths swapping, so
    /// odd bit counts need no padding to an even width (fewer cycle-walking steps).
    pub fn permute(&self, v: u32) -> u32 {
        let mut wl = self.bits / 2;
        let mut wh = self.bits - wl;
        let mask = |w: u32| if w >= 32 { u32::MAX } else { (1u32 << w) - 1 };
        let mut lo = v & mask(wl);
        let mut hi = (v >> wl) & mask(wh);
        for r in 0..ROUNDS {
            let new_hi = lo;
            let new_lo = hi ^ (self.f(r, lo) as u32 & mask(wh));
            hi = new_hi;
            lo = new_lo;
            std::mem::swap(&mut wl, &mut wh);
            // After the swap, `hi` has wh bits and `lo` has wl bits again.
        }
        (hi << wl) | lo
    }

    /// The permutation restricted to `[0, size)` by cycle walking (size ≤ 2^bits).
    pub fn permute_below(&self, v: u32, size: u32) -> u32 {
        let mut y = self.permute(v);
        while y >= size {
            y = self.permute(y);
        }
        y
    }
}

/// Bits of the smallest power of two ≥ n.
pub fn domain_bits(n: u32) -> u32 {
    32 - n.saturating_sub(1).leading_zeros()
}

/// The table of a keyed permutation of `[0, size)`.
pub fn permutation_table(key: SipKey, size: u32) -> Vec<u32> {
    let f = Feistel::new(key, domain_bits(size));
    (0..size).map(|d| f.permute_below(d, size)).collect()
}

/// Dense level indexed `table[reference dense index]`, the table a keyed permutation of
/// its slots.
pub fn permuted_dense(level: &LevelInfo, key: SipKey) -> LevelIndex {
    LevelIndex::reference(level).with_table(permutation_table(key, level.size))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn feistel_is_a_bijection_for_odd_and_even_widths() {
        for bits in [2u32, 5, 8, 11] {
            let f = Feistel::new([1, 2], bits);
            let mut seen = vec![false; 1 << bits];
            for v in 0..(1u32 << bits) {
                let y = f.permute(v);
                assert!(y < 1 << bits);
                assert!(!seen[y as usize], "bits {bits}: collision at {v}");
                seen[y as usize] = true;
            }
        }
    }

    #[test]
    fn table_is_a_permutation_and_keyed() {
        for size in [4096u32, 12168, 29792] {
            let t = permutation_table([3, 4], size);
            let mut s = t.clone();
            s.sort_unstable();
            assert!(
                s.iter().enumerate().all(|(i, &v)| i as u32 == v),
                "size {size}"
            );
            let fixed = t
                .iter()
                .enumerate()
                .filter(|&(i, &v)| i as u32 == v)
                .count();
            assert!(fixed < 20, "size {size}: {fixed} fixed points");
            let u = permutation_table([3, 5], size);
            let same = t.iter().zip(&u).filter(|(a, b)| a == b).count();
            assert!(same < 20, "size {size}: keys agree on {same} slots");
        }
        assert_eq!(domain_bits(4096), 12);
        assert_eq!(domain_bits(4097), 13);
        assert_eq!(domain_bits(205384), 18);
    }
}
