//! Each attack on a small random model whose stored grid occupies a ball in the box's
//! centre: exact counts, determinism, bounds, and the cover's renders bit-identical after
//! `purify`.

use super::*;
use ngp::camera::Camera;
use ngp::encoding::layout::GridConfig;
use ngp::encoding::reference_indices;
use ngp::network::{ModelConfig, NerfLayout};
use ngp::occupancy::{GRID_SIZE, N_CELLS, morton3d};
use ngp::render::image::{RenderOptions, render_image};
use ngp::rng::Pcg32;
use ngp::snapshot::{self, DatasetImage, Snapshot, SnapshotDataset};
use weights::quantisation_blocks;

fn config() -> ModelConfig {
    ModelConfig {
        grid: GridConfig {
            n_levels: 8,
            n_features: 2,
            log2_hashmap_size: 14,
            base_resolution: 16,
        },
        aabb_scale: 1,
    }
}

/// A camera looking at the box's centre from +z.
fn camera(size: u32) -> Camera {
    Camera {
        c2w: [
            [1.0, 0.0, 0.0, 0.5],
            [0.0, -1.0, 0.0, 0.5],
            [0.0, 0.0, -1.0, 1.8],
        ],
        fx: size as f32,
        fy: size as f32,
        cx: size as f32 / 2.0,
        cy: size as f32 / 2.0,
        width: size,
        height: size,
        distortion: None,
    }
}

/// Random weights (the table well off its initialisation), a stored grid dense in a ball
/// of radius 0.2 round the centre and empty elsewhere, and one stored camera; read back
/// from its file, as an attacker gets it.
fn model() -> Model {
    let c = config();
    let n = NerfLayout::new(c).unwrap().n_params;
    let mut r = Pcg32::new(11, 3);
    let params: Vec<f32> = (0..n).map(|_| r.next_f32() * 2.0 - 1.0).collect();
    let mut density = vec![0.0f32; N_CELLS];
    let g = GRID_SIZE as f32;
    for x in 0..GRID_SIZE {
        for y in 0..GRID_SIZE {
            for z in 0..GRID_SIZE {
                let p = [x, y, z].map(|v| (v as f32 + 0.5) / g - 0.5);
                if p.iter().map(|v| v * v).sum::<f32>() < 0.04 {
                    density[morton3d(x, y, z) as usize] = 5.0;
                }
            }
        }
    }
    let cam = camera(24);
    let mut img = DatasetImage::new([24, 24], [24.0, 24.0], cam.c2w);
    img.principal_point = [0.5, 0.5];
    let mut snap = Snapshot::new(c, params, density);
    snap.dataset = Some(SnapshotDataset::new(vec!["a.png".into()], vec![img], 1));
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.ingp");
    snapshot::save(&path, &snap).unwrap();
    Model::load(&path).unwrap()
}

fn cover_render(m: &Model) -> Vec<f32> {
    let idx = reference_indices(&m.net.layout.grid);
    let r = render_image(
        &m.view(&idx, &m.grid),
        &camera(32),
        &RenderOptions::default(),
    );
    assert!(r.n_samples > 1000, "the view must see the ball");
    r.rgb.iter().chain(&r.depth).copied().collect()
}

#[test]
fn attacks_parse_and_print_back() {
    for s in [
        "noise=0.001",
        "prune=0.1",
        "prune-magnitude=0.25",
        "quantise=8",
        "quantise=4",
        "purify",
        "purify-contribution=0.000001",
        "purify-mlp=50",
        "refit-mlp=5",
        "finetune=100",
        "finetune-renders=500",
        "redistil=2000",
    ] {
        let a: Attack = s.parse().unwrap();
        assert_eq!(a.to_string().parse::<Attack>().unwrap(), a, "{s}");
    }
    assert_eq!(
        "quantize=8".parse::<Attack>().unwrap(),
        Attack::Quantise { bits: 8 }
    );
    for (bad, says) in [
        ("noise=-0.1", "≥ 0"),
        ("noise", "give a value"),
        ("noise=abc", "not a number"),
        ("noise=inf", "not a number"),
        ("prune=1.5", "between 0 and 1"),
        ("prune=-0.1", "between 0 and 1"),
        ("prune-magnitude=nan", "not a number"),
        ("quantise=3", "8 or 4"),
        ("purify=3", "takes no value"),
        ("finetune=0", "step count"),
        ("finetune=-5", "step count"),
        ("redistil=99999999", "step count"),
        ("blur=3", "unknown attack"),
        ("", "unknown attack"),
    ] {
        let e = bad.parse::<Attack>().unwrap_err().to_string();
        assert!(e.contains(says), "{bad}: {e}");
    }
}

#[test]
fn finetune_without_photos_is_refused_before_anything_runs() {
    let e = apply(
        model(),
        &Attack::Finetune { steps: 10 },
        &AttackContext::default(),
    )
    .err()
    .unwrap()
    .to_string();
    assert!(e.contains("--data"), "{e}");
}

#[test]
fn noise_has_the_standard_deviation_asked_for_and_repeats_for_a_seed() {
    let m = model();
    let p = m.params().to_vec();
    let a = weights::noise(&p, 0.01, 5);
    assert_eq!(a, weights::noise(&p, 0.01, 5));
    assert_ne!(a, weights::noise(&p, 0.01, 6));
    let d: Vec<f64> = a.iter().zip(&p).map(|(x, y)| (x - y) as f64).collect();
    let mean = d.iter().sum::<f64>() / d.len() as f64;
    let sd = (d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / d.len() as f64).sqrt();
    assert!(mean.abs() < 2e-4, "mean {mean}");
    assert!(
        (sd - 0.01).abs() < 2e-4,
        "standard deviation {sd}, not σ = 0.01"
    );
    assert_eq!(weights::noise(&p, 0.0, 5), p);
}

#[test]
fn pruning_zeroes_exactly_the_fraction_asked() {
    let m = model();
    let l = &m.net.layout;
    let nf = l.grid.config.n_features as usize;
    let n = l.grid.n_entries as u64;
    let zero_entries = |p: &[f32]| {
        p[l.grid_offset..]
            .chunks(nf)
            .filter(|e| e.iter().all(|&x| x == 0.0))
            .count() as u64
    };
    for f in [0.0f32, 0.05, 0.25, 1.0] {
        let want = (f as f64 * n as f64).round() as u64;
        let (p, k) = weights::prune_random(l, m.params(), f, 1);
        assert_eq!((k, zero_entries(&p)), (want, want), "random {f}");
        assert_eq!(
            p[..l.grid_offset],
            m.params()[..l.grid_offset],
            "MLPs untouched"
        );
        let (q, k) = weights::prune_magnitude(l, m.params(), f);
        assert_eq!((k, zero_entries(&q)), (want, want), "magnitude {f}");
    }
    // Magnitude pruning takes the smallest: every entry kept is at least as large as
    // every entry zeroed.
    let (q, _) = weights::prune_magnitude(l, m.params(), 0.3);
    let norm = |e: &[f32]| e.iter().map(|x| x * x).sum::<f32>();
    let (mut largest_zeroed, mut smallest_kept) = (0.0f32, f32::MAX);
    for (orig, now) in m.params()[l.grid_offset..]
        .chunks(nf)
        .zip(q[l.grid_offset..].chunks(nf))
    {
        if now.iter().all(|&x| x == 0.0) {
            largest_zeroed = largest_zeroed.max(norm(orig));
        } else {
            smallest_kept = smallest_kept.min(norm(orig));
        }
    }
    assert!(largest_zeroed <= smallest_kept);
    // Random pruning differs by seed.
    assert_ne!(
        weights::prune_random(l, m.params(), 0.1, 1).0,
        weights::prune_random(l, m.params(), 0.1, 2).0
    );
}

#[test]
fn quantisation_keeps_at_most_its_levels_and_half_a_step_of_error() {
    let m = model();
    let l = &m.net.layout;
    for bits in [8u32, 4] {
        let q = weights::quantise(l, m.params(), bits);
        let q_max = ((1u32 << (bits - 1)) - 1) as f32;
        for block in quantisation_blocks(l) {
            let orig = &m.params()[block.clone()];
            let absmax = orig.iter().fold(0.0f32, |a, x| a.max(x.abs()));
            let s = absmax / q_max;
            let mut levels: Vec<i64> = q[block.clone()]
                .iter()
                .map(|x| (x / s).round() as i64)
                .collect();
            levels.sort();
            levels.dedup();
            assert!(
                (levels.len() as u32) < (1 << bits),
                "{bits} bits: {} levels",
                levels.len()
            );
            for (a, b) in orig.iter().zip(&q[block]) {
                assert!((a - b).abs() <= s * 0.5 + 1e-6, "{a} → {b} (step {s})");
            }
        }
    }
    // The blocks cover every weight once.
    let covered: usize = quantisation_blocks(l).iter().map(|b| b.len()).sum();
    assert_eq!(covered, l.n_params);
}

#[test]
fn purify_resets_only_what_the_cover_cannot_reach_and_no_cover_pixel_changes() {
    let m = model();
    let before = cover_render(&m);
    let reach = purify::cover_reachable(&m);
    let unreachable: u64 = reach.iter().map(|s| (s.size() - s.len()) as u64).sum();
    assert!(
        unreachable > 1000,
        "the ball leaves entries unreached ({unreachable})"
    );
    let (m, r) = apply(m, &Attack::Purify, &AttackContext::default()).unwrap();
    assert_eq!(r.entries_changed, unreachable);
    // Written and read back as a file, as the attacked model is published.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("purified.ingp");
    m.save(&path).unwrap();
    let back = Model::load(&path).unwrap();
    let after = cover_render(&back);
    assert!(
        before
            .iter()
            .zip(&after)
            .all(|(a, b)| a.to_bits() == b.to_bits()),
        "the cover's render moved"
    );
    // Every reset entry sits in the initialisation's range.
    let l = &back.net.layout;
    let nf = l.grid.config.n_features as usize;
    let table = &back.params()[l.grid_offset..];
    for (level, set) in l.grid.levels.iter().zip(&reach) {
        for e in 0..level.size {
            if !set.contains(e) {
                let at = (level.offset + e) as usize * nf;
                assert!(
                    table[at..at + nf]
                        .iter()
                        .all(|x| x.abs() <= stego::steganalysis::INIT_BOUND),
                    "level {} entry {e}: {:?}",
                    level.level,
                    &table[at..at + nf]
                );
            }
        }
    }
}

#[test]
fn contribution_is_zero_off_the_rays_and_purifying_by_it_resets_a_superset_of_purify() {
    let m = model();
    let cams = views::stored_cameras(&m, 24, 8).unwrap();
    let c = purify::contributions(&m, &cams);
    let reach = purify::cover_reachable(&m);
    let l = &m.net.layout.grid;
    let mut used = 0;
    for (level, set) in l.levels.iter().zip(&reach) {
        for e in 0..level.size {
            let v = c[(level.offset + e) as usize];
            assert!(v >= 0.0);
            if v > 0.0 {
                used += 1;
                assert!(
                    set.contains(e),
                    "an entry no cover sample reaches contributes"
                );
            }
        }
    }
    assert!(used > 100, "{used} entries contribute");
    let ctx = AttackContext {
        render_side: 24,
        render_views: 8,
        ..AttackContext::default()
    };
    let (_, n_any) = purify::purify_by_contribution(&m, f32::MIN_POSITIVE, &ctx).unwrap();
    let unreachable: u64 = reach.iter().map(|s| (s.size() - s.len()) as u64).sum();
    assert!(
        n_any > unreachable,
        "{n_any} reset against {unreachable} unreachable"
    );
    let (p0, n0) = purify::purify_by_contribution(&m, 0.0, &ctx).unwrap();
    assert_eq!((n0, &p0[..]), (0, m.params()), "ε = 0 resets nothing");
    // Deterministic.
    assert_eq!(c, purify::contributions(&m, &cams));
}

#[test]
fn a_chain_is_deterministic_for_a_seed() {
    let chain: Vec<Attack> = ["noise=0.001", "prune=0.1", "quantise=8", "purify"]
        .iter()
        .map(|s| s.parse().unwrap())
        .collect();
    let ctx = AttackContext {
        seed: 9,
        ..AttackContext::default()
    };
    let (a, ra) = apply_all(model(), &chain, &ctx, |_| {}).unwrap();
    let (b, _) = apply_all(model(), &chain, &ctx, |_| {}).unwrap();
    assert_eq!(a.params(), b.params());
    assert_eq!(ra.len(), 4);
    let (c, _) = apply_all(model(), &chain, &AttackContext::default(), |_| {}).unwrap();
    assert_ne!(a.params(), c.params());
}

#[test]
fn refitting_the_mlps_leaves_the_table_as_it_was() {
    let m = model();
    let g = m.net.layout.grid_offset;
    let table = m.params()[g..].to_vec();
    let ctx = AttackContext {
        render_side: 16,
        render_views: 2,
        ..AttackContext::default()
    };
    let (r, rep) = apply(m, &Attack::RefitMlp { steps: 3 }, &ctx).unwrap();
    assert_eq!(&r.params()[g..], &table[..]);
    assert!(rep.params_changed > 0, "the MLPs trained");
    assert_eq!(rep.entries_changed, 0);
}
