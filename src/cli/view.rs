//! `stegongp view MODEL`: the local web viewer. Frames are rendered here, on the chosen
//! device, so the page works over an SSH tunnel to a headless GPU machine.

use super::common::{DeviceArg, check_parent_dir, frame_size, transmittance};
use super::video::SceneCameras;
use anyhow::{Result, bail};
use std::io::Write;
use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::path::PathBuf;
use stegongp::ngp::model::Model;
use stegongp::ngp::render::image::{Background, VIEWING_MIN_TRANSMITTANCE};
use stegongp::stego::options::choice;
use stegongp::viewer::server::{Viewer, ViewerOptions, ViewerRig};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Model file (.ingp or .msgpack).
    pub model: PathBuf,
    #[command(flatten)]
    pub cameras: SceneCameras,
    /// Address to listen on. Anything but loopback lets other machines reach the viewer
    /// (the token still guards it); over SSH, forward a port instead.
    #[arg(long, default_value_t = IpAddr::V4(Ipv4Addr::LOCALHOST))]
    pub address: IpAddr,
    /// Port (0: any free one).
    #[arg(long, default_value_t = 7007)]
    pub port: u16,
    /// Host names the page may be reached by besides the address (e.g. a machine's DNS name
    /// when --address is not loopback).
    #[arg(long)]
    pub allow_host: Vec<String>,
    /// Full frame size (default: the cameras' aspect, 400 to 800 pixels on the longer side
    /// (their own size where it falls in that range), else 400×400).
    #[arg(long)]
    pub width: Option<u32>,
    #[arg(long)]
    pub height: Option<u32>,
    /// Interactive frames (while the camera moves) are at most this fraction of the full
    /// size on a side.
    #[arg(long, default_value_t = 0.25)]
    pub interactive_scale: f32,
    /// The render time interactive frames aim at, in seconds: their size adapts after each
    /// one (down to 1/16 of the full size on a side, up to --interactive-scale), so the view
    /// follows the mouse on a slow device. 0: always --interactive-scale.
    #[arg(long, default_value_t = 0.25)]
    pub frame_seconds: f32,
    #[arg(long, value_parser = choice::<Background>(), default_value_t = Background::White)]
    pub background: Background,
    /// Transmittance a full frame's rays stop at: 0.01, as instant-ngp's own viewer and
    /// `render` (1e-4, as `eval` scores views, takes ~60 % longer on a capture for a change
    /// the eye hardly sees). Interactive frames stop at 0.01 at least.
    #[arg(long, default_value_t = VIEWING_MIN_TRANSMITTANCE, value_parser = transmittance)]
    pub min_transmittance: f32,
    /// The camera path file the page's record button appends to (nerfstudio's format; an
    /// existing one is continued).
    #[arg(long, default_value = "camera_path.json")]
    pub record: PathBuf,
    /// Seed of a key holder's grid rebuild.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[command(flatten)]
    pub device: DeviceArg,
}

pub fn run(a: Args) -> Result<()> {
    if !(a.interactive_scale > 0.0 && a.interactive_scale <= 1.0) {
        bail!("--interactive-scale {}: not in (0, 1]", a.interactive_scale);
    }
    if !(a.frame_seconds.is_finite() && (0.0..=60.0).contains(&a.frame_seconds)) {
        bail!("--frame-seconds {}: not in [0, 60]", a.frame_seconds);
    }
    check_parent_dir(&a.record)?;
    let model = Model::load(&a.model)?;
    let rig = a.cameras.open(&model)?;
    let (width, height) = match frame_size(a.width, a.height)? {
        Some(size) => size,
        None => match rig.size {
            Some((w, h)) => {
                // Big enough to look at, small enough to render in about a second on a CPU.
                let s = (800.0 / w.max(h) as f32)
                    .min(1.0)
                    .max(400.0 / w.max(h) as f32);
                (
                    ((w as f32 * s).round() as u32).max(1),
                    ((h as f32 * s).round() as u32).max(1),
                )
            }
            None => (400, 400),
        },
    };
    let device = a.device.open()?;
    let mut viewer = Viewer::bind(SocketAddr::new(a.address, a.port))?;
    for h in &a.allow_host {
        viewer.allow_host(&format!("{h}:{}", viewer.port()));
    }
    if !a.address.is_loopback() {
        eprintln!(
            "warning: listening on {} — other machines can reach this viewer; anyone with the URL's token can drive it and see what it renders",
            a.address
        );
    }
    eprintln!("device: {}", device.report());
    eprintln!("model: {} ({}x{} frames)", a.model.display(), width, height);
    // The URL on stdout, alone on its line, so scripts (and the tests) can read it.
    println!("open {}", viewer.url());
    std::io::stdout().flush()?;
    let rig = ViewerRig {
        cameras: rig.cameras,
        rig: rig.rig,
        frame: rig.frame,
    };
    let opts = ViewerOptions {
        width,
        height,
        interactive_scale: a.interactive_scale,
        frame_seconds: a.frame_seconds,
        background: a.background.rgb(),
        min_transmittance: a.min_transmittance,
        record: a.record.clone(),
        seed: a.seed,
    };
    viewer.serve(&device, &model, &rig, &opts, |line| eprintln!("{line}"))?;
    Ok(())
}
