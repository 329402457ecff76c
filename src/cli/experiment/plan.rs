//! `experiment NAME --plan DIR`, `experiment run-job DIR ID`, `experiment collect DIR`: the
//! options of an experiment's plan of jobs, and what these commands print. The plan itself
//! (its document, its jobs' locks, logs and done files, the report job, Slurm's scripts) is
//! [`stegongp::experiments::plan`]'s; the experiment a job runs is [`experiment`]'s, from the
//! options the plan recorded.

use super::{Args, experiment};
use anyhow::{Context, Result, bail};
use clap::Parser;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use stegongp::experiments::plan::{self, JobRun, Plan, PlanSpec, REPORT_JOB};
use stegongp::experiments::{Experiment, JobMode, slurm};

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

/// The experiment's options as `plan` recorded them, parsed again, in the folder the plan
/// was made from (relative paths in them mean what they meant there).
fn recorded_args(plan: &Plan) -> Result<Args> {
    plan.enter_cwd()?;
    #[derive(Parser)]
    struct Options {
        #[command(flatten)]
        args: Args,
    }
    let argv = std::iter::once("experiment".to_string()).chain(plan.argv());
    let o = Options::try_parse_from(argv).with_context(|| {
        format!(
            "{}: its options no longer parse",
            Plan::file(&plan.dir).display()
        )
    })?;
    Ok(o.args)
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
    let all: Vec<String> = std::env::args().collect();
    let argv = plan::recorded_argv(&all, &a.name, &dir)?;
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
    let spec = PlanSpec {
        dir: &dir,
        experiment: name,
        argv,
        report_dir: &cfg.out,
        gpu,
    };
    let plan = plan::write(spec, &mode.planned())?;
    print_summary(&plan);
    if plan_args.slurm {
        let script = slurm::write(&plan, &plan_args.sbatch)?;
        println!("Slurm: {}", script.display());
        if plan_args.submit {
            slurm::submit(&script)?;
        }
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
    let run = || -> Result<()> {
        let args = recorded_args(&plan)?;
        experiment(args, Arc::new(JobMode::One(id.clone())), false)?;
        Ok(())
    };
    match plan::run_job(&plan, &id, run)? {
        JobRun::AlreadyDone => println!(
            "job {id}: finished already ({})",
            plan.done_path(&id).display()
        ),
        JobRun::Finished { seconds } => println!("job {id}: finished in {seconds:.1} s"),
    }
    Ok(())
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
    let (cfg, _) = plan::collect(plan, partial, |mode| {
        experiment(recorded_args(plan)?, mode, true)
    })?;
    println!("report: {}", cfg.out.join("report.md").display());
    Ok(())
}
