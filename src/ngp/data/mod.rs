//! Datasets: NeRF-synthetic (`transforms_{train,val,test}.json`) and instant-ngp
//! (`transforms.json`, every 8th frame held out), cameras converted to ngp space as the
//! reference does, images kept compact (see [`image`]).

pub mod color;
pub mod image;
pub mod transforms;

use std::path::{Path, PathBuf};

use rayon::prelude::*;

pub use color::{linear_to_srgb, srgb_to_linear};
pub use image::{Image, image_size, load_png_rgb, save_png_gray, save_png_rgb};

use crate::error::{Error, Result};
use crate::ngp::camera::Camera;
use transforms::{FrameSpec, Transforms, nerf_to_ngp, parse_transforms};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Split {
    Train,
    Val,
    Test,
}

impl Split {
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Val => "val",
            Split::Test => "test",
        }
    }
}

#[derive(Clone, Debug)]
pub struct LoadOptions {
    /// Integer downscale factor; 1 = full size.
    pub downscale: u32,
}

impl Default for LoadOptions {
    fn default() -> Self {
        LoadOptions { downscale: 1 }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DatasetFormat {
    /// One JSON per split: `transforms_{train,val,test}.json`.
    NerfSynthetic,
    /// One `transforms.json`; test/val = frames with index % 8 == 0.
    InstantNgp,
}

pub struct Frame {
    pub camera: Camera,
    pub image: Image,
    /// As written in the JSON.
    pub file_path: String,
}

pub struct Dataset {
    pub root: PathBuf,
    pub split: Split,
    /// After downscaling; all frames share it.
    pub width: u32,
    pub height: u32,
    pub frames: Vec<Frame>,
    /// Power of two ≤ 128 (default 1).
    pub aabb_scale: u32,
    /// nerf → ngp conversion used (0.33 and 0.5 by default).
    pub scale: f32,
    pub offset: [f32; 3],
    /// Some frame has a pixel that is not fully opaque.
    pub has_alpha: bool,
    pub format: DatasetFormat,
}

/// Camera-level description of a dataset split (no pixels).
#[derive(Clone, Debug)]
pub struct DatasetMeta {
    pub root: PathBuf,
    pub split: Split,
    pub format: DatasetFormat,
    /// The JSON file the frames came from (after split fallback).
    pub json_path: PathBuf,
    pub aabb_scale: u32,
    pub scale: f32,
    pub offset: [f32; 3],
    /// After downscaling.
    pub width: u32,
    pub height: u32,
    /// Number of frames (= cameras) in the split.
    pub n: usize,
    /// `file_path` of each frame, as written in the JSON, in frame order.
    pub file_paths: Vec<String>,
    /// Frames the reference's sharpness filter drops because their image is missing.
    pub dropped: Vec<String>,
}

impl DatasetMeta {
    pub fn aabb(&self) -> ([f32; 3], [f32; 3]) {
        aabb_for_scale(self.aabb_scale)
    }
}

/// The ngp-space AABB `[0.5 − s/2, 0.5 + s/2]³`, `s = min(aabb_scale, 128)`.
pub fn aabb_for_scale(aabb_scale: u32) -> ([f32; 3], [f32; 3]) {
    let s = aabb_scale.clamp(1, 128) as f32;
    ([0.5 - s / 2.0; 3], [0.5 + s / 2.0; 3])
}

/// Which file holds a split, and which of its frames belong to it.
struct Source {
    format: DatasetFormat,
    json_path: PathBuf,
    /// For instant-ngp files: Some(true) keeps index % 8 == 0, Some(false) the rest.
    every_eighth: Option<bool>,
}

fn locate(dir: &Path, split: Split) -> Result<Source> {
    // A path to a single JSON file is read as an instant-ngp transforms file.
    if dir.is_file() {
        return Ok(Source {
            format: DatasetFormat::InstantNgp,
            json_path: dir.to_path_buf(),
            every_eighth: Some(split != Split::Train),
        });
    }
    if !dir.is_dir() {
        return Err(Error::io(
            dir,
            std::io::Error::new(std::io::ErrorKind::NotFound, "dataset folder not found"),
        ));
    }
    let per_split = |s: Split| dir.join(format!("transforms_{}.json", s.name()));
    let any_split = [Split::Train, Split::Val, Split::Test]
        .iter()
        .any(|&s| per_split(s).is_file());
    if any_split {
        let order: &[Split] = match split {
            Split::Train => &[Split::Train],
            Split::Val => &[Split::Val, Split::Test],
            Split::Test => &[Split::Test, Split::Val],
        };
        for &s in order {
            if per_split(s).is_file() {
                return Ok(Source {
                    format: DatasetFormat::NerfSynthetic,
                    json_path: per_split(s),
                    every_eighth: None,
                });
            }
        }
        let tried: Vec<String> = order
            .iter()
            .map(|&s| per_split(s).display().to_string())
            .collect();
        return Err(Error::format(
            dir,
            format!(
                "NeRF-synthetic dataset has no {} split (looked for {})",
                split.name(),
                tried.join(", ")
            ),
        ));
    }
    let single = dir.join("transforms.json");
    if single.is_file() {
        return Ok(Source {
            format: DatasetFormat::InstantNgp,
            json_path: single,
            every_eighth: Some(split != Split::Train),
        });
    }
    Err(Error::format(
        dir,
        "no transforms.json or transforms_{train,val,test}.json in this folder",
    ))
}

/// Parses the split's JSON and keeps the split's frames.
fn split_frames(dir: &Path, split: Split, opts: &LoadOptions) -> Result<(Source, Transforms)> {
    if opts.downscale == 0 {
        return Err(Error::Config("downscale must be at least 1".into()));
    }
    let src = locate(dir, split)?;
    let mut t = parse_transforms(&src.json_path)?;
    if let Some(held_out) = src.every_eighth {
        let mut i = 0;
        t.frames.retain(|_| {
            let keep = (i % 8 == 0) == held_out;
            i += 1;
            keep
        });
    }
    if t.frames.is_empty() {
        return Err(Error::format(
            &src.json_path,
            format!("frames: the {} split has no frames", split.name()),
        ));
    }
    Ok((src, t))
}

fn missing_image(t: &Transforms, f: &FrameSpec) -> Error {
    Error::format(
        &t.json_path,
        format!(
            "frames[{}].file_path: image file {} not found",
            f.json_index,
            f.image_path.display()
        ),
    )
}

fn make_camera(t: &Transforms, f: &FrameSpec, full: (u32, u32), n: u32) -> Result<Camera> {
    let k = f.intrinsics(&t.json_path, full)?;
    let inv = 1.0 / n as f32;
    let (w, h) = (full.0 / n, full.1 / n);
    if w == 0 || h == 0 {
        return Err(Error::Config(format!(
            "downscale {n} leaves nothing of the {}x{} images of {}",
            full.0,
            full.1,
            t.json_path.display()
        )));
    }
    Ok(Camera {
        c2w: nerf_to_ngp(&f.nerf_pose, t.scale, t.offset),
        fx: k.fx * inv,
        fy: k.fy * inv,
        cx: k.cx * inv,
        cy: k.cy * inv,
        width: w,
        height: h,
        distortion: k.distortion,
    })
}

fn check_same_size(t: &Transforms, sizes: &[(u32, u32)]) -> Result<()> {
    let first = sizes[0];
    for (f, &s) in t.frames.iter().zip(sizes) {
        if s != first {
            return Err(Error::format(
                &f.image_path,
                format!(
                    "image is {}x{} but {} is {}x{}: all images must share one size",
                    s.0,
                    s.1,
                    t.frames[0].image_path.display(),
                    first.0,
                    first.1
                ),
            ));
        }
    }
    Ok(())
}

fn meta(dir: &Path, split: Split, src: &Source, t: &Transforms, w: u32, h: u32) -> DatasetMeta {
    DatasetMeta {
        root: dir.to_path_buf(),
        split,
        format: src.format,
        json_path: src.json_path.clone(),
        aabb_scale: t.aabb_scale,
        scale: t.scale,
        offset: t.offset,
        width: w,
        height: h,
        n: t.frames.len(),
        file_paths: t.frames.iter().map(|f| f.file_path.clone()).collect(),
        dropped: t.dropped.clone(),
    }
}

impl Dataset {
    /// Loads one split. `dir` holds `transforms_{train,val,test}.json` (NeRF-synthetic) or
    /// `transforms.json` (instant-ngp), or is the path of a single instant-ngp JSON file.
    /// NeRF-synthetic: a missing Val falls back to Test and a missing Test to Val.
    /// instant-ngp: Test/Val = frames with index % 8 == 0 (after the reference's natural sort
    /// and missing-image filter), Train = the rest. Images are decoded in parallel.
    pub fn load(dir: &Path, split: Split, opts: &LoadOptions) -> Result<Dataset> {
        let (src, t) = split_frames(dir, split, opts)?;
        let n = opts.downscale;
        let decoded: Vec<Result<((u32, u32), Image)>> = t
            .frames
            .par_iter()
            .map(|f| {
                if !f.image_path.is_file() {
                    return Err(missing_image(&t, f));
                }
                let img = image::decode_image_file(&f.image_path)?;
                let full = (img.width, img.height);
                let img = if n == 1 {
                    img
                } else {
                    img.downscale(n)
                        .map_err(|e| Error::format(&f.image_path, format!("downscale {n}: {e}")))?
                };
                Ok((full, img))
            })
            .collect();
        let mut sizes = Vec::with_capacity(decoded.len());
        let mut images = Vec::with_capacity(decoded.len());
        for d in decoded {
            let (s, img) = d?;
            sizes.push(s);
            images.push(img);
        }
        check_same_size(&t, &sizes)?;
        let mut frames = Vec::with_capacity(images.len());
        for (f, image) in t.frames.iter().zip(images) {
            frames.push(Frame {
                camera: make_camera(&t, f, sizes[0], n)?,
                image,
                file_path: f.file_path.clone(),
            });
        }
        let has_alpha = frames.iter().any(|f| f.image.has_alpha());
        Ok(Dataset {
            root: dir.to_path_buf(),
            split,
            width: frames[0].image.width,
            height: frames[0].image.height,
            frames,
            aabb_scale: t.aabb_scale,
            scale: t.scale,
            offset: t.offset,
            has_alpha,
            format: src.format,
        })
    }

    /// Cameras only, no pixels decoded. Image sizes come from each image's header when the
    /// file exists, else from the JSON's `w`/`h` (so views can be rendered without images).
    pub fn load_cameras(
        dir: &Path,
        split: Split,
        opts: &LoadOptions,
    ) -> Result<(Vec<Camera>, DatasetMeta)> {
        let (src, t) = split_frames(dir, split, opts)?;
        let sizes: Vec<Result<(u32, u32)>> = t
            .frames
            .par_iter()
            .map(|f| {
                if f.image_path.is_file() {
                    image_size(&f.image_path)
                } else {
                    f.json_size().ok_or_else(|| missing_image(&t, f))
                }
            })
            .collect();
        let sizes: Vec<(u32, u32)> = sizes.into_iter().collect::<Result<_>>()?;
        check_same_size(&t, &sizes)?;
        let n = opts.downscale;
        let cams: Vec<Camera> = t
            .frames
            .iter()
            .map(|f| make_camera(&t, f, sizes[0], n))
            .collect::<Result<_>>()?;
        let (w, h) = (cams[0].width, cams[0].height);
        Ok((cams, meta(dir, split, &src, &t, w, h)))
    }

    /// The ngp-space AABB: `[0.5 − s/2, 0.5 + s/2]³` with `s = min(aabb_scale, 128)`.
    pub fn aabb(&self) -> ([f32; 3], [f32; 3]) {
        aabb_for_scale(self.aabb_scale)
    }

    /// The camera-level description of this dataset. `Dataset` does not keep the JSON path
    /// or the dropped frames: `json_path` is empty and `dropped` too (`load_cameras` has them).
    pub fn meta(&self) -> DatasetMeta {
        DatasetMeta {
            root: self.root.clone(),
            split: self.split,
            format: self.format,
            json_path: PathBuf::new(),
            aabb_scale: self.aabb_scale,
            scale: self.scale,
            offset: self.offset,
            width: self.width,
            height: self.height,
            n: self.frames.len(),
            file_paths: self.frames.iter().map(|f| f.file_path.clone()).collect(),
            dropped: Vec::new(),
        }
    }

    pub fn cameras(&self) -> Vec<Camera> {
        self.frames.iter().map(|f| f.camera.clone()).collect()
    }
}

#[cfg(test)]
mod tests;
