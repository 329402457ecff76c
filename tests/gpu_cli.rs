//! `--device` as a user meets it: `train`, `eval` and `render` on the GPU (in CI: Mesa's
//! software llvmpipe), the device named in the output and in `--json`, and the same model
//! scored the same on both devices.
#![cfg(feature = "gpu")]

use serde_json::Value;
use std::process::Output;
use stegongp::gpu::{AdapterRequest, GpuContext, test_context};
use testkit::cli::stegongp;

fn ok(out: Output) -> (String, String) {
    let err = testkit::cli::ok(&out);
    (String::from_utf8_lossy(&out.stdout).into_owned(), err)
}

fn json(out: Output) -> Value {
    let (stdout, _) = ok(out);
    serde_json::from_str(&stdout).unwrap_or_else(|e| panic!("{e}: {stdout}"))
}

#[test]
fn train_eval_and_render_on_the_gpu_agree_with_the_cpu() {
    if test_context().is_none() {
        return;
    }
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_str().unwrap().to_string();
    let (cover, text, key, model) = (p("cover"), p("text"), p("k.json"), p("m.ingp"));
    for (scene, dir) in [("object", &cover), ("text", &text)] {
        ok(stegongp(&[
            "synth", "--scene", scene, "--res", "32", "--train", "16", "--test", "2", "--out", dir,
        ]));
    }
    ok(stegongp(&["keygen", "--scheme", "prf", "--out", &key]));
    let trained = json(stegongp(&[
        "train",
        &cover,
        "--hidden",
        &text,
        "--key",
        &key,
        "--steps",
        "40",
        "--batch",
        "4096",
        "--log2-t",
        "14",
        "--occupancy-fraction",
        "0.01",
        "--device",
        "gpu",
        "--json",
        "--out",
        &model,
    ]));
    assert_eq!(trained["device"]["kind"], "gpu", "{trained}");
    assert_eq!(trained["steps"], 40);
    assert!(trained["samples_per_second"].as_f64().unwrap() > 0.0);

    // The same file scored on both devices. (A key holder's grid rebuild on the device is
    // tested against the CPU's in gpu_render.rs: on llvmpipe it takes about a minute.)
    let score = |device: &str| {
        let r = json(stegongp(&[
            "eval",
            "--model",
            &model,
            "--data",
            &cover,
            "--no-lpips",
            "--json",
            "--device",
            device,
        ]));
        assert_eq!(r["device"]["kind"], device, "{r}");
        (
            r["psnr"].as_f64().unwrap(),
            r["blank_psnr"].as_f64().unwrap(),
        )
    };
    let ((cpu, blank), (gpu, _)) = (score("cpu"), score("gpu"));
    eprintln!("cover: CPU {cpu:.3} dB, GPU {gpu:.3} dB, empty render {blank:.3}");
    assert!(
        (cpu - gpu).abs() < 0.1,
        "CPU {cpu:.3} dB against GPU {gpu:.3} dB"
    );
    assert!(
        cpu > blank + 2.0,
        "cover {cpu:.2} dB against empty {blank:.2}: learnt nothing"
    );

    let out = p("renders");
    let (_, log) = ok(stegongp(&[
        "render", "--model", &model, "--data", &cover, "--views", "1", "--device", "gpu", "--out",
        &out,
    ]));
    assert!(log.contains("device: gpu"), "{log}");
    for f in ["rgb_000.png", "depth_000.png", "opacity_000.png"] {
        assert!(d.path().join("renders").join(f).is_file(), "{f} missing");
    }
}

/// `auto` never takes a software adapter: on a machine whose only GPU is llvmpipe (CI) it
/// runs on the CPU and says why; `cpu` is the CPU.
#[test]
fn auto_and_cpu_say_which_device_ran() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_str().unwrap().to_string();
    let (scene, model) = (p("scene"), p("m.ingp"));
    ok(stegongp(&[
        "synth", "--scene", "object", "--res", "16", "--train", "2", "--test", "1", "--out", &scene,
    ]));
    let hardware = GpuContext::new(AdapterRequest::Auto).is_ok();
    for (device, kind) in [
        ("cpu", "cpu"),
        ("auto", if hardware { "gpu" } else { "cpu" }),
    ] {
        let r = json(stegongp(&[
            "train", &scene, "--steps", "2", "--batch", "1024", "--log2-t", "12", "--device",
            device, "--json", "--out", &model,
        ]));
        assert_eq!(r["device"]["kind"], kind, "--device {device}: {r}");
        let fallback = r["device"].get("fallback").is_some();
        assert_eq!(fallback, device == "auto" && !hardware, "{r}");
    }
    let out = stegongp(&["train", &scene, "--device", "cuda", "--out", &model]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("cuda") && err.contains("gpu"), "{err}");
}

/// `train` of a 16 px generated object for one step on the GPU with `options`, which must
/// fail naming each of `says` and write nothing; its standard error.
fn refused_on_the_gpu(options: &[&str], says: &[&str]) -> String {
    let d = tempfile::tempdir().unwrap();
    let scene = d.path().join("obj");
    testkit::cli::synth(&scene, "object", 16, 2);
    let model = d.path().join("m.ingp");
    let (scene, out) = (scene.to_str().unwrap(), model.to_str().unwrap());
    let mut args = vec![
        "train", scene, "--steps", "1", "--device", "gpu", "--out", out,
    ];
    args.extend_from_slice(options);
    let run = stegongp(&args);
    testkit::cli::fails_naming(&run, says);
    assert!(!model.exists());
    String::from_utf8_lossy(&run.stderr).into_owned()
}

/// A batch the device cannot hold is refused before training, with the most it holds. A
/// batch near 2^32 used to wrap in the capacity's rounding and report "hold 0".
#[test]
fn a_batch_larger_than_the_device_holds_is_refused_with_its_limit() {
    if test_context().is_none() {
        return;
    }
    for batch in ["4000000000", "4294967295"] {
        let says = [batch, "samples per batch", "at most"];
        let err = refused_on_the_gpu(&["--batch", batch], &says);
        assert!(!err.contains("at most 0 "), "{err}");
    }
}

/// Camera refinement is the CPU trainer's (so far): on the GPU it is refused by name, with
/// nothing written.
#[test]
fn camera_refinement_on_the_gpu_is_refused_naming_it() {
    if test_context().is_none() {
        return;
    }
    let options = ["--refine-cameras", "--batch", "4096"];
    refused_on_the_gpu(&options, &["camera refinement", "CPU"]);
}
