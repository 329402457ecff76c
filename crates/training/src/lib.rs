//! One training run, as every front end trains: `train`, the demo, every experiment, the
//! attacks that fine-tune, the test kit and the benchmarks.
//!
//! - [`recipe`]: what trains — the cover under the reference index, each hidden scene
//!   under its key's, the options (schedule, weight, warm-up, stealth, robust), a budget;
//!   [`recipe::Recipe::check`] validates them before anything is read or written.
//! - [`steps`]: a recipe's training in progress on a device, to its budget: the totals and
//!   the losses a model file stores.
//! - [`state`]: the run's whole state between two steps (a secret run state, a plain
//!   run's checkpoint snapshot, an experiment model's state), and `--save-every`'s cadence.
//! - [`checkpoints`]: `--checkpoints`, the cover's test views scored at given minutes.
//! - [`run`]: the stream: start, resume, step, save state, score checkpoints, finish, as one
//!   type that emits [`run::Event`]s; front ends only display them.
//!
//! The engine (`ngp`) knows nothing of it; keys come from `stego`, devices from `backend`.

pub mod checkpoints;
pub mod recipe;
pub mod run;
pub mod state;
pub mod steps;
