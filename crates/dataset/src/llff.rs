//! LLFF captures: `poses_bounds.npy` (N×17, float64 or float32) with `images/` or an
//! `images_N/` folder of downsampled copies.
//!
//! Each row is a 3×5 matrix, row-major, `[R | t | hwf]`, then the near and far bounds. The
//! rotation's columns are LLFF's camera axes [down, right, backwards] in the world of the
//! COLMAP run that posed the images, `t` the camera centre, and `hwf` = [H, W, focal] of the
//! ORIGINAL images. Rows are matched to the image files sorted as the LLFF tools sort them
//! (plain byte order of the file names, extensions jpg, JPG, png, PNG); the counts must agree.
//! Intrinsics are scaled to the images actually read (factor = width / W, checked against
//! height / H), principal point at the image centre, no distortion.
//!
//! The poses are handed to the colmap2nerf normalisation as COLMAP camera-to-world matrices
//! (OpenCV axes right, down, forward = LLFF columns [1, 0, −2]): LLFF's world *is* COLMAP's
//! world, so a capture imported from its COLMAP model or from its `poses_bounds.npy` ends up
//! with the same cameras. (Equivalently: OpenGL axes [right, up, back] = [col1, −col0, col2],
//! then the script's world flips, up→z rotation, recentring and scale to mean distance 4.)
//! One departure, for forward-facing captures: the centre the cameras look at is taken from
//! the bounds (the harmonic mean of near and far along each camera's axis, see
//! [`crate::colmap2nerf::normalise`]) instead of the intersection of nearly parallel axes.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use rayon::prelude::*;

use crate::colmap2nerf::{ImportCamera, ImportFrame, ImportedScene, find_image_root, image_dims};
use crate::transforms::not_rigid;
use ngp::data::DatasetFormat;
use ngp::error::{Error, Result};

/// Default `aabb_scale` of an LLFF import (forward-facing captures: the background reaches
/// far behind the focus). Overridden by `LoadOptions::aabb_scale`.
pub const LLFF_AABB_SCALE: u32 = 16;

pub const POSES_BOUNDS: &str = "poses_bounds.npy";

/// Extensions of the image files the LLFF tools list.
const LLFF_EXTENSIONS: [&str; 4] = ["jpg", "JPG", "png", "PNG"];

/// Reads `poses_bounds.npy`: N rows of 17 numbers (float64 or float32, either byte order,
/// C or Fortran order).
pub fn read_poses_bounds(path: &Path) -> Result<Vec<[f64; 17]>> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let bad = |msg: String| Error::format(path, msg);
    check_npy_header_length(&bytes).map_err(bad)?;
    let npy =
        npyz::NpyFile::new(&bytes[..]).map_err(|e| bad(format!("not a valid .npy file: {e}")))?;
    let size = match npy.dtype() {
        npyz::DType::Plain(ts)
            if ts.type_char() == npyz::TypeChar::Float && matches!(ts.size_field(), 4 | 8) =>
        {
            ts.size_field() as usize
        }
        other => {
            return Err(bad(format!(
                "dtype {}: expected float64 or float32",
                other.descr()
            )));
        }
    };
    let shape = npy.shape().to_vec();
    if shape.len() != 2 || shape[1] != 17 {
        return Err(bad(format!(
            "shape {shape:?}: expected (N, 17) (a 3x5 pose [R|t|hwf] and near, far per image)"
        )));
    }
    let n = shape[0] as usize;
    if n == 0 {
        return Err(bad("shape (0, 17): no cameras".into()));
    }
    // The header cannot promise more data than the file holds (no huge allocation).
    if (shape[0]).saturating_mul(17 * size as u64) > bytes.len() as u64 {
        return Err(bad(format!(
            "shape {shape:?} needs more data than the file's {} bytes (truncated file)",
            bytes.len()
        )));
    }
    let fortran = npy.order() == npyz::Order::Fortran;
    let flat: Vec<f64> = if size == 8 {
        npy.into_vec::<f64>()
    } else {
        npy.into_vec::<f32>()
            .map(|v| v.into_iter().map(f64::from).collect())
    }
    .map_err(|e| bad(format!("reading the data: {e}")))?;
    if flat.len() != n * 17 {
        return Err(bad(format!(
            "{} values for shape {shape:?} (truncated file)",
            flat.len()
        )));
    }
    let mut rows = vec![[0.0; 17]; n];
    for (i, row) in rows.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = if fortran {
                flat[j * n + i]
            } else {
                flat[i * 17 + j]
            };
        }
    }
    Ok(rows)
}

/// npyz allocates the header length a file declares before reading it (a 300-byte file
/// of version 2 or 3 can declare 4 GiB): refuse a length the file does not hold first.
fn check_npy_header_length(bytes: &[u8]) -> std::result::Result<(), String> {
    if bytes.len() < 10 || !bytes.starts_with(b"\x93NUMPY") {
        return Ok(()); // npyz says what is wrong
    }
    let (start, len) = match bytes[6] {
        1 => (10, u16::from_le_bytes([bytes[8], bytes[9]]) as u64),
        _ if bytes.len() >= 12 => (
            12,
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as u64,
        ),
        _ => return Ok(()),
    };
    if start + len > bytes.len() as u64 {
        return Err(format!(
            "header length {len} (version {}): more than the file's {} bytes (truncated or forged)",
            bytes[6],
            bytes.len()
        ));
    }
    Ok(())
}

/// The image files of an LLFF image folder, sorted by name (byte order).
pub fn list_images(dir: &Path) -> Result<Vec<String>> {
    let rd = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    let mut names = Vec::new();
    for e in rd {
        let e = e.map_err(|e| Error::io(dir, e))?;
        let Some(name) = e.file_name().to_str().map(str::to_string) else {
            continue;
        };
        let ext_ok = Path::new(&name)
            .extension()
            .and_then(|x| x.to_str())
            .is_some_and(|x| LLFF_EXTENSIONS.contains(&x));
        if ext_ok && e.path().is_file() {
            names.push(name);
        }
    }
    names.sort();
    Ok(names)
}

/// COLMAP camera-to-world (OpenCV axes) of one row, checked to be finite and rigid.
fn row_pose(path: &Path, i: usize, row: &[f64; 17]) -> Result<[[f64; 4]; 3]> {
    if let Some(v) = row.iter().find(|v| !v.is_finite()) {
        return Err(Error::format(
            path,
            format!("row {i}: value {v} is not finite"),
        ));
    }
    let m = |r: usize, c: usize| row[r * 5 + c];
    let mut g = [[0.0; 4]; 3];
    for (r, gr) in g.iter_mut().enumerate() {
        *gr = [m(r, 1), m(r, 0), -m(r, 2), m(r, 3)];
    }
    if let Some(why) = not_rigid(&g) {
        return Err(Error::format(
            path,
            format!("row {i}: rotation [down, right, back] is not rigid ({why})"),
        ));
    }
    Ok(g)
}

/// Imports the LLFF capture in `dir` (which holds `poses_bounds.npy`), with images from
/// `images` (a folder name) or `images/`, or else the `images_N/` with the smallest N.
pub fn import(dir: &Path, images: Option<&str>) -> Result<ImportedScene> {
    let npy = dir.join(POSES_BOUNDS);
    let rows = read_poses_bounds(&npy)?;
    let (root, images_dir) = find_image_root(&[dir.to_path_buf()], images, &npy)?;
    let img_dir = root.join(&images_dir);
    let names = list_images(&img_dir)?;
    if names.len() != rows.len() {
        return Err(Error::format(
            &npy,
            format!(
                "{} poses but {} images (jpg/png) in {}: the counts must be equal",
                rows.len(),
                names.len(),
                img_dir.display()
            ),
        ));
    }
    let paths: Vec<PathBuf> = names.iter().map(|n| img_dir.join(n)).collect();
    let dims: Vec<(u32, u32)> = paths
        .par_iter()
        .zip(&names)
        .map(|(p, n)| image_dims(p, &npy, n))
        .collect::<Vec<_>>()
        .into_iter()
        .collect::<Result<_>>()?;
    let mut cameras: Vec<ImportCamera> = Vec::new();
    let mut cam_index: BTreeMap<[u64; 5], usize> = BTreeMap::new();
    let mut frames = Vec::with_capacity(rows.len());
    for (i, ((row, name), path)) in rows.iter().zip(&names).zip(paths).enumerate() {
        let c2w = row_pose(&npy, i, row)?;
        let (hh, ww, focal) = (row[4], row[9], row[14]);
        if !(hh >= 1.0 && ww >= 1.0 && focal > 0.0) {
            return Err(Error::format(
                &npy,
                format!(
                    "row {i}: hwf = [{hh}, {ww}, {focal}] is not a valid size and focal length"
                ),
            ));
        }
        let (w, h) = dims[i];
        let key = [
            hh.to_bits(),
            ww.to_bits(),
            focal.to_bits(),
            w as u64,
            h as u64,
        ];
        let idx = match cam_index.get(&key) {
            Some(&k) => k,
            None => {
                let (sx, sy) = (w as f64 / ww, h as f64 / hh);
                if (h as f64 - hh * sx).abs() > 1.0 + 1e-9 * h as f64 {
                    return Err(Error::format(
                        &path,
                        format!(
                            "image is {w}x{h} but row {i} of {} gives the original as {ww}x{hh}: \
                             not the same picture at another size",
                            npy.display()
                        ),
                    ));
                }
                cameras.push(ImportCamera {
                    width: w,
                    height: h,
                    fx: focal * sx,
                    fy: focal * sy,
                    cx: w as f64 / 2.0,
                    cy: h as f64 / 2.0,
                    k1: 0.0,
                    k2: 0.0,
                    p1: 0.0,
                    p2: 0.0,
                });
                cam_index.insert(key, cameras.len() - 1);
                cameras.len() - 1
            }
        };
        frames.push(ImportFrame {
            name: name.clone(),
            image_path: path,
            camera: idx,
            c2w,
            depth_bounds: Some([row[15], row[16]]),
        });
    }
    Ok(ImportedScene {
        format: DatasetFormat::Llff,
        source: npy,
        root,
        images_dir,
        cameras,
        frames,
        default_aabb_scale: LLFF_AABB_SCALE,
        points: None,
    })
}
