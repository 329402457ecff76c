//! `train --save-every` / `--resume`: a run stopped (or killed) and resumed writes the same
//! model, byte for byte, as the run that never stopped; a stego run's state is owner-only;
//! a state from another run, or not a state at all, is refused by name.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use testkit::cli::{bin, fails_naming, run_ok, stegongp};

fn synth(dir: &Path, scene: &str) {
    testkit::cli::synth(dir, scene, 24, 8);
}

/// Common options of every run here: small and fast, the same for all.
const RUN: &[&str] = &[
    "--batch",
    "1024",
    "--levels",
    "8",
    "--log2-t",
    "12",
    "--seed",
    "3",
    "--occupancy-fraction",
    "0.05",
    "--device",
    "cpu",
];

fn train(scene: &Path, out: &Path, extra: &[&str]) -> String {
    let mut args = vec![
        "train",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(RUN);
    args.extend_from_slice(extra);
    run_ok(&args)
}

fn bytes(p: &Path) -> Vec<u8> {
    std::fs::read(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// The checkpoint's `snapshot.optimizer` is laid out as tiny-cuda-nn's `Ema` ∘
/// `ExponentialDecay` ∘ `Adam` serialise it (what instant-ngp's loader reads back): fp16 EMA
/// weights, f32 moments and u32 step counts of every parameter, the step and rates.
fn assert_ngp_optimizer_layout(checkpoint: &Path) {
    use rmpv::Value;
    let doc = rmpv::decode::read_value(&mut bytes(checkpoint).as_slice()).unwrap();
    let get = |v: &Value, k: &str| -> Value {
        v.as_map()
            .and_then(|m| m.iter().find(|(x, _)| x.as_str() == Some(k)))
            .map(|(_, v)| v.clone())
            .unwrap_or_else(|| panic!("no {k}"))
    };
    let snap = get(&doc, "snapshot");
    let n = get(&snap, "n_params").as_u64().unwrap() as usize;
    let bin = |v: Value| v.as_slice().map(<[u8]>::len).unwrap();
    let ema = get(&snap, "optimizer");
    assert_eq!(bin(get(&ema, "weights_ema_binary")), n * 2);
    let decay = get(&ema, "nested");
    assert_eq!(get(&decay, "learning_rate").as_f64(), Some(1e-2f32 as f64));
    assert_eq!(get(&decay, "learning_rate_factor").as_f64(), Some(1.0));
    let adam = get(&decay, "nested");
    for k in [
        "first_moments_binary",
        "second_moments_binary",
        "param_steps_binary",
    ] {
        assert_eq!(bin(get(&adam, k)), n * 4, "{k}");
    }
    assert_eq!(
        get(&adam, "current_step").as_u64(),
        get(&snap, "training_step").as_u64()
    );
    assert!(get(&adam, "base_learning_rate").as_f64().is_some());
}

#[test]
fn a_resumed_run_writes_the_uninterrupted_runs_model() {
    let d = tempfile::tempdir().unwrap();
    let scene = d.path().join("scene");
    synth(&scene, "object");
    let whole = d.path().join("whole.ingp");
    train(&scene, &whole, &["--steps", "40"]);
    // Stopped at step 16 (a state every 8 steps and at the end), then resumed to 40.
    let part = d.path().join("part.ingp");
    let err = train(&scene, &part, &["--steps", "16", "--save-every", "8"]);
    let state = d.path().join("part.checkpoint.msgpack");
    assert!(err.contains("part.checkpoint.msgpack"), "{err}");
    // The checkpoint is a snapshot with its optimizer state, as instant-ngp saves one: our
    // tools open it as a model; the published model has neither optimizer nor run state.
    let inspect = |p: &Path| -> serde_json::Value {
        let out = stegongp(&["inspect", p.to_str().unwrap(), "--json"]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        serde_json::from_slice(&out.stdout).unwrap()
    };
    let c = inspect(&state);
    assert_eq!(c["has_optimizer_state"], true, "{c}");
    assert_eq!(c["has_run_state"], true, "{c}");
    assert_ngp_optimizer_layout(&state);
    assert_eq!(c["training_step"], 16, "{c}");
    assert_eq!(inspect(&part)["has_optimizer_state"], false);
    let raw = bytes(&state);
    let needle = b"stegongp_run_state";
    assert!(raw.windows(needle.len()).any(|w| w == needle));
    assert!(!bytes(&part).windows(needle.len()).any(|w| w == needle));
    let resumed = d.path().join("resumed.ingp");
    let err = train(
        &scene,
        &resumed,
        &["--steps", "40", "--resume", state.to_str().unwrap()],
    );
    assert!(
        err.contains("resumed from") && err.contains("at step 16"),
        "{err}"
    );
    assert!(
        bytes(&resumed) == bytes(&whole),
        "the resumed model differs"
    );
    // Not by accident: the model of step 16 is another file.
    assert!(bytes(&part) != bytes(&whole));
}

#[test]
fn a_stego_run_resumes_too_and_its_state_is_owner_only() {
    use std::os::unix::fs::PermissionsExt;
    let d = tempfile::tempdir().unwrap();
    let (cover, text) = (d.path().join("cover"), d.path().join("text"));
    synth(&cover, "object");
    synth(&text, "text");
    let key = d.path().join("k.json");
    run_ok(&["keygen", "--scheme", "prf", "--out", key.to_str().unwrap()]);
    let stego = [
        "--hidden",
        text.to_str().unwrap(),
        "--key",
        key.to_str().unwrap(),
    ];
    let whole = d.path().join("whole.ingp");
    train(&cover, &whole, &[&stego[..], &["--steps", "30"]].concat());
    let part = d.path().join("part.ingp");
    let state = d.path().join("run.state");
    let err = train(
        &cover,
        &part,
        &[
            &stego[..],
            &[
                "--steps",
                "12",
                "--save-every",
                "12",
                "--state",
                state.to_str().unwrap(),
            ],
        ]
        .concat(),
    );
    assert!(err.contains("keep it like the keys"), "{err}");
    let mode = std::fs::metadata(&state).unwrap().permissions().mode() & 0o777;
    assert_eq!(mode, 0o600, "the state of a stego run is owner-only");
    let resumed = d.path().join("resumed.ingp");
    train(
        &cover,
        &resumed,
        &[
            &stego[..],
            &["--steps", "30", "--resume", state.to_str().unwrap()],
        ]
        .concat(),
    );
    assert!(
        bytes(&resumed) == bytes(&whole),
        "the resumed stego model differs"
    );
}

/// `--stealth` (its policy's state: the confinement it made, held-back gradients, bounds,
/// gradients of hidden-only steps waiting for the cover's) resumes byte for byte too, with
/// the shared MLP and with the cover's own, on the schedule whose hidden steps update
/// nothing.
#[test]
fn a_stealth_run_resumes_byte_for_byte() {
    let d = tempfile::tempdir().unwrap();
    let (cover, text) = (d.path().join("cover"), d.path().join("text"));
    synth(&cover, "object");
    synth(&text, "text");
    let key = d.path().join("k.json");
    run_ok(&["keygen", "--scheme", "prf", "--out", key.to_str().unwrap()]);
    let stego = [
        "--hidden",
        text.to_str().unwrap(),
        "--key",
        key.to_str().unwrap(),
        "--stealth",
        "--schedule",
        "random-scene",
        "--hidden-from",
        "4",
    ];
    for mlp in [&[][..], &["--cover-only-mlp"][..]] {
        let opts = [&stego[..], mlp].concat();
        let whole = d.path().join("whole.ingp");
        train(&cover, &whole, &[&opts[..], &["--steps", "36"]].concat());
        // The step after 13 trains the cover and refreshes the confinement; the one after
        // 17 trains the hidden scene alone, on the confinement the state carried (a resume
        // that rebuilt it from the installation's would differ there, as measured).
        for stop in ["13", "17"] {
            let part = d.path().join("part.ingp");
            let state = d.path().join("run.state");
            let s = state.to_str().unwrap();
            let save = ["--steps", stop, "--save-every", "5", "--state", s];
            train(&cover, &part, &[&opts[..], &save].concat());
            let resumed = d.path().join("resumed.ingp");
            let err = train(
                &cover,
                &resumed,
                &[&opts[..], &["--steps", "36", "--resume", s]].concat(),
            );
            assert!(err.contains(&format!("at step {stop}")), "{err}");
            assert!(
                bytes(&resumed) == bytes(&whole),
                "{mlp:?} stopped at {stop}: the resumed stealth model differs"
            );
        }
    }
}

/// kill -9 at a random step of a run that saves every 4 steps; the run resumed from what
/// was left writes the uninterrupted run's model.
#[test]
fn a_run_killed_at_any_moment_resumes_to_the_same_model() {
    let d = tempfile::tempdir().unwrap();
    let scene = d.path().join("scene");
    synth(&scene, "object");
    let whole = d.path().join("whole.ingp");
    train(&scene, &whole, &["--steps", "60"]);
    let reference = bytes(&whole);
    for (trial, delay_ms) in [250u64, 700, 1300].into_iter().enumerate() {
        let out = d.path().join(format!("killed{trial}.ingp"));
        let state = d.path().join(format!("killed{trial}.checkpoint.msgpack"));
        let mut child = Command::new(bin())
            .arg("train")
            .arg(&scene)
            .arg("--out")
            .arg(&out)
            .args(RUN)
            .args(["--steps", "60", "--save-every", "4"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        // Kill once the first state exists, after a further delay.
        let t0 = Instant::now();
        while !state.exists() && t0.elapsed() < Duration::from_secs(60) {
            std::thread::sleep(Duration::from_millis(5));
        }
        std::thread::sleep(Duration::from_millis(delay_ms));
        let _ = child.kill();
        let status = child.wait().unwrap();
        let resumed = d.path().join(format!("resumed{trial}.ingp"));
        train(
            &scene,
            &resumed,
            &["--steps", "60", "--resume", state.to_str().unwrap()],
        );
        assert!(
            bytes(&resumed) == reference,
            "trial {trial} (killed: {:?}) resumed to another model",
            status.code()
        );
    }
}

#[test]
fn a_state_from_another_run_or_no_state_is_refused_by_name() {
    let d = tempfile::tempdir().unwrap();
    let scene = d.path().join("scene");
    synth(&scene, "object");
    let m = d.path().join("m.ingp");
    train(&scene, &m, &["--steps", "4", "--save-every", "4"]);
    let state = d.path().join("m.checkpoint.msgpack");
    let out = d.path().join("o.ingp");
    let (s, o) = (state.to_str().unwrap(), out.to_str().unwrap());
    let sc = scene.to_str().unwrap();
    // Another seed: the options differ.
    let mut other: Vec<&str> = vec!["train", sc, "--out", o, "--resume", s, "--steps", "8"];
    other.extend(RUN.iter().map(|x| if *x == "3" { "4" } else { x }));
    fails_naming(&stegongp(&other), &["m.checkpoint.msgpack", "options"]);
    // A model is not a state: it has no run state to go on from.
    let mut wrong: Vec<&str> = vec!["train", sc, "--out", o, "--resume", m.to_str().unwrap()];
    wrong.extend_from_slice(RUN);
    fails_naming(&stegongp(&wrong), &["m.ingp", "run state"]);
    // Bad --save-every values and the state over the model.
    for bad in ["0", "-3", "5x", "0m", "nanm"] {
        let flag = format!("--save-every={bad}");
        let mut a: Vec<&str> = vec!["train", sc, "--out", o, &flag];
        a.extend_from_slice(RUN);
        fails_naming(&stegongp(&a), &["--save-every"]);
    }
    let mut same: Vec<&str> = vec!["train", sc, "--out", o, "--save-every", "2", "--state", o];
    same.extend_from_slice(RUN);
    fails_naming(&stegongp(&same), &["two files"]);
    // A plain run's state is a snapshot: a name its writer refuses is refused before any
    // step is spent, not at the first save.
    let bad_state = d.path().join("s.state");
    let mut named: Vec<&str> = vec!["train", sc, "--out", o, "--save-every", "2"];
    named.extend(["--state", bad_state.to_str().unwrap()]);
    named.extend_from_slice(RUN);
    fails_naming(&stegongp(&named), &["--state", "s.state", ".ingp"]);
    assert!(!out.exists(), "nothing written");
    assert!(!bad_state.exists(), "no state written");
}
