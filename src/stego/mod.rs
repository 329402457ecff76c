//! The key layer: key schemes, keyed per-level index functions, key files, key strength.
//!
//! Two schemes share one key-file format ([`keyfile`]):
//! - `primes` (the paper's): m prime triples, level l (0-based) uses triple `l mod m`.
//!   Hashed levels: `(x·k1 ⊕ y·k2 ⊕ z·k3) mod T` (u64 products; only `k mod T` matters,
//!   see [`strength`]). Π = {1, 2654435761, 805459861} is the reference index on every
//!   level, dense ones included.
//! - `prf` (ours, the default): a 256-bit secret; `index = SipHash-2-4(subkey_l, x‖y‖z)
//!   mod size_l` with per-level subkeys from a documented KDF ([`prf`]).
//!
//! Every level is keyed. Dense levels (res³ ≤ T, sizes not powers of two) use, per the
//! key's `dense` option, either a keyed permutation of the reference dense index
//! ([`permute`], default: no cell of the level collides, as in the cover's dense layout)
//! or the scheme's hash modulo the level size ([`index`]).

pub mod diagnostics;
pub mod index;
pub mod keyfile;
pub mod keys;
pub mod permute;
pub mod prf;
pub mod primes;
pub mod strength;

#[cfg(test)]
mod bench;
#[cfg(test)]
mod tests;

pub use keyfile::{load_key, parse_key, save_key};
pub use keys::{
    DenseMode, GroupKey, Key, KeyScheme, Mixed, PI, derive_prf_from_passphrase, generate_prf,
    generate_primes,
};
pub use strength::{KeyStrength, key_strength};
