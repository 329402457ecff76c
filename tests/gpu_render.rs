//! Rendering and the key holder's occupancy rebuild on the device (`crates/gpu/src/renderer.rs`)
//! against the CPU engine (`render_image`, `OccupancyGrid::rebuild`), on a small stego model
//! trained on the CPU: a generated object as the cover (reference index) and a generated
//! logo as the hidden scene (a seeded `prf` key).
#![cfg(feature = "gpu")]

use std::sync::{Arc, OnceLock};
use std::time::Instant;
use stegongp::gpu::{GpuRenderer, rebuild_occupancy_gpu, refine_occupancy_gpu, test_context};
use stegongp::ngp::camera::{Camera, Distortion};
use stegongp::ngp::data::Dataset;
use stegongp::ngp::encoding::{LevelIndices, reference_indices};
use stegongp::ngp::model::Model;
use stegongp::ngp::network::ModelConfig;
use stegongp::ngp::occupancy::{GRID_SIZE, N_CELLS, OccupancyGrid, morton3d_invert};
use stegongp::ngp::render::image::{RenderOptions, RenderedImage, SceneView, render_image};
use stegongp::score::metrics::psnr;
use stegongp::stego::SchemeKind;
use stegongp::stego::occupancy::{rebuild_occupancy, refine_occupancy};
use stegongp::synth::SceneKind;
use stegongp::training::recipe::StepOptions;
use testkit::keys::seeded_key;
use testkit::models::trained;
use testkit::scenes::generated;

/// CPU training steps of the fixture: enough that both scenes have surfaces, opaque and
/// semi-transparent regions and empty space for the comparisons to cover.
const STEPS: u32 = 60;
/// Points per cell of the rebuilds compared here (the key holder's default is 4): every
/// round is a pass of the network over all 2^21 cells, which llvmpipe runs at ~0.1 M
/// cells/s. The rounds' octants and seeds are checked bit for bit by the unit test
/// `gpu::occupancy::tests::rebuild_rounds_match_the_cpu`.
const REBUILD_SAMPLES: usize = 1;
const REBUILD_SEED: u64 = 0x5eed;

struct Fixture {
    _dir: tempfile::TempDir,
    model: Model,
    cover_test: Dataset,
    hidden_test: Dataset,
    reference: LevelIndices,
    key: LevelIndices,
    /// The hidden scene's grid rebuilt by the CPU and by the device.
    cpu_grid: OccupancyGrid,
    gpu_grid: OccupancyGrid,
}

fn scene(dir: &std::path::Path, scene: SceneKind, seed: u64) -> (Dataset, Dataset) {
    generated(dir, scene, 40, 40, 4, seed).pair()
}

fn fixture() -> Option<&'static Fixture> {
    let ctx = test_context()?;
    static F: OnceLock<Fixture> = OnceLock::new();
    Some(F.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let (cover_train, cover_test) = scene(&dir.path().join("cover"), SceneKind::Object, 3);
        let (hidden_train, hidden_test) = scene(&dir.path().join("hidden"), SceneKind::Logo, 20);
        let mut cfg = ModelConfig::default();
        cfg.grid.log2_hashmap_size = 16;
        let layout = stegongp::ngp::network::NerfLayout::new(cfg).unwrap();
        let key = seeded_key(SchemeKind::Prf, 1, 42, 1);
        let reference = reference_indices(&layout.grid);
        let t0 = Instant::now();
        // The fixture is built by hand on the reference's schedule and step.
        let steps = StepOptions::reference_schedule(7, 1 << 12, 1.0 / 128.0);
        let hidden = vec![(Arc::new(hidden_train), key.clone())];
        let model = trained(cfg, Arc::new(cover_train), hidden, steps, STEPS);
        let key = key.level_indices(&layout.grid);
        eprintln!("CPU training: {:.1} s", t0.elapsed().as_secs_f64());

        let t0 = Instant::now();
        let cpu_grid = rebuild_occupancy(
            &model.net,
            model.params(),
            &key,
            1,
            REBUILD_SAMPLES,
            REBUILD_SEED,
        );
        let t_cpu = t0.elapsed().as_secs_f64();
        let t0 = Instant::now();
        let gpu_grid =
            rebuild_occupancy_gpu(ctx, &model, &key, REBUILD_SAMPLES, REBUILD_SEED).unwrap();
        eprintln!(
            "rebuild, {REBUILD_SAMPLES} point(s) a cell: CPU {t_cpu:.1} s, GPU {:.1} s",
            t0.elapsed().as_secs_f64()
        );
        Fixture {
            _dir: dir,
            model,
            cover_test,
            hidden_test,
            reference,
            key,
            cpu_grid,
            gpu_grid,
        }
    }))
}

/// How two renderings of one view differ.
struct Agreement {
    psnr: f64,
    max_opacity: f32,
    /// Largest depth difference among pixels both see as at least half opaque.
    max_depth: f32,
    /// Pixels whose opacity differs by more than 0.01.
    opacity_outliers: usize,
    samples: (u64, u64),
}

fn compare(cpu: &RenderedImage, gpu: &RenderedImage) -> Agreement {
    assert_eq!((cpu.width, cpu.height), (gpu.width, gpu.height));
    assert_eq!(cpu.rgb.len(), gpu.rgb.len());
    let mut max_opacity = 0f32;
    let mut max_depth = 0f32;
    let mut opacity_outliers = 0;
    for i in 0..cpu.opacity.len() {
        let d = (cpu.opacity[i] - gpu.opacity[i]).abs();
        assert!(
            d.is_finite(),
            "pixel {i}: {} vs {}",
            cpu.opacity[i],
            gpu.opacity[i]
        );
        max_opacity = max_opacity.max(d);
        opacity_outliers += (d > 0.01) as usize;
        if cpu.opacity[i] > 0.5 && gpu.opacity[i] > 0.5 {
            max_depth = max_depth.max((cpu.depth[i] - gpu.depth[i]).abs());
        }
    }
    Agreement {
        psnr: psnr(&gpu.rgb, &cpu.rgb),
        max_opacity,
        max_depth,
        opacity_outliers,
        samples: (cpu.n_samples, gpu.n_samples),
    }
}

/// Renders `cams` on both sides and checks every view: RGB PSNR ≥ 40 dB, opacity and depth
/// close, sample counts close.
fn check_views(
    what: &str,
    view: &SceneView,
    gpu: &mut GpuRenderer,
    cams: &[Camera],
    opts: &RenderOptions,
) {
    for (k, cam) in cams.iter().enumerate() {
        let t0 = Instant::now();
        let cpu = render_image(view, cam, opts);
        let t_cpu = t0.elapsed().as_secs_f64();
        let t0 = Instant::now();
        let got = gpu.render(cam, opts).unwrap();
        let t_gpu = t0.elapsed().as_secs_f64();
        let a = compare(&cpu, &got);
        let seen = cpu.opacity.iter().filter(|&&o| o > 0.5).count();
        eprintln!(
            "{what} view {k} ({}×{}): PSNR {:.2} dB, max |Δopacity| {:.2e} ({} > 0.01), \
             max |Δdepth| {:.2e}, samples CPU {} GPU {}, {seen} opaque pixels; \
             CPU {t_cpu:.2} s, GPU {t_gpu:.2} s",
            cam.width,
            cam.height,
            a.psnr,
            a.max_opacity,
            a.opacity_outliers,
            a.max_depth,
            a.samples.0,
            a.samples.1
        );
        assert!(a.psnr >= 40.0, "{what} view {k}: PSNR {:.2} dB", a.psnr);
        assert!(
            a.opacity_outliers * 100 <= cpu.opacity.len(),
            "{what} view {k}: {} pixels' opacity differ by > 0.01",
            a.opacity_outliers
        );
        assert!(
            a.max_depth <= 0.05,
            "{what} view {k}: depth off by {}",
            a.max_depth
        );
        let (c, g) = (a.samples.0 as f64, a.samples.1 as f64);
        assert!(
            (c - g).abs() <= 0.01 * c + 100.0,
            "{what} view {k}: {c} vs {g} samples"
        );
    }
}

fn test_cams(data: &Dataset) -> Vec<Camera> {
    data.frames.iter().map(|f| f.camera.clone()).collect()
}

/// (a) The cover: reference index, the grid training left.
#[test]
fn cover_views_match_the_cpu() {
    let Some(f) = fixture() else { return };
    let ctx = test_context().unwrap();
    let m = &f.model;
    let mut gpu = GpuRenderer::new(ctx, m, &f.reference, &m.grid).unwrap();
    let view = m.view(&f.reference, &m.grid);
    let cams = test_cams(&f.cover_test);
    check_views("cover", &view, &mut gpu, &cams, &RenderOptions::default());
}

/// (b) The hidden scene as its key holder sees it: the key's index, the grid rebuilt on
/// each side (the device's own rebuild on the device, the CPU's on the CPU), over a black
/// background; the renderer switches scenes without uploading the weights again.
#[test]
fn hidden_views_under_the_key_match_the_cpu() {
    let Some(f) = fixture() else { return };
    let ctx = test_context().unwrap();
    let m = &f.model;
    let mut gpu = GpuRenderer::new(ctx, m, &f.reference, &m.grid).unwrap();
    gpu.set_scene(&f.key, &f.gpu_grid).unwrap();
    let view = m.view(&f.key, &f.cpu_grid);
    let opts = RenderOptions {
        background: [0.0; 3],
        ..Default::default()
    };
    let cams = test_cams(&f.hidden_test);
    check_views("hidden", &view, &mut gpu, &cams[..2], &opts);
}

/// (c) The rebuild on the device against `OccupancyGrid::rebuild` with the CPU network:
/// the same points (drawn bit for bit), so densities agree to the two networks' rounding;
/// the bitfields agree except for cells at the threshold.
#[test]
fn rebuilt_grid_matches_the_cpu() {
    let Some(f) = fixture() else { return };
    let (cpu, gpu) = (&f.cpu_grid, &f.gpu_grid);
    assert_eq!(gpu.n_cascades, cpu.n_cascades);
    assert_eq!(gpu.ema_step, cpu.ema_step);
    let mut max_rel = 0f32;
    for (i, (&g, &c)) in gpu.density.iter().zip(&cpu.density).enumerate() {
        let rel = (g - c).abs() / c.abs().max(1e-12);
        assert!(rel <= 1e-3, "cell {i}: {g} vs {c}");
        max_rel = max_rel.max(rel);
    }
    assert!(
        (gpu.mean - cpu.mean).abs() <= 1e-4 * cpu.mean,
        "mean {} vs {}",
        gpu.mean,
        cpu.mean
    );
    let thresh = cpu.mean.min(0.01);
    // Cells of cascade 0 whose bit differs, and how many lie within 1e-3 of the threshold.
    let bit = |g: &OccupancyGrid, i: usize| g.bitfield()[i / 8] >> (i % 8) & 1;
    let mut differ = 0;
    for i in 0..N_CELLS * cpu.n_cascades {
        if bit(gpu, i) != bit(cpu, i) {
            differ += 1;
            let d = cpu.density[i];
            assert!(
                i >= N_CELLS || (d - thresh).abs() <= 1e-3 * thresh,
                "cell {i}: density {d} (GPU {}), threshold {thresh}",
                gpu.density[i]
            );
        }
    }
    let near = cpu
        .density
        .iter()
        .filter(|&&d| (d - thresh).abs() <= 1e-3 * thresh)
        .count();
    let occupied: u32 = cpu.bitfield().iter().map(|b| b.count_ones()).sum();
    eprintln!(
        "rebuild: densities within {max_rel:.2e} relative, mean {} vs {}; {differ} bits \
         differ, {near} cells within 1e-3 of the threshold {thresh}; {occupied} bits set",
        gpu.mean, cpu.mean
    );
    assert!(
        differ <= near.max(1),
        "{differ} bits differ, {near} cells near"
    );
    assert!(
        occupied > 1000,
        "the rebuilt grid is not trivial: {occupied} bits"
    );
}

/// (d) Cameras off the training rig: a distorted (OpenCV) one, one far outside the box
/// (most rays miss it), one inside it (rays start at t = 0); also more samples per wave
/// and small tiles (several tiles a view).
#[test]
fn unusual_cameras_and_tiles_match_the_cpu() {
    let Some(f) = fixture() else { return };
    let ctx = test_context().unwrap();
    let m = &f.model;
    let mut gpu = GpuRenderer::new(ctx, m, &f.reference, &m.grid).unwrap();
    let view = m.view(&f.reference, &m.grid);
    let base = f.cover_test.frames[0].camera.clone();
    let mut distorted = base.clone();
    distorted.distortion = Some(Distortion {
        k1: -0.12,
        k2: 0.03,
        p1: 0.002,
        p2: -0.001,
    });
    // Ten times as far from the box's centre, with a longer lens: the object small.
    let mut far = base.clone();
    for r in 0..3 {
        far.c2w[r][3] = 0.5 + 10.0 * (base.c2w[r][3] - 0.5);
    }
    far.fx *= 6.0;
    far.fy *= 6.0;
    // Inside the box, looking at the centre from a quarter of the way.
    let mut inside = base.clone();
    for r in 0..3 {
        inside.c2w[r][3] = 0.5 + 0.25 * (base.c2w[r][3] - 0.5).signum();
    }
    check_views(
        "distorted/far/inside",
        &view,
        &mut gpu,
        &[distorted, far, inside],
        &RenderOptions::default(),
    );
    gpu.set_max_wave_samples(1024);
    let opts = RenderOptions {
        samples_per_wave: 13,
        background: [0.2, 0.5, 0.9],
        ..Default::default()
    };
    check_views("tiles of 78 rays", &view, &mut gpu, &[base], &opts);
}

/// The waves of a tile are recorded a batch at a time and the host waits once a batch, not
/// once a wave: one sample a ray per wave makes a tile take as many waves as its longest
/// ray has samples, and the view still matches the CPU's. Two tiles of 800 rays.
#[test]
fn waves_are_read_back_a_batch_at_a_time() {
    let Some(f) = fixture() else { return };
    let ctx = test_context().unwrap();
    let m = &f.model;
    let mut gpu = GpuRenderer::new(ctx, m, &f.reference, &m.grid).unwrap();
    gpu.set_max_wave_samples(1024);
    let opts = RenderOptions {
        samples_per_wave: 1,
        ..Default::default()
    };
    let cam = f.cover_test.frames[0].camera.clone();
    check_views(
        "one sample a wave",
        &m.view(&f.reference, &m.grid),
        &mut gpu,
        std::slice::from_ref(&cam),
        &opts,
    );
    let w = gpu.last_waits();
    eprintln!("one sample a wave: {w:?}");
    let pixels = cam.width * cam.height;
    assert_eq!(w.tiles, pixels.div_ceil(1024), "{w:?}");
    assert!(
        w.waves >= 40 * w.tiles,
        "too few waves to test batching: {w:?}"
    );
    // A wait a wave would be w.waves + w.tiles; batches of 4, 8, 16, then 32 waves, and the
    // pixels, wait far less.
    assert!(w.waits <= w.tiles * 5 + w.waves / 32, "{w:?}");
}

/// An 800×800 view (the paper's test resolution) renders in tiles within the device's
/// storage-binding limits (llvmpipe: 128 MiB, which the default wave's grid encoding fills
/// exactly). The grid keeps only the cells of a small ball at the centre, so that the
/// network runs on few samples and llvmpipe finishes quickly; every ray still marches.
#[test]
fn a_large_view_renders_in_tiles() {
    let Some(f) = fixture() else { return };
    let ctx = test_context().unwrap();
    let m = &f.model;
    let mut grid = m.grid.clone();
    for (i, d) in grid.density.iter_mut().enumerate() {
        let c =
            |axis: u32| (morton3d_invert(i as u32 >> axis) as f32 + 0.5) / GRID_SIZE as f32 - 0.5;
        if c(0).powi(2) + c(1).powi(2) + c(2).powi(2) > 0.05f32.powi(2) {
            *d = 0.0;
        }
    }
    grid.update_bitfield();
    let mut cam = f.cover_test.frames[1].camera.clone();
    let s = 800.0 / cam.width as f32;
    (cam.fx, cam.fy, cam.cx, cam.cy) = (cam.fx * s, cam.fy * s, cam.cx * s, cam.cy * s);
    (cam.width, cam.height) = (800, 800);
    let mut gpu = GpuRenderer::new(ctx, m, &f.reference, &grid).unwrap();
    check_views(
        "800×800",
        &m.view(&f.reference, &grid),
        &mut gpu,
        &[cam],
        &RenderOptions::default(),
    );
}

#[test]
fn bad_inputs_are_errors() {
    let Some(f) = fixture() else { return };
    let ctx = test_context().unwrap();
    let m = &f.model;
    let mut gpu = GpuRenderer::new(ctx, m, &f.reference, &m.grid).unwrap();
    let cam = f.cover_test.frames[0].camera.clone();
    let zero = RenderOptions {
        samples_per_wave: 0,
        ..Default::default()
    };
    assert!(gpu.render(&cam, &zero).is_err());
    let huge = RenderOptions {
        samples_per_wave: 1 << 30,
        ..Default::default()
    };
    assert!(gpu.render(&cam, &huge).is_err());
    let wrong = OccupancyGrid::new(4);
    assert!(gpu.set_scene(&f.reference, &wrong).is_err());
    assert!(GpuRenderer::new(ctx, m, &f.reference, &wrong).is_err());
    assert!(gpu.set_scene(&f.reference[..3].to_vec(), &m.grid).is_err());
    let mut empty = cam.clone();
    empty.width = 0;
    let img = gpu.render(&empty, &RenderOptions::default()).unwrap();
    assert!(img.rgb.is_empty() && img.n_samples == 0);
    // Still renders after the refusals.
    gpu.render(&cam, &RenderOptions::default()).unwrap();
}

/// The key holder's second stage, more points near the occupied cells, with the densities
/// on the device: the cells the host picks from the device's rebuilt grid are the CPU's, and
/// they get the CPU's densities (to the device's rounding).
#[test]
fn refined_grid_matches_the_cpu() {
    let Some(f) = fixture() else { return };
    let Some(ctx) = test_context() else { return };
    const MORE: usize = 4;
    let (mut cpu, mut gpu) = (f.cpu_grid.clone(), f.gpu_grid.clone());
    let aabb = f.model.config.aabb_scale;
    let want = refine_occupancy(
        &f.model.net,
        f.model.params(),
        &f.key,
        &mut cpu,
        aabb,
        MORE,
        REBUILD_SAMPLES,
        REBUILD_SEED,
    );
    let got = refine_occupancy_gpu(
        ctx,
        &f.model,
        &f.key,
        &mut gpu,
        MORE,
        REBUILD_SAMPLES,
        REBUILD_SEED,
    )
    .unwrap();
    assert_eq!(got, want, "the same cells sampled again");
    assert!(want.cells > 0, "{want:?}");
    let mut raised = 0;
    for (i, ((&g, &c), &before)) in gpu
        .density
        .iter()
        .zip(&cpu.density)
        .zip(&f.cpu_grid.density)
        .enumerate()
    {
        let rel = (g - c).abs() / c.abs().max(1e-12);
        assert!(rel <= 1e-3, "cell {i}: {g} vs {c}");
        raised += usize::from(c > before);
    }
    eprintln!("refine: {want:?}, {raised} cells raised");
    assert!(raised > 0, "the refinement raised no cell");
}
