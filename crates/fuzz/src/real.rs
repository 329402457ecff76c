//! Seeds from the real datasets in `../shared/data` (read in place, never copied into the
//! repository): lego's and fox's transforms files, fox-colmap's binary and text models,
//! flower's and horns' `poses_bounds.npy`, and real PNGs and JPEGs. A dataset's photos are
//! replaced by tiny stand-ins of the same names, so a case stays small: the files that
//! describe the capture are the real ones.

use crate::seeds::{Case, jpeg_sized, png};
use std::path::Path;

fn read(p: &Path) -> Option<Vec<u8>> {
    std::fs::read(p).ok()
}

fn names_in(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .map(|d| {
            d.filter_map(|e| e.ok())
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

/// A stand-in of the kind the name says, with the real image's aspect ratio (the loaders
/// check that an image is the camera's picture at some size) and a side of tens of pixels.
fn stand_in(name: &str, real: &Path) -> Vec<u8> {
    let (w, h) = ngp::data::image::image_size(real).unwrap_or((8, 8));
    let g = gcd(w, h).max(1);
    let (mut w, mut h) = (w / g, h / g);
    while w.max(h) < 16 {
        (w, h) = (w * 2, h * 2);
    }
    let lower = name.to_ascii_lowercase();
    if lower.ends_with(".jpg") || lower.ends_with(".jpeg") {
        jpeg_sized(w.min(4096) as u16, h.min(4096) as u16)
    } else {
        png(w.min(4096), h.min(4096), false)
    }
}

fn gcd(a: u32, b: u32) -> u32 {
    if b == 0 { a } else { gcd(b, a % b) }
}

/// A transforms file cut to its first `n` frames, with stand-ins for their images.
fn transforms_case(root: &Path, files: &[&str], n: usize, real_images: bool) -> Option<Case> {
    let mut case = Vec::new();
    for f in files {
        let mut v: serde_json::Value = serde_json::from_slice(&read(&root.join(f))?).ok()?;
        let frames = v.get_mut("frames")?.as_array_mut()?;
        frames.truncate(n);
        for fr in frames.iter() {
            let p = fr.get("file_path")?.as_str()?.trim_start_matches("./");
            let with_ext = if Path::new(p).extension().is_some() {
                p.to_string()
            } else {
                format!("{p}.png")
            };
            if !root.join(&with_ext).is_file() {
                continue; // a frame whose photo is missing, as fox has: the loader skips it
            }
            let bytes = if real_images {
                read(&root.join(&with_ext))?
            } else {
                stand_in(&with_ext, &root.join(&with_ext))
            };
            case.push((with_ext, bytes));
        }
        case.push((f.to_string(), serde_json::to_vec_pretty(&v).ok()?));
    }
    Some(case)
}

fn capture_case(root: &Path, model: &[(&str, &str)], images: &str) -> Option<Case> {
    let mut case = Vec::new();
    for (from, to) in model {
        case.push((to.to_string(), read(&root.join(from))?));
    }
    for n in names_in(&root.join(images)) {
        let name = format!("{images}/{n}");
        case.push((name.clone(), stand_in(&name, &root.join(&name))));
    }
    Some(case)
}

/// The real seeds of `target` below `data` (empty where none apply or the data is absent).
pub fn seeds(target: &str, data: &Path) -> Vec<Case> {
    let mut out: Vec<Option<Case>> = Vec::new();
    match target {
        "transforms" => {
            let lego = data.join("lego");
            out.push(transforms_case(
                &lego,
                &["transforms_train.json", "transforms_test.json"],
                2,
                true,
            ));
            out.push(transforms_case(
                &data.join("fox"),
                &["transforms.json"],
                9,
                false,
            ));
        }
        "colmap" => {
            let fc = data.join("fox-colmap");
            let bins = ["cameras.bin", "images.bin", "points3D.bin"].map(|f| {
                let p = format!("sparse/0/{f}");
                (p.clone(), p)
            });
            let bins: Vec<(&str, &str)> =
                bins.iter().map(|(a, b)| (a.as_str(), b.as_str())).collect();
            out.push(capture_case(&fc, &bins, "images"));
            let txts = ["cameras.txt", "images.txt", "points3D.txt"]
                .map(|f| (format!("sparse_txt/0/{f}"), format!("sparse/0/{f}")));
            let txts: Vec<(&str, &str)> =
                txts.iter().map(|(a, b)| (a.as_str(), b.as_str())).collect();
            out.push(capture_case(&fc, &txts, "images"));
        }
        "llff" => {
            for scene in ["flower", "horns"] {
                out.push(capture_case(
                    &data.join(scene),
                    &[("poses_bounds.npy", "poses_bounds.npy")],
                    "images_8",
                ));
            }
        }
        "image" => {
            let first = |dir: &Path| names_in(dir).into_iter().next().map(|n| dir.join(n));
            for (dir, name) in [
                (data.join("lego/train"), "a.png"),
                (data.join("horns/images_8"), "a.png"),
                (data.join("fox/images"), "a.jpg"),
            ] {
                out.push(
                    first(&dir)
                        .and_then(|p| read(&p))
                        .map(|b| vec![(name.to_string(), b)]),
                );
            }
        }
        _ => {}
    }
    out.into_iter().flatten().collect()
}
