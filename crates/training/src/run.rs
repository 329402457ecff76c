//! The training run as one stream: [`Run::start`] builds the recipe's trainer on a device
//! and goes on from a saved state if asked; [`Run::run`] steps it to the budget, saving its
//! state on the cadence and scoring checkpoints as their minutes come, and tells the
//! caller each thing as an [`Event`]; [`Run::finish`] saves the last state where the
//! cadence keeps one and gives the model as published. `train`, the demo, every
//! experiment and the test kit consume it; they only display what it says.

use crate::checkpoints::{Checkpoint, CheckpointPlan, CheckpointScorer};
use crate::recipe::Checked;
use crate::state::{Saved, StateFile, StateSaver, Tagged, damaged, is_run_state};
use crate::steps::{Trained, Training};
use backend::Device;
use ngp::error::{Error, Result};
use std::path::{Path, PathBuf};

/// What a run goes on from.
pub enum ResumeFrom {
    /// A state read from `origin` (`train --resume`): a run state or a plain run's
    /// checkpoint snapshot, told apart by their first bytes.
    Bytes { bytes: Vec<u8>, origin: PathBuf },
    /// The saver's own tagged file, if it holds a state of its configuration (an
    /// experiment's model, interrupted and run again).
    OwnState,
}

/// Everything a run does besides stepping.
#[derive(Default)]
pub struct RunOptions {
    pub resume: Option<ResumeFrom>,
    pub save: Option<StateSaver>,
    pub checkpoints: Option<CheckpointPlan>,
}

/// Where a run went on from, if it did.
#[derive(Clone, Debug, Default, PartialEq)]
pub enum Resumed {
    /// From its first step.
    #[default]
    Fresh,
    /// From the state at `from`, at `step` with `trained_seconds` of training done;
    /// restoring it took `seconds`.
    From {
        from: PathBuf,
        step: u32,
        trained_seconds: f64,
        seconds: f64,
    },
    /// From its first step: the state found was another configuration's, and is removed.
    StaleRemoved(PathBuf),
}

/// What a run tells its front end, in order, after each step.
pub enum Event<'a, 'd> {
    /// A step was taken; the training as it is now.
    Step(&'a Training<'d>),
    /// The state was written to `path` at `step`.
    StateSaved { path: &'a Path, step: u32 },
    /// The device cannot save a state (why); the run goes on without.
    StateOff { why: &'a str },
    /// A checkpoint was scored.
    Checkpoint(&'a Checkpoint),
}

/// A training run in progress.
pub struct Run<'d> {
    device: &'d Device,
    training: Training<'d>,
    saver: Option<StateSaver>,
    scorer: Option<CheckpointScorer>,
    resumed: Resumed,
}

/// A finished run: the model as published and what the run did besides.
pub struct Finished {
    pub trained: Trained,
    /// States written and their seconds (outside the training's time).
    pub state_saves: u32,
    pub state_save_seconds: f64,
    pub checkpoints: Vec<Checkpoint>,
    pub resumed: Resumed,
}

impl<'d> Run<'d> {
    /// The recipe's training on `device`, gone on from `opts.resume` if given.
    pub fn start(recipe: &Checked, device: &'d Device, opts: RunOptions) -> Result<Self> {
        let mut training = recipe.start(device)?;
        let resumed = match opts.resume {
            None => Resumed::Fresh,
            Some(from) => resume(&mut training, from, opts.save.as_ref())?,
        };
        let mut saver = opts.save;
        if let Some(s) = saver.as_mut() {
            s.start_at(&training);
        }
        let scorer = match opts.checkpoints {
            Some(plan) => Some(CheckpointScorer::new(plan, recipe.model, &training)?),
            None => None,
        };
        Ok(Run {
            device,
            training,
            saver,
            scorer,
            resumed,
        })
    }

    pub fn training(&self) -> &Training<'d> {
        &self.training
    }

    pub fn training_mut(&mut self) -> &mut Training<'d> {
        &mut self.training
    }

    pub fn resumed(&self) -> &Resumed {
        &self.resumed
    }

    /// Steps to the budget, telling `on` of each step, each state saved and each
    /// checkpoint scored; an error from `on` stops the run.
    pub fn run(&mut self, mut on: impl FnMut(Event<'_, 'd>) -> Result<()>) -> Result<()> {
        while self.training.step()?.is_some() {
            on(Event::Step(&self.training))?;
            if let Some(saver) = self.saver.as_mut() {
                match saver.after_step(&self.training)? {
                    Saved::Nothing => {}
                    Saved::Written => on(Event::StateSaved {
                        path: &saver.file.path,
                        step: self.training.totals().steps,
                    })?,
                    Saved::Off(why) => on(Event::StateOff { why: &why })?,
                }
            }
            if let Some(scorer) = self.scorer.as_mut() {
                while let Some(c) = scorer.next_due(&self.training, self.device)? {
                    on(Event::Checkpoint(c))?;
                }
            }
        }
        Ok(())
    }

    /// Saves the run's last state where its cadence keeps one (`train --save-every`), and
    /// returns its file then. Call before [`Self::finish`], which may refuse the model.
    pub fn save_last_state(&mut self) -> Result<Option<&StateFile>> {
        let Some(saver) = self.saver.as_mut() else {
            return Ok(None);
        };
        Ok(saver.finish(&self.training)?.then_some(&saver.file))
    }

    /// The device's milliseconds a step in each of its phases (`--profile-every`).
    pub fn device_profile(&self) -> Vec<(String, f64)> {
        self.training.trainer().device_profile()
    }

    /// The model as published ([`Training::finish`] refuses one whose hidden scenes never
    /// trained), and what the run did besides.
    pub fn finish(self) -> Result<Finished> {
        let (state_saves, state_save_seconds) = self
            .saver
            .as_ref()
            .map_or((0, 0.0), |s| (s.saves, s.seconds));
        Ok(Finished {
            trained: self.training.finish()?,
            state_saves,
            state_save_seconds,
            checkpoints: self.scorer.map(|s| s.done).unwrap_or_default(),
            resumed: self.resumed,
        })
    }
}

/// Goes on from `from` into a fresh `training`.
fn resume(
    training: &mut Training,
    from: ResumeFrom,
    saver: Option<&StateSaver>,
) -> Result<Resumed> {
    let t0 = std::time::Instant::now();
    let origin = match from {
        ResumeFrom::Bytes { bytes, origin } => {
            if is_run_state(&bytes) {
                training.restore_state(&bytes, &origin)?;
            } else {
                let snap =
                    ngp::snapshot::from_bytes(&bytes).map_err(|m| Error::format(&origin, m))?;
                training.restore_checkpoint(snap, &origin)?;
            }
            origin
        }
        ResumeFrom::OwnState => {
            let Some(file) = saver.map(|s| &s.file) else {
                return Err(Error::Config(
                    "resuming from its own state needs a saver".into(),
                ));
            };
            match file.read_tagged()? {
                Tagged::None => return Ok(Resumed::Fresh),
                Tagged::Stale => return Ok(Resumed::StaleRemoved(file.path.clone())),
                Tagged::Run(doc) => {
                    training
                        .restore_state_doc(&doc, &file.path)
                        .map_err(damaged)?;
                    file.path.clone()
                }
            }
        }
    };
    let t = training.totals();
    Ok(Resumed::From {
        from: origin,
        step: t.steps,
        trained_seconds: t.seconds,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::recipe::{Budget, GridOptions, Recipe, StepOptions};
    use crate::state::{SaveEvery, StateForm};
    use dataset::LoadOptions;
    use ngp::data::Split;
    use ngp::network::ModelConfig;
    use std::sync::Arc;

    /// A plain recipe of a tiny generated scene: `steps` steps of 2^12 samples.
    fn tiny(dir: &Path, steps: u32) -> Checked {
        let opts = synth::SynthOptions {
            resolution: 24,
            n_train: 4,
            n_val: 0,
            n_test: 1,
            seed: 5,
            aabb_scale: 1,
            ..Default::default()
        };
        synth::generate(&opts, dir).unwrap();
        let cover = dataset::load(dir, Split::Train, &LoadOptions::default()).unwrap();
        let grid = GridOptions {
            levels: 8,
            features: 2,
            log2_t: 12,
        };
        let model = ModelConfig {
            grid: grid.grid(),
            aabb_scale: 1,
        };
        let step = StepOptions {
            seed: 3,
            batch: 1 << 12,
            workers: 1,
            ..Default::default()
        };
        Recipe::plain(model, Arc::new(cover), step, Budget::Steps(steps))
            .check()
            .unwrap()
    }

    /// The stream says every step, then each state the cadence saves; the last state is
    /// not written twice; and a run resumed from a state it saved ends with the same model,
    /// byte for byte, as the run that was never stopped.
    #[test]
    fn the_stream_saves_on_its_cadence_and_resumes_exactly() {
        let d = tempfile::tempdir().unwrap();
        let recipe = tiny(&d.path().join("scene"), 6);
        let cpu = Device::default();
        let file = StateFile {
            path: d.path().join("state.msgpack"),
            form: StateForm::Snapshot,
        };
        let at_4 = d.path().join("at4.msgpack");
        let opts = RunOptions {
            save: Some(StateSaver::for_run(SaveEvery::Steps(2), file.clone())),
            ..Default::default()
        };
        let mut run = Run::start(&recipe, &cpu, opts).unwrap();
        let mut said = Vec::new();
        run.run(|event| {
            match event {
                Event::Step(t) => said.push(format!("step {}", t.totals().steps)),
                Event::StateSaved { path, step } => {
                    said.push(format!("saved {step}"));
                    if step == 4 {
                        std::fs::copy(path, &at_4).unwrap();
                    }
                }
                Event::StateOff { .. } | Event::Checkpoint(_) => said.push("other".into()),
            }
            Ok(())
        })
        .unwrap();
        let expected = "step 1,step 2,saved 2,step 3,step 4,saved 4,step 5,step 6,saved 6";
        assert_eq!(said.join(","), expected);
        assert_eq!(run.save_last_state().unwrap(), Some(&file));
        let whole = run.finish().unwrap();
        assert_eq!(
            whole.state_saves, 3,
            "the end of a run that just saved saves again"
        );
        assert_eq!(whole.resumed, Resumed::Fresh);

        let opts = RunOptions {
            resume: Some(ResumeFrom::Bytes {
                bytes: std::fs::read(&at_4).unwrap(),
                origin: at_4.clone(),
            }),
            ..Default::default()
        };
        let mut run = Run::start(&recipe, &cpu, opts).unwrap();
        assert!(
            matches!(run.resumed(), Resumed::From { step: 4, from, .. } if *from == at_4),
            "{:?}",
            run.resumed()
        );
        let mut steps = 0;
        run.run(|_| {
            steps += 1;
            Ok(())
        })
        .unwrap();
        assert_eq!(steps, 2, "a resumed run takes only the steps left");
        let resumed = run.finish().unwrap();
        let bytes =
            |m: &ngp::model::Model| ngp::snapshot::to_bytes(&m.to_snapshot(), false).unwrap();
        assert!(
            bytes(&resumed.trained.model) == bytes(&whole.trained.model),
            "the resumed run's model differs from the uninterrupted one's"
        );
    }
}
