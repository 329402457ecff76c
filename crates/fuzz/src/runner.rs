//! The mutation loop: a case is a seed (or an earlier case that drew an error message not
//! seen before) with one to three of its files mutated, written to a folder and handed to
//! the target. A panic, an allocation its input cannot back or a slow case is a finding,
//! kept on disk as a case folder that [`replay`] runs again.

use crate::alloc::Tracking;
use crate::mutate::{Rng, mutate_file};
use crate::seeds::Case;
use crate::targets::Target;
use std::collections::HashSet;
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// The most a case may ask for in one allocation. A tiny model's loader needs well under
/// this; the largest legitimate request seen in the seeds is an empty model's 64 MiB
/// occupancy grid (aabb 128).
pub const ALLOC_BOUND: usize = 128 << 20;
/// A case slower than this is a finding (a hang, or work its input does not justify).
pub const SLOW_BOUND: Duration = Duration::from_secs(3);
/// Cases kept for further mutation because they drew a new error.
const MAX_CORPUS: usize = 400;
/// Mutants larger than this are dropped unrun: growth by repeated duplication, not input a
/// parser should be judged on.
const MAX_CASE_BYTES: usize = 32 << 20;
/// A case may allocate this many times its input (reading a file is allowed to cost its
/// size) before the [`ALLOC_BOUND`] applies.
const ALLOC_PER_INPUT_BYTE: usize = 8;

#[derive(Clone, Debug, Default)]
pub struct Stats {
    pub cases: u64,
    /// Cases the target refused with an error (the right answer to most mutants).
    pub errors: u64,
    /// Errors whose message names a file of the case.
    pub errors_naming_file: u64,
    /// Distinct error messages (digits folded).
    pub distinct_errors: usize,
    pub findings: Vec<Finding>,
    pub largest_alloc: usize,
    pub slowest: Duration,
    pub seconds: f64,
}

#[derive(Clone, Debug)]
pub struct Finding {
    pub what: String,
    /// Where the case was saved, if a findings folder was given.
    pub saved: Option<PathBuf>,
}

static PANIC_MSG: Mutex<String> = Mutex::new(String::new());
/// Whether a case is running: its panics are findings; any other goes to the usual hook.
static IN_CASE: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Panics inside cases are findings, not noise on the terminal: the hook keeps the message
/// and its location for the report. Panics outside cases (a failing assertion) print as
/// usual.
pub fn quiet_panics() {
    let usual = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        if !IN_CASE.load(std::sync::atomic::Ordering::Relaxed) {
            return usual(info);
        }
        let msg = info
            .payload()
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| info.payload().downcast_ref::<String>().cloned())
            .unwrap_or_default();
        let at = info
            .location()
            .map(|l| format!(" at {}:{}", l.file(), l.line()))
            .unwrap_or_default();
        if let Ok(mut m) = PANIC_MSG.lock() {
            *m = format!("{msg}{at}");
        }
    }));
}

/// Writes `case` into `dir`, emptied first.
pub fn write_case(dir: &Path, case: &Case) -> std::io::Result<()> {
    if dir.exists() {
        std::fs::remove_dir_all(dir)?;
    }
    std::fs::create_dir_all(dir)?;
    for (name, bytes) in case {
        let p = dir.join(name);
        if let Some(parent) = p.parent() {
            std::fs::create_dir_all(parent)?;
        }
        std::fs::write(p, bytes)?;
    }
    Ok(())
}

/// Reads a case folder back (every file below it, by relative path), leaving out the
/// finding's own note.
pub fn read_case(dir: &Path) -> std::io::Result<Case> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d)? {
            let p = e?.path();
            if p.is_dir() {
                stack.push(p);
            } else if p.file_name().is_some_and(|n| n != NOTE) {
                let rel = p
                    .strip_prefix(dir)
                    .expect("below the case folder")
                    .to_string_lossy()
                    .replace('\\', "/");
                out.push((rel, std::fs::read(&p)?));
            }
        }
    }
    out.sort();
    Ok(out)
}

/// The note a saved finding carries: what went wrong.
pub const NOTE: &str = "FINDING.txt";

/// Outcome of one case.
enum Outcome {
    Ok,
    Err(String),
    Finding(String),
}

fn run_one(target: &Target, dir: &Path, case: &Case) -> (Outcome, usize, Duration) {
    if let Err(e) = write_case(dir, case) {
        return (
            Outcome::Finding(format!("could not write the case: {e}")),
            0,
            Duration::ZERO,
        );
    }
    Tracking::reset();
    let t0 = Instant::now();
    IN_CASE.store(true, std::sync::atomic::Ordering::Relaxed);
    let r = catch_unwind(AssertUnwindSafe(|| (target.run)(dir)));
    IN_CASE.store(false, std::sync::atomic::Ordering::Relaxed);
    let dt = t0.elapsed();
    let largest = Tracking::largest();
    let input: usize = case.iter().map(|(_, b)| b.len()).sum();
    let outcome = match r {
        Err(_) => {
            let msg = PANIC_MSG.lock().map(|m| m.clone()).unwrap_or_default();
            Outcome::Finding(format!("panic: {msg}"))
        }
        Ok(_) if largest > ALLOC_BOUND.max(ALLOC_PER_INPUT_BYTE * input) => {
            Outcome::Finding(format!(
                "allocation of {largest} bytes from {input} bytes of input (bound {})",
                ALLOC_BOUND.max(ALLOC_PER_INPUT_BYTE * input)
            ))
        }
        Ok(_) if dt > SLOW_BOUND => Outcome::Finding(format!(
            "took {:.1} s on {input} bytes of input (bound {:.0} s)",
            dt.as_secs_f64(),
            SLOW_BOUND.as_secs_f64()
        )),
        Ok(Ok(())) => Outcome::Ok,
        Ok(Err(e)) => Outcome::Err(e),
    };
    (outcome, largest, dt)
}

fn signature(msg: &str) -> String {
    msg.chars()
        .map(|c| if c.is_ascii_digit() { '#' } else { c })
        .collect()
}

/// Whether an error names one of the case's files (not just its folder).
fn names_file(msg: &str, case: &Case) -> bool {
    case.iter().any(|(n, _)| {
        let base = n.rsplit('/').next().unwrap_or(n);
        msg.contains(base)
    })
}

fn save_finding(root: &Path, target: &Target, case: &Case, what: &str) -> Option<PathBuf> {
    let h = fnv(case
        .iter()
        .flat_map(|(n, b)| n.as_bytes().iter().chain(b))
        .copied());
    let dir = root.join(target.name).join(format!("{h:016x}"));
    write_case(&dir, case).ok()?;
    std::fs::write(dir.join(NOTE), format!("{what}\n")).ok()?;
    Some(dir)
}

/// What a run of one target is given.
pub struct RunConfig<'a> {
    pub cases: u64,
    /// Stop earlier once this much time has gone.
    pub max_time: Option<Duration>,
    pub seed: u64,
    /// Where cases are written before they run (the last one stays after a crash).
    pub work: &'a Path,
    /// Where findings are saved, if anywhere.
    pub findings: Option<&'a Path>,
    /// The real datasets' folder (`../shared/data`), whose files join the seeds.
    pub real: Option<&'a Path>,
}

/// Runs `cfg.cases` mutated cases of `target`.
pub fn run_target(target: &Target, cfg: &RunConfig) -> Stats {
    let dir = cfg.work.join(target.name);
    let mut rng = Rng::new(cfg.seed, fnv(target.name.bytes()));
    let mut seeds = (target.seeds)();
    if let Some(data) = cfg.real {
        seeds.extend(crate::real::seeds(target.name, data));
    }
    assert!(!seeds.is_empty(), "target {} has no seeds", target.name);
    let mut corpus: Vec<Case> = seeds.clone();
    let mut seen: HashSet<String> = HashSet::new();
    let mut stats = Stats::default();
    let t0 = Instant::now();
    for _ in 0..cfg.cases {
        if cfg.max_time.is_some_and(|m| t0.elapsed() > m) {
            break;
        }
        let from_corpus = rng.chance(0.5) && corpus.len() > seeds.len();
        let base = if from_corpus {
            &corpus[seeds.len() + rng.below(corpus.len() - seeds.len())]
        } else {
            &seeds[rng.below(seeds.len())]
        };
        let mut case = base.clone();
        for _ in 0..1 + rng.below(3) {
            mutate_some_file(&mut case, &seeds, &mut rng);
        }
        if case.iter().map(|(_, b)| b.len()).sum::<usize>() > MAX_CASE_BYTES {
            continue;
        }
        let (outcome, largest, dt) = run_one(target, &dir, &case);
        stats.cases += 1;
        stats.largest_alloc = stats.largest_alloc.max(largest);
        stats.slowest = stats.slowest.max(dt);
        match outcome {
            Outcome::Ok => {}
            Outcome::Err(msg) => {
                stats.errors += 1;
                let named = names_file(&msg, &case);
                stats.errors_naming_file += named as u64;
                if !named && std::env::var_os("STEGONGP_FUZZ_SHOW_UNNAMED").is_some() {
                    eprintln!("{}: an error naming no file: {msg}", target.name);
                }
                if seen.insert(signature(&msg)) && corpus.len() < seeds.len() + MAX_CORPUS {
                    corpus.push(case);
                }
            }
            Outcome::Finding(what) => {
                let saved = cfg
                    .findings
                    .and_then(|root| save_finding(root, target, &case, &what));
                stats.findings.push(Finding { what, saved });
            }
        }
    }
    stats.distinct_errors = seen.len();
    stats.seconds = t0.elapsed().as_secs_f64();
    stats
}

/// Mutates one file of the case, the images less often than the files that describe them.
fn mutate_some_file(case: &mut Case, seeds: &[Case], rng: &mut Rng) {
    let weight = |n: &str| {
        if n.ends_with(".png") && n.contains('/') || n.starts_with("r_") {
            1
        } else {
            8
        }
    };
    let total: usize = case.iter().map(|(n, _)| weight(n)).sum();
    let mut pick = rng.below(total);
    let mut idx = 0;
    for (i, (n, _)) in case.iter().enumerate() {
        let w = weight(n);
        if pick < w {
            idx = i;
            break;
        }
        pick -= w;
    }
    let name = case[idx].0.clone();
    let pool: Vec<Vec<u8>> = seeds
        .iter()
        .flat_map(|s| s.iter())
        .filter(|(n, _)| n.rsplit('.').next() == name.rsplit('.').next())
        .map(|(_, b)| b.clone())
        .collect();
    mutate_file(&name, &mut case[idx].1, &pool, rng);
}

/// Runs every saved case below `dir/<target>/`; returns the ones that still fail.
pub fn replay(target: &Target, dir: &Path, work: &Path) -> std::io::Result<(usize, Vec<String>)> {
    let root = dir.join(target.name);
    if !root.is_dir() {
        return Ok((0, Vec::new()));
    }
    let mut entries: Vec<PathBuf> = std::fs::read_dir(&root)?
        .map(|e| e.map(|e| e.path()))
        .collect::<std::io::Result<_>>()?;
    entries.sort();
    let mut failed = Vec::new();
    let mut n = 0;
    for e in entries.iter().filter(|e| e.is_dir()) {
        let case = read_case(e)?;
        n += 1;
        if let (Outcome::Finding(what), ..) = run_one(target, &work.join(target.name), &case) {
            failed.push(format!("{}: {what}", e.display()));
        }
    }
    Ok((n, failed))
}

/// FNV-1a: a case's folder name, a target's random stream.
fn fnv(bytes: impl Iterator<Item = u8>) -> u64 {
    bytes.fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
        (h ^ b as u64).wrapping_mul(0x100_0000_01b3)
    })
}
