//! Samples per second through the network after the grid (SH, density MLP, colour MLP) on
//! the GPU adapter found, forward and forward + backward, beside one CPU core running the
//! same stages through the CPU engine's MLP functions (what `NerfNetwork` calls after its
//! grid encoding, in chunks of 512).
//!
//! cargo run --release --example bench_gpu_mlp -- [SAMPLES] [auto|software|any]
//! (default: 2^18 samples, 2^16 on a software adapter; the hardware adapter if there is
//! one, else the software one; `BENCH_GPU=software` in the environment picks as the second
//! argument does.)
//! GPU: every buffer resident, dispatch and wait, best of 5 after a warm-up.

#[cfg(not(feature = "gpu"))]
fn main() {
    eprintln!("bench_gpu_mlp needs the `gpu` feature");
}

#[cfg(feature = "gpu")]
fn main() {
    bench::main()
}

#[cfg(feature = "gpu")]
mod bench {
    use std::time::Instant;
    use stegongp::gpu::mlp::{upload, zeroed};
    use stegongp::gpu::{EncodedBatch, GpuContext, MlpKernels};
    use stegongp::ngp::encoding::sh;
    use stegongp::ngp::network::layout::DENSITY_OUT;
    use stegongp::ngp::network::mlp;
    use stegongp::ngp::network::nerf::{CHUNK, NerfNetwork};
    use stegongp::ngp::network::{ModelConfig, NerfLayout};
    use stegongp::rng::Pcg32;

    pub fn main() {
        let args: Vec<String> = std::env::args().collect();
        let choice = args
            .get(2)
            .cloned()
            .or_else(|| std::env::var("BENCH_GPU").ok());
        let ctx = GpuContext::from_arg(choice.as_deref()).unwrap_or_else(|e| {
            eprintln!("{e}");
            std::process::exit(1);
        });
        // A training step's 2^18 samples on a GPU; 2^16 on a software adapter, whose
        // storage bindings (128 MiB on llvmpipe) and speed are far smaller.
        let default_n = if ctx.report().software {
            1 << 16
        } else {
            1 << 18
        };
        let n: usize = args
            .get(1)
            .and_then(|s| s.parse().ok())
            .unwrap_or(default_n);
        let net = NerfNetwork::new(ModelConfig::default()).expect("default config");
        let l = &net.layout;
        let mut r = Pcg32::new(1, 2);
        let params = net.init_params(1);
        let n_enc = l.grid.config.n_output_dims();
        let enc: Vec<f32> = (0..n_enc * n).map(|_| r.next_f32() * 2.0 - 1.0).collect();
        let dirs: Vec<f32> = (0..n)
            .flat_map(|_| {
                let v = [0; 3].map(|_: u8| r.next_f32() * 2.0 - 1.0);
                let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-3);
                v.map(|c| c / len)
            })
            .collect();
        let d_out: Vec<f32> = (0..4 * n).map(|_| (r.next_f32() - 0.5) * 1e-2).collect();

        let kernels = MlpKernels::new(&ctx, l).unwrap();
        println!("adapter: {}", ctx.report());
        println!(
            "{n} samples, default network (16×2 grid features → 64 → 16; 32 → 64 → 64 → 3), \
             tile {} samples; M samples/s, best of 5",
            kernels.tile()
        );
        let p = upload(&ctx, "params", &params[..l.grid_offset]).unwrap();
        let e = upload(&ctx, "enc", &enc).unwrap();
        let dirs_buf = upload(&ctx, "dirs", &dirs).unwrap();
        let d_out_buf = upload(&ctx, "d_out", &d_out).unwrap();
        let out = zeroed(&ctx, "out", 4 * n as u64).unwrap();
        let dens = zeroed(&ctx, "density", n as u64).unwrap();
        let grad = zeroed(&ctx, "grad", l.grid_offset as u64).unwrap();
        let d_enc = zeroed(&ctx, "d_enc", (n_enc * n) as u64).unwrap();
        let ws = kernels.workspace(&ctx, n as u32).unwrap();
        let batch = EncodedBatch {
            params: &p,
            enc: &e,
            ld: n as u32,
            n: n as u32,
        };
        let gpu_fwd = best_of(5, || {
            kernels
                .forward(&ctx, &batch, &dirs_buf, &out, None)
                .unwrap()
        });
        let gpu_dens = best_of(5, || kernels.density(&ctx, &batch, &dens).unwrap());
        let gpu_fb = best_of(5, || {
            let mut enc_ = ctx.device.create_command_encoder(&Default::default());
            kernels
                .encode_forward(&ctx, &mut enc_, &batch, &dirs_buf, &out, Some(&ws))
                .unwrap();
            kernels
                .encode_backward(&ctx, &mut enc_, &batch, &d_out_buf, &ws, &grad, &d_enc)
                .unwrap();
            ctx.queue.submit([enc_.finish()]);
            ctx.wait().unwrap();
        });

        let cpu = CpuMlp::new(l);
        let mut cpu_state = cpu.state();
        let cpu_n = n.min(1 << 15);
        let cpu_fwd = best_of(3, || {
            cpu.run(&params, &enc, n, &dirs, cpu_n, None, &mut cpu_state)
        });
        let cpu_fb = best_of(3, || {
            cpu.run(&params, &enc, n, &dirs, cpu_n, Some(&d_out), &mut cpu_state)
        });
        let rate = |s: usize, t: f64| s as f64 / t / 1e6;
        println!("{:<18} {:>10} {:>12}", "", "GPU", "CPU 1 core");
        println!(
            "{:<18} {:>10.4} {:>12.3}",
            "forward",
            rate(n, gpu_fwd),
            rate(cpu_n, cpu_fwd)
        );
        println!(
            "{:<18} {:>10.4} {:>12}",
            "density only",
            rate(n, gpu_dens),
            "-"
        );
        println!(
            "{:<18} {:>10.4} {:>12.3}",
            "forward+backward",
            rate(n, gpu_fb),
            rate(cpu_n, cpu_fb)
        );
    }

    /// The CPU engine's network stages after the grid, as `NerfNetwork::forward/backward`
    /// call them on a chunk (their public building blocks; the grid is left out on both
    /// sides).
    struct CpuMlp {
        layout: NerfLayout,
    }

    struct CpuState {
        x: Vec<f32>,
        dh: Vec<f32>,
        cin: Vec<f32>,
        ch: Vec<f32>,
        rgb: Vec<f32>,
        d_rgb: Vec<f32>,
        d_hidden: Vec<f32>,
        d_dens: Vec<f32>,
        d_x: Vec<f32>,
        grad: Vec<f32>,
    }

    impl CpuMlp {
        fn new(layout: &NerfLayout) -> CpuMlp {
            CpuMlp {
                layout: layout.clone(),
            }
        }

        fn state(&self) -> CpuState {
            let (dm, cm) = (self.layout.density_mlp, self.layout.color_mlp);
            CpuState {
                x: vec![0.0; dm.n_in * CHUNK],
                dh: vec![0.0; mlp::hidden_len(&dm, CHUNK)],
                cin: vec![0.0; cm.n_in * CHUNK],
                ch: vec![0.0; mlp::hidden_len(&cm, CHUNK)],
                rgb: vec![0.0; 3 * CHUNK],
                d_rgb: vec![0.0; 3 * CHUNK],
                d_hidden: vec![0.0; 2 * 64 * CHUNK],
                d_dens: vec![0.0; DENSITY_OUT * CHUNK],
                d_x: vec![0.0; dm.n_in * CHUNK],
                grad: vec![0.0; self.layout.grid_offset],
            }
        }

        #[allow(clippy::too_many_arguments)]
        fn run(
            &self,
            params: &[f32],
            enc: &[f32],
            ld_enc: usize,
            dirs: &[f32],
            n: usize,
            d_out: Option<&[f32]>,
            st: &mut CpuState,
        ) {
            let l = &self.layout;
            let (dm, cm) = (l.density_mlp, l.color_mlp);
            let wd = &params[l.density_offset..l.color_offset];
            let wc = &params[l.color_offset..l.grid_offset];
            let n_enc = l.grid.config.n_output_dims();
            let (gd, gc) = st.grad.split_at_mut(l.color_offset);
            for c0 in (0..n).step_by(CHUNK) {
                let m = CHUNK.min(n - c0);
                // The grid's output, as grid::forward leaves it in the workspace.
                for f in 0..n_enc {
                    st.x[f * CHUNK..f * CHUNK + m]
                        .copy_from_slice(&enc[f * ld_enc + c0..f * ld_enc + c0 + m]);
                }
                mlp::forward(
                    &dm,
                    wd,
                    &st.x,
                    &mut st.dh,
                    &mut st.cin[..DENSITY_OUT * CHUNK],
                    DENSITY_OUT,
                    m,
                    CHUNK,
                );
                let d: Vec<[f32; 3]> = (c0..c0 + m)
                    .map(|s| [dirs[3 * s], dirs[3 * s + 1], dirs[3 * s + 2]])
                    .collect();
                sh::encode(&d, &mut st.cin[DENSITY_OUT * CHUNK..], CHUNK);
                mlp::forward(&cm, wc, &st.cin, &mut st.ch, &mut st.rgb, 3, m, CHUNK);
                let Some(d_out) = d_out else { continue };
                for s in 0..m {
                    for k in 0..3 {
                        st.d_rgb[k * CHUNK + s] = d_out[4 * (c0 + s) + k];
                    }
                }
                mlp::backward(
                    &cm,
                    wc,
                    &st.cin,
                    &st.ch,
                    &st.d_rgb,
                    3,
                    m,
                    CHUNK,
                    gc,
                    &mut st.d_hidden,
                    Some((&mut st.d_dens, DENSITY_OUT)),
                );
                for s in 0..m {
                    st.d_dens[s] += d_out[4 * (c0 + s) + 3];
                }
                mlp::backward(
                    &dm,
                    wd,
                    &st.x,
                    &st.dh,
                    &st.d_dens,
                    DENSITY_OUT,
                    m,
                    CHUNK,
                    gd,
                    &mut st.d_hidden,
                    Some((&mut st.d_x, n_enc)),
                );
            }
        }
    }

    fn best_of(reps: usize, mut f: impl FnMut()) -> f64 {
        f(); // warm-up: pipelines, first touch
        (0..reps)
            .map(|_| {
                let t = Instant::now();
                f();
                t.elapsed().as_secs_f64()
            })
            .fold(f64::INFINITY, f64::min)
    }
}
