//! The GPU pieces of a training step and a render beyond the field, timed on the adapter
//! found beside the CPU engine doing the same work: Adam + EMA over the paper model's
//! parameter vector, the per-ray training loss, one occupancy update (draw and splat; the
//! field's densities given), and one wave of rendering's compositing.
//!
//! cargo run --release --example bench_gpu_step_parts -- [auto|software|any]
//! (default: the hardware adapter if there is one, else the software one)

use std::time::Instant;
use stegongp::gpu::{
    CompositeKernel, GpuContext, GpuOccupancy, GpuOptimizer, GpuRay, HostBatch, LossConfig,
    LossKernel, WaveSamples,
};
use stegongp::ngp::network::ModelConfig;
use stegongp::ngp::network::nerf::NerfNetwork;
use stegongp::ngp::occupancy::{N_CELLS, OccupancyGrid};
use stegongp::ngp::render::composite::composite;
use stegongp::ngp::render::march::Marcher;
use stegongp::ngp::train::loss::{DENSITY_PULL_UP, ray_loss};
use stegongp::ngp::train::{Optimizer, OptimizerConfig};
use stegongp::rng::Pcg32;
use wgpu::util::DeviceExt;

const REPS: usize = 5;

/// Best of `REPS` runs of `f`, in seconds.
fn best(mut f: impl FnMut()) -> f64 {
    (0..REPS)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

fn buffer(ctx: &GpuContext, label: &str, bytes: &[u8]) -> wgpu::Buffer {
    ctx.device
        .create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents: bytes,
            usage: wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_SRC
                | wgpu::BufferUsages::COPY_DST,
        })
}

fn submit(ctx: &GpuContext, f: impl FnOnce(&mut wgpu::CommandEncoder)) {
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    f(&mut encoder);
    ctx.queue.submit([encoder.finish()]);
    ctx.wait().expect("device wait");
}

fn main() {
    let ctx = GpuContext::from_arg(std::env::args().nth(1).as_deref()).unwrap_or_else(|e| {
        eprintln!("{e}");
        std::process::exit(1);
    });
    let ctx = &ctx;
    println!("adapter: {}", ctx.report());
    println!("{:<60} {:>14} {:>14}", "", "GPU", "CPU");
    // One generator, drawn by the parts in turn: their order fixes each part's data.
    let mut rng = Pcg32::new(3, 3);
    bench_optimizer(ctx, &mut rng);
    let samples = Samples::draw(&mut rng, 1 << 14, 16);
    bench_loss(ctx, &samples);
    bench_occupancy(ctx, &mut rng);
    bench_compositing(ctx, &samples);
}

/// Adam + EMA over the paper model (16×2, T = 2^19): every parameter with a gradient.
fn bench_optimizer(ctx: &GpuContext, rng: &mut Pcg32) {
    let net = NerfNetwork::new(ModelConfig::default()).unwrap();
    let n = net.layout.n_params;
    let n_matrix = net.layout.n_mlp_params();
    let mut w = net.init_params(1);
    let g: Vec<f32> = (0..n).map(|_| rng.next_f32() - 0.5).collect();
    let weights = buffer(ctx, "weights", bytemuck::cast_slice(&w));
    let grad = buffer(ctx, "grad", bytemuck::cast_slice(&g));
    let mut gpu_opt = GpuOptimizer::new(ctx, OptimizerConfig::default(), n, n_matrix).unwrap();
    let t_gpu = best(|| {
        ctx.queue.write_buffer(&grad, 0, bytemuck::cast_slice(&g));
        gpu_opt.step(ctx, &weights, &grad).unwrap();
    });
    let mut cpu_opt = Optimizer::new(OptimizerConfig::default(), n, n_matrix);
    let mut grads = vec![g.clone()];
    let t_cpu = best(|| {
        grads[0].copy_from_slice(&g);
        cpu_opt.step(&mut w, &mut grads, None);
    });
    println!(
        "{:<60} {:>11.1} ms {:>11.1} ms",
        format!(
            "Adam + EMA step, {:.1} M parameters (CPU: all cores)",
            n as f64 / 1e6
        ),
        1e3 * t_gpu,
        1e3 * t_cpu
    );
}

/// Rays of samples for the loss (and, the first of them, for compositing).
struct Samples {
    raw: Vec<[f32; 4]>,
    dt: Vec<f32>,
    dist: Vec<f32>,
    pos: Vec<[f32; 3]>,
    rays: Vec<GpuRay>,
}

impl Samples {
    /// `n_rays` rays of `per_ray` random samples.
    fn draw(rng: &mut Pcg32, n_rays: usize, per_ray: usize) -> Samples {
        let ns = n_rays * per_ray;
        let raw: Vec<[f32; 4]> = (0..ns)
            .map(|_| std::array::from_fn(|k| rng.next_f32() * 4.0 - if k == 3 { 3.0 } else { 2.0 }))
            .collect();
        let dt = vec![0.01f32; ns];
        let dist: Vec<f32> = (0..ns).map(|i| 0.5 + 0.01 * (i % per_ray) as f32).collect();
        let pos: Vec<[f32; 3]> = (0..ns)
            .map(|_| [rng.next_f32(), rng.next_f32(), rng.next_f32()])
            .collect();
        let rays: Vec<GpuRay> = (0..n_rays)
            .map(|r| GpuRay {
                start: (r * per_ray) as u32,
                n: per_ray as u32,
                bg: [0.5; 3],
                target: [0.2, 0.4, 0.6],
            })
            .collect();
        Samples {
            raw,
            dt,
            dist,
            pos,
            rays,
        }
    }
}

/// The training loss over `samples` (2^14 rays of 16 samples).
fn bench_loss(ctx: &GpuContext, samples: &Samples) {
    let Samples {
        raw,
        dt,
        dist,
        pos,
        rays,
    } = samples;
    let (n_rays, ns) = (rays.len(), raw.len());
    let marcher = Marcher::new(1);
    let cfg = LossConfig::new(&marcher, 1.0 / n_rays as f32, DENSITY_PULL_UP);
    let loss = LossKernel::new(ctx).unwrap();
    let host = HostBatch {
        rays,
        raw,
        dt,
        dist,
        pos,
    };
    // Upload and readback included: an upper bound on the kernel's time.
    let t_gpu = best(|| {
        loss.run_host(ctx, &host, &cfg).unwrap();
    });
    let mut d_raw = vec![[0.0f32; 4]; ns];
    let t_cpu = best(|| {
        for r in rays {
            let s = r.start as usize..(r.start + r.n) as usize;
            let p = &pos[s.clone()];
            ray_loss(
                &raw[s.clone()],
                &dt[s.clone()],
                &dist[s.clone()],
                |j| marcher.in_cascade0(p[j]),
                r.bg,
                r.target,
                cfg.loss_norm,
                cfg.pull_up,
                &mut d_raw[s],
            );
        }
    });
    println!(
        "{:<60} {:>11.2} M/s {:>10.2} M/s",
        "training loss, samples/s (GPU: with transfers; CPU: 1 core)",
        ns as f64 / t_gpu / 1e6,
        ns as f64 / t_cpu / 1e6
    );
}

/// One occupancy update at aabb 1 as in the first 256 steps: every cell drawn once.
fn bench_occupancy(ctx: &GpuContext, rng: &mut Pcg32) {
    let marcher = Marcher::new(1);
    let mut cpu_grid = OccupancyGrid::new(1);
    let mut gpu_grid = GpuOccupancy::upload(ctx, &cpu_grid, &marcher).unwrap();
    let ld: Vec<f32> = (0..N_CELLS).map(|_| rng.next_f32() * 4.0 - 2.0).collect();
    let ld_buf = buffer(ctx, "log density", bytemuck::cast_slice(&ld));
    let t_gpu = best(|| {
        submit(ctx, |e| {
            gpu_grid
                .encode_samples(ctx, e, N_CELLS as u32, 0, 5)
                .unwrap();
            gpu_grid.encode_splat(ctx, e, &ld_buf).unwrap();
        })
    });
    let t_cpu = best(|| {
        let (_, cells) = cpu_grid.sample_positions(N_CELLS, 0, 5);
        cpu_grid.splat(&cells, &ld);
    });
    println!(
        "{:<60} {:>11.1} ms {:>11.1} ms",
        "occupancy update, 2^21 samples, no field (CPU: all cores)",
        1e3 * t_gpu,
        1e3 * t_cpu
    );
}

/// A rendering wave: 2^15 rays of 8 samples (the loss's samples again).
fn bench_compositing(ctx: &GpuContext, samples: &Samples) {
    let n_rays = 1u32 << 15;
    let ns = 8 * n_rays as usize;
    let comp = CompositeKernel::new(ctx).unwrap();
    let state = comp.state(ctx, n_rays).unwrap();
    let waves: Vec<[u32; 2]> = (0..n_rays).map(|r| [8 * r, 8]).collect();
    let (raw, dt, dist) = (&samples.raw[..ns], &samples.dt[..ns], &samples.dist[..ns]);
    let b = |l, v: &[u8]| buffer(ctx, l, v);
    let (wave, b_raw, b_dt, b_dist) = (
        b("wave", bytemuck::cast_slice(&waves)),
        b("raw", bytemuck::cast_slice(raw)),
        b("dt", bytemuck::cast_slice(dt)),
        b("dist", bytemuck::cast_slice(dist)),
    );
    let samples = WaveSamples {
        wave: &wave,
        raw: &b_raw,
        dt: &b_dt,
        dist: &b_dist,
    };
    let t_gpu = best(|| {
        submit(ctx, |e| {
            comp.encode_wave(ctx, e, &state, &samples, 1e-4).unwrap()
        })
    });
    let t_cpu = best(|| {
        for r in 0..n_rays as usize {
            let s = 8 * r..8 * r + 8;
            std::hint::black_box(composite(
                &raw[s.clone()],
                &dt[s.clone()],
                &dist[s],
                1.0,
                1e-4,
            ));
        }
    });
    println!(
        "{:<60} {:>11.2} M/s {:>10.2} M/s",
        "rendering compositing, samples/s (CPU: 1 core)",
        ns as f64 / t_gpu / 1e6,
        ns as f64 / t_cpu / 1e6
    );
}
