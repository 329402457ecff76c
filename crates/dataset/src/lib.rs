//! Captures on disk read into the engine's [`ngp::data::Dataset`]: NeRF-synthetic and
//! instant-ngp `transforms*.json` ([`transforms`]), COLMAP models ([`colmap`]) and LLFF
//! `poses_bounds.npy` ([`llff`]), the latter two converted with colmap2nerf's maths
//! ([`colmap2nerf`]). This crate knows files and their formats; it must not know training,
//! rendering, keys or devices (the engine trains on what [`load`] returns and never reads a
//! capture itself).
//!
//! The format of a folder is detected, in this order:
//!
//! 1. NeRF-synthetic: `transforms_{train,val,test}.json`;
//! 2. instant-ngp: `transforms.json` (every 8th frame held out, after the reference's
//!    natural sort) — it wins over a COLMAP or LLFF model in the same folder;
//! 3. LLFF: `poses_bounds.npy` with `images/` or `images_N/` ([`llff`]);
//! 4. COLMAP: a sparse model in `sparse/0/`, `sparse/`, the folder itself or its `0/`
//!    (`cameras` and `images`, `.bin` or `.txt`), images in `images/` or `images_N/` beside it ([`colmap`]).
//!
//! LLFF is tried before COLMAP because LLFF releases ship renamed `images_N/` copies that
//! their COLMAP model's image names do not match. COLMAP and LLFF captures are converted in
//! memory to the transforms instant-ngp's `colmap2nerf.py` would write ([`colmap2nerf`])
//! and then loaded exactly like such a file; their held-out views are every 8th image
//! (image 0 first) in plain byte order of the image names, as the LLFF tools sort. Default
//! `aabb_scale`: [`colmap::COLMAP_AABB_SCALE`] and [`llff::LLFF_AABB_SCALE`] (16;
//! colmap2nerf's is 32); [`LoadOptions::aabb_scale`] overrides it for every format.

pub mod colmap;
pub mod colmap2nerf;
pub mod llff;
pub mod transforms;

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use rayon::prelude::*;

use colmap2nerf::{ImportedScene, to_transforms};
use ngp::camera::{Camera, nerf_to_ngp};
use ngp::data::image::{self, Image, image_size};
use ngp::data::{Dataset, DatasetFormat, DatasetMeta, Frame, Split, check_aabb_scale};
use ngp::error::{Error, Result};
use transforms::{FrameSpec, Transforms, parse_transforms};

#[derive(Clone, Debug)]
pub struct LoadOptions {
    /// Integer downscale factor; 1 = full size.
    pub downscale: u32,
    /// COLMAP / LLFF: the image folder to read (e.g. `images_8`), inside the dataset
    /// folder. Default: `images/` if present, else the `images_N/` with the smallest N.
    /// Intrinsics are scaled to the size of the images found there.
    pub images: Option<String>,
    /// Overrides the dataset's `aabb_scale` (any format): a power of two in 1..=128.
    pub aabb_scale: Option<u32>,
}

impl Default for LoadOptions {
    fn default() -> Self {
        LoadOptions {
            downscale: 1,
            images: None,
            aabb_scale: None,
        }
    }
}

/// Which file holds a split, and which of its frames belong to it.
struct Source {
    format: DatasetFormat,
    /// The JSON file, or the COLMAP / LLFF model.
    json_path: PathBuf,
    /// For instant-ngp files: Some(true) keeps index % 8 == 0, Some(false) the rest;
    /// for COLMAP / LLFF the same, in byte order of the image names.
    every_eighth: Option<bool>,
}

/// A COLMAP or LLFF capture in `dir`, ignoring any `transforms.json`: (format, the model:
/// the sparse folder or `poses_bounds.npy`). LLFF first (see the module documentation).
/// `dir` may also be the `poses_bounds.npy` file itself.
pub fn find_capture(dir: &Path) -> Option<(DatasetFormat, PathBuf)> {
    if dir.is_file() {
        return (dir.file_name().is_some_and(|n| n == llff::POSES_BOUNDS))
            .then(|| (DatasetFormat::Llff, dir.to_path_buf()));
    }
    let npy = dir.join(llff::POSES_BOUNDS);
    if npy.is_file() {
        return Some((DatasetFormat::Llff, npy));
    }
    colmap::find_model_dir(dir).map(|m| (DatasetFormat::Colmap, m))
}

/// Reads the COLMAP or LLFF capture in `dir` ([`find_capture`]), with images from the
/// folder `images` names (default `images/`, else the `images_N/` with the smallest N).
pub fn import_capture(dir: &Path, images: Option<&str>) -> Result<ImportedScene> {
    match find_capture(dir) {
        Some((DatasetFormat::Llff, npy)) => {
            llff::import(npy.parent().unwrap_or(Path::new(".")), images)
        }
        Some((_, model)) => colmap::import(&model, images),
        None => Err(Error::format(
            dir,
            format!("no COLMAP or LLFF capture here (looked for {CAPTURES_LOOKED_FOR})"),
        )),
    }
}

/// What [`find_capture`] looks for, for messages.
const CAPTURES_LOOKED_FOR: &str = "poses_bounds.npy (LLFF), and cameras + images (.bin or .txt) \
     in sparse/0/, sparse/, the folder itself or its 0/ (COLMAP)";

fn locate(dir: &Path, split: Split) -> Result<Source> {
    // A path to a single JSON file is read as an instant-ngp transforms file.
    if dir.is_file() {
        if let Some((format, model)) = find_capture(dir) {
            return Ok(Source {
                format,
                json_path: model,
                every_eighth: Some(split != Split::Train),
            });
        }
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
    if let Some((format, model)) = find_capture(dir) {
        return Ok(Source {
            format,
            json_path: model,
            every_eighth: Some(split != Split::Train),
        });
    }
    Err(Error::format(
        dir,
        format!(
            "no dataset recognised in this folder: looked for transforms_{{train,val,test}}.json \
             (NeRF-synthetic), transforms.json (instant-ngp), {CAPTURES_LOOKED_FOR}"
        ),
    ))
}

/// The split's frames, with the image folder of a COLMAP / LLFF import.
struct Loaded {
    src: Source,
    t: Transforms,
    images_dir: Option<String>,
}

/// A COLMAP / LLFF capture imported and converted once, for every split taken from it
/// ([`load_splits`]): all its frames, the held-out ones' names and the image folder.
struct Imported {
    model: PathBuf,
    t: Transforms,
    held: HashSet<String>,
    images_dir: String,
}

/// Imports and converts the COLMAP / LLFF capture of `src`.
fn import_converted(src: &Source, opts: &LoadOptions) -> Result<Imported> {
    let scene = match src.format {
        DatasetFormat::Llff => llff::import(
            src.json_path.parent().unwrap_or(Path::new(".")),
            opts.images.as_deref(),
        )?,
        _ => colmap::import(&src.json_path, opts.images.as_deref())?,
    };
    let aabb = opts.aabb_scale.unwrap_or(scene.default_aabb_scale);
    let conv = to_transforms(&scene, aabb, &scene.root);
    let t = conv.transforms(&src.json_path, &scene.root)?;
    // Hold out every 8th image in byte order of the names (frames are in that order in the
    // conversion; the transforms are sorted naturally).
    let held = conv
        .frames
        .iter()
        .step_by(8)
        .map(|f| f.file_path.clone())
        .collect();
    Ok(Imported {
        model: src.json_path.clone(),
        t,
        held,
        images_dir: scene.images_dir,
    })
}

/// Parses the split's JSON (or imports and converts a COLMAP / LLFF capture, or takes the
/// one `imported` holds from an earlier split) and keeps the split's frames.
fn split_frames(
    dir: &Path,
    split: Split,
    opts: &LoadOptions,
    imported: &mut Option<Imported>,
) -> Result<Loaded> {
    if opts.downscale == 0 {
        return Err(Error::Config("downscale must be at least 1".into()));
    }
    if let Some(a) = opts.aabb_scale {
        check_aabb_scale(a)?;
    }
    let src = locate(dir, split)?;
    let (mut t, images_dir) = match src.format {
        DatasetFormat::Colmap | DatasetFormat::Llff => {
            let i = match imported {
                Some(i) if i.model == src.json_path => i,
                slot => slot.insert(import_converted(&src, opts)?),
            };
            let mut t = i.t.clone();
            let want_held = split != Split::Train;
            t.frames
                .retain(|f| i.held.contains(&f.file_path) == want_held);
            (t, Some(i.images_dir.clone()))
        }
        _ => {
            let mut t = parse_transforms(&src.json_path)?;
            if let Some(a) = opts.aabb_scale {
                t.aabb_scale = a;
            }
            (t, None)
        }
    };
    if let (Some(held_out), DatasetFormat::InstantNgp) = (src.every_eighth, src.format) {
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
    Ok(Loaded { src, t, images_dir })
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

fn meta(dir: &Path, split: Split, l: &Loaded, w: u32, h: u32) -> DatasetMeta {
    let (src, t) = (&l.src, &l.t);
    DatasetMeta {
        root: dir.to_path_buf(),
        split,
        format: src.format,
        json_path: src.json_path.clone(),
        images_dir: l.images_dir.clone(),
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

/// Loads one split. `dir` holds `transforms_{train,val,test}.json` (NeRF-synthetic),
/// `transforms.json` (instant-ngp), an LLFF or COLMAP capture (see the module
/// documentation), or is the path of a single instant-ngp JSON file.
/// NeRF-synthetic: a missing Val falls back to Test and a missing Test to Val.
/// instant-ngp: Test/Val = frames with index % 8 == 0 (after the reference's natural sort
/// and missing-image filter), Train = the rest. Images are decoded in parallel.
pub fn load(dir: &Path, split: Split, opts: &LoadOptions) -> Result<Dataset> {
    load_from(dir, split, opts, &mut None)
}

/// One capture, its splits loaded from a single import: a COLMAP or LLFF capture is read
/// and converted once for every split taken from it (each split decodes its own images),
/// where [`load`] imports it again for each.
pub struct Capture {
    dir: PathBuf,
    opts: LoadOptions,
    imported: Option<Imported>,
}

impl Capture {
    /// The capture at `dir`, read as `opts` say; nothing is read before [`Self::load`].
    pub fn new(dir: &Path, opts: &LoadOptions) -> Self {
        Capture {
            dir: dir.to_path_buf(),
            opts: opts.clone(),
            imported: None,
        }
    }

    /// [`load`] of one split.
    pub fn load(&mut self, split: Split) -> Result<Dataset> {
        load_from(&self.dir, split, &self.opts, &mut self.imported)
    }
}

fn load_from(
    dir: &Path,
    split: Split,
    opts: &LoadOptions,
    imported: &mut Option<Imported>,
) -> Result<Dataset> {
    let Loaded { src, t, .. } = split_frames(dir, split, opts, imported)?;
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
    let l = split_frames(dir, split, opts, &mut None)?;
    let t = &l.t;
    let sizes: Vec<Result<(u32, u32)>> = t
        .frames
        .par_iter()
        .map(|f| {
            if f.image_path.is_file() {
                image_size(&f.image_path)
            } else {
                f.json_size().ok_or_else(|| missing_image(t, f))
            }
        })
        .collect();
    let sizes: Vec<(u32, u32)> = sizes.into_iter().collect::<Result<_>>()?;
    check_same_size(t, &sizes)?;
    let n = opts.downscale;
    let cams: Vec<Camera> = t
        .frames
        .iter()
        .map(|f| make_camera(t, f, sizes[0], n))
        .collect::<Result<_>>()?;
    let (w, h) = (cams[0].width, cams[0].height);
    Ok((cams, meta(dir, split, &l, w, h)))
}

#[cfg(test)]
mod tests;
