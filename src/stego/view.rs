//! Opening a published model for viewing: with no key, the cover (reference index, stored
//! grid); with a key, the hidden scene it unlocks (the key's index functions, confined to the
//! cover's reachable entries for a stealth model, and an occupancy grid rebuilt from the
//! network, since a hidden scene's grid is never stored). One recipe for the CLI, the demo,
//! the experiments and the tests.

use super::keys::Key;
use super::stealth::hidden_indices;
use crate::ngp::encoding::{LevelIndices, reference_indices};
use crate::ngp::model::Model;
use crate::ngp::occupancy::OccupancyGrid;
use crate::ngp::render::image::{KEY_HOLDER_SAMPLES_PER_CELL, SceneView, rebuild_occupancy};

/// What renders: index functions and, for a key, the rebuilt grid.
pub struct OpenedScene {
    pub indices: LevelIndices,
    /// `None`: the model's stored grid (the cover's).
    pub rebuilt: Option<OccupancyGrid>,
}

impl OpenedScene {
    pub fn view<'a>(&'a self, model: &'a Model) -> SceneView<'a> {
        model.view(&self.indices, self.rebuilt.as_ref().unwrap_or(&model.grid))
    }
}

/// Opens `model` as seen through `key` (`None` or the reference key: the cover). `stealth`
/// says the model was trained with `train --stealth`; `seed` draws the rebuild's samples.
pub fn open_scene(model: &Model, key: Option<&Key>, stealth: bool, seed: u64) -> OpenedScene {
    let layout = &model.net.layout.grid;
    match key {
        Some(k) if !k.is_reference() => {
            let indices = hidden_indices(k, &model.net.layout, &model.grid, &model.params, stealth);
            let rebuilt = rebuild_occupancy(
                &model.net,
                &model.params,
                &indices,
                model.config.aabb_scale,
                KEY_HOLDER_SAMPLES_PER_CELL,
                seed,
            );
            OpenedScene {
                indices,
                rebuilt: Some(rebuilt),
            }
        }
        _ => OpenedScene {
            indices: reference_indices(layout),
            rebuilt: None,
        },
    }
}
