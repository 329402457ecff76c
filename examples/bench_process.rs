//! The generated capture of `stegongp process`'s benchmark: the room photographed along an
//! arc from known cameras (as tests/process_cli.rs does, at any size), and how far a
//! reconstruction's poses are from them.
//!
//! cargo run --release --example bench_process -- render DIR VIEWS WIDTH HEIGHT [ARC_DEG]
//!     DIR/images/NNNN.png, and DIR/sparse/0/*.txt: the true cameras as a COLMAP model, a
//!     capture `train` reads and normalises exactly as it does `process`'s output
//! cargo run --release --example bench_process -- errors TRUE_DIR CAPTURE_DIR
//!     CAPTURE_DIR/sparse/0 against the true cameras (frame_NNNNNN.png, a video's frame
//!     names, is view NNNN); JSON on stdout

use std::collections::HashMap;
use std::path::Path;
use stegongp::dataset::colmap::read_model;
use stegongp::dataset::colmap2nerf::colmap_c2w;
use testkit::capture::{Arc, Pose, pose_errors, room_arc, write_colmap_text, write_png};

fn render(dir: &Path, views: usize, width: u32, height: u32, arc_deg: f32) {
    let a = Arc {
        views,
        width,
        height,
        fov_deg: 65.0,
        arc_deg,
        grain: 0.8,
    };
    let t0 = std::time::Instant::now();
    let (frames, poses, focal) = room_arc(&a);
    let images = dir.join("images");
    std::fs::create_dir_all(&images).expect("images folder");
    let names: Vec<String> = (0..views).map(|i| format!("{i:04}.png")).collect();
    for (name, f) in names.iter().zip(&frames) {
        write_png(&images.join(name), width, height, f);
    }
    write_colmap_text(&dir.join("sparse/0"), &names, &poses, width, height, focal);
    eprintln!(
        "{views} views of {width}x{height} in {:.1} s into {}",
        t0.elapsed().as_secs_f64(),
        dir.display()
    );
}

/// The true cameras of a rendered capture, by image name, under both naming schemes.
fn known(true_dir: &Path) -> HashMap<String, Pose> {
    let model = read_model(&true_dir.join("sparse/0")).expect("the true cameras");
    let mut k = HashMap::new();
    for im in model.images {
        // Back from COLMAP's OpenCV world-to-camera to an OpenGL camera-to-world.
        let m = colmap_c2w(im.qvec, im.tvec);
        let mut p = [[0.0f32; 4]; 4];
        for i in 0..3 {
            p[i] = [
                m[i][0] as f32,
                -m[i][1] as f32,
                -m[i][2] as f32,
                m[i][3] as f32,
            ];
        }
        p[3][3] = 1.0;
        let n: usize = im.name.trim_end_matches(".png").parse().expect("NNNN.png");
        k.insert(format!("frame_{n:06}.png"), p);
        k.insert(im.name, p);
    }
    k
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    match a.get(1).map(String::as_str) {
        Some("render") if a.len() >= 6 => render(
            Path::new(&a[2]),
            a[3].parse().expect("VIEWS"),
            a[4].parse().expect("WIDTH"),
            a[5].parse().expect("HEIGHT"),
            a.get(6).map_or(120.0, |s| s.parse().expect("ARC_DEG")),
        ),
        Some("errors") if a.len() == 4 => {
            let e = pose_errors(&Path::new(&a[3]).join("sparse/0"), &known(Path::new(&a[2])));
            println!(
                "{}",
                serde_json::json!({
                    "cameras": e.cameras,
                    "max_rotation_deg": e.max_rotation_deg,
                    "mean_rotation_deg": e.mean_rotation_deg,
                    "max_position_share": e.max_position,
                    "mean_position_share": e.mean_position,
                })
            );
        }
        _ => {
            eprintln!(
                "usage: bench_process render DIR VIEWS WIDTH HEIGHT [ARC_DEG] | errors TRUE_DIR CAPTURE_DIR"
            );
            std::process::exit(2);
        }
    }
}
