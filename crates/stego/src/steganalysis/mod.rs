//! Steganalysis: what an analyst can measure in one model file, without the images, the key
//! or a plain model of the same cover to compare with, and a detector built on it.
//!
//! A hidden scene leaves traces because it trains the one shared set of weights through an
//! index the cover does not use. Each statistic below says what it measures and why a hidden
//! scene could move it.
//!
//! **Hash table, per level** ([`LevelStats`]). An entry's *magnitude* is the largest
//! |feature| among its F features (max-abs, not L2: it is the same norm as the
//! at-initialisation test, so "at init" is exactly "magnitude ≤ [`INIT_BOUND`]", and it does
//! not grow with F). Quantiles are nearest-rank.
//! - `init_frac`: the fraction of entries still at their ±1e-4 initialisation
//!   ([`INIT_BOUND`] explains the bound). The optimizer skips entries whose gradient is
//!   exactly zero, so an entry no training sample ever reached keeps its initial value. In a
//!   plain model that is every entry outside the image of the occupied region under the
//!   standard hash (at the first hashed level, about a third of the slots); a hidden scene's
//!   keyed index lands on them and trains them.
//! - The *reachable* set: the entries that some grid vertex around an occupied cell of the
//!   file's stored occupancy grid maps to under the standard index
//!   ([`ngp::encoding::reach`]); `reachable_frac` is its share of the level. After
//!   the first occupancy updates, a plain model's training samples only there.
//! - For the reachable and the unreachable set each: count, fraction at init, and the mean,
//!   median, 90th percentile and maximum magnitude. In a plain model the unreachable entries
//!   are at init or frozen where Adam left them during the first steps (before the grid
//!   pruned empty space): small. A hidden scene keeps training many of them all the way
//!   through: fewer at init, larger magnitudes.
//!
//! **MLPs** ([`MatrixStats`]): mean, standard deviation, mean |w|, max |w| and excess
//! kurtosis of each weight matrix (tcnn's padding rows and columns left out: nothing trains
//! them). The MLPs are shared by every scene, so a hidden scene asks more of them: they
//! could drift further from their uniform initialisation (kurtosis −1.2) and grow heavier
//! tails.
//!
//! **`loss` and `training_step`**: the snapshot's `loss` field was once the sum of all
//! scenes' losses, so a stego model reported a larger loss than its cover's quality
//! explains. No cheap self-check exists: the file holds the training cameras' poses and
//! intrinsics but no pixels, so the loss cannot be recomputed from the file alone; only its
//! value (against what models of the same size and step count usually report) is evidence.
//!
//! **Occupancy grid**: the occupied fraction of cascade 0, and its cells' mean and largest
//! optical thickness. instant-ngp marks a cell occupied above `min(0.01, mean)`, and in our
//! small scenes the mean is the smaller: a cover whose density field changed (a hidden scene
//! pushing on the entries it shares, inside objects where no cover ray constrains the
//! density) moves the threshold and with it the cells the grid keeps.
//!
//! **Compression** ([`Compression`]): the ratio of compressed to uncompressed bytes. A hidden
//! scene replaces initial noise and frozen values with trained ones, which changes the
//! entropy of the parameter bytes. For an `.ingp` it is the file's own ratio (and its gzip
//! header: mtime, XFL and OS show which writer made it); a raw `.msgpack` is deflated with
//! flate2 at the default level.
//!
//! [`Analysis::features`] turns all of this into scale-free scalars (fractions, ratios and
//! logarithms rather than counts) for a population-level [`Detector`].

mod detector;
mod stats;

pub use detector::{
    Detector, FeatureWeight, auc_p_value, directed_auc_p_value, feature_matrix, roc_auc,
};
pub use stats::{
    INIT_BOUND, LevelStats, MatrixSpan, MatrixStats, SetStats, Summary, level_stats, mlp_matrices,
    mlp_stats,
};

use ngp::encoding::reach::reference_reachable;
use ngp::encoding::reference_indices;
use ngp::error::{Error, Result};
use ngp::network::NerfLayout;
use ngp::network::nerf::NerfNetwork;
use ngp::occupancy::{N_CELLS, OccupancyGrid};
use ngp::render::march::Marcher;
use ngp::snapshot::{self, Snapshot};
use serde::Serialize;
use std::io::{Read, Write};
use std::path::Path;

/// Largest decompressed document accepted (as the snapshot reader): a corrupt or hostile
/// stream cannot make us allocate more.
const MAX_DOCUMENT_BYTES: u64 = 4 << 30;

/// The 10-byte gzip header (RFC 1952) of an `.ingp`: which writer made the file.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct GzipHeader {
    /// FLG: 0 unless the writer stored a name, comment or header CRC.
    pub flags: u8,
    /// Modification time; zlib through zstr (instant-ngp) writes 0.
    pub mtime: u32,
    /// Extra flags as zlib sets them: 2 at level 9, 4 below level 2, else 0.
    pub xfl: u8,
    /// Operating system byte: 3 = unix, 255 = unknown.
    pub os: u8,
}

/// How compressible the file's msgpack document is.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Compression {
    /// Compressed bytes / uncompressed msgpack bytes.
    pub ratio: f64,
    /// Where `ratio` comes from: "file" (a gzip or zlib-framed file's own bytes) or
    /// "flate2 default level" (a raw msgpack file, compressed here).
    pub measured: String,
    /// Only for gzip-framed files.
    pub gzip_header: Option<GzipHeader>,
}

/// Everything [`analyse_file`] measures in one model file.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Analysis {
    pub path: String,
    /// "ingp (gzip msgpack)", "zlib msgpack" or "msgpack".
    pub format: String,
    pub file_bytes: u64,
    pub msgpack_bytes: u64,
    pub n_levels: u32,
    pub n_features_per_level: u32,
    pub log2_hashmap_size: u32,
    pub aabb_scale: u32,
    /// False when the file holds no occupancy grid: every entry then counts as reachable.
    pub density_grid_stored: bool,
    /// Fraction of cascade-0 cells the stored grid marks occupied.
    pub occupied_frac: f64,
    /// Mean optical thickness of the stored grid's cascade-0 cells: below 0.01 it is the
    /// occupancy threshold itself (`min(0.01, mean)`), so a few very dense cells (the inside
    /// of an object whose density no training ray constrains) raise it and empty the cells
    /// near it: a stealth model's giveaway (benchmarks/steganalysis.md).
    pub grid_mean: f64,
    /// Largest optical thickness of a cascade-0 cell.
    pub grid_max: f64,
    /// Fraction of cascade 0 (the unit box, where keys place hidden scenes) where the
    /// density network outputs a raw log-density within ±[`NEAR_ZERO`] of 0: one point in
    /// each of every [`FIELD_STRIDE`]-th cell. A trained plain cover decodes its empty space
    /// to small positive values, off 0 in all but a few percent of the box; covers sharing
    /// their weights with a hidden text scene decode ≈ 0 in up to three quarters of it,
    /// and an untrained network everywhere (benchmarks/steganalysis.md, "What chance gives").
    pub field_near_zero_frac: f64,
    /// Magnitude at or below which an entry counts as at initialisation.
    pub init_bound: f32,
    pub levels: Vec<LevelStats>,
    pub mlp: Vec<MatrixStats>,
    pub loss: f32,
    pub training_step: u32,
    pub compression: Compression,
}

/// Raw log-densities within this of 0 count as "near zero" ([`Analysis::field_near_zero_frac`]):
/// densities within 0.1 % of 1, what the network outputs where no hidden unit with a density
/// weight fires.
pub const NEAR_ZERO: f32 = 1e-3;

/// [`Analysis::field_near_zero_frac`] evaluates the field in every this-many-th cell of
/// cascade 0 (about 300 000 of its 2^21): the fraction to a few parts in a thousand, in
/// well under a second.
pub const FIELD_STRIDE: usize = 7;

/// [`Analysis::field_near_zero_frac`] of a snapshot's network.
fn field_near_zero_frac(snap: &Snapshot) -> Result<f64> {
    let net = NerfNetwork::new(snap.config)?;
    let cells: Vec<u32> = (0..N_CELLS as u32).step_by(FIELD_STRIDE).collect();
    let marcher = Marcher::new(snap.config.aabb_scale);
    let pos: Vec<[f32; 3]> = OccupancyGrid::points_in_cells(&cells, 0x5eed)
        .into_iter()
        .map(|p| marcher.warp(p))
        .collect();
    let raw = net.density_batch(&snap.params, &reference_indices(&net.layout.grid), &pos);
    let near = raw.iter().filter(|r| r.abs() <= NEAR_ZERO).count();
    Ok(near as f64 / raw.len().max(1) as f64)
}

/// Reads a model file once and measures it. Errors name the file.
pub fn analyse_file(path: &Path) -> Result<Analysis> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    analyse_bytes(path, &bytes)
}

/// [`analyse_file`] on bytes already read; `path` is for the report and error messages.
pub fn analyse_bytes(path: &Path, bytes: &[u8]) -> Result<Analysis> {
    let (raw, format, header) = unframe(bytes).map_err(|m| Error::format(path, m))?;
    let snap = snapshot::from_bytes(&raw).map_err(|m| Error::format(path, m))?;
    let compression = if format == "msgpack" {
        Compression {
            ratio: deflated_len(&raw).map_err(|e| Error::io(path, e))? as f64
                / raw.len().max(1) as f64,
            measured: "flate2 default level".into(),
            gzip_header: None,
        }
    } else {
        Compression {
            ratio: bytes.len() as f64 / raw.len().max(1) as f64,
            measured: "file".into(),
            gzip_header: header,
        }
    };
    let mut a = analyse_snapshot(&snap)?;
    a.path = path.display().to_string();
    a.format = format.into();
    a.file_bytes = bytes.len() as u64;
    a.msgpack_bytes = raw.len() as u64;
    a.compression = compression;
    Ok(a)
}

/// The statistics of a snapshot in memory; the file facts (path, sizes, compression) are
/// left empty for [`analyse_bytes`] to fill.
pub fn analyse_snapshot(snap: &Snapshot) -> Result<Analysis> {
    let layout = NerfLayout::new(snap.config)?;
    if snap.params.len() != layout.n_params {
        return Err(Error::Other(format!(
            "{} parameters, but the configuration has {}",
            snap.params.len(),
            layout.n_params
        )));
    }
    let grid = OccupancyGrid::from_density(snap.density_grid.clone());
    let reach = grid
        .as_ref()
        .map(|g| reference_reachable(&layout.grid, g, snap.config.aabb_scale));
    let g = &layout.grid.config;
    Ok(Analysis {
        path: String::new(),
        format: String::new(),
        file_bytes: 0,
        msgpack_bytes: 0,
        n_levels: g.n_levels,
        n_features_per_level: g.n_features,
        log2_hashmap_size: g.log2_hashmap_size,
        aabb_scale: snap.config.aabb_scale,
        density_grid_stored: grid.is_some(),
        occupied_frac: grid.as_ref().map_or(0.0, |g| g.occupied_fraction()),
        // The mean the grid's own threshold was computed from.
        grid_mean: grid.as_ref().map_or(0.0, |g| g.mean as f64),
        grid_max: grid.as_ref().map_or(0.0, |g| {
            g.density[..N_CELLS]
                .iter()
                .fold(0.0f64, |m, &v| m.max(v as f64))
        }),
        field_near_zero_frac: field_near_zero_frac(snap)?,
        init_bound: INIT_BOUND,
        levels: level_stats(
            &layout.grid,
            &snap.params[layout.grid_offset..],
            reach.as_deref(),
        ),
        mlp: mlp_stats(&layout, &snap.params),
        loss: snap.loss,
        training_step: snap.training_step,
        compression: Compression {
            ratio: 0.0,
            measured: String::new(),
            gzip_header: None,
        },
    })
}

/// Strips gzip or zlib framing as the snapshot reader does (zstr's detection by the first
/// two bytes), keeping what the reader discards: the format and the gzip header.
fn unframe(
    bytes: &[u8],
) -> std::result::Result<(Vec<u8>, &'static str, Option<GzipHeader>), String> {
    if bytes.is_empty() {
        return Err("file is empty".into());
    }
    let (format, header) = match bytes {
        [0x1f, 0x8b, _, flags, m0, m1, m2, m3, xfl, os, ..] => (
            "ingp (gzip msgpack)",
            Some(GzipHeader {
                flags: *flags,
                mtime: u32::from_le_bytes([*m0, *m1, *m2, *m3]),
                xfl: *xfl,
                os: *os,
            }),
        ),
        [0x1f, 0x8b, ..] => return Err("corrupt gzip stream: the header is cut short".into()),
        [0x78, 0x01 | 0x9c | 0xda, ..] => ("zlib msgpack", None),
        // A snapshot is a msgpack map: fixmap, map16 or map32.
        [0x80..=0x8f | 0xde | 0xdf, ..] => return Ok((bytes.to_vec(), "msgpack", None)),
        _ => {
            let head: Vec<String> = bytes.iter().take(8).map(|b| format!("{b:02x}")).collect();
            return Err(format!(
                "not an instant-ngp snapshot: neither gzip/zlib-compressed nor a msgpack map (the file starts with {})",
                head.join(" ")
            ));
        }
    };
    let mut out = Vec::new();
    let res = if header.is_some() {
        flate2::read::GzDecoder::new(bytes)
            .take(MAX_DOCUMENT_BYTES + 1)
            .read_to_end(&mut out)
    } else {
        flate2::read::ZlibDecoder::new(bytes)
            .take(MAX_DOCUMENT_BYTES + 1)
            .read_to_end(&mut out)
    };
    let name = if header.is_some() { "gzip" } else { "zlib" };
    res.map_err(|e| format!("corrupt {name} stream: {e}"))?;
    if out.len() as u64 > MAX_DOCUMENT_BYTES {
        return Err(format!("{name} stream decompresses to more than 4 GiB"));
    }
    Ok((out, format, header))
}

/// Length of `raw` deflated by flate2 at the default level (zlib's level 6), without
/// keeping the output.
fn deflated_len(raw: &[u8]) -> std::io::Result<u64> {
    struct Count(u64);
    impl Write for Count {
        fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
            self.0 += b.len() as u64;
            Ok(b.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }
    let mut enc = flate2::write::GzEncoder::new(Count(0), flate2::Compression::default());
    enc.write_all(raw)?;
    Ok(enc.finish()?.0)
}

/// log10 with a floor, so that an exact zero gives a finite feature.
fn log10_floor(x: f64) -> f64 {
    x.max(1e-8).log10()
}

impl Analysis {
    /// Scale-free scalar features for a population-level detector, with stable names:
    ///
    /// - per level `l`: `init_frac_l{l}`, `unreach_init_frac_l{l}` and
    ///   `unreach_log10_mag_median_l{l}` (the last two only when the level has unreachable
    ///   entries);
    /// - aggregates over the dense and over the hashed levels (entry-weighted):
    ///   `init_frac_{dense,hashed}`, `unreach_init_frac_{dense,hashed}`,
    ///   `reach_frac_{dense,hashed}`, and the mean over hashed levels of
    ///   `{reach,unreach}_log10_mag_median_hashed`;
    /// - per MLP matrix: `mlp_{density,color}{layer}_std` and `…_kurt`;
    /// - `log10_loss` (when the loss is positive), `gzip_ratio`, `field_near_zero_frac`,
    ///   `occupied_frac`, and with a stored grid `grid_log10_mean` and `grid_log10_max`
    ///   (cascade 0's optical thickness).
    ///
    /// Fractions and ratios rather than counts, so a detector fitted on small tables applies
    /// to 2^19 ones. Models with other level counts give other names; a detector treats a
    /// name it lacks as missing. At most 3·L + 24 features (72 for 16 levels).
    pub fn features(&self) -> Vec<(String, f64)> {
        let mut f: Vec<(String, f64)> = Vec::new();
        for l in &self.levels {
            f.push((format!("init_frac_l{}", l.level), l.init_frac));
            if l.unreachable.count > 0 {
                f.push((
                    format!("unreach_init_frac_l{}", l.level),
                    l.unreachable.init_frac,
                ));
                f.push((
                    format!("unreach_log10_mag_median_l{}", l.level),
                    log10_floor(l.unreachable.magnitude.median),
                ));
            }
        }
        for (kind, dense) in [("dense", true), ("hashed", false)] {
            let ls: Vec<&LevelStats> = self.levels.iter().filter(|l| l.dense == dense).collect();
            let entries: f64 = ls.iter().map(|l| l.entries as f64).sum();
            if entries == 0.0 {
                continue;
            }
            let init: f64 = ls.iter().map(|l| l.init_frac * l.entries as f64).sum();
            let reach: f64 = ls.iter().map(|l| l.reachable.count as f64).sum();
            let unreach: f64 = ls.iter().map(|l| l.unreachable.count as f64).sum();
            let unreach_init: f64 = ls
                .iter()
                .map(|l| l.unreachable.init_frac * l.unreachable.count as f64)
                .sum();
            f.push((format!("init_frac_{kind}"), init / entries));
            f.push((format!("reach_frac_{kind}"), reach / entries));
            if unreach > 0.0 {
                f.push((format!("unreach_init_frac_{kind}"), unreach_init / unreach));
            }
            if !dense {
                let mean_log = |sel: &dyn Fn(&LevelStats) -> &SetStats| {
                    let v: Vec<f64> = ls
                        .iter()
                        .filter(|l| sel(l).count > 0)
                        .map(|l| log10_floor(sel(l).magnitude.median))
                        .collect();
                    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
                };
                if let Some(v) = mean_log(&|l| &l.reachable) {
                    f.push(("reach_log10_mag_median_hashed".into(), v));
                }
                if let Some(v) = mean_log(&|l| &l.unreachable) {
                    f.push(("unreach_log10_mag_median_hashed".into(), v));
                }
            }
        }
        for m in &self.mlp {
            f.push((format!("mlp_{}{}_std", m.network, m.layer), m.std));
            f.push((
                format!("mlp_{}{}_kurt", m.network, m.layer),
                m.excess_kurtosis,
            ));
        }
        if self.loss.is_finite() && self.loss > 0.0 {
            f.push(("log10_loss".into(), (self.loss as f64).log10()));
        }
        f.push(("gzip_ratio".into(), self.compression.ratio));
        f.push(("field_near_zero_frac".into(), self.field_near_zero_frac));
        f.push(("occupied_frac".into(), self.occupied_frac));
        if self.density_grid_stored {
            f.push(("grid_log10_mean".into(), log10_floor(self.grid_mean)));
            f.push(("grid_log10_max".into(), log10_floor(self.grid_max)));
        }
        f.retain(|(_, v)| v.is_finite());
        f
    }
}

#[cfg(test)]
mod tests;
