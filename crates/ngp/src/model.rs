//! A trained model as it is published: architecture, inference (EMA) weights and the cover's
//! occupancy grid, stored as an instant-ngp snapshot.

use crate::data::Dataset;
use crate::encoding::LevelIndices;
use crate::encoding::grid;
use crate::error::{Error, Result};
use crate::network::ModelConfig;
use crate::network::nerf::NerfNetwork;
use crate::occupancy::OccupancyGrid;
use crate::render::image::SceneView;
use crate::render::march::Marcher;
use crate::snapshot::{self, DatasetImage, Lens, Snapshot, SnapshotDataset};
use std::path::Path;

pub struct Model {
    pub config: ModelConfig,
    pub net: NerfNetwork,
    /// Private so that [`Model::grid_f16`] cannot go stale: read with [`Model::params`].
    params: Vec<f32>,
    /// The grid block as fp16 bits, where every value is one (a model read from its file):
    /// views read it, the same encoding from half the memory.
    grid_f16: Option<Vec<u16>>,
    /// The cover's occupancy grid (the only one a file holds).
    pub grid: OccupancyGrid,
    pub training_step: u32,
    pub loss: f32,
    /// The cover's training cameras (what instant-ngp stores under `nerf.dataset`); never a
    /// hidden scene's.
    pub dataset: Option<SnapshotDataset>,
    /// Rays per batch, trained and marched samples of the cover's last step.
    pub batch_counters: (u32, u32, u32),
}

impl Model {
    /// A model from any backend's state: the inference (EMA) weights, scene 0's grid and
    /// its training images' metadata (what `Model::from_trainer` takes from a CPU trainer).
    pub fn from_parts(
        config: ModelConfig,
        params: Vec<f32>,
        grid: OccupancyGrid,
        training_step: u32,
        loss: f32,
        dataset: &Dataset,
        batch_counters: (u32, u32, u32),
    ) -> Result<Self> {
        let net = NerfNetwork::new(config)?;
        if params.len() != net.layout.n_params {
            return Err(Error::Config(format!(
                "{} parameters for a {}-parameter network",
                params.len(),
                net.layout.n_params
            )));
        }
        Ok(Model {
            config,
            grid_f16: grid::exact_half_table(&params[net.layout.grid_offset..]),
            net,
            params,
            grid,
            training_step,
            loss,
            dataset: Some(snapshot_dataset(dataset)),
            batch_counters,
        })
    }

    pub fn load(path: &Path) -> Result<Self> {
        Self::from_snapshot(snapshot::load(path)?, path)
    }

    /// This model as a reader of its published file gets it: saved as [`Model::save`] saves
    /// (fp16 weights and grid) and read back, without touching a disk. What an edit of the
    /// published file starts from.
    pub fn published(&self) -> Result<Self> {
        let origin = Path::new("the published model");
        let bytes = snapshot::to_bytes(&self.to_snapshot(), false)?;
        let snap = snapshot::from_bytes(&bytes).map_err(|m| Error::format(origin, m))?;
        Self::from_snapshot(snap, origin)
    }

    /// A model from a snapshot read from `path` (named in errors).
    pub fn from_snapshot(snap: Snapshot, path: &Path) -> Result<Self> {
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
            grid_f16: grid::exact_half_table(&snap.params[net.layout.grid_offset..]),
            net,
            params: snap.params,
            grid,
            training_step: snap.training_step,
            loss: snap.loss,
            dataset: snap.dataset,
            batch_counters: (
                snap.rays_per_batch,
                snap.measured_batch_size,
                snap.measured_batch_size_before_compaction,
            ),
        })
    }

    pub fn to_snapshot(&self) -> Snapshot {
        let mut s = Snapshot::new(self.config, self.params.clone(), self.grid.density.clone());
        s.training_step = self.training_step;
        s.loss = self.loss;
        s.dataset = self.dataset.clone();
        (
            s.rays_per_batch,
            s.measured_batch_size,
            s.measured_batch_size_before_compaction,
        ) = self.batch_counters;
        s
    }

    pub fn save(&self, path: &Path) -> Result<()> {
        snapshot::save(path, &self.to_snapshot())
    }

    /// Saves the weights and the density grid at full precision ([`Snapshot::exact`]):
    /// [`Model::load`] gives back a model that renders to the bit as this one does, where
    /// [`Model::save`]'s fp16 would move every weight and cells near the threshold.
    pub fn save_exact(&self, path: &Path) -> Result<()> {
        let mut s = self.to_snapshot();
        s.exact = true;
        snapshot::save(path, &s)
    }

    /// This model with other weights (an edit of a published file: noise, pruning,
    /// quantisation, a fine-tune): the same configuration, grid and stored cameras.
    pub fn with_params(self, params: Vec<f32>) -> Result<Self> {
        if params.len() != self.net.layout.n_params {
            return Err(Error::Config(format!(
                "{} parameters for a {}-parameter network",
                params.len(),
                self.net.layout.n_params
            )));
        }
        Ok(Model {
            grid_f16: grid::exact_half_table(&params[self.net.layout.grid_offset..]),
            params,
            ..self
        })
    }

    /// The inference weights (the layout's blocks: density MLP, colour MLP, grid).
    pub fn params(&self) -> &[f32] {
        &self.params
    }

    /// Whether views read the grid from its fp16 copy (every grid value is an fp16).
    pub fn reads_grid_as_f16(&self) -> bool {
        self.grid_f16.is_some()
    }

    pub fn marcher(&self) -> Marcher {
        Marcher::new(self.config.aabb_scale)
    }

    /// A renderable view with the given index functions and occupancy grid.
    pub fn view<'a>(&'a self, indices: &'a LevelIndices, grid: &'a OccupancyGrid) -> SceneView<'a> {
        SceneView {
            net: &self.net,
            params: &self.params,
            grid_f16: self.grid_f16.as_deref(),
            indices,
            grid,
            marcher: self.marcher(),
        }
    }
}

/// What instant-ngp stores about the training images: paths as given in the transforms
/// file, resolution, focal length, principal point, lens and the ngp-space pose.
pub fn snapshot_dataset(data: &Dataset) -> SnapshotDataset {
    let images = data
        .frames
        .iter()
        .map(|f| {
            let c = &f.camera;
            let mut img = DatasetImage::new([c.width as i32, c.height as i32], [c.fx, c.fy], c.c2w);
            img.principal_point = [c.cx / c.width as f32, c.cy / c.height as f32];
            if let Some(d) = c.distortion {
                img.lens = Lens::OpenCv {
                    k1: d.k1,
                    k2: d.k2,
                    p1: d.p1,
                    p2: d.p2,
                };
            }
            img
        })
        .collect();
    let paths = data.frames.iter().map(|f| f.file_path.clone()).collect();
    let mut ds = SnapshotDataset::new(paths, images, data.aabb_scale);
    ds.scale = data.scale;
    ds.offset = data.offset;
    ds
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Camera;
    use crate::encoding::layout::GridConfig;
    use crate::encoding::reference_indices;
    use crate::network::NerfLayout;
    use crate::occupancy::n_cascades;
    use crate::render::image::{RenderOptions, render_image};
    use crate::rng::Pcg32;
    use crate::snapshot::DENSITY_GRID_CELLS;

    #[test]
    fn a_model_read_from_its_file_renders_from_the_fp16_grid_to_the_same_bits() {
        let config = ModelConfig {
            grid: GridConfig {
                n_levels: 6,
                n_features: 2,
                log2_hashmap_size: 12,
                base_resolution: 8,
            },
            aabb_scale: 4,
        };
        let n = NerfLayout::new(config).unwrap().n_params;
        let mut r = Pcg32::new(7, 1);
        let params: Vec<f32> = (0..n).map(|_| r.next_f32() * 2.0 - 1.0).collect();
        let cells = DENSITY_GRID_CELLS * n_cascades(config.aabb_scale);
        let density = (0..cells).map(|_| r.next_f32() * 0.1).collect();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.ingp");
        snapshot::save(&path, &Snapshot::new(config, params, density)).unwrap();
        let model = Model::load(&path).unwrap();
        assert!(model.reads_grid_as_f16(), "the file stores fp16");
        let idx = reference_indices(&model.net.layout.grid);
        let fp16 = model.view(&idx, &model.grid);
        assert!(fp16.grid_f16.is_some());
        let f32_view = SceneView {
            grid_f16: None,
            ..model.view(&idx, &model.grid)
        };
        let cam = Camera {
            c2w: [
                [1.0, 0.0, 0.0, 0.5],
                [0.0, -1.0, 0.0, 0.5],
                [0.0, 0.0, -1.0, 2.5],
            ],
            fx: 20.0,
            fy: 20.0,
            cx: 12.0,
            cy: 8.0,
            width: 24,
            height: 16,
            distortion: None,
        };
        let opts = RenderOptions::default();
        let (a, b) = (
            render_image(&fp16, &cam, &opts),
            render_image(&f32_view, &cam, &opts),
        );
        assert!(
            a.n_samples > 1000,
            "{} samples: the view must see the field",
            a.n_samples
        );
        assert_eq!(a.n_samples, b.n_samples);
        for (x, y) in a
            .rgb
            .iter()
            .chain(&a.depth)
            .zip(b.rgb.iter().chain(&b.depth))
        {
            assert_eq!(x.to_bits(), y.to_bits());
        }
    }

    /// An exact file gives back the weights and the densities to the bit (fp16 moves both).
    #[test]
    fn an_exact_file_reads_back_to_the_bit() {
        let config = ModelConfig {
            grid: GridConfig {
                n_levels: 4,
                n_features: 2,
                log2_hashmap_size: 10,
                base_resolution: 8,
            },
            aabb_scale: 2,
        };
        let n = NerfLayout::new(config).unwrap().n_params;
        let mut r = Pcg32::new(3, 9);
        let params: Vec<f32> = (0..n).map(|_| r.next_f32() * 2.0 - 1.0).collect();
        let cells = DENSITY_GRID_CELLS * n_cascades(config.aabb_scale);
        let density: Vec<f32> = (0..cells).map(|_| r.next_f32() * 0.1).collect();
        let dir = tempfile::tempdir().unwrap();
        let grid = OccupancyGrid::from_density(density.clone()).unwrap();
        let mut snap = Snapshot::new(config, params.clone(), density.clone());
        snap.loss = 0.25;
        let model = Model::load(&{
            let p = dir.path().join("plain.ingp");
            snapshot::save(&p, &snap).unwrap();
            p
        })
        .unwrap();
        assert_ne!(model.params(), &params[..], "fp16 moves the weights");
        let exact = Model {
            params: params.clone(),
            grid_f16: None,
            grid,
            ..model
        };
        let path = dir.path().join("exact.ingp");
        exact.save_exact(&path).unwrap();
        let back = Model::load(&path).unwrap();
        assert_eq!(back.params(), &params[..]);
        assert_eq!(back.grid.density, density);
        assert_eq!(back.loss, 0.25);
        assert!(snapshot::load(&path).unwrap().exact);
        let plain = snapshot::load(&dir.path().join("plain.ingp")).unwrap();
        assert!(!plain.exact);
    }
}
