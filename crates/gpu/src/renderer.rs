//! Whole images and the key holder's occupancy grid on the device (issue 10), composed from
//! the tested kernels.
//!
//! [`GpuRenderer::render`] gives what [`render_image`] gives (colour, depth, opacity and the
//! samples evaluated) for every camera [`Camera::ray`] models (pinhole, OpenCV distortion):
//! the rays are made on the device from the camera (`renderer.wgsl`, through `rays.wgsl`'s
//! camera and marching functions), marched in waves of `samples_per_wave` samples per live
//! ray through the scene's occupancy bitfield, every wave's samples through the grid and the
//! full network ([`GpuField`]), composited ([`CompositeKernel`]) and retired below the
//! transmittance threshold or outside the box, as the CPU does. The rays' state stays on the
//! device; one read of four counters (live rays, samples of the next wave) per wave comes
//! back, since the network kernels take their sample count from the host, and the pixels
//! once per tile. Pixels go in tiles of as many rays as a wave's samples fit the device's
//! storage bindings (the grid encoding, 4 bytes per feature a sample, is the largest buffer;
//! [`GpuRenderer::set_max_wave_samples`] bounds it further).
//!
//! [`rebuild_occupancy_gpu`] and [`GpuRenderer::rebuild_occupancy`] are
//! [`OccupancyGrid::rebuild`] on the device: the same cells in the same rounds, octants and
//! seeds, the points drawn bit for bit as [`OccupancyGrid::points_in_cell_octant`] draws them
//! ([`GpuOccupancy::encode_cell_points`]), log-densities from the field, max-splat and the
//! bitfield. Only the network's and `exp`'s rounding differ from the CPU.
//!
//! [`render_image`]: ngp::render::image::render_image

use super::field::{DensityScratch, GpuField};
use super::grid::GridShape;
use super::index::{PCG_WGSL, U64_WGSL};
use super::mlp::EncodedBatch;
use super::occupancy::GpuOccupancy;
use super::rays::{RAYS_WGSL, box_extent, gpu_cam, ray_params};
use super::render::{CompositeKernel, RayState, WaveSamples};
use super::{
    GpuContext, GpuError, GpuResult, auto_layout_pipelines, buffer_entry, check_binding,
    device_buffer,
};
use ngp::camera::Camera;
use ngp::encoding::LevelIndices;
use ngp::model::Model;
use ngp::occupancy::{N_CELLS, OccupancyGrid, REBUILD_OCTANTS};
use ngp::render::image::{RenderOptions, RenderedImage};
use ngp::render::march::Marcher;
use wgpu::util::DeviceExt;

const RENDERER_WGSL: &str = include_str!("renderer.wgsl");
const WORKGROUP: u32 = 64;
/// Most samples one wave holds by default (before the device's binding limit): 128 MiB of
/// grid encoding for the paper's 32 features, llvmpipe's whole binding.
const DEFAULT_WAVE_SAMPLES: u32 = 1 << 20;
/// Sample capacities are multiples of this (the encoding's leading dimension is the wave's
/// sample count rounded up to it).
const LD_GRANULE: u32 = 256;
/// Cells per submission of a rebuild: 32 MiB of encoding for 32 features.
const REBUILD_CHUNK: u32 = 1 << 18;
/// Waves of one tile at most: far past any real scene (every wave moves every live ray on by
/// at least one sample or one cell), so that a device fault cannot loop for ever.
const MAX_WAVES: u32 = 1 << 20;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct RenderParams {
    n_tile: u32,
    first_pixel: u32,
    width: u32,
    row_width: u32,
    samples_per_wave: u32,
    n_live: u32,
    min_transmittance: f32,
    _pad: u32,
}

/// The buffers of one tile's waves.
struct Waves {
    rays_per_tile: u32,
    samples_per_wave: u32,
    /// Samples a wave may hold (`rays_per_tile · samples_per_wave`, rounded up).
    capacity: u32,
    rays: wgpu::Buffer,
    live: wgpu::Buffer,
    live_next: wgpu::Buffer,
    counters: wgpu::Buffer,
    wave: wgpu::Buffer,
    pos: wgpu::Buffer,
    dir: wgpu::Buffer,
    dt: wgpu::Buffer,
    dist: wgpu::Buffer,
    raw: wgpu::Buffer,
    enc: wgpu::Buffer,
    state: RayState,
}

/// A model's weights on the device, with one scene (index functions and occupancy grid)
/// to render.
pub struct GpuRenderer<'c> {
    ctx: &'c GpuContext,
    field: GpuField,
    marcher: Marcher,
    aabb_scale: u32,
    composite: CompositeKernel,
    generate: wgpu::ComputePipeline,
    march: wgpu::ComputePipeline,
    retire: wgpu::ComputePipeline,
    /// The marching uniform (`RayParams`: box and stepping space).
    marching: wgpu::Buffer,
    /// The scene's occupancy bitfield (the CPU's bytes).
    bitfield: wgpu::Buffer,
    max_wave_samples: u32,
    waves: Option<Waves>,
}

fn input<T>(msg: String) -> GpuResult<T> {
    Err(GpuError::Input(msg))
}

/// Workgroups for `n` invocations, folded into y past the dimension limit.
fn groups(ctx: &GpuContext, n: u32) -> [u32; 2] {
    let max_dim = ctx.device.limits().max_compute_workgroups_per_dimension;
    let g = n.div_ceil(WORKGROUP).max(1);
    let gx = g.min(max_dim);
    [gx, g.div_ceil(gx)]
}

/// The device's largest storage binding.
fn max_binding(ctx: &GpuContext) -> u64 {
    let limits = ctx.device.limits();
    limits
        .max_storage_buffer_binding_size
        .min(limits.max_buffer_size)
}

fn check_grid(grid: &OccupancyGrid, marcher: &Marcher) -> GpuResult<()> {
    if grid.n_cascades as u32 != marcher.max_cascade + 1 {
        return input(format!(
            "render: a grid of {} cascades for a box of {}",
            grid.n_cascades,
            marcher.max_cascade + 1
        ));
    }
    Ok(())
}

fn upload_bitfield(ctx: &GpuContext, grid: &OccupancyGrid) -> GpuResult<wgpu::Buffer> {
    ctx.scoped("render bitfield", || {
        ctx.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("render bitfield"),
                contents: grid.bitfield(),
                usage: wgpu::BufferUsages::STORAGE,
            })
    })
}

impl<'c> GpuRenderer<'c> {
    /// Uploads `model`'s weights (once) and the scene `indices` + `grid`.
    pub fn new(
        ctx: &'c GpuContext,
        model: &Model,
        indices: &LevelIndices,
        grid: &OccupancyGrid,
    ) -> GpuResult<Self> {
        let marcher = model.marcher();
        let inv_extent = 1.0 / box_extent(&marcher)?;
        check_grid(grid, &marcher)?;
        let field = GpuField::new(ctx, &model.net.layout, model.params(), indices)?;
        let composite = CompositeKernel::new(ctx)?;
        let bitfield = upload_bitfield(ctx, grid)?;
        let params = ray_params(&marcher, inv_extent, 0, [0, 0], 0, 0);
        let (generate, march, retire, marching) = ctx.scoped("render kernels", || {
            let source = format!("{U64_WGSL}\n{PCG_WGSL}\n{RAYS_WGSL}\n{RENDERER_WGSL}");
            let [generate, march, retire] = auto_layout_pipelines(
                ctx,
                "renderer.wgsl",
                &source,
                ["render_gen_main", "render_march_main", "render_retire_main"],
            );
            (
                generate,
                march,
                retire,
                ctx.device
                    .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                        label: Some("render marching params"),
                        contents: bytemuck::bytes_of(&params),
                        usage: wgpu::BufferUsages::UNIFORM,
                    }),
            )
        })?;
        Ok(GpuRenderer {
            ctx,
            field,
            marcher,
            aabb_scale: model.config.aabb_scale,
            composite,
            generate,
            march,
            retire,
            marching,
            bitfield,
            max_wave_samples: DEFAULT_WAVE_SAMPLES,
            waves: None,
        })
    }

    /// Another scene of the same weights: `indices` and its `grid` (the cover's stored grid,
    /// or a key holder's rebuilt one).
    pub fn set_scene(&mut self, indices: &LevelIndices, grid: &OccupancyGrid) -> GpuResult<()> {
        check_grid(grid, &self.marcher)?;
        let bitfield = upload_bitfield(self.ctx, grid)?;
        self.field.set_index(self.ctx, indices)?;
        self.bitfield = bitfield;
        Ok(())
    }

    /// The key holder's scene: `indices` with an occupancy grid rebuilt from the field under
    /// them ([`OccupancyGrid::rebuild`] with `samples_per_cell` and `seed`, on the device),
    /// which renders from now on and is returned. After an error the scene is undefined
    /// until the next [`Self::set_scene`] or rebuild.
    pub fn rebuild_occupancy(
        &mut self,
        indices: &LevelIndices,
        samples_per_cell: usize,
        seed: u64,
    ) -> GpuResult<OccupancyGrid> {
        self.field.set_index(self.ctx, indices)?;
        let occ = rebuild_on_device(
            self.ctx,
            &self.field,
            &self.marcher,
            self.aabb_scale,
            samples_per_cell,
            seed,
        )?;
        self.bitfield = occ.bitfield.clone();
        occ.download(self.ctx)
    }

    /// Bounds the samples one wave holds (rounded down to a multiple of 256, at least 256),
    /// and so the rays per tile: `max / samples_per_wave`. The default, 2^20, is further
    /// bounded by the device's storage-binding limit.
    pub fn set_max_wave_samples(&mut self, max: u32) {
        self.max_wave_samples = (max / LD_GRANULE).max(1) * LD_GRANULE;
        self.waves = None;
    }

    /// Samples one wave may hold on this device.
    fn wave_capacity(&self) -> u32 {
        let width = self.field.layout().grid.config.n_output_dims() as u64;
        // The encoding (4·width bytes a sample) is the largest per-sample buffer.
        let fit = (max_binding(self.ctx) / (4 * width.max(4))).min(u32::MAX as u64) as u32;
        self.max_wave_samples.min(fit / LD_GRANULE * LD_GRANULE)
    }

    /// Tile buffers for `spw` samples per wave and images of `n_pixels`.
    fn prepare(&mut self, spw: u32, n_pixels: u32) -> GpuResult<()> {
        let cap = self.wave_capacity();
        if spw > cap {
            return input(format!(
                "render: {spw} samples per wave; a wave holds {cap} samples on this device"
            ));
        }
        let rays = (cap / spw).min(n_pixels).max(1);
        if let Some(w) = &self.waves
            && w.samples_per_wave == spw
            && w.rays_per_tile >= rays
            && w.rays_per_tile <= cap / spw
        {
            return Ok(());
        }
        // Drop the old buffers before making the new ones.
        self.waves = None;
        let ctx = self.ctx;
        let capacity = (rays * spw).div_ceil(LD_GRANULE) * LD_GRANULE;
        let width = self.field.layout().grid.config.n_output_dims() as u64;
        let (r, s) = (rays as u64, capacity as u64);
        check_binding(ctx, "render: encoding", 4 * width * s)?;
        check_binding(ctx, "render: network outputs", 16 * s)?;
        check_binding(ctx, "render: rays", 32 * r)?;
        let state = self.composite.state(ctx, rays)?;
        let waves = ctx.scoped("render buffers", || Waves {
            rays_per_tile: rays,
            samples_per_wave: spw,
            capacity,
            rays: device_buffer(ctx, "render rays", 32 * r),
            live: device_buffer(ctx, "render live rays", 4 * r),
            live_next: device_buffer(ctx, "render next live rays", 4 * r),
            counters: device_buffer(ctx, "render counters", 16),
            wave: device_buffer(ctx, "render wave", 8 * r),
            pos: device_buffer(ctx, "render positions", 12 * s),
            dir: device_buffer(ctx, "render directions", 12 * s),
            dt: device_buffer(ctx, "render dt", 4 * s),
            dist: device_buffer(ctx, "render distances", 4 * s),
            raw: device_buffer(ctx, "render network outputs", 16 * s),
            enc: device_buffer(ctx, "render encoding", 4 * width * s),
            state,
        })?;
        self.waves = Some(waves);
        Ok(())
    }

    /// Renders `cam`'s view of the scene: what [`render_image`] gives, on the device.
    ///
    /// [`render_image`]: ngp::render::image::render_image
    pub fn render(&mut self, cam: &Camera, opts: &RenderOptions) -> GpuResult<RenderedImage> {
        let n_pixels = cam.width.checked_mul(cam.height).ok_or_else(|| {
            GpuError::Input(format!(
                "render: {}×{} pixels, past 2^32",
                cam.width, cam.height
            ))
        })?;
        let spw = u32::try_from(opts.samples_per_wave)
            .ok()
            .filter(|&s| s > 0)
            .ok_or_else(|| {
                GpuError::Input(format!(
                    "render: {} samples per wave (1 to 2^32 − 1)",
                    opts.samples_per_wave
                ))
            })?;
        let n = n_pixels as usize;
        let mut out = RenderedImage {
            width: cam.width,
            height: cam.height,
            rgb: vec![0.0; 3 * n],
            depth: vec![0.0; n],
            opacity: vec![0.0; n],
            n_samples: 0,
            profile: Default::default(),
        };
        if n_pixels == 0 {
            return Ok(out);
        }
        self.prepare(spw, n_pixels)?;
        let camera = gpu_cam(cam);
        let cams = self.ctx.scoped("render camera", || {
            self.ctx
                .device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some("render camera"),
                    contents: bytemuck::bytes_of(&camera),
                    usage: wgpu::BufferUsages::STORAGE,
                })
        })?;
        let Some(w) = &self.waves else {
            return input("render: no tile buffers".into());
        };
        let mut first = 0u32;
        while first < n_pixels {
            let n_tile = w.rays_per_tile.min(n_pixels - first);
            let tile = Tile {
                cams: &cams,
                width: cam.width,
                first,
                n_tile,
                opts,
            };
            out.n_samples += self.render_tile(w, &tile, &mut out)?;
            first += n_tile;
        }
        Ok(out)
    }

    fn params(&self, tile: &Tile, spw: u32, n_live: u32, n: u32) -> ([u32; 2], wgpu::Buffer) {
        let g = groups(self.ctx, n);
        let params = RenderParams {
            n_tile: tile.n_tile,
            first_pixel: tile.first,
            width: tile.width,
            row_width: g[0] * WORKGROUP,
            samples_per_wave: spw,
            n_live,
            min_transmittance: tile.opts.min_transmittance,
            _pad: 0,
        };
        let buffer = self
            .ctx
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("render params"),
                contents: bytemuck::bytes_of(&params),
                usage: wgpu::BufferUsages::UNIFORM,
            });
        (g, buffer)
    }

    fn dispatch(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        pipeline: &wgpu::ComputePipeline,
        entries: &[wgpu::BindGroupEntry<'_>],
        [gx, gy]: [u32; 2],
    ) {
        let bg = self
            .ctx
            .device
            .create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("render"),
                layout: &pipeline.get_bind_group_layout(0),
                entries,
            });
        let mut pass = encoder.begin_compute_pass(&Default::default());
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, &bg, &[]);
        pass.dispatch_workgroups(gx, gy, 1);
    }

    /// Records one wave's marching of the live rays (at most `bound` of them; the list's
    /// length is on the device).
    fn encode_march(&self, encoder: &mut wgpu::CommandEncoder, w: &Waves, tile: &Tile, bound: u32) {
        let e = buffer_entry;
        encoder.clear_buffer(&w.counters, 0, Some(4));
        let (g, params) = self.params(tile, w.samples_per_wave, 0, bound);
        self.dispatch(
            encoder,
            &self.march,
            &[
                e(5, &self.bitfield),
                e(11, &self.marching),
                e(12, &w.rays),
                e(13, &w.live),
                e(15, &w.counters),
                e(16, &w.wave),
                e(17, &w.pos),
                e(18, &w.dir),
                e(19, &w.dt),
                e(20, &w.dist),
                e(22, &params),
            ],
            g,
        );
    }

    /// (samples of the wave marched last, live rays), read back.
    fn counters(&self, w: &Waves) -> GpuResult<(u32, u32)> {
        let c: Vec<u32> = self.ctx.read_buffer(&w.counters, 16)?;
        Ok((c[0], c[1]))
    }

    /// Records the network over the `n` samples of the wave marched last into `w.raw`.
    fn encode_network(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        w: &Waves,
        n: u32,
    ) -> GpuResult<()> {
        if n > w.capacity {
            return Err(GpuError::Device {
                what: "render",
                msg: format!("{n} samples in a wave of {}", w.capacity),
            });
        }
        let ctx = self.ctx;
        let layout = self.field.layout();
        let (g0, g1) = (4 * layout.grid_offset as u64, 4 * layout.n_params as u64);
        let ld = n
            .div_ceil(LD_GRANULE)
            .saturating_mul(LD_GRANULE)
            .min(w.capacity);
        let forward = self.field.grid().bind_forward(
            ctx,
            self.field.index(),
            w.pos.slice(..),
            self.field.params.slice(g0..g1),
            w.enc.slice(..),
            GridShape { n_samples: n, ld },
        )?;
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            forward.record(&mut pass);
        }
        let batch = EncodedBatch {
            params: &self.field.params,
            enc: &w.enc,
            ld,
            n,
        };
        self.field
            .mlp()
            .encode_forward(ctx, encoder, &batch, &w.dir, &w.raw, None)
    }

    /// Renders one tile into `out`; returns its samples.
    fn render_tile(&self, w: &Waves, tile: &Tile, out: &mut RenderedImage) -> GpuResult<u64> {
        let ctx = self.ctx;
        let e = buffer_entry;
        let spw = w.samples_per_wave;
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        ctx.scoped("render rays", || {
            encoder.clear_buffer(&w.counters, 0, None);
            encoder.clear_buffer(&w.wave, 0, None);
            encoder.clear_buffer(&w.state.acc, 0, None);
            let (g, params) = self.params(tile, spw, 0, tile.n_tile);
            self.dispatch(
                &mut encoder,
                &self.generate,
                &[
                    e(0, tile.cams),
                    e(11, &self.marching),
                    e(12, &w.rays),
                    e(13, &w.live),
                    e(15, &w.counters),
                    e(21, &w.state.trans),
                    e(22, &params),
                ],
                g,
            );
            self.encode_march(&mut encoder, w, tile, tile.n_tile);
            ctx.queue.submit([encoder.finish()]);
        })?;
        let (mut n_samples, mut n_live) = self.counters(w)?;
        let mut total = 0u64;
        let mut waves = 0u32;
        while n_live > 0 {
            waves += 1;
            if waves > MAX_WAVES {
                return Err(GpuError::Device {
                    what: "render",
                    msg: format!("{n_live} rays still live after {MAX_WAVES} waves"),
                });
            }
            total += n_samples as u64;
            let mut encoder = ctx.device.create_command_encoder(&Default::default());
            if n_samples > 0 {
                self.encode_network(&mut encoder, w, n_samples)?;
            }
            let samples = WaveSamples {
                wave: &w.wave,
                raw: &w.raw,
                dt: &w.dt,
                dist: &w.dist,
            };
            self.composite.encode_wave(
                ctx,
                &mut encoder,
                &w.state,
                &samples,
                tile.opts.min_transmittance,
            )?;
            ctx.scoped("render wave", || {
                encoder.clear_buffer(&w.counters, 4, Some(4));
                let (g, params) = self.params(tile, spw, n_live, n_live);
                self.dispatch(
                    &mut encoder,
                    &self.retire,
                    &[
                        e(12, &w.rays),
                        e(13, &w.live),
                        e(14, &w.live_next),
                        e(15, &w.counters),
                        e(16, &w.wave),
                        e(21, &w.state.trans),
                        e(22, &params),
                    ],
                    g,
                );
                encoder.copy_buffer_to_buffer(&w.live_next, 0, &w.live, 0, 4 * n_live as u64);
                self.encode_march(&mut encoder, w, tile, n_live);
                ctx.queue.submit([encoder.finish()]);
            })?;
            (n_samples, n_live) = self.counters(w)?;
        }
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        self.composite
            .encode_finish(ctx, &mut encoder, &w.state, tile.opts.background)?;
        ctx.scoped("render finish", || ctx.queue.submit([encoder.finish()]))?;
        let n = tile.n_tile as u64;
        let rgba: Vec<[f32; 4]> = ctx.read_buffer(&w.state.pixel_rgba, 16 * n)?;
        let depth: Vec<f32> = ctx.read_buffer(&w.state.pixel_depth, 4 * n)?;
        let first = tile.first as usize;
        for (k, (px, d)) in rgba.iter().zip(&depth).enumerate() {
            let i = first + k;
            out.rgb[3 * i..3 * i + 3].copy_from_slice(&px[..3]);
            out.opacity[i] = px[3];
            out.depth[i] = *d;
        }
        Ok(total)
    }
}

/// One tile of a render: pixels `first..first + n_tile` of an image `width` wide.
struct Tile<'a> {
    cams: &'a wgpu::Buffer,
    width: u32,
    first: u32,
    n_tile: u32,
    opts: &'a RenderOptions,
}

/// [`OccupancyGrid::rebuild`] of the scene `field` holds, on the device: every round's
/// points drawn there, their log-densities, the max-splat, and at the end the bitfield.
fn rebuild_on_device(
    ctx: &GpuContext,
    field: &GpuField,
    marcher: &Marcher,
    aabb_scale: u32,
    samples_per_cell: usize,
    seed: u64,
) -> GpuResult<GpuOccupancy> {
    let mut start = OccupancyGrid::new(aabb_scale);
    start.density.iter_mut().for_each(|d| *d = 0.0);
    let mut occ = GpuOccupancy::upload(ctx, &start, marcher)?;
    let total = u32::try_from(start.density.len())
        .map_err(|_| GpuError::Input("rebuild: more than 2^32 cells".into()))?;
    debug_assert_eq!(total as usize, N_CELLS * start.n_cascades);
    let width = field.layout().grid.config.n_output_dims() as u64;
    let fit = (max_binding(ctx) / (4 * width.max(4))).min(u32::MAX as u64) as u32;
    let chunk = REBUILD_CHUNK.min(fit).max(1);
    let mut scratch = DensityScratch::default();
    for round in 0..samples_per_cell {
        let octant = REBUILD_OCTANTS[round % 8];
        let round_seed = seed.wrapping_add(round as u64);
        let mut first = 0u32;
        while first < total {
            let n = chunk.min(total - first);
            let mut encoder = ctx.device.create_command_encoder(&Default::default());
            occ.encode_cell_points(ctx, &mut encoder, first, n, octant, round_seed)?;
            field.encode_density(ctx, &mut encoder, &occ.sample_pos, n, &mut scratch)?;
            let Some(log_density) = &scratch.out else {
                return input("rebuild: no density output".into());
            };
            occ.encode_splat_max(ctx, &mut encoder, log_density)?;
            ctx.scoped("rebuild round", || ctx.queue.submit([encoder.finish()]))?;
            first += n;
        }
    }
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    occ.encode_bitfield(ctx, &mut encoder)?;
    ctx.scoped("rebuild bitfield", || ctx.queue.submit([encoder.finish()]))?;
    Ok(occ)
}

/// How a key holder recovers a hidden scene's grid ([`rebuild_occupancy`] on the CPU), on
/// the device: [`OccupancyGrid::rebuild`] of `model`'s field under `indices` with
/// `samples_per_cell` points per cell and `seed`. Uploads the weights; a
/// [`GpuRenderer`] that holds them already rebuilds with
/// [`GpuRenderer::rebuild_occupancy`].
///
/// [`rebuild_occupancy`]: ngp::render::image::rebuild_occupancy
pub fn rebuild_occupancy_gpu(
    ctx: &GpuContext,
    model: &Model,
    indices: &LevelIndices,
    samples_per_cell: usize,
    seed: u64,
) -> GpuResult<OccupancyGrid> {
    let field = GpuField::new(ctx, &model.net.layout, model.params(), indices)?;
    rebuild_on_device(
        ctx,
        &field,
        &model.marcher(),
        model.config.aabb_scale,
        samples_per_cell,
        seed,
    )?
    .download(ctx)
}
