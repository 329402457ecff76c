//! A recipe's training in progress: the steps to the budget, the totals and the losses a
//! model file stores.

use crate::recipe::{Budget, StoredLoss};
use backend::TrainBackend;
use ngp::error::{Error, Result};
use ngp::model::Model;
use ngp::train::StepStats;

/// What a training has done so far.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Totals {
    pub steps: u32,
    /// Training time: the steps' own.
    pub seconds: f64,
    /// Samples that reached the loss.
    pub samples: u64,
    /// Samples marched.
    pub marched: u64,
    /// Rays that trained (that reached the loss).
    pub rays: u64,
    /// Samples through the whole network, forward passes counted separately
    /// ([`StepStats::n_network`]).
    pub network: u64,
    /// Rays that trained nothing because a device buffer was full.
    pub dropped_rays: u64,
    /// The device's host waits and command submissions.
    pub host_waits: u64,
    pub submissions: u64,
    /// The steps' time in occupancy updates, in rays and in the optimizer.
    pub occupancy_seconds: f64,
    pub rays_seconds: f64,
    pub optimizer_seconds: f64,
    /// The steps' time waiting for a separate device (a GPU running ahead of the host).
    pub wait_seconds: f64,
    /// Occupancy-grid updates made, and the densities they evaluated.
    pub occupancy_updates: u32,
    pub occupancy_evaluations: u64,
}

impl Totals {
    pub fn samples_per_second(&self) -> f64 {
        self.samples as f64 / self.seconds.max(1e-9)
    }

    pub fn steps_per_second(&self) -> f64 {
        self.steps as f64 / self.seconds.max(1e-9)
    }

    /// Where the time went, for a progress line: "occupancy 12% · rays 70% · optimizer 18%",
    /// and "· waiting for the device N%" where the host waited for a GPU.
    pub fn phase_split(&self) -> String {
        let pct = |s: f64| 100.0 * s / self.seconds.max(1e-9);
        let mut s = format!(
            "occupancy {:.0}% · rays {:.0}% · optimizer {:.0}%",
            pct(self.occupancy_seconds),
            pct(self.rays_seconds),
            pct(self.optimizer_seconds)
        );
        if self.wait_seconds > 0.0 {
            s += &format!(" · waiting for the device {:.0}%", pct(self.wait_seconds));
        }
        s
    }
}

/// A recipe's training in progress.
pub struct Training<'d> {
    pub(crate) trainer: Box<dyn TrainBackend + 'd>,
    pub(crate) budget: Budget,
    pub(crate) per_round: u32,
    pub(crate) solo: u32,
    pub(crate) stored_loss: StoredLoss,
    pub(crate) totals: Totals,
    pub(crate) last_loss: f32,
    pub(crate) smoothed: Option<f32>,
    pub(crate) shown: f32,
    /// Whether the trainer's measurements not yet reported were added once the budget was
    /// spent (a GPU reads its steps' measurements late).
    pub(crate) flushed: bool,
}

/// A finished training: the model as published, and what it took.
pub struct Trained {
    pub model: Model,
    pub totals: Totals,
}

impl Training<'_> {
    /// Whether the budget is spent.
    pub fn done(&self) -> bool {
        let steps = self.trainer.step();
        match self.budget {
            Budget::Steps(n) => steps >= n,
            Budget::Seconds(s) => self.totals.seconds >= s && steps.is_multiple_of(self.per_round),
        }
    }

    /// One step, or `None` once the budget is spent.
    pub fn step(&mut self) -> Result<Option<StepStats>> {
        if self.done() {
            if !self.flushed {
                self.flushed = true;
                let st = self.trainer.flush_stats()?;
                self.add(&st);
            }
            return Ok(None);
        }
        let st = self.trainer.train_step()?;
        self.add(&st);
        Ok(Some(st))
    }

    /// Adds a step's stats (or measurements reported late) to the totals and the losses.
    fn add(&mut self, st: &StepStats) {
        let t = &mut self.totals;
        t.steps = self.trainer.step();
        t.seconds += st.seconds;
        t.samples += st.n_samples;
        t.marched += st.n_marched;
        t.rays += st.n_rays;
        t.network += st.n_network;
        t.dropped_rays += st.dropped_rays;
        t.host_waits += st.host_waits as u64;
        t.submissions += st.submissions as u64;
        t.occupancy_seconds += st.occupancy_seconds;
        t.rays_seconds += st.rays_seconds;
        t.optimizer_seconds += st.optimizer_seconds;
        t.wait_seconds += st.wait_seconds;
        t.occupancy_updates += st.occupancy_updates;
        t.occupancy_evaluations += st.occupancy_evaluations;
        self.shown = if t.steps == 1 {
            st.loss
        } else {
            0.95 * self.shown + 0.05 * st.loss
        };
        if let Some(c) = st.primary_loss {
            self.last_loss = c;
            self.smoothed = Some(self.smoothed.map_or(c, |e| 0.95 * e + 0.05 * c));
        }
    }

    pub fn totals(&self) -> &Totals {
        &self.totals
    }

    /// Every scene's loss, smoothed over the steps (what a progress line shows).
    pub fn shown_loss(&self) -> f32 {
        self.shown
    }

    /// The loss the model file stores (the cover's alone, as a plain model's).
    pub fn stored_loss(&self) -> f32 {
        match self.stored_loss {
            StoredLoss::Smoothed => self.smoothed.unwrap_or(0.0),
            StoredLoss::Last => self.last_loss,
        }
    }

    pub fn trainer(&self) -> &dyn TrainBackend {
        self.trainer.as_ref()
    }

    pub fn trainer_mut(&mut self) -> &mut dyn TrainBackend {
        self.trainer.as_mut()
    }

    /// The model as it would be published now.
    pub fn model(&self) -> Result<Model> {
        self.trainer.model(self.stored_loss())
    }

    /// The model as published; refused when the budget ended inside the cover's warm-up,
    /// so that the hidden scenes never trained.
    pub fn finish(self) -> Result<Trained> {
        if self.trainer.n_scenes() > 1 && self.trainer.step() <= self.solo {
            return Err(Error::Config(format!(
                "training stopped at step {} with --hidden-from {}: the hidden scenes never \
                 trained (give more time or a smaller --hidden-from)",
                self.trainer.step(),
                self.solo
            )));
        }
        Ok(Trained {
            model: self.model()?,
            totals: self.totals,
        })
    }
}
