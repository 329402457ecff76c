//! The key layer: key schemes, keyed per-level index functions, key files, key strength.
//!
//! Two schemes share one key-file format ([`keyfile`]):
//! - `primes` (the paper's): m prime triples, level l (0-based) uses triple `l mod m`.
//!   Hashed levels: `(x·k1 ⊕ y·k2 ⊕ z·k3) mod T` (u64 products; only `k mod T` matters,
//!   see [`strength`]). Π = {1, 2654435761, 805459861} is the reference index on every
//!   level, dense ones included.
//! - `prf` (ours, the default): m independent 256-bit secrets (key file version 2);
//!   `index = SipHash-2-4(subkey_l, x‖y‖z) mod size_l` with per-level subkeys from a
//!   documented KDF of the master that all m secrets make together ([`prf`]). Version-1
//!   files (one secret in m shares) still load, flagged as the weaker layout.
//!
//! Every level is keyed. Dense levels (res³ ≤ T, sizes not powers of two) use, per the
//! key's `dense` option, either a keyed permutation of the reference dense index
//! ([`permute`], default: no cell of the level collides, as in the cover's dense layout)
//! or the scheme's hash modulo the level size ([`index`]).
//!
//! Why `permute` is the default (measured by `tests::dense_hash_vs_permute_occupancy`, all
//! res³ cells of a level): a keyed hash leaves 36.7% (level 1, 12 168 slots) / 36.8%
//! (level 4, 205 384 slots) of the slots unused and puts 62.9% / 63.2% of the cells in a
//! shared slot (up to 7-9 cells per slot); the permutation uses every slot once (0
//! collisions), exactly as the reference dense layout does for the cover.
//!
//! Cost (`bench::bench_corners`, ns per `corners()` through `dyn`, best of 7, Xeon with
//! AVX-512, shared machine): reference 4.2 hashed / 18 dense; primes 5.3 / 17 (permute),
//! 19 (hash); prf 28 hashed, 17 dense (permute), 31 (hash). Dense levels are dominated by
//! the reference's u32 `% size`; the permutation adds one table lookup per corner.
//!
//! Key strength ([`strength`]), paper config (16 levels, T = 2^19): a prime triple is worth
//! 54 bits on hashed levels (only k mod 2^19, odd, matters) and ≤ 86.3 bits on dense ones;
//! with a per-key oracle (which the paper's partial-key PSNR table exhibits) m = 1 costs
//! ~2^54 and m = 16 ~2^88.6, not the paper's 2^1380. `prf`: 256-bit master, 128-bit
//! subkey per level, 2^132 even with a per-level oracle; with m − 1 of its m secrets
//! disclosed, still 256 bits (2^132 per-level) — version 1's shares left 256/m bits.

pub mod diagnostics;
pub mod index;
pub mod keyfile;
pub mod keys;
pub mod occupancy;
pub mod options;
pub mod permute;
pub mod prf;
pub mod primes;
pub mod stealth;
pub mod steganalysis;
pub mod strength;
pub mod variant;
pub mod view;

#[cfg(test)]
mod bench;
#[cfg(test)]
mod tests;

pub use keyfile::{
    LoadedKey, key_file_warnings, load_key, load_key_with_warnings, parse_key, save_key,
};
pub use keys::{
    Argon2Cost, DenseMode, GroupKey, Key, KeyScheme, Mixed, PI, SchemeKind,
    derive_prf_from_passphrase, derive_prf_from_passphrase_with, generate_prf, generate_primes,
    generate_with, random_salt,
};
pub use strength::{Disclosure, KeyStrength, key_strength};
pub use variant::KeyVariant;
pub use view::{OpenedScene, open_scene, open_scene_on};
