//! The COLMAP stages on `images/`: features, matching, mapping, then the largest model kept
//! as `sparse/0`. Options are those of a CPU: SIFT without affine shapes or domain-size
//! pooling (neither has a fast path; colmap2nerf turns both on for a GPU), every core, no
//! GPU unless asked, and the mapper's global bundle adjustment stopped at a relative
//! tolerance of 1e-6 as nerfstudio does (COLMAP's default, 0, runs it to its iteration cap).

use crate::Ui;
use crate::colmap::{
    Analysis, Colmap, Log, extraction_progress, mapping_progress, matching_progress,
};
use anyhow::{Context, Result};
use dataset::colmap::read_model;
use std::ffi::OsString;
use std::path::{Path, PathBuf};

/// How COLMAP matches features between images.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Matcher {
    /// A video's frames with `sequential` (each with its next 10, and 2, 4, 8… ahead),
    /// photos with `exhaustive` up to 200 of them, else `sequential` (in name order).
    Auto,
    /// Each image with the ones after it in name order: linear cost, for a video.
    Sequential,
    /// Every pair: quadratic cost, for photos taken in no particular order.
    Exhaustive,
}

/// Photos up to this many are matched exhaustively by `--matcher auto`.
pub const EXHAUSTIVE_UP_TO: usize = 200;

/// The camera models the loaders read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum CameraModel {
    /// fx, fy, cx, cy and k1, k2, p1, p2 (colmap2nerf's and nerfstudio's default).
    Opencv,
    /// fx, fy, cx, cy, no distortion.
    Pinhole,
    /// One focal length, cx, cy, k1.
    SimpleRadial,
}

impl CameraModel {
    pub fn colmap_name(self) -> &'static str {
        match self {
            CameraModel::Opencv => "OPENCV",
            CameraModel::Pinhole => "PINHOLE",
            CameraModel::SimpleRadial => "SIMPLE_RADIAL",
        }
    }
}

pub struct SfmOptions {
    pub camera_model: CameraModel,
    pub single_camera: bool,
    pub matcher: Matcher,
    pub threads: usize,
    pub max_features: u32,
    pub gpu: bool,
}

/// What the stages made.
pub struct Sfm {
    /// Models the mapper made (the largest is kept).
    pub models: usize,
    /// Names of the registered images.
    pub registered: Vec<String>,
    pub analysis: Analysis,
    /// Wall and processor seconds of features, matching and mapping.
    pub seconds: [(f64, f64); 3],
}

/// Appends `--NAME value` for the first of `names` that `cmd` takes; a COLMAP that takes
/// none of them keeps its default, and the log says so.
fn opt(
    args: &mut Vec<OsString>,
    colmap: &mut Colmap,
    log: &mut Log,
    cmd: &str,
    names: &[&str],
    value: impl ToString,
) -> Result<()> {
    match colmap.pick(cmd, names)? {
        Some(n) => {
            args.push(format!("--{n}").into());
            args.push(value.to_string().into());
        }
        None => log.note(&format!(
            "COLMAP {} {cmd} takes none of {names:?}: left at its default",
            colmap.version
        ))?,
    }
    Ok(())
}

fn paths(args: &mut Vec<OsString>, pairs: &[(&str, &Path)]) {
    for (k, p) in pairs {
        args.push(format!("--{k}").into());
        args.push(p.as_os_str().into());
    }
}

/// Runs the three stages in `work` (which holds `images/`), `n` images.
pub fn reconstruct(
    colmap: &mut Colmap,
    o: &SfmOptions,
    work: &Path,
    n: usize,
    log: &mut Log,
    ui: &dyn Ui,
) -> Result<Sfm> {
    let (db, images, sparse) = (
        work.join("database.db"),
        work.join("images"),
        work.join("sparse"),
    );
    let cmd = "feature_extractor";
    let mut a = Vec::new();
    paths(&mut a, &[("database_path", &db), ("image_path", &images)]);
    for (k, v) in [
        ("ImageReader.camera_model", o.camera_model.colmap_name()),
        (
            "ImageReader.single_camera",
            if o.single_camera { "1" } else { "0" },
        ),
    ] {
        a.push(format!("--{k}").into());
        a.push(v.into());
    }
    let ext = |s: &str| {
        [
            format!("FeatureExtraction.{s}"),
            format!("SiftExtraction.{s}"),
        ]
    };
    for (names, v) in [
        (ext("use_gpu"), (o.gpu as u32).to_string()),
        (ext("num_threads"), o.threads.to_string()),
        (ext("max_num_features"), o.max_features.to_string()),
    ] {
        let names: Vec<&str> = names.iter().map(String::as_str).collect();
        opt(&mut a, colmap, log, cmd, &names, v)?;
    }
    let pb = ui.bar(n as u64, "images: features");
    let features = colmap.run(cmd, &a, log, &*pb, extraction_progress)?;
    pb.finish();

    let cmd = match o.matcher {
        Matcher::Exhaustive => "exhaustive_matcher",
        _ => "sequential_matcher",
    };
    let mut a = Vec::new();
    paths(&mut a, &[("database_path", &db)]);
    let mat = |s: &str| [format!("FeatureMatching.{s}"), format!("SiftMatching.{s}")];
    for (names, v) in [
        (mat("use_gpu"), (o.gpu as u32).to_string()),
        (mat("num_threads"), o.threads.to_string()),
    ] {
        let names: Vec<&str> = names.iter().map(String::as_str).collect();
        opt(&mut a, colmap, log, cmd, &names, v)?;
    }
    let pb = ui.bar(0, "matched");
    let matching = colmap.run(cmd, &a, log, &*pb, matching_progress)?;
    pb.finish();

    let cmd = "mapper";
    std::fs::create_dir(&sparse).with_context(|| format!("{}: cannot create", sparse.display()))?;
    let mut a = Vec::new();
    paths(
        &mut a,
        &[
            ("database_path", &db),
            ("image_path", &images),
            ("output_path", &sparse),
        ],
    );
    opt(&mut a, colmap, log, cmd, &["Mapper.num_threads"], o.threads)?;
    opt(
        &mut a,
        colmap,
        log,
        cmd,
        &["Mapper.ba_global_function_tolerance"],
        "1e-6",
    )?;
    let pb = ui.bar(n as u64, "images registered");
    let mapping = colmap.run(cmd, &a, log, &*pb, mapping_progress);
    pb.finish();
    // COLMAP's mapper exits with an error when no pair of images starts a model: that is
    // "nothing registered", not a crash.
    let mapping = match mapping {
        Err(_) if log.no_model => {
            return Err(none_registered(n, log));
        }
        r => r?,
    };

    let (model, models, registered) = keep_largest(&sparse, n, log)?;
    let analysis = colmap.analyze(&model, log)?;
    Ok(Sfm {
        models,
        registered,
        analysis,
        seconds: [features, matching, mapping],
    })
}

fn none_registered(n: usize, log: &Log) -> anyhow::Error {
    anyhow::anyhow!(
        "COLMAP registered none of the {n} images: no two of them share enough features to \
         start a model. Try more frames (--frames), --matcher exhaustive, or a capture with \
         more overlap between neighbouring views, more texture and less blur; the last lines \
         of its log:\n{}",
        log.tail()
    )
}

/// Keeps the mapper's largest model as `sparse/0` and removes the others.
fn keep_largest(sparse: &Path, n: usize, log: &mut Log) -> Result<(PathBuf, usize, Vec<String>)> {
    let mut models = Vec::new();
    for e in
        std::fs::read_dir(sparse).with_context(|| format!("{}: cannot list", sparse.display()))?
    {
        let p = e
            .with_context(|| format!("{}: cannot list", sparse.display()))?
            .path();
        let numbered = p
            .file_name()
            .and_then(|s| s.to_str())
            .is_some_and(|s| s.parse::<u32>().is_ok());
        if numbered && p.is_dir() {
            let names: Vec<String> = read_model(&p)?.images.into_iter().map(|i| i.name).collect();
            models.push((names, p));
        }
    }
    models.sort_by_key(|(names, p)| (std::cmp::Reverse(names.len()), p.clone()));
    let Some((names, best)) = models.first().cloned() else {
        return Err(none_registered(n, log));
    };
    let count = models.len();
    for (other, p) in &models[1..] {
        log.note(&format!(
            "a smaller model of {} images ({}) is dropped: the largest has {}",
            other.len(),
            p.display(),
            names.len()
        ))?;
        std::fs::remove_dir_all(p).with_context(|| format!("{}: cannot remove", p.display()))?;
    }
    let zero = sparse.join("0");
    if best != zero {
        std::fs::rename(&best, &zero)
            .with_context(|| format!("{}: cannot rename to {}", best.display(), zero.display()))?;
    }
    Ok((zero, count, names))
}
