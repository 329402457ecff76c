//! A capture made here: the generated room photographed along an arc from known cameras,
//! for the tests and the benchmark of `stegongp process`, and how far a reconstruction's
//! poses are from the known ones.

use crate::geometry::{rot_to_quat, rotation_angle_deg, similarity};
use dataset::colmap::read_model;
use dataset::colmap2nerf::colmap_c2w;
use std::collections::HashMap;
use std::path::Path;
use synth::{RoomOptions, SceneKind, SynthOptions, look_at, render_pinhole, room};

/// A camera-to-world matrix with OpenGL axes (right, up, back), as the synth scenes use.
pub type Pose = [[f32; 4]; 4];

/// How the arc is photographed.
#[derive(Clone, Copy, Debug)]
pub struct Arc {
    pub views: usize,
    pub width: u32,
    pub height: u32,
    pub fov_deg: f32,
    /// The arc the cameras cover around the room's centre.
    pub arc_deg: f32,
    /// `synth::scene::Scene::grain` of the room.
    pub grain: f32,
}

/// The views (RGB8, row-major) and their poses: the bare room (box of `aabb_scale` 4)
/// seen from its cameras' distance, azimuth along the arc, the elevation swaying between 8°
/// and 32° so that the cameras do not all lie in one plane.
pub fn room_arc(a: &Arc) -> (Vec<Vec<u8>>, Vec<Pose>, f32) {
    let opts = SynthOptions {
        scene: SceneKind::Room,
        aabb_scale: 4,
        room: RoomOptions::default(),
        ..Default::default()
    };
    let (mut scene, radius) = room(&opts).expect("the room at aabb_scale 4");
    scene.grain = a.grain;
    let focal = 0.5 * a.width as f32 / (0.5 * a.fov_deg.to_radians()).tan();
    let poses: Vec<Pose> = (0..a.views)
        .map(|i| {
            let t = i as f32 / (a.views.max(2) - 1) as f32;
            let az = (a.arc_deg * t).to_radians();
            let el = (20.0 + 12.0 * (7.0 * t).sin()).to_radians();
            look_at([
                radius * el.cos() * az.cos(),
                radius * el.cos() * az.sin(),
                radius * el.sin(),
            ])
        })
        .collect();
    let frames = poses
        .iter()
        .map(|p| {
            let rgba = render_pinhole(&scene, p, a.width, a.height, focal);
            rgba.chunks_exact(4)
                .flat_map(|q| [q[0], q[1], q[2]])
                .collect()
        })
        .collect();
    (frames, poses, focal)
}

/// Writes 8-bit RGB as a PNG.
pub fn write_png(path: &Path, w: u32, h: u32, rgb: &[u8]) {
    let f = std::fs::File::create(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut e = png::Encoder::new(std::io::BufWriter::new(f), w, h);
    e.set_color(png::ColorType::Rgb);
    e.set_depth(png::BitDepth::Eight);
    e.write_header()
        .and_then(|mut w| w.write_image_data(rgb))
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
}

/// OpenCV camera-to-world rotation (right, down, forward) of an OpenGL pose.
fn opencv_rotation(p: &Pose) -> [[f64; 3]; 3] {
    [0, 1, 2].map(|i| [p[i][0] as f64, -p[i][1] as f64, -p[i][2] as f64])
}

/// The known cameras as a COLMAP text model in `dir` (PINHOLE, one camera): a capture the
/// loaders normalise exactly as they normalise `process`'s output.
pub fn write_colmap_text(dir: &Path, names: &[String], poses: &[Pose], w: u32, h: u32, focal: f32) {
    std::fs::create_dir_all(dir).expect("model folder");
    let cams = format!(
        "1 PINHOLE {w} {h} {focal} {focal} {} {}\n",
        w as f32 / 2.0,
        h as f32 / 2.0
    );
    std::fs::write(dir.join("cameras.txt"), cams).expect("cameras.txt");
    let mut images = String::new();
    for (i, (name, p)) in names.iter().zip(poses).enumerate() {
        let r = opencv_rotation(p);
        // World-to-camera: Rᵀ and −Rᵀc.
        let rt = [0, 1, 2].map(|a| [0, 1, 2].map(|b| r[b][a]));
        let c = [0, 1, 2].map(|k| p[k][3] as f64);
        let t = [0, 1, 2].map(|a| -(0..3).map(|k| rt[a][k] * c[k]).sum::<f64>());
        let q = rot_to_quat(&rt);
        images += &format!(
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
    std::fs::write(dir.join("images.txt"), images).expect("images.txt");
}

/// How far a reconstruction's cameras are from the known ones after the best similarity.
#[derive(Clone, Copy, Debug)]
pub struct PoseErrors {
    pub cameras: usize,
    pub max_rotation_deg: f64,
    pub mean_rotation_deg: f64,
    /// As a share of the cameras' mean distance from what they look at (the origin).
    pub max_position: f64,
    pub mean_position: f64,
}

/// The errors of the COLMAP model in `model_dir` against `known` (image name → pose);
/// every image of the model must be known.
pub fn pose_errors(model_dir: &Path, known: &HashMap<String, Pose>) -> PoseErrors {
    let model = read_model(model_dir).expect("a COLMAP model");
    let (mut rec_c, mut true_c, mut rec_r, mut true_r) = (vec![], vec![], vec![], vec![]);
    for im in &model.images {
        let m = colmap_c2w(im.qvec, im.tvec);
        rec_c.push([m[0][3], m[1][3], m[2][3]]);
        rec_r.push([0, 1, 2].map(|i| [m[i][0], m[i][1], m[i][2]]));
        let k = known
            .get(&im.name)
            .unwrap_or_else(|| panic!("{} is not a known view", im.name));
        true_c.push([0, 1, 2].map(|i| k[i][3] as f64));
        true_r.push(opencv_rotation(k));
    }
    let (s, r, t) = similarity(&rec_c, &true_c);
    let n = true_c.len() as f64;
    let reach = true_c
        .iter()
        .map(|c| c.iter().map(|v| v * v).sum::<f64>().sqrt())
        .sum::<f64>()
        / n;
    let mut e = PoseErrors {
        cameras: true_c.len(),
        max_rotation_deg: 0.0,
        mean_rotation_deg: 0.0,
        max_position: 0.0,
        mean_position: 0.0,
    };
    let apply = |v: [f64; 3]| [0, 1, 2].map(|a| (0..3).map(|k| r[a][k] * v[k]).sum::<f64>());
    for i in 0..rec_c.len() {
        let moved = apply(rec_c[i]).map(|v| v * s);
        let d = (0..3)
            .map(|k| (moved[k] + t[k] - true_c[i][k]).powi(2))
            .sum::<f64>()
            .sqrt()
            / reach;
        let turned = [0, 1, 2]
            .map(|a| [0, 1, 2].map(|b| (0..3).map(|k| r[a][k] * rec_r[i][k][b]).sum::<f64>()));
        let rot = rotation_angle_deg(&true_r[i], &turned);
        e.max_rotation_deg = e.max_rotation_deg.max(rot);
        e.mean_rotation_deg += rot / n;
        e.max_position = e.max_position.max(d);
        e.mean_position += d / n;
    }
    e
}
