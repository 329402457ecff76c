//! Hash-grid index functions on the device: one [`GpuLevel`] record per level plus one
//! buffer of all levels' tables, evaluated by the WGSL in `index.wgsl` bit for bit as the
//! CPU evaluates them (reference, `primes` with u64 products, SipHash-2-4 `prf`, keyed
//! permutation tables, stealth confinement maps). The engine's kernels include
//! [`INDEX_WGSL`]; [`CornerKernel`] runs it alone, for the tests and the benchmark.

use super::{GpuContext, GpuError, GpuResult, buffer_entry as entry, check_binding};
use ngp::encoding::{IndexFn, LevelIndex};
use std::sync::Mutex;
use wgpu::util::DeviceExt;

/// u64 arithmetic on pairs of u32 words, for kernels that need it without the index.
pub const U64_WGSL: &str = include_str!("u64.wgsl");
/// The CPU's PCG32 in WGSL (after [`U64_WGSL`]), for kernels that draw as the CPU draws.
pub const PCG_WGSL: &str = include_str!("pcg.wgsl");
/// The index functions (with [`U64_WGSL`] first), to be concatenated into any kernel that
/// indexes the grid.
pub const INDEX_WGSL: &str = concat!(include_str!("u64.wgsl"), include_str!("index.wgsl"));
const CORNERS_WGSL: &str = include_str!("corners.wgsl");

/// One level's index function as the device reads it (`struct LevelIndex` in
/// `index.wgsl`, 72 bytes): a [`LevelIndex`] with its u64 values split into (low, high) u32
/// words and its table placed in the one buffer of all levels' tables.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct GpuLevel {
    /// 0 reference, 1 primes, 2 SipHash.
    pub kind: u32,
    pub resolution: u32,
    pub size: u32,
    pub dense: u32,
    /// `primes`: k1, k2, k3.
    pub k: [[u32; 2]; 3],
    /// `prf`: the SipHash key (k0, k1).
    pub sip: [[u32; 2]; 2],
    /// Where the level's table starts in the tables buffer; `table_len` 0: no table.
    pub table_offset: u32,
    pub table_len: u32,
    /// `floor((2^64 − 1) / size)`: the device reduces u64 hashes modulo a size that is not a
    /// power of two by multiplying with it (Barrett), not by dividing.
    pub mu: [u32; 2],
}

fn words(v: u64) -> [u32; 2] {
    [v as u32, (v >> 32) as u32]
}

impl GpuLevel {
    /// The record of `index`, its table not yet placed.
    fn new(index: &LevelIndex) -> GpuLevel {
        let (kind, k, sip) = match index.base {
            IndexFn::Reference => (0, [0; 3], [0; 2]),
            IndexFn::Primes(k) => (1, k, [0; 2]),
            IndexFn::Sip(key) => (2, [0; 3], key),
        };
        GpuLevel {
            kind,
            resolution: index.resolution,
            size: index.size,
            dense: index.dense as u32,
            k: k.map(words),
            sip: sip.map(words),
            table_offset: 0,
            table_len: 0,
            mu: words(u64::MAX.checked_div(index.size as u64).unwrap_or(0)),
        }
    }
}

/// Level records and all their tables packed into one array: a kernel binds two buffers,
/// whatever the number of levels.
fn pack(indices: &[LevelIndex]) -> GpuResult<(Vec<GpuLevel>, Vec<u32>)> {
    if indices.is_empty() {
        return Err(GpuError::Input("no levels".into()));
    }
    let mut levels = Vec::with_capacity(indices.len());
    let mut tables = Vec::new();
    for (l, index) in indices.iter().enumerate() {
        if index.size == 0 {
            return Err(GpuError::Input(format!("level {l} has size 0")));
        }
        let mut record = GpuLevel::new(index);
        if let Some(t) = &index.table {
            let offset = u32::try_from(tables.len()).ok();
            let len = u32::try_from(t.len()).ok();
            match (offset, len) {
                (Some(o), Some(n)) if o.checked_add(n).is_some() => {
                    record.table_offset = o;
                    record.table_len = n;
                }
                _ => return Err(GpuError::Input("index tables past 2^32 entries".into())),
            }
            tables.extend_from_slice(t);
        }
        levels.push(record);
    }
    Ok((levels, tables))
}

/// A grid's index functions resident on the device.
pub struct GpuIndex {
    pub levels: wgpu::Buffer,
    pub tables: wgpu::Buffer,
    n_levels: u32,
    kinds: u32,
}

impl GpuIndex {
    /// Uploads one index function per level (what `Key::level_indices` and
    /// `stealth::confine` hand the engine).
    pub fn upload(ctx: &GpuContext, indices: &[LevelIndex]) -> GpuResult<GpuIndex> {
        let (levels, tables) = pack(indices)?;
        // A binding cannot be empty: a grid without tables binds one unused word.
        let tables: &[u32] = if tables.is_empty() { &[0] } else { &tables };
        check_binding(ctx, "index tables", 4 * tables.len() as u64)?;
        ctx.scoped("index upload", || {
            let init = |label, contents: &[u8]| {
                ctx.device
                    .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                        label: Some(label),
                        contents,
                        usage: wgpu::BufferUsages::STORAGE,
                    })
            };
            GpuIndex {
                levels: init("index levels", bytemuck::cast_slice(&levels)),
                tables: init("index tables", bytemuck::cast_slice(tables)),
                n_levels: levels.len() as u32,
                kinds: levels.iter().fold(0, |m, l| m | 1 << l.kind),
            }
        })
    }

    pub fn n_levels(&self) -> u32 {
        self.n_levels
    }

    /// The kinds of index present, bit k for kind k (`INDEX_KINDS` in `index.wgsl`).
    pub fn kinds(&self) -> u32 {
        self.kinds
    }

    /// The pipeline constants of a kernel that evaluates this index: only the kinds it has
    /// are compiled in.
    pub fn constants(&self) -> [(&'static str, f64); 1] {
        [("INDEX_KINDS", self.kinds as f64)]
    }
}

/// The compute pipelines of `corners.wgsl`: 8 corner indices per (cell, level), one
/// pipeline per set of index kinds, made when first needed.
pub struct CornerKernel {
    module: wgpu::ShaderModule,
    pipelines: Mutex<[Option<wgpu::ComputePipeline>; 8]>,
}

const WORKGROUP: u32 = 64;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct CornerParams {
    n_items: u32,
    n_levels: u32,
    row_width: u32,
    _pad: u32,
}

/// Cells and results of one corner evaluation, resident on the device, so that the
/// benchmark can time dispatches alone.
pub struct CornerBatch {
    pipeline: wgpu::ComputePipeline,
    bind_group: wgpu::BindGroup,
    out: wgpu::Buffer,
    n_pairs: u32,
    groups: [u32; 3],
}

impl CornerKernel {
    pub fn new(ctx: &GpuContext) -> GpuResult<CornerKernel> {
        let source = format!("{INDEX_WGSL}\n{CORNERS_WGSL}");
        let module = ctx.scoped("corner kernel", || {
            ctx.device
                .create_shader_module(wgpu::ShaderModuleDescriptor {
                    label: Some("corners.wgsl"),
                    source: wgpu::ShaderSource::Wgsl(source.into()),
                })
        })?;
        Ok(CornerKernel {
            module,
            pipelines: Mutex::new(Default::default()),
        })
    }

    fn pipeline(&self, ctx: &GpuContext, index: &GpuIndex) -> GpuResult<wgpu::ComputePipeline> {
        let mut cache = self
            .pipelines
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        let slot = &mut cache[index.kinds as usize & 7];
        if let Some(p) = slot {
            return Ok(p.clone());
        }
        let p = ctx.scoped("corner pipeline", || {
            ctx.device
                .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some("corners"),
                    layout: None,
                    module: &self.module,
                    entry_point: Some("corners_main"),
                    compilation_options: wgpu::PipelineCompilationOptions {
                        constants: &index.constants(),
                        ..Default::default()
                    },
                    cache: None,
                })
        })?;
        Ok(slot.insert(p).clone())
    }

    /// Uploads `cells` (cell `i·L + l` is item i's cell on level l, L = `index.n_levels()`)
    /// and binds them with `index`.
    pub fn prepare(
        &self,
        ctx: &GpuContext,
        index: &GpuIndex,
        cells: &[[u32; 3]],
    ) -> GpuResult<CornerBatch> {
        let l = index.n_levels as usize;
        if cells.is_empty() || !cells.len().is_multiple_of(l) {
            return Err(GpuError::Input(format!(
                "{} cells for {l} levels: need a positive multiple",
                cells.len()
            )));
        }
        let n_pairs = u32::try_from(cells.len())
            .map_err(|_| GpuError::Input("more than 2^32 cells".into()))?;
        check_binding(ctx, "cells", 12 * n_pairs as u64)?;
        check_binding(ctx, "corners", 32 * n_pairs as u64)?;
        // One level per workgroup (z), so that a level's branch is uniform across it; items
        // past one row of workgroups fold into y.
        let n_items = n_pairs / index.n_levels;
        let max_dim = ctx.device.limits().max_compute_workgroups_per_dimension;
        let n_groups = n_items.div_ceil(WORKGROUP);
        let gx = n_groups.min(max_dim);
        let gy = n_groups.div_ceil(gx);
        if gy > max_dim || index.n_levels > max_dim {
            return Err(GpuError::Input(format!("{n_pairs} cells in one dispatch")));
        }
        let params = CornerParams {
            n_items,
            n_levels: index.n_levels,
            row_width: gx * WORKGROUP,
            _pad: 0,
        };
        let pipeline = self.pipeline(ctx, index)?;
        ctx.scoped("corner buffers", || {
            let d = &ctx.device;
            let cells = d.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("cells"),
                contents: bytemuck::cast_slice(cells),
                usage: wgpu::BufferUsages::STORAGE,
            });
            let out = d.create_buffer(&wgpu::BufferDescriptor {
                label: Some("corners"),
                size: 32 * n_pairs as u64,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            });
            let params = d.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("corner params"),
                contents: bytemuck::bytes_of(&params),
                usage: wgpu::BufferUsages::UNIFORM,
            });
            let bind_group = d.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("corners"),
                layout: &pipeline.get_bind_group_layout(0),
                entries: &[
                    entry(0, &index.levels),
                    entry(1, &index.tables),
                    entry(2, &cells),
                    entry(3, &out),
                    entry(4, &params),
                ],
            });
            CornerBatch {
                pipeline,
                bind_group,
                out,
                n_pairs,
                groups: [gx, gy, index.n_levels],
            }
        })
    }

    /// The corners of every cell, in the order of `cells` (upload, run, read back).
    pub fn corners(
        &self,
        ctx: &GpuContext,
        index: &GpuIndex,
        cells: &[[u32; 3]],
    ) -> GpuResult<Vec<[u32; 8]>> {
        let batch = self.prepare(ctx, index, cells)?;
        batch.dispatch(ctx)?;
        batch.read(ctx)
    }
}

impl CornerBatch {
    /// Runs the kernel over the batch and waits for it.
    pub fn dispatch(&self, ctx: &GpuContext) -> GpuResult<()> {
        ctx.scoped("corner dispatch", || {
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            {
                let mut pass = enc.begin_compute_pass(&Default::default());
                pass.set_pipeline(&self.pipeline);
                pass.set_bind_group(0, &self.bind_group, &[]);
                let [x, y, z] = self.groups;
                pass.dispatch_workgroups(x, y, z);
            }
            ctx.queue.submit([enc.finish()]);
        })?;
        ctx.wait()
    }

    pub fn read(&self, ctx: &GpuContext) -> GpuResult<Vec<[u32; 8]>> {
        ctx.read_buffer(&self.out, 32 * self.n_pairs as u64)
    }

    /// Number of (cell, level) pairs.
    pub fn len(&self) -> usize {
        self.n_pairs as usize
    }

    pub fn is_empty(&self) -> bool {
        self.n_pairs == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_context;
    use ngp::encoding::index::{REFERENCE_PRIMES, coherent_prime_hash};

    fn level(resolution: u32, size: u32, dense: bool, base: IndexFn) -> LevelIndex {
        LevelIndex {
            resolution,
            size,
            dense,
            base,
            table: None,
        }
    }

    fn run(levels: &[LevelIndex], cells: &[[u32; 3]]) -> Vec<[u32; 8]> {
        let ctx = test_context().expect("checked by the caller");
        let index = GpuIndex::upload(ctx, levels).unwrap();
        CornerKernel::new(ctx)
            .unwrap()
            .corners(ctx, &index, cells)
            .unwrap()
    }

    #[test]
    fn records_split_u64_words_and_place_tables() {
        assert_eq!(std::mem::size_of::<GpuLevel>(), 72);
        let primes = level(16, 12, true, IndexFn::Primes([1 << 40 | 7, 2, 3]));
        let sip = level(16, 4096, true, IndexFn::Sip([5, u64::MAX])).with_table(vec![1; 4096]);
        let (levels, tables) = pack(&[primes.with_table(vec![0; 12]), sip]).unwrap();
        assert_eq!((levels[0].kind, levels[0].k[0]), (1, [7, 256]));
        assert_eq!(levels[0].mu, [0x5555_5555, 0x1555_5555]); // (2^64 − 1) / 12
        assert_eq!((levels[1].kind, levels[1].sip[1]), (2, [u32::MAX; 2]));
        assert_eq!((levels[1].table_offset, levels[1].table_len), (12, 4096));
        assert_eq!(tables.len(), 12 + 4096);
    }

    /// The 64-bit emulation against u64 arithmetic where it is hardest: products that
    /// wrap, and sizes from 3 to 2^32 − 1 (past 2^31, h − q·s passes 2^32 in Barrett).
    #[test]
    fn wide_products_and_modulo_are_exact() {
        if test_context().is_none() {
            return;
        }
        let k = [0xffff_ffff_ffff_fffb, 0x8000_0001_0000_0003, 0x3_ffff_fffd];
        let sizes = [
            1u32,
            3,
            12_168,
            (1 << 24) - 3,
            1 << 24,
            25_672_376,
            (1 << 31) + 11,
            u32::MAX,
        ];
        let levels: Vec<_> = sizes
            .iter()
            .map(|&s| level(2048, s, true, IndexFn::Primes(k)))
            .collect();
        let probes = [
            [0u32, 0, 0],
            [1, 2, 3],
            [0xffff_fffe, 0x8000_0000, 12345],
            [2047, 2047, 2047],
        ];
        let cells: Vec<[u32; 3]> = probes
            .iter()
            .flat_map(|&p| std::iter::repeat_n(p, sizes.len()))
            .collect();
        let got = run(&levels, &cells);
        for (i, (cell, corners)) in cells.iter().zip(&got).enumerate() {
            let size = sizes[i % sizes.len()] as u64;
            for (c, &got) in corners.iter().enumerate() {
                let h = (0..3).fold(0u64, |h, d| {
                    let v = cell[d] as u64 + (c >> d & 1) as u64;
                    h ^ v.wrapping_mul(k[d])
                });
                assert_eq!(got as u64, h % size, "cell {cell:?} size {size} corner {c}");
            }
        }
    }

    #[test]
    fn reference_hash_by_hand() {
        if test_context().is_none() {
            return;
        }
        let got = run(
            &[level(2048, 1 << 19, false, IndexFn::Reference)],
            &[[1, 2, 3], [0, 0, 0]],
        );
        // Worked out in ngp::encoding::index's tests.
        assert_eq!(got[0][0], 128_476);
        assert_eq!(got[1][0], 0);
        let h = coherent_prime_hash(2, 3, 4, REFERENCE_PRIMES);
        assert_eq!(got[0][7], h & ((1 << 19) - 1));
    }

    #[test]
    fn tables_are_looked_up_and_entries_past_them_are_refused() {
        if test_context().is_none() {
            return;
        }
        let size = 64u32;
        let dense = level(4, size, true, IndexFn::Reference);
        let rev: Vec<u32> = (0..size).rev().collect();
        let levels = [dense.clone().with_table(rev), dense.with_table(vec![9; 4])];
        let got = run(&levels, &[[0, 0, 0], [1, 0, 0]]);
        // Dense corners of cell 0 on res 4: 0, 1, 4, 5, 16, 17, 20, 21.
        assert_eq!(got[0], [63, 62, 59, 58, 47, 46, 43, 42]);
        // A table shorter than the level (one LevelIndex::check refuses): u32::MAX, as the
        // CPU gives, past its end.
        let m = u32::MAX;
        assert_eq!(got[1], [9, 9, m, m, m, m, m, m]);
    }

    #[test]
    fn bad_inputs_are_errors() {
        let Some(ctx) = test_context() else { return };
        assert!(GpuIndex::upload(ctx, &[]).is_err());
        let dense = level(4, 64, true, IndexFn::Reference);
        let empty = level(4, 0, true, IndexFn::Reference);
        assert!(GpuIndex::upload(ctx, &[dense.clone(), empty]).is_err());
        let index = GpuIndex::upload(ctx, &[dense.clone(), dense]).unwrap();
        assert_eq!(index.kinds(), 1);
        let k = CornerKernel::new(ctx).unwrap();
        assert!(k.prepare(ctx, &index, &[[0, 0, 0]; 3]).is_err());
        assert!(k.prepare(ctx, &index, &[]).is_err());
    }
}
