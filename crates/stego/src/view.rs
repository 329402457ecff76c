//! Opening a published model for viewing: with no key, the cover (reference index, stored
//! grid); with a key, the hidden scene it unlocks (the key's index functions, confined to the
//! cover's reachable entries for a stealth model, and an occupancy grid rebuilt from the
//! network, since a hidden scene's grid is never stored, cut to the key's box, with more
//! points near its occupied cells). One recipe for the CLI, the demo,
//! the experiments and the tests.

use super::keys::Key;
use super::occupancy::{KEY_HOLDER_REFINE_SAMPLES, KEY_HOLDER_SAMPLES_PER_CELL};
use super::stealth::{hidden_indices, robust_indices};
use backend::{Device, RenderBackend};
use ngp::encoding::{LevelIndices, reference_indices};
use ngp::error::Result;
use ngp::model::Model;
use ngp::occupancy::OccupancyGrid;
use ngp::render::image::SceneView;

/// What renders: index functions and, for a key, the rebuilt grid.
pub struct OpenedScene {
    pub indices: LevelIndices,
    /// `None`: the model's stored grid (the cover's).
    pub rebuilt: Option<OccupancyGrid>,
}

impl OpenedScene {
    pub fn view<'a>(&'a self, model: &'a Model) -> SceneView<'a> {
        model.view(&self.indices, self.grid(model))
    }

    /// The occupancy grid to march through: the rebuilt one, else the model's stored one.
    pub fn grid<'a>(&'a self, model: &'a Model) -> &'a OccupancyGrid {
        self.rebuilt.as_ref().unwrap_or(&model.grid)
    }

    /// This scene through a grid rebuilt from the network, as a key holder's is, where it
    /// still had the model's stored grid (the cover): a plain model scored on the terms its
    /// hidden scenes are, since the grid a hidden scene trained with is never stored.
    pub fn with_rebuilt_grid(self, device: &Device, model: &Model, seed: u64) -> Result<Self> {
        if self.rebuilt.is_some() {
            return Ok(self);
        }
        let rebuilt = key_holder_grid_on(device, model, &self.indices, None, seed)?;
        Ok(OpenedScene {
            rebuilt: Some(rebuilt),
            ..self
        })
    }

    /// A renderer of this scene on `device`.
    pub fn renderer<'a>(
        &'a self,
        device: &'a Device,
        model: &'a Model,
    ) -> Result<Box<dyn RenderBackend + 'a>> {
        device.renderer(model, &self.indices, self.grid(model))
    }
}

/// Opens `model` as seen through `key` (`None` or the reference key: the cover). `stealth`
/// says the model was trained with `train --stealth`; `seed` draws the rebuild's samples.
pub fn open_scene(model: &Model, key: Option<&Key>, stealth: bool, seed: u64) -> OpenedScene {
    // The key holder's grid has one recipe (`key_holder_grid_on`); the CPU engine's
    // rebuild and refinement return no error.
    open_scene_on(&Device::default(), model, key, stealth, seed)
        .expect("the CPU engine's grid rebuild does not fail")
}

/// A key holder's grid of `model` under `indices`, on `device`: the rebuild's points in every
/// cell (cut to `scene_box`), then more near the occupied cells.
fn key_holder_grid_on(
    device: &Device,
    model: &Model,
    indices: &LevelIndices,
    scene_box: Option<u32>,
    seed: u64,
) -> Result<OccupancyGrid> {
    let mut grid =
        device.rebuild_occupancy(model, indices, scene_box, KEY_HOLDER_SAMPLES_PER_CELL, seed)?;
    device.refine_occupancy(
        model,
        indices,
        &mut grid,
        KEY_HOLDER_REFINE_SAMPLES,
        KEY_HOLDER_SAMPLES_PER_CELL,
        seed,
    )?;
    Ok(grid)
}

/// [`open_scene`] with a key holder's grid rebuilt on `device` (the same grid as the CPU's
/// up to cells at the threshold).
pub fn open_scene_on(
    device: &Device,
    model: &Model,
    key: Option<&Key>,
    stealth: bool,
    seed: u64,
) -> Result<OpenedScene> {
    let layout = &model.net.layout.grid;
    Ok(match key {
        Some(k) if !k.is_reference() => {
            // A robust key says how its scene was confined (to what the stored grid
            // reaches), with or without stealth's other parts.
            let indices = if k.robust() {
                robust_indices(k, &model.net.layout, &model.grid)
            } else {
                hidden_indices(k, &model.net.layout, model.params(), stealth)
            };
            // Cut to the box the scene was trained in: outside it, its index meets only
            // the cover's entries, whose density would render as haze.
            let rebuilt = key_holder_grid_on(device, model, &indices, k.scene_box(), seed)?;
            OpenedScene {
                indices,
                rebuilt: Some(rebuilt),
            }
        }
        _ => OpenedScene {
            indices: reference_indices(layout),
            rebuilt: None,
        },
    })
}
