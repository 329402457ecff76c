//! `stegongp process INPUT --out DIR`: a phone video or a folder of photos to a posed
//! capture that `train` reads with its default options. The pipeline (ffmpeg's frames or
//! the photos, COLMAP, the published folder) is the `stegongp-capture` crate; this is its
//! front end: the options, the progress bars and notes on standard error, and the report.

use anyhow::Result;
use indicatif::ProgressBar;
use std::path::PathBuf;
use stegongp::capture::{Options, Progress, Summary, Ui, process};

pub use stegongp::capture::{CameraModel, Matcher};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// A video (whatever the installed ffmpeg decodes: a phone's MP4 or MOV, H.264 or
    /// HEVC) or a folder of photos (JPEG, PNG; subfolders are not read).
    pub input: PathBuf,
    /// The capture folder to write: images/, sparse/0, colmap.log, process.json.
    #[arg(long)]
    pub out: PathBuf,
    /// Video: about this many frames, the sharpest of each equal stretch of the clip.
    #[arg(long, default_value_t = 150)]
    pub frames: usize,
    /// Longest side of the images, in pixels (larger ones are shrunk; 0 keeps them).
    #[arg(long, default_value_t = 960)]
    pub max_size: u32,
    #[arg(long, value_enum, default_value_t = Matcher::Auto)]
    pub matcher: Matcher,
    /// COLMAP's camera model (one for the whole capture).
    #[arg(long, value_enum, default_value_t = CameraModel::Opencv)]
    pub camera_model: CameraModel,
    /// Photos: COLMAP fits each photo's own intrinsics (several cameras, or zoom) instead
    /// of one camera for all.
    #[arg(long)]
    pub camera_per_photo: bool,
    /// Most SIFT features an image (COLMAP's default 8192).
    #[arg(long, default_value_t = 8192)]
    pub max_features: u32,
    /// Threads for COLMAP (default: every core).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Let COLMAP use its GPU (a COLMAP built with CUDA); off, it runs on the CPU headless.
    #[arg(long)]
    pub colmap_gpu: bool,
    /// Refuse a result with fewer than this share of the images registered.
    #[arg(long, default_value_t = 0.5)]
    pub min_registered: f64,
    /// Also write the capture as instant-ngp's transforms.json (what `convert` writes);
    /// `train` then reads it instead of sparse/0, with the same poses.
    #[arg(long)]
    pub transforms: bool,
    /// With --transforms: its aabb_scale (default 16, as the loaders use for COLMAP).
    #[arg(long)]
    pub aabb_scale: Option<u32>,
    /// Keep COLMAP's database.db (features and matches, to rerun a stage by hand).
    #[arg(long)]
    pub keep_database: bool,
    /// Replace an existing output folder.
    #[arg(long)]
    pub force: bool,
    /// The colmap program (default: `colmap` on PATH).
    #[arg(long, value_name = "PATH")]
    pub colmap: Option<PathBuf>,
    /// The ffmpeg program (default: `ffmpeg` on PATH; ffprobe is looked for beside it).
    #[arg(long, value_name = "PATH")]
    pub ffmpeg: Option<PathBuf>,
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
}

/// A stage's progress bar on standard error (hidden when that is not a terminal).
struct Bar(ProgressBar);

impl Progress for Bar {
    fn set_length(&self, len: u64) {
        self.0.set_length(len);
    }
    fn set_position(&self, pos: u64) {
        self.0.set_position(pos);
    }
    fn inc(&self, delta: u64) {
        self.0.inc(delta);
    }
    fn finish(&self) {
        self.0.finish();
    }
}

/// Bars and notes on standard error; with `--json` the notes that are not warnings are
/// left out.
struct Terminal {
    json: bool,
}

impl Ui for Terminal {
    fn bar(&self, len: u64, what: &str) -> Box<dyn Progress> {
        Box::new(Bar(super::common::progress(
            len,
            &format!("{{spinner}} [{{elapsed_precise}}] {{bar:30}} {{pos}}/{{len}} {what}"),
        )))
    }
    fn info(&self, line: &str) {
        if !self.json {
            eprintln!("{line}");
        }
    }
    fn warn(&self, line: &str) {
        eprintln!("{line}");
    }
}

pub fn run(a: Args) -> Result<()> {
    let o = Options {
        input: a.input,
        out: a.out,
        frames: a.frames,
        max_size: a.max_size,
        matcher: a.matcher,
        camera_model: a.camera_model,
        camera_per_photo: a.camera_per_photo,
        max_features: a.max_features,
        threads: a.threads,
        colmap_gpu: a.colmap_gpu,
        min_registered: a.min_registered,
        transforms: a.transforms,
        aabb_scale: a.aabb_scale,
        keep_database: a.keep_database,
        force: a.force,
        colmap: a.colmap,
        ffmpeg: a.ffmpeg,
    };
    let summary = process(&o, &Terminal { json: a.json })?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        print_summary(&summary);
    }
    Ok(())
}

fn print_summary(s: &Summary) {
    let opt = |v: Option<f64>, unit: &str| v.map_or("?".into(), |v| format!("{v:.2}{unit}"));
    println!(
        "COLMAP {}: {} of {} images registered ({:.0} %), {} points, mean reprojection error {}{}",
        s.colmap,
        s.registered,
        s.frames,
        100.0 * s.registered_share,
        s.points.map_or("?".into(), |p| p.to_string()),
        opt(s.mean_reprojection_error_px, " px"),
        if s.models > 1 {
            format!(" (the largest of {} models)", s.models)
        } else {
            String::new()
        }
    );
    for (what, t) in [
        ("seconds", &s.seconds),
        ("processor seconds", &s.cpu_seconds),
    ] {
        println!(
            "{what}: {} {:.1}, features {:.1}, matching {:.1}, mapping {:.1}; {:.1} in all",
            if s.kind == "video" {
                "frames"
            } else {
                "photos"
            },
            t.frames,
            t.features,
            t.matching,
            t.mapping,
            t.total
        );
    }
    println!(
        "wrote {} (images/, sparse/0, colmap.log, process.json{}); next: stegongp train {} --out model.ingp",
        s.out.display(),
        if s.transforms.is_some() {
            ", transforms.json"
        } else {
            ""
        },
        s.out.display()
    );
}
