//! `stegongp detect MODEL [--json] [--detector FILE]`: what an analyst can measure in a model
//! file alone (no images, no key), and the combined detector's score.

use anyhow::{Context, Result};
use std::path::PathBuf;
use stegongp::steganalysis::{Analysis, Detector, NEAR_ZERO, analyse_file};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Model file (.ingp or .msgpack)
    pub model: PathBuf,
    /// Print the full analysis, the features and the score as JSON
    #[arg(long)]
    pub json: bool,
    /// Detector to score with (JSON, as `experiment detectability` writes it); default: the
    /// built-in one
    #[arg(long)]
    pub detector: Option<PathBuf>,
}

fn verdict(score: f64) -> &'static str {
    if score >= 0.5 {
        "looks like a stego model (a hidden scene is more likely than not)"
    } else {
        "looks like a plain model"
    }
}

pub fn run(args: Args) -> Result<()> {
    let detector = match &args.detector {
        Some(p) => Detector::load(p)?,
        None => Detector::embedded().context("the built-in detector")?,
    };
    let a = analyse_file(&args.model)?;
    let features = a.features();
    let score = detector.score(&features);
    if args.json {
        let mut v = serde_json::to_value(&a)?;
        if let serde_json::Value::Object(m) = &mut v {
            m.insert(
                "features".into(),
                serde_json::Value::Object(
                    features
                        .iter()
                        .map(|(n, x)| (n.clone(), serde_json::json!(x)))
                        .collect(),
                ),
            );
            m.insert("score".into(), serde_json::json!(score));
            m.insert("verdict".into(), serde_json::json!(verdict(score)));
            m.insert(
                "detector_fitted_on".into(),
                serde_json::json!(detector.fitted_on),
            );
        }
        println!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    print_report(&a);
    println!(
        "score         {score:.3}: {}\n              (detector fitted on {})",
        verdict(score),
        detector.fitted_on
    );
    Ok(())
}

fn pct(x: f64) -> String {
    format!("{:.2}", 100.0 * x)
}

fn print_report(a: &Analysis) {
    println!("file          {}", a.path);
    println!(
        "model         {}, {:.2} MiB; {}×{} grid, T=2^{}, aabb_scale {}",
        a.format,
        a.file_bytes as f64 / (1024.0 * 1024.0),
        a.n_levels,
        a.n_features_per_level,
        a.log2_hashmap_size,
        a.aabb_scale
    );
    if a.density_grid_stored {
        println!(
            "occupancy     {}% of cascade-0 cells occupied (stored grid); optical thickness \
             mean {:.3e} (threshold {:.3e}), max {:.3e}",
            pct(a.occupied_frac),
            a.grid_mean,
            a.grid_mean.min(0.01),
            a.grid_max
        );
    } else {
        println!("occupancy     no grid stored: every entry counts as reachable");
    }
    println!(
        "field         {}% of cascade 0 decodes a raw log-density within ±{:e} of 0",
        pct(a.field_near_zero_frac),
        NEAR_ZERO
    );
    println!(
        "at init       an entry whose every feature has |v| ≤ {:.6e}",
        a.init_bound
    );
    println!("magnitude     max |feature| of an entry; median reachable / unreachable\n");
    println!(
        "{:>5}  {:<6} {:>8} {:>8} {:>8} {:>14} {:>11} {:>11}",
        "level",
        "kind",
        "entries",
        "init %",
        "reach %",
        "unreach init %",
        "med reach",
        "med unreach"
    );
    for l in &a.levels {
        let unreach = |s: String| {
            if l.unreachable.count > 0 {
                s
            } else {
                "-".into()
            }
        };
        println!(
            "{:>5}  {:<6} {:>8} {:>8} {:>8} {:>14} {:>11.3e} {:>11}",
            l.level,
            if l.dense { "dense" } else { "hashed" },
            l.entries,
            pct(l.init_frac),
            pct(l.reachable_frac),
            unreach(pct(l.unreachable.init_frac)),
            l.reachable.magnitude.median,
            unreach(format!("{:.3e}", l.unreachable.magnitude.median)),
        );
    }
    println!();
    println!(
        "{:<10} {:>9} {:>10} {:>10} {:>10} {:>10} {:>8}",
        "MLP", "rows×cols", "mean", "std", "mean |w|", "max |w|", "ex.kurt"
    );
    for m in &a.mlp {
        println!(
            "{:<10} {:>9} {:>10.2e} {:>10.4} {:>10.4} {:>10.4} {:>8.2}",
            format!("{} {}", m.network, m.layer),
            format!("{}×{}", m.rows, m.cols),
            m.mean,
            m.std,
            m.mean_abs,
            m.max_abs,
            m.excess_kurtosis
        );
    }
    println!();
    println!(
        "loss          {} at step {} (no self-check: the file holds camera poses, no pixels)",
        a.loss, a.training_step
    );
    let c = &a.compression;
    match &c.gzip_header {
        Some(h) => println!(
            "compression   {:.4} (file / msgpack); gzip header mtime {}, XFL {}, OS {}, flags {}",
            c.ratio, h.mtime, h.xfl, h.os, h.flags
        ),
        None => println!("compression   {:.4} ({})", c.ratio, c.measured),
    }
}
