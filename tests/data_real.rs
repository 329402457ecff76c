//! Loader checks on the real datasets in ../shared/data (skipped when absent).

use std::path::{Path, PathBuf};
use std::time::Instant;

use stegongp::ngp::camera::Camera;
use stegongp::ngp::data::{Dataset, DatasetFormat, LoadOptions, Split};

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
    let train = Dataset::load(&dir, Split::Train, &opts).unwrap();
    println!(
        "lego train x4: {} frames in {:.2?}",
        train.frames.len(),
        t0.elapsed()
    );
    assert_eq!(train.frames.len(), 100);
    let t0 = Instant::now();
    let test = Dataset::load(&dir, Split::Test, &opts).unwrap();
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
    let (cams, meta) = Dataset::load_cameras(&dir, Split::Val, &opts).unwrap();
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
    let (test_cams, test_meta) = Dataset::load_cameras(&dir, Split::Test, &opts).unwrap();
    assert_eq!(
        test_meta.dropped.len(),
        17,
        "67 frames listed, 50 images present"
    );
    assert_eq!(test_meta.n, 7);
    assert_eq!(test_meta.file_paths[0], "images/0001.jpg");
    let t0 = Instant::now();
    let train = Dataset::load(&dir, Split::Train, &opts).unwrap();
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
    let train = Dataset::load(&dir, Split::Train, &LoadOptions::default()).unwrap();
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
