//! Tests of the key layer as a whole: index functions, key files, key variants, strength.

use super::keys::{Argon2Cost, DenseMode, Key, KeyScheme, Mixed, PI};
use super::permute::{Feistel, domain_bits};
use super::prf;
use super::*;
use ngp::encoding::{GridConfig, GridLayout, IndexFn, LevelIndex};
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

fn test_secret(j: usize) -> [u8; 32] {
    std::array::from_fn(|i| {
        (i as u8)
            .wrapping_mul(37)
            .wrapping_add(11)
            .wrapping_add((j as u8).wrapping_mul(101))
    })
}

/// A version-2 `prf` key: m independent secrets.
fn prf_key(m: usize, dense: DenseMode) -> Key {
    let secrets = (0..m).map(test_secret).collect();
    Key::new(KeyScheme::Prf { secrets }, dense).unwrap()
}

/// A version-1 `prf` key: one secret in m shares.
fn legacy_prf_key(m: usize, dense: DenseMode) -> Key {
    Key::new(
        KeyScheme::PrfShares {
            secret: test_secret(0),
            m,
        },
        dense,
    )
    .unwrap()
}

/// The 256-bit master every level's subkey of a `prf` key is derived from.
fn master(key: &Key) -> [u8; 32] {
    match key.group(0) {
        GroupKey::Prf(m) => m,
        other => panic!("not a keyed prf group: {}", other == GroupKey::Reference),
    }
}

/// A cheap Argon2id cost for unit tests only (keygen uses `Argon2Cost::DEFAULT`).
const CHEAP: Argon2Cost = Argon2Cost {
    m_cost_kib: 256,
    t_cost: 1,
    p_cost: 1,
};

fn corner(cell: [u32; 3], c: usize) -> (u32, u32, u32) {
    (
        cell[0] + (c as u32 & 1),
        cell[1] + ((c as u32 >> 1) & 1),
        cell[2] + ((c as u32 >> 2) & 1),
    )
}

fn same_on_level(a: &LevelIndex, b: &LevelIndex, res: u32) -> bool {
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
    let reduced = LevelIndex::new(&g.levels[9], IndexFn::Primes([152579, 180565, 425927]));
    assert_eq!(reduced.index(3, 4, 5), 362430);
}

fn prf_reference(key: &Key, level: usize, x: u32, y: u32, z: u32) -> u32 {
    let lv = layout().levels[level];
    let sk = prf::derive_subkey(&master(key), prf::PURPOSE_INDEX, lv.level, lv.size);
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
    // Version 2: the master is the documented chain over the secrets; version 1: the secret.
    assert_eq!(master(&key), prf::combine_secrets(&[test_secret(0)]));
    assert_eq!(master(&legacy_prf_key(3, DenseMode::Hash)), test_secret(0));
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
            KeyScheme::Prf { .. } | KeyScheme::PrfShares { .. } => {
                prf::derive_subkey(&master(&key), prf::PURPOSE_DENSE_PERMUTE, 3, lv.size)
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
        assert!(same_on_level(&idx[8], &h[8], g.levels[8].resolution));
        assert!(!same_on_level(&idx[3], &h[3], g.levels[3].resolution));
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
                let r = LevelIndex::reference(lv);
                assert!(same_on_level(&idx[l], &r, lv.resolution), "level {l}");
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
            let o = diagnostics::slot_occupancy(&key.level_indices(&g)[l], &lv);
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
        let r = diagnostics::slot_occupancy(&LevelIndex::reference(&lv), &lv);
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
        let a = LevelIndex::new(&lv, IndexFn::Primes(K));
        let b = LevelIndex::new(&lv, IndexFn::Primes(k2));
        assert!(same_on_level(&a, &b, lv.resolution), "level {l}");
    }
    // On a dense level (hash mode) the full key counts.
    let lv = g.levels[4];
    assert!(!same_on_level(
        &LevelIndex::new(&lv, IndexFn::Primes(K)),
        &LevelIndex::new(&lv, IndexFn::Primes(k2)),
        lv.resolution
    ));
}

#[test]
fn prf_has_no_such_reduction_one_bit_changes_everything() {
    let g = layout();
    let key = prf_key(1, DenseMode::Hash);
    for bit in [0usize, 100, 255] {
        let mut s2 = test_secret(0);
        s2[bit / 8] ^= 1 << (bit % 8);
        let other = Key::new(KeyScheme::Prf { secrets: vec![s2] }, DenseMode::Hash).unwrap();
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
    // (The paper's own key 1 is above 1e10, outside its stated range: key files refuse it,
    // see `primes_key_files_are_checked_on_load_and_save`.)
    let keys = [
        primes_key(
            vec![
                K,
                [10_000_121, 10_000_139, 10_000_141],
                [1, 2654435761, 10_000_121],
            ],
            DenseMode::Hash,
        ),
        prf_key(4, DenseMode::Permute),
        prf_key(4, DenseMode::Permute).partial(0.5),
        prf_key(4, DenseMode::Permute).disclose_levels(0.5),
        derive_prf_from_passphrase_with("correct horse", "model-1", 2, CHEAP).unwrap(),
        Key::reference(),
        legacy_prf_key(4, DenseMode::Hash),
        prf_key(4, DenseMode::Permute)
            .with_scene_box(Some(4))
            .unwrap(),
        legacy_prf_key(2, DenseMode::Hash)
            .with_scene_box(Some(1))
            .unwrap(),
    ];
    for (i, key) in keys.iter().enumerate() {
        let p = dir.path().join(format!("k{i}.json"));
        save_key(&p, key, false).unwrap();
        let loaded = load_key_with_warnings(&p).unwrap();
        assert_eq!(&loaded.key, key, "key {i}");
        // Only a version-1 prf key is written (back) as version 1.
        assert_eq!(loaded.legacy_layout, key.is_legacy_layout(), "key {i}");
        assert_eq!(loaded.version, if key.is_legacy_layout() { 1 } else { 2 });
        assert!(
            loaded.warnings.iter().all(|w| !w.contains("chmod")),
            "key {i}: {:?}",
            loaded.warnings
        );
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
        ("version", format!(r#"{{"version":3,"scheme":"prf","m":1,"secrets":["{hex64}"]}}"#), "unsupported version 3"),
        ("scheme", r#"{"version":1,"scheme":"aes","m":1}"#.into(), "unknown scheme \"aes\""),
        ("m0", format!(r#"{{"version":1,"scheme":"prf","m":0,"secret":"{hex64}"}}"#), "`m`"),
        ("m33", format!(r#"{{"version":1,"scheme":"prf","m":33,"secret":"{hex64}"}}"#), "`m`"),
        ("nokeys", r#"{"version":1,"scheme":"primes","keys":[]}"#.into(), "`keys`"),
        ("notprime", r#"{"version":1,"scheme":"primes","keys":[[10000019,10000079,10000103],[10000019,10000080,10000103]]}"#.into(), "`keys[1][1]`: key 1: 10000080 is not prime"),
        ("v2nosecrets", format!(r#"{{"version":2,"scheme":"prf","m":1,"secret":"{hex64}"}}"#), "`secrets`: missing"),
        ("v2mcount", format!(r#"{{"version":2,"scheme":"prf","m":2,"secrets":["{hex64}"]}}"#), "`m`: m = 2 but the file has 1 secrets"),
        ("v2short", format!(r#"{{"version":2,"scheme":"prf","secrets":["{hex64}","abcd"]}}"#), "`secrets[1]`: expected 64 hex digits"),
        ("v2empty", r#"{"version":2,"scheme":"prf","secrets":[]}"#.into(), "`secrets`: m = 0"),
        ("pair", r#"{"version":1,"scheme":"primes","keys":[[10000019,10000079]]}"#.into(), "`keys[0]`"),
        ("short", r#"{"version":1,"scheme":"prf","m":1,"secret":"abcd"}"#.into(), "`secret`: expected 64 hex digits"),
        ("nothex", format!(r#"{{"version":1,"scheme":"prf","m":1,"secret":"{}"}}"#, "zz".repeat(32)), "`secret`: not hexadecimal"),
        ("nosecret", r#"{"version":1,"scheme":"prf","m":1}"#.into(), "`secret`: missing"),
        ("dense", format!(r#"{{"version":1,"scheme":"prf","m":1,"dense":"feistel","secret":"{hex64}"}}"#), "`dense`"),
        ("format", format!(r#"{{"format":"x","version":1,"scheme":"prf","m":1,"secret":"{hex64}"}}"#), "`format`"),
        ("groups", format!(r#"{{"version":1,"scheme":"prf","m":2,"reference_groups":[2],"secret":"{hex64}"}}"#), "`reference_groups`"),
        ("box3", format!(r#"{{"version":2,"scheme":"prf","secrets":["{hex64}"],"aabb_scale":3}}"#), "`aabb_scale`: expected a power of two between 1 and 128, got 3"),
        ("box256", format!(r#"{{"version":2,"scheme":"prf","secrets":["{hex64}"],"aabb_scale":256}}"#), "`aabb_scale`"),
        ("boxstr", format!(r#"{{"version":2,"scheme":"prf","secrets":["{hex64}"],"aabb_scale":"1"}}"#), "`aabb_scale`"),
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
    let d = |pass: &str, salt: &str, m: usize| {
        derive_prf_from_passphrase_with(pass, salt, m, CHEAP).unwrap()
    };
    let a = d("tr0ub4dor", "s1", 4);
    assert_eq!(a, d("tr0ub4dor", "s1", 4));
    assert_ne!(a.scheme(), d("tr0ub4dor", "s2", 4).scheme());
    assert_ne!(a.scheme(), d("tr0ub4dor!", "s1", 4).scheme());
    // m secrets, each with its own index: distinct, and m is part of the derivation.
    let s = prf_secrets(&a);
    assert_eq!(s.len(), 4);
    for i in 0..4 {
        for j in i + 1..4 {
            assert_ne!(s[i], s[j]);
        }
    }
    assert_ne!(prf_secrets(&d("tr0ub4dor", "s1", 3))[..], s[..3]);
    let kdf = a.kdf().unwrap();
    assert_eq!(
        (kdf.algorithm.as_str(), kdf.version, kdf.salt.as_str()),
        ("argon2id", 19, "s1")
    );
    assert_eq!(kdf.cost(), CHEAP);
    assert!(derive_prf_from_passphrase_with("", "s", 1, CHEAP).is_err());
    assert!(derive_prf_from_passphrase_with("tr0ub4dor", "", 1, CHEAP).is_err());
    // keygen's cost meets OWASP's Argon2id minimum; the test cost does not.
    assert!(Argon2Cost::DEFAULT.meets_owasp() && !CHEAP.meets_owasp());
    for (m, t, ok) in [
        (19_456, 2, true),
        (19_455, 2, false),
        (19_456, 1, false),
        (47_104, 1, true),
    ] {
        let c = Argon2Cost {
            m_cost_kib: m,
            t_cost: t,
            p_cost: 1,
        };
        assert_eq!(c.meets_owasp(), ok, "{c:?}");
    }
    // Random salts: 128 bits, hex, fresh each time.
    let (s1, s2) = (random_salt().unwrap(), random_salt().unwrap());
    assert!(s1.len() == 32 && s1.bytes().all(|b| b.is_ascii_hexdigit()) && s1 != s2);
}

fn prf_secrets(k: &Key) -> Vec<[u8; 32]> {
    match k.scheme() {
        KeyScheme::Prf { secrets } => secrets.clone(),
        KeyScheme::PrfShares { secret, .. } => vec![*secret],
        KeyScheme::Primes { .. } => panic!("not a prf key"),
    }
}

fn same_key_on_level(a: &Key, b: &Key, l: usize) -> bool {
    let g = layout();
    let (ia, ib) = (a.level_indices(&g), b.level_indices(&g));
    same_on_level(&ia[l], &ib[l], g.levels[l].resolution)
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
    // prf partial keys are all-or-nothing: any missing secret (or, version 1, share)
    // changes every level, so no level matches the key (nor Π) until all are given.
    for key in [
        prf_key(4, DenseMode::Permute),
        prf_key(8, DenseMode::Hash),
        legacy_prf_key(4, DenseMode::Hash),
    ] {
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
        let (full, three_quarters) = (prf_secrets(&key), prf_secrets(&key.partial(0.75)));
        if key.is_legacy_layout() {
            // Version 1: share j of m = 4 is bytes [8j, 8j + 8): 75 % zeroes the last 8.
            assert_eq!(three_quarters[0][..24], full[0][..24]);
            assert_eq!(three_quarters[0][24..], [0u8; 8]);
        } else {
            // Version 2: the first round(0.75·m) secrets kept, the others replaced.
            let keep = (0.75 * key.m() as f64).round() as usize;
            assert_eq!(three_quarters[..keep], full[..keep]);
            assert!(three_quarters[keep..].iter().all(|s| *s == [0; 32]));
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
    for (mixed, full) in prf_secrets(&p.mixed(Mixed::Pi1Pi2K3))
        .iter()
        .zip(prf_secrets(&p))
    {
        assert!(mixed[..21].iter().all(|&b| b == 0) && mixed[21..] == full[21..]);
    }
    for l in [0usize, 3, 6, 15] {
        assert!(!same_key_on_level(&p, &p.mixed(Mixed::Pi1K2K3), l));
    }
    for like in [key, p, legacy_prf_key(2, DenseMode::Hash)] {
        let w = Key::wrong(7, &like);
        assert_eq!(
            (w.m(), w.scheme().name(), w.dense(), w.is_legacy_layout()),
            (
                like.m(),
                like.scheme().name(),
                like.dense(),
                like.is_legacy_layout()
            )
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
            KeyScheme::Prf { secrets } => secrets[0],
            KeyScheme::PrfShares { secret, .. } => *secret,
            _ => [0; 32],
        }
    }
}

#[test]
fn debug_prints_no_secret() {
    for p in [
        prf_key(2, DenseMode::Permute),
        legacy_prf_key(2, DenseMode::Permute),
    ] {
        let s = format!("{p:?} {:?} {:#?}", p.scheme(), p);
        for secret in prf_secrets(&p).iter().chain([&master(&p)]) {
            let hex: String = secret.iter().map(|b| format!("{b:02x}")).collect();
            for w in 0..hex.len() - 6 {
                assert!(!s.contains(&hex[w..w + 6]), "{s}");
            }
        }
        assert!(s.contains("Prf") && s.contains("redacted"));
    }
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

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() < 1e-6
}

#[test]
fn strength_after_disclosure_by_hand() {
    let g = layout();
    let log2u = 454_387_932f64.log2();
    let triple = 3.0 * log2u; // 86.28: a dense level sees all of every prime
    // With the oracle a group costs 2^54 (residues mod 2^19 on a hashed level: 3 × 18 bits,
    // primes odd) + 2^32.28 (the rest of the primes on a dense level): log2 ≈ 54.
    let group_oracle = (54f64.exp2() + (triple - 54.0).exp2()).log2();
    for m in [1usize, 4, 8, 16] {
        let s = key_strength(&generate_primes(m).unwrap(), &g);
        assert_eq!(s.after_disclosure.len(), m);
        assert!(
            s.after_disclosure
                .iter()
                .enumerate()
                .all(|(j, d)| d.disclosed == j)
        );
        assert!(close(s.after_disclosure[0].brute_force_bits, s.total_bits));
        assert!(close(s.after_disclosure[0].oracle_bits, s.oracle_bits));
        // Levels 0-4 are dense: group j has a dense level iff j < 5 (or m ≤ 5).
        let dense_groups = m.min(5);
        let last = &s.after_disclosure[m - 1];
        // The worst case leaves a hashed-only group once there are more than 5 groups.
        let (want_brute, want_oracle) = if m > 5 {
            (54.0, 54.0)
        } else {
            (triple, group_oracle)
        };
        assert!(close(last.brute_force_bits, want_brute), "m {m}: {last:?}");
        assert!(close(last.oracle_bits, want_oracle), "m {m}: {last:?}");
        // Brute force: the product (sum of bits) of what is left; oracle: the sum of 2^bits.
        if m == 16 {
            let d = &s.after_disclosure[3];
            assert!(
                close(d.brute_force_bits, 2.0 * triple + 11.0 * 54.0),
                "{d:?}"
            );
            let want = (2.0 * triple.exp2() + 11.0 * 54f64.exp2()).log2();
            assert!(close(d.oracle_bits, want), "{d:?}");
            let d = &s.after_disclosure[dense_groups];
            assert!(close(d.brute_force_bits, 11.0 * 54.0));
            assert!(close(d.oracle_bits, 54.0 + 11f64.log2()));
        }
    }
    // primes m = 4 with 3 disclosed: one triple, 86.28 bits, or 2^54 + 2^32.28 with an oracle.
    let s = key_strength(&generate_primes(4).unwrap(), &g);
    let d = &s.after_disclosure[3];
    assert!((d.brute_force_bits - 86.28).abs() < 0.01 && (d.oracle_bits - 54.0).abs() < 1e-6);
    // prf (version 2): 256 bits whatever the number disclosed (< m); per-level 128 + log2 16.
    for m in [1usize, 4, 8, 16] {
        let s = key_strength(&prf_key(m, DenseMode::Permute), &g);
        for d in &s.after_disclosure {
            assert_eq!(
                (d.brute_force_bits, d.oracle_bits),
                (256.0, 132.0),
                "m {m}: {d:?}"
            );
        }
    }
    // prf version 1: the undisclosed shares' bits — 16 for m = 16 with 15 disclosed.
    let s = key_strength(&legacy_prf_key(16, DenseMode::Permute), &g);
    let bits: Vec<f64> = s
        .after_disclosure
        .iter()
        .map(|d| d.brute_force_bits)
        .collect();
    assert_eq!(bits[0], 256.0);
    assert_eq!(bits[15], 16.0);
    assert_eq!(bits[8], 128.0);
    assert_eq!(s.after_disclosure[15].oracle_bits, 16.0);
    assert_eq!(s.after_disclosure[4].oracle_bits, 132.0);
    // m = 3 shares are 10, 11, 11 bytes: the attacker learns the two 11-byte ones.
    let s = key_strength(&legacy_prf_key(3, DenseMode::Permute), &g);
    assert_eq!(s.after_disclosure[2].brute_force_bits, 80.0);
    assert_eq!(
        key_strength(&Key::reference(), &g).after_disclosure[0].brute_force_bits,
        0.0
    );
}

/// Index outputs of a level over a lattice of points.
fn level_table(key: &Key, l: usize) -> Vec<u32> {
    let g = layout();
    let idx = &key.level_indices(&g)[l];
    let r = g.levels[l].resolution;
    let step = (r / 7).max(1);
    let mut out = Vec::new();
    for z in (0..=r).step_by(step as usize) {
        for y in (0..=r).step_by(step as usize) {
            for x in (0..=r).step_by(step as usize) {
                out.push(idx.index(x, y, z));
            }
        }
    }
    out
}

#[test]
fn any_m_minus_1_disclosed_secrets_leave_every_level_changed() {
    let g = layout();
    for (m, dense) in [
        (4usize, DenseMode::Permute),
        (16, DenseMode::Hash),
        (1, DenseMode::Permute),
    ] {
        let key = prf_key(m, dense);
        let truth: Vec<Vec<u32>> = (0..g.levels.len()).map(|l| level_table(&key, l)).collect();
        // The attacker holds every secret but one (each choice of the missing one) and
        // guesses it: a wrong guess, zeros or a one-bit-off value, changes every level.
        for missing in 0..m {
            let secrets = prf_secrets(&key);
            let mut guesses = vec![[0u8; 32], [0xff; 32]];
            let mut near = secrets[missing];
            near[missing % 32] ^= 0x80;
            guesses.push(near);
            for guess in guesses {
                let mut s = secrets.clone();
                s[missing] = guess;
                let attempt = Key::new(KeyScheme::Prf { secrets: s }, dense).unwrap();
                for (l, want) in truth.iter().enumerate() {
                    let got = level_table(&attempt, l);
                    let same = got.iter().zip(want).filter(|(a, b)| a == b).count();
                    // Unrelated tables agree on about n/size points: far below a tenth.
                    assert!(
                        same * 10 < want.len(),
                        "m {m}, secret {missing} wrong, level {l}: {same}/{} equal",
                        want.len()
                    );
                }
            }
        }
    }
}

/// A key file exactly as the previous build (format version 1, `serde_json` pretty) wrote
/// it: a passphrase key, m = 4, whose secret is `test_secret(0)`.
const V1_PRF_FIXTURE: &str = r#"{
  "format": "stegongp-key",
  "version": 1,
  "scheme": "prf",
  "dense": "permute",
  "m": 4,
  "secret": "0b30557a9fc4e90e33587da2c7ec11365b80a5caef14395e83a8cdf2173c6186",
  "kdf": {
    "algorithm": "argon2id",
    "salt": "demo",
    "m_cost_kib": 65536,
    "t_cost": 3,
    "p_cost": 1
  }
}
"#;

#[test]
fn version_1_files_load_flagged_and_index_as_before() {
    let secret_hex: String = test_secret(0).iter().map(|b| format!("{b:02x}")).collect();
    let text = V1_PRF_FIXTURE;
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("old.json");
    std::fs::write(&p, text).unwrap();
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o600)).unwrap();
    let loaded = load_key_with_warnings(&p).unwrap();
    assert!(loaded.legacy_layout && loaded.key.is_legacy_layout());
    assert_eq!(loaded.version, 1);
    assert_eq!(loaded.warnings.len(), 1, "{:?}", loaded.warnings);
    assert!(
        loaded.warnings[0].contains("version-1") && loaded.warnings[0].contains("64 bits"),
        "{:?}",
        loaded.warnings
    );
    assert_eq!(
        loaded.key,
        legacy_prf_key(4, DenseMode::Permute).with_kdf(loaded.key.kdf().cloned())
    );
    assert_eq!(loaded.key.kdf().unwrap().salt, "demo");
    // Its index functions are the version-1 ones: the KDF straight from the one secret.
    let g = layout();
    let idx = loaded.key.level_indices(&g);
    let s = test_secret(0);
    for l in [6usize, 15] {
        let lv = g.levels[l];
        let sk = prf::derive_subkey(&s, prf::PURPOSE_INDEX, lv.level, lv.size);
        let want =
            (prf::siphash24(sk, &[1, 0, 0, 0, 2, 0, 0, 0, 3, 0, 0, 0]) % lv.size as u64) as u32;
        assert_eq!(idx[l].index(1, 2, 3), want);
    }
    // It is written back as version 1 (the only layout that keeps those functions).
    let back = dir.path().join("back.json");
    save_key(&back, &loaded.key, false).unwrap();
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&back).unwrap()).unwrap();
    assert_eq!(
        (v["version"].as_u64(), v["secret"].as_str()),
        (Some(1), Some(&secret_hex[..]))
    );
    assert!(v["kdf"].get("version").is_none(), "{v}");
    // m = 1 version-1 keys are flagged as old but not as weaker.
    let one = text.replace("\"m\": 4", "\"m\": 1");
    let l1 = keyfile::parse_key_with_warnings(&p, &one).unwrap();
    assert!(
        l1.legacy_layout && l1.warnings[0].contains("as strong"),
        "{:?}",
        l1.warnings
    );
    // A version-2 file of the same scheme is not flagged.
    let v2 = keyfile::key_to_json(&prf_key(4, DenseMode::Permute)).to_string();
    let l2 = keyfile::parse_key_with_warnings(&p, &v2).unwrap();
    assert!(!l2.legacy_layout && l2.version == 2 && l2.warnings.is_empty());
}

#[test]
fn primes_key_files_are_checked_on_load_and_save() {
    let dir = tempfile::tempdir().unwrap();
    let good = "10000019,10000079,10000103";
    let cases = [
        (
            "low",
            "[9999991,10000079,10000103]",
            "keys[0][0]",
            "9999991 is outside",
        ),
        (
            "high",
            "[10000019,10000079,10000103],[10000019,10000000019,10000103]",
            "keys[1][1]",
            "10000000019 is outside",
        ),
        (
            "paper",
            "[10123105283,9423208789,10600480711]",
            "keys[0][0]",
            "10123105283 is outside",
        ),
        (
            "composite",
            "[10000019,10000079,10000101]",
            "keys[0][2]",
            "10000101 is not prime",
        ),
        (
            "carmichael",
            "[10024561,10000079,10000103]",
            "keys[0][0]",
            "10024561 is not prime",
        ),
        (
            "repeat",
            "[10000019,10000079,10000019]",
            "keys[0][2]",
            "10000019 is repeated",
        ),
        (
            "repeat2",
            "[10000019,10000079,10000103],[10000019,10000019,10000103]",
            "keys[1][1]",
            "10000019 is repeated",
        ),
        (
            "zero",
            "[0,10000079,10000103]",
            "keys[0][0]",
            "0 is outside",
        ),
    ];
    for (name, keys, field, want) in cases {
        let p = dir.path().join(format!("{name}.json"));
        std::fs::write(
            &p,
            format!(r#"{{"version":2,"scheme":"primes","keys":[{keys}]}}"#),
        )
        .unwrap();
        let e = load_key(&p).unwrap_err().to_string();
        let key_no = &field[5..6];
        assert!(
            e.contains(&format!("{name}.json"))
                && e.contains(field)
                && e.contains(want)
                && e.contains(&format!("key {key_no}")),
            "{name}: {e}"
        );
    }
    // 10024561 = 97 · 103 · 1003 is composite (a Carmichael-like product, not a prime).
    assert!(!super::primes::is_prime(10_024_561));
    // The same checks guard writing: a key that could not be loaded is not written.
    let p = dir.path().join("paper.key");
    let e = save_key(&p, &primes_key(vec![PAPER_K1], DenseMode::Hash), false)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("10123105283") && e.contains("not written"),
        "{e}"
    );
    assert!(!p.exists());
    // Π's own entries are accepted (reference, partial and mixed diagnostic keys), the
    // mixed ones with a warning.
    let p = dir.path().join("ok.json");
    std::fs::write(&p, format!(r#"{{"version":2,"scheme":"primes","keys":[[{good}],[1,2654435761,805459861],[1,10000079,10000103]]}}"#)).unwrap();
    let l = load_key_with_warnings(&p).unwrap();
    let w: Vec<&String> = l.warnings.iter().filter(|w| !w.contains("chmod")).collect();
    assert!(
        w.len() == 1 && w[0].contains("key 2") && w[0].contains("[0]"),
        "{w:?}"
    );
}

#[test]
fn key_files_are_never_written_through_links() {
    use std::os::unix::fs::{PermissionsExt, symlink};
    let dir = tempfile::tempdir().unwrap();
    let target = dir.path().join("precious.txt");
    std::fs::write(&target, "precious").unwrap();
    let key = prf_key(2, DenseMode::Permute);
    let text = serde_json::to_string(&keyfile::key_to_json(&key)).unwrap();
    let out = dir.path().join("k.json");

    // A symlink at the temporary path: skipped (O_EXCL), never opened; a fresh name is used.
    let planted = dir.path().join(".k.json.0000000000000001.tmp");
    symlink(&target, &planted).unwrap();
    let mut names = ["0000000000000001", "00000000000000aa"].into_iter();
    let mut next = || Ok(names.next().unwrap_or("00000000000000bb").to_string());
    keyfile::write_private(&out, text.as_bytes(), false, &mut next).unwrap();
    assert_eq!(std::fs::read_to_string(&target).unwrap(), "precious");
    assert!(
        std::fs::symlink_metadata(&planted)
            .unwrap()
            .file_type()
            .is_symlink()
    );
    assert_eq!(load_key(&out).unwrap(), key);
    let mode = std::fs::metadata(&out).unwrap().permissions().mode() & 0o777;
    assert_eq!(mode, 0o600);
    // Every name taken by a link: an error, still nothing written through.
    let out2 = dir.path().join("k2.json");
    let planted2 = dir.path().join(".k2.json.0000000000000001.tmp");
    symlink(&target, &planted2).unwrap();
    let mut same = || Ok("0000000000000001".to_string());
    assert!(keyfile::write_private(&out2, text.as_bytes(), false, &mut same).is_err());
    assert!(!out2.exists());
    assert_eq!(std::fs::read_to_string(&target).unwrap(), "precious");

    // A symlink (live or dangling) at the output path: refused without force; with force
    // the link itself is replaced by a new 0600 file and its target keeps its content.
    let link = dir.path().join("link.json");
    symlink(&target, &link).unwrap();
    let e = save_key(&link, &key, false).unwrap_err().to_string();
    assert!(e.contains("--force"), "{e}");
    assert_eq!(std::fs::read_to_string(&target).unwrap(), "precious");
    save_key(&link, &key, true).unwrap();
    assert!(
        std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_file()
    );
    assert_eq!(std::fs::read_to_string(&target).unwrap(), "precious");
    assert_eq!(load_key(&link).unwrap(), key);
    let dangling = dir.path().join("dangling.json");
    let nowhere = dir.path().join("nowhere.txt");
    symlink(&nowhere, &dangling).unwrap();
    assert!(save_key(&dangling, &key, false).is_err());
    assert!(!nowhere.exists());
    // No temporary file is left behind.
    let tmps = std::fs::read_dir(dir.path())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| {
            let n = e.file_name().to_string_lossy().into_owned();
            n.ends_with(".tmp") && !n.contains("0000000000000001")
        })
        .count();
    assert_eq!(tmps, 0);
}

#[test]
fn readable_key_files_are_reported() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("k.json");
    save_key(&p, &prf_key(1, DenseMode::Permute), false).unwrap();
    assert!(key_file_warnings(&p).is_empty());
    assert!(load_key_with_warnings(&p).unwrap().warnings.is_empty());
    for (mode, who) in [
        (0o644, "group and others"),
        (0o640, "its group"),
        (0o604, "others"),
    ] {
        std::fs::set_permissions(&p, std::fs::Permissions::from_mode(mode)).unwrap();
        let w = load_key_with_warnings(&p).unwrap().warnings;
        assert!(
            w.len() == 1
                && w[0].contains(&format!("{mode:04o}"))
                && w[0].contains(who)
                && w[0].contains("k.json"),
            "{w:?}"
        );
    }
}

/// FNV-1a of every corner of random cells (and of the cell's own vertex) on every level:
/// a fingerprint of an index function over in-range cells and, one cell in eight, cells up
/// to 2^21 where the u32 arithmetic wraps.
fn index_digest(idx: &ngp::encoding::LevelIndices, g: &GridLayout, seed: u64) -> u64 {
    let mut rng = ngp::rng::Pcg32::new(seed, 3);
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    let mut eat = |v: u32| {
        for b in v.to_le_bytes() {
            h = (h ^ b as u64).wrapping_mul(0x0100_0000_01b3);
        }
    };
    for (l, lv) in g.levels.iter().enumerate() {
        let r = lv.resolution;
        for i in 0..512 {
            let cell = if i % 8 == 7 {
                [0; 3].map(|_: u32| rng.next_u32() >> 11)
            } else {
                [0; 3].map(|_: u32| rng.below(r + 1))
            };
            let mut out = [0u32; 8];
            idx[l].corners(cell, &mut out);
            out.into_iter().for_each(&mut eat);
            eat(idx[l].index(cell[0], cell[1], cell[2]));
        }
    }
    h
}

/// Deterministic confinement maps: about 30 % of each level's slots reachable.
fn test_maps(g: &GridLayout) -> Vec<std::sync::Arc<[u32]>> {
    let mut rng = ngp::rng::Pcg32::new(77, 5);
    g.levels
        .iter()
        .map(|lv| {
            let mut set = ngp::encoding::reach::EntrySet::new(lv.size);
            for s in 0..lv.size {
                if rng.below(10) < 3 {
                    set.insert(s);
                }
            }
            std::sync::Arc::from(stealth::confinement_map(&set))
        })
        .collect()
}

fn digest_cases() -> Vec<(String, u64)> {
    let mut v = Vec::new();
    for (gi, g) in [
        layout(),
        GridLayout::new(GridConfig::base_json_2023(), 1).unwrap(),
    ]
    .iter()
    .enumerate()
    {
        let maps = test_maps(g);
        let mut keys = all_keys();
        keys.push(legacy_prf_key(3, DenseMode::Permute));
        keys.push(prf_key(16, DenseMode::Hash));
        for (ki, key) in keys.iter().enumerate() {
            let name = format!(
                "layout {gi} key {ki} {}/{:?}",
                key.scheme().name(),
                key.dense()
            );
            v.push((
                name.clone(),
                index_digest(&key.level_indices(g), g, ki as u64),
            ));
            let confined = stealth::confine(key, g, &maps);
            v.push((
                format!("{name} confined"),
                index_digest(&confined, g, ki as u64),
            ));
        }
    }
    v
}

/// Digests of [`digest_cases`] computed by the previous implementation (one trait object per
/// level, `corners` through `dyn`, commit 82cada1): the data-driven indices are bit for bit
/// the same for every scheme, dense mode, confinement and layout.
const DIGESTS_BEFORE_DATA: [(&str, u64); 28] = [
    ("layout 0 key 0 primes/Permute", 0xe4688ee26b60d57c),
    ("layout 0 key 0 primes/Permute confined", 0xa71479f35c1df34f),
    ("layout 0 key 1 primes/Permute", 0xc0381ee1141e7b81),
    ("layout 0 key 1 primes/Permute confined", 0x1db8a468db8705f7),
    ("layout 0 key 2 prf/Permute", 0x166a7448e1a6d7d8),
    ("layout 0 key 2 prf/Permute confined", 0x86a8c408127fe9b1),
    ("layout 0 key 3 primes/Hash", 0x99620bbc6c951037),
    ("layout 0 key 3 primes/Hash confined", 0xedfb874182e6398a),
    ("layout 0 key 4 prf/Hash", 0xf952e2c7c2b3e36d),
    ("layout 0 key 4 prf/Hash confined", 0xc095184ce62a0f7e),
    ("layout 0 key 5 prf/Permute", 0x932eabf8fea49165),
    ("layout 0 key 5 prf/Permute confined", 0xf2dbb95d6f867bc5),
    ("layout 0 key 6 prf/Hash", 0x07f33389ee9a1483),
    ("layout 0 key 6 prf/Hash confined", 0x5b3f37390b94a746),
    ("layout 1 key 0 primes/Permute", 0x0c0c50a0a63b6457),
    ("layout 1 key 0 primes/Permute confined", 0xc45530d22191d592),
    ("layout 1 key 1 primes/Permute", 0xad6db1e70f6eb0db),
    ("layout 1 key 1 primes/Permute confined", 0xf0db5a0bd8d7c318),
    ("layout 1 key 2 prf/Permute", 0xa55fa7de012733a7),
    ("layout 1 key 2 prf/Permute confined", 0xef848da01923578f),
    ("layout 1 key 3 primes/Hash", 0x5503caad3f6e6c8b),
    ("layout 1 key 3 primes/Hash confined", 0x4e478d9e323b349c),
    ("layout 1 key 4 prf/Hash", 0x5b85bfc61bcab0a9),
    ("layout 1 key 4 prf/Hash confined", 0x952bfef6df7831e1),
    ("layout 1 key 5 prf/Permute", 0x42fc449f25b0d241),
    ("layout 1 key 5 prf/Permute confined", 0x3dbe64349fb3c400),
    ("layout 1 key 6 prf/Hash", 0xa461e557246fd6f5),
    ("layout 1 key 6 prf/Hash confined", 0xc0e8d9129905be44),
];

#[test]
fn indices_are_bit_identical_to_the_trait_object_version() {
    let got = digest_cases();
    assert_eq!(got.len(), DIGESTS_BEFORE_DATA.len());
    for ((name, d), (want_name, want)) in got.iter().zip(DIGESTS_BEFORE_DATA) {
        assert_eq!(name, want_name);
        assert_eq!(*d, want, "{name}: {d:#018x}");
    }
}

#[test]
fn scene_boxes_travel_with_a_key_but_do_not_change_its_index() {
    let k = prf_key(4, DenseMode::Permute);
    let boxed = k.clone().with_scene_box(Some(2)).unwrap();
    assert_eq!(boxed.scene_box(), Some(2));
    assert_eq!(k.scene_box(), None);
    // Same index functions: the same key as far as two hidden scenes are concerned.
    assert!(boxed.same_index(&k) && boxed != k);
    assert!(!boxed.same_index(&prf_key(4, DenseMode::Hash)));
    // A wrong key is tried in the hidden scene's box; partial keys keep it too.
    assert_eq!(Key::wrong(7, &boxed).scene_box(), Some(2));
    assert!(!Key::wrong(7, &boxed).same_index(&boxed));
    assert_eq!(boxed.partial(0.5).scene_box(), Some(2));
    for bad in [0, 3, 256] {
        let e = k.clone().with_scene_box(Some(bad)).unwrap_err().to_string();
        assert!(
            e.contains(&bad.to_string()) && e.contains("power of two"),
            "{e}"
        );
    }
}
