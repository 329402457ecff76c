//! GPU training rays (`crates/gpu/src/rays.rs`) against the CPU trainer's draws and
//! `Marcher::march`, on whatever adapter `test_context` finds (lavapipe in CI).
//!
//! Tolerances. Draws (image, pixel, background) are bit-identical: PCG32 in 64-bit words.
//! Origins are copied, so equal. Directions: |gpu − cpu| ≤ 1e-5 per component (WGSL's
//! division and sqrt are not correctly rounded; 1e-4 with lens distortion, whose Newton
//! iteration stops on a float threshold). Targets: ≤ 1e-4 (pow is exp2·log2 on the device).
//! Start t: ≤ 1e-5·(1 + t). Marching from the same (o, d, t): sample counts equal on at
//! least 98 % of rays (GPU log/exp are not correctly rounded, so a step landing on a voxel
//! boundary may go the other way and shift a ray's samples); where counts agree, positions,
//! positions within 1e-4 (warped units), dt within 1e-5·(1 + t) and distances within
//! 5e-5·(1 + t) (measured on llvmpipe: 7e-6, 7e-7·, 1.9e-5·).
#![cfg(feature = "gpu")]

use stegongp::gpu::{GenRay, GpuOccupancy, RayBatch, RayKernels, test_context};
use stegongp::ngp::camera::{Camera, Distortion};
use stegongp::ngp::data::{Frame, Image};
use stegongp::ngp::occupancy::{GRID_SIZE, N_CELLS, OccupancyGrid, morton3d_invert, n_cascades};
use stegongp::ngp::render::march::{MAX_SAMPLES_PER_RAY, Marcher, advance_n_steps};
use stegongp::rng::Pcg32;

fn normalize(a: [f32; 3]) -> [f32; 3] {
    let n = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    [a[0] / n, a[1] / n, a[2] / n]
}

fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// A camera at `pos` looking at `at` (right, down, forward columns).
fn camera(pos: [f32; 3], at: [f32; 3], w: u32, h: u32, distortion: Option<Distortion>) -> Camera {
    let f = normalize([at[0] - pos[0], at[1] - pos[1], at[2] - pos[2]]);
    let r = normalize(cross(f, [0.0, 0.0, 1.0]));
    let down = cross(f, r);
    let mut c2w = [[0.0; 4]; 3];
    for k in 0..3 {
        c2w[k] = [r[k], down[k], f[k], pos[k]];
    }
    Camera {
        c2w,
        fx: 0.9 * w as f32,
        fy: 0.9 * w as f32,
        cx: w as f32 / 2.0 + 0.3,
        cy: h as f32 / 2.0 - 0.2,
        width: w,
        height: h,
        distortion,
    }
}

/// Three frames: RGBA8 with random alpha, an f16 (downscaled-like) image, and a distorted
/// camera; `inside` puts the last camera inside the box.
fn frames(seed: u64, inside: bool) -> Vec<Frame> {
    let mut r = Pcg32::new(seed, 1);
    let (w, h) = (37, 29);
    let rgba: Vec<u8> = (0..4 * w * h).map(|_| r.next_u32() as u8).collect();
    let lin: Vec<f32> = (0..w * h)
        .flat_map(|_| {
            let a = r.next_f32();
            [r.next_f32() * a, r.next_f32() * a, r.next_f32() * a, a]
        })
        .collect();
    let rgba2: Vec<u8> = (0..4 * w * h)
        .map(|k| if k % 4 == 3 { 255 } else { r.next_u32() as u8 })
        .collect();
    let dist = Distortion {
        k1: -0.12,
        k2: 0.03,
        p1: 0.002,
        p2: -0.001,
    };
    let last = if inside {
        [0.6, 0.45, 0.5]
    } else {
        [0.5, -1.6, 0.9]
    };
    vec![
        Frame {
            camera: camera([2.1, 1.3, 0.9], [0.5, 0.5, 0.5], w, h, None),
            image: Image::from_rgba8(w, h, rgba).unwrap(),
            file_path: "a".into(),
        },
        Frame {
            camera: camera([-1.2, 0.4, 1.7], [0.5, 0.5, 0.45], w, h, None),
            image: Image::from_linear_premul(w, h, &lin).unwrap(),
            file_path: "b".into(),
        },
        Frame {
            camera: camera(last, [0.5, 0.55, 0.5], w, h, Some(dist)),
            image: Image::from_rgba8(w, h, rgba2).unwrap(),
            file_path: "c".into(),
        },
    ]
}

/// The CPU trainer's draw of ray i (`train_rays`), as a [`GenRay`].
fn cpu_draw(fr: &[Frame], m: &Marcher, seed: u64, i: usize, n_rays: usize) -> GenRay {
    let mut rng = Pcg32::new(seed, i as u64);
    let img = i * fr.len() / n_rays;
    let f = &fr[img];
    let x = rng.below(f.image.width);
    let y = rng.below(f.image.height);
    let bg = [rng.next_f32(), rng.next_f32(), rng.next_f32()];
    let ray = f.camera.ray(x as f32 + 0.5, y as f32 + 0.5);
    let (hit, t) = match m.intersect(ray.o, ray.d) {
        Some((tmin, _)) => (1, advance_n_steps(tmin, m.cone_angle(), rng.next_f32())),
        None => (0, 0.0),
    };
    GenRay {
        o: ray.o,
        t,
        d: ray.d,
        hit,
        bg,
        pixel: y * f.image.width + x,
        target: f.image.target_on(x, y, bg),
        image: img as u32,
    }
}

#[test]
fn ray_draws_match_the_cpu() {
    let Some(ctx) = test_context() else { return };
    for (aabb, inside) in [(1, false), (16, true)] {
        let m = Marcher::new(aabb);
        let fr = frames(7 + aabb as u64, inside);
        let k = RayKernels::new(ctx, &fr, &m).unwrap();
        let (n, seed) = (3001usize, 0x1234_5678_9abc_def0u64 + aabb as u64);
        let gpu = k.generate_host(ctx, n as u32, seed).unwrap();
        let mut hits = 0;
        for (i, g) in gpu.iter().enumerate() {
            let c = cpu_draw(&fr, &m, seed, i, n);
            assert_eq!(
                (g.image, g.pixel, g.bg),
                (c.image, c.pixel, c.bg),
                "ray {i}"
            );
            assert_eq!(g.o, c.o, "ray {i}");
            let tol_d = if c.image == 2 { 1e-4 } else { 1e-5 };
            for q in 0..3 {
                assert!(
                    (g.d[q] - c.d[q]).abs() <= tol_d,
                    "ray {i}: d {:?} {:?}",
                    g.d,
                    c.d
                );
                assert!(
                    (g.target[q] - c.target[q]).abs() <= 1e-4,
                    "ray {i}: target {:?} {:?}",
                    g.target,
                    c.target
                );
            }
            assert_eq!(g.hit, c.hit, "ray {i}");
            hits += c.hit;
            assert!(
                (g.t - c.t).abs() <= 1e-5 * (1.0 + c.t),
                "ray {i}: t {} {}",
                g.t,
                c.t
            );
        }
        assert!(hits > n as u32 / 3, "{hits} of {n} rays meet the box");
    }
}

/// Blobs: cells whose centre lies within one of a few random balls (per cascade, in ngp
/// space), density 1, else 0.
fn blob_grid(aabb: u32, seed: u64) -> OccupancyGrid {
    let nc = n_cascades(aabb);
    let mut r = Pcg32::new(seed, 2);
    let s = aabb as f32;
    let balls: Vec<([f32; 3], f32)> = (0..6)
        .map(|_| {
            let c = [0.0; 3].map(|_: f32| 0.5 + (r.next_f32() - 0.5) * 0.8 * s.sqrt());
            (c, (0.05 + 0.2 * r.next_f32()) * s.sqrt())
        })
        .collect();
    let mut density = vec![0.0f32; N_CELLS * nc];
    let g = GRID_SIZE as f32;
    for c in 0..nc {
        let sc = (c as f32).exp2();
        for idx in 0..N_CELLS as u32 {
            let cell = [idx, idx >> 1, idx >> 2].map(|v| morton3d_invert(v) as f32 + 0.5);
            let p = cell.map(|v| (v / g - 0.5) * sc + 0.5);
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

/// Rays from random origins outside the box (and, for `inside`, half from inside it)
/// toward random points in the unit cube, with the CPU's start t.
fn march_rays(m: &Marcher, n: usize, seed: u64, inside: bool) -> Vec<GenRay> {
    let mut r = Pcg32::new(seed, 4);
    let s = m.aabb_max[0] - m.aabb_min[0];
    let mut out = Vec::new();
    while out.len() < n {
        let o = if inside && out.len() % 2 == 0 {
            [0.0; 3].map(|_: f32| m.aabb_min[0] + s * (0.05 + 0.9 * r.next_f32()))
        } else {
            let dir = normalize([0.0; 3].map(|_: f32| r.next_f32() - 0.5));
            [0, 1, 2].map(|k| 0.5 + dir[k] * s * 1.2)
        };
        let at = [0.0; 3].map(|_: f32| r.next_f32());
        let d = normalize([at[0] - o[0], at[1] - o[1], at[2] - o[2]]);
        let Some((tmin, _)) = m.intersect(o, d) else {
            continue;
        };
        let t = advance_n_steps(tmin, m.cone_angle(), r.next_f32());
        out.push(GenRay {
            o,
            t,
            d,
            hit: 1,
            ..Default::default()
        });
    }
    out
}

#[test]
fn marching_matches_the_cpu() {
    let Some(ctx) = test_context() else { return };
    for (aabb, inside) in [(1, false), (16, true)] {
        let m = Marcher::new(aabb);
        let grid = blob_grid(aabb, 3 + aabb as u64);
        let k = RayKernels::new(ctx, &[], &m).unwrap();
        let n = 2000;
        let rays = march_rays(&m, n, 11 + aabb as u64, inside);
        let budget = (n * MAX_SAMPLES_PER_RAY) as u32;
        let out = k.march_host(ctx, &grid, &rays, budget).unwrap();
        let (mut differ, mut total, mut nonempty) = (0, 0usize, 0);
        // Largest |Δ position| (warped), |Δ dt| and |Δ distance| over 1 + distance.
        let mut err = [0.0f32; 3];
        for (i, ray) in rays.iter().enumerate() {
            let (mut p, mut dt, mut ts) = (vec![], vec![], vec![]);
            m.march(
                &grid,
                ray.o,
                ray.d,
                ray.t,
                MAX_SAMPLES_PER_RAY,
                &mut p,
                &mut dt,
                &mut ts,
            );
            total += p.len();
            nonempty += !p.is_empty() as usize;
            let g = out.rays[i];
            if g.n as usize != p.len() {
                differ += 1;
                continue;
            }
            for j in 0..p.len() {
                let s = g.start as usize + j;
                for (a, b) in out.pos[s].iter().zip(p[j]) {
                    err[0] = err[0].max((a - b).abs());
                }
                err[1] = err[1].max((out.dt[s] - dt[j]).abs() / (1.0 + ts[j]));
                err[2] = err[2].max((out.dist[s] - ts[j]).abs() / (1.0 + ts[j]));
            }
        }
        assert!(
            err[0] <= 1e-4 && err[1] <= 1e-5 && err[2] <= 5e-5,
            "aabb {aabb}: errors {err:?}"
        );
        eprintln!(
            "aabb {aabb}: {total} samples on {nonempty} of {n} rays (GPU {}), {differ} rays' \
             counts differ, errors {err:?}",
            out.pos.len()
        );
        assert!(
            nonempty > n / 5 && total > 5 * n,
            "{nonempty} rays, {total} samples"
        );
        assert!(
            differ * 50 <= n,
            "{differ} of {n} rays' sample counts differ"
        );
        // Compaction: the rays' ranges tile 0..used exactly.
        let mut ranges: Vec<(u32, u32)> = out
            .rays
            .iter()
            .filter(|r| r.n > 0)
            .map(|r| (r.start, r.n))
            .collect();
        ranges.sort();
        let mut end = 0;
        for (s, c) in ranges {
            assert_eq!(s, end);
            end += c;
        }
        assert_eq!(end as usize, out.pos.len());
        assert_eq!(out.asked as usize, out.pos.len());

        // A budget that binds: rays that fit keep their samples, the rest get none.
        let small = (total / 3) as u32;
        let cut = k.march_host(ctx, &grid, &rays, small).unwrap();
        assert!(cut.pos.len() as u32 <= small && cut.pos.len() as u32 > small / 2);
        assert_eq!(cut.asked, out.asked);
        let sum: u32 = cut.rays.iter().map(|r| r.n).sum();
        assert_eq!(sum as usize, cut.pos.len());
        for (i, r) in cut.rays.iter().enumerate() {
            assert!(r.n == 0 || r.n == out.rays[i].n, "ray {i}");
            if r.n == 0 {
                assert_eq!(r.target, r.bg, "an empty ray's loss must be 0");
            }
        }
    }
}

/// The whole batch on the device: draw, march through a [`GpuOccupancy`]'s bitfield,
/// compact; against the CPU trainer's draws marched by `Marcher::march`. The directions
/// differ by a few ulp here, so a few more rays' counts may differ than from identical
/// rays: at most 4 %.
#[test]
fn a_whole_batch_matches_the_cpu() {
    let Some(ctx) = test_context() else { return };
    for (aabb, inside) in [(1, false), (16, true)] {
        let m = Marcher::new(aabb);
        let fr = frames(21 + aabb as u64, inside);
        let grid = blob_grid(aabb, 5 + aabb as u64);
        let occ = GpuOccupancy::upload(ctx, &grid, &m).unwrap();
        let k = RayKernels::new(ctx, &fr, &m).unwrap();
        let (n, seed) = (1500usize, 99 + aabb as u64);
        let batch = RayBatch::new(ctx, n as u32, (n * MAX_SAMPLES_PER_RAY) as u32).unwrap();
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        k.encode(ctx, &mut enc, &batch, &occ.bitfield, n as u32, seed)
            .unwrap();
        ctx.queue.submit([enc.finish()]);
        let out = k.read_marched(ctx, &batch, n as u32).unwrap();
        let (mut differ, mut with_samples) = (0, 0);
        for i in 0..n {
            let c = cpu_draw(&fr, &m, seed, i, n);
            let (mut p, mut dt, mut ts) = (vec![], vec![], vec![]);
            if c.hit == 1 {
                m.march(
                    &grid,
                    c.o,
                    c.d,
                    c.t,
                    MAX_SAMPLES_PER_RAY,
                    &mut p,
                    &mut dt,
                    &mut ts,
                );
            }
            let g = out.rays[i];
            with_samples += !p.is_empty() as usize;
            if g.n as usize != p.len() {
                differ += 1;
                continue;
            }
            assert_eq!(g.bg, c.bg);
            if g.n > 0 {
                for q in 0..3 {
                    assert!((g.target[q] - c.target[q]).abs() <= 1e-4, "ray {i}");
                }
                let s = g.start as usize;
                assert!(
                    (out.dist[s] - ts[0]).abs() <= 5e-5 * (1.0 + ts[0]),
                    "ray {i}"
                );
            } else {
                assert_eq!(g.target, g.bg, "ray {i}: no samples, loss 0");
            }
        }
        eprintln!("aabb {aabb}: {with_samples} of {n} rays with samples, {differ} counts differ");
        assert!(with_samples > n / 10, "{with_samples} rays with samples");
        assert!(
            differ * 25 <= n,
            "{differ} of {n} rays' sample counts differ"
        );
        assert_eq!(
            out.rays_with_samples as usize,
            out.rays.iter().filter(|r| r.n > 0).count()
        );
    }
}
