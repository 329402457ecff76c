//! `stegongp process` through the real ffmpeg and COLMAP: a generated room photographed
//! from known cameras along an arc, as photos and as an H.264 video made by our own
//! encoder. Every image must be registered, the recovered poses must equal the known ones
//! up to a similarity (rotation error under a degree, position error a small fraction of
//! the cameras' distance), and a model trained on the result must reach a PSNR on its
//! held-out views. Then the errors a user meets, most of them without COLMAP (a stand-in
//! script plays a crashing one). The tests that need colmap or ffmpeg skip without them
//! and fail when CI=true (`.ci/run` installs both).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use stegongp::dataset::colmap::read_model;
use stegongp::viewer::frame::Rgb8;
use stegongp::viewer::video::Mp4Video;
use testkit::capture::{Arc, Pose, PoseErrors, pose_errors, room_arc, write_png};
use testkit::cli::{fails_naming, ok, stegongp};

/// Photos of the photo test: every pair is matched, so their count costs quadratically.
const PHOTOS: usize = 16;
/// Training steps of the photo test.
const STEPS: &str = "250";

/// Views of a phone's 3:2 frame and 65° field of view over a third of a circle, small
/// enough for CI. The room is grained: its flat colours alone give SIFT too few features
/// to register small views (14 of 24 without, every one with).
fn arc(views: usize) -> Arc {
    Arc {
        views,
        width: 320,
        height: 214,
        fov_deg: 65.0,
        arc_deg: 120.0,
        grain: 0.8,
    }
}

fn have(program: &str, arg: &str) -> bool {
    Command::new(program).arg(arg).output().is_ok()
}

fn model_errors(cap: &Path, known: &HashMap<String, Pose>) -> PoseErrors {
    pose_errors(&cap.join("sparse/0"), known)
}

fn summary(out: &std::process::Output) -> serde_json::Value {
    ok(out);
    serde_json::from_slice(&out.stdout).expect("process --json")
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn photos_of_a_generated_room_are_posed_and_train() {
    if !have("colmap", "-h") {
        return testkit::missing("colmap", "apt-get install colmap");
    }
    let t = tempfile::tempdir().unwrap();
    let photos = t.path().join("photos");
    std::fs::create_dir(&photos).unwrap();
    let a = arc(PHOTOS);
    let (frames, poses, _) = room_arc(&a);
    let mut known = HashMap::new();
    for (i, (f, p)) in frames.iter().zip(&poses).enumerate() {
        let name = format!("view_{i:02}.png");
        write_png(&photos.join(&name), a.width, a.height, f);
        known.insert(name, *p);
    }
    let cap = t.path().join("cap");
    let t0 = std::time::Instant::now();
    let out = stegongp(&[
        "process",
        s(&photos),
        "--out",
        s(&cap),
        "--max-features",
        "1024",
        "--json",
    ]);
    let sum = summary(&out);
    testkit::golden::assert_json_shape("process", &sum);
    eprintln!(
        "photos: process {:.1} s ({})",
        t0.elapsed().as_secs_f64(),
        sum["seconds"]
    );
    assert_eq!(sum["frames"], PHOTOS, "{sum}");
    assert_eq!(sum["registered"], PHOTOS, "{sum}");
    assert_eq!(sum["matcher"], "exhaustive", "{sum}");
    assert!(
        sum["mean_reprojection_error_px"].as_f64().unwrap() < 1.0,
        "{sum}"
    );
    let e = model_errors(&cap, &known);
    eprintln!("photos: {e:?}");
    assert!(e.max_rotation_deg < 1.0 && e.max_position < 0.02, "{e:?}");
    for f in [
        "colmap.log",
        "process.json",
        "images/view_00.png",
        "sparse/0/images.bin",
    ] {
        assert!(cap.join(f).is_file(), "{f}");
    }
    assert!(!cap.join("database.db").exists());
    let log = std::fs::read_to_string(cap.join("colmap.log")).unwrap();
    assert!(
        log.contains("== colmap exhaustive_matcher") && log.contains("use_gpu 0"),
        "{log}"
    );

    // `train` reads the folder with its default options.
    let model = t.path().join("m.ingp");
    let t0 = std::time::Instant::now();
    // A small table and batch keep CI's two cores to seconds (the defaults take minutes).
    ok(&stegongp(&[
        "train",
        s(&cap),
        "--out",
        s(&model),
        "--steps",
        STEPS,
        "--batch",
        "8192",
        "--log2-t",
        "15",
        "--device",
        "cpu",
    ]));
    let t1 = std::time::Instant::now();
    let ev = stegongp(&[
        "eval",
        "--model",
        s(&model),
        "--data",
        s(&cap),
        "--downscale",
        "2",
        "--no-lpips",
        "--device",
        "cpu",
        "--json",
    ]);
    let ev: serde_json::Value = serde_json::from_slice(&ok_stdout(&ev)).unwrap();
    let (psnr, blank) = (
        ev["psnr"].as_f64().unwrap(),
        ev["blank_psnr"].as_f64().unwrap(),
    );
    eprintln!(
        "photos: held-out PSNR {psnr:.2} dB after {STEPS} steps (an empty render: {blank:.2}); \
         train {:.1} s, eval {:.1} s",
        (t1 - t0).as_secs_f64(),
        t1.elapsed().as_secs_f64()
    );
    // Measured 16.5–17.0 dB (16 photos, 250 steps) in 17 runs here, 730–790 samples a ray.
    // COLMAP 3.8 poses and self-calibrates differently from run to run, even on one thread
    // (sparse/0 differs byte for byte), and nothing refines cameras yet (issue 66): one CI
    // run's capture trained to 13.70 dB with a far emptier grid (130 samples a ray). The
    // floor keeps that apart from a broken pipeline, which scores near the empty render's
    // 5.2 dB.
    assert!(psnr > 12.5, "{ev}");
}

fn ok_stdout(out: &std::process::Output) -> Vec<u8> {
    ok(out);
    out.stdout.clone()
}

#[test]
fn a_video_of_a_generated_room_goes_through_the_video_path() {
    if !have("colmap", "-h") || !have("ffmpeg", "-version") {
        return testkit::missing("colmap or ffmpeg", "apt-get install colmap ffmpeg");
    }
    let t = tempfile::tempdir().unwrap();
    let a = arc(30);
    let (frames, poses, _) = room_arc(&a);
    let clip = t.path().join("clip.mp4");
    let mut v = Mp4Video::create(&clip, a.width, a.height, 10).unwrap();
    for f in frames {
        v.push(&Rgb8 {
            width: a.width,
            height: a.height,
            data: f,
        })
        .unwrap();
    }
    v.finish().unwrap();
    let cap = t.path().join("cap");
    let out = stegongp(&[
        "process",
        s(&clip),
        "--out",
        s(&cap),
        "--frames",
        "12",
        "--max-features",
        "1024",
        "--json",
        "--transforms",
    ]);
    let sum = summary(&out);
    assert_eq!(sum["kind"], "video", "{sum}");
    assert_eq!(sum["video"]["frames"], 30, "{sum}");
    assert_eq!(sum["frames"], 12, "{sum}");
    assert_eq!(sum["matcher"], "sequential", "{sum}");
    assert_eq!(sum["registered"], 12, "{sum}");
    // Each frame is named after its index in the clip, one from each stretch of 2–3.
    let known: HashMap<String, Pose> = (0..poses.len())
        .map(|i| (format!("frame_{i:06}.png"), poses[i]))
        .collect();
    let names: Vec<String> = read_model(&cap.join("sparse/0"))
        .unwrap()
        .images
        .into_iter()
        .map(|i| i.name)
        .collect();
    assert!(names.iter().all(|n| known.contains_key(n)), "{names:?}");
    let e = model_errors(&cap, &known);
    eprintln!("video: {e:?}");
    // Looser than the photos': 12 frames 11° apart through a lossy codec, matched only to
    // their neighbours (measured 0.7°, 0.8 %). What this checks is that every frame is the
    // one its name says.
    assert!(e.max_rotation_deg < 2.0 && e.max_position < 0.05, "{e:?}");
    // --transforms writes what `convert` writes for the folder.
    let conv = t.path().join("convert.json");
    ok(&stegongp(&["convert", s(&cap), "--out", s(&conv)]));
    let a: serde_json::Value =
        serde_json::from_slice(&std::fs::read(cap.join("transforms.json")).unwrap()).unwrap();
    let b: serde_json::Value = serde_json::from_slice(&std::fs::read(&conv).unwrap()).unwrap();
    assert_eq!(a["frames"].as_array().unwrap().len(), 12);
    assert_eq!(
        a["frames"][3]["transform_matrix"],
        b["frames"][3]["transform_matrix"]
    );
}

/// A stand-in for colmap: says it is COLMAP 3.8, lists 3.8's option names, and crashes in
/// feature extraction as a broken installation would.
fn crashing_colmap(dir: &Path) -> PathBuf {
    let p = dir.join("colmap");
    std::fs::write(
        &p,
        "#!/bin/sh\n\
         if [ \"$1\" = \"-h\" ]; then echo 'COLMAP 3.8 -- Structure-from-Motion'; exit 0; fi\n\
         if [ \"$2\" = \"-h\" ]; then echo '  --SiftExtraction.use_gpu arg (=1)'; echo '  --SiftExtraction.num_threads arg'; exit 0; fi\n\
         echo 'Processed file [1/3]'\n\
         echo 'F1202 12:00:00 sift.cc:42] Check failed: descriptors.rows() == 7' >&2\n\
         exit 134\n",
    )
    .unwrap();
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o755)).unwrap();
    p
}

/// Nothing but the output's parent's other entries: no output, no hidden working folder.
fn left_nothing(parent: &Path, out: &Path) {
    assert!(!out.exists(), "{} written", out.display());
    let hidden: Vec<_> = std::fs::read_dir(parent)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains(".process."))
        .collect();
    assert!(hidden.is_empty(), "{hidden:?}");
}

#[test]
fn errors_a_user_can_act_on() {
    let t = tempfile::tempdir().unwrap();
    let colmap = crashing_colmap(t.path());
    let cm = s(&colmap);
    let out = t.path().join("cap");
    let photos = t.path().join("photos");
    std::fs::create_dir(&photos).unwrap();
    std::fs::write(photos.join("notes.txt"), b"x").unwrap();
    let run = |input: &Path, extra: &[&str]| {
        let mut args = vec!["process", s(input), "--out", s(&out), "--colmap", cm];
        args.extend_from_slice(extra);
        stegongp(&args)
    };
    fails_naming(&run(&photos, &[]), &["no photos here", "1 other file"]);
    let small = Arc {
        width: 64,
        height: 44,
        ..arc(3)
    };
    let (frames, _, _) = room_arc(&small);
    for (i, f) in frames.iter().take(2).enumerate() {
        write_png(&photos.join(format!("{i}.png")), 64, 44, f);
    }
    fails_naming(&run(&photos, &[]), &["only 2 photo(s)"]);
    write_png(&photos.join("2.png"), 64, 44, &frames[2]);
    std::fs::write(photos.join("3.jpg"), b"not a jpeg").unwrap();
    fails_naming(&run(&photos, &[]), &["3.jpg"]);
    left_nothing(t.path(), &out);
    std::fs::remove_file(photos.join("3.jpg")).unwrap();
    // COLMAP crashes: its last lines, nothing left behind.
    let e = run(&photos, &[]);
    fails_naming(
        &e,
        &[
            "colmap feature_extractor failed",
            "Check failed: descriptors.rows() == 7",
            "Processed file [1/3]",
        ],
    );
    left_nothing(t.path(), &out);
    // Missing programs name their package.
    let missing = t.path().join("nowhere/colmap");
    fails_naming(
        &stegongp(&[
            "process",
            s(&photos),
            "--out",
            s(&out),
            "--colmap",
            s(&missing),
        ]),
        &["colmap not found", "apt-get install colmap"],
    );
    let clip = t.path().join("clip.mp4");
    std::fs::write(&clip, b"not a video at all").unwrap();
    let no_ffmpeg = t.path().join("nowhere/ffmpeg");
    fails_naming(
        &run(&clip, &["--ffmpeg", s(&no_ffmpeg)]),
        &["ffmpeg not found", "apt-get install ffmpeg"],
    );
    if have("ffprobe", "-version") {
        fails_naming(
            &run(&clip, &[]),
            &["clip.mp4", "not a video ffmpeg can read"],
        );
        fails_naming(
            &run(&photos.join("0.png"), &[]),
            &["a single png image, not a video", "folder"],
        );
    } else {
        testkit::missing("ffprobe", "apt-get install ffmpeg");
    }
    left_nothing(t.path(), &out);
    // An existing output is kept without --force; the input is never inside the output.
    std::fs::create_dir(&out).unwrap();
    std::fs::write(out.join("keep"), b"mine").unwrap();
    fails_naming(&run(&photos, &[]), &["exists", "--force"]);
    fails_naming(
        &run(&photos, &["--force"]),
        &["colmap feature_extractor failed"],
    );
    assert_eq!(std::fs::read(out.join("keep")).unwrap(), b"mine");
    fails_naming(
        &stegongp(&[
            "process",
            s(&photos),
            "--out",
            s(t.path()),
            "--force",
            "--colmap",
            cm,
        ]),
        &["hold the input"],
    );
    fails_naming(&run(&photos, &["--frames", "2"]), &["--frames 2"]);
}

#[test]
fn images_without_shared_features_register_nothing_and_say_what_to_try() {
    if !have("colmap", "-h") {
        return testkit::missing("colmap", "apt-get install colmap");
    }
    let t = tempfile::tempdir().unwrap();
    let photos = t.path().join("flat");
    std::fs::create_dir(&photos).unwrap();
    for (i, c) in [[200, 30, 30], [30, 200, 30], [30, 30, 200], [128, 128, 128]]
        .iter()
        .enumerate()
    {
        let f = Rgb8::new(64, 48, *c);
        write_png(&photos.join(format!("{i}.png")), 64, 48, &f.data);
    }
    let out = t.path().join("cap");
    let e = stegongp(&["process", s(&photos), "--out", s(&out)]);
    fails_naming(
        &e,
        &[
            "registered none of the 4 images",
            "--matcher exhaustive",
            "overlap",
        ],
    );
    left_nothing(t.path(), &out);
}
