//! Where the engine runs: the CPU engine or the wgpu backend behind one boundary, so that
//! every subcommand trains and renders the same way on either (`--device auto|cpu|gpu`).
//!
//! [`TrainBackend`] is what a training loop needs from a trainer (a step, the scenes, the
//! model as published); [`RenderBackend`] is what evaluation needs from a renderer (one
//! image per camera). Both are the engine's traits: the CPU `Trainer` and `SceneView`
//! implement them there, the GPU trainer and renderer in the `gpu` crate; the kernels below
//! them stay each backend's own business. This crate only opens a device and hands out
//! the trainer or renderer that runs on it.

use ngp::encoding::LevelIndices;
use ngp::error::{Error, Result};
use ngp::model::Model;
use ngp::network::ModelConfig;
use ngp::occupancy::{OccupancyGrid, RefineReport};
pub use ngp::render::RenderBackend;
use ngp::render::march::log_density_at;
pub use ngp::train::TrainBackend;
use ngp::train::{SceneSpec, TrainConfig, Trainer};
use serde::Serialize;

/// Which device a command asks for.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum DeviceRequest {
    /// A hardware GPU when there is one, the CPU otherwise (never a software GPU, which is
    /// slower than the CPU engine).
    #[default]
    Auto,
    /// The CPU engine.
    Cpu,
    /// A GPU, hardware first; a software one (Mesa's llvmpipe) when it is the only one. An
    /// error where none exists.
    Gpu,
}

impl DeviceRequest {
    pub fn name(self) -> &'static str {
        match self {
            DeviceRequest::Auto => "auto",
            DeviceRequest::Cpu => "cpu",
            DeviceRequest::Gpu => "gpu",
        }
    }
}

impl std::str::FromStr for DeviceRequest {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        [DeviceRequest::Auto, DeviceRequest::Cpu, DeviceRequest::Gpu]
            .into_iter()
            .find(|d| d.name() == s)
            .ok_or_else(|| Error::Config(format!("device `{s}`: one of auto, cpu, gpu")))
    }
}

/// What ran, for a command's output and its `--json`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct DeviceReport {
    /// `cpu` or `gpu`.
    pub kind: &'static str,
    /// The CPU's thread count, or the adapter's name, API and driver.
    pub name: String,
    /// A software GPU (llvmpipe): correct, and far slower than a hardware one.
    pub software: bool,
    /// Why `auto` fell back to the CPU, when it did.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fallback: Option<String>,
}

impl std::fmt::Display for DeviceReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", self.kind, self.name)?;
        if let Some(why) = &self.fallback {
            write!(f, " (no GPU: {why})")?;
        }
        Ok(())
    }
}

/// Density evaluations per trained sample the CPU's occupancy updates spend by default.
pub const CPU_OCCUPANCY_BUDGET: f32 = 1.0;

/// The CPU's default coarse-march aim ([`Device::default_coarse_march`]).
pub const CPU_COARSE_MARCH: u32 = 96;

/// An opened device.
pub enum Device {
    Cpu {
        fallback: Option<String>,
    },
    #[cfg(feature = "gpu")]
    Gpu(Box<gpu::GpuContext>),
}

impl std::fmt::Debug for Device {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Device({})", self.report())
    }
}

impl Default for Device {
    fn default() -> Self {
        Device::Cpu { fallback: None }
    }
}

impl Device {
    /// Opens what `request` asks for (see [`DeviceRequest`]).
    pub fn open(request: DeviceRequest) -> Result<Device> {
        match request {
            DeviceRequest::Cpu => Ok(Device::default()),
            #[cfg(feature = "gpu")]
            DeviceRequest::Auto => {
                use gpu::{AdapterRequest, GpuContext};
                Ok(match GpuContext::new(AdapterRequest::Auto) {
                    Ok(ctx) => Device::Gpu(Box::new(ctx)),
                    Err(e) => Device::Cpu {
                        fallback: Some(e.to_string()),
                    },
                })
            }
            #[cfg(feature = "gpu")]
            DeviceRequest::Gpu => {
                use gpu::{AdapterRequest, GpuContext};
                GpuContext::new(AdapterRequest::Any)
                    .map(|ctx| Device::Gpu(Box::new(ctx)))
                    .map_err(gpu_error)
            }
            #[cfg(not(feature = "gpu"))]
            DeviceRequest::Auto => Ok(Device::Cpu {
                fallback: Some("built without the `gpu` feature".into()),
            }),
            #[cfg(not(feature = "gpu"))]
            DeviceRequest::Gpu => Err(Error::Config(
                "--device gpu: this build has no GPU backend (the `gpu` feature)".into(),
            )),
        }
    }

    pub fn report(&self) -> DeviceReport {
        match self {
            Device::Cpu { fallback } => DeviceReport {
                kind: "cpu",
                name: format!("{} threads", rayon::current_num_threads()),
                software: false,
                fallback: fallback.clone(),
            },
            #[cfg(feature = "gpu")]
            Device::Gpu(ctx) => {
                let r = ctx.report();
                DeviceReport {
                    kind: "gpu",
                    name: format!("{} ({}, {})", r.name, r.backend, r.driver),
                    software: r.software,
                    fallback: None,
                }
            }
        }
    }

    /// The occupancy-update budget a training on this device uses unless told otherwise
    /// ([`GridUpdates`](ngp::train::GridUpdates)). On the CPU one density evaluation per
    /// trained sample: a whole update of a capture's five cascades (10.5 M evaluations)
    /// costs seconds there, and the reference's 67 in the first 256 steps took most of the
    /// first minutes (benchmarks/engine.md, "The first minutes of a real capture"). A GPU
    /// keeps the reference's schedule, where an update costs a millisecond.
    pub fn default_occupancy_budget(&self) -> Option<f32> {
        match self {
            Device::Cpu { .. } => Some(CPU_OCCUPANCY_BUDGET),
            #[cfg(feature = "gpu")]
            Device::Gpu(_) => None,
        }
    }

    /// The coarse march's aim a training on this device uses unless told otherwise
    /// ([`ngp::train::coarse`]): on the CPU, rays of about 96 to 192 samples while a
    /// capture's grid is full of fog, where a 360° room's rays of ~900 samples left a step
    /// a few hundred rays (benchmarks/engine.md, "360° captures"). A GPU keeps the
    /// reference's step, where a step costs milliseconds.
    pub fn default_coarse_march(&self) -> Option<u32> {
        match self {
            Device::Cpu { .. } => Some(CPU_COARSE_MARCH),
            #[cfg(feature = "gpu")]
            Device::Gpu(_) => None,
        }
    }

    /// A trainer of `scenes` on this device, starting from the weights and grids the CPU
    /// [`Trainer`] starts from for `config.seed`.
    pub fn trainer<'d>(
        &'d self,
        model: ModelConfig,
        scenes: Vec<SceneSpec>,
        config: TrainConfig,
    ) -> Result<Box<dyn TrainBackend + 'd>> {
        match self {
            Device::Cpu { .. } => Ok(Box::new(Trainer::new(model, scenes, config)?)),
            #[cfg(feature = "gpu")]
            Device::Gpu(ctx) => {
                let mut t = gpu::GpuTrainer::new(ctx, model, scenes, config).map_err(gpu_error)?;
                // A whole run: the device one step ahead of the host, never waiting for it
                // (a policy installed later reads back in step again).
                t.set_read_lag(gpu::trainer::MAX_LAG).map_err(gpu_error)?;
                Ok(Box::new(t))
            }
        }
    }

    /// A renderer of `model` seen through `indices` and `grid` (what
    /// [`OpenedScene`](stego::OpenedScene) gives: the cover's stored grid, or a key
    /// holder's rebuilt one).
    pub fn renderer<'d>(
        &'d self,
        model: &'d Model,
        indices: &'d LevelIndices,
        grid: &'d OccupancyGrid,
    ) -> Result<Box<dyn RenderBackend + 'd>> {
        match self {
            Device::Cpu { .. } => Ok(Box::new(model.view(indices, grid))),
            #[cfg(feature = "gpu")]
            Device::Gpu(ctx) => Ok(Box::new(
                gpu::GpuRenderer::new(ctx, model, indices, grid).map_err(gpu_error)?,
            )),
        }
    }
}

impl Device {
    /// [`OccupancyGrid::refine_near_occupied`] of a rebuilt `grid` of `model` under
    /// `indices`, the densities evaluated on this device.
    pub fn refine_occupancy(
        &self,
        model: &Model,
        indices: &LevelIndices,
        grid: &mut OccupancyGrid,
        rounds: usize,
        first_round: usize,
        seed: u64,
    ) -> Result<RefineReport> {
        match self {
            Device::Cpu { .. } => Ok(grid.refine_near_occupied(
                rounds,
                first_round,
                seed,
                log_density_at(&model.net, model.params(), indices, model.config.aabb_scale),
            )),
            #[cfg(feature = "gpu")]
            Device::Gpu(ctx) => {
                gpu::refine_occupancy_gpu(ctx, model, indices, grid, rounds, first_round, seed)
                    .map_err(gpu_error)
            }
        }
    }

    /// A key holder's occupancy grid of `model` under `indices`, rebuilt from the network
    /// on this device ([`OccupancyGrid::rebuild_in_box`]'s samples), confined to
    /// `scene_box` when the key gives one.
    pub fn rebuild_occupancy(
        &self,
        model: &Model,
        indices: &LevelIndices,
        scene_box: Option<u32>,
        samples_per_cell: usize,
        seed: u64,
    ) -> Result<OccupancyGrid> {
        match self {
            Device::Cpu { .. } => Ok(OccupancyGrid::rebuild_in_box(
                model.config.aabb_scale,
                scene_box,
                samples_per_cell,
                seed,
                log_density_at(&model.net, model.params(), indices, model.config.aabb_scale),
            )),
            #[cfg(feature = "gpu")]
            Device::Gpu(ctx) => {
                // The device samples every cell; cut to the box after (the same grid).
                let mut grid =
                    gpu::rebuild_occupancy_gpu(ctx, model, indices, samples_per_cell, seed)
                        .map_err(gpu_error)?;
                if let Some(b) = scene_box.filter(|&b| b < model.config.aabb_scale) {
                    grid.confine_to_box(b);
                }
                Ok(grid)
            }
        }
    }
}

/// The raw density output (log-density) of a model's field at ngp-space positions, on the
/// device that made it: what a mesh's lattice asks for, slab after slab.
pub type DensityFn<'a> = Box<dyn FnMut(&[[f32; 3]]) -> Result<Vec<f32>> + 'a>;

impl Device {
    /// `model`'s density field under `indices` on this device (the GPU uploads the weights
    /// once, here).
    pub fn density_field<'a>(
        &'a self,
        model: &'a Model,
        indices: &'a LevelIndices,
    ) -> Result<DensityFn<'a>> {
        match self {
            Device::Cpu { .. } => {
                let mut density =
                    log_density_at(&model.net, model.params(), indices, model.config.aabb_scale);
                Ok(Box::new(move |pos: &[[f32; 3]]| Ok(density(pos))))
            }
            #[cfg(feature = "gpu")]
            Device::Gpu(ctx) => {
                let mut probe = gpu::DensityProbe::new(ctx, model, indices).map_err(gpu_error)?;
                Ok(Box::new(move |pos: &[[f32; 3]]| {
                    probe.log_densities(ctx, pos).map_err(gpu_error)
                }))
            }
        }
    }
}

#[cfg(feature = "gpu")]
fn gpu_error(e: gpu::GpuError) -> Error {
    e.into()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn requests_parse_their_names_only() {
        for d in [DeviceRequest::Auto, DeviceRequest::Cpu, DeviceRequest::Gpu] {
            assert_eq!(d.name().parse::<DeviceRequest>().unwrap(), d);
        }
        let e = "cuda".parse::<DeviceRequest>().unwrap_err().to_string();
        assert!(e.contains("cuda") && e.contains("auto, cpu, gpu"), "{e}");
    }

    #[test]
    fn cpu_reports_itself() {
        let d = Device::open(DeviceRequest::Cpu).unwrap();
        let r = d.report();
        assert_eq!(r.kind, "cpu");
        assert!(matches!(d, Device::Cpu { .. }) && r.fallback.is_none());
        let json = serde_json::to_value(&r).unwrap();
        assert_eq!(json["kind"], "cpu");
        assert!(json.get("fallback").is_none());
    }
}
