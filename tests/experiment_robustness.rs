//! `experiment robustness`: models of each mode attacked at each strength, as one run and as
//! a plan of jobs (every attacked file a job waiting for its model), the two reports the
//! same; `purify` leaves every cover pixel as it was. (That it leaves a robust hidden scene
//! as it was too is `tests/attack_cli.rs`'s, on the command a user runs.)

use serde_json::Value;
use std::path::Path;
use std::process::Command;
use stegongp::experiments::report::comparable;
use testkit::cli::{bin, report_table, run_ok, stdout_ok, stegongp};

// One attack (purify: the one the robust mode exists for), one mode: each measured scene
// with a key rebuilds its occupancy grid (seconds on two cores), so every model and attack
// costs more than its own time (a second mode cost this test 65 s); the attacks and the
// modes themselves have their own tests (attack_cli, the crate's).
const ARGS: [&str; 16] = [
    "robustness",
    "--res",
    "32",
    "--steps",
    "40",
    "--batch",
    "4096",
    "--eval-views",
    "1",
    "--no-lpips",
    "--log2-t",
    "14",
    "--modes",
    "default",
    "--attack",
    "purify",
];

fn args(extra: &[&str]) -> Vec<String> {
    let mut v = vec!["experiment".to_string()];
    v.extend(ARGS.iter().chain(extra).map(|s| s.to_string()));
    v
}

fn strs(v: &[String]) -> Vec<&str> {
    v.iter().map(String::as_str).collect()
}

fn report(dir: &Path) -> Value {
    let text = std::fs::read_to_string(dir.join("robustness/report.json")).unwrap();
    let text = text.replace(dir.to_str().unwrap(), "DIR");
    comparable(&serde_json::from_str(&text).unwrap())
}

#[test]
fn robustness_as_jobs_writes_the_single_machine_report() {
    let d = tempfile::tempdir().unwrap();
    let (here, plan) = (d.path().join("here"), d.path().join("plan"));
    run_ok(&strs(&args(&["--out", here.to_str().unwrap()])));
    stdout_ok(&stegongp(&strs(&args(&["--plan", plan.to_str().unwrap()]))));
    let doc: Value =
        serde_json::from_slice(&std::fs::read(plan.join("plan.json")).unwrap()).unwrap();
    let jobs = doc["jobs"].as_array().unwrap();
    let ids: Vec<&str> = jobs.iter().map(|j| j["id"].as_str().unwrap()).collect();
    // The model, its attack, the report.
    assert_eq!(ids.len(), 1 + 1 + 1, "{ids:?}");
    let attack_job = jobs
        .iter()
        .find(|j| j["id"].as_str().unwrap().contains("attack"))
        .unwrap();
    let after = attack_job["after"].as_array().unwrap();
    assert_eq!(
        after.len(),
        1,
        "an attack waits for its model: {attack_job}"
    );
    assert!(ids.contains(&after[0].as_str().unwrap()));
    let p = plan.to_str().unwrap();
    let script = format!(
        "set -e; for w in {p}/waves/*.txt; do xargs -P 2 -I{{}} {} experiment run-job {p} {{}} < \"$w\"; done; {} experiment collect {p}",
        bin().display(),
        bin().display()
    );
    assert!(
        Command::new("bash")
            .args(["-c", &script])
            .status()
            .unwrap()
            .success()
    );
    assert_eq!(
        report(&plan),
        report(&here),
        "the plan's report is the single machine's"
    );
    for f in ["curves.png", "hidden_after_attacks.png", "report.md"] {
        assert!(plan.join("robustness").join(f).is_file(), "{f} missing");
    }

    let r = report(&here);
    let rows = report_table(&r, "Every attack");
    let find = |mode: &str, attack: &str| {
        rows.iter()
            .find(|x| x["mode"] == mode && x["attack"] == attack)
            .unwrap_or_else(|| panic!("no row {mode} {attack}"))
    };
    let (none, purified) = (find("default", "none"), find("default", "purify"));
    assert_eq!(
        none["cover_psnr"], purified["cover_psnr"],
        "purify moved the cover"
    );
    assert!(purified["wrong_key_psnr"].is_number() && purified["empty_psnr"].is_number());
    assert_eq!(report_table(&r, "Headline").len(), 1);
}
