//! A summary of a model file: what it is and how it is configured. It describes only what
//! any instant-ngp user can see in the file; it says nothing about hidden scenes.

use super::n_cascades;
use super::read::{Framing, from_msgpack, unframe};
use crate::error::{Error, Result};
use crate::network::NerfLayout;
use crate::occupancy::OccupancyGrid;
use std::path::Path;

#[derive(Clone, Debug, serde::Serialize)]
pub struct LevelSummary {
    pub level: u32,
    pub resolution: u32,
    pub entries: u32,
    pub dense: bool,
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct SnapshotInfo {
    pub path: String,
    /// "ingp (gzip msgpack)", "zlib msgpack" or "msgpack".
    pub format: String,
    pub file_bytes: u64,
    pub msgpack_bytes: u64,
    pub version: u64,
    pub mode: String,
    pub n_levels: u32,
    pub n_features_per_level: u32,
    pub log2_hashmap_size: u32,
    pub base_resolution: u32,
    pub per_level_scale: f32,
    pub dense_levels: Vec<u32>,
    pub levels: Vec<LevelSummary>,
    pub n_params: usize,
    pub n_mlp_params: usize,
    pub n_grid_params: usize,
    pub grid_offset: usize,
    pub params_type: String,
    pub params_bytes: usize,
    pub density_grid_cascades: usize,
    pub density_grid_cells: usize,
    pub density_grid_bytes: usize,
    /// Per cascade, the fraction of its cells occupied (above instant-ngp's threshold,
    /// `min(0.01, mean density of cascade 0)`): how much of the box the model fills, the
    /// background of a capture in the outer cascades.
    pub occupied_per_cascade: Vec<f64>,
    pub aabb_scale: u32,
    pub aabb_min: [f32; 3],
    pub aabb_max: [f32; 3],
    pub training_step: u32,
    pub loss: f32,
    pub n_images: usize,
    pub has_optimizer_state: bool,
    /// A `train --save-every` checkpoint: `train --resume` goes on from it exactly.
    pub has_run_state: bool,
}

pub fn inspect(path: &Path) -> Result<SnapshotInfo> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let (raw, framing) = unframe(&bytes).map_err(|m| Error::format(path, m))?;
    let snap = from_msgpack(&raw).map_err(|m| Error::format(path, m))?;
    let layout = NerfLayout::new(snap.config)?;
    // from_msgpack validated the type; fetch its name for the report.
    let params_type = match super::msgpack::decode(&raw) {
        Ok(rmpv::Value::Map(m)) => m
            .iter()
            .find(|(k, _)| k.as_str() == Some("snapshot"))
            .and_then(|(_, v)| v.as_map())
            .and_then(|s| {
                s.iter()
                    .rev()
                    .find(|(k, _)| k.as_str() == Some("params_type"))
                    .and_then(|(_, v)| v.as_str().map(str::to_string))
            })
            .unwrap_or_else(|| "__half".into()),
        _ => "__half".into(),
    };
    let elem = if params_type == "float" { 4 } else { 2 };
    let g = &layout.grid;
    let cascades = n_cascades(snap.config.aabb_scale);
    Ok(SnapshotInfo {
        path: path.display().to_string(),
        format: match framing {
            Framing::Gzip => "ingp (gzip msgpack)",
            Framing::Zlib => "zlib msgpack",
            Framing::Raw => "msgpack",
        }
        .into(),
        file_bytes: bytes.len() as u64,
        msgpack_bytes: raw.len() as u64,
        version: super::SNAPSHOT_VERSION,
        mode: "nerf".into(),
        n_levels: g.config.n_levels,
        n_features_per_level: g.config.n_features,
        log2_hashmap_size: g.config.log2_hashmap_size,
        base_resolution: g.config.base_resolution,
        per_level_scale: g.per_level_scale,
        dense_levels: g
            .levels
            .iter()
            .filter(|l| l.dense)
            .map(|l| l.level)
            .collect(),
        levels: g
            .levels
            .iter()
            .map(|l| LevelSummary {
                level: l.level,
                resolution: l.resolution,
                entries: l.size,
                dense: l.dense,
            })
            .collect(),
        n_params: layout.n_params,
        n_mlp_params: layout.n_mlp_params(),
        n_grid_params: g.n_params(),
        grid_offset: layout.grid_offset,
        params_type,
        params_bytes: layout.n_params * elem,
        density_grid_cascades: cascades,
        density_grid_cells: snap.density_grid.len(),
        density_grid_bytes: snap.density_grid.len() * 2,
        occupied_per_cascade: OccupancyGrid::from_density(snap.density_grid.clone())
            .map(|grid| {
                (0..grid.n_cascades)
                    .map(|c| grid.occupied_fraction_in(c))
                    .collect()
            })
            .unwrap_or_default(),
        aabb_scale: snap.config.aabb_scale,
        aabb_min: snap.view.aabb.min,
        aabb_max: snap.view.aabb.max,
        training_step: snap.training_step,
        loss: snap.loss,
        n_images: snap.dataset.as_ref().map_or(0, |d| d.images.len()),
        has_optimizer_state: snap.has_optimizer_state(),
        has_run_state: snap.preserved.run_state.is_some(),
    })
}
