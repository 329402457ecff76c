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
//! How the work is split (`mlp.wgsl` says how a tile goes through a layer):
//! - forward, density and the backward of the activations run per tile of 128 samples:
//!   a workgroup carries its tile through every layer in one workgroup-memory tile, each
//!   row group keeping its block of a layer's products in registers and reading the
//!   weights straight from device memory (a subgroup reads one address at a time: a
//!   broadcast from the cache); the forward reads a transposed copy of the weights, which
//!   a small pass writes before each forward, so that those reads are whole vec4. Device
//!   memory is touched only for the encoding in, the outputs out and (training) the
//!   activations and per-layer output gradients that the weight gradients need;
//! - the weight gradients `dW = dY · Xᵀ` are a reduction over every sample: each workgroup
//!   sums one chunk of samples for one matrix, at the matrix's own shape, in registers
//!   (through workgroup-memory tiles padded against bank conflicts) and writes a partial;
//!   a two-level pass adds the chunks' partials, in a fixed order, into the gradient
//!   buffer. No float atomics: the sum is the same on every run and every adapter (a
//!   trainer that is reproducible run to run, like the CPU one), and 10 240 weights hit by
//!   thousands of workgroups would serialise atomics (or CAS loops, where the adapter has
//!   no float atomics) on the same addresses, while the reduction reads each partial once.
//!
//! The module is compiled without naga's runtime checks
//! (`unchecked_auto_layout_pipelines`): with them the driver's compiler saw every
//! accumulator array indexed through a clamp and every loop behind a counter, and kept
//! them in device memory. [`MlpKernels::new`] says why each index is in bounds.

use super::count::{DeviceCount, Slot};
use super::{
    GpuContext, GpuError, GpuResult, buffer_entry as entry, check_binding,
    unchecked_auto_layout_pipelines,
};
use ngp::network::layout::{DENSITY_OUT, NerfLayout, SH_DIMS};
use ngp::network::mlp::matrix_offset;
use std::fmt::Write;
use std::sync::atomic::{AtomicU32, Ordering};
use wgpu::util::DeviceExt;

/// The kernels, with their shape constants prepended by [`MlpKernels::new`].
pub const MLP_WGSL: &str = include_str!("mlp.wgsl");

/// Invocations per workgroup (`WG` in `mlp.wgsl`).
const WORKGROUP: u32 = 128;
/// Samples per workgroup tile (`T`): 32 lanes of 4.
const TILE: u32 = 128;
/// Workgroup memory of the tile: 64 rows × TILE samples of f32.
const TILE_BYTES: u32 = 64 * TILE * 4;
/// Hidden width of both MLPs (`WIDTH`).
const WIDTH: usize = 64;
/// Rows of the saved activations: density hidden (64), colour input (32), colour hidden ×2.
pub(crate) const ACT_ROWS: u64 = 224;
/// Rows of the saved output gradients: density hidden, density out, colour hidden ×2, rgb.
const DY_ROWS: u64 = 211;
/// Samples per weight-gradient chunk: each chunk adds one partial of every weight for the
/// reduction to sum, so the partials cost 1/CH of the products, and a chunk of each of the
/// five matrices is one workgroup's work (2^18 samples: 256 chunks, 1280 workgroups).
const CHUNK: u32 = 1024;
/// Chunks the reduction's first level sums per thread (`RG_CHUNKS`): 2^18 samples' 256
/// partials of each weight in 8 groups.
const REDUCE_GROUP: u32 = 32;

/// One weight matrix's gradient kernel: `rows` × `cols` outputs (`rows_used` of them with a
/// gradient; `rows_stored` in the parameter vector), invocation `lid` owning rows
/// `lid % rg + rg·i` (i < rr) and columns `lid / rg + cg·j` (j < cc), with rg·cg = 128.
struct WgradShape {
    name: &'static str,
    off: &'static str,
    rows_used: u32,
    rows: u32,
    rows_stored: u32,
    cols: u32,
    dy_row: &'static str,
    /// The saved-activation row of X, or `None`: X is the encoding.
    x_row: Option<&'static str>,
    rg: u32,
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct MlpParams {
    n: u32,
    ld_enc: u32,
    ld: u32,
    store: u32,
    tiles_x: u32,
    stage: u32,
    _pad: [u32; 2],
}

/// Compiled kernels for one network layout.
pub struct MlpKernels {
    forward: wgpu::ComputePipeline,
    density: wgpu::ComputePipeline,
    backward: wgpu::ComputePipeline,
    /// One per weight matrix: density ×2, colour ×3.
    wgrad: [wgpu::ComputePipeline; 5],
    reduce: wgpu::ComputePipeline,
    transpose: wgpu::ComputePipeline,
    /// The forward's transposed weights, rewritten before each forward.
    transposed: wgpu::Buffer,
    /// Bound in place of the saved activations when the forward keeps none (rendering).
    dummy: wgpu::Buffer,
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

/// A device count of at most `n` samples: the buffers hold `n`.
fn check_count(count: Option<&DeviceCount>, n: u32) -> GpuResult<()> {
    match count {
        Some(c) if c.max() > n => Err(GpuError::Input(format!(
            "a count of up to {} samples, buffers for {n}",
            c.max()
        ))),
        _ => Ok(()),
    }
}

fn check_len(what: &str, buffer: &wgpu::Buffer, bytes: u64) -> GpuResult<()> {
    check_slice(what, &buffer.slice(..), bytes)
}

fn check_slice(what: &str, slice: &wgpu::BufferSlice, bytes: u64) -> GpuResult<()> {
    if slice.size() < bytes {
        return Err(GpuError::Input(format!(
            "{what}: {} bytes, need {bytes}",
            slice.size()
        )));
    }
    Ok(())
}

fn slice_entry<'a>(binding: u32, slice: &wgpu::BufferSlice<'a>) -> wgpu::BindGroupEntry<'a> {
    wgpu::BindGroupEntry {
        binding,
        resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer: slice.buffer(),
            offset: slice.offset(),
            size: std::num::NonZeroU64::new(slice.size()),
        }),
    }
}

/// A dispatch's workgroups: from the host, or slot `.1` of a count on the device.
#[derive(Clone, Copy)]
enum Groups<'a> {
    Host([u32; 2]),
    Device(&'a DeviceCount, usize),
}

impl From<[u32; 2]> for Groups<'_> {
    fn from(g: [u32; 2]) -> Self {
        Groups::Host(g)
    }
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
    /// features). They need 32 KiB of workgroup memory (one 64-row tile of 128 samples).
    ///
    /// Why every index the kernels compute is in bounds (they are compiled without naga's
    /// runtime checks):
    /// - workgroup memory: tile rows are below 64 and lanes below 32 by construction (row
    ///   blocks of R ≤ 64 / 4 per group of 4, DIN ≤ 64); staging rows are below 64 and
    ///   samples below 33;
    /// - private arrays: constant indices, or loops with constant bounds below their length;
    /// - weights: the offsets below and the matrices' sizes stay inside the parameter
    ///   vector's MLP blocks, which `check_batch` checks the buffer holds;
    /// - samples: every read and write of sample s is behind `s < n`, except the vec4 of a
    ///   lane whose first sample is below n in `acts` and `dys`, whose leading dimension
    ///   (the workspace's capacity, a multiple of 4, ≥ n) holds it whole; `enc`, `dirs`,
    ///   `out`, `d_out`, `d_enc` and the workspace are checked against n and the leading
    ///   dimensions on the host before every dispatch; partials hold every chunk;
    /// - every loop's bound is a constant or a count the host checked.
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
        // A row group's share of the encoding rows (DIN / 4) is read as whole vec4.
        if dm.n_in > WIDTH || dm.n_in % 16 != 0 || n_enc == 0 || n_enc > dm.n_in {
            return Err(GpuError::Input(format!(
                "{n_enc} grid features (padded to {}): the kernels take 1 to {WIDTH}, padded \
                 to a multiple of 16",
                dm.n_in
            )));
        }
        let limits = ctx.device.limits();
        if limits.max_compute_workgroup_storage_size < TILE_BYTES {
            return Err(GpuError::Input(format!(
                "the adapter allows {} bytes of workgroup memory; the MLP kernels need \
                 {TILE_BYTES}",
                limits.max_compute_workgroup_storage_size
            )));
        }
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
        // The weights are read as vec4.
        if offsets.iter().any(|o| o % 4 != 0) {
            return Err(GpuError::Input(format!(
                "MLP matrices at {offsets:?}: the kernels read them as vec4"
            )));
        }
        let n_weights = (mlp_end - d) as u32;
        let din = dm.n_in as u32;
        let mut source = format!(
            "const N_ENC: u32 = {n_enc}u;\nconst DIN: u32 = {din}u;\nconst RD: u32 = {rd}u;\n\
             const NW: u32 = {n_weights}u;\nconst CH: u32 = {CHUNK}u;\n\
             const RG_CHUNKS: u32 = {REDUCE_GROUP}u;\n",
            rd = din / 4,
        );
        for (name, o) in ["D0", "D1", "C0", "C1", "C2"].iter().zip(offsets) {
            let _ = writeln!(source, "const OFF_{name}: u32 = {o}u;");
            let _ = writeln!(source, "const T{name}: u32 = {}u;", o - d);
        }
        source.push_str(MLP_WGSL);
        source.push_str(&generated_wgsl(din));
        let wgrad_names: Vec<String> = (0..5).map(|m| format!("wgrad_{m}")).collect();
        let [
            forward,
            density,
            backward,
            reduce,
            transpose,
            w0,
            w1,
            w2,
            w3,
            w4,
        ] = ctx.scoped("mlp kernels", || {
            // SAFETY: the bounds argument in this function's documentation; every
            // dispatch below checks its buffers against the counts it passes.
            unsafe {
                unchecked_auto_layout_pipelines(
                    ctx,
                    "mlp.wgsl",
                    &source,
                    [
                        "forward_main",
                        "density_main",
                        "backward_main",
                        "reduce_main",
                        "transpose_main",
                        &wgrad_names[0],
                        &wgrad_names[1],
                        &wgrad_names[2],
                        &wgrad_names[3],
                        &wgrad_names[4],
                    ],
                )
            }
        })?;
        Ok(MlpKernels {
            forward,
            density,
            backward,
            wgrad: [w0, w1, w2, w3, w4],
            reduce,
            transpose,
            transposed: zeroed(ctx, "mlp transposed weights", u64::from(n_weights))?,
            dummy: zeroed(ctx, "mlp no activations", 4)?,
            n_enc: n_enc as u32,
            mlp_end: mlp_end as u64,
            n_weights,
        })
    }

    /// Samples per workgroup tile.
    pub fn tile(&self) -> u32 {
        TILE
    }

    /// Buffers for forward-with-backward batches of up to `capacity` samples (rounded up
    /// to a multiple of 4: the kernels move saved rows 4 samples at a time).
    pub fn workspace(&self, ctx: &GpuContext, capacity: u32) -> GpuResult<MlpWorkspace> {
        if capacity == 0 || capacity > u32::MAX - 3 {
            return Err(GpuError::Input(format!("workspace of {capacity} samples")));
        }
        let capacity = capacity.next_multiple_of(4);
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
        let t = n.div_ceil(TILE);
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
                // A count known only on the device is copied into `n`.
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            })
    }

    fn pass<'a>(
        encoder: &mut wgpu::CommandEncoder,
        pipeline: &wgpu::ComputePipeline,
        group: &wgpu::BindGroup,
        groups: impl Into<Groups<'a>>,
    ) {
        let mut pass = encoder.begin_compute_pass(&Default::default());
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, group, &[]);
        match groups.into() {
            Groups::Host([x, y]) => pass.dispatch_workgroups(x, y, 1),
            Groups::Device(c, i) => c.dispatch(&mut pass, i),
        }
    }

    /// Records the transposed copy of `params`' weights the forward kernels read.
    fn encode_transpose(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        params: &wgpu::Buffer,
    ) {
        let group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("mlp transpose"),
            layout: &self.transpose.get_bind_group_layout(0),
            entries: &[entry(0, params), entry(13, &self.transposed)],
        });
        Self::pass(
            encoder,
            &self.transpose,
            &group,
            [self.n_weights.div_ceil(WORKGROUP), 1],
        );
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
        self.encode_forward_slice(ctx, encoder, batch, dirs.slice(..), out, keep, None)
    }

    /// Dispatch shapes a [`DeviceCount`] must provide for the counted passes over batches
    /// of up to `max` samples: tiles, weight-gradient chunks, the reduction's first level.
    pub fn count_slots(&self, ctx: &GpuContext, max: u32) -> GpuResult<[Slot; 3]> {
        let [x, _] = self.tiles(ctx, max)?;
        Ok([
            Slot {
                divisor: TILE,
                max_x: x,
                z: 1,
                fixed_x: 0,
            },
            Slot {
                divisor: CHUNK,
                max_x: ctx.device.limits().max_compute_workgroups_per_dimension,
                z: 1,
                fixed_x: 0,
            },
            Slot {
                divisor: CHUNK * REDUCE_GROUP,
                max_x: 1,
                z: 1,
                fixed_x: self.n_weights.div_ceil(WORKGROUP),
            },
        ])
    }

    /// [`encode_forward`](Self::encode_forward) with `dirs` a slice (a chunk of a larger
    /// batch) and, with `count`, of only the first n samples of `batch`, n known only on the
    /// device (at most `batch.n`, which the buffers are checked against).
    #[allow(clippy::too_many_arguments)]
    pub fn encode_forward_slice(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        batch: &EncodedBatch,
        dirs: wgpu::BufferSlice<'_>,
        out: &wgpu::Buffer,
        keep: Option<&MlpWorkspace>,
        count: Option<&DeviceCount>,
    ) -> GpuResult<()> {
        self.check_batch(batch)?;
        let n = u64::from(batch.n);
        check_slice("directions", &dirs, bytes_of_floats(3 * n))?;
        check_len("outputs", out, bytes_of_floats(4 * n))?;
        if let Some(ws) = keep
            && batch.n > ws.capacity
        {
            return Err(GpuError::Input(format!(
                "{} samples, workspace of {}",
                batch.n, ws.capacity
            )));
        }
        check_count(count, batch.n)?;
        if batch.n == 0 {
            if let Some(ws) = keep {
                ws.kept.store(0, Ordering::Relaxed);
            }
            return Ok(());
        }
        let groups = self.dispatch_of(ctx, batch.n, count, 0)?;
        ctx.scoped("mlp forward", || {
            let p = Self::params(
                ctx,
                MlpParams {
                    n: batch.n,
                    ld_enc: batch.ld,
                    ld: keep.map_or(0, |ws| ws.capacity),
                    store: keep.is_some() as u32,
                    tiles_x: self.tiles_x(ctx, batch.n),
                    stage: 0,
                    _pad: [0; 2],
                },
            );
            let acts = keep.map_or(&self.dummy, |ws| &ws.acts);
            let group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("mlp forward"),
                layout: &self.forward.get_bind_group_layout(0),
                entries: &[
                    entry(1, batch.enc),
                    slice_entry(2, &dirs),
                    entry(3, out),
                    entry(5, acts),
                    entry(11, &p),
                    entry(12, &self.transposed),
                ],
            });
            self.encode_transpose(ctx, encoder, batch.params);
            if let Some(c) = count {
                c.copy_n(encoder, &p);
            }
            Self::pass(encoder, &self.forward, &group, groups);
        })?;
        if let Some(ws) = keep {
            ws.kept.store(batch.n, Ordering::Relaxed);
        }
        Ok(())
    }

    /// Workgroups for `n` samples from the host, or slot `which` of `count_slots` from the
    /// device.
    fn dispatch_of<'a>(
        &self,
        ctx: &GpuContext,
        n: u32,
        count: Option<&'a DeviceCount>,
        which: usize,
    ) -> GpuResult<Groups<'a>> {
        match count {
            None => Ok(Groups::Host(self.tiles(ctx, n)?)),
            Some(c) => {
                let slot = self.count_slots(ctx, n)?[which];
                Ok(Groups::Device(c, c.slot(slot)?))
            }
        }
    }

    /// Tiles per dispatch row for batches of `n` samples (the fold the kernels undo).
    fn tiles_x(&self, ctx: &GpuContext, n: u32) -> u32 {
        self.tiles(ctx, n).map_or(1, |[x, _]| x)
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
        self.encode_density_counted(ctx, encoder, batch, out, None)
    }

    /// [`encode_density`](Self::encode_density) of, with `count`, only the first n samples
    /// of `batch`, n known only on the device (at most `batch.n`). Its log-densities are
    /// the bits [`encode_forward`](Self::encode_forward) gives (the same products in the
    /// same order), so a ray stops where the whole network would stop it.
    pub fn encode_density_counted(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        batch: &EncodedBatch,
        out: &wgpu::Buffer,
        count: Option<&DeviceCount>,
    ) -> GpuResult<()> {
        self.check_batch(batch)?;
        check_len("density outputs", out, bytes_of_floats(u64::from(batch.n)))?;
        check_count(count, batch.n)?;
        if batch.n == 0 {
            return Ok(());
        }
        let groups = self.dispatch_of(ctx, batch.n, count, 0)?;
        ctx.scoped("mlp density", || {
            let p = Self::params(
                ctx,
                MlpParams {
                    n: batch.n,
                    ld_enc: batch.ld,
                    ld: 0,
                    store: 0,
                    tiles_x: self.tiles_x(ctx, batch.n),
                    stage: 0,
                    _pad: [0; 2],
                },
            );
            let group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("mlp density"),
                layout: &self.density.get_bind_group_layout(0),
                entries: &[
                    entry(1, batch.enc),
                    entry(4, out),
                    entry(5, &self.dummy),
                    entry(11, &p),
                    entry(12, &self.transposed),
                ],
            });
            self.encode_transpose(ctx, encoder, batch.params);
            if let Some(c) = count {
                c.copy_n(encoder, &p);
            }
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
        self.encode_backward_slice(ctx, encoder, batch, d_out.slice(..), ws, grad, d_enc, None)
    }

    /// [`encode_backward`](Self::encode_backward) with `d_out` a slice (a chunk of a larger
    /// batch) and, with `count`, after an [`encode_forward_slice`](Self::encode_forward_slice)
    /// with the same count.
    #[allow(clippy::too_many_arguments)]
    pub fn encode_backward_slice(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        batch: &EncodedBatch,
        d_out: wgpu::BufferSlice<'_>,
        ws: &MlpWorkspace,
        grad: &wgpu::Buffer,
        d_enc: &wgpu::Buffer,
        count: Option<&DeviceCount>,
    ) -> GpuResult<()> {
        self.check_batch(batch)?;
        let n = batch.n;
        let kept = ws.kept.load(Ordering::Relaxed);
        if kept != n {
            return Err(GpuError::Input(format!(
                "backward of {n} samples; the workspace holds a forward of {kept}"
            )));
        }
        if let Some(c) = count
            && c.max() > n
        {
            return Err(GpuError::Input(format!(
                "a count of up to {} samples, buffers for {n}",
                c.max()
            )));
        }
        check_slice(
            "output gradients",
            &d_out,
            bytes_of_floats(4 * u64::from(n)),
        )?;
        check_len("weight gradients", grad, bytes_of_floats(self.mlp_end))?;
        check_len(
            "encoding gradients",
            d_enc,
            bytes_of_floats(u64::from(self.n_enc - 1) * u64::from(batch.ld) + u64::from(n)),
        )?;
        if n == 0 {
            return Ok(());
        }
        let tiles = self.dispatch_of(ctx, n, count, 0)?;
        let n_chunks = n.div_ceil(CHUNK);
        let chunks = match count {
            None => Groups::Host([n_chunks, 1]),
            Some(_) => self.dispatch_of(ctx, n, count, 1)?,
        };
        let x = self.n_weights.div_ceil(WORKGROUP);
        let first_level = match count {
            None => Groups::Host([x, n_chunks.div_ceil(REDUCE_GROUP)]),
            Some(_) => self.dispatch_of(ctx, n, count, 2)?,
        };
        ctx.scoped("mlp backward", || {
            let params = |stage| {
                Self::params(
                    ctx,
                    MlpParams {
                        n,
                        ld_enc: batch.ld,
                        ld: ws.capacity,
                        store: 1,
                        tiles_x: self.tiles_x(ctx, n),
                        stage,
                        _pad: [0; 2],
                    },
                )
            };
            let (p, p_final) = (params(0), params(1));
            if let Some(c) = count {
                c.copy_n(encoder, &p);
                c.copy_n(encoder, &p_final);
            }
            let d = &ctx.device;
            let group = |pipeline: &wgpu::ComputePipeline, entries: &[wgpu::BindGroupEntry]| {
                d.create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some("mlp backward"),
                    layout: &pipeline.get_bind_group_layout(0),
                    entries,
                })
            };
            let backward = group(
                &self.backward,
                &[
                    entry(0, batch.params),
                    entry(5, &ws.acts),
                    entry(6, &ws.dys),
                    slice_entry(7, &d_out),
                    entry(8, d_enc),
                    entry(11, &p),
                ],
            );
            Self::pass(encoder, &self.backward, &backward, tiles);
            for (m, pipeline) in self.wgrad.iter().enumerate() {
                // The density input matrix's X is the encoding; the others' are saved
                // activations.
                let mut entries = vec![
                    entry(5, &ws.acts),
                    entry(6, &ws.dys),
                    entry(9, &ws.partials),
                    entry(11, &p),
                ];
                if m == 0 {
                    entries.push(entry(1, batch.enc));
                }
                let g = group(pipeline, &entries);
                Self::pass(encoder, pipeline, &g, chunks);
            }
            let first = group(
                &self.reduce,
                &[entry(9, &ws.partials), entry(10, grad), entry(11, &p)],
            );
            Self::pass(encoder, &self.reduce, &first, first_level);
            let last = group(
                &self.reduce,
                &[entry(9, &ws.partials), entry(10, grad), entry(11, &p_final)],
            );
            Self::pass(encoder, &self.reduce, &last, [x, 1]);
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

/// The functions `mlp.wgsl` calls and the weight-gradient kernels, written out for the
/// density MLP's `din` inputs: every accumulator index a constant.
fn generated_wgsl(din: u32) -> String {
    let mut s = String::new();
    for r in [16, 4] {
        layer_product(&mut s, &format!("mmF{r}"), "wt4", r);
        layer_product(&mut s, &format!("mmB{r}"), "weights4", r);
        row_writes(&mut s, r);
    }
    let rd = din / 4;
    layer_product(&mut s, "mmBD", "weights4", rd);
    let _ = writeln!(
        s,
        "fn d_enc_rows(a: array<vec4<f32>, {rd}>, row0: u32, sl: u32) {{"
    );
    for i in 0..rd {
        let _ = writeln!(s, "    d_enc4(row0 + {i}u, sl, a[{i}]);");
    }
    s.push_str("}\n");
    for (m, shape) in wgrad_shapes(din).iter().enumerate() {
        wgrad_kernel(&mut s, m, shape);
    }
    s
}

/// `fn name(b4, stride4, n_k, lane) -> array<vec4<f32>, r>`: rows `r` of a layer's product
/// for the lane's 4 samples, Σ_k W[row][k] · tile[k], the weights of input k the `r / 4`
/// vec4 at `b4 + k·stride4` of `weights`.
fn layer_product(s: &mut String, name: &str, weights: &str, r: u32) {
    let _ = writeln!(
        s,
        "fn {name}(b4: u32, stride4: u32, n_k: u32, lane: u32) -> array<vec4<f32>, {r}> {{\n    \
         var a: array<vec4<f32>, {r}>;\n    for (var k = 0u; k < n_k; k++) {{\n        \
         let x = tile[k * LANES + lane];\n        let b = b4 + k * stride4;"
    );
    for q in 0..r / 4 {
        let _ = writeln!(s, "        let w{q} = {weights}[b + {q}u];");
        for (m, c) in ["x", "y", "z", "w"].iter().enumerate() {
            let i = 4 * q + m as u32;
            let _ = writeln!(s, "        a[{i}] = fma(vec4<f32>(w{q}.{c}), x, a[{i}]);");
        }
    }
    s.push_str("    }\n    return a;\n}\n");
}

/// A row block's writes: `relu{r}`, `put{r}` (into the tile), `keep{r}` (to acts),
/// `mask{r}` (zero where the saved activation is ≤ 0, as the CPU's ReLU mask), `dy{r}` (to
/// dys).
fn row_writes(s: &mut String, r: u32) {
    let ty = format!("array<vec4<f32>, {r}>");
    let _ = writeln!(s, "fn relu{r}(a: {ty}) -> {ty} {{\n    var b = a;");
    for i in 0..r {
        let _ = writeln!(s, "    b[{i}] = max(a[{i}], vec4<f32>(0.0));");
    }
    s.push_str("    return b;\n}\n");
    let _ = writeln!(s, "fn put{r}(a: {ty}, row0: u32, lane: u32) {{");
    for i in 0..r {
        let _ = writeln!(s, "    tile[(row0 + {i}u) * LANES + lane] = a[{i}];");
    }
    s.push_str("}\n");
    for (name, buf) in [("keep", "acts4"), ("dy", "dys4")] {
        let _ = writeln!(s, "fn {name}{r}(a: {ty}, row0: u32, sl: u32) {{");
        for i in 0..r {
            let _ = writeln!(s, "    {buf}[at4(row0 + {i}u, sl)] = a[{i}];");
        }
        s.push_str("}\n");
    }
    let _ = writeln!(
        s,
        "fn mask{r}(a: {ty}, row0: u32, sl: u32) -> {ty} {{\n    var b = a;\n    \
         if (sl < p.n) {{"
    );
    for i in 0..r {
        let _ = writeln!(
            s,
            "        b[{i}] = select(a[{i}], vec4<f32>(0.0), \
             acts4[at4(row0 + {i}u, sl)] <= vec4<f32>(0.0));"
        );
    }
    s.push_str("    }\n    return b;\n}\n");
}

/// The five weight matrices' gradient shapes, in the parameter vector's order.
fn wgrad_shapes(din: u32) -> [WgradShape; 5] {
    let w = WIDTH as u32;
    let dout = DENSITY_OUT as u32;
    [
        WgradShape {
            name: "density input",
            off: "OFF_D0",
            rows_used: w,
            rows: w,
            rows_stored: w,
            cols: din,
            dy_row: "G_DH",
            x_row: None,
            rg: 16,
        },
        WgradShape {
            name: "density output",
            off: "OFF_D1",
            rows_used: dout,
            rows: dout,
            rows_stored: dout,
            cols: w,
            dy_row: "G_DOUT",
            x_row: Some("A_DH"),
            rg: 16,
        },
        WgradShape {
            name: "colour input",
            off: "OFF_C0",
            rows_used: w,
            rows: w,
            rows_stored: w,
            cols: dout + SH_DIMS as u32,
            dy_row: "G_H1",
            x_row: Some("A_CIN"),
            rg: 16,
        },
        WgradShape {
            name: "colour hidden",
            off: "OFF_C1",
            rows_used: w,
            rows: w,
            rows_stored: w,
            cols: w,
            dy_row: "G_H2",
            x_row: Some("A_H1"),
            rg: 16,
        },
        // 3 rgb rows of the 16 stored, computed as 4.
        WgradShape {
            name: "colour output",
            off: "OFF_C2",
            rows_used: 3,
            rows: 4,
            rows_stored: 16,
            cols: w,
            dy_row: "G_RGB",
            x_row: Some("A_H2"),
            rg: 4,
        },
    ]
}

/// `wgrad_{m}`: per chunk of CH samples, partial dW[o][i] = Σ_s dY[o][s] · X[i][s] of matrix
/// `m`, to partials[chunk·NW + (offset − OFF_D0) + o·cols + i] (its padded rows: 0). Staged
/// ST samples at a time; invocation lid owns rows `lid % rg + rg·i` and columns
/// `lid / rg + cg·j`: per sample rr + cc workgroup reads (distinct banks, or one address)
/// feed rr·cc multiply-adds.
fn wgrad_kernel(s: &mut String, m: usize, w: &WgradShape) {
    let rg = w.rg;
    let cg = WORKGROUP / rg;
    let rr = w.rows / rg;
    let cc = w.cols / cg;
    debug_assert!(rr * rg == w.rows && cc * cg == w.cols && rr >= 1 && cc >= 1);
    let _ = writeln!(
        s,
        "// {name}: {rows} × {cols}.\n@compute @workgroup_size(128)\nfn wgrad_{m}(\n    \
         @builtin(workgroup_id) wid: vec3<u32>,\n    \
         @builtin(local_invocation_index) lid: u32,\n) {{\n    let chunk = wid.x;\n    \
         let rg = lid % {rg}u;\n    let cg = lid / {rg}u;\n    \
         var acc: array<f32, {n}>;\n    let begin = chunk * CH;\n    \
         let end = min(begin + CH, p.n);\n    for (var b = begin; b < end; b += ST) {{\n        \
         stage_saved(true, {dy}, {used}u, b, end, lid, true);",
        name = w.name,
        rows = w.rows_used,
        cols = w.cols,
        n = rr * cc,
        dy = w.dy_row,
        used = w.rows_used,
    );
    if w.rows > w.rows_used {
        // The computed rows past the used ones read zeros.
        let _ = writeln!(
            s,
            "        for (var e = {u}u * SP + lid; e < {r}u * SP; e += WG) {{ shy[e] = 0.0; }}",
            u = w.rows_used,
            r = w.rows
        );
    }
    match w.x_row {
        Some(x) => {
            let _ = writeln!(
                s,
                "        stage_saved(false, {x}, {c}u, b, end, lid, false);",
                c = w.cols
            );
        }
        None => s.push_str("        stage_enc(b, end, lid);\n"),
    }
    s.push_str("        workgroupBarrier();\n        for (var t = 0u; t < ST; t++) {\n");
    for i in 0..rr {
        let _ = writeln!(
            s,
            "            let y{i} = shy[(rg + {}u) * SP + t];",
            rg * i
        );
    }
    for j in 0..cc {
        let _ = writeln!(
            s,
            "            let x{j} = shx[(cg + {}u) * SP + t];",
            cg * j
        );
    }
    for i in 0..rr {
        for j in 0..cc {
            let k = i * cc + j;
            let _ = writeln!(s, "            acc[{k}] = fma(y{i}, x{j}, acc[{k}]);");
        }
    }
    s.push_str("        }\n        workgroupBarrier();\n    }\n");
    let _ = writeln!(
        s,
        "    let base = chunk * NW + {off} - OFF_D0;",
        off = w.off
    );
    for i in 0..rr {
        for j in 0..cc {
            let _ = writeln!(
                s,
                "    if (rg + {ri}u < {used}u) {{ partials[base + (rg + {ri}u) * {cols}u + cg + \
                 {cj}u] = acc[{k}]; }}",
                ri = rg * i,
                cj = cg * j,
                used = w.rows_used,
                cols = w.cols,
                k = i * cc + j,
            );
        }
    }
    if w.rows_stored > w.rows_used {
        let _ = writeln!(
            s,
            "    for (var e = {a}u + lid; e < {b}u; e += WG) {{ partials[base + e] = 0.0; }}",
            a = w.rows_used * w.cols,
            b = w.rows_stored * w.cols,
        );
    }
    s.push_str("}\n");
}
