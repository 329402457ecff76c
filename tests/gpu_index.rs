//! The GPU's hash-grid indices against the CPU's, bit for bit: every level of the paper's
//! layout under real keys of both schemes and both dense modes, plain and confined to a
//! cover's entries (stealth), on random cells and on the cells where arithmetic wraps.
//! Runs on whatever adapter `test_context` finds (lavapipe in CI).
#![cfg(feature = "gpu")]

use std::sync::Arc;
use stegongp::gpu::{CornerKernel, GpuContext, GpuIndex, test_context};
use stegongp::ngp::encoding::{GridConfig, GridLayout, LevelIndex, reference_indices};
use stegongp::rng::Pcg32;
use stegongp::stego::stealth::confine;
use stegongp::stego::{DenseMode, Key, KeyScheme, SchemeKind};
use testkit::keys::seeded_key;

/// Per level: every cell whose coordinates are 0, res − 1 or res (the upper corners wrap
/// into the next row or past the table), one far out where u32 and u64 products wrap, and
/// `n_random` cells inside the level. Cell `i·L + l` is on level l.
fn cells(layout: &GridLayout, n_random: usize, seed: u64) -> Vec<[u32; 3]> {
    let mut rng = Pcg32::new(seed, 7);
    let l = layout.levels.len();
    let edges = 27 + 1;
    let mut out = vec![[0u32; 3]; (edges + n_random) * l];
    for (li, lv) in layout.levels.iter().enumerate() {
        let r = lv.resolution;
        let e = [0, r - 1, r];
        for i in 0..edges + n_random {
            out[i * l + li] = if i < 27 {
                [e[i % 3], e[i / 3 % 3], e[i / 9]]
            } else if i == 27 {
                [0xffff_fffe, 0x8000_0001, 0x7fff_ffff]
            } else {
                [rng.below(r), rng.below(r), rng.below(r)]
            };
        }
    }
    out
}

fn cpu_corners(indices: &[LevelIndex], cells: &[[u32; 3]]) -> Vec<[u32; 8]> {
    let l = indices.len();
    cells
        .iter()
        .enumerate()
        .map(|(i, &c)| {
            let mut out = [0u32; 8];
            indices[i % l].corners(c, &mut out);
            out
        })
        .collect()
}

/// What the CPU engine evaluates, uploaded and evaluated on the device.
fn assert_identical(ctx: &GpuContext, what: &str, indices: &[LevelIndex], cells: &[[u32; 3]]) {
    let index = GpuIndex::upload(ctx, indices).unwrap();
    let got = CornerKernel::new(ctx)
        .unwrap()
        .corners(ctx, &index, cells)
        .unwrap();
    let want = cpu_corners(indices, cells);
    let l = indices.len();
    assert_eq!(got.len(), want.len());
    for (i, (g, w)) in got.iter().zip(&want).enumerate() {
        assert_eq!(
            g,
            w,
            "{what}: level {} cell {:?} ({:?})",
            i % l,
            cells[i],
            indices[i % l]
        );
    }
}

fn paper_layout() -> GridLayout {
    GridLayout::new(GridConfig::default(), 1).unwrap()
}

#[test]
fn every_key_kind_and_dense_mode_is_bit_identical() {
    let Some(ctx) = test_context() else { return };
    let layout = paper_layout();
    let cells = cells(&layout, 600, 1);
    for (kind, m) in [(SchemeKind::Primes, 16), (SchemeKind::Prf, 4)] {
        for dense in [DenseMode::Permute, DenseMode::Hash] {
            let key = seeded_key(kind, m, 11, 3).with_dense(dense);
            let what = format!("{} m={m} dense={}", kind.name(), dense.name());
            assert_identical(ctx, &what, &key.level_indices(&layout), &cells);
        }
    }
}

#[test]
fn reference_and_partly_disclosed_keys_are_bit_identical() {
    let Some(ctx) = test_context() else { return };
    let layout = paper_layout();
    let cells = cells(&layout, 300, 2);
    assert_identical(ctx, "reference", &reference_indices(&layout), &cells);
    // Half the levels on the reference index, half keyed, in one upload.
    for kind in [SchemeKind::Primes, SchemeKind::Prf] {
        let key = seeded_key(kind, 4, 5, 3).disclose_levels(0.5);
        assert_identical(ctx, "disclosed", &key.level_indices(&layout), &cells);
    }
}

/// Primes past 2^32 (the CPU's u64 products keep their high words on the dense levels in
/// hash mode).
#[test]
fn primes_past_two_to_the_32_are_bit_identical() {
    let Some(ctx) = test_context() else { return };
    let layout = paper_layout();
    let cells = cells(&layout, 300, 3);
    // 2^32 + 15, 2^33 + 17 and 9 999 999 967 (the largest prime below 1e10) are prime.
    let big = [4_294_967_311, 8_589_934_609, 9_999_999_967];
    for dense in [DenseMode::Hash, DenseMode::Permute] {
        let key = Key::new(
            KeyScheme::Primes {
                keys: vec![big, [10_000_019, 4_294_967_291, 2_654_435_761]],
            },
            dense,
        )
        .unwrap();
        assert_identical(ctx, "big primes", &key.level_indices(&layout), &cells);
    }
}

/// Stealth: the keyed index followed by a per-level map into the cover's entries (composed
/// with a dense level's permutation into one table).
#[test]
fn confined_indices_are_bit_identical() {
    let Some(ctx) = test_context() else { return };
    let layout = paper_layout();
    let cells = cells(&layout, 300, 4);
    let mut rng = Pcg32::new(9, 1);
    // Maps onto a random tenth of each level's slots, as a cover's reach would be.
    let maps: Vec<Arc<[u32]>> = layout
        .levels
        .iter()
        .map(|lv| {
            let n = (lv.size / 10).max(1);
            (0..lv.size).map(|_| rng.below(n) * 10 % lv.size).collect()
        })
        .collect();
    for kind in [SchemeKind::Primes, SchemeKind::Prf] {
        for dense in [DenseMode::Permute, DenseMode::Hash] {
            let key = seeded_key(kind, 16, 21, 3).with_dense(dense);
            let what = format!("confined {} {}", kind.name(), dense.name());
            assert_identical(ctx, &what, &confine(&key, &layout, &maps), &cells);
        }
    }
}

/// Larger tables and boxes: a 2^26 table has dense levels of up to 25 672 376 slots, and
/// aabb 8 gives resolutions past 2048.
#[test]
fn other_layouts_are_bit_identical() {
    let Some(ctx) = test_context() else { return };
    let wide = GridConfig {
        log2_hashmap_size: 26,
        ..GridConfig::default()
    };
    for (config, aabb) in [(wide, 1), (GridConfig::base_json_2023(), 8)] {
        let layout = GridLayout::new(config, aabb).unwrap();
        let cells = cells(&layout, 100, 6);
        for kind in [SchemeKind::Primes, SchemeKind::Prf] {
            // Hash mode: a permutation of a 2^25-slot level would take the CPU a while.
            let key = seeded_key(kind, 3, 8, 3).with_dense(DenseMode::Hash);
            let what = format!(
                "{} log2 T {} aabb {aabb}",
                kind.name(),
                config.log2_hashmap_size
            );
            assert_identical(ctx, &what, &key.level_indices(&layout), &cells);
        }
    }
}
