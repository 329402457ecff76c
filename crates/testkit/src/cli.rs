//! The `stegongp` program, run as a user runs it.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The program cargo built beside the running test (`target/<profile>/stegongp`).
pub fn bin() -> PathBuf {
    let exe = std::env::current_exe().expect("the test's own path");
    // target/<profile>/deps/<test>-<hash> → target/<profile>/stegongp
    let dir = exe
        .parent()
        .and_then(Path::parent)
        .expect("a test binary under target/<profile>/deps");
    let bin = dir.join(format!("stegongp{}", std::env::consts::EXE_SUFFIX));
    assert!(bin.exists(), "{} not built", bin.display());
    bin
}

/// Runs `stegongp args`.
pub fn stegongp(args: &[&str]) -> Output {
    Command::new(bin())
        .args(args)
        .output()
        .expect("run stegongp")
}

/// `stegongp synth --scene SCENE` into `dir`: `res` px, `train` training views, one
/// held-out view, no validation split.
pub fn synth(dir: &Path, scene: &str, res: u32, train: u32) {
    run_ok(&[
        "synth",
        "--scene",
        scene,
        "--res",
        &res.to_string(),
        "--train",
        &train.to_string(),
        "--test",
        "1",
        "--val",
        "0",
        "--out",
        dir.to_str().expect("a UTF-8 path"),
    ]);
}

/// The standard error of a run that must have succeeded.
pub fn ok(out: &Output) -> String {
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "stegongp failed: {err}");
    err
}

/// Runs `stegongp args`, which must succeed; its standard error.
pub fn run_ok(args: &[&str]) -> String {
    let out = stegongp(args);
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "stegongp {args:?} failed: {err}");
    err
}

/// The standard output of a run that must have succeeded.
pub fn stdout_ok(out: &Output) -> String {
    ok(out);
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// A run that must have failed cleanly: an exit code other than 0, no panic, and a message
/// naming every one of `needles`.
pub fn fails_naming(out: &Output, needles: &[&str]) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "expected failure, stderr: {err}");
    assert!(!err.contains("panicked"), "panic: {err}");
    for n in needles {
        assert!(err.contains(n), "stderr lacks {n:?}: {err}");
    }
}

/// `stegongp args` is refused with a message naming `says`, and `out_dir` is not created.
pub fn refused_before_writing(args: &[&str], says: &str, out_dir: &Path) {
    let out = stegongp(args);
    fails_naming(&out, &[says]);
    assert!(!out_dir.exists(), "{args:?} wrote {}", out_dir.display());
}

/// The rows of the table of an experiment's `report.json` whose title starts with `prefix`.
pub fn report_table<'a>(report: &'a serde_json::Value, prefix: &str) -> &'a Vec<serde_json::Value> {
    report["tables"]
        .as_array()
        .expect("a report's tables")
        .iter()
        .find(|t| t["title"].as_str().is_some_and(|s| s.starts_with(prefix)))
        .unwrap_or_else(|| panic!("no table '{prefix}…' in {report}"))["rows"]
        .as_array()
        .expect("a table's rows")
}
