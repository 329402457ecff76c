//! A plan as Slurm job arrays (`experiment NAME --plan DIR --slurm`): `DIR/submit.sh`
//! submits, wave by wave of dependencies, one array task per unfinished job
//! (`experiment run-job DIR ID`), each wave after the one before (`afterok`), then the report
//! job after all of them (`afterany`, so that it runs and lists what failed). Running it
//! again submits only the jobs not finished. Slurm does the scheduling; we only describe.

use crate::plan::{Plan, REPORT_JOB, bare, context};
use ngp::error::{Error, Result};
use serde_json::Value;
use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Single-quoted for the shell.
fn sh(s: &str) -> String {
    format!("'{}'", s.replace('\'', r"'\''"))
}

/// Each training job's wave: 0 for a job that waits for none, else one more than the
/// latest wave among those it waits for.
pub fn waves(jobs: &[Value]) -> Result<Vec<Vec<String>>> {
    let train: Vec<&Value> = jobs.iter().filter(|j| j["kind"] == "train").collect();
    let mut wave: HashMap<String, usize> = HashMap::new();
    // A plan lists a job after those it waits for; more passes than jobs means a cycle.
    for _ in 0..=train.len() {
        let mut changed = false;
        for j in &train {
            let id = j["id"].as_str().unwrap_or("").to_string();
            let w = j["after"]
                .as_array()
                .into_iter()
                .flatten()
                .map(|a| wave.get(a.as_str().unwrap_or("")).map(|w| w + 1))
                .try_fold(0usize, |m, w| w.map(|w| m.max(w)));
            if let Some(w) = w
                && wave.get(&id) != Some(&w)
            {
                wave.insert(id, w);
                changed = true;
            }
        }
        if !changed {
            break;
        }
    }
    if wave.len() != train.len() {
        return Err(Error::Other(
            "the plan's jobs wait for jobs it does not have, or for each other".into(),
        ));
    }
    let n = wave.values().max().map_or(0, |m| m + 1);
    let mut out = vec![Vec::new(); n];
    for j in &train {
        let id = j["id"].as_str().unwrap_or("");
        out[wave[id]].push(id.to_string());
    }
    Ok(out)
}

/// A wave's sbatch time limit: three times its longest estimate, at least 10 minutes.
fn time_limit(jobs: &[Value], ids: &[String]) -> String {
    let longest = jobs
        .iter()
        .filter(|j| ids.iter().any(|i| j["id"] == i.as_str()))
        .filter_map(|j| j["estimated_seconds"].as_f64())
        .fold(0.0f64, f64::max);
    let minutes = ((longest * 3.0 / 60.0).ceil() as u64).max(10);
    format!("{}:{:02}:00", minutes / 60, minutes % 60)
}

/// Writes `DIR/submit.sh` and the scripts it submits; returns the path of submit.sh.
pub fn write(plan: &Plan, extra: &[String]) -> Result<PathBuf> {
    let dir = &plan.dir;
    let sdir = dir.join("slurm");
    std::fs::create_dir_all(sdir.join("logs"))
        .map_err(context(format!("{}: cannot create", sdir.display())))?;
    let d = dir.display().to_string();
    let bin = plan.doc["binary"]
        .as_str()
        .unwrap_or("stegongp")
        .to_string();
    let gpu = plan.doc["device"] == "gpu";
    let name = plan.experiment.name();
    let mut common = format!(
        "--parsable --job-name=stegongp-{name} --cpus-per-task={} --mem={}",
        if gpu { 8 } else { 2 },
        if gpu { "48G" } else { "4G" }
    );
    if gpu {
        common += " --gres=gpu:1";
    }
    for e in extra {
        common += &format!(" {}", sh(e));
    }
    let task = format!(
        "#!/bin/bash\n# One array task: line SLURM_ARRAY_TASK_ID + 1 of the list in $1 is the job.\nid=$(sed -n \"$((SLURM_ARRAY_TASK_ID + 1))p\" \"$1\")\nexec {} experiment run-job {} \"$id\"\n",
        sh(&bin),
        sh(&d)
    );
    write_script(&sdir.join("task.sh"), &task)?;
    let report = format!(
        "#!/bin/bash\nexec {} experiment run-job {} {REPORT_JOB}\n",
        sh(&bin),
        sh(&d)
    );
    write_script(&sdir.join("report.sh"), &report)?;
    let mut s = String::new();
    writeln!(
        s,
        "#!/bin/bash\n# Submits the unfinished jobs of the plan in {d} to Slurm (written by stegongp experiment {name} --plan --slurm).\n# Run it again after a failure or a cancellation: it submits only what has not finished.\nset -euo pipefail\nD={}\nS=\"$D/slurm\"\nCOMMON=({common})\nafter=\"\"\nall=\"\"",
        sh(&d)
    )
    .map_err(bare)?;
    s += "# The jobs of list $1 that have not finished, as an array after the previous wave.\n";
    s += "submit_wave() {\n  local list=\"$D/waves/$1\" pending; shift\n  pending=\"$S/pending-$(basename \"$list\" .txt)-$(date +%s)-$$.txt\"\n";
    s += "  : > \"$pending\"\n  while read -r id; do [ -e \"$D/jobs/$id.done\" ] || echo \"$id\" >> \"$pending\"; done < \"$list\"\n";
    s += "  local n; n=$(wc -l < \"$pending\")\n  if [ \"$n\" -eq 0 ]; then rm -f \"$pending\"; return 0; fi\n";
    s += "  local dep=(); [ -n \"$after\" ] && dep=(--dependency=\"afterok:$after\")\n";
    s += "  local id; id=$(sbatch \"${COMMON[@]}\" \"${dep[@]}\" \"$@\" --array=0-$((n - 1)) --output=\"$S/logs/%A_%a.out\" \"$S/task.sh\" \"$pending\")\n";
    s += "  id=${id%%;*}\n  echo \"wave $(basename \"$list\" .txt): $n jobs, Slurm job $id\"\n  after=\"$id\"; all=\"$all:$id\"\n}\n";
    let jobs = plan.jobs();
    for (k, ids) in waves(jobs)?.iter().enumerate() {
        let list = format!("{k:02}.txt");
        writeln!(s, "submit_wave {list} --time={}", time_limit(jobs, ids)).map_err(bare)?;
    }
    let report_time = time_limit(jobs, &[REPORT_JOB.to_string()]);
    s += "dep=(); [ -n \"$all\" ] && dep=(--dependency=\"afterany${all}\")\n";
    writeln!(
        s,
        "id=$(sbatch \"${{COMMON[@]}}\" \"${{dep[@]}}\" --time={report_time} --output=\"$S/logs/report-%j.out\" \"$S/report.sh\")\necho \"report: Slurm job ${{id%%;*}} (then: $D/{name}/report.md)\""
    )
    .map_err(bare)?;
    let path = dir.join("submit.sh");
    write_script(&path, &s)?;
    Ok(path)
}

fn write_script(path: &Path, text: &str) -> Result<()> {
    use std::os::unix::fs::PermissionsExt;
    ngp::util::write_atomic(path, text.as_bytes())?;
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o755)).map_err(context(
        format!("{}: cannot make it executable", path.display()),
    ))
}

/// Runs submit.sh (sbatch must be on PATH), its output (the Slurm job ids) shown.
pub fn submit(script: &Path) -> Result<()> {
    let found = std::env::var_os("PATH")
        .map(|p| std::env::split_paths(&p).any(|d| d.join("sbatch").is_file()))
        .unwrap_or(false);
    if !found {
        return Err(Error::Other(format!(
            "sbatch is not on PATH: this machine cannot submit to Slurm (run {} on a login node of the cluster, or run the jobs another way: see plan.json)",
            script.display()
        )));
    }
    let status = std::process::Command::new("bash")
        .arg(script)
        .status()
        .map_err(context(format!("running {}", script.display())))?;
    if !status.success() {
        return Err(Error::Other(format!(
            "{} failed ({status}): sbatch refused a job (see above)",
            script.display()
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn waves_follow_the_dependencies() {
        let jobs = vec![
            json!({"id": "a", "kind": "train", "after": []}),
            json!({"id": "b", "kind": "train", "after": ["a"]}),
            json!({"id": "c", "kind": "train", "after": []}),
            json!({"id": "d", "kind": "train", "after": ["b", "c"]}),
            json!({"id": "report", "kind": "report", "after": ["a", "b", "c", "d"]}),
        ];
        let w = waves(&jobs).unwrap();
        assert_eq!(w, vec![vec!["a", "c"], vec!["b"], vec!["d"]]);
        let cycle = vec![
            json!({"id": "a", "kind": "train", "after": ["b"]}),
            json!({"id": "b", "kind": "train", "after": ["a"]}),
        ];
        assert!(waves(&cycle).is_err());
        let unknown = vec![json!({"id": "a", "kind": "train", "after": ["zz"]})];
        assert!(waves(&unknown).is_err());
    }

    #[test]
    fn time_limits_leave_room() {
        let jobs = vec![
            json!({"id": "a", "estimated_seconds": 100.0}),
            json!({"id": "b", "estimated_seconds": 7200.0}),
        ];
        assert_eq!(time_limit(&jobs, &["a".into()]), "0:10:00");
        assert_eq!(time_limit(&jobs, &["a".into(), "b".into()]), "6:00:00");
    }

    #[test]
    fn shell_quoting_survives_quotes() {
        assert_eq!(sh("a b"), "'a b'");
        assert_eq!(sh("it's"), r"'it'\''s'");
    }
}
