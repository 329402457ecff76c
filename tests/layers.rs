//! The workspace's crates are its layers, and their dependencies run one way: the app on the
//! experiments, the viewer layer (camera paths, video, web viewer), the meshes and the capture pipeline,
//! the experiments on the attacks, those on the stego layer, the stego layer on the device
//! boundary and the capture readers (dataset), those on the engine (and its wgpu backend),
//! the experiments and the app on the scoring too (which reads the engine alone), and the
//! engine on no other crate of ours, nor on wgpu or clap. Read from `cargo metadata` (the
//! resolved graph, so a dependency of a dependency counts too).

use serde_json::Value;
use std::collections::{BTreeMap, BTreeSet};
use std::process::Command;

/// Each crate of the workspace and the crates of ours it may depend on (normal and build
/// dependencies; tests may use more).
const ALLOWED: [(&str, &[&str]); 16] = [
    ("stegongp-ngp", &[]),
    // Captures on disk (transforms.json, COLMAP, LLFF) read into the engine's datasets.
    ("stegongp-dataset", &["stegongp-ngp"]),
    // The capture pipeline (`process`): ffmpeg and COLMAP driven, the capture checked by
    // the loaders.
    ("stegongp-capture", &["stegongp-ngp", "stegongp-dataset"]),
    ("stegongp-gpu", &["stegongp-ngp"]),
    ("stegongp-backend", &["stegongp-ngp", "stegongp-gpu"]),
    ("stegongp-synth", &["stegongp-ngp", "stegongp-dataset"]),
    // Meshes out of a model's density: the engine alone (the caller passes the density).
    ("stegongp-mesh", &["stegongp-ngp"]),
    // Metrics, LPIPS and the evaluation protocols: they render through the engine's
    // `RenderBackend` and score; the engine knows nothing of them.
    ("stegongp-score", &["stegongp-ngp"]),
    (
        "stegongp-stego",
        &[
            "stegongp-ngp",
            "stegongp-dataset",
            "stegongp-gpu",
            "stegongp-backend",
        ],
    ),
    // The one training run (recipe, steps, state, checkpoints): keys from stego, devices
    // from backend; nothing above them.
    (
        "stegongp-training",
        &[
            "stegongp-ngp",
            "stegongp-dataset",
            "stegongp-gpu",
            "stegongp-backend",
            "stegongp-stego",
            "stegongp-score",
        ],
    ),
    // Edits of a published model (noise, pruning, fine-tuning, purification): they read
    // files and train through the recipe, and know nothing of the experiments.
    (
        "stegongp-attack",
        &[
            "stegongp-ngp",
            "stegongp-dataset",
            "stegongp-gpu",
            "stegongp-backend",
            "stegongp-stego",
            "stegongp-training",
            "stegongp-score",
        ],
    ),
    (
        "stegongp-experiments",
        &[
            "stegongp-ngp",
            "stegongp-dataset",
            "stegongp-gpu",
            "stegongp-backend",
            "stegongp-stego",
            "stegongp-training",
            "stegongp-synth",
            "stegongp-attack",
            "stegongp-score",
        ],
    ),
    (
        "stegongp-viewer",
        &[
            "stegongp-ngp",
            "stegongp-dataset",
            "stegongp-gpu",
            "stegongp-backend",
            "stegongp-stego",
        ],
    ),
    // A tool beside the app: it drives the same readers the app does.
    (
        "stegongp-fuzz",
        &[
            "stegongp-ngp",
            "stegongp-dataset",
            "stegongp-gpu",
            "stegongp-backend",
            "stegongp-stego",
            "stegongp-training",
            "stegongp-synth",
            "stegongp-experiments",
            "stegongp-viewer",
            "stegongp-attack",
            "stegongp-score",
        ],
    ),
    (
        "stegongp-testkit",
        &[
            "stegongp-ngp",
            "stegongp-dataset",
            "stegongp-gpu",
            "stegongp-backend",
            "stegongp-stego",
            "stegongp-training",
            "stegongp-score",
            "stegongp-synth",
        ],
    ),
    (
        "stegongp",
        &[
            "stegongp-ngp",
            "stegongp-dataset",
            "stegongp-capture",
            "stegongp-gpu",
            "stegongp-backend",
            "stegongp-stego",
            "stegongp-training",
            "stegongp-synth",
            "stegongp-experiments",
            "stegongp-viewer",
            "stegongp-attack",
            "stegongp-mesh",
            "stegongp-score",
        ],
    ),
];

/// Crates of the outside world a layer must not reach: the engine knows no device and no
/// command line.
const FORBIDDEN: [(&str, &[&str]); 5] = [
    ("stegongp-ngp", &["wgpu", "clap", "anyhow", "indicatif"]),
    ("stegongp-dataset", &["wgpu", "clap", "anyhow", "indicatif"]),
    // The program draws the pipeline's progress.
    ("stegongp-capture", &["wgpu", "indicatif"]),
    ("stegongp-gpu", &["clap", "anyhow", "indicatif"]),
    ("stegongp-synth", &["wgpu"]),
];

/// Package name → the names of everything it depends on (normal and build), transitively.
fn closure() -> BTreeMap<String, BTreeSet<String>> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    // The host's graph: the crates built here, which are what an offline run has.
    let version = Command::new(&cargo)
        .arg("-vV")
        .output()
        .expect("run cargo -vV");
    let version = String::from_utf8_lossy(&version.stdout);
    let host = version
        .lines()
        .find_map(|l| l.strip_prefix("host: "))
        .expect("cargo -vV names the host");
    let out = Command::new(&cargo)
        .args(["metadata", "--format-version", "1", "--locked", "--offline"])
        .args(["--filter-platform", host])
        .arg("--manifest-path")
        .arg(concat!(env!("CARGO_MANIFEST_DIR"), "/Cargo.toml"))
        .output()
        .expect("run cargo metadata");
    assert!(
        out.status.success(),
        "cargo metadata: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let meta: Value = serde_json::from_slice(&out.stdout).expect("cargo metadata's JSON");
    let name_of: BTreeMap<&str, &str> = meta["packages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| (p["id"].as_str().unwrap(), p["name"].as_str().unwrap()))
        .collect();
    // Direct edges, without dev-dependencies.
    let mut direct: BTreeMap<&str, Vec<&str>> = BTreeMap::new();
    for node in meta["resolve"]["nodes"].as_array().unwrap() {
        let id = node["id"].as_str().unwrap();
        let deps = node["deps"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|d| {
                d["dep_kinds"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .any(|k| k["kind"].as_str() != Some("dev"))
            })
            .map(|d| d["pkg"].as_str().unwrap())
            .collect();
        direct.insert(id, deps);
    }
    let members: Vec<&str> = meta["workspace_members"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| m.as_str().unwrap())
        .collect();
    members
        .iter()
        .map(|&m| {
            let mut seen = BTreeSet::new();
            let mut stack = direct[m].clone();
            while let Some(id) = stack.pop() {
                if seen.insert(name_of[id].to_string()) {
                    stack.extend(direct[id].iter().copied());
                }
            }
            (name_of[m].to_string(), seen)
        })
        .collect()
}

#[test]
fn dependencies_run_down_the_layers() {
    let deps = closure();
    let ours: BTreeSet<&str> = ALLOWED.iter().map(|(n, _)| *n).collect();
    let members: BTreeSet<&str> = deps.keys().map(String::as_str).collect();
    assert_eq!(members, ours, "a crate without its place in ALLOWED");
    for (krate, allowed) in ALLOWED {
        let reached: BTreeSet<&str> = deps[krate]
            .iter()
            .map(String::as_str)
            .filter(|d| ours.contains(d))
            .collect();
        let extra: Vec<&&str> = reached.iter().filter(|d| !allowed.contains(d)).collect();
        assert!(extra.is_empty(), "{krate} depends on {extra:?}");
    }
    for (krate, forbidden) in FORBIDDEN {
        for f in forbidden {
            assert!(!deps[krate].contains(*f), "{krate} depends on {f}");
        }
    }
    // What the boundary is for: the engine reaches nothing of ours, the app everything.
    assert!(
        deps["stegongp-ngp"]
            .iter()
            .all(|d| !ours.contains(d.as_str()))
    );
    assert!(deps["stegongp"].contains("stegongp-experiments"));
}
