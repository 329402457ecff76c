//! The GPU benchmark script (`scripts/gpu_bench.py`) end to end in its small mode, on the
//! adapter CI has (llvmpipe): prepare a carry folder from a generated scene and this build's
//! binary, run every phase, and read back the JSON a GPU machine's run would write. Needs
//! Python 3 with Pillow (`.ci/run` installs Debian's); with `CI=true` their absence fails.

use std::path::Path;
use std::process::{Command, Output};
use testkit::cli::{bin, ok, stdout_ok, stegongp};

fn s_phases(r: &serde_json::Value) -> serde_json::Map<String, serde_json::Value> {
    r["summary"]["lego_device_ms_per_step"]
        .as_object()
        .cloned()
        .unwrap_or_default()
}

/// The generated object at `res` px with `train` + `test` views, into `out`.
fn synth_object(out: &str, res: &str, train: &str, test: &str) {
    ok(&stegongp(&[
        "synth", "--scene", "object", "--res", res, "--train", train, "--test", test, "--out", out,
    ]));
}

/// The first Python 3 that has Pillow: the one on PATH, then the system's. A version
/// manager's shim (pyenv) can come first on PATH without Pillow while Debian's
/// `python3-pil`, which `.ci/run` installs, sits under /usr/bin.
/// Probed once: every run of the script asks.
fn python_with_pillow() -> Option<&'static str> {
    static FOUND: std::sync::OnceLock<Option<&'static str>> = std::sync::OnceLock::new();
    *FOUND.get_or_init(|| {
        ["python3", "/usr/bin/python3", "/usr/local/bin/python3"]
            .into_iter()
            .find(|python| {
                Command::new(python)
                    .args(["-c", "import PIL.Image, lzma"])
                    .output()
                    .is_ok_and(|o| o.status.success())
            })
    })
}

fn script(args: &[&str]) -> Output {
    let python = python_with_pillow().expect("checked before the first call");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/gpu_bench.py");
    Command::new(python)
        .arg(script)
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("{python} runs: {e}"))
}

fn ok_script(args: &[&str]) -> String {
    let out = script(args);
    assert!(
        out.status.success(),
        "gpu_bench.py {args:?} failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Whether the script can run here: a Python with Pillow (said when missing) and an adapter.
fn script_can_run() -> bool {
    if python_with_pillow().is_none() {
        testkit::missing(
            "python3 with Pillow (on PATH or /usr/bin)",
            "the GPU benchmark's test needs it; Debian: python3-pil",
        );
        return false;
    }
    stegongp::gpu::test_context().is_some()
}

#[test]
fn gpu_bench_script_runs_end_to_end_in_small_mode() {
    if !script_can_run() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let p = |name: &str| dir.path().join(name).to_str().unwrap().to_string();
    synth_object(&p("obj"), "32", "12", "4");
    let binary = bin();
    let binary = binary.to_str().unwrap();
    let prepared = ok_script(&[
        "prepare",
        &p("carry"),
        "--small",
        "--lego",
        &p("obj"),
        "--binary",
        binary,
        "--no-loader",
    ]);
    let manifest: serde_json::Value = serde_json::from_str(&prepared).unwrap();
    // Every view recompressed, losslessly (the script checks each one decoded back).
    assert_eq!(manifest["lego"]["views"]["train"], 12);
    assert_eq!(manifest["lego"]["views"]["test"], 4);
    assert!(manifest["carried_bytes"].as_u64().unwrap() > 1 << 20);

    let software = stegongp::gpu::test_context().unwrap().report().software;
    if software {
        // A run that would measure llvmpipe fails loudly, before anything is trained.
        let out = script(&["run", &p("carry"), &p("refused")]);
        assert!(!out.status.success());
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains("only a software adapter"), "{err}");
        let partial: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(p("refused/gpu_bench.json")).unwrap())
                .unwrap();
        assert!(partial.get("lego").is_none());
    }

    ok_script(&["run", &p("carry"), &p("out"), "--small", "--allow-software"]);
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(p("out/gpu_bench.json")).unwrap()).unwrap();
    let limits = &r["devices"]["opened"]["limits"];
    assert!(limits["max_storage_buffer_binding_size"].as_u64().unwrap() > 0);
    let lego = &r["lego"];
    assert_eq!(lego["device"]["kind"], "gpu");
    assert_eq!(lego["checkpoints"].as_array().unwrap().len(), 5);
    // The step's own counters: the network's passes cover at least the trained samples;
    // the host waits at most once a step in this run, all warm-up (each step read at its
    // end), and to read a profiled step's timestamps (one step in 5); a step is one
    // submission, and one per occupancy update.
    let trained = lego["trained_per_step"].as_f64().unwrap();
    assert!(trained > 0.0);
    assert!(lego["network_per_step"].as_f64().unwrap() >= trained);
    let waits = lego["host_waits_per_step"].as_f64().unwrap();
    assert!(waits > 0.0 && waits <= 1.25, "{waits} host waits a step");
    let submissions = lego["submissions_per_step"].as_f64().unwrap();
    assert!(
        (1.0..=2.0).contains(&submissions),
        "{submissions} submissions a step"
    );
    // The device's phases, timed with timestamps (llvmpipe writes them too).
    let phases = &s_phases(&r);
    for name in [
        "rays: draw and march",
        "density network (marched)",
        "network backward (trained)",
        "optimizer (Adam + EMA)",
    ] {
        let ms = phases.get(name).and_then(|v| v.as_f64()).unwrap_or(-1.0);
        assert!(ms > 0.0, "{name}: {ms} in {phases:?}");
    }
    let s = &r["summary"];
    for k in [
        "pair_cover_psnr",
        "pair_hidden_psnr_key",
        "pair_hidden_psnr_wrong_key",
        "plain_text_psnr_same_steps",
        "plain_text_psnr_rebuilt_grid",
    ] {
        let v = s[k].as_f64().unwrap_or(f64::NAN);
        assert!(v.is_finite() && v > 5.0, "{k}: {v}");
    }
    assert_eq!(s["lego_psnr_by_minute"].as_object().unwrap().len(), 5);
    let lpips = s["lego_lpips_by_minute"].as_object().unwrap();
    assert_eq!(lpips.len(), 5);
    assert!(
        lpips
            .values()
            .all(|l| l.as_f64().is_some_and(|l| l > 0.0 && l < 1.0)),
        "{lpips:?}"
    );
    assert_eq!(r["plain_text"]["steps"], r["pair"]["steps"]);
    assert!(Path::new(&p("out/log.txt")).is_file());
}

/// A real capture carried instead of lego (here a generated scene, with a file the carry
/// leaves out), trained on the adapter in small mode, its model brought back in parts that
/// `join` puts together again, byte for byte, into a model the CPU renders; a damaged part
/// is refused and leaves no model.
#[test]
fn gpu_bench_capture_mode_brings_the_model_back() {
    if !script_can_run() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let p = |name: &str| dir.path().join(name).to_str().unwrap().to_string();
    synth_object(&p("cap"), "24", "6", "2");
    std::fs::create_dir(p("cap/notes")).unwrap();
    std::fs::write(p("cap/notes/big.txt"), vec![b'x'; 1 << 16]).unwrap();
    let binary = bin();
    let prepared = ok_script(&[
        "prepare",
        &p("carry"),
        "--small",
        "--capture",
        &p("cap"),
        "--capture-skip",
        "notes",
        "--binary",
        binary.to_str().unwrap(),
        "--no-loader",
    ]);
    let manifest: serde_json::Value = serde_json::from_str(&prepared).unwrap();
    // 6 + 2 images and the two transforms files, the notes left behind; no lego.
    assert_eq!(manifest["capture"]["files"], 10, "{manifest}");
    assert!(manifest.get("lego").is_none());
    assert!(Path::new(&p("carry/capture/transforms_train.json")).is_file());
    assert!(!Path::new(&p("carry/capture/notes")).exists());
    // A skip outside the capture is an error naming it.
    let out = script(&[
        "prepare",
        &p("carry2"),
        "--small",
        "--capture",
        &p("cap"),
        "--capture-skip",
        "../x",
        "--binary",
        binary.to_str().unwrap(),
        "--no-loader",
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--capture-skip ../x"));

    ok_script(&["run", &p("carry"), &p("out"), "--small", "--allow-software"]);
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(p("out/gpu_bench.json")).unwrap()).unwrap();
    assert!(r.get("lego").is_none() && r.get("pair").is_none());
    let c = &r["capture"];
    assert_eq!(c["device"]["kind"], "gpu");
    assert_eq!(c["checkpoints"].as_array().unwrap().len(), 2);
    let psnr = r["summary"]["capture_psnr_by_minute"].as_object().unwrap();
    assert_eq!(psnr.len(), 2);
    assert!(
        psnr.values().all(|v| v.as_f64().is_some_and(|v| v > 5.0)),
        "{psnr:?}"
    );
    let parts = r["capture_model"]["parts"].as_array().unwrap();
    assert!(!parts.is_empty());
    for part in parts {
        let f = dir.path().join("out").join(part.as_str().unwrap());
        assert!(std::fs::metadata(&f).unwrap().len() <= 15 << 20);
    }

    ok_script(&["join", &p("out"), &p("m.ingp")]);
    let size = std::fs::metadata(p("m.ingp")).unwrap().len();
    assert_eq!(size, r["capture_model"]["bytes"].as_u64().unwrap());
    let eval = stdout_ok(&stegongp(&[
        "eval",
        "--model",
        &p("m.ingp"),
        "--data",
        &p("cap"),
        "--device",
        "cpu",
        "--no-lpips",
        "--json",
    ]));
    let eval: serde_json::Value = serde_json::from_str(&eval).unwrap();
    assert!(eval["psnr"].as_f64().unwrap() > 5.0, "{eval}");

    let last = dir
        .path()
        .join("out")
        .join(parts.last().unwrap().as_str().unwrap());
    let mut bytes = std::fs::read(&last).unwrap();
    bytes[0] ^= 1;
    std::fs::write(&last, bytes).unwrap();
    let out = script(&["join", &p("out"), &p("m2.ingp")]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("do not make the model the run wrote"), "{err}");
    assert!(!Path::new(&p("m2.ingp")).exists() && !Path::new(&p("m2.ingp.tmp")).exists());
}

/// `train` on the CPU engine over a small generated object, 2 steps, with `extra` options;
/// the folder (for the model's path) and the process's output.
fn train_on_cpu(extra: &[&str]) -> (tempfile::TempDir, std::process::Output) {
    let dir = tempfile::tempdir().unwrap();
    let p = |name: &str| dir.path().join(name).to_str().unwrap().to_string();
    synth_object(&p("obj"), "24", "4", "1");
    let (obj, model) = (p("obj"), p("m.ingp"));
    let mut args = vec![
        "train", &obj, "--out", &model, "--device", "cpu", "--steps", "2",
    ];
    args.extend_from_slice(extra);
    let out = stegongp(&args);
    (dir, out)
}

/// `--profile-every` on the CPU engine: said to be ignored, the training unchanged, no
/// device phases in the JSON.
#[test]
fn profile_every_is_ignored_with_a_notice_on_the_cpu() {
    let (_dir, out) = train_on_cpu(&["--batch", "4096", "--profile-every", "1", "--json"]);
    let stdout = stdout_ok(&out);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("--profile-every") && err.contains("ignored"),
        "{err}"
    );
    let summary: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(summary["steps"], 2);
    assert!(summary.get("device_phases_ms").is_none());
    assert_eq!(summary["host_waits_per_step"], 0.0);
}

/// `--half-grid` is a GPU option: on the CPU it is an error naming it, before any training,
/// and no model is written.
#[test]
fn half_grid_on_the_cpu_is_an_error() {
    let (dir, out) = train_on_cpu(&["--half-grid"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("fp16 copy of the grid is a GPU option"),
        "{err}"
    );
    assert!(!dir.path().join("m.ingp").exists());
}

/// Without Pillow (`python3 -S` leaves out the site packages it lives in) the script stops
/// at once, naming the interpreter and the missing module, before building anything.
#[test]
fn without_pillow_the_script_stops_before_building() {
    let Ok(probe) = Command::new("python3").arg("--version").output() else {
        eprintln!("skipping: no python3");
        return;
    };
    assert!(probe.status.success());
    let dir = tempfile::tempdir().unwrap();
    let carry = dir.path().join("carry");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/gpu_bench.py");
    for args in [
        vec!["prepare", carry.to_str().unwrap()],
        vec![
            "run",
            carry.to_str().unwrap(),
            dir.path().join("out").to_str().unwrap(),
        ],
    ] {
        let out = Command::new("python3")
            .arg("-S")
            .arg(&script)
            .args(&args)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{args:?}: {err}");
        assert!(err.contains("has no Pillow"), "{args:?}: {err}");
        assert!(!carry.exists(), "{args:?} made the carry folder");
    }
}
