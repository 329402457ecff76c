//! What a key holder's rebuilt occupancy grid costs in quality: a model rendered with the
//! grid stored in its file (trained over many steps) against grids rebuilt from the
//! network alone with 1 and 4 density samples per cell (`SPC=4,8`: others), each followed by
//! `REFINE=28` more points in the cells near occupied ones, as `eval --key` rebuilds.
//!
//! SPC=4 REFINE=28 cargo run --release --example occupancy_rebuild -- MODEL DATA_DIR [DOWNSCALE] [KEYFILE] [VIEWS]

use stegongp::dataset::LoadOptions;
use stegongp::ngp::data::Split;
use stegongp::ngp::encoding::reference_indices;
use stegongp::ngp::model::Model;
use stegongp::ngp::render::image::RenderOptions;
use stegongp::score::eval::{evaluate, spread_views};
use stegongp::stego::load_key;
use stegongp::stego::occupancy::rebuild_occupancy;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        eprintln!("usage: occupancy_rebuild MODEL DATA_DIR [DOWNSCALE] [KEYFILE] [VIEWS]");
        std::process::exit(2);
    }
    let model = Model::load(args[1].as_ref()).unwrap_or_else(|e| panic!("{e}"));
    let downscale = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(1);
    let data = stegongp::dataset::load(
        args[2].as_ref(),
        Split::Test,
        &LoadOptions {
            downscale,
            ..Default::default()
        },
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let key = args
        .get(4)
        .filter(|s| !s.is_empty() && *s != "-")
        .map(|k| load_key(k.as_ref()).unwrap_or_else(|e| panic!("{e}")));
    let views: usize = args.get(5).and_then(|s| s.parse().ok()).unwrap_or(25);
    let indices = match &key {
        Some(k) => k.level_indices(&model.net.layout.grid),
        None => reference_indices(&model.net.layout.grid),
    };
    let which = spread_views(data.frames.len(), views);
    let opts = RenderOptions::default();
    let score = |grid: &stegongp::ngp::occupancy::OccupancyGrid| {
        let view = model.view(&indices, grid);
        let r = evaluate(&view, &data, &opts, Some(&which), |_, _, _| {});
        (r.psnr, r.ssim)
    };
    if key.is_none() {
        let (p, s) = score(&model.grid);
        println!("stored grid: PSNR {p:.2} dB SSIM {s:.4}");
    }
    let spcs: Vec<usize> = std::env::var("SPC")
        .ok()
        .map(|s| s.split(',').filter_map(|x| x.parse().ok()).collect())
        .unwrap_or(vec![1, 4]);
    // REFINE=28,60: that many more points in the cells near occupied ones, after each.
    let refines: Vec<usize> = std::env::var("REFINE")
        .ok()
        .map(|s| s.split(',').filter_map(|x| x.parse().ok()).collect())
        .unwrap_or_default();
    let marcher = model.marcher();
    for spc in spcs {
        let t0 = std::time::Instant::now();
        let g = rebuild_occupancy(
            &model.net,
            model.params(),
            &indices,
            model.config.aabb_scale,
            spc,
            0,
        );
        let secs = t0.elapsed().as_secs_f64();
        let (p, s) = score(&g);
        println!("rebuilt, {spc} sample(s)/cell ({secs:.1} s): PSNR {p:.2} dB SSIM {s:.4}");
        for &more in &refines {
            let t0 = std::time::Instant::now();
            let mut r = g.clone();
            let rep = r.refine_near_occupied(more, spc, 0, |pos| {
                let w: Vec<[f32; 3]> = pos.iter().map(|&p| marcher.warp(p)).collect();
                model.net.density_batch(model.params(), &indices, &w)
            });
            let secs = secs + t0.elapsed().as_secs_f64();
            let (p, s) = score(&r);
            println!(
                "  + {more} more near occupied cells ({} cells in {} passes; {secs:.1} s in all): \
                 PSNR {p:.2} dB SSIM {s:.4}",
                rep.cells, rep.passes
            );
        }
    }
}
