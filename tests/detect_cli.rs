//! `stegongp detect` on a tiny trained model (readable and JSON output), and on files that
//! are not models: a clear error naming the file, a non-zero exit, no panic.

use std::path::Path;
use testkit::cli::{fails_naming, stdout_ok as ok, stegongp};

/// A model of a few seconds' training: 8 levels × 2, T = 2^12 (dense and hashed levels).
fn tiny_model(dir: &Path) -> std::path::PathBuf {
    let scene = dir.join("scene");
    let model = dir.join("tiny.ingp");
    ok(&stegongp(&[
        "synth",
        "--scene",
        "object",
        "--res",
        "16",
        "--train",
        "8",
        "--test",
        "1",
        "--out",
        scene.to_str().unwrap(),
    ]));
    ok(&stegongp(&[
        "train",
        scene.to_str().unwrap(),
        "--levels",
        "8",
        "--log2-t",
        "12",
        "--steps",
        "20",
        "--batch",
        "2048",
        "--occupancy-fraction",
        "0.01",
        // The reference's schedule: twenty steps of a budget would update so few cells that
        // the stored grid, mostly zeros, compresses past what the test expects of a file.
        "--occupancy-budget",
        "0",
        "--out",
        model.to_str().unwrap(),
    ]));
    model
}

#[test]
fn detect_reports_a_trained_model_and_refuses_what_is_not_one() {
    let d = tempfile::tempdir().unwrap();
    let model = tiny_model(d.path());
    let m = model.to_str().unwrap();

    let text = ok(&stegongp(&["detect", m]));
    println!("{text}");
    for want in [
        "tiny.ingp",
        "8×2 grid, T=2^12",
        "init %",
        "reach %",
        "unreach init %",
        "hashed",
        "dense",
        "density 0",
        "color 2",
        "loss",
        "optical thickness mean",
        "gzip header mtime 0",
        "score",
        "detector fitted on",
    ] {
        assert!(text.contains(want), "output lacks {want:?}");
    }
    // One row per level.
    let rows = text
        .lines()
        .filter(|l| l.contains(" dense ") || l.contains(" hashed "))
        .count();
    assert_eq!(rows, 8);

    let v: serde_json::Value =
        serde_json::from_str(&ok(&stegongp(&["detect", m, "--json"]))).expect("--json prints JSON");
    assert_eq!(v["n_levels"], 8);
    assert_eq!(v["format"], "ingp (gzip msgpack)");
    let levels = v["levels"].as_array().unwrap();
    assert_eq!(levels.len(), 8);
    for l in levels {
        let (r, u) = (
            l["reachable"]["count"].as_u64().unwrap(),
            l["unreachable"]["count"].as_u64().unwrap(),
        );
        assert_eq!(r + u, l["entries"].as_u64().unwrap());
        let f = l["init_frac"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&f));
    }
    // Twenty steps cannot have trained every entry of the finest levels' reach, nor left
    // the coarsest untouched.
    assert!(levels[0]["init_frac"].as_f64().unwrap() < 0.5);
    assert_eq!(v["mlp"].as_array().unwrap().len(), 5);
    assert_eq!(v["training_step"], 20);
    assert!(v["loss"].as_f64().unwrap() > 0.0);
    let ratio = v["compression"]["ratio"].as_f64().unwrap();
    assert!(ratio > 0.1 && ratio < 1.0, "{ratio}");
    assert!(v["features"]["init_frac_l7"].is_number());
    let (mean, max) = (
        v["grid_mean"].as_f64().unwrap(),
        v["grid_max"].as_f64().unwrap(),
    );
    assert!(mean > 0.0 && mean < max, "grid mean {mean}, max {max}");
    assert_eq!(
        v["features"]["grid_log10_max"].as_f64().unwrap(),
        max.log10()
    );
    let score = v["score"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&score));
    assert!(v["detector_fitted_on"].as_str().unwrap().len() > 3);

    // A detector file: a bad one is refused by name, a good one changes the score.
    let det = d.path().join("det.json");
    std::fs::write(&det, "{ not json").unwrap();
    fails_naming(
        &stegongp(&["detect", m, "--detector", det.to_str().unwrap()]),
        &["det.json"],
    );
    std::fs::write(
        &det,
        r#"{"fitted_on": "test", "classifier": "lr", "l2": 1.0, "bias": 3.0, "features": []}"#,
    )
    .unwrap();
    let v: serde_json::Value = serde_json::from_str(&ok(&stegongp(&[
        "detect",
        m,
        "--json",
        "--detector",
        det.to_str().unwrap(),
    ])))
    .unwrap();
    let want = 1.0 / (1.0 + (-3.0f64).exp());
    assert!((v["score"].as_f64().unwrap() - want).abs() < 1e-12);

    // Not models.
    let bytes = std::fs::read(&model).unwrap();
    let truncated = d.path().join("truncated.ingp");
    std::fs::write(&truncated, &bytes[..bytes.len() * 2 / 3]).unwrap();
    fails_naming(
        &stegongp(&["detect", truncated.to_str().unwrap()]),
        &["truncated.ingp", "gzip"],
    );
    let foreign = d.path().join("scene").join("transforms_train.json");
    fails_naming(
        &stegongp(&["detect", foreign.to_str().unwrap()]),
        &["transforms_train.json", "not an instant-ngp snapshot"],
    );
    let corrupt = d.path().join("corrupt.ingp");
    let mut c = bytes.clone();
    for b in &mut c[100..200] {
        *b ^= 0x5a;
    }
    std::fs::write(&corrupt, &c).unwrap();
    fails_naming(
        &stegongp(&["detect", corrupt.to_str().unwrap()]),
        &["corrupt.ingp"],
    );
    fails_naming(
        &stegongp(&["detect", d.path().join("missing.ingp").to_str().unwrap()]),
        &["missing.ingp"],
    );
}

/// A reader that stops early (`stegongp detect M | head`) ends the program quietly: no
/// panic from println! on the closed pipe. The read end is closed before the program has
/// loaded the model, so its first line already meets a closed pipe.
#[test]
fn a_closed_pipe_ends_detect_without_a_panic() {
    use std::process::{Command, Stdio};
    let d = tempfile::tempdir().unwrap();
    let model = tiny_model(d.path());
    let mut child = Command::new(env!("CARGO_BIN_EXE_stegongp"))
        .args(["detect", model.to_str().unwrap()])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("run stegongp");
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.contains("panicked"), "panic on a closed pipe: {err}");
    assert!(!out.status.success(), "the report cannot have been written");
}
