//! The CPU optimizer's step (Adam + EMA over every parameter, `touched` = None) on a
//! lego-sized parameter vector: 12 M parameters, two workers' gradient buffers, two
//! gradients in three non-zero. Prints the fastest of 10 steps (after 2 of warm-up) and a
//! weight, which must not change between builds of the same arithmetic.
//!
//! RAYON_NUM_THREADS=2 cargo run --release --example bench_optimizer

use std::time::Instant;
use stegongp::ngp::train::optimizer::{Optimizer, OptimizerConfig};

fn main() {
    let n = 12_000_000usize;
    let mut opt = Optimizer::new(OptimizerConfig::default(), n, 10_000);
    let mut w: Vec<f32> = (0..n).map(|i| (i as f32 * 0.37).sin()).collect();
    let mut grads = vec![vec![0.0f32; n]; 2];
    let mut best = f64::MAX;
    for step in 0..12u32 {
        for (k, g) in grads.iter_mut().enumerate() {
            for (i, x) in g.iter_mut().enumerate() {
                let h = (i as u32)
                    .wrapping_mul(2_654_435_761)
                    .wrapping_add(step * 7 + k as u32);
                *x = if h.is_multiple_of(3) {
                    0.0
                } else {
                    (h % 1000) as f32 * 1e-4 - 0.05
                };
            }
        }
        let t0 = Instant::now();
        opt.step(&mut w, &mut grads, None);
        if step >= 2 {
            best = best.min(t0.elapsed().as_secs_f64());
        }
    }
    println!(
        "optimizer step over {n} parameters: {:.1} ms (fastest of 10); w[5] = {}",
        best * 1e3,
        w[5]
    );
}
