//! How a held-out view is scored: ours, or instant-ngp's `scripts/run.py` (with or without
//! its `--nerf_compatibility`), read from its source.
//!
//! What run.py does with `--test_transforms` (instant-ngp at abe236e, 2026-02-02; the
//! scoring has been the same since 2b6a55f, 2022-01-15):
//! - every frame of the given transforms file (`transforms_test.json`), at its own
//!   resolution (`run.py` 284–291);
//! - background black: `testbed.background_color = [0, 0, 0, 1]` (`run.py` 270);
//! - rays through pixel centres (`snap_to_pixel_centers`, 274; the 8 samples a pixel, 275,
//!   are then the same ray: `ld_random_pixel_offset(0)` is (0.5, 0.5), `random_val.cuh`
//!   320–325), stopped at transmittance 1e-4 (277);
//! - the render: the network's colours are composited in sRGB as trained, and the
//!   accumulated, premultiplied colour is decoded to linear light (`shade_kernel_nerf`,
//!   `testbed_nerf.cu` 1369–1372); the background is decoded to linear and added with
//!   weight 1 − α there (`tonemap_kernel`, `render_buffer.cu` 521–529), and `render(…,
//!   linear=True)` returns linear light (`python_api.cu` 146–213, `testbed.cu` 5044);
//! - the ground truth: the PNG's sRGB decoded and premultiplied (`read_rgba`,
//!   `nerf_device.cuh` 857–858), the background added in linear light
//!   (`overlay_image_kernel`, `render_buffer.cu` 390–403);
//! - both encoded with the script's `linear_to_srgb` (exponent 1/2.4, `common.py` 129–131)
//!   and clipped to [0, 1] (`run.py` 301–302); PSNR = −10·log10 of each view's MSE over
//!   pixels and channels (`common.py` 35, 212–256), averaged over the views (307, 315);
//!   SSIM is `common.py`'s own (175–198, [`ssim_instant_ngp`]).
//!
//! `--nerf_compatibility` (run.py 164–191) sets the colour space to sRGB: the ground
//! truth's alpha is then applied to its sRGB colour (`render_buffer.cu` 394–400), and the
//! render's background is added in sRGB (`accumulate_kernel` re-encodes the frame,
//! `render_buffer.cu` 253–256, before `tonemap_kernel` adds it). Its commit message
//! (2b6a55f) names it as the setting that reproduces the paper's lego PSNR.

use crate::metrics::{ssim, ssim_instant_ngp};
use ngp::choice::Choice;
use ngp::data::Image;
use ngp::data::color::{linear_to_srgb, linear_to_srgb_exact, srgb_to_linear};
use ngp::render::image::RenderedImage;

/// The rules a view is scored under (`eval --protocol`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Protocol {
    /// Ours: the background asked for (white by default), added to the render in sRGB;
    /// the ground truth composited on it in linear light; the literature's SSIM.
    #[default]
    StegoNgp,
    /// instant-ngp's `scripts/run.py` as it runs by default.
    InstantNgp,
    /// instant-ngp's `scripts/run.py --nerf_compatibility`.
    InstantNgpCompat,
}

impl Choice for Protocol {
    const ALL: &'static [Self] = &[
        Protocol::StegoNgp,
        Protocol::InstantNgp,
        Protocol::InstantNgpCompat,
    ];
    fn name(self) -> &'static str {
        match self {
            Protocol::StegoNgp => "stegongp",
            Protocol::InstantNgp => "instant-ngp",
            Protocol::InstantNgpCompat => "instant-ngp-compat",
        }
    }
    fn help(self) -> &'static str {
        match self {
            Protocol::StegoNgp => {
                "ours (default): on --background (white unless given), the render's \
                 background added in sRGB, the ground truth composited in linear light then \
                 sRGB-encoded; PSNR per view (render clipped to [0, 1]) averaged over the \
                 views; SSIM with an 11×11 Gaussian window (σ 1.5) on R, G and B"
            }
            Protocol::InstantNgp => {
                "instant-ngp's scripts/run.py: on black; the render's colour decoded to \
                 linear light and the background added there, the ground truth composited in \
                 linear light; both sRGB-encoded (exponent 1/2.4) and clipped; PSNR per view \
                 averaged over the views; run.py's SSIM (luminance, 5-tap blur)"
            }
            Protocol::InstantNgpCompat => {
                "run.py --nerf_compatibility: as instant-ngp, but the ground truth's alpha \
                 applied to its sRGB colour and the background added in sRGB"
            }
        }
    }
}

impl std::fmt::Display for Protocol {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl serde::Serialize for Protocol {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.name())
    }
}

/// `x` clipped to [0, 1], as f32 (what run.py's `np.clip` leaves).
fn unit(x: f64) -> f32 {
    x.clamp(0.0, 1.0) as f32
}

impl Protocol {
    /// The background views are scored on, given the one asked for: instant-ngp's run.py
    /// always scores on black.
    pub fn background(self, asked: [f32; 3]) -> [f32; 3] {
        match self {
            Protocol::StegoNgp => asked,
            Protocol::InstantNgp | Protocol::InstantNgpCompat => [0.0; 3],
        }
    }

    /// The background the renderer is to add itself (in sRGB, `Σ w·c + T·bg`): ours lets it
    /// add the scoring background; instant-ngp's protocols take the bare premultiplied
    /// colour (black) and add the background themselves, in [`Protocol::render_pixel`].
    pub fn render_background(self, bg: [f32; 3]) -> [f32; 3] {
        match self {
            Protocol::StegoNgp => bg,
            Protocol::InstantNgp | Protocol::InstantNgpCompat => [0.0; 3],
        }
    }

    /// One scored pixel of a render, from what the renderer returned for it: `rgb` (with
    /// [`Protocol::render_background`] already added) and its opacity `alpha` (1 − T).
    pub fn render_pixel(self, rgb: [f32; 3], alpha: f32, bg: [f32; 3]) -> [f32; 3] {
        let t = 1.0 - alpha as f64;
        match self {
            // The renderer already added the background in sRGB; PSNR and SSIM clip.
            Protocol::StegoNgp => rgb,
            // Premultiplied sRGB decoded to linear as it stands, the background added there.
            Protocol::InstantNgp => std::array::from_fn(|c| {
                let lin = srgb_to_linear(rgb[c]) as f64 + t * srgb_to_linear(bg[c]) as f64;
                unit(linear_to_srgb_exact(lin))
            }),
            // The frame re-encoded to sRGB (the CUDA exponent), the background added in sRGB,
            // then decoded for the linear output and encoded again by the script.
            Protocol::InstantNgpCompat => std::array::from_fn(|c| {
                let s = linear_to_srgb(srgb_to_linear(rgb[c])) as f64 + t * bg[c] as f64;
                unit(linear_to_srgb_exact(srgb_to_linear(s as f32) as f64))
            }),
        }
    }

    /// One ground-truth pixel: `premul` is the image's linear, premultiplied colour and its
    /// alpha ([`Image::linear_premul`]).
    pub fn truth_pixel(self, premul: [f32; 4], bg: [f32; 3]) -> [f32; 3] {
        let a = premul[3];
        let t = 1.0 - a as f64;
        match self {
            // Linear light, encoded with the training targets' transfer function (as
            // `Image::target_on`).
            Protocol::StegoNgp => std::array::from_fn(|c| {
                linear_to_srgb(premul[c] + (1.0 - a) * srgb_to_linear(bg[c]))
            }),
            Protocol::InstantNgp => std::array::from_fn(|c| {
                let lin = premul[c] as f64 + t * srgb_to_linear(bg[c]) as f64;
                unit(linear_to_srgb_exact(lin))
            }),
            // The straight colour encoded to sRGB, then alpha applied there.
            Protocol::InstantNgpCompat => std::array::from_fn(|c| {
                let s = if a > 0.0 {
                    linear_to_srgb(premul[c] / a) as f64 * a as f64
                } else {
                    0.0
                };
                let s = s + t * bg[c] as f64;
                unit(linear_to_srgb_exact(srgb_to_linear(s as f32) as f64))
            }),
        }
    }

    /// Rewrites `img.rgb` into the image this protocol scores (nothing to do for ours).
    pub fn score_image(self, img: &mut RenderedImage, bg: [f32; 3]) {
        if self == Protocol::StegoNgp {
            return;
        }
        for (px, &a) in img.rgb.chunks_exact_mut(3).zip(&img.opacity) {
            let out = self.render_pixel([px[0], px[1], px[2]], a, bg);
            px.copy_from_slice(&out);
        }
    }

    /// The ground truth of `image` on `bg`, interleaved RGB.
    pub fn ground_truth(self, image: &Image, bg: [f32; 3]) -> Vec<f32> {
        let mut out = Vec::with_capacity(3 * image.width as usize * image.height as usize);
        for y in 0..image.height {
            for x in 0..image.width {
                out.extend_from_slice(&self.truth_pixel(image.linear_premul(x, y), bg));
            }
        }
        out
    }

    /// An empty render (nothing in the scene) as this protocol scores it.
    pub fn blank_pixel(self, bg: [f32; 3]) -> [f32; 3] {
        self.render_pixel(self.render_background(bg), 0.0, bg)
    }

    /// SSIM as this protocol computes it.
    pub fn ssim(self, pred: &[f32], gt: &[f32], width: usize, height: usize) -> f64 {
        match self {
            Protocol::StegoNgp => ssim(pred, gt, width, height),
            Protocol::InstantNgp | Protocol::InstantNgpCompat => {
                ssim_instant_ngp(pred, gt, width, height)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const WHITE: [f32; 3] = [1.0; 3];
    const BLACK: [f32; 3] = [0.0; 3];

    fn close(got: [f32; 3], want: [f64; 3], tol: f64) {
        for c in 0..3 {
            assert!(
                (got[c] as f64 - want[c]).abs() <= tol,
                "channel {c}: {got:?} against {want:?}"
            );
        }
    }

    #[test]
    fn names_parse_and_instant_ngp_scores_on_black_whatever_is_asked() {
        for &p in Protocol::ALL {
            assert_eq!(Protocol::from_name(p.name()), Ok(p));
            assert!(!p.help().is_empty(), "{p:?} has no help");
        }
        assert_eq!(Protocol::default(), Protocol::StegoNgp);
        assert_eq!(Protocol::StegoNgp.background(WHITE), WHITE);
        assert_eq!(Protocol::InstantNgp.background(WHITE), BLACK);
        assert_eq!(Protocol::InstantNgpCompat.background(WHITE), BLACK);
        assert_eq!(Protocol::StegoNgp.render_background(WHITE), WHITE);
        assert_eq!(Protocol::InstantNgp.render_background(WHITE), BLACK);
    }

    /// A ground-truth pixel half covered (α = 0.5) by linear colour (1, 0.5, 0), i.e.
    /// premultiplied (0.5, 0.25, 0), worked by hand.
    #[test]
    fn half_covered_ground_truth_pixel_under_each_protocol() {
        let premul = [0.5, 0.25, 0.0, 0.5];
        // Ours on white, in linear light: (0.5 + 0.5, 0.25 + 0.5, 0 + 0.5) encoded with the
        // truncated exponent 0.41666: (1, 1.055·0.75^0.41666 − 0.055, 1.055·0.5^0.41666 −
        // 0.055).
        close(
            Protocol::StegoNgp.truth_pixel(premul, WHITE),
            [1.0, 0.880_826_816, 0.735_360_635],
            1e-6,
        );
        // Ours on black: the premultiplied values encoded (0.25 → 0.537104…).
        close(
            Protocol::StegoNgp.truth_pixel(premul, BLACK),
            [0.735_360_635, 0.537_104_203, 0.0],
            1e-6,
        );
        // run.py: on black, linear light, exponent 1/2.4: 1.055·0.5^(1/2.4) − 0.055 and
        // 1.055·0.25^(1/2.4) − 0.055.
        close(
            Protocol::InstantNgp.truth_pixel(premul, BLACK),
            [0.735_356_983, 0.537_098_730, 0.0],
            1e-6,
        );
        // run.py --nerf_compatibility: the straight colour (1, 0.5, 0) encoded, then halved
        // in sRGB: (0.5, 0.5·0.735361 = 0.367680, 0), round-tripped through linear light.
        close(
            Protocol::InstantNgpCompat.truth_pixel(premul, BLACK),
            [0.5, 0.367_680_318, 0.0],
            2e-6,
        );
    }

    /// A rendered pixel whose samples add up to premultiplied sRGB colour 0.5 at opacity 0.5.
    #[test]
    fn half_transparent_render_pixel_under_each_protocol() {
        // Ours: the renderer adds T·bg in sRGB: 0.5 + 0.5·1 = 1 on white.
        close(
            Protocol::StegoNgp.render_pixel([1.0; 3], 0.5, WHITE),
            [1.0; 3],
            0.0,
        );
        // instant-ngp on black: srgb(lin(0.5)) = 0.5 (the two exponents are inverses here).
        let ingp = Protocol::InstantNgp;
        close(ingp.render_pixel([0.5; 3], 0.5, BLACK), [0.5; 3], 1e-6);
        // Its blend in linear light, on white (what run.py would score if it used white):
        // lin(0.5) = 0.214041, + 0.5 = 0.714041, encoded 1.055·0.714041^(1/2.4) − 0.055 =
        // 0.861862, far from the sRGB blend's 1.
        close(
            ingp.render_pixel([0.5; 3], 0.5, WHITE),
            [0.861_861_6; 3],
            1e-6,
        );
        // --nerf_compatibility adds the background in sRGB: 0.5 + 0.5 = 1.
        close(
            Protocol::InstantNgpCompat.render_pixel([0.5; 3], 0.5, WHITE),
            [1.0; 3],
            1e-6,
        );
        // An empty render is the background itself under each.
        close(Protocol::StegoNgp.blank_pixel(WHITE), [1.0; 3], 0.0);
        close(ingp.blank_pixel(BLACK), [0.0; 3], 0.0);
    }

    #[test]
    fn scores_clip_both_images_under_instant_ngp() {
        // A render above 1 (an over-bright sample sum) and a negative one are clipped.
        let ingp = Protocol::InstantNgp;
        close(
            ingp.render_pixel([1.2, -0.1, 0.3], 1.0, BLACK),
            [1.0, 0.0, 0.3],
            1e-6,
        );
        close(
            ingp.truth_pixel([1.5, 0.0, 0.0, 1.0], BLACK),
            [1.0, 0.0, 0.0],
            0.0,
        );
    }
}
