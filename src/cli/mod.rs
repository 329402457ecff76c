//! One module per subcommand, plus what they share.

pub mod common;
pub mod demo;
pub mod eval;
pub mod experiment;
pub mod inspect;
pub mod keygen;
pub mod render;
pub mod synth;
pub mod train;

use anyhow::{Result, bail};
use std::path::{Path, PathBuf};
use stegongp::ngp::data::LoadOptions;
use stegongp::ngp::encoding::{LevelIndices, reference_indices};
use stegongp::ngp::model::Model;
use stegongp::ngp::network::NerfLayout;
use stegongp::ngp::occupancy::OccupancyGrid;
use stegongp::ngp::train::SceneSpec;

/// The hidden scenes of a `train --hidden … --key …` call.
pub fn stego_scenes(
    hidden: &[PathBuf],
    keys: &[PathBuf],
    _layout: &NerfLayout,
    _opts: &LoadOptions,
    _aabb_scale: u32,
) -> Result<Vec<SceneSpec>> {
    if !hidden.is_empty() || !keys.is_empty() {
        bail!("hidden scenes are not supported yet");
    }
    Ok(Vec::new())
}

/// Index functions and occupancy grid to render a model with: the reference index and the
/// stored grid without a key; the key's indices and a grid rebuilt from the network with it.
pub fn scene_for_key(model: &Model, key: Option<&Path>) -> Result<(LevelIndices, Option<OccupancyGrid>)> {
    match key {
        None => Ok((reference_indices(&model.net.layout.grid), None)),
        Some(_) => bail!("--key is not supported yet"),
    }
}
