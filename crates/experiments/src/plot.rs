//! Line plots as PNG, drawn here (a report's curves need no plotting library): panels of
//! series over categorical x positions, labelled with the synth crate's 5×7 bitmap font.

use ngp::data::save_png_rgb;
use ngp::error::Result;
use std::path::Path;
use synth::font::{GLYPH_H, GLYPH_W, glyph};

/// One line of a panel: its label, colour, whether dashed, and a y value (or a gap) per x.
pub struct Series {
    pub label: String,
    pub colour: [f32; 3],
    pub dashed: bool,
    pub ys: Vec<Option<f64>>,
}

/// One panel: a title, the x positions' labels, and its series.
pub struct Panel {
    pub title: String,
    pub xs: Vec<String>,
    pub series: Vec<Series>,
}

const PW: usize = 300;
const PH: usize = 200;
const MARGIN: usize = 34;
const TOP: usize = 16;
const BOTTOM: usize = 14;

struct Canvas {
    w: usize,
    h: usize,
    rgb: Vec<f32>,
}

impl Canvas {
    fn put(&mut self, x: i64, y: i64, c: [f32; 3]) {
        if x >= 0 && y >= 0 && (x as usize) < self.w && (y as usize) < self.h {
            let i = (y as usize * self.w + x as usize) * 3;
            self.rgb[i..i + 3].copy_from_slice(&c);
        }
    }

    fn text(&mut self, x: usize, y: usize, s: &str, c: [f32; 3]) {
        for (k, ch) in s.chars().enumerate() {
            let Some(rows) = glyph(ch) else { continue };
            for (gy, row) in rows.iter().enumerate() {
                for (gx, b) in row.bytes().enumerate() {
                    if b == b'#' {
                        let px = x + k * (GLYPH_W + 1) + gx;
                        self.put(px as i64, (y + gy) as i64, c);
                    }
                }
            }
        }
    }

    /// A line two pixels wide; `dashed` draws 6 of every 10 pixels.
    fn line(&mut self, a: (f64, f64), b: (f64, f64), c: [f32; 3], dashed: bool) {
        let n = ((b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil() as usize).max(1);
        for i in 0..=n {
            if dashed && i % 10 >= 6 {
                continue;
            }
            let t = i as f64 / n as f64;
            let (x, y) = (a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t);
            for (dx, dy) in [(0, 0), (1, 0), (0, 1)] {
                self.put(x.round() as i64 + dx, y.round() as i64 + dy, c);
            }
        }
    }
}

/// Draws `panels` side by side, `cols` a row, each with its y axis from `y_range` (ticks
/// every `y_tick`), a legend under the title, and saves the PNG.
pub fn save_panels(
    path: &Path,
    panels: &[Panel],
    cols: usize,
    y_range: (f64, f64),
    y_tick: f64,
) -> Result<()> {
    let cols = cols.max(1).min(panels.len().max(1));
    let rows = panels.len().div_ceil(cols);
    let legend_rows = panels.first().map_or(0, |p| p.series.len());
    let legend_h = legend_rows * (GLYPH_H + 3) + 4;
    let cell_h = TOP + legend_h + PH + BOTTOM;
    let mut c = Canvas {
        w: cols * (MARGIN + PW + 10),
        h: rows * cell_h,
        rgb: vec![1.0; cols * (MARGIN + PW + 10) * rows * cell_h * 3],
    };
    let grey = [0.6, 0.6, 0.6];
    let black = [0.0, 0.0, 0.0];
    let (y0, y1) = y_range;
    for (k, p) in panels.iter().enumerate() {
        let ox = (k % cols) * (MARGIN + PW + 10) + MARGIN;
        let oy = (k / cols) * cell_h;
        c.text(ox, oy + 4, &p.title, black);
        for (i, s) in p.series.iter().enumerate() {
            let ly = oy + TOP + i * (GLYPH_H + 3);
            c.line(
                (ox as f64, ly as f64 + 3.0),
                (ox as f64 + 16.0, ly as f64 + 3.0),
                s.colour,
                s.dashed,
            );
            c.text(ox + 22, ly, &s.label, black);
        }
        let top = oy + TOP + legend_h;
        let to_y = |v: f64| top as f64 + (1.0 - ((v - y0) / (y1 - y0)).clamp(0.0, 1.0)) * PH as f64;
        let n = p.xs.len().max(1);
        let to_x = |i: usize| ox as f64 + (i as f64 + 0.5) * PW as f64 / n as f64;
        // Axes and the y ticks' grid.
        let mut v = y0;
        while v <= y1 + 1e-9 {
            let y = to_y(v);
            c.line(
                (ox as f64, y),
                ((ox + PW) as f64, y),
                [0.9, 0.9, 0.9],
                false,
            );
            c.text(
                ox - MARGIN + 2,
                y as usize - GLYPH_H / 2,
                &format!("{v:.0}"),
                grey,
            );
            v += y_tick;
        }
        c.line(
            (ox as f64, top as f64),
            (ox as f64, (top + PH) as f64),
            grey,
            false,
        );
        for (i, x) in p.xs.iter().enumerate() {
            let label: String = x.chars().take(PW / n / (GLYPH_W + 1)).collect();
            let lx = (to_x(i) as usize).saturating_sub(label.len() * (GLYPH_W + 1) / 2);
            c.text(lx, top + PH + 4, &label, grey);
        }
        for s in &p.series {
            let pts: Vec<(f64, f64)> =
                s.ys.iter()
                    .enumerate()
                    .filter_map(|(i, y)| y.map(|y| (to_x(i), to_y(y))))
                    .collect();
            for w in pts.windows(2) {
                c.line(w[0], w[1], s.colour, s.dashed);
            }
            for &(x, y) in &pts {
                for dx in -2..=2 {
                    for dy in -2..=2 {
                        c.put(x.round() as i64 + dx, y.round() as i64 + dy, s.colour);
                    }
                }
            }
        }
    }
    save_png_rgb(path, c.w as u32, c.h as u32, &c.rgb)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_plot_draws_its_series_where_their_values_are() {
        let d = tempfile::tempdir().unwrap();
        let path = d.path().join("p.png");
        let panel = Panel {
            title: "noise".into(),
            xs: vec!["0".into(), "1".into()],
            series: vec![Series {
                label: "hidden".into(),
                colour: [1.0, 0.0, 0.0],
                dashed: false,
                ys: vec![Some(40.0), Some(10.0)],
            }],
        };
        save_panels(&path, &[panel], 1, (10.0, 40.0), 10.0).unwrap();
        let img = ngp::data::load_png_rgb(&path).unwrap();
        let (w, rgb) = (img.0 as usize, &img.2);
        let red = |x: usize, y: usize| {
            let i = (y * w + x) * 3;
            rgb[i] > 0.9 && rgb[i + 1] < 0.1
        };
        // The first point (40 dB) is at the panel's top, the second at its bottom.
        let legend_h = GLYPH_H + 3 + 4;
        let top = TOP + legend_h;
        let (x0, x1) = (MARGIN + PW / 4, MARGIN + 3 * PW / 4);
        assert!(red(x0, top), "the first point at the top");
        assert!(red(x1, top + PH), "the second at the bottom");
        assert!(red((x0 + x1) / 2, top + PH / 2), "the line between them");
    }
}
