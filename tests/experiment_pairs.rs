//! `stegongp experiment pairs` on two tiny generated pairs sharing a cover: the report's
//! shape (Table 1, per-pair and stego-against-plain tables, image grids), a rerun that trains
//! nothing and reports the same numbers, and a pairs file naming a missing scene refused
//! before any training.

use std::path::Path;
use testkit::cli::{report_table as table, run_ok, stegongp};

fn synth(dir: &Path, scene: &str, seed: &str) {
    run_ok(&[
        "synth",
        "--scene",
        scene,
        "--out",
        dir.to_str().unwrap(),
        "--res",
        "40",
        "--train",
        "12",
        "--test",
        "2",
        "--seed",
        seed,
    ]);
}

fn report(dir: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(dir.join("pairs/report.json")).unwrap()).unwrap()
}

#[test]
fn two_pairs_report_and_a_rerun_trains_nothing() {
    let d = tempfile::tempdir().unwrap();
    let (cover, text, logo) = (
        d.path().join("cover"),
        d.path().join("text"),
        d.path().join("logo"),
    );
    synth(&cover, "object", "1");
    synth(&text, "text", "2");
    synth(&logo, "logo", "3");
    let pairs = d.path().join("pairs.json");
    std::fs::write(
        &pairs,
        r#"{"pairs": ["cover:text", {"cover": "cover", "hidden": "logo"}]}"#,
    )
    .unwrap();
    let out = d.path().join("out");
    let args = [
        "experiment",
        "pairs",
        "--pairs",
        pairs.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--steps",
        "12",
        "--batch",
        "2048",
        "--levels",
        "8",
        "--log2-t",
        "12",
        "--eval-views",
        "2",
        "--occupancy-fraction",
        "0.02",
    ];
    run_ok(&args);
    let r = report(&out);
    // One cover shared by both pairs: 1 plain cover + 2 plain hidden + 2 stego models.
    assert_eq!(r["setup"]["models_trained"], 5, "{}", r["setup"]);
    let t1 = table(&r, "Table 1");
    assert_eq!(t1.len(), 2);
    for row in t1 {
        for col in ["cover", "hidden"] {
            let p = row[format!("{col} PSNR")].as_f64().unwrap();
            let s = row[format!("{col} SSIM")].as_f64().unwrap();
            let l = row[format!("{col} LPIPS")].as_f64().unwrap();
            assert!(p > 5.0 && p < 100.0, "{row}");
            assert!(s > -1.0 && s <= 1.0, "{row}");
            assert!((0.0..2.0).contains(&l), "{row}");
        }
        assert_eq!(row["pairs"], 2);
    }
    assert_eq!(table(&r, "Per pair").len(), 8);
    let imp = table(&r, "Stego against plain");
    assert_eq!(imp.len(), 4);
    for f in [
        "report.md",
        "pair1_cover.png",
        "pair1_hidden.png",
        "pair2_hidden.png",
    ] {
        assert!(out.join("pairs").join(f).is_file(), "{f} missing");
    }
    let models: Vec<_> = std::fs::read_dir(out.join("pairs/models"))
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.path().extension().is_some_and(|x| x == "ingp"))
        .collect();
    assert_eq!(models.len(), 5);

    // The rerun loads every model and scores the same files the same way.
    let err = run_ok(&args);
    assert!(!err.contains("trained "), "a rerun trained: {err}");
    let r2 = report(&out);
    assert_eq!(r2["setup"]["models_trained"], 0);
    assert_eq!(r2["setup"]["models_reused"], 6);
    assert_eq!(table(&r2, "Table 1"), t1);
    assert_eq!(table(&r2, "Stego against plain"), imp);

    // A budget change is a different model: nothing stale is reused.
    let mut more = args.to_vec();
    more[7] = "13";
    let e = stegongp(&[&more[..2], &["--no-lpips"], &more[2..]].concat());
    assert!(e.status.success());
    assert_eq!(report(&out)["setup"]["models_trained"], 5);
}

#[test]
fn a_missing_scene_is_refused_before_training() {
    let d = tempfile::tempdir().unwrap();
    let pairs = d.path().join("pairs.json");
    std::fs::write(&pairs, r#"["nowhere_cover:nowhere_hidden"]"#).unwrap();
    let out = stegongp(&[
        "experiment",
        "pairs",
        "--pairs",
        pairs.to_str().unwrap(),
        "--out",
        d.path().join("o").to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("nowhere_cover"), "{err}");
    assert!(
        !d.path().join("o/pairs/models").exists()
            || std::fs::read_dir(d.path().join("o/pairs/models"))
                .unwrap()
                .next()
                .is_none()
    );
    let out = stegongp(&["experiment", "pairs", "--pair", "no-colon-here"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("COVER:HIDDEN"));
    let out = stegongp(&["experiment", "fidelity", "--minutes", "1"]);
    assert!(!out.status.success());
}
