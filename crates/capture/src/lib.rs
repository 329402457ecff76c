//! The capture pipeline `stegongp process` runs: a phone video or a folder of photos to a
//! posed capture that `train` reads with its default options, as instant-ngp's colmap2nerf
//! (`--video_in --run_colmap`) and nerfstudio's `ns-process-data` do, driving the real
//! `ffmpeg` and `colmap` programs:
//!
//! 1. frames: a video's sharpest frame in each of `--frames` equal stretches ([`video`]),
//!    or the folder's photos ([`photos`]), long side capped at `--max-size`, in `images/`;
//! 2. COLMAP's features, matching and mapper, its largest model kept as `sparse/0`
//!    ([`sfm`]), its output in `colmap.log`;
//! 3. a summary (`process.json`, and `--json`), and with `--transforms` the
//!    `transforms.json` that `convert` writes.
//!
//! Poses stay in COLMAP's frame in `sparse/0`: the loaders orient (mean camera up → +z),
//! centre (where the optical axes meet) and scale (mean camera distance 4) a COLMAP model
//! as colmap2nerf does when they read it, and `convert` writes the same numbers.
//! Everything is built in a hidden folder beside DIR and renamed at the end ([`output`]).
//!
//! This crate knows the programs it drives and the capture it writes; it must not know the
//! command line or the terminal: the program parses the options, draws the progress and
//! notes it is handed ([`Ui`]) and reports the [`Summary`]. Nor does it train.

pub mod colmap;
pub mod output;
pub mod photos;
pub mod pixels;
pub mod sfm;
pub mod tools;
pub mod video;

use anyhow::{Context, Result, bail};
use dataset::colmap2nerf::to_transforms;
use dataset::{LoadOptions, import_capture};
use ngp::data::{Split, check_aabb_scale};
use ngp::util::write_atomic;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

pub use sfm::{CameraModel, Matcher};

/// How far a long stage is (a progress bar, where the program draws one).
pub trait Progress: Sync {
    fn set_length(&self, len: u64);
    fn set_position(&self, pos: u64);
    fn inc(&self, delta: u64);
    fn finish(&self);
}

/// Shows nothing.
impl Progress for () {
    fn set_length(&self, _: u64) {}
    fn set_position(&self, _: u64) {}
    fn inc(&self, _: u64) {}
    fn finish(&self) {}
}

/// What the pipeline shows while it runs: the program draws it, the library only says it.
pub trait Ui {
    /// A stage's progress, `len` steps (0: not known yet) of `what`.
    fn bar(&self, len: u64, what: &str) -> Box<dyn Progress>;
    /// A line about the run (the images found, the COLMAP that runs).
    fn info(&self, line: &str);
    /// A warning that does not stop the run.
    fn warn(&self, line: &str);
}

/// What to process, and how (the options of `stegongp process`, whose names the messages
/// use).
#[derive(Clone, Debug)]
pub struct Options {
    /// A video or a folder of photos.
    pub input: PathBuf,
    /// The capture folder to write.
    pub out: PathBuf,
    /// Video: about this many frames.
    pub frames: usize,
    /// Longest side of the images (0 keeps them).
    pub max_size: u32,
    pub matcher: Matcher,
    pub camera_model: CameraModel,
    /// Photos: one camera a photo instead of one for all.
    pub camera_per_photo: bool,
    /// Most SIFT features an image.
    pub max_features: u32,
    /// Threads for COLMAP (default: every core).
    pub threads: Option<usize>,
    /// Let COLMAP use its GPU.
    pub colmap_gpu: bool,
    /// Refuse a result with fewer than this share of the images registered.
    pub min_registered: f64,
    /// Also write transforms.json.
    pub transforms: bool,
    /// transforms.json's aabb_scale.
    pub aabb_scale: Option<u32>,
    /// Keep COLMAP's database.db.
    pub keep_database: bool,
    /// Replace an existing output folder.
    pub force: bool,
    /// The colmap program (default: `colmap` on PATH).
    pub colmap: Option<PathBuf>,
    /// The ffmpeg program (default: `ffmpeg` on PATH).
    pub ffmpeg: Option<PathBuf>,
}

#[derive(Serialize)]
pub struct VideoInfo {
    pub codec: String,
    pub width: u32,
    pub height: u32,
    pub frames: u64,
    pub decoded: u64,
    pub seconds: Option<f64>,
    pub ffmpeg: String,
}

#[derive(Serialize)]
pub struct Seconds {
    pub frames: f64,
    pub features: f64,
    pub matching: f64,
    pub mapping: f64,
    pub total: f64,
}

impl Seconds {
    fn of(frames: f64, sfm: [f64; 3], total: f64) -> Seconds {
        Seconds {
            frames,
            features: sfm[0],
            matching: sfm[1],
            mapping: sfm[2],
            total,
        }
    }
}

#[derive(Serialize)]
pub struct Summary {
    pub input: PathBuf,
    pub kind: &'static str,
    pub out: PathBuf,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub video: Option<VideoInfo>,
    /// Images given to COLMAP.
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    pub colmap: String,
    pub matcher: Matcher,
    pub camera_model: &'static str,
    pub single_camera: bool,
    pub threads: usize,
    pub registered: usize,
    pub registered_share: f64,
    pub unregistered: Vec<String>,
    pub models: usize,
    pub points: Option<u64>,
    pub mean_track_length: Option<f64>,
    pub mean_reprojection_error_px: Option<f64>,
    pub seconds: Seconds,
    /// Processor seconds (this program and the ones it ran, every core): what each stage
    /// costs whatever else the machine runs.
    pub cpu_seconds: Seconds,
    pub transforms: Option<PathBuf>,
}

/// The images `process` hands to COLMAP.
struct Gathered {
    names: Vec<String>,
    size: (u32, u32),
    video: Option<VideoInfo>,
    seconds: f64,
    cpu_seconds: f64,
}

fn check_args(a: &Options) -> Result<()> {
    if a.frames < 3 {
        bail!(
            "--frames {}: a capture needs at least 3 (about 100–300)",
            a.frames
        );
    }
    if a.max_size != 0 && a.max_size < 64 {
        bail!(
            "--max-size {}: at least 64 pixels (0 keeps the size)",
            a.max_size
        );
    }
    if !(a.min_registered > 0.0 && a.min_registered <= 1.0) {
        bail!("--min-registered {}: a share in (0, 1]", a.min_registered);
    }
    if a.threads == Some(0) {
        bail!("--threads 0: at least 1");
    }
    if let Some(s) = a.aabb_scale {
        check_aabb_scale(s).context("--aabb-scale")?;
        if !a.transforms {
            bail!("--aabb-scale is for --transforms' transforms.json");
        }
    }
    if !a.input.exists() {
        bail!("{}: no such file or folder", a.input.display());
    }
    Ok(())
}

/// Frames of the video, or the folder's photos, into `work/images`.
fn gather(a: &Options, work: &Path, ui: &dyn Ui) -> Result<Gathered> {
    let (t0, cpu0) = (Instant::now(), tools::cpu_seconds());
    let images = work.join("images");
    std::fs::create_dir(&images).with_context(|| format!("{}: cannot create", images.display()))?;
    if a.input.is_dir() {
        let list = photos::list(&a.input)?;
        let pb = ui.bar(list.len() as u64, "photos");
        let (names, size) = photos::import(&list, a.max_size, &images, &*pb)?;
        pb.finish();
        return Ok(Gathered {
            names,
            size,
            video: None,
            seconds: t0.elapsed().as_secs_f64(),
            cpu_seconds: tools::cpu_seconds() - cpu0,
        });
    }
    let ffmpeg = tools::ffmpeg(a.ffmpeg.as_deref());
    let version_out = ffmpeg.output(["-version"])?;
    let version = tools::version_after(&String::from_utf8_lossy(&version_out.stdout), "ffmpeg")
        .unwrap_or_else(|| "unknown".into());
    let probe = video::probe(&tools::ffprobe(a.ffmpeg.as_deref()), &a.input)?;
    let pb = ui.bar(probe.frames, "frames decoded");
    let got = video::extract(
        &ffmpeg,
        tools::major_minor(&version),
        &a.input,
        &probe,
        &video::Wanted {
            frames: a.frames,
            max_side: a.max_size,
        },
        &images,
        &*pb,
    )?;
    pb.finish();
    Ok(Gathered {
        size: (got.width, got.height),
        names: got.names,
        video: Some(VideoInfo {
            codec: probe.codec,
            width: probe.width,
            height: probe.height,
            frames: probe.frames,
            decoded: got.decoded,
            seconds: probe.seconds,
            ffmpeg: version,
        }),
        seconds: t0.elapsed().as_secs_f64(),
        cpu_seconds: tools::cpu_seconds() - cpu0,
    })
}

/// Refuses a reconstruction that left too many images out, saying what to try.
fn check_registered(
    min: f64,
    registered: usize,
    frames: usize,
    video: bool,
    ui: &dyn Ui,
) -> Result<()> {
    let share = registered as f64 / frames as f64;
    if share >= min {
        if share < 0.8 {
            ui.warn(&format!(
                "warning: COLMAP registered only {registered} of {frames} images ({:.0} %); \
                 the rest are left out of training",
                100.0 * share
            ));
        }
        return Ok(());
    }
    let more = if video {
        "more frames (--frames), --matcher exhaustive, or a slower pass around the scene"
    } else {
        "--matcher exhaustive, or more photos, each sharing most of what it sees with its \
         neighbours"
    };
    bail!(
        "COLMAP registered only {registered} of {frames} images ({:.0} %, below \
         --min-registered {}): the others share too few features with them. Try {more}; \
         avoid blur, moving things and bare walls (--min-registered {:.2} would accept this \
         result)",
        100.0 * share,
        min,
        ((share * 100.0 - 1e-6).floor() / 100.0).max(0.01)
    )
}

/// The `transforms.json` `convert` writes, checked by loading it first.
fn write_transforms(work: &Path, aabb_scale: Option<u32>) -> Result<()> {
    let scene = import_capture(work, None)?;
    let aabb = aabb_scale.unwrap_or(scene.default_aabb_scale);
    let conv = to_transforms(&scene, aabb, work);
    let path = work.join("transforms.json");
    conv.transforms(&path, work)?;
    write_atomic(
        &path,
        serde_json::to_string_pretty(&conv.to_json())?.as_bytes(),
    )?;
    Ok(())
}

/// Runs the pipeline (see the crate documentation) as `o` says, drawing progress and notes
/// through `ui`, and publishes the capture folder: its summary, as written to
/// `process.json`.
pub fn process(a: &Options, ui: &dyn Ui) -> Result<Summary> {
    let (t0, cpu0) = (Instant::now(), tools::cpu_seconds());
    check_args(a)?;
    output::check(&a.out, &a.input, a.force)?;
    let mut colmap = colmap::Colmap::open(tools::colmap(a.colmap.as_deref()))?;
    let staging = output::Staging::create(&a.out)?;
    let work = staging.dir.clone();
    let got = gather(a, &work, ui)?;
    let is_video = got.video.is_some();
    let matcher = match a.matcher {
        Matcher::Auto if is_video || got.names.len() > sfm::EXHAUSTIVE_UP_TO => Matcher::Sequential,
        Matcher::Auto => Matcher::Exhaustive,
        m => m,
    };
    let threads = a
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let opts = sfm::SfmOptions {
        camera_model: a.camera_model,
        single_camera: is_video || !a.camera_per_photo,
        matcher,
        threads,
        max_features: a.max_features,
        gpu: a.colmap_gpu,
    };
    ui.info(&format!(
        "{} images of {}x{}; COLMAP {} ({}), {matcher:?} matching, {threads} thread(s), {}",
        got.names.len(),
        got.size.0,
        got.size.1,
        colmap.version,
        a.colmap.as_deref().unwrap_or(Path::new("colmap")).display(),
        if a.colmap_gpu { "its GPU" } else { "CPU" }
    ));
    let mut log = colmap::Log::create(&work.join("colmap.log"))?;
    let res = sfm::reconstruct(&mut colmap, &opts, &work, got.names.len(), &mut log, ui);
    let sfm = res?;
    log.finish()?;
    check_registered(
        a.min_registered,
        sfm.registered.len(),
        got.names.len(),
        is_video,
        ui,
    )?;
    if !a.keep_database {
        let db = work.join("database.db");
        std::fs::remove_file(&db).with_context(|| format!("{}: cannot remove", db.display()))?;
    }
    if a.transforms {
        write_transforms(&work, a.aabb_scale)?;
    }
    // What `train` will read must load now: nothing is published otherwise.
    dataset::load_cameras(&work, Split::Train, &LoadOptions::default())
        .context("the finished capture does not load")?;
    let registered: std::collections::HashSet<&str> =
        sfm.registered.iter().map(String::as_str).collect();
    let summary = Summary {
        input: a.input.clone(),
        kind: if is_video { "video" } else { "photos" },
        out: a.out.clone(),
        frames: got.names.len(),
        width: got.size.0,
        height: got.size.1,
        colmap: colmap.version.clone(),
        matcher,
        camera_model: a.camera_model.colmap_name(),
        single_camera: opts.single_camera,
        threads,
        registered: sfm.registered.len(),
        registered_share: sfm.registered.len() as f64 / got.names.len() as f64,
        unregistered: got
            .names
            .iter()
            .filter(|n| !registered.contains(n.as_str()))
            .cloned()
            .collect(),
        models: sfm.models,
        points: sfm.analysis.points,
        mean_track_length: sfm.analysis.mean_track_length,
        mean_reprojection_error_px: sfm.analysis.mean_reprojection_error_px,
        seconds: Seconds::of(
            got.seconds,
            sfm.seconds.map(|s| s.0),
            t0.elapsed().as_secs_f64(),
        ),
        cpu_seconds: Seconds::of(
            got.cpu_seconds,
            sfm.seconds.map(|s| s.1),
            tools::cpu_seconds() - cpu0,
        ),
        transforms: a.transforms.then(|| a.out.join("transforms.json")),
        video: got.video,
    };
    let text = serde_json::to_string_pretty(&summary)?;
    write_atomic(&work.join("process.json"), text.as_bytes())?;
    staging.commit(a.force)?;
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Draws nothing.
    struct Quiet;
    impl Ui for Quiet {
        fn bar(&self, _: u64, _: &str) -> Box<dyn Progress> {
            Box::new(())
        }
        fn info(&self, _: &str) {}
        fn warn(&self, _: &str) {}
    }

    #[test]
    fn too_few_registered_says_how_many_and_what_to_try() {
        check_registered(0.5, 10, 20, true, &Quiet).unwrap();
        let e = check_registered(0.5, 9, 20, true, &Quiet)
            .unwrap_err()
            .to_string();
        for needle in [
            "9 of 20",
            "45 %",
            "--frames",
            "--matcher exhaustive",
            "--min-registered 0.44",
        ] {
            assert!(e.contains(needle), "{needle}: {e}");
        }
        let e = check_registered(0.9, 3, 30, false, &Quiet)
            .unwrap_err()
            .to_string();
        assert!(e.contains("more photos") && !e.contains("--frames"), "{e}");
    }
}
