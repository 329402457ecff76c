//! Full-size 16×2 files through the public API and the `inspect` subcommand.

use stegongp::ngp::network::{ModelConfig, NerfLayout};
use stegongp::ngp::snapshot::{self, DENSITY_GRID_CELLS, Snapshot};
use stegongp::rng::Pcg32;

#[test]
fn full_size_16x2_files_and_inspect() {
    let config = ModelConfig::default();
    let layout = NerfLayout::new(config).unwrap();
    let mut r = Pcg32::new(7, 7);
    // MLP weights Xavier-like, grid features as initialised (±1e-4), as after few steps.
    let params: Vec<f32> = (0..layout.n_params)
        .map(|i| {
            let a = if i < layout.grid_offset { 0.2 } else { 1e-4 };
            (r.next_f32() * 2.0 - 1.0) * a
        })
        .collect();
    let grid: Vec<f32> = (0..DENSITY_GRID_CELLS)
        .map(|i| if i % 3 == 0 { -1.0 } else { 0.0 })
        .collect();
    let snap = Snapshot::new(config, params, grid);
    let dir = tempfile::tempdir().unwrap();
    let ingp = dir.path().join("m.ingp");
    let mp = dir.path().join("m.msgpack");
    snapshot::save(&ingp, &snap).unwrap();
    snapshot::save(&mp, &snap).unwrap();
    let (a, b) = (
        std::fs::metadata(&ingp).unwrap().len(),
        std::fs::metadata(&mp).unwrap().len(),
    );
    println!("16x2 aabb_scale 1: .ingp {a} bytes, .msgpack {b} bytes");
    assert!(b > 24_412_960 + 4_194_304);
    let info = snapshot::inspect(&ingp).unwrap();
    assert_eq!(info.n_params, 12_206_480);
    assert_eq!(info.grid_offset, 10_240);
    assert_eq!(info.dense_levels, vec![0, 1, 2, 3, 4]);
    let exe = env!("CARGO_BIN_EXE_stegongp");
    let out = std::process::Command::new(exe)
        .args(["inspect", ingp.to_str().unwrap(), "--json"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["n_params"], 12_206_480);
    assert_eq!(v["format"], "ingp (gzip msgpack)");
    // No cell above the threshold (every density ≤ 0), one cascade at aabb_scale 1.
    assert_eq!(v["occupied_per_cascade"], serde_json::json!([0.0]));
    let text = std::process::Command::new(exe)
        .args(["inspect", mp.to_str().unwrap()])
        .output()
        .unwrap();
    let t = String::from_utf8_lossy(&text.stdout);
    println!("{t}");
    assert!(t.contains("L=16 levels × F=2 features, T=2^19"));
    assert!(t.contains("occupied      0.0 % (per cascade)"));
    let bad = dir.path().join("x.ingp");
    std::fs::write(&bad, b"\x1f\x8bgarbage").unwrap();
    let e = std::process::Command::new(exe)
        .args(["inspect", bad.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(!e.status.success());
    assert!(String::from_utf8_lossy(&e.stderr).contains("x.ingp"));
}
