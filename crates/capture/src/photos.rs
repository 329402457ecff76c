//! A folder of photos: its JPEG and PNG files (not its subfolders), copied as they are, or
//! shrunk to the size cap and written as PNG. Every photo is read through the loaders'
//! own decoder first, so a file `train` could not read is named here, not after COLMAP.

use crate::Progress;
use crate::pixels::{capped_size, copy_synced, resize_area, write_png};
use anyhow::{Context, Result, bail};
use ngp::data::image::{decode_image_file, image_size};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

fn is_photo(p: &Path) -> bool {
    let ext = p
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    matches!(ext.as_deref(), Some("jpg" | "jpeg" | "png"))
}

/// The photos directly in `dir`, by name; an error when there are none.
pub fn list(dir: &Path) -> Result<Vec<PathBuf>> {
    let rd = std::fs::read_dir(dir).with_context(|| format!("{}: cannot list", dir.display()))?;
    let (mut photos, mut others) = (Vec::new(), 0usize);
    for e in rd {
        let e = e.with_context(|| format!("{}: cannot list", dir.display()))?;
        let p = e.path();
        let hidden = e.file_name().to_string_lossy().starts_with('.');
        if hidden || !p.is_file() {
            continue;
        }
        if is_photo(&p) {
            photos.push(p);
        } else {
            others += 1;
        }
    }
    photos.sort();
    if photos.is_empty() {
        bail!(
            "{}: no photos here (JPEG or PNG files directly in the folder; {others} other \
             file(s), subfolders not searched)",
            dir.display()
        );
    }
    if photos.len() < 3 {
        bail!(
            "{}: only {} photo(s); COLMAP needs many overlapping views of the scene (a few \
             dozen, each sharing most of what it sees with its neighbours)",
            dir.display(),
            photos.len()
        );
    }
    Ok(photos)
}

/// One photo's place in the output.
struct Plan {
    from: PathBuf,
    name: String,
    size: (u32, u32),
    resize: Option<(u32, u32)>,
}

/// Copies (or shrinks) `photos` into `images`; returns their names there and their common
/// size. Photos of several sizes after the cap are refused: the loaders take one size.
pub fn import(
    photos: &[PathBuf],
    max_side: u32,
    images: &Path,
    pb: &dyn Progress,
) -> Result<(Vec<String>, (u32, u32))> {
    let plans = plan(photos, max_side)?;
    let outs: Vec<(u32, u32)> = plans.iter().map(|p| p.resize.unwrap_or(p.size)).collect();
    let mut sizes: BTreeMap<(u32, u32), Vec<&str>> = BTreeMap::new();
    for (p, s) in plans.iter().zip(&outs) {
        sizes.entry(*s).or_default().push(&p.name);
    }
    if sizes.len() > 1 {
        let list: Vec<String> = sizes
            .iter()
            .map(|((w, h), n)| format!("{w}x{h}: {} (e.g. {})", n.len(), n[0]))
            .collect();
        bail!(
            "the photos come in {} sizes ({}); give photos of one size (one camera, one \
             orientation)",
            sizes.len(),
            list.join("; ")
        );
    }
    plans
        .par_iter()
        .map(|p| {
            let r = write(p, images);
            pb.inc(1);
            r
        })
        .collect::<Result<Vec<()>>>()?;
    Ok((plans.into_iter().map(|p| p.name).collect(), outs[0]))
}

/// Each photo's size from its header, and what becomes of it.
fn plan(photos: &[PathBuf], max_side: u32) -> Result<Vec<Plan>> {
    let mut names: BTreeMap<String, &Path> = BTreeMap::new();
    let mut plans = Vec::with_capacity(photos.len());
    for from in photos {
        let (w, h) = image_size(from)?;
        let (nw, nh) = capped_size(w, h, max_side);
        let resize = ((nw, nh) != (w, h)).then_some((nw, nh));
        let file = from
            .file_name()
            .and_then(|n| n.to_str())
            .with_context(|| format!("{}: not a UTF-8 file name", from.display()))?;
        let name = match resize {
            None => file.to_string(),
            Some(_) => format!(
                "{}.png",
                Path::new(file)
                    .file_stem()
                    .and_then(|s| s.to_str())
                    .unwrap_or(file)
            ),
        };
        if let Some(other) = names.insert(name.clone(), from) {
            bail!(
                "{} and {} would both become images/{name}: rename one",
                other.display(),
                from.display()
            );
        }
        plans.push(Plan {
            from: from.clone(),
            name,
            size: (w, h),
            resize,
        });
    }
    Ok(plans)
}

fn write(p: &Plan, images: &Path) -> Result<()> {
    // Decoded either way: a photo the loaders cannot read is refused now, by name.
    let img = decode_image_file(&p.from)?;
    let to = images.join(&p.name);
    let Some((nw, nh)) = p.resize else {
        return copy_synced(&p.from, &to);
    };
    let rgba = img
        .srgb8()
        .with_context(|| format!("{}: decoded without 8-bit pixels", p.from.display()))?;
    let (w, h) = (img.width as usize, img.height as usize);
    let ch = if img.has_alpha() { 4 } else { 3 };
    let px: Vec<u8> = if ch == 4 {
        rgba.to_vec()
    } else {
        rgba.chunks_exact(4)
            .flat_map(|q| [q[0], q[1], q[2]])
            .collect()
    };
    let small = resize_area(&px, ch, w, h, nw as usize, nh as usize);
    write_png(&to, nw, nh, ch, &small)
}
