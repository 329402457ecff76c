//! Camera paths: generated ones (an orbit around the scene, the forward-facing spiral of LLFF
//! scenes) and paths read from nerfstudio's `camera_path.json` and instant-ngp's
//! `base_cam.json`; written in nerfstudio's format so other tools read ours.
//!
//! A path is kept in ngp space (the space the renderer marches in). instant-ngp's keyframes
//! are in that space already; nerfstudio's `camera_to_world` matrices are OpenGL-convention
//! poses in the capture's `transforms.json` frame, mapped with the model's own nerf → ngp
//! scale and offset.

use ngp::camera::Camera;
use ngp::camera::nerf_to_ngp;
use ngp::error::{Error, Result};
use ngp::geometry::normalize_by_reciprocal as normalize;
use ngp::geometry::{add, cross, dist, dot, norm, scale, sub};
use serde_json::{Map, Value, json};
use std::path::Path;

/// Frames per second of a path that does not say.
pub const DEFAULT_FPS: f32 = 24.0;
/// instant-ngp's default vertical field of view (degrees).
pub const DEFAULT_FOV_Y: f32 = 50.625;
/// Largest frame side a path file or a command may ask for (8K).
pub const MAX_SIDE: u32 = 8192;
/// Most frames a path may hold or a video may ask for.
pub const MAX_FRAMES: usize = 100_000;

/// One camera of a path: a pose in ngp space (columns right, down, forward, position) and a
/// vertical field of view.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PathCamera {
    pub c2w: [[f32; 4]; 3],
    pub fov_y_deg: f32,
}

impl PathCamera {
    /// The pinhole camera of a `width`×`height` frame (square pixels, centred).
    pub fn camera(&self, width: u32, height: u32) -> Camera {
        let fy = 0.5 * height as f32 / (0.5 * self.fov_y_deg.to_radians()).tan();
        Camera {
            c2w: self.c2w,
            fx: fy,
            fy,
            cx: 0.5 * width as f32,
            cy: 0.5 * height as f32,
            width,
            height,
            distortion: None,
        }
    }

    /// The path camera of a dataset camera: its pose and vertical field of view.
    pub fn of(camera: &Camera) -> Self {
        PathCamera {
            c2w: camera.c2w,
            fov_y_deg: fov_deg(camera.height as f32, camera.fy),
        }
    }
}

fn fov_deg(size: f32, focal: f32) -> f32 {
    2.0 * (0.5 * size / focal).atan().to_degrees()
}

/// The frames of a video: cameras, and what the file said of frame rate and size.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraPath {
    pub cameras: Vec<PathCamera>,
    pub fps: f32,
    /// Width, height the path was made for, when a file says.
    pub size: Option<(u32, u32)>,
}

/// The capture's nerf (transforms.json) frame: ngp = cycle(nerf · scale + offset).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NerfFrame {
    pub scale: f32,
    pub offset: [f32; 3],
}

impl Default for NerfFrame {
    /// The loaders' defaults (instant-ngp's 0.33 and 0.5).
    fn default() -> Self {
        NerfFrame {
            scale: 0.33,
            offset: [0.5; 3],
        }
    }
}

impl NerfFrame {
    pub fn to_ngp(&self, nerf: &[[f32; 4]; 3]) -> [[f32; 4]; 3] {
        nerf_to_ngp(nerf, self.scale, self.offset)
    }

    /// The inverse of [`to_ngp`](Self::to_ngp).
    pub fn to_nerf(&self, ngp: &[[f32; 4]; 3]) -> [[f32; 4]; 3] {
        let mut r = [ngp[2], ngp[0], ngp[1]];
        for (i, row) in r.iter_mut().enumerate() {
            row[1] = -row[1];
            row[2] = -row[2];
            row[3] = (row[3] - self.offset[i]) / self.scale;
        }
        r
    }
}

/// The cameras a model keeps: instant-ngp stores the cover's training cameras (never a
/// hidden scene's) under `nerf.dataset`; none for a model saved without them.
pub fn model_cameras(model: &ngp::model::Model) -> Vec<PathCamera> {
    model.dataset.as_ref().map_or_else(Vec::new, |d| {
        d.images
            .iter()
            .filter(|im| im.resolution[1] > 0 && im.focal_length[1] > 0.0)
            .map(|im| PathCamera {
                c2w: im.xform_start,
                fov_y_deg: fov_deg(im.resolution[1] as f32, im.focal_length[1]),
            })
            .collect()
    })
}

/// The size of the model's first stored camera, when it keeps one.
pub fn model_frame_size(model: &ngp::model::Model) -> Option<(u32, u32)> {
    let im = model.dataset.as_ref()?.images.first()?;
    let (w, h) = (im.resolution[0], im.resolution[1]);
    (w > 0 && h > 0).then_some((w as u32, h as u32))
}

impl NerfFrame {
    /// The frame a model was trained in (its stored dataset's scale and offset), else the
    /// loaders' defaults.
    pub fn of_model(model: &ngp::model::Model) -> Self {
        model
            .dataset
            .as_ref()
            .map_or_else(NerfFrame::default, |d| NerfFrame {
                scale: d.scale,
                offset: d.offset,
            })
    }
}

// ---------------------------------------------------------------------------------------------
// Generated paths

/// Where a scene is and which way is up, read off the cameras that captured it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneRig {
    /// The point the cameras look at (least squares over their optical axes), or the box's
    /// centre when the axes are near parallel.
    pub centre: [f32; 3],
    /// Unit vector, the mean of the cameras' up (−down) axes.
    pub up: [f32; 3],
    /// Mean distance of the cameras from the centre.
    pub distance: f32,
    /// Mean elevation of the cameras above the centre, radians.
    pub elevation: f32,
    /// Azimuth of the first camera about `up`, radians.
    pub azimuth: f32,
    /// Mean vertical field of view, degrees.
    pub fov_y_deg: f32,
    /// Mean position and forward axis (for the spiral).
    pub mean_position: [f32; 3],
    pub mean_forward: [f32; 3],
    pub mean_right: [f32; 3],
    /// 90th percentile of |position − mean| along right, down, forward.
    pub spread: [f32; 3],
    /// The azimuths the cameras cover about `up`: where the covered arc starts and how wide
    /// it is (radians; 2π when no gap between neighbouring cameras exceeds 90°).
    pub arc_start: f32,
    pub arc_span: f32,
}

impl SceneRig {
    /// The rig of `cameras` (at least one); `box_centre` stands in for the focus point when the
    /// optical axes do not meet.
    pub fn of(cameras: &[PathCamera], box_centre: [f32; 3]) -> Option<Self> {
        if cameras.is_empty() {
            return None;
        }
        let n = cameras.len() as f32;
        let col = |c: &PathCamera, k: usize| normalize([c.c2w[0][k], c.c2w[1][k], c.c2w[2][k]]);
        let pos = |c: &PathCamera| [c.c2w[0][3], c.c2w[1][3], c.c2w[2][3]];
        let mut up = [0.0f32; 3];
        let mut fwd = [0.0f32; 3];
        let mut right = [0.0f32; 3];
        let mut mean = [0.0f32; 3];
        let mut fov = 0.0;
        // Least squares focus: Σ (I − d dᵀ) x = Σ (I − d dᵀ) o.
        let mut a = [[0.0f64; 3]; 3];
        let mut b = [0.0f64; 3];
        for c in cameras {
            let (d, o) = (col(c, 2), pos(c));
            up = add(up, scale(col(c, 1), -1.0));
            fwd = add(fwd, d);
            right = add(right, col(c, 0));
            mean = add(mean, o);
            fov += c.fov_y_deg;
            for i in 0..3 {
                for j in 0..3 {
                    let m = if i == j { 1.0 } else { 0.0 } - d[i] as f64 * d[j] as f64;
                    a[i][j] += m;
                    b[i] += m * o[j] as f64;
                }
            }
        }
        let up = snap_to_axis(level_up(cameras, normalize(up)));
        let mean = scale(mean, 1.0 / n);
        let fwd = normalize(fwd);
        let centre = solve3(a, b, n as f64)
            .map(|x| [x[0] as f32, x[1] as f32, x[2] as f32])
            // A focus behind the cameras, or far beyond the box, means the axes barely meet.
            .filter(|x| {
                dot(sub(*x, mean), fwd) > 0.0
                    && dist(*x, box_centre) < 4.0 * dist(mean, box_centre).max(1.0)
            })
            .unwrap_or(box_centre);
        let mut distance = 0.0;
        let mut elevation = 0.0;
        for c in cameras {
            let v = sub(pos(c), centre);
            let r = norm(v).max(1e-6);
            distance += r;
            elevation += (dot(v, up) / r).clamp(-1.0, 1.0).asin();
        }
        let (e1, e2) = basis(up);
        let v0 = sub(pos(&cameras[0]), centre);
        let azimuth = dot(v0, e2).atan2(dot(v0, e1));
        let right = normalize(right);
        let down = scale(up, -1.0);
        let mut offs: [Vec<f32>; 3] = Default::default();
        for c in cameras {
            let v = sub(pos(c), mean);
            for (k, axis) in [right, down, fwd].into_iter().enumerate() {
                offs[k].push(dot(v, axis).abs());
            }
        }
        // The covered arc: the circle less its widest gap between neighbouring azimuths.
        let mut az: Vec<f32> = cameras
            .iter()
            .map(|c| {
                let v = sub(pos(c), centre);
                dot(v, e2).atan2(dot(v, e1))
            })
            .collect();
        az.sort_by(|a, b| a.total_cmp(b));
        let tau = std::f32::consts::TAU;
        let (mut gap, mut gap_end) = (az[0] + tau - az[az.len() - 1], az[0]);
        for w in az.windows(2) {
            if w[1] - w[0] > gap {
                (gap, gap_end) = (w[1] - w[0], w[1]);
            }
        }
        let (arc_start, arc_span) = if gap > tau / 4.0 {
            (gap_end, tau - gap)
        } else {
            (azimuth, tau)
        };
        let spread = offs.map(|mut v| {
            v.sort_by(|a, b| a.total_cmp(b));
            v[((v.len() - 1) as f32 * 0.9).round() as usize]
        });
        Some(SceneRig {
            centre,
            up,
            distance: distance / n,
            elevation: elevation / n,
            azimuth,
            fov_y_deg: fov / n,
            mean_position: mean,
            mean_forward: fwd,
            mean_right: right,
            spread,
            arc_start,
            arc_span,
        })
    }

    /// instant-ngp's default view of an object in the unit box, for a model that keeps no
    /// cameras: centred on the box, +y up, from 1.5 away and 30° above.
    pub fn default_object() -> Self {
        SceneRig {
            centre: [0.5; 3],
            up: [0.0, 1.0, 0.0],
            distance: 1.5,
            elevation: 30f32.to_radians(),
            azimuth: 0.0,
            fov_y_deg: DEFAULT_FOV_Y,
            mean_position: [0.5, 0.5, -1.0],
            mean_forward: [0.0, 0.0, 1.0],
            mean_right: [1.0, 0.0, 0.0],
            spread: [0.1; 3],
            arc_start: 0.0,
            arc_span: std::f32::consts::TAU,
        }
    }

    /// Whether the cameras stand all around the scene (no gap wider than 90°).
    pub fn surrounds(&self) -> bool {
        self.arc_span >= std::f32::consts::TAU - 1e-6
    }

    /// `n` cameras swinging over the arc the cameras cover and back (eased at its ends), at
    /// the mean distance and elevation: an orbit for a capture taken from one side, which
    /// a full circle would show from behind, where no camera looked.
    pub fn sweep(&self, n: usize) -> Vec<PathCamera> {
        (0..n)
            .map(|i| {
                let t = std::f32::consts::TAU * i as f32 / n as f32;
                let az = self.arc_start + self.arc_span * 0.5 * (1.0 - t.cos());
                self.camera_at(az)
            })
            .collect()
    }

    fn camera_at(&self, az: f32) -> PathCamera {
        let (e1, e2) = basis(self.up);
        let (ce, se) = (self.elevation.cos(), self.elevation.sin());
        let dir = add(
            scale(add(scale(e1, az.cos()), scale(e2, az.sin())), ce),
            scale(self.up, se),
        );
        let p = add(self.centre, scale(dir, self.distance));
        PathCamera {
            c2w: look_at(p, self.centre, self.up),
            fov_y_deg: self.fov_y_deg,
        }
    }

    /// `n` cameras on a circle about `up` through the centre, at the mean distance and
    /// elevation, starting at the first camera's azimuth, each looking at the centre.
    pub fn orbit(&self, n: usize) -> Vec<PathCamera> {
        (0..n)
            .map(|i| self.camera_at(self.azimuth + std::f32::consts::TAU * i as f32 / n as f32))
            .collect()
    }

    /// The forward-facing spiral NeRF renders LLFF scenes with: two turns of an ellipse
    /// (the cameras' 90th-percentile spread) around the mean camera, half a cycle in depth,
    /// every camera looking at the focus point in front of the mean camera.
    pub fn spiral(&self, n: usize) -> Vec<PathCamera> {
        let fwd = self.mean_forward;
        let focus_depth = dot(sub(self.centre, self.mean_position), fwd).max(1e-3);
        let focus = add(self.mean_position, scale(fwd, focus_depth));
        let right = normalize(sub(self.mean_right, scale(fwd, dot(self.mean_right, fwd))));
        let down = cross(fwd, right);
        (0..n)
            .map(|i| {
                let t = 2.0 * std::f32::consts::TAU * i as f32 / n as f32;
                let off = add(
                    add(
                        scale(right, t.cos() * self.spread[0]),
                        scale(down, t.sin() * self.spread[1]),
                    ),
                    scale(fwd, (0.5 * t).sin() * self.spread[2]),
                );
                let p = add(self.mean_position, off);
                PathCamera {
                    c2w: look_at(p, focus, scale(down, -1.0)),
                    fov_y_deg: self.fov_y_deg,
                }
            })
            .collect()
    }
}

/// The pose at `eye` looking at `target`, its down axis as close to −`up` as it can be.
pub fn look_at(eye: [f32; 3], target: [f32; 3], up: [f32; 3]) -> [[f32; 4]; 3] {
    let f = normalize(sub(target, eye));
    let mut d = sub(scale(up, -1.0), scale(f, dot(scale(up, -1.0), f)));
    if norm(d) < 1e-6 {
        // Looking straight along up: any perpendicular will do.
        d = basis(f).0;
    }
    let d = normalize(d);
    // Right-handed: right × down = forward.
    let r = cross(d, f);
    [
        [r[0], d[0], f[0], eye[0]],
        [r[1], d[1], f[1], eye[1]],
        [r[2], d[2], f[2], eye[2]],
    ]
}

// ---------------------------------------------------------------------------------------------
// Files

/// Reads a path file, nerfstudio's `camera_path.json` (it has `camera_path`) or
/// instant-ngp's `base_cam.json` (it has `path`). `frames` resamples an instant-ngp path's
/// keyframes (a nerfstudio file lists its frames, and is rendered as it is); `frame` maps
/// nerfstudio's poses into ngp space.
pub fn read_path(path: &Path, frames: Option<usize>, frame: &NerfFrame) -> Result<CameraPath> {
    let meta = std::fs::metadata(path).map_err(|e| Error::io(path, e))?;
    // A path of 100 000 cameras is ~40 MB of JSON; anything larger is not a path.
    if meta.len() > 64 << 20 {
        return Err(Error::format(
            path,
            format!("{} bytes: too large for a camera path", meta.len()),
        ));
    }
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    parse_path(path, &text, frames, frame)
}

/// [`read_path`] on text already read; `path` names it in errors.
pub fn parse_path(
    path: &Path,
    text: &str,
    frames: Option<usize>,
    frame: &NerfFrame,
) -> Result<CameraPath> {
    let v: Value =
        serde_json::from_str(text).map_err(|e| Error::format(path, format!("not JSON: {e}")))?;
    let obj = v
        .as_object()
        .ok_or_else(|| Error::format(path, "a camera path is a JSON object"))?;
    let r = if obj.contains_key("camera_path") {
        if frames.is_some() {
            return Err(Error::format(
                path,
                "a nerfstudio camera_path.json lists its frames: --frames applies to generated paths and instant-ngp keyframes",
            ));
        }
        parse_nerfstudio(obj, frame)
    } else if obj.contains_key("path") {
        parse_instant_ngp(obj, frames)
    } else {
        Err("neither `camera_path` (nerfstudio) nor `path` (instant-ngp base_cam.json)".into())
    };
    r.map_err(|msg| Error::format(path, msg))
}

type Parse<T> = std::result::Result<T, String>;

fn number(v: Option<&Value>, field: &str) -> Parse<f32> {
    let x = v
        .ok_or_else(|| format!("{field}: missing"))?
        .as_f64()
        .ok_or_else(|| format!("{field}: expected a number"))?;
    let x = x as f32;
    if !x.is_finite() {
        return Err(format!("{field}: {x} is not a finite 32-bit number"));
    }
    Ok(x)
}

fn numbers<const N: usize>(v: Option<&Value>, field: &str) -> Parse<[f32; N]> {
    let a = v
        .ok_or_else(|| format!("{field}: missing"))?
        .as_array()
        .ok_or_else(|| format!("{field}: expected an array of {N} numbers"))?;
    if a.len() != N {
        return Err(format!("{field}: {} numbers, expected {N}", a.len()));
    }
    let mut out = [0.0; N];
    for (i, x) in a.iter().enumerate() {
        out[i] = number(Some(x), &format!("{field}[{i}]"))?;
    }
    Ok(out)
}

fn fov_field(v: Option<&Value>, field: &str) -> Parse<f32> {
    let f = number(v, field)?;
    if !(f > 0.0 && f < 180.0) {
        return Err(format!(
            "{field}: {f} is not a field of view in (0, 180) degrees"
        ));
    }
    Ok(f)
}

fn side(v: Option<&Value>, field: &str) -> Parse<Option<u32>> {
    match v {
        None | Some(Value::Null) => Ok(None),
        Some(x) => match x.as_u64() {
            Some(s) if (1..=MAX_SIDE as u64).contains(&s) => Ok(Some(s as u32)),
            _ => Err(format!(
                "{field}: expected a whole number of pixels in 1..={MAX_SIDE}"
            )),
        },
    }
}

fn fps_field(v: Option<&Value>, field: &str) -> Parse<f32> {
    match v {
        None | Some(Value::Null) => Ok(DEFAULT_FPS),
        x => {
            let f = number(x, field)?;
            if !(f > 0.0 && f <= 1000.0) {
                return Err(format!(
                    "{field}: {f} frames per second is not in (0, 1000]"
                ));
            }
            Ok(f)
        }
    }
}

/// A rotation's columns must be near orthonormal: a pose that scales or shears is no camera.
fn check_rotation(m: &[[f32; 4]; 3], field: &str) -> Parse<()> {
    let col = |k: usize| [m[0][k], m[1][k], m[2][k]];
    for k in 0..3 {
        if (norm(col(k)) - 1.0).abs() > 0.05 {
            return Err(format!(
                "{field}: column {k} of the rotation has length {:.3}, not 1",
                norm(col(k))
            ));
        }
    }
    if dot(cross(col(0), col(1)), col(2)) < 0.5 {
        return Err(format!(
            "{field}: the rotation is not a right-handed orthonormal one"
        ));
    }
    Ok(())
}

/// The non-empty, bounded array under `field`, of `what`.
fn entries<'a>(obj: &'a Map<String, Value>, field: &str, what: &str) -> Parse<&'a Vec<Value>> {
    let list = obj[field]
        .as_array()
        .ok_or_else(|| format!("{field}: expected an array of {what}"))?;
    if list.is_empty() {
        return Err(format!("{field}: no {what}"));
    }
    if list.len() > MAX_FRAMES {
        return Err(format!(
            "{field}: {} {what}, more than {MAX_FRAMES}",
            list.len()
        ));
    }
    Ok(list)
}

fn parse_nerfstudio(obj: &Map<String, Value>, frame: &NerfFrame) -> Parse<CameraPath> {
    if let Some(t) = obj.get("camera_type").and_then(Value::as_str)
        && !t.eq_ignore_ascii_case("perspective")
    {
        return Err(format!(
            "camera_type: {t:?} cameras are not supported (perspective only)"
        ));
    }
    let w = side(obj.get("render_width"), "render_width")?;
    let h = side(obj.get("render_height"), "render_height")?;
    let fps = fps_field(obj.get("fps"), "fps")?;
    let list = entries(obj, "camera_path", "cameras")?;
    let mut cameras = Vec::with_capacity(list.len());
    for (i, c) in list.iter().enumerate() {
        let field = format!("camera_path[{i}]");
        let c = c
            .as_object()
            .ok_or_else(|| format!("{field}: expected an object"))?;
        let m: [f32; 16] = numbers(
            c.get("camera_to_world"),
            &format!("{field}.camera_to_world"),
        )?;
        let nerf = [
            [m[0], m[1], m[2], m[3]],
            [m[4], m[5], m[6], m[7]],
            [m[8], m[9], m[10], m[11]],
        ];
        check_rotation(&nerf, &format!("{field}.camera_to_world"))?;
        let fov_y_deg = fov_field(c.get("fov"), &format!("{field}.fov"))?;
        cameras.push(PathCamera {
            c2w: frame.to_ngp(&nerf),
            fov_y_deg,
        });
    }
    Ok(CameraPath {
        cameras,
        fps,
        size: w.zip(h),
    })
}

/// One instant-ngp keyframe: rotation (x, y, z, w), position, field of view, end time.
#[derive(Clone, Copy, Debug)]
struct Keyframe {
    r: [f32; 4],
    t: [f32; 3],
    fov: f32,
    timestamp: f32,
}

impl Keyframe {
    fn scaled(&self, f: f32) -> Keyframe {
        Keyframe {
            r: self.r.map(|x| x * f),
            t: self.t.map(|x| x * f),
            fov: self.fov * f,
            timestamp: self.timestamp,
        }
    }

    /// instant-ngp's keyframe sum: the right quaternion flips to the left's hemisphere.
    fn plus(&self, rhs: &Keyframe) -> Keyframe {
        let d: f32 = (0..4).map(|i| self.r[i] * rhs.r[i]).sum();
        let s = if d < 0.0 { -1.0 } else { 1.0 };
        Keyframe {
            r: std::array::from_fn(|i| self.r[i] + s * rhs.r[i]),
            t: std::array::from_fn(|i| self.t[i] + rhs.t[i]),
            fov: self.fov + rhs.fov,
            timestamp: rhs.timestamp,
        }
    }

    fn camera(&self) -> PathCamera {
        let rot = quat_to_mat(self.r);
        PathCamera {
            c2w: [
                [rot[0][0], rot[0][1], rot[0][2], self.t[0]],
                [rot[1][0], rot[1][1], rot[1][2], self.t[1]],
                [rot[2][0], rot[2][1], rot[2][2], self.t[2]],
            ],
            fov_y_deg: self.fov,
        }
    }
}

fn parse_instant_ngp(obj: &Map<String, Value>, frames: Option<usize>) -> Parse<CameraPath> {
    let list = entries(obj, "path", "keyframes")?;
    let looped = match obj.get("loop") {
        None | Some(Value::Null) => false,
        Some(v) => v.as_bool().ok_or("loop: expected true or false")?,
    };
    let order = match obj.get("spline_order") {
        None | Some(Value::Null) => 3,
        Some(v) => match v.as_u64() {
            Some(o) if o <= 3 => o as u32,
            _ => return Err("spline_order: expected 0, 1, 2 or 3".into()),
        },
    };
    let mut keys = Vec::with_capacity(list.len());
    for (i, k) in list.iter().enumerate() {
        let field = format!("path[{i}]");
        let k = k
            .as_object()
            .ok_or_else(|| format!("{field}: expected an object"))?;
        let r: [f32; 4] = numbers(k.get("R"), &format!("{field}.R"))?;
        let n = r.iter().map(|x| x * x).sum::<f32>().sqrt();
        if n.is_nan() || n <= 1e-6 {
            return Err(format!("{field}.R: a zero quaternion is no rotation"));
        }
        let t: [f32; 3] = numbers(k.get("T"), &format!("{field}.T"))?;
        let fov = fov_field(k.get("fov"), &format!("{field}.fov"))?;
        let timestamp = match k.get("timestamp") {
            None | Some(Value::Null) => 0.0,
            x => number(x, &format!("{field}.timestamp"))?,
        };
        keys.push(Keyframe {
            r: r.map(|x| x / n),
            t,
            fov,
            timestamp,
        });
    }
    // As instant-ngp's sanitize_keyframes: without strictly increasing timestamps, space the
    // keyframes evenly (keyframe i's timestamp ends segment i).
    let valid = keys
        .iter()
        .scan(0.0f32, |prev, k| {
            let ok = k.timestamp > *prev;
            *prev = k.timestamp;
            Some(ok)
        })
        .all(|ok| ok);
    if !valid {
        let n = keys.len() as f32;
        for (i, k) in keys.iter_mut().enumerate() {
            k.timestamp = (i + 1) as f32 / n;
        }
    }
    let n_frames = frames.unwrap_or(keys.len().max(2) * 8);
    let cameras = (0..n_frames)
        .map(|i| eval_keyframes(&keys, looped, order, i as f32 / n_frames as f32).camera())
        .collect();
    Ok(CameraPath {
        cameras,
        fps: DEFAULT_FPS,
        size: None,
    })
}

/// instant-ngp's `eval_camera_path` at play time `t` in [0, 1).
fn eval_keyframes(keys: &[Keyframe], looped: bool, order: u32, t: f32) -> Keyframe {
    let n = keys.len() as i64;
    let key = |i: i64| -> &Keyframe {
        if looped {
            &keys[i.rem_euclid(n) as usize]
        } else {
            &keys[i.clamp(0, n - 1) as usize]
        }
    };
    let (i, f) = if n == 1 {
        (0i64, t)
    } else {
        let duration = if looped {
            keys[keys.len() - 1].timestamp
        } else {
            keys[keys.len() - 2].timestamp
        };
        let play = t * duration;
        let above = keys.partition_point(|k| k.timestamp <= play) as i64;
        let i = above.clamp(0, n - if looped { 1 } else { 2 });
        let prev = if i == 0 {
            0.0
        } else {
            keys[i as usize - 1].timestamp
        };
        (i, (play - prev) / (keys[i as usize].timestamp - prev))
    };
    let norm_q = |mut k: Keyframe| {
        let n = k.r.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-12);
        k.r = k.r.map(|x| x / n);
        k
    };
    match order {
        0 => *key(i + f.round() as i64),
        1 => norm_q(key(i).scaled(1.0 - f).plus(&key(i + 1).scaled(f))),
        2 => {
            let (a, b, c) = (
                (1.0 - f) * (1.0 - f) * 0.5,
                (-2.0 * f * f + 2.0 * f + 1.0) * 0.5,
                f * f * 0.5,
            );
            norm_q(
                key(i - 1)
                    .scaled(a)
                    .plus(&key(i).scaled(b))
                    .plus(&key(i + 1).scaled(c)),
            )
        }
        _ => {
            let (tt, ttt) = (f * f, f * f * f);
            let a = (1.0 - f) * (1.0 - f) * (1.0 - f) / 6.0;
            let b = (3.0 * ttt - 6.0 * tt + 4.0) / 6.0;
            let c = (-3.0 * ttt + 3.0 * tt + 3.0 * f + 1.0) / 6.0;
            let d = ttt / 6.0;
            norm_q(
                key(i - 1)
                    .scaled(a)
                    .plus(&key(i).scaled(b))
                    .plus(&key(i + 1).scaled(c))
                    .plus(&key(i + 2).scaled(d)),
            )
        }
    }
}

/// nerfstudio's `camera_path.json` for `path` at `width`×`height`: each camera's
/// `camera_to_world` in the capture's transforms.json frame (OpenGL convention), its vertical
/// `fov` in degrees.
pub fn nerfstudio_json(path: &CameraPath, width: u32, height: u32, frame: &NerfFrame) -> Value {
    let cams: Vec<Value> = path
        .cameras
        .iter()
        .map(|c| {
            let m = frame.to_nerf(&c.c2w);
            let flat: Vec<f32> = m
                .iter()
                .flatten()
                .copied()
                .chain([0.0, 0.0, 0.0, 1.0])
                .collect();
            json!({
                "camera_to_world": flat,
                "fov": c.fov_y_deg,
                "aspect": width as f32 / height as f32,
            })
        })
        .collect();
    let n = path.cameras.len() as f32;
    json!({
        "camera_type": "perspective",
        "render_width": width,
        "render_height": height,
        "fps": path.fps,
        "seconds": n / path.fps,
        "smoothness_value": 0,
        "is_cycle": false,
        "camera_path": cams,
    })
}

/// Writes `path` as nerfstudio's `camera_path.json` (temporary file, then rename).
pub fn write_nerfstudio(
    out: &Path,
    path: &CameraPath,
    width: u32,
    height: u32,
    frame: &NerfFrame,
) -> Result<()> {
    let v = nerfstudio_json(path, width, height, frame);
    let text = serde_json::to_string_pretty(&v).map_err(|e| Error::format(out, e.to_string()))?;
    ngp::util::write_atomic(out, text.as_bytes())
}

/// instant-ngp's `base_cam.json` of `path`'s cameras as keyframes (linear spline, so the
/// frames are the keyframes themselves).
pub fn instant_ngp_json(path: &CameraPath) -> Value {
    let n = path.cameras.len() as f32;
    let keys: Vec<Value> = path
        .cameras
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let rot = [
                [c.c2w[0][0], c.c2w[0][1], c.c2w[0][2]],
                [c.c2w[1][0], c.c2w[1][1], c.c2w[1][2]],
                [c.c2w[2][0], c.c2w[2][1], c.c2w[2][2]],
            ];
            json!({
                "R": mat_to_quat(rot),
                "T": [c.c2w[0][3], c.c2w[1][3], c.c2w[2][3]],
                "fov": c.fov_y_deg,
                "slice": 0.0,
                "scale": 1.0,
                "aperture_size": 0.0,
                "timestamp": (i + 1) as f32 / n,
            })
        })
        .collect();
    json!({"loop": false, "time": 0.0, "path": keys, "duration_seconds": n / path.fps, "spline_order": 1})
}

// ---------------------------------------------------------------------------------------------
// Small vector algebra

/// Up as the direction the cameras' right axes are most nearly perpendicular to (upright
/// cameras hold their right axis level), found by power iteration from `mean_up`, the mean
/// of their up axes: that mean leans towards the scene when the cameras look down on it
/// from one side. Where the right axes are all alike (a forward-facing capture) any level
/// direction fits and the iteration keeps the mean.
fn level_up(cameras: &[PathCamera], mean_up: [f32; 3]) -> [f32; 3] {
    let mut m = [[0.0f32; 3]; 3];
    for c in cameras {
        let r = normalize([c.c2w[0][0], c.c2w[1][0], c.c2w[2][0]]);
        for i in 0..3 {
            for j in 0..3 {
                m[i][j] += r[i] * r[j];
            }
        }
    }
    let tr = m[0][0] + m[1][1] + m[2][2];
    let mut v = mean_up;
    for _ in 0..64 {
        // (tr·I − M) v: its largest eigenvalue belongs to M's smallest.
        let w = std::array::from_fn(|i| tr * v[i] - dot(m[i], v));
        let n = norm(w);
        if n.is_nan() || n <= 0.0 {
            return mean_up;
        }
        v = scale(w, 1.0 / n);
    }
    if dot(v, mean_up) < 0.0 {
        scale(v, -1.0)
    } else {
        v
    }
}

/// The nearest coordinate axis when `up` is within 10° of it: the loaders orient captures
/// so that ngp's +y is up, and the mean of the cameras' up axes leans by a few degrees when
/// they look down on an object from one side.
fn snap_to_axis(up: [f32; 3]) -> [f32; 3] {
    let k = (0..3)
        .max_by(|&a, &b| up[a].abs().total_cmp(&up[b].abs()))
        .unwrap_or(1);
    if up[k].abs() >= 10f32.to_radians().cos() {
        let mut axis = [0.0; 3];
        axis[k] = up[k].signum();
        axis
    } else {
        up
    }
}

/// Two unit vectors completing `n` to a right-handed orthonormal basis (e1, e2, n).
fn basis(n: [f32; 3]) -> ([f32; 3], [f32; 3]) {
    let helper = if n[0].abs() < 0.9 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 0.0, 1.0]
    };
    let e1 = normalize(cross(helper, n));
    // Pick e1 so that e1 × e2 = n.
    let e2 = cross(n, e1);
    (e1, e2)
}

fn solve3(a: [[f64; 3]; 3], b: [f64; 3], n: f64) -> Option<[f64; 3]> {
    let det = a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1])
        - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
        + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0]);
    // Axes within a few degrees of parallel make the system near singular.
    if det.abs() < 1e-3 * n * n * n {
        return None;
    }
    let mut x = [0.0; 3];
    for (k, xk) in x.iter_mut().enumerate() {
        let mut m = a;
        for i in 0..3 {
            m[i][k] = b[i];
        }
        *xk = (m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]))
            / det;
    }
    Some(x)
}

/// Rotation of unit quaternion (x, y, z, w), the order of nerfstudio's and instant-ngp's
/// path files.
pub fn quat_to_mat(q: [f32; 4]) -> [[f32; 3]; 3] {
    let [x, y, z, w] = q;
    ngp::geometry::quat_to_rotation([w, x, y, z])
}

/// Unit quaternion (x, y, z, w) of a rotation matrix (Shepperd's method).
pub fn mat_to_quat(m: [[f32; 3]; 3]) -> [f32; 4] {
    let tr = m[0][0] + m[1][1] + m[2][2];
    let q = if tr > 0.0 {
        let s = (tr + 1.0).sqrt() * 2.0;
        [
            (m[2][1] - m[1][2]) / s,
            (m[0][2] - m[2][0]) / s,
            (m[1][0] - m[0][1]) / s,
            0.25 * s,
        ]
    } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
        let s = (1.0 + m[0][0] - m[1][1] - m[2][2]).sqrt() * 2.0;
        [
            0.25 * s,
            (m[0][1] + m[1][0]) / s,
            (m[0][2] + m[2][0]) / s,
            (m[2][1] - m[1][2]) / s,
        ]
    } else if m[1][1] > m[2][2] {
        let s = (1.0 + m[1][1] - m[0][0] - m[2][2]).sqrt() * 2.0;
        [
            (m[0][1] + m[1][0]) / s,
            0.25 * s,
            (m[1][2] + m[2][1]) / s,
            (m[0][2] - m[2][0]) / s,
        ]
    } else {
        let s = (1.0 + m[2][2] - m[0][0] - m[1][1]).sqrt() * 2.0;
        [
            (m[0][2] + m[2][0]) / s,
            (m[1][2] + m[2][1]) / s,
            0.25 * s,
            (m[1][0] - m[0][1]) / s,
        ]
    };
    let n = q.iter().map(|x| x * x).sum::<f32>().sqrt();
    q.map(|x| x / n)
}

#[cfg(test)]
mod tests;
