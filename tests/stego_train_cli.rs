//! `stegongp train --hidden`: each scene is trained at its own resolution (the cover's
//! `--downscale` does not shrink the hidden scenes), and the key opens the hidden scene.

use std::process::{Command, Output};

fn stegongp(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_stegongp"))
        .args(args)
        .output()
        .expect("run stegongp")
}

fn ok(out: Output) -> String {
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(out.status.success(), "stegongp failed: {err}");
    err
}

#[test]
fn cover_downscale_leaves_hidden_scenes_at_their_resolution() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_str().unwrap().to_string();
    let (cover, text, key, model) = (p("cover"), p("text"), p("k.json"), p("m.ingp"));
    for (scene, dir) in [("object", &cover), ("text", &text)] {
        ok(stegongp(&[
            "synth", "--scene", scene, "--res", "32", "--train", "4", "--test", "1", "--out", dir,
        ]));
    }
    ok(stegongp(&["keygen", "--scheme", "prf", "--out", &key]));
    let log = ok(stegongp(&[
        "train",
        &cover,
        "--downscale",
        "2",
        "--hidden",
        &text,
        "--key",
        &key,
        "--steps",
        "2",
        "--batch",
        "2048",
        "--log2-t",
        "14",
        "--out",
        &model,
    ]));
    assert!(log.contains("cover: 4 images of 16×16"), "{log}");
    assert!(log.contains("hidden: 4 images of 32×32"), "{log}");
    let log = ok(stegongp(&[
        "train",
        &cover,
        "--hidden",
        &text,
        "--key",
        &key,
        "--hidden-downscale",
        "4",
        "--steps",
        "1",
        "--batch",
        "2048",
        "--log2-t",
        "14",
        "--out",
        &model,
    ]));
    assert!(log.contains("cover: 4 images of 32×32"), "{log}");
    assert!(log.contains("hidden: 4 images of 8×8"), "{log}");
}
