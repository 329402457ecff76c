//! Held-out evaluation: render every camera of a split, PSNR, SSIM and LPIPS (AlexNet,
//! v0.1) against the images composited on the same background, under a [`Protocol`]: ours
//! (white by default, as the NeRF literature) or instant-ngp's `scripts/run.py` (black,
//! blended in linear light; see [`protocol`]).

pub mod protocol;

pub use protocol::Protocol;

use crate::lpips::{Lpips, LpipsFeatures};
use crate::metrics::psnr;
use ngp::camera::Camera;
use ngp::data::Dataset;
use ngp::error::Result;
use ngp::render::RenderBackend;
use ngp::render::image::{RenderOptions, RenderedImage, SceneView, render_image};
use serde::Serialize;
use std::convert::Infallible;

#[derive(Clone, Debug, Serialize)]
pub struct ViewScore {
    pub index: usize,
    pub file_path: String,
    pub psnr: f64,
    pub ssim: f64,
    /// LPIPS (AlexNet, v0.1; lower is better). `None` when skipped or when the view is
    /// smaller than 31 pixels in either direction.
    pub lpips: Option<f64>,
    /// Seconds the view took to render.
    pub render_seconds: f64,
    /// Network samples per ray that entered the scene's box (the CPU renderer's count; 0
    /// where the renderer does not count rays).
    pub samples_per_ray: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct EvalResult {
    /// The rules the views were scored under.
    pub protocol: Protocol,
    /// The background they were scored on (sRGB).
    pub background: [f32; 3],
    /// Mean over the views of each view's PSNR (as run.py averages).
    pub psnr: f64,
    pub ssim: f64,
    /// Mean LPIPS over the views that have one; `None` when skipped or when no view is
    /// large enough.
    pub lpips: Option<f64>,
    pub n_views: usize,
    /// Views in the split (run.py scores all of them).
    pub split_views: usize,
    /// PSNR, SSIM and LPIPS of an empty render (the background colour everywhere) on the
    /// same views: the score of showing nothing, the floor a render that carries no
    /// information about the scene sits near. Key experiments compare wrong and partial keys
    /// with it.
    pub blank_psnr: f64,
    pub blank_ssim: f64,
    pub blank_lpips: Option<f64>,
    pub views: Vec<ViewScore>,
    pub seconds: f64,
}

/// The ground truth of a frame on `bg` under our protocol, as an interleaved RGB float
/// image.
pub fn ground_truth(data: &Dataset, frame: usize, bg: [f32; 3]) -> Vec<f32> {
    Protocol::StegoNgp.ground_truth(&data.frames[frame].image, bg)
}

/// Scores views `which` (all when `None`) with PSNR, SSIM and LPIPS (the embedded
/// weights), calling `on_view` with each rendering.
pub fn evaluate(
    view: &SceneView,
    data: &Dataset,
    opts: &RenderOptions,
    which: Option<&[usize]>,
    on_view: impl FnMut(usize, &RenderedImage, &[f32]),
) -> EvalResult {
    evaluate_with(view, data, opts, which, Some(Lpips::embedded()), on_view)
}

/// [`evaluate`] with the LPIPS network given: `None` skips LPIPS (every `lpips` is `None`).
pub fn evaluate_with(
    view: &SceneView,
    data: &Dataset,
    opts: &RenderOptions,
    which: Option<&[usize]>,
    lpips: Option<&Lpips>,
    mut on_view: impl FnMut(usize, &RenderedImage, &[f32]),
) -> EvalResult {
    evaluate_each(view, data, opts, which, lpips, |score, img, gt| {
        on_view(score.index, img, gt)
    })
}

/// [`evaluate_with`], calling `on_view` with each view's scores as well as its rendering
/// and ground truth (for printing per-view scores as they come).
pub fn evaluate_each(
    view: &SceneView,
    data: &Dataset,
    opts: &RenderOptions,
    which: Option<&[usize]>,
    lpips: Option<&Lpips>,
    on_view: impl FnMut(&ViewScore, &RenderedImage, &[f32]),
) -> EvalResult {
    let render = |cam: &Camera, o: &RenderOptions| Ok::<_, Infallible>(render_image(view, cam, o));
    let Ok(r) = evaluate_by(
        render,
        Protocol::StegoNgp,
        data,
        opts,
        which,
        lpips,
        on_view,
    );
    r
}

/// [`evaluate_each`] on any device: `renderer` renders each view.
pub fn evaluate_on(
    renderer: &mut dyn RenderBackend,
    data: &Dataset,
    opts: &RenderOptions,
    which: Option<&[usize]>,
    lpips: Option<&Lpips>,
    on_view: impl FnMut(&ViewScore, &RenderedImage, &[f32]),
) -> Result<EvalResult> {
    evaluate_under(
        Protocol::StegoNgp,
        renderer,
        data,
        opts,
        which,
        lpips,
        on_view,
    )
}

/// [`evaluate_on`] under `protocol`: `opts.background` is the background asked for, which
/// instant-ngp's protocols replace with black. `on_view` gets the image as scored.
pub fn evaluate_under(
    protocol: Protocol,
    renderer: &mut dyn RenderBackend,
    data: &Dataset,
    opts: &RenderOptions,
    which: Option<&[usize]>,
    lpips: Option<&Lpips>,
    on_view: impl FnMut(&ViewScore, &RenderedImage, &[f32]),
) -> Result<EvalResult> {
    evaluate_by(
        |cam, o| renderer.render(cam, o),
        protocol,
        data,
        opts,
        which,
        lpips,
        on_view,
    )
}

fn evaluate_by<E>(
    mut render: impl FnMut(&Camera, &RenderOptions) -> std::result::Result<RenderedImage, E>,
    protocol: Protocol,
    data: &Dataset,
    opts: &RenderOptions,
    which: Option<&[usize]>,
    lpips: Option<&Lpips>,
    mut on_view: impl FnMut(&ViewScore, &RenderedImage, &[f32]),
) -> std::result::Result<EvalResult, E> {
    let t0 = std::time::Instant::now();
    let bg = protocol.background(opts.background);
    let render_opts = RenderOptions {
        background: protocol.render_background(bg),
        ..*opts
    };
    let blank_pixel = protocol.blank_pixel(bg);
    let all: Vec<usize> = (0..data.frames.len()).collect();
    let which = which.unwrap_or(&all);
    let mut views = Vec::new();
    let (mut blank_psnr, mut blank_ssim) = (0.0, 0.0);
    let (mut blank_lpips, mut n_lpips) = (0.0, 0usize);
    let mut blank: Vec<f32> = Vec::new();
    // The empty render's features, kept while the views' size stays the same.
    let mut blank_features: Option<LpipsFeatures> = None;
    for &i in which {
        let frame = &data.frames[i];
        let t_render = std::time::Instant::now();
        let mut img = render(&frame.camera, &render_opts)?;
        let render_seconds = t_render.elapsed().as_secs_f64();
        protocol.score_image(&mut img, bg);
        let gt = protocol.ground_truth(&frame.image, bg);
        let (w, h) = (img.width as usize, img.height as usize);
        blank.clear();
        blank.extend((0..w * h).flat_map(|_| blank_pixel));
        // On a GPU the render takes tens of milliseconds and these scores most of a view.
        let ((p, s), (bp, bs)) = rayon::join(
            || (psnr(&img.rgb, &gt), protocol.ssim(&img.rgb, &gt, w, h)),
            || (psnr(&blank, &gt), protocol.ssim(&blank, &gt, w, h)),
        );
        blank_psnr += bp;
        blank_ssim += bs;
        let mut lp = None;
        if let Some(net) = lpips {
            // The ground truth goes through the network once for both comparisons.
            let (fg, fp) = rayon::join(|| net.features(&gt, w, h), || net.features(&img.rgb, w, h));
            if let (Some(fg), Some(fp)) = (fg, fp) {
                if blank_features
                    .as_ref()
                    .is_none_or(|f| (f.width(), f.height()) != (w, h))
                {
                    blank_features = net.features(&blank, w, h);
                }
                let fb = blank_features.as_ref().expect("same size as the view");
                lp = Some(net.distance_features(&fp, &fg));
                blank_lpips += net.distance_features(fb, &fg);
                n_lpips += 1;
            }
        }
        let score = ViewScore {
            index: i,
            file_path: frame.file_path.clone(),
            psnr: p,
            ssim: s,
            lpips: lp,
            render_seconds,
            samples_per_ray: img.samples_per_ray().unwrap_or(0.0),
        };
        on_view(&score, &img, &gt);
        views.push(score);
    }
    let n = views.len().max(1) as f64;
    let lpips_mean =
        (n_lpips > 0).then(|| views.iter().filter_map(|v| v.lpips).sum::<f64>() / n_lpips as f64);
    Ok(EvalResult {
        protocol,
        background: bg,
        psnr: views.iter().map(|v| v.psnr).sum::<f64>() / n,
        ssim: views.iter().map(|v| v.ssim).sum::<f64>() / n,
        lpips: lpips_mean,
        n_views: views.len(),
        split_views: data.frames.len(),
        blank_psnr: blank_psnr / n,
        blank_ssim: blank_ssim / n,
        blank_lpips: (n_lpips > 0).then(|| blank_lpips / n_lpips as f64),
        views,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// `n` view indices spread evenly over `total` (all when n ≥ total).
pub fn spread_views(total: usize, n: usize) -> Vec<usize> {
    if n >= total || n == 0 {
        return (0..total).collect();
    }
    (0..n).map(|k| k * total / n).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use ngp::data::{DatasetFormat, Frame, Image, Split};
    use ngp::render::image::RenderProfile;

    /// A split of one-pixel frames, each half covered (α = 0.5) by linear grey 1, i.e.
    /// premultiplied 0.5; frame `i`'s camera sits at x = `i` so a renderer knows the frame.
    fn half_covered(n: usize) -> Dataset {
        let frames = (0..n)
            .map(|i| Frame {
                camera: Camera {
                    c2w: [
                        [1.0, 0.0, 0.0, i as f32],
                        [0.0, 1.0, 0.0, 0.0],
                        [0.0, 0.0, 1.0, 0.0],
                    ],
                    fx: 1.0,
                    fy: 1.0,
                    cx: 0.5,
                    cy: 0.5,
                    width: 1,
                    height: 1,
                    distortion: None,
                },
                image: Image::from_linear_premul(1, 1, &[0.5, 0.5, 0.5, 0.5]).unwrap(),
                file_path: format!("./test/r_{i}"),
            })
            .collect();
        Dataset {
            root: "half".into(),
            split: Split::Test,
            width: 1,
            height: 1,
            frames,
            aabb_scale: 1,
            scale: 0.33,
            offset: [0.5; 3],
            has_alpha: true,
            format: DatasetFormat::NerfSynthetic,
        }
    }

    /// What a renderer returns for a pixel whose samples sum to premultiplied sRGB grey `s`
    /// at opacity `alpha`: `s + (1 − alpha)·bg` in sRGB, as ours and the GPU's do.
    fn pixel(s: f32, alpha: f32, bg: [f32; 3]) -> RenderedImage {
        RenderedImage {
            width: 1,
            height: 1,
            rgb: bg.iter().map(|b| s + (1.0 - alpha) * b).collect(),
            depth: vec![1.0],
            opacity: vec![alpha],
            n_samples: 1,
            profile: RenderProfile::default(),
        }
    }

    /// Scores `data` under `protocol`, frame `i` rendered as grey `s[i]` at opacity 0.5,
    /// asking for a white background; returns the result, the backgrounds the renderer was
    /// asked for, and each view's (scored render, ground truth) pixel.
    fn score(
        protocol: Protocol,
        data: &Dataset,
        s: &[f32],
        which: Option<&[usize]>,
    ) -> (EvalResult, Vec<[f32; 3]>, Vec<(f32, f32)>) {
        let mut asked = Vec::new();
        let mut pixels = Vec::new();
        let opts = RenderOptions {
            background: [1.0; 3],
            ..Default::default()
        };
        let render = |cam: &Camera, o: &RenderOptions| {
            asked.push(o.background);
            Ok::<_, Infallible>(pixel(s[cam.c2w[0][3] as usize], 0.5, o.background))
        };
        let Ok(r) = evaluate_by(render, protocol, data, &opts, which, None, |_, img, gt| {
            pixels.push((img.rgb[0], gt[0]))
        });
        (r, asked, pixels)
    }

    #[test]
    fn a_half_covered_pixel_under_each_protocol() {
        let data = half_covered(1);
        // Ours: the renderer adds white in sRGB (0.3 + 0.5 = 0.8); the truth is composited
        // in linear light, 0.5 + 0.5 = 1, encoded 1.
        let (r, asked, px) = score(Protocol::StegoNgp, &data, &[0.3], None);
        assert_eq!(asked, vec![[1.0; 3]]);
        assert!(
            (px[0].0 - 0.8).abs() < 1e-6 && (px[0].1 - 1.0).abs() < 1e-6,
            "{px:?}"
        );
        assert!((r.psnr - 20.0 * 5f64.log10()).abs() < 1e-4, "{}", r.psnr);
        assert_eq!((r.protocol, r.background), (Protocol::StegoNgp, [1.0; 3]));
        // instant-ngp: white asked for, black used; the renderer adds nothing, the render
        // stays 0.3 (decoded and encoded again) and the truth is 1.055·0.5^(1/2.4) − 0.055.
        let (r, asked, px) = score(Protocol::InstantNgp, &data, &[0.3], None);
        assert_eq!(asked, vec![[0.0; 3]]);
        assert!((px[0].0 - 0.3).abs() < 1e-6, "{px:?}");
        assert!((px[0].1 as f64 - 0.735_356_983).abs() < 1e-6, "{px:?}");
        let want = -10.0 * ((0.735_356_983f64 - 0.3).powi(2)).log10();
        assert!((r.psnr - want).abs() < 1e-4, "{} against {want}", r.psnr);
        assert_eq!((r.protocol, r.background), (Protocol::InstantNgp, [0.0; 3]));
        // The empty render is black under instant-ngp's rules: its PSNR is the truth's.
        let blank = -10.0 * (0.735_356_983f64.powi(2)).log10();
        assert!((r.blank_psnr - blank).abs() < 1e-4, "{}", r.blank_psnr);
    }

    #[test]
    fn psnr_is_the_mean_of_each_views_psnr_over_every_view_of_the_split() {
        // Off by 0.1 (20 dB) and by 0.01 (40 dB): run.py reports the mean of the views'
        // PSNRs, 30 dB, not the PSNR of their mean MSE (22.97 dB).
        let data = half_covered(2);
        let truth = 0.735_357_f32;
        let (r, _, _) = score(
            Protocol::InstantNgp,
            &data,
            &[truth - 0.1, truth - 0.01],
            None,
        );
        assert!((r.psnr - 30.0).abs() < 1e-3, "{}", r.psnr);
        // Every frame of the split, in order, when no views are named.
        let idx: Vec<usize> = r.views.iter().map(|v| v.index).collect();
        assert_eq!(idx, vec![0, 1]);
        assert_eq!((r.n_views, r.split_views), (2, 2));
        // Named views only; the split's size is still reported.
        let (r, _, _) = score(Protocol::InstantNgp, &data, &[0.0, truth], Some(&[1]));
        assert_eq!((r.n_views, r.split_views, r.views[0].index), (1, 2, 1));
        assert!(r.psnr > 60.0, "{}", r.psnr);
    }

    #[test]
    fn our_ground_truth_is_the_training_target() {
        // Eval's truth under our protocol must stay the target training fits (target_on).
        let mut rng = ngp::rng::Pcg32::new(3, 5);
        let rgba: Vec<u8> = (0..4 * 7 * 5)
            .map(|_| (rng.next_f32() * 255.0) as u8)
            .collect();
        let img = Image::from_rgba8(7, 5, rgba).unwrap();
        for bg in [[1.0; 3], [0.0; 3], [0.2, 0.5, 0.9]] {
            let gt = Protocol::StegoNgp.ground_truth(&img, bg);
            for y in 0..5 {
                for x in 0..7 {
                    let i = 3 * (y * 7 + x) as usize;
                    assert_eq!(gt[i..i + 3], img.target_on(x, y, bg));
                }
            }
        }
    }
}
