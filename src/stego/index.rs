//! Keyed per-level index functions and their assembly from a [`Key`].
//!
//! Arithmetic, per level of size `s` (see also the `stego` module docs):
//! - `primes`, hashed level (s = T, a power of two): `(x·k1 ⊕ y·k2 ⊕ z·k3) mod T` with
//!   wrapping u64 products. The low bits of a u64 product equal those of tcnn's u32
//!   product, so with Π this is exactly the reference hash.
//! - `primes`, dense level, `dense = "hash"`: the same u64 expression `mod s`. With x, y,
//!   z < 2^11 and k < 2^34 nothing wraps, so every bit of every k can move the result.
//! - `prf`: `SipHash-2-4(subkey_l, x‖y‖z) mod s` on every level in `hash` mode.
//! - `dense = "permute"` (both schemes): `P_l(d)` with `d` the reference dense index and
//!   `P_l` a keyed Feistel permutation of `[0, s)` ([`super::permute`]).
//! - A key group equal to Π (or masked to the reference by a partial key) uses
//!   [`ReferenceIndex`] on all its levels, so `Key::reference()` *is* the reference.

use super::keys::{DenseMode, GroupKey, Key};
use super::permute::PermutedDenseIndex;
use super::prf::{self, PrfIndex};
use crate::ngp::encoding::{GridLayout, LevelIndex, LevelIndices, LevelInfo, ReferenceIndex};
use std::sync::Arc;

/// `(x·k1 ⊕ y·k2 ⊕ z·k3) mod size` in wrapping u64.
#[derive(Clone, Copy, Debug)]
pub struct PrimeIndex {
    k: [u64; 3],
    size: u32,
}

impl PrimeIndex {
    pub fn new(k: [u64; 3], size: u32) -> Self {
        PrimeIndex { k, size }
    }

    #[inline(always)]
    fn reduce(&self, h: u64) -> u32 {
        if self.size.is_power_of_two() {
            (h & (self.size as u64 - 1)) as u32
        } else {
            (h % self.size as u64) as u32
        }
    }
}

impl LevelIndex for PrimeIndex {
    #[inline]
    fn index(&self, x: u32, y: u32, z: u32) -> u32 {
        let h = (x as u64).wrapping_mul(self.k[0])
            ^ (y as u64).wrapping_mul(self.k[1])
            ^ (z as u64).wrapping_mul(self.k[2]);
        self.reduce(h)
    }

    fn corners(&self, cell: [u32; 3], out: &mut [u32; 8]) {
        let axis = |i: usize| {
            let c = cell[i] as u64;
            [c.wrapping_mul(self.k[i]), (c + 1).wrapping_mul(self.k[i])]
        };
        let (hx, hy, hz) = (axis(0), axis(1), axis(2));
        for (c, o) in out.iter_mut().enumerate() {
            *o = self.reduce(hx[c & 1] ^ hy[(c >> 1) & 1] ^ hz[(c >> 2) & 1]);
        }
    }
}

/// Permutation key for a prime triple on a dense level: the documented KDF applied to the
/// triple (24 bytes LE, zero-padded to 32) so that all bits of all three primes count.
fn primes_permute_key(k: [u64; 3], level: &LevelInfo) -> prf::SipKey {
    let mut s = [0u8; 32];
    for (i, v) in k.iter().enumerate() {
        s[8 * i..8 * i + 8].copy_from_slice(&v.to_le_bytes());
    }
    prf::derive_subkey(
        &s,
        prf::PURPOSE_PRIMES_DENSE_PERMUTE,
        level.level,
        level.size,
    )
}

/// The index function of one level under one key group.
pub fn level_index(
    group: &GroupKey,
    dense_mode: DenseMode,
    level: &LevelInfo,
) -> Arc<dyn LevelIndex> {
    match group {
        GroupKey::Reference => Arc::new(ReferenceIndex::new(level)),
        GroupKey::Primes(k) => {
            if !level.dense || dense_mode == DenseMode::Hash {
                Arc::new(PrimeIndex::new(*k, level.size))
            } else {
                Arc::new(PermutedDenseIndex::new(
                    level,
                    primes_permute_key(*k, level),
                ))
            }
        }
        GroupKey::Prf(secret) => {
            if !level.dense || dense_mode == DenseMode::Hash {
                let sk = prf::derive_subkey(secret, prf::PURPOSE_INDEX, level.level, level.size);
                Arc::new(PrfIndex::new(sk, level.size))
            } else {
                let sk =
                    prf::derive_subkey(secret, prf::PURPOSE_DENSE_PERMUTE, level.level, level.size);
                Arc::new(PermutedDenseIndex::new(level, sk))
            }
        }
    }
}

/// One index function per level of `layout`: level `l` (0-based) uses key group `l mod m`.
pub fn level_indices(key: &Key, layout: &GridLayout) -> LevelIndices {
    layout
        .levels
        .iter()
        .map(|lv| level_index(&key.group_for_level(lv.level as usize), key.dense(), lv))
        .collect()
}
