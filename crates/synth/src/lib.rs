//! Generated scenes, ray-traced into the NeRF-synthetic (Blender) dataset format: RGBA PNG
//! views with transparent background, `transforms_{train,val,test}.json` with
//! `camera_angle_x` and camera-to-world matrices (OpenGL camera: looks down −z, +y up).
//! Train views are random on the upper hemisphere (radius 4, looking at the origin, like the
//! Blender scenes); test and val views circle the object at a few elevations.
//!
//! The `logo` scene ([`logo`]) is a seeded 3-D logo rendered exactly like the text.
//!
//! [`cameras_from::generate_from_cameras`] renders any of the bounded scenes from the
//! cameras of an existing dataset instead (its splits, intrinsics, sizes and poses, bit for
//! bit as the loader reads them): a hidden scene seen from the cover's very cameras.
//!
//! The `room` scene is the layout of a real capture instead: the object inside a room whose
//! walls are a far, opaque background, cameras inside the room (and inside the scene's box
//! for the chosen `aabb_scale`), written in the instant-ngp format (`transforms.json` with
//! `fl_x`/`fl_y`/`cx`/`cy`/`aabb_scale`, opaque PNGs in `images/`, every 8th view held out
//! by the loader).

pub mod cameras_from;
pub mod font;
pub mod logo;
pub mod scene;

use ngp::error::{Error, Result};
use ngp::rng::Pcg32;
use ngp::util::{write_atomic, write_atomic_with};
use rayon::prelude::*;
use scene::{Scene, V3, cross, normalize, object_scene, shapes_scene, text_scene};
use serde::Serialize;
use std::path::{Path, PathBuf};

/// Horizontal field of view of every view (lego's).
pub const CAMERA_ANGLE_X: f32 = 0.691_111_2;
/// Distance of the cameras from the origin.
pub const CAMERA_RADIUS: f32 = 4.0;
/// Most characters per line of a text scene before it wraps.
const LINE_CHARS: usize = 10;

/// What a generated scene shows. With the `cli` feature it parses (clap's `ValueEnum`) from
/// its name alone, `object`, `text`, `logo` or `room`; a text scene parsed so has an empty
/// message until [`SceneKind::with_text`] gives it one.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum SceneKind {
    /// Textured primitives on a checkered platform.
    Object,
    /// Extruded 3D text (the natural hidden message).
    Text(String),
    /// The object inside a room (an unbounded-looking capture); needs `aabb_scale` ≥ 2.
    Room,
    /// A generated 3-D logo ([`logo::Logo`]), drawn from [`SynthOptions::seed`].
    Logo,
    /// A ball, a box and a torus of known surfaces ([`scene::shapes_scene`]), seen from all round
    /// (training views below the horizon too): what a mesh is measured against.
    Shapes,
}

impl SceneKind {
    /// The kind's name: `object`, `text`, `logo` or `room`.
    pub fn name(&self) -> &'static str {
        match self {
            SceneKind::Object => "object",
            SceneKind::Text(_) => "text",
            SceneKind::Logo => "logo",
            SceneKind::Room => "room",
            SceneKind::Shapes => "shapes",
        }
    }

    /// This kind, with `text` as its message when it is a text scene.
    pub fn with_text(self, text: &str) -> SceneKind {
        match self {
            SceneKind::Text(_) => SceneKind::Text(text.into()),
            other => other,
        }
    }
}

/// By hand, as a text scene carries its message: the kinds in `synth --scene`'s order, the
/// text one with an empty message.
#[cfg(feature = "clap")]
impl clap::ValueEnum for SceneKind {
    fn value_variants<'a>() -> &'a [Self] {
        const KINDS: &[SceneKind] = &[
            SceneKind::Object,
            SceneKind::Text(String::new()),
            SceneKind::Logo,
            SceneKind::Room,
            SceneKind::Shapes,
        ];
        KINDS
    }

    fn to_possible_value(&self) -> Option<clap::builder::PossibleValue> {
        let help = match self {
            SceneKind::Object => "Textured primitives on a checkered platform",
            SceneKind::Text(_) => "Extruded 3D text (the natural hidden message)",
            SceneKind::Logo => {
                "A 3D logo drawn from --seed: a ring, shield or polygon frame around a plate, \
                 with a star, chevrons or a cross in front (extruded, flat colours)"
            }
            SceneKind::Room => {
                "The object inside a room, cameras inside the room: a capture-like unbounded \
                 scene in the instant-ngp format (needs --aabb-scale ≥ 2)"
            }
            SceneKind::Shapes => {
                "A ball, a box and a torus of known surfaces, seen from all round (for measuring meshes)"
            }
        };
        Some(clap::builder::PossibleValue::new(self.name()).help(help))
    }
}

/// The bounded scene of a kind (room excluded) and its name for summaries; `seed` picks
/// the logo.
pub fn bounded_scene(kind: &SceneKind, seed: u64) -> Result<(Scene, String)> {
    Ok(match kind {
        SceneKind::Object => (object_scene(), "object".to_string()),
        SceneKind::Shapes => (shapes_scene(), "shapes".to_string()),
        SceneKind::Text(t) => (text_scene(&layout_text(t)?), format!("text {t:?}")),
        SceneKind::Logo => {
            let l = logo::Logo::from_seed(seed);
            (l.scene(), format!("logo ({}, seed {seed})", l.describe()))
        }
        SceneKind::Room => {
            return Err(Error::Config(
                "the room scene is not a bounded scene: it brings its own cameras and walls".into(),
            ));
        }
    })
}

#[derive(Clone, Debug)]
pub struct SynthOptions {
    pub scene: SceneKind,
    /// Width and height of every view.
    pub resolution: u32,
    pub n_train: usize,
    pub n_val: usize,
    pub n_test: usize,
    pub seed: u64,
    /// Written into the transforms as `aabb_scale` (power of two ≤ 128). A room's walls are
    /// placed inside the box it gives; object and text scenes fit the unit box whatever it is.
    pub aabb_scale: u32,
    /// The room scene's own choices (ignored by the other scenes).
    pub room: RoomOptions,
}

/// How a room scene looks and is photographed.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RoomOptions {
    /// Height of every view (default: the width, `resolution`).
    pub height: Option<u32>,
    /// Horizontal field of view in degrees (default: lego's, 39.6°).
    pub fov_x_degrees: Option<f32>,
    /// A furnished room ([`scene::furnished_room`]: brick walls nearer the object, a floor
    /// under a pedestal, furniture drawn from the seed) instead of the bare one.
    pub furnished: bool,
}

impl Default for SynthOptions {
    fn default() -> Self {
        SynthOptions {
            scene: SceneKind::Object,
            resolution: 200,
            n_train: 100,
            n_val: 0,
            n_test: 25,
            seed: 0,
            aabb_scale: 1,
            room: RoomOptions::default(),
        }
    }
}

/// The reference's nerf → ngp scale (`nerf_loader.h`): world metres × 0.33 = ngp units.
const NGP_SCALE: f32 = 0.33;

/// Half-size of a room's walls for a box of `aabb_scale`: 80 % of the box's half-size in
/// world units, so the walls are inside the box with a margin.
pub fn room_half_size(aabb_scale: u32) -> f32 {
    0.8 * (aabb_scale as f32 / 2.0) / NGP_SCALE
}

/// Distance of a room's cameras from the origin: as the Blender scenes' 4 where the room is
/// large enough, else half-way to the walls.
pub fn room_camera_radius(aabb_scale: u32) -> f32 {
    CAMERA_RADIUS.min(0.55 * room_half_size(aabb_scale))
}

/// Room views: random azimuth, elevation in [−10°, 45°], looking at the origin.
fn room_poses(n: usize, radius: f32, seed: u64) -> Vec<[[f32; 4]; 4]> {
    let mut rng = Pcg32::new(seed, 4);
    (0..n)
        .map(|_| {
            let az = rng.next_f32() * std::f32::consts::TAU;
            let el = (-10.0 + 55.0 * rng.next_f32()).to_radians();
            look_at([
                radius * el.cos() * az.cos(),
                radius * el.cos() * az.sin(),
                radius * el.sin(),
            ])
        })
        .collect()
}

#[derive(Clone, Debug, Serialize)]
pub struct SynthSummary {
    pub dir: PathBuf,
    pub scene: String,
    /// Width of every view (and its height, but with `cameras_from`).
    pub resolution: u32,
    /// Height of every view (the width, but for a room's [`RoomOptions::height`] and the
    /// cameras of `cameras_from`).
    pub height: u32,
    pub n_train: usize,
    pub n_val: usize,
    pub n_test: usize,
    pub seconds: f64,
    /// Set when the cameras came from a dataset ([`cameras_from`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cameras_from: Option<cameras_from::CamerasFromInfo>,
}

/// Splits a message into lines of at most [`LINE_CHARS`], at spaces where possible, and
/// checks every character has a glyph.
pub fn layout_text(text: &str) -> Result<Vec<Vec<char>>> {
    let text = text.trim();
    if text.is_empty() {
        return Err(Error::Config("the text of a text scene is empty".into()));
    }
    if let Some(c) = text.chars().find(|&c| font::glyph(c).is_none()) {
        return Err(Error::Config(format!(
            "character {c:?} has no glyph (supported: A–Z, a–z, 0–9, space and .,:;!?-()@#&/'©)"
        )));
    }
    let mut lines: Vec<Vec<char>> = Vec::new();
    let mut cur: Vec<char> = Vec::new();
    for word in text.split_whitespace() {
        let w: Vec<char> = word.chars().collect();
        for piece in w.chunks(LINE_CHARS) {
            let need = if cur.is_empty() {
                piece.len()
            } else {
                cur.len() + 1 + piece.len()
            };
            if need > LINE_CHARS && !cur.is_empty() {
                lines.push(std::mem::take(&mut cur));
            }
            if !cur.is_empty() {
                cur.push(' ');
            }
            cur.extend_from_slice(piece);
        }
    }
    if !cur.is_empty() {
        lines.push(cur);
    }
    if lines.len() > 4 {
        return Err(Error::Config(format!(
            "text too long: {} lines of up to {LINE_CHARS} characters (at most 4)",
            lines.len()
        )));
    }
    Ok(lines)
}

/// Camera-to-world (Blender/OpenGL) for a camera at `pos` looking at the origin.
pub fn look_at(pos: V3) -> [[f32; 4]; 4] {
    let z = normalize(pos); // the camera looks down −z
    let up = if z[2].abs() > 0.999 {
        [0.0, 1.0, 0.0]
    } else {
        [0.0, 0.0, 1.0]
    };
    let x = normalize(cross(up, z));
    let y = cross(z, x);
    [
        [x[0], y[0], z[0], pos[0]],
        [x[1], y[1], z[1], pos[1]],
        [x[2], y[2], z[2], pos[2]],
        [0.0, 0.0, 0.0, 1.0],
    ]
}

fn hemisphere(azimuth: f32, elevation: f32) -> V3 {
    let (ce, se) = (elevation.cos(), elevation.sin());
    [
        CAMERA_RADIUS * ce * azimuth.cos(),
        CAMERA_RADIUS * ce * azimuth.sin(),
        CAMERA_RADIUS * se,
    ]
}

/// Poses of a split: random on the upper hemisphere (train; the whole sphere but the poles
/// when `all_round`) or rings at a few elevations.
fn poses(n: usize, random: bool, all_round: bool, seed: u64, stream: u64) -> Vec<[[f32; 4]; 4]> {
    let mut rng = Pcg32::new(seed, stream);
    let lowest: f32 = if all_round { -80.0 } else { 8.0 };
    (0..n)
        .map(|i| {
            let pos = if random {
                // Uniform over the band between `lowest` and 80° of elevation.
                let z = (lowest.to_radians().sin())
                    + rng.next_f32() * (80f32.to_radians().sin() - lowest.to_radians().sin());
                hemisphere(rng.next_f32() * std::f32::consts::TAU, z.asin())
            } else {
                let elev = [30.0f32, 15.0, 50.0][i % 3].to_radians();
                // View 0 faces the text scene from the front (−y), where it reads correctly.
                let az = i as f32 / n.max(1) as f32 * std::f32::consts::TAU
                    - std::f32::consts::FRAC_PI_2
                    + 0.15;
                hemisphere(az, elev)
            };
            look_at(pos)
        })
        .collect()
}

/// Straight-alpha RGBA8 rendering of one view, 2×2 stratified samples per pixel.
pub fn render_view(scene: &Scene, c2w: &[[f32; 4]; 4], res: u32) -> Vec<u8> {
    let focal = 0.5 * res as f32 / (0.5 * CAMERA_ANGLE_X).tan();
    render_pinhole(scene, c2w, res, res, focal)
}

/// [`render_view`] of a `w×h` pinhole camera of focal length `focal` pixels, centred
/// (camera-to-world `c2w` with OpenGL axes: the camera looks down −z, +y up).
pub fn render_pinhole(scene: &Scene, c2w: &[[f32; 4]; 4], w: u32, h: u32, focal: f32) -> Vec<u8> {
    let o = [c2w[0][3], c2w[1][3], c2w[2][3]];
    let (half_w, half_h) = (0.5 * w as f32, 0.5 * h as f32);
    render_rgba(scene, w as usize, h as usize, |x, y| {
        let dc = [(x - half_w) / focal, -(y - half_h) / focal, -1.0];
        let d = normalize([
            c2w[0][0] * dc[0] + c2w[0][1] * dc[1] + c2w[0][2] * dc[2],
            c2w[1][0] * dc[0] + c2w[1][1] * dc[1] + c2w[1][2] * dc[2],
            c2w[2][0] * dc[0] + c2w[2][1] * dc[1] + c2w[2][2] * dc[2],
        ]);
        (o, d)
    })
}

/// Straight-alpha RGBA8 rendering of a `w×h` image: `ray(x, y)` gives the ray (origin,
/// unit direction, in the scene's frame) through pixel position (x, y); 2×2 stratified
/// samples per pixel, alpha the fraction that hit the scene.
pub(crate) fn render_rgba(
    scene: &Scene,
    w: usize,
    h: usize,
    ray: impl Fn(f32, f32) -> (V3, V3) + Sync,
) -> Vec<u8> {
    let mut out = vec![0u8; w * h * 4];
    out.par_chunks_mut(w * 4).enumerate().for_each(|(j, row)| {
        for i in 0..w {
            let (mut acc, mut hits) = ([0.0f32; 3], 0u32);
            for s in 0..4 {
                let (sx, sy) = (0.25 + 0.5 * (s & 1) as f32, 0.25 + 0.5 * (s >> 1) as f32);
                let (o, d) = ray(i as f32 + sx, j as f32 + sy);
                if let Some(c) = scene.shade(o, d) {
                    for k in 0..3 {
                        acc[k] += c[k];
                    }
                    hits += 1;
                }
            }
            let px = &mut row[i * 4..i * 4 + 4];
            if hits > 0 {
                for k in 0..3 {
                    px[k] = (acc[k] / hits as f32 * 255.0 + 0.5).clamp(0.0, 255.0) as u8;
                }
                px[3] = (hits * 255 / 4) as u8;
            }
        }
    });
    debug_assert_eq!(out.len(), w * h * 4);
    out
}

pub(crate) fn encode_png(w: u32, h: u32, rgba: &[u8]) -> std::io::Result<Vec<u8>> {
    ngp::data::png_bytes(w, h, 4, rgba, false)
}

/// Renders the scene of `opts` into `out_dir` (created if needed). Images are written
/// first and the JSON files last, so an interrupted run never looks complete.
pub fn generate(opts: &SynthOptions, out_dir: &Path) -> Result<SynthSummary> {
    let t0 = std::time::Instant::now();
    if opts.resolution < 8 || opts.resolution > 4096 {
        return Err(Error::Config(format!(
            "resolution {} outside 8..=4096",
            opts.resolution
        )));
    }
    if opts.n_train == 0 || opts.n_test == 0 {
        return Err(Error::Config(
            "a scene needs at least one train and one test view".into(),
        ));
    }
    if !(opts.aabb_scale.is_power_of_two() && opts.aabb_scale <= 128) {
        return Err(Error::Config(format!(
            "aabb_scale {} is not a power of two between 1 and 128",
            opts.aabb_scale
        )));
    }
    let (scene, name) = match &opts.scene {
        SceneKind::Room => return generate_room(opts, out_dir, t0),
        kind => bounded_scene(kind, opts.seed)?,
    };
    let splits = [
        ("train", opts.n_train, true, 1u64),
        ("val", opts.n_val, false, 2),
        ("test", opts.n_test, false, 3),
    ];
    for (split, n, random, stream) in splits {
        if n == 0 {
            continue;
        }
        let dir = out_dir.join(split);
        std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        let ps = poses(
            n,
            random,
            opts.scene == SceneKind::Shapes,
            opts.seed,
            stream,
        );
        for (i, p) in ps.iter().enumerate() {
            let rgba = render_view(&scene, p, opts.resolution);
            let path = dir.join(format!("r_{i}.png"));
            write_atomic_with(&path, |f| {
                use std::io::Write;
                f.write_all(&encode_png(opts.resolution, opts.resolution, &rgba)?)
            })?;
        }
        let frames: Vec<serde_json::Value> = ps
            .iter()
            .enumerate()
            .map(|(i, p)| serde_json::json!({"file_path": format!("./{split}/r_{i}"), "rotation": 0.0, "transform_matrix": p}))
            .collect();
        let mut json = serde_json::json!({"camera_angle_x": CAMERA_ANGLE_X, "frames": frames});
        if opts.aabb_scale != 1 {
            json["aabb_scale"] = opts.aabb_scale.into();
        }
        let text = serde_json::to_string_pretty(&json).map_err(|e| Error::Other(e.to_string()))?;
        write_atomic(
            &out_dir.join(format!("transforms_{split}.json")),
            text.as_bytes(),
        )?;
    }
    Ok(SynthSummary {
        dir: out_dir.to_path_buf(),
        scene: name,
        resolution: opts.resolution,
        height: opts.resolution,
        n_train: opts.n_train,
        n_val: opts.n_val,
        n_test: opts.n_test,
        seconds: t0.elapsed().as_secs_f64(),
        cameras_from: None,
    })
}

/// A furnished room's walls, as a share of the bare room's half-size: about three times the
/// cameras' distance from the object, as in an indoor 360° capture.
const FURNISHED_WALLS: f32 = 0.6;

/// A room view's width, height and focal length (pixels), checked.
fn room_camera(opts: &SynthOptions) -> Result<(u32, u32, f32)> {
    let (w, h) = (opts.resolution, opts.room.height.unwrap_or(opts.resolution));
    if !(8..=4096).contains(&h) {
        return Err(Error::Config(format!("height {h} outside 8..=4096")));
    }
    let fov = opts
        .room
        .fov_x_degrees
        .map_or(CAMERA_ANGLE_X, f32::to_radians);
    if !(fov.is_finite() && fov > 0.01 && fov < 3.0) {
        return Err(Error::Config(format!(
            "field of view {} degrees outside (0.6, 171)",
            fov.to_degrees()
        )));
    }
    Ok((w, h, 0.5 * w as f32 / (0.5 * fov).tan()))
}

/// The room scene `opts` asks for (bare or furnished, its walls inside the box of its
/// `aabb_scale`), and the distance from the object at which its cameras are placed: for
/// views other than `generate`'s own, rendered with [`render_pinhole`].
pub fn room(opts: &SynthOptions) -> Result<(Scene, f32)> {
    if opts.aabb_scale < 2 {
        return Err(Error::Config(
            "a room scene needs aabb_scale ≥ 2: its walls lie outside the unit box".into(),
        ));
    }
    let half = room_half_size(opts.aabb_scale);
    let radius = room_camera_radius(opts.aabb_scale);
    let scene = if opts.room.furnished {
        scene::furnished_room(FURNISHED_WALLS * half, radius + 1.5, opts.seed)
    } else {
        scene::room_scene(half)
    };
    Ok((scene, radius))
}

/// The room scene in the instant-ngp format: `n_train + n_test` views in one list (the
/// loader holds out every 8th), opaque RGB PNGs in `images/`, pixel intrinsics.
fn generate_room(
    opts: &SynthOptions,
    out_dir: &Path,
    t0: std::time::Instant,
) -> Result<SynthSummary> {
    let (scene, radius) = room(opts)?;
    let (res, height, focal) = room_camera(opts)?;
    let n = opts.n_train + opts.n_val + opts.n_test;
    let images = out_dir.join("images");
    std::fs::create_dir_all(&images).map_err(|e| Error::io(&images, e))?;
    let ps = room_poses(n, radius, opts.seed);
    for (i, p) in ps.iter().enumerate() {
        let rgba = render_pinhole(&scene, p, res, height, focal);
        let path = images.join(format!("{i:04}.png"));
        write_atomic_with(&path, |f| {
            use std::io::Write;
            f.write_all(&encode_png(res, height, &rgba)?)
        })?;
    }
    let frames: Vec<serde_json::Value> = ps
        .iter()
        .enumerate()
        .map(|(i, p)| serde_json::json!({"file_path": format!("images/{i:04}.png"), "transform_matrix": p}))
        .collect();
    let json = serde_json::json!({
        "fl_x": focal, "fl_y": focal,
        "cx": res as f32 / 2.0, "cy": height as f32 / 2.0,
        "w": res, "h": height,
        "aabb_scale": opts.aabb_scale,
        "frames": frames,
    });
    let text = serde_json::to_string_pretty(&json).map_err(|e| Error::Other(e.to_string()))?;
    write_atomic(&out_dir.join("transforms.json"), text.as_bytes())?;
    let n_test = n.div_ceil(8);
    Ok(SynthSummary {
        dir: out_dir.to_path_buf(),
        scene: format!(
            "{}room (aabb_scale {})",
            if opts.room.furnished {
                "furnished "
            } else {
                ""
            },
            opts.aabb_scale
        ),
        resolution: res,
        height,
        n_train: n - n_test,
        n_val: 0,
        n_test,
        seconds: t0.elapsed().as_secs_f64(),
        cameras_from: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg(feature = "clap")]
    #[test]
    fn scene_kinds_parse_by_name_and_take_their_text() {
        use clap::ValueEnum;
        for kind in SceneKind::value_variants() {
            let parsed = SceneKind::from_str(kind.name(), false).unwrap();
            assert_eq!(&parsed, kind);
        }
        let text = SceneKind::from_str("text", false).unwrap();
        assert_eq!(text, SceneKind::Text(String::new()));
        assert_eq!(text.with_text("HI"), SceneKind::Text("HI".into()));
        assert_eq!(SceneKind::Logo.with_text("HI"), SceneKind::Logo);
        assert!(SceneKind::from_str("castle", false).is_err());
    }

    #[test]
    fn cameras_look_at_the_origin() {
        for p in poses(20, true, false, 5, 1) {
            let pos = [p[0][3], p[1][3], p[2][3]];
            let r = scene::dot(pos, pos).sqrt();
            assert!((r - CAMERA_RADIUS).abs() < 1e-4);
            assert!(pos[2] > 0.0, "upper hemisphere");
            // −z axis of the camera points at the origin.
            let fwd = [-p[0][2], -p[1][2], -p[2][2]];
            let to_o = normalize([-pos[0], -pos[1], -pos[2]]);
            assert!(scene::dot(fwd, to_o) > 0.9999);
            // Rotation is orthonormal and right-handed.
            let x = [p[0][0], p[1][0], p[2][0]];
            let y = [p[0][1], p[1][1], p[2][1]];
            let z = [p[0][2], p[1][2], p[2][2]];
            let c = cross(x, y);
            assert!((scene::dot(c, z) - 1.0).abs() < 1e-4);
        }
    }

    #[test]
    fn object_view_is_opaque_in_the_middle_and_clear_in_the_corner() {
        let img = render_view(&object_scene(), &look_at(hemisphere(0.7, 0.5)), 32);
        let px = |x: usize, y: usize| &img[(y * 32 + x) * 4..(y * 32 + x) * 4 + 4];
        assert_eq!(px(16, 16)[3], 255);
        assert_eq!(px(0, 0)[3], 0);
    }

    #[test]
    fn text_silhouette_from_the_front_matches_the_glyph() {
        // One glyph seen straight from −y: rays parallel to +y through each cell centre.
        let lines = layout_text("T").unwrap();
        let scene = text_scene(&lines);
        let g = font::glyph('T').unwrap();
        let (lo, hi) = (scene.lo, scene.hi);
        let (w, h) = ((hi[0] - lo[0]) / 5.0, (hi[2] - lo[2]) / 7.0);
        for (r, row) in g.iter().enumerate() {
            for (c, ch) in row.chars().enumerate() {
                // The bounding box spans the glyph's filled columns: 'T' fills all 5.
                let o = [
                    lo[0] + (c as f32 + 0.5) * w,
                    -5.0,
                    hi[2] - (r as f32 + 0.5) * h,
                ];
                let hit = scene.intersect(o, [0.0, 1.0, 0.0]).is_some();
                assert_eq!(hit, ch == '#', "row {r} col {c}");
            }
        }
    }

    #[test]
    fn text_layout_and_errors() {
        assert_eq!(layout_text("(c) StegoNGP 2026").unwrap().len(), 3); // (C) / STEGONGP / 2026
        assert_eq!(
            layout_text("HI THERE").unwrap(),
            vec!["HI THERE".chars().collect::<Vec<_>>()]
        );
        assert!(layout_text("   ").is_err());
        assert!(layout_text("bad ~ char").is_err());
        assert!(layout_text(&"W".repeat(60)).is_err());
    }

    #[test]
    fn generation_is_deterministic_and_complete() {
        let d = tempfile::tempdir().unwrap();
        let opts = SynthOptions {
            resolution: 16,
            n_train: 3,
            n_test: 2,
            seed: 4,
            ..Default::default()
        };
        generate(&opts, &d.path().join("a")).unwrap();
        generate(&opts, &d.path().join("b")).unwrap();
        let a = std::fs::read(d.path().join("a/train/r_1.png")).unwrap();
        let b = std::fs::read(d.path().join("b/train/r_1.png")).unwrap();
        assert_eq!(a, b);
        let json: serde_json::Value = serde_json::from_slice(
            &std::fs::read(d.path().join("a/transforms_train.json")).unwrap(),
        )
        .unwrap();
        assert_eq!(json["frames"].as_array().unwrap().len(), 3);
        assert_eq!(json["frames"][0]["file_path"], "./train/r_0");
        assert!(!d.path().join("a/transforms_val.json").exists());
        let other = poses(3, true, false, 5, 1);
        assert_ne!(other, poses(3, true, false, 4, 1));
    }

    /// A furnished room photographed as a phone does (3:2, 65°) loads as a capture: the
    /// size and focal length asked for, opaque views (the room encloses every camera), the
    /// same bytes for a seed, other furniture for another, and not the bare room.
    #[test]
    fn a_furnished_room_is_a_capture_of_the_size_and_lens_asked_for() {
        use dataset::LoadOptions;
        use ngp::data::Split;
        let d = tempfile::tempdir().unwrap();
        let room = |furnished: bool, seed: u64, name: &str| {
            let opts = SynthOptions {
                scene: SceneKind::Room,
                resolution: 36,
                n_train: 7,
                n_test: 1,
                seed,
                aabb_scale: 16,
                room: RoomOptions {
                    height: Some(24),
                    fov_x_degrees: Some(65.0),
                    furnished,
                },
                ..Default::default()
            };
            let s = generate(&opts, &d.path().join(name)).unwrap();
            assert_eq!(
                (s.resolution, s.height, s.n_train, s.n_test),
                (36, 24, 7, 1)
            );
            std::fs::read(d.path().join(name).join("images/0002.png")).unwrap()
        };
        let a = room(true, 3, "a");
        assert_eq!(a, room(true, 3, "b"));
        assert_ne!(a, room(true, 4, "c"), "the seed draws the furniture");
        assert_ne!(a, room(false, 3, "bare"));
        let data =
            dataset::load(&d.path().join("a"), Split::Train, &LoadOptions::default()).unwrap();
        assert_eq!(data.frames.len(), 7);
        let f = &data.frames[0];
        assert_eq!((f.image.width, f.image.height), (36, 24));
        assert!(!f.image.has_alpha(), "a room's views are opaque");
        let want = 18.0 / (32.5f32.to_radians()).tan();
        assert!(
            (f.camera.fx - want).abs() < 1e-3,
            "{} vs {want}",
            f.camera.fx
        );
        // Sizes and lenses out of range are refused before anything is written.
        for (height, fov) in [(Some(4), None), (None, Some(0.0)), (None, Some(200.0))] {
            let opts = SynthOptions {
                scene: SceneKind::Room,
                resolution: 36,
                aabb_scale: 16,
                room: RoomOptions {
                    height,
                    fov_x_degrees: fov,
                    furnished: true,
                },
                ..Default::default()
            };
            let out = d.path().join("bad");
            assert!(generate(&opts, &out).is_err(), "{height:?} {fov:?}");
            assert!(!out.join("transforms.json").exists());
        }
    }

    #[test]
    fn prism_hits_its_faces_with_outward_normals() {
        // A unit square in x–z, y in [−0.5, 0.5], given clockwise (prism() fixes it).
        let sq = scene::prism(
            [[-0.5, -0.5], [-0.5, 0.5], [0.5, 0.5], [0.5, -0.5]],
            -0.5,
            0.5,
        );
        let hit = |o: V3, d: V3| sq.intersect(o, d, [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]]);
        let (t, n) = hit([0.1, -3.0, 0.2], [0.0, 1.0, 0.0]).unwrap();
        assert!((t - 2.5).abs() < 1e-4 && n == [0.0, -1.0, 0.0]);
        let (t, n) = hit([3.0, 0.0, 0.0], [-1.0, 0.0, 0.0]).unwrap();
        assert!((t - 2.5).abs() < 1e-4 && (n[0] - 1.0).abs() < 1e-6);
        let (t, n) = hit([0.0, 0.0, -3.0], normalize([0.0, 0.1, 1.0])).unwrap();
        assert!(t > 2.5 && (n[2] + 1.0).abs() < 1e-6, "{t} {n:?}");
        // From inside: the exit, facing out.
        let (t, n) = hit([0.0, 0.0, 0.0], [0.0, 0.0, 1.0]).unwrap();
        assert!((t - 0.5).abs() < 1e-4 && (n[2] - 1.0).abs() < 1e-6);
        assert!(hit([0.7, -3.0, 0.0], [0.0, 1.0, 0.0]).is_none());
        assert!(hit([0.0, -3.0, 0.0], [0.0, -1.0, 0.0]).is_none());
        // A triangle repeats its last point.
        let tri = scene::prism([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.0, 1.0]], 0.0, 0.1);
        let d = [0.0, 1.0, 0.0];
        let inv = [f32::INFINITY, 1.0, f32::INFINITY];
        assert!(tri.intersect([0.2, -1.0, 0.2], d, inv).is_some());
        assert!(tri.intersect([0.6, -1.0, 0.6], d, inv).is_none());
    }

    /// The front view (from −y, as view 0 of the test ring nearly is) at 32×32.
    fn front(scene: &Scene) -> Vec<u8> {
        render_view(scene, &look_at([0.0, -CAMERA_RADIUS, 0.0]), 32)
    }

    #[test]
    fn logo_is_deterministic_non_empty_and_differs_by_seed() {
        assert_eq!(logo::Logo::from_seed(7), logo::Logo::from_seed(7));
        assert_eq!(front(&logo::logo_scene(7)), front(&logo::logo_scene(7)));
        let mut views = Vec::new();
        let mut kinds = std::collections::HashSet::new();
        for seed in 0..12 {
            let l = logo::Logo::from_seed(seed);
            kinds.insert(l.describe());
            let img = front(&l.scene());
            let alpha = |x: usize, y: usize| img[(y * 32 + x) * 4 + 3];
            // Opaque in the middle, clear in the corners, a good part of the view covered.
            assert_eq!(alpha(16, 16), 255, "seed {seed}");
            assert_eq!(alpha(0, 0), 0, "seed {seed}");
            let covered = (0..32 * 32).filter(|i| img[i * 4 + 3] > 0).count();
            assert!(covered > 200, "seed {seed}: {covered} pixels");
            views.push(img);
        }
        for i in 0..views.len() {
            for j in 0..i {
                assert_ne!(views[i], views[j], "seeds {i} and {j} look the same");
            }
        }
        assert!(kinds.len() >= 6, "{kinds:?}");
        // Not the text: another silhouette altogether.
        let text = front(&text_scene(&layout_text("(c) StegoNGP 2026").unwrap()));
        let differ = (0..32 * 32)
            .filter(|i| (text[i * 4 + 3] > 127) != (views[0][i * 4 + 3] > 127))
            .count();
        assert!(differ > 150, "{differ}");
    }

    #[test]
    fn logo_generates_like_text() {
        let d = tempfile::tempdir().unwrap();
        let opts = SynthOptions {
            scene: SceneKind::Logo,
            resolution: 16,
            n_train: 2,
            n_test: 1,
            seed: 9,
            ..Default::default()
        };
        let s = generate(&opts, d.path()).unwrap();
        assert!(s.scene.starts_with("logo ("), "{}", s.scene);
        assert!(d.path().join("train/r_1.png").is_file());
        assert!(d.path().join("transforms_test.json").is_file());
        assert!(bounded_scene(&SceneKind::Room, 0).is_err());
    }
}
