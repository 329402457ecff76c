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
//!
//! Time, not only bits: [`key_trial_cost`] measures what one brute-force trial costs on
//! this machine (derive a candidate key's index functions, index a fixed set of probe
//! points with them, compare with what the true key gives), and
//! [`brute_force_years_log10`] turns bits and that cost into the expected search time —
//! the paper's brute-force column, from a measurement instead of an assumed frame rate.

use super::keys::{GroupKey, Key, KeyScheme, PI, SchemeKind, generate_with, share_range};
use super::primes::PRIMES_IN_RANGE;
use ngp::encoding::GridLayout;
use ngp::encoding::grid::cell_of;
use ngp::error::Result;
use ngp::rng::Pcg32;
use std::hint::black_box;
use std::time::Instant;

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

/// Probe points per key trial: the fewest with which a candidate can be told apart by
/// running the model. Recognising a hidden scene needs a few rays' colours (a coherent
/// patch against noise): 32 rays × 128 samples, or 64 × 64, is 4096 encoded points, and
/// each encodes on every level (8 corners). Fewer rays cannot tell a scene from noise
/// reliably; an attacker's trial is at least this much index work (and the MLP besides,
/// which is left out: the figure is a lower bound on the attacker's cost per trial).
pub const PROBE_POINTS: usize = 4096;

/// Seconds per Julian year, for [`brute_force_years_log10`].
pub const SECONDS_PER_YEAR: f64 = 365.25 * 86_400.0;

/// What one brute-force key trial costs on this machine, on one core (medians of several
/// warm runs).
#[derive(Clone, Debug, serde::Serialize)]
pub struct KeyTrialCost {
    pub scheme: String,
    pub m: usize,
    pub probes: usize,
    pub levels: usize,
    /// Corner indices computed per trial: probes × levels × 8.
    pub lookups: usize,
    /// One whole trial: derive the candidate's index functions (`Key::level_indices`, the
    /// dense levels' permutation tables included), index every probe's 8 corners on every
    /// level, compare with the true key's indices.
    pub trial_seconds: f64,
    /// The derivation alone.
    pub derive_seconds: f64,
    /// Indexing and comparing alone (index functions already derived): no trial costs
    /// less, so it bounds the attacker's cost from below (one who permutes only the
    /// probes' dense-level corners, lazily, pays between this and `trial_seconds`).
    pub index_seconds: f64,
    /// Timed runs (after one warm-up run), and trials per run.
    pub runs: usize,
    pub trials_per_run: usize,
}

/// Measures [`KeyTrialCost`] for a key of `kind` with `m` groups on
/// `layout`: `probes` points uniform in the unit cube (fixed, seeded), one true key and
/// `trials_per_run` candidate keys drawn from a seeded generator (drawn before timing: an
/// attacker enumerates candidates, e.g. from a prime sieve, for next to nothing), `runs`
/// timed runs after a warm-up, the median per trial reported.
pub fn key_trial_cost(
    kind: SchemeKind,
    m: usize,
    layout: &GridLayout,
    probes: usize,
    runs: usize,
    trials_per_run: usize,
) -> Result<KeyTrialCost> {
    let (runs, trials_per_run, probes) = (runs.max(1), trials_per_run.max(1), probes.max(1));
    let mut rng = Pcg32::new(0x7e57, 9);
    let points: Vec<[f32; 3]> = (0..probes)
        .map(|_| [rng.next_f32(), rng.next_f32(), rng.next_f32()])
        .collect();
    // Level-major: each level's cells of every probe, then its indices (the order an
    // attacker would pick, one index function at a time).
    let cells: Vec<Vec<[u32; 3]>> = layout
        .levels
        .iter()
        .map(|lv| points.iter().map(|&p| cell_of(lv, p).0).collect())
        .collect();
    let mut draw = |stream: u64| {
        let mut r = Pcg32::new(0x6b65_7973, stream);
        generate_with(kind, m, move || {
            Ok((r.next_u32() as u64) << 32 | r.next_u32() as u64)
        })
    };
    let truth = draw(0)?;
    let index_all = |idx: &ngp::encoding::LevelIndices, out: &mut Vec<u32>| {
        out.clear();
        let mut c = [0u32; 8];
        for (l, cl) in cells.iter().enumerate() {
            let f = &idx[l];
            for &cell in cl {
                f.corners(cell, &mut c);
                out.extend_from_slice(&c);
            }
        }
    };
    let mut expected = Vec::new();
    index_all(&truth.level_indices(layout), &mut expected);
    let candidates: Vec<Key> = (1..=trials_per_run as u64)
        .map(&mut draw)
        .collect::<Result<_>>()?;
    let compare = |idx: &ngp::encoding::LevelIndices| -> usize {
        let mut matches = 0usize;
        let mut c = [0u32; 8];
        let mut k = 0;
        for (l, cl) in cells.iter().enumerate() {
            let f = &idx[l];
            for &cell in cl {
                f.corners(black_box(cell), &mut c);
                matches += c
                    .iter()
                    .zip(&expected[k..k + 8])
                    .filter(|(a, b)| a == b)
                    .count();
                k += 8;
            }
        }
        matches
    };
    let derived: Vec<_> = candidates.iter().map(|k| k.level_indices(layout)).collect();
    let median_of = |f: &mut dyn FnMut() -> usize| -> f64 {
        let mut times = Vec::with_capacity(runs);
        for r in 0..=runs {
            let t = Instant::now();
            black_box(f());
            let s = t.elapsed().as_secs_f64() / trials_per_run as f64;
            if r > 0 {
                times.push(s);
            }
        }
        times.sort_by(f64::total_cmp);
        times[times.len() / 2]
    };
    let trial_seconds = median_of(&mut || {
        candidates
            .iter()
            .map(|k| compare(&black_box(k).level_indices(layout)))
            .sum()
    });
    let derive_seconds = median_of(&mut || {
        candidates
            .iter()
            .map(|k| black_box(black_box(k).level_indices(layout)).len())
            .sum()
    });
    let index_seconds = median_of(&mut || derived.iter().map(&compare).sum());
    Ok(KeyTrialCost {
        scheme: truth.scheme().name().into(),
        m,
        probes,
        levels: layout.levels.len(),
        lookups: probes * layout.levels.len() * 8,
        trial_seconds,
        derive_seconds,
        index_seconds,
        runs,
        trials_per_run,
    })
}

/// log10 of the expected years of a brute-force search over `bits` bits at
/// `trial_seconds` per candidate: half the space on average, 2^(bits−1) trials. A log
/// because 2^1379 overflows an f64. `None` for an empty key space.
pub fn brute_force_years_log10(bits: f64, trial_seconds: f64) -> Option<f64> {
    (bits > 0.0 && trial_seconds > 0.0)
        .then(|| (bits - 1.0) * 2f64.log10() + trial_seconds.log10() - SECONDS_PER_YEAR.log10())
}

/// `10^x` written as `7.43e16` (3 significant digits), for any x an f64 can hold.
pub fn format_pow10(x: f64) -> String {
    let mut e = x.floor();
    let mut mant = 10f64.powf(x - e);
    if (mant * 100.0).round() >= 1000.0 {
        mant /= 10.0;
        e += 1.0;
    }
    format!("{mant:.2}e{}", e as i64)
}

#[cfg(test)]
mod trial_tests {
    use super::*;
    use ngp::encoding::GridConfig;

    #[test]
    fn paper_arithmetic_and_formatting() {
        // The paper: U³ ≈ 9.364e25 keys, half searched at 20 FPS, 3.15e7 s a year: 7.43e16.
        let bits = 9.364e25f64.log2();
        let y = brute_force_years_log10(bits, 1.0 / 20.0).unwrap();
        // Our year is 3.156e7 s, the paper's 3.15e7: 7.42e16.
        assert_eq!(format_pow10(y), "7.42e16");
        assert_eq!(format_pow10(0.0), "1.00e0");
        assert_eq!(format_pow10(2.0f64.log10() + 300.0), "2.00e300");
        assert_eq!(format_pow10(0.999_999_9), "1.00e1");
        assert!(brute_force_years_log10(0.0, 1.0).is_none());
        // 1380 bits: far past f64, still a number.
        assert!(brute_force_years_log10(1380.0, 0.01).unwrap() > 400.0);
    }

    #[test]
    fn a_trial_is_measured_for_both_schemes() {
        let g = GridLayout::new(GridConfig::default(), 1).unwrap();
        for kind in [SchemeKind::Prf, SchemeKind::Primes] {
            let c = key_trial_cost(kind, 2, &g, 64, 3, 1).unwrap();
            assert_eq!(c.scheme, kind.name());
            assert_eq!(c.lookups, 64 * 16 * 8);
            assert!(c.trial_seconds > 0.0 && c.derive_seconds > 0.0 && c.index_seconds > 0.0);
            assert!(c.index_seconds < c.trial_seconds, "{c:?}");
        }
    }
}
