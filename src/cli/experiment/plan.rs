//! `experiment NAME --plan DIR`, `experiment run-job DIR ID`, `experiment collect DIR`: an
//! experiment as a list of jobs that any scheduler runs (Slurm, GNU parallel, an indexed
//! Kubernetes Job), each in its own process, on nodes that share a filesystem; the report
//! written from their models is the one a single machine writes.
//!
//! A plan's folder holds `plan.json` (the jobs: id, command, inputs, outputs, the jobs each
//! waits for, device, cost) and, per job, `jobs/ID.lock` (held while it runs: a second copy
//! is refused), `jobs/ID.log` (everything it printed, every attempt) and `jobs/ID.done`
//! (written last: a finished job does nothing when run again). The experiment's own files
//! (scenes, models, report) are where `experiment NAME --out DIR` puts them.

use super::tee::Tee;
use super::{Args, experiment};
use anyhow::{Context, Result, bail};
use clap::Parser;
use serde_json::{Value, json};
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use stegongp::experiments::{Experiment, JobMode, PlannedModel};
use stegongp::util::write_atomic;

/// What a plan's document says it is.
const PLAN_FORMAT: &str = "stegongp-experiment-plan";
/// Bumped when a plan's layout or the meaning of its jobs changes.
const PLAN_VERSION: u64 = 1;
/// The job that writes the report once every model's job has finished.
pub(super) const REPORT_JOB: &str = "report";

/// Options of a plan and of its jobs.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct PlanArgs {
    /// Write the experiment as a plan of jobs into DIR (its output folder, on a filesystem
    /// every node sees) instead of running it: `plan.json`, then `experiment run-job DIR ID`
    /// for each job (in any order that respects `after`) and `experiment collect DIR`.
    #[arg(long, value_name = "DIR")]
    pub plan: Option<PathBuf>,
    /// With --plan: also write DIR/submit.sh, which submits the unfinished jobs to Slurm as
    /// job arrays (one task a job, one array per wave of dependencies) and the report job
    /// after them.
    #[arg(long, requires = "plan")]
    pub slurm: bool,
    /// With --plan --slurm: run DIR/submit.sh now (sbatch) and print the Slurm job ids.
    #[arg(long, requires = "slurm")]
    pub submit: bool,
    /// With --slurm: an option for every sbatch call (repeatable), e.g.
    /// `--sbatch=--partition=gpu` or `--sbatch=--account=lab`.
    #[arg(
        long = "sbatch",
        value_name = "OPTION",
        requires = "slurm",
        allow_hyphen_values = true
    )]
    pub sbatch: Vec<String>,
    /// collect: write the report from the jobs that finished, saying which did not (their
    /// models' figures empty), instead of refusing.
    #[arg(long)]
    pub partial: bool,
}

impl PlanArgs {
    /// The options that only a plan or its jobs take are refused elsewhere.
    pub(super) fn refuse_without_plan(&self) -> Result<()> {
        if self.partial {
            bail!("--partial belongs to `experiment collect DIR`");
        }
        Ok(())
    }
}

/// A plan as read back: its document and the job list.
pub(super) struct Plan {
    pub dir: PathBuf,
    pub doc: Value,
    pub experiment: Experiment,
}

impl Plan {
    fn file(dir: &Path) -> PathBuf {
        dir.join("plan.json")
    }

    /// Reads and checks `DIR/plan.json`: a plan, of this version, naming an experiment.
    pub fn read(dir: &Path) -> Result<Plan> {
        let path = Self::file(dir);
        if !dir.is_dir() {
            bail!(
                "{}: no such folder (expected a plan's folder, made by `experiment NAME --plan DIR`)",
                dir.display()
            );
        }
        let bytes = std::fs::read(&path).with_context(|| {
            format!(
                "{}: not a plan's folder (no plan.json; make one with `experiment NAME --plan {}`)",
                dir.display(),
                dir.display()
            )
        })?;
        if bytes.len() > 64 << 20 {
            bail!(
                "{}: {} bytes, too large for a plan",
                path.display(),
                bytes.len()
            );
        }
        let doc: Value = serde_json::from_slice(&bytes)
            .with_context(|| format!("{}: not JSON", path.display()))?;
        if doc["format"] != PLAN_FORMAT {
            bail!("{}: not a stegongp experiment plan", path.display());
        }
        let (v, by) = (
            doc["version"].as_u64(),
            doc["stegongp"].as_str().unwrap_or("?"),
        );
        if v != Some(PLAN_VERSION) || by != env!("CARGO_PKG_VERSION") {
            bail!(
                "{}: a plan of format {} written by stegongp {by}; this is stegongp {} (plan format {PLAN_VERSION}): make the plan again with this version, or run its jobs with the version that made it",
                path.display(),
                v.map_or("?".into(), |v| v.to_string()),
                env!("CARGO_PKG_VERSION")
            );
        }
        let experiment: Experiment = doc["experiment"]
            .as_str()
            .unwrap_or("")
            .parse()
            .with_context(|| format!("{}: field experiment", path.display()))?;
        if !doc["jobs"].is_array() || !doc["argv"].is_array() {
            bail!("{}: no jobs or argv list", path.display());
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
            anyhow::anyhow!(
                "{}: no job '{id}' (its {} jobs: {shown}{})",
                Self::file(&self.dir).display(),
                ids.len(),
                if ids.len() > 6 { ", …" } else { "" }
            )
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

    /// The experiment's options as the plan recorded them, parsed again, in the folder the
    /// plan was made from (relative paths in them mean what they meant there).
    fn args(&self) -> Result<Args> {
        let cwd = self.doc["cwd"].as_str().unwrap_or(".");
        std::env::set_current_dir(cwd).with_context(|| {
            format!(
                "the plan was made in {cwd}, which this node cannot enter (a plan's paths must be the same on every node)"
            )
        })?;
        let argv: Vec<String> = self.doc["argv"]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|v| v.as_str().map(String::from))
            .collect();
        #[derive(Parser)]
        struct Options {
            #[command(flatten)]
            args: Args,
        }
        let o = Options::try_parse_from(std::iter::once("experiment".to_string()).chain(argv))
            .with_context(|| {
                format!(
                    "{}: its options no longer parse",
                    Self::file(&self.dir).display()
                )
            })?;
        Ok(o.args)
    }
}

/// The experiment's options on the command line, without the plan's own (`--plan`,
/// `--slurm`, `--submit`, `--sbatch`) and without `--out`, which is the plan's folder.
fn recorded_argv(name: &str, dir: &Path) -> Result<Vec<String>> {
    let all: Vec<String> = std::env::args().collect();
    let start = all
        .iter()
        .position(|s| s == "experiment")
        .map(|i| i + 1)
        .context("cannot find the experiment's options on the command line")?;
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
        bail!("the experiment's name must come first after `experiment`");
    }
    out.extend(["--out".to_string(), dir.display().to_string()]);
    Ok(out)
}

/// `experiment NAME --plan DIR`: the shared scenes prepared, the plan written.
pub(super) fn make(mut a: Args) -> Result<()> {
    let Some(dir) = a.plan.plan.clone() else {
        bail!("--plan DIR is needed")
    };
    if a.plan.partial {
        bail!("--partial belongs to `experiment collect DIR`");
    }
    if a.out != Path::new("out/experiments") {
        bail!("--plan DIR is the plan's output folder: leave out --out");
    }
    if !a.operands.is_empty() {
        bail!("`experiment {} --plan DIR` takes no other folder", a.name);
    }
    std::fs::create_dir_all(&dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    let dir = std::fs::canonicalize(&dir)?;
    if Plan::file(&dir).exists() {
        // The same plan again (to resubmit): its ids are stable, its finished jobs stay.
        eprintln!(
            "{}: replacing its plan.json (finished jobs stay finished)",
            dir.display()
        );
    }
    let argv = recorded_argv(&a.name, &dir)?;
    let gpu = a.device.request == stegongp::backend::DeviceRequest::Gpu;
    let plan_args = a.plan.clone();
    a.out = dir.clone();
    a.plan = PlanArgs::default();
    let mode = Arc::new(JobMode::Plan(Mutex::default()));
    let (cfg, _) = experiment(a, mode.clone(), true)?;
    let name: Experiment = cfg
        .out
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or("")
        .parse()?;
    let models = mode.planned();
    let doc = plan_document(&dir, name, argv, &models, &cfg.out, gpu)?;
    let text = serde_json::to_string_pretty(&doc)?;
    write_atomic(&Plan::file(&dir), text.as_bytes())?;
    std::fs::create_dir_all(dir.join("jobs"))?;
    let plan = Plan::read(&dir)?;
    write_waves(&plan)?;
    print_summary(&plan);
    if plan_args.slurm {
        let script = super::slurm::write(&plan, &plan_args.sbatch)?;
        println!("Slurm: {}", script.display());
        if plan_args.submit {
            super::slurm::submit(&script)?;
        }
    }
    Ok(())
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

fn plan_document(
    dir: &Path,
    name: Experiment,
    argv: Vec<String>,
    models: &[PlannedModel],
    report_dir: &Path,
    gpu: bool,
) -> Result<Value> {
    let exe = std::env::current_exe()?;
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
        "format": PLAN_FORMAT, "version": PLAN_VERSION, "stegongp": env!("CARGO_PKG_VERSION"),
        "experiment": name.name(), "dir": dir, "cwd": std::env::current_dir()?,
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
            .with_context(|| format!("{}: cannot replace", wdir.display()))?;
    }
    std::fs::create_dir_all(&wdir).with_context(|| format!("{}: cannot create", wdir.display()))?;
    for (k, ids) in super::slurm::waves(plan.jobs())?.iter().enumerate() {
        write_atomic(
            &wdir.join(format!("{k:02}.txt")),
            (ids.join("\n") + "\n").as_bytes(),
        )?;
    }
    Ok(())
}

fn print_summary(plan: &Plan) {
    let jobs = plan.jobs();
    let total: f64 = jobs
        .iter()
        .filter_map(|j| j["estimated_seconds"].as_f64())
        .sum();
    let done = jobs
        .iter()
        .filter(|j| plan.is_done(j["id"].as_str().unwrap_or("")))
        .count();
    println!(
        "plan: {} ({} jobs, {done} finished; about {:.1} {} hours in all, {})",
        Plan::file(&plan.dir).display(),
        jobs.len(),
        total / 3600.0,
        plan.doc["device"].as_str().unwrap_or("cpu").to_uppercase(),
        plan.doc["rates"].as_str().unwrap_or("")
    );
    let d = plan.dir.display();
    println!(
        "run each job: stegongp experiment run-job {d} ID   (ids in plan.json; `report` last)"
    );
    println!(
        "on one machine, two at a time: for w in {d}/waves/*.txt; do xargs -P 2 -I{{}} stegongp experiment run-job {d} {{}} < \"$w\" || break; done; stegongp experiment collect {d}"
    );
}

/// `experiment run-job DIR ID`.
pub(super) fn run_job(a: Args) -> Result<()> {
    let [dir, id] = a.operands.as_slice() else {
        bail!("usage: stegongp experiment run-job DIR ID (a plan's folder and one of its job ids)");
    };
    let id = id.to_string_lossy().into_owned();
    let plan = Plan::read(dir)?;
    if id == REPORT_JOB {
        return collect_plan(&plan, a.plan.partial);
    }
    let job = plan.job(&id)?.clone();
    let _lock = lock_job(&plan, &id)?;
    if plan.is_done(&id) {
        println!(
            "job {id}: finished already ({})",
            plan.done_path(&id).display()
        );
        return Ok(());
    }
    for w in job["after"].as_array().into_iter().flatten() {
        let w = w.as_str().unwrap_or("");
        if !plan.is_done(w) {
            bail!("job {id} waits for job {w}, which has not finished (run it first)");
        }
    }
    let tee = Tee::start(&plan.log_path(&id))?;
    let t0 = std::time::Instant::now();
    eprintln!("== job {id} on {} ==", host());
    let run = || -> Result<()> {
        let args = plan.args()?;
        experiment(args, Arc::new(JobMode::One(id.clone())), false)?;
        for o in job["outputs"].as_array().into_iter().flatten() {
            let o = Path::new(o.as_str().unwrap_or(""));
            if !o.to_string_lossy().contains('*') && !o.exists() {
                bail!("job {id} ran but {} is not there", o.display());
            }
        }
        Ok(())
    };
    let result = run();
    if let Err(e) = &result {
        eprintln!("job {id} failed: {e:#}");
    }
    tee.stop();
    result?;
    let done = json!({"id": id, "seconds": t0.elapsed().as_secs_f64(), "host": host()});
    write_atomic(
        &plan.done_path(&id),
        serde_json::to_string_pretty(&done)?.as_bytes(),
    )?;
    println!("job {id}: finished in {:.1} s", t0.elapsed().as_secs_f64());
    Ok(())
}

/// Holds `jobs/ID.lock` while the job runs: a second copy of a running job is refused.
fn lock_job(plan: &Plan, id: &str) -> Result<File> {
    let jobs = plan.dir.join("jobs");
    std::fs::create_dir_all(&jobs).with_context(|| format!("{}: cannot create", jobs.display()))?;
    let path = jobs.join(format!("{id}.lock"));
    let f = File::options()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(&path)
        .with_context(|| format!("{}: cannot open", path.display()))?;
    match f.try_lock() {
        Ok(()) => Ok(f),
        Err(std::fs::TryLockError::WouldBlock) => bail!(
            "job {id} is running already ({} is held by another process): not started twice",
            path.display()
        ),
        Err(std::fs::TryLockError::Error(e)) => Err(e).context(path.display().to_string()),
    }
}

fn host() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|s| s.trim().to_string())
        .unwrap_or_else(|_| "?".into())
}

/// `experiment collect DIR`.
pub(super) fn collect(a: Args) -> Result<()> {
    let [dir] = a.operands.as_slice() else {
        bail!("usage: stegongp experiment collect DIR (a plan's folder)");
    };
    let plan = Plan::read(dir)?;
    collect_plan(&plan, a.plan.partial)
}

fn collect_plan(plan: &Plan, partial: bool) -> Result<()> {
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
            bail!(
                "{msg}\n(the report is not written; `collect --partial` writes it from the finished jobs and says which are missing)"
            );
        }
        eprintln!("{msg}\n(a partial report: their models' figures stay empty)");
    }
    let _lock = lock_job(plan, REPORT_JOB)?;
    let args = plan.args()?;
    let mode = Arc::new(JobMode::Collect {
        partial,
        missing: Mutex::default(),
    });
    let (cfg, report) = experiment(args, mode, true)?;
    if report.missing_jobs.is_empty() {
        let done = json!({"id": REPORT_JOB, "host": host()});
        write_atomic(
            &plan.done_path(REPORT_JOB),
            serde_json::to_string_pretty(&done)?.as_bytes(),
        )?;
    }
    println!("report: {}", cfg.out.join("report.md").display());
    Ok(())
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
