use super::common::{Background, SplitArg, ensure_dir};
use anyhow::{Result, bail};
use std::path::PathBuf;
use stegongp::ngp::data::{Dataset, LoadOptions, save_png_rgb};
use stegongp::ngp::eval::{evaluate_each, spread_views};
use stegongp::ngp::lpips::Lpips;
use stegongp::ngp::model::Model;
use stegongp::ngp::render::image::RenderOptions;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Model file (.ingp or .msgpack).
    #[arg(long)]
    pub model: PathBuf,
    /// Dataset with the held-out views.
    #[arg(long)]
    pub data: PathBuf,
    #[arg(long, value_enum, default_value_t = SplitArg::Test)]
    pub split: SplitArg,
    #[arg(long, default_value_t = 1)]
    pub downscale: u32,
    /// COLMAP / LLFF data: the image folder to read (e.g. images_4).
    #[arg(long)]
    pub images: Option<String>,
    /// Evaluate at most this many views, spread over the split (0 = all).
    #[arg(long, default_value_t = 0)]
    pub views: usize,
    #[arg(long, value_enum, default_value_t = Background::White)]
    pub background: Background,
    /// Key file: evaluate the hidden scene it unlocks.
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
    /// Also write each rendering (and ground truth) as PNG into this directory.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print one JSON object (psnr, ssim, lpips, n_views, the empty render's scores,
    /// per-view scores; lpips is null with --no-lpips).
    #[arg(long)]
    pub json: bool,
    /// Skip LPIPS (AlexNet v0.1, computed on the CPU from the embedded weights).
    #[arg(long)]
    pub no_lpips: bool,
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
    if let Some(dir) = &a.out {
        ensure_dir(dir)?;
    }
    let opts = RenderOptions {
        background: a.background.rgb(),
        ..Default::default()
    };
    let which = spread_views(data.frames.len(), a.views);
    let mut io_err = None;
    let lpips = (!a.no_lpips).then(Lpips::embedded);
    let r = evaluate_each(&view, &data, &opts, Some(&which), lpips, |v, img, gt| {
        let i = v.index;
        if let Some(dir) = &a.out {
            let res = save_png_rgb(
                &dir.join(format!("rgb_{i:03}.png")),
                img.width,
                img.height,
                &img.rgb,
            )
            .and_then(|_| {
                save_png_rgb(
                    &dir.join(format!("gt_{i:03}.png")),
                    img.width,
                    img.height,
                    gt,
                )
            });
            if let Err(e) = res {
                io_err.get_or_insert(e);
            }
        }
        if !a.json {
            eprintln!(
                "view {i:3}: PSNR {:.2} dB, SSIM {:.4}{}",
                v.psnr,
                v.ssim,
                v.lpips
                    .map(|l| format!(", LPIPS {l:.4}"))
                    .unwrap_or_default()
            );
        }
    });
    if let Some(e) = io_err {
        return Err(e.into());
    }
    if a.json {
        println!("{}", serde_json::to_string(&r)?);
    } else {
        let lp = |l: Option<f64>| l.map(|l| format!(", LPIPS {l:.4}")).unwrap_or_default();
        println!(
            "{} views: PSNR {:.3} dB, SSIM {:.4}{} ({:.1} s); an empty render scores {:.2} dB, SSIM {:.4}{}",
            r.n_views,
            r.psnr,
            r.ssim,
            lp(r.lpips),
            r.seconds,
            r.blank_psnr,
            r.blank_ssim,
            lp(r.blank_lpips)
        );
        if !a.no_lpips && r.lpips.is_none() {
            println!(
                "LPIPS: no view is large enough (AlexNet needs at least {0}×{0} pixels)",
                stegongp::ngp::lpips::MIN_SIZE
            );
        }
    }
    Ok(())
}
