//! Parsing of NeRF `transforms*.json` files, with the reference loader's rules
//! (`src/nerf_loader.cu`): natural sort by `file_path`, `n_frames` cull, the sharpness filter
//! that drops frames whose image is missing, global intrinsics with per-frame overrides,
//! scene `scale`/`offset`/`aabb`/`aabb_scale`, and the nerf → ngp pose conversion.

use std::cmp::Ordering;
use std::path::{Path, PathBuf};

use serde_json::{Map, Value};

use ngp::camera::Distortion;
use ngp::error::{Error, Result};

/// The reference's default scene scale and offset (`nerf_loader.h`).
pub const NERF_SCALE: f32 = 0.33;
pub const NERF_OFFSET: [f32; 3] = [0.5, 0.5, 0.5];

/// Largest rotation deviation from orthonormality accepted in a pose (max |RᵀR − I|).
/// COLMAP-derived poses are orthonormal to ~1e-6; 1e-2 leaves room for rounding in
/// hand-written files while still rejecting scaled or sheared matrices.
pub const ORTHONORMAL_TOL: f64 = 1e-2;

/// Image extensions tried, in the reference's order, for a `file_path` without extension.
const IMAGE_EXTENSIONS: [&str; 10] = [
    "png", "jpg", "jpeg", "bmp", "gif", "tga", "pic", "pnm", "psd", "exr",
];

/// One focal-length source for an axis, in the reference's order of precedence.
#[derive(Clone, Copy, Debug)]
pub(crate) enum FocalVal {
    FovDeg(f64),
    Pixels(f64),
    AngleRad(f64),
}

impl FocalVal {
    fn pixels(self, res: u32) -> f64 {
        match self {
            FocalVal::Pixels(f) => f,
            FocalVal::FovDeg(d) => 0.5 * res as f64 / (0.5 * d.to_radians()).tan(),
            FocalVal::AngleRad(a) => 0.5 * res as f64 / (0.5 * a).tan(),
        }
    }
}

/// Intrinsics as read from one JSON object (top level or frame); resolution comes later.
#[derive(Clone, Debug, Default)]
pub(crate) struct Intrinsics {
    pub(crate) fl: [Option<FocalVal>; 2],
    /// (cx or cy, the w or h it is relative to, if given).
    pub(crate) pp: [Option<(f64, Option<f64>)>; 2],
    /// k1, k2, p1, p2 where present.
    pub(crate) lens: [Option<f32>; 4],
    pub(crate) wh: [Option<f64>; 2],
}

/// Everything a frame needs to become a camera once its image size is known.
#[derive(Clone, Debug)]
pub struct FrameSpec {
    /// Index in the JSON `frames` array (before sorting), for error messages.
    pub json_index: usize,
    /// `file_path` exactly as written in the JSON.
    pub file_path: String,
    /// Resolved image path (extension added where the reference would add one).
    pub image_path: PathBuf,
    /// Camera-to-world 3×4 in the file's (nerf/OpenGL) convention.
    pub nerf_pose: [[f32; 4]; 3],
    top: Intrinsics,
    own: Intrinsics,
}

#[derive(Clone, Debug)]
pub struct Transforms {
    pub json_path: PathBuf,
    pub scale: f32,
    pub offset: [f32; 3],
    pub aabb_scale: u32,
    /// Frames after sort, cull and sharpness filter.
    pub frames: Vec<FrameSpec>,
    /// `file_path`s the sharpness filter dropped (their images are missing).
    pub dropped: Vec<String>,
}

/// Pixel-space intrinsics of the full-resolution image.
#[derive(Clone, Copy, Debug)]
pub struct PixelIntrinsics {
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub distortion: Option<Distortion>,
}

impl FrameSpec {
    /// Width and height the JSON gives for this frame (per-frame `w`/`h` first), if any.
    pub fn json_size(&self) -> Option<(u32, u32)> {
        let w = self.own.wh[0].or(self.top.wh[0])?;
        let h = self.own.wh[1].or(self.top.wh[1])?;
        if w >= 1.0 && h >= 1.0 && w.fract() == 0.0 && h.fract() == 0.0 {
            Some((w as u32, h as u32))
        } else {
            None
        }
    }

    /// Intrinsics in pixels of an image of `res` (the image actually loaded, not the JSON
    /// `w`/`h`: the reference measures fields of view against the loaded image, and places
    /// the principal point at `cx / w` of it).
    pub fn intrinsics(&self, json_path: &Path, res: (u32, u32)) -> Result<PixelIntrinsics> {
        let resolve = |i: &Intrinsics| -> Option<[f64; 2]> {
            let x = i.fl[0].map(|f| f.pixels(res.0)).filter(|&f| f != 0.0);
            let y = i.fl[1].map(|f| f.pixels(res.1)).filter(|&f| f != 0.0);
            match (x, y) {
                (Some(x), Some(y)) => Some([x, y]),
                (Some(x), None) => Some([x, x]),
                (None, Some(y)) => Some([y, y]),
                (None, None) => None,
            }
        };
        let fl = resolve(&self.own).or_else(|| resolve(&self.top)).ok_or_else(|| {
            Error::format(
                json_path,
                format!(
                    "frames[{}] ({}): no focal length (need fl_x/fl_y, camera_angle_x/y or x_fov/y_fov)",
                    self.json_index, self.file_path
                ),
            )
        })?;
        if !(fl[0].is_finite() && fl[1].is_finite() && fl[0] > 0.0 && fl[1] > 0.0) {
            return Err(Error::format(
                json_path,
                format!(
                    "frames[{}] ({}): focal length {fl:?} is not positive and finite",
                    self.json_index, self.file_path
                ),
            ));
        }
        let mut pp = [0.5f64; 2];
        let dims = [res.0 as f64, res.1 as f64];
        for (a, ppa) in pp.iter_mut().enumerate() {
            let from_top = self.top.pp[a].map(|(c, w)| (c, w.or(self.top.wh[a])));
            let from_own =
                self.own.pp[a].map(|(c, w)| (c, w.or(self.own.wh[a]).or(self.top.wh[a])));
            if let Some((c, w)) = from_own.or(from_top) {
                *ppa = c / w.unwrap_or(dims[a]);
            }
        }
        let mut k = [0.0f32; 4];
        for (i, v) in k.iter_mut().enumerate() {
            *v = self.own.lens[i].or(self.top.lens[i]).unwrap_or(0.0);
        }
        let distortion = (k != [0.0; 4]).then_some(Distortion {
            k1: k[0],
            k2: k[1],
            p1: k[2],
            p2: k[3],
        });
        Ok(PixelIntrinsics {
            fx: fl[0] as f32,
            fy: fl[1] as f32,
            cx: (pp[0] * dims[0]) as f32,
            cy: (pp[1] * dims[1]) as f32,
            distortion,
        })
    }
}

/// Natural string order (digit runs compare by value), as `SI::natural::compare`.
pub fn natural_cmp(a: &str, b: &str) -> Ordering {
    let (a, b) = (a.as_bytes(), b.as_bytes());
    let (mut i, mut j) = (0, 0);
    while i < a.len() && j < b.len() {
        if a[i].is_ascii_digit() && b[j].is_ascii_digit() {
            let si = i;
            while i < a.len() && a[i].is_ascii_digit() {
                i += 1;
            }
            let sj = j;
            while j < b.len() && b[j].is_ascii_digit() {
                j += 1;
            }
            let da = trim_zeros(&a[si..i]);
            let db = trim_zeros(&b[sj..j]);
            let o = da.len().cmp(&db.len()).then_with(|| da.cmp(db));
            if o != Ordering::Equal {
                return o;
            }
        } else {
            if a[i] != b[j] {
                return a[i].cmp(&b[j]);
            }
            i += 1;
            j += 1;
        }
    }
    (a.len() - i).cmp(&(b.len() - j))
}

fn trim_zeros(d: &[u8]) -> &[u8] {
    let k = d.iter().position(|&c| c != b'0').unwrap_or(d.len());
    &d[k..]
}

/// `file_path` resolved against the JSON's folder; without an extension and not existing
/// as given, the first existing `path.<ext>` among the reference's image extensions.
pub fn resolve_image_path(base: &Path, file_path: &str) -> PathBuf {
    let local = PathBuf::from(file_path.replace('\\', "/"));
    let path = if local.is_absolute() {
        local
    } else {
        base.join(local)
    };
    if path.extension().is_none() && !path.exists() {
        for ext in IMAGE_EXTENSIONS {
            let p = path.with_extension(ext);
            if p.exists() {
                return p;
            }
        }
    }
    path
}

struct Ctx<'a> {
    path: &'a Path,
}

impl Ctx<'_> {
    fn err(&self, msg: impl Into<String>) -> Error {
        Error::format(self.path, msg)
    }

    fn num(&self, obj: &Map<String, Value>, key: &str, where_: &str) -> Result<Option<f64>> {
        match obj.get(key) {
            None | Some(Value::Null) => Ok(None),
            Some(v) => match v.as_f64() {
                Some(x) if x.is_finite() => Ok(Some(x)),
                _ => Err(self.err(format!("{where_}{key}: expected a finite number, got {v}"))),
            },
        }
    }

    fn intrinsics(&self, obj: &Map<String, Value>, where_: &str) -> Result<Intrinsics> {
        for key in [
            "ftheta_p0",
            "latlong",
            "equirectangular",
            "orthographic",
            "transform_matrix_start",
            "transform_matrix_end",
        ] {
            if obj.contains_key(key) {
                return Err(self.err(format!("{where_}{key}: this camera model is not supported")));
            }
        }
        if obj.get("is_fisheye").and_then(Value::as_bool) == Some(true) {
            return Err(self.err(format!(
                "{where_}is_fisheye: fisheye lenses are not supported"
            )));
        }
        for key in ["k3", "k4"] {
            if self.num(obj, key, where_)?.unwrap_or(0.0) != 0.0 {
                return Err(self.err(format!(
                    "{where_}{key}: only k1, k2, p1, p2 (OpenCV) distortion is supported"
                )));
            }
        }
        let mut i = Intrinsics::default();
        for (a, axis) in ["x", "y"].iter().enumerate() {
            i.fl[a] = if let Some(v) = self.num(obj, &format!("{axis}_fov"), where_)? {
                Some(FocalVal::FovDeg(v))
            } else if let Some(v) = self.num(obj, &format!("fl_{axis}"), where_)? {
                Some(FocalVal::Pixels(v))
            } else {
                self.num(obj, &format!("camera_angle_{axis}"), where_)?
                    .map(FocalVal::AngleRad)
            };
        }
        i.wh = [self.num(obj, "w", where_)?, self.num(obj, "h", where_)?];
        for (a, key) in ["cx", "cy"].iter().enumerate() {
            if let Some(c) = self.num(obj, key, where_)? {
                i.pp[a] = Some((c, i.wh[a]));
            }
        }
        for (k, key) in ["k1", "k2", "p1", "p2"].iter().enumerate() {
            i.lens[k] = self.num(obj, key, where_)?.map(|v| v as f32);
        }
        Ok(i)
    }

    fn pose(&self, frame: &Map<String, Value>, where_: &str) -> Result<[[f32; 4]; 3]> {
        let field = format!("{where_}transform_matrix");
        let rows = frame
            .get("transform_matrix")
            .ok_or_else(|| self.err(format!("{field}: missing")))?
            .as_array()
            .ok_or_else(|| self.err(format!("{field}: expected a 4x4 array")))?;
        if rows.len() != 3 && rows.len() != 4 {
            return Err(self.err(format!("{field}: expected 4 rows, got {}", rows.len())));
        }
        let mut m = [[0f64; 4]; 3];
        for (r, row) in rows.iter().take(3).enumerate() {
            let row = row
                .as_array()
                .filter(|a| a.len() == 4)
                .ok_or_else(|| self.err(format!("{field}[{r}]: expected 4 numbers")))?;
            for (c, v) in row.iter().enumerate() {
                m[r][c] = v.as_f64().filter(|x| x.is_finite()).ok_or_else(|| {
                    self.err(format!("{field}[{r}][{c}]: not a finite number ({v})"))
                })?;
            }
        }
        self.rigid(&field, &m)
    }

    /// `m`'s rotation checked to be rigid, as `f32`. `field` names the matrix in messages.
    fn rigid(&self, field: &str, m: &[[f64; 4]; 3]) -> Result<[[f32; 4]; 3]> {
        if let Some(why) = not_rigid(m) {
            return Err(self.err(format!("{field}: rotation is not rigid ({why})")));
        }
        Ok(m.map(|row| row.map(|v| v as f32)))
    }
}

/// Why the rotation of a camera-to-world matrix is not rigid (a reflection, or columns
/// further than [`ORTHONORMAL_TOL`] from orthonormal), or `None` where it is.
pub(crate) fn not_rigid(m: &[[f64; 4]; 3]) -> Option<String> {
    let mut worst = 0.0f64;
    for a in 0..3 {
        for b in 0..3 {
            let d: f64 = (0..3).map(|k| m[k][a] * m[k][b]).sum();
            worst = worst.max((d - if a == b { 1.0 } else { 0.0 }).abs());
        }
    }
    let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
    (worst > ORTHONORMAL_TOL || det <= 0.0)
        .then(|| format!("max |RᵀR−I| = {worst:.3e}, det = {det:.4}"))
}

/// Reads and validates one transforms JSON file (image paths relative to its folder).
pub fn parse_transforms(json_path: &Path) -> Result<Transforms> {
    let text = std::fs::read_to_string(json_path).map_err(|e| Error::io(json_path, e))?;
    let root: Value = serde_json::from_str(&text)
        .map_err(|e| Error::format(json_path, format!("malformed JSON: {e}")))?;
    let base = json_path.parent().unwrap_or(Path::new(""));
    parse_transforms_value(&root, json_path, base)
}

/// Validates a transforms JSON already in memory, exactly as [`parse_transforms`] does a
/// file: `json_path` names it in messages (and becomes [`Transforms::json_path`]),
/// `base_dir` is the folder `file_path`s are relative to.
pub fn parse_transforms_value(
    root: &Value,
    json_path: &Path,
    base_dir: &Path,
) -> Result<Transforms> {
    let ctx = Ctx { path: json_path };
    let obj = root
        .as_object()
        .ok_or_else(|| ctx.err("top level is not a JSON object"))?;
    for key in ["from_mitsuba", "normal_mts_args"] {
        if obj.contains_key(key) {
            return Err(ctx.err(format!("{key}: Mitsuba scenes are not supported")));
        }
    }
    let placement = ctx.placement(obj)?;
    let top = ctx.intrinsics(obj, "")?;
    let base = base_dir.to_path_buf();
    let mut raw = ctx.listed_frames(obj)?;
    let dropped = ctx.sharpness_filter(obj, &base, &mut raw)?;
    let mut frames = Vec::with_capacity(raw.len());
    for r in raw {
        let where_ = format!("frames[{}] ({}): ", r.idx, r.file_path);
        let nerf_pose = ctx.pose(r.obj, &where_)?;
        let own = ctx.intrinsics(r.obj, &where_)?;
        frames.push(FrameSpec {
            json_index: r.idx,
            image_path: resolve_image_path(&base, &r.file_path),
            file_path: r.file_path,
            nerf_pose,
            top: top.clone(),
            own,
        });
    }
    Ok(Transforms {
        json_path: json_path.to_path_buf(),
        scale: placement.scale,
        offset: placement.offset,
        aabb_scale: placement.aabb_scale,
        frames,
        dropped,
    })
}

/// Whether a file's `aabb_scale` is a power of two between 1 and 128.
fn aabb_scale_ok(v: f64) -> bool {
    v.fract() == 0.0 && (1.0..=128.0).contains(&v) && (v as u32).is_power_of_two()
}

/// One frame of a transforms structure made in memory (a converted capture), as a file
/// would list it: no `sharpness`, the reference's default pose conventions.
pub(crate) struct MadeFrame {
    pub(crate) file_path: String,
    /// Camera-to-world 3×4 (nerf convention); an entry that is not finite stands where a
    /// file would have `null`.
    pub(crate) pose: [[f64; 4]; 3],
    /// The frame's own intrinsics (none where the scene has one camera).
    pub(crate) own: Intrinsics,
}

/// The [`Transforms`] that [`parse_transforms_value`] makes of a file with these frames
/// (listed in this order), `top` as its top-level intrinsics, this `aabb_scale` and no
/// `scale`, `offset`, `aabb` or `n_frames`: the same checks, in the same order, with the
/// same messages, without the JSON.
pub(crate) fn made_transforms(
    json_path: &Path,
    base_dir: &Path,
    aabb_scale: u32,
    top: &Intrinsics,
    frames: Vec<MadeFrame>,
) -> Result<Transforms> {
    let ctx = Ctx { path: json_path };
    if !aabb_scale_ok(aabb_scale as f64) {
        return Err(ctx.err(format!(
            "aabb_scale: {aabb_scale} is not a power of two between 1 and 128"
        )));
    }
    let mut listed: Vec<(usize, MadeFrame)> = Vec::with_capacity(frames.len());
    for (idx, f) in frames.into_iter().enumerate() {
        if f.file_path.is_empty() {
            return Err(ctx.err(format!("frames[{idx}].file_path: empty")));
        }
        listed.push((idx, f));
    }
    listed.sort_by(|(_, a), (_, b)| {
        natural_cmp(
            &a.file_path.replace('\\', "/"),
            &b.file_path.replace('\\', "/"),
        )
    });
    let mut specs = Vec::with_capacity(listed.len());
    for (idx, f) in listed {
        let field = format!("frames[{idx}] ({}): transform_matrix", f.file_path);
        for (r, row) in f.pose.iter().enumerate() {
            if let Some(c) = row.iter().position(|v| !v.is_finite()) {
                return Err(ctx.err(format!("{field}[{r}][{c}]: not a finite number (null)")));
            }
        }
        specs.push(FrameSpec {
            json_index: idx,
            image_path: resolve_image_path(base_dir, &f.file_path),
            nerf_pose: ctx.rigid(&field, &f.pose)?,
            file_path: f.file_path,
            top: top.clone(),
            own: f.own,
        });
    }
    Ok(Transforms {
        json_path: json_path.to_path_buf(),
        scale: NERF_SCALE,
        offset: NERF_OFFSET,
        aabb_scale,
        frames: specs,
        dropped: Vec::new(),
    })
}

/// Where the scene sits in the unit cube: the file's `scale`, `offset` (or `aabb`, which
/// overrides both) and `aabb_scale`.
struct Placement {
    scale: f32,
    offset: [f32; 3],
    aabb_scale: u32,
}

/// A `frames` entry before its pose and intrinsics are read.
struct RawFrame<'a> {
    /// Its index in the JSON array.
    idx: usize,
    obj: &'a Map<String, Value>,
    file_path: String,
}

impl Ctx<'_> {
    /// The top-level `scale`, `aabb_scale`, `offset` and `aabb`, in the reference's order.
    fn placement(&self, obj: &Map<String, Value>) -> Result<Placement> {
        let mut scale = NERF_SCALE;
        let mut offset = NERF_OFFSET;
        if let Some(s) = self.num(obj, "scale", "")? {
            scale = s as f32;
        }
        let mut aabb_scale = 1u32;
        if let Some(a) = obj.get("aabb_scale") {
            let v = a.as_f64().unwrap_or(f64::NAN);
            if !aabb_scale_ok(v) {
                return Err(self.err(format!(
                    "aabb_scale: {a} is not a power of two between 1 and 128"
                )));
            }
            aabb_scale = v as u32;
        }
        if let Some(o) = obj.get("offset") {
            offset = self.offset(o)?;
        }
        if let Some(a) = obj.get("aabb") {
            // [[min],[max]] mapped isotropically into the unit cube, centred at 0.5.
            let mut b = [[0f32; 3]; 2];
            for (i, bi) in b.iter_mut().enumerate() {
                for (k, v) in bi.iter_mut().enumerate() {
                    *v = a
                        .get(i)
                        .and_then(|r| r.get(k))
                        .and_then(Value::as_f64)
                        .filter(|x| x.is_finite())
                        .ok_or_else(|| self.err(format!("aabb[{i}][{k}]: expected a number")))?
                        as f32;
                }
            }
            let len = (0..3)
                .map(|k| (b[1][k] - b[0][k]).abs())
                .fold(0.000_001f32, f32::max);
            scale = 1.0 / len;
            for k in 0..3 {
                offset[k] = (b[1][k] + b[0][k]) * 0.5 * -scale + 0.5;
            }
        }
        if !(scale.is_finite() && scale > 0.0) {
            return Err(self.err(format!("scale: {scale} is not positive")));
        }
        Ok(Placement {
            scale,
            offset,
            aabb_scale,
        })
    }

    /// `offset`: three numbers, or one for all three axes.
    fn offset(&self, o: &Value) -> Result<[f32; 3]> {
        Ok(match o {
            Value::Array(a) if a.len() == 3 => {
                let mut r = [0f32; 3];
                for (k, v) in a.iter().enumerate() {
                    r[k] = v
                        .as_f64()
                        .filter(|x| x.is_finite())
                        .ok_or_else(|| self.err(format!("offset[{k}]: not a finite number")))?
                        as f32;
                }
                r
            }
            _ => {
                let v = o
                    .as_f64()
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| self.err("offset: expected a number or 3 numbers"))?;
                [v as f32; 3]
            }
        })
    }

    /// The `frames` entries with their `file_path`s, in natural order of the paths, the
    /// first `n_frames` where that is given.
    fn listed_frames<'a>(&self, obj: &'a Map<String, Value>) -> Result<Vec<RawFrame<'a>>> {
        let frames_v = obj
            .get("frames")
            .ok_or_else(|| self.err("frames: missing"))?
            .as_array()
            .ok_or_else(|| self.err("frames: not an array"))?;
        let mut raw = Vec::with_capacity(frames_v.len());
        for (idx, f) in frames_v.iter().enumerate() {
            let fo = f
                .as_object()
                .ok_or_else(|| self.err(format!("frames[{idx}]: not an object")))?;
            let file_path = fo
                .get("file_path")
                .ok_or_else(|| self.err(format!("frames[{idx}].file_path: missing")))?
                .as_str()
                .ok_or_else(|| self.err(format!("frames[{idx}].file_path: not a string")))?
                .to_string();
            if file_path.is_empty() {
                return Err(self.err(format!("frames[{idx}].file_path: empty")));
            }
            raw.push(RawFrame {
                idx,
                obj: fo,
                file_path,
            });
        }
        raw.sort_by(|a, b| {
            natural_cmp(
                &a.file_path.replace('\\', "/"),
                &b.file_path.replace('\\', "/"),
            )
        });
        if let Some(n) = self.num(obj, "n_frames", "")? {
            raw.truncate(n.max(0.0) as usize);
        }
        Ok(raw)
    }

    /// The reference keeps only frames whose image exists (and that are sharp enough) when
    /// the first frame has a "sharpness" entry: that is how fox's 67 frames become 50.
    /// Drops the others from `raw` and returns their `file_path`s.
    fn sharpness_filter(
        &self,
        obj: &Map<String, Value>,
        base: &Path,
        raw: &mut Vec<RawFrame>,
    ) -> Result<Vec<String>> {
        let mut dropped = Vec::new();
        if !raw.first().is_some_and(|r| r.obj.contains_key("sharpness")) {
            return Ok(dropped);
        }
        let threshold = self
            .num(obj, "sharpness_discard_threshold", "")?
            .unwrap_or(0.0);
        let sharp: Vec<f64> = raw
            .iter()
            .map(|r| {
                r.obj
                    .get("sharpness")
                    .and_then(Value::as_f64)
                    .unwrap_or(1.0)
            })
            .collect();
        let n = raw.len();
        let keep: Vec<bool> = (0..n)
            .map(|i| {
                let (s, e) = (i.saturating_sub(3), (i + 3).min(n - 1));
                // The reference divides by an empty range for a single frame (NaN, frame
                // dropped); we use the frame's own sharpness then.
                let mean = if e > s {
                    sharp[s..e].iter().sum::<f64>() / (e - s) as f64
                } else {
                    sharp[i]
                };
                resolve_image_path(base, &raw[i].file_path).exists() && sharp[i] > threshold * mean
            })
            .collect();
        let mut k = 0;
        raw.retain(|r| {
            let kept = keep[k];
            k += 1;
            if !kept {
                dropped.push(r.file_path.clone());
            }
            kept
        });
        Ok(dropped)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn natural_order() {
        let mut v = vec!["r_10", "r_2", "r_1", "r_100", "a", "r_02", "r_9x"];
        v.sort_by(|a, b| natural_cmp(a, b));
        assert_eq!(v, vec!["a", "r_1", "r_2", "r_02", "r_9x", "r_10", "r_100"]);
    }
}
