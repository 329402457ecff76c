//! The occupancy grid's training update on the device (`occupancy.wgsl`): the draw of an
//! update's cells and positions, bit-identical to [`OccupancyGrid::sample_positions`] (then
//! warped as the trainer warps them), and, once the field's log-densities at those
//! positions are in a buffer, [`OccupancyGrid::splat`]'s max-splat, decay, cascade-0 mean,
//! bitfield and pooled cascades. The density itself is the network's business: any kernel
//! that writes one log-density per sample.

use super::field::{DensityScratch, GpuField};
use super::index::{PCG_WGSL, U64_WGSL};
use super::{
    GpuContext, GpuError, GpuIndex, GpuResult, buffer_entry, check_binding,
    device_buffer as storage, shared_layout_pipelines,
};
use ngp::occupancy::{N_CELLS, OccupancyGrid};
use ngp::render::march::Marcher;
use wgpu::util::DeviceExt;

const OCCUPANCY_WGSL: &str = include_str!("occupancy.wgsl");
/// Uniform slots, one per pass shape, chosen by dynamic offset: every pass of one submission
/// reads its own values (queue writes all land before the submission runs). Slot 0: the
/// draw; 1..=7: pooling into cascade 1..=7; 8: the cell passes; 9: the splat.
const SLOTS: u64 = 10;
const DRAW_SLOT: u32 = 0;
const CELLS_SLOT: u32 = 8;
const SPLAT_SLOT: u32 = 9;
const SLOT_BYTES: u64 = 256;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct OccParams {
    seed: [u32; 2],
    n_uniform: u32,
    n_nonuniform: u32,
    ema_step: u32,
    n_cascades: u32,
    row_width: u32,
    level: u32,
    aabb_min: [f32; 3],
    inv_extent: f32,
    first: u32,
    octant: u32,
    _pad: [u32; 2],
}

struct Pipelines {
    sample: wgpu::ComputePipeline,
    splat: wgpu::ComputePipeline,
    decay: wgpu::ComputePipeline,
    sum: wgpu::ComputePipeline,
    mean: wgpu::ComputePipeline,
    bits: wgpu::ComputePipeline,
    pool: wgpu::ComputePipeline,
    cell_points: wgpu::ComputePipeline,
    splat_max: wgpu::ComputePipeline,
}

/// What the sample buffers hold: an update's draw (cells in `sample_cell`) or a rebuild's
/// points in the cells `first..first + n` (cells implicit).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Drawn {
    Nothing,
    Update,
    Cells { first: u32 },
}

/// One scene's occupancy grid resident on the device, with the buffers of one update's
/// samples.
pub struct GpuOccupancy {
    pub n_cascades: u32,
    /// Optical thickness per cell, `N_CELLS` per cascade, Morton order (f32).
    pub density: wgpu::Buffer,
    /// One bit per cell per cascade, 32 cells per word: the CPU's bitfield bytes.
    pub bitfield: wgpu::Buffer,
    fresh: wgpu::Buffer,
    /// [0]: the cascade-0 mean after the last update; then partial sums.
    sums: wgpu::Buffer,
    /// The last draw's warped positions (3 floats a sample) and cells.
    pub sample_pos: wgpu::Buffer,
    pub sample_cell: wgpu::Buffer,
    capacity: u32,
    n_samples: u32,
    n_uniform: u32,
    drawn: Drawn,
    dummy: wgpu::Buffer,
    uniform: wgpu::Buffer,
    layout: wgpu::BindGroupLayout,
    pipelines: Pipelines,
    aabb_min: [f32; 3],
    inv_extent: f32,
    /// Updates so far (seeds the cell hash, as the CPU's `ema_step`).
    pub ema_step: u32,
}

/// Workgroups for `n` invocations of `size`, folded into y past the dimension limit.
fn groups(ctx: &GpuContext, n: u32, size: u32) -> [u32; 2] {
    let max_dim = ctx.device.limits().max_compute_workgroups_per_dimension;
    let g = n.div_ceil(size).max(1);
    let gx = g.min(max_dim);
    [gx, g.div_ceil(gx)]
}

impl GpuOccupancy {
    /// Uploads `grid` (the CPU marks untrained cells before training starts) for a scene
    /// marched by `marcher`.
    pub fn upload(
        ctx: &GpuContext,
        grid: &OccupancyGrid,
        marcher: &Marcher,
    ) -> GpuResult<GpuOccupancy> {
        let extent = marcher.aabb_max[0] - marcher.aabb_min[0];
        if extent.is_nan() || extent <= 0.0 || extent.log2().fract() != 0.0 {
            return Err(GpuError::Input(format!(
                "aabb side {extent}: the device warps by a power-of-two side only"
            )));
        }
        let nc = grid.n_cascades as u32;
        let bits = grid.bitfield();
        ctx.scoped("occupancy upload", || {
            let d = &ctx.device;
            let init = |label, contents: &[u8]| {
                d.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents,
                    usage: wgpu::BufferUsages::STORAGE
                        | wgpu::BufferUsages::COPY_SRC
                        | wgpu::BufferUsages::COPY_DST,
                })
            };
            let source = format!("{U64_WGSL}\n{PCG_WGSL}\n{OCCUPANCY_WGSL}");
            let (layout, p) = shared_layout_pipelines(
                ctx,
                "occupancy.wgsl",
                &source,
                7,
                |b| b == 5,
                true,
                &[
                    "sample_main",
                    "splat_main",
                    "decay_main",
                    "sum_main",
                    "mean_main",
                    "bits_main",
                    "pool_main",
                    "cell_points_main",
                    "splat_max_main",
                ],
            );
            let [
                sample,
                splat,
                decay,
                sum,
                mean,
                bits_p,
                pool,
                cell_points,
                splat_max,
            ] = <[wgpu::ComputePipeline; 9]>::try_from(p).expect("nine entry points");
            let pipelines = Pipelines {
                sample,
                splat,
                decay,
                sum,
                mean,
                bits: bits_p,
                pool,
                cell_points,
                splat_max,
            };
            let mut sums = vec![0.0f32; 1 + N_CELLS / 256];
            sums[0] = grid.mean;
            GpuOccupancy {
                n_cascades: nc,
                density: init("occupancy density", bytemuck::cast_slice(&grid.density)),
                bitfield: init("occupancy bitfield", bits),
                fresh: storage(ctx, "occupancy fresh", 4 * grid.density.len() as u64),
                sums: init("occupancy sums", bytemuck::cast_slice(&sums)),
                sample_pos: storage(ctx, "occupancy sample positions", 0),
                sample_cell: storage(ctx, "occupancy sample cells", 0),
                capacity: 0,
                n_samples: 0,
                n_uniform: 0,
                drawn: Drawn::Nothing,
                dummy: storage(ctx, "occupancy no density", 0),
                uniform: d.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("occupancy params"),
                    size: SLOTS * SLOT_BYTES,
                    usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                }),
                layout,
                pipelines,
                aabb_min: marcher.aabb_min,
                inv_extent: 1.0 / extent,
                ema_step: grid.ema_step,
            }
        })
    }

    /// Samples of the last draw (`n_uniform + n_nonuniform`).
    pub fn n_samples(&self) -> u32 {
        self.n_samples
    }

    fn params(&self, seed: u64, row_width: u32, level: u32) -> OccParams {
        let seed = seed ^ ((self.ema_step as u64) << 32);
        OccParams {
            seed: [seed as u32, (seed >> 32) as u32],
            n_uniform: self.n_uniform,
            n_nonuniform: self.n_samples - self.n_uniform,
            ema_step: self.ema_step,
            n_cascades: self.n_cascades,
            row_width,
            level,
            aabb_min: self.aabb_min,
            inv_extent: self.inv_extent,
            first: 0,
            octant: 0,
            _pad: [0; 2],
        }
    }

    fn bind_group(&self, ctx: &GpuContext, log_density: &wgpu::Buffer) -> wgpu::BindGroup {
        let e = buffer_entry;
        ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("occupancy"),
            layout: &self.layout,
            entries: &[
                e(0, &self.density),
                e(1, &self.fresh),
                e(2, &self.bitfield),
                e(3, &self.sample_pos),
                e(4, &self.sample_cell),
                e(5, log_density),
                e(6, &self.sums),
                wgpu::BindGroupEntry {
                    binding: 7,
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: &self.uniform,
                        offset: 0,
                        size: wgpu::BufferSize::new(std::mem::size_of::<OccParams>() as u64),
                    }),
                },
            ],
        })
    }

    /// Sample buffers for `n` samples.
    fn reserve(&mut self, ctx: &GpuContext, n: u32) -> GpuResult<()> {
        if n > self.capacity {
            check_binding(ctx, &format!("occupancy: {n} samples"), 12 * n as u64)?;
            (self.sample_pos, self.sample_cell) = ctx.scoped("occupancy samples", || {
                (
                    storage(ctx, "occupancy sample positions", 12 * n as u64),
                    storage(ctx, "occupancy sample cells", 4 * n as u64),
                )
            })?;
            self.capacity = n;
        }
        Ok(())
    }

    /// Records one pass over `n` samples with the uniform of `slot`.
    fn record_samples_pass(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        pipeline: &wgpu::ComputePipeline,
        log_density: &wgpu::Buffer,
        slot: u32,
        mut params: OccParams,
    ) -> GpuResult<()> {
        let [gx, gy] = groups(ctx, params.n_uniform + params.n_nonuniform, 64);
        params.row_width = gx * 64;
        ctx.scoped("occupancy samples pass", || {
            ctx.queue.write_buffer(
                &self.uniform,
                slot as u64 * SLOT_BYTES,
                bytemuck::bytes_of(&params),
            );
            let bg = self.bind_group(ctx, log_density);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, &bg, &[slot * SLOT_BYTES as u32]);
            pass.dispatch_workgroups(gx, gy, 1);
        })
    }

    /// Records the draw of one update's samples, `n_uniform` among seen cells and
    /// `n_nonuniform` among occupied ones (counts as `OccupancyGrid::update_sample_counts`
    /// gives them), into [`Self::sample_pos`] and [`Self::sample_cell`], warped for the
    /// network. `seed` is the scene's update seed, as the CPU trainer passes it.
    pub fn encode_samples(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        n_uniform: u32,
        n_nonuniform: u32,
        seed: u64,
    ) -> GpuResult<()> {
        let n = n_uniform
            .checked_add(n_nonuniform)
            .ok_or_else(|| GpuError::Input("occupancy: more than 2^32 samples".into()))?;
        self.reserve(ctx, n)?;
        self.n_samples = n;
        self.n_uniform = n_uniform;
        self.drawn = Drawn::Update;
        let params = self.params(seed, 0, 0);
        self.record_samples_pass(
            ctx,
            encoder,
            &self.pipelines.sample,
            &self.dummy,
            DRAW_SLOT,
            params,
        )
    }

    /// Records the draw of one round of a rebuild ([`OccupancyGrid::rebuild`]) over the
    /// cells `first..first + n` (indices over all cascades, as the CPU's `cells`): one
    /// point per cell in its octant `octant`, as [`OccupancyGrid::points_in_cell_octant`]
    /// draws it with `seed` (bit for bit), warped for the network into
    /// [`Self::sample_pos`].
    pub fn encode_cell_points(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        first: u32,
        n: u32,
        octant: u32,
        seed: u64,
    ) -> GpuResult<()> {
        let cells = N_CELLS as u64 * self.n_cascades as u64;
        if first as u64 + n as u64 > cells || octant > 7 {
            return Err(GpuError::Input(format!(
                "occupancy: cells {first}..{} of {cells}, octant {octant}",
                first as u64 + n as u64
            )));
        }
        self.reserve(ctx, n)?;
        self.n_samples = n;
        self.n_uniform = n;
        self.drawn = Drawn::Cells { first };
        let mut params = self.params(0, 0, 0);
        params.seed = [seed as u32, (seed >> 32) as u32];
        params.first = first;
        params.octant = octant;
        self.record_samples_pass(
            ctx,
            encoder,
            &self.pipelines.cell_points,
            &self.dummy,
            DRAW_SLOT,
            params,
        )
    }

    fn check_log_density(&self, log_density: &wgpu::Buffer) -> GpuResult<()> {
        if log_density.size() < 4 * self.n_samples as u64 {
            return Err(GpuError::Input(format!(
                "occupancy: {} bytes of log-density for {} samples",
                log_density.size(),
                self.n_samples
            )));
        }
        Ok(())
    }

    /// Records [`OccupancyGrid::splat_max`] after [`Self::encode_cell_points`]: each cell
    /// of the draw rises to the optical thickness of its point's `log_density` (no decay;
    /// call [`Self::encode_bitfield`] when every round is in).
    pub fn encode_splat_max(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        log_density: &wgpu::Buffer,
    ) -> GpuResult<()> {
        let Drawn::Cells { first } = self.drawn else {
            return Err(GpuError::Input(
                "occupancy: splat_max without a draw of cell points".into(),
            ));
        };
        self.check_log_density(log_density)?;
        let mut params = self.params(0, 0, 0);
        params.first = first;
        self.record_samples_pass(
            ctx,
            encoder,
            &self.pipelines.splat_max,
            log_density,
            SPLAT_SLOT,
            params,
        )
    }

    /// Records the rest of the update: every sample of the last draw splats
    /// `log_density[k]` (one f32 per sample, from the field) into its cell, then decay, the
    /// cascade-0 mean and the bitfield, as [`OccupancyGrid::splat`]. Counts one update.
    pub fn encode_splat(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        log_density: &wgpu::Buffer,
    ) -> GpuResult<()> {
        if self.drawn != Drawn::Update {
            return Err(GpuError::Input(
                "occupancy: a splat without an update's draw".into(),
            ));
        }
        self.check_log_density(log_density)?;
        let params = self.params(0, 0, 0);
        self.record_samples_pass(
            ctx,
            encoder,
            &self.pipelines.splat,
            log_density,
            SPLAT_SLOT,
            params,
        )?;
        let n_cells = N_CELLS as u32 * self.n_cascades;
        let g_cells = groups(ctx, n_cells, 256);
        self.write_slot(ctx, CELLS_SLOT, self.params(0, g_cells[0] * 256, 0))?;
        ctx.scoped("occupancy decay", || {
            let bg = self.bind_group(ctx, log_density);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_bind_group(0, &bg, &[CELLS_SLOT * SLOT_BYTES as u32]);
            pass.set_pipeline(&self.pipelines.decay);
            pass.dispatch_workgroups(g_cells[0], g_cells[1], 1);
        })?;
        self.encode_bitfield(ctx, encoder)?;
        self.ema_step += 1;
        Ok(())
    }

    fn write_slot(&self, ctx: &GpuContext, slot: u32, params: OccParams) -> GpuResult<()> {
        ctx.scoped("occupancy params", || {
            ctx.queue.write_buffer(
                &self.uniform,
                slot as u64 * SLOT_BYTES,
                bytemuck::bytes_of(&params),
            )
        })
    }

    /// Records [`OccupancyGrid::update_bitfield`] from the densities on the device: the
    /// cascade-0 mean, the thresholded bits of every cascade, then each cascade OR-pooling
    /// the finer one.
    pub fn encode_bitfield(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
    ) -> GpuResult<()> {
        let nc = self.n_cascades;
        let n_cells = N_CELLS as u32 * nc;
        let g_cells = groups(ctx, n_cells, 256);
        let g_words = groups(ctx, n_cells / 32, 256);
        let g_pool = groups(ctx, N_CELLS as u32 / 64, 256);
        // Slot l: pooling into cascade l, with its own row width. The bitfield pass
        // (≤ 2048 workgroups) and the sums never fold into y, so they need no row width of
        // their own.
        for l in 1..nc {
            self.write_slot(ctx, l, self.params(0, g_pool[0] * 256, l))?;
        }
        self.write_slot(ctx, CELLS_SLOT, self.params(0, g_cells[0] * 256, 0))?;
        ctx.scoped("occupancy bitfield", || {
            let bg = self.bind_group(ctx, &self.dummy);
            let off = |slot: u32| [slot * SLOT_BYTES as u32];
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_bind_group(0, &bg, &off(CELLS_SLOT));
            pass.set_pipeline(&self.pipelines.sum);
            pass.dispatch_workgroups(N_CELLS as u32 / 256, 1, 1);
            pass.set_pipeline(&self.pipelines.mean);
            pass.dispatch_workgroups(1, 1, 1);
            pass.set_pipeline(&self.pipelines.bits);
            pass.dispatch_workgroups(g_words[0], g_words[1], 1);
            for l in 1..nc {
                pass.set_bind_group(0, &bg, &off(l));
                pass.set_pipeline(&self.pipelines.pool);
                pass.dispatch_workgroups(g_pool[0], g_pool[1], 1);
            }
        })
    }

    /// Records one whole training update with the field on the device: the draw, the
    /// field's log-densities there, the splat (what `OccupancyGrid::update` does with the
    /// CPU network). One update of this grid per submission.
    #[allow(clippy::too_many_arguments)]
    pub fn encode_update(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        field: &GpuField,
        scratch: &mut DensityScratch,
        n_uniform: u32,
        n_nonuniform: u32,
        seed: u64,
    ) -> GpuResult<()> {
        let index = field.index();
        self.encode_update_under(
            ctx,
            encoder,
            field,
            index,
            scratch,
            n_uniform,
            n_nonuniform,
            seed,
        )
    }

    /// [`encode_update`](Self::encode_update) with the field seen through `index` (the
    /// scene's own, where several scenes share the weights).
    #[allow(clippy::too_many_arguments)]
    pub fn encode_update_under(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        field: &GpuField,
        index: &GpuIndex,
        scratch: &mut DensityScratch,
        n_uniform: u32,
        n_nonuniform: u32,
        seed: u64,
    ) -> GpuResult<()> {
        self.encode_samples(ctx, encoder, n_uniform, n_nonuniform, seed)?;
        field.encode_density_under(
            ctx,
            encoder,
            index,
            &self.sample_pos,
            self.n_samples,
            scratch,
        )?;
        match &scratch.out {
            Some(out) => self.encode_splat(ctx, encoder, out),
            None => Err(GpuError::Input("occupancy: an update of 0 samples".into())),
        }
    }

    /// The buffer whose first f32 is the cascade-0 mean after the last update (what
    /// decides the loss's density pull-up), for a pass that reads it on the device or a copy
    /// into a step's measurements.
    pub fn mean_buffer(&self) -> &wgpu::Buffer {
        &self.sums
    }

    /// The grid as the CPU holds it (density, bitfield, mean, update count), read back.
    pub fn download(&self, ctx: &GpuContext) -> GpuResult<OccupancyGrid> {
        let n = N_CELLS as u64 * self.n_cascades as u64;
        let density: Vec<f32> = ctx.read_buffer(&self.density, 4 * n)?;
        let bitfield: Vec<u8> = ctx.read_buffer(&self.bitfield, n / 8)?;
        let mean: Vec<f32> = ctx.read_buffer(&self.sums, 4)?;
        OccupancyGrid::from_parts(density, bitfield, mean[0], self.ema_step)
            .ok_or_else(|| GpuError::Input("occupancy: inconsistent grid read back".into()))
    }

    /// Replaces the grid on the device with `grid` (a saved one: density, bitfield, mean,
    /// update count), between updates. The same number of cascades.
    pub fn restore(&mut self, ctx: &GpuContext, grid: &OccupancyGrid) -> GpuResult<()> {
        if grid.n_cascades as u32 != self.n_cascades {
            return Err(GpuError::Input(format!(
                "occupancy: a grid of {} cascades for one of {}",
                grid.n_cascades, self.n_cascades
            )));
        }
        ctx.scoped("occupancy restore", || {
            ctx.queue
                .write_buffer(&self.density, 0, bytemuck::cast_slice(&grid.density));
            ctx.queue.write_buffer(&self.bitfield, 0, grid.bitfield());
            ctx.queue
                .write_buffer(&self.sums, 0, bytemuck::bytes_of(&grid.mean));
        })?;
        self.ema_step = grid.ema_step;
        Ok(())
    }

    /// The last draw's (warped positions, cells), read back.
    #[allow(clippy::type_complexity)]
    pub fn download_samples(&self, ctx: &GpuContext) -> GpuResult<(Vec<[f32; 3]>, Vec<u32>)> {
        let n = self.n_samples as u64;
        Ok((
            ctx.read_buffer(&self.sample_pos, 12 * n)?,
            ctx.read_buffer(&self.sample_cell, 4 * n)?,
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_context;
    use ngp::occupancy::MIN_CONE_STEPSIZE;
    use ngp::rng::Pcg32;
    use wgpu::util::DeviceExt;

    /// An aabb-4 grid (3 cascades) mid-training: densities around the threshold, a tenth of
    /// the cells culled, an update count that is not 0.
    fn grid() -> OccupancyGrid {
        let mut r = Pcg32::new(9, 2);
        let density = (0..3 * N_CELLS)
            .map(|_| {
                if r.next_f32() < 0.1 {
                    -1.0
                } else {
                    r.next_f32() * 0.02
                }
            })
            .collect();
        let mut g = OccupancyGrid::from_density(density).unwrap();
        g.ema_step = 37;
        g
    }

    fn run(ctx: &GpuContext, f: impl FnOnce(&mut wgpu::CommandEncoder)) {
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        f(&mut encoder);
        ctx.queue.submit([encoder.finish()]);
        ctx.wait().unwrap();
    }

    /// Cells and warped positions of two updates' draws, bit for bit the CPU trainer's
    /// (`sample_positions`, then `Marcher::warp`), and the splat that follows: densities
    /// within 1e-6 relative (the device's exp is not correctly rounded), the mean within
    /// 1e-5, the bitfield exactly except for cells within 1e-5 of the threshold.
    #[test]
    fn updates_match_the_cpu_grid() {
        let Some(ctx) = test_context() else { return };
        let marcher = Marcher::new(4);
        let mut cpu = grid();
        let mut gpu = GpuOccupancy::upload(ctx, &cpu, &marcher).unwrap();
        let mut r = Pcg32::new(4, 4);
        for (update, (nu, nn)) in [(20_000u32, 7_000u32), (3_000, 9_000)]
            .into_iter()
            .enumerate()
        {
            let seed = 0x1234_5678_9abc_def0 + update as u64;
            run(ctx, |e| gpu.encode_samples(ctx, e, nu, nn, seed).unwrap());
            let (pos, cells) = gpu.download_samples(ctx).unwrap();
            let (want_pos, want_cells) = cpu.sample_positions(nu as usize, nn as usize, seed);
            assert_eq!(cells, want_cells, "update {update}: cells");
            for (k, (got, want)) in pos.iter().zip(&want_pos).enumerate() {
                assert_eq!(*got, marcher.warp(*want), "update {update}: sample {k}");
            }
            let ld: Vec<f32> = (0..nu + nn)
                .map(|_| (r.next_f32() * 0.03 / MIN_CONE_STEPSIZE).ln())
                .collect();
            let buf = ctx
                .device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some("log density"),
                    contents: bytemuck::cast_slice(&ld),
                    usage: wgpu::BufferUsages::STORAGE,
                });
            run(ctx, |e| gpu.encode_splat(ctx, e, &buf).unwrap());
            cpu.splat(&want_cells, &ld);
            let got = gpu.download(ctx).unwrap();
            assert_eq!(got.ema_step, cpu.ema_step);
            assert!(
                (got.mean - cpu.mean).abs() <= 1e-5 * cpu.mean,
                "mean {} vs {}",
                got.mean,
                cpu.mean
            );
            for (i, (&g, &c)) in got.density.iter().zip(&cpu.density).enumerate() {
                assert!((g - c).abs() <= 1e-6 * c.abs(), "cell {i}: {g} vs {c}");
            }
            let thresh = cpu.mean.min(0.01);
            let near = |i: usize| (cpu.density[i] - thresh).abs() <= 1e-5 * thresh;
            let (gb, cb) = (got.bitfield(), cpu.bitfield());
            let mut differ = 0;
            for (byte, (&g, &c)) in gb.iter().zip(cb).enumerate() {
                if g != c {
                    // A differing bit of cascade 0's own cells must sit at the threshold;
                    // coarser bytes then differ through pooling, which must be rare.
                    if byte < N_CELLS / 8 {
                        for j in 0..8 {
                            if (g ^ c) >> j & 1 == 1 {
                                assert!(
                                    near(byte * 8 + j),
                                    "update {update}: cell {}",
                                    byte * 8 + j
                                );
                            }
                        }
                    }
                    differ += 1;
                }
            }
            assert!(
                differ <= 8,
                "update {update}: {differ} bitfield bytes differ"
            );
            let occupied = cb.iter().map(|b| b.count_ones()).sum::<u32>();
            assert!(
                occupied > 100_000,
                "the test grid has a real bitfield: {occupied}"
            );
        }
    }

    /// A whole update on the device (draw, the field's densities through the GPU grid and
    /// network, splat) against `OccupancyGrid::update` with the CPU network, on an aabb-4
    /// model with random weights, under the reference index and a keyed (SipHash) one: the same cells,
    /// densities within 1e-4 relative (the two networks' log-densities agree to ~1e-5 after
    /// exp), the bitfield equal but for cells at the threshold. Each update starts both
    /// sides from the CPU's grid, so that a near-threshold cell cannot steer the next draw.
    #[test]
    fn updates_with_the_gpu_field_match_the_cpu_network() {
        use ngp::encoding::reference_indices;
        use ngp::encoding::{IndexFn, LevelIndex, LevelIndices};
        use ngp::network::ModelConfig;
        use ngp::network::nerf::NerfNetwork;
        let Some(ctx) = test_context() else { return };
        let net = NerfNetwork::new(ModelConfig {
            aabb_scale: 4,
            ..Default::default()
        })
        .unwrap();
        let layout = &net.layout;
        let mut params = net.init_params(3);
        let mut r = Pcg32::new(8, 8);
        for (i, p) in params.iter_mut().enumerate() {
            *p += (r.next_f32() - 0.5) * if i < layout.grid_offset { 0.2 } else { 2.0 };
        }
        let marcher = Marcher::new(4);
        // A keyed index as a `prf` key gives one (SipHash on every level), built from the
        // engine's parts: this crate sits below the key layer.
        let keyed: LevelIndices = layout
            .grid
            .levels
            .iter()
            .map(|lv| LevelIndex::new(lv, IndexFn::Sip([5, 9])))
            .collect();
        for indices in [reference_indices(&layout.grid), keyed] {
            let mut field = GpuField::new(ctx, layout, &params, &indices).unwrap();
            field.set_index(ctx, &indices).unwrap();
            let mut scratch = DensityScratch::default();
            let mut cpu = OccupancyGrid::new(4);
            for step in 0..2u32 {
                let mut gpu = GpuOccupancy::upload(ctx, &cpu, &marcher).unwrap();
                let (nu, nn) = (20_000, 4_000 * step);
                let seed = 77 + step as u64;
                run(ctx, |e| {
                    gpu.encode_update(ctx, e, &field, &mut scratch, nu, nn, seed)
                        .unwrap()
                });
                let (_, cells) = cpu.sample_positions(nu as usize, nn as usize, seed);
                let (_, gpu_cells) = gpu.download_samples(ctx).unwrap();
                assert_eq!(gpu_cells, cells, "step {step}: cells");
                // What OccupancyGrid::update does with the CPU network (its counts aside).
                let (pos, _) = cpu.sample_positions(nu as usize, nn as usize, seed);
                let warped: Vec<[f32; 3]> = pos.iter().map(|&p| marcher.warp(p)).collect();
                let ld = net.density_batch(&params, &indices, &warped);
                cpu.splat(&cells, &ld);
                let got = gpu.download(ctx).unwrap();
                let mut touched = 0;
                for (i, (&g, &c)) in got.density.iter().zip(&cpu.density).enumerate() {
                    assert!(
                        (g - c).abs() <= 1e-4 * c.abs(),
                        "step {step} cell {i}: {g} vs {c}"
                    );
                    touched += (c > 0.0) as u32;
                }
                assert!(touched > 10_000, "the update reached {touched} cells");
                assert!((got.mean - cpu.mean).abs() <= 1e-4 * cpu.mean);
                let thresh = cpu.mean.min(0.01);
                let differ = got
                    .bitfield()
                    .iter()
                    .zip(cpu.bitfield())
                    .filter(|(g, c)| g != c)
                    .count();
                let near = cpu
                    .density
                    .iter()
                    .filter(|&&d| (d - thresh).abs() <= 1e-4 * thresh)
                    .count();
                assert!(
                    differ <= 2 * near,
                    "step {step}: {differ} bytes differ, {near} cells at the threshold"
                );
            }
        }
    }

    /// An update whose densities are evaluated in chunks (as on a device whose bindings do
    /// not hold a whole update's encoding) gives the grid the one-pass evaluation gives, bit
    /// for bit; the scratch then serves a smaller update in one pass.
    #[test]
    fn an_update_in_chunks_equals_one_pass() {
        use ngp::encoding::reference_indices;
        use ngp::network::ModelConfig;
        use ngp::network::nerf::NerfNetwork;
        let Some(ctx) = test_context() else { return };
        let net = NerfNetwork::new(ModelConfig::default()).unwrap();
        let layout = &net.layout;
        let mut params = net.init_params(4);
        let mut r = Pcg32::new(9, 9);
        for (i, p) in params.iter_mut().enumerate() {
            *p += (r.next_f32() - 0.5) * if i < layout.grid_offset { 0.2 } else { 2.0 };
        }
        let indices = reference_indices(&layout.grid);
        let field = GpuField::new(ctx, layout, &params, &indices).unwrap();
        let marcher = Marcher::new(1);
        let start = OccupancyGrid::new(1);
        let update = |scratch: &mut DensityScratch, nu: u32, nn: u32| {
            let mut gpu = GpuOccupancy::upload(ctx, &start, &marcher).unwrap();
            run(ctx, |e| {
                gpu.encode_update(ctx, e, &field, scratch, nu, nn, 5)
                    .unwrap()
            });
            gpu.download(ctx).unwrap()
        };
        let whole = update(&mut DensityScratch::default(), 20_000, 4_000);
        let mut chunked = DensityScratch::default();
        chunked.chunk_limit = Some(4_100);
        // 24 000 samples in chunks of 4 096 (the limit rounded down to 64): the last 3 520.
        assert!(update(&mut chunked, 20_000, 4_000) == whole);
        assert!(whole.density.iter().filter(|&&d| d > 0.0).count() > 10_000);
        let small = update(&mut DensityScratch::default(), 3_000, 0);
        assert!(update(&mut chunked, 3_000, 0) == small);
    }

    /// A rebuild's rounds on the device against the CPU's: the points of chunks of cells
    /// (one straddling two cascades) bit for bit `points_in_cell_octant` warped, for two
    /// octants and seeds; then `splat_max` of given log-densities (culled cells stay
    /// culled) and the bitfield as `update_bitfield` makes it.
    #[test]
    fn rebuild_rounds_match_the_cpu() {
        let Some(ctx) = test_context() else { return };
        let marcher = Marcher::new(2);
        let mut cpu = OccupancyGrid::new(2);
        let mut r = Pcg32::new(6, 6);
        for d in cpu.density.iter_mut() {
            *d = if r.next_f32() < 0.05 { -1.0 } else { 0.0 };
        }
        let mut gpu = GpuOccupancy::upload(ctx, &cpu, &marcher).unwrap();
        let all: Vec<u32> = (0..2 * N_CELLS as u32).collect();
        let n0 = N_CELLS as u32;
        for (round, (octant, seed)) in [(0u32, 99u64), (5, 100)].into_iter().enumerate() {
            let want = cpu.points_in_cell_octant(&all, octant, seed);
            for (first, n) in [(0u32, 5000u32), (n0 - 3000, 6000), (2 * n0 - 64, 64)] {
                run(ctx, |e| {
                    gpu.encode_cell_points(ctx, e, first, n, octant, seed)
                        .unwrap()
                });
                let (pos, _) = gpu.download_samples(ctx).unwrap();
                assert_eq!(pos.len(), n as usize);
                for (k, p) in pos.iter().enumerate() {
                    let c = first as usize + k;
                    assert_eq!(*p, marcher.warp(want[c]), "round {round}: cell {c}");
                }
                let ld: Vec<f32> = (0..n)
                    .map(|_| (r.next_f32() * 0.03 / MIN_CONE_STEPSIZE).ln())
                    .collect();
                let buf = ctx
                    .device
                    .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                        label: Some("log density"),
                        contents: bytemuck::cast_slice(&ld),
                        usage: wgpu::BufferUsages::STORAGE,
                    });
                run(ctx, |e| gpu.encode_splat_max(ctx, e, &buf).unwrap());
                cpu.splat_max(&all[first as usize..(first + n) as usize], &ld);
            }
        }
        run(ctx, |e| gpu.encode_bitfield(ctx, e).unwrap());
        cpu.update_bitfield();
        let got = gpu.download(ctx).unwrap();
        for (i, (&g, &c)) in got.density.iter().zip(&cpu.density).enumerate() {
            assert!((g - c).abs() <= 1e-6 * c.abs(), "cell {i}: {g} vs {c}");
        }
        assert!((got.mean - cpu.mean).abs() <= 1e-5 * cpu.mean);
        assert!(cpu.mean > 0.0 && got.ema_step == 0);
        let thresh = cpu.mean.min(0.01);
        for (byte, (&g, &c)) in got.bitfield().iter().zip(cpu.bitfield()).enumerate() {
            if g != c && byte < N_CELLS / 8 {
                for j in 0..8 {
                    let i = byte * 8 + j;
                    assert!(
                        (g ^ c) >> j & 1 == 0 || (cpu.density[i] - thresh).abs() <= 1e-5 * thresh,
                        "cell {i}"
                    );
                }
            }
        }
        let set: u32 = cpu.bitfield().iter().map(|b| b.count_ones()).sum();
        assert!(set > 5000, "{set} bits set");
    }

    #[test]
    fn bad_inputs_are_errors() {
        let Some(ctx) = test_context() else { return };
        let g = OccupancyGrid::new(1);
        let mut odd = Marcher::new(1);
        odd.aabb_max = [1.5; 3];
        assert!(GpuOccupancy::upload(ctx, &g, &odd).is_err());
        let mut gpu = GpuOccupancy::upload(ctx, &g, &Marcher::new(1)).unwrap();
        let short = ctx.device.create_buffer(&wgpu::BufferDescriptor {
            label: None,
            size: 16,
            usage: wgpu::BufferUsages::STORAGE,
            mapped_at_creation: false,
        });
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        gpu.encode_samples(ctx, &mut encoder, 1000, 0, 1).unwrap();
        assert!(gpu.encode_splat(ctx, &mut encoder, &short).is_err());
        assert_eq!(gpu.ema_step, 0, "a refused splat does not count");
        assert!(
            gpu.encode_samples(ctx, &mut encoder, u32::MAX, 1, 1)
                .is_err()
        );
        // A rebuild's splat needs a rebuild's draw, an update's splat an update's draw; a
        // draw past the grid's cells or octants is refused.
        assert!(gpu.encode_splat_max(ctx, &mut encoder, &short).is_err());
        gpu.encode_cell_points(ctx, &mut encoder, 0, 3, 7, 1)
            .unwrap();
        assert!(gpu.encode_splat(ctx, &mut encoder, &short).is_err());
        gpu.encode_splat_max(ctx, &mut encoder, &short).unwrap();
        assert!(
            gpu.encode_cell_points(ctx, &mut encoder, N_CELLS as u32 - 2, 3, 0, 1)
                .is_err()
        );
        assert!(
            gpu.encode_cell_points(ctx, &mut encoder, 0, 3, 8, 1)
                .is_err()
        );
    }
}
