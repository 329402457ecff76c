//! The statistics on hand-built snapshots whose values are known, through the file format
//! (so fp16 rounding and the gzip framing are part of what is tested).

use super::*;
use ngp::encoding::GridConfig;
use ngp::network::ModelConfig;
use ngp::network::nerf::NerfNetwork;
use ngp::occupancy::{N_CELLS, morton3d};

/// Two levels, T = 2^12: level 0 is dense (16³ = 4096 vertices), level 1 (2048 per axis)
/// hashes. Small enough to reason about, with both kinds of level.
fn config() -> ModelConfig {
    ModelConfig {
        grid: GridConfig {
            n_levels: 2,
            n_features: 2,
            log2_hashmap_size: 12,
            base_resolution: 16,
        },
        aabb_scale: 1,
    }
}

/// The grid with only cell (64, 64, 64) of cascade 0 occupied.
fn one_cell_grid() -> Vec<f32> {
    let mut d = vec![0.0f32; N_CELLS];
    d[morton3d(64, 64, 64) as usize] = 1.0;
    d
}

fn analyse(snap: &Snapshot, ext: &str) -> Analysis {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join(format!("m.{ext}"));
    snapshot::save(&p, snap).unwrap();
    analyse_file(&p).unwrap()
}

fn untouched() -> (NerfLayout, Vec<f32>) {
    let net = NerfNetwork::new(config()).unwrap();
    let p = net.init_params(11);
    (net.layout, p)
}

/// Sets entry `e` of `level` to `v` (all features).
fn set(layout: &NerfLayout, p: &mut [f32], level: usize, e: u32, v: [f32; 2]) {
    let l = layout.grid.levels[level];
    let at = layout.grid_offset + (l.offset + e) as usize * 2;
    p[at..at + 2].copy_from_slice(&v);
}

#[test]
fn an_untouched_table_is_all_at_initialisation() {
    let (layout, p) = untouched();
    assert_eq!(layout.grid.levels[0].size, 4096);
    assert!(layout.grid.levels[0].dense && !layout.grid.levels[1].dense);
    let a = analyse(&Snapshot::new(config(), p, one_cell_grid()), "ingp");
    for l in &a.levels {
        assert_eq!(l.init_frac, 1.0, "level {}", l.level);
        assert_eq!(l.reachable.init_frac, 1.0);
        assert_eq!(l.unreachable.init_frac, 1.0);
        assert!(l.unreachable.magnitude.max <= INIT_BOUND as f64);
        // Uniform in ±1e-4, the largest of two |features|: median near 1e-4·√½.
        let med = l.unreachable.magnitude.median;
        assert!((6.5e-5..7.6e-5).contains(&med), "median {med}");
    }
    // The initial MLP is uniform: excess kurtosis −1.2.
    for m in &a.mlp {
        assert!((m.excess_kurtosis + 1.2).abs() < 0.15, "{m:?}");
    }
    assert_eq!(a.format, "ingp (gzip msgpack)");
    let h = a.compression.gzip_header.unwrap();
    assert_eq!((h.mtime, h.os, h.flags), (0, 3, 0));
    assert_eq!(a.compression.measured, "file");
    let ratio = a.file_bytes as f64 / a.msgpack_bytes as f64;
    assert_eq!(a.compression.ratio, ratio);
    // The mostly empty occupancy grid (4 MiB of fp16) dominates so small a model.
    assert!(ratio > 0.0 && ratio < 0.5, "{ratio}");
}

#[test]
fn moved_entries_give_exact_fractions() {
    let (layout, mut p) = untouched();
    // Level 0: three entries moved in one feature or both; one at exactly 1e-4 (still init)
    // and one just past the bound in its second feature (moved).
    set(&layout, &mut p, 0, 0, [0.5, 0.0]);
    set(&layout, &mut p, 0, 17, [0.0, -0.25]);
    set(&layout, &mut p, 0, 4095, [1e-4, -1e-4]);
    set(&layout, &mut p, 0, 300, [0.0, 1.25e-4]);
    // Level 1: 1024 of 4096 entries moved.
    for e in (0..4096).step_by(4) {
        set(&layout, &mut p, 1, e, [0.125, 0.125]);
    }
    let a = analyse(&Snapshot::new(config(), p, one_cell_grid()), "msgpack");
    assert_eq!(a.levels[0].init_frac, (4096.0 - 3.0) / 4096.0);
    assert_eq!(a.levels[1].init_frac, 0.75);
    assert_eq!(a.format, "msgpack");
    assert_eq!(a.compression.measured, "flate2 default level");
    assert!(a.compression.gzip_header.is_none());
    assert!(a.compression.ratio > 0.0 && a.compression.ratio < 0.5);
    let f: std::collections::HashMap<String, f64> = a.features().into_iter().collect();
    assert_eq!(f["init_frac_l1"], 0.75);
    assert_eq!(f["init_frac_hashed"], 0.75);
    assert_eq!(f["init_frac_dense"], (4096.0 - 3.0) / 4096.0);
}

#[test]
fn one_occupied_cell_splits_each_level_into_reachable_and_not() {
    let (layout, mut p) = untouched();
    // Cell (64,64,64) spans [0.5, 0.5 + 1/128]³. Level 0 (scale 15): 15x + 0.5 ∈ [8, 8.12],
    // vertices 8..=9 per axis, dense index x + 16y + 256z.
    let mut reach0 = Vec::new();
    for z in 8..=9u32 {
        for y in 8..=9u32 {
            for x in 8..=9u32 {
                reach0.push(x + 16 * y + 256 * z);
            }
        }
    }
    // Reachable magnitudes k/16, k = 1..=8 (the second feature smaller, of opposite sign).
    for (k, &e) in reach0.iter().enumerate() {
        let v = (k + 1) as f32 / 16.0;
        set(&layout, &mut p, 0, e, [v, -v / 2.0]);
    }
    // Two unreachable entries moved.
    set(&layout, &mut p, 0, 0, [0.125, 0.0]);
    set(&layout, &mut p, 0, 1, [0.0, -0.0625]);
    // Level 1 (scale 2047): 2047x + 0.5 ∈ [1024, 1039.99], vertices 1024..=1040 per axis,
    // hashed by the reference primes — computed here from the spec, not from the library.
    let mut reach1 = std::collections::BTreeSet::new();
    for z in 1024..=1040u32 {
        for y in 1024..=1040u32 {
            for x in 1024..=1040u32 {
                reach1.insert(
                    (x ^ y.wrapping_mul(2_654_435_761) ^ z.wrapping_mul(805_459_861)) % 4096,
                );
            }
        }
    }
    assert_eq!(layout.grid.levels[1].scale, 2047.0);
    let a = analyse(&Snapshot::new(config(), p, one_cell_grid()), "ingp");
    let l0 = &a.levels[0];
    assert_eq!(l0.reachable.count, 8);
    assert_eq!(l0.unreachable.count, 4088);
    assert_eq!(l0.reachable_frac, 8.0 / 4096.0);
    assert_eq!(l0.reachable.init_frac, 0.0);
    let m = l0.reachable.magnitude;
    assert_eq!(m.mean, 4.5 / 16.0);
    assert_eq!(m.median, 4.0 / 16.0);
    assert_eq!(m.p90, 0.5);
    assert_eq!(m.max, 0.5);
    assert_eq!(l0.unreachable.init_frac, 4086.0 / 4088.0);
    assert_eq!(l0.unreachable.magnitude.max, 0.125);
    assert!(l0.unreachable.magnitude.median <= INIT_BOUND as f64);
    let l1 = &a.levels[1];
    assert_eq!(l1.reachable.count as usize, reach1.len());
    assert_eq!(l1.unreachable.count as usize, 4096 - reach1.len());
    assert!(
        reach1.len() > 1000 && reach1.len() < 4096,
        "{}",
        reach1.len()
    );
    assert_eq!(a.occupied_frac, 1.0 / N_CELLS as f64);
    // One cell at optical thickness 1, the rest 0.
    assert_eq!(a.grid_max, 1.0);
    assert!(
        (a.grid_mean * N_CELLS as f64 - 1.0).abs() < 1e-9,
        "{}",
        a.grid_mean
    );
    // Features exist for both levels and carry these numbers.
    let f: std::collections::HashMap<String, f64> = a.features().into_iter().collect();
    assert_eq!(f["unreach_init_frac_l0"], 4086.0 / 4088.0);
    assert_eq!(f["reach_frac_dense"], 8.0 / 4096.0);
    assert!(f["unreach_log10_mag_median_l0"] < -3.9);
    assert_eq!(f["grid_log10_max"], 0.0);
    assert!((f["grid_log10_mean"] + (N_CELLS as f64).log10()).abs() < 1e-9);
}

#[test]
fn no_stored_grid_counts_everything_reachable() {
    let (_, p) = untouched();
    let a = analyse(&Snapshot::new(config(), p, Vec::new()), "ingp");
    assert!(!a.density_grid_stored);
    for l in &a.levels {
        assert_eq!(l.reachable.count, l.entries);
        assert_eq!(l.unreachable.count, 0);
    }
    let names: Vec<String> = a.features().into_iter().map(|(n, _)| n).collect();
    assert!(
        !names.iter().any(|n| n.starts_with("unreach_")),
        "{names:?}"
    );
}

#[test]
fn features_have_unique_stable_names_and_stay_few() {
    let (_, p) = untouched();
    let mut snap = Snapshot::new(config(), p, one_cell_grid());
    snap.loss = 0.01;
    let a = analyse(&snap, "ingp");
    let f = a.features();
    let mut names: Vec<&str> = f.iter().map(|(n, _)| n.as_str()).collect();
    for want in [
        "init_frac_l0",
        "unreach_init_frac_l1",
        "unreach_log10_mag_median_l1",
        "init_frac_hashed",
        "reach_log10_mag_median_hashed",
        "mlp_density0_kurt",
        "mlp_color2_std",
        "gzip_ratio",
        "field_near_zero_frac",
        "occupied_frac",
        "grid_log10_mean",
        "grid_log10_max",
    ] {
        assert!(names.contains(&want), "{want} missing from {names:?}");
    }
    assert!((f.iter().find(|(n, _)| n == "log10_loss").unwrap().1 + 2.0).abs() < 1e-6);
    assert!(f.len() <= 3 * 2 + 24);
    assert!(f.iter().all(|(_, v)| v.is_finite()));
    names.sort();
    names.dedup();
    assert_eq!(names.len(), f.len(), "duplicate feature names");
    // The colour MLP's output layer counts its 3 used rows, not the 16 stored.
    let last = a.mlp.last().unwrap();
    assert_eq!(
        (last.network.as_str(), last.rows, last.cols),
        ("color", 3, 64)
    );
    assert_eq!(a.mlp.len(), 5);
}

#[test]
fn bad_files_are_named_in_the_error() {
    let dir = tempfile::tempdir().unwrap();
    let (_, p) = untouched();
    let good = dir.path().join("good.ingp");
    snapshot::save(&good, &Snapshot::new(config(), p, one_cell_grid())).unwrap();
    let bytes = std::fs::read(&good).unwrap();
    let cases: [(&str, &[u8], &str); 4] = [
        ("trunc.ingp", &bytes[..bytes.len() / 2], "gzip"),
        ("short.ingp", &bytes[..5], "gzip"),
        (
            "foreign.ingp",
            b"PK\x03\x04 a zip file",
            "not an instant-ngp snapshot",
        ),
        ("empty.msgpack", b"", "empty"),
    ];
    for (name, content, needle) in cases {
        let f = dir.path().join(name);
        std::fs::write(&f, content).unwrap();
        let e = analyse_file(&f).unwrap_err().to_string();
        assert!(e.contains(name) && e.contains(needle), "{name}: {e}");
    }
    let e = analyse_file(&dir.path().join("absent.ingp"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("absent.ingp"), "{e}");
}

/// The field's near-zero fraction on networks whose density output is known everywhere:
/// an untrained one (every entry at ±1e-4, so raw log-densities of order 1e-5), one whose
/// density output row is zero (raw exactly 0), and one that decodes 1 at every point (every
/// feature 1, every input weight 1/32, the output row 1/64: each hidden unit 1, raw 1).
#[test]
fn the_fields_near_zero_fraction_on_known_networks() {
    let (layout, p) = untouched();
    let a = analyse(&Snapshot::new(config(), p.clone(), one_cell_grid()), "ingp");
    assert_eq!(a.field_near_zero_frac, 1.0);

    let dm = layout.density_mlp;
    let (w0_len, width) = (dm.width * dm.n_in, dm.width);
    let out_row = layout.density_offset + w0_len..layout.density_offset + w0_len + width;
    let mut zero_out = p.clone();
    zero_out[out_row.clone()].fill(0.0);
    // Even with every table entry moved: the output row alone decides.
    for v in &mut zero_out[layout.grid_offset..] {
        *v = 0.5;
    }
    let a = analyse(&Snapshot::new(config(), zero_out, one_cell_grid()), "ingp");
    assert_eq!(a.field_near_zero_frac, 1.0);

    let mut one = p;
    let w0 = layout.density_offset..layout.density_offset + w0_len;
    one[w0].fill(1.0 / dm.n_in as f32);
    one[out_row].fill(1.0 / width as f32);
    for v in &mut one[layout.grid_offset..] {
        *v = 1.0;
    }
    // fp16 keeps 1/32 and 1/64 exactly: raw is 1 up to rounding, far from 0.
    let a = analyse(&Snapshot::new(config(), one, one_cell_grid()), "ingp");
    assert_eq!(a.field_near_zero_frac, 0.0);
    let f = a.features();
    let got = f
        .iter()
        .find(|(n, _)| n == "field_near_zero_frac")
        .unwrap()
        .1;
    assert_eq!(got, 0.0);
}
