//! instant-ngp model files: `.ingp` (gzip-framed msgpack) and `.msgpack` (raw msgpack), laid
//! out as `Testbed::save_snapshot` writes them (instant-ngp-spec.md §4): the whole network
//! config plus a `snapshot` object holding fp16 EMA weights, the fp16 occupancy grid and the
//! testbed state. Reading accepts our files and the reference's (16×2 or 8×4 hash grids, any
//! aabb_scale, fp16 or fp32 weights, with or without optimizer state) and refuses everything
//! the engine cannot run, saying what the file holds.

mod config;
mod inspect;
pub mod msgpack;
mod read;
pub(crate) mod write;

pub use inspect::{SnapshotInfo, inspect};

use crate::error::{Error, Result};
use crate::network::ModelConfig;
use std::path::Path;

/// Cells per axis of one occupancy-grid cascade (`NERF_GRIDSIZE`).
pub const DENSITY_GRID_SIZE: usize = 128;
/// Cells of one cascade.
pub const DENSITY_GRID_CELLS: usize = DENSITY_GRID_SIZE * DENSITY_GRID_SIZE * DENSITY_GRID_SIZE;
/// `NERF_CASCADES`: the largest aabb_scale instant-ngp accepts is 2^(8−1).
pub const MAX_AABB_SCALE: u32 = 128;
/// `SNAPSHOT_FORMAT_VERSION`.
pub const SNAPSHOT_VERSION: u64 = 1;

/// Number of occupancy cascades for an aabb scale: `log2(aabb_scale) + 1` (the reference's
/// `max_cascade` is the smallest c with 2^c ≥ aabb_scale).
pub fn n_cascades(aabb_scale: u32) -> usize {
    let mut c = 0;
    while (1u64 << c) < aabb_scale as u64 {
        c += 1;
    }
    c + 1
}

/// Interleaves the low 10 bits of x, y, z into a Morton code, x in bit 0 (`morton3D`).
pub fn morton3d(x: u32, y: u32, z: u32) -> u32 {
    spread3(x) | (spread3(y) << 1) | (spread3(z) << 2)
}

/// Inverse of [`morton3d`].
pub fn morton3d_inverse(m: u32) -> (u32, u32, u32) {
    (compact3(m), compact3(m >> 1), compact3(m >> 2))
}

fn spread3(v: u32) -> u32 {
    let mut x = v & 0x3ff;
    x = (x | (x << 16)) & 0x0300_00ff;
    x = (x | (x << 8)) & 0x0300_f00f;
    x = (x | (x << 4)) & 0x030c_30c3;
    (x | (x << 2)) & 0x0924_9249
}

fn compact3(v: u32) -> u32 {
    let mut x = v & 0x0924_9249;
    x = (x | (x >> 2)) & 0x030c_30c3;
    x = (x | (x >> 4)) & 0x0300_f00f;
    x = (x | (x >> 8)) & 0x0300_00ff;
    (x | (x >> 16)) & 0x3ff
}

/// An axis-aligned box as the reference's `BoundingBox` (default: empty, min = +∞, max = −∞).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    pub min: [f32; 3],
    pub max: [f32; 3],
}

impl Aabb {
    pub const EMPTY: Aabb = Aabb {
        min: [f32::INFINITY; 3],
        max: [f32::NEG_INFINITY; 3],
    };

    /// `[0.5 − s/2, 0.5 + s/2]³` with `s = min(aabb_scale, 128)`.
    pub fn for_scale(aabb_scale: u32) -> Self {
        let h = 0.5 * aabb_scale.min(MAX_AABB_SCALE) as f32;
        Aabb {
            min: [0.5 - h; 3],
            max: [0.5 + h; 3],
        }
    }
}

pub const IDENTITY3: [[f32; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

/// A camera lens model as `json_binding.h` stores it (a perspective lens is stored as null).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Lens {
    Perspective,
    OpenCv { k1: f32, k2: f32, p1: f32, p2: f32 },
    OpenCvFisheye { k1: f32, k2: f32, k3: f32, k4: f32 },
    FTheta { p: [f32; 5], w: f32, h: f32 },
    LatLong,
    Equirectangular,
    Orthographic,
}

/// One training image's metadata and pose, as under `nerf.dataset`.
#[derive(Clone, Debug, PartialEq)]
pub struct DatasetImage {
    /// Focal length in pixels (x, y).
    pub focal_length: [f32; 2],
    pub lens: Lens,
    /// In units of the image size; (0.5, 0.5) is the centre.
    pub principal_point: [f32; 2],
    pub rolling_shutter: [f32; 4],
    /// Width, height in pixels.
    pub resolution: [i32; 2],
    /// Camera-to-world in ngp coordinates (after `nerf_matrix_to_ngp`), 3 rows × 4 columns.
    pub xform_start: [[f32; 4]; 3],
    pub xform_end: [[f32; 4]; 3],
}

impl DatasetImage {
    /// A pinhole image with the principal point at the centre and a fixed pose.
    pub fn new(resolution: [i32; 2], focal_length: [f32; 2], xform: [[f32; 4]; 3]) -> Self {
        DatasetImage {
            focal_length,
            lens: Lens::Perspective,
            principal_point: [0.5, 0.5],
            rolling_shutter: [0.0; 4],
            resolution,
            xform_start: xform,
            xform_end: xform,
        }
    }
}

/// What the reference stores under `snapshot.nerf.dataset` (`json_binding.h`, NerfDataset).
#[derive(Clone, Debug, PartialEq)]
pub struct SnapshotDataset {
    /// Image paths as in transforms.json (`file_path`), one per image.
    pub paths: Vec<String>,
    /// One per image; `n_images` is its length.
    pub images: Vec<DatasetImage>,
    pub render_aabb: Aabb,
    pub render_aabb_to_local: [[f32; 3]; 3],
    pub up: [f32; 3],
    pub offset: [f32; 3],
    pub envmap_resolution: [i32; 2],
    pub scale: f32,
    pub aabb_scale: i32,
    pub from_mitsuba: bool,
    pub is_hdr: bool,
    pub wants_importance_sampling: bool,
    pub n_extra_learnable_dims: u32,
}

impl SnapshotDataset {
    /// A NeRF-synthetic-like dataset with the loader's defaults (scale 0.33, offset 0.5,
    /// up +y, empty render aabb).
    pub fn new(paths: Vec<String>, images: Vec<DatasetImage>, aabb_scale: u32) -> Self {
        SnapshotDataset {
            paths,
            images,
            render_aabb: Aabb::EMPTY,
            render_aabb_to_local: IDENTITY3,
            up: [0.0, 1.0, 0.0],
            offset: [0.5, 0.5, 0.5],
            envmap_resolution: [0, 0],
            scale: 0.33,
            aabb_scale: aabb_scale as i32,
            from_mitsuba: false,
            is_hdr: false,
            wants_importance_sampling: true,
            n_extra_learnable_dims: 0,
        }
    }
}

/// The viewer camera (`snapshot.camera`).
#[derive(Clone, Debug, PartialEq)]
pub struct SnapshotCamera {
    /// Camera-to-world, 3 rows × 4 columns.
    pub matrix: [[f32; 4]; 3],
    pub fov_axis: u32,
    pub relative_focal_length: [f32; 2],
    pub screen_center: [f32; 2],
    pub zoom: f32,
    pub scale: f32,
    pub aperture_size: f32,
    pub autofocus: bool,
    pub autofocus_target: [f32; 3],
    pub autofocus_depth: f32,
}

impl Default for SnapshotCamera {
    /// `Testbed::reset_camera` for NeRF: default camera pulled back by scale 1.5 along its
    /// view direction, fov 50.625° on the y axis.
    fn default() -> Self {
        let fov = 50.625f32;
        let focal = 0.5f32 / (0.5f32 * fov * std::f32::consts::PI / 180.0).tan();
        SnapshotCamera {
            matrix: [
                [1.0, 0.0, 0.0, 0.5],
                [0.0, -1.0, 0.0, 0.5],
                [0.0, 0.0, -1.0, 2.0],
            ],
            fov_axis: 1,
            relative_focal_length: [focal, focal],
            screen_center: [0.5, 0.5],
            zoom: 1.0,
            scale: 1.5,
            aperture_size: 0.0,
            autofocus: false,
            autofocus_target: [0.5, 0.5, 0.5],
            autofocus_depth: 0.0,
        }
    }
}

/// Scene-level testbed state stored beside the camera.
#[derive(Clone, Debug, PartialEq)]
pub struct SnapshotView {
    pub aabb: Aabb,
    pub bounding_radius: f32,
    pub render_aabb: Aabb,
    pub render_aabb_to_local: [[f32; 3]; 3],
    pub up_dir: [f32; 3],
    pub sun_dir: [f32; 3],
    pub exposure: f32,
    pub background_color: [f32; 4],
}

impl SnapshotView {
    /// What `load_nerf_post` and the testbed defaults leave for a scene of this aabb scale.
    pub fn for_scale(aabb_scale: u32) -> Self {
        let s = 1.0f32 / 3.0f32.sqrt();
        SnapshotView {
            aabb: Aabb::for_scale(aabb_scale),
            bounding_radius: 1.0,
            render_aabb: Aabb::for_scale(aabb_scale),
            render_aabb_to_local: IDENTITY3,
            up_dir: [0.0, 1.0, 0.0],
            sun_dir: [s, s, s],
            exposure: 0.0,
            background_color: [0.0, 0.0, 0.0, 1.0],
        }
    }
}

/// Parts of a file we read that the engine does not interpret, written back unchanged so that
/// re-saving a reference file keeps them. `None`: write what a fresh reference run leaves.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Preserved {
    /// The file's top-level config (without `snapshot`), used when it describes `config`.
    pub network_config: Option<rmpv::Value>,
    /// `snapshot.optimizer` (only present when saved with optimizer state).
    pub optimizer: Option<rmpv::Value>,
    pub cam_pos_offset: Option<rmpv::Value>,
    pub cam_rot_offset: Option<rmpv::Value>,
    pub extra_dims_opt: Option<rmpv::Value>,
    /// `snapshot.stegongp_run_state`: a training checkpoint's run state beside the
    /// optimizer's (`train --save-every`); never in a published model.
    pub run_state: Option<rmpv::Value>,
}

/// A whole model file.
#[derive(Clone, Debug, PartialEq)]
pub struct Snapshot {
    pub config: ModelConfig,
    /// EMA (inference) parameters in NerfLayout order; written as fp16.
    pub params: Vec<f32>,
    /// 128³ values per cascade, Morton order within a cascade, −1 = culled; written as fp16.
    /// Empty means "never populated", which the reference also accepts.
    pub density_grid: Vec<f32>,
    pub training_step: u32,
    pub loss: f32,
    pub dataset: Option<SnapshotDataset>,
    pub rays_per_batch: u32,
    pub measured_batch_size: u32,
    pub measured_batch_size_before_compaction: u32,
    pub camera: SnapshotCamera,
    pub view: SnapshotView,
    pub preserved: Preserved,
    /// Written at full precision: `params_type` "float" (which instant-ngp also reads) and
    /// the density grid a second time as f32 under `stegongp_density_grid_float`, so that a
    /// model read back renders to the bit what the process that trained it rendered. For an
    /// experiment's models that other processes score (`experiment --plan`); a published
    /// model is fp16 like the reference's.
    pub exact: bool,
}

impl Snapshot {
    /// A snapshot with the values a reference training run leaves besides the model itself
    /// (batch counters at their start values: 4096 rays, nothing measured).
    pub fn new(config: ModelConfig, params: Vec<f32>, density_grid: Vec<f32>) -> Self {
        Snapshot {
            config,
            params,
            density_grid,
            training_step: 0,
            loss: 0.0,
            dataset: None,
            rays_per_batch: 1 << 12,
            measured_batch_size: 0,
            measured_batch_size_before_compaction: 0,
            camera: SnapshotCamera::default(),
            view: SnapshotView::for_scale(config.aabb_scale),
            preserved: Preserved::default(),
            exact: false,
        }
    }

    /// Whether the file this came from held optimizer state.
    pub fn has_optimizer_state(&self) -> bool {
        self.preserved.optimizer.is_some()
    }
}

/// Container chosen by the file extension, as `save_snapshot` does.
fn gzip_for_path(path: &Path) -> Result<bool> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase());
    match ext.as_deref() {
        Some("ingp") => Ok(true),
        Some("msgpack") => Ok(false),
        _ => Err(Error::format(
            path,
            "model files must end in .ingp (gzip-compressed) or .msgpack (raw)",
        )),
    }
}

/// The file's bytes: msgpack, gzip-framed (zlib's header: no name, mtime 0, OS unix) or not.
pub fn to_bytes(snap: &Snapshot, gzip: bool) -> Result<Vec<u8>> {
    let raw = write::to_msgpack(snap)?;
    if !gzip {
        return Ok(raw);
    }
    gzip_bytes(&raw).map_err(|e| Error::Other(format!("gzip compression failed: {e}")))
}

fn gzip_bytes(raw: &[u8]) -> std::io::Result<Vec<u8>> {
    use std::io::Write;
    let mut enc = flate2::GzBuilder::new().mtime(0).operating_system(3).write(
        Vec::with_capacity(raw.len() / 2),
        flate2::Compression::default(),
    );
    enc.write_all(raw)?;
    enc.finish()
}

/// Writes `snap` to `path` (format by extension), atomically.
pub fn save(path: &Path, snap: &Snapshot) -> Result<()> {
    let gzip = gzip_for_path(path)?;
    let bytes = to_bytes(snap, gzip).map_err(|e| match e {
        Error::Other(m) | Error::Config(m) => Error::format(path, m),
        e => e,
    })?;
    crate::util::write_atomic(path, &bytes)
}

/// Reads a model file; gzip or zlib framing is detected from the content, like zstr does.
pub fn load(path: &Path) -> Result<Snapshot> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    from_bytes(&bytes).map_err(|m| Error::format(path, m))
}

/// Parses a model file's bytes; the error says which field is wrong.
pub fn from_bytes(bytes: &[u8]) -> std::result::Result<Snapshot, String> {
    let (raw, _) = read::unframe(bytes)?;
    read::from_msgpack(&raw)
}

#[cfg(test)]
mod tests;
