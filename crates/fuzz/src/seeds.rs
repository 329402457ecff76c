//! Real seeds, made by the project's own writers where it has them (snapshots, key files,
//! camera paths, PNGs) and by the formats' specifications where it only reads them (COLMAP
//! binary and text models, `poses_bounds.npy`, a baseline JPEG). Every seed loads without
//! error: a mutation starts from an input that reaches deep into its parser.

use ngp::network::ModelConfig;
use ngp::snapshot::{self, DatasetImage, Snapshot, SnapshotDataset};
use serde_json::json;
use stego::{DenseMode, Key, KeyScheme};
use viewer::path::{CameraPath, NerfFrame, SceneRig};

/// One input: files by relative path (a dataset is several).
pub type Case = Vec<(String, Vec<u8>)>;

fn file(name: &str, bytes: Vec<u8>) -> (String, Vec<u8>) {
    (name.to_string(), bytes)
}

/// A small grid: 4 levels, T = 2^10, so a snapshot is a few tens of KB.
pub fn tiny_config(aabb_scale: u32) -> ModelConfig {
    ModelConfig {
        grid: ngp::encoding::layout::GridConfig {
            n_levels: 4,
            n_features: 2,
            log2_hashmap_size: 10,
            base_resolution: 4,
        },
        aabb_scale,
    }
}

fn tiny_snapshot(aabb_scale: u32, with_dataset: bool) -> Snapshot {
    let config = tiny_config(aabb_scale);
    let net = ngp::network::nerf::NerfNetwork::new(config).expect("a valid tiny config");
    let params = net.init_params(5);
    let mut s = Snapshot::new(config, params, Vec::new());
    s.training_step = 17;
    s.loss = 0.25;
    if with_dataset {
        let images = (0..2)
            .map(|i| DatasetImage::new([8, 6], [7.0, 7.0], pose(i as f32)))
            .collect();
        s.dataset = Some(SnapshotDataset::new(
            vec!["a.png".into(), "b.png".into()],
            images,
            aabb_scale,
        ));
    }
    s
}

/// A camera 2 units from the box centre, turned by `a` radians about +y, looking at it.
fn pose(a: f32) -> [[f32; 4]; 3] {
    let (s, c) = a.sin_cos();
    [
        [c, 0.0, s, 0.5 + 2.0 * s],
        [0.0, 1.0, 0.0, 0.5],
        [-s, 0.0, c, 0.5 + 2.0 * c],
    ]
}

pub fn snapshots() -> Vec<Case> {
    let mut out = Vec::new();
    for (aabb, ds) in [(1, true), (4, false)] {
        let s = tiny_snapshot(aabb, ds);
        out.push(vec![file(
            "model.msgpack",
            snapshot::to_bytes(&s, false).expect("a snapshot serialises"),
        )]);
        out.push(vec![file(
            "model.ingp",
            snapshot::to_bytes(&s, true).expect("a snapshot serialises"),
        )]);
    }
    out
}

pub fn keys() -> Vec<Case> {
    let schemes = [
        KeyScheme::Primes {
            keys: vec![[10_000_019, 10_000_079, 10_000_103]],
        },
        KeyScheme::Prf {
            secrets: vec![[7; 32], [9; 32]],
        },
        KeyScheme::PrfShares {
            secret: [3; 32],
            m: 4,
        },
    ];
    let mut out = Vec::new();
    for (i, scheme) in schemes.into_iter().enumerate() {
        let mut key = Key::new(scheme, DenseMode::Permute).expect("a valid fixed key");
        if i == 1 {
            key = key.with_scene_box(Some(4)).expect("a valid box");
        }
        let text = serde_json::to_vec_pretty(&stego::keyfile::key_to_json(&key))
            .expect("a key serialises");
        out.push(vec![file("key.json", text)]);
    }
    out
}

/// An `w`×`h` RGBA PNG with a gradient (alpha varies too).
pub fn png(w: u32, h: u32, alpha: bool) -> Vec<u8> {
    let mut out = Vec::new();
    {
        let mut e = png::Encoder::new(&mut out, w, h);
        e.set_color(if alpha {
            png::ColorType::Rgba
        } else {
            png::ColorType::Rgb
        });
        e.set_depth(png::BitDepth::Eight);
        let mut wr = e.write_header().expect("writing to memory");
        let ch = if alpha { 4 } else { 3 };
        let px: Vec<u8> = (0..w * h * ch).map(|i| (i * 37 % 251) as u8).collect();
        wr.write_image_data(&px).expect("writing to memory");
    }
    out
}

/// A baseline JPEG's markers up to its scan's start, `w`×`h`, one grey component: one
/// quantisation table of ones, one-code Huffman tables (DC category 0; AC end-of-block).
/// The entropy-coded data is the caller's.
pub fn jpeg_header(w: u16, h: u16) -> Vec<u8> {
    let mut j = vec![0xff, 0xd8];
    j.extend([0xff, 0xdb, 0x00, 0x43, 0x00]);
    j.extend([1u8; 64]);
    j.extend([0xff, 0xc0, 0x00, 0x0b, 0x08]);
    j.extend(h.to_be_bytes());
    j.extend(w.to_be_bytes());
    j.extend([0x01, 0x01, 0x11, 0x00]);
    for class in [0x00u8, 0x10] {
        j.extend([0xff, 0xc4, 0x00, 0x14, class, 0x01]);
        j.extend([0u8; 15]);
        j.push(0x00);
    }
    j.extend([0xff, 0xda, 0x00, 0x08, 0x01, 0x01, 0x00, 0x00, 0x3f, 0x00]);
    j
}

/// A baseline JPEG, `w`×`h`, grey: the smallest file the decoder fully reads (one
/// quantisation table, one-code Huffman tables, every block a DC of 0 and an end-of-block).
pub fn jpeg_sized(w: u16, h: u16) -> Vec<u8> {
    let mut j = jpeg_header(w, h);
    // Two zero bits a block (DC code '0', EOB code '0'), the last byte padded with ones.
    let blocks = (w as usize).div_ceil(8) * (h as usize).div_ceil(8);
    let bits = 2 * blocks;
    j.extend(std::iter::repeat_n(0u8, bits / 8));
    if !bits.is_multiple_of(8) {
        j.push(0xffu8 >> (bits % 8));
    }
    j.extend([0xff, 0xd9]);
    j
}

pub fn jpeg() -> Vec<u8> {
    jpeg_sized(8, 8)
}

pub fn images() -> Vec<Case> {
    vec![
        vec![file("a.png", png(5, 4, true))],
        vec![file("a.png", png(3, 7, false))],
        vec![file("a.jpg", jpeg())],
    ]
}

fn transform_matrix(a: f32) -> serde_json::Value {
    let m = pose(a);
    json!([m[0], m[1], m[2], [0.0, 0.0, 0.0, 1.0]])
}

/// instant-ngp's dialect (intrinsics at the top, `transforms.json`) and NeRF-synthetic's
/// (`camera_angle_x`, one file per split, paths without extension).
pub fn transforms() -> Vec<Case> {
    let frames: Vec<_> = (0..3)
        .map(|i| json!({"file_path": format!("images/{i}.png"), "transform_matrix": transform_matrix(i as f32)}))
        .collect();
    let ngp = json!({
        "fl_x": 7.0, "fl_y": 7.0, "cx": 4.0, "cy": 3.0, "w": 8, "h": 6,
        "k1": 0.01, "p1": 0.0, "aabb_scale": 4, "scale": 0.33, "offset": [0.5, 0.5, 0.5],
        "frames": frames,
    });
    let mut a: Case = vec![file(
        "transforms.json",
        serde_json::to_vec_pretty(&ngp).expect("JSON"),
    )];
    for i in 0..3 {
        a.push(file(&format!("images/{i}.png"), png(8, 6, false)));
    }
    let split = |n: usize, off: usize| {
        let frames: Vec<_> = (0..n)
            .map(|i| json!({"file_path": format!("./r_{}", i + off), "rotation": 0.0, "transform_matrix": transform_matrix(i as f32)}))
            .collect();
        serde_json::to_vec_pretty(&json!({"camera_angle_x": 0.69, "frames": frames})).expect("JSON")
    };
    let mut b: Case = vec![
        file("transforms_train.json", split(2, 0)),
        file("transforms_test.json", split(1, 2)),
    ];
    for i in 0..3 {
        b.push(file(&format!("r_{i}.png"), png(6, 6, true)));
    }
    vec![a, b]
}

/// Three cameras on a circle looking at the origin, in COLMAP's world-to-camera form.
fn colmap_poses() -> Vec<([f64; 4], [f64; 3])> {
    (0..3)
        .map(|i| {
            let a = i as f64 * 0.4;
            // Rotation about y by −a as a quaternion, and t = −R·C with C on the circle.
            let q = [(a / 2.0).cos(), 0.0, -(a / 2.0).sin(), 0.0];
            let c = [3.0 * a.sin(), 0.0, -3.0 * a.cos()];
            let (s, co) = (-a).sin_cos();
            let r = [[co, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, co]];
            let t = [0, 1, 2].map(|k| -(r[k][0] * c[0] + r[k][1] * c[1] + r[k][2] * c[2]));
            (q, t)
        })
        .collect()
}

pub fn colmap() -> Vec<Case> {
    let poses = colmap_poses();
    // Binary model: cameras (OPENCV, id 4), images with two 2-D points each, points.
    let mut cams = Vec::new();
    cams.extend(1u64.to_le_bytes());
    cams.extend(1i32.to_le_bytes());
    cams.extend(4i32.to_le_bytes());
    cams.extend(8u64.to_le_bytes());
    cams.extend(6u64.to_le_bytes());
    for p in [7.0f64, 7.0, 4.0, 3.0, 0.01, 0.0, 0.0, 0.0] {
        cams.extend(p.to_le_bytes());
    }
    let mut imgs = Vec::new();
    imgs.extend((poses.len() as u64).to_le_bytes());
    for (i, (q, t)) in poses.iter().enumerate() {
        imgs.extend((i as i32 + 1).to_le_bytes());
        for v in q.iter().chain(t) {
            imgs.extend(v.to_le_bytes());
        }
        imgs.extend(1i32.to_le_bytes());
        imgs.extend(format!("{i}.png").as_bytes());
        imgs.push(0);
        imgs.extend(2u64.to_le_bytes());
        for k in 0..2i64 {
            imgs.extend(1.5f64.to_le_bytes());
            imgs.extend(2.5f64.to_le_bytes());
            imgs.extend((k + 1).to_le_bytes());
        }
    }
    let mut pts = Vec::new();
    pts.extend(2u64.to_le_bytes());
    for k in 0..2u64 {
        pts.extend((k + 1).to_le_bytes());
        for v in [0.1f64 * k as f64, 0.2, -0.1] {
            pts.extend(v.to_le_bytes());
        }
        pts.extend([200u8, 100, 50]);
        pts.extend(0.5f64.to_le_bytes());
        pts.extend(2u64.to_le_bytes());
        for im in 1..=2i32 {
            pts.extend(im.to_le_bytes());
            pts.extend((k as i32).to_le_bytes());
        }
    }
    let mut bin: Case = vec![
        file("sparse/0/cameras.bin", cams),
        file("sparse/0/images.bin", imgs),
        file("sparse/0/points3D.bin", pts),
    ];
    // Text model of the same capture.
    let cams_txt = "# Camera list\n1 OPENCV 8 6 7 7 4 3 0.01 0 0 0\n".to_string();
    let mut imgs_txt = String::from("# Image list\n");
    for (i, (q, t)) in poses.iter().enumerate() {
        imgs_txt += &format!(
            "{} {} {} {} {} {} {} {} 1 {i}.png\n1.5 2.5 1 3.5 4.5 -1\n",
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
    let pts_txt = "# 3D points\n1 0 0.2 -0.1 200 100 50 0.5 1 0 2 0\n";
    let mut txt: Case = vec![
        file("sparse/0/cameras.txt", cams_txt.into_bytes()),
        file("sparse/0/images.txt", imgs_txt.into_bytes()),
        file("sparse/0/points3D.txt", pts_txt.as_bytes().to_vec()),
    ];
    for case in [&mut bin, &mut txt] {
        for i in 0..3 {
            case.push(file(&format!("images/{i}.png"), png(8, 6, false)));
        }
    }
    vec![bin, txt]
}

/// `poses_bounds.npy`: N×17 little-endian f64 (a 3×5 [R | t | h w f] per image, then the
/// near and far bounds), as LLFF's imgs2poses writes it.
pub fn npy_poses_bounds(rows: &[[f64; 17]]) -> Vec<u8> {
    let dict = format!(
        "{{'descr': '<f8', 'fortran_order': False, 'shape': ({}, 17), }}",
        rows.len()
    );
    let mut header = dict.into_bytes();
    // Magic (6) + version (2) + length (2) + header, padded with spaces to 64, then '\n'.
    while !(10 + header.len() + 1).is_multiple_of(64) {
        header.push(b' ');
    }
    header.push(b'\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend((header.len() as u16).to_le_bytes());
    out.extend(header);
    for r in rows {
        for v in r {
            out.extend(v.to_le_bytes());
        }
    }
    out
}

pub fn llff() -> Vec<Case> {
    let rows: Vec<[f64; 17]> = (0..3)
        .map(|i| {
            let a = i as f64 * 0.1;
            let (s, c) = a.sin_cos();
            // LLFF's columns are [down, right, back]; camera i a little to the side.
            let r = [[0.0, c, s], [-1.0, 0.0, 0.0], [0.0, -s, c]];
            let t = [0.2 * i as f64, 0.0, 0.0];
            let mut row = [0.0; 17];
            for k in 0..3 {
                row[k * 5..k * 5 + 3].copy_from_slice(&r[k]);
                row[k * 5 + 3] = t[k];
            }
            row[4] = 6.0;
            row[9] = 8.0;
            row[14] = 7.0;
            row[15] = 1.0;
            row[16] = 10.0;
            row
        })
        .collect();
    let mut case: Case = vec![file("poses_bounds.npy", npy_poses_bounds(&rows))];
    for i in 0..3 {
        case.push(file(&format!("images/{i}.png"), png(8, 6, false)));
    }
    vec![case]
}

pub fn pairs() -> Vec<Case> {
    let docs = [
        json!(["covers/a:hidden/b", "c:d"]),
        json!({"pairs": [{"cover": "a", "hidden": "b"}]}),
        json!([{"cover": "x/y", "hidden": "z"}, "p:q"]),
    ];
    docs.iter()
        .map(|d| vec![file("pairs.json", serde_json::to_vec(d).expect("JSON"))])
        .collect()
}

pub fn camera_paths() -> Vec<Case> {
    let rig = SceneRig::default_object();
    let path = CameraPath {
        cameras: rig.orbit(4),
        fps: 24.0,
        size: Some((64, 48)),
    };
    let ns = viewer::path::nerfstudio_json(&path, 64, 48, &NerfFrame::default());
    let ingp = viewer::path::instant_ngp_json(&path);
    vec![
        vec![file(
            "camera_path.json",
            serde_json::to_vec_pretty(&ns).expect("JSON"),
        )],
        vec![file(
            "base_cam.json",
            serde_json::to_vec_pretty(&ingp).expect("JSON"),
        )],
    ]
}
