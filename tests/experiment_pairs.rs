//! `stegongp experiment pairs` on two tiny generated pairs sharing a cover: the report's
//! shape (Table 1, per-pair and stego-against-plain tables, image grids), a rerun that trains
//! nothing and reports the same numbers, and a pairs file naming a missing scene refused
//! before any training; an experiment killed inside a model goes on inside it.
// A test reads as one story; the 120-line limit (clippy.toml) is the program's.
#![allow(clippy::too_many_lines)]

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
    assert_eq!(t1.len(), 3);
    for row in t1 {
        for col in ["cover", "hidden"] {
            if col == "cover"
                && row["method"]
                    .as_str()
                    .unwrap()
                    .contains("key holder's grid")
            {
                // Only hidden scenes are seen through a rebuilt grid.
                assert!(row["cover PSNR"].is_null(), "{row}");
                continue;
            }
            let p = row[format!("{col} PSNR")].as_f64().unwrap();
            let s = row[format!("{col} SSIM")].as_f64().unwrap();
            let l = row[format!("{col} LPIPS")].as_f64().unwrap();
            assert!(p > 5.0 && p < 100.0, "{row}");
            assert!(s > -1.0 && s <= 1.0, "{row}");
            assert!((0.0..2.0).contains(&l), "{row}");
        }
        assert_eq!(row["pairs"], 2);
    }
    let per_pair = table(&r, "Per pair");
    assert_eq!(per_pair.len(), 10);
    // The plain hidden model through a key holder's grid is what `eval --rebuild-grid`
    // scores on the same views with the same seed.
    let row = |scene: &str| {
        per_pair
            .iter()
            .find(|r| r["pair"] == "cover : text" && r["scene"] == scene)
            .unwrap_or_else(|| panic!("no row {scene}"))
    };
    let plain_text = std::fs::read_dir(out.join("pairs/models"))
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .find(|p| {
            let name = p.file_name().unwrap().to_str().unwrap();
            name.starts_with("plain-text-") && name.ends_with(".ingp")
        })
        .expect("the plain text model");
    let eval = |extra: &[&str]| -> f64 {
        let mut a = vec![
            "eval",
            "--model",
            plain_text.to_str().unwrap(),
            "--data",
            text.to_str().unwrap(),
            "--no-lpips",
            "--json",
        ];
        a.extend_from_slice(extra);
        let o = stegongp(&a);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        serde_json::from_slice::<serde_json::Value>(&o.stdout).unwrap()["psnr"]
            .as_f64()
            .unwrap()
    };
    let near = |a: f64, b: &serde_json::Value| (a - b.as_f64().unwrap()).abs() < 1e-3;
    let rebuilt = row("hidden, plain, key holder's grid");
    assert!(
        near(eval(&["--rebuild-grid"]), &rebuilt["PSNR"]),
        "{rebuilt}"
    );
    assert!(near(eval(&[]), &row("hidden, plain")["PSNR"]));
    let middle = &t1[1];
    let other = per_pair
        .iter()
        .find(|r| r["pair"] == "cover : logo" && r["scene"] == "hidden, plain, key holder's grid")
        .unwrap()["PSNR"]
        .as_f64()
        .unwrap();
    // Rounded to 1e-3 in the rows and in the table.
    let mean = (rebuilt["PSNR"].as_f64().unwrap() + other) / 2.0;
    assert!(
        (mean - middle["hidden PSNR"].as_f64().unwrap()).abs() < 2e-3,
        "{middle}"
    );
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

/// An experiment killed (-9) inside a model goes on inside it when rerun: the model's state
/// (`MODEL.ingp.state`, owner-only) is taken back, the models written are those of a run
/// that was never interrupted, byte for byte, and no state is left behind.
#[test]
fn a_killed_experiment_resumes_inside_the_model_it_was_training() {
    use std::os::unix::fs::PermissionsExt;
    use std::process::Stdio;
    use std::time::{Duration, Instant};
    let d = tempfile::tempdir().unwrap();
    let (cover, text) = (d.path().join("cover"), d.path().join("text"));
    synth(&cover, "object", "1");
    synth(&text, "text", "2");
    let pair = format!("{}:{}", cover.display(), text.display());
    let args = |out: &Path| -> Vec<String> {
        [
            "experiment",
            "pairs",
            "--pair",
            &pair,
            "--out",
            out.to_str().unwrap(),
            "--steps",
            "30",
            "--batch",
            "2048",
            "--levels",
            "8",
            "--log2-t",
            "12",
            "--eval-views",
            "1",
            "--occupancy-fraction",
            "0.02",
            "--no-lpips",
            "--save-every",
            "5",
        ]
        .map(String::from)
        .to_vec()
    };
    let models = |out: &Path, ext: &str| -> Vec<(String, Vec<u8>)> {
        let dir = out.join("pairs/models");
        let mut v: Vec<_> = std::fs::read_dir(&dir)
            .map(|r| r.filter_map(|e| e.ok()).map(|e| e.path()).collect())
            .unwrap_or_else(|_| Vec::new())
            .into_iter()
            .filter(|p: &std::path::PathBuf| p.to_string_lossy().ends_with(ext))
            .map(|p| {
                let name = p.file_name().unwrap().to_string_lossy().into_owned();
                (name, std::fs::read(&p).unwrap_or_default())
            })
            .collect();
        v.sort();
        v
    };
    let whole = d.path().join("whole");
    let a: Vec<String> = args(&whole);
    run_ok(&a.iter().map(String::as_str).collect::<Vec<_>>());
    assert_eq!(models(&whole, ".ingp").len(), 3);
    assert!(
        models(&whole, ".state").is_empty(),
        "a state was left behind"
    );

    // Killed once the first model has saved a state (the first of 6 during its 30 steps).
    let part = d.path().join("part");
    let mut child = std::process::Command::new(testkit::cli::bin())
        .args(args(&part))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    let state = loop {
        if let Some((name, _)) = models(&part, ".state").into_iter().next() {
            break part.join("pairs/models").join(name);
        }
        assert!(t0.elapsed() < Duration::from_secs(120), "no state appeared");
        assert!(
            child.try_wait().unwrap().is_none(),
            "finished before a state"
        );
        std::thread::sleep(Duration::from_millis(5));
    };
    child.kill().unwrap();
    child.wait().unwrap();
    let mode = std::fs::metadata(&state).unwrap().permissions().mode() & 0o777;
    assert_eq!(mode, 0o600, "a model's state is owner-only");
    let p: Vec<String> = args(&part);
    let err = run_ok(&p.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(err.contains("resumed") && err.contains(".state"), "{err}");
    assert!(
        models(&part, ".state").is_empty(),
        "a state was left behind"
    );
    let (w, r) = (models(&whole, ".ingp"), models(&part, ".ingp"));
    assert_eq!(
        w.iter().map(|m| &m.0).collect::<Vec<_>>(),
        r.iter().map(|m| &m.0).collect::<Vec<_>>()
    );
    for ((name, a), (_, b)) in w.iter().zip(&r) {
        assert!(a == b, "{name}: the resumed experiment wrote another model");
    }
}
