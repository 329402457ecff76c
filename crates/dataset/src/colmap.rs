//! COLMAP sparse models, binary (`cameras.bin`, `images.bin`, `points3D.bin`, little-endian,
//! COLMAP's documented layout) or text (`cameras.txt`, `images.txt`, `points3D.txt`); binary
//! is preferred when a folder holds both. `points3D` is optional: when present its count,
//! bounding box and tracks are kept; the tracks give each image the depth range of the
//! points it sees, as LLFF's `imgs2poses` takes its bounds (see [`depth_bounds`]).
//!
//! Camera models SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL and OPENCV are read (their
//! distortion is OpenCV's k1, k2, p1, p2, which is what [`ngp::camera::Distortion`]
//! models); any other model is refused with its name. Every read of a binary file is
//! checked, and counts are capped by what the rest of the file can hold, so a damaged file
//! gives an error naming the file and the field, never a panic or a huge allocation.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use rayon::prelude::*;

use crate::colmap2nerf::{
    ImportCamera, ImportFrame, ImportedScene, colmap_c2w, find_image_root, image_dims,
};
use ngp::data::DatasetFormat;
use ngp::error::{Error, Result};

/// Default `aabb_scale` of a COLMAP import (colmap2nerf's is 32; 16 keeps the grid's finest
/// cells twice as fine around the cameras' focus, and the unbounded background still fits
/// for typical object-centred captures). Overridden by `LoadOptions::aabb_scale`.
pub const COLMAP_AABB_SCALE: u32 = 16;

/// Model id → (name, number of parameters, supported).
const MODELS: [(&str, usize, bool); 12] = [
    ("SIMPLE_PINHOLE", 3, true),
    ("PINHOLE", 4, true),
    ("SIMPLE_RADIAL", 4, true),
    ("RADIAL", 5, true),
    ("OPENCV", 8, true),
    ("OPENCV_FISHEYE", 8, false),
    ("FULL_OPENCV", 12, false),
    ("FOV", 5, false),
    ("SIMPLE_RADIAL_FISHEYE", 4, false),
    ("RADIAL_FISHEYE", 5, false),
    ("THIN_PRISM_FISHEYE", 12, false),
    ("RAD_TAN_THIN_PRISM_FISHEYE", 16, false),
];

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ModelFormat {
    Binary,
    Text,
}

impl ModelFormat {
    fn ext(self) -> &'static str {
        match self {
            ModelFormat::Binary => "bin",
            ModelFormat::Text => "txt",
        }
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct ColmapCamera {
    pub id: i32,
    /// COLMAP's model name (one of the supported ones).
    pub model: &'static str,
    pub width: u64,
    pub height: u64,
    pub params: Vec<f64>,
}

impl ColmapCamera {
    /// (fx, fy, cx, cy, [k1, k2, p1, p2]) at the model's resolution.
    pub fn intrinsics(&self) -> (f64, f64, f64, f64, [f64; 4]) {
        let p = &self.params;
        match self.model {
            "SIMPLE_PINHOLE" => (p[0], p[0], p[1], p[2], [0.0; 4]),
            "PINHOLE" => (p[0], p[1], p[2], p[3], [0.0; 4]),
            "SIMPLE_RADIAL" => (p[0], p[0], p[1], p[2], [p[3], 0.0, 0.0, 0.0]),
            "RADIAL" => (p[0], p[0], p[1], p[2], [p[3], p[4], 0.0, 0.0]),
            // OPENCV (the only other model that is ever constructed).
            _ => (p[0], p[1], p[2], p[3], [p[4], p[5], p[6], p[7]]),
        }
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct ColmapImage {
    pub id: i32,
    /// World-to-camera rotation (w, x, y, z), normalised.
    pub qvec: [f64; 4],
    pub tvec: [f64; 3],
    pub camera_id: i32,
    pub name: String,
}

pub use crate::colmap2nerf::PointsSummary;

#[derive(Clone, Debug)]
pub struct ColmapModel {
    pub dir: PathBuf,
    pub format: ModelFormat,
    /// By id.
    pub cameras: BTreeMap<i32, ColmapCamera>,
    /// In file order.
    pub images: Vec<ColmapImage>,
    pub points: Option<PointsSummary>,
    /// Which points each image sees, when `points3D` is present.
    pub tracks: Option<PointTracks>,
}

/// The points of a model and the images that see them (COLMAP world coordinates).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PointTracks {
    /// Each point's position (non-finite points are left out).
    pub xyz: Vec<[f64; 3]>,
    /// (image id, index into `xyz`) for every observation.
    pub seen: Vec<(i32, u32)>,
}

impl PointTracks {
    fn push(&mut self, xyz: [f64; 3], images: impl IntoIterator<Item = i32>) {
        if !xyz.iter().all(|v| v.is_finite()) {
            return;
        }
        let k = self.xyz.len() as u32;
        self.xyz.push(xyz);
        self.seen.extend(images.into_iter().map(|id| (id, k)));
    }
}

/// The percentiles of what a camera sees that LLFF's `imgs2poses` keeps as its near and
/// far bounds.
const NEAR_PERCENTILE: f64 = 0.1;
const FAR_PERCENTILE: f64 = 99.9;

/// numpy's `percentile` (linear interpolation) of sorted values.
fn percentile(sorted: &[f64], q: f64) -> f64 {
    let x = q / 100.0 * (sorted.len() - 1) as f64;
    let (i, f) = (x.floor() as usize, x.fract());
    let j = (i + 1).min(sorted.len() - 1);
    sorted[i] + (sorted[j] - sorted[i]) * f
}

/// Near and far depth of what each image sees, by image id: the 0.1st and 99.9th
/// percentiles of the depths along the camera's axis of the points in its track, as LLFF's
/// `imgs2poses` writes into `poses_bounds.npy`. Points behind the camera are ignored; an
/// image that sees none has no entry.
pub fn depth_bounds(images: &[ColmapImage], tracks: &PointTracks) -> BTreeMap<i32, [f64; 2]> {
    let poses: BTreeMap<i32, [[f64; 4]; 3]> = images
        .iter()
        .map(|im| (im.id, colmap_c2w(im.qvec, im.tvec)))
        .collect();
    let mut depths: BTreeMap<i32, Vec<f64>> = BTreeMap::new();
    for &(id, k) in &tracks.seen {
        let (Some(m), Some(p)) = (poses.get(&id), tracks.xyz.get(k as usize)) else {
            continue;
        };
        // OpenCV axes: the camera looks down its third column.
        let z: f64 = (0..3).map(|i| (p[i] - m[i][3]) * m[i][2]).sum();
        if z > 0.0 && z.is_finite() {
            depths.entry(id).or_default().push(z);
        }
    }
    depths
        .into_iter()
        .map(|(id, mut z)| {
            z.sort_by(f64::total_cmp);
            (
                id,
                [
                    percentile(&z, NEAR_PERCENTILE),
                    percentile(&z, FAR_PERCENTILE),
                ],
            )
        })
        .collect()
}

impl ColmapModel {
    /// The images file, for messages.
    pub fn images_file(&self) -> PathBuf {
        self.dir.join(format!("images.{}", self.format.ext()))
    }
}

/// Which model `dir` directly holds: cameras + images, binary first.
pub fn model_format(dir: &Path) -> Option<ModelFormat> {
    [ModelFormat::Binary, ModelFormat::Text]
        .into_iter()
        .find(|f| {
            let e = f.ext();
            dir.join(format!("cameras.{e}")).is_file() && dir.join(format!("images.{e}")).is_file()
        })
}

/// The model folder of a dataset folder: `sparse/0`, `sparse`, the folder itself, or its
/// `0` (COLMAP's mapper writes model 0 into `0/` of the folder it is given, so a user may
/// well name `sparse` or a copy such as `sparse_txt`).
pub fn find_model_dir(dir: &Path) -> Option<PathBuf> {
    [
        dir.join("sparse").join("0"),
        dir.join("sparse"),
        dir.to_path_buf(),
        dir.join("0"),
    ]
    .into_iter()
    .find(|d| model_format(d).is_some())
}

fn check_model_id(path: &Path, id: i64, what: &str) -> Result<(&'static str, usize)> {
    let (name, n, ok) = usize::try_from(id)
        .ok()
        .and_then(|i| MODELS.get(i).copied())
        .ok_or_else(|| Error::format(path, format!("{what}: unknown camera model id {id}")))?;
    if !ok {
        return Err(unsupported(path, what, name));
    }
    Ok((name, n))
}

fn unsupported(path: &Path, what: &str, name: &str) -> Error {
    Error::format(
        path,
        format!(
            "{what}: camera model {name} is not supported (only SIMPLE_PINHOLE, PINHOLE, \
             SIMPLE_RADIAL, RADIAL and OPENCV: lens distortion k1, k2, p1, p2)"
        ),
    )
}

fn check_camera(path: &Path, what: &str, c: &ColmapCamera) -> Result<()> {
    if c.width == 0 || c.height == 0 || c.width > u32::MAX as u64 || c.height > u32::MAX as u64 {
        return Err(Error::format(
            path,
            format!("{what}: image size {}x{} is not valid", c.width, c.height),
        ));
    }
    if let Some(v) = c.params.iter().find(|v| !v.is_finite()) {
        return Err(Error::format(
            path,
            format!("{what}: parameter {v} is not finite"),
        ));
    }
    let (fx, fy, ..) = c.intrinsics();
    if fx <= 0.0 || fy <= 0.0 {
        return Err(Error::format(
            path,
            format!("{what}: focal length ({fx}, {fy}) is not positive"),
        ));
    }
    Ok(())
}

/// Normalises the quaternion; refuses non-finite values or a zero quaternion.
fn check_pose(path: &Path, what: &str, q: [f64; 4], t: [f64; 3]) -> Result<[f64; 4]> {
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    if !(n.is_finite() && n > 1e-12 && t.iter().all(|v| v.is_finite())) {
        return Err(Error::format(
            path,
            format!("{what}: pose (q = {q:?}, t = {t:?}) is not a finite rotation and translation"),
        ));
    }
    Ok(q.map(|v| v / n))
}

/// Little-endian reader over a whole file; every read checked.
struct Bin<'a> {
    path: &'a Path,
    data: &'a [u8],
    pos: usize,
}

impl<'a> Bin<'a> {
    fn remaining(&self) -> usize {
        self.data.len() - self.pos
    }

    fn truncated(&self, what: &str, need: usize) -> Error {
        Error::format(
            self.path,
            format!(
                "truncated file: {what} needs {need} bytes at offset {}, {} left",
                self.pos,
                self.remaining()
            ),
        )
    }

    fn take(&mut self, n: usize, what: impl Fn() -> String) -> Result<&'a [u8]> {
        if self.remaining() < n {
            return Err(self.truncated(&what(), n));
        }
        let s = &self.data[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    fn arr<const N: usize>(&mut self, what: impl Fn() -> String) -> Result<[u8; N]> {
        let s = self.take(N, what)?;
        let mut a = [0u8; N];
        a.copy_from_slice(s);
        Ok(a)
    }

    fn u64(&mut self, what: impl Fn() -> String) -> Result<u64> {
        Ok(u64::from_le_bytes(self.arr(what)?))
    }

    fn i32(&mut self, what: impl Fn() -> String) -> Result<i32> {
        Ok(i32::from_le_bytes(self.arr(what)?))
    }

    fn f64(&mut self, what: impl Fn() -> String) -> Result<f64> {
        Ok(f64::from_le_bytes(self.arr(what)?))
    }

    fn f64s<const N: usize>(&mut self, what: impl Fn() -> String) -> Result<[f64; N]> {
        let mut a = [0.0; N];
        for v in a.iter_mut() {
            *v = self.f64(&what)?;
        }
        Ok(a)
    }

    /// A count of records of at least `min_bytes` each, capped by what is left.
    fn count(&mut self, min_bytes: usize, what: impl Fn() -> String) -> Result<usize> {
        let n = self.u64(&what)?;
        let fits = (self.remaining() / min_bytes.max(1)) as u64;
        if n > fits {
            return Err(Error::format(
                self.path,
                format!(
                    "{}: count {n} cannot fit in the {} bytes left (truncated or corrupt file)",
                    what(),
                    self.remaining()
                ),
            ));
        }
        Ok(n as usize)
    }

    /// Skips `n` records of `size` bytes.
    fn skip(&mut self, n: usize, size: usize, what: impl Fn() -> String) -> Result<()> {
        let bytes = n
            .checked_mul(size)
            .ok_or_else(|| self.truncated(&what(), usize::MAX))?;
        self.take(bytes, what).map(|_| ())
    }

    fn cstr(&mut self, what: impl Fn() -> String) -> Result<String> {
        let rest = &self.data[self.pos..];
        let end = rest.iter().position(|&b| b == 0).ok_or_else(|| {
            Error::format(
                self.path,
                format!("truncated file: {} has no terminating NUL", what()),
            )
        })?;
        let s = std::str::from_utf8(&rest[..end])
            .map_err(|_| Error::format(self.path, format!("{}: not UTF-8", what())))?
            .to_string();
        self.pos += end + 1;
        Ok(s)
    }

    fn finish(&self) -> Result<()> {
        if self.remaining() != 0 {
            return Err(Error::format(
                self.path,
                format!(
                    "{} unexpected bytes after the last record (corrupt file)",
                    self.remaining()
                ),
            ));
        }
        Ok(())
    }
}

fn read_file(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| Error::io(path, e))
}

pub fn read_cameras_bin(path: &Path) -> Result<Vec<ColmapCamera>> {
    let data = read_file(path)?;
    let mut r = Bin {
        path,
        data: &data,
        pos: 0,
    };
    // id, model, width, height and at least 3 parameters.
    let n = r.count(4 + 4 + 8 + 8 + 24, || "number of cameras".into())?;
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let w = |f: &str| format!("camera {i}: {f}");
        let id = r.i32(|| w("camera_id"))?;
        let model_id = r.i32(|| w("model_id"))?;
        let what = format!("camera {i} (id {id})");
        let (model, np) = check_model_id(path, model_id as i64, &what)?;
        let width = r.u64(|| w("width"))?;
        let height = r.u64(|| w("height"))?;
        let mut params = Vec::with_capacity(np);
        for k in 0..np {
            params.push(r.f64(|| w(&format!("params[{k}] of {model}")))?);
        }
        let c = ColmapCamera {
            id,
            model,
            width,
            height,
            params,
        };
        check_camera(path, &what, &c)?;
        out.push(c);
    }
    r.finish()?;
    Ok(out)
}

pub fn read_images_bin(path: &Path) -> Result<Vec<ColmapImage>> {
    let data = read_file(path)?;
    let mut r = Bin {
        path,
        data: &data,
        pos: 0,
    };
    // id, q, t, camera id, a name of at least its NUL, the point count.
    let n = r.count(4 + 56 + 4 + 1 + 8, || "number of images".into())?;
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let w = |f: &str| format!("image {i}: {f}");
        let id = r.i32(|| w("image_id"))?;
        let q = r.f64s::<4>(|| w("qvec"))?;
        let t = r.f64s::<3>(|| w("tvec"))?;
        let camera_id = r.i32(|| w("camera_id"))?;
        let name = r.cstr(|| w("name"))?;
        let what = format!("image {i} (id {id}, {name})");
        let np = r.count(24, || format!("{what}: number of 2D points"))?;
        r.skip(np, 24, || format!("{what}: 2D points"))?;
        let qvec = check_pose(path, &what, q, t)?;
        if name.is_empty() {
            return Err(Error::format(path, format!("{what}: empty name")));
        }
        out.push(ColmapImage {
            id,
            qvec,
            tvec: t,
            camera_id,
            name,
        });
    }
    r.finish()?;
    Ok(out)
}

/// Extends a bounding box.
fn grow(s: &mut PointsSummary, p: [f64; 3]) {
    for (k, v) in p.into_iter().enumerate() {
        s.min[k] = s.min[k].min(v);
        s.max[k] = s.max[k].max(v);
    }
    s.count += 1;
}

fn empty_points() -> PointsSummary {
    PointsSummary {
        count: 0,
        min: [f64::INFINITY; 3],
        max: [f64::NEG_INFINITY; 3],
    }
}

pub fn read_points_bin(path: &Path) -> Result<(PointsSummary, PointTracks)> {
    let data = read_file(path)?;
    let mut r = Bin {
        path,
        data: &data,
        pos: 0,
    };
    let n = r.count(8 + 24 + 3 + 8 + 8, || "number of points".into())?;
    let mut s = empty_points();
    let mut tracks = PointTracks::default();
    let mut ids = Vec::new();
    for i in 0..n {
        let w = |f: &str| format!("point {i}: {f}");
        let _id = r.u64(|| w("point3D_id"))?;
        let xyz = r.f64s::<3>(|| w("xyz"))?;
        r.take(3, || w("rgb"))?;
        let _err = r.f64(|| w("error"))?;
        let tl = r.count(8, || w("track length"))?;
        ids.clear();
        for _ in 0..tl {
            ids.push(r.i32(|| w("track image_id"))?);
            let _point2d = r.i32(|| w("track point2D_idx"))?;
        }
        if xyz.iter().all(|v| v.is_finite()) {
            grow(&mut s, xyz);
        }
        tracks.push(xyz, ids.iter().copied());
    }
    r.finish()?;
    Ok((s, tracks))
}

fn read_text(path: &Path) -> Result<String> {
    std::fs::read_to_string(path).map_err(|e| match e.kind() {
        std::io::ErrorKind::InvalidData => Error::format(path, "not a UTF-8 text file"),
        _ => Error::io(path, e),
    })
}

/// The first `n` whitespace-separated fields of `l` and the trimmed rest of the line.
fn fields_and_rest(l: &str, n: usize) -> Option<(Vec<&str>, &str)> {
    let mut rest = l.trim_start();
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        let end = rest.find(char::is_whitespace)?;
        out.push(&rest[..end]);
        rest = rest[end..].trim_start();
    }
    Some((out, rest.trim_end()))
}

fn line_err(path: &Path, line: usize, msg: impl std::fmt::Display) -> Error {
    Error::format(path, format!("line {line}: {msg}"))
}

fn parse_num<T: std::str::FromStr>(path: &Path, line: usize, field: &str, s: &str) -> Result<T> {
    s.parse()
        .map_err(|_| line_err(path, line, format!("{field}: {s:?} is not a valid number")))
}

pub fn read_cameras_txt(path: &Path) -> Result<Vec<ColmapCamera>> {
    let text = read_text(path)?;
    let mut out = Vec::new();
    for (i, l) in text.lines().enumerate() {
        let ln = i + 1;
        let l = l.trim();
        if l.is_empty() || l.starts_with('#') {
            continue;
        }
        let el: Vec<&str> = l.split_whitespace().collect();
        if el.len() < 4 {
            return Err(line_err(
                path,
                ln,
                "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]",
            ));
        }
        let id: i32 = parse_num(path, ln, "CAMERA_ID", el[0])?;
        let what = format!("line {ln}: camera {id}");
        let (model, np, ok) = MODELS
            .iter()
            .copied()
            .find(|m| m.0 == el[1])
            .ok_or_else(|| {
                Error::format(path, format!("{what}: unknown camera model {}", el[1]))
            })?;
        if !ok {
            return Err(unsupported(path, &what, model));
        }
        let width: u64 = parse_num(path, ln, "WIDTH", el[2])?;
        let height: u64 = parse_num(path, ln, "HEIGHT", el[3])?;
        if el.len() != 4 + np {
            return Err(line_err(
                path,
                ln,
                format!(
                    "camera {id}: {model} has {np} parameters, the line has {}",
                    el.len() - 4
                ),
            ));
        }
        let params = el[4..]
            .iter()
            .enumerate()
            .map(|(k, s)| parse_num(path, ln, &format!("PARAMS[{k}]"), s))
            .collect::<Result<Vec<f64>>>()?;
        let c = ColmapCamera {
            id,
            model,
            width,
            height,
            params,
        };
        check_camera(path, &what, &c)?;
        out.push(c);
    }
    Ok(out)
}

pub fn read_images_txt(path: &Path) -> Result<Vec<ColmapImage>> {
    let text = read_text(path)?;
    let mut out = Vec::new();
    let mut expect_points = false;
    for (i, l) in text.lines().enumerate() {
        let ln = i + 1;
        if l.starts_with('#') {
            continue;
        }
        if expect_points {
            // IMAGE's second line: POINTS2D[] as (X, Y, POINT3D_ID), possibly empty.
            expect_points = false;
            continue;
        }
        let l = l.trim();
        if l.is_empty() {
            continue;
        }
        let Some((el, name)) = fields_and_rest(l, 9).filter(|(_, n)| !n.is_empty()) else {
            return Err(line_err(
                path,
                ln,
                "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME",
            ));
        };
        let id: i32 = parse_num(path, ln, "IMAGE_ID", el[0])?;
        let names = ["QW", "QX", "QY", "QZ", "TX", "TY", "TZ"];
        let mut v = [0.0f64; 7];
        for k in 0..7 {
            v[k] = parse_num(path, ln, names[k], el[k + 1])?;
        }
        let camera_id: i32 = parse_num(path, ln, "CAMERA_ID", el[8])?;
        let name = name.to_string();
        let what = format!("line {ln}: image {id} ({name})");
        let q = [v[0], v[1], v[2], v[3]];
        let t = [v[4], v[5], v[6]];
        let qvec = check_pose(path, &what, q, t)?;
        out.push(ColmapImage {
            id,
            qvec,
            tvec: t,
            camera_id,
            name,
        });
        expect_points = true;
    }
    Ok(out)
}

pub fn read_points_txt(path: &Path) -> Result<(PointsSummary, PointTracks)> {
    let text = read_text(path)?;
    let mut s = empty_points();
    let mut tracks = PointTracks::default();
    for (i, l) in text.lines().enumerate() {
        let ln = i + 1;
        let l = l.trim();
        if l.is_empty() || l.starts_with('#') {
            continue;
        }
        let el: Vec<&str> = l.split_whitespace().collect();
        if el.len() < 8 || !(el.len() - 8).is_multiple_of(2) {
            return Err(line_err(
                path,
                ln,
                "expected POINT3D_ID X Y Z R G B ERROR TRACK[] (pairs IMAGE_ID POINT2D_IDX)",
            ));
        }
        let mut p = [0.0f64; 3];
        for k in 0..3 {
            p[k] = parse_num(path, ln, ["X", "Y", "Z"][k], el[k + 1])?;
        }
        let images = el[8..]
            .chunks(2)
            .map(|pair| parse_num::<i32>(path, ln, "TRACK IMAGE_ID", pair[0]))
            .collect::<Result<Vec<i32>>>()?;
        if p.iter().all(|v| v.is_finite()) {
            grow(&mut s, p);
        }
        tracks.push(p, images);
    }
    Ok((s, tracks))
}

/// Reads the model that `dir` directly holds (binary preferred).
pub fn read_model(dir: &Path) -> Result<ColmapModel> {
    let format = model_format(dir).ok_or_else(|| {
        Error::format(
            dir,
            "no COLMAP model here (need cameras.bin + images.bin or cameras.txt + images.txt)",
        )
    })?;
    let e = format.ext();
    let cam_path = dir.join(format!("cameras.{e}"));
    let img_path = dir.join(format!("images.{e}"));
    let pts_path = dir.join(format!("points3D.{e}"));
    let (cams, images) = match format {
        ModelFormat::Binary => (read_cameras_bin(&cam_path)?, read_images_bin(&img_path)?),
        ModelFormat::Text => (read_cameras_txt(&cam_path)?, read_images_txt(&img_path)?),
    };
    let (points, tracks) = if pts_path.is_file() {
        let (s, t) = match format {
            ModelFormat::Binary => read_points_bin(&pts_path)?,
            ModelFormat::Text => read_points_txt(&pts_path)?,
        };
        (Some(s), Some(t))
    } else {
        (None, None)
    };
    let mut cameras = BTreeMap::new();
    for c in cams {
        let id = c.id;
        if cameras.insert(id, c).is_some() {
            return Err(Error::format(
                &cam_path,
                format!("camera id {id} appears twice"),
            ));
        }
    }
    if cameras.is_empty() {
        return Err(Error::format(&cam_path, "no cameras in the model"));
    }
    if images.is_empty() {
        return Err(Error::format(&img_path, "no images in the model"));
    }
    let mut names = std::collections::HashSet::new();
    for im in &images {
        if !cameras.contains_key(&im.camera_id) {
            return Err(Error::format(
                &img_path,
                format!(
                    "image {} ({}): camera_id {} is not in {}",
                    im.id,
                    im.name,
                    im.camera_id,
                    cam_path.display()
                ),
            ));
        }
        if !names.insert(im.name.as_str()) {
            return Err(Error::format(
                &img_path,
                format!("image name {} appears twice", im.name),
            ));
        }
    }
    Ok(ColmapModel {
        dir: dir.to_path_buf(),
        format,
        cameras,
        images,
        points,
        tracks,
    })
}

/// Imports the model in `model_dir` with images from `images/` (or the folder `images`
/// names, or the first `images_N/`) in the model folder, its parent or its grandparent —
/// the first that has one (`DATASET/sparse/0` → `DATASET`). Intrinsics are scaled to the
/// size of the images found; frames are sorted by image name.
pub fn import(model_dir: &Path, images: Option<&str>) -> Result<ImportedScene> {
    let model = read_model(model_dir)?;
    let img_file = model.images_file();
    let roots: Vec<PathBuf> = model_dir
        .ancestors()
        .take(3)
        .map(Path::to_path_buf)
        .collect();
    let (root, images_dir) = find_image_root(&roots, images, model_dir)?;
    let mut order: Vec<&ColmapImage> = model.images.iter().collect();
    order.sort_by(|a, b| a.name.cmp(&b.name));
    let paths: Vec<PathBuf> = order
        .iter()
        .map(|im| root.join(&images_dir).join(&im.name))
        .collect();
    let dims: Vec<Result<(u32, u32)>> = order
        .par_iter()
        .zip(&paths)
        .map(|(im, p)| image_dims(p, &img_file, &format!("image {} ({})", im.id, im.name)))
        .collect();
    let mut cameras: Vec<ImportCamera> = Vec::new();
    let mut cam_index: BTreeMap<(i32, u32, u32), usize> = BTreeMap::new();
    let bounds = model
        .tracks
        .as_ref()
        .map(|t| depth_bounds(&model.images, t))
        .unwrap_or_default();
    let mut frames = Vec::with_capacity(order.len());
    for ((im, path), d) in order.iter().zip(paths).zip(dims) {
        let (w, h) = d?;
        let c = &model.cameras[&im.camera_id];
        let idx = match cam_index.get(&(c.id, w, h)) {
            Some(&k) => k,
            None => {
                let (fx, fy, cx, cy, k) = c.intrinsics();
                let s = w as f64 / c.width as f64;
                if (h as f64 - c.height as f64 * s).abs() > 1.0 + 1e-9 * h as f64 {
                    return Err(Error::format(
                        &path,
                        format!(
                            "image is {w}x{h} but camera {} of {} is {}x{}: not the same \
                             picture at another size",
                            c.id,
                            img_file.display(),
                            c.width,
                            c.height
                        ),
                    ));
                }
                let sy = h as f64 / c.height as f64;
                cameras.push(ImportCamera {
                    width: w,
                    height: h,
                    fx: fx * s,
                    fy: fy * sy,
                    cx: cx * s,
                    cy: cy * sy,
                    k1: k[0],
                    k2: k[1],
                    p1: k[2],
                    p2: k[3],
                });
                cam_index.insert((c.id, w, h), cameras.len() - 1);
                cameras.len() - 1
            }
        };
        frames.push(ImportFrame {
            name: im.name.clone(),
            image_path: path,
            camera: idx,
            c2w: colmap_c2w(im.qvec, im.tvec),
            depth_bounds: bounds.get(&im.id).copied(),
        });
    }
    Ok(ImportedScene {
        format: DatasetFormat::Colmap,
        source: model_dir.to_path_buf(),
        root,
        images_dir,
        cameras,
        frames,
        default_aabb_scale: COLMAP_AABB_SCALE,
        points: model.points,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_fields_and_names_with_spaces() {
        let (f, rest) = fields_and_rest("1  0.5 a  b c d e f 7 my image.jpg ", 9).unwrap();
        assert_eq!(f, vec!["1", "0.5", "a", "b", "c", "d", "e", "f", "7"]);
        assert_eq!(rest, "my image.jpg");
        assert!(fields_and_rest("1 2 3", 9).is_none());
    }

    #[test]
    fn text_model_by_hand() {
        let t = tempfile::tempdir().unwrap();
        let cams = t.path().join("cameras.txt");
        std::fs::write(
            &cams,
            "# comment\n\n1 SIMPLE_RADIAL 40 30 50 20 15 0.1\n2 PINHOLE 40 30 60 61 19 14\n",
        )
        .unwrap();
        let c = read_cameras_txt(&cams).unwrap();
        assert_eq!(c.len(), 2);
        assert_eq!(
            c[0].intrinsics(),
            (50.0, 50.0, 20.0, 15.0, [0.1, 0.0, 0.0, 0.0])
        );
        assert_eq!(c[1].intrinsics(), (60.0, 61.0, 19.0, 14.0, [0.0; 4]));
        let imgs = t.path().join("images.txt");
        // Image 1's point line is empty; the quaternion is normalised (2, 0, 0, 0) → identity.
        std::fs::write(
            &imgs,
            "# header\n1 2 0 0 0 1 2 3 1 a.png\n\n2 1 0 0 0 0 0 0 2 b.png\n1 2 -1\n",
        )
        .unwrap();
        let i = read_images_txt(&imgs).unwrap();
        assert_eq!(i.len(), 2);
        assert_eq!(i[0].qvec, [1.0, 0.0, 0.0, 0.0]);
        assert_eq!((i[0].tvec, i[0].name.as_str()), ([1.0, 2.0, 3.0], "a.png"));
        assert_eq!((i[1].camera_id, i[1].name.as_str()), (2, "b.png"));
        std::fs::write(&imgs, "1 0 0 0 0 1 2 3 1 a.png\n").unwrap();
        let e = read_images_txt(&imgs).unwrap_err().to_string();
        assert!(
            e.contains("line 1") && e.contains("not a finite rotation"),
            "{e}"
        );
    }

    #[test]
    fn depth_bounds_are_llffs_percentiles_of_the_points_in_front() {
        // Image 1 at the origin looking down +z (identity), image 2 one unit further back
        // along z; points at depths 1..=1000 in front of image 1, one behind both.
        let im = |id, tz| ColmapImage {
            id,
            qvec: [1.0, 0.0, 0.0, 0.0],
            tvec: [0.0, 0.0, tz],
            camera_id: 1,
            name: format!("{id}.png"),
        };
        let mut t = PointTracks::default();
        for d in 1..=1000 {
            t.push([0.3, -0.2, d as f64], [1, 2]);
        }
        t.push([0.0, 0.0, -5.0], [1, 2]);
        t.push([f64::NAN, 0.0, 1.0], [1]);
        assert_eq!(t.xyz.len(), 1001, "non-finite points are dropped");
        let b = depth_bounds(&[im(1, 0.0), im(2, 1.0), im(3, 0.0)], &t);
        // numpy.percentile(range(1, 1001), [0.1, 99.9]) = 1.999, 999.001.
        assert!((b[&1][0] - 1.999).abs() < 1e-9 && (b[&1][1] - 999.001).abs() < 1e-9);
        assert!((b[&2][0] - 2.999).abs() < 1e-9 && (b[&2][1] - 1000.001).abs() < 1e-9);
        assert!(
            !b.contains_key(&3),
            "an image that sees no point has no bounds"
        );
    }

    #[test]
    fn text_points_carry_their_tracks() {
        let t = tempfile::tempdir().unwrap();
        let p = t.path().join("points3D.txt");
        std::fs::write(&p, "# c\n7 1 2 3 9 9 9 0.5 4 0 5 2\n8 0 0 1 9 9 9 0.5\n").unwrap();
        let (s, tr) = read_points_txt(&p).unwrap();
        assert_eq!(s.count, 2);
        assert_eq!(tr.xyz, vec![[1.0, 2.0, 3.0], [0.0, 0.0, 1.0]]);
        assert_eq!(tr.seen, vec![(4, 0), (5, 0)]);
        std::fs::write(&p, "7 1 2 3 9 9 9 0.5 4\n").unwrap();
        let e = read_points_txt(&p).unwrap_err().to_string();
        assert!(
            e.contains("line 1") && e.contains("IMAGE_ID POINT2D_IDX"),
            "{e}"
        );
    }

    #[test]
    fn binary_camera_by_hand_and_truncation() {
        let t = tempfile::tempdir().unwrap();
        let p = t.path().join("cameras.bin");
        let mut b = Vec::new();
        b.extend(1u64.to_le_bytes());
        b.extend(3i32.to_le_bytes());
        b.extend(1i32.to_le_bytes()); // PINHOLE: fx, fy, cx, cy
        b.extend(64u64.to_le_bytes());
        b.extend(48u64.to_le_bytes());
        for v in [70.0f64, 71.0, 32.0, 24.0] {
            b.extend(v.to_le_bytes());
        }
        std::fs::write(&p, &b).unwrap();
        let c = read_cameras_bin(&p).unwrap();
        assert_eq!(
            (c[0].id, c[0].model, c[0].width, c[0].height),
            (3, "PINHOLE", 64, 48)
        );
        assert_eq!(c[0].intrinsics(), (70.0, 71.0, 32.0, 24.0, [0.0; 4]));
        std::fs::write(&p, &b[..b.len() - 1]).unwrap();
        let e = read_cameras_bin(&p).unwrap_err().to_string();
        assert!(
            e.contains("params[3] of PINHOLE") && e.contains("truncated"),
            "{e}"
        );
        // Shorter than the smallest camera record: refused by the count check.
        std::fs::write(&p, &b[..40]).unwrap();
        let e = read_cameras_bin(&p).unwrap_err().to_string();
        assert!(e.contains("count 1 cannot fit"), "{e}");
        let mut extra = b.clone();
        extra.push(0);
        std::fs::write(&p, &extra).unwrap();
        let e = read_cameras_bin(&p).unwrap_err().to_string();
        assert!(e.contains("1 unexpected bytes"), "{e}");
    }
}
