//! How far matching a model's weight statistics to a plain model's could take stealth: maps
//! each MLP matrix's values, and each level's moved table entries' magnitudes, onto a
//! reference model's by quantile (the sorted values of the one become the other's, rank for
//! rank; entries at initialisation are left alone), then saves the result. Everything the
//! detector reads from the weights' first moments then equals the reference's; what the
//! cover's grid, loss and compression show does not change. A diagnostic: the mapped model
//! renders worse (nothing retrains it), and benchmarks/steganalysis.md ("What chance gives") reports what
//! the detectors make of such models.
//!
//! ```sh
//! cargo run --release --example match_statistics -- STEALTH.ingp PLAIN.ingp OUT.ingp [all|mlp|table]
//! ```

use anyhow::{Context, Result, bail};
use std::path::Path;
use stegongp::ngp::network::NerfLayout;
use stegongp::ngp::snapshot;
use stegongp::steganalysis::{INIT_BOUND, mlp_matrices};

/// Replaces `vals` by `reference`'s values of the same rank (linear between ranks when the
/// two differ in length).
fn quantile_map(vals: &mut [f32], reference: &[f32]) {
    let mut r = reference.to_vec();
    r.sort_by(f32::total_cmp);
    let mut order: Vec<usize> = (0..vals.len()).collect();
    order.sort_by(|&a, &b| vals[a].total_cmp(&vals[b]));
    let n = vals.len();
    for (rank, &i) in order.iter().enumerate() {
        let q = if n > 1 {
            rank as f64 / (n - 1) as f64
        } else {
            0.5
        };
        let pos = q * (r.len() - 1) as f64;
        let lo = pos.floor() as usize;
        let hi = (lo + 1).min(r.len() - 1);
        let t = (pos - lo as f64) as f32;
        vals[i] = r[lo] * (1.0 - t) + r[hi] * t;
    }
}

fn match_mlp(layout: &NerfLayout, params: &mut [f32], reference: &[f32]) {
    // The weights the detector counts: tcnn's padding stays as it is.
    for m in mlp_matrices(layout) {
        let idx: Vec<usize> = m.indices().collect();
        let mut v: Vec<f32> = idx.iter().map(|&i| params[i]).collect();
        let rv: Vec<f32> = idx.iter().map(|&i| reference[i]).collect();
        quantile_map(&mut v, &rv);
        for (&i, x) in idx.iter().zip(v) {
            params[i] = x;
        }
    }
}

fn match_table(layout: &NerfLayout, params: &mut [f32], reference: &[f32]) {
    let nf = layout.config.grid.n_features as usize;
    for lv in &layout.grid.levels {
        let base = layout.grid_offset + lv.offset as usize * nf;
        let mag = |p: &[f32], e: usize| {
            p[base + e * nf..base + (e + 1) * nf]
                .iter()
                .fold(0.0f32, |m, v| m.max(v.abs()))
        };
        let moved: Vec<usize> = (0..lv.size as usize)
            .filter(|&e| mag(params, e) > INIT_BOUND)
            .collect();
        let target: Vec<f32> = (0..lv.size as usize)
            .map(|e| mag(reference, e))
            .filter(|&m| m > INIT_BOUND)
            .collect();
        if moved.is_empty() || target.is_empty() {
            continue;
        }
        let before: Vec<f32> = moved.iter().map(|&e| mag(params, e)).collect();
        let mut after = before.clone();
        quantile_map(&mut after, &target);
        for ((&e, b), a) in moved.iter().zip(before).zip(after) {
            // A moved entry stays moved: never scaled back into the initial box.
            let scale = a.max(INIT_BOUND * 1.01) / b;
            for v in &mut params[base + e * nf..base + (e + 1) * nf] {
                *v *= scale;
            }
        }
    }
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 3 || args.len() > 4 {
        bail!("usage: match_statistics MODEL REFERENCE OUT [all|mlp|table]");
    }
    let what = args.get(3).map(String::as_str).unwrap_or("all");
    if !["all", "mlp", "table"].contains(&what) {
        bail!("what to match: all, mlp or table, not {what:?}");
    }
    let load = |p: &str| snapshot::load(Path::new(p)).with_context(|| format!("reading {p}"));
    let mut model = load(&args[0])?;
    let reference = load(&args[1])?;
    if model.config != reference.config || model.params.len() != reference.params.len() {
        bail!(
            "{} and {} have different configurations: nothing to match",
            args[0],
            args[1]
        );
    }
    let layout = NerfLayout::new(model.config)?;
    if what != "table" {
        match_mlp(&layout, &mut model.params, &reference.params);
    }
    if what != "mlp" {
        match_table(&layout, &mut model.params, &reference.params);
    }
    snapshot::save(Path::new(&args[2]), &model).with_context(|| format!("writing {}", args[2]))
}
