//! Micro-benchmark of `corners()` per index function:
//! `cargo test --release --lib stego::bench -- --ignored --nocapture`.

use super::keys::{DenseMode, Key, KeyScheme};
use ngp::encoding::{GridConfig, GridLayout, LevelIndices, reference_indices};
use ngp::rng::Pcg32;
use std::hint::black_box;
use std::time::Instant;

/// ns per `LevelIndex::corners()` call (one `match` on the description each), over random
/// cells of `levels` (best of 7).
fn ns_per_call(idx: &LevelIndices, layout: &GridLayout, levels: &[usize]) -> f64 {
    let mut rng = Pcg32::new(1, 2);
    let cells: Vec<(usize, [u32; 3])> = (0..4096)
        .map(|i| {
            let l = levels[i % levels.len()];
            let r = layout.levels[l].resolution - 1;
            (l, [rng.below(r), rng.below(r), rng.below(r)])
        })
        .collect();
    let mut out = [0u32; 8];
    let mut acc = 0u32;
    let reps = 60;
    // The best of several runs: the machine is shared, and noise only adds time.
    let mut best = f64::INFINITY;
    for _ in 0..7 {
        let t = Instant::now();
        for _ in 0..reps {
            for &(l, c) in &cells {
                idx[l].corners(black_box(c), &mut out);
                acc = acc.wrapping_add(out[0] ^ out[7]);
            }
        }
        best = best.min(t.elapsed().as_nanos() as f64 / (reps * cells.len()) as f64);
    }
    black_box(acc);
    best
}

#[test]
#[ignore]
fn bench_corners() {
    let g = GridLayout::new(GridConfig::default(), 1).unwrap();
    let primes = Key::new(
        KeyScheme::Primes {
            keys: vec![[10_000_019, 10_000_079, 10_000_103]],
        },
        DenseMode::Permute,
    )
    .unwrap();
    let prf = Key::new(
        KeyScheme::Prf {
            secrets: vec![[9; 32]],
        },
        DenseMode::Permute,
    )
    .unwrap();
    let cases: Vec<(&str, LevelIndices)> = vec![
        ("reference", reference_indices(&g)),
        ("primes/permute", primes.level_indices(&g)),
        (
            "primes/hash",
            primes.clone().with_dense(DenseMode::Hash).level_indices(&g),
        ),
        ("prf/permute", prf.level_indices(&g)),
        (
            "prf/hash",
            prf.clone().with_dense(DenseMode::Hash).level_indices(&g),
        ),
    ];
    let all: Vec<usize> = (0..16).collect();
    println!("ns per corners() call (match per call, random cells):");
    println!(
        "{:16} {:>8} {:>8} {:>8}",
        "index", "hashed", "dense", "all 16"
    );
    for (name, idx) in &cases {
        let h = ns_per_call(idx, &g, &[5, 9, 12, 15]);
        let d = ns_per_call(idx, &g, &[0, 2, 4]);
        let a = ns_per_call(idx, &g, &all);
        println!("{name:16} {h:8.2} {d:8.2} {a:8.2}");
    }
}

/// The cost of one brute-force key trial ([`super::strength::key_trial_cost`]):
/// `cargo test --release --lib stego::bench::bench_key_trial -- --ignored --nocapture`.
#[test]
#[ignore]
fn bench_key_trial() {
    use super::strength::{PROBE_POINTS, key_trial_cost};
    let g = GridLayout::new(GridConfig::default(), 1).unwrap();
    println!("one key trial, {PROBE_POINTS} probes × 16 levels × 8 corners, one core:");
    println!(
        "{:8} {:>3} {:>10} {:>10} {:>10}",
        "scheme", "m", "trial ms", "derive ms", "index ms"
    );
    use super::SchemeKind::{Prf, Primes};
    for (kind, m) in [(Primes, 1), (Primes, 16), (Prf, 1), (Prf, 16)] {
        let c = key_trial_cost(kind, m, &g, PROBE_POINTS, 9, 3).unwrap();
        println!(
            "{:8} {:>3} {:>10.3} {:>10.3} {:>10.3}",
            c.scheme,
            m,
            c.trial_seconds * 1e3,
            c.derive_seconds * 1e3,
            c.index_seconds * 1e3
        );
    }
}
