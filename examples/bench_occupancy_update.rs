//! What one occupancy-grid update of the warm-up costs on the CPU, and where: drawing the
//! cells, the network's densities at the drawn points in the order drawn and grouped by
//! blocks of 8³ cells (so neighbouring points share table entries), and how much of a capture's
//! box its cameras see (the cells an update evaluates).
//!
//! cargo run --release --example bench_occupancy_update -- MODEL [DATA_DIR [DOWNSCALE]]

use std::time::Instant;
use stegongp::dataset::LoadOptions;
use stegongp::ngp::data::Split;
use stegongp::ngp::encoding::reference_indices;
use stegongp::ngp::model::Model;
use stegongp::ngp::occupancy::{N_CELLS, in_block_order};
use stegongp::ngp::render::march::Marcher;
use stegongp::ngp::train::schedule::starting_grid;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 2 {
        eprintln!("usage: bench_occupancy_update MODEL [DATA_DIR [DOWNSCALE]]");
        std::process::exit(2);
    }
    let model = Model::load(args[1].as_ref()).unwrap_or_else(|e| panic!("{e}"));
    let aabb = model.net.layout.config.aabb_scale;
    let indices = reference_indices(&model.net.layout.grid);
    let marcher = Marcher::new(aabb);
    let mut grid = model.grid.clone();
    if let Some(dir) = args.get(2) {
        let downscale = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(1);
        let data = stegongp::dataset::load(
            dir.as_ref(),
            Split::Train,
            &LoadOptions {
                downscale,
                ..Default::default()
            },
        )
        .unwrap_or_else(|e| panic!("{e}"));
        let t = Instant::now();
        let start = starting_grid(aabb, &data);
        println!("starting grid: {:.2} s", t.elapsed().as_secs_f64());
        for c in 0..start.n_cascades {
            let live = start.density[c * N_CELLS..(c + 1) * N_CELLS]
                .iter()
                .filter(|&&d| d >= 0.0)
                .count();
            println!(
                "cascade {c}: {:.1} % of the cells seen by a training camera",
                100.0 * live as f64 / N_CELLS as f64
            );
            // Keep the model's values where the cameras see, cull the rest.
            for i in c * N_CELLS..(c + 1) * N_CELLS {
                if start.density[i] < 0.0 {
                    grid.density[i] = -1.0;
                }
            }
        }
    }
    let (nu, nn) = grid.update_sample_counts(0, 1.0);
    let t = Instant::now();
    let (pos, cells) = grid.sample_positions(nu, nn, 1);
    let t_draw = t.elapsed().as_secs_f64();
    let live: Vec<usize> = (0..cells.len())
        .filter(|&i| grid.density[cells[i] as usize] >= 0.0)
        .collect();
    let eval = |pos: &[[f32; 3]]| {
        let warped: Vec<[f32; 3]> = pos.iter().map(|&p| marcher.warp(p)).collect();
        let t = Instant::now();
        let d = model.net.density_batch(model.params(), &indices, &warped);
        (d, t.elapsed().as_secs_f64())
    };
    let drawn: Vec<[f32; 3]> = live.iter().map(|&i| pos[i]).collect();
    let (d_drawn, t_drawn) = eval(&drawn);
    let live_cells: Vec<u32> = live.iter().map(|&i| cells[i]).collect();
    let t = Instant::now();
    let (sorted, sorted_cells) = in_block_order(&drawn, &live_cells);
    let t_sort = t.elapsed().as_secs_f64();
    let (d_sorted, t_sorted) = eval(&sorted);
    // The same maximum per cell, whatever the order.
    let max_per_cell = |cells: &[u32], d: &[f32]| {
        let mut m = std::collections::HashMap::new();
        for (&c, &v) in cells.iter().zip(d) {
            let e = m.entry(c).or_insert(f32::MIN);
            *e = e.max(v);
        }
        m
    };
    let same = max_per_cell(&live_cells, &d_drawn) == max_per_cell(&sorted_cells, &d_sorted);
    println!(
        "one warm-up update, {} cascades: {} draws ({:.2} s), {} in cells a camera sees",
        grid.n_cascades,
        pos.len(),
        t_draw,
        live.len()
    );
    println!(
        "densities in the order drawn: {:.2} s ({:.2} M/s)",
        t_drawn,
        live.len() as f64 / t_drawn / 1e6
    );
    println!(
        "in blocks of 8³ cells: counting sort {:.2} s + densities {:.2} s ({:.2} M/s); same values: {same}",
        t_sort,
        t_sorted,
        live.len() as f64 / t_sorted / 1e6
    );
}
