use anyhow::{Result, bail};
use std::path::PathBuf;
use stegongp::dataset::LoadOptions;
use stegongp::synth::cameras_from::generate_from_cameras;
use stegongp::synth::{RoomOptions, SceneKind, SynthOptions, generate};

#[derive(clap::Args, Debug)]
pub struct Args {
    #[arg(long, value_enum)]
    pub scene: SceneKind,
    /// The message of a text scene.
    #[arg(long, default_value = "(c) StegoNGP 2026")]
    pub text: String,
    /// Output directory (must be empty or absent unless --force).
    #[arg(long)]
    pub out: PathBuf,
    /// Width and height of every view [default: 200].
    #[arg(long)]
    pub res: Option<u32>,
    /// Train views [default: 100].
    #[arg(long)]
    pub train: Option<usize>,
    /// Test views [default: 25].
    #[arg(long)]
    pub test: Option<usize>,
    /// Val views [default: 0].
    #[arg(long)]
    pub val: Option<usize>,
    /// Seed of the cameras, and of the logo.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// `aabb_scale` written into the transforms (a room's walls are placed inside its box)
    /// [default: 1]; with --cameras-from, overrides the source's as `train --aabb-scale` would.
    #[arg(long)]
    pub aabb_scale: Option<u32>,
    /// Render the scene from exactly the cameras of this dataset (any format `train` reads;
    /// its splits, intrinsics, image sizes and poses), placed at the box centre where they
    /// look. Counts and sizes come from DIR: --res, --train, --val, --test are refused.
    #[arg(long, value_name = "DIR")]
    pub cameras_from: Option<PathBuf>,
    /// With --cameras-from: read DIR's cameras at this downscale (the views are rendered at
    /// DIR's image size divided by it).
    #[arg(long)]
    pub downscale: Option<u32>,
    /// With --cameras-from: the COLMAP / LLFF image folder whose size the cameras take
    /// (e.g. images_8), as `train --images`.
    #[arg(long)]
    pub images: Option<String>,
    /// Room scene: the height of every view (default: --res, square views), e.g. --res 400
    /// --height 266 for a phone photo's 3:2.
    #[arg(long)]
    pub height: Option<u32>,
    /// Room scene: the horizontal field of view in degrees (default: lego's 39.6; a phone's
    /// main camera is about 65).
    #[arg(long, value_name = "DEGREES")]
    pub fov: Option<f32>,
    /// Room scene: a furnished room, like an indoor 360° capture (brick walls about three
    /// times the cameras' distance away, a plank floor under a pedestal, furniture drawn
    /// from --seed; every surface with detail a few pixels across) instead of the bare one.
    #[arg(long)]
    pub furnished: bool,
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
    let scene = a.scene.clone().with_text(&a.text);
    if scene != SceneKind::Room && (a.height.is_some() || a.fov.is_some() || a.furnished) {
        bail!(
            "--height, --fov and --furnished are the room scene's (--scene room); the other \
             scenes are seen by lego's square cameras"
        );
    }
    let s = if let Some(from) = &a.cameras_from {
        let given: Vec<&str> = [
            ("--res", a.res.is_some()),
            ("--train", a.train.is_some()),
            ("--val", a.val.is_some()),
            ("--test", a.test.is_some()),
        ]
        .into_iter()
        .filter_map(|(n, g)| g.then_some(n))
        .collect();
        if !given.is_empty() {
            bail!(
                "{} cannot be used with --cameras-from: the views, their count and size are \
                 those of {} (use --downscale N for smaller views)",
                given.join(", "),
                from.display()
            );
        }
        if scene == SceneKind::Room {
            bail!(
                "--scene room cannot be used with --cameras-from: the room places its own \
                 cameras inside its walls (use object, text or logo)"
            );
        }
        let load = LoadOptions {
            downscale: a.downscale.unwrap_or(1),
            images: a.images.clone(),
            aabb_scale: a.aabb_scale,
        };
        generate_from_cameras(&scene, a.seed, from, &load, &a.out)?
    } else {
        if a.downscale.is_some() || a.images.is_some() {
            bail!("--downscale and --images only apply with --cameras-from DIR");
        }
        let opts = SynthOptions {
            scene,
            resolution: a.res.unwrap_or(200),
            n_train: a.train.unwrap_or(100),
            n_val: a.val.unwrap_or(0),
            n_test: a.test.unwrap_or(25),
            seed: a.seed,
            aabb_scale: a.aabb_scale.unwrap_or(1),
            room: RoomOptions {
                height: a.height,
                fov_x_degrees: a.fov,
                furnished: a.furnished,
            },
        };
        generate(&opts, &a.out)?
    };
    if a.json {
        println!("{}", serde_json::to_string_pretty(&s)?);
    } else {
        let size = match &s.cameras_from {
            Some(c) => format!(
                "{}×{} from the cameras of {} ({}; {} of {} views see the box centre)",
                c.width,
                c.height,
                c.source.display(),
                c.format,
                c.views_seeing_centre,
                c.views
            ),
            None => format!("{}×{}", s.resolution, s.height),
        };
        eprintln!(
            "{}: {} scene, {} train + {} val + {} test views at {size} in {:.1} s",
            a.out.display(),
            s.scene,
            s.n_train,
            s.n_val,
            s.n_test,
            s.seconds
        );
    }
    Ok(())
}
