//! The radiance field on the device: one parameter vector (laid out as the CPU's), one
//! index per level, and the grid and network kernels composed. What an occupancy update, a
//! key holder's grid rebuild and rendering ask of a model.

use super::grid::{GradAtomics, GridEncoding, GridShape};
use super::mlp::{EncodedBatch, MlpKernels};
use super::{GpuContext, GpuError, GpuIndex, GpuResult, device_buffer as storage};
use crate::ngp::encoding::LevelIndex;
use crate::ngp::network::layout::NerfLayout;
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
    enc: Option<wgpu::Buffer>,
    /// One log-density per sample of the last evaluation.
    pub out: Option<wgpu::Buffer>,
    capacity: u32,
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
        if n > scratch.capacity || scratch.enc.is_none() {
            let (enc, out) = ctx.scoped("field scratch", || {
                (
                    storage(ctx, "field encoding", 4 * width * n as u64),
                    storage(ctx, "field log-density", 4 * n as u64),
                )
            })?;
            *scratch = DensityScratch {
                enc: Some(enc),
                out: Some(out),
                capacity: n,
            };
        }
        let (Some(enc), Some(out)) = (&scratch.enc, &scratch.out) else {
            unreachable!("allocated above")
        };
        let g0 = 4 * self.layout.grid_offset as u64;
        let g1 = 4 * self.layout.n_params as u64;
        let dispatch = self.grid.bind_forward(
            ctx,
            index,
            positions.slice(..),
            self.params.slice(g0..g1),
            enc.slice(..),
            GridShape::new(n),
        )?;
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch.record(&mut pass);
        }
        let batch = EncodedBatch {
            params: &self.params,
            enc,
            ld: n,
            n,
        };
        self.mlp.encode_density(ctx, encoder, &batch, out)
    }
}
