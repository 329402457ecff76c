//! COLMAP (binary and text) and LLFF import on a generated scene whose poses are known:
//! the model files are written here from the scene's cameras, imported, and compared with
//! the poses they came from (up to the similarity colmap2nerf applies) and with each other.
//! Then bad input, through the library and the command line.
#![allow(clippy::needless_range_loop)]
// A test reads as one story; the 120-line limit (clippy.toml) is the program's.
#![allow(clippy::too_many_lines)]

use std::path::{Path, PathBuf};
use std::process::Command;
use testkit::geometry::rot_to_quat;

use npyz::WriterBuilder;
use serde_json::Value;
use stegongp::dataset::colmap2nerf::{
    ImportCamera, ImportFrame, ImportedScene, colmap_c2w, to_transforms,
};
use stegongp::dataset::{LoadOptions, import_capture};
use stegongp::ngp::camera::Camera;
use stegongp::ngp::data::{DatasetFormat, Split};
use stegongp::synth::{CAMERA_ANGLE_X, SceneKind, SynthOptions, generate};

const RES: u32 = 32;
const N: usize = 12;

type M3 = [[f64; 3]; 3];

/// One known camera: OpenCV camera-to-world (right, down, forward) in the generated
/// scene's world, which plays COLMAP's world here.
struct Known {
    c2w: [[f64; 4]; 3],
    name: String,
}

fn focal() -> f64 {
    0.5 * RES as f64 / (0.5 * CAMERA_ANGLE_X as f64).tan()
}

/// World-to-camera (q, t) of an OpenCV camera-to-world.
fn w2c(c2w: &[[f64; 4]; 3]) -> ([f64; 4], [f64; 3]) {
    let mut r = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            r[i][j] = c2w[j][i];
        }
    }
    let c = [c2w[0][3], c2w[1][3], c2w[2][3]];
    let t = [0, 1, 2].map(|i| -(r[i][0] * c[0] + r[i][1] * c[1] + r[i][2] * c[2]));
    (rot_to_quat(&r), t)
}

fn read_png(p: &Path) -> (u32, u32, Vec<u8>) {
    let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(p).unwrap()));
    let mut r = dec.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    let info = r.next_frame(&mut buf).unwrap();
    assert_eq!(info.color_type, png::ColorType::Rgba);
    buf.truncate(info.buffer_size());
    (info.width, info.height, buf)
}

fn write_png(p: &Path, w: u32, h: u32, rgba: &[u8]) {
    let f = std::fs::File::create(p).unwrap();
    let mut enc = png::Encoder::new(std::io::BufWriter::new(f), w, h);
    enc.set_color(png::ColorType::Rgba);
    enc.set_depth(png::BitDepth::Eight);
    let mut wr = enc.write_header().unwrap();
    wr.write_image_data(rgba).unwrap();
}

/// 2× box downscale of RGBA8.
fn half(w: u32, h: u32, px: &[u8]) -> Vec<u8> {
    let (w2, h2) = (w / 2, h / 2);
    let mut out = vec![0u8; (w2 * h2 * 4) as usize];
    for y in 0..h2 {
        for x in 0..w2 {
            for c in 0..4 {
                let mut s = 0u32;
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    s += px[(((2 * y + dy) * w + 2 * x + dx) * 4 + c) as usize] as u32;
                }
                out[((y * w2 + x) * 4 + c) as usize] = ((s + 2) / 4) as u8;
            }
        }
    }
    out
}

/// Generates the scene; returns its cameras, with images copied to `dir/images` (and a
/// half-size copy in `dir/images_2`) as `view_NN.png`.
fn scene(dir: &Path) -> Vec<Known> {
    let synth = dir.join("synth");
    generate(
        &SynthOptions {
            scene: SceneKind::Object,
            resolution: RES,
            n_train: N,
            n_val: 0,
            n_test: 1,
            seed: 11,
            ..Default::default()
        },
        &synth,
    )
    .unwrap();
    let t: Value = serde_json::from_str(
        &std::fs::read_to_string(synth.join("transforms_train.json")).unwrap(),
    )
    .unwrap();
    std::fs::create_dir_all(dir.join("images")).unwrap();
    std::fs::create_dir_all(dir.join("images_2")).unwrap();
    let mut out = Vec::new();
    for (i, f) in t["frames"].as_array().unwrap().iter().enumerate() {
        let m = &f["transform_matrix"];
        let mut c2w = [[0.0; 4]; 3];
        for r in 0..3 {
            for c in 0..4 {
                // OpenGL (right, up, back) → OpenCV (right, down, forward).
                let sign = if c == 1 || c == 2 { -1.0 } else { 1.0 };
                c2w[r][c] = sign * m[r][c].as_f64().unwrap();
            }
        }
        // Made exactly rigid (the JSON holds f32 values): what the models store.
        let (q, t) = w2c(&c2w);
        let c2w = colmap_c2w(q, t);
        let name = format!("view_{i:02}.png");
        let (w, h, px) = read_png(&synth.join(format!("train/r_{i}.png")));
        write_png(&dir.join("images").join(&name), w, h, &px);
        write_png(
            &dir.join("images_2").join(&name),
            w / 2,
            h / 2,
            &half(w, h, &px),
        );
        out.push(Known { c2w, name });
    }
    out
}

fn le_model(model: &Path, cams: &[Known], camera_id: i32) {
    std::fs::create_dir_all(model).unwrap();
    let f = focal();
    let mut b = Vec::new();
    b.extend(1u64.to_le_bytes());
    b.extend(camera_id.to_le_bytes());
    b.extend(1i32.to_le_bytes()); // PINHOLE
    b.extend((RES as u64).to_le_bytes());
    b.extend((RES as u64).to_le_bytes());
    for p in [f, f, RES as f64 / 2.0, RES as f64 / 2.0] {
        b.extend(p.to_le_bytes());
    }
    std::fs::write(model.join("cameras.bin"), b).unwrap();
    let mut b = Vec::new();
    b.extend((cams.len() as u64).to_le_bytes());
    // Written in reverse name order: the importer sorts by name.
    for (i, k) in cams.iter().enumerate().rev() {
        let (q, t) = w2c(&k.c2w);
        b.extend((i as i32 + 1).to_le_bytes());
        for v in q.iter().chain(&t) {
            b.extend(v.to_le_bytes());
        }
        b.extend(1i32.to_le_bytes());
        b.extend(k.name.as_bytes());
        b.push(0);
        b.extend(2u64.to_le_bytes());
        for p in 0..2 {
            b.extend((p as f64 * 3.5).to_le_bytes());
            b.extend(1.25f64.to_le_bytes());
            b.extend((if p == 0 { -1i64 } else { 0 }).to_le_bytes());
        }
    }
    std::fs::write(model.join("images.bin"), b).unwrap();
    let mut b = Vec::new();
    b.extend(2u64.to_le_bytes());
    for (id, xyz) in [(0u64, [-0.5f64, 0.1, 0.2]), (1, [0.4, -0.3, 0.6])] {
        b.extend(id.to_le_bytes());
        for v in xyz {
            b.extend(v.to_le_bytes());
        }
        b.extend([200u8, 100, 50]);
        b.extend(0.5f64.to_le_bytes());
        b.extend(1u64.to_le_bytes());
        b.extend(1i32.to_le_bytes());
        b.extend(1i32.to_le_bytes());
    }
    std::fs::write(model.join("points3D.bin"), b).unwrap();
}

fn text_model(model: &Path, cams: &[Known]) {
    std::fs::create_dir_all(model).unwrap();
    let f = focal();
    let c = RES as f64 / 2.0;
    std::fs::write(
        model.join("cameras.txt"),
        format!(
            "# Camera list with one line of data per camera:\n# Number of cameras: 1\n\
             1 OPENCV {RES} {RES} {f} {f} {c} {c} 0 0 0 0\n"
        ),
    )
    .unwrap();
    let mut s = String::from("# Image list with two lines of data per image:\n");
    for (i, k) in cams.iter().enumerate() {
        let (q, t) = w2c(&k.c2w);
        s += &format!(
            "{} {} {} {} {} {} {} {} 1 {}\n",
            i + 1,
            q[0],
            q[1],
            q[2],
            q[3],
            t[0],
            t[1],
            t[2],
            k.name
        );
        // Second line: points, or empty.
        s += if i % 2 == 0 {
            "1.5 2.5 -1 3.5 4.5 0\n"
        } else {
            "\n"
        };
    }
    std::fs::write(model.join("images.txt"), s).unwrap();
    std::fs::write(
        model.join("points3D.txt"),
        "# 3D point list\n0 -0.5 0.1 0.2 200 100 50 0.5 1 1\n1 0.4 -0.3 0.6 1 2 3 0.5 1 1\n",
    )
    .unwrap();
}

/// LLFF rows: [down, right, back | centre | H W focal] + near, far, for originals twice the
/// size of the images written (so the import has to scale by ½).
fn write_npy_f64(path: &Path, rows: &[Vec<f64>], cols: u64) {
    let mut w = npyz::WriteOptions::new()
        .default_dtype()
        .shape(&[rows.len() as u64, cols])
        .writer(std::fs::File::create(path).unwrap())
        .begin_nd()
        .unwrap();
    for r in rows {
        w.extend(r.iter().copied()).unwrap();
    }
    w.finish().unwrap();
}

fn llff_rows(cams: &[Known]) -> Vec<Vec<f64>> {
    let (hh, ww, f) = (2.0 * RES as f64, 2.0 * RES as f64, 2.0 * focal());
    cams.iter()
        .map(|k| {
            let g = &k.c2w;
            let mut r = Vec::new();
            for i in 0..3 {
                r.extend([g[i][1], g[i][0], -g[i][2], g[i][3], [hh, ww, f][i]]);
            }
            // The cameras stand 4 from the origin they look at; near 3 and far 6 have the
            // harmonic mean 4, so the LLFF focus is that same origin.
            r.extend([3.0, 6.0]);
            r
        })
        .collect()
}

/// One scene folder holding a binary model in sparse/0, a text model in sparse_txt/0 and
/// (in a sibling folder) an LLFF capture of the same views.
struct Fixture {
    _tmp: tempfile::TempDir,
    cap: PathBuf,
    llff: PathBuf,
    known: Vec<Known>,
}

fn fixture() -> Fixture {
    let tmp = tempfile::tempdir().unwrap();
    let cap = tmp.path().join("cap");
    let known = scene(&cap);
    le_model(&cap.join("sparse/0"), &known, 1);
    text_model(&cap.join("sparse_txt/0"), &known);
    let llff = tmp.path().join("llff");
    std::fs::create_dir_all(&llff).unwrap();
    std::fs::rename(cap.join("synth"), tmp.path().join("synth")).unwrap();
    copy_dir(&cap.join("images"), &llff.join("images"));
    write_npy_f64(&llff.join("poses_bounds.npy"), &llff_rows(&known), 17);
    Fixture {
        _tmp: tmp,
        cap,
        llff,
        known,
    }
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
    }
}

fn opts() -> LoadOptions {
    LoadOptions::default()
}

fn cams(dir: &Path, split: Split, o: &LoadOptions) -> Vec<Camera> {
    stegongp::dataset::load_cameras(dir, split, o).unwrap().0
}

fn rot(c: &Camera) -> M3 {
    let m = c.c2w;
    [0, 1, 2].map(|i| [0, 1, 2].map(|j| m[i][j] as f64))
}

fn rel(a: &M3, b: &M3) -> M3 {
    // aᵀ b
    [0, 1, 2].map(|i| [0, 1, 2].map(|j| (0..3).map(|k| a[k][i] * b[k][j]).sum()))
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

fn pos(c: &Camera) -> [f64; 3] {
    c.position().map(|v| v as f64)
}

fn same_cameras(a: &[Camera], b: &[Camera], tol: f32) {
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        for i in 0..3 {
            for j in 0..4 {
                assert!(
                    (x.c2w[i][j] - y.c2w[i][j]).abs() <= tol,
                    "{:?} vs {:?}",
                    x.c2w,
                    y.c2w
                );
            }
        }
        for (p, q) in [(x.fx, y.fx), (x.fy, y.fy), (x.cx, y.cx), (x.cy, y.cy)] {
            assert!((p - q).abs() <= tol * p.abs().max(1.0), "{p} vs {q}");
        }
        assert_eq!((x.width, x.height), (y.width, y.height));
    }
}

#[test]
fn colmap_bin_text_and_llff_recover_the_known_poses() {
    let fx = fixture();
    // Binary and text models of the same cameras import identically.
    let bin = import_capture(&fx.cap, None).unwrap();
    let txt = import_capture(&fx.cap.join("sparse_txt/0"), None).unwrap();
    assert_eq!(bin.format, DatasetFormat::Colmap);
    assert_eq!(
        (bin.images_dir.as_str(), txt.images_dir.as_str()),
        ("images", "images")
    );
    assert_eq!(bin.root, fx.cap);
    assert_eq!(txt.root, fx.cap, "images/ two folders up from sparse_txt/0");
    assert_eq!(bin.points.as_ref().unwrap().count, 2);
    assert_eq!(bin.points, txt.points);
    assert_eq!(bin.points.as_ref().unwrap().min, [-0.5, -0.3, 0.2]);
    assert_eq!(bin.cameras.len(), 1);
    assert_eq!(bin.cameras, txt.cameras);
    for (a, b) in bin.frames.iter().zip(&txt.frames) {
        assert_eq!(a.name, b.name);
        for i in 0..3 {
            for j in 0..4 {
                assert!((a.c2w[i][j] - b.c2w[i][j]).abs() < 1e-12);
            }
        }
    }
    // Frames sorted by name; the model's world-to-camera inverts back to the known poses.
    for (f, k) in bin.frames.iter().zip(&fx.known) {
        assert_eq!(f.name, k.name);
        for i in 0..3 {
            for j in 0..4 {
                assert!((f.c2w[i][j] - k.c2w[i][j]).abs() < 1e-9, "{:?}", f.c2w);
            }
        }
    }
    // The same known poses handed to the conversion directly give the same JSON.
    let by_hand = ImportedScene {
        format: DatasetFormat::Colmap,
        source: fx.cap.clone(),
        root: fx.cap.clone(),
        images_dir: "images".into(),
        cameras: vec![ImportCamera {
            width: RES,
            height: RES,
            fx: focal(),
            fy: focal(),
            cx: RES as f64 / 2.0,
            cy: RES as f64 / 2.0,
            k1: 0.0,
            k2: 0.0,
            p1: 0.0,
            p2: 0.0,
        }],
        frames: fx
            .known
            .iter()
            .map(|k| ImportFrame {
                name: k.name.clone(),
                image_path: fx.cap.join("images").join(&k.name),
                camera: 0,
                c2w: k.c2w,
                depth_bounds: None,
            })
            .collect(),
        default_aabb_scale: 16,
        points: None,
    };
    let a = to_transforms(&bin, 16, &fx.cap);
    let b = to_transforms(&by_hand, 16, &fx.cap);
    let (a, b) = ((a.to_json(), a.norm), (b.to_json(), b.norm));
    assert!((a.1.scale - b.1.scale).abs() < 1e-9);
    let fa = a.0["frames"].as_array().unwrap();
    let fb = b.0["frames"].as_array().unwrap();
    for (x, y) in fa.iter().zip(fb) {
        assert_eq!(x["file_path"], y["file_path"]);
        for i in 0..4 {
            for j in 0..4 {
                let (p, q) = (
                    x["transform_matrix"][i][j].as_f64().unwrap(),
                    y["transform_matrix"][i][j].as_f64().unwrap(),
                );
                assert!((p - q).abs() < 1e-9);
            }
        }
    }
    assert_eq!(a.0["fl_x"], b.0["fl_x"]);
    assert_eq!(a.0["aabb_scale"], 16);
    assert!(a.0.get("sharpness").is_none() && fa[0].get("sharpness").is_none());

    // Loaded cameras: every 8th view held out (0 and 8), the rest for training.
    let o = opts();
    let (test, meta) = stegongp::dataset::load_cameras(&fx.cap, Split::Test, &o).unwrap();
    assert_eq!(meta.format, DatasetFormat::Colmap);
    assert_eq!(meta.images_dir.as_deref(), Some("images"));
    assert_eq!(meta.aabb_scale, 16);
    assert_eq!(
        meta.file_paths,
        vec!["images/view_00.png", "images/view_08.png"]
    );
    let train = cams(&fx.cap, Split::Train, &o);
    assert_eq!(train.len(), N - 2);
    assert!((test[0].fx as f64 - focal()).abs() < 1e-4);
    // All views in name order, to compare with the known poses.
    let (_, tm) = stegongp::dataset::load_cameras(&fx.cap, Split::Train, &o).unwrap();
    let mut all: Vec<(String, Camera)> = tm
        .file_paths
        .iter()
        .cloned()
        .zip(train.iter().cloned())
        .chain(meta.file_paths.iter().cloned().zip(test.iter().cloned()))
        .collect();
    all.sort_by(|a, b| a.0.cmp(&b.0));
    let all: Vec<Camera> = all.into_iter().map(|(_, c)| c).collect();
    // Relative rotations between cameras are unchanged (ngp axes are OpenCV's: right,
    // down, forward; the world rotation cancels in RᵢᵀRⱼ) and distance ratios too.
    let known_r: Vec<M3> = fx
        .known
        .iter()
        .map(|k| [0, 1, 2].map(|i| [0, 1, 2].map(|j| k.c2w[i][j])))
        .collect();
    let known_p: Vec<[f64; 3]> = fx
        .known
        .iter()
        .map(|k| [k.c2w[0][3], k.c2w[1][3], k.c2w[2][3]])
        .collect();
    let d01 = dist(pos(&all[0]), pos(&all[1])) / dist(known_p[0], known_p[1]);
    for i in 0..N {
        for j in 0..N {
            let (a, b) = (
                rel(&rot(&all[i]), &rot(&all[j])),
                rel(&known_r[i], &known_r[j]),
            );
            for r in 0..3 {
                for c in 0..3 {
                    assert!((a[r][c] - b[r][c]).abs() < 1e-4, "{i} {j}: {a:?} vs {b:?}");
                }
            }
            if i != j {
                let ratio = dist(pos(&all[i]), pos(&all[j])) / dist(known_p[i], known_p[j]);
                assert!(
                    (ratio / d01 - 1.0).abs() < 1e-4,
                    "{i} {j}: {ratio} vs {d01}"
                );
            }
        }
    }
    // The generated cameras all look at the origin: colmap2nerf's focus is that point,
    // which ngp puts at the centre of the unit cube; mean distance 4 · 0.33.
    let mean: f64 = all.iter().map(|c| dist(pos(c), [0.5; 3])).sum::<f64>() / N as f64;
    assert!((mean - 4.0 * 0.33).abs() < 1e-4, "{mean}");

    // Text model (its folder given directly) and LLFF give the same cameras.
    for split in [Split::Train, Split::Test] {
        let b = cams(&fx.cap, split, &o);
        same_cameras(&b, &cams(&fx.cap.join("sparse_txt/0"), split, &o), 1e-5);
        let (l, lm) = stegongp::dataset::load_cameras(&fx.llff, split, &o).unwrap();
        assert_eq!(lm.format, DatasetFormat::Llff);
        same_cameras(&b, &l, 1e-4);
    }

    // images_2: half-size images, intrinsics halved, same poses.
    let o2 = LoadOptions {
        images: Some("images_2".into()),
        ..Default::default()
    };
    let (h2, m2) = stegongp::dataset::load_cameras(&fx.cap, Split::Test, &o2).unwrap();
    assert_eq!(m2.images_dir.as_deref(), Some("images_2"));
    assert_eq!(m2.file_paths[0], "images_2/view_00.png");
    assert_eq!((h2[0].width, h2[0].height), (RES / 2, RES / 2));
    assert!((h2[0].fx as f64 - focal() / 2.0).abs() < 1e-4);
    assert!((h2[0].cx - RES as f32 / 4.0).abs() < 1e-5);
    assert_eq!(h2[0].c2w, test[0].c2w);

    // Pixels load too, and an aabb_scale override applies.
    let o8 = LoadOptions {
        aabb_scale: Some(8),
        ..Default::default()
    };
    let d = stegongp::dataset::load(&fx.cap, Split::Train, &o8).unwrap();
    assert_eq!((d.frames.len(), d.width, d.aabb_scale), (N - 2, RES, 8));
    assert_eq!(d.format, DatasetFormat::Colmap);
    same_cameras(&d.cameras(), &train, 0.0);

    // Both splits of one import (`train --checkpoints`) are the splits loaded one by one,
    // COLMAP and LLFF alike: the same frames, cameras and pixels.
    for cap in [&fx.cap, &fx.llff] {
        let mut capture = stegongp::dataset::Capture::new(cap, &o8);
        for split in [Split::Train, Split::Test] {
            let got = capture.load(split).unwrap();
            let one = stegongp::dataset::load(cap, split, &o8).unwrap();
            assert_eq!(got.split, split);
            assert_eq!(got.frames.len(), one.frames.len(), "{split}");
            same_cameras(&got.cameras(), &one.cameras(), 0.0);
            for (a, b) in got.frames.iter().zip(&one.frames) {
                assert_eq!(a.file_path, b.file_path);
                let px = |im: &stegongp::ngp::data::Image| {
                    (0..im.height)
                        .flat_map(|y| (0..im.width).map(move |x| im.linear_premul(x, y)))
                        .collect::<Vec<_>>()
                };
                assert!(
                    px(&a.image) == px(&b.image),
                    "{}: pixels differ",
                    a.file_path
                );
            }
        }
    }
}

#[test]
fn convert_writes_a_transforms_json_that_loads_back() {
    let fx = fixture();
    let bin = env!("CARGO_BIN_EXE_stegongp");
    let o = opts();
    // Written elsewhere (paths relative to the output's folder) and inside the capture.
    for (cap, out) in [
        (&fx.cap, fx.cap.parent().unwrap().join("elsewhere/t.json")),
        (&fx.llff, fx.llff.join("transforms.json")),
    ] {
        std::fs::create_dir_all(out.parent().unwrap()).unwrap();
        let r = Command::new(bin)
            .args([
                "convert",
                cap.to_str().unwrap(),
                "--out",
                out.to_str().unwrap(),
            ])
            .output()
            .unwrap();
        let msg = String::from_utf8_lossy(&r.stdout);
        assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
        assert!(
            msg.contains(&format!("{N} frames")) && msg.contains("aabb_scale 16"),
            "{msg}"
        );
        let v: Value = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
        let fp = v["frames"][0]["file_path"].as_str().unwrap();
        assert!(
            fp.ends_with("images/view_00.png") && !fp.starts_with('/'),
            "{fp}"
        );
        for split in [Split::Train, Split::Test] {
            let (a, am) = stegongp::dataset::load_cameras(&out, split, &o).unwrap();
            assert_eq!(am.format, DatasetFormat::InstantNgp);
            same_cameras(&a, &cams(cap, split, &o), 1e-6);
        }
    }
    // With transforms.json beside the LLFF model, the JSON wins.
    let (_, m) = stegongp::dataset::load_cameras(&fx.llff, Split::Train, &o).unwrap();
    assert_eq!(m.format, DatasetFormat::InstantNgp);
    // --json, --aabb-scale and --images.
    let out = fx.cap.join("t2.json");
    let r = Command::new(bin)
        .args([
            "convert",
            fx.cap.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--aabb-scale",
            "4",
            "--images",
            "images_2",
            "--json",
        ])
        .output()
        .unwrap();
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let s: Value = serde_json::from_slice(&r.stdout).unwrap();
    testkit::golden::assert_json_shape("convert", &s);
    assert_eq!(
        (s["aabb_scale"].as_u64(), s["frames"].as_u64()),
        (Some(4), Some(N as u64))
    );
    assert_eq!(s["images_dir"], "images_2");
    let v: Value = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert_eq!(v["w"].as_f64(), Some(RES as f64 / 2.0));
    assert_eq!(v["frames"][0]["file_path"], "images_2/view_00.png");
}

fn err_of<T>(r: stegongp::error::Result<T>) -> String {
    match r {
        Ok(_) => panic!("expected an error"),
        Err(e) => e.to_string(),
    }
}

fn has(msg: &str, needles: &[&str]) {
    for n in needles {
        assert!(msg.contains(n), "{msg:?} lacks {n:?}");
    }
}

#[test]
fn bad_colmap_models_are_refused_with_the_file_and_field() {
    let fx = fixture();
    let model = fx.cap.join("sparse/0");
    let load = |dir: &Path| stegongp::dataset::load_cameras(dir, Split::Train, &opts()).map(|_| ());
    let cams_bin = std::fs::read(model.join("cameras.bin")).unwrap();
    let imgs_bin = std::fs::read(model.join("images.bin")).unwrap();
    let pts_bin = std::fs::read(model.join("points3D.bin")).unwrap();
    let restore = || {
        std::fs::write(model.join("cameras.bin"), &cams_bin).unwrap();
        std::fs::write(model.join("images.bin"), &imgs_bin).unwrap();
        std::fs::write(model.join("points3D.bin"), &pts_bin).unwrap();
    };
    // Truncated at every length: an error naming the file, never a panic.
    for (file, bytes) in [
        ("cameras.bin", &cams_bin),
        ("images.bin", &imgs_bin),
        ("points3D.bin", &pts_bin),
    ] {
        let step = (bytes.len() / 97).max(1);
        for cut in (0..bytes.len()).step_by(step) {
            std::fs::write(model.join(file), &bytes[..cut]).unwrap();
            let e = err_of(load(&fx.cap));
            has(&e, &[file]);
        }
        restore();
    }
    let e = {
        std::fs::write(model.join("images.bin"), &imgs_bin[..imgs_bin.len() - 10]).unwrap();
        err_of(load(&fx.cap))
    };
    has(&e, &["images.bin", "truncated", "image 11", "2D points"]);
    restore();
    // An absurd count is refused before allocating.
    let mut b = imgs_bin.clone();
    b[..8].copy_from_slice(&u64::MAX.to_le_bytes());
    std::fs::write(model.join("images.bin"), &b).unwrap();
    has(
        &err_of(load(&fx.cap)),
        &["images.bin", "number of images", "cannot fit"],
    );
    restore();
    // Unknown and unsupported camera models.
    for (id, needle) in [
        (99i32, "unknown camera model id 99"),
        (5, "OPENCV_FISHEYE"),
        (6, "FULL_OPENCV"),
    ] {
        let mut b = cams_bin.clone();
        b[12..16].copy_from_slice(&id.to_le_bytes());
        std::fs::write(model.join("cameras.bin"), &b).unwrap();
        has(&err_of(load(&fx.cap)), &["cameras.bin", needle]);
    }
    restore();
    // A camera id no camera has.
    le_model(&model, &fx.known, 7);
    has(
        &err_of(load(&fx.cap)),
        &["images.bin", "camera_id 1 is not in"],
    );
    restore();
    // An image named in the model but missing on disk.
    std::fs::rename(
        fx.cap.join("images/view_03.png"),
        fx.cap.join("view_03.png"),
    )
    .unwrap();
    has(
        &err_of(load(&fx.cap)),
        &["images.bin", "view_03.png", "not found"],
    );
    std::fs::rename(
        fx.cap.join("view_03.png"),
        fx.cap.join("images/view_03.png"),
    )
    .unwrap();
    // A chosen image folder that does not exist.
    let o = LoadOptions {
        images: Some("images_4".into()),
        ..Default::default()
    };
    has(
        &err_of(stegongp::dataset::load_cameras(&fx.cap, Split::Train, &o).map(|_| ())),
        &["images_4", "not found"],
    );
    // A bad aabb_scale override.
    let o = LoadOptions {
        aabb_scale: Some(3),
        ..Default::default()
    };
    has(
        &err_of(stegongp::dataset::load_cameras(&fx.cap, Split::Train, &o).map(|_| ())),
        &["aabb_scale 3"],
    );

    // Text models: malformed lines name the line.
    let txt = fx.cap.join("sparse_txt/0");
    let cams_txt = std::fs::read_to_string(txt.join("cameras.txt")).unwrap();
    let imgs_txt = std::fs::read_to_string(txt.join("images.txt")).unwrap();
    std::fs::write(
        txt.join("cameras.txt"),
        cams_txt.replace("OPENCV 32", "OPENCV x32"),
    )
    .unwrap();
    has(&err_of(load(&txt)), &["cameras.txt", "line 3", "WIDTH"]);
    std::fs::write(
        txt.join("cameras.txt"),
        cams_txt.replace(" 0 0 0 0", " 0 0 0"),
    )
    .unwrap();
    has(
        &err_of(load(&txt)),
        &["cameras.txt", "line 3", "8 parameters"],
    );
    std::fs::write(
        txt.join("cameras.txt"),
        cams_txt.replace("OPENCV", "FULL_OPENCV"),
    )
    .unwrap();
    has(
        &err_of(load(&txt)),
        &["cameras.txt", "FULL_OPENCV", "not supported"],
    );
    std::fs::write(txt.join("cameras.txt"), &cams_txt).unwrap();
    let mut lines: Vec<String> = imgs_txt.lines().map(str::to_string).collect();
    lines[3] = lines[3].replacen(' ', " nan-ish ", 1);
    std::fs::write(txt.join("images.txt"), lines.join("\n")).unwrap();
    has(&err_of(load(&txt)), &["images.txt", "line 4", "QW"]);
    let mut lines: Vec<String> = imgs_txt.lines().map(str::to_string).collect();
    lines[1] = "1 1 0 0 0 0 0 0 1".into();
    std::fs::write(txt.join("images.txt"), lines.join("\n")).unwrap();
    has(&err_of(load(&txt)), &["images.txt", "line 2", "NAME"]);
    std::fs::write(txt.join("images.txt"), &imgs_txt).unwrap();

    // A folder with nothing recognisable lists what was looked for.
    let empty = fx.cap.join("images");
    has(
        &err_of(load(&empty)),
        &["transforms.json", "poses_bounds.npy", "sparse/0", "cameras"],
    );
}

#[test]
fn bad_llff_captures_are_refused() {
    let fx = fixture();
    let npy = fx.llff.join("poses_bounds.npy");
    let load = || stegongp::dataset::load_cameras(&fx.llff, Split::Train, &opts()).map(|_| ());
    // Wrong shape.
    let rows: Vec<Vec<f64>> = llff_rows(&fx.known)
        .into_iter()
        .map(|r| r[..15].to_vec())
        .collect();
    write_npy_f64(&npy, &rows, 15);
    has(
        &err_of(load()),
        &["poses_bounds.npy", "shape [12, 15]", "(N, 17)"],
    );
    // Wrong dtype.
    let mut w = npyz::WriteOptions::new()
        .default_dtype()
        .shape(&[2, 17])
        .writer(std::fs::File::create(&npy).unwrap())
        .begin_nd()
        .unwrap();
    w.extend(0..34i64).unwrap();
    w.finish().unwrap();
    has(
        &err_of(load()),
        &["poses_bounds.npy", "dtype '<i8'", "float64"],
    );
    // Not a .npy at all, and truncated data.
    std::fs::write(&npy, b"hello").unwrap();
    has(&err_of(load()), &["poses_bounds.npy", "not a valid .npy"]);
    write_npy_f64(&npy, &llff_rows(&fx.known), 17);
    let b = std::fs::read(&npy).unwrap();
    for cut in [b.len() - 1, b.len() - 500, 140] {
        std::fs::write(&npy, &b[..cut]).unwrap();
        has(&err_of(load()), &["poses_bounds.npy"]);
    }
    // float32 is read too.
    let mut w = npyz::WriteOptions::new()
        .default_dtype()
        .shape(&[N as u64, 17])
        .writer(std::fs::File::create(&npy).unwrap())
        .begin_nd()
        .unwrap();
    for r in llff_rows(&fx.known) {
        w.extend(r.iter().map(|&v| v as f32)).unwrap();
    }
    w.finish().unwrap();
    load().unwrap();
    // Count mismatch names both counts.
    let rows = llff_rows(&fx.known);
    write_npy_f64(&npy, &rows[..N - 1], 17);
    has(
        &err_of(load()),
        &["poses_bounds.npy", "11 poses but 12 images"],
    );
    // A pose that is not a rotation.
    let mut rows = llff_rows(&fx.known);
    rows[2][0] += 0.5;
    write_npy_f64(&npy, &rows, 17);
    has(&err_of(load()), &["poses_bounds.npy", "row 2", "not rigid"]);
}

#[test]
fn convert_cli_refuses_bad_input_and_writes_nothing() {
    let fx = fixture();
    let bin = env!("CARGO_BIN_EXE_stegongp");
    let out = fx.cap.parent().unwrap().join("out.json");
    let run = |args: &[&str]| Command::new(bin).args(args).output().unwrap();
    let fails = |o: &std::process::Output, needles: &[&str]| {
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "expected failure: {err}");
        assert!(!err.contains("panicked"), "{err}");
        has(&err, needles);
    };
    let o = out.to_str().unwrap();
    // Truncated images.bin.
    let model = fx.cap.join("sparse/0");
    let b = std::fs::read(model.join("images.bin")).unwrap();
    std::fs::write(model.join("images.bin"), &b[..b.len() / 2]).unwrap();
    fails(
        &run(&["convert", fx.cap.to_str().unwrap(), "--out", o]),
        &["images.bin", "truncated"],
    );
    std::fs::write(model.join("images.bin"), &b).unwrap();
    // No capture in the folder (an instant-ngp folder is not a capture either).
    let synth = fx.cap.parent().unwrap().join("synth");
    fails(
        &run(&["convert", synth.to_str().unwrap(), "--out", o]),
        &["no COLMAP or LLFF capture", "poses_bounds.npy"],
    );
    // LLFF count mismatch.
    std::fs::remove_file(fx.llff.join("images/view_05.png")).unwrap();
    fails(
        &run(&["convert", fx.llff.to_str().unwrap(), "--out", o]),
        &["12 poses but 11 images"],
    );
    // Bad --aabb-scale, missing output folder.
    fails(
        &run(&[
            "convert",
            fx.cap.to_str().unwrap(),
            "--out",
            o,
            "--aabb-scale",
            "3",
        ]),
        &["--aabb-scale", "3"],
    );
    let deep = fx.cap.join("no/such/t.json");
    fails(
        &run(&[
            "convert",
            fx.cap.to_str().unwrap(),
            "--out",
            deep.to_str().unwrap(),
        ]),
        &["does not exist"],
    );
    assert!(!out.exists(), "nothing may be written on failure");
}
