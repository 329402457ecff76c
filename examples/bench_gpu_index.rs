//! Hash-grid index evaluations per second on the GPU adapter found, per kind of key, beside
//! one CPU core evaluating the same corners (and checking that both agree bit for bit).
//!
//! cargo run --release --example bench_gpu_index -- [CELLS_PER_LEVEL] [auto|software|any]
//! (default: 65536 random cells on each of the paper layout's 16 levels, on the hardware
//! adapter if there is one, else the software one)

use std::sync::Arc;
use std::time::Instant;
use stegongp::gpu::{CornerKernel, GpuContext, GpuIndex};
use stegongp::ngp::encoding::{GridConfig, GridLayout, LevelIndices, reference_indices};
use stegongp::rng::Pcg32;
use stegongp::stego::stealth::confine;
use stegongp::stego::{DenseMode, SchemeKind, generate_with};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let per_level: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(1 << 16);
    let ctx = GpuContext::from_arg(args.get(2).map(String::as_str)).unwrap_or_else(|e| {
        eprintln!("{e}");
        std::process::exit(1);
    });
    println!("adapter: {}", ctx.report());
    let layout = GridLayout::new(GridConfig::default(), 1).unwrap();
    let l = layout.levels.len();
    let mut rng = Pcg32::new(1, 2);
    let cells: Vec<[u32; 3]> = (0..per_level * l)
        .map(|i| {
            let r = layout.levels[i % l].resolution;
            [rng.below(r), rng.below(r), rng.below(r)]
        })
        .collect();
    let key = |kind, dense| {
        let mut rng = Pcg32::new(7, 3);
        generate_with(kind, 16, || {
            Ok((rng.next_u32() as u64) << 32 | rng.next_u32() as u64)
        })
        .unwrap()
        .with_dense(dense)
    };
    // Stealth maps onto a tenth of each level's slots.
    let maps: Vec<Arc<[u32]>> = layout
        .levels
        .iter()
        .map(|lv| (0..lv.size).map(|i| i / 10 * 10).collect())
        .collect();
    let kinds: [(&str, LevelIndices); 6] = [
        ("reference (the cover)", reference_indices(&layout)),
        (
            "primes, dense permuted",
            key(SchemeKind::Primes, DenseMode::Permute).level_indices(&layout),
        ),
        (
            "primes, dense hashed (u64 mod)",
            key(SchemeKind::Primes, DenseMode::Hash).level_indices(&layout),
        ),
        (
            "prf, dense permuted",
            key(SchemeKind::Prf, DenseMode::Permute).level_indices(&layout),
        ),
        (
            "prf, dense hashed",
            key(SchemeKind::Prf, DenseMode::Hash).level_indices(&layout),
        ),
        (
            "prf, dense permuted, stealth",
            confine(&key(SchemeKind::Prf, DenseMode::Permute), &layout, &maps),
        ),
    ];
    let kernel = CornerKernel::new(&ctx).unwrap();
    println!(
        "{per_level} cells × {l} levels, 8 corners each: M index evaluations/s, best of 5 \
         (GPU: dispatch and wait; CPU: LevelIndex::corners)"
    );
    println!("{:<32} {:>10} {:>12}", "index", "GPU", "CPU 1 core");
    let evals = (8 * cells.len()) as f64;
    for (name, indices) in kinds {
        let index = GpuIndex::upload(&ctx, &indices).unwrap();
        let batch = kernel.prepare(&ctx, &index, &cells).unwrap();
        let gpu = best_of(5, || batch.dispatch(&ctx).unwrap());
        let got = batch.read(&ctx).unwrap();
        let mut want = vec![[0u32; 8]; cells.len()];
        let cpu = best_of(5, || {
            for (i, (c, o)) in cells.iter().zip(want.iter_mut()).enumerate() {
                indices[i % l].corners(*c, o);
            }
        });
        assert!(got == want, "{name}: GPU and CPU indices differ");
        println!(
            "{name:<32} {:>10.1} {:>12.1}",
            evals / gpu / 1e6,
            evals / cpu / 1e6
        );
    }
    println!("GPU and CPU indices bit-identical on every corner");
}

fn best_of(n: usize, mut f: impl FnMut()) -> f64 {
    (0..n)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}
