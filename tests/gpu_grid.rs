//! The GPU hash-grid encoding against the CPU's `grid::forward` and `grid::backward`: the
//! paper's layout under the reference index and real keys (prf, primes, dense levels
//! permuted, stealth-confined), a larger box, every feature count, both ways of
//! accumulating the gradient, and bad inputs. Runs on whatever adapter `test_context`
//! finds (lavapipe in CI).
//!
//! Tolerances. Forward: |gpu − cpu| ≤ 1e-6 + 1e-5·|cpu|. The kernel forms the cell, the
//! weights and the sum with the CPU's f32 operations in the CPU's order (fma where the CPU
//! has `mul_add`), so the outputs are expected to agree to a few ulp of the table's O(1)
//! values; WGSL only promises fma the accuracy of a multiply and an add, which the bound
//! allows, while a cell chosen differently (a non-fused `scale·x + 0.5` at a cell edge)
//! would move a fine level's output by ~1e-4 and fail it. Backward: |gpu − cpu| ≤
//! 1e-5·Σ w·|d_enc| per entry (the CPU's backward of |d_enc|): atomics add the k terms of an
//! entry in another order and round w·d before adding where the CPU fuses it, an error
//! below (k + 1)·2^-24·Σ|terms|; k stays under ~60 here. Entries the CPU's forward did not
//! read must stay exactly +0.
#![cfg(feature = "gpu")]

use std::sync::Arc;
use stegongp::gpu::grid::{download_f32, upload_f32, upload_positions};
use stegongp::gpu::{GpuContext, GpuError, GradAtomics, GridEncoding, GridShape, test_context};
use stegongp::ngp::encoding::grid::{self, GridCache};
use stegongp::ngp::encoding::{GridConfig, GridLayout, LevelIndex, reference_indices};
use stegongp::rng::Pcg32;
use stegongp::stego::stealth::confine;
use stegongp::stego::{DenseMode, SchemeKind};
use testkit::keys::seeded_key;

fn random_f32(n: usize, seed: u64) -> Vec<f32> {
    let mut r = Pcg32::new(seed, 5);
    (0..n).map(|_| r.next_f32() * 2.0 - 1.0).collect()
}

/// `n_random` random positions, then the cube's corners and face centres, then per level
/// positions on cell edges (`scale·x + 0.5` at or one ulp either side of an integer in one
/// coordinate, random in the others).
fn positions(layout: &GridLayout, n_random: usize, seed: u64) -> Vec<[f32; 3]> {
    let mut r = Pcg32::new(seed, 9);
    let mut out: Vec<[f32; 3]> = (0..n_random)
        .map(|_| [r.next_f32(), r.next_f32(), r.next_f32()])
        .collect();
    for c in 0..8 {
        out.push([(c & 1) as f32, (c >> 1 & 1) as f32, (c >> 2) as f32]);
    }
    for d in 0..3 {
        for v in [0.0, 1.0] {
            let mut p = [0.5; 3];
            p[d] = v;
            out.push(p);
        }
    }
    for lv in &layout.levels {
        for i in 0..12 {
            let k = 1 + r.below(lv.scale as u32);
            let edge = (k as f32 - 0.5) / lv.scale;
            let x = match i % 3 {
                0 => edge,
                1 => f32::from_bits(edge.to_bits() + 1),
                _ => f32::from_bits(edge.to_bits() - 1),
            }
            .clamp(0.0, 1.0);
            let mut p = [r.next_f32(), r.next_f32(), r.next_f32()];
            p[i % 3] = x;
            if i % 4 == 3 {
                p = [x; 3];
            }
            out.push(p);
        }
    }
    out
}

/// What the CPU engine gives for one batch.
struct Cpu {
    enc: Vec<f32>,
    grad: Vec<f32>,
    /// Σ w·|d_enc| per entry.
    mag: Vec<f32>,
    /// Parameters the forward read.
    touched: Vec<bool>,
}

fn cpu(
    layout: &GridLayout,
    table: &[f32],
    indices: &[LevelIndex],
    pos: &[[f32; 3]],
    d_enc: &[f32],
    ld: usize,
) -> Cpu {
    let n = pos.len();
    let width = layout.config.n_output_dims();
    let f = layout.config.n_features as usize;
    let mut enc = vec![0f32; width * ld];
    let mut cache = GridCache::new(layout, n);
    let indices = indices.to_vec();
    grid::forward(layout, table, &indices, pos, &mut cache, &mut enc, ld);
    let mut grad = vec![0f32; layout.n_params()];
    grid::backward(layout, &cache, d_enc, ld, &mut grad);
    let abs: Vec<f32> = d_enc.iter().map(|v| v.abs()).collect();
    let mut mag = vec![0f32; layout.n_params()];
    grid::backward(layout, &cache, &abs, ld, &mut mag);
    let mut touched = vec![false; layout.n_params()];
    for l in 0..layout.levels.len() {
        for s in 0..n {
            for &o in cache.corner_offsets(l, s) {
                touched[o as usize..o as usize + f].fill(true);
            }
        }
    }
    Cpu {
        enc,
        grad,
        mag,
        touched,
    }
}

/// One layout's kernels, both ways of accumulating, and its random table on the device.
struct Rig<'a> {
    ctx: &'a GpuContext,
    layout: GridLayout,
    table: Vec<f32>,
    table_buf: wgpu::Buffer,
    encodings: Vec<GridEncoding>,
}

impl<'a> Rig<'a> {
    fn new(ctx: &'a GpuContext, layout: GridLayout, seed: u64) -> Rig<'a> {
        let table = random_f32(layout.n_params(), seed);
        let table_buf = upload_f32(ctx, "table", &table).unwrap();
        let auto = GridEncoding::new(ctx, &layout, GradAtomics::Auto).unwrap();
        let cas = GridEncoding::new(ctx, &layout, GradAtomics::CompareSwap).unwrap();
        assert_eq!(cas.atomics(), GradAtomics::CompareSwap);
        if ctx.report().float32_atomics {
            assert_eq!(auto.atomics(), GradAtomics::Float);
        } else {
            assert_eq!(auto.atomics(), GradAtomics::CompareSwap);
            eprintln!("no float atomics on this adapter: compare-and-swap tested twice");
        }
        Rig {
            ctx,
            layout,
            table,
            table_buf,
            encodings: vec![auto, cas],
        }
    }

    /// Forward and backward of `pos` under `indices` on the device against the CPU, the
    /// backward once per way of accumulating; padded to a leading dimension past n.
    fn check(&self, what: &str, indices: &[LevelIndex], pos: &[[f32; 3]], seed: u64) {
        let ctx = self.ctx;
        let n = pos.len();
        let ld = (n + 100).next_multiple_of(128);
        let width = self.layout.config.n_output_dims();
        let mut d_enc = random_f32(width * ld, seed);
        // Padding columns carry a gradient the backward must ignore.
        for (i, v) in d_enc.iter_mut().enumerate() {
            if i % ld >= n {
                *v = 1e3;
            }
        }
        let want = cpu(&self.layout, &self.table, indices, pos, &d_enc, ld);
        let shape = GridShape {
            n_samples: n as u32,
            ld: ld as u32,
        };
        let p = upload_positions(ctx, pos, shape.ld).unwrap();
        let de = upload_f32(ctx, "d_enc", &d_enc).unwrap();
        for (k, g) in self.encodings.iter().enumerate() {
            let index = g.upload_index(ctx, indices).unwrap();
            if k == 0 {
                // Stale values everywhere, the padding included, must be overwritten.
                let e = upload_f32(ctx, "enc", &vec![f32::NAN; width * ld]).unwrap();
                g.bind_forward(
                    ctx,
                    &index,
                    p.slice(..),
                    self.table_buf.slice(..),
                    e.slice(..),
                    shape,
                )
                .unwrap()
                .run(ctx)
                .unwrap();
                let got = download_f32(ctx, &e, width * ld).unwrap();
                let (mut max, mut same) = (0f32, 0usize);
                for (i, (&a, &b)) in got.iter().zip(&want.enc).enumerate() {
                    let (j, s) = (i / ld, i % ld);
                    if s >= n {
                        assert_eq!(
                            a.to_bits(),
                            0,
                            "{what}: padding feature {j} sample {s}: {a}"
                        );
                        continue;
                    }
                    let err = (a - b).abs();
                    assert!(
                        err <= 1e-6 + 1e-5 * b.abs(),
                        "{what}: feature {j} sample {s} at {:?}: gpu {a} cpu {b}",
                        pos[s]
                    );
                    max = max.max(err);
                    same += (a.to_bits() == b.to_bits()) as usize;
                }
                eprintln!(
                    "{what}: forward max |Δ| {max:.2e}, {same} of {} bit-identical",
                    n * width
                );
            }
            let gr = upload_f32(ctx, "grad", &vec![0.0; self.layout.n_params()]).unwrap();
            g.bind_backward(ctx, &index, p.slice(..), de.slice(..), gr.slice(..), shape)
                .unwrap()
                .run(ctx)
                .unwrap();
            let got = download_f32(ctx, &gr, self.layout.n_params()).unwrap();
            let mut max_rel = 0f32;
            for (i, &a) in got.iter().enumerate() {
                if !want.touched[i] {
                    assert_eq!(a.to_bits(), 0, "{what}: unread parameter {i} got {a}");
                    continue;
                }
                let (b, m) = (want.grad[i], want.mag[i]);
                assert!(
                    (a - b).abs() <= 1e-5 * m,
                    "{what} ({:?}): parameter {i}: gpu {a} cpu {b} (Σ|terms| {m})",
                    g.atomics()
                );
                if m > 0.0 {
                    max_rel = max_rel.max((a - b).abs() / m);
                }
            }
            eprintln!(
                "{what}: backward ({:?}) max |Δ|/Σ|terms| {max_rel:.2e}",
                g.atomics()
            );
        }
    }
}

fn paper(aabb: u32) -> GridLayout {
    GridLayout::new(GridConfig::default(), aabb).unwrap()
}

#[test]
fn paper_layout_matches_the_cpu_under_every_index_kind() {
    let Some(ctx) = test_context() else { return };
    let layout = paper(1);
    let rig = Rig::new(ctx, layout.clone(), 1);
    let pos = positions(&layout, 3000, 2);
    rig.check("reference", &reference_indices(&layout), &pos, 3);
    for kind in [SchemeKind::Prf, SchemeKind::Primes] {
        let key = seeded_key(kind, 4, 7, 3).with_dense(DenseMode::Permute);
        let what = format!("{} dense permuted", kind.name());
        rig.check(&what, &key.level_indices(&layout), &pos, 4);
    }
    // Stealth: a prf key confined to a random tenth of each level's slots, as a cover's
    // reach would be (composed with the dense levels' permutation into one table).
    let mut rng = Pcg32::new(9, 1);
    let maps: Vec<Arc<[u32]>> = layout
        .levels
        .iter()
        .map(|lv| {
            let n = (lv.size / 10).max(1);
            (0..lv.size).map(|_| rng.below(n) * 10 % lv.size).collect()
        })
        .collect();
    let key = seeded_key(SchemeKind::Prf, 16, 21, 3);
    rig.check("stealth prf", &confine(&key, &layout, &maps), &pos, 5);
}

/// The layout depends on the box (per-level scale, resolutions past 2048).
#[test]
fn a_larger_box_matches_the_cpu() {
    let Some(ctx) = test_context() else { return };
    let layout = paper(8);
    let rig = Rig::new(ctx, layout.clone(), 11);
    let pos = positions(&layout, 2000, 12);
    rig.check("reference aabb 8", &reference_indices(&layout), &pos, 13);
    let key = seeded_key(SchemeKind::Primes, 16, 14, 3).with_dense(DenseMode::Hash);
    rig.check(
        "primes dense hashed aabb 8",
        &key.level_indices(&layout),
        &pos,
        15,
    );
}

#[test]
fn every_feature_count_matches_the_cpu() {
    let Some(ctx) = test_context() else { return };
    for (f, levels, log2) in [(1, 6, 12), (4, 8, 14), (8, 4, 12)] {
        let layout = GridLayout::new(
            GridConfig {
                n_levels: levels,
                n_features: f,
                log2_hashmap_size: log2,
                base_resolution: 8,
            },
            1,
        )
        .unwrap();
        let rig = Rig::new(ctx, layout.clone(), 20 + f as u64);
        let pos = positions(&layout, 1000, 30 + f as u64);
        let key = seeded_key(SchemeKind::Prf, 2, 40, 3).with_dense(DenseMode::Permute);
        rig.check(
            &format!("F = {f} reference"),
            &reference_indices(&layout),
            &pos,
            50,
        );
        rig.check(
            &format!("F = {f} prf"),
            &key.level_indices(&layout),
            &pos,
            51,
        );
    }
}

/// The sample count changed on the device side of a bound dispatch: the samples past it
/// read as padding.
#[test]
fn the_sample_count_can_change_after_binding() {
    let Some(ctx) = test_context() else { return };
    let layout = GridLayout::new(
        GridConfig {
            n_levels: 4,
            log2_hashmap_size: 12,
            ..GridConfig::default()
        },
        1,
    )
    .unwrap();
    let width = layout.config.n_output_dims();
    let table = random_f32(layout.n_params(), 1);
    let pos = positions(&layout, 300, 2);
    let ld = pos.len() as u32;
    let g = GridEncoding::new(ctx, &layout, GradAtomics::Auto).unwrap();
    let index = g.upload_index(ctx, &reference_indices(&layout)).unwrap();
    let p = upload_positions(ctx, &pos, ld).unwrap();
    let t = upload_f32(ctx, "table", &table).unwrap();
    let e = upload_f32(ctx, "enc", &vec![1.0; width * ld as usize]).unwrap();
    let fwd = g
        .bind_forward(
            ctx,
            &index,
            p.slice(..),
            t.slice(..),
            e.slice(..),
            GridShape::new(ld),
        )
        .unwrap();
    let half = ld / 2;
    fwd.set_samples(ctx, half).unwrap();
    assert!(matches!(
        fwd.set_samples(ctx, ld + 1),
        Err(GpuError::Input(_))
    ));
    fwd.run(ctx).unwrap();
    let got = download_f32(ctx, &e, width * ld as usize).unwrap();
    let want = cpu(
        &layout,
        &table,
        &reference_indices(&layout),
        &pos[..half as usize],
        &vec![0.0; width * ld as usize],
        ld as usize,
    );
    for (i, (&a, &b)) in got.iter().zip(&want.enc).enumerate() {
        let s = i as u32 % ld;
        if s >= half {
            assert_eq!(a, 0.0, "sample {s} past the count");
        } else {
            assert!((a - b).abs() <= 1e-6 + 1e-5 * b.abs(), "{i}: {a} vs {b}");
        }
    }
}

/// The trainer's copy of encodings (a one-chunk step's trained samples from the marched
/// ones): each copied sample's columns are, to the bit, what the forward at its position
/// writes, in a batch of another leading dimension, with zeros past the count; under a
/// keyed index, where a recomputation would be dearest.
#[test]
fn copied_encodings_are_the_forward_at_the_copied_samples() {
    let Some(ctx) = test_context() else { return };
    let layout = paper(1);
    let width = layout.config.n_output_dims();
    let table = random_f32(layout.n_params(), 4);
    let key = seeded_key(SchemeKind::Prf, 4, 3, 1);
    let indices = key.level_indices(&layout);
    let pos = positions(&layout, 500, 5);
    let ld = pos.len() as u32;
    let g = GridEncoding::new(ctx, &layout, GradAtomics::Auto).unwrap();
    let index = g.upload_index(ctx, &indices).unwrap();
    let t = upload_f32(ctx, "table", &table).unwrap();
    let forward = |pos: &[[f32; 3]], shape: GridShape| -> Vec<f32> {
        let p = upload_positions(ctx, pos, shape.ld).unwrap();
        let e = upload_f32(ctx, "enc", &vec![1.0; width * shape.ld as usize]).unwrap();
        g.bind_forward(ctx, &index, p.slice(..), t.slice(..), e.slice(..), shape)
            .unwrap()
            .run(ctx)
            .unwrap();
        download_f32(ctx, &e, width * shape.ld as usize).unwrap()
    };
    let marched = forward(&pos, GridShape::new(ld));
    let marched_buf = upload_f32(ctx, "marched", &marched).unwrap();
    // Out of order, repeated, the first and the last; 5 padding samples after them.
    let mut r = Pcg32::new(6, 1);
    let mut from: Vec<u32> = (0..200).map(|_| r.below(ld)).collect();
    from.extend([0, ld - 1, 7, 7]);
    let (m, ld2) = (from.len() as u32, from.len() as u32 + 5);
    // Sized for the leading dimension, as the trainer's is for its chunk: the count can
    // grow to it on the device.
    let from_words: Vec<f32> = from
        .iter()
        .chain(&[u32::MAX; 5])
        .map(|&i| f32::from_bits(i))
        .collect();
    let from_buf = upload_f32(ctx, "from", &from_words).unwrap();
    let copied = upload_f32(ctx, "copied", &vec![1.0; width * ld2 as usize]).unwrap();
    let shape = GridShape {
        n_samples: m,
        ld: ld2,
    };
    let bind = |from_ld: u32, shape: GridShape| {
        g.bind_copy(
            ctx,
            from_buf.slice(..),
            marched_buf.slice(..),
            from_ld,
            copied.slice(..),
            shape,
        )
    };
    bind(ld, shape).unwrap().run(ctx).unwrap();
    let got = download_f32(ctx, &copied, width * ld2 as usize).unwrap();
    let picked: Vec<[f32; 3]> = from.iter().map(|&i| pos[i as usize]).collect();
    let want = forward(&picked, shape);
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&got), bits(&want));
    assert!(got.iter().any(|&x| x != 0.0));
    for (i, &x) in got.iter().enumerate() {
        if i as u32 % ld2 >= m {
            assert_eq!(x.to_bits(), 0, "padding sample {}", i as u32 % ld2);
        }
    }
    // A copy from a batch of no samples, or a count past the leading dimension, is refused.
    let bad = |from_ld: u32, shape: GridShape| input(bind(from_ld, shape));
    assert!(bad(0, shape));
    assert!(bad(
        ld,
        GridShape {
            n_samples: ld2 + 1,
            ld: ld2
        }
    ));
}

fn input<T>(r: Result<T, GpuError>) -> bool {
    matches!(r, Err(GpuError::Input(_)))
}

#[test]
fn bad_inputs_are_errors_not_panics() {
    let Some(ctx) = test_context() else { return };
    let layout = GridLayout::new(
        GridConfig {
            n_levels: 4,
            log2_hashmap_size: 12,
            ..GridConfig::default()
        },
        1,
    )
    .unwrap();
    let width = layout.config.n_output_dims();
    let np = layout.n_params();
    let g = GridEncoding::new(ctx, &layout, GradAtomics::CompareSwap).unwrap();
    let indices = reference_indices(&layout);
    let index = g.upload_index(ctx, &indices).unwrap();
    let ld = 256u32;
    let shape = GridShape::new(ld);
    let buf = |n: usize| upload_f32(ctx, "buf", &vec![0.0; n]).unwrap();
    let (p, t, e) = (buf(3 * 256), buf(np), buf(width * 256));
    // The right sizes bind.
    assert!(
        g.bind_forward(ctx, &index, p.slice(..), t.slice(..), e.slice(..), shape)
            .is_ok()
    );
    assert!(
        g.bind_backward(ctx, &index, p.slice(..), e.slice(..), t.slice(..), shape)
            .is_ok()
    );
    let short = buf(3 * 255);
    let fwd = |p: &wgpu::Buffer, t: &wgpu::Buffer, e: &wgpu::Buffer, s: GridShape| {
        g.bind_forward(ctx, &index, p.slice(..), t.slice(..), e.slice(..), s)
    };
    assert!(input(fwd(&short, &t, &e, shape)), "positions short of ld");
    assert!(input(fwd(&p, &buf(np - 1), &e, shape)), "table short");
    assert!(input(fwd(&p, &buf(np + 1), &e, shape)), "table long");
    assert!(
        input(fwd(&p, &t, &buf(width * 256 - 1), shape)),
        "enc short"
    );
    let over = GridShape {
        n_samples: 257,
        ld: 256,
    };
    assert!(input(fwd(&p, &t, &e, over)), "n > ld");
    assert!(input(fwd(&p, &t, &e, GridShape::new(0))), "ld 0");
    let bwd = |d: &wgpu::Buffer, gr: &wgpu::Buffer| {
        g.bind_backward(ctx, &index, p.slice(..), d.slice(..), gr.slice(..), shape)
    };
    assert!(input(bwd(&buf(width * 256 - 1), &t)), "d_enc short");
    assert!(input(bwd(&e, &buf(np + 4))), "grad long");
    // The grid block at an offset of a larger parameter buffer binds; a misaligned one
    // does not.
    let align = ctx.device.limits().min_storage_buffer_offset_alignment as u64;
    let params = buf(np + align as usize);
    assert!(
        g.bind_forward(
            ctx,
            &index,
            p.slice(..),
            params.slice(align * 4..),
            e.slice(..),
            shape
        )
        .is_ok()
    );
    if align > 4 {
        let off = params.slice(4..4 + 4 * np as u64);
        assert!(input(g.bind_forward(
            ctx,
            &index,
            p.slice(..),
            off,
            e.slice(..),
            shape
        )));
    }
    // A buffer that cannot be bound as storage.
    let uniform = ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: None,
        size: 4 * np as u64,
        usage: wgpu::BufferUsages::UNIFORM,
        mapped_at_creation: false,
    });
    assert!(input(fwd(&p, &uniform, &e, shape)), "no STORAGE usage");
    // An index of another layout, and features per level the kernels do not take.
    let other = paper(1);
    assert!(input(g.upload_index(ctx, &reference_indices(&other))));
    let foreign = GridEncoding::new(ctx, &other, GradAtomics::Auto)
        .unwrap()
        .upload_index(ctx, &reference_indices(&other))
        .unwrap();
    assert!(input(g.bind_forward(
        ctx,
        &foreign,
        p.slice(..),
        t.slice(..),
        e.slice(..),
        shape
    )));
    let mut three = layout.clone();
    three.config.n_features = 3;
    assert!(input(GridEncoding::new(ctx, &three, GradAtomics::Auto)));
    if !ctx.report().float32_atomics {
        assert!(input(GridEncoding::new(ctx, &layout, GradAtomics::Float)));
    }
    // Out-of-level entries are refused at upload (the CPU panics on them).
    let bad: Vec<LevelIndex> = indices
        .iter()
        .map(|ix| ix.clone().with_table(vec![u32::MAX; ix.size as usize]))
        .collect();
    assert!(input(g.upload_index(ctx, &bad)));
}

/// The fp16 copy of the table holds each float rounded to the nearest fp16 (as the CPU's
/// `half` and a snapshot round), and the forward over it computes what the CPU's forward
/// computes over that rounded table (the same entries and weights; the forward tolerance).
/// An odd feature count is refused.
#[test]
fn the_fp16_table_is_the_rounded_table_and_the_forward_reads_it() {
    let Some(ctx) = test_context() else { return };
    for (f, levels, log2) in [(2, 16, 19), (4, 8, 14), (8, 4, 12)] {
        let layout = GridLayout::new(
            GridConfig {
                n_levels: levels,
                n_features: f,
                log2_hashmap_size: log2,
                base_resolution: 16,
            },
            1,
        )
        .unwrap();
        let mut table = random_f32(layout.n_params(), 60 + f as u64);
        // Values that round in every way: ties, subnormals, past the range (clamped).
        table[0] = 1.0 + 2f32.powi(-11);
        table[1] = 1e-6;
        table[2] = 1e6;
        table[3] = -7e4;
        let rounded: Vec<f32> = table
            .iter()
            .map(|&v| half::f16::from_f32(v.clamp(-65504.0, 65504.0)).to_f32())
            .collect();
        let buf = upload_f32(ctx, "table", &table).unwrap();
        let g = GridEncoding::new(ctx, &layout, GradAtomics::Auto).unwrap();
        let half = g.half_table(ctx, buf.slice(..)).unwrap();
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        half.encode_pack(&mut encoder);
        ctx.queue.submit([encoder.finish()]);
        let words: Vec<u32> = ctx
            .read_buffer(half.buffer(), 2 * layout.n_params() as u64)
            .unwrap();
        for (w, &word) in words.iter().enumerate() {
            for k in 0..2 {
                let want = half::f16::from_f32(rounded[2 * w + k]).to_bits();
                let got = (word >> (16 * k)) as u16;
                assert_eq!(
                    got,
                    want,
                    "F = {f}: float {} ({})",
                    2 * w + k,
                    table[2 * w + k]
                );
            }
        }

        let pos = positions(&layout, 1500, 70 + f as u64);
        let n = pos.len();
        let ld = n.next_multiple_of(128);
        let width = layout.config.n_output_dims();
        let indices = reference_indices(&layout);
        let want = cpu(
            &layout,
            &rounded,
            &indices,
            &pos,
            &vec![0.0; width * ld],
            ld,
        );
        let shape = GridShape {
            n_samples: n as u32,
            ld: ld as u32,
        };
        let p = upload_positions(ctx, &pos, shape.ld).unwrap();
        let e = upload_f32(ctx, "enc", &vec![f32::NAN; width * ld]).unwrap();
        let index = g.upload_index(ctx, &indices).unwrap();
        g.bind_forward_half(ctx, &index, p.slice(..), &half, e.slice(..), shape)
            .unwrap()
            .run(ctx)
            .unwrap();
        let got = download_f32(ctx, &e, width * ld).unwrap();
        let mut max = 0f32;
        for (i, (&a, &b)) in got.iter().zip(&want.enc).enumerate() {
            let (j, s) = (i / ld, i % ld);
            if s >= n {
                assert_eq!(a.to_bits(), 0, "F = {f}: padding feature {j} sample {s}");
                continue;
            }
            assert!(
                (a - b).abs() <= 1e-6 + 1e-5 * b.abs(),
                "F = {f}: feature {j} sample {s}: gpu {a} cpu over the rounded table {b}"
            );
            max = max.max((a - b).abs());
        }
        eprintln!("F = {f}: fp16 forward max |Δ| {max:.2e} against the CPU over the rounded table");
    }
    let odd = GridLayout::new(
        GridConfig {
            n_levels: 4,
            n_features: 1,
            log2_hashmap_size: 12,
            base_resolution: 8,
        },
        1,
    )
    .unwrap();
    let buf = upload_f32(ctx, "table", &vec![0.0; odd.n_params()]).unwrap();
    let g = GridEncoding::new(ctx, &odd, GradAtomics::Auto).unwrap();
    assert!(matches!(
        g.half_table(ctx, buf.slice(..)),
        Err(GpuError::Input(_))
    ));
}
