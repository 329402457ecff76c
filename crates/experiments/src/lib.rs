//! The StegoNGP paper's experiments, and ours: each trains the models it needs on the given
//! (or generated) scenes, evaluates held-out views, and writes a Markdown + JSON report with
//! PNG image grids into its output directory.
//!
//! It drives the recipe, the attacks and the steganalysis of the layers below; it knows no
//! command line (neither clap nor anyhow) and nothing of the viewer or video.

pub mod detectability;
pub mod jobs;
pub mod pairs;
pub mod plot;
pub mod report;
pub mod robustness;
pub mod runs;
pub mod setup;
mod store;

pub use detectability::{DetectOptions, run_detectability};
pub use jobs::{JobMode, PlannedModel};
pub use pairs::{PairSpec, PairsOptions, cover_with_each, read_pairs_file, run_pairs};
pub use robustness::{Mode, RobustnessOptions, default_attacks, run_robustness};
pub use runs::run_experiment;
pub use setup::{ExpConfig, Experiment};
