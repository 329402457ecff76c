//! The paper's Table 1 at its own scale (`experiment pairs --paper-scale --cover ROOT`): the
//! eight NeRF-synthetic objects under ROOT (800 px, its train and test splits) as covers,
//! two generated logo scenes standing in for the paper's Google and Twitter (which are not
//! public), paired as the paper pairs them, 50 000 steps a scene, the reference's 2^18
//! samples a step, every test view scored: 8 stego models and 10 plain baselines.

use crate::pairs::PairSpec;
use ngp::error::Result;
use std::path::{Path, PathBuf};
use synth::{SceneKind, SynthOptions, generate};

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
pub const RES: u32 = 800;
pub const TRAIN_VIEWS: usize = 100;
pub const TEST_VIEWS: usize = 200;

/// The eight covers' names, as a list to show.
pub fn scene_names() -> String {
    PAPER_PAIRS.map(|(c, _)| c).join(", ")
}

/// The covers of [`PAPER_PAIRS`] that are not under `root`.
pub fn missing_scenes(root: &Path) -> Vec<&'static str> {
    PAPER_PAIRS
        .iter()
        .map(|(c, _)| *c)
        .filter(|c| !root.join(c).join("transforms_train.json").is_file())
        .collect()
}

/// The paper's pairs: each cover under `root`, its logo under `data` (where
/// [`generate_logos`] puts them: `OUT/data`).
pub fn pairs(root: &Path, data: &Path) -> Vec<PairSpec> {
    PAPER_PAIRS
        .iter()
        .map(|(c, h)| PairSpec {
            cover: root.join(c),
            hidden: data.join(h),
        })
        .collect()
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
