//! Training rays on the device (`rays.wgsl`): what comes before the network in a training
//! step. Ray generation draws ray i of a batch exactly as the CPU trainer's `train_rays`
//! does (image `i·n_images/n_rays`, pixel and random background from `Pcg32::new(seed, i)`,
//! bit-identical), the camera ray through the pixel's centre (pinhole, OpenCV distortion
//! inverted by the CPU's Newton iteration), the target pixel on that background
//! (`Image::target_on`, from the training images uploaded once: RGBA8 sRGB as stored, or
//! f16 linear premultiplied for downscaled images) and where marching starts. Marching then
//! follows [`Marcher::march`] through the device's occupancy bitfield ([`GpuOccupancy`]'s
//! layout) and writes the samples compactly for the loss kernel: per ray one [`GpuRay`]
//! (`start`, `n`, background, target), per sample the warped position, dt and distance.
//!
//! Compaction: each ray counts its samples, reserves them with one atomic add on a batch
//! counter, then marches again writing them (instant-ngp's scheme: no per-ray scratch of
//! `MAX_SAMPLES_PER_RAY` slots, no scan pass). A ray whose reservation ends past the batch's
//! sample budget gets `n = 0`, and so does every ray after it in counter order, so the
//! samples in use are exactly `0..used` ([`RayBatch::counters`]`[1]`). Where the budget
//! binds, which rays fit depends on the order the device runs them; each ray's samples do
//! not. A ray with no samples (it misses the box, crosses only empty cells, or is past the
//! budget) carries its background as its target, so the loss kernel gives it loss 0 and no
//! gradient, as the CPU, which drops such rays, does.
//!
//! [`Marcher::march`]: ngp::render::march::Marcher::march
//! [`GpuOccupancy`]: super::GpuOccupancy

use super::index::{PCG_WGSL, U64_WGSL};
use super::loss::GpuRay;
use super::{GpuContext, GpuError, GpuResult, auto_layout_pipelines, buffer_entry, device_buffer};
use ngp::camera::Camera;
use ngp::data::Frame;
use ngp::data::color::SRGB8_TO_LINEAR;
use ngp::occupancy::{N_CELLS, OccupancyGrid};
use ngp::render::march::{MAX_CONE_STEPSIZE, MAX_SAMPLES_PER_RAY, Marcher};
use wgpu::util::DeviceExt;

pub const RAYS_WGSL: &str = include_str!("rays.wgsl");
const WORKGROUP: u32 = 64;

/// One drawn training ray (`struct GenRay` in `rays.wgsl`): the ray-generation kernel's
/// output and the marching kernel's input.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct GenRay {
    pub o: [f32; 3],
    /// Where marching starts: `advance_n_steps(tmin, cone_angle, u)`.
    pub t: f32,
    /// Unit direction.
    pub d: [f32; 3],
    /// 1 when the ray meets the box (else `t` is 0 and nothing is marched).
    pub hit: u32,
    pub bg: [f32; 3],
    /// `y·width + x`.
    pub pixel: u32,
    pub target: [f32; 3],
    pub image: u32,
}

/// A camera as the device reads it (`struct Cam`).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct GpuCam {
    c2w: [[f32; 4]; 3],
    intr: [f32; 4],
    dist: [f32; 4],
    width: u32,
    height: u32,
    offset: u32,
    flags: u32,
}

const F16_PIXELS: u32 = 1;
const DISTORTED: u32 = 2;

/// The marching kernels' uniform (`struct RayParams`).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct RayParams {
    seed: [u32; 2],
    n_rays: u32,
    n_images: u32,
    aabb_min: [f32; 3],
    cone_angle: f32,
    aabb_max: [f32; 3],
    inv_extent: f32,
    row_width: u32,
    sample_budget: u32,
    max_per_ray: u32,
    max_cascade: u32,
    /// l, a, b, at, bt of the stepping space, then MAX_CONE_STEPSIZE.
    step: [f32; 6],
    _pad: [u32; 2],
}

/// One batch's buffers on the device: per ray a [`GenRay`] (`drawn`) and a [`GpuRay`]
/// (`rays`), per sample of the budget the warped position (3 f32), `dt` and `dist`; and
/// `counters`: `[0]` samples asked for (past the budget too), `[1]` samples written (the
/// batch's compacted length), `[2]` rays with samples.
pub struct RayBatch {
    pub drawn: wgpu::Buffer,
    pub rays: wgpu::Buffer,
    pub pos: wgpu::Buffer,
    pub dt: wgpu::Buffer,
    pub dist: wgpu::Buffer,
    pub counters: wgpu::Buffer,
    max_rays: u32,
    sample_budget: u32,
}

impl RayBatch {
    /// Buffers for up to `max_rays` rays and `sample_budget` samples.
    pub fn new(ctx: &GpuContext, max_rays: u32, sample_budget: u32) -> GpuResult<RayBatch> {
        let limits = ctx.device.limits();
        let max = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        let (r, s) = (max_rays as u64, sample_budget as u64);
        if 64 * r > max || 12 * s > max {
            return Err(GpuError::Input(format!(
                "rays: {max_rays} rays / {sample_budget} samples past the device's \
                 {max}-byte binding"
            )));
        }
        ctx.scoped("ray batch", || RayBatch {
            drawn: device_buffer(ctx, "rays drawn", 64 * r),
            rays: device_buffer(ctx, "rays", 32 * r),
            pos: device_buffer(ctx, "rays pos", 12 * s),
            dt: device_buffer(ctx, "rays dt", 4 * s),
            dist: device_buffer(ctx, "rays dist", 4 * s),
            counters: device_buffer(ctx, "rays counters", 16),
            max_rays,
            sample_budget,
        })
    }

    pub fn max_rays(&self) -> u32 {
        self.max_rays
    }

    pub fn sample_budget(&self) -> u32 {
        self.sample_budget
    }

    /// The counters read back: (samples asked for, samples written, rays with samples).
    pub fn read_counters(&self, ctx: &GpuContext) -> GpuResult<(u32, u32, u32)> {
        let c = self.read_all_counters(ctx)?;
        Ok((c[0], c[1], c[2]))
    }

    /// All four counters: those of [`Self::read_counters`], then the rays with samples that
    /// did not fit the budget.
    pub fn read_all_counters(&self, ctx: &GpuContext) -> GpuResult<[u32; 4]> {
        let c: Vec<u32> = ctx.read_buffer(&self.counters, 16)?;
        Ok([c[0], c[1], c[2], c[3]])
    }
}

/// A marched batch read back to the host (tests and benchmarks).
#[derive(Clone, Debug, Default)]
pub struct MarchedHost {
    pub rays: Vec<GpuRay>,
    /// The `used` compacted samples.
    pub pos: Vec<[f32; 3]>,
    pub dt: Vec<f32>,
    pub dist: Vec<f32>,
    /// Samples the rays asked for, the budget notwithstanding.
    pub asked: u32,
    pub rays_with_samples: u32,
}

/// The ray-generation and marching kernels of one scene, with its cameras and training
/// images resident on the device.
pub struct RayKernels {
    gen_pipeline: wgpu::ComputePipeline,
    march_pipeline: wgpu::ComputePipeline,
    uniform: wgpu::Buffer,
    cams: wgpu::Buffer,
    images: wgpu::Buffer,
    lut: wgpu::Buffer,
    n_images: u32,
    marcher: Marcher,
    inv_extent: f32,
}

/// Workgroups for `n` invocations, folded into y past the dimension limit.
fn groups(ctx: &GpuContext, n: u32) -> [u32; 2] {
    let max_dim = ctx.device.limits().max_compute_workgroups_per_dimension;
    let g = n.div_ceil(WORKGROUP).max(1);
    let gx = g.min(max_dim);
    [gx, g.div_ceil(gx)]
}

/// Cameras and pixels of `frames` as the device reads them: one [`GpuCam`] per frame and
/// one word per RGBA8 pixel (r in the low byte) or two per f16 pixel.
fn pack_frames(frames: &[Frame]) -> GpuResult<(Vec<GpuCam>, Vec<u32>)> {
    let mut cams = Vec::with_capacity(frames.len());
    let mut words: Vec<u32> = Vec::new();
    for (k, f) in frames.iter().enumerate() {
        let (c, im) = (&f.camera, &f.image);
        if c.width != im.width || c.height != im.height {
            return Err(GpuError::Input(format!(
                "rays: frame {k}: camera {}x{} but image {}x{}",
                c.width, c.height, im.width, im.height
            )));
        }
        let offset = u32::try_from(words.len())
            .map_err(|_| GpuError::Input("rays: more than 2^32 words of pixels".into()))?;
        let mut flags = 0;
        match im.srgb8() {
            Some(bytes) => words.extend(
                bytes
                    .chunks_exact(4)
                    .map(|p| u32::from_le_bytes([p[0], p[1], p[2], p[3]])),
            ),
            None => {
                // Downscaled images are f16 on the CPU: their f32 reads convert back to
                // the same f16 exactly.
                flags |= F16_PIXELS;
                for y in 0..im.height {
                    for x in 0..im.width {
                        let q = im
                            .linear_premul(x, y)
                            .map(|v| half::f16::from_f32(v).to_bits());
                        words.push(q[0] as u32 | (q[1] as u32) << 16);
                        words.push(q[2] as u32 | (q[3] as u32) << 16);
                    }
                }
            }
        }
        let mut cam = gpu_cam(c);
        cam.offset = offset;
        cam.flags |= flags;
        cams.push(cam);
    }
    Ok((cams, words))
}

/// `c` as the device reads it (no pixels: offset 0).
pub(crate) fn gpu_cam(c: &Camera) -> GpuCam {
    let mut dist = [0.0; 4];
    let mut flags = 0;
    if let Some(d) = c.distortion {
        flags |= DISTORTED;
        dist = [d.k1, d.k2, d.p1, d.p2];
    }
    GpuCam {
        c2w: c.c2w,
        intr: [c.fx, c.fy, c.cx, c.cy],
        dist,
        width: c.width,
        height: c.height,
        offset: 0,
        flags,
    }
}

/// The side of `marcher`'s box, refused unless a power of two (the device warps by
/// multiplying with its inverse, which is then the CPU's division to the bit).
pub(crate) fn box_extent(marcher: &Marcher) -> GpuResult<f32> {
    let extent = marcher.aabb_max[0] - marcher.aabb_min[0];
    if extent.is_nan() || extent <= 0.0 || extent.log2().fract() != 0.0 {
        return Err(GpuError::Input(format!(
            "rays: aabb side {extent}: the device warps by a power-of-two side only"
        )));
    }
    Ok(extent)
}

/// The marching uniform for `marcher`: the box, the cone angle and the stepping-space
/// constants computed with the CPU's own f32 operations (march.rs computes them on every
/// call; here once, so only ln/exp of t itself run on the device).
/// `inv_extent` is 1 / [`box_extent`].
pub(crate) fn ray_params(
    marcher: &Marcher,
    inv_extent: f32,
    n_images: u32,
    [n_rays, row_width]: [u32; 2],
    seed: u64,
    budget: u32,
) -> RayParams {
    let m = marcher;
    let [l, a, b, at, bt] = m.stepping_constants();
    RayParams {
        seed: [seed as u32, (seed >> 32) as u32],
        n_rays,
        n_images,
        aabb_min: m.aabb_min,
        cone_angle: m.cone_angle(),
        aabb_max: m.aabb_max,
        inv_extent,
        row_width,
        sample_budget: budget,
        max_per_ray: MAX_SAMPLES_PER_RAY as u32,
        max_cascade: m.max_cascade,
        step: [l, a, b, at, bt, MAX_CONE_STEPSIZE],
        _pad: [0; 2],
    }
}

impl RayKernels {
    /// The kernels for a scene marched by `marcher`, with `frames` (its training views)
    /// uploaded once. `frames` may be empty for marching host-made rays only.
    pub fn new(ctx: &GpuContext, frames: &[Frame], marcher: &Marcher) -> GpuResult<RayKernels> {
        let extent = box_extent(marcher)?;
        let n_images = u32::try_from(frames.len())
            .map_err(|_| GpuError::Input("rays: more than 2^32 frames".into()))?;
        let (cams, words) = pack_frames(frames)?;
        let limits = ctx.device.limits();
        let max = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        if 4 * words.len() as u64 > max {
            return Err(GpuError::Input(format!(
                "rays: {} bytes of training images past the device's {max}-byte binding",
                4 * words.len()
            )));
        }
        ctx.scoped("ray kernels", || {
            let d = &ctx.device;
            let source = format!("{U64_WGSL}\n{PCG_WGSL}\n{RAYS_WGSL}");
            let [gen_pipeline, march_pipeline] =
                auto_layout_pipelines(ctx, "rays.wgsl", &source, ["gen_main", "march_main"]);
            let init = |label: &str, bytes: &[u8]| {
                // A binding cannot be empty.
                let bytes: &[u8] = if bytes.is_empty() { &[0; 16] } else { bytes };
                d.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents: bytes,
                    usage: wgpu::BufferUsages::STORAGE,
                })
            };
            RayKernels {
                gen_pipeline,
                march_pipeline,
                uniform: d.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("rays params"),
                    size: std::mem::size_of::<RayParams>() as u64,
                    usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                }),
                cams: init("rays cameras", bytemuck::cast_slice(&cams)),
                images: init("rays images", bytemuck::cast_slice(&words)),
                lut: init("rays srgb lut", bytemuck::cast_slice(&SRGB8_TO_LINEAR[..])),
                n_images,
                marcher: *marcher,
                inv_extent: 1.0 / extent,
            }
        })
    }

    fn params(&self, n_rays: u32, row_width: u32, seed: u64, budget: u32) -> RayParams {
        ray_params(
            &self.marcher,
            self.inv_extent,
            self.n_images,
            [n_rays, row_width],
            seed,
            budget,
        )
    }

    fn check(
        &self,
        batch: &RayBatch,
        bitfield: Option<&wgpu::Buffer>,
        n_rays: u32,
    ) -> GpuResult<()> {
        if n_rays > batch.max_rays {
            return Err(GpuError::Input(format!(
                "rays: {n_rays} rays for a batch of {}",
                batch.max_rays
            )));
        }
        if let Some(b) = bitfield {
            let need = (N_CELLS as u64 / 8) * (self.marcher.max_cascade as u64 + 1);
            if b.size() < need {
                return Err(GpuError::Input(format!(
                    "rays: a {}-byte bitfield for {} cascades ({need} bytes)",
                    b.size(),
                    self.marcher.max_cascade + 1
                )));
            }
        }
        Ok(())
    }

    /// Records one training batch: draw `n_rays` rays with `seed` (the CPU's per-step
    /// seed), march them through `bitfield` (the scene's [`super::GpuOccupancy::bitfield`])
    /// and compact their samples into `batch`. The uniform is written at once: one batch
    /// per submission.
    pub fn encode(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        batch: &RayBatch,
        bitfield: &wgpu::Buffer,
        n_rays: u32,
        seed: u64,
    ) -> GpuResult<()> {
        if self.n_images == 0 {
            return Err(GpuError::Input("rays: no training frames uploaded".into()));
        }
        self.check(batch, Some(bitfield), n_rays)?;
        self.record(ctx, encoder, batch, Some(bitfield), n_rays, seed, true)
    }

    /// Records marching only, of the `n_rays` rays already in `batch.drawn`.
    pub fn encode_march(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        batch: &RayBatch,
        bitfield: &wgpu::Buffer,
        n_rays: u32,
    ) -> GpuResult<()> {
        self.check(batch, Some(bitfield), n_rays)?;
        self.record(ctx, encoder, batch, Some(bitfield), n_rays, 0, false)
    }

    #[allow(clippy::too_many_arguments)]
    fn record(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        batch: &RayBatch,
        bitfield: Option<&wgpu::Buffer>,
        n_rays: u32,
        seed: u64,
        generate: bool,
    ) -> GpuResult<()> {
        if n_rays == 0 {
            return Ok(());
        }
        let [gx, gy] = groups(ctx, n_rays);
        let params = self.params(n_rays, gx * WORKGROUP, seed, batch.sample_budget);
        ctx.scoped("rays dispatch", || {
            ctx.queue
                .write_buffer(&self.uniform, 0, bytemuck::bytes_of(&params));
            encoder.clear_buffer(&batch.counters, 0, None);
            let e = buffer_entry;
            let mut pass = encoder.begin_compute_pass(&Default::default());
            if generate {
                let bg = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some("rays gen"),
                    layout: &self.gen_pipeline.get_bind_group_layout(0),
                    entries: &[
                        e(0, &self.cams),
                        e(1, &self.images),
                        e(2, &self.lut),
                        e(3, &batch.drawn),
                        e(11, &self.uniform),
                    ],
                });
                pass.set_pipeline(&self.gen_pipeline);
                pass.set_bind_group(0, &bg, &[]);
                pass.dispatch_workgroups(gx, gy, 1);
            }
            if let Some(bits) = bitfield {
                let bg = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some("rays march"),
                    layout: &self.march_pipeline.get_bind_group_layout(0),
                    entries: &[
                        e(4, &batch.drawn),
                        e(5, bits),
                        e(6, &batch.rays),
                        e(7, &batch.pos),
                        e(8, &batch.dt),
                        e(9, &batch.dist),
                        e(10, &batch.counters),
                        e(11, &self.uniform),
                    ],
                });
                pass.set_pipeline(&self.march_pipeline);
                pass.set_bind_group(0, &bg, &[]);
                pass.dispatch_workgroups(gx, gy, 1);
            }
        })
    }

    /// Draws `n_rays` rays and reads them back, unmarched (tests).
    pub fn generate_host(
        &self,
        ctx: &GpuContext,
        n_rays: u32,
        seed: u64,
    ) -> GpuResult<Vec<GenRay>> {
        if self.n_images == 0 {
            return Err(GpuError::Input("rays: no training frames uploaded".into()));
        }
        let batch = RayBatch::new(ctx, n_rays, 0)?;
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        self.record(ctx, &mut encoder, &batch, None, n_rays, seed, true)?;
        ctx.queue.submit([encoder.finish()]);
        ctx.read_buffer(&batch.drawn, 64 * n_rays as u64)
    }

    /// Marches host-made rays through `grid` (uploaded here) with a budget of
    /// `sample_budget` samples and reads the batch back (tests).
    pub fn march_host(
        &self,
        ctx: &GpuContext,
        grid: &OccupancyGrid,
        rays: &[GenRay],
        sample_budget: u32,
    ) -> GpuResult<MarchedHost> {
        let n_rays = u32::try_from(rays.len())
            .map_err(|_| GpuError::Input("rays: more than 2^32 rays".into()))?;
        if grid.n_cascades as u32 != self.marcher.max_cascade + 1 {
            return Err(GpuError::Input(format!(
                "rays: a grid of {} cascades for a box of {}",
                grid.n_cascades,
                self.marcher.max_cascade + 1
            )));
        }
        let batch = RayBatch::new(ctx, n_rays, sample_budget)?;
        let bits = ctx.scoped("rays bitfield", || {
            ctx.device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some("rays bitfield"),
                    contents: grid.bitfield(),
                    usage: wgpu::BufferUsages::STORAGE,
                })
        })?;
        ctx.queue
            .write_buffer(&batch.drawn, 0, bytemuck::cast_slice(rays));
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        self.encode_march(ctx, &mut encoder, &batch, &bits, n_rays)?;
        ctx.queue.submit([encoder.finish()]);
        self.read_marched(ctx, &batch, n_rays)
    }

    /// Reads a marched batch back (tests and benchmarks).
    pub fn read_marched(
        &self,
        ctx: &GpuContext,
        batch: &RayBatch,
        n_rays: u32,
    ) -> GpuResult<MarchedHost> {
        let (asked, used, rays_with_samples) = batch.read_counters(ctx)?;
        let u = used as u64;
        Ok(MarchedHost {
            rays: ctx.read_buffer(&batch.rays, 32 * n_rays as u64)?,
            pos: ctx.read_buffer(&batch.pos, 12 * u)?,
            dt: ctx.read_buffer(&batch.dt, 4 * u)?,
            dist: ctx.read_buffer(&batch.dist, 4 * u)?,
            asked,
            rays_with_samples,
        })
    }
}
