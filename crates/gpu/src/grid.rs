//! The hash-grid encoding on the device, forward and backward (`grid.wgsl`), computing what
//! the CPU's [`ngp::encoding::grid`] computes: the same cells (the `scale·x + 0.5`
//! that picks them rounded once, as the CPU's `mul_add`, on every adapter), the same corner
//! entries ([`INDEX_WGSL`], bit-identical) and trilinear weights, and the sums in the CPU's
//! order with WGSL's `fma`, which some adapters (llvmpipe) round twice: outputs agree to a
//! few ulp, the entries read exactly.
//!
//! Buffers stay on the device: [`GridEncoding::bind_forward`] and
//! [`GridEncoding::bind_backward`] take slices of buffers a trainer owns (the grid block of
//! its parameter vector, its gradient vector, the MLP's input and input-gradient matrices)
//! and give a [`GridDispatch`] to record into the trainer's own compute pass;
//! [`GridEncoding::bind_forward_half`] reads an fp16 copy of the table instead
//! ([`GridEncoding::half_table`], as tiny-cuda-nn's forward reads fp16). Layouts:
//!
//! - positions: 3 f32 per sample, in [0, 1]^3;
//! - table and gradient: level l's entry e, feature f at `(offset_l + e)·F + f`, f32;
//! - encoded features and their gradient: feature-major, feature `l·F + f` of sample s at
//!   `(l·F + f)·ld + s` with `ld ≥ n` (the CPU's `enc`). Consecutive invocations (samples)
//!   write consecutive words, and the MLP reads a feature row of a tile of samples
//!   contiguously. The forward writes zeros for the padding samples `n..ld`, so an MLP may
//!   run over whole tiles; the backward ignores them.
//!
//! The backward adds into the gradient (clear it first, as on the CPU) with float atomics
//! where the adapter has them, or with a compare-and-swap loop on the words' bits
//! ([`GradAtomics`]). The upload and download helpers at the end are for tests and
//! benchmarks only.

use super::count::{DeviceCount, Slot};
use super::{GpuContext, GpuError, GpuIndex, GpuResult, INDEX_WGSL, buffer_entry};
use ngp::encoding::{GridLayout, LevelIndex, check_indices};
use std::num::NonZeroU64;
use std::sync::Mutex;
use wgpu::util::DeviceExt;

const GRID_WGSL: &str = include_str!("grid.wgsl");

// The gradient binding and its accumulation, one of two, appended to grid.wgsl: a module
// that declares `atomic<f32>` does not validate on a device without the feature, so the
// choice is made in the source. Adding zero is skipped: it changes no value (but −0) and
// costs an atomic.
const GRAD_FLOAT_WGSL: &str = "
@group(0) @binding(8) var<storage, read_write> grad: array<atomic<f32>>;

fn grad_add(i: u32, v: f32) {
    if (v != 0.0) {
        atomicAdd(&grad[i], v);
    }
}
";

// Without float atomics: retry until no other invocation changed the word in between.
// Every failed exchange means another's succeeded, so the loop always makes progress.
const GRAD_CAS_WGSL: &str = "
@group(0) @binding(8) var<storage, read_write> grad: array<atomic<u32>>;

fn grad_add(i: u32, v: f32) {
    if (v == 0.0) {
        return;
    }
    var old = atomicLoad(&grad[i]);
    loop {
        let r = atomicCompareExchangeWeak(&grad[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if (r.exchanged) {
            break;
        }
        old = r.old_value;
    }
}
";

/// Invocations per workgroup (`@workgroup_size` in `grid.wgsl`).
const WORKGROUP: u32 = 128;

/// How the backward accumulates into the gradient.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GradAtomics {
    /// Float atomics if the adapter has them ([`super::AdapterReport::float32_atomics`]),
    /// else compare-and-swap.
    Auto,
    /// `atomicAdd` on `atomic<f32>` (`SHADER_FLOAT32_ATOMIC`); an error where the adapter
    /// lacks it.
    Float,
    /// A compare-and-swap loop on `atomic<u32>` holding the floats' bits: every adapter.
    CompareSwap,
}

/// One level's geometry as `grid.wgsl` reads it (`struct GridLevel`, 16 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
struct GridLevel {
    scale: f32,
    offset: u32,
    size: u32,
    _pad: u32,
}

/// `struct GridParams` in `grid.wgsl`: `n_samples` first, at byte 0 of
/// [`GridDispatch::params_buffer`].
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
struct GridParams {
    n_samples: u32,
    ld: u32,
    row_width: u32,
    /// [`GridEncoding::bind_copy`]: the leading dimension copied from (0 elsewhere).
    from_ld: u32,
}

/// Samples of one dispatch: `n_samples` real ones of a batch laid out with leading
/// dimension `ld ≥ n_samples` (the padded sample count the buffers are sized for).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GridShape {
    pub n_samples: u32,
    pub ld: u32,
}

impl GridShape {
    /// `n` samples, no padding.
    pub fn new(n: u32) -> GridShape {
        GridShape {
            n_samples: n,
            ld: n,
        }
    }
}

type PipelineCache = Mutex<[Option<wgpu::ComputePipeline>; 8]>;

/// The encoding's kernels for one grid layout (pipelines made per set of index kinds when
/// first needed), and the layout's per-level geometry on the device.
pub struct GridEncoding {
    layout: GridLayout,
    levels: wgpu::Buffer,
    atomics: GradAtomics,
    /// The adapter's fma rounds once ([`GpuContext::fma_fused`]): the cells come from it.
    hardware_fma: bool,
    module: wgpu::ShaderModule,
    forward: PipelineCache,
    forward_half: PipelineCache,
    backward: PipelineCache,
    pack: PipelineCache,
    copy: PipelineCache,
    /// Workgroups per dispatch row before folding into y; the device's limit, lowered by
    /// the unit tests to exercise the fold.
    max_groups_x: u32,
}

#[derive(Clone, Copy)]
enum Pass {
    Forward,
    ForwardHalf,
    Backward,
    Pack,
    Copy,
}

impl Pass {
    fn entry(self) -> &'static str {
        match self {
            Pass::Forward => "forward_main",
            Pass::ForwardHalf => "forward_half_main",
            Pass::Backward => "backward_main",
            Pass::Pack => "pack_half_main",
            Pass::Copy => "copy_main",
        }
    }

    fn what(self) -> &'static str {
        match self {
            Pass::Forward => "grid forward",
            Pass::ForwardHalf => "grid forward (fp16 table)",
            Pass::Backward => "grid backward",
            Pass::Pack => "grid table to fp16",
            Pass::Copy => "grid encodings copied",
        }
    }
}

/// The grid table's fp16 copy on the device (tiny-cuda-nn's forward reads fp16 parameters;
/// the f32 master stays for Adam), and the dispatch that refreshes it from the f32 table.
/// Made by [`GridEncoding::half_table`], read by [`GridEncoding::bind_forward_half`].
pub struct HalfTable {
    buffer: wgpu::Buffer,
    pack: GridDispatch,
}

impl HalfTable {
    /// Records the copy from the f32 table (its contents when the dispatch runs): record it
    /// after the last change to the table and before the forwards that read the copy.
    pub fn encode_pack(&self, encoder: &mut wgpu::CommandEncoder) {
        self.pack
            .record(&mut encoder.begin_compute_pass(&Default::default()));
    }

    /// The copy: `n_params / 2` words, each two fp16 (`pack2x16float`, low half first).
    pub fn buffer(&self) -> &wgpu::Buffer {
        &self.buffer
    }
}

/// One bound dispatch of the forward or the backward: record it into a compute pass as
/// often as needed (the buffers' contents may change between runs; their identity not).
pub struct GridDispatch {
    pipeline: wgpu::ComputePipeline,
    bind_group: wgpu::BindGroup,
    params: wgpu::Buffer,
    ld: u32,
    groups: [u32; 3],
    what: &'static str,
}

fn input<T>(msg: impl Into<String>) -> GpuResult<T> {
    Err(GpuError::Input(msg.into()))
}

/// Workgroups `[x, y]` covering `items` invocations, at most `max_x` per row.
fn fold_groups(items: u32, max_x: u32, max_dim: u32) -> GpuResult<[u32; 2]> {
    let n = items.div_ceil(WORKGROUP).max(1);
    let x = n.min(max_x.max(1));
    let y = n.div_ceil(x);
    if y > max_dim {
        return input(format!("{items} samples in one dispatch"));
    }
    Ok([x, y])
}

/// That `slice` can be bound as a storage buffer of `need` bytes (and then binds exactly
/// those); `exact`: the slice must be that long, not longer.
fn storage_binding<'a>(
    ctx: &GpuContext,
    what: &str,
    slice: wgpu::BufferSlice<'a>,
    need: u64,
    exact: bool,
) -> GpuResult<wgpu::BufferBinding<'a>> {
    let limits = ctx.device.limits();
    if !slice.buffer().usage().contains(wgpu::BufferUsages::STORAGE) {
        return input(format!("{what}: buffer without STORAGE usage"));
    }
    let align = limits.min_storage_buffer_offset_alignment as u64;
    if !slice.offset().is_multiple_of(align) {
        return input(format!(
            "{what}: offset {} is not a multiple of the device's {align}-byte storage alignment",
            slice.offset()
        ));
    }
    let have = slice.size();
    if have < need || (exact && have != need) {
        return input(format!(
            "{what}: {have} bytes, need {}{need}",
            if exact { "" } else { "at least " }
        ));
    }
    let max = limits
        .max_storage_buffer_binding_size
        .min(limits.max_buffer_size);
    if need > max {
        return input(format!(
            "{what}: {need} bytes, past the device's {max}-byte storage binding"
        ));
    }
    let size = NonZeroU64::new(need).ok_or_else(|| GpuError::Input(format!("{what}: 0 bytes")))?;
    Ok(wgpu::BufferBinding {
        buffer: slice.buffer(),
        offset: slice.offset(),
        size: Some(size),
    })
}

impl GridEncoding {
    /// The kernels for `layout` (F = 1, 2, 4 or 8 features per level), with the gradient
    /// accumulated as `atomics` asks.
    pub fn new(ctx: &GpuContext, layout: &GridLayout, atomics: GradAtomics) -> GpuResult<Self> {
        let f = layout.config.n_features;
        if ![1, 2, 4, 8].contains(&f) {
            return input(format!(
                "{f} features per level: the GPU grid takes 1, 2, 4 or 8"
            ));
        }
        let max_dim = ctx.device.limits().max_compute_workgroups_per_dimension;
        let nl = layout.levels.len();
        if nl == 0 || nl as u64 > max_dim as u64 {
            return input(format!("{nl} grid levels"));
        }
        let n_entries = layout.n_entries as u64;
        if n_entries * f as u64 > u32::MAX as u64 {
            return input("grid past 2^32 parameters");
        }
        for lv in &layout.levels {
            if lv.size == 0 || lv.offset as u64 + lv.size as u64 > n_entries {
                return input(format!(
                    "level {}: entries {}..{} outside the grid's {n_entries}",
                    lv.level,
                    lv.offset,
                    lv.offset as u64 + lv.size as u64
                ));
            }
        }
        let float = ctx.report().float32_atomics;
        let atomics = match atomics {
            GradAtomics::Auto if float => GradAtomics::Float,
            GradAtomics::Auto => GradAtomics::CompareSwap,
            GradAtomics::Float if !float => {
                return input(format!(
                    "{} has no float atomics (SHADER_FLOAT32_ATOMIC)",
                    ctx.report().name
                ));
            }
            a => a,
        };
        let grad = match atomics {
            GradAtomics::Float => GRAD_FLOAT_WGSL,
            _ => GRAD_CAS_WGSL,
        };
        let source = format!("{INDEX_WGSL}\n{GRID_WGSL}\n{grad}");
        let records: Vec<GridLevel> = layout
            .levels
            .iter()
            .map(|lv| GridLevel {
                scale: lv.scale,
                offset: lv.offset,
                size: lv.size,
                _pad: 0,
            })
            .collect();
        let (module, levels) = ctx.scoped("grid kernel", || {
            let module = ctx
                .device
                .create_shader_module(wgpu::ShaderModuleDescriptor {
                    label: Some("grid.wgsl"),
                    source: wgpu::ShaderSource::Wgsl(source.into()),
                });
            let levels = ctx
                .device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some("grid levels"),
                    contents: bytemuck::cast_slice(&records),
                    usage: wgpu::BufferUsages::STORAGE,
                });
            (module, levels)
        })?;
        Ok(GridEncoding {
            layout: layout.clone(),
            levels,
            atomics,
            hardware_fma: ctx.fma_fused()?,
            module,
            forward: Mutex::new(Default::default()),
            forward_half: Mutex::new(Default::default()),
            backward: Mutex::new(Default::default()),
            pack: Mutex::new(Default::default()),
            copy: Mutex::new(Default::default()),
            max_groups_x: max_dim,
        })
    }

    /// Whether the cells come from the adapter's own fma (fused, [`GpuContext::fma_fused`])
    /// rather than the exact integer emulation.
    pub fn hardware_fma(&self) -> bool {
        self.hardware_fma
    }

    /// How this encoding's backward accumulates ([`GradAtomics::Auto`] resolved).
    pub fn atomics(&self) -> GradAtomics {
        self.atomics
    }

    pub fn layout(&self) -> &GridLayout {
        &self.layout
    }

    /// Uploads `indices` after checking that they index this layout's levels
    /// ([`check_indices`]): an entry outside its level would otherwise read (and write)
    /// nothing on the device where the CPU refuses it.
    pub fn upload_index(&self, ctx: &GpuContext, indices: &[LevelIndex]) -> GpuResult<GpuIndex> {
        check_indices(indices, &self.layout).map_err(|e| GpuError::Input(e.to_string()))?;
        GpuIndex::upload(ctx, indices)
    }

    /// The copy reads no index: one pipeline, made with the default index kinds.
    fn pack_pipeline(&self, ctx: &GpuContext) -> GpuResult<wgpu::ComputePipeline> {
        self.pipeline_for(ctx, 7, Pass::Pack)
    }

    fn pipeline(
        &self,
        ctx: &GpuContext,
        index: &GpuIndex,
        pass: Pass,
    ) -> GpuResult<wgpu::ComputePipeline> {
        self.pipeline_for(ctx, index.kinds(), pass)
    }

    fn pipeline_for(
        &self,
        ctx: &GpuContext,
        kinds: u32,
        pass: Pass,
    ) -> GpuResult<wgpu::ComputePipeline> {
        let cache = match pass {
            Pass::Forward => &self.forward,
            Pass::ForwardHalf => &self.forward_half,
            Pass::Backward => &self.backward,
            Pass::Pack => &self.pack,
            Pass::Copy => &self.copy,
        };
        let mut cache = cache.lock().unwrap_or_else(|p| p.into_inner());
        let slot = &mut cache[kinds as usize & 7];
        if let Some(p) = slot {
            return Ok(p.clone());
        }
        let constants = [
            ("INDEX_KINDS", kinds as f64),
            ("N_FEATURES", self.layout.config.n_features as f64),
            ("HARDWARE_FMA", self.hardware_fma as u32 as f64),
        ];
        let p = ctx.scoped(pass.what(), || {
            ctx.device
                .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some(pass.what()),
                    layout: None,
                    module: &self.module,
                    entry_point: Some(pass.entry()),
                    compilation_options: wgpu::PipelineCompilationOptions {
                        constants: &constants,
                        ..Default::default()
                    },
                    cache: None,
                })
        })?;
        Ok(slot.insert(p).clone())
    }

    /// Width of the encoding (`L·F` rows of `ld` floats).
    fn width(&self) -> u64 {
        self.layout.config.n_output_dims() as u64
    }

    fn check_shape(&self, index: &GpuIndex, shape: GridShape) -> GpuResult<()> {
        let nl = self.layout.levels.len() as u32;
        if index.n_levels() != nl {
            return input(format!(
                "an index of {} levels for a grid of {nl}",
                index.n_levels()
            ));
        }
        self.check_ld(shape)
    }

    fn check_ld(&self, shape: GridShape) -> GpuResult<()> {
        if shape.ld == 0 || shape.n_samples > shape.ld {
            return input(format!(
                "{} samples with leading dimension {}: need 0 < n ≤ ld",
                shape.n_samples, shape.ld
            ));
        }
        // Word indices in the kernels are u32.
        if self.width() * shape.ld as u64 > u32::MAX as u64 || 3 * shape.ld as u64 > u32::MAX as u64
        {
            return input(format!("leading dimension {} past 2^32 words", shape.ld));
        }
        Ok(())
    }

    /// The forward over `positions` (3·ld f32) with `table` (exactly the grid's
    /// `n_params` f32) into `enc` (`L·F·ld` f32).
    pub fn bind_forward(
        &self,
        ctx: &GpuContext,
        index: &GpuIndex,
        positions: wgpu::BufferSlice<'_>,
        table: wgpu::BufferSlice<'_>,
        enc: wgpu::BufferSlice<'_>,
        shape: GridShape,
    ) -> GpuResult<GridDispatch> {
        let ld = shape.ld as u64;
        let n_params = self.layout.n_params() as u64;
        self.bind(
            ctx,
            index,
            shape,
            Pass::Forward,
            [
                (4, "positions", positions, 12 * ld, false),
                (5, "grid table", table, 4 * n_params, true),
                (6, "encoding", enc, 4 * self.width() * ld, false),
            ],
        )
    }

    /// The encodings of `shape`'s samples copied into `enc` (`L·F·ld` f32) from `from_enc`,
    /// an earlier forward's encodings laid out with leading dimension `from_ld`: sample `s`
    /// gets the columns of sample `from[s]` (each below `from_ld`). What
    /// [`Self::bind_forward`] would write over those samples' positions, with the same
    /// parameters, without reading the table again.
    pub fn bind_copy(
        &self,
        ctx: &GpuContext,
        from: wgpu::BufferSlice<'_>,
        from_enc: wgpu::BufferSlice<'_>,
        from_ld: u32,
        enc: wgpu::BufferSlice<'_>,
        shape: GridShape,
    ) -> GpuResult<GridDispatch> {
        self.check_ld(shape)?;
        self.check_ld(GridShape::new(from_ld))?;
        let (ld, width) = (shape.ld as u64, self.width());
        let pipeline = self.pipeline_for(ctx, 0, Pass::Copy)?;
        let buffers = [
            (10, "copied samples' sources", from, 4 * ld, false),
            (
                11,
                "encodings copied from",
                from_enc,
                4 * width * from_ld as u64,
                false,
            ),
            (6, "encoding", enc, 4 * width * ld, false),
        ];
        self.bound(ctx, Pass::Copy, pipeline, shape, from_ld, &[], buffers)
    }

    /// An fp16 copy of `table` (exactly the grid's `n_params` f32), refreshed by
    /// [`HalfTable::encode_pack`], for [`Self::bind_forward_half`]. Features go in pairs:
    /// an error for an odd F.
    pub fn half_table(
        &self,
        ctx: &GpuContext,
        table: wgpu::BufferSlice<'_>,
    ) -> GpuResult<HalfTable> {
        let f = self.layout.config.n_features;
        if !f.is_multiple_of(2) {
            return input(format!(
                "{f} feature per level: the fp16 table holds features in pairs"
            ));
        }
        let n_params = self.layout.n_params() as u64;
        let words = u32::try_from(n_params / 2)
            .map_err(|_| GpuError::Input("grid past 2^33 parameters".into()))?;
        let table = storage_binding(ctx, "grid table", table, 4 * n_params, true)?;
        let max_dim = ctx.device.limits().max_compute_workgroups_per_dimension;
        let [gx, gy] = fold_groups(words, self.max_groups_x.min(max_dim), max_dim)?;
        let params = GridParams {
            n_samples: words,
            ld: words,
            row_width: gx * WORKGROUP,
            from_ld: 0,
        };
        let pipeline = self.pack_pipeline(ctx)?;
        ctx.scoped(Pass::Pack.what(), || {
            let buffer = ctx.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("grid table, fp16"),
                size: 4 * words as u64,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            });
            let params = ctx
                .device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some("grid pack params"),
                    contents: bytemuck::bytes_of(&params),
                    usage: wgpu::BufferUsages::UNIFORM,
                });
            let bind_group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some(Pass::Pack.what()),
                layout: &pipeline.get_bind_group_layout(0),
                entries: &[
                    buffer_entry(3, &params),
                    wgpu::BindGroupEntry {
                        binding: 5,
                        resource: wgpu::BindingResource::Buffer(table),
                    },
                    buffer_entry(10, &buffer),
                ],
            });
            HalfTable {
                buffer,
                pack: GridDispatch {
                    pipeline,
                    bind_group,
                    params,
                    ld: words,
                    groups: [gx, gy, 1],
                    what: Pass::Pack.what(),
                },
            }
        })
    }

    /// [`Self::bind_forward`] reading the fp16 copy `half` (of this grid's table) instead of
    /// the f32 table: the same entries and weights, the features rounded to fp16.
    pub fn bind_forward_half(
        &self,
        ctx: &GpuContext,
        index: &GpuIndex,
        positions: wgpu::BufferSlice<'_>,
        half: &HalfTable,
        enc: wgpu::BufferSlice<'_>,
        shape: GridShape,
    ) -> GpuResult<GridDispatch> {
        let ld = shape.ld as u64;
        let n_params = self.layout.n_params() as u64;
        self.bind(
            ctx,
            index,
            shape,
            Pass::ForwardHalf,
            [
                (4, "positions", positions, 12 * ld, false),
                (
                    9,
                    "grid table, fp16",
                    half.buffer.slice(..),
                    2 * n_params,
                    true,
                ),
                (6, "encoding", enc, 4 * self.width() * ld, false),
            ],
        )
    }

    /// The backward: adds `w·d_enc` into `grad` (exactly the grid's `n_params` f32) at the
    /// entries the forward over the same `positions` and index reads. `d_enc` has the
    /// encoding's layout.
    pub fn bind_backward(
        &self,
        ctx: &GpuContext,
        index: &GpuIndex,
        positions: wgpu::BufferSlice<'_>,
        d_enc: wgpu::BufferSlice<'_>,
        grad: wgpu::BufferSlice<'_>,
        shape: GridShape,
    ) -> GpuResult<GridDispatch> {
        let ld = shape.ld as u64;
        let n_params = self.layout.n_params() as u64;
        self.bind(
            ctx,
            index,
            shape,
            Pass::Backward,
            [
                (4, "positions", positions, 12 * ld, false),
                (7, "encoding gradient", d_enc, 4 * self.width() * ld, false),
                (8, "grid gradient", grad, 4 * n_params, true),
            ],
        )
    }

    /// The dispatch shape of a pass bound with a leading dimension of `ld`, for a
    /// [`DeviceCount`] its [`GridDispatch::record_counted`] takes: the rows folded as the
    /// pass's parameters fold them, one level per z.
    pub fn count_slot(&self, ctx: &GpuContext, ld: u32) -> GpuResult<Slot> {
        let max_dim = ctx.device.limits().max_compute_workgroups_per_dimension;
        let [gx, _] = fold_groups(ld, self.max_groups_x.min(max_dim), max_dim)?;
        Ok(Slot {
            divisor: WORKGROUP,
            max_x: gx,
            z: self.layout.levels.len() as u32,
            fixed_x: 0,
        })
    }

    fn bind(
        &self,
        ctx: &GpuContext,
        index: &GpuIndex,
        shape: GridShape,
        pass: Pass,
        buffers: [(u32, &str, wgpu::BufferSlice<'_>, u64, bool); 3],
    ) -> GpuResult<GridDispatch> {
        self.check_shape(index, shape)?;
        let pipeline = self.pipeline(ctx, index, pass)?;
        let fixed = [(0, &index.levels), (1, &index.tables), (2, &self.levels)];
        self.bound(ctx, pass, pipeline, shape, 0, &fixed, buffers)
    }

    /// `pipeline` over `shape` (one invocation a sample and level, rows folded into y),
    /// bound to a fresh uniform of its parameters (binding 3), the buffers `fixed` and the
    /// storage ranges `buffers` (binding, what, range, bytes needed, exactly).
    #[allow(clippy::too_many_arguments)]
    fn bound(
        &self,
        ctx: &GpuContext,
        pass: Pass,
        pipeline: wgpu::ComputePipeline,
        shape: GridShape,
        from_ld: u32,
        fixed: &[(u32, &wgpu::Buffer)],
        buffers: [(u32, &str, wgpu::BufferSlice<'_>, u64, bool); 3],
    ) -> GpuResult<GridDispatch> {
        let mut data = Vec::with_capacity(buffers.len());
        for (binding, what, slice, need, exact) in buffers {
            data.push((binding, storage_binding(ctx, what, slice, need, exact)?));
        }
        let max_dim = ctx.device.limits().max_compute_workgroups_per_dimension;
        let [gx, gy] = fold_groups(shape.ld, self.max_groups_x.min(max_dim), max_dim)?;
        let params = GridParams {
            n_samples: shape.n_samples,
            ld: shape.ld,
            row_width: gx * WORKGROUP,
            from_ld,
        };
        let groups = [gx, gy, self.layout.levels.len() as u32];
        ctx.scoped(pass.what(), || {
            let params = ctx
                .device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some("grid params"),
                    contents: bytemuck::bytes_of(&params),
                    usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                });
            let mut entries: Vec<_> = fixed.iter().map(|&(b, buf)| buffer_entry(b, buf)).collect();
            entries.push(buffer_entry(3, &params));
            entries.extend(data.into_iter().map(|(binding, b)| wgpu::BindGroupEntry {
                binding,
                resource: wgpu::BindingResource::Buffer(b),
            }));
            let bind_group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some(pass.what()),
                layout: &pipeline.get_bind_group_layout(0),
                entries: &entries,
            });
            GridDispatch {
                pipeline,
                bind_group,
                params,
                ld: shape.ld,
                groups,
                what: pass.what(),
            }
        })
    }
}

impl GridDispatch {
    /// Records the dispatch into a pass of the caller's (nothing is submitted).
    pub fn record(&self, pass: &mut wgpu::ComputePass<'_>) {
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        let [x, y, z] = self.groups;
        pass.dispatch_workgroups(x, y, z);
    }

    /// Records the dispatch into a pass of its own: counted on the device with `count`
    /// ([`Self::record_counted`]), else over its whole bound shape.
    pub fn record_maybe_counted(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        count: Option<&DeviceCount>,
    ) -> GpuResult<()> {
        match count {
            Some(c) => self.record_counted(encoder, c),
            None => {
                self.record(&mut encoder.begin_compute_pass(&Default::default()));
                Ok(())
            }
        }
    }

    /// Records the dispatch with the sample count known only on the device: `count`'s n
    /// copied into the parameters, its [`Self::count_slot`] arguments dispatched (nothing
    /// when n is 0). The count's maximum must not exceed the bound `ld`.
    pub fn record_counted(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        count: &DeviceCount,
    ) -> GpuResult<()> {
        if count.max() > self.ld {
            return input(format!(
                "a count of up to {} samples past the bound ld {}",
                count.max(),
                self.ld
            ));
        }
        let slot = count.slot(self.count_slot())?;
        count.copy_n(encoder, &self.params);
        let mut pass = encoder.begin_compute_pass(&Default::default());
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        count.dispatch(&mut pass, slot);
        Ok(())
    }

    /// The dispatch shape a [`DeviceCount`] must provide for [`Self::record_counted`]
    /// ([`GridEncoding::count_slot`] of this dispatch's `ld`).
    pub fn count_slot(&self) -> Slot {
        Slot {
            divisor: WORKGROUP,
            max_x: self.groups[0],
            z: self.groups[2],
            fixed_x: 0,
        }
    }

    /// Runs the dispatch alone and waits for it (tests, benchmarks).
    pub fn run(&self, ctx: &GpuContext) -> GpuResult<()> {
        ctx.scoped(self.what, || {
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            {
                let mut pass = enc.begin_compute_pass(&Default::default());
                self.record(&mut pass);
            }
            ctx.queue.submit([enc.finish()]);
        })?;
        ctx.wait()
    }

    /// Changes the number of real samples (at most the bound `ld`) for the dispatches
    /// submitted after this call.
    pub fn set_samples(&self, ctx: &GpuContext, n: u32) -> GpuResult<()> {
        if n > self.ld {
            return input(format!("{n} samples past the bound ld {}", self.ld));
        }
        ctx.queue
            .write_buffer(&self.params, 0, bytemuck::bytes_of(&n));
        Ok(())
    }

    /// The dispatch's parameters (`UNIFORM | COPY_DST`): the sample count is the u32 at
    /// byte 0, where a trainer can copy a count computed on the device (it must not exceed
    /// `ld`: the kernels then read past the real samples, within the bound buffers).
    pub fn params_buffer(&self) -> &wgpu::Buffer {
        &self.params
    }

    pub fn ld(&self) -> u32 {
        self.ld
    }
}

/// Test and benchmark helper: a storage buffer holding `data` (also a copy source and
/// destination, so that it can be read back and cleared).
pub fn upload_f32(ctx: &GpuContext, label: &str, data: &[f32]) -> GpuResult<wgpu::Buffer> {
    if data.is_empty() {
        return input(format!("{label}: empty"));
    }
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

/// Test and benchmark helper: `positions` padded with zeros to `ld` samples.
pub fn upload_positions(
    ctx: &GpuContext,
    positions: &[[f32; 3]],
    ld: u32,
) -> GpuResult<wgpu::Buffer> {
    if positions.len() > ld as usize {
        return input(format!("{} positions past ld {ld}", positions.len()));
    }
    let mut flat = positions.as_flattened().to_vec();
    flat.resize(3 * ld as usize, 0.0);
    upload_f32(ctx, "positions", &flat)
}

/// Test and benchmark helper: the first `len` f32 of `buffer` (a `COPY_SRC` buffer).
pub fn download_f32(ctx: &GpuContext, buffer: &wgpu::Buffer, len: usize) -> GpuResult<Vec<f32>> {
    if 4 * len as u64 > buffer.size() {
        return input(format!("{len} floats from a {}-byte buffer", buffer.size()));
    }
    ctx.read_buffer(buffer, 4 * len as u64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_context;
    use ngp::encoding::grid::{self, GridCache};
    use ngp::encoding::{GridConfig, reference_indices};
    use ngp::rng::Pcg32;

    #[test]
    fn groups_fold_into_rows() {
        assert_eq!(fold_groups(1, 65535, 65535).unwrap(), [1, 1]);
        assert_eq!(fold_groups(128 * 65535, 65535, 65535).unwrap(), [65535, 1]);
        assert_eq!(
            fold_groups(128 * 65535 + 1, 65535, 65535).unwrap(),
            [65535, 2]
        );
        assert_eq!(fold_groups(1000, 3, 65535).unwrap(), [3, 3]);
        assert!(fold_groups(u32::MAX, 2, 1000).is_err());
    }

    /// `fma_half`, the exact `scale·x + 0.5` that picks cells, bit for bit against the
    /// CPU's `mul_add` for every level scale of three boxes, on cell edges and one ulp
    /// either side, at 0, 1, tiny and subnormal positions, and at random.
    #[test]
    fn the_cell_fma_is_rounded_once() {
        let Some(ctx) = test_context() else { return };
        let mut rng = Pcg32::new(3, 3);
        let mut pairs: Vec<[f32; 2]> = Vec::new();
        for aabb in [1, 8, 128] {
            let layout = GridLayout::new(GridConfig::default(), aabb).unwrap();
            for lv in &layout.levels {
                let s = lv.scale;
                for x in [
                    0.0,
                    1.0,
                    1e-30,
                    1e-40,
                    f32::MIN_POSITIVE,
                    0.5,
                    1.0 - f32::EPSILON,
                ] {
                    pairs.push([s, x]);
                }
                for _ in 0..400 {
                    let k = 1 + rng.below(s as u32);
                    let edge = (k as f32 - 0.5) / s;
                    for x in [
                        edge,
                        f32::from_bits(edge.to_bits() + 1),
                        f32::from_bits(edge.to_bits() - 1),
                    ] {
                        pairs.push([s, x]);
                    }
                    pairs.push([s, rng.next_f32()]);
                    pairs.push([s, rng.next_f32() * 1e-6]);
                }
            }
        }
        // Products just past halfway between floats, where a double rounding goes wrong.
        for _ in 0..2000 {
            pairs.push([1.0 + rng.next_f32(), rng.next_f32()]);
        }
        let probe = format!(
            "{INDEX_WGSL}\n{GRID_WGSL}\n{GRAD_CAS_WGSL}
@group(0) @binding(9) var<storage, read_write> probe: array<f32>;
@compute @workgroup_size(64)
fn probe_main(@builtin(global_invocation_id) gid: vec3<u32>) {{
    let i = gid.x;
    if (2u * i + 1u < arrayLength(&probe)) {{
        probe[2u * i] = fma_half(probe[2u * i], probe[2u * i + 1u]);
    }}
}}"
        );
        let n = pairs.len();
        let fused = ctx.fma_fused().unwrap();
        let buf = upload_f32(ctx, "probe", pairs.as_flattened()).unwrap();
        ctx.scoped("probe", || {
            let d = &ctx.device;
            let module = d.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: None,
                source: wgpu::ShaderSource::Wgsl(probe.into()),
            });
            let pipeline = d.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: None,
                layout: None,
                module: &module,
                entry_point: Some("probe_main"),
                // The path the grid compiles on this adapter (the builtin where it is fused).
                compilation_options: wgpu::PipelineCompilationOptions {
                    constants: &[("HARDWARE_FMA", fused as u32 as f64)],
                    ..Default::default()
                },
                cache: None,
            });
            let bind_group = d.create_bind_group(&wgpu::BindGroupDescriptor {
                label: None,
                layout: &pipeline.get_bind_group_layout(0),
                entries: &[wgpu::BindGroupEntry {
                    binding: 9,
                    resource: buf.as_entire_binding(),
                }],
            });
            let mut enc = d.create_command_encoder(&Default::default());
            {
                let mut pass = enc.begin_compute_pass(&Default::default());
                pass.set_pipeline(&pipeline);
                pass.set_bind_group(0, &bind_group, &[]);
                pass.dispatch_workgroups((n as u32).div_ceil(64), 1, 1);
            }
            ctx.queue.submit([enc.finish()]);
        })
        .unwrap();
        let got = download_f32(ctx, &buf, 2 * n).unwrap();
        for (i, [s, x]) in pairs.iter().enumerate() {
            let want = s.mul_add(*x, 0.5);
            assert_eq!(
                got[2 * i].to_bits(),
                want.to_bits(),
                "fma_half({s:e}, {x:e}) = {:e}, CPU {want:e}",
                got[2 * i]
            );
        }
    }

    /// A dispatch folded into several rows (the row limit lowered to 3 workgroups) encodes
    /// and differentiates every sample as the CPU does.
    #[test]
    fn folded_dispatch_covers_every_sample() {
        let Some(ctx) = test_context() else { return };
        let layout = GridLayout::new(
            GridConfig {
                n_levels: 3,
                n_features: 2,
                log2_hashmap_size: 10,
                base_resolution: 4,
            },
            1,
        )
        .unwrap();
        let mut rng = Pcg32::new(4, 1);
        let table: Vec<f32> = (0..layout.n_params())
            .map(|_| rng.next_f32() * 2.0 - 1.0)
            .collect();
        let n = 1000usize;
        let pos: Vec<[f32; 3]> = (0..n)
            .map(|_| [rng.next_f32(), rng.next_f32(), rng.next_f32()])
            .collect();
        let indices = reference_indices(&layout);
        let width = layout.config.n_output_dims();
        let mut enc = vec![0f32; width * n];
        let mut cache = GridCache::new(&layout, n);
        grid::forward(&layout, &table, &indices, &pos, &mut cache, &mut enc, n);
        let d: Vec<f32> = (0..width * n).map(|i| (i % 7) as f32 - 3.0).collect();
        let mut want_grad = vec![0f32; layout.n_params()];
        grid::backward(&layout, &cache, &d, n, &mut want_grad);
        // Σ w·|d| per entry: the scale of each sum's rounding (a coarse entry here sums
        // ~100 terms in another order than the CPU).
        let abs: Vec<f32> = d.iter().map(|v| v.abs()).collect();
        let mut mag = vec![0f32; layout.n_params()];
        grid::backward(&layout, &cache, &abs, n, &mut mag);

        let mut g = GridEncoding::new(ctx, &layout, GradAtomics::CompareSwap).unwrap();
        g.max_groups_x = 3;
        let index = g.upload_index(ctx, &indices).unwrap();
        let shape = GridShape::new(n as u32);
        let p = upload_positions(ctx, &pos, shape.ld).unwrap();
        let t = upload_f32(ctx, "table", &table).unwrap();
        let e = upload_f32(ctx, "enc", &vec![7.0; width * n]).unwrap();
        let de = upload_f32(ctx, "d_enc", &d).unwrap();
        let gr = upload_f32(ctx, "grad", &vec![0.0; layout.n_params()]).unwrap();
        let fwd = g
            .bind_forward(ctx, &index, p.slice(..), t.slice(..), e.slice(..), shape)
            .unwrap();
        assert_eq!(fwd.groups, [3, 3, 3]);
        fwd.run(ctx).unwrap();
        let got = download_f32(ctx, &e, width * n).unwrap();
        for (i, (a, b)) in got.iter().zip(&enc).enumerate() {
            assert!(
                (a - b).abs() <= 1e-6 + 1e-5 * b.abs(),
                "enc {i}: {a} vs {b}"
            );
        }
        g.bind_backward(ctx, &index, p.slice(..), de.slice(..), gr.slice(..), shape)
            .unwrap()
            .run(ctx)
            .unwrap();
        let got = download_f32(ctx, &gr, layout.n_params()).unwrap();
        for (i, (a, b)) in got.iter().zip(&want_grad).enumerate() {
            assert!((a - b).abs() <= 1e-5 * mag[i], "grad {i}: {a} vs {b}");
        }
    }
}
