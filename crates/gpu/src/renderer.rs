//! Whole images and the key holder's occupancy grid on the device (issue 10), composed from
//! the tested kernels.
//!
//! [`GpuRenderer::render`] gives what [`render_image`] gives (colour, depth, opacity and the
//! samples evaluated) for every camera [`Camera::ray`] models (pinhole, OpenCV distortion):
//! the rays are made on the device from the camera (`renderer.wgsl`, through `rays.wgsl`'s
//! camera and marching functions), marched in waves of `samples_per_wave` samples per live
//! ray through the scene's occupancy bitfield, every wave's samples through the grid and the
//! full network ([`GpuField`]), composited ([`CompositeKernel`]) and retired below the
//! transmittance threshold or outside the box, as the CPU does. The rays' state and every
//! count stay on the device (the network takes its sample count from a [`DeviceCount`]), so
//! a submission records a batch of waves (4, then twice as many each time up to 32) and the
//! host reads the counters once after it, to see whether a ray is still live: a few waits a
//! tile where there was one a wave ([`GpuRenderer::last_waits`]), the next batch recorded
//! while the device runs the last; and the pixels once per tile. Pixels go in tiles of as
//! many rays as a wave's samples fit the device's storage bindings (the grid encoding, 4
//! bytes per feature a sample, is the largest buffer; [`GpuRenderer::set_max_wave_samples`]
//! bounds it further).
//!
//! [`rebuild_occupancy_gpu`] and [`GpuRenderer::rebuild_occupancy`] are
//! [`OccupancyGrid::rebuild`] on the device: the same cells in the same rounds, octants and
//! seeds, the points drawn bit for bit as [`OccupancyGrid::points_in_cell_octant`] draws them
//! ([`GpuOccupancy::encode_cell_points`]), log-densities from the field, max-splat and the
//! bitfield. Only the network's and `exp`'s rounding differ from the CPU.
//!
//! [`render_image`]: ngp::render::image::render_image

use super::count::{CountKernel, DeviceCount};
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
use ngp::occupancy::{N_CELLS, OccupancyGrid, REBUILD_OCTANTS, RefineReport};
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
/// Waves the first submission of a tile records; each later one records twice as many, up
/// to [`MAX_BATCH_WAVES`]. A wave recorded after the last ray retired costs its ray passes
/// over the tile and dispatches nothing else.
const FIRST_BATCH_WAVES: u32 = 4;
const MAX_BATCH_WAVES: u32 = 32;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct RenderParams {
    n_tile: u32,
    first_pixel: u32,
    width: u32,
    row_width: u32,
    samples_per_wave: u32,
    min_transmittance: f32,
    _pad: [u32; 2],
}

/// The buffers of one tile's waves.
struct Waves {
    rays_per_tile: u32,
    samples_per_wave: u32,
    /// Samples a wave may hold (`rays_per_tile · samples_per_wave`, rounded up).
    capacity: u32,
    rays: wgpu::Buffer,
    /// The live-ray lists: a wave marches one and its retire pass writes the other.
    live: [wgpu::Buffer; 2],
    /// `renderer.wgsl`'s `rcount`: the wave's samples, live rays, samples since the last
    /// read, rays appended to the next list.
    counters: wgpu::Buffer,
    /// The wave's sample count (`counters[0]`) for the network's passes.
    samples: DeviceCount,
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
    next: wgpu::ComputePipeline,
    counter: CountKernel,
    /// The marching uniform (`RayParams`: box and stepping space).
    marching: wgpu::Buffer,
    /// The scene's occupancy bitfield (the CPU's bytes).
    bitfield: wgpu::Buffer,
    max_wave_samples: u32,
    waves: Option<Waves>,
    last: std::cell::Cell<RenderWaits>,
}

/// How the last [`GpuRenderer::render`] went between host and device.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RenderWaits {
    /// Tiles of the image.
    pub tiles: u32,
    /// Waves recorded (those after a tile's last ray retired included).
    pub waves: u32,
    /// Times the host waited for the device: a read of the counters after each batch of
    /// waves, and the pixels once a tile.
    pub waits: u32,
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
        let counter = CountKernel::new(ctx)?;
        let (generate, march, retire, next, marching) = ctx.scoped("render kernels", || {
            let source = format!("{U64_WGSL}\n{PCG_WGSL}\n{RAYS_WGSL}\n{RENDERER_WGSL}");
            let [generate, march, retire, next] = auto_layout_pipelines(
                ctx,
                "renderer.wgsl",
                &source,
                [
                    "render_gen_main",
                    "render_march_main",
                    "render_retire_main",
                    "render_next_main",
                ],
            );
            (
                generate,
                march,
                retire,
                next,
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
            next,
            counter,
            marching,
            bitfield,
            max_wave_samples: DEFAULT_WAVE_SAMPLES,
            waves: None,
            last: Default::default(),
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
        let counters = device_buffer(ctx, "render counters", 16);
        let grid_slot = self.field.grid().count_slot(ctx, capacity)?;
        let [tiles, ..] = self.field.mlp().count_slots(ctx, capacity)?;
        let samples = DeviceCount::new(
            ctx,
            &self.counter,
            &counters,
            0,
            0,
            capacity,
            &[grid_slot, tiles],
        )?;
        let waves = ctx.scoped("render buffers", || Waves {
            rays_per_tile: rays,
            samples_per_wave: spw,
            capacity,
            rays: device_buffer(ctx, "render rays", 32 * r),
            live: [
                device_buffer(ctx, "render live rays", 4 * r),
                device_buffer(ctx, "render next live rays", 4 * r),
            ],
            counters,
            samples,
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

    /// Tiles, waves and host waits of the last [`Self::render`].
    pub fn last_waits(&self) -> RenderWaits {
        self.last.get()
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
        self.last.set(RenderWaits::default());
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

    /// A tile's uniform and its passes' workgroups: one invocation per ray of the tile (the
    /// passes over live rays read the list's length on the device).
    fn params(&self, tile: &Tile, spw: u32) -> ([u32; 2], wgpu::Buffer) {
        let g = groups(self.ctx, tile.n_tile);
        let params = RenderParams {
            n_tile: tile.n_tile,
            first_pixel: tile.first,
            width: tile.width,
            row_width: g[0] * WORKGROUP,
            samples_per_wave: spw,
            min_transmittance: tile.opts.min_transmittance,
            _pad: [0; 2],
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

    /// Records one wave's marching of the rays in list `live` (its length is on the device).
    fn encode_march(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        w: &Waves,
        live: &wgpu::Buffer,
        (g, params): &([u32; 2], wgpu::Buffer),
    ) {
        let e = buffer_entry;
        self.dispatch(
            encoder,
            &self.march,
            &[
                e(5, &self.bitfield),
                e(11, &self.marching),
                e(12, &w.rays),
                e(13, live),
                e(15, &w.counters),
                e(16, &w.wave),
                e(17, &w.pos),
                e(18, &w.dir),
                e(19, &w.dt),
                e(20, &w.dist),
                e(22, params),
            ],
            *g,
        );
    }

    /// The grid's forward over a wave's samples, bound once for a tile (the scene's index
    /// can change between renders) and dispatched with the wave's count.
    fn bind_grid(&self, w: &Waves) -> GpuResult<super::grid::GridDispatch> {
        self.field.grid().bind_forward(
            self.ctx,
            self.field.index(),
            w.pos.slice(..),
            self.field.params.slice(self.field.grid_bytes()),
            w.enc.slice(..),
            GridShape {
                n_samples: w.capacity,
                ld: w.capacity,
            },
        )
    }

    /// Records one wave: the network over the samples marched last (as many as the device
    /// counted), compositing, retiring the rays of list `live` into the other list, and
    /// marching that one.
    fn encode_wave(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        w: &Waves,
        grid: &super::grid::GridDispatch,
        tile: &Tile,
        live: usize,
        params: &([u32; 2], wgpu::Buffer),
    ) -> GpuResult<()> {
        let ctx = self.ctx;
        let e = buffer_entry;
        w.samples.encode(encoder);
        grid.record_counted(encoder, &w.samples)?;
        let batch = EncodedBatch {
            params: &self.field.params,
            enc: &w.enc,
            ld: w.capacity,
            n: w.capacity,
        };
        self.field.mlp().encode_forward_slice(
            ctx,
            encoder,
            &batch,
            w.dir.slice(..),
            &w.raw,
            None,
            Some(&w.samples),
        )?;
        let samples = WaveSamples {
            wave: &w.wave,
            raw: &w.raw,
            dt: &w.dt,
            dist: &w.dist,
        };
        self.composite.encode_wave(
            ctx,
            encoder,
            &w.state,
            &samples,
            tile.opts.min_transmittance,
        )?;
        let (current, next) = (&w.live[live], &w.live[1 - live]);
        ctx.scoped("render wave", || {
            self.dispatch(
                encoder,
                &self.retire,
                &[
                    e(12, &w.rays),
                    e(13, current),
                    e(14, next),
                    e(15, &w.counters),
                    e(16, &w.wave),
                    e(21, &w.state.trans),
                    e(22, &params.1),
                ],
                params.0,
            );
            self.dispatch(encoder, &self.next, &[e(15, &w.counters)], [1, 1]);
            self.encode_march(encoder, w, next, params);
        })
    }

    fn count(&self, f: impl FnOnce(&mut RenderWaits)) {
        let mut l = self.last.get();
        f(&mut l);
        self.last.set(l);
    }

    /// Renders one tile into `out`; returns its samples.
    fn render_tile(&self, w: &Waves, tile: &Tile, out: &mut RenderedImage) -> GpuResult<u64> {
        let ctx = self.ctx;
        let e = buffer_entry;
        let params = self.params(tile, w.samples_per_wave);
        let grid = self.bind_grid(w)?;
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        ctx.scoped("render rays", || {
            encoder.clear_buffer(&w.counters, 0, None);
            encoder.clear_buffer(&w.wave, 0, None);
            encoder.clear_buffer(&w.state.acc, 0, None);
            self.dispatch(
                &mut encoder,
                &self.generate,
                &[
                    e(0, tile.cams),
                    e(11, &self.marching),
                    e(12, &w.rays),
                    e(13, &w.live[0]),
                    e(15, &w.counters),
                    e(21, &w.state.trans),
                    e(22, &params.1),
                ],
                params.0,
            );
            self.encode_march(&mut encoder, w, &w.live[0], &params);
        })?;
        let mut total = 0u64;
        let mut waves = 0u32;
        // The list the next wave marches (the lists swap roles every wave).
        let mut live = 0;
        let mut record = |encoder: &mut wgpu::CommandEncoder, n: u32| -> GpuResult<()> {
            for _ in 0..n {
                self.encode_wave(encoder, w, &grid, tile, live, &params)?;
                live = 1 - live;
            }
            Ok(())
        };
        let mut batch = FIRST_BATCH_WAVES;
        record(&mut encoder, batch)?;
        loop {
            ctx.scoped("render waves", || ctx.queue.submit([encoder.finish()]))?;
            waves += batch;
            // The next batch is recorded while the device runs this one, and submitted only
            // if a ray is still live.
            let next_batch = (2 * batch).min(MAX_BATCH_WAVES);
            let mut next = ctx.device.create_command_encoder(&Default::default());
            next.clear_buffer(&w.counters, 8, Some(4));
            record(&mut next, next_batch)?;
            // [samples of the wave marched last, live rays, samples since the last read, _]
            let c: Vec<u32> = ctx.read_buffer(&w.counters, 16)?;
            self.count(|l| {
                l.waves += batch;
                l.waits += 1;
            });
            total += u64::from(c[2]);
            if c[1] == 0 {
                break;
            }
            if waves >= MAX_WAVES {
                return Err(GpuError::Device {
                    what: "render",
                    msg: format!("{} rays still live after {waves} waves", c[1]),
                });
            }
            (encoder, batch) = (next, next_batch);
        }
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        self.composite
            .encode_finish(ctx, &mut encoder, &w.state, tile.opts.background)?;
        ctx.scoped("render finish", || ctx.queue.submit([encoder.finish()]))?;
        let (rgba, depth) = self.composite.read(ctx, &w.state, tile.n_tile)?;
        self.count(|l| {
            l.tiles += 1;
            l.waits += 1;
        });
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

/// How a key holder recovers a hidden scene's grid (on the CPU, [`OccupancyGrid::rebuild`]
/// of [`log_density_at`]), on the device: [`OccupancyGrid::rebuild`] of `model`'s field
/// under `indices` with `samples_per_cell` points per cell and `seed`. Uploads the weights;
/// a [`GpuRenderer`] that holds them already rebuilds with
/// [`GpuRenderer::rebuild_occupancy`].
///
/// [`log_density_at`]: ngp::render::march::log_density_at
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

/// [`OccupancyGrid::refine_near_occupied`] of a key holder's rebuilt `grid` with the
/// densities of `model`'s field under `indices` evaluated on the device: the host picks the
/// cells near occupied ones and draws their points as the CPU does, the device evaluates
/// them (a few per cent of the cells, so the points travel to the device).
pub fn refine_occupancy_gpu(
    ctx: &GpuContext,
    model: &Model,
    indices: &LevelIndices,
    grid: &mut OccupancyGrid,
    rounds: usize,
    first_round: usize,
    seed: u64,
) -> GpuResult<RefineReport> {
    let field = GpuField::new(ctx, &model.net.layout, model.params(), indices)?;
    let marcher = model.marcher();
    let mut scratch = DensityScratch::default();
    // One staging buffer for the points of every round of every pass.
    let points = ctx.scoped("refine positions", || {
        device_buffer(ctx, "refine positions", 12 * u64::from(REBUILD_CHUNK))
    })?;
    let mut failed = None;
    let report = grid.refine_near_occupied(rounds, first_round, seed, |pos| {
        if failed.is_none() {
            match densities_on_device(ctx, &field, &marcher, pos, &points, &mut scratch) {
                Ok(d) => return d,
                Err(e) => failed = Some(e),
            }
        }
        vec![f32::NEG_INFINITY; pos.len()]
    });
    match failed {
        Some(e) => Err(e),
        None => Ok(report),
    }
}

/// A model's density field on the device under one index, asked for many batches of
/// positions (a mesh's lattice, slab after slab) with the weights uploaded once.
pub struct DensityProbe {
    field: GpuField,
    marcher: Marcher,
    points: wgpu::Buffer,
    scratch: DensityScratch,
}

impl DensityProbe {
    pub fn new(ctx: &GpuContext, model: &Model, indices: &LevelIndices) -> GpuResult<Self> {
        let field = GpuField::new(ctx, &model.net.layout, model.params(), indices)?;
        let points = ctx.scoped("probe positions", || {
            device_buffer(ctx, "probe positions", 12 * u64::from(REBUILD_CHUNK))
        })?;
        Ok(DensityProbe {
            field,
            marcher: model.marcher(),
            points,
            scratch: DensityScratch::default(),
        })
    }

    /// The raw density output (log-density) at ngp-space `positions`.
    pub fn log_densities(
        &mut self,
        ctx: &GpuContext,
        positions: &[[f32; 3]],
    ) -> GpuResult<Vec<f32>> {
        densities_on_device(
            ctx,
            &self.field,
            &self.marcher,
            positions,
            &self.points,
            &mut self.scratch,
        )
    }
}

/// Log-densities of `field` at ngp-space `positions`, in chunks of [`REBUILD_CHUNK`] warped
/// into `buf`.
fn densities_on_device(
    ctx: &GpuContext,
    field: &GpuField,
    marcher: &Marcher,
    positions: &[[f32; 3]],
    buf: &wgpu::Buffer,
    scratch: &mut DensityScratch,
) -> GpuResult<Vec<f32>> {
    let mut out = Vec::with_capacity(positions.len());
    let mut warped = Vec::new();
    for part in positions.chunks(REBUILD_CHUNK as usize) {
        warped.clear();
        warped.extend(part.iter().flat_map(|&p| marcher.warp(p)));
        ctx.queue
            .write_buffer(buf, 0, bytemuck::cast_slice(&warped));
        let n = part.len() as u32;
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        field.encode_density(ctx, &mut encoder, buf, n, scratch)?;
        ctx.scoped("refine densities", || ctx.queue.submit([encoder.finish()]))?;
        let Some(log_density) = &scratch.out else {
            return input("refine: no density output".into());
        };
        out.extend(ctx.read_buffer::<f32>(log_density, 4 * u64::from(n))?);
    }
    Ok(out)
}
