//! The datasets the engine trains on, in memory: a split's frames (camera and image), the
//! scene's box (`aabb_scale`, scale, offset), cameras already in ngp space, images kept
//! compact (see [`image`]), colour conversion and PNG helpers. Reading a capture from disk
//! (transforms.json, COLMAP, LLFF) is the `stegongp-dataset` crate's job, not the engine's.

pub mod color;
pub mod image;

use std::path::PathBuf;

pub use color::{linear_to_srgb, srgb_to_linear};
pub use image::{Image, image_size, load_png_rgb, png_bytes, save_png_gray, save_png_rgb};

use crate::camera::Camera;
use crate::error::{Error, Result};

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

impl crate::choice::Choice for Split {
    const ALL: &'static [Self] = &[Split::Train, Split::Val, Split::Test];
    fn name(self) -> &'static str {
        Split::name(self)
    }
    fn help(self) -> &'static str {
        match self {
            Split::Train => "the training views",
            Split::Val => "the validation views (NeRF-synthetic; none in a capture)",
            Split::Test => "the held-out views (a capture's every 8th)",
        }
    }
}

impl std::fmt::Display for Split {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Checks an `aabb_scale`: a power of two in 1..=128.
pub fn check_aabb_scale(a: u32) -> Result<u32> {
    if (1..=128).contains(&a) && a.is_power_of_two() {
        Ok(a)
    } else {
        Err(Error::Config(format!(
            "aabb_scale {a} is not a power of two between 1 and 128"
        )))
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DatasetFormat {
    /// One JSON per split: `transforms_{train,val,test}.json`.
    NerfSynthetic,
    /// One `transforms.json`; test/val = frames with index % 8 == 0.
    InstantNgp,
    /// A COLMAP sparse model (binary or text) and its images.
    Colmap,
    /// LLFF `poses_bounds.npy` and its images.
    Llff,
}

impl DatasetFormat {
    pub fn name(self) -> &'static str {
        match self {
            DatasetFormat::NerfSynthetic => "NeRF-synthetic",
            DatasetFormat::InstantNgp => "instant-ngp",
            DatasetFormat::Colmap => "COLMAP",
            DatasetFormat::Llff => "LLFF",
        }
    }
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
    /// Power of two ≤ 128 (default 1): the box the scene trains in.
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
    /// The JSON file the frames came from (after split fallback); for COLMAP and LLFF the
    /// model they were converted from (the sparse folder, or `poses_bounds.npy`).
    pub json_path: PathBuf,
    /// COLMAP / LLFF: the image folder read (`images`, `images_8`, …).
    pub images_dir: Option<String>,
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

impl Dataset {
    /// The ngp-space AABB: `[0.5 − s/2, 0.5 + s/2]³` with `s = min(aabb_scale, 128)`.
    pub fn aabb(&self) -> ([f32; 3], [f32; 3]) {
        aabb_for_scale(self.aabb_scale)
    }

    /// The camera-level description of this dataset. `Dataset` does not keep the JSON path,
    /// the dropped frames or the image folder: `json_path` is empty, `dropped` too and
    /// `images_dir` None (`stegongp-dataset`'s `load_cameras` has them).
    pub fn meta(&self) -> DatasetMeta {
        DatasetMeta {
            root: self.root.clone(),
            split: self.split,
            format: self.format,
            json_path: PathBuf::new(),
            images_dir: None,
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

    /// Puts this scene into the box of `aabb_scale` (another scene's, e.g. a stego model's
    /// cover). Every box is centred on the same point, so a scene whose own box is no larger
    /// already lies inside it: it keeps its poses and takes the larger box (where it trains
    /// as empty everything outside its own). A larger scene would be cut off: an error. So
    /// is a scene larger than `scene_box`, the box its occupancy grid will be
    /// cut to ([`crate::occupancy::OccupancyGrid::confine_to_box`]).
    pub fn fit_into_box(&mut self, aabb_scale: u32, scene_box: Option<u32>) -> Result<()> {
        check_aabb_scale(aabb_scale)?;
        if self.aabb_scale > aabb_scale {
            return Err(Error::Config(format!(
                "{}: its aabb_scale {} is larger than the model's {}: the scene would not fit in the model's box (train the cover with a larger --aabb-scale, e.g. {})",
                self.root.display(),
                self.aabb_scale,
                aabb_scale,
                self.aabb_scale
            )));
        }
        if let Some(b) = scene_box {
            check_aabb_scale(b)?;
            if self.aabb_scale > b {
                return Err(Error::Config(format!(
                    "{}: its aabb_scale {} is larger than the box {b} its key confines it to (make its key with `keygen --aabb-scale {}`)",
                    self.root.display(),
                    self.aabb_scale,
                    self.aabb_scale
                )));
            }
        }
        self.aabb_scale = aabb_scale;
        Ok(())
    }
}
