//! Effective key strength, counted from the index arithmetic actually used.
//!
//! `bits` of a level = log2 of the number of distinct index functions the key can give that
//! level (an upper bound for dense levels). `primes`: on a hashed level of size 2^t only
//! `k mod 2^t` matters and every prime is odd → `min(t−1, log2 U)` bits per prime
//! (T = 2^19: 18, so 54 per triple); on a dense level (hash: u64 products mod a
//! non-power-of-two size; permute: a KDF of the whole triple) every bit counts → log2 U ≈
//! 28.76 per prime, U = 454 387 932 primes in [1e7, 1e10]. Entries equal to Π count 0.
//! `prf`: every keyed level has its own 128-bit SipHash subkey derived from a 256-bit
//! master, which (version 2) is derived from all m 256-bit secrets together.
//!
//! `total_bits`: brute force over everything that changes some level's function.
//! `oracle_bits`: the work when each key group (primes) or each level (prf) can be
//! recognised on its own — the paper's partial-key table shows PSNR rising with each
//! correct key, so this is the realistic figure for `primes`.
//!
//! `after_disclosure[j]` (j = 0 … m − 1): what is left when j of the m keys are disclosed,
//! the worst case over which j (the attacker learns the most valuable ones; with the
//! paper's cyclic assignment those are the first j, whose groups hold the dense levels).
//! - `primes`: the undisclosed groups' bits. Brute force multiplies them (a sum of bits);
//!   with the per-group oracle each group is searched on its own, so the work is a *sum*
//!   of 2^bits over the undisclosed groups (its log2 is `oracle_bits`).
//! - `prf` (version 2): each key is an independent 256-bit secret and every subkey needs
//!   all of them, so any j < m leaves min(256·(m−j), 256) = 256 bits (past 256 the master
//!   itself is the cheaper target), and there is no per-key oracle: a wrong secret gives
//!   noise on every level. The per-level figure (a level's 128-bit subkey recognised on
//!   its own, `levels:P`) does not depend on j.
//! - `prf` version 1 (shares of one secret): the undisclosed shares' bits, e.g. 16 for
//!   m = 16 and j = 15.

use super::keys::{GroupKey, Key, KeyScheme, PI, share_range};
use super::primes::PRIMES_IN_RANGE;
use crate::ngp::encoding::GridLayout;

#[derive(Clone, Debug, serde::Serialize)]
pub struct LevelStrength {
    pub level: u32,
    pub resolution: u32,
    pub size: u32,
    pub dense: bool,
    pub group: usize,
    pub bits: f64,
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct KeyStrength {
    pub scheme: String,
    pub m: usize,
    pub dense_mode: String,
    pub levels: Vec<LevelStrength>,
    /// Bits that determine each group's index functions.
    pub group_bits: Vec<f64>,
    pub total_bits: f64,
    pub oracle_bits: f64,
    /// What the paper states for this m (86.3 bits per prime triple), primes only.
    pub paper_claim_bits: Option<f64>,
    /// Bits left when j = 0 … m − 1 of the m keys are disclosed (index j).
    pub after_disclosure: Vec<Disclosure>,
}

/// What an attacker still faces when `disclosed` of the `m` keys are known.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Disclosure {
    pub disclosed: usize,
    /// Brute force over the undisclosed keys together (product of their spaces).
    pub brute_force_bits: f64,
    /// With the per-group oracle (`primes`: sum over the undisclosed groups) or the
    /// per-level oracle (`prf`: a level's subkey on its own), whichever is cheaper than
    /// brute force.
    pub oracle_bits: f64,
}

fn log2_sum_pow2(bits: impl IntoIterator<Item = f64>) -> f64 {
    let b: Vec<f64> = bits.into_iter().filter(|&b| b > 0.0).collect();
    let Some(max) = b.iter().cloned().reduce(f64::max) else {
        return 0.0;
    };
    max + b.iter().map(|x| (x - max).exp2()).sum::<f64>().log2()
}

pub fn key_strength(key: &Key, layout: &GridLayout) -> KeyStrength {
    let log2u = PRIMES_IN_RANGE.log2();
    let m = key.m();
    let mut levels = Vec::new();
    for lv in &layout.levels {
        let group = key.group_of_level(lv.level as usize);
        let bits = match key.group(group) {
            GroupKey::Reference => 0.0,
            GroupKey::Prf(_) => 128.0,
            GroupKey::Primes(k) => {
                let per_prime = if lv.dense || !lv.size.is_power_of_two() {
                    log2u
                } else {
                    (lv.size.trailing_zeros() as f64 - 1.0).clamp(0.0, log2u)
                };
                k.iter().zip(PI).filter(|(k, p)| *k != p).count() as f64 * per_prime
            }
        };
        levels.push(LevelStrength {
            level: lv.level,
            resolution: lv.resolution,
            size: lv.size,
            dense: lv.dense,
            group,
            bits,
        });
    }
    let in_group = |j: usize| levels.iter().filter(move |l| l.group == j);
    let is_prf = key.scheme().is_prf();
    let mut group_bits = Vec::with_capacity(m);
    let mut group_oracle = Vec::with_capacity(m);
    for j in 0..m {
        if is_prf {
            let n = in_group(j).filter(|l| l.bits > 0.0).count() as f64;
            group_bits.push((128.0 * n).min(256.0));
            group_oracle.push(if n > 0.0 { 128.0 + n.log2() } else { 0.0 });
        } else {
            // A group's levels share one triple: hashed levels reveal k mod 2^t, dense ones
            // all of k, so the group is worth the most revealing level.
            let full = in_group(j).map(|l| l.bits).fold(0.0, f64::max);
            let hashed = in_group(j)
                .filter(|l| !l.dense)
                .map(|l| l.bits)
                .fold(0.0, f64::max);
            group_bits.push(full);
            // With an oracle: residues first on a hashed level, then the rest on a dense one.
            group_oracle.push(if hashed > 0.0 && full > hashed {
                log2_sum_pow2([hashed, full - hashed])
            } else {
                full
            });
        }
    }
    let sum: f64 = group_bits.iter().sum();
    let total_bits = if is_prf { sum.min(256.0) } else { sum };
    let oracle_bits = log2_sum_pow2(group_oracle.iter().copied());
    let after_disclosure = if is_prf {
        // Key material of key j, and whether the index has any keyed level at all.
        let key_bits: Vec<f64> = match key.scheme() {
            KeyScheme::PrfShares { m, .. } => (0..*m)
                .map(|j| 8.0 * share_range(*m, j).len() as f64)
                .collect(),
            _ => vec![256.0; m],
        };
        let keyed = total_bits > 0.0;
        disclosures(&key_bits, |rest| {
            let brute = if keyed {
                rest.iter().sum::<f64>().min(256.0)
            } else {
                0.0
            };
            (brute, oracle_bits.min(brute))
        })
    } else {
        let bits: Vec<(f64, f64)> = group_bits
            .iter()
            .copied()
            .zip(group_oracle.iter().copied())
            .collect();
        disclosures_by(&bits, |rest| {
            (
                rest.iter().map(|b| b.0).sum(),
                log2_sum_pow2(rest.iter().map(|b| b.1)),
            )
        })
    };
    KeyStrength {
        scheme: key.scheme().name().into(),
        m,
        dense_mode: key.dense().name().into(),
        levels,
        total_bits,
        oracle_bits,
        group_bits,
        paper_claim_bits: (!is_prf).then_some(3.0 * log2u * m as f64),
        after_disclosure,
    }
}

fn disclosures(key_bits: &[f64], left: impl Fn(&[f64]) -> (f64, f64)) -> Vec<Disclosure> {
    let pairs: Vec<(f64, f64)> = key_bits.iter().map(|&b| (b, b)).collect();
    disclosures_by(&pairs, |rest| {
        let b: Vec<f64> = rest.iter().map(|p| p.0).collect();
        left(&b)
    })
}

/// For j = 0 … m − 1: the keys sorted most valuable first (brute-force bits, then oracle
/// bits), the first j disclosed, `left` of the rest.
fn disclosures_by(
    keys: &[(f64, f64)],
    left: impl Fn(&[(f64, f64)]) -> (f64, f64),
) -> Vec<Disclosure> {
    let mut sorted = keys.to_vec();
    sorted.sort_by(|a, b| b.0.total_cmp(&a.0).then(b.1.total_cmp(&a.1)));
    (0..keys.len())
        .map(|j| {
            let (brute_force_bits, oracle_bits) = left(&sorted[j..]);
            Disclosure {
                disclosed: j,
                brute_force_bits,
                oracle_bits,
            }
        })
        .collect()
}
