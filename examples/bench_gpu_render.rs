//! One view rendered by `gpu::GpuRenderer` on the adapter found beside the CPU engine's
//! `render_image` (rayon, every core), and the key holder's occupancy rebuild
//! (`rebuild_occupancy_gpu` against `rebuild_occupancy`, one point a cell).
//!
//! cargo run --release --example bench_gpu_render -- [RES] [auto|software|any] [MODEL.ingp]
//!
//! Without a model, a generated object scene (20 views of RES×RES, default 200) is trained
//! on the CPU for 100 steps of 2^13 samples first (a real occupancy grid and surfaces, so
//! that rays stop where a trained model's do); with one, its stored grid and first training
//! camera (as a pinhole), scaled to RES wide. GPU: best of 3 after a warm-up render (buffers
//! and pipelines made; one run where the warm-up took over 2 s), everything from the camera
//! to the pixels read back included; CPU: best of 3.

use std::sync::Arc;
use std::time::Instant;
use stegongp::backend::Device;
use stegongp::dataset::LoadOptions;
use stegongp::gpu::{GpuContext, GpuRenderer, rebuild_occupancy_gpu};
use stegongp::ngp::camera::Camera;
use stegongp::ngp::data::Split;
use stegongp::ngp::encoding::reference_indices;
use stegongp::ngp::model::Model;
use stegongp::ngp::network::ModelConfig;
use stegongp::ngp::render::image::{RenderOptions, render_image};
use stegongp::score::metrics::psnr;
use stegongp::stego::occupancy::rebuild_occupancy;
use stegongp::synth::{SceneKind, SynthOptions, generate};
use stegongp::training::recipe::{Budget, Recipe, StepOptions, StoredLoss};
use stegongp::training::run::{Run, RunOptions};

/// Best of `reps` (≥ 1) runs of `f`, in seconds, and its last result.
fn best<T>(reps: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut out = None;
    let mut t = f64::INFINITY;
    for _ in 0..reps.max(1) {
        let t0 = Instant::now();
        out = Some(f());
        t = t.min(t0.elapsed().as_secs_f64());
    }
    (t, out.expect("at least one run"))
}

fn fail(msg: impl std::fmt::Display) -> ! {
    eprintln!("{msg}");
    std::process::exit(1);
}

/// A generated object scene trained briefly on the CPU, and a held-out camera.
fn trained(res: u32) -> (Model, Camera) {
    let dir = tempfile::tempdir().unwrap_or_else(|e| fail(e));
    generate(
        &SynthOptions {
            scene: SceneKind::Object,
            resolution: res,
            n_train: 20,
            n_val: 0,
            n_test: 1,
            seed: 3,
            aabb_scale: 1,
            ..Default::default()
        },
        dir.path(),
    )
    .unwrap_or_else(|e| fail(e));
    let o = LoadOptions {
        downscale: 1,
        ..Default::default()
    };
    let train = stegongp::dataset::load(dir.path(), Split::Train, &o).unwrap_or_else(|e| fail(e));
    let test = stegongp::dataset::load(dir.path(), Split::Test, &o).unwrap_or_else(|e| fail(e));
    let mut cfg = ModelConfig::default();
    cfg.grid.log2_hashmap_size = 16;
    let t0 = Instant::now();
    let steps = StepOptions {
        seed: 7,
        batch: 1 << 13,
        occupancy_fraction: 1.0 / 16.0,
        occupancy_budget: None,
        coarse_march: None,
        ..StepOptions::default()
    };
    let mut recipe = Recipe::plain(cfg, Arc::new(train), steps, Budget::Steps(100));
    recipe.stored_loss = StoredLoss::Last;
    let cpu = Device::default();
    let recipe = recipe.check().unwrap_or_else(|e| fail(e));
    let mut run = Run::start(&recipe, &cpu, RunOptions::default()).unwrap_or_else(|e| fail(e));
    run.run(|_| Ok(())).unwrap_or_else(|e| fail(e));
    let model = run.finish().unwrap_or_else(|e| fail(e)).trained.model;
    println!(
        "trained the {res}×{res} object scene on the CPU: 100 steps of 2^13 samples in {:.1} s",
        t0.elapsed().as_secs_f64()
    );
    (model, test.frames[0].camera.clone())
}

/// `model`'s first training camera (as a pinhole), scaled to `res` pixels wide.
fn stored_camera(model: &Model, res: u32) -> Camera {
    let Some(im) = model.dataset.as_ref().and_then(|d| d.images.first()) else {
        fail("the model stores no training cameras")
    };
    let [w, h] = im.resolution.map(|v| v.max(1) as f32);
    let s = res as f32 / w;
    let height = ((h * s).round() as u32).max(1);
    Camera {
        c2w: im.xform_start,
        fx: im.focal_length[0] * s,
        fy: im.focal_length[1] * s,
        cx: im.principal_point[0] * res as f32,
        cy: im.principal_point[1] * height as f32,
        width: res,
        height,
        distortion: None,
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let res: u32 = args
        .get(1)
        .map_or(Ok(200), |s| s.parse())
        .unwrap_or_else(|e| fail(format!("RES: {e}")));
    let ctx = GpuContext::from_arg(args.get(2).map(String::as_str)).unwrap_or_else(|e| fail(e));
    let ctx = &ctx;
    println!("adapter: {}", ctx.report());
    let (model, cam) = match args.get(3) {
        Some(path) => {
            let m = Model::load(std::path::Path::new(path)).unwrap_or_else(|e| fail(e));
            let c = stored_camera(&m, res);
            (m, c)
        }
        None => trained(res),
    };
    let indices = reference_indices(&model.net.layout.grid);
    let opts = RenderOptions::default();

    let mut gpu = GpuRenderer::new(ctx, &model, &indices, &model.grid).unwrap_or_else(|e| fail(e));
    let t0 = Instant::now();
    gpu.render(&cam, &opts).unwrap_or_else(|e| fail(e));
    // A software adapter takes tens of seconds a view: one timed run is enough there.
    let reps = if t0.elapsed().as_secs_f64() > 2.0 {
        1
    } else {
        3
    };
    let (t_gpu, g) = best(reps, || gpu.render(&cam, &opts).unwrap_or_else(|e| fail(e)));
    let view = model.view(&indices, &model.grid);
    let (t_cpu, c) = best(3, || render_image(&view, &cam, &opts));
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    println!(
        "view {}×{}: {} samples (CPU {}), GPU vs CPU PSNR {:.2} dB",
        cam.width,
        cam.height,
        g.n_samples,
        c.n_samples,
        psnr(&g.rgb, &c.rgb)
    );
    println!(
        "{:<44} {:>12} {:>12}",
        "",
        "GPU",
        format!("CPU ({cores} cores)")
    );
    println!(
        "{:<44} {:>9.1} ms {:>11.1} ms",
        "render, ms / image",
        1e3 * t_gpu,
        1e3 * t_cpu
    );
    println!(
        "{:<44} {:>10.3} M {:>12.3} M",
        "render, samples / s",
        g.n_samples as f64 / t_gpu / 1e6,
        c.n_samples as f64 / t_cpu / 1e6
    );

    // The key holder's rebuild, one point a cell, under the reference index (the cost does
    // not depend on which index).
    let n_cells = model.grid.density.len();
    let t0 = Instant::now();
    let got = rebuild_occupancy_gpu(ctx, &model, &indices, 1, 5).unwrap_or_else(|e| fail(e));
    let t_gpu = t0.elapsed().as_secs_f64();
    let t0 = Instant::now();
    let want = rebuild_occupancy(
        &model.net,
        model.params(),
        &indices,
        model.config.aabb_scale,
        1,
        5,
    );
    let t_cpu = t0.elapsed().as_secs_f64();
    let differ = got
        .bitfield()
        .iter()
        .zip(want.bitfield())
        .map(|(a, b)| (a ^ b).count_ones())
        .sum::<u32>();
    println!(
        "{:<44} {:>10.2} s {:>12.2} s",
        format!("rebuild, 1 point a cell ({n_cells} cells)"),
        t_gpu,
        t_cpu
    );
    println!(
        "{:<44} {:>10.3} M {:>12.3} M   ({differ} bits differ)",
        "rebuild, cells / s",
        n_cells as f64 / t_gpu / 1e6,
        n_cells as f64 / t_cpu / 1e6
    );
}
