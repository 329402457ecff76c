//! A generated scene rendered from the cameras of an existing dataset (`synth
//! --cameras-from DIR`): the hidden scene of a stego pair seen from the cover's very
//! cameras, as the paper's GS-Hider comparison needs.
//!
//! The cameras are read by the loader ([`dataset::load_cameras`]), so every format it
//! reads works (NeRF-synthetic, instant-ngp, COLMAP, LLFF), with its split conventions
//! (instant-ngp, COLMAP and LLFF hold out every 8th image) and the loader's options
//! (`downscale`, `images`, `aabb_scale`). The output is a NeRF-synthetic folder —
//! `transforms_train.json`, `transforms_test.json` (and `transforms_val.json` when the
//! source has a val split of its own; otherwise the loader's val → test fallback gives
//! the source's val, which is its test), RGBA PNGs with a transparent background — whose
//! frames carry each camera's intrinsics (`fl_x`, `fl_y`, `cx`, `cy`, `w`, `h`, and
//! `k1`, `k2`, `p1`, `p2` when the lens is distorted) and its pose, and whose
//! `aabb_scale` is the source's. Poses are written already in the engine's frame, with
//! `"scale": 1` and `"offset": [0, 0, 0]`, so the loader's nerf → ngp conversion is only
//! a permutation and sign flips: loading the output gives the source's cameras bit for
//! bit (same count, order, sizes, intrinsics and poses; the `scale`/`offset` metadata of a
//! snapshot trained on it then reads 1 and 0, which nothing but that metadata uses).

use super::scene::{Scene, V3, dot, normalize};
use super::{SceneKind, SynthSummary, bounded_scene, encode_png, render_rgba};
use dataset::LoadOptions;
use ngp::camera::Camera;
use ngp::data::{DatasetFormat, DatasetMeta, Split};
use ngp::error::{Error, Result};
use ngp::util::{write_atomic, write_atomic_with};
use serde::Serialize;
use std::path::{Path, PathBuf};

/// Where the scene stands in the engine's frame, and how large.
///
/// - **Centre**: the centre of the box, (0.5, 0.5, 0.5). Every loader puts the point the
///   cameras look at there: the Blender scenes' origin (offset 0.5), and for captures the
///   focus of the camera axes that `colmap2nerf.py` centres on (LLFF: the harmonic mean of
///   the near/far bounds along each axis). It is also the centre of every `aabb_scale`'s
///   box and of the densest grid levels, so the scene is where the model resolves best.
/// - **Axes**: the scene's axes are the source's world axes (engine (x, y, z) = world
///   (y, z, x), as the loader maps them), so the scene's up (+z) is the capture's up
///   (`colmap2nerf.py` turns the cameras' mean up to +z) and text stands upright. The scene
///   is turned about that up axis by `yaw` so that its front (−y, where text reads
///   correctly) faces the mean horizontal direction of the cameras — a forward-facing
///   capture sees the text from the front. When the cameras surround the scene (their
///   mean horizontal direction is under 0.3 of their mean horizontal distance) `yaw` is 0,
///   as for the generated scenes.
/// - **Size** (`scale`, engine units per scene metre): the largest at which the scene's
///   bounding sphere (radius the farthest corner of its bounding box, ~1.3–1.8 m) fills
///   80 % of the half field of view (the narrower of the two, from `fl_x`/`fl_y` and the
///   image size) of the median camera, so a typical view shows it whole and large (a
///   capture's subject fills its views, and so does this one); but the scene's bounding
///   box, turned, stays within 90 % of the box of the source's `aabb_scale`, the region
///   the model and its occupancy grid cover (for a Blender-like source, aabb_scale 1 and
///   cameras at 4 m, this is the binding limit only for wide scenes; a capture's box is
///   4–16 wide); and the nearest camera stays at least twice the bounding radius away, so
///   no camera stands inside it. A hidden scene so placed also fits the cover's box, which
///   `train --hidden` requires.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Placement {
    pub centre: [f32; 3],
    pub scale: f32,
    pub yaw: f32,
}

/// Fraction of the box's half-size the scene's turned bounding box may reach.
pub const BOX_FILL: f32 = 0.9;
/// Fraction of the half field of view the scene's bounding sphere fills at the median
/// camera.
pub const FILL: f32 = 0.8;

impl Placement {
    /// Engine point → scene point.
    pub fn to_scene(&self, q: [f32; 3]) -> V3 {
        let v = [
            q[0] - self.centre[0],
            q[1] - self.centre[1],
            q[2] - self.centre[2],
        ];
        let w = self.dir_to_scene(v);
        [w[0] / self.scale, w[1] / self.scale, w[2] / self.scale]
    }

    /// Engine direction → scene direction (a rotation: lengths are kept).
    pub fn dir_to_scene(&self, d: [f32; 3]) -> V3 {
        // World axes of the engine's: world (x, y, z) = engine (z, x, y).
        let w = [d[2], d[0], d[1]];
        // Undo the turn about z.
        let (s, c) = self.yaw.sin_cos();
        [c * w[0] + s * w[1], -s * w[0] + c * w[1], w[2]]
    }

    /// The placement for `cameras` (see the type's documentation) of `scene` in the box of
    /// `aabb_scale`.
    pub fn for_cameras(cameras: &[Camera], scene: &Scene, aabb_scale: u32) -> Placement {
        let radius = scene_radius(scene);
        let centre = [0.5f32; 3];
        let unturned = Placement {
            centre,
            scale: 1.0,
            yaw: 0.0,
        };
        let mut sizes = Vec::with_capacity(cameras.len());
        let (mut mean_h, mut mean_len, mut nearest) = ([0.0f64; 2], 0.0f64, f32::INFINITY);
        for c in cameras {
            let p = unturned.to_scene(c.position());
            let d = dot(p, p).sqrt();
            nearest = nearest.min(d);
            let half = (0.5 * c.width as f32 / c.fx).min(0.5 * c.height as f32 / c.fy);
            sizes.push(d * (FILL * half.atan()).sin() / radius);
            mean_h[0] += p[0] as f64;
            mean_h[1] += p[1] as f64;
            mean_len += (p[0] as f64).hypot(p[1] as f64);
        }
        sizes.sort_by(f32::total_cmp);
        let median = sizes[sizes.len() / 2];
        let (hx, hy) = (mean_h[0], mean_h[1]);
        let yaw = if hx.hypot(hy) >= 0.3 * mean_len && mean_len > 0.0 {
            // Turn the front (0, −1) onto the mean direction: (sin yaw, −cos yaw) = ĥ.
            hx.atan2(-hy) as f32
        } else {
            0.0
        };
        // Largest |coordinate| of the turned bounding box, for the box limit.
        let (s, c) = yaw.sin_cos();
        let mut extent = 0.0f32;
        for k in 0..8 {
            let p = corner(scene, k);
            extent = extent
                .max((c * p[0] - s * p[1]).abs())
                .max((s * p[0] + c * p[1]).abs())
                .max(p[2].abs());
        }
        let in_box = BOX_FILL * 0.5 * aabb_scale.clamp(1, 128) as f32 / extent;
        let scale = median.min(in_box).min(0.5 * nearest / radius);
        Placement { centre, scale, yaw }
    }
}

fn corner(scene: &Scene, k: usize) -> V3 {
    [
        if k & 1 == 0 { scene.lo[0] } else { scene.hi[0] },
        if k & 2 == 0 { scene.lo[1] } else { scene.hi[1] },
        if k & 4 == 0 { scene.lo[2] } else { scene.hi[2] },
    ]
}

/// The bounding radius of a scene: the farthest corner of its bounding box from the origin.
pub fn scene_radius(scene: &Scene) -> f32 {
    (0..8)
        .map(|k| {
            let c = corner(scene, k);
            dot(c, c).sqrt()
        })
        .fold(0.0, f32::max)
}

/// Straight-alpha RGBA8 rendering of `scene` placed by `place`, seen by `cam` (its own size
/// and lens), 2×2 stratified samples per pixel.
pub fn render_camera(scene: &Scene, cam: &Camera, place: &Placement) -> Vec<u8> {
    render_rgba(scene, cam.width as usize, cam.height as usize, |x, y| {
        let ray = cam.ray(x, y);
        (place.to_scene(ray.o), normalize(place.dir_to_scene(ray.d)))
    })
}

/// What `generate_from_cameras` took from the source.
#[derive(Clone, Debug, Serialize)]
pub struct CamerasFromInfo {
    pub source: PathBuf,
    /// The source's format, as detected.
    pub format: String,
    pub width: u32,
    pub height: u32,
    pub downscale: u32,
    pub aabb_scale: u32,
    pub placement: Placement,
    /// Views (all splits) in which the box centre projects inside the image.
    pub views_seeing_centre: usize,
    pub views: usize,
}

/// The source's splits: train and test always, val when the source has a val split of
/// its own (a NeRF-synthetic `transforms_val.json`; elsewhere val is the test split).
fn source_splits(dir: &Path, load: &LoadOptions) -> Result<Vec<(Split, Vec<Camera>, DatasetMeta)>> {
    let wrap = |e: Error| Error::Other(format!("cannot take cameras from {}: {e}", dir.display()));
    let mut out = Vec::new();
    for split in [Split::Train, Split::Val, Split::Test] {
        let (cams, meta) = dataset::load_cameras(dir, split, load).map_err(wrap)?;
        if split == Split::Val
            && !(meta.format == DatasetFormat::NerfSynthetic
                && meta
                    .json_path
                    .file_name()
                    .is_some_and(|n| n == "transforms_val.json"))
        {
            continue;
        }
        out.push((split, cams, meta));
    }
    Ok(out)
}

fn f(x: f32) -> serde_json::Value {
    // f32 → f64 is exact, and serde_json writes an f64 that reads back to the same f64.
    serde_json::Value::from(x as f64)
}

/// One frame of the output JSON: the camera's pose with `"scale": 1, "offset": 0` (the
/// inverse of the loader's permutation and sign flips, exactly) and its intrinsics.
fn frame_json(split: &str, i: usize, c: &Camera) -> serde_json::Value {
    let g = &c.c2w;
    // Loader: ngp rows = nerf rows (1, 2, 0), nerf columns 1 and 2 negated.
    let rows = [g[2], g[0], g[1]];
    let mut m: Vec<Vec<serde_json::Value>> = rows
        .iter()
        .map(|r| vec![f(r[0]), f(-r[1]), f(-r[2]), f(r[3])])
        .collect();
    m.push(vec![f(0.0), f(0.0), f(0.0), f(1.0)]);
    let mut j = serde_json::json!({
        "file_path": format!("./{split}/r_{i}"),
        "transform_matrix": m,
        "fl_x": f(c.fx), "fl_y": f(c.fy), "cx": f(c.cx), "cy": f(c.cy),
        "w": c.width, "h": c.height,
    });
    if let Some(d) = c.distortion {
        j["k1"] = f(d.k1);
        j["k2"] = f(d.k2);
        j["p1"] = f(d.p1);
        j["p2"] = f(d.p2);
    }
    j
}

/// Renders `scene` (any kind but room; `seed` picks a logo) from the cameras of the
/// dataset at `from` (read with `load`) into `out_dir`; see the module documentation.
/// Images are written first and the JSON files last, so an interrupted run never looks
/// complete.
pub fn generate_from_cameras(
    scene: &SceneKind,
    seed: u64,
    from: &Path,
    load: &LoadOptions,
    out_dir: &Path,
) -> Result<SynthSummary> {
    let t0 = std::time::Instant::now();
    if *scene == SceneKind::Room {
        return Err(Error::Config(
            "the room scene places its own cameras inside its walls: it cannot take another \
             dataset's cameras (use object, text or logo)"
                .into(),
        ));
    }
    let (sc, name) = bounded_scene(scene, seed)?;
    // Writing transforms_*.json beside the source would change what its folder loads as.
    let src_dir = if from.is_file() {
        from.parent().unwrap_or(Path::new("."))
    } else {
        from
    };
    if let (Ok(a), Ok(b)) = (src_dir.canonicalize(), out_dir.canonicalize())
        && a == b
    {
        return Err(Error::Config(format!(
            "{}: the output folder is the camera source itself",
            out_dir.display()
        )));
    }
    let splits = source_splits(from, load)?;
    let train = &splits[0].1;
    let place = Placement::for_cameras(train, &sc, splits[0].2.aabb_scale);
    if !(place.scale.is_finite() && place.scale > 0.0) {
        return Err(Error::Other(format!(
            "{}: a camera stands at the centre of the box, where the scene would stand",
            from.display()
        )));
    }
    let centre = place.centre;
    let views: usize = splits.iter().map(|s| s.1.len()).sum();
    let seeing = splits
        .iter()
        .flat_map(|s| s.1.iter())
        .filter(|c| c.sees(centre))
        .count();
    if !train.iter().any(|c| c.sees(centre)) {
        return Err(Error::Other(format!(
            "{}: none of its train cameras sees the centre of the box, where the scene would \
             stand",
            from.display()
        )));
    }
    for (split, cams, _) in &splits {
        let dir = out_dir.join(split.name());
        std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        for (i, c) in cams.iter().enumerate() {
            let rgba = render_camera(&sc, c, &place);
            let path = dir.join(format!("r_{i}.png"));
            write_atomic_with(&path, |f| {
                use std::io::Write;
                f.write_all(&encode_png(c.width, c.height, &rgba)?)
            })?;
        }
    }
    let meta = &splits[0].2;
    for (split, cams, _) in &splits {
        let frames: Vec<serde_json::Value> = cams
            .iter()
            .enumerate()
            .map(|(i, c)| frame_json(split.name(), i, c))
            .collect();
        let json = serde_json::json!({
            "scale": 1.0, "offset": [0.0, 0.0, 0.0],
            "aabb_scale": meta.aabb_scale,
            "frames": frames,
        });
        let text = serde_json::to_string_pretty(&json).map_err(|e| Error::Other(e.to_string()))?;
        write_atomic(
            &out_dir.join(format!("transforms_{}.json", split.name())),
            text.as_bytes(),
        )?;
    }
    let count = |s: Split| splits.iter().find(|x| x.0 == s).map_or(0, |x| x.1.len());
    Ok(SynthSummary {
        dir: out_dir.to_path_buf(),
        scene: name,
        resolution: meta.width,
        height: meta.height,
        n_train: count(Split::Train),
        n_val: count(Split::Val),
        n_test: count(Split::Test),
        seconds: t0.elapsed().as_secs_f64(),
        cameras_from: Some(CamerasFromInfo {
            source: from.to_path_buf(),
            format: meta.format.name().into(),
            width: meta.width,
            height: meta.height,
            downscale: load.downscale,
            aabb_scale: meta.aabb_scale,
            placement: place,
            views_seeing_centre: seeing,
            views,
        }),
    })
}
