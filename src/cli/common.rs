//! Pieces shared by the subcommands.

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::{Path, PathBuf};
use stegongp::backend::{Device, DeviceRequest};
use stegongp::dataset::LoadOptions;
use stegongp::ngp::data::{Dataset, Split};
use stegongp::ngp::model::Model;
use stegongp::ngp::render::image::{Background, RenderOptions};
use stegongp::score::eval::spread_views;
use stegongp::stego::OpenedScene;
use stegongp::stego::options::choice;
use stegongp::util::FolderLock;

/// A transmittance in [0, 1) (`--min-transmittance`).
pub fn transmittance(s: &str) -> std::result::Result<f32, String> {
    let t: f32 = s.parse().map_err(|e| format!("{e}"))?;
    if (0.0..1.0).contains(&t) {
        Ok(t)
    } else {
        Err(format!("{t} is not in [0, 1)"))
    }
}

/// What `render` and `eval` both take: a model, seen through an optional key, and the
/// cameras of a dataset's split.
#[derive(clap::Args, Debug)]
pub struct ViewArgs {
    /// Model file (.ingp or .msgpack).
    #[arg(long)]
    pub model: PathBuf,
    /// Dataset whose cameras (and, for eval, images) to use.
    #[arg(long)]
    pub data: PathBuf,
    #[arg(long, value_parser = choice::<Split>(), default_value_t = Split::Test)]
    pub split: Split,
    #[arg(long, default_value_t = 1)]
    pub downscale: u32,
    /// COLMAP / LLFF data: the image folder to read (e.g. images_4).
    #[arg(long)]
    pub images: Option<String>,
    /// At most this many views, spread over the split (0 = all).
    #[arg(long, default_value_t = 0)]
    pub views: usize,
    /// The background views are rendered and scored on (default white; `eval --protocol
    /// instant-ngp` scores on black and refuses white).
    #[arg(long, value_parser = choice::<Background>())]
    pub background: Option<Background>,
    /// A ray stops below this transmittance. Default: as instant-ngp, 1e-4 for `eval` (what
    /// its run.py scores test views with) and 0.01 for `render` (its default for everything
    /// else: screenshots, videos, its viewer), ~40 % faster on a capture for ~0.1 dB.
    #[arg(long, value_parser = transmittance)]
    pub min_transmittance: Option<f32>,
    #[command(flatten)]
    pub key: super::KeyArgs,
    /// Render through an occupancy grid rebuilt from the network, as a key holder's is,
    /// instead of the grid stored in the model: scores a plain model on the terms its hidden
    /// scenes are scored on (a hidden scene's grid is never stored). With --key the grid is
    /// rebuilt anyway.
    #[arg(long)]
    pub rebuild_grid: bool,
    #[command(flatten)]
    pub device: DeviceArg,
}

/// `--device`, as every subcommand that trains or renders takes it.
#[derive(clap::Args, Debug)]
pub struct DeviceArg {
    /// Where to run: auto (a hardware GPU when there is one, else the CPU), cpu, or gpu (any
    /// GPU, Mesa's software llvmpipe included). The device that ran is printed, and in
    /// `--json` output.
    #[arg(long = "device", value_name = "DEVICE", value_enum, default_value_t = DeviceRequest::Auto)]
    pub request: DeviceRequest,
}

impl DeviceArg {
    pub fn open(&self) -> Result<Device> {
        Ok(Device::open(self.request)?)
    }
}

/// A model opened for viewing on a dataset's cameras.
pub struct Viewing {
    pub device: Device,
    pub model: Model,
    pub data: Dataset,
    pub scene: OpenedScene,
    pub opts: RenderOptions,
    /// The views to render.
    pub which: Vec<usize>,
}

impl ViewArgs {
    /// Opens the model and the cameras; rays stop at `--min-transmittance`, else at
    /// `default_min_transmittance` (the subcommand's).
    pub fn open(&self, default_min_transmittance: f32) -> Result<Viewing> {
        if self.downscale == 0 {
            bail!("--downscale must be at least 1");
        }
        let model = Model::load(&self.model)?;
        let data = stegongp::dataset::load(
            &self.data,
            self.split,
            &LoadOptions {
                downscale: self.downscale,
                images: self.images.clone(),
                ..Default::default()
            },
        )?;
        let device = self.device.open()?;
        let mut scene = self.key.scene(&device, &model)?;
        if self.rebuild_grid {
            scene = scene.with_rebuilt_grid(&device, &model, 0)?;
        }
        let which = spread_views(data.frames.len(), self.views);
        Ok(Viewing {
            device,
            model,
            data,
            scene,
            opts: RenderOptions {
                background: self.background.unwrap_or_default().rgb(),
                min_transmittance: self.min_transmittance.unwrap_or(default_min_transmittance),
                ..Default::default()
            },
            which,
        })
    }
}

/// Fails before any work when a model can't be written to `path`.
pub fn check_model_path(path: &Path) -> Result<()> {
    match path.extension().and_then(|e| e.to_str()) {
        Some("ingp") | Some("msgpack") => {}
        _ => bail!(
            "{}: a model file must end in .ingp (gzip-compressed snapshot) or .msgpack",
            path.display()
        ),
    }
    check_parent_dir(path)?;
    Ok(())
}

pub fn ensure_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir)
        .with_context(|| format!("{}: cannot create directory", dir.display()))
}

/// Creates `dir` and locks it until the returned lock is dropped: a command that writes many
/// files into one folder over a long time refuses a second run into the same folder at once,
/// instead of the two interleaving (and overwriting) each other's files.
pub fn ensure_locked_dir(dir: &Path) -> Result<FolderLock> {
    ensure_dir(dir)?;
    Ok(FolderLock::acquire(dir)?)
}

pub fn progress(len: u64, template: &str) -> ProgressBar {
    let pb = ProgressBar::new(len);
    pb.set_style(
        ProgressStyle::with_template(template)
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    pb
}

/// An output file's folder must exist ([`stegongp::util::check_parent_dir`]).
pub fn check_parent_dir(path: &Path) -> Result<()> {
    Ok(stegongp::util::check_parent_dir(path)?)
}

/// `--width` and `--height`: both or neither, each 1..=`MAX_SIDE` pixels.
pub fn frame_size(width: Option<u32>, height: Option<u32>) -> Result<Option<(u32, u32)>> {
    use stegongp::viewer::path::MAX_SIDE;
    let side = |v: u32, name: &str| {
        if (1..=MAX_SIDE).contains(&v) {
            Ok(v)
        } else {
            Err(anyhow::anyhow!("{name} {v}: not in 1..={MAX_SIDE}"))
        }
    };
    match (width, height) {
        (Some(w), Some(h)) => Ok(Some((side(w, "--width")?, side(h, "--height")?))),
        (None, None) => Ok(None),
        _ => bail!("give --width and --height together"),
    }
}
