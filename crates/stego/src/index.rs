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
//!   [`IndexFn::Reference`] on all its levels, so `Key::reference()` *is* the reference.
//!
//! The result is plain data ([`LevelIndex`]: the arithmetic with its prime triple or
//! subkey, and a permutation table): keys, the KDF and the tables' making stay in this
//! layer; the engine only evaluates what it is handed.

use super::keys::{DenseMode, GroupKey, Key};
use super::permute::permuted_dense;
use super::prf;
use ngp::encoding::{GridLayout, IndexFn, LevelIndex, LevelIndices, LevelInfo};

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
pub fn level_index(group: &GroupKey, dense_mode: DenseMode, level: &LevelInfo) -> LevelIndex {
    let hashed = !level.dense || dense_mode == DenseMode::Hash;
    match group {
        GroupKey::Reference => LevelIndex::reference(level),
        GroupKey::Primes(k) if hashed => LevelIndex::new(level, IndexFn::Primes(*k)),
        GroupKey::Primes(k) => permuted_dense(level, primes_permute_key(*k, level)),
        GroupKey::Prf(secret) if hashed => {
            let sk = prf::derive_subkey(secret, prf::PURPOSE_INDEX, level.level, level.size);
            LevelIndex::new(level, IndexFn::Sip(sk))
        }
        GroupKey::Prf(secret) => {
            let sk =
                prf::derive_subkey(secret, prf::PURPOSE_DENSE_PERMUTE, level.level, level.size);
            permuted_dense(level, sk)
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

impl Key {
    /// The key's index function on every level of `layout`.
    pub fn level_indices(&self, layout: &GridLayout) -> LevelIndices {
        level_indices(self, layout)
    }
}
