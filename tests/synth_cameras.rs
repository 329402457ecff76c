//! `synth --cameras-from DIR`: a generated scene rendered from exactly a dataset's cameras.
//! Loading the output must give the source's cameras (count, order, sizes, intrinsics,
//! lens, poses) bit for bit, split by split, for every format the loader reads: a
//! generated NeRF-synthetic scene (with a val split), a generated instant-ngp scene (every
//! 8th view held out), a COLMAP text model with a distorted non-square camera and an LLFF
//! capture written here, and the real fox-colmap and flower captures when ../shared/data
//! is present. Then the scene must be seen, and bad combinations refused.
#![allow(clippy::needless_range_loop)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use testkit::geometry::{cross, rot_to_quat};

use npyz::WriterBuilder;
use stegongp::dataset::LoadOptions;
use stegongp::ngp::camera::Camera;
use stegongp::ngp::data::Split;
use stegongp::synth::cameras_from::generate_from_cameras;
use stegongp::synth::{SceneKind, SynthOptions, generate};

fn stegongp(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_stegongp"))
        .args(args)
        .output()
        .unwrap()
}

fn cams(dir: &Path, split: Split, o: &LoadOptions) -> Vec<Camera> {
    stegongp::dataset::load_cameras(dir, split, o).unwrap().0
}

fn load(downscale: u32) -> LoadOptions {
    LoadOptions {
        downscale,
        ..Default::default()
    }
}

/// Bit-for-bit equal cameras (−0.0 and 0.0 aside, which `==` equates).
fn assert_same(what: &str, a: &[Camera], b: &[Camera]) {
    assert_eq!(a.len(), b.len(), "{what}: camera count");
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert_eq!(x.c2w, y.c2w, "{what}: pose of camera {i}");
        assert_eq!(
            [x.fx, x.fy, x.cx, x.cy],
            [y.fx, y.fy, y.cx, y.cy],
            "{what}: intrinsics of camera {i}"
        );
        assert_eq!((x.width, x.height), (y.width, y.height), "{what}: size");
        assert_eq!(x.distortion, y.distortion, "{what}: lens of camera {i}");
    }
}

/// Every split of `src` (at `downscale`) against the same split of `out` (full size), and
/// the PNGs: the cameras' size, and the scene seen in most views.
fn check_output(what: &str, src: &Path, src_opts: &LoadOptions, out: &Path) {
    for split in [Split::Train, Split::Val, Split::Test] {
        let a = cams(src, split, src_opts);
        let b = cams(out, split, &load(1));
        assert_same(&format!("{what} {}", split.name()), &a, &b);
    }
    let test = stegongp::dataset::load(out, Split::Test, &load(1)).unwrap();
    let train = stegongp::dataset::load(out, Split::Train, &load(1)).unwrap();
    assert!(test.has_alpha, "{what}: a transparent background");
    let mut seen = 0;
    let frames: Vec<_> = train.frames.iter().chain(&test.frames).collect();
    for f in &frames {
        assert_eq!(
            (f.image.width, f.image.height),
            (f.camera.width, f.camera.height)
        );
        let cam = &f.camera;
        // The box centre's pixel shows the scene (or the scene is at least in the view).
        if let Some([px, py]) = cam.project([0.5; 3]) {
            let (w, h) = (cam.width as f32, cam.height as f32);
            if px > 0.0 && py > 0.0 && px < w && py < h {
                let (w, h) = (f.image.width, f.image.height);
                let n = (w * h) as usize;
                let covered = (0..h)
                    .flat_map(|y| (0..w).map(move |x| (x, y)))
                    .filter(|&(x, y)| f.image.linear_premul(x, y)[3] > 0.5)
                    .count();
                if covered * 50 > n {
                    seen += 1;
                }
            }
        }
    }
    assert!(
        seen * 4 >= frames.len() * 3,
        "{what}: the scene covers > 2 % of only {seen} of {} views",
        frames.len()
    );
}

#[test]
fn nerf_synthetic_source_with_val() {
    let d = tempfile::tempdir().unwrap();
    let src = d.path().join("src");
    generate(
        &SynthOptions {
            scene: SceneKind::Object,
            resolution: 24,
            n_train: 9,
            n_val: 3,
            n_test: 4,
            seed: 3,
            aabb_scale: 2,
            ..Default::default()
        },
        &src,
    )
    .unwrap();
    let out = d.path().join("out");
    let s = generate_from_cameras(&SceneKind::Logo, 5, &src, &load(1), &out).unwrap();
    assert_eq!((s.n_train, s.n_val, s.n_test), (9, 3, 4));
    assert!(out.join("transforms_val.json").is_file());
    let info = s.cameras_from.unwrap();
    assert_eq!(info.aabb_scale, 2);
    assert_eq!(info.views_seeing_centre, 16);
    check_output("nerf-synthetic", &src, &load(1), &out);
    // The aabb_scale is the source's, in every split.
    assert_eq!(
        stegongp::dataset::load_cameras(&out, Split::Test, &load(1))
            .unwrap()
            .1
            .aabb_scale,
        2
    );
}

#[test]
fn instant_ngp_source_holds_out_every_eighth() {
    let d = tempfile::tempdir().unwrap();
    let src = d.path().join("room");
    generate(
        &SynthOptions {
            scene: SceneKind::Room,
            resolution: 20,
            n_train: 14,
            n_val: 0,
            n_test: 3,
            seed: 2,
            aabb_scale: 4,
            ..Default::default()
        },
        &src,
    )
    .unwrap();
    let out = d.path().join("out");
    let s = generate_from_cameras(&SceneKind::Text("HI".into()), 0, &src, &load(1), &out).unwrap();
    // 17 views, every 8th held out: 0, 8, 16.
    assert_eq!((s.n_train, s.n_val, s.n_test), (14, 0, 3));
    assert!(!out.join("transforms_val.json").exists());
    check_output("instant-ngp", &src, &load(1), &out);
}

fn unit(a: [f64; 3]) -> [f64; 3] {
    let n = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    a.map(|v| v / n)
}

/// `n` OpenCV cameras (right, down, forward columns; centre) on an arc of radius 4 around
/// the z axis, 1 above the origin, looking at it.
fn arc_cameras(n: usize) -> Vec<([[f64; 3]; 3], [f64; 3])> {
    (0..n)
        .map(|i| {
            let a = -0.9 + 1.8 * i as f64 / (n - 1) as f64;
            let c = [4.0 * a.cos(), 4.0 * a.sin(), 1.0 + 0.1 * (i % 3) as f64];
            let f = unit(c.map(|v| -v));
            let r = unit(cross(f, [0.0, 0.0, 1.0]));
            let dn = cross(f, r);
            let m = [0, 1, 2].map(|k| [r[k], dn[k], f[k]]);
            (m, c)
        })
        .collect()
}

fn write_png(p: &Path, w: u32, h: u32) {
    let f = std::fs::File::create(p).unwrap();
    let mut enc = png::Encoder::new(std::io::BufWriter::new(f), w, h);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let mut wr = enc.write_header().unwrap();
    wr.write_image_data(&vec![128u8; (w * h * 3) as usize])
        .unwrap();
}

const W: u32 = 40;
const H: u32 = 26;

/// A COLMAP text model (one OPENCV camera with distortion, non-square images) of
/// [`arc_cameras`], images named so that byte order differs from capture order.
fn colmap_capture(dir: &Path, n: usize) {
    let model = dir.join("sparse/0");
    std::fs::create_dir_all(&model).unwrap();
    std::fs::create_dir_all(dir.join("images")).unwrap();
    std::fs::write(
        model.join("cameras.txt"),
        format!("1 OPENCV {W} {H} 31.5 30.25 20.5 12.75 0.031 -0.012 0.0011 -0.0007\n"),
    )
    .unwrap();
    let mut s = String::new();
    for (i, (m, c)) in arc_cameras(n).iter().enumerate() {
        // World-to-camera: R = mᵀ, t = −R c.
        let r = [0, 1, 2].map(|a| [0, 1, 2].map(|b| m[b][a]));
        let t = [0, 1, 2].map(|a| -(r[a][0] * c[0] + r[a][1] * c[1] + r[a][2] * c[2]));
        let q = rot_to_quat(&r);
        let name = format!(
            "img_{}.png",
            [7, 3, 11, 0, 5, 9, 1, 10, 2, 8, 4, 6][i % 12] + 12 * (i / 12)
        );
        write_png(&dir.join("images").join(&name), W, H);
        s += &format!(
            "{} {} {} {} {} {} {} {} 1 {name}\n\n",
            i + 1,
            q[0],
            q[1],
            q[2],
            q[3],
            t[0],
            t[1],
            t[2]
        );
    }
    std::fs::write(model.join("images.txt"), s).unwrap();
    std::fs::write(model.join("points3D.txt"), "").unwrap();
}

/// An LLFF capture of [`arc_cameras`]: rows [down, right, back | centre | H W focal] and
/// near/far bounds around the origin, for originals twice the images' size.
fn llff_capture(dir: &Path, n: usize) {
    std::fs::create_dir_all(dir.join("images")).unwrap();
    let rows: Vec<Vec<f64>> = arc_cameras(n)
        .iter()
        .enumerate()
        .map(|(i, (m, c))| {
            write_png(&dir.join("images").join(format!("{i:03}.png")), W, H);
            let mut r = Vec::new();
            let hwf = [2.0 * H as f64, 2.0 * W as f64, 64.0];
            for k in 0..3 {
                r.extend([m[k][1], m[k][0], -m[k][2], c[k], hwf[k]]);
            }
            r.extend([2.5, 7.0]);
            r
        })
        .collect();
    let mut w = npyz::WriteOptions::new()
        .default_dtype()
        .shape(&[rows.len() as u64, 17])
        .writer(std::fs::File::create(dir.join("poses_bounds.npy")).unwrap())
        .begin_nd()
        .unwrap();
    for r in &rows {
        w.extend(r.iter().copied()).unwrap();
    }
    w.finish().unwrap();
}

#[test]
fn colmap_source_distorted_non_square_at_a_downscale() {
    let d = tempfile::tempdir().unwrap();
    let src = d.path().join("cap");
    colmap_capture(&src, 12);
    let out = d.path().join("out");
    let s = generate_from_cameras(&SceneKind::Object, 0, &src, &load(2), &out).unwrap();
    assert_eq!((s.n_train, s.n_val, s.n_test), (10, 0, 2));
    let info = s.cameras_from.unwrap();
    assert_eq!((info.width, info.height), (W / 2, H / 2));
    assert_eq!(info.format, "COLMAP");
    let c = cams(&out, Split::Train, &load(1));
    assert!(
        c[0].distortion.is_some(),
        "the lens travels with the cameras"
    );
    check_output("colmap", &src, &load(2), &out);
}

#[test]
fn llff_source() {
    let d = tempfile::tempdir().unwrap();
    let src = d.path().join("llff");
    llff_capture(&src, 10);
    let out = d.path().join("out");
    let s = generate_from_cameras(&SceneKind::Text("OK".into()), 0, &src, &load(1), &out).unwrap();
    assert_eq!((s.n_train, s.n_test), (8, 2));
    check_output("llff", &src, &load(1), &out);
    // The front of the text faces the cameras (they stand on one side).
    let p = s.cameras_from.unwrap().placement;
    let front = [0.0f32, -1.0, 0.0];
    let c = cams(&src, Split::Train, &load(1));
    let to_cam = p.to_scene(c[c.len() / 2].position());
    let cos = (front[0] * to_cam[0] + front[1] * to_cam[1]) / (to_cam[0].hypot(to_cam[1]));
    assert!(cos > 0.9, "the front faces the middle camera: cos {cos}");
}

fn shared(name: &str) -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/data")
        .join(name);
    if p.is_dir() {
        Some(p)
    } else {
        eprintln!("skipping: {} is absent", p.display());
        None
    }
}

#[test]
fn real_captures_fox_colmap_and_flower() {
    for (name, downscale, images) in [("fox-colmap", 8, None), ("flower", 4, Some("images_8"))] {
        let Some(src) = shared(name) else { continue };
        let d = tempfile::tempdir().unwrap();
        let out = d.path().join("out");
        let o = LoadOptions {
            downscale,
            images: images.map(str::to_string),
            aabb_scale: None,
        };
        let s = generate_from_cameras(&SceneKind::Logo, 1, &src, &o, &out).unwrap();
        let info = s.cameras_from.as_ref().unwrap();
        assert_eq!(info.views_seeing_centre, info.views, "{name}");
        check_output(name, &src, &o, &out);
    }
}

#[test]
fn the_cli_refuses_conflicts_and_bad_sources() {
    let d = tempfile::tempdir().unwrap();
    let src = d.path().join("src");
    generate(
        &SynthOptions {
            scene: SceneKind::Object,
            resolution: 16,
            n_train: 2,
            n_test: 1,
            ..Default::default()
        },
        &src,
    )
    .unwrap();
    let s = src.to_str().unwrap();
    let out = d.path().join("out");
    let o = out.to_str().unwrap();
    let err = |args: &[&str], needles: &[&str]| {
        let r = stegongp(args);
        assert!(!r.status.success(), "{args:?} should fail");
        let msg = String::from_utf8_lossy(&r.stderr).to_string();
        for n in needles {
            assert!(msg.contains(n), "{args:?}: {msg:?} lacks {n:?}");
        }
        assert!(
            !out.join("transforms_train.json").exists(),
            "{args:?} wrote output"
        );
    };
    let base = ["synth", "--scene", "logo", "--out", o, "--cameras-from", s];
    err(
        &[&base[..], &["--res", "64"]].concat(),
        &["--res", "--cameras-from", s],
    );
    err(
        &[&base[..], &["--train", "5", "--test", "2"]].concat(),
        &["--train, --test", "--cameras-from"],
    );
    err(
        &[
            "synth",
            "--scene",
            "room",
            "--aabb-scale",
            "4",
            "--out",
            o,
            "--cameras-from",
            s,
        ],
        &["room", "--cameras-from"],
    );
    err(
        &["synth", "--scene", "logo", "--out", o, "--downscale", "2"],
        &["--downscale", "--cameras-from"],
    );
    let missing = d.path().join("nothing-here");
    let m = missing.to_str().unwrap();
    err(
        &["synth", "--scene", "logo", "--out", o, "--cameras-from", m],
        &[m, "not found"],
    );
    let empty = d.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let e = empty.to_str().unwrap();
    err(
        &["synth", "--scene", "logo", "--out", o, "--cameras-from", e],
        &[e, "no dataset recognised"],
    );
    // Into the source itself.
    let r = stegongp(&[
        "synth",
        "--scene",
        "logo",
        "--out",
        s,
        "--force",
        "--cameras-from",
        s,
    ]);
    assert!(!r.status.success());
    assert!(String::from_utf8_lossy(&r.stderr).contains("camera source itself"));
    // And a good run, with --aabb-scale as the loader's override.
    let r = stegongp(&[&base[..], &["--aabb-scale", "4", "--json"]].concat());
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let v: serde_json::Value = serde_json::from_slice(&r.stdout).unwrap();
    assert_eq!(v["cameras_from"]["aabb_scale"], 4);
    assert_eq!(v["n_train"], 2);
}
