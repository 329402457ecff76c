//! `stegongp convert DIR --out transforms.json [--aabb-scale N] [--images images_N] [--json]`:
//! a COLMAP or LLFF capture written as the instant-ngp `transforms.json` that instant-ngp's
//! `colmap2nerf.py` would write (no `sharpness` entries), image paths relative to the output
//! file's folder. Like `train --out`, an existing file is replaced; the file appears whole
//! (written beside it, then renamed) and only after the conversion loaded back cleanly.

use anyhow::{Context, Result, bail};
use serde::Serialize;
use std::path::{Path, PathBuf};
use stegongp::dataset::colmap2nerf::{CentreFrom, to_transforms};
use stegongp::dataset::import_capture;
use stegongp::ngp::data::check_aabb_scale;
use stegongp::util::write_atomic;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Capture folder: COLMAP (a sparse model in sparse/0, sparse, the folder itself or
    /// its 0/, .bin or .txt) or LLFF (poses_bounds.npy), with images/ or images_N/.
    pub dir: PathBuf,
    /// transforms.json to write.
    #[arg(long)]
    pub out: PathBuf,
    /// Scene bounds for instant-ngp, a power of two 1..=128 (default 16).
    #[arg(long)]
    pub aabb_scale: Option<u32>,
    /// Image folder inside the capture (e.g. images_8); default images/, else the
    /// images_N/ with the smallest N. Intrinsics are scaled to its images.
    #[arg(long)]
    pub images: Option<String>,
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct Summary {
    format: &'static str,
    source: PathBuf,
    out: PathBuf,
    frames: usize,
    cameras: usize,
    images_dir: String,
    aabb_scale: u32,
    /// Mean camera up axis (after colmap2nerf's world flips), rotated onto +z.
    up: [f64; 3],
    /// The cameras' focus, moved to the origin.
    centre: [f64; 3],
    /// 4 / mean camera distance.
    scale: f64,
    /// `axes` (colmap2nerf's closest point of the optical axes) or `focus` (the depth of
    /// what each camera sees: LLFF's bounds, or a forward-facing COLMAP model's points).
    centre_from: CentreFrom,
    /// How nearly the cameras look the same way (1: all alike, near 0: all round).
    view_alignment: f64,
    /// COLMAP points3D count, when the model has one.
    points: Option<u64>,
}

fn check_out(out: &Path) -> Result<()> {
    if out.is_dir() {
        bail!("{}: is a directory; give the file to write", out.display());
    }
    super::common::check_parent_dir(out)?;
    Ok(())
}

pub fn run(a: Args) -> Result<()> {
    check_out(&a.out)?;
    if let Some(s) = a.aabb_scale {
        check_aabb_scale(s).context("--aabb-scale")?;
    }
    let scene = import_capture(&a.dir, a.images.as_deref())?;
    let aabb = a.aabb_scale.unwrap_or(scene.default_aabb_scale);
    let base = match a.out.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let conv = to_transforms(&scene, aabb, &base);
    // What instant-ngp will read must load here first: nothing is written otherwise.
    conv.transforms(&a.out, &base)?;
    let text = serde_json::to_string_pretty(&conv.to_json())?;
    write_atomic(&a.out, text.as_bytes())?;
    let s = Summary {
        format: scene.format.name(),
        source: scene.source.clone(),
        out: a.out.clone(),
        frames: scene.frames.len(),
        cameras: scene.cameras.len(),
        images_dir: scene.images_dir.clone(),
        aabb_scale: aabb,
        up: conv.norm.up,
        centre: conv.norm.centre,
        scale: conv.norm.scale,
        centre_from: conv.norm.centre_from,
        view_alignment: conv.norm.view_alignment,
        points: scene.points.as_ref().map(|p| p.count),
    };
    if a.json {
        println!("{}", serde_json::to_string_pretty(&s)?);
    } else {
        let v = |p: [f64; 3]| format!("({:.4}, {:.4}, {:.4})", p[0], p[1], p[2]);
        println!(
            "{} {}: {} frames, {} camera{}, images from {}/, aabb_scale {}, centre {} (from the {}) scaled by {:.5}{}; wrote {}",
            s.format,
            s.source.display(),
            s.frames,
            s.cameras,
            if s.cameras == 1 { "" } else { "s" },
            s.images_dir,
            s.aabb_scale,
            v(s.centre),
            match s.centre_from {
                CentreFrom::Axes => "cameras' axes",
                CentreFrom::Focus => "depth the cameras see",
            },
            s.scale,
            s.points
                .map(|n| format!(", {n} points"))
                .unwrap_or_default(),
            s.out.display()
        );
    }
    Ok(())
}
