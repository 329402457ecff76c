//! Hash-grid encoding throughput: forward and backward samples/s on the GPU adapter found
//! (the paper's layout: 16 levels × 2 features, T = 2^19, aabb 1; positions, table,
//! encoding and gradient resident on the device; dispatch and wait, best of 3), beside the
//! CPU grid on one core (`grid::forward` / `grid::backward` in chunks of 512 samples, as a
//! trainer's worker runs them). The GPU forward is checked against the CPU's.
//!
//! cargo run --release --example bench_gpu_grid -- [SAMPLES] [--software]
//! (default 2^18 samples, a training step's worth; a hardware adapter only, unless
//! `--software` or STEGONGP_GPU_SOFTWARE=1 allows a software one such as llvmpipe)

#[cfg(feature = "gpu")]
fn main() {
    bench::main()
}

#[cfg(not(feature = "gpu"))]
fn main() {
    eprintln!("bench_gpu_grid needs the `gpu` feature");
    std::process::exit(1);
}

#[cfg(feature = "gpu")]
mod bench {
    use std::time::Instant;
    use stegongp::gpu::grid::{download_f32, upload_f32, upload_positions};
    use stegongp::gpu::{AdapterRequest, GpuContext, GradAtomics, GridEncoding, GridShape};
    use stegongp::ngp::encoding::grid::{self, GridCache};
    use stegongp::ngp::encoding::{GridConfig, GridLayout, LevelIndices, reference_indices};
    use stegongp::rng::Pcg32;
    use stegongp::stego::{DenseMode, SchemeKind, generate_with};

    const CPU_CHUNK: usize = 512;

    pub fn main() {
        let args: Vec<String> = std::env::args().skip(1).collect();
        let software = args.iter().any(|a| a == "--software")
            || std::env::var("STEGONGP_GPU_SOFTWARE").is_ok_and(|v| v == "1");
        let n: usize = args.iter().find_map(|a| a.parse().ok()).unwrap_or(1 << 18);
        let request = if software {
            AdapterRequest::Any
        } else {
            AdapterRequest::Auto
        };
        let ctx = match GpuContext::new(request) {
            Ok(c) => c,
            Err(e) => {
                eprintln!("{e} (--software allows a software adapter)");
                std::process::exit(1);
            }
        };
        println!("adapter: {}", ctx.report());
        let layout = GridLayout::new(GridConfig::default(), 1).unwrap();
        let width = layout.config.n_output_dims();
        let mut rng = Pcg32::new(1, 2);
        let table: Vec<f32> = (0..layout.n_params())
            .map(|_| (rng.next_f32() * 2.0 - 1.0) * 1e-2)
            .collect();
        let pos: Vec<[f32; 3]> = (0..n)
            .map(|_| [rng.next_f32(), rng.next_f32(), rng.next_f32()])
            .collect();
        let d_enc: Vec<f32> = (0..width * n).map(|_| rng.next_f32() - 0.5).collect();
        let key = generate_with(SchemeKind::Prf, 16, || {
            Ok((rng.next_u32() as u64) << 32 | rng.next_u32() as u64)
        })
        .unwrap()
        .with_dense(DenseMode::Permute);
        let kinds: [(&str, LevelIndices); 2] = [
            ("reference (the cover)", reference_indices(&layout)),
            ("prf, dense permuted", key.level_indices(&layout)),
        ];

        let shape = GridShape::new(n as u32);
        let p = upload_positions(&ctx, &pos, shape.ld).unwrap();
        let t = upload_f32(&ctx, "table", &table).unwrap();
        let e = upload_f32(&ctx, "enc", &vec![0.0; width * n]).unwrap();
        let de = upload_f32(&ctx, "d_enc", &d_enc).unwrap();
        let gr = upload_f32(&ctx, "grad", &vec![0.0; layout.n_params()]).unwrap();
        let float = GridEncoding::new(&ctx, &layout, GradAtomics::Auto).unwrap();
        let cas = GridEncoding::new(&ctx, &layout, GradAtomics::CompareSwap).unwrap();

        println!(
            "{n} samples × {} levels × {} features, T = 2^{}: M samples/s, best of 3",
            layout.levels.len(),
            layout.config.n_features,
            layout.config.log2_hashmap_size
        );
        println!(
            "{:<24} {:>9} {:>12} {:>12} {:>11} {:>11}",
            "index",
            "GPU fwd",
            format!("GPU bwd {}", short(float.atomics())),
            "GPU bwd CAS",
            "CPU1 fwd",
            "CPU1 bwd"
        );
        let ms = |secs: f64| n as f64 / secs / 1e6;
        for (name, indices) in kinds {
            let index = float.upload_index(&ctx, &indices).unwrap();
            let fwd = float
                .bind_forward(&ctx, &index, p.slice(..), t.slice(..), e.slice(..), shape)
                .unwrap();
            let t_fwd = best_of(3, || fwd.run(&ctx).unwrap());
            let mut bwd = [0.0; 2];
            for (k, g) in [&float, &cas].into_iter().enumerate() {
                let d = g
                    .bind_backward(&ctx, &index, p.slice(..), de.slice(..), gr.slice(..), shape)
                    .unwrap();
                bwd[k] = best_of(3, || d.run(&ctx).unwrap());
            }
            let got = download_f32(&ctx, &e, width * n).unwrap();
            let (cpu_fwd, cpu_bwd, max) = cpu(&layout, &table, &indices, &pos, &d_enc, &got);
            assert!(max <= 1e-6, "{name}: GPU and CPU encodings differ by {max}");
            println!(
                "{name:<24} {:>9.2} {:>12.2} {:>12.2} {:>11.2} {:>11.2}",
                ms(t_fwd),
                ms(bwd[0]),
                ms(bwd[1]),
                ms(cpu_fwd),
                ms(cpu_bwd)
            );
        }
        println!("GPU forward within 1e-6 of the CPU's on every feature");
    }

    fn short(a: GradAtomics) -> &'static str {
        match a {
            GradAtomics::Float => "f32",
            _ => "CAS",
        }
    }

    /// One core's forward and backward seconds over all samples (512 at a time), and the
    /// largest difference from the GPU's encoding.
    fn cpu(
        layout: &GridLayout,
        table: &[f32],
        indices: &LevelIndices,
        pos: &[[f32; 3]],
        d_enc: &[f32],
        gpu_enc: &[f32],
    ) -> (f64, f64, f32) {
        let n = pos.len();
        let width = layout.config.n_output_dims();
        let mut cache = GridCache::new(layout, CPU_CHUNK);
        let mut enc = vec![0f32; width * CPU_CHUNK];
        let mut d = vec![0f32; width * CPU_CHUNK];
        let mut grad = vec![0f32; layout.n_params()];
        let (mut t_fwd, mut t_bwd, mut max) = (0.0, 0.0, 0f32);
        for start in (0..n).step_by(CPU_CHUNK) {
            let m = CPU_CHUNK.min(n - start);
            for j in 0..width {
                d[j * CPU_CHUNK..j * CPU_CHUNK + m]
                    .copy_from_slice(&d_enc[j * n + start..j * n + start + m]);
            }
            let t0 = Instant::now();
            let chunk = &pos[start..start + m];
            grid::forward(
                layout, table, indices, chunk, &mut cache, &mut enc, CPU_CHUNK,
            );
            let t1 = Instant::now();
            grid::backward(layout, &cache, &d, CPU_CHUNK, &mut grad);
            t_bwd += t1.elapsed().as_secs_f64();
            t_fwd += (t1 - t0).as_secs_f64();
            for j in 0..width {
                for s in 0..m {
                    let g = gpu_enc[j * n + start + s];
                    max = max.max((g - enc[j * CPU_CHUNK + s]).abs());
                }
            }
        }
        (t_fwd, t_bwd, max)
    }

    fn best_of(k: usize, mut f: impl FnMut()) -> f64 {
        (0..k)
            .map(|_| {
                let t = Instant::now();
                f();
                t.elapsed().as_secs_f64()
            })
            .fold(f64::INFINITY, f64::min)
    }
}
