//! Training images in compact storage, decoding (PNG, JPEG), area downscaling, PNG writing.
//!
//! Full-size images stay as the file gave them (RGBA8, sRGB, straight alpha), exactly what the
//! reference keeps on the GPU; reads decode sRGB through a LUT and premultiply. Downscaled
//! images are averages of linear premultiplied values, which 8-bit sRGB cannot hold without
//! a second rounding, so they are stored as f16 linear premultiplied RGBA.

use std::io::Cursor;
use std::path::Path;

use half::f16;

use super::color::{SRGB8_TO_LINEAR, linear_to_srgb, srgb_to_linear};
use crate::error::{Error, Result};

#[derive(Clone, Debug)]
enum Pixels {
    /// RGBA8, sRGB-encoded colour, straight (non-premultiplied) alpha.
    Srgb8(Vec<u8>),
    /// RGBA f16, linear colour premultiplied by alpha.
    LinearF16(Vec<f16>),
}

/// One image, row-major from the top-left pixel.
#[derive(Clone, Debug)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pixels: Pixels,
    has_alpha: bool,
}

impl Image {
    /// From RGBA8 sRGB straight-alpha bytes (`4·w·h` of them).
    pub fn from_rgba8(width: u32, height: u32, rgba: Vec<u8>) -> Result<Image> {
        if rgba.len() != 4 * width as usize * height as usize {
            return Err(Error::Other(format!(
                "Image::from_rgba8: {} bytes for {width}x{height}",
                rgba.len()
            )));
        }
        let has_alpha = rgba.chunks_exact(4).any(|p| p[3] != 255);
        Ok(Image {
            width,
            height,
            pixels: Pixels::Srgb8(rgba),
            has_alpha,
        })
    }

    /// From linear premultiplied RGBA floats (`4·w·h`), stored as f16.
    pub fn from_linear_premul(width: u32, height: u32, rgba: &[f32]) -> Result<Image> {
        if rgba.len() != 4 * width as usize * height as usize {
            return Err(Error::Other(format!(
                "Image::from_linear_premul: {} values for {width}x{height}",
                rgba.len()
            )));
        }
        let v: Vec<f16> = rgba.iter().map(|&x| f16::from_f32(x)).collect();
        let has_alpha = v.chunks_exact(4).any(|p| p[3] != f16::ONE);
        Ok(Image {
            width,
            height,
            pixels: Pixels::LinearF16(v),
            has_alpha,
        })
    }

    /// The stored RGBA8 bytes (sRGB, straight alpha) when the image is kept that way (not
    /// downscaled): what a GPU uploads as is.
    pub fn srgb8(&self) -> Option<&[u8]> {
        match &self.pixels {
            Pixels::Srgb8(p) => Some(p),
            Pixels::LinearF16(_) => None,
        }
    }

    /// Linear-light RGB premultiplied by alpha, and alpha. (x, y) must be inside the image.
    #[inline]
    pub fn linear_premul(&self, x: u32, y: u32) -> [f32; 4] {
        let i = 4 * (y as usize * self.width as usize + x as usize);
        match &self.pixels {
            Pixels::Srgb8(p) => {
                let lut = &*SRGB8_TO_LINEAR;
                let a = p[i + 3] as f32 * (1.0 / 255.0);
                [
                    lut[p[i] as usize] * a,
                    lut[p[i + 1] as usize] * a,
                    lut[p[i + 2] as usize] * a,
                    a,
                ]
            }
            Pixels::LinearF16(p) => [
                p[i].to_f32(),
                p[i + 1].to_f32(),
                p[i + 2].to_f32(),
                p[i + 3].to_f32(),
            ],
        }
    }

    /// The reference's target on background `bg` (sRGB in [0,1]):
    /// `srgb(lin_rgb·a + (1−a)·lin(bg))`.
    #[inline]
    pub fn target_on(&self, x: u32, y: u32, bg: [f32; 3]) -> [f32; 3] {
        let p = self.linear_premul(x, y);
        let t = 1.0 - p[3];
        [
            linear_to_srgb(p[0] + t * srgb_to_linear(bg[0])),
            linear_to_srgb(p[1] + t * srgb_to_linear(bg[1])),
            linear_to_srgb(p[2] + t * srgb_to_linear(bg[2])),
        ]
    }

    /// True when some pixel is not fully opaque.
    pub fn has_alpha(&self) -> bool {
        self.has_alpha
    }

    /// Bytes held by the pixel storage.
    pub fn storage_bytes(&self) -> usize {
        match &self.pixels {
            Pixels::Srgb8(p) => p.len(),
            Pixels::LinearF16(p) => 2 * p.len(),
        }
    }

    /// Integer area downscale by `n`: each output pixel is the mean of an n×n block of linear
    /// premultiplied values. Sizes not divisible by `n` are floored: the right/bottom
    /// remainder is dropped, so the top-left origin (and hence `cx/n`, `cy/n`) stays exact.
    pub fn downscale(&self, n: u32) -> Result<Image> {
        if n == 0 {
            return Err(Error::Config("downscale factor must be >= 1".into()));
        }
        if n == 1 {
            return Ok(self.clone());
        }
        let (w, h) = (self.width / n, self.height / n);
        if w == 0 || h == 0 {
            return Err(Error::Config(format!(
                "downscale {n} leaves nothing of a {}x{} image",
                self.width, self.height
            )));
        }
        let inv = 1.0 / (n * n) as f32;
        let mut out = Vec::with_capacity(4 * w as usize * h as usize);
        if let Pixels::Srgb8(p) = &self.pixels {
            // Hot path of dataset loading: one LUT borrow, row slices, no per-pixel dispatch.
            let lut = &*SRGB8_TO_LINEAR;
            let (n, w, stride) = (n as usize, w as usize, 4 * self.width as usize);
            let mut acc = vec![0.0f32; 4 * w];
            for oy in 0..h as usize {
                acc.fill(0.0);
                for y in oy * n..(oy + 1) * n {
                    let row = &p[y * stride..y * stride + 4 * n * w];
                    for (ox, block) in row.chunks_exact(4 * n).enumerate() {
                        let a = &mut acc[4 * ox..4 * ox + 4];
                        for q in block.chunks_exact(4) {
                            let al = q[3] as f32 * (1.0 / 255.0);
                            a[0] += lut[q[0] as usize] * al;
                            a[1] += lut[q[1] as usize] * al;
                            a[2] += lut[q[2] as usize] * al;
                            a[3] += al;
                        }
                    }
                }
                out.extend(acc.iter().map(|v| v * inv));
            }
            return Image::from_linear_premul(w as u32, h, &out);
        }
        for oy in 0..h {
            for ox in 0..w {
                let mut acc = [0.0f32; 4];
                for y in oy * n..(oy + 1) * n {
                    for x in ox * n..(ox + 1) * n {
                        let p = self.linear_premul(x, y);
                        for c in 0..4 {
                            acc[c] += p[c];
                        }
                    }
                }
                out.extend(acc.iter().map(|v| v * inv));
            }
        }
        Image::from_linear_premul(w, h, &out)
    }
}

/// Width and height from a PNG or JPEG header, without decoding pixels.
pub fn image_size(path: &Path) -> Result<(u32, u32)> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let reader = std::io::BufReader::new(file);
    if is_jpeg_path(path) {
        let mut dec = jpeg_decoder::Decoder::new(reader);
        dec.read_info()
            .map_err(|e| Error::format(path, format!("JPEG header: {e}")))?;
        let info = dec
            .info()
            .ok_or_else(|| Error::format(path, "JPEG header: no frame info"))?;
        Ok((info.width as u32, info.height as u32))
    } else {
        let dec = png::Decoder::new(reader);
        let r = dec
            .read_info()
            .map_err(|e| Error::format(path, format!("PNG header: {e}")))?;
        Ok(r.info().size())
    }
}

fn is_jpeg_path(path: &Path) -> bool {
    matches!(
        path.extension()
            .and_then(|e| e.to_str())
            .map(|e| e.to_ascii_lowercase())
            .as_deref(),
        Some("jpg" | "jpeg")
    )
}

/// Decodes a PNG or JPEG file (chosen by content, not extension) into RGBA8 sRGB straight
/// alpha, as stb_image does for the reference (16-bit PNGs are reduced to 8 bits).
pub fn decode_image_file(path: &Path) -> Result<Image> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    if bytes.starts_with(&[0x89, b'P', b'N', b'G']) {
        decode_png(path, &bytes)
    } else if bytes.starts_with(&[0xFF, 0xD8]) {
        decode_jpeg(path, &bytes)
    } else {
        Err(Error::format(
            path,
            "not a PNG or JPEG file (unsupported image format)",
        ))
    }
}

/// The largest image any loader takes: 2^28 pixels (16384²), 1 GiB as RGBA.
pub const MAX_IMAGE_PIXELS: u64 = 1 << 28;
/// Deflate's best ratio: a PNG's compressed data cannot hold more raw bytes than this many
/// times its own size.
const DEFLATE_MAX_RATIO: u64 = 1032;
/// A baseline or progressive JPEG spends at least a bit per 8×8 block of a component on
/// its DC coefficient: 512 pixels a byte at most.
const JPEG_MAX_PIXELS_PER_BYTE: u64 = 512;

/// Refuses a declared size the file cannot back, before anything is allocated for it: a
/// 100-byte header may say 65535×65535.
fn check_declared_size(path: &Path, what: &str, w: u32, h: u32, backed: u64) -> Result<()> {
    let pixels = w as u64 * h as u64;
    if pixels == 0 {
        return Err(Error::format(
            path,
            format!("{what}: {w}x{h}, an empty image"),
        ));
    }
    if pixels > MAX_IMAGE_PIXELS {
        return Err(Error::format(
            path,
            format!("{what}: {w}x{h} is more than the {MAX_IMAGE_PIXELS} pixels an image may have"),
        ));
    }
    if pixels > backed {
        return Err(Error::format(
            path,
            format!(
                "{what}: {w}x{h} pixels, more than the file's compressed data can hold (truncated or forged)"
            ),
        ));
    }
    Ok(())
}

fn decode_png(path: &Path, bytes: &[u8]) -> Result<Image> {
    let perr = |e: png::DecodingError| Error::format(path, format!("PNG decoding: {e}"));
    let mut dec = png::Decoder::new(Cursor::new(bytes));
    dec.set_transformations(png::Transformations::normalize_to_color8());
    let mut reader = dec.read_info().map_err(perr)?;
    {
        let info = reader.info();
        let (w, h) = info.size();
        // Raw scanline bytes the IHDR implies, against what deflate can expand the file to;
        // as pixels, so one check serves every bit depth.
        let raw = info.raw_row_length() as u64 * h as u64;
        let backed = (DEFLATE_MAX_RATIO * bytes.len() as u64 + 4096)
            .saturating_mul(w as u64 * h as u64)
            / raw.max(1);
        check_declared_size(path, "PNG header (IHDR)", w, h, backed)?;
    }
    let (color, _) = reader.output_color_type();
    use png::ColorType::*;
    let ch = match color {
        Grayscale => 1,
        GrayscaleAlpha => 2,
        Rgb => 3,
        Rgba => 4,
        Indexed => return Err(Error::format(path, "PNG palette was not expanded")),
    };
    let (w, h) = reader.info().size();
    let n = w as usize * h as usize;
    let mut rgba = Vec::new();
    let push = |row: &[u8], rgba: &mut Vec<u8>| {
        for p in row[..ch * w as usize].chunks_exact(ch) {
            match ch {
                1 => rgba.extend_from_slice(&[p[0], p[0], p[0], 255]),
                2 => rgba.extend_from_slice(&[p[0], p[0], p[0], p[1]]),
                3 => rgba.extend_from_slice(&[p[0], p[1], p[2], 255]),
                _ => rgba.extend_from_slice(p),
            }
        }
    };
    if reader.info().interlaced {
        // Adam7 passes are not rows of the image: the decoder assembles the frame.
        let size = reader
            .output_buffer_size()
            .ok_or_else(|| Error::format(path, "PNG too large"))?;
        let mut buf = vec![0u8; size];
        let info = reader.next_frame(&mut buf).map_err(perr)?;
        rgba.reserve_exact(4 * n);
        for row in buf[..info.line_size * h as usize].chunks_exact(info.line_size) {
            push(row, &mut rgba);
        }
    } else {
        // Row by row, so memory grows with the pixels the file really holds, not with the
        // size its header declares (a forged IHDR stops at the first missing row).
        while let Some(row) = reader.next_row().map_err(perr)? {
            push(row.data(), &mut rgba);
        }
    }
    if rgba.len() != 4 * n {
        return Err(Error::format(path, "PNG decoding: truncated pixel data"));
    }
    rgba.shrink_to_fit();
    Image::from_rgba8(w, h, rgba)
}

fn decode_jpeg(path: &Path, bytes: &[u8]) -> Result<Image> {
    let mut dec = jpeg_decoder::Decoder::new(Cursor::new(bytes));
    dec.read_info()
        .map_err(|e| Error::format(path, format!("JPEG header: {e}")))?;
    let info = dec
        .info()
        .ok_or_else(|| Error::format(path, "JPEG header: no frame info"))?;
    let backed = JPEG_MAX_PIXELS_PER_BYTE * bytes.len() as u64;
    check_declared_size(
        path,
        "JPEG header (SOF)",
        info.width as u32,
        info.height as u32,
        backed,
    )?;
    // The decoder's own planes (up to 4 components) stay within the same bound.
    dec.set_max_decoding_buffer_size((4 * backed.min(MAX_IMAGE_PIXELS)) as usize);
    let data = dec
        .decode()
        .map_err(|e| Error::format(path, format!("JPEG decoding: {e}")))?;
    let info = dec
        .info()
        .ok_or_else(|| Error::format(path, "JPEG decoding: no frame info"))?;
    let (w, h) = (info.width as u32, info.height as u32);
    let n = w as usize * h as usize;
    let mut rgba = Vec::with_capacity(4 * n);
    match info.pixel_format {
        jpeg_decoder::PixelFormat::RGB24 => {
            for p in data.chunks_exact(3).take(n) {
                rgba.extend_from_slice(&[p[0], p[1], p[2], 255]);
            }
        }
        jpeg_decoder::PixelFormat::L8 => {
            for &v in data.iter().take(n) {
                rgba.extend_from_slice(&[v, v, v, 255]);
            }
        }
        other => {
            return Err(Error::format(
                path,
                format!("JPEG pixel format {other:?} is not supported (only RGB and 8-bit grey)"),
            ));
        }
    }
    if rgba.len() != 4 * n {
        return Err(Error::format(path, "JPEG decoding: truncated pixel data"));
    }
    Image::from_rgba8(w, h, rgba)
}

/// A PNG of 8-bit pixels, grey (`channels` = 1), RGB (3) or RGBA (4), in memory: the one
/// encoder every writer of the workspace uses. `fast`: the encoder's fast compression (a
/// viewer's frames, a capture's staged photos), else its default.
pub fn png_bytes(
    w: u32,
    h: u32,
    channels: usize,
    data: &[u8],
    fast: bool,
) -> std::io::Result<Vec<u8>> {
    let color = match channels {
        1 => png::ColorType::Grayscale,
        3 => png::ColorType::Rgb,
        4 => png::ColorType::Rgba,
        n => {
            return Err(std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                format!("a PNG of {n} channels (1, 3 or 4 are written)"),
            ));
        }
    };
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, w, h);
    enc.set_color(color);
    enc.set_depth(png::BitDepth::Eight);
    if fast {
        enc.set_compression(png::Compression::Fast);
    }
    let mut writer = enc.write_header().map_err(std::io::Error::other)?;
    writer
        .write_image_data(data)
        .map_err(std::io::Error::other)?;
    writer.finish().map_err(std::io::Error::other)?;
    Ok(out)
}

fn encode_png(path: &Path, w: u32, h: u32, channels: usize, data: &[u8]) -> Result<()> {
    let bytes = png_bytes(w, h, channels, data, false).map_err(|e| Error::io(path, e))?;
    crate::util::write_atomic(path, &bytes)
}

#[inline]
fn to_u8(v: f32) -> u8 {
    // NaN maps to 0 (`as` saturates and sends NaN to 0).
    (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
}

/// Writes interleaved RGB values in [0,1] (clipped, rounded to 8 bits, no transfer function
/// applied: they are taken as sRGB) to a PNG, atomically.
pub fn save_png_rgb(path: &Path, w: u32, h: u32, rgb: &[f32]) -> Result<()> {
    if rgb.len() != 3 * w as usize * h as usize {
        return Err(Error::format(
            path,
            format!("save_png_rgb: {} values for {w}x{h}", rgb.len()),
        ));
    }
    let bytes: Vec<u8> = rgb.iter().map(|&v| to_u8(v)).collect();
    encode_png(path, w, h, 3, &bytes)
}

/// Writes a greyscale PNG of `v / max` clipped to [0,1] (depth or opacity pictures).
pub fn save_png_gray(path: &Path, w: u32, h: u32, v: &[f32], max: f32) -> Result<()> {
    if v.len() != w as usize * h as usize {
        return Err(Error::format(
            path,
            format!("save_png_gray: {} values for {w}x{h}", v.len()),
        ));
    }
    let inv = if max > 0.0 && max.is_finite() {
        1.0 / max
    } else {
        0.0
    };
    let bytes: Vec<u8> = v.iter().map(|&x| to_u8(x * inv)).collect();
    encode_png(path, w, h, 1, &bytes)
}

/// Reads a PNG as interleaved RGB floats in [0,1] (8-bit codes / 255, no transfer function;
/// any alpha channel is ignored).
pub fn load_png_rgb(path: &Path) -> Result<(u32, u32, Vec<f32>)> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    if !bytes.starts_with(&[0x89, b'P', b'N', b'G']) {
        return Err(Error::format(path, "not a PNG file"));
    }
    let img = decode_png(path, &bytes)?;
    let Pixels::Srgb8(p) = &img.pixels else {
        unreachable!("decode_png stores RGBA8")
    };
    let rgb = p
        .chunks_exact(4)
        .flat_map(|q| q[..3].iter().map(|&c| c as f32 / 255.0))
        .collect();
    Ok((img.width, img.height, rgb))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn premultiplied_read_and_target() {
        let img = Image::from_rgba8(2, 1, vec![255, 128, 0, 255, 255, 255, 255, 51]).unwrap();
        assert!(img.has_alpha());
        let p = img.linear_premul(0, 0);
        assert_eq!(p, [1.0, srgb_to_linear(128.0 / 255.0), 0.0, 1.0]);
        let q = img.linear_premul(1, 0);
        assert!((q[3] - 0.2).abs() < 1e-7 && (q[0] - 0.2).abs() < 1e-6);
        // White at alpha 0.2 on black: srgb(0.2).
        let t = img.target_on(1, 0, [0.0; 3]);
        assert!((t[0] - linear_to_srgb(0.2)).abs() < 1e-6);
        // On white background a white pixel stays white whatever its alpha.
        let t = img.target_on(1, 0, [1.0; 3]);
        assert!((t[1] - 1.0).abs() < 1e-4);
        // Opaque pixel ignores the background.
        assert_eq!(img.target_on(0, 0, [0.3; 3]), img.target_on(0, 0, [0.9; 3]));
        let opaque = Image::from_rgba8(1, 1, vec![1, 2, 3, 255]).unwrap();
        assert!(!opaque.has_alpha());
        assert!(Image::from_rgba8(2, 2, vec![0; 4]).is_err());
    }

    #[test]
    fn downscale_averages_premultiplied_linear() {
        // 2x2 block: opaque red, transparent (colour must not leak), half-alpha white, opaque
        // sRGB 128 grey. Expected mean of premultiplied linear values, worked out by hand:
        let g = srgb_to_linear(128.0 / 255.0);
        let a2 = 128.0 / 255.0;
        let img = Image::from_rgba8(
            2,
            2,
            vec![
                255, 0, 0, 255, /**/ 0, 255, 0, 0, //
                255, 255, 255, 128, /**/ 128, 128, 128, 255,
            ],
        )
        .unwrap();
        let d = img.downscale(2).unwrap();
        assert_eq!((d.width, d.height), (1, 1));
        let p = d.linear_premul(0, 0);
        let expect = [
            (1.0 + 0.0 + a2 + g) / 4.0,
            (0.0 + 0.0 + a2 + g) / 4.0,
            (0.0 + 0.0 + a2 + g) / 4.0,
            (1.0 + 0.0 + a2 + 1.0) / 4.0,
        ];
        for c in 0..4 {
            // f16 storage: relative precision 2^-11.
            assert!(
                (p[c] - expect[c]).abs() < 1e-3,
                "{c}: {} vs {}",
                p[c],
                expect[c]
            );
        }
        assert!(d.has_alpha());
        // Floor for sizes not divisible by n; f16 storage is 8 bytes per pixel.
        let big = Image::from_rgba8(5, 3, vec![255; 60]).unwrap();
        let d = big.downscale(2).unwrap();
        assert_eq!((d.width, d.height), (2, 1));
        assert_eq!(d.storage_bytes(), 2 * 8);
        assert!(!d.has_alpha());
        assert!(big.downscale(0).is_err());
        // The f16 path: halving twice equals quartering (up to f16 rounding).
        let px: Vec<u8> = (0..8 * 4 * 4).map(|i| (i * 37 % 256) as u8).collect();
        let img = Image::from_rgba8(8, 4, px).unwrap();
        let (a, b) = (
            img.downscale(4).unwrap(),
            img.downscale(2).unwrap().downscale(2).unwrap(),
        );
        assert_eq!((b.width, b.height), (2, 1));
        for x in 0..2 {
            let (p, q) = (a.linear_premul(x, 0), b.linear_premul(x, 0));
            for c in 0..4 {
                assert!((p[c] - q[c]).abs() < 2e-3, "{p:?} {q:?}");
            }
        }
        assert!(big.downscale(4).is_err());
    }

    #[test]
    fn png_round_trip_and_decoding() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.png");
        let rgb = [0.0, 0.5, 1.0, 2.0, -1.0, f32::NAN];
        save_png_rgb(&p, 2, 1, &rgb).unwrap();
        let (w, h, back) = load_png_rgb(&p).unwrap();
        assert_eq!((w, h), (2, 1));
        assert_eq!(back, vec![0.0, 128.0 / 255.0, 1.0, 1.0, 0.0, 0.0]);
        assert_eq!(image_size(&p).unwrap(), (2, 1));
        let img = decode_image_file(&p).unwrap();
        assert!(!img.has_alpha());
        assert_eq!(img.linear_premul(0, 0)[3], 1.0);

        let g = dir.path().join("g.png");
        save_png_gray(&g, 3, 1, &[0.0, 2.0, 8.0], 4.0).unwrap();
        let (_, _, back) = load_png_rgb(&g).unwrap();
        assert_eq!(back[3..6], [128.0 / 255.0; 3]);
        assert_eq!(back[6], 1.0);

        assert!(save_png_rgb(&p, 3, 1, &rgb).is_err());
        let bad = dir.path().join("bad.png");
        std::fs::write(&bad, b"hello").unwrap();
        let e = decode_image_file(&bad).unwrap_err().to_string();
        assert!(e.contains("bad.png"), "{e}");
    }
}
