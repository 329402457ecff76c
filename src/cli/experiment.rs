use anyhow::{Result, bail};
use std::path::PathBuf;
use stegongp::experiments::{EXPERIMENTS, ExpConfig, KeySchemeArg, run_experiment};
use stegongp::ngp::encoding::GridConfig;
use stegongp::ngp::train::Schedule;
use stegongp::synth::{SceneKind, SynthOptions, generate};

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum SchemeArg {
    Prf,
    Primes,
}

#[derive(clap::Args, Debug)]
pub struct Args {
    /// fidelity | key-sensitivity | partial-keys | multi-hidden | table-size | key-strength
    pub name: String,
    /// Output directory: the report goes to OUT/NAME/ (report.md, report.json, PNG grids),
    /// generated scenes to OUT/data/.
    #[arg(long, default_value = "out/experiments")]
    pub out: PathBuf,
    /// Cover scene (default: a generated object scene).
    #[arg(long)]
    pub cover: Option<PathBuf>,
    /// Hidden scene(s) (default: generated 3D text scenes).
    #[arg(long)]
    pub hidden: Vec<PathBuf>,
    /// Downscale factor of the cover's images.
    #[arg(long, default_value_t = 1)]
    pub downscale: u32,
    /// Downscale factor of the hidden scenes' images.
    #[arg(long, default_value_t = 1)]
    pub hidden_downscale: u32,
    /// Training steps per model.
    #[arg(long, default_value_t = 300)]
    pub steps: u32,
    /// Samples per scene per step.
    #[arg(long, default_value_t = 1 << 15)]
    pub batch: u32,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Held-out views evaluated per scene.
    #[arg(long, default_value_t = 8)]
    pub eval_views: usize,
    #[arg(long, default_value_t = 0.125)]
    pub occupancy_fraction: f32,
    #[arg(long, default_value_t = 16)]
    pub levels: u32,
    #[arg(long, default_value_t = 2)]
    pub features: u32,
    #[arg(long, default_value_t = 19)]
    pub log2_t: u32,
    /// Key scheme of the hidden scenes (key-sensitivity and partial-keys always run both).
    #[arg(long, value_enum, default_value_t = SchemeArg::Prf)]
    pub scheme: SchemeArg,
    /// Train the stego models with stealth (hidden scenes confined to the cover's reachable
    /// table entries; see `train --stealth`).
    #[arg(long)]
    pub stealth: bool,
    /// Use the paper's one-scene-per-step schedule instead of mixed batches.
    #[arg(long)]
    pub random_scene: bool,
    /// Resolution of generated scenes.
    #[arg(long, default_value_t = 64)]
    pub res: u32,
}

pub fn run(a: Args) -> Result<()> {
    if !EXPERIMENTS.contains(&a.name.as_str()) {
        bail!(
            "unknown experiment '{}': one of {}",
            a.name,
            EXPERIMENTS.join(", ")
        );
    }
    std::fs::create_dir_all(&a.out)?;
    let data = a.out.join("data");
    let gen_scene = |name: &str, kind: SceneKind, seed: u64| -> Result<PathBuf> {
        let dir = data.join(name);
        if !dir.join("transforms_train.json").exists() {
            let opts = SynthOptions {
                scene: kind,
                resolution: a.res,
                n_train: 60,
                n_val: 0,
                n_test: 10,
                seed,
                aabb_scale: 1,
            };
            eprintln!("generating {} ({} px)", dir.display(), a.res);
            generate(&opts, &dir)?;
        }
        Ok(dir)
    };
    let needs_scenes = a.name != "key-strength";
    let cover = match &a.cover {
        Some(c) => c.clone(),
        None if needs_scenes => gen_scene("cover_object", SceneKind::Object, 1)?,
        None => PathBuf::new(),
    };
    let mut hidden = a.hidden.clone();
    if hidden.is_empty() && needs_scenes {
        let n = if a.name == "multi-hidden" { 4 } else { 1 };
        for i in 0..n {
            let text = ["(c) StegoNGP", "SECRET 2", "HIDDEN #3", "KEY 4 ONLY"][i];
            hidden.push(gen_scene(
                &format!("hidden_text_{}", i + 1),
                SceneKind::Text(text.into()),
                10 + i as u64,
            )?);
        }
    }
    let cfg = ExpConfig {
        out: a.out.join(&a.name),
        cover,
        hidden,
        downscale: a.downscale,
        hidden_downscale: a.hidden_downscale,
        steps: a.steps,
        batch: a.batch,
        seed: a.seed,
        eval_views: a.eval_views,
        occupancy_fraction: a.occupancy_fraction,
        grid: GridConfig {
            n_levels: a.levels,
            n_features: a.features,
            log2_hashmap_size: a.log2_t,
            base_resolution: 16,
        },
        scheme: match a.scheme {
            SchemeArg::Prf => KeySchemeArg::Prf,
            SchemeArg::Primes => KeySchemeArg::Primes,
        },
        schedule: if a.random_scene {
            Schedule::RandomScene
        } else {
            Schedule::Mixed
        },
        stealth: a.stealth,
        verbose: true,
    };
    let report = run_experiment(&a.name, &cfg)?;
    for t in &report.tables {
        println!("{}", t.markdown());
    }
    for n in &report.notes {
        println!("{n}\n");
    }
    println!("report: {}", cfg.out.join("report.md").display());
    Ok(())
}
