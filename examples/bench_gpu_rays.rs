//! Training rays per second on the GPU adapter found: draw, march through the occupancy
//! bitfield and compact one batch (`gpu::RayKernels::encode`), beside one CPU core doing
//! the same per ray as the trainer's `train_rays` (draw, `Camera::ray`, `intersect`,
//! `Marcher::march`, `target_on`).
//!
//! cargo run --release --example bench_gpu_rays -- [RAYS] [AABB] [auto|software|any]
//! (default: 2^18 rays on a GPU, 2^14 on a software adapter; aabb 1; the hardware adapter if
//! there is one, else the software one.) The scene: 8 views of 200×200 random RGBA8 pixels
//! on a sphere around the box, an occupancy grid of 6 random balls; the sample budget is
//! 2^18 (a training step's), so where the rays ask for more, the ones past it get none.
//! GPU: everything resident, dispatch and wait, best of 5 after a warm-up.

#[cfg(not(feature = "gpu"))]
fn main() {
    eprintln!("bench_gpu_rays needs the `gpu` feature");
}

#[cfg(feature = "gpu")]
fn main() {
    bench::main()
}

#[cfg(feature = "gpu")]
mod bench {
    use std::time::Instant;
    use stegongp::gpu::{GpuContext, GpuOccupancy, RayBatch, RayKernels};
    use stegongp::ngp::camera::Camera;
    use stegongp::ngp::data::{Frame, Image};
    use stegongp::ngp::geometry::normalize;
    use stegongp::ngp::occupancy::{
        GRID_SIZE, N_CELLS, OccupancyGrid, morton3d_invert, n_cascades,
    };
    use stegongp::ngp::render::march::{MAX_SAMPLES_PER_RAY, Marcher, advance_n_steps};
    use stegongp::rng::Pcg32;

    const BUDGET: u32 = 1 << 18;

    fn frames(aabb: u32) -> Vec<Frame> {
        let mut r = Pcg32::new(5, 1);
        let (w, h) = (200, 200);
        (0..8)
            .map(|k| {
                let a = k as f32 * 0.785;
                let rad = 1.5 + 0.3 * aabb as f32;
                let pos = [0.5 + rad * a.cos(), 0.5 + rad * a.sin(), 0.5 + 0.3 * rad];
                let f = normalize([0.5 - pos[0], 0.5 - pos[1], 0.5 - pos[2]]);
                let right = normalize([f[1], -f[0], 0.0]);
                let down = [
                    f[1] * right[2] - f[2] * right[1],
                    f[2] * right[0] - f[0] * right[2],
                    f[0] * right[1] - f[1] * right[0],
                ];
                let mut c2w = [[0.0; 4]; 3];
                for d in 0..3 {
                    c2w[d] = [right[d], down[d], f[d], pos[d]];
                }
                let rgba: Vec<u8> = (0..4 * w * h).map(|_| r.next_u32() as u8).collect();
                Frame {
                    camera: Camera {
                        c2w,
                        fx: 220.0,
                        fy: 220.0,
                        cx: 100.0,
                        cy: 100.0,
                        width: w,
                        height: h,
                        distortion: None,
                    },
                    image: Image::from_rgba8(w, h, rgba).unwrap(),
                    file_path: String::new(),
                }
            })
            .collect()
    }

    fn grid(aabb: u32) -> OccupancyGrid {
        let nc = n_cascades(aabb);
        let mut r = Pcg32::new(3, 2);
        let balls: Vec<([f32; 3], f32)> = (0..6)
            .map(|_| {
                (
                    [0.0; 3].map(|_: f32| 0.2 + 0.6 * r.next_f32()),
                    0.1 + 0.15 * r.next_f32(),
                )
            })
            .collect();
        let mut density = vec![0.0f32; N_CELLS * nc];
        for c in 0..nc {
            let sc = (c as f32).exp2();
            for idx in 0..N_CELLS as u32 {
                let cell = [idx, idx >> 1, idx >> 2].map(|v| morton3d_invert(v) as f32 + 0.5);
                let p = cell.map(|v| (v / GRID_SIZE as f32 - 0.5) * sc + 0.5);
                if balls.iter().any(|(o, rad)| {
                    let d = [p[0] - o[0], p[1] - o[1], p[2] - o[2]];
                    d[0] * d[0] + d[1] * d[1] + d[2] * d[2] < rad * rad
                }) {
                    density[c * N_CELLS + idx as usize] = 1.0;
                }
            }
        }
        OccupancyGrid::from_density(density).unwrap()
    }

    fn best_of(n: usize, mut f: impl FnMut()) -> f64 {
        f();
        (0..n)
            .map(|_| {
                let t = Instant::now();
                f();
                t.elapsed().as_secs_f64()
            })
            .fold(f64::INFINITY, f64::min)
    }

    pub fn main() {
        let args: Vec<String> = std::env::args().collect();
        let ctx = GpuContext::from_arg(args.get(3).map(String::as_str)).unwrap_or_else(|e| {
            eprintln!("{e}");
            std::process::exit(1);
        });
        let default_n = if ctx.report().software {
            1 << 14
        } else {
            1 << 18
        };
        let n: u32 = args
            .get(1)
            .and_then(|s| s.parse().ok())
            .unwrap_or(default_n);
        let aabb: u32 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(1);
        let m = Marcher::new(aabb);
        let fr = frames(aabb);
        let g = grid(aabb);
        let occ = GpuOccupancy::upload(&ctx, &g, &m).unwrap();
        let k = RayKernels::new(&ctx, &fr, &m).unwrap();
        let batch = RayBatch::new(&ctx, n, BUDGET).unwrap();
        println!("adapter: {}", ctx.report());
        let mut seed = 0u64;
        let t = best_of(5, || {
            seed += 1;
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            k.encode(&ctx, &mut enc, &batch, &occ.bitfield, n, seed)
                .unwrap();
            ctx.queue.submit([enc.finish()]);
            ctx.wait().unwrap();
        });
        let (asked, used, with) = batch.read_counters(&ctx).unwrap();
        println!(
            "{n} rays, aabb {aabb}, budget {BUDGET}: {with} rays with samples, {used} samples \
             written ({asked} asked for)"
        );
        // One CPU core, the trainer's per-ray work on the same draws.
        let cpu_n = n.min(1 << 13) as usize;
        let (mut pos, mut dt, mut ts) = (Vec::new(), Vec::new(), Vec::new());
        let mut cpu_samples = 0;
        let tc = best_of(3, || {
            cpu_samples = 0;
            for i in 0..cpu_n {
                let mut rng = Pcg32::new(seed, i as u64);
                let f = &fr[i * fr.len() / cpu_n];
                let x = rng.below(f.image.width);
                let y = rng.below(f.image.height);
                let bg = [rng.next_f32(), rng.next_f32(), rng.next_f32()];
                let ray = f.camera.ray(x as f32 + 0.5, y as f32 + 0.5);
                let Some((tmin, _)) = m.intersect(ray.o, ray.d) else {
                    continue;
                };
                let t = advance_n_steps(tmin, m.cone_angle(), rng.next_f32());
                pos.clear();
                dt.clear();
                ts.clear();
                m.march(
                    &g,
                    ray.o,
                    ray.d,
                    t,
                    MAX_SAMPLES_PER_RAY,
                    &mut pos,
                    &mut dt,
                    &mut ts,
                );
                std::hint::black_box(f.image.target_on(x, y, bg));
                cpu_samples += pos.len();
            }
        });
        println!("{:<12} {:>12} {:>12}", "", "GPU", "CPU 1 core");
        println!(
            "{:<12} {:>12.3} {:>12.3}",
            "M rays/s",
            n as f64 / t / 1e6,
            cpu_n as f64 / tc / 1e6
        );
        println!(
            "{:<12} {:>12.3} {:>12.3}",
            "M samples/s",
            used as f64 / t / 1e6,
            cpu_samples as f64 / tc / 1e6
        );
    }
}
