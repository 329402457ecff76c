//! What scoring one view costs beside its render: PSNR and SSIM of an 800×800 view, as
//! `eval` and `train`'s checkpoints compute them for every view (the render's SSIM and the
//! empty image's). On a GPU a view renders in tens of milliseconds, so this is most of an
//! evaluation there.
//!
//! cargo run --release --example bench_scoring -- [SIDE] [ROUNDS]   (default 800, 5)
//! LPIPS, which `eval` adds unless `--no-lpips`, is timed after them.

use std::time::Instant;
use stegongp::ngp::rng::Pcg32;
use stegongp::score::metrics::{psnr, ssim};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let side: usize = args.get(1).map_or(800, |s| s.parse().expect("SIDE"));
    let rounds: usize = args.get(2).map_or(5, |s| s.parse().expect("ROUNDS"));
    // A smooth image and a noisy copy: the metrics cost the same on any content.
    let mut rng = Pcg32::new(7, 1);
    let gt: Vec<f32> = (0..3 * side * side)
        .map(|i| (((i / 3) % side) as f32 / side as f32 + (i % 3) as f32 * 0.2).fract())
        .collect();
    let pred: Vec<f32> = gt
        .iter()
        .map(|v| v + 0.05 * (rng.next_f32() - 0.5))
        .collect();
    let blank = vec![1.0f32; gt.len()];
    let mut best = [f64::INFINITY; 3];
    let mut check = 0.0;
    for _ in 0..rounds {
        let t = Instant::now();
        check += psnr(&pred, &gt);
        let a = t.elapsed().as_secs_f64();
        let t = Instant::now();
        check += ssim(&pred, &gt, side, side);
        let b = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let (s, p) = rayon::join(
            || (psnr(&pred, &gt), ssim(&pred, &gt, side, side)),
            || (psnr(&blank, &gt), ssim(&blank, &gt, side, side)),
        );
        check += s.1 + p.1;
        let c = t.elapsed().as_secs_f64();
        for (m, v) in best.iter_mut().zip([a, b, c]) {
            *m = m.min(v);
        }
    }
    println!(
        "{side}x{side}, best of {rounds} ({} threads): psnr {:.1} ms, ssim {:.1} ms, a view's scores (render and empty image) {:.1} ms",
        rayon::current_num_threads(),
        best[0] * 1e3,
        best[1] * 1e3,
        best[2] * 1e3
    );
    // LPIPS, as `eval` computes it by default: the ground truth's and the render's features
    // side by side (the empty image's are computed once per size).
    let net = stegongp::score::lpips::Lpips::embedded();
    let mut lp = f64::INFINITY;
    for _ in 0..rounds.min(2) {
        let t = Instant::now();
        let (a, b) = rayon::join(
            || net.features(&gt, side, side),
            || net.features(&pred, side, side),
        );
        if let (Some(a), Some(b)) = (a, b) {
            check += net.distance_features(&a, &b);
        }
        lp = lp.min(t.elapsed().as_secs_f64());
    }
    // The sum of every score keeps the work from being optimised away, and shows that a
    // change to the metrics kept their values.
    println!(
        "LPIPS of a view (two images' features and their distance): {:.1} ms [{check:e}]",
        lp * 1e3
    );
}
