//! The cover as the file shows it: cameras from the training views a snapshot keeps, and
//! renders of the cover from them (what an analyst without the photos trains on).

use ngp::camera::Camera;
use ngp::data::{Dataset, DatasetFormat, Frame, Image, Split};
use ngp::encoding::reference_indices;
use ngp::error::{Error, Result};
use ngp::model::Model;
use ngp::render::image::{RenderOptions, render_image};
use std::path::PathBuf;

/// Up to `max_views` of the file's stored cameras, spread evenly over them, as pinhole
/// cameras whose long side is at most `side` pixels (a lens's distortion is dropped: the
/// renders are of the model, which has none).
pub fn stored_cameras(model: &Model, side: u32, max_views: usize) -> Result<Vec<Camera>> {
    let images = match &model.dataset {
        Some(d) if !d.images.is_empty() => &d.images,
        _ => {
            return Err(Error::Config(
                "the file keeps no training cameras to render the cover from".into(),
            ));
        }
    };
    let usable: Vec<_> = images
        .iter()
        .filter(|im| {
            im.resolution[0] > 0
                && im.resolution[1] > 0
                && im.focal_length[0] > 0.0
                && im.focal_length[1] > 0.0
        })
        .collect();
    if usable.is_empty() {
        return Err(Error::Config(
            "the file's stored cameras have no size or focal length".into(),
        ));
    }
    let n = usable.len().min(max_views.max(1));
    Ok((0..n)
        .map(|k| {
            let im = usable[k * usable.len() / n];
            let (w, h) = (im.resolution[0] as f32, im.resolution[1] as f32);
            let s = (side as f32 / w.max(h)).min(1.0);
            let (width, height) = ((w * s).round().max(1.0), (h * s).round().max(1.0));
            let (sx, sy) = (width / w, height / h);
            Camera {
                c2w: im.xform_start,
                fx: im.focal_length[0] * sx,
                fy: im.focal_length[1] * sy,
                cx: im.principal_point[0] * width,
                cy: im.principal_point[1] * height,
                width: width as u32,
                height: height as u32,
                distortion: None,
            }
        })
        .collect())
}

/// sRGB straight-alpha bytes of a render on black: colour `rgb / opacity`, alpha the
/// opacity.
fn rgba_of(rgb: &[f32], opacity: &[f32]) -> Vec<u8> {
    let byte = |x: f32| (x.clamp(0.0, 1.0) * 255.0).round() as u8;
    let mut out = Vec::with_capacity(opacity.len() * 4);
    for (c, &a) in rgb.chunks(3).zip(opacity) {
        let inv = if a > 1e-6 { 1.0 / a } else { 0.0 };
        out.extend([
            byte(c[0] * inv),
            byte(c[1] * inv),
            byte(c[2] * inv),
            byte(a),
        ]);
    }
    out
}

/// The cover rendered (reference index, stored grid) from `cameras`, as a training set in
/// the model's box and frame: RGBA, so the transparent background trains as the cover's
/// did.
pub fn cover_renders(model: &Model, cameras: &[Camera]) -> Result<Dataset> {
    let layout = &model.net.layout.grid;
    let idx = reference_indices(layout);
    let view = model.view(&idx, &model.grid);
    let opts = RenderOptions {
        background: [0.0; 3],
        ..RenderOptions::default()
    };
    let mut frames = Vec::with_capacity(cameras.len());
    for (i, cam) in cameras.iter().enumerate() {
        let r = render_image(&view, cam, &opts);
        let image = Image::from_rgba8(cam.width, cam.height, rgba_of(&r.rgb, &r.opacity))?;
        frames.push(Frame {
            camera: cam.clone(),
            image,
            file_path: format!("render_{i:04}"),
        });
    }
    let first = &cameras[0];
    let (scale, offset) = model
        .dataset
        .as_ref()
        .map_or((0.33, [0.5; 3]), |d| (d.scale, d.offset));
    Ok(Dataset {
        root: PathBuf::from("renders of the cover"),
        split: Split::Train,
        width: first.width,
        height: first.height,
        frames,
        aabb_scale: model.config.aabb_scale,
        scale,
        offset,
        has_alpha: true,
        format: DatasetFormat::InstantNgp,
    })
}
