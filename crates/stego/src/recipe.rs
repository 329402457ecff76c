//! The one training recipe: a cover, hidden scenes each under its own key, the options of
//! how they train (schedule, weight, warm-up, stealth), a budget and a device give a model
//! as it will be published. `train`, the demo, every experiment and the benchmarks train
//! through it, so a model trains the same way whoever asks for it.
//!
//! [`Recipe::check`] validates every option before anything is trained or written;
//! [`Recipe::start`] builds the trainer on the device (the cover under the reference index,
//! each hidden scene under its key's, the stealth policy when asked); [`Training::step`]
//! runs it to the budget, keeping the totals and the loss a model file stores; and
//! [`Training::finish`] refuses a model whose hidden scenes never trained.

use crate::keys::Key;
use crate::stealth::{ConfineTo, Stealth, StealthOptions};
use backend::{Device, TrainBackend};
use ngp::data::{Dataset, LoadOptions, Split};
use ngp::encoding::{GridConfig, reference_indices};
use ngp::error::{Error, Result};
use ngp::model::Model;
use ngp::network::{ModelConfig, NerfLayout};
use ngp::train::{SceneSpec, Schedule, StepStats, TrainConfig};
use std::path::Path;
use std::sync::Arc;

#[cfg(feature = "clap")]
use crate::options::choice;

/// The model's hash grid.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct GridOptions {
    /// Hash-grid levels.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 16))]
    pub levels: u32,
    /// Features per level.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 2))]
    pub features: u32,
    /// log2 of the hash table size T.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 19))]
    pub log2_t: u32,
}

impl Default for GridOptions {
    fn default() -> Self {
        GridOptions {
            levels: 16,
            features: 2,
            log2_t: 19,
        }
    }
}

impl GridOptions {
    /// The grid (base resolution 16, the reference's).
    pub fn grid(&self) -> GridConfig {
        GridConfig {
            n_levels: self.levels,
            n_features: self.features,
            log2_hashmap_size: self.log2_t,
            base_resolution: 16,
        }
    }
}

/// How every step trains.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct StepOptions {
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0))]
    pub seed: u64,
    /// Target trained samples per step (the reference's 2^18 by default).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 1 << 18))]
    pub batch: u32,
    /// Fraction of the reference's occupancy-grid update samples.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 1.0))]
    pub occupancy_fraction: f32,
    /// Density evaluations per trained sample that occupancy-grid updates may spend: after a
    /// first whole update, each of the reference's updates draws the share of its cells the
    /// steps since the last one paid for (0: the reference's updates, every cell at each of
    /// the first 32 steps). Default: 1 on the CPU, where a capture's whole update costs
    /// seconds; a GPU keeps the reference's.
    #[cfg_attr(feature = "clap", arg(long, value_name = "R"))]
    pub occupancy_budget: Option<f32>,
    /// Samples a training ray should reach the loss with: while its rays, counted at the
    /// reference's step, have at least twice as many, a step marches 2, 4 or 8 of the
    /// reference's steps per sample, so that it trains that many times the rays while a
    /// capture's grid is still full of fog (a 360° room); the stride falls back to 1 as the
    /// rays shorten. The model and how it renders stay the reference's. 0: the reference's
    /// step throughout. Default: 96 on the CPU; a GPU keeps the reference's.
    #[cfg_attr(feature = "clap", arg(long, value_name = "S"))]
    pub coarse_march: Option<u32>,
    /// Worker threads (gradient partitions, each a whole gradient buffer); 0 = one per core;
    /// at most 256, and no more than the memory available holds.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0))]
    pub workers: usize,
}

impl Default for StepOptions {
    fn default() -> Self {
        StepOptions {
            seed: 0,
            batch: 1 << 18,
            occupancy_fraction: 1.0,
            occupancy_budget: None,
            coarse_march: None,
            workers: 0,
        }
    }
}

impl StepOptions {
    /// The reference's occupancy-grid schedule and march step on every device (where
    /// `Default` leaves each to the device: a budget and a coarse march on the CPU): the
    /// schedule the experiments' and the demo's recorded figures were made on.
    pub fn reference_schedule(seed: u64, batch: u32, occupancy_fraction: f32) -> StepOptions {
        StepOptions {
            seed,
            batch,
            occupancy_fraction,
            occupancy_budget: Some(0.0),
            coarse_march: Some(0),
            workers: 0,
        }
    }
}

/// How hidden scenes train beside the cover.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct HiddenOptions {
    /// How the cover and the hidden scenes share the steps.
    #[cfg_attr(
        feature = "clap",
        arg(long, value_parser = choice::<Schedule>(), default_value_t = Schedule::Mixed)
    )]
    pub schedule: Schedule,
    /// Loss weight of each hidden scene relative to the cover's 1: where the scenes share
    /// table entries, a larger weight moves quality from the cover to the hidden scenes.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 1.0))]
    pub hidden_weight: f32,
    /// Steps the cover trains alone before the hidden scenes join (they train for the
    /// remaining steps). A real capture's first steps settle its occupancy grid and its
    /// background; a few hundred steps of it alone keep most of the quality a hidden scene
    /// otherwise costs it (fox: −0.3 dB against −2.1 dB at 600 steps; benchmarks/stego.md,
    /// "A cover warm-up").
    #[cfg_attr(feature = "clap", arg(long, value_name = "N", default_value_t = 0))]
    pub hidden_from: u32,
    /// The samples a step trains of each hidden scene, as a fraction of `--batch` (the
    /// cover trains all of them; at least 1/16). Every hidden scene otherwise costs a step as
    /// much as the cover: a hidden text needs far fewer, and at a fixed time the cover keeps
    /// the steps it would lose (a 360° capture with a room and a text, benchmarks/engine.md,
    /// "Stego on a 360° cover").
    #[cfg_attr(feature = "clap", arg(long, value_name = "F", default_value_t = 1.0))]
    pub hidden_batch: f32,
    /// Robust: confine the hidden scenes to the table entries the cover's own occupancy
    /// grid reaches, so that resetting the entries the cover cannot reach (`stegongp
    /// attack … purify`), which is free for the cover, leaves them; the key files record
    /// it (`"robust": true`, written by train), so reading needs only the key. Combines
    /// with --stealth (README, "What the hidden scene survives").
    #[cfg_attr(feature = "clap", arg(long))]
    pub robust: bool,
    #[cfg_attr(feature = "clap", command(flatten))]
    pub stealth: StealthOptions,
}

impl Default for HiddenOptions {
    fn default() -> Self {
        HiddenOptions {
            schedule: Schedule::Mixed,
            hidden_weight: 1.0,
            hidden_from: 0,
            hidden_batch: 1.0,
            robust: false,
            stealth: StealthOptions::default(),
        }
    }
}

impl HiddenOptions {
    /// The checks that need no scene: a weight that is a positive number, stealth's own.
    pub fn check(&self) -> Result<()> {
        if !(self.hidden_weight.is_finite() && self.hidden_weight > 0.0) {
            return Err(Error::Config(
                "--hidden-weight must be a positive number".into(),
            ));
        }
        if !(self.hidden_batch >= 1.0 / 16.0 && self.hidden_batch <= 1.0) {
            return Err(Error::Config(format!(
                "--hidden-batch must be between 1/16 and 1, not {}",
                self.hidden_batch
            )));
        }
        self.stealth.check(self.stealth.enabled)
    }

    /// Refuses a cover warm-up that leaves the hidden scenes none of `steps` steps.
    pub fn check_steps(&self, steps: u32) -> Result<()> {
        if self.hidden_from >= steps {
            return Err(Error::Config(format!(
                "--hidden-from {} leaves the hidden scenes none of the {steps} training steps",
                self.hidden_from
            )));
        }
        Ok(())
    }

    /// The options as they apply to a model of `n_hidden` hidden scenes: none without one
    /// (a plain model trains plain), and stealth's own only with stealth.
    pub fn applied(&self, n_hidden: usize) -> HiddenOptions {
        if n_hidden == 0 {
            return HiddenOptions::default();
        }
        let mut o = *self;
        if !o.stealth.enabled {
            o.stealth = StealthOptions::default();
        }
        o
    }

    /// Trainer steps a run of `n_steps` (per scene, as the experiments count them) takes:
    /// the random-scene schedule trains one scene a step.
    pub fn steps_for(&self, n_steps: u32, n_scenes: usize) -> u32 {
        n_steps.saturating_mul(self.steps_per_round(n_scenes))
    }

    /// Trainer steps in which every scene trains once, on average.
    pub fn steps_per_round(&self, n_scenes: usize) -> u32 {
        match self.schedule {
            Schedule::Mixed => 1,
            Schedule::RandomScene => n_scenes.max(1) as u32,
        }
    }
}

/// How long a model trains.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Budget {
    /// Trainer steps.
    Steps(u32),
    /// Seconds of training (the steps' own time: setup and evaluations excluded), ending on
    /// a whole round of steps (under the random-scene schedule, a multiple of the scene
    /// count).
    Seconds(f64),
}

/// What the model file's `loss` field records.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum StoredLoss {
    /// The cover's loss smoothed over the steps (an EMA of 0.95), as instant-ngp's GUI
    /// shows and `train` has always written.
    #[default]
    Smoothed,
    /// The cover's loss at its last step, as the experiments and the demo have always
    /// written (their earlier models, and the detector fitted on them, stay comparable).
    Last,
}

/// A hidden scene and its key.
pub struct HiddenScene {
    pub dataset: Arc<Dataset>,
    pub key: Key,
    /// How messages name the scene's key (its file, say).
    pub key_name: String,
}

impl HiddenScene {
    /// Loads `dir`'s training images as a hidden scene under `key` (named `key_name` in
    /// messages), placed in the cover's box of `cover_box`; refused when the scene is larger
    /// than its key's box or than the cover's.
    pub fn load(
        dir: &Path,
        key: Key,
        key_name: &str,
        opts: &LoadOptions,
        cover_box: u32,
    ) -> Result<HiddenScene> {
        let mut data = Dataset::load(dir, Split::Train, opts)?;
        data.fit_into_box(cover_box, key.scene_box())
            .map_err(|e| Error::Other(format!("{e} (placing it with its key {key_name})")))?;
        Ok(HiddenScene {
            dataset: Arc::new(data),
            key,
            key_name: key_name.to_string(),
        })
    }
}

/// Everything one model's training needs.
pub struct Recipe {
    /// The architecture; its `aabb_scale` is the cover's box, every scene's.
    pub model: ModelConfig,
    /// The cover's training images (trained under the reference index).
    pub cover: Arc<Dataset>,
    pub hidden: Vec<HiddenScene>,
    pub steps: StepOptions,
    pub options: HiddenOptions,
    pub budget: Budget,
    pub stored_loss: StoredLoss,
}

impl Recipe {
    /// A plain model of `cover`: no hidden scene, no stealth.
    pub fn plain(
        model: ModelConfig,
        cover: Arc<Dataset>,
        steps: StepOptions,
        budget: Budget,
    ) -> Self {
        Recipe {
            model,
            cover,
            hidden: Vec::new(),
            steps,
            options: HiddenOptions::default(),
            budget,
            stored_loss: StoredLoss::default(),
        }
    }

    /// Every check, before anything is trained or written.
    pub fn check(&self) -> Result<()> {
        self.options.check()?;
        let layout = NerfLayout::new(self.model)?;
        if self.steps.batch == 0 {
            return Err(Error::Config("--batch must be at least 1".into()));
        }
        if !(self.steps.occupancy_fraction.is_finite() && self.steps.occupancy_fraction > 0.0) {
            return Err(Error::Config(
                "--occupancy-fraction must be a positive number".into(),
            ));
        }
        if let Some(r) = self.steps.occupancy_budget
            && !(r.is_finite() && r >= 0.0)
        {
            return Err(Error::Config(
                "--occupancy-budget must be a number ≥ 0 (0: the reference's schedule)".into(),
            ));
        }
        match self.budget {
            Budget::Steps(0) => return Err(Error::Config("a budget of 0 steps".into())),
            Budget::Seconds(s) if !(s.is_finite() && s > 0.0) => {
                return Err(Error::Config(
                    "a training time must be a positive number of minutes".into(),
                ));
            }
            _ => {}
        }
        if self.hidden.is_empty() {
            if self.options.stealth.enabled {
                return Err(Error::Config(
                    "--stealth needs at least one --hidden scene".into(),
                ));
            }
            if self.options.hidden_from > 0 {
                return Err(Error::Config(
                    "--hidden-from needs at least one --hidden scene".into(),
                ));
            }
            if self.options.robust {
                return Err(Error::Config(
                    "--robust needs at least one --hidden scene".into(),
                ));
            }
        }
        if let Budget::Steps(steps) = self.budget
            && !self.hidden.is_empty()
        {
            self.options.check_steps(steps)?;
        }
        for (i, h) in self.hidden.iter().enumerate() {
            h.key.validate_for(&layout.grid).map_err(|e| {
                Error::Other(format!("{}: key does not fit this model: {e}", h.key_name))
            })?;
            if h.key.robust() != self.options.robust {
                return Err(Error::Config(format!(
                    "{}: the key {} the robust mode and the training {}: a key holder reads \
                     the scene as its key says",
                    h.key_name,
                    if h.key.robust() {
                        "records"
                    } else {
                        "does not record"
                    },
                    if self.options.robust {
                        "uses it"
                    } else {
                        "does not"
                    }
                )));
            }
            if h.key.is_reference() {
                return Err(Error::Config(format!(
                    "{}: this key is the reference index Π, which is the cover's: the hidden scene would overwrite it",
                    h.key_name
                )));
            }
            if let Some(other) = self.hidden[..i].iter().find(|o| o.key.same_index(&h.key)) {
                return Err(Error::Config(format!(
                    "{} and {}: two hidden scenes share one key and would overwrite each other",
                    h.key_name, other.key_name
                )));
            }
        }
        for data in std::iter::once(&self.cover).chain(self.hidden.iter().map(|h| &h.dataset)) {
            if data.aabb_scale != self.model.aabb_scale {
                return Err(Error::Config(format!(
                    "{}: aabb_scale {} differs from the model's {}",
                    data.root.display(),
                    data.aabb_scale,
                    self.model.aabb_scale
                )));
            }
        }
        Ok(())
    }

    /// The engine's configuration of this recipe on `device` (a checked recipe: without
    /// hidden scenes there is no warm-up).
    pub fn train_config(&self, device: &Device) -> TrainConfig {
        TrainConfig {
            seed: self.steps.seed,
            batch_samples: self.steps.batch,
            occupancy_fraction: self.steps.occupancy_fraction,
            occupancy_budget: self.occupancy_budget(device),
            coarse_march: self.coarse_march(device),
            schedule: self.options.schedule,
            others_weight: self.options.hidden_weight,
            others_batch: self.options.hidden_batch,
            solo_steps: self.options.hidden_from,
            workers: self.steps.workers,
            ..Default::default()
        }
    }

    /// The occupancy-update budget training on `device` uses: the one asked for, else the
    /// device's ([`Device::default_occupancy_budget`]); `None` for the reference's schedule.
    pub fn occupancy_budget(&self, device: &Device) -> Option<f32> {
        match self.steps.occupancy_budget {
            Some(r) => Some(r).filter(|&r| r > 0.0),
            None => device.default_occupancy_budget(),
        }
    }

    /// The coarse march's aim on `device` ([`ngp::train::coarse`]): the one asked for, else
    /// the device's ([`Device::default_coarse_march`]); `None` for the reference's step.
    pub fn coarse_march(&self, device: &Device) -> Option<u32> {
        match self.steps.coarse_march {
            Some(s) => Some(s).filter(|&s| s > 0),
            None => device.default_coarse_march(),
        }
    }

    /// Checks the recipe and starts its training on `device`.
    pub fn start<'d>(&self, device: &'d Device) -> Result<Training<'d>> {
        self.check()?;
        let layout = NerfLayout::new(self.model)?;
        let mut scenes = vec![SceneSpec {
            dataset: self.cover.clone(),
            indices: reference_indices(&layout.grid),
        }];
        scenes.extend(self.hidden.iter().map(|h| SceneSpec {
            dataset: h.dataset.clone(),
            indices: h.key.level_indices(&layout.grid),
        }));
        let config = self.train_config(device);
        let solo = config.solo_steps;
        let mut trainer = device.trainer(self.model, scenes, config)?;
        let keys: Vec<Key> = self.hidden.iter().map(|h| h.key.clone()).collect();
        match (self.options.stealth.enabled, self.options.robust) {
            (true, robust) => {
                let to = if robust {
                    ConfineTo::Reachable
                } else {
                    ConfineTo::Moved
                };
                let policy = Stealth::new(layout, &keys, &self.options.stealth)?.confined_to(to);
                trainer.set_policy(Box::new(policy))?;
            }
            (false, true) => trainer.set_policy(Box::new(Stealth::robust(layout, &keys)?))?,
            (false, false) => {}
        }
        Ok(Training {
            trainer,
            budget: self.budget,
            per_round: self.options.steps_per_round(1 + self.hidden.len()),
            solo,
            stored_loss: self.stored_loss,
            totals: Totals::default(),
            last_loss: 0.0,
            smoothed: None,
            shown: 0.0,
            flushed: false,
        })
    }
}

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

/// A recipe's training in progress.
pub struct Training<'d> {
    trainer: Box<dyn TrainBackend + 'd>,
    budget: Budget,
    per_round: u32,
    solo: u32,
    stored_loss: StoredLoss,
    totals: Totals,
    last_loss: f32,
    smoothed: Option<f32>,
    shown: f32,
    /// Whether the trainer's measurements not yet reported were added once the budget was
    /// spent (a GPU reads its steps' measurements late).
    flushed: bool,
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

    /// Runs to the budget, calling `each` after every step.
    pub fn run(&mut self, mut each: impl FnMut(&Self, &StepStats) -> Result<()>) -> Result<()> {
        while let Some(st) = self.step()? {
            each(self, &st)?;
        }
        Ok(())
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
        if f.str("format")? != RUN_STATE_FORMAT {
            return Err(f.err("format", format!("not a run state ({RUN_STATE_FORMAT})")));
        }
        let v = f.u64("version")?;
        if v != RUN_STATE_VERSION {
            return Err(f.err(
                "version",
                format!("{v}: this program reads version {RUN_STATE_VERSION}"),
            ));
        }
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
        crate::keyfile::write_secret(path, &self.save_state()?)
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
