//! The NeRF network after the hash grid on the device (`mlp.wgsl`): SH of the view
//! direction, the density MLP and the colour MLP, forward and backward, exactly as
//! [`NerfNetwork`](ngp::network::nerf::NerfNetwork) defines them (the CPU engine is
//! the oracle the tests hold these kernels to).
//!
//! Everything stays on the device: the caller owns the parameter, encoding, direction,
//! output and gradient buffers and records the kernels into its own command encoder
//! (`encode_*`), so a trainer's step submits once with no host round trip; the
//! `forward`/`density`/`backward` wrappers submit and wait, for tests and benchmarks.
//!
//! How the work is split:
//! - forward, density and the backward of the activations run per tile of `T` samples:
//!   a workgroup loads one layer's weights into workgroup memory at a time and carries its
//!   tile through every layer in two workgroup-memory activation tiles, touching device
//!   memory only for the encoding in, the outputs out and (training) the activations and
//!   per-layer output gradients that the weight gradients need;
//! - the weight gradients `dW = dY · Xᵀ` are a reduction over every sample: each workgroup
//!   sums one chunk of samples for one matrix in registers (through workgroup-memory
//!   tiles) and writes a partial; a second pass adds the chunks' partials, in order, into
//!   the gradient buffer. No float atomics: the sum is the same on every run and every
//!   adapter (a trainer that is reproducible run to run, like the CPU one), and 10 240
//!   weights hit by thousands of workgroups would serialise atomics (or CAS loops, where
//!   the adapter has no float atomics) on the same addresses, while the second pass reads
//!   each partial once.

use super::{
    GpuContext, GpuError, GpuResult, auto_layout_pipelines, buffer_entry as entry, check_binding,
};
use ngp::network::layout::{DENSITY_OUT, NerfLayout, SH_DIMS};
use ngp::network::mlp::matrix_offset;
use std::sync::atomic::{AtomicU32, Ordering};
use wgpu::util::DeviceExt;

/// The kernels, with their shape constants prepended by [`MlpKernels::new`].
pub const MLP_WGSL: &str = include_str!("mlp.wgsl");

/// Invocations per workgroup (`WG` in `mlp.wgsl`).
const WORKGROUP: u32 = 128;
/// Hidden width of both MLPs (`WIDTH`).
const WIDTH: usize = 64;
/// Rows of the saved activations: density hidden (64), colour input (32), colour hidden ×2.
pub(crate) const ACT_ROWS: u64 = 224;
/// Rows of the saved output gradients: density hidden, density out, colour hidden ×2, rgb.
const DY_ROWS: u64 = 211;
/// Samples per weight-gradient chunk: each chunk adds one partial of every weight for the
/// second pass to sum, so the partials cost 1/CH of the products and CH·5 products are one
/// workgroup's work.
const CHUNK: u32 = 512;
/// Weight matrices (density ×2, colour ×3): the y extent of the weight-gradient dispatch.
const N_MATRICES: u32 = 5;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct MlpParams {
    n: u32,
    ld_enc: u32,
    ld: u32,
    store: u32,
    tiles_x: u32,
    n_chunks: u32,
    _pad: [u32; 2],
}

/// Compiled kernels for one network layout.
pub struct MlpKernels {
    forward: wgpu::ComputePipeline,
    density: wgpu::ComputePipeline,
    backward: wgpu::ComputePipeline,
    wgrad: wgpu::ComputePipeline,
    reduce: wgpu::ComputePipeline,
    /// Bound in place of the saved activations when the forward keeps none (rendering).
    dummy: wgpu::Buffer,
    tile: u32,
    n_enc: u32,
    /// Floats of the parameter vector's MLP blocks, from its start: what the weight buffer
    /// and the gradient buffer must hold at least.
    mlp_end: u64,
    n_weights: u32,
}

/// What a training step keeps on the device between forward and backward: the activations
/// and per-layer output gradients of up to `capacity` samples and the weight-gradient
/// partials.
pub struct MlpWorkspace {
    capacity: u32,
    acts: wgpu::Buffer,
    dys: wgpu::Buffer,
    partials: wgpu::Buffer,
    /// Samples of the last forward that kept its activations (0: none), so that a backward
    /// with another count is refused instead of reading stale rows.
    kept: AtomicU32,
}

impl MlpWorkspace {
    pub fn capacity(&self) -> u32 {
        self.capacity
    }
}

/// The grid encoding a batch starts from: `enc[(l·F + f)·ld + s]` for the first `n` samples,
/// as the grid kernels (and the CPU's `grid::forward`) write it. The backward's `d_enc` has
/// the same layout.
#[derive(Clone, Copy)]
pub struct EncodedBatch<'a> {
    /// The parameter vector (at least its MLP blocks: density, colour).
    pub params: &'a wgpu::Buffer,
    pub enc: &'a wgpu::Buffer,
    pub ld: u32,
    pub n: u32,
}

fn bytes_of_floats(n: u64) -> u64 {
    4 * n
}

fn check_len(what: &str, buffer: &wgpu::Buffer, bytes: u64) -> GpuResult<()> {
    if buffer.size() < bytes {
        return Err(GpuError::Input(format!(
            "{what}: {} bytes, need {bytes}",
            buffer.size()
        )));
    }
    Ok(())
}

/// A storage buffer the tests and benchmarks fill from the host (also `COPY_SRC`, so it can
/// be read back, and `COPY_DST`, so it can be rewritten).
pub fn upload(ctx: &GpuContext, label: &str, data: &[f32]) -> GpuResult<wgpu::Buffer> {
    // A binding cannot be empty.
    let data: &[f32] = if data.is_empty() { &[0.0] } else { data };
    check_binding(ctx, label, bytes_of_floats(data.len() as u64))?;
    ctx.scoped("upload", || {
        ctx.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytemuck::cast_slice(data),
                usage: wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_SRC
                    | wgpu::BufferUsages::COPY_DST,
            })
    })
}

/// A zeroed storage buffer of `floats` f32 (outputs, gradients), readable back.
pub fn zeroed(ctx: &GpuContext, label: &str, floats: u64) -> GpuResult<wgpu::Buffer> {
    let bytes = bytes_of_floats(floats.max(1));
    check_binding(ctx, label, bytes)?;
    ctx.scoped("buffer", || {
        ctx.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: bytes,
            usage: wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_SRC
                | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    })
}

impl MlpKernels {
    /// Compiles the kernels for `layout` (the default model and any grid of at most 64
    /// features). The tile is the largest of 64, 32 or 16 samples whose workgroup memory
    /// the adapter allows: one layer's weights (64 × 64) and two 64-row tiles.
    pub fn new(ctx: &GpuContext, layout: &NerfLayout) -> GpuResult<MlpKernels> {
        let (dm, cm) = (layout.density_mlp, layout.color_mlp);
        let n_enc = layout.grid.config.n_output_dims();
        // The kernels are written for NerfLayout's architecture; refuse anything else
        // rather than compute something different.
        if dm.width != WIDTH
            || dm.n_hidden_layers != 1
            || dm.n_out_padded != DENSITY_OUT
            || cm.width != WIDTH
            || cm.n_hidden_layers != 2
            || cm.n_in != DENSITY_OUT + SH_DIMS
            || cm.n_out_padded != 16
            || cm.n_out != 3
        {
            return Err(GpuError::Input(format!(
                "unsupported network shape: density {dm:?}, colour {cm:?}"
            )));
        }
        if dm.n_in > WIDTH || n_enc == 0 || n_enc > dm.n_in {
            return Err(GpuError::Input(format!(
                "{n_enc} grid features (padded to {}): the kernels take 1 to {WIDTH}",
                dm.n_in
            )));
        }
        let limits = ctx.device.limits();
        let shared = |t: u32| 4 * (WIDTH as u32 * WIDTH as u32 + 2 * WIDTH as u32 * t);
        let tile = [64, 32, 16]
            .into_iter()
            .find(|&t| shared(t) <= limits.max_compute_workgroup_storage_size)
            .ok_or_else(|| {
                GpuError::Input(format!(
                    "the adapter allows {} bytes of workgroup memory; the MLP kernels need {}",
                    limits.max_compute_workgroup_storage_size,
                    shared(16)
                ))
            })?;
        if limits.max_compute_invocations_per_workgroup < WORKGROUP
            || limits.max_compute_workgroup_size_x < WORKGROUP
        {
            return Err(GpuError::Input(format!(
                "the adapter allows {} invocations per workgroup; the MLP kernels use {WORKGROUP}",
                limits.max_compute_invocations_per_workgroup
            )));
        }
        let d = layout.density_offset;
        let c = layout.color_offset;
        let offsets = [
            d + matrix_offset(&dm, 0),
            d + matrix_offset(&dm, 1),
            c + matrix_offset(&cm, 0),
            c + matrix_offset(&cm, 1),
            c + matrix_offset(&cm, 2),
        ];
        // The gradient pass indexes both MLPs as one block from the density matrix on.
        let mlp_end = c + cm.n_params();
        if c != d + dm.n_params() || mlp_end > u32::MAX as usize {
            return Err(GpuError::Input("MLP blocks not contiguous".into()));
        }
        let n_weights = (mlp_end - d) as u32;
        let header = format!(
            "const T: u32 = {tile}u;\nconst SB: u32 = {sb}u;\nconst N_ENC: u32 = {n_enc}u;\n\
             const DIN: u32 = {din}u;\nconst OFF_D0: u32 = {}u;\nconst OFF_D1: u32 = {}u;\n\
             const OFF_C0: u32 = {}u;\nconst OFF_C1: u32 = {}u;\nconst OFF_C2: u32 = {}u;\n\
             const NW: u32 = {n_weights}u;\nconst CH: u32 = {CHUNK}u;\n",
            offsets[0],
            offsets[1],
            offsets[2],
            offsets[3],
            offsets[4],
            sb = tile / 8,
            din = dm.n_in,
        );
        let source = format!("{header}{MLP_WGSL}");
        let [forward, density, backward, wgrad, reduce] = ctx.scoped("mlp kernels", || {
            auto_layout_pipelines(
                ctx,
                "mlp.wgsl",
                &source,
                [
                    "forward_main",
                    "density_main",
                    "backward_main",
                    "wgrad_main",
                    "reduce_main",
                ],
            )
        })?;
        Ok(MlpKernels {
            forward,
            density,
            backward,
            wgrad,
            reduce,
            dummy: zeroed(ctx, "mlp no activations", 4)?,
            tile,
            n_enc: n_enc as u32,
            mlp_end: mlp_end as u64,
            n_weights,
        })
    }

    /// Samples per workgroup tile on this adapter.
    pub fn tile(&self) -> u32 {
        self.tile
    }

    /// Buffers for forward-with-backward batches of up to `capacity` samples.
    pub fn workspace(&self, ctx: &GpuContext, capacity: u32) -> GpuResult<MlpWorkspace> {
        if capacity == 0 {
            return Err(GpuError::Input("workspace of 0 samples".into()));
        }
        let cap = u64::from(capacity);
        let chunks = u64::from(capacity.div_ceil(CHUNK));
        if chunks > u64::from(ctx.device.limits().max_compute_workgroups_per_dimension) {
            return Err(GpuError::Input(format!("{capacity} samples in one batch")));
        }
        Ok(MlpWorkspace {
            capacity,
            acts: zeroed(ctx, "mlp activations", ACT_ROWS * cap)?,
            dys: zeroed(ctx, "mlp output gradients", DY_ROWS * cap)?,
            partials: zeroed(
                ctx,
                "mlp weight partials",
                chunks * u64::from(self.n_weights),
            )?,
            kept: AtomicU32::new(0),
        })
    }

    fn check_batch(&self, b: &EncodedBatch) -> GpuResult<()> {
        if b.n > b.ld {
            return Err(GpuError::Input(format!(
                "{} samples with a leading dimension of {}",
                b.n, b.ld
            )));
        }
        check_len("parameters", b.params, bytes_of_floats(self.mlp_end))?;
        let rows = u64::from(self.n_enc);
        check_len(
            "encoding",
            b.enc,
            bytes_of_floats((rows - 1) * u64::from(b.ld) + u64::from(b.n)),
        )
    }

    /// Workgroups for `n` samples, one tile each, folded into y past the dimension limit.
    fn tiles(&self, ctx: &GpuContext, n: u32) -> GpuResult<[u32; 2]> {
        let max = ctx.device.limits().max_compute_workgroups_per_dimension;
        let t = n.div_ceil(self.tile);
        let x = t.clamp(1, max);
        let y = t.div_ceil(x);
        if y > max {
            return Err(GpuError::Input(format!("{n} samples in one dispatch")));
        }
        Ok([x, y])
    }

    fn params(ctx: &GpuContext, p: MlpParams) -> wgpu::Buffer {
        // A buffer per call, filled at creation: several calls recorded into one encoder
        // each see their own values (queue.write_buffer would apply the last before all).
        ctx.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("mlp params"),
                contents: bytemuck::bytes_of(&p),
                usage: wgpu::BufferUsages::UNIFORM,
            })
    }

    fn pass(
        encoder: &mut wgpu::CommandEncoder,
        pipeline: &wgpu::ComputePipeline,
        group: &wgpu::BindGroup,
        [x, y]: [u32; 2],
    ) {
        let mut pass = encoder.begin_compute_pass(&Default::default());
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, group, &[]);
        pass.dispatch_workgroups(x, y, 1);
    }

    /// Records the forward of `batch` with view directions `dirs` (`[x, y, z]` per sample)
    /// into `encoder`: `out[s] = [r_raw, g_raw, b_raw, log_density_raw]` (vec4 per sample),
    /// as `NerfNetwork::forward`. With `keep`, the activations stay in `ws` for
    /// [`encode_backward`](Self::encode_backward) (`n` ≤ its capacity).
    pub fn encode_forward(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        batch: &EncodedBatch,
        dirs: &wgpu::Buffer,
        out: &wgpu::Buffer,
        keep: Option<&MlpWorkspace>,
    ) -> GpuResult<()> {
        self.check_batch(batch)?;
        let n = u64::from(batch.n);
        check_len("directions", dirs, bytes_of_floats(3 * n))?;
        check_len("outputs", out, bytes_of_floats(4 * n))?;
        if let Some(ws) = keep
            && batch.n > ws.capacity
        {
            return Err(GpuError::Input(format!(
                "{} samples, workspace of {}",
                batch.n, ws.capacity
            )));
        }
        if batch.n == 0 {
            if let Some(ws) = keep {
                ws.kept.store(0, Ordering::Relaxed);
            }
            return Ok(());
        }
        let groups = self.tiles(ctx, batch.n)?;
        ctx.scoped("mlp forward", || {
            let p = Self::params(
                ctx,
                MlpParams {
                    n: batch.n,
                    ld_enc: batch.ld,
                    ld: keep.map_or(0, |ws| ws.capacity),
                    store: keep.is_some() as u32,
                    tiles_x: groups[0],
                    n_chunks: 0,
                    _pad: [0; 2],
                },
            );
            let acts = keep.map_or(&self.dummy, |ws| &ws.acts);
            let group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("mlp forward"),
                layout: &self.forward.get_bind_group_layout(0),
                entries: &[
                    entry(0, batch.params),
                    entry(1, batch.enc),
                    entry(2, dirs),
                    entry(3, out),
                    entry(5, acts),
                    entry(11, &p),
                ],
            });
            Self::pass(encoder, &self.forward, &group, groups);
        })?;
        if let Some(ws) = keep {
            ws.kept.store(batch.n, Ordering::Relaxed);
        }
        Ok(())
    }

    /// Records the density-only forward (`NerfNetwork::density`): `out[s]` = log-density
    /// (one f32 per sample), for occupancy updates and rendering.
    pub fn encode_density(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        batch: &EncodedBatch,
        out: &wgpu::Buffer,
    ) -> GpuResult<()> {
        self.check_batch(batch)?;
        check_len("density outputs", out, bytes_of_floats(u64::from(batch.n)))?;
        if batch.n == 0 {
            return Ok(());
        }
        let groups = self.tiles(ctx, batch.n)?;
        ctx.scoped("mlp density", || {
            let p = Self::params(
                ctx,
                MlpParams {
                    n: batch.n,
                    ld_enc: batch.ld,
                    ld: 0,
                    store: 0,
                    tiles_x: groups[0],
                    n_chunks: 0,
                    _pad: [0; 2],
                },
            );
            let group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("mlp density"),
                layout: &self.density.get_bind_group_layout(0),
                entries: &[
                    entry(0, batch.params),
                    entry(1, batch.enc),
                    entry(4, out),
                    entry(11, &p),
                ],
            });
            Self::pass(encoder, &self.density, &group, groups);
        })
    }

    /// Records the backward of the last [`encode_forward`](Self::encode_forward) that kept
    /// its activations in `ws` (same batch): `d_out` holds dL/d[r, g, b, log-density] per
    /// sample (vec4). ACCUMULATES the weights' gradients into `grad` (laid out as the
    /// parameter vector: its MLP blocks; the colour MLP's padded output rows get 0) and
    /// WRITES dL/d(enc) to `d_enc` (`enc`'s layout and leading dimension).
    #[allow(clippy::too_many_arguments)]
    pub fn encode_backward(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        batch: &EncodedBatch,
        d_out: &wgpu::Buffer,
        ws: &MlpWorkspace,
        grad: &wgpu::Buffer,
        d_enc: &wgpu::Buffer,
    ) -> GpuResult<()> {
        self.check_batch(batch)?;
        let n = batch.n;
        let kept = ws.kept.load(Ordering::Relaxed);
        if kept != n {
            return Err(GpuError::Input(format!(
                "backward of {n} samples; the workspace holds a forward of {kept}"
            )));
        }
        check_len("output gradients", d_out, bytes_of_floats(4 * u64::from(n)))?;
        check_len("weight gradients", grad, bytes_of_floats(self.mlp_end))?;
        check_len(
            "encoding gradients",
            d_enc,
            bytes_of_floats(u64::from(self.n_enc - 1) * u64::from(batch.ld) + u64::from(n)),
        )?;
        if n == 0 {
            return Ok(());
        }
        let groups = self.tiles(ctx, n)?;
        let n_chunks = n.div_ceil(CHUNK);
        ctx.scoped("mlp backward", || {
            let p = Self::params(
                ctx,
                MlpParams {
                    n,
                    ld_enc: batch.ld,
                    ld: ws.capacity,
                    store: 1,
                    tiles_x: groups[0],
                    n_chunks,
                    _pad: [0; 2],
                },
            );
            let d = &ctx.device;
            let backward = d.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("mlp backward"),
                layout: &self.backward.get_bind_group_layout(0),
                entries: &[
                    entry(0, batch.params),
                    entry(5, &ws.acts),
                    entry(6, &ws.dys),
                    entry(7, d_out),
                    entry(8, d_enc),
                    entry(11, &p),
                ],
            });
            let wgrad = d.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("mlp weight gradients"),
                layout: &self.wgrad.get_bind_group_layout(0),
                entries: &[
                    entry(1, batch.enc),
                    entry(5, &ws.acts),
                    entry(6, &ws.dys),
                    entry(9, &ws.partials),
                    entry(11, &p),
                ],
            });
            let reduce = d.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("mlp gradient sum"),
                layout: &self.reduce.get_bind_group_layout(0),
                entries: &[entry(9, &ws.partials), entry(10, grad), entry(11, &p)],
            });
            Self::pass(encoder, &self.backward, &backward, groups);
            Self::pass(encoder, &self.wgrad, &wgrad, [n_chunks, N_MATRICES]);
            Self::pass(
                encoder,
                &self.reduce,
                &reduce,
                [self.n_weights.div_ceil(WORKGROUP), 1],
            );
        })
    }

    fn submit(
        &self,
        ctx: &GpuContext,
        what: &'static str,
        f: impl FnOnce(&mut wgpu::CommandEncoder) -> GpuResult<()>,
    ) -> GpuResult<()> {
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        f(&mut encoder)?;
        ctx.scoped(what, || ctx.queue.submit([encoder.finish()]))?;
        ctx.wait()
    }

    /// [`encode_forward`](Self::encode_forward), submitted and waited for.
    pub fn forward(
        &self,
        ctx: &GpuContext,
        batch: &EncodedBatch,
        dirs: &wgpu::Buffer,
        out: &wgpu::Buffer,
        keep: Option<&MlpWorkspace>,
    ) -> GpuResult<()> {
        self.submit(ctx, "mlp forward", |e| {
            self.encode_forward(ctx, e, batch, dirs, out, keep)
        })
    }

    /// [`encode_density`](Self::encode_density), submitted and waited for.
    pub fn density(
        &self,
        ctx: &GpuContext,
        batch: &EncodedBatch,
        out: &wgpu::Buffer,
    ) -> GpuResult<()> {
        self.submit(ctx, "mlp density", |e| {
            self.encode_density(ctx, e, batch, out)
        })
    }

    /// [`encode_backward`](Self::encode_backward), submitted and waited for.
    pub fn backward(
        &self,
        ctx: &GpuContext,
        batch: &EncodedBatch,
        d_out: &wgpu::Buffer,
        ws: &MlpWorkspace,
        grad: &wgpu::Buffer,
        d_enc: &wgpu::Buffer,
    ) -> GpuResult<()> {
        self.submit(ctx, "mlp backward", |e| {
            self.encode_backward(ctx, e, batch, d_out, ws, grad, d_enc)
        })
    }
}
