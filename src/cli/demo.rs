//! The whole story on generated scenes: a cover object and a hidden 3D-text message in one
//! Instant-NGP model; the cover renders for everyone, the text only with the key.

use super::common::{DeviceArg, ensure_dir, ensure_locked_dir};
use anyhow::Result;
use std::path::{Path, PathBuf};
use stegongp::backend::Device;
use stegongp::dataset::LoadOptions;
use stegongp::experiments::report::save_grid;
use stegongp::ngp::data::{Dataset, Split, save_png_rgb};
use stegongp::ngp::model::Model;
use stegongp::ngp::network::ModelConfig;
use stegongp::ngp::render::image::{RenderOptions, VIEWING_MIN_TRANSMITTANCE};
use stegongp::score::eval::{evaluate_on, ground_truth, spread_views};
use stegongp::score::lpips::Lpips;
use stegongp::stego::{Key, generate_prf, load_key, open_scene_on, save_key};
use stegongp::synth::{SceneKind, SynthOptions, generate};
use stegongp::training::recipe::{
    Budget, Checked, HiddenOptions, HiddenScene, Recipe, StepOptions, StoredLoss,
};
use stegongp::training::run::{Event, Run, RunOptions};
use stegongp::viewer::frame::Rgb8;
use stegongp::viewer::frame::{render_frame, video_frame_size};
use stegongp::viewer::path::{PathCamera, SceneRig};
use stegongp::viewer::video::Mp4Video;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Output directory (scenes, key, model, images).
    #[arg(long, default_value = "out/demo")]
    pub out: PathBuf,
    /// Resolution of the generated scenes.
    #[arg(long, default_value_t = 64)]
    pub res: u32,
    /// Training steps (each step trains both scenes).
    #[arg(long, default_value_t = 600)]
    pub steps: u32,
    /// Samples per scene per step.
    #[arg(long, default_value_t = 1 << 14)]
    pub batch: u32,
    /// The hidden message.
    #[arg(long, default_value = "(c) StegoNGP")]
    pub text: String,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Frames of the side-by-side orbit video (cover, key, wrong key) at 12 frames a
    /// second; 0: no video.
    #[arg(long, default_value_t = 24)]
    pub video_frames: usize,
    /// Side of each panel of the video, in pixels (even). A wrong key's haze fills the whole
    /// box, so its panel takes several times the cover's time to render.
    #[arg(long, default_value_t = 128)]
    pub video_size: u32,
    /// Side of each panel of the large figure, in pixels (even).
    #[arg(long, default_value_t = 256)]
    pub figure_size: u32,
    #[command(flatten)]
    pub device: DeviceArg,
}

pub fn run(a: Args) -> Result<()> {
    for (name, v) in [
        ("--figure-size", a.figure_size),
        ("--video-size", a.video_size),
    ] {
        if v == 0 || !v.is_multiple_of(2) || v > 2048 {
            anyhow::bail!("{name} {v}: an even number of pixels up to 2048");
        }
    }
    let t0 = std::time::Instant::now();
    let _lock = ensure_locked_dir(&a.out)?;
    let cover_dir = a.out.join("cover");
    let hidden_dir = a.out.join("hidden");
    generate_scenes(&a, &cover_dir, &hidden_dir)?;
    let key_path = a.out.join("secret.key");
    let key = if key_path.exists() {
        load_key(&key_path)?
    } else {
        let k = generate_prf(1)?;
        save_key(&key_path, &k, false)?;
        k
    };
    let opts = LoadOptions {
        downscale: 1,
        ..Default::default()
    };
    let (recipe, cover_cameras) = recipe(&a, &cover_dir, &hidden_dir, &key, &key_path, &opts)?;
    let device = a.device.open()?;
    eprintln!("device: {}", device.report());
    let model_path = a.out.join("model.ingp");
    let totals = train(&a, &recipe, &device, &model_path)?;

    // Everything below uses only the published file, as a viewer or a key holder would.
    let published = Published {
        device: &device,
        model: Model::load(&model_path)?,
        cover_test: stegongp::dataset::load(&cover_dir, Split::Test, &opts)?,
        hidden_test: stegongp::dataset::load(&hidden_dir, Split::Test, &opts)?,
        wrong: Key::wrong(a.seed ^ 0x5eed, &key),
        key,
        seed: a.seed,
    };
    let views = spread_views(published.cover_test.frames.len(), 8);
    let files = Files {
        images: a.out.join("images"),
        grid: a.out.join("demo.png"),
        large: a.out.join("demo_large.png"),
        video: a.out.join("demo.mp4"),
        model: model_path,
        key: key_path,
    };
    let rows = score_cases(&published, &views, &files)?;
    render_large(&a, &published, &views, &cover_cameras, &files)?;
    print_summary(&a, &device, totals, &rows, &files, t0);
    Ok(())
}

/// Generates the cover (an object) and the hidden scene (the text) where they are not
/// there yet.
fn generate_scenes(a: &Args, cover_dir: &Path, hidden_dir: &Path) -> Result<()> {
    for (dir, scene, seed) in [
        (cover_dir, SceneKind::Object, 1),
        (hidden_dir, SceneKind::Text(a.text.clone()), 2),
    ] {
        if !dir.join("transforms_train.json").exists() {
            eprintln!("generating {} ...", dir.display());
            generate(
                &SynthOptions {
                    scene,
                    resolution: a.res,
                    n_train: 60,
                    n_val: 0,
                    n_test: 8,
                    seed,
                    aabb_scale: 1,
                    ..Default::default()
                },
                dir,
            )?;
        }
    }
    Ok(())
}

/// The training of cover and hidden scene, and the cover's training cameras (the video
/// orbits them).
fn recipe(
    a: &Args,
    cover_dir: &Path,
    hidden_dir: &Path,
    key: &Key,
    key_path: &Path,
    opts: &LoadOptions,
) -> Result<(Checked, Vec<PathCamera>)> {
    let cover = stegongp::dataset::load(cover_dir, Split::Train, opts)?;
    let cover_cameras: Vec<PathCamera> = cover
        .frames
        .iter()
        .map(|f| PathCamera::of(&f.camera))
        .collect();
    let model = ModelConfig::default();
    let hidden = HiddenScene::load(
        hidden_dir,
        key.clone(),
        &key_path.display().to_string(),
        opts,
        model.aabb_scale,
    )?;
    let recipe = Recipe {
        model,
        cover: cover.into(),
        hidden: vec![hidden],
        // An eighth of the reference's occupancy-update samples, as the demo has always had.
        steps: StepOptions::reference_schedule(a.seed, a.batch, 0.125),
        options: HiddenOptions::default(),
        budget: Budget::Steps(a.steps),
        stored_loss: StoredLoss::Last,
    };
    Ok((recipe.check()?, cover_cameras))
}

/// Trains `recipe` with a progress bar and saves the model to `model_path`; returns the
/// training's seconds and samples.
fn train(a: &Args, recipe: &Checked, device: &Device, model_path: &Path) -> Result<(f64, u64)> {
    let mut run = Run::start(recipe, device, RunOptions::default())?;
    let pb = super::common::progress(
        a.steps as u64,
        "{spinner} training cover + hidden [{elapsed_precise}] {bar:30} {pos}/{len} {msg}",
    );
    run.run(|event| {
        let Event::Step(t) = event else {
            return Ok(());
        };
        pb.inc(1);
        pb.set_message(format!(
            "loss {:.4} {:.0}k samples/s",
            t.stored_loss(),
            t.totals().samples_per_second() / 1e3
        ));
        Ok(())
    })?;
    pb.finish_and_clear();
    let trained = run.finish()?.trained;
    trained.model.save(model_path)?;
    Ok((trained.totals.seconds, trained.totals.samples))
}

/// The published model, opened as a viewer or a key holder would, and the test views it
/// is scored on.
struct Published<'a> {
    device: &'a Device,
    model: Model,
    cover_test: Dataset,
    hidden_test: Dataset,
    key: Key,
    wrong: Key,
    seed: u64,
}

/// Where the demo writes.
struct Files {
    images: PathBuf,
    grid: PathBuf,
    large: PathBuf,
    video: PathBuf,
    model: PathBuf,
    key: PathBuf,
}

/// One scored rendering: label, PSNR, SSIM, LPIPS.
type Row = (&'static str, f64, f64, Option<f64>);

/// Scores the model with no key, the key and a wrong key on `views`, saves each case's
/// first view under `files.images` and the figure to `files.grid`.
fn score_cases(p: &Published, views: &[usize], files: &Files) -> Result<Vec<Row>> {
    let ropts = RenderOptions::default();
    let mut rows = Vec::new();
    let mut tiles = Vec::new();
    let mut blank = (0.0, 0.0, None);
    let cases: [(&str, Option<&Key>, &Dataset); 4] = [
        ("no key → cover", None, &p.cover_test),
        ("no key vs hidden text", None, &p.hidden_test),
        ("secret key → hidden text", Some(&p.key), &p.hidden_test),
        ("wrong key vs hidden text", Some(&p.wrong), &p.hidden_test),
    ];
    ensure_dir(&files.images)?;
    for (label, k, data) in cases {
        let scene = open_scene_on(p.device, &p.model, k, false, p.seed)?;
        let mut renderer = scene.renderer(p.device, &p.model)?;
        let mut first = None;
        let r = evaluate_on(
            renderer.as_mut(),
            data,
            &ropts,
            Some(views),
            Some(Lpips::embedded()),
            |_, img, _| {
                first.get_or_insert_with(|| img.rgb.clone());
            },
        )?;
        let img = first.unwrap_or_default();
        let name = label
            .split(' ')
            .take(2)
            .collect::<Vec<_>>()
            .join("_")
            .replace(['→', '/'], "");
        save_png_rgb(
            &files.images.join(format!("{name}.png")),
            data.width,
            data.height,
            &img,
        )?;
        tiles.push(img);
        rows.push((label, r.psnr, r.ssim, r.lpips));
        if std::ptr::eq(data, &p.hidden_test) {
            blank = (r.blank_psnr, r.blank_ssim, r.blank_lpips);
        }
    }
    // What an image of background only scores on the hidden views: a wrong key lands
    // near it (a faint haze), i.e. it shows nothing, not something cover-like.
    rows.push(("empty image vs hidden text", blank.0, blank.1, blank.2));
    tiles.insert(0, ground_truth(&p.hidden_test, views[0], [1.0; 3]));
    tiles.insert(0, ground_truth(&p.cover_test, views[0], [1.0; 3]));
    let (w, h) = (p.cover_test.width, p.cover_test.height);
    save_grid(&files.grid, &tiles, w, h, 3)?;
    Ok(rows)
}

/// Larger than the training images (a NeRF renders at any size): the figure's first view,
/// and an orbit video around `cover_cameras`, cover, key and wrong key side by side.
fn render_large(
    a: &Args,
    p: &Published,
    views: &[usize],
    cover_cameras: &[PathCamera],
    files: &Files,
) -> Result<()> {
    let looks: [(Option<&Key>, &str); 3] = [
        (None, "cover (no key)"),
        (Some(&p.key), "hidden (key)"),
        (Some(&p.wrong), "wrong key"),
    ];
    let opened = looks
        .iter()
        .map(|(k, _)| open_scene_on(p.device, &p.model, *k, false, p.seed))
        .collect::<stegongp::Result<Vec<_>>>()?;
    let mut renderers = opened
        .iter()
        .map(|s| s.renderer(p.device, &p.model))
        .collect::<stegongp::Result<Vec<_>>>()?;
    let labels: Vec<&str> = looks.iter().map(|(_, l)| *l).collect();
    // Pictures to look at stop rays where `render` and `video` do; the scores, where
    // `eval` does.
    let look = RenderOptions {
        min_transmittance: VIEWING_MIN_TRANSMITTANCE,
        ..RenderOptions::default()
    };
    let mut side_by_side = |camera: &PathCamera, size: u32| -> Result<Rgb8> {
        Ok(render_frame(
            &mut renderers,
            &labels,
            &camera.camera(size, size),
            &look,
        )?)
    };
    let large = side_by_side(
        &PathCamera::of(&p.cover_test.frames[views[0]].camera),
        a.figure_size,
    )?;
    stegongp::util::write_atomic(&files.large, &large.png())?;
    if a.video_frames > 0 {
        let rig = SceneRig::of(cover_cameras, [0.5; 3]).unwrap_or_else(SceneRig::default_object);
        let pb = super::common::progress(
            a.video_frames as u64,
            "{spinner} video [{elapsed_precise}] {bar:30} {pos}/{len} frames",
        );
        let (w, h) = video_frame_size(labels.len() as u32, a.video_size, a.video_size);
        let mut video = Mp4Video::create(&files.video, w, h, 12)?;
        for camera in rig.orbit(a.video_frames) {
            video.push(&side_by_side(&camera, a.video_size)?)?;
            pb.inc(1);
        }
        pb.finish_and_clear();
        video.finish()?;
    }
    Ok(())
}

/// The training's speed, the scores' table and where everything went; `(secs, samples)`:
/// the training's, `t0`: when the demo started.
fn print_summary(
    a: &Args,
    device: &Device,
    (secs, samples): (f64, u64),
    rows: &[Row],
    files: &Files,
    t0: std::time::Instant,
) {
    println!(
        "\nStegoNGP demo: one Instant-NGP model, {} steps on the {} ({:.0} s training, {:.0}k samples/s)",
        a.steps,
        device.report().kind,
        secs,
        samples as f64 / secs / 1e3
    );
    println!(
        "{:<28} {:>9} {:>7} {:>7}",
        "rendering", "PSNR dB", "SSIM", "LPIPS"
    );
    for (label, p, s, l) in rows {
        let l = l.map_or("—".to_string(), |l| format!("{l:.3}"));
        println!("{label:<28} {p:>9.2} {s:>7.3} {l:>7}");
    }
    println!(
        "\nmodel: {} (a plain instant-ngp snapshot; no key inside)",
        files.model.display()
    );
    println!("key:   {} (owner-only)", files.key.display());
    println!(
        "figure: {} — cover GT, hidden GT, no key, no key vs text, key, wrong key",
        files.grid.display()
    );
    println!(
        "large figure: {} — cover, key and wrong key at {} px",
        files.large.display(),
        a.figure_size
    );
    if a.video_frames > 0 {
        println!(
            "video: {} — {} frames orbiting, cover, key and wrong key",
            files.video.display(),
            a.video_frames
        );
    }
    println!(
        "images: {}; total {:.0} s",
        files.images.display(),
        t0.elapsed().as_secs_f64()
    );
}
