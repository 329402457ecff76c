//! What `process` does to pixels itself: a frame's sharpness, shrinking a photo, and
//! writing a frame as PNG (lossless: COLMAP and the loaders read it as it was decoded).

use anyhow::{Context, Result};
use std::path::Path;

/// Variance of the Laplacian of the luma (BT.601 weights, 3×3 kernel 0 1 0 / 1 −4 1 /
/// 0 1 0 over the interior pixels): colmap2nerf's sharpness measure. A blurred frame (the
/// phone moved during the exposure) has weak second derivatives and a low variance.
pub fn sharpness(rgb: &[u8], w: usize, h: usize) -> f64 {
    if w < 3 || h < 3 || rgb.len() < 3 * w * h {
        return 0.0;
    }
    let luma: Vec<f32> = rgb
        .chunks_exact(3)
        .take(w * h)
        .map(|p| 0.299 * p[0] as f32 + 0.587 * p[1] as f32 + 0.114 * p[2] as f32)
        .collect();
    let (mut sum, mut sum2) = (0.0f64, 0.0f64);
    for y in 1..h - 1 {
        let row = y * w;
        let mut acc = (0.0f64, 0.0f64);
        for x in 1..w - 1 {
            let i = row + x;
            let l = luma[i - 1] + luma[i + 1] + luma[i - w] + luma[i + w] - 4.0 * luma[i];
            acc.0 += l as f64;
            acc.1 += (l * l) as f64;
        }
        sum += acc.0;
        sum2 += acc.1;
    }
    let n = ((w - 2) * (h - 2)) as f64;
    let mean = sum / n;
    (sum2 / n - mean * mean).max(0.0)
}

/// The size a `w×h` image takes with its long side capped at `max_side` (0: no cap); never
/// enlarged, aspect kept to the nearest pixel.
pub fn capped_size(w: u32, h: u32, max_side: u32) -> (u32, u32) {
    let long = w.max(h);
    if max_side == 0 || long <= max_side {
        return (w, h);
    }
    let s = max_side as f64 / long as f64;
    let side = |v: u32| ((v as f64 * s).round() as u32).max(1);
    if w >= h {
        (max_side, side(h))
    } else {
        (side(w), max_side)
    }
}

/// For each of `m` output samples over `n` input samples, the inputs it covers and their
/// share (area averaging: every input sample counts in proportion to its overlap).
fn area_weights(n: usize, m: usize) -> Vec<Vec<(usize, f32)>> {
    let scale = n as f64 / m as f64;
    (0..m)
        .map(|o| {
            let (a, b) = (o as f64 * scale, (o + 1) as f64 * scale);
            let mut v = Vec::new();
            let mut s = a.floor() as usize;
            while (s as f64) < b && s < n {
                let overlap = b.min(s as f64 + 1.0) - a.max(s as f64);
                if overlap > 0.0 {
                    v.push((s, (overlap / scale) as f32));
                }
                s += 1;
            }
            v
        })
        .collect()
}

/// Shrinks interleaved 8-bit pixels (`ch` channels) from `w×h` to `nw×nh` by area averaging
/// (in the stored sRGB values, as ffmpeg's `area` scaler does).
pub fn resize_area(src: &[u8], ch: usize, w: usize, h: usize, nw: usize, nh: usize) -> Vec<u8> {
    let (wx, wy) = (area_weights(w, nw), area_weights(h, nh));
    let mut rows = vec![0f32; h * nw * ch];
    for y in 0..h {
        let (s, d) = (&src[y * w * ch..(y + 1) * w * ch], &mut rows[y * nw * ch..]);
        for (ox, ws) in wx.iter().enumerate() {
            for &(sx, k) in ws {
                for c in 0..ch {
                    d[ox * ch + c] += s[sx * ch + c] as f32 * k;
                }
            }
        }
    }
    let mut out = vec![0u8; nw * nh * ch];
    let mut acc = vec![0f32; nw * ch];
    for (oy, ws) in wy.iter().enumerate() {
        acc.iter_mut().for_each(|v| *v = 0.0);
        for &(sy, k) in ws {
            for (a, r) in acc.iter_mut().zip(&rows[sy * nw * ch..(sy + 1) * nw * ch]) {
                *a += r * k;
            }
        }
        for (o, a) in out[oy * nw * ch..(oy + 1) * nw * ch].iter_mut().zip(&acc) {
            *o = (a + 0.5).clamp(0.0, 255.0) as u8;
        }
    }
    out
}

/// Writes 8-bit RGB (`ch` = 3) or RGBA (4) pixels as a PNG, synced: the whole output folder
/// is renamed into place at the end, and must be on disk when it is.
pub fn write_png(path: &Path, w: u32, h: u32, ch: usize, px: &[u8]) -> Result<()> {
    use std::io::Write;
    let bytes = ngp::data::png_bytes(w, h, ch, px, true)
        .with_context(|| format!("{}: encoding", path.display()))?;
    let mut file = std::fs::File::create(path)
        .with_context(|| format!("{}: cannot create", path.display()))?;
    file.write_all(&bytes)
        .with_context(|| format!("{}: writing", path.display()))?;
    file.sync_all()
        .with_context(|| format!("{}: syncing", path.display()))?;
    Ok(())
}

/// Copies a file and syncs the copy.
pub fn copy_synced(from: &Path, to: &Path) -> Result<()> {
    std::fs::copy(from, to)
        .with_context(|| format!("copying {} to {}", from.display(), to.display()))?;
    let f = std::fs::OpenOptions::new()
        .write(true)
        .open(to)
        .with_context(|| format!("{}: cannot open", to.display()))?;
    f.sync_all()
        .with_context(|| format!("{}: syncing", to.display()))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A checkerboard of `cell`-pixel squares, grey.
    fn checker(w: usize, h: usize, cell: usize) -> Vec<u8> {
        (0..w * h)
            .flat_map(|i| {
                let v = if ((i % w) / cell + (i / w) / cell).is_multiple_of(2) {
                    30
                } else {
                    220
                };
                [v, v, v]
            })
            .collect()
    }

    #[test]
    fn sharp_frames_score_above_blurred_ones() {
        let (w, h) = (64, 48);
        let sharp = checker(w, h, 4);
        // The same pattern through a 2× area shrink and back: blurred edges.
        let small = resize_area(&sharp, 3, w, h, w / 3, h / 3);
        let blurred: Vec<u8> = (0..w * h)
            .flat_map(|i| {
                let (x, y) = ((i % w) / 3, (i / w) / 3);
                let j = (y.min(h / 3 - 1) * (w / 3) + x.min(w / 3 - 1)) * 3;
                [small[j], small[j + 1], small[j + 2]]
            })
            .collect();
        let flat = vec![128u8; w * h * 3];
        let (s, b, f) = (
            sharpness(&sharp, w, h),
            sharpness(&blurred, w, h),
            sharpness(&flat, w, h),
        );
        assert!(s > b && b > f, "{s} {b} {f}");
        assert_eq!(f, 0.0);
        // By hand: one bright pixel (255 luma) in a 5×5 black image; the Laplacian over the
        // 3×3 interior is −1020 at the centre and 255 at its four neighbours.
        let mut dot = vec![0u8; 5 * 5 * 3];
        dot[(2 * 5 + 2) * 3..(2 * 5 + 2) * 3 + 3].copy_from_slice(&[255, 255, 255]);
        let l: [f64; 9] = [0., 255., 0., 255., -1020., 255., 0., 255., 0.];
        let mean = l.iter().sum::<f64>() / 9.0;
        let var = l.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / 9.0;
        assert!((sharpness(&dot, 5, 5) - var).abs() < 1e-3 * var);
    }

    #[test]
    fn sizes_are_capped_on_the_long_side() {
        assert_eq!(capped_size(1920, 1080, 960), (960, 540));
        assert_eq!(capped_size(1080, 1920, 960), (540, 960));
        assert_eq!(capped_size(640, 480, 960), (640, 480));
        assert_eq!(capped_size(4032, 3024, 1000), (1000, 750));
        assert_eq!(capped_size(4000, 3000, 0), (4000, 3000));
    }

    #[test]
    fn area_resize_averages_what_each_pixel_covers() {
        // 4×1 → 2×1: pairs averaged; 3×1 → 2×1: 1.5 pixels each.
        assert_eq!(
            resize_area(&[0, 100, 200, 50], 1, 4, 1, 2, 1),
            vec![50, 125]
        );
        assert_eq!(resize_area(&[0, 90, 180], 1, 3, 1, 2, 1), vec![30, 150]);
        // A flat image stays flat at any size; the mean is kept.
        let img = vec![77u8; 7 * 5 * 3];
        assert!(resize_area(&img, 3, 7, 5, 3, 2).iter().all(|&v| v == 77));
        let grad: Vec<u8> = (0..16u8).map(|v| v * 16).collect();
        let out = resize_area(&grad, 1, 4, 4, 2, 2);
        let mean_in = grad.iter().map(|&v| v as f64).sum::<f64>() / 16.0;
        let mean_out = out.iter().map(|&v| v as f64).sum::<f64>() / 4.0;
        assert!((mean_in - mean_out).abs() < 1.0);
    }
}
