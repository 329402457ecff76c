//! `stegongp video`: a camera path rendered from a model, as the cover, as the hidden scene of
//! a key, or both beside a wrong key's, to an H.264 MP4 and/or numbered PNGs.

use super::common::{
    DeviceArg, check_parent_dir, ensure_locked_dir, frame_size, progress, transmittance,
};
use anyhow::{Result, bail};
use std::path::{Path, PathBuf};
use stegongp::dataset::LoadOptions;
use stegongp::ngp::camera::Camera;
use stegongp::ngp::data::{DatasetFormat, Split};
use stegongp::ngp::model::Model;
use stegongp::ngp::render::image::{Background, RenderOptions, VIEWING_MIN_TRANSMITTANCE};
use stegongp::stego::options::choice;
use stegongp::stego::{Key, open_scene_on};
use stegongp::viewer::frame::{Rgb8, render_frame, video_frame_size};
use stegongp::viewer::path::{
    CameraPath, DEFAULT_FPS, MAX_FRAMES, NerfFrame, PathCamera, SceneRig, model_cameras,
    model_frame_size, read_path, write_nerfstudio,
};
use stegongp::viewer::video::{Mp4Video, VideoSummary};

/// Where a scene's cameras come from, shared by `video` and `view`.
#[derive(clap::Args, Debug, Clone)]
pub struct SceneCameras {
    /// Dataset whose cameras place generated paths (centre, distance, elevation, spread), and
    /// whose frame nerfstudio path files are read and written in. Without it, the cameras
    /// the model keeps (instant-ngp stores the cover's training cameras).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// COLMAP / LLFF data: the image folder (sizes only; no pixel is read).
    #[arg(long)]
    pub images: Option<String>,
    #[arg(long, value_parser = choice::<Split>(), default_value_t = Split::Train)]
    pub split: Split,
}

/// A scene's cameras, the frame its path files use, and whether it faces forward (LLFF).
pub struct Rig {
    pub cameras: Vec<PathCamera>,
    pub frame: NerfFrame,
    pub size: Option<(u32, u32)>,
    pub forward_facing: bool,
    pub rig: SceneRig,
}

impl SceneCameras {
    pub fn open(&self, model: &Model) -> Result<Rig> {
        let (cameras, frame, size, forward_facing) = match &self.data {
            Some(dir) => {
                let (cams, meta) = stegongp::dataset::load_cameras(
                    dir,
                    self.split,
                    &LoadOptions {
                        images: self.images.clone(),
                        ..Default::default()
                    },
                )?;
                let size = cams.first().map(|c| (c.width, c.height));
                (
                    cams.iter().map(PathCamera::of).collect::<Vec<_>>(),
                    NerfFrame {
                        scale: meta.scale,
                        offset: meta.offset,
                    },
                    size,
                    meta.format == DatasetFormat::Llff,
                )
            }
            None => (
                model_cameras(model),
                NerfFrame::of_model(model),
                model_frame_size(model),
                false,
            ),
        };
        let rig = SceneRig::of(&cameras, [0.5; 3]).unwrap_or_else(SceneRig::default_object);
        Ok(Rig {
            cameras,
            frame,
            size,
            forward_facing,
            rig,
        })
    }
}

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Model file (.ingp or .msgpack).
    #[arg(long)]
    pub model: PathBuf,
    #[command(flatten)]
    pub key: super::KeyArgs,
    /// Three labelled panels: the cover (no key), the hidden scene (--key) and a wrong key's
    /// view of the same file.
    #[arg(long, requires = "key")]
    pub side_by_side: bool,
    #[command(flatten)]
    pub cameras: SceneCameras,
    /// orbit (around the scene's centre at the cameras' mean distance and elevation), sweep
    /// (back and forth over the arc the cameras cover, for a capture taken from one side),
    /// spiral (LLFF's forward-facing path), auto (spiral for LLFF data, sweep where the
    /// cameras leave a gap wider than 90°, else orbit), or a path file: nerfstudio's
    /// camera_path.json or instant-ngp's base_cam.json.
    #[arg(long, default_value = "auto")]
    pub path: String,
    /// Frames of a generated path or of an instant-ngp path's spline (default 120; a
    /// nerfstudio file lists its own frames).
    #[arg(long)]
    pub frames: Option<usize>,
    /// Frames per second (default: the path file's, else 24).
    #[arg(long)]
    pub fps: Option<u32>,
    /// Frame width in pixels (default: the path file's, else the cameras', else 400).
    #[arg(long)]
    pub width: Option<u32>,
    #[arg(long)]
    pub height: Option<u32>,
    #[arg(long, value_parser = choice::<Background>(), default_value_t = Background::White)]
    pub background: Background,
    /// A ray stops below this transmittance: 0.01 by default, as instant-ngp's videos and
    /// `render`; 1e-4, as `eval` scores views, takes ~60 % longer on a capture.
    #[arg(long, default_value_t = VIEWING_MIN_TRANSMITTANCE, value_parser = transmittance)]
    pub min_transmittance: f32,
    /// The MP4 to write (H.264, yuv420p).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Also (or instead) write the frames as frame_00000.png … into this folder.
    #[arg(long)]
    pub frames_dir: Option<PathBuf>,
    /// Write the path rendered as nerfstudio's camera_path.json.
    #[arg(long)]
    pub write_path: Option<PathBuf>,
    /// Seed of the wrong key in --side-by-side and of a key holder's grid rebuild.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Print a JSON summary.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub device: DeviceArg,
}

/// The path asked for: generated from the rig, or read from a file.
pub fn make_path(spec: &str, frames: Option<usize>, rig: &Rig) -> Result<CameraPath> {
    let n = frames.unwrap_or(120);
    if n == 0 || n > MAX_FRAMES {
        bail!("--frames {n}: not in 1..={MAX_FRAMES}");
    }
    let generated = |cams| CameraPath {
        cameras: cams,
        fps: DEFAULT_FPS,
        size: None,
    };
    Ok(match spec {
        "orbit" => generated(rig.rig.orbit(n)),
        "sweep" => generated(rig.rig.sweep(n)),
        "spiral" => generated(rig.rig.spiral(n)),
        "auto" if rig.forward_facing => generated(rig.rig.spiral(n)),
        "auto" if !rig.rig.surrounds() => generated(rig.rig.sweep(n)),
        "auto" => generated(rig.rig.orbit(n)),
        file => read_path(Path::new(file), frames, &rig.frame)?,
    })
}

pub fn run(a: Args) -> Result<()> {
    check_outputs(&a)?;
    let model = Model::load(&a.model)?;
    let rig = a.cameras.open(&model)?;
    let path = make_path(&a.path, a.frames, &rig)?;
    let (w, h) = frame_size(a.width, a.height)?
        .or(path.size)
        .or(rig.size)
        .unwrap_or((400, 400));
    let fps = match a.fps {
        Some(f) => f,
        None => path.fps.round().clamp(1.0, 240.0) as u32,
    };
    let device = a.device.open()?;
    eprintln!("device: {}", device.report());
    let keys = panel_keys(&a, &model)?;
    let labels: Vec<&str> = if a.side_by_side {
        keys.iter().map(|(_, l)| *l).collect()
    } else {
        Vec::new()
    };
    let scenes = keys
        .iter()
        .map(|(k, _)| open_scene_on(&device, &model, k.as_ref(), a.key.stealth, a.seed))
        .collect::<stegongp::Result<Vec<_>>>()?;
    let mut renderers = scenes
        .iter()
        .map(|s| s.renderer(&device, &model))
        .collect::<stegongp::Result<Vec<_>>>()?;
    let opts = RenderOptions {
        background: a.background.rgb(),
        min_transmittance: a.min_transmittance,
        ..Default::default()
    };
    let _lock = a.frames_dir.as_deref().map(ensure_locked_dir).transpose()?;
    if let Some(p) = &a.write_path {
        write_nerfstudio(p, &path, w, h, &rig.frame)?;
    }
    let render = |camera: &Camera| Ok(render_frame(&mut renderers, &labels, camera, &opts)?);
    let rendered = render_path(&a, &path.cameras, (w, h), fps, render)?;
    if a.json {
        let n = rendered.frames;
        let summary = &rendered.video;
        let report = serde_json::json!({
            "model": a.model,
            "device": device.report(),
            "frames": n,
            "width": w,
            "height": h,
            "fps": fps,
            "side_by_side": a.side_by_side,
            "video": summary,
            "frames_dir": a.frames_dir,
            "seconds": rendered.seconds,
            "render_seconds_per_frame": rendered.render_seconds / n as f64,
            "encode_seconds_per_frame": summary.as_ref().map(|s| s.encode_seconds / n as f64),
        });
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        rendered.tell(a.frames_dir.as_deref());
    }
    Ok(())
}

/// Refuses a run with nowhere to write, or a video or path file whose folder is not there,
/// before the model is read.
fn check_outputs(a: &Args) -> Result<()> {
    if a.out.is_none() && a.frames_dir.is_none() {
        bail!("say where the frames go: --out VIDEO.mp4 and/or --frames-dir DIR");
    }
    if let Some(out) = &a.out {
        if out.extension().and_then(|e| e.to_str()) != Some("mp4") {
            bail!("{}: the video file must end in .mp4", out.display());
        }
        check_parent_dir(out)?;
    }
    if let Some(p) = &a.write_path {
        check_parent_dir(p)?;
    }
    Ok(())
}

/// The keys of the panels, with their labels: the one asked for (unlabelled), or cover,
/// key and wrong key side by side.
fn panel_keys(a: &Args, model: &Model) -> Result<Vec<(Option<Key>, &'static str)>> {
    let mut keys: Vec<(Option<Key>, &str)> = Vec::new();
    let key = a.key.load(model)?;
    if a.side_by_side {
        let k = key.clone().expect("clap requires --key");
        let wrong = Key::wrong(a.seed ^ 0x5eed, &k);
        keys.push((None, "cover (no key)"));
        keys.push((Some(k), "hidden scene (key)"));
        keys.push((Some(wrong), "wrong key"));
    } else {
        keys.push((key, ""));
    }
    Ok(keys)
}

/// What rendering a path took and wrote.
struct Rendered {
    frames: usize,
    /// The MP4, when one was asked for.
    video: Option<VideoSummary>,
    /// Seconds in all, and rendering alone.
    seconds: f64,
    render_seconds: f64,
}

impl Rendered {
    /// Says on stderr what was written.
    fn tell(&self, frames_dir: Option<&Path>) {
        let n = self.frames;
        if let Some(s) = &self.video {
            eprintln!(
                "wrote {} ({} frames, {}x{}, {} fps, {:.1} MB): {:.2} s/frame rendering, {:.3} s/frame encoding",
                s.path.display(),
                s.frames,
                s.width,
                s.height,
                s.fps,
                s.bytes as f64 / 1e6,
                self.render_seconds / n as f64,
                s.encode_seconds / n as f64
            );
        }
        if let Some(dir) = frames_dir {
            eprintln!("wrote {n} frames into {}", dir.display());
        }
    }
}

/// Renders every camera of `cameras` at `w`×`h` with `render` into the video and/or the
/// frame folder that `a` names, with a progress bar.
fn render_path(
    a: &Args,
    cameras: &[PathCamera],
    (w, h): (u32, u32),
    fps: u32,
    mut render: impl FnMut(&Camera) -> Result<Rgb8>,
) -> Result<Rendered> {
    let n = cameras.len();
    let (vw, vh) = video_frame_size(if a.side_by_side { 3 } else { 1 }, w, h);
    let mut video = match &a.out {
        Some(out) => Some(Mp4Video::create(out, vw, vh, fps)?),
        None => None,
    };
    let pb = progress(
        n as u64,
        "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} frames {msg}",
    );
    let t0 = std::time::Instant::now();
    let mut render_seconds = 0.0;
    for (i, pc) in cameras.iter().enumerate() {
        let camera = pc.camera(w, h);
        let tr = std::time::Instant::now();
        let frame = render(&camera)?;
        render_seconds += tr.elapsed().as_secs_f64();
        if let Some(dir) = &a.frames_dir {
            let p = dir.join(format!("frame_{i:05}.png"));
            stegongp::util::write_atomic(&p, &frame.png())?;
        }
        if let Some(v) = video.as_mut() {
            v.push(&frame.even())?;
        }
        pb.inc(1);
        pb.set_message(format!(
            "{:.2} s/frame",
            t0.elapsed().as_secs_f64() / (i + 1) as f64
        ));
    }
    pb.finish_and_clear();
    let video = match video {
        Some(v) => Some(v.finish()?),
        None => None,
    };
    Ok(Rendered {
        frames: n,
        video,
        seconds: t0.elapsed().as_secs_f64(),
        render_seconds,
    })
}
