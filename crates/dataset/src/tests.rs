//! Loader tests on tiny hand-built datasets.
#![allow(clippy::needless_range_loop)]
// A test reads as one story; the 120-line limit (clippy.toml) is the program's.
#![allow(clippy::too_many_lines)]

use std::path::Path;

use serde_json::{Value, json};

use super::*;
use ngp::data::srgb_to_linear;

/// Writes an RGBA8 PNG.
fn write_png(path: &Path, w: u32, h: u32, rgba: &[u8]) {
    let f = std::fs::File::create(path).unwrap();
    let mut enc = png::Encoder::new(std::io::BufWriter::new(f), w, h);
    enc.set_color(png::ColorType::Rgba);
    enc.set_depth(png::BitDepth::Eight);
    let mut wr = enc.write_header().unwrap();
    wr.write_image_data(rgba).unwrap();
    wr.finish().unwrap();
}

/// 4×4 RGBA with distinct values: pixel (x, y) = (16x, 16y, 200, 255 − 40x).
fn pixels4() -> Vec<u8> {
    let mut v = Vec::new();
    for y in 0..4u8 {
        for x in 0..4u8 {
            v.extend_from_slice(&[16 * x, 16 * y, 200, 255 - 40 * x]);
        }
    }
    v
}

fn write_json(path: &Path, v: &Value) {
    std::fs::write(path, serde_json::to_string_pretty(v).unwrap()).unwrap();
}

/// Camera at nerf (0, −4, 0) looking along nerf +y, up = nerf +z (Blender/OpenGL columns:
/// x = (1,0,0), y = (0,0,1), z = (0,−1,0) since the camera looks along −z).
fn pose_looking_y() -> Value {
    json!([[1, 0, 0, 0], [0, 0, -1, -4], [0, 1, 0, 0], [0, 0, 0, 1]])
}

fn identity_pose() -> Value {
    json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
}

fn synthetic(dir: &Path, splits: &[&str]) {
    std::fs::create_dir_all(dir.join("train")).unwrap();
    write_png(&dir.join("train/r_0.png"), 4, 4, &pixels4());
    for s in splits {
        write_json(
            &dir.join(format!("transforms_{s}.json")),
            &json!({
                "camera_angle_x": std::f64::consts::FRAC_PI_2,
                "frames": [{"file_path": "./train/r_0", "transform_matrix": pose_looking_y()}]
            }),
        );
    }
}

fn opts(n: u32) -> LoadOptions {
    LoadOptions {
        downscale: n,
        ..Default::default()
    }
}

fn close(a: f32, b: f32) -> bool {
    (a - b).abs() < 1e-5
}

#[test]
fn nerf_synthetic_pose_intrinsics_and_pixels() {
    let t = tempfile::tempdir().unwrap();
    synthetic(t.path(), &["train"]);
    let d = load(t.path(), Split::Train, &opts(1)).unwrap();
    assert_eq!(d.format, DatasetFormat::NerfSynthetic);
    assert_eq!((d.width, d.height, d.frames.len()), (4, 4, 1));
    assert_eq!((d.aabb_scale, d.scale, d.offset), (1, 0.33, [0.5; 3]));
    assert_eq!(d.aabb(), ([0.0; 3], [1.0; 3]));
    assert!(d.has_alpha);
    let f = &d.frames[0];
    assert_eq!(f.file_path, "./train/r_0");
    // focal = 0.5·4 / tan(π/4) = 2; principal point at the image centre.
    let c = &f.camera;
    assert!(close(c.fx, 2.0) && close(c.fy, 2.0));
    assert_eq!((c.cx, c.cy, c.width, c.height), (2.0, 2.0, 4, 4));
    assert!(c.distortion.is_none());
    // By hand: negate columns 1, 2 → rows (1,0,0|0), (0,0,1|−4), (0,−1,0|0); translation
    // ·0.33 + 0.5 → 0.5, −0.82, 0.5; rows cycled to (row1, row2, row0).
    let expect = [
        [0.0, 0.0, 1.0, -0.82],
        [0.0, -1.0, 0.0, 0.5],
        [1.0, 0.0, 0.0, 0.5],
    ];
    for r in 0..3 {
        for k in 0..4 {
            assert!(close(c.c2w[r][k], expect[r][k]), "{:?}", c.c2w);
        }
    }
    // Principal-point ray = camera forward = nerf +y = ngp +x.
    let ray = c.ray(2.0, 2.0);
    assert_eq!(ray.d, [1.0, 0.0, 0.0]);
    assert!(close(ray.o[0], -0.82) && close(ray.o[1], 0.5) && close(ray.o[2], 0.5));
    // Top-left pixel centre: u = v = (0.5 − 2)/2 = −0.75; d ∝ −0.75·right − 0.75·down + fwd
    // = (1, 0.75, −0.75): up is ngp +y (nerf +z), left is ngp −z (nerf −x).
    let r = c.ray(0.5, 0.5);
    let n = (1.0f32 + 2.0 * 0.5625).sqrt();
    assert!(close(r.d[0], 1.0 / n) && close(r.d[1], 0.75 / n) && close(r.d[2], -0.75 / n));
    // Pixel (3, 1) = (48, 16, 200, 135): linear values × alpha.
    let p = f.image.linear_premul(3, 1);
    // (codes scale by 1/255 as a product, as the reference's rgba32_to_rgba does)
    let a = 135.0 * (1.0 / 255.0);
    let l = |v: f32| srgb_to_linear(v * (1.0 / 255.0));
    assert_eq!(p, [l(48.0) * a, l(16.0) * a, l(200.0) * a, a]);
}

#[test]
fn downscale_scales_intrinsics_and_averages() {
    let t = tempfile::tempdir().unwrap();
    synthetic(t.path(), &["train"]);
    let d = load(t.path(), Split::Train, &opts(2)).unwrap();
    assert_eq!((d.width, d.height), (2, 2));
    let c = &d.frames[0].camera;
    assert!(close(c.fx, 1.0) && close(c.cx, 1.0) && close(c.cy, 1.0));
    assert_eq!((c.width, c.height), (2, 2));
    // Output (1, 0) averages pixels x ∈ {2, 3}, y ∈ {0, 1} of linear premultiplied values.
    let px = pixels4();
    let mut e = [0.0f32; 4];
    for y in 0..2 {
        for x in 2..4 {
            let q = &px[4 * (y * 4 + x)..];
            let a = q[3] as f32 / 255.0;
            for k in 0..3 {
                e[k] += srgb_to_linear(q[k] as f32 / 255.0) * a / 4.0;
            }
            e[3] += a / 4.0;
        }
    }
    let p = d.frames[0].image.linear_premul(1, 0);
    for k in 0..4 {
        assert!(
            (p[k] - e[k]).abs() < 1e-3 * e[k].max(0.01),
            "{k}: {p:?} {e:?}"
        );
    }
    // Same cameras without decoding pixels.
    let (cams, meta) = load_cameras(t.path(), Split::Train, &opts(2)).unwrap();
    assert_eq!((meta.width, meta.height, meta.n), (2, 2, 1));
    assert_eq!(cams[0].c2w, c.c2w);
    assert_eq!((cams[0].fx, cams[0].cx), (c.fx, c.cx));
    // Too coarse for the image.
    assert!(load(t.path(), Split::Train, &opts(8)).is_err());
}

#[test]
fn missing_split_falls_back() {
    let t = tempfile::tempdir().unwrap();
    synthetic(t.path(), &["train", "test"]);
    let d = load(t.path(), Split::Val, &opts(1)).unwrap();
    assert_eq!(d.split, Split::Val);
    let (_, m) = load_cameras(t.path(), Split::Val, &opts(1)).unwrap();
    assert!(m.json_path.ends_with("transforms_test.json"));

    let t = tempfile::tempdir().unwrap();
    synthetic(t.path(), &["train", "val"]);
    let (_, m) = load_cameras(t.path(), Split::Test, &opts(1)).unwrap();
    assert!(m.json_path.ends_with("transforms_val.json"));
    let t = tempfile::tempdir().unwrap();
    synthetic(t.path(), &["train"]);
    let e = load(t.path(), Split::Test, &opts(1))
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("transforms_test.json") && e.contains("transforms_val.json"),
        "{e}"
    );
    let t = tempfile::tempdir().unwrap();
    synthetic(t.path(), &["test"]);
    let e = load(t.path(), Split::Train, &opts(1))
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("transforms_train.json"), "{e}");
}

/// instant-ngp folder: 10 frames img_1..img_10 written out of order, with distortion.
fn ingp(dir: &Path, extra: impl FnOnce(&mut Value)) {
    std::fs::create_dir_all(dir.join("images")).unwrap();
    let mut frames = Vec::new();
    for i in [3, 10, 1, 7, 2, 9, 4, 5, 8, 6] {
        write_png(&dir.join(format!("images/img_{i}.png")), 4, 4, &pixels4());
        let mut p = identity_pose();
        p[0][3] = json!(i);
        frames.push(json!({"file_path": format!("images/img_{i}.png"), "transform_matrix": p}));
    }
    // Per-frame focal override on img_5.
    frames[7]["fl_x"] = json!(7.0);
    let mut v = json!({
        "fl_x": 3.0, "fl_y": 3.5, "cx": 50.0, "cy": 25.0, "w": 100, "h": 50,
        "k1": 0.1, "k2": -0.02, "p1": 0.001, "p2": 0.002,
        "aabb_scale": 4, "scale": 0.5, "offset": [0.1, 0.2, 0.3],
        "frames": frames
    });
    extra(&mut v);
    write_json(&dir.join("transforms.json"), &v);
}

#[test]
fn instant_ngp_every_eighth_and_intrinsics() {
    let t = tempfile::tempdir().unwrap();
    ingp(t.path(), |_| {});
    let test = load(t.path(), Split::Test, &opts(1)).unwrap();
    let train = load(t.path(), Split::Train, &opts(1)).unwrap();
    assert_eq!(test.format, DatasetFormat::InstantNgp);
    // Natural order img_1..img_10; indices 0 and 8 are held out.
    let names = |d: &Dataset| {
        d.frames
            .iter()
            .map(|f| f.file_path.clone())
            .collect::<Vec<_>>()
    };
    assert_eq!(names(&test), vec!["images/img_1.png", "images/img_9.png"]);
    let tr = names(&train);
    assert_eq!(tr.len(), 8);
    assert_eq!(tr[0], "images/img_2.png");
    assert_eq!(tr[7], "images/img_10.png");
    let (_, m) = load_cameras(t.path(), Split::Val, &opts(1)).unwrap();
    assert_eq!(m.file_paths, names(&test));

    assert_eq!(train.aabb_scale, 4);
    assert_eq!(train.aabb(), ([-1.5; 3], [2.5; 3]));
    assert_eq!((train.scale, train.offset), (0.5, [0.1, 0.2, 0.3]));
    assert!(train.has_alpha);
    let c = &test.frames[0].camera;
    // Principal point cx/w of the loaded 4-pixel image: 0.5·4, 0.5·4.
    assert_eq!((c.fx, c.fy, c.cx, c.cy), (3.0, 3.5, 2.0, 2.0));
    assert_eq!(
        c.distortion,
        Some(ngp::camera::Distortion {
            k1: 0.1,
            k2: -0.02,
            p1: 0.001,
            p2: 0.002
        })
    );
    // img_1 is at nerf (1, 0, 0): ·0.5 + offset = (0.6, 0.2, 0.3) (offset applies before the
    // row cycle), then ngp = (nerf y, z, x) = (0.2, 0.3, 0.6).
    assert!(close(c.c2w[0][3], 0.2) && close(c.c2w[1][3], 0.3) && close(c.c2w[2][3], 0.6));
    // Per-frame override of fl_x (img_5 is train index 3): fl_y stays the top-level one.
    let c5 = &train.frames[3].camera;
    assert_eq!(train.frames[3].file_path, "images/img_5.png");
    assert_eq!((c5.fx, c5.fy), (7.0, 7.0));
    // Distorted ray of the principal point is still the forward axis; other rays invert
    // the forward distortion model.
    let r = c.ray(2.0, 2.0);
    // Identity nerf pose looks along nerf −z = ngp −y.
    assert!(
        close(r.d[0], 0.0) && close(r.d[1], -1.0) && close(r.d[2], 0.0),
        "{:?}",
        r.d
    );
    let r = c.ray(0.5, 3.5);
    let m = &c.c2w;
    let cc = [0, 1, 2].map(|k| m[0][k] * r.d[0] + m[1][k] * r.d[1] + m[2][k] * r.d[2]);
    let (u, v) = c.distortion.unwrap().distort(cc[0] / cc[2], cc[1] / cc[2]);
    assert!(close(u, (0.5 - 2.0) / 3.0) && close(v, (3.5 - 2.0) / 3.5));
}

#[test]
fn sharpness_filter_drops_missing_images() {
    let t = tempfile::tempdir().unwrap();
    ingp(t.path(), |v| {
        let frames = v["frames"].as_array_mut().unwrap();
        for f in frames.iter_mut() {
            f["sharpness"] = json!(10.0);
        }
        frames.push(json!({"file_path": "images/img_11.png", "sharpness": 10.0,
                           "transform_matrix": identity_pose()}));
    });
    let (_, m) = load_cameras(t.path(), Split::Train, &opts(1)).unwrap();
    assert_eq!(m.dropped, vec!["images/img_11.png".to_string()]);
    assert_eq!(m.n, 8);
    // Without sharpness entries a missing image is an error naming the file.
    let t = tempfile::tempdir().unwrap();
    ingp(t.path(), |v| {
        v["frames"]
            .as_array_mut()
            .unwrap()
            .push(json!({"file_path": "images/img_11.png", "transform_matrix": identity_pose()}));
    });
    let e = load(t.path(), Split::Train, &opts(1))
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("transforms.json") && e.contains("img_11.png") && e.contains("file_path"),
        "{e}"
    );
}

/// Loads a synthetic dataset whose transforms_train.json is `v` and returns the error.
fn synth_err(v: Value) -> String {
    let t = tempfile::tempdir().unwrap();
    synthetic(t.path(), &["train"]);
    write_json(&t.path().join("transforms_train.json"), &v);
    match load(t.path(), Split::Train, &opts(1)) {
        Ok(_) => panic!("loaded {v}"),
        Err(e) => e.to_string(),
    }
}

fn frame(m: Value) -> Value {
    json!({"camera_angle_x": 1.0, "frames": [{"file_path": "./train/r_0", "transform_matrix": m}]})
}

#[test]
fn errors_name_file_and_field() {
    let has = |e: &str, parts: &[&str]| {
        assert!(e.contains("transforms_train.json"), "{e}");
        for p in parts {
            assert!(e.contains(p), "{p} not in: {e}");
        }
    };
    has(
        &synth_err(json!({"camera_angle_x": 1.0})),
        &["frames", "missing"],
    );
    has(
        &synth_err(json!({"camera_angle_x": 1.0, "frames": []})),
        &["frames", "no frames"],
    );
    has(
        &synth_err(
            json!({"camera_angle_x": 1.0, "frames": [{"transform_matrix": identity_pose()}]}),
        ),
        &["frames[0].file_path"],
    );
    has(
        &synth_err(json!({"camera_angle_x": 1.0, "frames": [{"file_path": "./train/r_0"}]})),
        &["frames[0]", "transform_matrix", "missing"],
    );
    has(
        &synth_err(frame(json!([[1, 0, 0, 0], [0, 1, "x", 0], [0, 0, 1, 0]]))),
        &["frames[0]", "transform_matrix[1][2]"],
    );
    has(
        &synth_err(frame(json!([[1, 0, 0, 0], [0, 1, 0, 0]]))),
        &["transform_matrix", "rows"],
    );
    has(
        &synth_err(frame(json!([[2, 0, 0, 0], [0, 2, 0, 0], [0, 0, 2, 0]]))),
        &["transform_matrix", "not rigid"],
    );
    has(
        &synth_err(frame(json!([[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]))),
        &["transform_matrix", "not rigid"],
    );
    has(
        &synth_err(
            json!({"frames": [{"file_path": "./train/r_0", "transform_matrix": identity_pose()}]}),
        ),
        &["frames[0]", "focal length"],
    );
    has(
        &synth_err(json!({"camera_angle_x": "wide", "frames": []})),
        &["camera_angle_x"],
    );
    for bad in [json!(3), json!(256), json!(0), json!(2.5), json!("4")] {
        has(
            &synth_err(json!({"aabb_scale": bad, "camera_angle_x": 1.0, "frames": []})),
            &["aabb_scale"],
        );
    }
    has(
        &synth_err(
            json!({"camera_angle_x": 1.0, "frames": [{"file_path": "./train/nothere", "transform_matrix": identity_pose()}]}),
        ),
        &["frames[0].file_path", "nothere", "not found"],
    );

    // Malformed JSON.
    let t = tempfile::tempdir().unwrap();
    synthetic(t.path(), &["train"]);
    std::fs::write(t.path().join("transforms_train.json"), "{\"frames\": [").unwrap();
    let e = load(t.path(), Split::Train, &opts(1))
        .err()
        .unwrap()
        .to_string();
    has(&e, &["malformed JSON"]);

    // Mixed image sizes: the error names the odd image.
    let t = tempfile::tempdir().unwrap();
    synthetic(t.path(), &["train"]);
    write_png(&t.path().join("train/r_1.png"), 2, 2, &[9; 16]);
    write_json(
        &t.path().join("transforms_train.json"),
        &json!({"camera_angle_x": 1.0, "frames": [
            {"file_path": "./train/r_0", "transform_matrix": identity_pose()},
            {"file_path": "./train/r_1", "transform_matrix": identity_pose()}]}),
    );
    let e = load(t.path(), Split::Train, &opts(1))
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("r_1.png") && e.contains("2x2") && e.contains("4x4"),
        "{e}"
    );
    assert!(load_cameras(t.path(), Split::Train, &opts(1)).is_err());

    // Corrupt image file.
    std::fs::write(t.path().join("train/r_1.png"), b"\x89PNG garbage").unwrap();
    let e = load(t.path(), Split::Train, &opts(1))
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("r_1.png"), "{e}");

    // Downscale 0, empty folder, missing folder.
    let e = load(t.path(), Split::Train, &opts(0))
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("downscale"), "{e}");
    let empty = tempfile::tempdir().unwrap();
    let e = load(empty.path(), Split::Train, &opts(1))
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("transforms.json"), "{e}");
    let e = load(&empty.path().join("nope"), Split::Train, &opts(1))
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("nope"), "{e}");

    // instant-ngp: a single frame leaves the train split empty.
    let t = tempfile::tempdir().unwrap();
    ingp(t.path(), |v| {
        v["frames"].as_array_mut().unwrap().truncate(1);
    });
    let e = load(t.path(), Split::Train, &opts(1))
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("transforms.json") && e.contains("train split has no frames"),
        "{e}"
    );
    assert!(load(t.path(), Split::Test, &opts(1)).is_ok());
}

#[test]
fn cameras_without_images_use_json_size() {
    let t = tempfile::tempdir().unwrap();
    write_json(
        &t.path().join("transforms.json"),
        &json!({"camera_angle_x": std::f64::consts::FRAC_PI_2, "w": 8, "h": 6, "frames": [
            {"file_path": "a.png", "transform_matrix": pose_looking_y()}]}),
    );
    let (cams, m) = load_cameras(t.path(), Split::Test, &opts(1)).unwrap();
    assert_eq!((m.width, m.height), (8, 6));
    assert_eq!((cams[0].fx, cams[0].cx, cams[0].cy), (4.0, 4.0, 3.0));
    assert!(load(t.path(), Split::Test, &opts(1)).is_err());
}
