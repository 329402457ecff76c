//! `stegongp experiment`: a small partial-keys run writes its Markdown and JSON report and
//! its PNG grids, with a row per scheme and m, and the keys are reproducible from --seed.

use testkit::cli::{refused_before_writing, run_ok};

#[test]
fn partial_keys_report_and_figures() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().to_str().unwrap();
    // Tiny everything: 4 levels (so m = 4 only; 8 and 16 exceed the levels and are
    // skipped), T = 2^12, 24 px scenes, a few steps. Only the plumbing is under test here;
    // the numbers are benchmarks/stego.md's.
    let args = [
        "experiment",
        "partial-keys",
        "--out",
        out,
        "--res",
        "24",
        "--steps",
        "3",
        "--batch",
        "2048",
        "--eval-views",
        "1",
        "--levels",
        "4",
        "--log2-t",
        "12",
    ];
    run_ok(&args);
    let dir = d.path().join("partial-keys");
    let md = std::fs::read_to_string(dir.join("report.md")).unwrap();
    assert!(md.contains("Partial key disclosure"), "{md}");
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("report.json")).unwrap()).unwrap();
    let rows = json["tables"][0]["rows"].as_array().expect("rows");
    // primes m=4 (keys), prf m=4 (secret shares, level subkeys).
    assert_eq!(rows.len(), 3, "{rows:?}");
    for r in rows {
        assert_eq!(r["m"], 4);
        for col in [
            "0%",
            "25%",
            "50%",
            "75%",
            "100%",
            "wrong key",
            "empty render",
        ] {
            let v = r[col].as_f64().unwrap_or_else(|| panic!("{col} in {r}"));
            assert!(v.is_finite() && v > 0.0, "{col} = {v}");
        }
    }
    for png in [
        "partial_primes_keys_m4.png",
        "partial_prf_secret_shares_m4.png",
        "partial_prf_level_subkeys_m4.png",
    ] {
        let bytes = std::fs::read(dir.join(png)).unwrap_or_else(|e| panic!("{png}: {e}"));
        assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
    }
    // Same seed, same keys, same training: the same report numbers.
    let again = tempfile::tempdir().unwrap();
    let mut args2 = args;
    args2[3] = again.path().to_str().unwrap();
    run_ok(&args2);
    let json2: serde_json::Value = serde_json::from_slice(
        &std::fs::read(again.path().join("partial-keys/report.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(json["tables"], json2["tables"]);
}

/// `--cover-only-mlp` changes stealth training: without `--stealth` (outside detectability)
/// or with detectability's stealth arm left out, it is refused before anything is written.
#[test]
fn cover_only_mlp_without_stealth_is_refused() {
    let d = tempfile::tempdir().unwrap();
    let out_dir = d.path().join("out");
    let out = out_dir.to_str().unwrap();
    for (args, says) in [
        (
            vec!["experiment", "fidelity", "--cover-only-mlp", "--out", out],
            "--stealth",
        ),
        (
            vec![
                "experiment",
                "detectability",
                "--cover-only-mlp",
                "--no-stealth-arm",
                "--out",
                out,
            ],
            "--no-stealth-arm",
        ),
    ] {
        refused_before_writing(&args, says, &out_dir);
    }
}

/// `--hidden-from` must leave the hidden scenes steps to train, and means nothing to an
/// experiment that trains no model; `--hidden-weight` must be positive: refused before
/// anything is written.
#[test]
fn hidden_from_is_checked_before_anything_is_written() {
    let d = tempfile::tempdir().unwrap();
    let out_dir = d.path().join("out");
    let out = out_dir.to_str().unwrap();
    for (args, says) in [
        (
            vec![
                "experiment",
                "fidelity",
                "--hidden-from",
                "300",
                "--out",
                out,
            ],
            "300 training steps",
        ),
        (
            vec![
                "experiment",
                "multi-hidden",
                "--steps",
                "20",
                "--hidden-from",
                "25",
                "--out",
                out,
            ],
            "--hidden-from 25",
        ),
        (
            vec![
                "experiment",
                "key-strength",
                "--hidden-from",
                "5",
                "--out",
                out,
            ],
            "key-strength",
        ),
        (
            vec![
                "experiment",
                "fidelity",
                "--hidden-weight",
                "0",
                "--out",
                out,
            ],
            "--hidden-weight",
        ),
    ] {
        refused_before_writing(&args, says, &out_dir);
    }
}

/// `--density-cap` changes stealth training only: refused without stealth models to train
/// and when not a number ≥ 0, before anything is written.
#[test]
fn density_cap_is_checked_before_anything_is_written() {
    let d = tempfile::tempdir().unwrap();
    let out_dir = d.path().join("out");
    let out = out_dir.to_str().unwrap();
    for (args, says) in [
        (
            vec![
                "experiment",
                "fidelity",
                "--density-cap",
                "10",
                "--out",
                out,
            ],
            "--stealth",
        ),
        (
            vec![
                "experiment",
                "detectability",
                "--no-stealth-arm",
                "--density-cap",
                "10",
                "--out",
                out,
            ],
            "--no-stealth-arm",
        ),
        (
            vec![
                "experiment",
                "fidelity",
                "--stealth",
                "--density-cap=-2",
                "--out",
                out,
            ],
            "≥ 0",
        ),
    ] {
        refused_before_writing(&args, says, &out_dir);
    }
}
