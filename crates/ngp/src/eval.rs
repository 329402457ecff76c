//! Held-out evaluation: render every camera of a split, PSNR, SSIM and LPIPS (AlexNet,
//! v0.1) against the images composited on the same background (white by default, as the
//! NeRF literature).

use crate::camera::Camera;
use crate::data::Dataset;
use crate::error::Result;
use crate::lpips::{Lpips, LpipsFeatures};
use crate::metrics::{psnr, ssim};
use crate::render::RenderBackend;
use crate::render::image::{RenderOptions, RenderedImage, SceneView, render_image};
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
    pub psnr: f64,
    pub ssim: f64,
    /// Mean LPIPS over the views that have one; `None` when skipped or when no view is
    /// large enough.
    pub lpips: Option<f64>,
    pub n_views: usize,
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

/// The ground truth of a frame on `bg`, as an interleaved RGB float image.
pub fn ground_truth(data: &Dataset, frame: usize, bg: [f32; 3]) -> Vec<f32> {
    let img = &data.frames[frame].image;
    let mut out = Vec::with_capacity((img.width * img.height * 3) as usize);
    for y in 0..img.height {
        for x in 0..img.width {
            out.extend_from_slice(&img.target_on(x, y, bg));
        }
    }
    out
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
    let Ok(r) = evaluate_by(render, data, opts, which, lpips, on_view);
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
    evaluate_by(
        |cam, o| renderer.render(cam, o),
        data,
        opts,
        which,
        lpips,
        on_view,
    )
}

fn evaluate_by<E>(
    mut render: impl FnMut(&Camera, &RenderOptions) -> std::result::Result<RenderedImage, E>,
    data: &Dataset,
    opts: &RenderOptions,
    which: Option<&[usize]>,
    lpips: Option<&Lpips>,
    mut on_view: impl FnMut(&ViewScore, &RenderedImage, &[f32]),
) -> std::result::Result<EvalResult, E> {
    let t0 = std::time::Instant::now();
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
        let img = render(&frame.camera, opts)?;
        let render_seconds = t_render.elapsed().as_secs_f64();
        let gt = ground_truth(data, i, opts.background);
        let (w, h) = (img.width as usize, img.height as usize);
        blank.clear();
        blank.extend((0..w * h).flat_map(|_| opts.background));
        // On a GPU the render takes tens of milliseconds and these scores most of a view.
        let ((p, s), (bp, bs)) = rayon::join(
            || (psnr(&img.rgb, &gt), ssim(&img.rgb, &gt, w, h)),
            || (psnr(&blank, &gt), ssim(&blank, &gt, w, h)),
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
        psnr: views.iter().map(|v| v.psnr).sum::<f64>() / n,
        ssim: views.iter().map(|v| v.ssim).sum::<f64>() / n,
        lpips: lpips_mean,
        n_views: views.len(),
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
