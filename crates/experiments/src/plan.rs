//! An experiment as a plan of jobs that any scheduler runs (Slurm, GNU parallel, an indexed
//! Kubernetes Job), each in its own process, on nodes that share a filesystem; the report
//! written from their models is the one a single machine writes. `stegongp experiment NAME
//! --plan DIR` makes one, `experiment run-job DIR ID` runs a job ([`run_job`]),
//! `experiment collect DIR` writes the report ([`collect`]).
//!
//! A plan's folder holds `plan.json` (the jobs: id, command, inputs, outputs, the jobs each
//! waits for, device, cost) and, per job, `jobs/ID.lock` (held while it runs: a second copy
//! is refused), `jobs/ID.log` (everything it printed, every attempt) and `jobs/ID.done`
//! (written last: a finished job does nothing when run again). The experiment's own files
//! (scenes, models, report) are where `experiment NAME --out DIR` puts them.
//!
//! The experiment itself is the caller's to run (from the options the plan recorded): a
//! job and the report hand it over as a closure, and this module keeps the files around it.

use crate::jobs::{JobMode, PlannedModel};
use crate::report::Report;
use crate::setup::Experiment;
use crate::tee::Tee;
use ngp::error::{Error, Result};
use ngp::util::write_atomic;
use serde_json::{Value, json};
use std::fmt::Display;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

/// What a plan's document says it is.
const PLAN_FORMAT: &str = "stegongp-experiment-plan";
/// Bumped when a plan's layout or the meaning of its jobs changes.
const PLAN_VERSION: u64 = 1;
/// The program's version, which a plan records and its jobs must share (the workspace's
/// crates share one version, the program's).
const STEGONGP_VERSION: &str = env!("CARGO_PKG_VERSION");
/// The job that writes the report once every model's job has finished.
pub const REPORT_JOB: &str = "report";

/// An I/O or parsing error after a message, as `message: error`.
pub(crate) fn context<E: Display>(message: impl Display) -> impl FnOnce(E) -> Error {
    move |e| Error::Other(format!("{message}: {e}"))
}

/// An error as its own message alone.
pub(crate) fn bare<E: Display>(e: E) -> Error {
    Error::Other(e.to_string())
}

/// A plan as read back: its document and the job list.
pub struct Plan {
    pub dir: PathBuf,
    pub doc: Value,
    pub experiment: Experiment,
}

impl Plan {
    /// `DIR/plan.json`.
    pub fn file(dir: &Path) -> PathBuf {
        dir.join("plan.json")
    }

    /// Reads and checks `DIR/plan.json`: a plan, of this version, naming an experiment.
    pub fn read(dir: &Path) -> Result<Plan> {
        let path = Self::file(dir);
        if !dir.is_dir() {
            return Err(Error::Other(format!(
                "{}: no such folder (expected a plan's folder, made by `experiment NAME --plan DIR`)",
                dir.display()
            )));
        }
        let bytes = std::fs::read(&path).map_err(context(format!(
            "{}: not a plan's folder (no plan.json; make one with `experiment NAME --plan {}`)",
            dir.display(),
            dir.display()
        )))?;
        if bytes.len() > 64 << 20 {
            return Err(Error::Other(format!(
                "{}: {} bytes, too large for a plan",
                path.display(),
                bytes.len()
            )));
        }
        let doc: Value = serde_json::from_slice(&bytes)
            .map_err(context(format!("{}: not JSON", path.display())))?;
        if doc["format"] != PLAN_FORMAT {
            return Err(Error::Other(format!(
                "{}: not a stegongp experiment plan",
                path.display()
            )));
        }
        let (v, by) = (
            doc["version"].as_u64(),
            doc["stegongp"].as_str().unwrap_or("?"),
        );
        if v != Some(PLAN_VERSION) || by != STEGONGP_VERSION {
            return Err(Error::Other(format!(
                "{}: a plan of format {} written by stegongp {by}; this is stegongp {STEGONGP_VERSION} (plan format {PLAN_VERSION}): make the plan again with this version, or run its jobs with the version that made it",
                path.display(),
                v.map_or("?".into(), |v| v.to_string()),
            )));
        }
        let experiment: Experiment = doc["experiment"]
            .as_str()
            .unwrap_or("")
            .parse()
            .map_err(context(format!("{}: field experiment", path.display())))?;
        if !doc["jobs"].is_array() || !doc["argv"].is_array() {
            return Err(Error::Other(format!(
                "{}: no jobs or argv list",
                path.display()
            )));
        }
        Ok(Plan {
            dir: dir.to_path_buf(),
            doc,
            experiment,
        })
    }

    pub fn jobs(&self) -> &[Value] {
        self.doc["jobs"].as_array().map_or(&[], |v| v.as_slice())
    }

    pub fn job(&self, id: &str) -> Result<&Value> {
        self.jobs().iter().find(|j| j["id"] == id).ok_or_else(|| {
            let ids: Vec<&str> = self
                .jobs()
                .iter()
                .filter_map(|j| j["id"].as_str())
                .collect();
            let shown = ids.iter().take(6).copied().collect::<Vec<_>>().join(", ");
            Error::Other(format!(
                "{}: no job '{id}' (its {} jobs: {shown}{})",
                Self::file(&self.dir).display(),
                ids.len(),
                if ids.len() > 6 { ", …" } else { "" }
            ))
        })
    }

    pub fn done_path(&self, id: &str) -> PathBuf {
        self.dir.join("jobs").join(format!("{id}.done"))
    }

    pub fn log_path(&self, id: &str) -> PathBuf {
        self.dir.join("jobs").join(format!("{id}.log"))
    }

    pub fn is_done(&self, id: &str) -> bool {
        self.done_path(id).is_file()
    }

    /// Enters the folder the plan was made from, so that relative paths in its recorded
    /// options mean what they meant there.
    pub fn enter_cwd(&self) -> Result<()> {
        let cwd = self.doc["cwd"].as_str().unwrap_or(".");
        std::env::set_current_dir(cwd).map_err(context(format!(
            "the plan was made in {cwd}, which this node cannot enter (a plan's paths must be the same on every node)"
        )))
    }

    /// The experiment's options as the plan recorded them (the name first, `--out DIR`
    /// last), to be parsed again.
    pub fn argv(&self) -> Vec<String> {
        self.doc["argv"]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|v| v.as_str().map(String::from))
            .collect()
    }
}

/// The experiment's options in the command line `all` (the program's whole argv), without
/// the plan's own (`--plan`, `--slurm`, `--submit`, `--sbatch`) and without `--out`, which
/// is the plan's folder `dir`.
pub fn recorded_argv(all: &[String], name: &str, dir: &Path) -> Result<Vec<String>> {
    let start = all
        .iter()
        .position(|s| s == "experiment")
        .map(|i| i + 1)
        .ok_or_else(|| {
            Error::Other("cannot find the experiment's options on the command line".into())
        })?;
    let mut out = Vec::new();
    let mut it = all[start..].iter();
    while let Some(s) = it.next() {
        let takes_value = ["--plan", "--sbatch", "--out"];
        if takes_value.contains(&s.as_str()) {
            it.next();
            continue;
        }
        if takes_value.iter().any(|f| s.starts_with(&format!("{f}=")))
            || s == "--slurm"
            || s == "--submit"
        {
            continue;
        }
        out.push(s.clone());
    }
    if out.first().map(String::as_str) != Some(name) {
        return Err(Error::Other(
            "the experiment's name must come first after `experiment`".into(),
        ));
    }
    out.extend(["--out".to_string(), dir.display().to_string()]);
    Ok(out)
}

/// Seconds a job is expected to take: its samples at a stated rate, plus what every model
/// pays besides (reading its scenes, the occupancy grid's first updates, saving).
fn estimate_seconds(m: &PlannedModel, gpu: bool) -> f64 {
    // Measured: 2 CPU cores ≈ 600 k trained samples/s on lego ×4 (BENCHMARKS.md); an
    // H100 28.1 M samples/s on lego 800 px.
    let (rate, fixed) = if gpu { (28.1e6, 30.0) } else { (6.0e5, 10.0) };
    match (m.samples, m.seconds) {
        (Some(s), _) => s as f64 / rate + fixed,
        (None, Some(t)) => t + fixed,
        (None, None) => fixed,
    }
}

/// What a plan's document records besides its jobs.
pub struct PlanSpec<'a> {
    /// The plan's folder (absolute).
    pub dir: &'a Path,
    pub experiment: Experiment,
    /// The experiment's options, from [`recorded_argv`].
    pub argv: Vec<String>,
    /// Where the report goes (the experiment's output folder).
    pub report_dir: &'a Path,
    /// Whether the jobs train on a GPU.
    pub gpu: bool,
}

/// Writes the plan of the models an experiment's dry run recorded ([`JobMode::planned`]):
/// `DIR/plan.json` (a job a model, the report job after them all), `DIR/jobs/` and
/// `DIR/waves/`; returns it as read back.
pub fn write(spec: PlanSpec, models: &[PlannedModel]) -> Result<Plan> {
    let dir = spec.dir;
    let doc = plan_document(spec, models)?;
    let text = serde_json::to_string_pretty(&doc).map_err(bare)?;
    write_atomic(&Plan::file(dir), text.as_bytes())?;
    std::fs::create_dir_all(dir.join("jobs")).map_err(bare)?;
    let plan = Plan::read(dir)?;
    write_waves(&plan)?;
    Ok(plan)
}

fn plan_document(spec: PlanSpec, models: &[PlannedModel]) -> Result<Value> {
    let PlanSpec {
        dir,
        experiment: name,
        argv,
        report_dir,
        gpu,
    } = spec;
    let exe = std::env::current_exe().map_err(bare)?;
    let device = if gpu { "gpu" } else { "cpu" };
    let command = |args: &[&str]| -> Value {
        let mut c = vec![exe.display().to_string(), "experiment".into()];
        c.extend(args.iter().map(|s| s.to_string()));
        json!(c)
    };
    let d = dir.display().to_string();
    let mut jobs: Vec<Value> = Vec::new();
    let mut seen = std::collections::HashSet::new();
    for m in models {
        if !seen.insert(m.id.clone()) {
            // A scene trained once for several pairs is met again: one job.
            continue;
        }
        let mut j = m.to_json();
        j["kind"] = json!("train");
        j["command"] = command(&["run-job", &d, &m.id]);
        j["outputs"] = json!([m.output, m.output.with_extension("json")]);
        j["device"] = json!(device);
        j["estimated_seconds"] = json!(estimate_seconds(m, gpu).round());
        jobs.push(j);
    }
    let all: Vec<Value> = jobs.iter().map(|j| j["id"].clone()).collect();
    // Scoring every model once they are all there (LPIPS, renders at every held-out view).
    let score_s: f64 = models.len() as f64 * if gpu { 20.0 } else { 60.0 };
    jobs.push(json!({
        "id": REPORT_JOB, "kind": "report", "label": "the report, from every model",
        "command": command(&["collect", &d]), "after": all, "inputs": [],
        "outputs": [report_dir.join("report.md"), report_dir.join("report.json")],
        "device": device, "estimated_seconds": score_s.max(30.0),
    }));
    Ok(json!({
        "format": PLAN_FORMAT, "version": PLAN_VERSION, "stegongp": STEGONGP_VERSION,
        "experiment": name.name(), "dir": dir, "cwd": std::env::current_dir().map_err(bare)?,
        "argv": argv, "binary": exe, "device": device,
        "shared_filesystem": "every node runs the jobs on the same paths: the plan's folder, the binary, the datasets and the folder the plan was made in",
        "rates": if gpu { "estimates at 28.1 M trained samples/s (an H100, lego 800 px) + 30 s a model" } else { "estimates at 600 k trained samples/s (2 CPU cores, lego ×4) + 10 s a model" },
        "jobs": jobs,
    }))
}

/// `DIR/waves/K.txt`: the ids of the training jobs of wave K, one a line (wave 0 waits for
/// nothing; wave K + 1 for jobs of waves up to K), for schedulers that take a list.
fn write_waves(plan: &Plan) -> Result<()> {
    let wdir = plan.dir.join("waves");
    if wdir.is_dir() {
        std::fs::remove_dir_all(&wdir)
            .map_err(context(format!("{}: cannot replace", wdir.display())))?;
    }
    std::fs::create_dir_all(&wdir)
        .map_err(context(format!("{}: cannot create", wdir.display())))?;
    for (k, ids) in crate::slurm::waves(plan.jobs())?.iter().enumerate() {
        write_atomic(
            &wdir.join(format!("{k:02}.txt")),
            (ids.join("\n") + "\n").as_bytes(),
        )?;
    }
    Ok(())
}

/// What `run-job` did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum JobRun {
    /// The job had finished before: nothing was run.
    AlreadyDone,
    /// The job ran and finished in this many seconds.
    Finished { seconds: f64 },
}

/// Runs training job `id` of `plan` (not the report job: see [`collect`]): refused while
/// another copy runs or while a job it waits for has not finished, nothing done if it
/// finished before; else `run` (the experiment, as [`JobMode::One`]`(id)`) with stderr
/// copied into the job's log, its outputs checked, and `jobs/ID.done` written.
pub fn run_job<E>(
    plan: &Plan,
    id: &str,
    run: impl FnOnce() -> std::result::Result<(), E>,
) -> std::result::Result<JobRun, E>
where
    E: From<Error> + Display,
{
    let job = plan.job(id)?.clone();
    let _lock = lock_job(plan, id)?;
    if plan.is_done(id) {
        return Ok(JobRun::AlreadyDone);
    }
    for w in job["after"].as_array().into_iter().flatten() {
        let w = w.as_str().unwrap_or("");
        if !plan.is_done(w) {
            return Err(Error::Other(format!(
                "job {id} waits for job {w}, which has not finished (run it first)"
            ))
            .into());
        }
    }
    let tee = Tee::start(&plan.log_path(id))?;
    let t0 = std::time::Instant::now();
    eprintln!("== job {id} on {} ==", host());
    let checked = || -> std::result::Result<(), E> {
        run()?;
        for o in job["outputs"].as_array().into_iter().flatten() {
            let o = Path::new(o.as_str().unwrap_or(""));
            if !o.to_string_lossy().contains('*') && !o.exists() {
                return Err(
                    Error::Other(format!("job {id} ran but {} is not there", o.display())).into(),
                );
            }
        }
        Ok(())
    };
    let result = checked();
    if let Err(e) = &result {
        eprintln!("job {id} failed: {e:#}");
    }
    tee.stop();
    result?;
    let seconds = t0.elapsed().as_secs_f64();
    let done = json!({"id": id, "seconds": seconds, "host": host()});
    write_atomic(
        &plan.done_path(id),
        serde_json::to_string_pretty(&done)
            .map_err(bare)?
            .as_bytes(),
    )?;
    Ok(JobRun::Finished { seconds })
}

/// Holds `jobs/ID.lock` while the job runs: a second copy of a running job is refused.
fn lock_job(plan: &Plan, id: &str) -> Result<File> {
    let jobs = plan.dir.join("jobs");
    std::fs::create_dir_all(&jobs)
        .map_err(context(format!("{}: cannot create", jobs.display())))?;
    let path = jobs.join(format!("{id}.lock"));
    let f = File::options()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(&path)
        .map_err(context(format!("{}: cannot open", path.display())))?;
    match f.try_lock() {
        Ok(()) => Ok(f),
        Err(std::fs::TryLockError::WouldBlock) => Err(Error::Other(format!(
            "job {id} is running already ({} is held by another process): not started twice",
            path.display()
        ))),
        Err(std::fs::TryLockError::Error(e)) => Err(context(path.display())(e)),
    }
}

fn host() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|s| s.trim().to_string())
        .unwrap_or_else(|_| "?".into())
}

/// Writes `plan`'s report: `run` is the experiment as [`JobMode::Collect`] (every model
/// read from its job's file). Refused while a training job has not finished, unless
/// `partial` (then said on stderr, and the report lists them); `jobs/report.done` is
/// written once a report lacks nothing. Returns what `run` returned.
pub fn collect<T, E>(
    plan: &Plan,
    partial: bool,
    run: impl FnOnce(Arc<JobMode>) -> std::result::Result<(T, Report), E>,
) -> std::result::Result<(T, Report), E>
where
    E: From<Error>,
{
    let unfinished: Vec<&Value> = plan
        .jobs()
        .iter()
        .filter(|j| j["kind"] == "train" && !plan.is_done(j["id"].as_str().unwrap_or("")))
        .collect();
    if !unfinished.is_empty() {
        let mut msg = format!(
            "{} of {} jobs of {} have not finished:",
            unfinished.len(),
            plan.jobs().len() - 1,
            plan.dir.display()
        );
        for j in unfinished.iter().take(20) {
            let id = j["id"].as_str().unwrap_or("");
            msg += &format!("\n  {id}: {}", log_tail(&plan.log_path(id)));
        }
        if !partial {
            return Err(Error::Other(format!(
                "{msg}\n(the report is not written; `collect --partial` writes it from the finished jobs and says which are missing)"
            ))
            .into());
        }
        eprintln!("{msg}\n(a partial report: their models' figures stay empty)");
    }
    let _lock = lock_job(plan, REPORT_JOB)?;
    let mode = Arc::new(JobMode::Collect {
        partial,
        missing: Mutex::default(),
    });
    let (t, report) = run(mode)?;
    if report.missing_jobs.is_empty() {
        let done = json!({"id": REPORT_JOB, "host": host()});
        write_atomic(
            &plan.done_path(REPORT_JOB),
            serde_json::to_string_pretty(&done)
                .map_err(bare)?
                .as_bytes(),
        )?;
    }
    Ok((t, report))
}

/// The last lines of a job's log, on one line; or that it never ran.
fn log_tail(path: &Path) -> String {
    match std::fs::read_to_string(path) {
        Ok(s) => {
            let lines: Vec<&str> = s.lines().filter(|l| !l.trim().is_empty()).collect();
            let tail = &lines[lines.len().saturating_sub(3)..];
            format!("{} (log {})", tail.join(" | "), path.display())
        }
        Err(_) => "never started (no log)".into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn argv(s: &str) -> Vec<String> {
        s.split(' ').map(String::from).collect()
    }

    #[test]
    fn the_plans_own_options_are_not_recorded() {
        let all = argv(
            "stegongp experiment fidelity --steps 5 --plan p --slurm --sbatch=--qos=x --out o --seed 2",
        );
        let got = recorded_argv(&all, "fidelity", Path::new("/d")).unwrap();
        assert_eq!(got, argv("fidelity --steps 5 --seed 2 --out /d"));
        let misplaced = argv("stegongp experiment --steps 5 fidelity");
        assert!(recorded_argv(&misplaced, "fidelity", Path::new("/d")).is_err());
    }

    #[test]
    fn an_error_keeps_its_context_first() {
        let e = context("x: cannot create")(std::io::Error::other("denied"));
        assert_eq!(e.to_string(), "x: cannot create: denied");
    }
}
