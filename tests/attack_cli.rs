//! `stegongp attack`: bad input refused with nothing written, and on small trained models
//! the free removal measured as an analyst would run it: `purify` leaves every cover pixel
//! as it was, erases part of a default hidden scene, and leaves a `--robust` one whole.

use serde_json::Value;
use std::path::Path;
use testkit::cli::{fails_naming, ok, stdout_ok, stegongp};

fn p(d: &Path, n: &str) -> String {
    d.join(n).to_str().unwrap().to_string()
}

/// A generated object cover and text at 32 px, (cover, text).
fn scenes(d: &Path) -> (String, String) {
    let (cover, text) = (p(d, "cover"), p(d, "text"));
    for (scene, dir) in [("object", &cover), ("text", &text)] {
        ok(&stegongp(&[
            "synth", "--scene", scene, "--res", "32", "--train", "12", "--test", "3", "--out", dir,
        ]));
    }
    (cover, text)
}

/// Trains a model of `cover` (with `text` under a fresh key when `hidden`), `extra` options.
fn train(
    d: &Path,
    name: &str,
    cover: &str,
    hidden: Option<(&str, &str)>,
    extra: &[&str],
    steps: &str,
) -> String {
    let model = p(d, &format!("{name}.ingp"));
    let mut args = vec![
        "train", cover, "--steps", steps, "--batch", "4096", "--log2-t", "14", "--out", &model,
    ];
    if let Some((text, key)) = hidden {
        args.extend(["--hidden", text, "--key", key]);
    }
    args.extend(extra);
    ok(&stegongp(&args));
    model
}

/// `eval --json`'s PSNR of `model` on `data` (with `key`).
fn psnr(model: &str, data: &str, key: Option<&str>) -> f64 {
    let mut args = vec![
        "eval",
        "--model",
        model,
        "--data",
        data,
        "--no-lpips",
        "--json",
    ];
    if let Some(k) = key {
        args.extend(["--key", k]);
    }
    let v: Value = serde_json::from_str(&stdout_ok(&stegongp(&args))).unwrap();
    v["psnr"].as_f64().unwrap()
}

#[test]
fn bad_attacks_and_files_are_refused_before_anything_is_written() {
    let d = tempfile::tempdir().unwrap();
    let (cover, _) = scenes(d.path());
    let model = train(d.path(), "m", &cover, None, &[], "2");
    let out = p(d.path(), "attacked.ingp");
    for (attack, says) in [
        ("blur=3", "unknown attack"),
        ("noise=-0.1", "≥ 0"),
        ("noise=x", "not a number"),
        ("prune=1.5", "between 0 and 1"),
        ("prune-magnitude=-0.2", "between 0 and 1"),
        ("quantise=3", "8 or 4"),
        ("finetune=0", "step count"),
        ("finetune=10", "--data"),
    ] {
        fails_naming(
            &stegongp(&["attack", &model, "--out", &out, attack]),
            &[says],
        );
        assert!(!Path::new(&out).exists(), "{attack} wrote its output");
    }
    let junk = p(d.path(), "junk.ingp");
    std::fs::write(&junk, b"not a snapshot at all").unwrap();
    fails_naming(
        &stegongp(&["attack", &junk, "--out", &out, "purify"]),
        &["junk.ingp"],
    );
    fails_naming(
        &stegongp(&["attack", &model, "--out", &model, "purify"]),
        &["--out is the model"],
    );
    fails_naming(
        &stegongp(&["attack", &model, "--out", &p(d.path(), "a.png"), "purify"]),
        &[".ingp"],
    );
    fails_naming(
        &stegongp(&[
            "attack",
            &model,
            "--out",
            &out,
            "finetune=3",
            "--data",
            &p(d.path(), "nowhere"),
        ]),
        &["nowhere"],
    );
    fails_naming(&stegongp(&["attack", &model, "--out", &out]), &["ATTACK"]);
    assert!(!Path::new(&out).exists());
    // A chain, as JSON: what each attack did.
    let v: Value = serde_json::from_str(&stdout_ok(&stegongp(&[
        "attack",
        &model,
        "--out",
        &out,
        "noise=0.001",
        "prune=0.1",
        "quantise=8",
        "--json",
        "--seed",
        "3",
    ])))
    .unwrap();
    let attacks = v["attacks"].as_array().unwrap();
    assert_eq!(attacks.len(), 3);
    assert_eq!(attacks[1]["attack"], "prune=0.1");
    let total = attacks[1]["entries_total"].as_u64().unwrap();
    let pruned = attacks[1]["entries_changed"].as_u64().unwrap();
    assert_eq!(pruned, (total as f64 * 0.1).round() as u64);
    // The result is a model every tool reads.
    ok(&stegongp(&["inspect", &out]));
    // Deterministic for a seed.
    let again = p(d.path(), "again.ingp");
    ok(&stegongp(&[
        "attack",
        &model,
        "--out",
        &again,
        "noise=0.001",
        "prune=0.1",
        "quantise=8",
        "--seed",
        "3",
    ]));
    assert_eq!(std::fs::read(&out).unwrap(), std::fs::read(&again).unwrap());
}

#[test]
fn purify_is_free_for_the_cover_erases_a_default_hidden_scene_and_not_a_robust_one() {
    let d = tempfile::tempdir().unwrap();
    let (cover, text) = scenes(d.path());
    let (key, robust_key) = (p(d.path(), "k.json"), p(d.path(), "robust.json"));
    ok(&stegongp(&["keygen", "--out", &key]));
    ok(&stegongp(&["keygen", "--out", &robust_key]));
    let default = train(d.path(), "default", &cover, Some((&text, &key)), &[], "200");
    let robust = train(
        d.path(),
        "robust",
        &cover,
        Some((&text, &robust_key)),
        &["--robust"],
        "250",
    );
    // train --robust recorded the mode in the key file, which stays owner-only.
    let kf: Value = serde_json::from_slice(&std::fs::read(&robust_key).unwrap()).unwrap();
    assert_eq!(kf["robust"], true, "{kf}");
    use std::os::unix::fs::PermissionsExt;
    assert_eq!(
        std::fs::metadata(&robust_key).unwrap().permissions().mode() & 0o777,
        0o600
    );
    // A key that does not record it is refused for a robust training and the reverse.
    fails_naming(
        &stegongp(&[
            "train",
            &cover,
            "--hidden",
            &text,
            "--key",
            &robust_key,
            "--steps",
            "1",
            "--out",
            &p(d.path(), "x.ingp"),
        ]),
        &["robust"],
    );
    let mut rows = Vec::new();
    for (model, k) in [(&default, &key), (&robust, &robust_key)] {
        let purified = model.replace(".ingp", ".purified.ingp");
        ok(&stegongp(&["attack", model, "--out", &purified, "purify"]));
        let (c0, c1) = (psnr(model, &cover, None), psnr(&purified, &cover, None));
        let (h0, h1) = (psnr(model, &text, Some(k)), psnr(&purified, &text, Some(k)));
        assert_eq!(
            c0.to_bits(),
            c1.to_bits(),
            "{model}: the cover moved ({c0} → {c1})"
        );
        rows.push((h0, h1));
        eprintln!("{model}: cover {c0:.3} dB; hidden {h0:.3} → {h1:.3} dB");
    }
    let ((d0, d1), (r0, r1)) = (rows[0], rows[1]);
    assert!(
        d0 - d1 > 1.0,
        "purify should erase part of a default hidden scene: {d0} → {d1}"
    );
    assert_eq!(
        r0.to_bits(),
        r1.to_bits(),
        "a robust hidden scene moved: {r0} → {r1}"
    );
    assert!(
        r0 > psnr(&robust, &text, None) + 1.0,
        "the robust hidden scene trained ({r0})"
    );
}
