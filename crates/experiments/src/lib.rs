//! The StegoNGP paper's experiments, and ours: each trains the models it needs on the given
//! (or generated) scenes, evaluates held-out views, and writes a Markdown + JSON report with
//! PNG image grids into its output directory. An experiment also runs as a plan of jobs
//! ([`plan`]) that a scheduler such as Slurm ([`slurm`]) runs on many machines.
//!
//! It drives the recipe, the attacks and the steganalysis of the layers below; it knows no
//! command line (neither clap nor anyhow) and nothing of the viewer or video.

pub mod detectability;
pub mod jobs;
pub mod pairs;
pub mod paper;
pub mod plan;
pub mod plot;
pub mod report;
pub mod robustness;
pub mod runs;
pub mod setup;
pub mod slurm;
mod store;
mod tee;

pub use detectability::{DetectOptions, run_detectability};
pub use jobs::{JobMode, PlannedModel};
pub use pairs::{PairSpec, PairsOptions, cover_with_each, read_pairs_file, run_pairs};
pub use robustness::{Mode, RobustnessOptions, default_attacks, run_robustness};
pub use runs::run_experiment;
pub use setup::{ExpConfig, Experiment};
