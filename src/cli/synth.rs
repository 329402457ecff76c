use anyhow::{Result, bail};
use std::path::PathBuf;
use stegongp::synth::{SceneKind, SynthOptions, generate};

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum SceneArg {
    /// Textured primitives on a checkered platform.
    Object,
    /// Extruded 3D text (the natural hidden message).
    Text,
    /// The object inside a room, cameras inside the room: a capture-like unbounded scene in
    /// the instant-ngp format (needs --aabb-scale ≥ 2).
    Room,
}

#[derive(clap::Args, Debug)]
pub struct Args {
    #[arg(long, value_enum)]
    pub scene: SceneArg,
    /// The message of a text scene.
    #[arg(long, default_value = "(c) StegoNGP 2026")]
    pub text: String,
    /// Output directory (must be empty or absent unless --force).
    #[arg(long)]
    pub out: PathBuf,
    /// Width and height of every view.
    #[arg(long, default_value_t = 200)]
    pub res: u32,
    #[arg(long, default_value_t = 100)]
    pub train: usize,
    #[arg(long, default_value_t = 25)]
    pub test: usize,
    #[arg(long, default_value_t = 0)]
    pub val: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// `aabb_scale` written into the transforms (a room's walls are placed inside its box).
    #[arg(long, default_value_t = 1)]
    pub aabb_scale: u32,
    /// Write into a non-empty directory.
    #[arg(long)]
    pub force: bool,
    /// Print a JSON summary.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: Args) -> Result<()> {
    if a.out.is_dir() && !a.force && std::fs::read_dir(&a.out)?.next().is_some() {
        bail!(
            "{}: directory is not empty (use --force to write into it)",
            a.out.display()
        );
    }
    let opts = SynthOptions {
        scene: match a.scene {
            SceneArg::Object => SceneKind::Object,
            SceneArg::Text => SceneKind::Text(a.text.clone()),
            SceneArg::Room => SceneKind::Room,
        },
        resolution: a.res,
        n_train: a.train,
        n_val: a.val,
        n_test: a.test,
        seed: a.seed,
        aabb_scale: a.aabb_scale,
    };
    let s = generate(&opts, &a.out)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&s)?);
    } else {
        eprintln!(
            "{}: {} scene, {} train + {} val + {} test views at {}×{} in {:.1} s",
            a.out.display(),
            s.scene,
            s.n_train,
            s.n_val,
            s.n_test,
            s.resolution,
            s.resolution,
            s.seconds
        );
    }
    Ok(())
}
