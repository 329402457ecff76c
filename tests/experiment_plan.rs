//! `experiment NAME --plan DIR`, `run-job`, `collect`: an experiment run as separate jobs —
//! here by `xargs -P 2`, the recipe the plan prints for one machine — writes the report the
//! single-machine run writes (to the bit, wall-clock fields aside); a killed job goes on
//! from its saved state; finished jobs do nothing; a running job is not started twice; and
//! bad plans, ids and schedulers are refused with the file named.

use serde_json::Value;
use std::path::Path;
use std::process::{Command, Stdio};
use stegongp::experiments::report::comparable;
use testkit::cli::{bin, run_ok, stdout_ok, stegongp};

/// A small fidelity experiment: three models of 32 px scenes, 30 steps each.
const FIDELITY: [&str; 13] = [
    "fidelity",
    "--res",
    "32",
    "--steps",
    "30",
    "--batch",
    "4096",
    "--eval-views",
    "2",
    "--no-lpips",
    "--log2-t",
    "14",
    "--save-every=5",
];

fn experiment(extra: &[&str]) -> Vec<String> {
    let mut v = vec!["experiment".to_string()];
    v.extend(FIDELITY.iter().map(|s| s.to_string()));
    v.extend(extra.iter().map(|s| s.to_string()));
    v
}

fn strs(v: &[String]) -> Vec<&str> {
    v.iter().map(String::as_str).collect()
}

/// The report of `dir/fidelity` as [`comparable`] gives it, `dir` itself named `DIR`.
fn report(dir: &Path) -> Value {
    let text = std::fs::read_to_string(dir.join("fidelity/report.json")).unwrap();
    let text = text.replace(dir.to_str().unwrap(), "DIR");
    comparable(&serde_json::from_str(&text).unwrap())
}

fn job_ids(plan: &Path) -> Vec<String> {
    let doc: Value =
        serde_json::from_slice(&std::fs::read(plan.join("plan.json")).unwrap()).unwrap();
    doc["jobs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|j| j["id"].as_str().unwrap().to_string())
        .collect()
}

fn run_job(plan: &Path, id: &str) -> std::process::Output {
    stegongp(&["experiment", "run-job", plan.to_str().unwrap(), id])
}

#[test]
fn jobs_run_by_xargs_write_the_single_machine_report() {
    let d = tempfile::tempdir().unwrap();
    let (here, plan) = (d.path().join("here"), d.path().join("plan"));
    run_ok(&strs(&experiment(&["--out", here.to_str().unwrap()])));
    let out = stdout_ok(&stegongp(&strs(&experiment(&[
        "--plan",
        plan.to_str().unwrap(),
    ]))));
    assert!(
        out.contains("xargs -P 2"),
        "the plan prints its recipe: {out}"
    );
    let ids = job_ids(&plan);
    assert_eq!(
        ids,
        [
            "fidelity-plain-cover",
            "fidelity-plain-hidden",
            "fidelity-stego",
            "report"
        ]
    );
    // Nothing trained, nothing reported yet: a plan only describes.
    assert!(!plan.join("fidelity/models/stego.ingp").exists());
    assert!(!plan.join("fidelity/report.json").exists());
    let early = stegongp(&["experiment", "collect", plan.to_str().unwrap()]);
    let e = String::from_utf8_lossy(&early.stderr);
    assert!(
        !early.status.success() && e.contains("3 of 3 jobs") && e.contains("never started"),
        "{e}"
    );

    // The recipe the plan prints, as a user runs it.
    let p = plan.to_str().unwrap();
    let script = format!(
        "set -e; for w in {p}/waves/*.txt; do xargs -P 2 -I{{}} {} experiment run-job {p} {{}} < \"$w\"; done; {} experiment collect {p}",
        bin().display(),
        bin().display()
    );
    let st = Command::new("bash").args(["-c", &script]).status().unwrap();
    assert!(st.success());
    assert_eq!(
        report(&plan),
        report(&here),
        "the plan's report is the single machine's"
    );
    let png = |d: &Path| std::fs::read(d.join("fidelity/fidelity.png")).unwrap();
    assert!(png(&plan) == png(&here), "the figure differs");
    let md = std::fs::read_to_string(plan.join("fidelity/report.md")).unwrap();
    assert!(
        md.contains("Wall-clock and host figures") && md.contains("`train_s`"),
        "{md}"
    );
    let log = std::fs::read_to_string(plan.join("jobs/fidelity-stego.log")).unwrap();
    assert!(
        log.contains("trained stego"),
        "the job's log holds its output: {log}"
    );

    // Finished: running a job again does nothing.
    let again = run_job(&plan, "fidelity-stego");
    assert!(String::from_utf8_lossy(&again.stdout).contains("finished already"));
}

/// A job killed while it trains goes on from its saved state when run again, and the
/// report is the same as an uninterrupted run's; a second copy of a running job is refused.
#[test]
fn a_killed_job_resumes_and_a_running_job_is_not_started_twice() {
    let d = tempfile::tempdir().unwrap();
    let (a, b) = (d.path().join("a"), d.path().join("b"));
    for p in [&a, &b] {
        run_ok(&strs(&experiment(&["--plan", p.to_str().unwrap()])));
    }
    let state = b.join("fidelity/models/stego.ingp.state");
    let mut child = Command::new(bin())
        .args([
            "experiment",
            "run-job",
            b.to_str().unwrap(),
            "fidelity-stego",
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let t0 = std::time::Instant::now();
    while !state.exists() {
        assert!(t0.elapsed().as_secs() < 120, "no state was saved");
        assert!(
            child.try_wait().unwrap().is_none(),
            "the job ended before saving a state"
        );
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    // While it runs, a second copy is refused.
    let twice = run_job(&b, "fidelity-stego");
    let e = String::from_utf8_lossy(&twice.stderr);
    assert!(
        !twice.status.success() && e.contains("running already"),
        "{e}"
    );
    child.kill().unwrap();
    child.wait().unwrap();
    assert!(!b.join("jobs/fidelity-stego.done").exists());
    // A partial report says what it lacks.
    let partial = stegongp(&["experiment", "collect", b.to_str().unwrap(), "--partial"]);
    assert!(
        partial.status.success(),
        "{}",
        String::from_utf8_lossy(&partial.stderr)
    );
    let json: Value =
        serde_json::from_slice(&std::fs::read(b.join("fidelity/report.json")).unwrap()).unwrap();
    assert_eq!(json["partial"]["missing_jobs"].as_array().unwrap().len(), 3);
    for p in [&a, &b] {
        for id in [
            "fidelity-plain-cover",
            "fidelity-plain-hidden",
            "fidelity-stego",
        ] {
            let o = run_job(p, id);
            assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        }
        run_ok(&["experiment", "collect", p.to_str().unwrap()]);
    }
    let log = std::fs::read_to_string(b.join("jobs/fidelity-stego.log")).unwrap();
    assert!(
        log.contains("resumed"),
        "the second attempt went on from the state: {log}"
    );
    assert_eq!(report(&a), report(&b), "resumed, the same report");
}

#[test]
fn bad_plans_ids_and_schedulers_are_refused() {
    let d = tempfile::tempdir().unwrap();
    let plan = d.path().join("plan");
    let p = plan.to_str().unwrap();
    let fails = |args: &[&str], want: &[&str]| {
        let o = stegongp(args);
        let e = String::from_utf8_lossy(&o.stderr).to_string();
        assert!(!o.status.success(), "{args:?} succeeded");
        for w in want {
            assert!(e.contains(w), "{args:?}: '{w}' not in: {e}");
        }
    };
    let nothing = d.path().join("nothing");
    std::fs::create_dir(&nothing).unwrap();
    let n = nothing.to_str().unwrap();
    fails(&["experiment", "collect", n], &["not a plan's folder", n]);
    fails(&["experiment", "run-job", n, "x"], &["not a plan's folder"]);
    fails(&["experiment", "run-job", n], &["usage"]);
    run_ok(&strs(&experiment(&["--plan", p])));
    fails(
        &["experiment", "run-job", p, "no-such-job"],
        &["no job 'no-such-job'", "plan.json", "fidelity-stego"],
    );
    // --submit where there is no sbatch: refused, naming what is missing; the plan stays.
    let o = Command::new(bin())
        .args(strs(&experiment(&["--plan", p, "--slurm", "--submit"])))
        .env("PATH", "/nonexistent")
        .output()
        .unwrap();
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("sbatch is not on PATH"),
        "{e}"
    );
    let submit = std::fs::read_to_string(plan.join("submit.sh")).unwrap();
    assert!(
        submit.contains("--array=0-") && submit.contains("afterany"),
        "{submit}"
    );
    // A plan from another version.
    let file = plan.join("plan.json");
    let text = std::fs::read_to_string(&file).unwrap();
    let old = text.replace(
        &format!("\"stegongp\": \"{}\"", env!("CARGO_PKG_VERSION")),
        "\"stegongp\": \"0.0.1\"",
    );
    assert_ne!(old, text);
    std::fs::write(&file, old).unwrap();
    fails(
        &["experiment", "run-job", p, "fidelity-stego"],
        &["written by stegongp 0.0.1", "plan.json"],
    );
    std::fs::write(&file, "{not json").unwrap();
    fails(&["experiment", "collect", p], &["plan.json", "not JSON"]);
    // The plan's own options outside a plan, and --out beside --plan.
    fails(
        &["experiment", "fidelity", "--partial"],
        &["--partial belongs to"],
    );
    fails(
        &strs(&experiment(&["--plan", p, "--out", n])),
        &["leave out --out"],
    );
}
