//! `experiment pairs --paper-scale --cover ROOT`: the paper's Table 1 at its own scale. The
//! eight NeRF-synthetic objects under ROOT (800 px, its train and test splits) as covers,
//! two generated logo scenes standing in for the paper's Google and Twitter (which are not
//! public), paired as the paper pairs them, 50 000 steps a scene, the reference's 2^18
//! samples a step, every test view scored: 8 stego models and 10 plain baselines.

use super::Args;
use anyhow::{Result, bail};
use std::path::{Path, PathBuf};
use stegongp::experiments::PairSpec;
use stegongp::synth::{SceneKind, SynthOptions, generate};

/// The paper's pairing (its section on the main experiment): Lego, Mic, Chair and Ficus
/// hide Twitter; Hotdog, Drums, Ship and Materials hide Google.
pub const PAPER_PAIRS: [(&str, &str); 8] = [
    ("chair", TWITTER),
    ("drums", GOOGLE),
    ("ficus", TWITTER),
    ("hotdog", GOOGLE),
    ("lego", TWITTER),
    ("materials", GOOGLE),
    ("mic", TWITTER),
    ("ship", GOOGLE),
];
const GOOGLE: &str = "paper_logo_google";
const TWITTER: &str = "paper_logo_twitter";
pub const STEPS: u32 = 50_000;
pub const BATCH: u32 = 1 << 18;
/// The Blender scenes' split: 100 training and 200 test views of 800 × 800.
const RES: u32 = 800;
const TRAIN_VIEWS: usize = 100;
const TEST_VIEWS: usize = 200;

/// Turns `--paper-scale --cover ROOT` into the paper's pairs and budget, or refuses what
/// does not fit it.
pub fn configure(a: &mut Args) -> Result<()> {
    if a.name != "pairs" {
        bail!(
            "--paper-scale is the paper's Table 1: `experiment pairs --paper-scale --cover ROOT`"
        );
    }
    if !a.pairs.is_empty() || a.pairs_file.is_some() || !a.hidden.is_empty() {
        bail!("--paper-scale makes its own pairs: leave out --pair, --pairs and --hidden");
    }
    if a.steps.is_some() || a.minutes.is_some() || a.batch.is_some() || a.res.is_some() {
        bail!(
            "--paper-scale sets the budget ({STEPS} steps of {BATCH} samples a scene) and the logos' size ({RES} px): leave out --steps, --minutes, --batch and --res"
        );
    }
    let Some(root) = a.cover.take() else {
        bail!(
            "--paper-scale needs --cover ROOT: the NeRF-synthetic folder holding {}",
            names()
        );
    };
    let missing: Vec<&str> = PAPER_PAIRS
        .iter()
        .map(|(c, _)| *c)
        .filter(|c| !root.join(c).join("transforms_train.json").is_file())
        .collect();
    if !missing.is_empty() {
        bail!(
            "{}: --paper-scale needs the eight NeRF-synthetic scenes there ({}); missing: {}",
            root.display(),
            names(),
            missing.join(", ")
        );
    }
    let root = std::fs::canonicalize(&root)?;
    let data = std::path::absolute(a.out.join("data"))?;
    a.pairs = PAPER_PAIRS
        .iter()
        .map(|(c, h)| PairSpec {
            cover: root.join(c),
            hidden: data.join(h),
        })
        .collect();
    a.steps = Some(STEPS);
    a.batch = Some(BATCH);
    // Every test view, as the paper scores them (unless fewer are asked for).
    if a.eval_views == 8 {
        a.eval_views = TEST_VIEWS;
    }
    Ok(())
}

fn names() -> String {
    PAPER_PAIRS.map(|(c, _)| c).join(", ")
}

/// Generates the two logo scenes into `out/data` unless they are there (a plan makes them
/// once; its jobs find them).
pub fn generate_logos(out: &Path) -> Result<Vec<PathBuf>> {
    let mut dirs = Vec::new();
    for (name, seed) in [(GOOGLE, 71), (TWITTER, 72)] {
        let dir = out.join("data").join(name);
        if !dir.join("transforms_train.json").exists() {
            eprintln!(
                "generating {} ({RES} px, {TRAIN_VIEWS} + {TEST_VIEWS} views)",
                dir.display()
            );
            let opts = SynthOptions {
                scene: SceneKind::Logo,
                resolution: RES,
                n_train: TRAIN_VIEWS,
                n_val: 0,
                n_test: TEST_VIEWS,
                seed,
                aabb_scale: 1,
                ..Default::default()
            };
            generate(&opts, &dir)?;
        }
        dirs.push(dir);
    }
    Ok(dirs)
}
