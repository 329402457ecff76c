//! `stegongp mesh MODEL --out FILE.ply|FILE.obj`: the surface of the cover, or with `--key`
//! of the hidden scene, by marching cubes on the network's density as instant-ngp makes it
//! (`--save_mesh`): resolution 256 on the box's longest side, threshold 2.5 on the raw
//! density output, vertex colours from the colour network, positions in the dataset's
//! frame.

use super::common::{DeviceArg, check_parent_dir, progress};
use anyhow::{Context, Result, bail};
use std::path::{Path, PathBuf};
use std::time::Instant;
use stegongp::backend::DeviceReport;
use stegongp::mesh::frame::{Axes, Frame};
use stegongp::mesh::lattice::{occupied_box, occupied_box_within};
use stegongp::mesh::{Lattice, Mesh, colour, march, obj, ply};
use stegongp::ngp::model::Model;
use stegongp::stego::options::choice;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Model file (.ingp or .msgpack).
    pub model: PathBuf,
    /// The mesh to write: FILE.ply (binary little-endian, normals and colours) or FILE.obj.
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub key: super::KeyArgs,
    /// Lattice points along the box's longest side, the other sides in proportion (each
    /// rounded up to a multiple of 16, as instant-ngp's --marching_cubes_res).
    #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u32).range(16..=1 << 16))]
    pub resolution: u32,
    /// The surface lies where the raw density output (the log-density) crosses this
    /// (instant-ngp's --marching_cubes_density_thresh).
    #[arg(long, default_value_t = 2.5, allow_negative_numbers = true)]
    pub threshold: f32,
    /// Crop to X0,Y0,Z0,X1,Y1,Z1, in the coordinates the mesh is written in (--axes), or
    /// to `cascade:K`, the occupied part of the occupancy grid's cascade K (0: the unit
    /// cube of ngp space, where a capture's object sits; its background fills the outer
    /// ones). Default: the occupied part of the model's box, as its occupancy grid says
    /// (with --key, the hidden scene's grid rebuilt from the network).
    #[arg(
        long,
        value_name = "X0,Y0,Z0,X1,Y1,Z1|cascade:K",
        allow_hyphen_values = true
    )]
    pub r#box: Option<String>,
    /// The frame of the written coordinates.
    #[arg(long, value_parser = choice::<Axes>(), default_value_t = Axes::InstantNgp)]
    pub axes: Axes,
    /// Refuse a mesh of more triangles than this (its memory is counted before the march).
    #[arg(long, default_value_t = 30_000_000)]
    pub max_triangles: usize,
    /// Print one JSON object (counts, box, lattice, times, device) on standard output.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub device: DeviceArg,
}

#[derive(serde::Serialize)]
struct Report {
    out: String,
    hidden_scene: bool,
    vertices: usize,
    triangles: usize,
    /// Lattice points per axis (ngp's x, y, z).
    lattice: [usize; 3],
    /// The box, in the written coordinates.
    box_min: [f32; 3],
    box_max: [f32; 3],
    threshold: f32,
    evaluated_points: u64,
    /// The largest raw density the lattice met; `None` (JSON null) when no point was
    /// evaluated.
    max_density: Option<f32>,
    density_seconds: f64,
    cubes_seconds: f64,
    colour_seconds: f64,
    write_seconds: f64,
    estimated_bytes: u64,
    device: DeviceReport,
}

/// The written format, from the output's extension.
fn format_of(out: &Path) -> Result<&'static str> {
    match out
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .as_deref()
    {
        Some("ply") => Ok("ply"),
        Some("obj") => Ok("obj"),
        _ => bail!("{}: a mesh file must end in .ply or .obj", out.display()),
    }
}

/// `--box`'s six numbers as two ngp-space corners.
fn parse_box(s: &str, frame: &Frame) -> Result<([f32; 3], [f32; 3])> {
    let v: Vec<f32> = s
        .split(',')
        .map(|t| t.trim().parse::<f32>())
        .collect::<std::result::Result<_, _>>()
        .with_context(|| format!("--box {s}: six numbers X0,Y0,Z0,X1,Y1,Z1"))?;
    if v.len() != 6 || v.iter().any(|x| !x.is_finite()) {
        bail!("--box {s}: six finite numbers X0,Y0,Z0,X1,Y1,Z1");
    }
    if (0..3).any(|d| v[d] >= v[d + 3]) {
        bail!("--box {s}: each of X0, Y0, Z0 must be below X1, Y1, Z1");
    }
    let (a, b) = (
        frame.to_ngp([v[0], v[1], v[2]]),
        frame.to_ngp([v[3], v[4], v[5]]),
    );
    Ok((
        [0, 1, 2].map(|d| a[d].min(b[d])),
        [0, 1, 2].map(|d| a[d].max(b[d])),
    ))
}

/// Memory the system can give now (`MemAvailable`), when it says.
fn available_bytes() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = s.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

fn gib(b: u64) -> f64 {
    b as f64 / (1u64 << 30) as f64
}

/// What the march will hold, refused before anything is allocated when the system has
/// less.
fn check_memory(lattice: &Lattice, max_triangles: usize, resolution: u32) -> Result<u64> {
    let work = lattice.working_bytes();
    let mesh = Mesh::bytes_for(max_triangles as u64);
    let need = work.saturating_add(mesh);
    if let Some(avail) = available_bytes()
        && need > avail
    {
        bail!(
            "--resolution {resolution} needs about {:.2} GiB ({}×{}×{} lattice: {:.2} GiB of \
             slabs and layers, plus {:.2} GiB for a mesh of up to --max-triangles {}), more \
             than the {:.2} GiB available; lower --resolution or --max-triangles",
            gib(need),
            lattice.res[0],
            lattice.res[1],
            lattice.res[2],
            gib(work),
            gib(mesh),
            max_triangles,
            gib(avail)
        );
    }
    Ok(need)
}

pub fn run(a: Args) -> Result<()> {
    let format = format_of(&a.out)?;
    check_parent_dir(&a.out)?;
    if !a.threshold.is_finite() {
        bail!("--threshold {}: not a number", a.threshold);
    }
    let model = Model::load(&a.model)?;
    let (scale, offset) = model
        .dataset
        .as_ref()
        .map_or((0.33, [0.5; 3]), |d| (d.scale, d.offset));
    let frame = Frame::new(scale, offset, a.axes)
        .with_context(|| format!("{}: its dataset", a.model.display()))?;
    let device = a.device.open()?;
    if !a.json {
        eprintln!("device: {}", device.report());
    }
    let scene = a.key.scene(&device, &model)?;
    let grid = scene.grid(&model);
    let bounds = match a.r#box.as_deref() {
        Some(s) => match s.strip_prefix("cascade:") {
            Some(k) => {
                let k: u32 = k
                    .parse()
                    .with_context(|| format!("--box {s}: cascade:K with K a cascade number"))?;
                if k > grid.max_cascade() {
                    bail!(
                        "--box {s}: the model has cascades 0 to {}",
                        grid.max_cascade()
                    );
                }
                occupied_box_within(grid, k)
            }
            None => Some(parse_box(s, &frame)?),
        },
        None => occupied_box(grid),
    };
    let mut report = Report {
        out: a.out.display().to_string(),
        hidden_scene: a.key.key.is_some(),
        vertices: 0,
        triangles: 0,
        lattice: [0; 3],
        box_min: [0.0; 3],
        box_max: [0.0; 3],
        threshold: a.threshold,
        evaluated_points: 0,
        max_density: None,
        density_seconds: 0.0,
        cubes_seconds: 0.0,
        colour_seconds: 0.0,
        write_seconds: 0.0,
        estimated_bytes: 0,
        device: device.report(),
    };
    let mut mesh = match bounds {
        None => {
            eprintln!(
                "the occupancy grid has no occupied cell: nothing to mesh, the mesh is empty"
            );
            Mesh::default()
        }
        Some((lo, hi)) => {
            let lattice = Lattice::new(lo, hi, a.resolution)?;
            (report.box_min, report.box_max) = (frame.position(lo), frame.position(hi));
            report.lattice = lattice.res;
            report.estimated_bytes = check_memory(&lattice, a.max_triangles, a.resolution)?;
            march_lattice(&a, &device, &model, &scene, &lattice, &mut report)?
        }
    };
    if mesh.is_empty() {
        mesh = Mesh::default();
        if bounds.is_some() {
            let h = 0.5 * (grid.max_cascade() as f32).exp2();
            let whole = (frame.position([0.5 - h; 3]), frame.position([0.5 + h; 3]));
            eprintln!("{}", no_surface(&a, &report, whole));
        }
    } else {
        let t = Instant::now();
        mesh.colours = colour::vertex_colours(&scene.view(&model), &mesh.positions);
        report.colour_seconds = t.elapsed().as_secs_f64();
    }
    frame.apply(&mut mesh);
    let t = Instant::now();
    match format {
        "ply" => ply::write_ply(&a.out, &mesh)?,
        _ => obj::write_obj(&a.out, &mesh)?,
    }
    report.write_seconds = t.elapsed().as_secs_f64();
    (report.vertices, report.triangles) = (mesh.positions.len(), mesh.triangles.len());
    print_report(&a, &report)
}

/// Samples and meshes the lattice on the device, with a progress bar over its layers.
fn march_lattice(
    a: &Args,
    device: &stegongp::backend::Device,
    model: &Model,
    scene: &stegongp::stego::OpenedScene,
    lattice: &Lattice,
    report: &mut Report,
) -> Result<Mesh> {
    let mut field = device.density_field(model, &scene.indices)?;
    let pb = progress(
        lattice.res[2] as u64,
        "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} layers {msg}",
    );
    if a.json {
        pb.set_draw_target(indicatif::ProgressDrawTarget::hidden());
    }
    let started = Instant::now();
    let (mut density_seconds, mut max_density) = (0.0, f32::NEG_INFINITY);
    let out = march(
        lattice,
        Some(scene.grid(model)),
        a.threshold,
        a.max_triangles,
        |pos| {
            let t = Instant::now();
            let d = field(pos)?;
            density_seconds += t.elapsed().as_secs_f64();
            max_density = d.iter().cloned().fold(max_density, f32::max);
            Ok(d)
        },
        |layers| pb.set_position(layers as u64),
    )
    .with_context(|| format!("{}: meshing", a.model.display()))?;
    pb.finish_and_clear();
    report.evaluated_points = out.evaluated;
    report.density_seconds = density_seconds;
    report.cubes_seconds = started.elapsed().as_secs_f64() - density_seconds;
    report.max_density = (out.evaluated > 0).then_some(max_density);
    Ok(out.mesh)
}

/// Why a box gave no surface: none of its lattice points fell in an occupied cell (nothing
/// was evaluated: the box is elsewhere than the model's matter), or the density was
/// evaluated and never reached the threshold (a lower one may find a surface). `whole`:
/// the model's box, corners in the written coordinates.
fn no_surface(a: &Args, r: &Report, whole: ([f32; 3], [f32; 3])) -> String {
    let b = |v: [f32; 3]| format!("{:.4},{:.4},{:.4}", v[0], v[1], v[2]);
    match r.max_density {
        None => format!(
            "no surface: no lattice point of the box fell in a cell the occupancy grid calls \
             occupied, so no density was evaluated; the mesh is empty. Leave --box out to mesh \
             the occupied part of the model's box, or give a --box over it (the whole box: \
             --box {},{})",
            b([0, 1, 2].map(|d| whole.0[d].min(whole.1[d]))),
            b([0, 1, 2].map(|d| whole.0[d].max(whole.1[d]))),
        ),
        Some(max) => format!(
            "no surface: the raw density never crosses --threshold {} in the box ({} lattice \
             points evaluated, the largest density met {max}); the mesh is empty. A \
             --threshold below {max} may find one",
            a.threshold, r.evaluated_points
        ),
    }
}

fn print_report(a: &Args, r: &Report) -> Result<()> {
    if a.json {
        println!("{}", serde_json::to_string(r)?);
        return Ok(());
    }
    let b = |v: [f32; 3]| format!("({:.4}, {:.4}, {:.4})", v[0], v[1], v[2]);
    eprintln!(
        "lattice {}×{}×{} over {} – {}: {} points evaluated in {:.1} s, cubes {:.1} s, \
         colours {:.1} s",
        r.lattice[0],
        r.lattice[1],
        r.lattice[2],
        b(r.box_min),
        b(r.box_max),
        r.evaluated_points,
        r.density_seconds,
        r.cubes_seconds,
        r.colour_seconds
    );
    println!(
        "wrote {}: {} vertices, {} triangles",
        r.out, r.vertices, r.triangles
    );
    Ok(())
}
