//! Report writing: a table of rows as Markdown and JSON, and image grids as PNG.

use ngp::data::save_png_rgb;
use ngp::error::Result;
use ngp::util::write_atomic;
use serde_json::{Map, Value};
use std::path::Path;

/// A titled table whose rows are JSON objects sharing their keys.
#[derive(Clone, Debug, Default)]
pub struct Table {
    pub title: String,
    pub rows: Vec<Map<String, Value>>,
}

impl Table {
    pub fn new(title: &str) -> Self {
        Table {
            title: title.into(),
            rows: Vec::new(),
        }
    }

    pub fn push(&mut self, row: Value) {
        if let Value::Object(m) = row {
            self.rows.push(m);
        }
    }

    pub fn markdown(&self) -> String {
        let mut s = format!("### {}\n\n", self.title);
        if self.rows.is_empty() {
            return s + "(no rows)\n";
        }
        // Rows may grow columns (multi-hidden adds one per hidden scene): every key of
        // every row, in order of first appearance.
        let mut cols: Vec<&String> = Vec::new();
        for r in &self.rows {
            for k in r.keys() {
                if !cols.contains(&k) {
                    cols.push(k);
                }
            }
        }
        s += &format!(
            "| {} |\n",
            cols.iter()
                .map(|c| c.as_str())
                .collect::<Vec<_>>()
                .join(" | ")
        );
        s += &format!("|{}\n", "---|".repeat(cols.len()));
        for r in &self.rows {
            let cells: Vec<String> = cols
                .iter()
                .map(|c| match r.get(*c) {
                    Some(Value::Number(n)) => match n.as_f64() {
                        // Four places below 1 (SSIM, LPIPS, AUC), three above (dB, s);
                        // two significant digits below 1e-3 (p-values), where four places
                        // would print 0.0000.
                        Some(f) if n.is_f64() && f != 0.0 && f.abs() < 1e-3 => format!("{f:.1e}"),
                        Some(f) if n.is_f64() && f.abs() < 1.0 => format!("{f:.4}"),
                        Some(f) if n.is_f64() => format!("{f:.3}"),
                        _ => n.to_string(),
                    },
                    Some(Value::String(t)) => t.clone(),
                    Some(Value::Null) => "—".into(),
                    Some(v) => v.to_string(),
                    None => String::new(),
                })
                .collect();
            s += &format!("| {} |\n", cells.join(" | "));
        }
        s
    }
}

/// An experiment's report: prose, tables and the figures it wrote.
#[derive(Clone, Debug, Default)]
pub struct Report {
    pub name: String,
    pub setup: Value,
    pub notes: Vec<String>,
    pub tables: Vec<Table>,
    pub figures: Vec<(String, String)>,
    /// Sentences about this run alone (its wall time, its machine), after the notes.
    pub run_notes: Vec<String>,
    /// The setup's and the tables' fields that are wall-clock or host figures: they differ
    /// between two runs of the same models, where every other figure is the same to the
    /// bit (on the CPU). Named in the report, and blanked by [`comparable`].
    pub wall_clock: Vec<String>,
    /// Jobs of a plan whose models a partial report lacks (`experiment collect --partial`):
    /// their figures are empty.
    pub missing_jobs: Vec<String>,
}

impl Report {
    pub fn write(&self, dir: &Path) -> Result<()> {
        let mut md = format!("# Experiment: {}\n\n", self.name);
        if !self.missing_jobs.is_empty() {
            md += &format!(
                "**Partial report**: {} jobs of its plan had not finished, and their \
                 models' figures are empty: {}.\n\n",
                self.missing_jobs.len(),
                self.missing_jobs.join(", ")
            );
        }
        md += &format!("Setup: `{}`\n\n", self.setup);
        for n in self.notes.iter().chain(&self.run_notes) {
            md += &format!("{n}\n\n");
        }
        for t in &self.tables {
            md += &t.markdown();
            md += "\n";
        }
        for (file, caption) in &self.figures {
            md += &format!("![{caption}]({file})\n\n*{caption}*\n\n");
        }
        if !self.wall_clock.is_empty() {
            md += &format!(
                "Wall-clock and host figures, which differ between runs of the same models: \
                 {}; and the sentences about this run.\n",
                self.wall_clock
                    .iter()
                    .map(|k| format!("`{k}`"))
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
        write_atomic(&dir.join("report.md"), md.as_bytes())?;
        let mut json = serde_json::json!({
            "experiment": self.name,
            "setup": self.setup,
            "notes": self.notes,
            "tables": self.tables.iter().map(|t| serde_json::json!({"title": t.title, "rows": t.rows})).collect::<Vec<_>>(),
            "figures": self.figures.iter().map(|(f, c)| serde_json::json!({"file": f, "caption": c})).collect::<Vec<_>>(),
            "run_notes": self.run_notes,
            "wall_clock": self.wall_clock,
        });
        if !self.missing_jobs.is_empty() {
            json["partial"] = serde_json::json!({"missing_jobs": self.missing_jobs});
        }
        write_atomic(
            &dir.join("report.json"),
            serde_json::to_string_pretty(&json)
                .unwrap_or_default()
                .as_bytes(),
        )
    }
}

/// A written `report.json` with what differs between two runs of the same models taken
/// out: the fields it names as wall-clock blanked (in the setup and in every row), its
/// sentences about the run removed. Two such reports of the same models are equal.
pub fn comparable(report: &Value) -> Value {
    let mut v = report.clone();
    let names: Vec<String> = v["wall_clock"]
        .as_array()
        .map(|a| {
            a.iter()
                .filter_map(|s| s.as_str().map(String::from))
                .collect()
        })
        .unwrap_or_default();
    let blank = |o: &mut Map<String, Value>| {
        for n in &names {
            if let Some(x) = o.get_mut(n) {
                *x = Value::String("(wall clock)".into());
            }
        }
    };
    if let Some(o) = v["setup"].as_object_mut() {
        blank(o);
    }
    if let Some(tables) = v["tables"].as_array_mut() {
        for t in tables {
            for r in t["rows"].as_array_mut().into_iter().flatten() {
                if let Some(o) = r.as_object_mut() {
                    blank(o);
                }
            }
        }
    }
    if let Some(o) = v.as_object_mut() {
        o.remove("run_notes");
    }
    v
}

/// Tiles equally sized RGB images row by row, `cols` per row, with a 2-pixel grey gutter.
pub fn save_grid(path: &Path, tiles: &[Vec<f32>], w: u32, h: u32, cols: usize) -> Result<()> {
    let cols = cols.max(1).min(tiles.len().max(1));
    let rows = tiles.len().div_ceil(cols);
    let g = 2u32;
    let gw = cols as u32 * (w + g) - g;
    let gh = rows as u32 * (h + g) - g;
    let mut out = vec![0.5f32; (gw * gh * 3) as usize];
    for (k, t) in tiles.iter().enumerate() {
        let (cx, cy) = ((k % cols) as u32 * (w + g), (k / cols) as u32 * (h + g));
        for y in 0..h {
            for x in 0..w {
                let src = ((y * w + x) * 3) as usize;
                let dst = (((cy + y) * gw + cx + x) * 3) as usize;
                if src + 3 <= t.len() {
                    out[dst..dst + 3].copy_from_slice(&t[src..src + 3]);
                }
            }
        }
    }
    save_png_rgb(path, gw, gh, &out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn comparable_blanks_the_wall_clock_fields_alone() {
        let d = tempfile::tempdir().unwrap();
        let mut t = Table::new("t");
        t.push(serde_json::json!({"psnr": 30.5, "train_s": 1.25}));
        let report = |secs: f64, psnr: f64| {
            let mut t = t.clone();
            t.rows[0].insert("train_s".into(), serde_json::json!(secs));
            t.rows[0].insert("psnr".into(), serde_json::json!(psnr));
            let r = Report {
                name: "x".into(),
                setup: serde_json::json!({"threads": 2, "steps": 10}),
                tables: vec![t],
                run_notes: vec![format!("took {secs} s")],
                wall_clock: vec!["train_s".into(), "threads".into()],
                ..Default::default()
            };
            r.write(d.path()).unwrap();
            let md = std::fs::read_to_string(d.path().join("report.md")).unwrap();
            assert!(md.contains("`train_s`, `threads`"), "{md}");
            let text = std::fs::read(d.path().join("report.json")).unwrap();
            serde_json::from_slice::<Value>(&text).unwrap()
        };
        let (a, b, c) = (report(1.0, 30.5), report(9.0, 30.5), report(1.0, 30.25));
        assert_ne!(a, b);
        assert_eq!(comparable(&a), comparable(&b), "times differ, nothing else");
        assert_ne!(comparable(&a), comparable(&c), "a score is never blanked");
    }

    #[test]
    fn markdown_table_has_header_and_rows() {
        let mut t = Table::new("x");
        t.push(serde_json::json!({"a": 1, "b": 2.5}));
        t.push(serde_json::json!({"a": 3, "b": "z"}));
        let md = t.markdown();
        assert!(md.contains("| a | b |"));
        assert!(md.contains("| 1 | 2.500 |"));
        assert!(md.contains("| 3 | z |"));
        // A later row's extra column gets a header; earlier rows leave it empty.
        t.push(serde_json::json!({"a": 4, "b": 1, "c": 5}));
        let md = t.markdown();
        assert!(md.contains("| a | b | c |"), "{md}");
        assert!(md.contains("|---|---|---|\n"));
        assert!(md.contains("| 1 | 2.500 |  |"));
        assert!(md.contains("| 4 | 1 | 5 |"));
        // LPIPS-sized values keep a fourth place.
        t.push(serde_json::json!({"a": 0.01234, "b": -0.5}));
        assert!(t.markdown().contains("| 0.0123 | -0.5000 |"));
        // p-values below 1e-3 keep two significant digits; zero stays a number of places.
        t.push(serde_json::json!({"a": 5.4e-6, "b": 0.0}));
        assert!(
            t.markdown().contains("| 5.4e-6 | 0.0000 |"),
            "{}",
            t.markdown()
        );
    }
}
