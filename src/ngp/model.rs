//! A trained model as it is published: architecture, inference (EMA) weights and the cover's
//! occupancy grid, stored as an instant-ngp snapshot.

use crate::error::{Error, Result};
use crate::ngp::encoding::LevelIndices;
use crate::ngp::network::ModelConfig;
use crate::ngp::network::nerf::NerfNetwork;
use crate::ngp::occupancy::OccupancyGrid;
use crate::ngp::render::image::SceneView;
use crate::ngp::render::march::Marcher;
use crate::ngp::snapshot::{self, Snapshot};
use crate::ngp::train::Trainer;
use std::path::Path;

pub struct Model {
    pub config: ModelConfig,
    pub net: NerfNetwork,
    pub params: Vec<f32>,
    /// The cover's occupancy grid (the only one a file holds).
    pub grid: OccupancyGrid,
    pub training_step: u32,
    pub loss: f32,
}

impl Model {
    pub fn from_trainer(t: &Trainer, loss: f32) -> Self {
        let config = t.net.layout.config;
        Model {
            config,
            net: NerfNetwork::new(config).expect("trainer config is valid"),
            params: t.inference_params(),
            grid: t.grid(0).clone(),
            training_step: t.step,
            loss,
        }
    }

    pub fn load(path: &Path) -> Result<Self> {
        let snap = snapshot::load(path)?;
        let net = NerfNetwork::new(snap.config)?;
        if snap.params.len() != net.layout.n_params {
            return Err(Error::format(
                path,
                format!(
                    "params_binary holds {} parameters, the configuration needs {}",
                    snap.params.len(),
                    net.layout.n_params
                ),
            ));
        }
        // An empty grid means "never populated" to the reference: march everywhere.
        let grid = if snap.density_grid.is_empty() {
            OccupancyGrid::new(snap.config.aabb_scale)
        } else {
            OccupancyGrid::from_density(snap.density_grid)
                .ok_or_else(|| Error::format(path, "density_grid_binary has a wrong length"))?
        };
        Ok(Model {
            config: snap.config,
            net,
            params: snap.params,
            grid,
            training_step: snap.training_step,
            loss: snap.loss,
        })
    }

    pub fn to_snapshot(&self) -> Snapshot {
        let mut s = Snapshot::new(self.config, self.params.clone(), self.grid.density.clone());
        s.training_step = self.training_step;
        s.loss = self.loss;
        s
    }

    pub fn save(&self, path: &Path) -> Result<()> {
        snapshot::save(path, &self.to_snapshot())
    }

    pub fn marcher(&self) -> Marcher {
        Marcher::new(self.config.aabb_scale)
    }

    /// A renderable view with the given index functions and occupancy grid.
    pub fn view<'a>(&'a self, indices: &'a LevelIndices, grid: &'a OccupancyGrid) -> SceneView<'a> {
        SceneView {
            net: &self.net,
            params: &self.params,
            indices,
            grid,
            marcher: self.marcher(),
        }
    }
}
