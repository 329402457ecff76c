//! What each target hands the program: the case's files are written to a folder and the
//! same functions the commands call read them. An `Err` is the right answer to a bad input;
//! the runner looks for panics, oversized allocations and slow cases.

use crate::seeds::{self, Case};
use dataset::LoadOptions;
use ngp::data::Split;
use std::path::Path;

pub struct Target {
    pub name: &'static str,
    /// Cases in CI, where the default's would take too long (large cases).
    pub ci_cases: Option<u64>,
    /// What a user or a page hands the program here.
    pub about: &'static str,
    pub seeds: fn() -> Vec<Case>,
    pub run: fn(&Path) -> Result<(), String>,
}

fn first_existing(dir: &Path, names: &[&str]) -> Option<std::path::PathBuf> {
    names.iter().map(|n| dir.join(n)).find(|p| p.is_file())
}

fn snapshot(dir: &Path) -> Result<(), String> {
    let path = first_existing(dir, &["model.msgpack", "model.ingp"]).ok_or("no model file")?;
    let inspected = ngp::snapshot::inspect(&path).map_err(|e| e.to_string());
    let analysed = stego::steganalysis::analyse_file(&path).map_err(|e| e.to_string());
    let model = ngp::model::Model::load(&path).map_err(|e| e.to_string())?;
    // What every command does next with a model: its marcher and grid queries.
    let _ = model.marcher();
    let _ = model.grid.occupied_fraction();
    inspected?;
    analysed.map(|_| ())
}

fn key(dir: &Path) -> Result<(), String> {
    let key = stego::keyfile::load_key_with_warnings(&dir.join("key.json"))
        .map_err(|e| e.to_string())?
        .key;
    // Opening a scene derives the key's index functions for a model's grid.
    let layout = ngp::encoding::layout::GridLayout::new(seeds::tiny_config(1).grid, 1)
        .map_err(|e| e.to_string())?;
    let _ = key.level_indices(&layout);
    Ok(())
}

fn image(dir: &Path) -> Result<(), String> {
    let path = first_existing(dir, &["a.png", "a.jpg"]).ok_or("no image file")?;
    let size = ngp::data::image::image_size(&path).map_err(|e| e.to_string());
    let img = ngp::data::image::decode_image_file(&path).map_err(|e| e.to_string())?;
    let _ = img.downscale(2);
    size.map(|_| ())
}

/// Loads both splits, as `train` and `eval` do, and converts a capture as `convert` does.
fn dataset(dir: &Path) -> Result<(), String> {
    let opts = LoadOptions::default();
    let train = dataset::load(dir, Split::Train, &opts).map_err(|e| e.to_string());
    let test = dataset::load(dir, Split::Test, &opts).map_err(|e| e.to_string());
    if dataset::find_capture(dir).is_some() {
        let scene = dataset::import_capture(dir, None).map_err(|e| e.to_string())?;
        let _ = dataset::colmap2nerf::to_transforms(&scene, 16, dir).to_json();
    }
    let mut train = train?;
    test?;
    let box_scale = train.aabb_scale;
    train
        .fit_into_box(box_scale, None)
        .map_err(|e| e.to_string())
}

fn pairs(dir: &Path) -> Result<(), String> {
    experiments::pairs::read_pairs_file(&dir.join("pairs.json"))
        .map(|_| ())
        .map_err(|e| e.to_string())
}

fn camera_path(dir: &Path) -> Result<(), String> {
    let path =
        first_existing(dir, &["camera_path.json", "base_cam.json"]).ok_or("no camera path")?;
    let frame = viewer::path::NerfFrame::default();
    let frames = path.ends_with("base_cam.json").then_some(12);
    let p = viewer::path::read_path(&path, frames, &frame).map_err(|e| e.to_string())?;
    // What `video` does with it: a camera per frame at the path's size.
    let (w, h) = p.size.unwrap_or((64, 48));
    for c in p.cameras.iter().take(64) {
        let _ = c.camera(w.min(4096), h.min(4096));
    }
    Ok(())
}

pub const TARGETS: &[Target] = &[
    Target {
        ci_cases: None,
        name: "snapshot",
        about: "instant-ngp snapshots, .msgpack and gzip .ingp (inspect, detect, every loader)",
        seeds: seeds::snapshots,
        run: snapshot,
    },
    Target {
        ci_cases: None,
        name: "key",
        about: "key files, versions 1 and 2, primes and prf",
        seeds: seeds::keys,
        run: key,
    },
    Target {
        ci_cases: None,
        name: "image",
        about: "PNG and JPEG images",
        seeds: seeds::images,
        run: image,
    },
    Target {
        ci_cases: None,
        name: "transforms",
        about: "transforms*.json datasets, instant-ngp's and NeRF-synthetic's dialects",
        seeds: seeds::transforms,
        run: dataset,
    },
    Target {
        ci_cases: None,
        name: "colmap",
        about: "COLMAP models, binary and text, with their images",
        seeds: seeds::colmap,
        run: dataset,
    },
    Target {
        ci_cases: None,
        name: "llff",
        about: "LLFF captures: poses_bounds.npy with its images",
        seeds: seeds::llff,
        run: dataset,
    },
    Target {
        ci_cases: None,
        name: "pairs",
        about: "experiment pairs files",
        seeds: seeds::pairs,
        run: pairs,
    },
    Target {
        ci_cases: None,
        name: "camera-path",
        about: "camera paths, nerfstudio's camera_path.json and instant-ngp's base_cam.json",
        seeds: seeds::camera_paths,
        run: camera_path,
    },
    Target {
        ci_cases: None,
        name: "viewer",
        about: "HTTP requests to a live viewer on loopback (info, frame, key, record, forget)",
        seeds: crate::viewer::seeds,
        run: crate::viewer::run,
    },
    Target {
        ci_cases: Some(100),
        name: "train-state",
        about: "training states (train --resume): every field of the trainer's state",
        seeds: crate::state::seeds,
        run: crate::state::run,
    },
];

pub fn by_name(name: &str) -> Option<&'static Target> {
    TARGETS.iter().find(|t| t.name == name)
}
