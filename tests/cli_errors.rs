//! Bad input through the command line: a clear message naming the file or option, a
//! non-zero exit, no panic, nothing half-written.

use std::path::Path;
use testkit::cli::{fails_naming as fails_with, stegongp};

fn write(p: &Path, s: &str) {
    std::fs::create_dir_all(p.parent().unwrap()).unwrap();
    std::fs::write(p, s).unwrap();
}

#[test]
fn train_rejects_bad_datasets_without_writing_a_model() {
    let d = tempfile::tempdir().unwrap();
    let model = d.path().join("m.ingp");
    let m = model.to_str().unwrap();
    // Missing directory.
    let missing = d.path().join("nope");
    fails_with(
        &stegongp(&[
            "train",
            missing.to_str().unwrap(),
            "--out",
            m,
            "--steps",
            "1",
        ]),
        &["nope"],
    );
    // Malformed JSON.
    let bad = d.path().join("bad");
    write(
        &bad.join("transforms_train.json"),
        "{ \"camera_angle_x\": 0.5, \"frames\": [ ",
    );
    fails_with(
        &stegongp(&["train", bad.to_str().unwrap(), "--out", m, "--steps", "1"]),
        &["transforms_train.json"],
    );
    // Zero frames.
    let empty = d.path().join("empty");
    write(
        &empty.join("transforms_train.json"),
        "{ \"camera_angle_x\": 0.5, \"frames\": [] }",
    );
    fails_with(
        &stegongp(&["train", empty.to_str().unwrap(), "--out", m, "--steps", "1"]),
        &["transforms_train.json"],
    );
    // Missing image.
    let noimg = d.path().join("noimg");
    write(
        &noimg.join("transforms_train.json"),
        r#"{ "camera_angle_x": 0.5, "frames": [ { "file_path": "./train/r_0",
            "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]] } ] }"#,
    );
    fails_with(
        &stegongp(&["train", noimg.to_str().unwrap(), "--out", m, "--steps", "1"]),
        &["r_0"],
    );
    // NaN pose (JSON has no NaN literal; a string where a number belongs is the same error class).
    let nan = d.path().join("nan");
    write(
        &nan.join("transforms_train.json"),
        r#"{ "camera_angle_x": 0.5, "frames": [ { "file_path": "./train/r_0",
            "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,"x"],[0,0,0,1]] } ] }"#,
    );
    fails_with(
        &stegongp(&["train", nan.to_str().unwrap(), "--out", m, "--steps", "1"]),
        &["transforms_train.json"],
    );
    // Non-rigid pose.
    let shear = d.path().join("shear");
    write(
        &shear.join("transforms_train.json"),
        r#"{ "camera_angle_x": 0.5, "frames": [ { "file_path": "./train/r_0",
            "transform_matrix": [[2,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]] } ] }"#,
    );
    fails_with(
        &stegongp(&["train", shear.to_str().unwrap(), "--out", m, "--steps", "1"]),
        &["transforms_train.json"],
    );
    assert!(!model.exists(), "no model may be written on failure");
    // Wrong model extension is refused before any work.
    fails_with(
        &stegongp(&["train", bad.to_str().unwrap(), "--out", "x.bin"]),
        &["x.bin"],
    );
    // A key without a hidden scene.
    fails_with(
        &stegongp(&[
            "train",
            bad.to_str().unwrap(),
            "--out",
            m,
            "--key",
            "k.json",
        ]),
        &["--key"],
    );
    assert_eq!(
        std::fs::read_dir(d.path())
            .unwrap()
            .filter(|e| e.as_ref().unwrap().path().is_file())
            .count(),
        0
    );
}

/// A worker count or a table the machine cannot hold is refused before anything is
/// allocated, with the reason: `--workers 100000` was an out-of-memory kill (exit 137)
/// part-way through allocating 100 000 gradient buffers of 49 MB.
#[test]
fn training_larger_than_memory_is_refused_up_front() {
    let d = tempfile::tempdir().unwrap();
    let scene = d.path().join("obj");
    testkit::cli::synth(&scene, "object", 16, 2);
    let (s, m) = (scene.to_str().unwrap(), d.path().join("m.ingp"));
    let m = m.to_str().unwrap();
    let common = ["train", s, "--out", m, "--steps", "1", "--device", "cpu"];
    let out = stegongp(&[&common[..], &["--workers", "100000"]].concat());
    fails_with(&out, &["100000 workers", "at most 256"]);
    // 2^26 entries a level, 256 workers: terabytes, whatever the machine.
    let out = stegongp(&[&common[..], &["--workers", "256", "--log2-t", "26"]].concat());
    fails_with(&out, &["GB", "--workers", "--log2-t"]);
    assert!(!Path::new(m).exists());
}

#[test]
fn unknown_option_values_are_refused() {
    let out = stegongp(&[
        "eval",
        "--model",
        "m.ingp",
        "--data",
        ".",
        "--background",
        "pink",
    ]);
    fails_with(&out, &["pink"]);
    let out = stegongp(&[
        "eval",
        "--model",
        "m.ingp",
        "--data",
        ".",
        "--protocol",
        "nerf",
    ]);
    fails_with(&out, &["nerf", "instant-ngp"]);
    // instant-ngp's protocol is black's: white is refused before the (absent) model loads.
    let out = stegongp(&[
        "eval",
        "--model",
        "m.ingp",
        "--data",
        ".",
        "--protocol",
        "instant-ngp",
        "--background",
        "white",
    ]);
    fails_with(&out, &["--protocol instant-ngp scores on black"]);
    let out = stegongp(&["synth", "--scene", "castle", "--out", "x"]);
    fails_with(&out, &["castle"]);
    let out = stegongp(&["keygen", "--scheme", "rot13", "--out", "k"]);
    fails_with(&out, &["rot13"]);
    // A room's camera and furniture are the room's alone.
    let d = tempfile::tempdir().unwrap();
    let x = d.path().join("x");
    let out = stegongp(&[
        "synth",
        "--scene",
        "object",
        "--furnished",
        "--out",
        x.to_str().unwrap(),
    ]);
    fails_with(&out, &["--furnished", "room"]);
    let out = stegongp(&[
        "synth",
        "--scene",
        "room",
        "--aabb-scale",
        "16",
        "--height",
        "3",
        "--out",
        x.to_str().unwrap(),
    ]);
    fails_with(&out, &["height 3"]);
    assert!(!x.join("transforms.json").exists());
}

#[test]
fn unreadable_model_files_name_the_file() {
    let d = tempfile::tempdir().unwrap();
    let data = d.path().join("data");
    std::fs::create_dir_all(&data).unwrap();
    for (name, bytes) in [
        ("empty.ingp", Vec::new()),
        (
            "noise.ingp",
            (0..4000u32)
                .map(|i| ((i * 2654435761u32) >> 13) as u8)
                .collect(),
        ),
        ("truncated.ingp", vec![0x1f, 0x8b, 8, 0, 0, 0]),
        ("foreign.msgpack", vec![0x93, 1, 2, 3]),
    ] {
        let p = d.path().join(name);
        std::fs::write(&p, bytes).unwrap();
        for cmd in ["eval", "render"] {
            let mut args = vec![
                cmd,
                "--model",
                p.to_str().unwrap(),
                "--data",
                data.to_str().unwrap(),
            ];
            if cmd == "render" {
                args.extend(["--out", "/nonexistent/should-not-be-created"]);
            }
            fails_with(&stegongp(&args), &[name]);
        }
        fails_with(&stegongp(&["inspect", p.to_str().unwrap()]), &[name]);
    }
    assert!(!Path::new("/nonexistent/should-not-be-created").exists());
}
