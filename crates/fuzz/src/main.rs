//! Long fuzz runs: `cargo run --release -p stegongp-fuzz -- --cases 200000 --seed 7`.
//! Findings are saved as case folders (`--findings`, default `fuzz-findings/`); move the
//! ones worth keeping into `crates/fuzz/regressions/<target>/` once fixed.

use anyhow::{Context, Result, bail};
use clap::Parser;
use std::path::PathBuf;
use std::time::Duration;
use stegongp_fuzz::alloc::Tracking;
use stegongp_fuzz::runner::{RunConfig, quiet_panics, replay, run_target};
use stegongp_fuzz::targets::{TARGETS, by_name};

#[global_allocator]
static ALLOC: Tracking = Tracking;

#[derive(Parser)]
#[command(about = "Structure-aware fuzzing of every file StegoNGP reads")]
struct Args {
    /// Targets to run (default: all). `--list` names them.
    #[arg(long = "target")]
    targets: Vec<String>,
    /// Mutated cases per target.
    #[arg(long, default_value_t = 20_000)]
    cases: u64,
    /// Stop each target after this many seconds, whatever `--cases` says.
    #[arg(long)]
    seconds: Option<f64>,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Where findings go.
    #[arg(long, default_value = "fuzz-findings")]
    findings: PathBuf,
    /// Where each case is written before it runs (the last one stays after a crash).
    #[arg(long)]
    work: Option<PathBuf>,
    /// The real datasets whose files join the seeds (default: `../shared/data` beside the
    /// repository, when it is there).
    #[arg(long)]
    real: Option<PathBuf>,
    /// Generated seeds only.
    #[arg(long)]
    no_real: bool,
    /// Replays the saved cases under DIR/<target>/ (a findings folder) and exits: which
    /// still fail after a fix.
    #[arg(long, value_name = "DIR")]
    replay: Option<PathBuf>,
    /// Lists the targets and exits.
    #[arg(long)]
    list: bool,
    /// Prints one JSON line per target instead of text.
    #[arg(long)]
    json: bool,
}

fn main() -> Result<()> {
    let args = Args::parse();
    if args.list {
        for t in TARGETS {
            println!("{:12} {}", t.name, t.about);
        }
        return Ok(());
    }
    let targets: Vec<_> = if args.targets.is_empty() {
        TARGETS.iter().collect()
    } else {
        args.targets
            .iter()
            .map(|n| by_name(n).with_context(|| format!("no target '{n}' (--list names them)")))
            .collect::<Result<_>>()?
    };
    let work = args.work.clone().unwrap_or_else(|| {
        std::env::temp_dir().join(format!("stegongp-fuzz-{}", std::process::id()))
    });
    eprintln!("cases are written to {} before they run", work.display());
    let real = if args.no_real {
        None
    } else {
        args.real.clone().or_else(stegongp_fuzz::shared_data)
    };
    match &real {
        Some(r) => eprintln!("real seeds from {}", r.display()),
        None => eprintln!("generated seeds only (no ../shared/data; --real DIR names one)"),
    }
    quiet_panics();
    if let Some(dir) = &args.replay {
        let mut still = 0;
        for t in &targets {
            let (n, failing) =
                replay(t, dir, &work).with_context(|| format!("replaying {}", dir.display()))?;
            if n > 0 {
                println!(
                    "{:12} {n} cases replayed, {} still fail",
                    t.name,
                    failing.len()
                );
            }
            for f in &failing {
                println!("  {f}");
            }
            still += failing.len();
        }
        let _ = std::fs::remove_dir_all(&work);
        if still > 0 {
            bail!("{still} cases still fail");
        }
        return Ok(());
    }
    let mut failed = 0;
    for t in targets {
        let (n, still) = replay(t, &stegongp_fuzz::regressions_dir(), &work)
            .with_context(|| format!("replaying {}'s regressions", t.name))?;
        for s in &still {
            eprintln!("regression fails again: {s}");
        }
        failed += still.len();
        let cfg = RunConfig {
            cases: args.cases,
            max_time: args.seconds.map(Duration::from_secs_f64),
            seed: args.seed,
            work: &work,
            findings: Some(&args.findings),
            real: real.as_deref(),
        };
        let s = run_target(t, &cfg);
        failed += s.findings.len();
        if args.json {
            println!(
                "{}",
                serde_json::json!({
                    "target": t.name, "regressions": n, "cases": s.cases, "errors": s.errors,
                    "errors_naming_file": s.errors_naming_file,
                    "distinct_errors": s.distinct_errors, "findings": s.findings.len(),
                    "largest_alloc_bytes": s.largest_alloc,
                    "slowest_case_s": s.slowest.as_secs_f64(), "seconds": s.seconds,
                })
            );
        } else {
            println!(
                "{:12} {:>8} cases in {:6.1} s, {} regressions replayed; errors {:5.1} % ({:.0} % name their file, {} distinct); largest allocation {:.1} MiB; slowest case {:.0} ms; {} findings",
                t.name,
                s.cases,
                s.seconds,
                n,
                100.0 * s.errors as f64 / s.cases.max(1) as f64,
                100.0 * s.errors_naming_file as f64 / s.errors.max(1) as f64,
                s.distinct_errors,
                s.largest_alloc as f64 / (1 << 20) as f64,
                s.slowest.as_secs_f64() * 1e3,
                s.findings.len()
            );
        }
        for f in &s.findings {
            match &f.saved {
                Some(p) => eprintln!("  finding: {} (saved in {})", f.what, p.display()),
                None => eprintln!("  finding: {}", f.what),
            }
        }
    }
    let _ = std::fs::remove_dir_all(&work);
    if failed > 0 {
        bail!("{failed} failing cases");
    }
    Ok(())
}
