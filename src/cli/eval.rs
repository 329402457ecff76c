use super::common::{ViewArgs, Viewing, ensure_dir};
use anyhow::{Result, bail};
use std::path::PathBuf;
use stegongp::backend::DeviceReport;
use stegongp::ngp::data::save_png_rgb;
use stegongp::ngp::render::image::Background;
use stegongp::ngp::render::image::SCORING_MIN_TRANSMITTANCE;
use stegongp::score::eval::{EvalResult, Protocol, evaluate_under};
use stegongp::score::lpips::Lpips;
use stegongp::stego::options::choice;

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(flatten)]
    pub view: ViewArgs,
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
    /// The rules views are scored under. `stegongp`: ours. `instant-ngp`: what instant-ngp's
    /// scripts/run.py does with --test_transforms, read from its source: black background,
    /// the render's colour decoded to linear light and the background added there, the
    /// ground truth's alpha composited in linear light, both encoded to sRGB with the
    /// exponent 1/2.4 and clipped to [0, 1], PSNR per view averaged over the views, and its
    /// own SSIM (luminance, 5-tap blur; not the literature's). run.py scores every view of
    /// the split at the images' own size: compare with its figures at --views 0 and
    /// --downscale 1. `instant-ngp-compat`: run.py --nerf_compatibility, the setting its
    /// authors name for the paper's synthetic-scene PSNR (the ground truth's alpha applied
    /// in sRGB). LPIPS, which run.py does not compute, is ours on the images as scored.
    #[arg(long, value_parser = choice::<Protocol>(), default_value_t = Protocol::StegoNgp)]
    pub protocol: Protocol,
}

pub fn run(a: Args) -> Result<()> {
    // Refused before the model and the images load.
    if a.protocol != Protocol::StegoNgp && a.view.background == Some(Background::White) {
        bail!(
            "--protocol {} scores on black, as instant-ngp's run.py does: drop --background \
             white, or score on white with --protocol stegongp",
            a.protocol
        );
    }
    let Viewing {
        device,
        model,
        data,
        scene,
        opts,
        which,
    } = a.view.open(SCORING_MIN_TRANSMITTANCE)?;
    let mut renderer = scene.renderer(&device, &model)?;
    if !a.json {
        eprintln!("device: {}", device.report());
    }
    if let Some(dir) = &a.out {
        ensure_dir(dir)?;
    }
    let mut io_err = None;
    let mut done = 0;
    let lpips = (!a.no_lpips).then(Lpips::embedded);
    let r = evaluate_under(
        a.protocol,
        renderer.as_mut(),
        &data,
        &opts,
        Some(&which),
        lpips,
        |v, img, gt| {
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
            done += 1;
            if !a.json {
                let profile = img.profile_note();
                eprintln!(
                    "[{done}/{}] view {i:3}: PSNR {:.2} dB, SSIM {:.4}{} ({:.2} s{profile})",
                    which.len(),
                    v.psnr,
                    v.ssim,
                    v.lpips
                        .map(|l| format!(", LPIPS {l:.4}"))
                        .unwrap_or_default(),
                    v.render_seconds,
                );
            }
        },
    )?;
    if let Some(e) = io_err {
        return Err(e.into());
    }
    if a.json {
        #[derive(serde::Serialize)]
        struct WithDevice<'a> {
            device: DeviceReport,
            #[serde(flatten)]
            result: &'a EvalResult,
        }
        let out = WithDevice {
            device: device.report(),
            result: &r,
        };
        println!("{}", serde_json::to_string(&out)?);
    } else {
        let lp = |l: Option<f64>| l.map(|l| format!(", LPIPS {l:.4}")).unwrap_or_default();
        println!(
            "protocol {}, {} of {} views: PSNR {:.3} dB, SSIM {:.4}{} ({:.1} s); an empty render scores {:.2} dB, SSIM {:.4}{}",
            r.protocol,
            r.n_views,
            r.split_views,
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
                stegongp::score::lpips::MIN_SIZE
            );
        }
    }
    Ok(())
}
