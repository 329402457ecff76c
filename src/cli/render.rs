use super::common::{ViewArgs, Viewing, ensure_locked_dir, progress};
use anyhow::Result;
use std::path::PathBuf;
use stegongp::ngp::data::{save_png_gray, save_png_rgb};
use stegongp::ngp::render::image::VIEWING_MIN_TRANSMITTANCE;

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(flatten)]
    pub view: ViewArgs,
    /// Output directory for rgb_*.png, depth_*.png and opacity_*.png.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(a: Args) -> Result<()> {
    let Viewing {
        device,
        model,
        data,
        scene,
        opts,
        which,
    } = a.view.open(VIEWING_MIN_TRANSMITTANCE)?;
    let mut renderer = scene.renderer(&device, &model)?;
    eprintln!("device: {}", device.report());
    let _lock = ensure_locked_dir(&a.out)?;
    let pb = progress(
        which.len() as u64,
        "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} views {msg}",
    );
    for (done, &i) in which.iter().enumerate() {
        let started = std::time::Instant::now();
        let img = renderer.render(&data.frames[i].camera, &opts)?;
        let seconds = started.elapsed().as_secs_f64();
        let (w, h) = (img.width, img.height);
        pb.suspend(|| {
            eprintln!(
                "[{}/{}] view {i:3}: {w}×{h} in {seconds:.2} s{}",
                done + 1,
                which.len(),
                img.profile_note()
            )
        });
        save_png_rgb(&a.out.join(format!("rgb_{i:03}.png")), w, h, &img.rgb)?;
        let max_depth = img.depth.iter().cloned().fold(0.0f32, f32::max).max(1e-6);
        save_png_gray(
            &a.out.join(format!("depth_{i:03}.png")),
            w,
            h,
            &img.depth,
            max_depth,
        )?;
        save_png_gray(
            &a.out.join(format!("opacity_{i:03}.png")),
            w,
            h,
            &img.opacity,
            1.0,
        )?;
        pb.inc(1);
    }
    pb.finish_and_clear();
    eprintln!("rendered {} views into {}", which.len(), a.out.display());
    Ok(())
}
