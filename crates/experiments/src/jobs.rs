//! An experiment as independent jobs (`experiment NAME --plan DIR`): every model it trains
//! is a job that another process — a Slurm array task, a GNU parallel slot, a pod — trains
//! alone into a file on a shared filesystem, and the report is written from those files.
//!
//! The experiments are not written twice. A plan is the experiment run dry
//! ([`JobMode::Plan`]: each model it would train is recorded; nothing is trained, scored or
//! written but the scenes every job shares); a job is the same dry run that trains its own
//! model when it reaches it ([`JobMode::One`]); the report is the experiment run with every
//! model read from its job's file ([`JobMode::Collect`]). Because the one code path decides
//! which models exist, a plan cannot list a model the report does not read, or miss one.

use ngp::data::Dataset;
use ngp::error::{Error, Result};
use ngp::model::Model;
use ngp::network::{ModelConfig, NerfLayout};
use ngp::occupancy::OccupancyGrid;
use score::eval::EvalResult;
use serde_json::{Value, json};
use std::path::PathBuf;
use std::sync::Mutex;

/// How an experiment treats the models it meets.
#[derive(Debug, Default)]
pub enum JobMode {
    /// Train every model here, one after another (the single-machine run).
    #[default]
    All,
    /// Record every model; train, score and write nothing.
    Plan(Mutex<Vec<PlannedModel>>),
    /// Train the model with this id (or find it stored); pass over the others.
    One(String),
    /// Train nothing: read every model from its job's file. A missing model is an error,
    /// or with `partial` a gap in the report (its scores empty), recorded in `missing`.
    Collect {
        partial: bool,
        missing: Mutex<Vec<String>>,
    },
}

/// One model of an experiment, as a job: what it trains, where it writes, what it waits for.
#[derive(Clone, Debug, PartialEq)]
pub struct PlannedModel {
    /// Stable: the same experiment with the same options gives the same ids.
    pub id: String,
    /// What the model is, in the report's words.
    pub label: String,
    /// The model file the job writes (a sidecar `.json` beside it is written last: a model
    /// without one is not finished).
    pub output: PathBuf,
    /// Dataset folders it reads.
    pub inputs: Vec<PathBuf>,
    /// Jobs whose models it needs first (a budget measured by another model's training).
    pub after: Vec<String>,
    /// Training steps over all its scenes; `None` where the budget is a time.
    pub steps: Option<u64>,
    /// Samples trained: steps × samples a step (`None` with `steps`).
    pub samples: Option<u64>,
    /// A budget in seconds (`--minutes`), where there is one instead of steps.
    pub seconds: Option<f64>,
}

impl PlannedModel {
    /// As a plan's job lists it.
    pub fn to_json(&self) -> Value {
        json!({"id": self.id, "label": self.label, "output": self.output,
            "inputs": self.inputs, "after": self.after, "steps": self.steps,
            "samples": self.samples, "budget_seconds": self.seconds})
    }
}

/// What to do with a model the experiment has reached.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Action {
    /// Train it (or reuse its stored file).
    Train,
    /// Stand a placeholder in for it: this run scores nothing.
    PassOver,
    /// Read it from its job's file.
    Read,
}

impl JobMode {
    /// What to do with `model`; a plan records it.
    pub(crate) fn action(&self, model: PlannedModel) -> Action {
        match self {
            JobMode::All => Action::Train,
            JobMode::Plan(list) => {
                lock(list).push(model);
                Action::PassOver
            }
            JobMode::One(id) if *id == model.id => Action::Train,
            JobMode::One(_) => Action::PassOver,
            JobMode::Collect { .. } => Action::Read,
        }
    }

    /// Whether this run scores its models and writes the report.
    pub fn scores(&self) -> bool {
        matches!(self, JobMode::All | JobMode::Collect { .. })
    }

    /// Whether this run trains the models it meets in its own process (keeping nothing but
    /// what the experiment always kept).
    pub fn in_process(&self) -> bool {
        matches!(self, JobMode::All)
    }

    /// A model the report needs is not stored: an error naming its job, or with `partial`
    /// a gap, noted.
    pub(crate) fn missing(&self, id: &str, output: &std::path::Path) -> Result<()> {
        match self {
            JobMode::Collect {
                partial: true,
                missing,
            } => {
                lock(missing).push(id.to_string());
                Ok(())
            }
            _ => Err(Error::Other(format!(
                "job {id} has not finished: {} (or its sidecar) is missing",
                output.display()
            ))),
        }
    }

    /// The models a plan recorded, in the order the experiment met them.
    pub fn planned(&self) -> Vec<PlannedModel> {
        match self {
            JobMode::Plan(list) => lock(list).clone(),
            _ => Vec::new(),
        }
    }

    /// The jobs a partial report lacks.
    pub fn missing_jobs(&self) -> Vec<String> {
        match self {
            JobMode::Collect { missing, .. } => lock(missing).clone(),
            _ => Vec::new(),
        }
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    // A poisoned list is still the list: the panic that poisoned it is reported elsewhere.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// A model that stands in for one this run does not have: the right size, all zeros, and a
/// NaN loss, which no trained model has ([`is_placeholder`]).
pub(crate) fn placeholder(config: ModelConfig, dataset: &Dataset) -> Result<Model> {
    let n = NerfLayout::new(config)?.n_params;
    Model::from_parts(
        config,
        vec![0.0; n],
        OccupancyGrid::new(config.aabb_scale),
        0,
        f32::NAN,
        dataset,
        (0, 0, 0),
    )
}

/// Whether `m` is a [`placeholder`].
pub(crate) fn is_placeholder(m: &Model) -> bool {
    m.loss.is_nan() && m.training_step == 0
}

/// The scores of a model that is not there: every figure empty (`null` in the report).
pub(crate) fn no_scores() -> EvalResult {
    EvalResult {
        protocol: Default::default(),
        background: [f32::NAN; 3],
        split_views: 0,
        psnr: f64::NAN,
        ssim: f64::NAN,
        lpips: None,
        n_views: 0,
        blank_psnr: f64::NAN,
        blank_ssim: f64::NAN,
        blank_lpips: None,
        views: Vec::new(),
        seconds: 0.0,
    }
}

/// A label as a job id's part: lower case ASCII letters, digits and '-'.
pub(crate) fn slug(label: &str) -> String {
    let mut s = String::new();
    for c in label.chars() {
        let c = match c {
            'Φ' | 'φ' => {
                s.push_str("phi");
                continue;
            }
            c if c.is_ascii_alphanumeric() => c.to_ascii_lowercase(),
            _ => '-',
        };
        if !(c == '-' && (s.is_empty() || s.ends_with('-'))) {
            s.push(c);
        }
    }
    s.trim_end_matches('-').to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn planned(id: &str) -> PlannedModel {
        PlannedModel {
            id: id.into(),
            label: id.into(),
            output: PathBuf::from(format!("{id}.ingp")),
            inputs: vec![],
            after: vec![],
            steps: Some(10),
            samples: Some(100),
            seconds: None,
        }
    }

    #[test]
    fn each_mode_decides_as_documented() {
        assert_eq!(JobMode::All.action(planned("a")), Action::Train);
        let plan = JobMode::Plan(Mutex::default());
        assert_eq!(plan.action(planned("a")), Action::PassOver);
        assert_eq!(plan.action(planned("b")), Action::PassOver);
        let ids: Vec<String> = plan.planned().into_iter().map(|m| m.id).collect();
        assert_eq!(ids, ["a", "b"]);
        let one = JobMode::One("b".into());
        assert_eq!(one.action(planned("a")), Action::PassOver);
        assert_eq!(one.action(planned("b")), Action::Train);
        assert!(!one.scores() && !plan.scores() && JobMode::All.scores());
        let strict = JobMode::Collect {
            partial: false,
            missing: Mutex::default(),
        };
        assert_eq!(strict.action(planned("a")), Action::Read);
        let e = strict
            .missing("a", std::path::Path::new("m/a.ingp"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("job a") && e.contains("m/a.ingp"), "{e}");
        let partial = JobMode::Collect {
            partial: true,
            missing: Mutex::default(),
        };
        partial.missing("a", std::path::Path::new("a")).unwrap();
        assert_eq!(partial.missing_jobs(), ["a"]);
    }

    #[test]
    fn slugs_are_plain_ascii() {
        assert_eq!(slug("plain cover"), "plain-cover");
        assert_eq!(slug("Φ=3"), "phi-3");
        assert_eq!(slug("T=2^18"), "t-2-18");
        assert_eq!(slug("primes m=4"), "primes-m-4");
        assert_eq!(slug("  x  "), "x");
    }
}
