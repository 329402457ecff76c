//! Purification: table entries the cover does not need, reset to the initialisation's range
//! (uniform in ±1e-4, instant-ngp's), so whatever else they held is gone.
//!
//! - [`purify_unreachable`]: the entries the reference index cannot reach from the stored
//!   occupancy grid's occupied cells ([`reachable_entries`], what an analyst computes from
//!   the file). No cover sample reads them, so no cover pixel changes: a free removal.
//! - [`purify_by_contribution`]: the entries whose contribution to the cover's renders is
//!   below ε. A render reads entries in occupied cells behind the first surface too, where
//!   the transmittance has fallen to nothing; weighting each read by the sample's weight
//!   in the ray (transmittance × opacity) and its interpolation weight finds the entries
//!   the cover's pixels actually depend on, so occluded interiors go too.

use crate::AttackContext;
use crate::views::stored_cameras;
use ngp::camera::Camera;
use ngp::encoding::grid::cell_of;
use ngp::encoding::reach::{EntrySet, reachable_entries};
use ngp::encoding::{LevelIndices, reference_indices};
use ngp::error::Result;
use ngp::model::Model;
use ngp::network::nerf::CHUNK;
use ngp::render::composite::TRAIN_MIN_TRANSMITTANCE;
use ngp::rng::Pcg32;
use rayon::prelude::*;

/// instant-ngp's initialisation of the table: uniform in ±1e-4.
pub const INIT_RANGE: f32 = 1e-4;

/// Resets every entry outside `keep` (one set per level) to a fresh draw in ±[`INIT_RANGE`];
/// the weights and the count reset.
pub fn reset_outside(model: &Model, keep: &[EntrySet], seed: u64) -> (Vec<f32>, u64) {
    let layout = &model.net.layout;
    let nf = layout.grid.config.n_features as usize;
    let mut out = model.params().to_vec();
    let mut r = Pcg32::new(seed, 0x7075_7269);
    let mut reset = 0u64;
    let table = &mut out[layout.grid_offset..];
    for (level, set) in layout.grid.levels.iter().zip(keep) {
        let base = level.offset as usize * nf;
        for e in 0..level.size {
            if set.contains(e) {
                continue;
            }
            for x in &mut table[base + e as usize * nf..][..nf] {
                *x = (r.next_f32() * 2.0 - 1.0) * INIT_RANGE;
            }
            reset += 1;
        }
    }
    (out, reset)
}

/// The entries the cover can read: the reference index over the stored grid's occupied
/// cells.
pub fn cover_reachable(model: &Model) -> Vec<EntrySet> {
    let layout = &model.net.layout.grid;
    reachable_entries(
        layout,
        &model.grid,
        model.config.aabb_scale,
        &reference_indices(layout),
    )
}

/// `purify`: every entry the cover cannot reach reset.
pub fn purify_unreachable(model: &Model, seed: u64) -> (Vec<f32>, u64) {
    reset_outside(model, &cover_reachable(model), seed)
}

/// `purify-contribution=ε`: every entry whose mean contribution to a ray of the cover's
/// renders ([`contributions`]) is below ε reset. ε = 0 resets none.
pub fn purify_by_contribution(
    model: &Model,
    epsilon: f32,
    ctx: &AttackContext,
) -> Result<(Vec<f32>, u64)> {
    let c = contributions(
        model,
        &stored_cameras(model, ctx.render_side, ctx.render_views)?,
    );
    let layout = &model.net.layout.grid;
    let keep: Vec<EntrySet> = layout
        .levels
        .iter()
        .map(|level| {
            let mut set = EntrySet::new(level.size);
            let base = level.offset as usize;
            for e in 0..level.size {
                if c[base + e as usize] >= epsilon {
                    set.insert(e);
                }
            }
            set
        })
        .collect();
    Ok(reset_outside(model, &keep, ctx.seed))
}

/// Each table entry's contribution to the cover's renders from `cameras`: over every pixel's
/// ray, the sum of `w · t` over the samples that read it, `w` the sample's weight in the
/// ray (transmittance × opacity, as the renderer composites) and `t` its trilinear weight
/// on the entry; divided by the number of rays. An entry no visible sample reads scores 0.
pub fn contributions(model: &Model, cameras: &[Camera]) -> Vec<f32> {
    let layout = &model.net.layout;
    let n = layout.grid.n_entries as usize;
    let idx = reference_indices(&layout.grid);
    let n_rays: u64 = cameras
        .iter()
        .map(|c| c.width as u64 * c.height as u64)
        .sum();
    let rows: Vec<(usize, u32)> = cameras
        .iter()
        .enumerate()
        .flat_map(|(ci, c)| (0..c.height).map(move |y| (ci, y)))
        .collect();
    // A fixed partition summed in order: the same sums whatever the thread count.
    let part = rows.len().div_ceil(PARTS).max(1);
    let parts: Vec<Vec<f64>> = rows
        .par_chunks(part)
        .map(|chunk| {
            let (mut acc, mut ws) = (vec![0f64; n], model.net.inference_workspace());
            let mut b = RowBuffers::default();
            for &(ci, y) in chunk {
                row_contributions(model, &idx, &cameras[ci], y, &mut ws, &mut b, &mut acc);
            }
            acc
        })
        .collect();
    let mut sum = vec![0f64; n];
    for p in &parts {
        sum.iter_mut().zip(p).for_each(|(x, y)| *x += y);
    }
    let k = 1.0 / n_rays.max(1) as f64;
    sum.iter().map(|&s| (s * k) as f32).collect()
}

/// Parts the rows are summed in (each holds a whole table of sums).
const PARTS: usize = 4;

#[derive(Default)]
struct RowBuffers {
    pos: Vec<[f32; 3]>,
    dts: Vec<f32>,
    ts: Vec<f32>,
    raw: Vec<f32>,
}

/// One row of one camera: each ray marched whole through the stored grid, its densities
/// composited, and every sample's weight spread onto the entries it reads.
fn row_contributions(
    model: &Model,
    idx: &LevelIndices,
    cam: &Camera,
    y: u32,
    ws: &mut ngp::network::nerf::Workspace,
    b: &mut RowBuffers,
    acc: &mut [f64],
) {
    let marcher = model.marcher();
    let layout = &model.net.layout.grid;
    for x in 0..cam.width {
        let ray = cam.ray(x as f32 + 0.5, y as f32 + 0.5);
        let Some((t0, _)) = marcher.intersect(ray.o, ray.d) else {
            continue;
        };
        b.pos.clear();
        b.dts.clear();
        b.ts.clear();
        let mut t = Some(marcher.advance(t0, 0.5));
        while let Some(tt) = t {
            t = marcher.march(
                &model.grid,
                ray.o,
                ray.d,
                tt,
                1024,
                &mut b.pos,
                &mut b.dts,
                &mut b.ts,
            );
        }
        if b.pos.is_empty() {
            continue;
        }
        b.raw.resize(b.pos.len(), 0.0);
        for (p, o) in b.pos.chunks(CHUNK).zip(b.raw.chunks_mut(CHUNK)) {
            model.net.density(model.params(), idx, p, ws, o);
        }
        let mut tr = 1.0f32;
        for (j, p) in b.pos.iter().enumerate() {
            if tr < TRAIN_MIN_TRANSMITTANCE {
                break;
            }
            let alpha = 1.0 - (-b.raw[j].exp() * b.dts[j]).exp();
            let w = (alpha * tr) as f64;
            tr *= 1.0 - alpha;
            if w <= 0.0 {
                continue;
            }
            for (level, li) in layout.levels.iter().zip(idx) {
                let (cell, frac) = cell_of(level, *p);
                for c in 0..8u32 {
                    let (dx, dy, dz) = (c & 1, c >> 1 & 1, c >> 2 & 1);
                    let tri = [dx, dy, dz]
                        .iter()
                        .zip(frac)
                        .map(|(&d, f)| if d == 1 { f } else { 1.0 - f })
                        .product::<f32>();
                    let e = li.index(cell[0] + dx, cell[1] + dy, cell[2] + dz);
                    acc[level.offset as usize + e as usize] += w * tri as f64;
                }
            }
        }
    }
}
