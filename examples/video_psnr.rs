//! PSNR of an MP4's frames (decoded with the codec's own decoder) against the PNG frames the
//! same `stegongp video` run wrote with `--frames-dir`, and what 4:2:0 alone would keep.
//!
//! cargo run --release --example video_psnr -- VIDEO.mp4 FRAMES_DIR

use stegongp::viewer::frame::Rgb8;
use stegongp::viewer::video::decode_mp4;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() != 3 {
        eprintln!("usage: video_psnr VIDEO.mp4 FRAMES_DIR");
        std::process::exit(2);
    }
    let video = decode_mp4(std::path::Path::new(&args[1])).unwrap_or_else(|e| {
        eprintln!("{e}");
        std::process::exit(1)
    });
    let dir = std::path::Path::new(&args[2]);
    let mut sum = 0.0;
    let mut worst = f64::INFINITY;
    let mut bound = 0.0;
    for (i, frame) in video.frames.iter().enumerate() {
        let png = Rgb8::load_png(&dir.join(format!("frame_{i:05}.png")))
            .expect("a PNG frame")
            .even();
        let p = frame.psnr(&png);
        sum += p;
        bound += png.chroma_420_psnr();
        worst = worst.min(p);
    }
    let n = video.frames.len() as f64;
    println!(
        "{} frames {}x{} at {:.2} fps: mean PSNR {:.2} dB, worst {:.2} dB against the rendered PNGs (4:2:0 alone: {:.2} dB)",
        video.frames.len(),
        video.width,
        video.height,
        video.fps,
        sum / n,
        worst,
        bound / n
    );
}
