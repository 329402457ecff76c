//! The radiance field on the device: one parameter vector (laid out as the CPU's), one
//! index per level, and the grid and network kernels composed. What an occupancy update, a
//! key holder's grid rebuild and rendering ask of a model.

use super::grid::{GradAtomics, GridEncoding, GridShape};
use super::mlp::{EncodedBatch, MlpKernels};
use super::{GpuContext, GpuError, GpuIndex, GpuResult, device_buffer as storage};
use ngp::encoding::LevelIndex;
use ngp::network::layout::NerfLayout;
use wgpu::util::DeviceExt;

/// Weights and index resident on the device, with the kernels that evaluate them.
pub struct GpuField {
    layout: NerfLayout,
    grid: GridEncoding,
    mlp: MlpKernels,
    index: GpuIndex,
    /// The whole parameter vector: density MLP, colour MLP, grid (f32).
    pub params: wgpu::Buffer,
}

/// Scratch of a density evaluation, grown to the largest batch asked for.
#[derive(Default)]
pub struct DensityScratch {
    /// One chunk's encoding.
    enc: Option<wgpu::Buffer>,
    /// One chunk's log-densities, copied into `out` (when there is more than one chunk).
    part: Option<wgpu::Buffer>,
    /// One log-density per sample of the last evaluation.
    pub out: Option<wgpu::Buffer>,
    capacity: u32,
    chunk: u32,
    /// Most samples a chunk may hold, below what the device's bindings allow (tests).
    pub chunk_limit: Option<u32>,
}

/// Positions per chunk of a density evaluation: chunks start on a storage-aligned byte of
/// the positions (12 bytes each, so on a multiple of 64 positions for any alignment up to
/// 256) and their encoding fits one binding. An occupancy update of a 128³ cascade asks
/// for 2^21 positions, whose 16×2 encoding (256 MiB) is past many devices' 128 MiB.
fn density_chunk(ctx: &GpuContext, width: u64, limit: Option<u32>) -> u32 {
    let limits = ctx.device.limits();
    let max = limits
        .max_storage_buffer_binding_size
        .min(limits.max_buffer_size);
    let fits = (max / (4 * width)).min(u32::MAX as u64) as u32;
    let chunk = limit.map_or(fits, |l| l.min(fits));
    (chunk / 64 * 64).max(64)
}

impl GpuField {
    /// Uploads `params` (the CPU's vector for `layout`) under `indices`.
    pub fn new(
        ctx: &GpuContext,
        layout: &NerfLayout,
        params: &[f32],
        indices: &[LevelIndex],
    ) -> GpuResult<GpuField> {
        if params.len() != layout.n_params {
            return Err(GpuError::Input(format!(
                "{} parameters for a {}-parameter network",
                params.len(),
                layout.n_params
            )));
        }
        let align = ctx.device.limits().min_storage_buffer_offset_alignment as usize;
        if !(4 * layout.grid_offset).is_multiple_of(align) {
            return Err(GpuError::Input(format!(
                "the grid starts at byte {}, not a multiple of the device's {align}-byte \
                 storage alignment",
                4 * layout.grid_offset
            )));
        }
        let grid = GridEncoding::new(ctx, &layout.grid, GradAtomics::Auto)?;
        let mlp = MlpKernels::new(ctx, layout)?;
        let index = grid.upload_index(ctx, indices)?;
        let params = ctx.scoped("field parameters", || {
            ctx.device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some("field parameters"),
                    contents: bytemuck::cast_slice(params),
                    usage: wgpu::BufferUsages::STORAGE
                        | wgpu::BufferUsages::COPY_SRC
                        | wgpu::BufferUsages::COPY_DST,
                })
        })?;
        Ok(GpuField {
            layout: layout.clone(),
            grid,
            mlp,
            index,
            params,
        })
    }

    /// Looks at the same weights through other index functions (a key holder's).
    pub fn set_index(&mut self, ctx: &GpuContext, indices: &[LevelIndex]) -> GpuResult<()> {
        self.index = self.grid.upload_index(ctx, indices)?;
        Ok(())
    }

    pub fn layout(&self) -> &NerfLayout {
        &self.layout
    }

    /// Bytes of the grid's table in the parameters (and in a gradient of their layout).
    pub fn grid_bytes(&self) -> std::ops::Range<u64> {
        4 * self.layout.grid_offset as u64..4 * self.layout.n_params as u64
    }

    /// The grid kernels (a trainer records its forward and backward with them).
    pub fn grid(&self) -> &GridEncoding {
        &self.grid
    }

    /// The network kernels.
    pub fn mlp(&self) -> &MlpKernels {
        &self.mlp
    }

    /// The index the field is evaluated under.
    pub fn index(&self) -> &GpuIndex {
        &self.index
    }

    /// Records the raw log-density at the first `n` positions of `positions` (warped into
    /// the network's unit cube, 3 f32 each) into `scratch.out`.
    pub fn encode_density(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        positions: &wgpu::Buffer,
        n: u32,
        scratch: &mut DensityScratch,
    ) -> GpuResult<()> {
        self.encode_density_under(ctx, encoder, &self.index, positions, n, scratch)
    }

    /// [`encode_density`](Self::encode_density) through `index` instead of the field's own
    /// (one scene of a multi-scene trainer, each with its index on the device).
    pub fn encode_density_under(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        index: &GpuIndex,
        positions: &wgpu::Buffer,
        n: u32,
        scratch: &mut DensityScratch,
    ) -> GpuResult<()> {
        if n == 0 {
            return Ok(());
        }
        let width = self.layout.grid.config.n_output_dims() as u64;
        let chunk = density_chunk(ctx, width, scratch.chunk_limit).min(n);
        if n > scratch.capacity
            || chunk > scratch.chunk
            || scratch.out.is_none()
            || (chunk < n && scratch.part.is_none())
        {
            let (enc, out, part) = ctx.scoped("field scratch", || {
                (
                    storage(ctx, "field encoding", 4 * width * chunk as u64),
                    storage(ctx, "field log-density", 4 * n as u64),
                    (chunk < n).then(|| storage(ctx, "field log-density chunk", 4 * chunk as u64)),
                )
            })?;
            *scratch = DensityScratch {
                enc: Some(enc),
                part,
                out: Some(out),
                capacity: n,
                chunk,
                chunk_limit: scratch.chunk_limit,
            };
        }
        let (Some(enc), Some(out)) = (&scratch.enc, &scratch.out) else {
            unreachable!("allocated above")
        };
        for c0 in (0..n).step_by(chunk as usize) {
            let m = chunk.min(n - c0);
            let dispatch = self.grid.bind_forward(
                ctx,
                index,
                positions.slice(12 * c0 as u64..12 * (c0 + m) as u64),
                self.params.slice(self.grid_bytes()),
                enc.slice(..4 * width * m as u64),
                GridShape::new(m),
            )?;
            {
                let mut pass = encoder.begin_compute_pass(&Default::default());
                dispatch.record(&mut pass);
            }
            let batch = EncodedBatch {
                params: &self.params,
                enc,
                ld: m,
                n: m,
            };
            if m == n {
                return self.mlp.encode_density(ctx, encoder, &batch, out);
            }
            let Some(part) = &scratch.part else {
                unreachable!("allocated above for an evaluation in chunks")
            };
            self.mlp.encode_density(ctx, encoder, &batch, part)?;
            encoder.copy_buffer_to_buffer(part, 0, out, 4 * c0 as u64, 4 * m as u64);
        }
        Ok(())
    }
}
