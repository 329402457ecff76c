//! The GPU paths under the Khronos Vulkan validation layer with synchronization validation:
//! wgpu checks its own API, but only the layer sees what reaches the driver (a missing
//! barrier between two of our passes, a buffer bound past its range), which llvmpipe
//! forgives and a hardware driver may not. A plain run (fp16 grid copy, device profiling),
//! a stego run under a key, and a render: no error, warning or hazard reported.
//!
//! Needs the layer (Debian: vulkan-validationlayers; `.ci/run` installs it). Without it the
//! test says so and passes, except with CI=true, where it fails.
#![cfg(feature = "gpu")]

use std::path::Path;
use std::process::Command;
use stegongp::gpu::test_context;
use testkit::cli::bin;

const LAYER: &str = "VK_LAYER_KHRONOS_validation";
const MANIFEST_DIRS: [&str; 3] = [
    "/usr/share/vulkan/explicit_layer.d",
    "/usr/local/share/vulkan/explicit_layer.d",
    "/etc/vulkan/explicit_layer.d",
];

fn layer_installed() -> bool {
    MANIFEST_DIRS.iter().any(|d| {
        Path::new(d)
            .join("VkLayer_khronos_validation.json")
            .is_file()
    })
}

/// Runs `stegongp args` with the layer on, its messages written to `log`; the layer's
/// report, after checking the run succeeded.
fn run_validated(dir: &Path, name: &str, args: &[&str]) -> String {
    let log = dir.join(format!("{name}.log"));
    let settings = dir.join(format!("{name}_settings.txt"));
    std::fs::write(
        &settings,
        format!(
            "khronos_validation.report_flags = error,warn,perf,info\n\
             khronos_validation.debug_action = VK_DBG_LAYER_ACTION_LOG_MSG\n\
             khronos_validation.log_filename = {}\n\
             khronos_validation.enables = VK_VALIDATION_FEATURE_ENABLE_SYNCHRONIZATION_VALIDATION_EXT\n",
            log.display()
        ),
    )
    .unwrap();
    let out = Command::new(bin())
        .args(args)
        .env("VK_INSTANCE_LAYERS", LAYER)
        .env("VK_LAYER_SETTINGS_PATH", &settings)
        .output()
        .expect("run stegongp");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "stegongp {args:?} failed: {err}");
    std::fs::read_to_string(&log).unwrap_or_default()
}

/// The layer's reports that are problems: errors, warnings and performance warnings.
fn problems(report: &str) -> Vec<&str> {
    report
        .lines()
        .filter(|l| {
            [
                "Validation Error",
                "Validation Warning",
                "Validation Performance",
            ]
            .iter()
            .any(|k| l.contains(k))
        })
        .collect()
}

#[test]
fn the_problem_filter_keeps_errors_and_hazards_and_drops_information() {
    let report = "\
UNASSIGNED-khronos-validation-createinstance-status-message(INFO / SPEC): msgNum: -6 - Validation Information: [ x ]
SYNC-HAZARD-READ-AFTER-WRITE(ERROR / SPEC): msgNum: 1 - Validation Error: [ SYNC-HAZARD-READ-AFTER-WRITE ] vkCmdDispatch
VUID-vkCmdDispatch-None-02697(ERROR / SPEC): msgNum: 2 - Validation Error: [ VUID ] bound past its range
UNASSIGNED-x(WARN / SPEC): msgNum: 3 - Validation Warning: [ x ]";
    let p = problems(report);
    assert_eq!(p.len(), 3, "{p:?}");
    assert!(p[0].contains("SYNC-HAZARD"));
}

#[test]
fn gpu_runs_are_clean_under_the_validation_layer() {
    if test_context().is_none() {
        return;
    }
    if !layer_installed() {
        testkit::missing(
            LAYER,
            "Debian: vulkan-validationlayers, which .ci/run installs",
        );
        return;
    }
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n).to_str().unwrap().to_string();
    let (cover, text, key) = (p("cover"), p("text"), p("k.json"));
    let (plain, pair, views) = (p("plain.ingp"), p("pair.ingp"), p("views"));
    testkit::cli::synth(Path::new(&cover), "object", 32, 12);
    testkit::cli::synth(Path::new(&text), "text", 32, 12);
    testkit::cli::run_ok(&["keygen", "--out", &key]);
    let small = [
        "--steps",
        "6",
        "--batch",
        "4096",
        "--log2-t",
        "14",
        "--occupancy-fraction",
        "0.0078125",
        "--device",
        "gpu",
    ];
    let runs: [(&str, Vec<&str>); 3] = [
        (
            "plain",
            [
                &["train", &cover, "--half-grid", "--profile-every", "2"][..],
                &small,
                &["--out", &plain],
            ]
            .concat(),
        ),
        (
            "stego",
            [
                &["train", &cover, "--hidden", &text, "--key", &key][..],
                &small,
                &["--out", &pair],
            ]
            .concat(),
        ),
        (
            "render",
            vec![
                "render", "--model", &pair, "--data", &cover, "--views", "1", "--device", "gpu",
                "--out", &views,
            ],
        ),
    ];
    for (name, args) in &runs {
        let report = run_validated(d.path(), name, args);
        // The layer's own greeting: it ran, with synchronization validation on.
        assert!(
            report.contains("createinstance-status-message")
                && report.contains("SYNCHRONIZATION_VALIDATION"),
            "{name}: the validation layer did not report in: {report}"
        );
        let p = problems(&report);
        assert!(
            p.is_empty(),
            "{name}: {} reports:\n{}",
            p.len(),
            p.join("\n")
        );
    }
}
