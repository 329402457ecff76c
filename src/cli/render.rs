use super::common::{Background, SplitArg, ensure_dir, progress};
use anyhow::{Result, bail};
use std::path::PathBuf;
use stegongp::ngp::data::{Dataset, LoadOptions, save_png_gray, save_png_rgb};
use stegongp::ngp::eval::spread_views;
use stegongp::ngp::model::Model;
use stegongp::ngp::render::image::{RenderOptions, render_image};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Model file (.ingp or .msgpack).
    #[arg(long)]
    pub model: PathBuf,
    /// Dataset whose cameras to render.
    #[arg(long)]
    pub data: PathBuf,
    #[arg(long, value_enum, default_value_t = SplitArg::Test)]
    pub split: SplitArg,
    /// Output directory for rgb_*.png, depth_*.png and opacity_*.png.
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, default_value_t = 1)]
    pub downscale: u32,
    /// COLMAP / LLFF data: the image folder to read (e.g. images_4).
    #[arg(long)]
    pub images: Option<String>,
    /// Render at most this many views, spread over the split (0 = all).
    #[arg(long, default_value_t = 0)]
    pub views: usize,
    #[arg(long, value_enum, default_value_t = Background::White)]
    pub background: Background,
    /// Key file: render the hidden scene it unlocks instead of the cover.
    #[arg(long)]
    pub key: Option<PathBuf>,
    /// Diagnostic variant of --key: partial:P (the first P of the m keys, the rest Π; for
    /// prf the first P of the secret's m shares, the rest zero), levels:P (the subkeys of the
    /// first P of the m level groups, the other levels Π), mixed:pi1k2k3, mixed:pi1pi2k3,
    /// wrong[:SEED].
    #[arg(long)]
    pub key_variant: Option<String>,
    /// The model was trained with `train --stealth`: apply --key as stealth training did
    /// (confined to the cover's reachable table entries, computed from the stored grid).
    #[arg(long)]
    pub stealth: bool,
}

pub fn run(a: Args) -> Result<()> {
    if a.downscale == 0 {
        bail!("--downscale must be at least 1");
    }
    let model = Model::load(&a.model)?;
    let data = Dataset::load(
        &a.data,
        a.split.into(),
        &LoadOptions {
            downscale: a.downscale,
            images: a.images.clone(),
            ..Default::default()
        },
    )?;
    let scene = super::scene_for_key(
        &model,
        a.key.as_deref(),
        a.key_variant.as_deref(),
        a.stealth,
    )?;
    let view = scene.view(&model);
    ensure_dir(&a.out)?;
    let opts = RenderOptions {
        background: a.background.rgb(),
        ..Default::default()
    };
    let which = spread_views(data.frames.len(), a.views);
    let pb = progress(
        which.len() as u64,
        "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} views {msg}",
    );
    for &i in &which {
        let img = render_image(&view, &data.frames[i].camera, &opts);
        let (w, h) = (img.width, img.height);
        save_png_rgb(&a.out.join(format!("rgb_{i:03}.png")), w, h, &img.rgb)?;
        let max_depth = img.depth.iter().cloned().fold(0.0f32, f32::max).max(1e-6);
        save_png_gray(
            &a.out.join(format!("depth_{i:03}.png")),
            w,
            h,
            &img.depth,
            max_depth,
        )?;
        save_png_gray(
            &a.out.join(format!("opacity_{i:03}.png")),
            w,
            h,
            &img.opacity,
            1.0,
        )?;
        pb.inc(1);
    }
    pb.finish_and_clear();
    eprintln!("rendered {} views into {}", which.len(), a.out.display());
    Ok(())
}
