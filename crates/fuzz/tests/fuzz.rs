//! CI's fuzzing: every regression case again, then a seeded, bounded number of mutated
//! cases per target (about a minute in all on the 2-core machine). A failure names the
//! case folder it saved under the target directory.

use std::time::Duration;
use stegongp_fuzz::alloc::Tracking;
use stegongp_fuzz::runner::{RunConfig, quiet_panics, replay, run_target};
use stegongp_fuzz::targets::TARGETS;

#[global_allocator]
static ALLOC: Tracking = Tracking;

/// Cases per target in CI; `stegongp-fuzz --cases N` runs more.
const CI_CASES: u64 = 1500;

#[test]
fn every_target_survives_its_regressions_and_a_seeded_run() {
    quiet_panics();
    let tmp = std::env::temp_dir().join(format!("stegongp-fuzz-test-{}", std::process::id()));
    let findings = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("fuzz-findings");
    let mut failures = Vec::new();
    for t in TARGETS {
        let (n, still) = replay(t, &stegongp_fuzz::regressions_dir(), &tmp).expect("replay");
        failures.extend(still);
        let cfg = RunConfig {
            cases: t.ci_cases.unwrap_or(CI_CASES),
            max_time: Some(Duration::from_secs(60)),
            seed: 20261127,
            work: &tmp,
            findings: Some(&findings),
            // CI has no shared data; the generated seeds keep the run the same everywhere.
            real: None,
        };
        let s = run_target(t, &cfg);
        eprintln!(
            "{:12} {} regressions, {} cases in {:.1} s: {} errors ({} distinct), largest allocation {} bytes, slowest {:.0} ms, {} findings",
            t.name,
            n,
            s.cases,
            s.seconds,
            s.errors,
            s.distinct_errors,
            s.largest_alloc,
            s.slowest.as_secs_f64() * 1e3,
            s.findings.len()
        );
        // The mutants must reach the parsers' checks, not just their first byte.
        assert!(
            s.distinct_errors >= 5,
            "{}: only {} distinct errors: the mutations do not reach the parser",
            t.name,
            s.distinct_errors
        );
        // A refusal names the file it refuses (the viewer's answers are status lines).
        if t.name != "viewer" {
            assert!(
                s.errors_naming_file * 100 >= s.errors * 99,
                "{}: {} of {} errors name their file",
                t.name,
                s.errors_naming_file,
                s.errors
            );
        }
        failures.extend(s.findings.iter().map(|f| {
            format!(
                "{}: {} ({})",
                t.name,
                f.what,
                f.saved
                    .as_ref()
                    .map_or("not saved".into(), |p| p.display().to_string())
            )
        }));
    }
    let _ = std::fs::remove_dir_all(&tmp);
    assert!(
        failures.is_empty(),
        "fuzz findings:\n{}",
        failures.join("\n")
    );
}

#[test]
fn the_allocation_tracker_sees_a_large_request() {
    Tracking::reset();
    let v: Vec<u8> = Vec::with_capacity(3 << 20);
    assert!(Tracking::largest() >= 3 << 20);
    drop(v);
}

#[test]
fn every_seed_loads_cleanly() {
    // A seed that its own loader refuses would waste the mutations made from it.
    let tmp = std::env::temp_dir().join(format!("stegongp-fuzz-seeds-{}", std::process::id()));
    for t in TARGETS {
        for (i, case) in (t.seeds)().iter().enumerate() {
            // The viewer's key seed is refused on purpose (its key does not fit the model):
            // a key that fits makes the viewer rebuild a grid, a second for every mutant.
            if t.name == "viewer" && i == 4 {
                continue;
            }
            let dir = tmp.join(t.name).join(i.to_string());
            stegongp_fuzz::runner::write_case(&dir, case).expect("write");
            if let Err(e) = (t.run)(&dir) {
                panic!("{} seed {i} does not load: {e}", t.name);
            }
        }
    }
    let _ = std::fs::remove_dir_all(&tmp);
}

#[test]
fn every_real_seed_loads_cleanly() {
    let Some(data) = stegongp_fuzz::shared_data() else {
        eprintln!("skipped: ../shared/data is absent");
        return;
    };
    let tmp = std::env::temp_dir().join(format!("stegongp-fuzz-real-{}", std::process::id()));
    let mut n = 0;
    for t in TARGETS {
        for (i, case) in stegongp_fuzz::real::seeds(t.name, &data).iter().enumerate() {
            let dir = tmp.join(t.name).join(i.to_string());
            stegongp_fuzz::runner::write_case(&dir, case).expect("write");
            if let Err(e) = (t.run)(&dir) {
                panic!("{} real seed {i} does not load: {e}", t.name);
            }
            n += 1;
        }
    }
    assert!(n >= 9, "{n} real seeds");
    let _ = std::fs::remove_dir_all(&tmp);
}
