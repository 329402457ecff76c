//! What a user and a script see stays as it is (issue 67's restructuring may move every
//! piece behind the commands, not the commands): every command's `--help` text, and the
//! shape of every `--json` document a small run prints (its keys in order and the kind of
//! each value), against the golden files in `tests/golden/`.
//!
//! A deliberate change rewrites them: `STEGONGP_BLESS=1 cargo test --release --test
//! cli_golden`, then review the diff as part of the change.

use serde_json::Value;
use std::path::Path;
use std::process::Command;
use testkit::cli::{bin, ok, stdout_ok, stegongp};
use testkit::golden::{self, check};

/// Every subcommand, and `experiment`'s plans and jobs under it.
const COMMANDS: &[&str] = &[
    "",
    "synth",
    "train",
    "render",
    "eval",
    "inspect",
    "keygen",
    "demo",
    "experiment",
    "convert",
    "process",
    "detect",
    "video",
    "view",
    "devices",
    "mesh",
    "attack",
];

/// `--help` is as wide on every machine: clap reads no terminal here, and COLUMNS is set.
fn help(command: &str) -> String {
    let mut cmd = Command::new(bin());
    cmd.env("COLUMNS", "100");
    if !command.is_empty() {
        cmd.arg(command);
    }
    let out = cmd.arg("--help").output().expect("run stegongp");
    // The program's name as cargo built it: the same on every machine.
    stdout_ok(&out)
}

#[test]
fn every_commands_help_is_as_it_was() {
    let differ: Vec<String> = COMMANDS
        .iter()
        .filter_map(|c| {
            let name = if c.is_empty() { "stegongp" } else { c };
            check("help", name, &help(c))
        })
        .collect();
    assert!(differ.is_empty(), "{}", differ.join("\n"));
}

fn p(d: &Path, n: &str) -> String {
    d.join(n).to_str().unwrap().to_string()
}

/// The document a `--json` run prints on stdout, as its shape.
fn json_shape(args: &[&str]) -> String {
    let out = stegongp(args);
    let text = stdout_ok(&out);
    let v: Value = serde_json::from_str(&text)
        .unwrap_or_else(|e| panic!("stegongp {args:?}: not JSON ({e}): {text}"));
    golden::json_shape(&v)
}

/// `devices --json` where a GPU adapter opens (CI's is Mesa's llvmpipe): the adapters and
/// the opened device's features and limits.
#[test]
fn devices_json_is_shaped_as_it_was() {
    let text = stdout_ok(&stegongp(&["devices", "--json"]));
    let v: Value = serde_json::from_str(&text).expect("devices --json prints JSON");
    if v["opened"].is_null() {
        return testkit::missing(
            "GPU adapter",
            "apt-get install mesa-vulkan-drivers libvulkan1",
        );
    }
    golden::assert_json_shape("devices", &v);
}

/// Every command a few seconds can run, on a 32 px object and text trained for 6 steps on
/// the CPU: the shapes of their `--json`. `convert`'s and `process`'s are checked against
/// their golden files where their own tests run them (`tests/data_import.rs`,
/// `tests/process_cli.rs`), `devices`' above; `demo`, `render`, `view` and `experiment`
/// print no JSON document.
#[test]
fn every_small_runs_json_is_shaped_as_it_was() {
    let d = tempfile::tempdir().unwrap();
    let d = d.path();
    let (cover, text, key, model) = (p(d, "cover"), p(d, "text"), p(d, "k.key"), p(d, "m.ingp"));
    let mut shapes: Vec<(&str, String)> = Vec::new();
    shapes.push((
        "synth",
        json_shape(&[
            "synth", "--scene", "object", "--res", "32", "--train", "8", "--test", "2", "--out",
            &cover, "--json",
        ]),
    ));
    ok(&stegongp(&[
        "synth", "--scene", "text", "--res", "32", "--train", "8", "--test", "2", "--out", &text,
    ]));
    shapes.push(("keygen", json_shape(&["keygen", "--out", &key, "--json"])));
    let cpu = ["--device", "cpu"];
    let train = [
        "train",
        &cover,
        "--steps",
        "6",
        "--batch",
        "4096",
        "--log2-t",
        "12",
        "--hidden",
        &text,
        "--key",
        &key,
        "--checkpoints",
        "0.0001",
        "--eval-views",
        "1",
        "--save-every",
        "3",
        "--out",
        &model,
        "--json",
    ];
    shapes.push(("train", json_shape(&[&train[..], &cpu].concat())));
    shapes.push(("inspect", json_shape(&["inspect", &model, "--json"])));
    shapes.push((
        "eval",
        json_shape(&[
            "eval", "--model", &model, "--data", &text, "--key", &key, "--views", "1", "--json",
            "--device", "cpu",
        ]),
    ));
    shapes.push(("detect", json_shape(&["detect", &model, "--json"])));
    shapes.push((
        "mesh",
        json_shape(&[
            "mesh",
            &model,
            "--out",
            &p(d, "m.ply"),
            "--resolution",
            "16",
            "--json",
            "--device",
            "cpu",
        ]),
    ));
    shapes.push((
        "attack",
        json_shape(&[
            "attack",
            &model,
            "--out",
            &p(d, "a.ingp"),
            "noise=0.001",
            "prune=0.1",
            "--json",
        ]),
    ));
    shapes.push((
        "video",
        json_shape(&[
            "video",
            "--model",
            &model,
            "--frames",
            "2",
            "--width",
            "16",
            "--height",
            "16",
            "--frames-dir",
            &p(d, "frames"),
            "--json",
            "--device",
            "cpu",
        ]),
    ));
    let differ: Vec<String> = shapes
        .iter()
        .filter_map(|(name, s)| check("json", name, s))
        .collect();
    assert!(differ.is_empty(), "{}", differ.join("\n"));
}
