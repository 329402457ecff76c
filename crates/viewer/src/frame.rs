//! 8-bit RGB frames: from the renderer's floats, labelled with a small bitmap font, put side
//! by side. Labels are drawn, not typeset: no font file to ship or find.

/// An interleaved 8-bit RGB image.
#[derive(Clone, Debug, PartialEq)]
pub struct Rgb8 {
    pub width: u32,
    pub height: u32,
    pub data: Vec<u8>,
}

impl Rgb8 {
    pub fn new(width: u32, height: u32, fill: [u8; 3]) -> Self {
        let n = width as usize * height as usize;
        let mut data = Vec::with_capacity(3 * n);
        for _ in 0..n {
            data.extend_from_slice(&fill);
        }
        Rgb8 {
            width,
            height,
            data,
        }
    }

    /// Renderer floats in [0, 1] (taken as sRGB codes, as `render` writes its PNGs).
    pub fn from_floats(width: u32, height: u32, rgb: &[f32]) -> Self {
        debug_assert_eq!(rgb.len(), 3 * width as usize * height as usize);
        let data = rgb
            .iter()
            .map(|&v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8)
            .collect();
        Rgb8 {
            width,
            height,
            data,
        }
    }

    fn put(&mut self, x: u32, y: u32, c: [u8; 3]) {
        if x < self.width && y < self.height {
            let i = 3 * (y as usize * self.width as usize + x as usize);
            self.data[i..i + 3].copy_from_slice(&c);
        }
    }

    /// Copies `src` with its top-left corner at (x, y), clipped.
    pub fn blit(&mut self, src: &Rgb8, x: u32, y: u32) {
        for sy in 0..src.height {
            let ty = y + sy;
            if ty >= self.height {
                break;
            }
            let w = src.width.min(self.width.saturating_sub(x)) as usize;
            let s = 3 * (sy as usize * src.width as usize);
            let t = 3 * (ty as usize * self.width as usize + x as usize);
            self.data[t..t + 3 * w].copy_from_slice(&src.data[s..s + 3 * w]);
        }
    }

    /// Writes `text` (upper-cased; unknown characters as '?') at (x, y) in a box of the
    /// background colour, each font pixel `scale`×`scale`.
    pub fn label(&mut self, text: &str, x: u32, y: u32, scale: u32, fg: [u8; 3], bg: [u8; 3]) {
        let n = text.chars().count() as u32;
        let (w, h) = (n * 6 * scale + scale, 9 * scale);
        for yy in y..y + h {
            for xx in x..x + w {
                self.put(xx, yy, bg);
            }
        }
        for (k, ch) in text.chars().enumerate() {
            let g = glyph(ch);
            let gx = x + scale + k as u32 * 6 * scale;
            for (row, bits) in g.iter().enumerate() {
                for col in 0..5 {
                    if bits >> (4 - col) & 1 == 1 {
                        for dy in 0..scale {
                            for dx in 0..scale {
                                self.put(
                                    gx + col * scale + dx,
                                    y + scale + row as u32 * scale + dy,
                                    fg,
                                );
                            }
                        }
                    }
                }
            }
        }
    }

    /// Same-size panels side by side, each with its label in the top-left corner, separated
    /// by `gap` pixels of black; the width rounded up to even (H.264's 4:2:0 needs it).
    pub fn side_by_side(panels: &[(&Rgb8, &str)], gap: u32) -> Rgb8 {
        let (w, h) = panels.first().map_or((0, 0), |(p, _)| (p.width, p.height));
        let n = panels.len() as u32;
        let total = (n * w + n.saturating_sub(1) * gap).next_multiple_of(2);
        let mut out = Rgb8::new(total, h.next_multiple_of(2), [0, 0, 0]);
        let scale = (h / 120).clamp(1, 4);
        for (i, (p, text)) in panels.iter().enumerate() {
            let x = i as u32 * (w + gap);
            out.blit(p, x, 0);
            out.label(text, x + scale, scale, scale, [255, 255, 255], [0, 0, 0]);
        }
        out
    }

    /// The same image with odd sides padded by one repeated row or column (4:2:0 video needs
    /// even sides).
    pub fn even(&self) -> Rgb8 {
        let (w, h) = (
            self.width.next_multiple_of(2),
            self.height.next_multiple_of(2),
        );
        if (w, h) == (self.width, self.height) {
            return self.clone();
        }
        let mut out = Rgb8::new(w, h, [0, 0, 0]);
        for y in 0..h {
            for x in 0..w {
                let (sx, sy) = (x.min(self.width - 1), y.min(self.height - 1));
                let i = 3 * (sy as usize * self.width as usize + sx as usize);
                out.put(x, y, [self.data[i], self.data[i + 1], self.data[i + 2]]);
            }
        }
        out
    }

    /// A PNG file's 8-bit RGB (what `--frames-dir` and `render` write; alpha ignored).
    pub fn load_png(path: &std::path::Path) -> ngp::error::Result<Rgb8> {
        let (w, h, rgb) = ngp::data::load_png_rgb(path)?;
        Ok(Rgb8::from_floats(w, h, &rgb))
    }

    /// PNG bytes (fast compression: the viewer sends one per frame).
    pub fn png(&self) -> Vec<u8> {
        // Encoding into memory cannot fail for a well-formed image.
        ngp::data::png_bytes(self.width, self.height, 3, &self.data, true).unwrap_or_default()
    }

    /// PSNR (dB) against another image of the same size, over 8-bit codes.
    pub fn psnr(&self, other: &Rgb8) -> f64 {
        assert_eq!((self.width, self.height), (other.width, other.height));
        let se: f64 = self
            .data
            .iter()
            .zip(&other.data)
            .map(|(&a, &b)| {
                let d = (a as f64 - b as f64) / 255.0;
                d * d
            })
            .sum();
        let mse = se / self.data.len() as f64;
        if mse == 0.0 {
            f64::INFINITY
        } else {
            -10.0 * mse.log10()
        }
    }

    /// PSNR (dB) of this image after BT.601 limited-range 4:2:0 and back (chroma averaged
    /// over each 2×2 block and repeated) with no compression: the most any 4:2:0 video of
    /// it, such as an H.264 MP4, can keep.
    pub fn chroma_420_psnr(&self) -> f64 {
        let (w, h) = (self.width as usize / 2 * 2, self.height as usize / 2 * 2);
        let px = |x: usize, y: usize| {
            let i = 3 * (y * self.width as usize + x);
            bt601::to_ycbcr([
                self.data[i] as f32,
                self.data[i + 1] as f32,
                self.data[i + 2] as f32,
            ])
        };
        let mut out = self.clone();
        for by in 0..h / 2 {
            for bx in 0..w / 2 {
                let quad =
                    [(0, 0), (1, 0), (0, 1), (1, 1)].map(|(dx, dy)| px(2 * bx + dx, 2 * by + dy));
                let cb = quad.iter().map(|q| q[1]).sum::<f32>() / 4.0;
                let cr = quad.iter().map(|q| q[2]).sum::<f32>() / 4.0;
                for (k, (dx, dy)) in [(0, 0), (1, 0), (0, 1), (1, 1)].into_iter().enumerate() {
                    let i = 3 * ((2 * by + dy) * self.width as usize + 2 * bx + dx);
                    let rgb = bt601::to_rgb([quad[k][0], cb, cr]);
                    for (o, v) in out.data[i..i + 3].iter_mut().zip(rgb) {
                        *o = bt601::code(v);
                    }
                }
            }
        }
        out.psnr(self)
    }

    /// The `w`×`h` region at (x, y).
    pub fn crop(&self, x: u32, y: u32, w: u32, h: u32) -> Rgb8 {
        let mut out = Rgb8::new(w, h, [0, 0, 0]);
        for yy in 0..h {
            let s = 3 * ((y + yy) as usize * self.width as usize + x as usize);
            let t = 3 * (yy as usize * w as usize);
            out.data[t..t + 3 * w as usize].copy_from_slice(&self.data[s..s + 3 * w as usize]);
        }
        out
    }
}

/// BT.601 limited-range Y′CbCr, the colour space our videos are encoded in and say they are.
pub(crate) mod bt601 {
    /// (Y, Cb, Cr) codes, offsets included, of 8-bit R′G′B′ codes.
    pub fn to_ycbcr(p: [f32; 3]) -> [f32; 3] {
        let dot = |k: [f32; 3]| k[0] * p[0] + k[1] * p[1] + k[2] * p[2];
        [
            16.0 + dot([0.2578125, 0.50390625, 0.09765625]),
            128.0 + dot([-0.1484375, -0.2890625, 0.4375]),
            128.0 + dot([0.4375, -0.3671875, -0.0703125]),
        ]
    }

    /// R′G′B′ codes of (Y, Cb, Cr) codes.
    pub fn to_rgb([y, cb, cr]: [f32; 3]) -> [f32; 3] {
        let (l, u, v) = (1.164_383_6 * (y - 16.0), cb - 128.0, cr - 128.0);
        [
            l + 1.596_026_8 * v,
            l - 0.391_762_3 * u - 0.812_967_6 * v,
            l + 2.017_232_1 * u,
        ]
    }

    /// The nearest 8-bit code (the codec crate's own conversions truncate, a bias of about
    /// one code per channel that costs ~1 dB on a frame).
    pub fn code(v: f32) -> u8 {
        (v + 0.5).clamp(0.0, 255.0) as u8
    }
}

/// 5×7 glyphs, a row per byte, the leftmost pixel in bit 4.
fn glyph(c: char) -> [u8; 7] {
    match c.to_ascii_uppercase() {
        'A' => [0x0E, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'B' => [0x1E, 0x11, 0x11, 0x1E, 0x11, 0x11, 0x1E],
        'C' => [0x0E, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0E],
        'D' => [0x1E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x1E],
        'E' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x1F],
        'F' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x10],
        'G' => [0x0E, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0F],
        'H' => [0x11, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'I' => [0x0E, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E],
        'J' => [0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0C],
        'K' => [0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11],
        'L' => [0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1F],
        'M' => [0x11, 0x1B, 0x15, 0x15, 0x11, 0x11, 0x11],
        'N' => [0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11],
        'O' => [0x0E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'P' => [0x1E, 0x11, 0x11, 0x1E, 0x10, 0x10, 0x10],
        'Q' => [0x0E, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0D],
        'R' => [0x1E, 0x11, 0x11, 0x1E, 0x14, 0x12, 0x11],
        'S' => [0x0F, 0x10, 0x10, 0x0E, 0x01, 0x01, 0x1E],
        'T' => [0x1F, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04],
        'U' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'V' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x0A, 0x04],
        'W' => [0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0A],
        'X' => [0x11, 0x11, 0x0A, 0x04, 0x0A, 0x11, 0x11],
        'Y' => [0x11, 0x11, 0x11, 0x0A, 0x04, 0x04, 0x04],
        'Z' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1F],
        '0' => [0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E],
        '1' => [0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E],
        '2' => [0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F],
        '3' => [0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E],
        '4' => [0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02],
        '5' => [0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E],
        '6' => [0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E],
        '7' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08],
        '8' => [0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E],
        '9' => [0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C],
        ' ' => [0; 7],
        '.' => [0, 0, 0, 0, 0, 0x0C, 0x0C],
        ',' => [0, 0, 0, 0, 0x0C, 0x04, 0x08],
        ':' => [0, 0x0C, 0x0C, 0, 0x0C, 0x0C, 0],
        '-' => [0, 0, 0, 0x1F, 0, 0, 0],
        '+' => [0, 0x04, 0x04, 0x1F, 0x04, 0x04, 0],
        '/' => [0, 0x01, 0x02, 0x04, 0x08, 0x10, 0],
        '(' => [0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02],
        ')' => [0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08],
        '=' => [0, 0, 0x1F, 0, 0x1F, 0, 0],
        '_' => [0, 0, 0, 0, 0, 0, 0x1F],
        _ => [0x0E, 0x11, 0x01, 0x02, 0x04, 0, 0x04],
    }
}

/// Black pixels between side-by-side panels.
pub const GAP: u32 = 4;

/// The size of a video's frames of `panels` renders of `width`×`height` each: side by side,
/// [`GAP`] apart, as [`render_frame`] lays them out, each side rounded up to even (4:2:0
/// video needs even sides; [`Rgb8::even`] pads a single render to it).
pub fn video_frame_size(panels: u32, width: u32, height: u32) -> (u32, u32) {
    let w = panels * width + panels.saturating_sub(1) * GAP;
    (w.next_multiple_of(2), height.next_multiple_of(2))
}

/// One frame at `camera`: the one renderer's image, or each renderer's side by side under
/// its label (`labels`, one a renderer).
pub fn render_frame(
    renderers: &mut [Box<dyn ngp::render::RenderBackend + '_>],
    labels: &[&str],
    camera: &ngp::camera::Camera,
    opts: &ngp::render::image::RenderOptions,
) -> ngp::error::Result<Rgb8> {
    let mut panels = Vec::with_capacity(renderers.len());
    for r in renderers.iter_mut() {
        let img = r.render(camera, opts)?;
        panels.push(Rgb8::from_floats(img.width, img.height, &img.rgb));
    }
    if labels.is_empty() {
        return Ok(panels.pop().expect("one renderer"));
    }
    let labelled: Vec<(&Rgb8, &str)> = panels.iter().zip(labels.iter().copied()).collect();
    Ok(Rgb8::side_by_side(&labelled, GAP))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn video_frame_size_is_the_side_by_side_frame_evened() {
        for (w, h) in [(40, 30), (41, 31), (1, 1)] {
            let p = Rgb8::new(w, h, [0, 0, 0]);
            let s = Rgb8::side_by_side(&[(&p, "A"), (&p, "B"), (&p, "C")], GAP);
            assert_eq!(video_frame_size(3, w, h), (s.width, s.height));
            assert_eq!(video_frame_size(1, w, h), (p.even().width, p.even().height));
        }
    }

    #[test]
    fn side_by_side_keeps_each_panel_and_labels_it() {
        let a = Rgb8::new(40, 30, [200, 10, 10]);
        let b = Rgb8::new(40, 30, [10, 200, 10]);
        let c = Rgb8::new(40, 30, [10, 10, 200]);
        let s = Rgb8::side_by_side(&[(&a, "COVER"), (&b, "KEY"), (&c, "WRONG")], 3);
        assert_eq!((s.width, s.height), (126, 30));
        // Below the labels each panel is its own colour.
        for (i, p) in [&a, &b, &c].into_iter().enumerate() {
            let region = s.crop(i as u32 * 43, 15, 40, 15);
            assert_eq!(region, p.crop(0, 15, 40, 15));
        }
        // The label wrote white pixels into the first panel.
        let top = s.crop(0, 0, 40, 10);
        assert!(top.data.chunks(3).any(|p| p == [255, 255, 255]));
    }

    #[test]
    fn even_pads_odd_sides() {
        let a = Rgb8::new(5, 3, [1, 2, 3]);
        let e = a.even();
        assert_eq!((e.width, e.height), (6, 4));
        assert!(e.data.chunks(3).all(|p| p == [1, 2, 3]));
    }

    #[test]
    fn png_decodes_to_the_same_pixels() {
        let mut a = Rgb8::new(7, 5, [9, 8, 7]);
        a.label("A1", 0, 0, 1, [255, 0, 0], [0, 0, 255]);
        let bytes = a.png();
        let dec = png::Decoder::new(std::io::Cursor::new(bytes));
        let mut r = dec.read_info().unwrap();
        let mut buf = vec![0; r.output_buffer_size().unwrap()];
        r.next_frame(&mut buf).unwrap();
        assert_eq!(buf, a.data);
    }
}
