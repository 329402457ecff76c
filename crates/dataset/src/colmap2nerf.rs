//! Imported real captures (COLMAP, LLFF) and their conversion to an instant-ngp
//! `transforms.json`, with the maths of instant-ngp's `scripts/colmap2nerf.py`:
//!
//! 1. camera-to-world from COLMAP (`R(q)ᵀ`, `−R(q)ᵀ t`), camera axes OpenCV (right, down,
//!    forward);
//! 2. camera columns 1 and 2 negated (OpenGL axes: right, up, back), world rows 0 and 1
//!    swapped and world row 2 negated (COLMAP's world turned "upside down" as the script does);
//! 3. the sum of the cameras' up axes rotated onto +z ([`rotmat`]);
//! 4. the scene recentred on the weighted mean of the closest points between every pair of
//!    optical axes ([`closest_point_2_lines`], weight `|dₐ × d_b|²`, pairs with weight
//!    ≤ 1e-5 skipped), then scaled so that the mean camera distance to the origin is 4.
//!
//! The output has the script's shape: one camera → its intrinsics at the top level
//! (`camera_angle_x/y`, `fl_x/y`, `k1 k2 k3 k4 p1 p2`, `is_fisheye`, `cx cy w h`), several →
//! each frame carries its camera's intrinsics; `aabb_scale`; frames with `file_path` and a
//! 4×4 `transform_matrix`. Differences: no `sharpness` key (we do not compute the variance
//! of the Laplacian, and without it instant-ngp keeps every frame whose image exists), frames
//! are in file-name order, and intrinsics are those of the images actually read (scaled when
//! an `images_N/` folder is used). The script breaks the degenerate case "up = −z" with a
//! random perturbation; [`rotmat`] uses a fixed half-turn about x instead.

use std::path::{Component, Path, PathBuf};

use serde_json::{Value, json};

use crate::transforms::{FocalVal, Intrinsics, MadeFrame, Transforms, made_transforms};
use ngp::data::DatasetFormat;
use ngp::data::image::image_size;
use ngp::error::{Error, Result};
use ngp::geometry::{cross, dot, norm, quat_to_rotation, scale};

/// colmap2nerf's `--aabb_scale` default (ours are per format: see `colmap` and `llff`).
pub const COLMAP2NERF_AABB_SCALE: u32 = 32;

/// Weight below which a pair of nearly parallel axes is ignored (the script's 0.00001).
const PAIR_WEIGHT_MIN: f64 = 1e-5;

/// Pinhole intrinsics with OpenCV k1, k2, p1, p2, in pixels of the images actually read.
#[derive(Clone, Debug, PartialEq)]
pub struct ImportCamera {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub k1: f64,
    pub k2: f64,
    pub p1: f64,
    pub p2: f64,
}

impl ImportCamera {
    /// Width and height, and the script's `camera_angle_x` and `camera_angle_y`.
    fn size_and_angles(&self) -> ([f64; 2], [f64; 2]) {
        let (w, h) = (self.width as f64, self.height as f64);
        let ax = 2.0 * (w / (2.0 * self.fx)).atan();
        let ay = 2.0 * (h / (2.0 * self.fy)).atan();
        ([w, h], [ax, ay])
    }

    /// The script's per-camera dictionary (k3, k4 = 0, not fisheye).
    fn json_fields(&self) -> serde_json::Map<String, Value> {
        let ([w, h], [ax, ay]) = self.size_and_angles();
        let v = json!({
            "camera_angle_x": ax,
            "camera_angle_y": ay,
            "fl_x": self.fx,
            "fl_y": self.fy,
            "k1": self.k1,
            "k2": self.k2,
            "k3": 0.0,
            "k4": 0.0,
            "p1": self.p1,
            "p2": self.p2,
            "is_fisheye": false,
            "cx": self.cx,
            "cy": self.cy,
            "w": w,
            "h": h,
        });
        match v {
            Value::Object(m) => m,
            _ => unreachable!("json! of an object literal"),
        }
    }

    /// The intrinsics [`transforms`](crate::transforms) reads from [`Self::json_fields`]: a
    /// number that is not finite is JSON's `null` there, which reads as absent.
    fn intrinsics(&self) -> Intrinsics {
        let ([w, h], [ax, ay]) = self.size_and_angles();
        let finite = |x: f64| x.is_finite().then_some(x);
        let focal = |fl: f64, angle: f64| {
            finite(fl)
                .map(FocalVal::Pixels)
                .or_else(|| finite(angle).map(FocalVal::AngleRad))
        };
        Intrinsics {
            fl: [focal(self.fx, ax), focal(self.fy, ay)],
            pp: [
                finite(self.cx).map(|c| (c, Some(w))),
                finite(self.cy).map(|c| (c, Some(h))),
            ],
            lens: [self.k1, self.k2, self.p1, self.p2].map(|k| finite(k).map(|k| k as f32)),
            wh: [Some(w), Some(h)],
        }
    }
}

/// One posed image.
#[derive(Clone, Debug)]
pub struct ImportFrame {
    /// Image name relative to the image folder (COLMAP's `NAME`, or the LLFF file name).
    pub name: String,
    /// Where the image is on disk.
    pub image_path: PathBuf,
    /// Index into [`ImportedScene::cameras`].
    pub camera: usize,
    /// Camera-to-world 3×4 in COLMAP's world, camera axes right, down, forward (OpenCV).
    pub c2w: [[f64; 4]; 3],
    /// Near and far depth of what this camera sees, where the capture records it (LLFF's
    /// bounds, or the percentiles of a COLMAP model's point depths that LLFF's
    /// `imgs2poses` takes them from), in the units of `c2w`.
    pub depth_bounds: Option<[f64; 2]>,
}

/// Count and bounding box of a model's 3D points (COLMAP world coordinates).
#[derive(Clone, Debug, PartialEq)]
pub struct PointsSummary {
    pub count: u64,
    pub min: [f64; 3],
    pub max: [f64; 3],
}

/// A real capture as read from disk, before normalisation.
#[derive(Clone, Debug)]
pub struct ImportedScene {
    pub format: DatasetFormat,
    /// The model it came from (the sparse folder, or `poses_bounds.npy`): used in messages.
    pub source: PathBuf,
    /// The dataset folder: image paths in an in-memory transforms.json are relative to it.
    pub root: PathBuf,
    /// The image folder used, relative to `root` (`images`, `images_8`, …).
    pub images_dir: String,
    pub cameras: Vec<ImportCamera>,
    /// Sorted by `name` (plain byte order, as the LLFF tools sort).
    pub frames: Vec<ImportFrame>,
    /// The format's default `aabb_scale`.
    pub default_aabb_scale: u32,
    /// COLMAP's `points3D`, when present (COLMAP world coordinates).
    pub points: Option<PointsSummary>,
}

/// What the normalisation did, for reports.
#[derive(Clone, Debug, PartialEq)]
pub struct Normalisation {
    /// Mean camera up axis after the world flips, before rotation (unit length).
    pub up: [f64; 3],
    /// Rotation taking `up` onto +z.
    pub rotation: [[f64; 3]; 3],
    /// The point the cameras look at (after rotation), moved to the origin.
    pub centre: [f64; 3],
    /// Factor applied after recentring: 4 / mean camera distance.
    pub scale: f64,
    /// How the centre was found.
    pub centre_from: CentreFrom,
    /// How nearly the cameras look the same way ([`view_alignment`]).
    pub view_alignment: f64,
}

/// Where the normalisation's centre comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum CentreFrom {
    /// colmap2nerf's weighted closest point of the optical axes.
    Axes,
    /// The mean of the points at each camera's focus depth along its axis.
    Focus,
}

/// View alignment from which a capture counts as forward-facing: its cameras' axes then lie
/// within about 20° of their mean (0.97 is the alignment of axes spread evenly over ±25°).
/// colmap2nerf's closest point of nearly parallel axes is ill-conditioned: flower, posed by
/// `process`, aligns at 0.99 and its closest point fell among the cameras; 360° and
/// object-centred captures align far below (fox-colmap 0.82).
pub const FORWARD_FACING_ALIGNMENT: f64 = 0.97;

/// The length of the mean of the cameras' unit viewing directions (COLMAP camera-to-world,
/// OpenCV axes): 1 when every camera looks the same way, near 0 for cameras all round.
pub fn view_alignment(c2w_colmap: &[[[f64; 4]; 3]]) -> f64 {
    let mut sum = [0.0; 3];
    for m in c2w_colmap {
        let f = [m[0][2], m[1][2], m[2][2]];
        let n = norm(f);
        if n > 0.0 && n.is_finite() {
            for k in 0..3 {
                sum[k] += f[k] / n;
            }
        }
    }
    norm(sum) / c2w_colmap.len().max(1) as f64
}

/// The result of [`to_transforms`]: the instant-ngp transforms of a capture, as colmap2nerf
/// would write them. [`Converted::transforms`] reads them as the loader reads such a file,
/// [`Converted::to_json`] is the file.
#[derive(Clone, Debug)]
pub struct Converted {
    pub aabb_scale: u32,
    /// The capture's cameras: one → its intrinsics at the top level, several → each frame
    /// carries its camera's.
    pub cameras: Vec<ImportCamera>,
    /// In the capture's order (byte order of the image names).
    pub frames: Vec<ConvertedFrame>,
    pub norm: Normalisation,
}

/// One frame of [`Converted`].
#[derive(Clone, Debug)]
pub struct ConvertedFrame {
    /// The image, relative to the folder the transforms belong to.
    pub file_path: String,
    /// Index into [`Converted::cameras`].
    pub camera: usize,
    /// Camera-to-world 3×4, nerf (OpenGL) convention, after normalisation.
    pub transform_matrix: [[f64; 4]; 3],
}

/// Camera-to-world 3×4 of a COLMAP image (world-to-camera `x_c = R(q) x_w + t`).
pub fn colmap_c2w(q: [f64; 4], t: [f64; 3]) -> [[f64; 4]; 3] {
    let r = quat_to_rotation(q);
    let mut m = [[0.0; 4]; 3];
    for i in 0..3 {
        for j in 0..3 {
            m[i][j] = r[j][i];
        }
        m[i][3] = -(r[0][i] * t[0] + r[1][i] * t[1] + r[2][i] * t[2]);
    }
    m
}

/// The rotation taking direction `a` onto direction `b` (Rodrigues, as the script's
/// `rotmat`). For opposite directions (where the script perturbs `a` at random) it returns
/// a half-turn about an axis perpendicular to `b`.
pub fn rotmat(a: [f64; 3], b: [f64; 3]) -> [[f64; 3]; 3] {
    let a = scale(a, 1.0 / norm(a));
    let b = scale(b, 1.0 / norm(b));
    let v = cross(a, b);
    let c = dot(a, b);
    if c < -1.0 + 1e-10 {
        // Half-turn about a unit axis n ⟂ b: R = 2nnᵀ − I.
        let helper = if b[0].abs() < 0.9 {
            [1.0, 0.0, 0.0]
        } else {
            [0.0, 1.0, 0.0]
        };
        let n = cross(b, helper);
        let n = scale(n, 1.0 / norm(n));
        let mut r = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                r[i][j] = 2.0 * n[i] * n[j] - if i == j { 1.0 } else { 0.0 };
            }
        }
        return r;
    }
    let s2 = dot(v, v);
    let k = [[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]];
    let f = (1.0 - c) / (s2 + 1e-10);
    let mut r = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            let kk: f64 = (0..3).map(|l| k[i][l] * k[l][j]).sum();
            r[i][j] = if i == j { 1.0 } else { 0.0 } + k[i][j] + kk * f;
        }
    }
    r
}

/// The point nearest to both lines `oa + t·da` and `ob + t·db` (each parameter clamped to
/// t ≤ 0: behind an OpenGL camera's back axis is in front of it), and the weight
/// `|da × db|²`, which goes to 0 for parallel lines. The script's `closest_point_2_lines`.
pub fn closest_point_2_lines(
    oa: [f64; 3],
    da: [f64; 3],
    ob: [f64; 3],
    db: [f64; 3],
) -> ([f64; 3], f64) {
    let da = scale(da, 1.0 / norm(da));
    let db = scale(db, 1.0 / norm(db));
    let c = cross(da, db);
    let denom = dot(c, c);
    let t = [ob[0] - oa[0], ob[1] - oa[1], ob[2] - oa[2]];
    // det([t, d, c]) with rows t, d, c = t · (d × c).
    let ta = (dot(t, cross(db, c)) / (denom + 1e-10)).min(0.0);
    let tb = (dot(t, cross(da, c)) / (denom + 1e-10)).min(0.0);
    let mut p = [0.0; 3];
    for k in 0..3 {
        p[k] = (oa[k] + ta * da[k] + ob[k] + tb * db[k]) * 0.5;
    }
    (p, denom)
}

/// Depth along a camera's axis of the point it looks at, from the near and far depth of what
/// it sees: their harmonic mean, which weighs the near content (the subject of a
/// forward-facing capture) over a background that reaches far away.
pub fn focus_depth(bounds: [f64; 2]) -> f64 {
    2.0 / (1.0 / bounds[0] + 1.0 / bounds[1])
}

/// The script's normalisation of camera-to-world matrices given in COLMAP's world with
/// OpenCV camera axes: returns OpenGL/NeRF camera-to-world 3×4 matrices, up = +z, centred,
/// mean distance 4.
///
/// The centre is the script's weighted closest point of the camera axes, unless every camera
/// comes with the depth of what it looks at (`focus`, from LLFF's bounds): then it is the
/// mean of the points at that depth along each axis. The script's estimate assumes cameras
/// that look inwards; the nearly parallel axes of a forward-facing capture (LLFF flower)
/// give it almost no weight, and the few diverging pairs put the centre *among the
/// cameras*, scaling the scene's content out of any box (flower's nearest content lands 8.6
/// ngp units from the cameras and did not train).
pub fn normalise(
    c2w_colmap: &[[[f64; 4]; 3]],
    focus: Option<&[f64]>,
) -> (Vec<[[f64; 4]; 3]>, Normalisation) {
    let mut up = [0.0; 3];
    let mut ms: Vec<[[f64; 4]; 3]> = c2w_colmap
        .iter()
        .map(|m| {
            let mut g = *m;
            for row in g.iter_mut() {
                row[1] = -row[1];
                row[2] = -row[2];
            }
            let mut g = [g[1], g[0], g[2]];
            for v in g[2].iter_mut() {
                *v = -*v;
            }
            for k in 0..3 {
                up[k] += g[k][1];
            }
            g
        })
        .collect();
    let n_up = norm(up);
    let up = if n_up > 0.0 && n_up.is_finite() {
        scale(up, 1.0 / n_up)
    } else {
        [0.0, 0.0, 1.0]
    };
    let r = rotmat(up, [0.0, 0.0, 1.0]);
    for m in ms.iter_mut() {
        let old = *m;
        for i in 0..3 {
            for j in 0..4 {
                m[i][j] = (0..3).map(|l| r[i][l] * old[l][j]).sum();
            }
        }
    }
    let col = |m: &[[f64; 4]; 3], j: usize| [m[0][j], m[1][j], m[2][j]];
    let (mut totp, mut totw) = ([0.0; 3], 0.0);
    let focus = focus.filter(|f| f.len() == ms.len() && !f.is_empty());
    let centre_from = match focus {
        Some(_) => CentreFrom::Focus,
        None => CentreFrom::Axes,
    };
    match focus {
        Some(depths) => {
            for (m, &d) in ms.iter().zip(depths) {
                // OpenGL cameras look down −z: the point is o − d·z.
                let (o, z) = (col(m, 3), col(m, 2));
                for k in 0..3 {
                    totp[k] += o[k] - d * z[k];
                }
            }
            totp = scale(totp, 1.0 / ms.len() as f64);
        }
        None => {
            for f in &ms {
                for g in &ms {
                    let (p, w) = closest_point_2_lines(col(f, 3), col(f, 2), col(g, 3), col(g, 2));
                    if w > PAIR_WEIGHT_MIN {
                        for k in 0..3 {
                            totp[k] += p[k] * w;
                        }
                        totw += w;
                    }
                }
            }
            if totw > 0.0 {
                totp = scale(totp, 1.0 / totw);
            }
        }
    }
    let mut avglen = 0.0;
    for m in ms.iter_mut() {
        for k in 0..3 {
            m[k][3] -= totp[k];
        }
        avglen += norm(col(m, 3));
    }
    avglen /= ms.len().max(1) as f64;
    // The script divides by the mean distance unconditionally; one camera at the centre
    // would give NaN, so that case keeps the scale.
    let scale = if avglen > 1e-12 && avglen.is_finite() {
        4.0 / avglen
    } else {
        1.0
    };
    for m in ms.iter_mut() {
        for row in m.iter_mut() {
            row[3] *= scale;
        }
    }
    (
        ms,
        Normalisation {
            up,
            rotation: r,
            centre: totp,
            scale,
            centre_from,
            view_alignment: view_alignment(c2w_colmap),
        },
    )
}

/// `images_N` folders directly in `root`, by increasing N.
fn downsampled_folders(root: &Path) -> Vec<String> {
    let Ok(rd) = std::fs::read_dir(root) else {
        return Vec::new();
    };
    let mut v: Vec<(u64, String)> = rd
        .filter_map(|e| e.ok())
        .filter(|e| e.path().is_dir())
        .filter_map(|e| {
            let name = e.file_name().to_str()?.to_string();
            let n: u64 = name.strip_prefix("images_")?.parse().ok()?;
            Some((n, name))
        })
        .collect();
    v.sort();
    v.into_iter().map(|(_, n)| n).collect()
}

/// The dataset folder and image folder of an import: the first of `roots` that holds
/// `chosen` (when given) or else `images/`, or else `images_N/` with the smallest N.
/// `source` names the model in messages.
pub fn find_image_root(
    roots: &[PathBuf],
    chosen: Option<&str>,
    source: &Path,
) -> Result<(PathBuf, String)> {
    let looked: Vec<String> = roots.iter().map(|r| r.display().to_string()).collect();
    if let Some(name) = chosen {
        let p = Path::new(name);
        if name.is_empty() || p.is_absolute() || p.components().any(|c| c == Component::ParentDir) {
            return Err(Error::Config(format!(
                "image folder {name:?}: give a folder name inside the dataset, e.g. images_8"
            )));
        }
        for r in roots {
            if r.join(name).is_dir() {
                return Ok((r.clone(), name.trim_end_matches('/').to_string()));
            }
        }
        return Err(Error::format(
            source,
            format!(
                "image folder {name} not found (looked in {})",
                looked.join(", ")
            ),
        ));
    }
    for r in roots {
        if r.join("images").is_dir() {
            return Ok((r.clone(), "images".into()));
        }
        if let Some(n) = downsampled_folders(r).into_iter().next() {
            return Ok((r.clone(), n));
        }
    }
    Err(Error::format(
        source,
        format!(
            "no images/ or images_N/ folder for this model (looked in {})",
            looked.join(", ")
        ),
    ))
}

/// Size of an image the model names; a missing file is an error naming the model file.
pub fn image_dims(path: &Path, model_file: &Path, what: &str) -> Result<(u32, u32)> {
    if !path.is_file() {
        return Err(Error::format(
            model_file,
            format!("{what}: image file {} not found", path.display()),
        ));
    }
    image_size(path)
}

/// `to` relative to the folder `from`, both made absolute and cleaned of `.`/`..`
/// lexically; `/` separators. Falls back to the absolute path when no relative one exists
/// (another drive).
pub fn relative_path(from: &Path, to: &Path) -> String {
    let clean = |p: &Path| -> PathBuf {
        let abs = std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf());
        let mut out = PathBuf::new();
        for c in abs.components() {
            match c {
                Component::CurDir => {}
                Component::ParentDir => {
                    out.pop();
                }
                other => out.push(other.as_os_str()),
            }
        }
        out
    };
    let (from, to) = (clean(from), clean(to));
    let fc: Vec<Component> = from.components().collect();
    let tc: Vec<Component> = to.components().collect();
    if fc.first() != tc.first() {
        return to.to_string_lossy().replace('\\', "/");
    }
    let common = fc.iter().zip(&tc).take_while(|(a, b)| a == b).count();
    let mut parts: Vec<String> = vec!["..".to_string(); fc.len() - common];
    parts.extend(
        tc[common..]
            .iter()
            .map(|c| c.as_os_str().to_string_lossy().into_owned()),
    );
    parts.join("/")
}

/// An instant-ngp `transforms.json` for the scene, as colmap2nerf writes it (see the module
/// documentation), with `file_path`s relative to `base_dir` (the folder the JSON is written
/// to, or the dataset folder for an in-memory load).
pub fn to_transforms(scene: &ImportedScene, aabb_scale: u32, base_dir: &Path) -> Converted {
    let poses: Vec<[[f64; 4]; 3]> = scene.frames.iter().map(|f| f.c2w).collect();
    let focus: Option<Vec<f64>> = scene
        .frames
        .iter()
        .map(|f| f.depth_bounds.map(focus_depth))
        .collect();
    // LLFF's bounds centre every LLFF capture, as before COLMAP models carried depths;
    // a COLMAP model's point depths centre it only where colmap2nerf's estimate fails.
    let focus = focus.filter(|_| {
        scene.format == DatasetFormat::Llff || view_alignment(&poses) >= FORWARD_FACING_ALIGNMENT
    });
    let (ms, norm) = normalise(&poses, focus.as_deref());
    let frames = scene
        .frames
        .iter()
        .zip(ms)
        .map(|(f, m)| ConvertedFrame {
            file_path: relative_path(base_dir, &f.image_path),
            camera: f.camera,
            transform_matrix: m,
        })
        .collect();
    Converted {
        aabb_scale,
        cameras: scene.cameras.clone(),
        frames,
        norm,
    }
}

impl Converted {
    /// The `transforms.json` colmap2nerf would write.
    pub fn to_json(&self) -> Value {
        let single = self.cameras.len() == 1;
        let frames: Vec<Value> = self
            .frames
            .iter()
            .map(|f| {
                let mut o = serde_json::Map::new();
                o.insert("file_path".into(), Value::from(f.file_path.clone()));
                let rows: Vec<Value> = f
                    .transform_matrix
                    .iter()
                    .map(|r| json!(r))
                    .chain(std::iter::once(json!([0.0, 0.0, 0.0, 1.0])))
                    .collect();
                o.insert("transform_matrix".into(), Value::Array(rows));
                if !single {
                    let c = &self.cameras[f.camera];
                    let mut fields = c.json_fields();
                    let (ax, ay) = (
                        fields["camera_angle_x"].clone(),
                        fields["camera_angle_y"].clone(),
                    );
                    fields.insert(
                        "fovx".into(),
                        json!(ax.as_f64().unwrap_or(0.0).to_degrees()),
                    );
                    fields.insert(
                        "fovy".into(),
                        json!(ay.as_f64().unwrap_or(0.0).to_degrees()),
                    );
                    o.extend(fields);
                }
                Value::Object(o)
            })
            .collect();
        let mut top = if single {
            self.cameras[0].json_fields()
        } else {
            serde_json::Map::new()
        };
        top.insert("aabb_scale".into(), json!(self.aabb_scale));
        top.insert("frames".into(), Value::Array(frames));
        Value::Object(top)
    }

    /// What [`parse_transforms_value`](crate::transforms::parse_transforms_value) makes of
    /// [`Self::to_json`], built directly: `json_path` names the transforms in messages,
    /// `base_dir` is the folder the `file_path`s are relative to.
    pub fn transforms(&self, json_path: &Path, base_dir: &Path) -> Result<Transforms> {
        let single = self.cameras.len() == 1;
        let top = if single {
            self.cameras[0].intrinsics()
        } else {
            Intrinsics::default()
        };
        let frames = self
            .frames
            .iter()
            .map(|f| MadeFrame {
                file_path: f.file_path.clone(),
                pose: f.transform_matrix,
                own: if single {
                    Intrinsics::default()
                } else {
                    self.cameras[f.camera].intrinsics()
                },
            })
            .collect();
        made_transforms(json_path, base_dir, self.aabb_scale, &top, frames)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol
    }

    fn mat_close(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3], tol: f64) -> bool {
        (0..3).all(|i| (0..3).all(|j| close(a[i][j], b[i][j], tol)))
    }

    #[test]
    fn quaternion_to_rotation_by_hand() {
        assert!(mat_close(
            &quat_to_rotation([1.0, 0.0, 0.0, 0.0]),
            &[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            0.0
        ));
        // 90° about z: q = (cos 45°, 0, 0, sin 45°); x → y, y → −x.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        assert!(mat_close(
            &quat_to_rotation([h, 0.0, 0.0, h]),
            &[[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
            1e-12
        ));
        // 180° about x: q = (0, 1, 0, 0); y → −y, z → −z. −q is the same rotation.
        let r = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]];
        assert!(mat_close(&quat_to_rotation([0.0, 1.0, 0.0, 0.0]), &r, 0.0));
        assert!(mat_close(&quat_to_rotation([0.0, -1.0, 0.0, 0.0]), &r, 0.0));
    }

    #[test]
    fn colmap_c2w_inverts_world_to_camera() {
        // w2c: 90° about z, t = (1, 2, 3). Camera centre = −Rᵀt = −(2, −1, 3) = (−2, 1, −3).
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let m = colmap_c2w([h, 0.0, 0.0, h], [1.0, 2.0, 3.0]);
        let c = [m[0][3], m[1][3], m[2][3]];
        assert!(close(c[0], -2.0, 1e-12) && close(c[1], 1.0, 1e-12) && close(c[2], -3.0, 1e-12));
        // Rotation part is Rᵀ.
        assert!(close(m[0][1], 1.0, 1e-12) && close(m[1][0], -1.0, 1e-12));
    }

    #[test]
    fn rotmat_takes_a_onto_b() {
        let apply = |r: &[[f64; 3]; 3], v: [f64; 3]| [dot(r[0], v), dot(r[1], v), dot(r[2], v)];
        for a in [
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.3, -0.2, 0.9],
            [0.0, 0.0, 1.0],
            [0.0, 0.0, -1.0],
            [0.2, 0.0, -1.0],
        ] {
            let r = rotmat(a, [0.0, 0.0, 1.0]);
            let got = apply(&r, scale(a, 1.0 / norm(a)));
            assert!(
                close(got[0], 0.0, 1e-6) && close(got[1], 0.0, 1e-6) && close(got[2], 1.0, 1e-6),
                "{a:?} → {got:?}"
            );
            // Orthonormal, det +1.
            let det = dot(r[0], cross(r[1], r[2]));
            assert!(close(det, 1.0, 1e-6), "{det}");
        }
        // Nearly opposite: the reference's 1e-10 in (1 − c) / (s² + 1e-10) costs accuracy
        // (kept, to match it): within 1e-3 at 1e-3 from −z.
        let a = [1e-3, 0.0, -1.0];
        let got = apply(&rotmat(a, [0.0, 0.0, 1.0]), scale(a, 1.0 / norm(a)));
        assert!(close(got[2], 1.0, 1e-3), "{got:?}");
        // By hand: x onto z is a quarter turn about −y (v = x × z = −y, c = 0, R = I + K + K²).
        let r = rotmat([1.0, 0.0, 0.0], [0.0, 0.0, 1.0]);
        assert!(mat_close(
            &r,
            &[[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]],
            1e-9
        ));
    }

    #[test]
    fn closest_point_of_two_lines_by_hand() {
        // Line a: through (0,0,1) along x; line b: through (0,0,−1) along y. Nearest points
        // (0,0,1) and (0,0,−1): midpoint the origin, weight |x × y|² = 1.
        let (p, w) = closest_point_2_lines(
            [2.0, 0.0, 1.0],
            [1.0, 0.0, 0.0],
            [0.0, 3.0, -1.0],
            [0.0, 1.0, 0.0],
        );
        assert!(p.iter().all(|v| close(*v, 0.0, 1e-9)), "{p:?}");
        assert!(close(w, 1.0, 1e-12));
        // Nearest points ahead of the origins (t = 2 and t = 3 > 0) are clamped to the
        // origins: midpoint of (2,0,1) and (0,−3,−1).
        let (p, _) = closest_point_2_lines(
            [2.0, 0.0, 1.0],
            [-1.0, 0.0, 0.0],
            [0.0, -3.0, -1.0],
            [0.0, 1.0, 0.0],
        );
        assert!(close(p[0], 1.0, 1e-9) && close(p[1], -1.5, 1e-9) && close(p[2], 0.0, 1e-9));
        // Only a clamped: b's nearest point (0,0,−1) has t = −3 ≤ 0 and is kept.
        let (p, _) = closest_point_2_lines(
            [2.0, 0.0, 1.0],
            [-1.0, 0.0, 0.0],
            [0.0, -3.0, -1.0],
            [0.0, -1.0, 0.0],
        );
        assert!(close(p[0], 1.0, 1e-9) && close(p[1], 0.0, 1e-9) && close(p[2], 0.0, 1e-9));
        // Parallel lines: weight 0.
        let (_, w) =
            closest_point_2_lines([0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [2.0, 0.0, 0.0]);
        assert_eq!(w, 0.0);
    }

    /// COLMAP c2w of a camera at `pos` looking at `target`, COLMAP world up = −y (as COLMAP
    /// reconstructions of upright photos usually are).
    fn look_at_colmap(pos: [f64; 3], target: [f64; 3]) -> [[f64; 4]; 3] {
        let f = [target[0] - pos[0], target[1] - pos[1], target[2] - pos[2]];
        let f = scale(f, 1.0 / norm(f));
        let down = [0.0, 1.0, 0.0];
        let r = cross(down, f);
        let r = scale(r, 1.0 / norm(r));
        let d = cross(f, r);
        [
            [r[0], d[0], f[0], pos[0]],
            [r[1], d[1], f[1], pos[1]],
            [r[2], d[2], f[2], pos[2]],
        ]
    }

    #[test]
    fn normalisation_centres_on_the_focus_and_scales_to_4() {
        // Four cameras on a circle of radius 10 around (5, 0, 5), looking at it.
        let c = [5.0, 0.0, 5.0];
        let poses: Vec<_> = (0..4)
            .map(|i| {
                let a = i as f64 * std::f64::consts::FRAC_PI_2 + 0.3;
                let pos = [c[0] + 10.0 * a.cos(), -2.0, c[2] + 10.0 * a.sin()];
                look_at_colmap(pos, c)
            })
            .collect();
        let (ms, n) = normalise(&poses, None);
        // The mean up axis is rotated onto +z: every camera (tilted ~11° down) has its up
        // column close to +z.
        for m in &ms {
            assert!(m[2][1] > 0.9, "{m:?}");
        }
        // Mean distance 4.
        let mean: f64 = ms
            .iter()
            .map(|m| norm([m[0][3], m[1][3], m[2][3]]))
            .sum::<f64>()
            / 4.0;
        assert!(close(mean, 4.0, 1e-9), "{mean}");
        // Every optical axis (−column 2) passes through the origin (the common focus):
        // the cameras are 2 above the focus's plane, so the axes meet at the focus exactly.
        for m in &ms {
            let o = [m[0][3], m[1][3], m[2][3]];
            let d = [-m[0][2], -m[1][2], -m[2][2]];
            let t = -dot(o, d);
            let q = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
            assert!(norm(q) < 1e-9, "{q:?}");
        }
        // Scale: distance from camera to focus √(100 + 4) → 4.
        assert!(close(n.scale, 4.0 / 104f64.sqrt(), 1e-9), "{}", n.scale);
        // Rotations stay rigid.
        for m in &ms {
            let r = [
                [m[0][0], m[0][1], m[0][2]],
                [m[1][0], m[1][1], m[1][2]],
                [m[2][0], m[2][1], m[2][2]],
            ];
            assert!(close(dot(r[0], cross(r[1], r[2])), 1.0, 1e-9));
        }
    }

    #[test]
    fn relative_paths() {
        assert_eq!(
            relative_path(Path::new("/a/b"), Path::new("/a/b/images/x.png")),
            "images/x.png"
        );
        assert_eq!(
            relative_path(Path::new("/a/c/d"), Path::new("/a/b/images/x.png")),
            "../../b/images/x.png"
        );
        assert_eq!(
            relative_path(Path::new("/a/./b/../b"), Path::new("/a/b/x.png")),
            "x.png"
        );
    }

    /// A COLMAP capture of `c2w` poses, each seeing depths 2 to 6.
    fn colmap_capture(poses: &[[[f64; 4]; 3]]) -> ImportedScene {
        let camera = ImportCamera {
            width: 8,
            height: 6,
            fx: 7.0,
            fy: 7.0,
            cx: 4.0,
            cy: 3.0,
            k1: 0.0,
            k2: 0.0,
            p1: 0.0,
            p2: 0.0,
        };
        let frames = poses
            .iter()
            .enumerate()
            .map(|(i, &c2w)| ImportFrame {
                name: format!("{i}.png"),
                image_path: PathBuf::from(format!("/d/images/{i}.png")),
                camera: 0,
                c2w,
                depth_bounds: Some([2.0, 6.0]),
            })
            .collect();
        ImportedScene {
            format: DatasetFormat::Colmap,
            source: PathBuf::from("/d/sparse/0"),
            root: PathBuf::from("/d"),
            images_dir: "images".into(),
            cameras: vec![camera],
            frames,
            default_aabb_scale: 16,
            points: None,
        }
    }

    #[test]
    fn point_depths_centre_a_forward_facing_colmap_capture_only() {
        // Side by side, looking at points 3 ahead (+y) of the middle camera, the axes
        // diverging slightly (aligned at 0.99+): centred on the focus depth, as LLFF is.
        let ahead: Vec<_> = [-0.5, 0.0, 0.5]
            .iter()
            .map(|&x| look_at_colmap([x, 0.0, 0.0], [1.5 * x, 3.0, 0.0]))
            .collect();
        let c = to_transforms(&colmap_capture(&ahead), 16, Path::new("/d"));
        assert_eq!(c.norm.centre_from, CentreFrom::Focus);
        assert!(c.norm.view_alignment > FORWARD_FACING_ALIGNMENT);
        // All round a point: colmap2nerf's closest point of the axes, whatever the depths.
        let round: Vec<_> = (0..6)
            .map(|i| (i as f64 * 60.0).to_radians())
            .map(|a| look_at_colmap([5.0 * a.cos(), 0.5, 5.0 * a.sin()], [0.0; 3]))
            .collect();
        let c = to_transforms(&colmap_capture(&round), 16, Path::new("/d"));
        assert_eq!(c.norm.centre_from, CentreFrom::Axes);
        assert!(c.norm.view_alignment < 0.2);
        // An LLFF capture keeps its bounds' centre all round too.
        let mut llff = colmap_capture(&round);
        llff.format = DatasetFormat::Llff;
        let c = to_transforms(&llff, 16, Path::new("/d"));
        assert_eq!(c.norm.centre_from, CentreFrom::Focus);
    }

    #[test]
    fn view_alignment_tells_forward_facing_from_all_round() {
        let look = |f: [f64; 3]| {
            let mut m = [[0.0; 4]; 3];
            for k in 0..3 {
                m[k][2] = f[k] * 2.0;
            }
            m
        };
        let same = [look([0.0, 1.0, 0.0]); 3];
        assert!((view_alignment(&same) - 1.0).abs() < 1e-12);
        let round = [1.0, -1.0].map(|s| look([s, 0.0, 0.0]));
        assert!(view_alignment(&round).abs() < 1e-12);
        // Spread evenly over ±25°: the documented threshold.
        let spread: Vec<_> = (0..=50)
            .map(|i| (i as f64 - 25.0).to_radians())
            .map(|a| look([a.sin(), a.cos(), 0.0]))
            .collect();
        let a = view_alignment(&spread);
        assert!((a - FORWARD_FACING_ALIGNMENT).abs() < 0.005, "{a}");
        assert_eq!(view_alignment(&[]), 0.0);
    }

    #[test]
    fn forward_facing_cameras_centre_on_their_focus_depth() {
        // Three OpenCV cameras side by side, all looking down +y of COLMAP's world (axes
        // parallel: the script's estimate has no weight at all), each seeing content from
        // depth 2 to 6: the focus is 3 in front of each (harmonic mean), so the centre is 3
        // in front of the middle camera and the mean camera distance scales to 4.
        let r = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]];
        let poses: Vec<[[f64; 4]; 3]> = [-1.0, 0.0, 1.0]
            .iter()
            .map(|&x| {
                [
                    [r[0][0], r[0][1], r[0][2], x],
                    [r[1][0], r[1][1], r[1][2], 0.0],
                    [r[2][0], r[2][1], r[2][2], 0.0],
                ]
            })
            .collect();
        assert_eq!(focus_depth([2.0, 6.0]), 3.0);
        let (ms, n) = normalise(&poses, Some(&[3.0, 3.0, 3.0]));
        assert_eq!(n.centre_from, CentreFrom::Focus);
        let dists: Vec<f64> = ms
            .iter()
            .map(|m| norm([m[0][3], m[1][3], m[2][3]]))
            .collect();
        let (d_side, d_mid) = ((1.0f64 + 9.0).sqrt(), 3.0);
        let expect = 4.0 / ((2.0 * d_side + d_mid) / 3.0);
        assert!((n.scale - expect).abs() < 1e-12, "{} vs {expect}", n.scale);
        assert!((dists[1] - 3.0 * expect).abs() < 1e-9);
        assert!((dists[0] - d_side * expect).abs() < 1e-9);
        // Without the depths the axes never meet: the centre stays at the origin of the
        // rotated world, among the cameras.
        let (_, n0) = normalise(&poses, None);
        assert_eq!(n0.centre, [0.0; 3]);
        assert_eq!(n0.centre_from, CentreFrom::Axes);
    }
}
