//! `stegongp train --hidden`: each scene is trained at its own resolution (the cover's
//! `--downscale` does not shrink the hidden scenes), and the key opens the hidden scene;
//! the stealth flags.

use testkit::cli::{ok, stegongp};

/// In `d`: a generated object cover and text scene at `res` px (4 train views, 1 test), a
/// `prf` key, and where a model goes: (cover, text, key, model).
fn cover_text_key(d: &std::path::Path, res: &str) -> (String, String, String, String) {
    let p = |n: &str| d.join(n).to_str().unwrap().to_string();
    let (cover, text, key, model) = (p("cover"), p("text"), p("k.json"), p("m.ingp"));
    for (scene, dir) in [("object", &cover), ("text", &text)] {
        ok(&stegongp(&[
            "synth", "--scene", scene, "--res", res, "--train", "4", "--test", "1", "--out", dir,
        ]));
    }
    ok(&stegongp(&["keygen", "--scheme", "prf", "--out", &key]));
    (cover, text, key, model)
}

#[test]
fn cover_downscale_leaves_hidden_scenes_at_their_resolution() {
    let d = tempfile::tempdir().unwrap();
    let (cover, text, key, model) = cover_text_key(d.path(), "32");
    let log = ok(&stegongp(&[
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
    let log = ok(&stegongp(&[
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

/// A hidden scene whose box (aabb_scale 8) is larger than the capture-like cover's (4) is
/// refused before any training, naming both boxes; with `--aabb-scale 8` the cover takes the
/// larger box, and a key whose box holds the scene (`keygen --aabb-scale 8`; the default
/// box 1 is refused) trains it there; the file is the cover's, at aabb_scale 8.
#[test]
fn hidden_scenes_take_the_cover_box_or_are_refused() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_str().unwrap().to_string();
    let (room, text, key, model) = (p("room"), p("text"), p("k.json"), p("m.ingp"));
    ok(&stegongp(&[
        "synth",
        "--scene",
        "room",
        "--aabb-scale",
        "4",
        "--res",
        "16",
        "--train",
        "8",
        "--test",
        "1",
        "--out",
        &room,
    ]));
    ok(&stegongp(&[
        "synth",
        "--scene",
        "text",
        "--aabb-scale",
        "8",
        "--res",
        "16",
        "--train",
        "4",
        "--test",
        "1",
        "--out",
        &text,
    ]));
    ok(&stegongp(&["keygen", "--scheme", "prf", "--out", &key]));
    let common = [
        "--steps",
        "2",
        "--batch",
        "2048",
        "--log2-t",
        "14",
        "--occupancy-fraction",
        "0.01",
    ];
    let mut args = vec![
        "train", &room, "--hidden", &text, "--key", &key, "--out", &model,
    ];
    args.extend_from_slice(&common);
    let out = stegongp(&args);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("aabb_scale 8") && err.contains("model's 4") && err.contains("--aabb-scale"),
        "{err}"
    );
    assert!(!std::path::Path::new(&model).exists());

    // In a box large enough, a key whose own box (keygen's default 1) is smaller than the
    // scene is refused too, naming the key and the fix.
    args.extend_from_slice(&["--aabb-scale", "8"]);
    let out = stegongp(&args);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("k.json") && err.contains("keygen --aabb-scale 8"),
        "{err}"
    );
    assert!(!std::path::Path::new(&model).exists());
    let key8 = p("k8.json");
    ok(&stegongp(&[
        "keygen",
        "--scheme",
        "prf",
        "--aabb-scale",
        "8",
        "--out",
        &key8,
    ]));
    let i = args.iter().position(|a| *a == key.as_str()).unwrap();
    args[i] = &key8;
    let log = ok(&stegongp(&args));
    assert!(log.contains("hidden: 4 images of 16×16"), "{log}");
    let info = stegongp(&["inspect", &model, "--json"]);
    let info: serde_json::Value = serde_json::from_slice(&info.stdout).unwrap();
    assert_eq!(info["aabb_scale"], 8, "{info}");
}

/// `--stealth --cover-only-mlp` trains a stealth model the key opens with `--stealth`;
/// `--cover-only-mlp` alone is refused (it changes stealth training) and writes nothing.
#[test]
fn cover_only_mlp_trains_with_stealth_and_only_with_it() {
    let d = tempfile::tempdir().unwrap();
    let (cover, text, key, model) = cover_text_key(d.path(), "16");
    let train = |extra: &[&str]| {
        let mut args = vec![
            "train", &cover, "--hidden", &text, "--key", &key, "--steps", "3", "--batch", "2048",
            "--log2-t", "12", "--out", &model,
        ];
        args.extend_from_slice(extra);
        stegongp(&args)
    };
    let out = train(&["--cover-only-mlp"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("--stealth"), "{err}");
    assert!(
        !d.path().join("m.ingp").exists(),
        "a refused run wrote a model"
    );
    let log = ok(&train(&["--stealth", "--cover-only-mlp"]));
    assert!(log.contains("the MLP learnt from the cover alone"), "{log}");
    ok(&stegongp(&[
        "eval",
        "--model",
        &model,
        "--data",
        &text,
        "--key",
        &key,
        "--stealth",
        "--views",
        "1",
        "--no-lpips",
    ]));
}

/// `--hidden-from` must leave the hidden scenes steps to train and needs a hidden scene.
#[test]
fn hidden_from_is_checked_before_anything_is_written() {
    let d = tempfile::tempdir().unwrap();
    let (cover, text, key, model) = cover_text_key(d.path(), "16");
    let common = [
        "--steps", "3", "--batch", "2048", "--log2-t", "12", "--out", &model,
    ];
    let train = |extra: &[&str]| {
        let mut args = vec!["train", cover.as_str()];
        args.extend_from_slice(extra);
        args.extend_from_slice(&common);
        stegongp(&args)
    };
    for (extra, says) in [
        (
            &["--hidden", &text, "--key", &key, "--hidden-from", "3"][..],
            "--hidden-from 3",
        ),
        (&["--hidden-from", "1"][..], "--hidden"),
    ] {
        let out = train(extra);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{extra:?} was accepted");
        assert!(err.contains(says), "{err}");
        assert!(
            !d.path().join("m.ingp").exists(),
            "a refused run wrote a model"
        );
    }
    // A time budget that ends inside the warm-up: refused after training, nothing written.
    let mut short = vec!["train", cover.as_str(), "--hidden", &text, "--key", &key];
    short.extend_from_slice(&[
        "--hidden-from",
        "100000",
        "--minutes",
        "0.001",
        "--batch",
        "2048",
        "--log2-t",
        "12",
        "--out",
        &model,
    ]);
    let out = stegongp(&short);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("never"), "{err}");
    assert!(
        !d.path().join("m.ingp").exists(),
        "a cover-only model was written"
    );
    ok(&train(&[
        "--hidden",
        &text,
        "--key",
        &key,
        "--hidden-from",
        "2",
    ]));
    assert!(d.path().join("m.ingp").exists());
}

/// `--density-cap` (stealth's cap on the cover's optical thickness): reported in the log,
/// 0 turns it off, a negative or non-number cap and the option without `--stealth` are
/// refused before anything is written.
#[test]
fn density_cap_is_stealths_and_checked_before_anything_is_written() {
    let d = tempfile::tempdir().unwrap();
    let (cover, text, key, model) = cover_text_key(d.path(), "16");
    let train = |extra: &[&str]| {
        let mut args = vec![
            "train", &cover, "--hidden", &text, "--key", &key, "--steps", "3", "--batch", "2048",
            "--log2-t", "12", "--out", &model,
        ];
        args.extend_from_slice(extra);
        stegongp(&args)
    };
    for (extra, says) in [
        (&["--density-cap", "2"][..], "--stealth"),
        (&["--stealth", "--density-cap=-1"][..], "--density-cap"),
        (&["--stealth", "--density-cap", "NaN"][..], "--density-cap"),
        (&["--stealth", "--density-cap", "lots"][..], "--density-cap"),
    ] {
        let out = train(extra);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{extra:?} was accepted");
        assert!(err.contains(says), "{extra:?}: {err}");
        assert!(
            !d.path().join("m.ingp").exists(),
            "a refused run wrote a model"
        );
    }
    let log = ok(&train(&["--stealth"]));
    assert!(
        log.contains("the cover's optical thickness capped at 2"),
        "{log}"
    );
    let log = ok(&train(&["--stealth", "--density-cap", "0.5"]));
    assert!(
        log.contains("the cover's optical thickness capped at 0.5"),
        "{log}"
    );
    let log = ok(&train(&["--stealth", "--density-cap", "0"]));
    assert!(log.contains("the cover's density uncapped"), "{log}");
}

/// `eval --rebuild-grid` scores the cover through the grid a key holder would rebuild from
/// the network (the grid the library rebuilds, not the stored one), and changes nothing
/// where a key already makes eval rebuild it.
#[test]
fn rebuild_grid_scores_a_plain_scene_as_a_hidden_one_is_scored() {
    use stegongp::dataset::LoadOptions;
    use stegongp::ngp::data::Split;
    use stegongp::ngp::encoding::reference_indices;
    use stegongp::ngp::model::Model;
    use stegongp::ngp::render::image::RenderOptions;
    use stegongp::score::eval::evaluate_with;
    use stegongp::stego::occupancy::{
        KEY_HOLDER_REFINE_SAMPLES, KEY_HOLDER_SAMPLES_PER_CELL, rebuild_occupancy, refine_occupancy,
    };
    let d = tempfile::tempdir().unwrap();
    let (cover, text, key, model) = cover_text_key(d.path(), "24");
    ok(&stegongp(&[
        "train",
        &cover,
        "--hidden",
        &text,
        "--key",
        &key,
        "--steps",
        "40",
        "--batch",
        "4096",
        "--log2-t",
        "14",
        "--occupancy-fraction",
        "0.0078125",
        "--device",
        "cpu",
        "--out",
        &model,
    ]));
    let psnr = |extra: &[&str]| -> f64 {
        let mut args = vec![
            "eval",
            "--model",
            &model,
            "--no-lpips",
            "--device",
            "cpu",
            "--json",
        ];
        args.extend_from_slice(extra);
        let out = stegongp(&args);
        ok(&out);
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        v["psnr"].as_f64().unwrap()
    };
    let stored = psnr(&["--data", &cover]);
    let rebuilt = psnr(&["--data", &cover, "--rebuild-grid"]);

    let m = Model::load(model.as_ref()).unwrap();
    let indices = reference_indices(&m.net.layout.grid);
    let mut grid = rebuild_occupancy(
        &m.net,
        m.params(),
        &indices,
        m.config.aabb_scale,
        KEY_HOLDER_SAMPLES_PER_CELL,
        0,
    );
    refine_occupancy(
        &m.net,
        m.params(),
        &indices,
        &mut grid,
        m.config.aabb_scale,
        KEY_HOLDER_REFINE_SAMPLES,
        KEY_HOLDER_SAMPLES_PER_CELL,
        0,
    );
    assert_ne!(
        grid.density, m.grid.density,
        "the fixture's stored grid must differ from a rebuilt one for the test to tell them apart"
    );
    let data =
        stegongp::dataset::load(cover.as_ref(), Split::Test, &LoadOptions::default()).unwrap();
    let score = |g| {
        let view = m.view(&indices, g);
        evaluate_with(
            &view,
            &data,
            &RenderOptions::default(),
            None,
            None,
            |_, _, _| {},
        )
        .psnr
    };
    let (want, alone) = (score(&grid), score(&m.grid));
    // The CLI's scores sum in another order than evaluate's: the same to 1e-9 dB.
    let same = |a: f64, b: f64| (a - b).abs() < 1e-9;
    assert!(
        same(rebuilt, want),
        "--rebuild-grid renders through the rebuilt grid: {rebuilt} vs {want}"
    );
    assert!(
        same(stored, alone),
        "without it, through the stored grid: {stored} vs {alone}"
    );
    assert!(
        (want - alone).abs() > 1e-3,
        "the two grids render apart on this fixture: {want} vs {alone}"
    );
    let (with, without) = (
        psnr(&["--data", &text, "--key", &key, "--rebuild-grid"]),
        psnr(&["--data", &text, "--key", &key]),
    );
    assert!(
        same(with, without),
        "a key's scene is rebuilt either way: {with} vs {without}"
    );
}
