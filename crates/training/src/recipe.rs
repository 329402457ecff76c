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

use crate::steps::{Totals, Training};
use backend::Device;
use dataset::LoadOptions;
use ngp::data::{Dataset, Split};
use ngp::encoding::{GridConfig, reference_indices};
use ngp::error::{Error, Result};
use ngp::network::{ModelConfig, NerfLayout};
use ngp::train::cameras::CameraRefinement;
use ngp::train::{SceneSpec, Schedule, TrainConfig};
use std::path::Path;
use std::sync::Arc;
use stego::keys::Key;
use stego::stealth::{ConfineTo, Stealth, StealthOptions};

#[cfg(feature = "clap")]
use stego::options::choice;

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
    /// Refine the training cameras while training: per image, a rotation and a translation
    /// learned from the photometric loss with their own Adam (instant-ngp's
    /// `optimize_extrinsics`), for captures whose poses are a little wrong. The cover's
    /// cameras only; nothing of them is written to the model. CPU only, off by default.
    #[cfg_attr(feature = "clap", arg(long))]
    pub refine_cameras: bool,
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
            refine_cameras: false,
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
            refine_cameras: false,
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
        let mut data = dataset::load(dir, Split::Train, opts)?;
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

    /// Every check, before anything is trained or written: the recipe as one that may
    /// start. A recipe is checked here once; [`Checked::start`] takes it as it is.
    pub fn check(self) -> Result<Checked> {
        self.check_all()?;
        Ok(Checked(self))
    }

    fn check_all(&self) -> Result<()> {
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
}

/// A recipe [`Recipe::check`] passed: the only kind that trains.
pub struct Checked(Recipe);

impl std::ops::Deref for Checked {
    type Target = Recipe;
    fn deref(&self) -> &Recipe {
        &self.0
    }
}

impl Checked {
    /// Starts the recipe's training on `device`.
    pub fn start<'d>(&self, device: &'d Device) -> Result<Training<'d>> {
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
        if self.steps.refine_cameras {
            trainer.refine_cameras(CameraRefinement::default())?;
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
