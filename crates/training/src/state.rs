//! A run's whole state between two steps, the forms it takes on disk, and when to save it.
//!
//! One document ([`Training::save_state_doc`]: format `stegongp-run-state`, the loop's
//! totals and losses around the trainer's own state, `ngp::train::state`) in three forms
//! ([`StateForm`]):
//! - a stego run's **secret** state: the document, owner-only (it describes the hidden
//!   scenes, like their keys);
//! - a plain run's **checkpoint snapshot**: the model as published now, the optimizer in
//!   tiny-cuda-nn's layout and the rest of the document beside it, which instant-ngp loads;
//! - an experiment model's **tagged** state: the document inside one that names the model's
//!   configuration, so that a state left by another configuration is never taken for it.
//!
//! [`StateSaver`] is the one cadence (`--save-every N|Mm`) that writes them.

use crate::steps::{Totals, Training};
use ngp::error::{Error, Result};
use std::path::{Path, PathBuf};

/// How often a long training saves its state (`--save-every`): every N steps (`500`) or
/// every M minutes of training (`10m`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SaveEvery {
    Steps(u32),
    Minutes(f64),
}

impl std::str::FromStr for SaveEvery {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let bad = || format!("'{s}': expected a step count (500) or minutes (10m)");
        match s.strip_suffix('m') {
            Some(m) => match m.trim().parse::<f64>() {
                Ok(m) if m.is_finite() && m > 0.0 => Ok(SaveEvery::Minutes(m)),
                _ => Err(bad()),
            },
            None => match s.trim().parse::<u32>() {
                Ok(n) if n > 0 => Ok(SaveEvery::Steps(n)),
                _ => Err(bad()),
            },
        }
    }
}

impl SaveEvery {
    /// Whether a save is due after the step that brought the run to `totals`, the last save
    /// having been at `saved_at` seconds of training.
    pub fn due(&self, totals: &Totals, saved_at: f64) -> bool {
        match *self {
            SaveEvery::Steps(n) => totals.steps.is_multiple_of(n),
            SaveEvery::Minutes(m) => totals.seconds - saved_at >= m * 60.0,
        }
    }
}

/// The run-state document ([`Training::save_state`]).
pub const RUN_STATE_FORMAT: &str = "stegongp-run-state";
/// 2: the trainer's state nested as a map (it was a binary).
pub const RUN_STATE_VERSION: u64 = 2;

/// Whether `bytes` are a run-state document ([`Training::save_state`]) rather than a
/// checkpoint snapshot ([`Training::save_checkpoint`]): its format name opens it.
pub fn is_run_state(bytes: &[u8]) -> bool {
    let head = &bytes[..bytes.len().min(64)];
    head.windows(RUN_STATE_FORMAT.len())
        .any(|w| w == RUN_STATE_FORMAT.as_bytes())
}

impl Training<'_> {
    /// The run's whole state between two steps: the trainer's and this loop's (totals,
    /// losses), so that a resumed run ends as the uninterrupted one would (on the CPU, bit
    /// for bit).
    pub fn save_state(&self) -> Result<Vec<u8>> {
        Ok(ngp::train::state::encode(&self.save_state_doc()?))
    }

    /// [`save_state`](Self::save_state) as a document, for a caller that nests it.
    pub fn save_state_doc(&self) -> Result<rmpv::Value> {
        Ok(self.run_doc(self.trainer.save_state()?))
    }

    /// The run-state document around the trainer's own (`trainer`).
    fn run_doc(&self, trainer: rmpv::Value) -> rmpv::Value {
        use ngp::train::state::map;
        use rmpv::Value;
        let t = &self.totals;
        let totals = map(vec![
            ("steps", Value::from(t.steps)),
            ("seconds", Value::F64(t.seconds)),
            ("samples", Value::from(t.samples)),
            ("marched", Value::from(t.marched)),
            ("rays", Value::from(t.rays)),
            ("network", Value::from(t.network)),
            ("dropped_rays", Value::from(t.dropped_rays)),
            ("host_waits", Value::from(t.host_waits)),
            ("submissions", Value::from(t.submissions)),
            ("occupancy_seconds", Value::F64(t.occupancy_seconds)),
            ("rays_seconds", Value::F64(t.rays_seconds)),
            ("optimizer_seconds", Value::F64(t.optimizer_seconds)),
            ("wait_seconds", Value::F64(t.wait_seconds)),
            ("occupancy_updates", Value::from(t.occupancy_updates)),
            (
                "occupancy_evaluations",
                Value::from(t.occupancy_evaluations),
            ),
        ]);
        map(vec![
            ("format", Value::from(RUN_STATE_FORMAT)),
            ("version", Value::from(RUN_STATE_VERSION)),
            ("totals", totals),
            ("last_loss", Value::F32(self.last_loss)),
            ("smoothed", self.smoothed.map_or(Value::Nil, Value::F32)),
            ("shown", Value::F32(self.shown)),
            ("trainer", trainer),
        ])
    }

    /// Takes back a [`save_state`](Self::save_state) before the first step; `origin` names
    /// the state in errors.
    pub fn restore_state(&mut self, bytes: &[u8], origin: &Path) -> Result<()> {
        self.restore_state_doc(&ngp::train::state::open(origin, bytes)?, origin)
    }

    /// [`restore_state`](Self::restore_state) from the document.
    pub fn restore_state_doc(&mut self, doc: &rmpv::Value, origin: &Path) -> Result<()> {
        use ngp::train::state::Fields;
        let f = Fields::top(origin, doc)?;
        f.expect_format(RUN_STATE_FORMAT, "a run state")?;
        f.expect_version(RUN_STATE_VERSION)?;
        let tf = f.map("totals")?;
        let totals = Totals {
            steps: tf.u32("steps")?,
            seconds: tf.f64("seconds")?,
            samples: tf.u64("samples")?,
            marched: tf.u64("marched")?,
            // Absent from states saved before the rays were counted.
            rays: if tf.has("rays") { tf.u64("rays")? } else { 0 },
            network: tf.u64("network")?,
            dropped_rays: tf.u64("dropped_rays")?,
            host_waits: tf.u64("host_waits")?,
            submissions: tf.u64("submissions")?,
            occupancy_seconds: tf.f64("occupancy_seconds")?,
            rays_seconds: tf.f64("rays_seconds")?,
            optimizer_seconds: tf.f64("optimizer_seconds")?,
            // Absent from states saved before the GPU's late reads.
            wait_seconds: if tf.has("wait_seconds") {
                tf.f64("wait_seconds")?
            } else {
                0.0
            },
            occupancy_updates: tf.u32("occupancy_updates")?,
            occupancy_evaluations: tf.u64("occupancy_evaluations")?,
        };
        let last_loss = f.f32("last_loss")?;
        let smoothed = if f.has("smoothed") {
            Some(f.f32("smoothed")?)
        } else {
            None
        };
        let shown = f.f32("shown")?;
        self.trainer.restore_state(f.value("trainer")?, origin)?;
        if self.trainer.step() != totals.steps {
            return Err(f.err(
                "totals.steps",
                format!(
                    "{}, but the trainer is at step {}",
                    totals.steps,
                    self.trainer.step()
                ),
            ));
        }
        self.totals = totals;
        self.last_loss = last_loss;
        self.smoothed = smoothed;
        self.shown = shown;
        Ok(())
    }

    /// A plain run's checkpoint as instant-ngp writes one with its optional optimizer
    /// state: the model as it would be published now, `snapshot.optimizer` in
    /// tiny-cuda-nn's layout (instant-ngp loads it and trains on), and the rest of the run
    /// state beside it (`snapshot.stegongp_run_state`), so that `--resume` goes on exactly.
    /// `.msgpack` writes it raw (fast), `.ingp` gzipped; atomically. Refused for a run with
    /// hidden scenes: its optimizer state describes them ([`Self::save_state_to`]).
    pub fn save_checkpoint(&self, path: &Path) -> Result<()> {
        if self.trainer.n_scenes() > 1 {
            return Err(Error::Config(
                "a run with hidden scenes saves its state as a secret file, not a snapshot".into(),
            ));
        }
        use ngp::train::state::take;
        let mut trainer = self.trainer.save_state()?;
        let optimizer = take(&mut trainer, "optimizer");
        let mut snap = self.model()?.to_snapshot();
        snap.preserved.optimizer = optimizer;
        snap.preserved.run_state = Some(self.run_doc(trainer));
        ngp::snapshot::save(path, &snap)
    }

    /// Takes back a [`save_checkpoint`](Self::save_checkpoint) (`snap`, read from `path`)
    /// before the first step.
    pub fn restore_checkpoint(&mut self, snap: ngp::snapshot::Snapshot, path: &Path) -> Result<()> {
        use ngp::train::state::{put, take};
        let Some(mut run) = snap.preserved.run_state else {
            return Err(Error::format(
                path,
                "a snapshot without a StegoNGP run state (train --save-every writes one); it \
                 cannot be resumed exactly",
            ));
        };
        match (take(&mut run, "trainer"), snap.preserved.optimizer) {
            (Some(mut trainer), Some(optimizer)) => {
                put(&mut trainer, "optimizer", optimizer);
                put(&mut run, "trainer", trainer);
            }
            _ => {
                return Err(Error::format(
                    path,
                    "field snapshot.optimizer or snapshot.stegongp_run_state.trainer: missing",
                ));
            }
        }
        self.restore_state_doc(&run, path)
    }

    /// [`save_state`](Self::save_state) written to `path` as a key is: owner-only,
    /// atomically. A stego run's state describes its hidden scenes, so it is as secret as
    /// their keys; it never goes into the published model.
    pub fn save_state_to(&self, path: &Path) -> Result<()> {
        stego::keyfile::write_secret(path, &self.save_state()?)
    }
}

/// The form a run's state takes on disk.
#[derive(Clone, Debug, PartialEq)]
pub enum StateForm {
    /// A stego run's run state, owner-only ([`Training::save_state_to`]).
    Secret,
    /// A plain run's checkpoint snapshot ([`Training::save_checkpoint`]).
    Snapshot,
    /// An experiment model's: the run state in a document holding the model's
    /// configuration (JSON text), owner-only.
    Tagged { config: String },
}

/// The document around an experiment model's run state ([`StateForm::Tagged`]).
const TAGGED_FORMAT: &str = "stegongp-experiment-model-state";

/// A run state's file and its form.
#[derive(Clone, Debug, PartialEq)]
pub struct StateFile {
    pub path: PathBuf,
    pub form: StateForm,
}

/// What reading a tagged state found ([`StateFile::read_tagged`]).
pub enum Tagged {
    /// No state: the model trains from its first step.
    None,
    /// A state of another configuration, now removed.
    Stale,
    /// This configuration's run state.
    Run(rmpv::Value),
}

impl StateFile {
    /// An experiment model's state while it trains: `MODEL.ingp.state` beside the model
    /// file, tagged with the model's configuration (JSON text) so that a state left by
    /// another configuration is never taken for this one.
    pub fn beside_model(model: &Path, config: String) -> Self {
        let mut path = model.as_os_str().to_owned();
        path.push(".state");
        StateFile {
            path: PathBuf::from(path),
            form: StateForm::Tagged { config },
        }
    }

    /// Writes `training`'s state in this file's form, atomically.
    pub fn write(&self, training: &Training) -> Result<()> {
        match &self.form {
            StateForm::Secret => training.save_state_to(&self.path),
            StateForm::Snapshot => training.save_checkpoint(&self.path),
            StateForm::Tagged { config } => {
                use ngp::train::state::{encode, map};
                let doc = map(vec![
                    ("format", rmpv::Value::from(TAGGED_FORMAT)),
                    ("config", rmpv::Value::from(config.as_str())),
                    ("run", training.save_state_doc()?),
                ]);
                stego::keyfile::write_secret(&self.path, &encode(&doc))
            }
        }
    }

    /// A tagged state's run state, if the file holds one of this configuration. One of
    /// another configuration is removed (the model it belonged to is not this one); a
    /// damaged one is an error naming it, saying what to do.
    pub fn read_tagged(&self) -> Result<Tagged> {
        use ngp::train::state::{Fields, open, take};
        let StateForm::Tagged { config } = &self.form else {
            return Err(Error::Config("not an experiment model's state".into()));
        };
        let bytes = match std::fs::read(&self.path) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Tagged::None),
            Err(e) => return Err(Error::io(&self.path, e)),
        };
        let mut doc = open(&self.path, &bytes).map_err(damaged)?;
        drop(bytes);
        let f = Fields::top(&self.path, &doc).map_err(damaged)?;
        if f.str("format").map_err(damaged)? != TAGGED_FORMAT {
            return Err(damaged(f.err("format", "not a model's training state")));
        }
        // Compared as JSON values, not as text: the same configuration written another way
        // is still this model's.
        let same = serde_json::from_str::<serde_json::Value>(f.str("config").map_err(damaged)?)
            .ok()
            .zip(serde_json::from_str::<serde_json::Value>(config).ok())
            .is_some_and(|(saved, ours)| saved == ours);
        if !same {
            self.remove()?;
            return Ok(Tagged::Stale);
        }
        f.value("run").map_err(damaged)?;
        // Taken out of the document, not copied: a model's state is hundreds of megabytes.
        Ok(take(&mut doc, "run").map_or(Tagged::None, Tagged::Run))
    }

    /// Removes the file, if it is there.
    pub fn remove(&self) -> Result<()> {
        match std::fs::remove_file(&self.path) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(Error::io(&self.path, e)),
            _ => Ok(()),
        }
    }
}

/// An error about an experiment model's state, with what to do about it.
pub(crate) fn damaged(e: Error) -> Error {
    Error::Other(format!(
        "{e} (a model's training state left by an interrupted experiment: delete it to train \
         that model from its first step)"
    ))
}

/// What a device that cannot save a state does to the run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Unsaveable {
    /// The run fails (a user asked for `--save-every`).
    Fail,
    /// The run goes on without (an experiment's model is still written).
    GoOn,
}

/// `--save-every`'s cadence: when a state is due, where it goes, and what saving cost.
pub struct StateSaver {
    every: SaveEvery,
    pub file: StateFile,
    /// Whether the run's last state is saved at its end (`train`'s, for `--resume`), or the
    /// state is only a way back into an interrupted run (an experiment's).
    at_end: bool,
    unsaveable: Unsaveable,
    saved_at: f64,
    saved_step: Option<u32>,
    /// Set once the device could not save a state ([`Unsaveable::GoOn`]).
    off: bool,
    /// States written and their total seconds.
    pub saves: u32,
    pub seconds: f64,
}

/// What one [`StateSaver::after_step`] did.
pub enum Saved {
    Nothing,
    /// A state was written.
    Written,
    /// The device cannot save a state (why); the run goes on without.
    Off(String),
}

impl StateSaver {
    /// `train --save-every`: the last state is saved at the end too, and a device that
    /// cannot save one fails the run.
    pub fn for_run(every: SaveEvery, file: StateFile) -> Self {
        Self::new(every, file, true, Unsaveable::Fail)
    }

    /// An experiment model's: no state at the end (the model replaces it), and a device
    /// that cannot save one trains on without.
    pub fn for_experiment(every: SaveEvery, file: StateFile) -> Self {
        Self::new(every, file, false, Unsaveable::GoOn)
    }

    fn new(every: SaveEvery, file: StateFile, at_end: bool, unsaveable: Unsaveable) -> Self {
        StateSaver {
            every,
            file,
            at_end,
            unsaveable,
            saved_at: 0.0,
            saved_step: None,
            off: false,
            saves: 0,
            seconds: 0.0,
        }
    }

    /// The cadence counts from `training`'s time now (a resumed run's).
    pub fn start_at(&mut self, training: &Training) {
        self.saved_at = training.totals().seconds;
    }

    /// Saves the state if one is due after this step.
    pub fn after_step(&mut self, training: &Training) -> Result<Saved> {
        let t = training.totals();
        if self.off || !self.every.due(t, self.saved_at) {
            return Ok(Saved::Nothing);
        }
        let saved = self.save(training)?;
        self.saved_at = t.seconds;
        Ok(saved)
    }

    /// The run's last state, where the cadence keeps one; whether it is there.
    pub fn finish(&mut self, training: &Training) -> Result<bool> {
        if !self.at_end {
            return Ok(false);
        }
        self.save(training)?;
        Ok(true)
    }

    fn save(&mut self, training: &Training) -> Result<Saved> {
        let step = training.totals().steps;
        if self.saved_step == Some(step) {
            return Ok(Saved::Nothing); // the end of a run that just saved
        }
        self.saved_step = Some(step);
        let t0 = std::time::Instant::now();
        match self.file.write(training) {
            Ok(()) => {}
            Err(Error::Config(why)) if self.unsaveable == Unsaveable::GoOn => {
                self.off = true;
                return Ok(Saved::Off(why));
            }
            Err(e) => {
                return Err(Error::Other(format!(
                    "saving the training state to {}: {e}",
                    self.file.path.display()
                )));
            }
        }
        self.saves += 1;
        self.seconds += t0.elapsed().as_secs_f64();
        Ok(Saved::Written)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A tagged state is taken back only by the configuration that saved it: another's is
    /// removed, a damaged one is an error naming it and saying what to do, none is nothing.
    #[test]
    fn a_tagged_state_belongs_to_its_config() {
        use ngp::train::state::{encode, map};
        let d = tempfile::tempdir().unwrap();
        let path = d.path().join("m.ingp.state");
        let config = r#"{"seed":1,"steps":30}"#;
        let file = StateFile::beside_model(&d.path().join("m.ingp"), config.into());
        assert_eq!(file.path, path);
        assert!(matches!(file.read_tagged().unwrap(), Tagged::None));
        let doc = |config: &str| {
            encode(&map(vec![
                ("format", rmpv::Value::from(TAGGED_FORMAT)),
                ("config", rmpv::Value::from(config)),
                ("run", rmpv::Value::Binary(vec![1, 2, 3])),
            ]))
        };
        // The same configuration, its keys written in another order: this model's.
        std::fs::write(&path, doc(r#"{"steps":30,"seed":1}"#)).unwrap();
        match file.read_tagged().unwrap() {
            Tagged::Run(run) => assert_eq!(run, rmpv::Value::Binary(vec![1, 2, 3])),
            _ => panic!("this configuration's state was not taken back"),
        }
        // Another configuration's (the budget changed): removed, nothing resumed.
        std::fs::write(&path, doc(r#"{"steps":31,"seed":1}"#)).unwrap();
        assert!(matches!(file.read_tagged().unwrap(), Tagged::Stale));
        assert!(!path.exists(), "a stale state stays behind");
        // Damaged: an error naming the file.
        let mut bytes = doc(config);
        bytes.truncate(bytes.len() / 2);
        std::fs::write(&path, bytes).unwrap();
        let e = file
            .read_tagged()
            .err()
            .expect("a damaged state read")
            .to_string();
        assert!(e.contains("m.ingp.state") && e.contains("delete it"), "{e}");
        assert!(path.exists(), "a damaged state is the user's to delete");
    }
}
