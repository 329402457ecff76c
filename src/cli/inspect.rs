//! `stegongp inspect MODEL [--json]`: what a model file is and how it is configured, as any
//! instant-ngp user could read it from the file. Nothing about hidden scenes.

use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Model file (.ingp or .msgpack)
    pub model: PathBuf,
    /// Print the summary as JSON
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let info = stegongp::ngp::snapshot::inspect(&args.model)?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&info)?);
        return Ok(());
    }
    let mb = |b: u64| b as f64 / (1024.0 * 1024.0);
    println!("file          {}", info.path);
    println!(
        "format        {}, snapshot version {}, mode {}",
        info.format, info.version, info.mode
    );
    println!(
        "size          {:.2} MiB on disk, {:.2} MiB msgpack",
        mb(info.file_bytes),
        mb(info.msgpack_bytes)
    );
    println!(
        "hash grid     L={} levels × F={} features, T=2^{}, N_min={}, b={:.7}",
        info.n_levels,
        info.n_features_per_level,
        info.log2_hashmap_size,
        info.base_resolution,
        info.per_level_scale
    );
    let dense: Vec<String> = info.dense_levels.iter().map(|l| l.to_string()).collect();
    println!(
        "dense levels  {}",
        if dense.is_empty() {
            "none".to_string()
        } else {
            dense.join(", ")
        }
    );
    let res: Vec<String> = info
        .levels
        .iter()
        .map(|l| l.resolution.to_string())
        .collect();
    println!("resolutions   {}", res.join(" "));
    println!(
        "parameters    {} ({} MLP + {} grid, grid at offset {}), {} = {} bytes",
        info.n_params,
        info.n_mlp_params,
        info.n_grid_params,
        info.grid_offset,
        info.params_type,
        info.params_bytes
    );
    println!(
        "density grid  {} cascade(s) of 128³, {} cells, {} bytes fp16",
        info.density_grid_cascades, info.density_grid_cells, info.density_grid_bytes
    );
    let occupied: Vec<String> = info
        .occupied_per_cascade
        .iter()
        .map(|f| format!("{:.1} %", 100.0 * f))
        .collect();
    println!("occupied      {} (per cascade)", occupied.join(", "));
    println!(
        "aabb          scale {}, [{:?} .. {:?}]",
        info.aabb_scale, info.aabb_min, info.aabb_max
    );
    println!(
        "training      step {}, loss {}, {} images, optimizer state {}",
        info.training_step,
        info.loss,
        info.n_images,
        match (info.has_optimizer_state, info.has_run_state) {
            (_, true) => "yes (a training checkpoint: train --resume goes on from it)",
            (true, false) => "yes",
            (false, false) => "no",
        }
    );
    Ok(())
}
