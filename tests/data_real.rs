//! Loader checks on the real datasets in ../shared/data (skipped when absent).

use std::path::{Path, PathBuf};
use std::time::Instant;

use stegongp::dataset::LoadOptions;
use stegongp::ngp::camera::Camera;
use stegongp::ngp::data::{DatasetFormat, Split};

fn data_dir(name: &str) -> Option<PathBuf> {
    for base in ["/work/shared/data", "../shared/data", "../../shared/data"] {
        let p = Path::new(base).join(name);
        if p.is_dir() {
            return Some(p);
        }
    }
    println!("skipping: dataset {name} not found under ../shared/data");
    None
}

/// Distance from `p` to the ray through the principal point.
fn dist_to_axis(c: &Camera, p: [f32; 3]) -> f32 {
    let r = c.ray(c.cx, c.cy);
    let v = [p[0] - r.o[0], p[1] - r.o[1], p[2] - r.o[2]];
    let t = v[0] * r.d[0] + v[1] * r.d[1] + v[2] * r.d[2];
    let q = [v[0] - t * r.d[0], v[1] - t * r.d[1], v[2] - t * r.d[2]];
    (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt()
}

#[test]
fn lego_downscale_4() {
    let Some(dir) = data_dir("lego") else { return };
    let opts = LoadOptions {
        downscale: 4,
        ..Default::default()
    };
    let t0 = Instant::now();
    let train = stegongp::dataset::load(&dir, Split::Train, &opts).unwrap();
    println!(
        "lego train x4: {} frames in {:.2?}",
        train.frames.len(),
        t0.elapsed()
    );
    assert_eq!(train.frames.len(), 100);
    let t0 = Instant::now();
    let test = stegongp::dataset::load(&dir, Split::Test, &opts).unwrap();
    println!(
        "lego test x4: {} frames in {:.2?}",
        test.frames.len(),
        t0.elapsed()
    );
    assert_eq!(test.frames.len(), 200);
    assert_eq!((test.width, test.height), (200, 200));
    assert_eq!(test.format, DatasetFormat::NerfSynthetic);
    assert_eq!(test.aabb_scale, 1);
    assert!(test.has_alpha);
    assert_eq!(test.frames[0].file_path, "./test/r_0");
    assert_eq!(test.frames[199].file_path, "./test/r_199");
    // Val falls back to test.
    let (cams, meta) = stegongp::dataset::load_cameras(&dir, Split::Val, &opts).unwrap();
    assert_eq!(meta.n, 200);
    let c = &test.frames[0].camera;
    // 0.5·800 / tan(0.5·0.6911112) / 4.
    let f = 0.5 * 800.0 / (0.5f64 * 0.6911112070083618).tan() / 4.0;
    assert!((c.fx as f64 - f).abs() < 1e-3 && (c.fy as f64 - f).abs() < 1e-3);
    assert_eq!((c.cx, c.cy), (100.0, 100.0));
    assert_eq!(cams[0].c2w, c.c2w);
    // Every camera looks at the object centred at ngp (0.5, 0.5, 0.5), from ~4.03·0.33 away.
    for fr in train.frames.iter().chain(&test.frames) {
        let c = &fr.camera;
        assert!(dist_to_axis(c, [0.5; 3]) < 0.02, "{}", fr.file_path);
        let o = c.position();
        let r = ((o[0] - 0.5).powi(2) + (o[1] - 0.5).powi(2) + (o[2] - 0.5).powi(2)).sqrt();
        assert!((r - 4.031 * 0.33).abs() < 0.01, "{r}");
    }
    // Test views are on the upper hemisphere: nerf z ≥ 0 → ngp y ≥ 0.5.
    assert!(
        test.frames
            .iter()
            .all(|f| f.camera.position()[1] >= 0.5 - 1e-4)
    );
    // Images: corners are background (alpha 0), the centre is the opaque model.
    let img = &test.frames[0].image;
    assert_eq!(img.linear_premul(0, 0)[3], 0.0);
    assert!(img.linear_premul(100, 100)[3] > 0.99);
    // Compact: f16 RGBA, 8 bytes per pixel.
    assert_eq!(img.storage_bytes(), 200 * 200 * 8);
}

#[test]
fn fox_every_eighth_with_distortion() {
    let Some(dir) = data_dir("fox") else { return };
    let opts = LoadOptions {
        downscale: 4,
        ..Default::default()
    };
    let (test_cams, test_meta) = stegongp::dataset::load_cameras(&dir, Split::Test, &opts).unwrap();
    assert_eq!(
        test_meta.dropped.len(),
        17,
        "67 frames listed, 50 images present"
    );
    assert_eq!(test_meta.n, 7);
    assert_eq!(test_meta.file_paths[0], "images/0001.jpg");
    let t0 = Instant::now();
    let train = stegongp::dataset::load(&dir, Split::Train, &opts).unwrap();
    println!(
        "fox train x4: {} frames in {:.2?}",
        train.frames.len(),
        t0.elapsed()
    );
    assert_eq!(train.frames.len(), 43);
    assert_eq!(train.format, DatasetFormat::InstantNgp);
    assert_eq!((train.width, train.height), (270, 480));
    assert_eq!(train.aabb_scale, 4);
    assert_eq!(train.aabb(), ([-1.5; 3], [2.5; 3]));
    assert!(!train.has_alpha);
    let c = &train.frames[0].camera;
    assert!((c.fx - 1375.52 / 4.0).abs() < 1e-3 && (c.fy - 1374.49 / 4.0).abs() < 1e-3);
    assert!((c.cx - 554.558 / 4.0).abs() < 1e-3 && (c.cy - 965.268 / 4.0).abs() < 1e-3);
    let d = c.distortion.expect("fox has lens distortion");
    assert_eq!(
        (d.k1, d.k2, d.p1, d.p2),
        (0.0578421, -0.0805099, -0.000980296, 0.00015575)
    );
    // No frame appears in both splits.
    for f in &train.frames {
        assert!(!test_meta.file_paths.contains(&f.file_path));
    }
    // colmap2nerf centres the scene on the cameras' common focus: the optical axes pass
    // near the middle of the unit cube.
    let mut dists: Vec<f32> = train
        .frames
        .iter()
        .map(|f| dist_to_axis(&f.camera, [0.5; 3]))
        .chain(test_cams.iter().map(|c| dist_to_axis(c, [0.5; 3])))
        .collect();
    dists.sort_by(f32::total_cmp);
    println!(
        "fox: median axis distance to the cube centre {:.3}",
        dists[dists.len() / 2]
    );
    assert!(dists[dists.len() / 2] < 0.25);
    // A corner ray round-trips through the camera's projection (with distortion).
    let r = c.ray(3.5, 470.5);
    let p = [r.o[0] + r.d[0], r.o[1] + r.d[1], r.o[2] + r.d[2]];
    let q = c.project(p).unwrap();
    assert!(
        (q[0] - 3.5).abs() < 1e-2 && (q[1] - 470.5).abs() < 1e-2,
        "{q:?}"
    );
}

/// Full-size load time (run with `--ignored`): 100 frames of 800×800 RGBA8.
#[test]
#[ignore]
fn lego_full_size_timing() {
    let Some(dir) = data_dir("lego") else { return };
    let t0 = Instant::now();
    let train = stegongp::dataset::load(&dir, Split::Train, &LoadOptions::default()).unwrap();
    let bytes: usize = train.frames.iter().map(|f| f.image.storage_bytes()).sum();
    println!(
        "lego train x1: {} frames, {} MB in {:.2?}",
        train.frames.len(),
        bytes >> 20,
        t0.elapsed()
    );
    assert_eq!((train.width, train.height), (800, 800));
    assert_eq!(bytes, 100 * 800 * 800 * 4);
}

type V3 = [f64; 3];

fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn norm(a: V3) -> f64 {
    (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt()
}

fn mat_vec(r: &[[f64; 3]; 3], v: V3) -> V3 {
    [0, 1, 2].map(|i| r[i][0] * v[0] + r[i][1] * v[1] + r[i][2] * v[2])
}

fn mean(ps: &[V3]) -> V3 {
    let mut m = [0.0; 3];
    for p in ps {
        for k in 0..3 {
            m[k] += p[k] / ps.len() as f64;
        }
    }
    m
}

/// Best-fit similarity b ≈ s·R·a + t (Horn's quaternion method; the largest eigenvector by
/// shifted power iteration). Returns (s, R, t).
fn similarity(a: &[V3], b: &[V3]) -> (f64, [[f64; 3]; 3], V3) {
    let (ma, mb) = (mean(a), mean(b));
    let mut s = [[0.0; 3]; 3];
    for (p, q) in a.iter().zip(b) {
        let (p, q) = (sub(*p, ma), sub(*q, mb));
        for i in 0..3 {
            for j in 0..3 {
                s[i][j] += p[i] * q[j];
            }
        }
    }
    let [[xx, xy, xz], [yx, yy, yz], [zx, zy, zz]] = s;
    let n = [
        [xx + yy + zz, yz - zy, zx - xz, xy - yx],
        [yz - zy, xx - yy - zz, xy + yx, zx + xz],
        [zx - xz, xy + yx, -xx + yy - zz, yz + zy],
        [xy - yx, zx + xz, yz + zy, -xx - yy + zz],
    ];
    let shift: f64 = n.iter().flatten().map(|v| v * v).sum::<f64>().sqrt();
    let mut q = [1.0, 0.1, 0.2, 0.3];
    for _ in 0..20000 {
        let mut r = [0.0; 4];
        for i in 0..4 {
            r[i] = shift * q[i] + (0..4).map(|j| n[i][j] * q[j]).sum::<f64>();
        }
        let l = r.iter().map(|v| v * v).sum::<f64>().sqrt();
        q = r.map(|v| v / l);
    }
    let rot = stegongp::ngp::geometry::quat_to_rotation(q);
    let (mut num, mut den) = (0.0, 0.0);
    for (p, qq) in a.iter().zip(b) {
        let ra = mat_vec(&rot, sub(*p, ma));
        let d = sub(*qq, mb);
        num += ra[0] * d[0] + ra[1] * d[1] + ra[2] * d[2];
        den += norm(sub(*p, ma)).powi(2);
    }
    let sc = num / den;
    let t = sub(mb, mat_vec(&rot, ma).map(|v| v * sc));
    (sc, rot, t)
}

/// Every camera of a dataset (train and test) by image file name.
fn all_cameras(dir: &Path, opts: &LoadOptions) -> Vec<(String, Camera)> {
    let mut v = Vec::new();
    for split in [Split::Train, Split::Test] {
        let (cams, meta) = stegongp::dataset::load_cameras(dir, split, opts).unwrap();
        for (p, c) in meta.file_paths.iter().zip(cams) {
            let name = Path::new(p)
                .file_name()
                .unwrap()
                .to_string_lossy()
                .into_owned();
            v.push((name, c));
        }
    }
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}

fn assert_same_cameras(a: &[(String, Camera)], b: &[(String, Camera)], tol: f32) {
    assert_eq!(a.len(), b.len());
    for ((na, x), (nb, y)) in a.iter().zip(b) {
        assert_eq!(na, nb);
        for i in 0..3 {
            for j in 0..4 {
                assert!((x.c2w[i][j] - y.c2w[i][j]).abs() <= tol, "{na}");
            }
        }
        for (p, q) in [(x.fx, y.fx), (x.fy, y.fy), (x.cx, y.cx), (x.cy, y.cy)] {
            assert!((p - q).abs() <= tol * p.abs().max(1.0), "{na}: {p} vs {q}");
        }
        assert_eq!(x.distortion, y.distortion);
        assert_eq!((x.width, x.height), (y.width, y.height));
    }
}

/// `stegongp convert` into a temporary folder; the file loads back (instant-ngp path) into
/// the cameras the capture loads into directly.
fn convert_round_trip(dir: &Path) -> String {
    let t = tempfile::tempdir().unwrap();
    let out = t.path().join("transforms.json");
    let r = std::process::Command::new(env!("CARGO_BIN_EXE_stegongp"))
        .args([
            "convert",
            dir.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let o = LoadOptions::default();
    let back = all_cameras(&out, &o);
    assert_same_cameras(&back, &all_cameras(dir, &o), 1e-5);
    for split in [Split::Train, Split::Test] {
        let (_, a) = stegongp::dataset::load_cameras(&out, split, &o).unwrap();
        let (_, b) = stegongp::dataset::load_cameras(dir, split, &o).unwrap();
        assert_eq!(a.format, DatasetFormat::InstantNgp);
        assert_eq!(a.n, b.n, "same split");
    }
    String::from_utf8_lossy(&r.stdout).trim().to_string()
}

#[test]
fn fox_colmap_binary_and_text_agree_with_fox_transforms() {
    let Some(dir) = data_dir("fox-colmap") else {
        return;
    };
    let o = LoadOptions::default();
    let t0 = Instant::now();
    let bin = all_cameras(&dir, &o);
    println!("fox-colmap (binary) cameras in {:.2?}", t0.elapsed());
    let t0 = Instant::now();
    let txt = all_cameras(&dir.join("sparse_txt/0"), &o);
    println!("fox-colmap (text) cameras in {:.2?}", t0.elapsed());
    assert_eq!(bin.len(), 50);
    // The text model prints the binary's doubles with 17 digits: the same cameras.
    assert_same_cameras(&bin, &txt, 1e-6);
    // The folder COLMAP's mapper was given (model 0 in its `0/`) names the same model.
    assert_same_cameras(&txt, &all_cameras(&dir.join("sparse_txt"), &o), 0.0);
    let (test, meta) = stegongp::dataset::load_cameras(&dir, Split::Test, &o).unwrap();
    assert_eq!(meta.format, DatasetFormat::Colmap);
    assert_eq!(meta.images_dir.as_deref(), Some("images"));
    assert_eq!((meta.n, meta.aabb_scale), (7, 16));
    assert_eq!(meta.file_paths[0], "images/0001.jpg");
    // fox's 50 photos are numbered with gaps: the 9th is 0012.jpg.
    assert_eq!(meta.file_paths[1], "images/0012.jpg");
    let c = &test[0];
    assert_eq!((c.width, c.height), (1080, 1920));
    let d = c.distortion.expect("OPENCV camera");
    assert!(d.k1 > 0.05 && d.k2 < -0.07, "{d:?}");
    let imported = stegongp::dataset::import_capture(&dir, None).unwrap();
    let pts = imported.points.expect("points3D.bin");
    println!(
        "fox-colmap: {} points, bbox {:?} .. {:?} (COLMAP world)",
        pts.count, pts.min, pts.max
    );
    assert!(pts.count > 1000);

    // Against fox/transforms.json (another COLMAP run through colmap2nerf): focal lengths
    // within 2 %, and the camera centres the same up to a similarity.
    let Some(fox) = data_dir("fox") else { return };
    let reference = all_cameras(&fox, &o);
    // The same views held out as fox's (natural and byte order agree on these names).
    let (_, fox_test) = stegongp::dataset::load_cameras(&fox, Split::Test, &o).unwrap();
    assert_eq!(fox_test.file_paths, meta.file_paths);
    assert_eq!(reference.len(), 50);
    let mut a = Vec::new();
    let mut b = Vec::new();
    let mut ra = Vec::new();
    let mut rb = Vec::new();
    for ((na, x), (nb, y)) in bin.iter().zip(&reference) {
        assert_eq!(na, nb);
        assert!(
            (x.fx / y.fx - 1.0).abs() < 0.02,
            "{na}: fx {} vs {}",
            x.fx,
            y.fx
        );
        assert!(
            (x.fy / y.fy - 1.0).abs() < 0.02,
            "{na}: fy {} vs {}",
            x.fy,
            y.fy
        );
        a.push(x.position().map(|v| v as f64));
        b.push(y.position().map(|v| v as f64));
        ra.push(x.c2w.map(|r| [r[0] as f64, r[1] as f64, r[2] as f64]));
        rb.push(y.c2w.map(|r| [r[0] as f64, r[1] as f64, r[2] as f64]));
    }
    let (s, r, t) = similarity(&a, &b);
    let mb = mean(&b);
    let size = (b.iter().map(|p| norm(sub(*p, mb)).powi(2)).sum::<f64>() / b.len() as f64).sqrt();
    let rms = (a
        .iter()
        .zip(&b)
        .map(|(p, q)| {
            let m = mat_vec(&r, *p).map(|v| v * s);
            norm(sub([m[0] + t[0], m[1] + t[1], m[2] + t[2]], *q)).powi(2)
        })
        .sum::<f64>()
        / a.len() as f64)
        .sqrt();
    // Orientation residual: angle between R·R_a and R_b per camera.
    let mut worst = 0.0f64;
    for (x, y) in ra.iter().zip(&rb) {
        let mut tr = 0.0;
        for k in 0..3 {
            let col = mat_vec(&r, [x[0][k], x[1][k], x[2][k]]);
            tr += col[0] * y[0][k] + col[1] * y[1][k] + col[2] * y[2][k];
        }
        worst = worst.max(((tr - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees());
    }
    println!(
        "fox-colmap vs fox: similarity scale {s:.4}, centre RMS {rms:.4} = {:.2} % of the \
         camera spread {size:.3}, worst orientation {worst:.3}°",
        100.0 * rms / size
    );
    assert!(rms / size < 0.05, "{}", rms / size);
    assert!(worst < 2.0, "{worst}");
    println!("convert: {}", convert_round_trip(&dir));
}

#[test]
fn flower_llff_images_8() {
    let Some(dir) = data_dir("flower") else {
        return;
    };
    let o = LoadOptions::default();
    let rows = stegongp::dataset::llff::read_poses_bounds(&dir.join("poses_bounds.npy")).unwrap();
    assert_eq!(rows.len(), 34);
    let (h, w, f) = (rows[0][4], rows[0][9], rows[0][14]);
    assert_eq!((h, w), (3024.0, 4032.0));
    let t0 = Instant::now();
    let (test, meta) = stegongp::dataset::load_cameras(&dir, Split::Test, &o).unwrap();
    println!("flower test cameras in {:.2?}", t0.elapsed());
    assert_eq!(meta.format, DatasetFormat::Llff);
    assert_eq!(
        meta.images_dir.as_deref(),
        Some("images_8"),
        "picked by itself"
    );
    assert_eq!(meta.n, 5);
    assert_eq!(meta.file_paths[0], "images_8/image000.png");
    assert_eq!(meta.file_paths[4], "images_8/image032.png");
    let c = &test[0];
    assert_eq!((c.width, c.height), (504, 378));
    let fx = f * 504.0 / 4032.0;
    println!("flower: focal {f:.2} px at 4032 → {fx:.3} px at 504");
    assert!((c.fx as f64 - fx).abs() < 1e-3 && (c.fy as f64 - fx).abs() < 1e-3);
    assert_eq!((c.cx, c.cy), (252.0, 189.0));
    assert!(c.distortion.is_none());
    let t0 = Instant::now();
    let train = stegongp::dataset::load(&dir, Split::Train, &o).unwrap();
    println!(
        "flower train: {} images in {:.2?}",
        train.frames.len(),
        t0.elapsed()
    );
    assert_eq!(train.frames.len(), 29);
    assert_eq!(
        (train.width, train.height, train.aabb_scale),
        (504, 378, 16)
    );
    assert!(!train.has_alpha);
    // Forward-facing: every camera looks the same way, towards the recentred focus.
    let fwd0 = train.frames[0].camera.axis(2);
    for fr in &train.frames {
        let d = fr.camera.axis(2);
        let cos = d[0] * fwd0[0] + d[1] * fwd0[1] + d[2] * fwd0[2];
        assert!(cos > 0.95, "{}: {cos}", fr.file_path);
    }
    println!("convert: {}", convert_round_trip(&dir));
}
