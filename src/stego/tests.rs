//! Tests of the key layer as a whole: index functions, key files, key variants, strength.

use super::index::PrimeIndex;
use super::keys::{DenseMode, Key, KeyScheme, Mixed, PI};
use super::permute::{Feistel, domain_bits};
use super::prf;
use super::*;
use crate::ngp::encoding::{GridConfig, GridLayout, LevelIndex, ReferenceIndex};
use std::hash::Hasher;

fn layout() -> GridLayout {
    GridLayout::new(GridConfig::default(), 1).unwrap()
}

const K: [u64; 3] = [10_000_019, 10_000_079, 10_000_103];
/// Key 1 of the paper's multi-key table (entries above 2^32).
const PAPER_K1: [u64; 3] = [10_123_105_283, 9_423_208_789, 10_600_480_711];

fn primes_key(keys: Vec<[u64; 3]>, dense: DenseMode) -> Key {
    Key::new(KeyScheme::Primes { keys }, dense).unwrap()
}

fn prf_key(m: usize, dense: DenseMode) -> Key {
    let mut secret = [0u8; 32];
    for (i, b) in secret.iter_mut().enumerate() {
        *b = (i as u8).wrapping_mul(37).wrapping_add(11);
    }
    Key::new(KeyScheme::Prf { secret, m }, dense).unwrap()
}

fn corner(cell: [u32; 3], c: usize) -> (u32, u32, u32) {
    (
        cell[0] + (c as u32 & 1),
        cell[1] + ((c as u32 >> 1) & 1),
        cell[2] + ((c as u32 >> 2) & 1),
    )
}

fn same_on_level(a: &dyn LevelIndex, b: &dyn LevelIndex, res: u32) -> bool {
    let step = (res / 37).max(1);
    let mut p = 0u32;
    while p <= res {
        for (x, y, z) in [
            (p, 0, 0),
            (0, p, 0),
            (0, 0, p),
            (p, p / 2 + 1, res - p),
            (res, p, 3),
        ] {
            if a.index(x, y, z) != b.index(x, y, z) {
                return false;
            }
        }
        p += step;
    }
    true
}

fn all_keys() -> Vec<Key> {
    let mut v = vec![Key::reference()];
    for d in [DenseMode::Permute, DenseMode::Hash] {
        v.push(primes_key(vec![K, PAPER_K1, PI], d));
        v.push(prf_key(3, d));
    }
    v
}

#[test]
fn primes_index_by_hand() {
    let g = layout();
    let key = primes_key(vec![K], DenseMode::Hash);
    let idx = key.level_indices(&g);
    // 1·10000019 ⊕ 2·10000079 ⊕ 3·10000103 = 10000019 ⊕ 20000158 ⊕ 30000309 = 6324152,
    // 6324152 mod 2^19 = 6324152 − 12·524288 = 32696.
    assert_eq!(idx[5].index(1, 2, 3), 32696);
    assert_eq!(idx[15].index(1, 2, 3), 32696);
    // Dense level 1 (size 12168), hash mode: 50000095 ⊕ 70000553 ⊕ 110001133 = 5805211,
    // 5805211 − 477·12168 = 1075.
    assert_eq!(idx[1].index(5, 7, 11), 1075);
    // Paper key above 2^32, hashed level: only k mod 2^19 = (152579, 180565, 425927)
    // counts; (3·K1 ⊕ 4·K2 ⊕ 5·K3) mod 2^19 = 362430.
    let idx = primes_key(vec![PAPER_K1], DenseMode::Hash).level_indices(&g);
    assert_eq!(idx[9].index(3, 4, 5), 362430);
    let reduced = PrimeIndex::new([152579, 180565, 425927], 1 << 19);
    assert_eq!(reduced.index(3, 4, 5), 362430);
}

fn prf_reference(key: &Key, level: usize, x: u32, y: u32, z: u32) -> u32 {
    let KeyScheme::Prf { secret, .. } = key.scheme() else {
        panic!()
    };
    let lv = layout().levels[level];
    let sk = prf::derive_subkey(secret, prf::PURPOSE_INDEX, lv.level, lv.size);
    let mut h = siphasher::sip::SipHasher24::new_with_keys(sk[0], sk[1]);
    let mut m = Vec::new();
    for v in [x, y, z] {
        m.extend_from_slice(&v.to_le_bytes());
    }
    h.write(&m);
    (h.finish() % lv.size as u64) as u32
}

#[test]
fn prf_index_matches_siphasher_on_hashed_and_dense_levels() {
    let g = layout();
    let key = prf_key(1, DenseMode::Hash);
    let idx = key.level_indices(&g);
    for (l, cell) in [
        (15usize, [1000u32, 17, 2046]),
        (7, [0, 0, 0]),
        (2, [30, 29, 0]),
        (0, [15, 15, 15]),
    ] {
        let mut out = [0u32; 8];
        idx[l].corners(cell, &mut out);
        for (c, &o) in out.iter().enumerate() {
            let (x, y, z) = corner(cell, c);
            assert_eq!(o, prf_reference(&key, l, x, y, z), "level {l} corner {c}");
        }
    }
}

#[test]
fn permute_mode_dense_index_by_construction() {
    let g = layout();
    for key in [
        prf_key(1, DenseMode::Permute),
        primes_key(vec![K], DenseMode::Permute),
    ] {
        let idx = key.level_indices(&g);
        let lv = g.levels[3];
        let sk = match key.scheme() {
            KeyScheme::Prf { secret, .. } => {
                prf::derive_subkey(secret, prf::PURPOSE_DENSE_PERMUTE, 3, lv.size)
            }
            KeyScheme::Primes { keys } => {
                let mut s = [0u8; 32];
                for i in 0..3 {
                    s[8 * i..8 * i + 8].copy_from_slice(&keys[0][i].to_le_bytes());
                }
                prf::derive_subkey(&s, prf::PURPOSE_PRIMES_DENSE_PERMUTE, 3, lv.size)
            }
        };
        let f = Feistel::new(sk, domain_bits(lv.size));
        // d = 5 + 7·43 + 11·43² = 20645; the upper corner (43, 43, 43) wraps mod 79512.
        assert_eq!(idx[3].index(5, 7, 11), f.permute_below(20645, lv.size));
        let d = (43 + 43 * 43 + 43 * 43 * 43) % 79512;
        assert_eq!(idx[3].index(43, 43, 43), f.permute_below(d, lv.size));
        // Hashed levels are unaffected by the dense mode.
        let h = key.clone().with_dense(DenseMode::Hash).level_indices(&g);
        assert!(same_on_level(&*idx[8], &*h[8], g.levels[8].resolution));
        assert!(!same_on_level(&*idx[3], &*h[3], g.levels[3].resolution));
    }
}

#[test]
fn corners_equal_index_for_every_scheme() {
    for g in [
        layout(),
        GridLayout::new(GridConfig::base_json_2023(), 1).unwrap(),
    ] {
        for key in all_keys() {
            let idx = key.level_indices(&g);
            for (l, lv) in g.levels.iter().enumerate() {
                let r = lv.resolution;
                for cell in [
                    [0, 0, 0],
                    [r - 1, r - 1, r - 1],
                    [3, r / 2, 1],
                    [r - 1, 0, r / 3],
                ] {
                    let mut out = [0u32; 8];
                    idx[l].corners(cell, &mut out);
                    for (c, &o) in out.iter().enumerate() {
                        let (x, y, z) = corner(cell, c);
                        assert_eq!(o, idx[l].index(x, y, z), "{key:?} level {l} corner {c}");
                        assert!(o < lv.size);
                    }
                }
            }
        }
    }
}

#[test]
fn reference_key_is_the_reference_index_on_every_level() {
    for g in [
        layout(),
        GridLayout::new(GridConfig::base_json_2023(), 1).unwrap(),
    ] {
        for key in [
            Key::reference(),
            Key::reference().with_dense(DenseMode::Hash),
            primes_key(vec![PI; 4], DenseMode::Permute),
        ] {
            let idx = key.level_indices(&g);
            assert_eq!(idx.len(), g.levels.len());
            for (l, lv) in g.levels.iter().enumerate() {
                let r = ReferenceIndex::new(lv);
                assert!(same_on_level(&*idx[l], &r, lv.resolution), "level {l}");
                let mut a = [0u32; 8];
                let mut b = [0u32; 8];
                let cell = [lv.resolution - 1, 2, lv.resolution / 2];
                idx[l].corners(cell, &mut a);
                r.corners(cell, &mut b);
                assert_eq!(a, b);
            }
        }
    }
}

#[test]
fn permutation_is_a_bijection_on_dense_levels() {
    let g = layout();
    for key in [
        prf_key(1, DenseMode::Permute),
        primes_key(vec![K], DenseMode::Permute),
    ] {
        let idx = key.level_indices(&g);
        for l in [0usize, 1] {
            let lv = g.levels[l];
            let r = lv.resolution;
            let mut hit = vec![0u32; lv.size as usize];
            for z in 0..r {
                for y in 0..r {
                    for x in 0..r {
                        hit[idx[l].index(x, y, z) as usize] += 1;
                    }
                }
            }
            // res³ cells onto size = next_multiple(res³, 8) slots, each at most once.
            assert!(hit.iter().all(|&h| h <= 1), "level {l}: collision");
            assert_eq!(
                hit.iter().filter(|&&h| h == 1).count() as u64,
                (r as u64).pow(3)
            );
            // And it really is keyed: not the identity.
            let moved = (0..r)
                .filter(|&x| idx[l].index(x, 1, 1) != x + r + r * r)
                .count();
            assert!(moved as u32 > r - 3);
        }
    }
}

#[test]
fn dense_hash_vs_permute_occupancy() {
    let g = layout();
    for l in [1usize, 4] {
        let lv = g.levels[l];
        for key in [
            prf_key(1, DenseMode::Hash),
            prf_key(1, DenseMode::Permute),
            primes_key(vec![K], DenseMode::Hash),
        ] {
            let o = diagnostics::slot_occupancy(&*key.level_indices(&g)[l], &lv);
            println!(
                "level {l} {:?}/{:?}: {o:?}",
                key.scheme().name(),
                key.dense()
            );
            match key.dense() {
                DenseMode::Permute => {
                    assert_eq!(o.colliding_cell_fraction, 0.0);
                    assert!(o.unused_slot_fraction < 1e-3);
                }
                DenseMode::Hash => {
                    // res³ ≈ size balls in size bins: e^-1 ≈ 0.368 unused.
                    assert!((o.unused_slot_fraction - 0.368).abs() < 0.03, "{o:?}");
                    assert!(o.colliding_cell_fraction > 0.5, "{o:?}");
                }
            }
        }
        let r = diagnostics::slot_occupancy(&ReferenceIndex::new(&lv), &lv);
        assert_eq!(r.colliding_cell_fraction, 0.0);
    }
}

#[test]
fn prime_key_only_matters_mod_2_pow_19_on_hashed_levels() {
    let g = layout();
    // Keys differing by multiples of 2^19 (need not be prime to show it).
    let k2 = [
        K[0] + 3 * (1 << 19),
        K[1] + 1000 * (1 << 19),
        K[2] + (1u64 << 40),
    ];
    for l in 5..16 {
        let lv = g.levels[l];
        let a = PrimeIndex::new(K, lv.size);
        let b = PrimeIndex::new(k2, lv.size);
        assert!(same_on_level(&a, &b, lv.resolution), "level {l}");
    }
    // On a dense level (hash mode) the full key counts.
    let lv = g.levels[4];
    assert!(!same_on_level(
        &PrimeIndex::new(K, lv.size),
        &PrimeIndex::new(k2, lv.size),
        lv.resolution
    ));
}

#[test]
fn prf_has_no_such_reduction_one_bit_changes_everything() {
    let g = layout();
    let key = prf_key(1, DenseMode::Hash);
    let KeyScheme::Prf { secret, .. } = key.scheme() else {
        panic!()
    };
    for bit in [0usize, 100, 255] {
        let mut s2 = *secret;
        s2[bit / 8] ^= 1 << (bit % 8);
        let other = Key::new(KeyScheme::Prf { secret: s2, m: 1 }, DenseMode::Hash).unwrap();
        let (a, b) = (key.level_indices(&g), other.level_indices(&g));
        let (mut changed, mut bits, mut n) = (0usize, 0u32, 0usize);
        for l in [2usize, 9, 15] {
            for i in 0..2000u32 {
                let (x, y, z) = (i % 13, i / 13 % 17, i / 221);
                let (u, v) = (a[l].index(x, y, z), b[l].index(x, y, z));
                changed += (u != v) as usize;
                if l != 2 {
                    bits += (u ^ v).count_ones();
                }
                n += 1;
            }
        }
        assert!(changed as f64 > 0.99 * n as f64, "bit {bit}: {changed}/{n}");
        let frac = bits as f64 / (4000.0 * 19.0);
        assert!(
            (frac - 0.5).abs() < 0.02,
            "bit {bit}: {frac} of index bits flipped"
        );
    }
}

#[test]
fn key_file_round_trip_and_permissions() {
    let dir = tempfile::tempdir().unwrap();
    let keys = [
        primes_key(
            vec![K, PAPER_K1, [1, 2654435761, 10_000_121]],
            DenseMode::Hash,
        ),
        prf_key(4, DenseMode::Permute),
        prf_key(4, DenseMode::Permute).partial(0.5),
        prf_key(4, DenseMode::Permute).disclose_levels(0.5),
        derive_prf_from_passphrase("correct horse", "model-1", 2).unwrap(),
        Key::reference(),
    ];
    for (i, key) in keys.iter().enumerate() {
        let p = dir.path().join(format!("k{i}.json"));
        save_key(&p, key, false).unwrap();
        let back = load_key(&p).unwrap();
        assert_eq!(&back, key, "key {i}");
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = std::fs::metadata(&p).unwrap().permissions().mode() & 0o777;
            assert_eq!(mode, 0o600);
        }
        // No overwrite without force; with force it replaces.
        let e = save_key(&p, &Key::reference(), false)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains(&format!("k{i}.json")) && e.contains("--force"),
            "{e}"
        );
        assert_eq!(&load_key(&p).unwrap(), key);
        save_key(&p, &Key::reference(), true).unwrap();
        assert!(load_key(&p).unwrap().is_reference());
    }
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), keys.len());
}

#[test]
fn bad_key_files_are_rejected_with_file_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nope.json");
    assert!(
        load_key(&missing)
            .unwrap_err()
            .to_string()
            .contains("nope.json")
    );
    let hex64 = "00".repeat(32);
    let cases: Vec<(&str, String, &str)> = vec![
        ("malformed", "{\"version\": 1,".into(), "malformed JSON"),
        ("noversion", r#"{"scheme":"prf","m":1}"#.into(), "`version`: missing"),
        ("version", format!(r#"{{"version":2,"scheme":"prf","m":1,"secret":"{hex64}"}}"#), "unsupported version 2"),
        ("scheme", r#"{"version":1,"scheme":"aes","m":1}"#.into(), "unknown scheme \"aes\""),
        ("m0", format!(r#"{{"version":1,"scheme":"prf","m":0,"secret":"{hex64}"}}"#), "`m`"),
        ("m33", format!(r#"{{"version":1,"scheme":"prf","m":33,"secret":"{hex64}"}}"#), "`m`"),
        ("nokeys", r#"{"version":1,"scheme":"primes","keys":[]}"#.into(), "`keys`"),
        ("notprime", r#"{"version":1,"scheme":"primes","keys":[[10000019,10000079,10000103],[10000019,10000080,10000103]]}"#.into(), "`keys[1][1]`: 10000080 is not prime"),
        ("pair", r#"{"version":1,"scheme":"primes","keys":[[10000019,10000079]]}"#.into(), "`keys[0]`"),
        ("short", r#"{"version":1,"scheme":"prf","m":1,"secret":"abcd"}"#.into(), "`secret`: expected 64 hex digits"),
        ("nothex", format!(r#"{{"version":1,"scheme":"prf","m":1,"secret":"{}"}}"#, "zz".repeat(32)), "`secret`: not hexadecimal"),
        ("nosecret", r#"{"version":1,"scheme":"prf","m":1}"#.into(), "`secret`: missing"),
        ("dense", format!(r#"{{"version":1,"scheme":"prf","m":1,"dense":"feistel","secret":"{hex64}"}}"#), "`dense`"),
        ("format", format!(r#"{{"format":"x","version":1,"scheme":"prf","m":1,"secret":"{hex64}"}}"#), "`format`"),
        ("groups", format!(r#"{{"version":1,"scheme":"prf","m":2,"reference_groups":[2],"secret":"{hex64}"}}"#), "`reference_groups`"),
    ];
    for (name, text, want) in cases {
        let p = dir.path().join(format!("{name}.json"));
        std::fs::write(&p, text).unwrap();
        let e = load_key(&p).unwrap_err().to_string();
        assert!(e.contains(&format!("{name}.json")), "{name}: {e}");
        assert!(e.contains(want), "{name}: {e}");
    }
    // m out of range for a grid is checked at use time.
    let g = layout();
    assert!(prf_key(16, DenseMode::Permute).validate_for(&g).is_ok());
    let e = prf_key(17, DenseMode::Permute)
        .validate_for(&g)
        .unwrap_err()
        .to_string();
    assert!(e.contains("m = 17") && e.contains("16 levels"), "{e}");
    assert!(
        Key::new(
            KeyScheme::Primes {
                keys: vec![[4, 5, 7]]
            },
            DenseMode::Hash
        )
        .is_err()
    );
}

#[test]
fn generated_keys_are_primes_in_range_and_distinct() {
    fn trial(n: u64) -> bool {
        n >= 2
            && (2..)
                .take_while(|d| d * d <= n)
                .all(|d| !n.is_multiple_of(d))
    }
    let a = generate_primes(4).unwrap();
    let b = generate_primes(4).unwrap();
    let (KeyScheme::Primes { keys: ka }, KeyScheme::Primes { keys: kb }) = (a.scheme(), b.scheme())
    else {
        panic!()
    };
    let all: Vec<u64> = ka.iter().chain(kb).flatten().copied().collect();
    assert_eq!(all.len(), 24);
    for &p in &all {
        assert!((10_000_000..=10_000_000_000).contains(&p), "{p}");
        assert!(trial(p), "{p} not prime");
    }
    let mut d = all.clone();
    d.sort_unstable();
    d.dedup();
    assert_eq!(d.len(), 24, "repeated primes");
    // Uniform over [1e7, 1e10]: most draws are above 1e9.
    assert!(all.iter().filter(|&&p| p > 1_000_000_000).count() >= 12);
    let (p, q) = (generate_prf(2).unwrap(), generate_prf(2).unwrap());
    assert_ne!(p, q);
    assert_eq!(p.m(), 2);
    assert!(generate_primes(0).is_err() && generate_prf(33).is_err());
}

#[test]
fn passphrase_derivation_is_deterministic_and_salted() {
    let a = derive_prf_from_passphrase("tr0ub4dor", "s1", 1).unwrap();
    let b = derive_prf_from_passphrase("tr0ub4dor", "s1", 1).unwrap();
    let c = derive_prf_from_passphrase("tr0ub4dor", "s2", 1).unwrap();
    let d = derive_prf_from_passphrase("tr0ub4dor!", "s1", 1).unwrap();
    assert_eq!(a, b);
    assert_ne!(a.scheme(), c.scheme());
    assert_ne!(a.scheme(), d.scheme());
    assert!(derive_prf_from_passphrase("", "s", 1).is_err());
}

fn prf_key_secret(k: &Key) -> [u8; 32] {
    match k.scheme() {
        KeyScheme::Prf { secret, .. } => *secret,
        KeyScheme::Primes { .. } => panic!("not a prf key"),
    }
}

fn same_key_on_level(a: &Key, b: &Key, l: usize) -> bool {
    let g = layout();
    let (ia, ib) = (a.level_indices(&g), b.level_indices(&g));
    same_on_level(&*ia[l], &*ib[l], g.levels[l].resolution)
}

#[test]
fn partial_keys() {
    let g = layout();
    let primes = primes_key(
        vec![
            K,
            PAPER_K1,
            [10_000_121, 10_000_139, 10_000_141],
            [10_000_169, 10_000_189, 10_000_223],
        ],
        DenseMode::Permute,
    );
    // Per-level disclosure: primes' partial keys, and leaked prf level subkeys.
    type Disclose = fn(&Key, f64) -> Key;
    let disclosures: Vec<(Key, Disclose)> = vec![
        (primes.clone(), Key::partial),
        (primes, Key::disclose_levels),
        (prf_key(4, DenseMode::Permute), Key::disclose_levels),
        (prf_key(4, DenseMode::Hash), Key::disclose_levels),
    ];
    for (key, disclose) in disclosures {
        assert_eq!(disclose(&key, 1.0), key);
        assert!(disclose(&key, 0.0).is_reference());
        for l in 0..16 {
            assert!(
                same_key_on_level(&disclose(&key, 0.0), &Key::reference(), l),
                "level {l}"
            );
        }
        // 50% of m = 4: groups 0, 1 (levels l mod 4 < 2) keep the key.
        let half = disclose(&key, 0.5);
        for l in 0..16 {
            let keyed = same_key_on_level(&half, &key, l);
            let reference = same_key_on_level(&half, &Key::reference(), l);
            assert_eq!(
                (keyed, reference),
                (l % 4 < 2, l % 4 >= 2),
                "{key:?} level {l}"
            );
        }
        // round(0.25·4) = 1, round(0.75·4) = 3.
        let n_ref = |k: &Key| {
            (0..4)
                .filter(|&j| k.group(j) == GroupKey::Reference)
                .count()
        };
        assert_eq!(n_ref(&disclose(&key, 0.25)), 3);
        assert_eq!(n_ref(&disclose(&key, 0.75)), 1);
    }
    // prf partial keys are all-or-nothing: any missing share of the secret changes every
    // level, so no level matches the key (nor Π) until the whole secret is given.
    for key in [prf_key(4, DenseMode::Permute), prf_key(8, DenseMode::Hash)] {
        assert_eq!(key.partial(1.0), key);
        assert!(key.partial(0.0).is_reference());
        for p in [0.25, 0.5, 0.75] {
            let part = key.partial(p);
            assert!(!part.is_reference());
            for l in 0..g.levels.len() {
                assert!(!same_key_on_level(&part, &key, l), "p {p} level {l}");
                assert!(
                    !same_key_on_level(&part, &Key::reference(), l),
                    "p {p} level {l}"
                );
            }
        }
        // Share j of m = 4 is bytes [8j, 8j + 8): 75 % keeps 24 bytes, zeroes the last 8.
        let KeyScheme::Prf { secret: full, .. } = key.scheme() else {
            unreachable!()
        };
        let three_quarters = prf_key_secret(&key.partial(0.75));
        if key.m() == 4 {
            assert_eq!(three_quarters[..24], full[..24]);
            assert_eq!(three_quarters[24..], [0u8; 8]);
        }
    }
}

#[test]
fn mixed_and_wrong_keys() {
    let key = primes_key(vec![K, PAPER_K1], DenseMode::Permute);
    let KeyScheme::Primes { keys } = key.mixed(Mixed::Pi1K2K3).scheme().clone() else {
        panic!()
    };
    assert_eq!(keys, vec![[1, K[1], K[2]], [1, PAPER_K1[1], PAPER_K1[2]]]);
    let KeyScheme::Primes { keys } = key.mixed(Mixed::Pi1Pi2K3).scheme().clone() else {
        panic!()
    };
    assert_eq!(keys[0], [1, 2654435761, K[2]]);
    for l in [0usize, 3, 6, 15] {
        assert!(!same_key_on_level(&key, &key.mixed(Mixed::Pi1K2K3), l));
    }
    let p = prf_key(2, DenseMode::Permute);
    let KeyScheme::Prf { secret, .. } = p.mixed(Mixed::Pi1Pi2K3).scheme().clone() else {
        panic!()
    };
    assert!(
        secret[..21].iter().all(|&b| b == 0)
            && secret[21..] == prf_key(2, DenseMode::Permute).scheme_secret()[21..]
    );
    for like in [key, p] {
        let w = Key::wrong(7, &like);
        assert_eq!(
            (w.m(), w.scheme().name(), w.dense()),
            (like.m(), like.scheme().name(), like.dense())
        );
        assert_eq!(w, Key::wrong(7, &like));
        assert_ne!(w, Key::wrong(8, &like));
        assert_ne!(w, like);
        for l in [0usize, 3, 6, 15] {
            assert!(!same_key_on_level(&w, &like, l));
        }
    }
}

impl Key {
    fn scheme_secret(&self) -> [u8; 32] {
        match self.scheme() {
            KeyScheme::Prf { secret, .. } => *secret,
            _ => [0; 32],
        }
    }
}

#[test]
fn debug_prints_no_secret() {
    let p = prf_key(2, DenseMode::Permute);
    let s = format!("{p:?} {:?} {:#?}", p.scheme(), p);
    let hex: String = p
        .scheme_secret()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    for w in 0..hex.len() - 6 {
        assert!(!s.contains(&hex[w..w + 6]), "{s}");
    }
    assert!(s.contains("Prf") && s.contains("redacted"));
    let k = primes_key(vec![K, PAPER_K1], DenseMode::Hash);
    let s = format!("{k:?} {:?} {:#?}", k.scheme(), k);
    for v in K.iter().chain(&PAPER_K1) {
        assert!(!s.contains(&v.to_string()[..6]), "{s}");
    }
    let g = generate_prf(1).unwrap();
    let s = format!("{g:?}");
    assert!(!s.contains(&format!(
        "{:02x}{:02x}{:02x}",
        g.scheme_secret()[0],
        g.scheme_secret()[1],
        g.scheme_secret()[2]
    )));
}

#[test]
fn key_strength_numbers() {
    let g = layout();
    let s = key_strength(&primes_key(vec![K], DenseMode::Permute), &g);
    let log2u = 454_387_932f64.log2();
    assert!(s.levels[5..].iter().all(|l| l.bits == 54.0));
    assert!(
        s.levels[..5]
            .iter()
            .all(|l| (l.bits - 3.0 * log2u).abs() < 1e-9)
    );
    assert!(
        (s.total_bits - 3.0 * log2u).abs() < 1e-9 && (s.total_bits - 86.28).abs() < 0.01,
        "{}",
        s.total_bits
    );
    // Residues on a hashed level first (2^54), then the other 32.3 bits on a dense level.
    assert!((s.oracle_bits - 54.0).abs() < 0.01, "{}", s.oracle_bits);
    assert!((s.paper_claim_bits.unwrap() - 86.28).abs() < 0.01);
    // m = 16: groups 0-4 are dense-only, 5-15 hashed-only.
    let k16 = generate_primes(16).unwrap();
    let s = key_strength(&k16, &g);
    assert!((s.total_bits - (5.0 * 3.0 * log2u + 11.0 * 54.0)).abs() < 1e-6);
    assert!(
        (s.oracle_bits - (3.0 * log2u + (5.0f64).log2())).abs() < 0.01,
        "{}",
        s.oracle_bits
    );
    assert!((s.paper_claim_bits.unwrap() - 1380.45).abs() < 0.01);
    // Mixed {π1, π2, k3}: 18 bits on hashed levels.
    let s = key_strength(
        &primes_key(vec![K], DenseMode::Hash).mixed(Mixed::Pi1Pi2K3),
        &g,
    );
    assert_eq!(s.levels[10].bits, 18.0);
    let s = key_strength(&prf_key(4, DenseMode::Permute), &g);
    assert_eq!(s.total_bits, 256.0);
    assert!((s.oracle_bits - 132.0).abs() < 1e-9);
    assert_eq!(key_strength(&Key::reference(), &g).total_bits, 0.0);
    let s = key_strength(&prf_key(4, DenseMode::Permute).disclose_levels(0.5), &g);
    assert_eq!(s.levels.iter().filter(|l| l.bits == 0.0).count(), 8);
    println!("{}", serde_json::to_string(&s).unwrap());
}
