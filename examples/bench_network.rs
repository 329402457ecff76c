//! Throughput of the NeRF network kernels (16×2, T = 2^19) on samples laid out as in
//! training: runs of 30 samples along short rays crossing a surface.
//!
//! `cargo run --release --example bench_network` — prints samples/s for forward only,
//! forward + backward and density only, on 1 and 2 threads (per-thread Workspace and
//! gradient buffer, as the trainer uses them). `BENCH_INDEX=prf` or `primes` runs it under a
//! fixed key of that scheme (every level keyed, dense levels permuted) instead of the
//! reference index; `BENCH_THREADS=1` and `BENCH_FB_ONLY=1` narrow it down.

use rayon::prelude::*;
use std::time::Instant;
use stegongp::ngp::encoding::index::reference_indices;
use stegongp::ngp::network::ModelConfig;
use stegongp::ngp::network::nerf::{CHUNK, NerfNetwork};
use stegongp::rng::Pcg32;
use stegongp::stego::{DenseMode, Key, KeyScheme};

const SAMPLES: usize = 1 << 17;
const RUN: usize = 30;
const REPS: usize = 3;

fn unit(r: &mut Pcg32) -> [f32; 3] {
    loop {
        let v = [0; 3].map(|_: i32| r.next_f32() * 2.0 - 1.0);
        let l2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
        if l2 > 1e-4 && l2 <= 1.0 {
            let l = l2.sqrt();
            return v.map(|c| c / l);
        }
    }
}

/// Rays through points of a sphere (radius 0.3 around the cube centre), 30 samples each,
/// spaced by the minimum cone step sqrt(3)/1024 around the surface point.
fn make_samples(n: usize) -> (Vec<[f32; 3]>, Vec<[f32; 3]>) {
    let mut r = Pcg32::new(7, 1);
    let dt = 3f32.sqrt() / 1024.0;
    let (mut pos, mut dir) = (Vec::with_capacity(n), Vec::with_capacity(n));
    while pos.len() < n {
        let s = unit(&mut r);
        let d = unit(&mut r);
        let c = s.map(|v| 0.5 + 0.3 * v);
        for k in 0..RUN.min(n - pos.len()) {
            let t = (k as f32 - RUN as f32 / 2.0) * dt;
            pos.push([0, 1, 2].map(|i| (c[i] + t * d[i]).clamp(0.0, 1.0)));
            dir.push(d);
        }
    }
    (pos, dir)
}

#[derive(Clone, Copy, PartialEq)]
enum Mode {
    Forward,
    ForwardBackward,
    Density,
}

fn main() {
    let net = NerfNetwork::new(ModelConfig::default()).expect("default config");
    let params = net.init_params(1337);
    let scheme = match std::env::var("BENCH_INDEX").as_deref() {
        Ok("prf") => Some(KeyScheme::Prf {
            secrets: vec![[7; 32]],
        }),
        Ok("primes") => Some(KeyScheme::Primes {
            keys: vec![[10_000_019, 10_000_079, 10_000_103]],
        }),
        _ => None,
    };
    let indices = match &scheme {
        Some(s) => Key::new(s.clone(), DenseMode::Permute)
            .expect("a valid fixed key")
            .level_indices(&net.layout.grid),
        None => reference_indices(&net.layout.grid),
    };
    let (pos, dir) = make_samples(SAMPLES);
    println!(
        "NeRF network 16x2, T=2^19, {} params; {} samples per rep in runs of {RUN}, chunk {CHUNK}; index: {}",
        net.layout.n_params,
        SAMPLES,
        scheme.as_ref().map_or("reference", |s| s.name())
    );
    let only: Option<usize> = std::env::var("BENCH_THREADS")
        .ok()
        .and_then(|v| v.parse().ok());
    for threads in [1usize, 2] {
        if only.is_some_and(|o| o != threads) {
            continue;
        }
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("thread pool");
        // Per-thread state, allocated (and first touched) once, outside the timing.
        let mut state: Vec<_> = (0..threads)
            .map(|_| {
                (
                    net.workspace(),
                    vec![0f32; net.layout.n_params],
                    vec![[0f32; 4]; CHUNK],
                    vec![0f32; CHUNK],
                )
            })
            .collect();
        let fb_only = std::env::var("BENCH_FB_ONLY").is_ok();
        for mode in [Mode::Forward, Mode::ForwardBackward, Mode::Density] {
            if fb_only && mode != Mode::ForwardBackward {
                continue;
            }
            let per_thread = SAMPLES.div_ceil(threads);
            let mut best = f64::INFINITY;
            for rep in 0..=REPS {
                let t0 = Instant::now();
                pool.install(|| {
                    state.par_iter_mut().enumerate().for_each(|(t, st)| {
                        let (ws, grad, out, dens) = st;
                        let lo = t * per_thread;
                        let hi = ((t + 1) * per_thread).min(SAMPLES);
                        let d_out = [[1e-3f32, -2e-3, 1e-3, 5e-4]; CHUNK];
                        for start in (lo..hi).step_by(CHUNK) {
                            let end = (start + CHUNK).min(hi);
                            let (p, d) = (&pos[start..end], &dir[start..end]);
                            match mode {
                                Mode::Forward => net.forward(&params, &indices, p, d, ws, out),
                                Mode::ForwardBackward => {
                                    net.forward(&params, &indices, p, d, ws, out);
                                    net.backward(&params, &indices, &d_out, ws, grad);
                                }
                                Mode::Density => net.density(&params, &indices, p, ws, dens),
                            }
                        }
                    })
                });
                let dt = t0.elapsed().as_secs_f64();
                if rep > 0 {
                    best = best.min(dt);
                }
            }
            let name = match mode {
                Mode::Forward => "forward         ",
                Mode::ForwardBackward => "forward+backward",
                Mode::Density => "density only    ",
            };
            println!(
                "{threads} thread(s)  {name}  {:>6.3} M samples/s  ({:.2} us/sample/thread)",
                SAMPLES as f64 / best / 1e6,
                best * 1e6 * threads as f64 / SAMPLES as f64
            );
        }
    }
}
