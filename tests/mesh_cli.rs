//! `stegongp mesh` on a small stego model of generated scenes whose surfaces are known: the
//! cover (the object scene) without a key, the hidden scene (a ball, a box and a torus)
//! with it, measured against the scenes' exact surfaces in lattice cells; closed and
//! outward meshes, each shape one surface of its genus; a wrong key's mesh; the files read
//! back by real mesh tools; an empty mesh's report; and bad input refused before anything
//! is written.

use ply_rs_bw::parser::Parser;
use ply_rs_bw::ply::{DefaultElement, Property};
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;
use stegongp::mesh::Mesh;
use stegongp::mesh::topology::{components, edges, euler_characteristic, signed_volume};
use stegongp::ngp::network::ModelConfig;
use stegongp::stego::{SchemeKind, save_key};
use stegongp::synth::SceneKind;
use stegongp::synth::scene::{Shape, object_scene, shapes_scene};
use stegongp::training::recipe::StepOptions;
use testkit::cli::{fails_naming, stdout_ok, stegongp};
use testkit::keys::seeded_key;
use testkit::scenes::generated;

/// The bottom of the object scene's platform (`object_scene`'s first cylinder).
const PLATFORM_BOTTOM: f32 = -0.75;
const PLATFORM_TOP: f32 = -0.62;

/// Lattice points along the longest side in these tests.
const RES: &str = "64";

struct Fixture {
    dir: tempfile::TempDir,
    model: PathBuf,
    key: PathBuf,
    wrong_key: PathBuf,
}

/// One stego model for every test here: the object scene as the cover, the shapes under a
/// key, 40 px views, trained on the CPU.
fn fixture() -> &'static Fixture {
    static F: OnceLock<Fixture> = OnceLock::new();
    F.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let t = std::time::Instant::now();
        let (cover, _) =
            generated(&dir.path().join("cover"), SceneKind::Object, 40, 40, 1, 3).shared();
        let (hidden, _) =
            generated(&dir.path().join("hidden"), SceneKind::Shapes, 40, 40, 1, 4).shared();
        let key = seeded_key(SchemeKind::Prf, 4, 55, 1);
        let mut config = ModelConfig::default();
        config.grid.log2_hashmap_size = 16;
        let steps = StepOptions {
            seed: 7,
            batch: 1 << 15,
            occupancy_fraction: 1.0 / 32.0,
            ..Default::default()
        };
        let model =
            testkit::models::trained(config, cover, vec![(hidden, key.clone())], steps, 200);
        let f = Fixture {
            model: dir.path().join("model.ingp"),
            key: dir.path().join("secret.key"),
            wrong_key: dir.path().join("wrong.key"),
            dir,
        };
        model.save(&f.model).unwrap();
        save_key(&f.key, &key, false).unwrap();
        save_key(&f.wrong_key, &seeded_key(SchemeKind::Prf, 4, 56, 1), false).unwrap();
        eprintln!("fixture: {:.1} s", t.elapsed().as_secs_f64());
        f
    })
}

fn path_str(p: &Path) -> &str {
    p.to_str().expect("a UTF-8 path")
}

/// `stegongp mesh MODEL --out OUT --resolution RES --json EXTRA…`: its report.
fn mesh(out: &Path, extra: &[&str]) -> Value {
    let f = fixture();
    let mut args = vec![
        "mesh",
        path_str(&f.model),
        "--out",
        path_str(out),
        "--resolution",
        RES,
        "--json",
    ];
    args.extend_from_slice(extra);
    let o = stegongp(&args);
    serde_json::from_str(&stdout_ok(&o)).expect("one JSON report")
}

fn read_ply(path: &Path) -> Mesh {
    let ply = Parser::<DefaultElement>::new()
        .read_ply(&mut std::io::BufReader::new(
            std::fs::File::open(path).unwrap(),
        ))
        .unwrap();
    let f = |e: &DefaultElement, k: &str| match e[k] {
        Property::Float(v) => v,
        ref p => panic!("{k}: {p:?}"),
    };
    let u = |e: &DefaultElement, k: &str| match e[k] {
        Property::UChar(v) => v,
        ref p => panic!("{k}: {p:?}"),
    };
    let mut m = Mesh::default();
    for v in &ply.payload["vertex"] {
        m.positions.push([f(v, "x"), f(v, "y"), f(v, "z")]);
        m.normals.push([f(v, "nx"), f(v, "ny"), f(v, "nz")]);
        m.colours.push([u(v, "red"), u(v, "green"), u(v, "blue")]);
    }
    for t in &ply.payload["face"] {
        match &t["vertex_indices"] {
            Property::ListInt(l) if l.len() == 3 => {
                m.triangles.push([l[0] as u32, l[1] as u32, l[2] as u32])
            }
            p => panic!("a face: {p:?}"),
        }
    }
    m
}

/// The lattice's cell, in the report's (the written) units.
fn cell(report: &Value) -> f32 {
    (0..3)
        .map(|d| {
            let span =
                report["box_max"][d].as_f64().unwrap() - report["box_min"][d].as_f64().unwrap();
            (span / (report["lattice"][d].as_f64().unwrap() - 1.0)) as f32
        })
        .fold(0.0, f32::max)
}

/// How a mesh lies on `scene`'s surfaces, in cells.
#[derive(Debug)]
struct Fit {
    /// Distances of the vertices that are not more than a cell inside an object: the
    /// median, 90th and 99th percentiles, and the mean.
    median: f32,
    p90: f32,
    p99: f32,
    mean: f32,
    /// The share of vertices more than a cell inside an object: the walls of cavities a
    /// network leaves inside an opaque object it never sees into (no view shows them).
    inside: f32,
    /// Of the vertices within a cell outside the surface, the share whose normal points
    /// out of the object (along the gradient of the signed distance). Those just inside
    /// may belong to a cavity's wall, whose normal rightly points into the cavity.
    outward: f32,
}

/// [`Fit`] of the vertices `seen` keeps, against the signed distance `sd` (negative
/// inside).
fn fit(
    mesh: &Mesh,
    sd: impl Fn([f32; 3]) -> f32,
    cell: f32,
    seen: impl Fn([f32; 3]) -> bool,
) -> Fit {
    let mut d = Vec::new();
    let (mut inside, mut near, mut out, mut all) = (0usize, 0usize, 0usize, 0usize);
    for (p, n) in mesh.positions.iter().zip(&mesh.normals) {
        if !seen(*p) {
            continue;
        }
        all += 1;
        let s = sd(*p) / cell;
        if s < -1.0 {
            inside += 1;
            continue;
        }
        d.push(s.abs());
        if (0.0..1.0).contains(&s) {
            near += 1;
            let h = 1e-3;
            let g: Vec<f32> = (0..3)
                .map(|k| {
                    let (mut a, mut b) = (*p, *p);
                    a[k] += h;
                    b[k] -= h;
                    sd(a) - sd(b)
                })
                .collect();
            out += (g[0] * n[0] + g[1] * n[1] + g[2] * n[2] > 0.0) as usize;
        }
    }
    d.sort_by(f32::total_cmp);
    let q = |f: f32| d[((d.len() - 1) as f32 * f) as usize];
    Fit {
        median: q(0.5),
        p90: q(0.9),
        p99: q(0.99),
        mean: d.iter().sum::<f32>() / d.len() as f32,
        inside: inside as f32 / all.max(1) as f32,
        outward: out as f32 / near.max(1) as f32,
    }
}

/// Points spread over a shape's surface, each with the area it stands for: the ball on a
/// Fibonacci spiral, each face of the box on a grid, the torus on a grid of its two angles
/// (the area of a sample shrinks towards the hole, where the tube's circle is shorter).
fn surface_samples(shape: &Shape) -> Vec<([f32; 3], f32)> {
    let mut out = Vec::new();
    match *shape {
        Shape::Sphere { c, r } => {
            let n = 400;
            for i in 0..n {
                let z = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
                let a = i as f32 * 2.399_963;
                let s = (1.0 - z * z).sqrt();
                let p = [c[0] + r * s * a.cos(), c[1] + r * s * a.sin(), c[2] + r * z];
                out.push((p, 4.0 * std::f32::consts::PI * r * r / n as f32));
            }
        }
        Shape::Box { lo, hi } => {
            for axis in 0..3 {
                let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
                let area = (hi[u] - lo[u]) * (hi[v] - lo[v]) / 64.0;
                for side in [lo[axis], hi[axis]] {
                    for i in 0..8 {
                        for j in 0..8 {
                            let mut p = [0.0; 3];
                            p[axis] = side;
                            p[u] = lo[u] + (hi[u] - lo[u]) * (i as f32 + 0.5) / 8.0;
                            p[v] = lo[v] + (hi[v] - lo[v]) * (j as f32 + 0.5) / 8.0;
                            out.push((p, area));
                        }
                    }
                }
            }
        }
        Shape::Torus { c, major, minor } => {
            let (n, m) = (48, 16);
            let step = std::f32::consts::TAU;
            for i in 0..n {
                let a = (i as f32 + 0.5) / n as f32 * step;
                for j in 0..m {
                    let b = (j as f32 + 0.5) / m as f32 * step;
                    let rho = major + minor * b.cos();
                    let p = [
                        c[0] + rho * a.cos(),
                        c[1] + rho * a.sin(),
                        c[2] + minor * b.sin(),
                    ];
                    out.push((p, step * step / (n * m) as f32 * minor * rho));
                }
            }
        }
        other => panic!("no samples of {other:?}"),
    }
    out
}

/// The mean distance, in cells, from points spread over `shapes`' surfaces (weighted by
/// the area each stands for) to the nearest vertex: what of the surface the mesh misses.
fn completeness(mesh: &Mesh, shapes: &[Shape], cell: f32) -> f32 {
    let (mut sum, mut area) = (0.0, 0.0);
    for (s, w) in shapes.iter().flat_map(surface_samples) {
        let d = mesh
            .positions
            .iter()
            .map(|p| (0..3).map(|d| (p[d] - s[d]).powi(2)).sum::<f32>())
            .fold(f32::INFINITY, f32::min)
            .sqrt();
        sum += w * d;
        area += w;
    }
    sum / area / cell
}

fn scene_shapes() -> Vec<Shape> {
    shapes_scene().objects.iter().map(|o| o.shape).collect()
}

/// The hidden scene's mesh with the key (`--axes dataset`), made once: every `--key` run
/// rebuilds the scene's occupancy grid from the network, seconds on CI's two cores.
fn hidden_mesh() -> &'static (PathBuf, Value) {
    static H: OnceLock<(PathBuf, Value)> = OnceLock::new();
    H.get_or_init(|| {
        let f = fixture();
        let out = f.dir.path().join("hidden.ply");
        let r = mesh(&out, &["--key", path_str(&f.key), "--axes", "dataset"]);
        (out, r)
    })
}

#[test]
fn the_hidden_scene_with_its_key_is_its_shapes_closed_and_outward() {
    let (out, r) = hidden_mesh();
    let m = read_ply(out);
    assert_eq!(m.positions.len() as u64, r["vertices"].as_u64().unwrap());
    assert_eq!(m.triangles.len() as u64, r["triangles"].as_u64().unwrap());
    let cell = cell(r);
    let scene = shapes_scene();
    let f = fit(&m, |p| scene.signed_distance(p), cell, |_| true);
    let miss = completeness(&m, &scene_shapes(), cell);
    let chamfer = 0.5 * (f.mean + miss);
    let e = edges(&m);
    eprintln!(
        "hidden: {} vertices, {} triangles, cell {cell:.4}; {f:?}; surface to mesh {miss:.2} \
         cells; Chamfer {chamfer:.2} cells; {e:?}",
        m.positions.len(),
        m.triangles.len(),
    );
    assert!(e.closed_and_oriented(), "{e:?}");
    assert!(signed_volume(&m) > 0.0);
    assert!(f.median < 0.5 && f.p90 < 1.5 && f.p99 < 3.0, "{f:?}");
    // Cavities a young model leaves inside the ball and the box (39 % measured): bounded.
    assert!(f.inside < 0.6, "{f:?}");
    assert!(miss < 1.0, "surface to mesh {miss}");
    assert!(chamfer < 0.75, "Chamfer {chamfer}");
    assert!(f.outward > 0.95, "{f:?}");
}

/// The torus's part of the hidden mesh: the vertices nearest the torus of the three shapes
/// fit its exact surface and cover it, and none lies in its hole (a model that had filled
/// the hole would mesh a disc there). Its genus is not asserted: CI's 200-step model joins
/// the torus to the box two cells away and leaves tunnels into the solids' cavities, so the
/// components' Euler characteristics (printed) are not yet 2, 2 and 0 (benchmarks/mesh.md).
#[test]
fn the_torus_is_meshed_as_a_ring_with_its_hole_open() {
    let (out, r) = hidden_mesh();
    let m = read_ply(out);
    let cell = cell(r);
    let parts = components(&m);
    eprintln!(
        "hidden: {} components, (triangles, χ) of the largest {:?}",
        parts.len(),
        parts
            .iter()
            .take(6)
            .map(|p| (p.triangles.len(), euler_characteristic(p)))
            .collect::<Vec<_>>()
    );
    let shapes = scene_shapes();
    let k = shapes
        .iter()
        .position(|s| matches!(s, Shape::Torus { .. }))
        .expect("the shapes scene has a torus");
    let Shape::Torus { c, major, minor } = shapes[k] else {
        unreachable!()
    };
    let nearest = |p: [f32; 3]| {
        (0..shapes.len())
            .min_by(|&a, &b| {
                let (da, db) = (shapes[a].signed_distance(p), shapes[b].signed_distance(p));
                da.abs().total_cmp(&db.abs())
            })
            .unwrap()
    };
    let torus = |p: [f32; 3]| shapes[k].signed_distance(p);
    let f = fit(&m, torus, cell, |p| nearest(p) == k);
    let miss = completeness(&m, std::slice::from_ref(&shapes[k]), cell);
    let chamfer = 0.5 * (f.mean + miss);
    // The hole: within a cell less than the inner radius of the axis, as high as the tube.
    let hole = m
        .positions
        .iter()
        .filter(|p| {
            let rho = ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2)).sqrt();
            rho < major - minor - cell && (p[2] - c[2]).abs() < minor
        })
        .count();
    eprintln!(
        "torus: {f:?}; surface to mesh {miss:.2} cells; Chamfer {chamfer:.2} cells; \
         {hole} vertices in the hole"
    );
    assert!(f.median < 0.5 && f.p90 < 1.5, "{f:?}");
    assert!(f.outward > 0.95, "{f:?}");
    assert!(miss < 1.0 && chamfer < 0.75, "{miss} {chamfer}");
    assert_eq!(hole, 0, "the torus's hole is meshed over");
}

#[test]
fn the_cover_without_a_key_is_the_object_scene() {
    let f = fixture();
    let out = f.dir.path().join("cover.ply");
    let r = mesh(&out, &["--axes", "dataset"]);
    let m = read_ply(&out);
    let cell = cell(&r);
    // No view looks from below the platform (its cameras are above the horizon), so what
    // the network puts under it is never seen: the platform's underside and below count
    // out.
    let above = |p: [f32; 3]| p[2] > PLATFORM_BOTTOM;
    let scene = object_scene();
    let f = fit(&m, |p| scene.signed_distance(p), cell, above);
    let e = edges(&m);
    eprintln!(
        "cover: {} vertices, {} triangles, cell {cell:.4}; {f:?}; {e:?}",
        m.positions.len(),
        m.triangles.len()
    );
    assert!(e.closed_and_oriented(), "{e:?}");
    assert!(f.median < 0.5 && f.p90 < 2.0, "{f:?}");
    // The platform is under three cells thick, so a vertex within a cell of its top or
    // bottom may be either's; the objects standing on it are not.
    let on_top = fit(
        &m,
        |p| scene.signed_distance(p),
        cell,
        |p| p[2] > PLATFORM_TOP + 2.0 * cell,
    );
    eprintln!("cover, above the platform: {on_top:?}");
    // The cover's surface is rough at this size and training (its density hovers around
    // the threshold in a thin fuzz, each bump with its own normal): mostly outward, where
    // the hidden shapes' smooth faces are almost all so. The orientation itself is exact
    // (closed, consistently oriented, positive volume).
    assert!(on_top.outward > 0.65, "{on_top:?}");
    assert!(signed_volume(&m) > 0.0);
    // Far from the shapes: the key makes the difference.
    let shapes = shapes_scene();
    let far = fit(&m, |p| shapes.signed_distance(p), cell, above);
    assert!(
        far.median > 4.0 * f.median,
        "the cover's mesh lies near the hidden shapes: {far:?}"
    );
}

#[test]
fn a_wrong_key_meshes_little() {
    let f = fixture();
    let out = f.dir.path().join("wrong.ply");
    let r = mesh(&out, &["--key", path_str(&f.wrong_key)]);
    let (w, h) = (
        r["triangles"].as_u64().unwrap(),
        hidden_mesh().1["triangles"].as_u64().unwrap(),
    );
    eprintln!("wrong key: {w} triangles (the key: {h}); {r}");
    assert!(w * 10 < h, "a wrong key meshed {w} triangles, the key {h}");
}

#[test]
fn instant_ngp_axes_are_the_dataset_axes_cycled_and_obj_matches_ply() {
    let f = fixture();
    let (a, b, o) = (
        f.dir.path().join("ngp_axes.ply"),
        f.dir.path().join("data_axes.ply"),
        f.dir.path().join("ngp_axes.obj"),
    );
    mesh(&a, &[]);
    mesh(&b, &["--axes", "dataset"]);
    mesh(&o, &[]);
    let (ma, mb) = (read_ply(&a), read_ply(&b));
    assert_eq!(ma.triangles, mb.triangles);
    for (p, q) in ma.positions.iter().zip(&mb.positions) {
        // instant-ngp's x, y, z are the data's y, z, x.
        assert!(
            (p[0] - q[1]).abs() < 1e-5 && (p[1] - q[2]).abs() < 1e-5 && (p[2] - q[0]).abs() < 1e-5
        );
    }
    let text = std::fs::read_to_string(&o).unwrap();
    let vs: Vec<&str> = text.lines().filter(|l| l.starts_with("v ")).collect();
    assert_eq!(vs.len(), ma.positions.len());
    assert_eq!(
        text.lines().filter(|l| l.starts_with("vn ")).count(),
        ma.positions.len()
    );
    assert_eq!(
        text.lines().filter(|l| l.starts_with("f ")).count(),
        ma.triangles.len()
    );
    let v0: Vec<f32> = vs[0]
        .split_whitespace()
        .skip(1)
        .map(|t| t.parse().unwrap())
        .collect();
    assert_eq!(&v0[..3], &ma.positions[0][..]);
    for k in 0..3 {
        assert!((v0[3 + k] - ma.colours[0][k] as f32 / 255.0).abs() < 1e-3);
    }
}

/// The counts a tool prints for a mesh file, by a command and a parser of its output.
fn counts_by(cmd: &mut Command, parse: impl Fn(&str) -> Option<(u64, u64)>) -> Option<(u64, u64)> {
    let o = cmd.output().ok()?;
    let text =
        String::from_utf8_lossy(&o.stdout).into_owned() + &String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{cmd:?}: {text}");
    Some(parse(&text).unwrap_or_else(|| panic!("{cmd:?} printed no counts: {text}")))
}

fn number_after(text: &str, label: &str) -> Option<u64> {
    let line = text.lines().find(|l| l.trim_start().starts_with(label))?;
    line.split(':')
        .nth(1)?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

#[test]
fn assimp_and_trimesh_read_the_files_with_the_same_counts() {
    let f = fixture();
    let (ply, r) = hidden_mesh();
    let obj = f.dir.path().join("tools.obj");
    let ro = mesh(&obj, &[]);
    let counts = |r: &Value| {
        (
            r["vertices"].as_u64().unwrap(),
            r["triangles"].as_u64().unwrap(),
        )
    };
    let files = [(ply.clone(), counts(r)), (obj, counts(&ro))];
    // Debian's assimp-utils: `assimp info` prints the scene's vertices and faces.
    if Command::new("assimp").arg("version").output().is_err() {
        testkit::missing("assimp", "apt-get install assimp-utils");
    } else {
        for (file, want) in &files {
            // Its default import drops nothing (no degenerate triangle to split off, shared
            // vertices joined) and a raw import (no post-processing) keeps every vertex.
            for raw in [false, true] {
                let mut cmd = Command::new("assimp");
                cmd.arg("info").arg(file);
                if raw {
                    cmd.arg("-r");
                }
                let got = counts_by(&mut cmd, |t| {
                    Some((number_after(t, "Vertices:")?, number_after(t, "Faces:")?))
                });
                eprintln!("assimp {} (raw {raw}): {got:?}", file.display());
                // Raw, OBJ's importer gives each face its own three vertices.
                let is_obj = file.extension().is_some_and(|e| e == "obj");
                let want = if raw && is_obj {
                    (3 * want.1, want.1)
                } else {
                    *want
                };
                assert_eq!(got, Some(want), "{}", file.display());
            }
        }
    }
    // trimesh from PyPI, where it is installed: vertices, faces, and watertight.
    let script = "import sys, trimesh\n\
        for f in sys.argv[1:]:\n\
        \x20   m = trimesh.load(f, process=False)\n\
        \x20   print(len(m.vertices), len(m.faces), m.is_watertight, m.is_winding_consistent)";
    let o = Command::new("python3")
        .arg("-c")
        .arg(script)
        .arg(&files[0].0)
        .arg(&files[1].0)
        .output();
    match o {
        Ok(o) if o.status.success() => {
            let text = String::from_utf8_lossy(&o.stdout);
            let lines: Vec<&str> = text.lines().collect();
            assert_eq!(lines.len(), 2, "{text}");
            for (line, (_, want)) in lines.iter().zip(&files) {
                eprintln!("trimesh: {line}");
                let w: Vec<&str> = line.split_whitespace().collect();
                assert_eq!(w[0].parse::<u64>().unwrap(), want.0, "{line}");
                assert_eq!(w[1].parse::<u64>().unwrap(), want.1, "{line}");
                assert_eq!(&w[2..], ["True", "True"], "{line}");
            }
        }
        _ => eprintln!("skipping trimesh: python3 with trimesh not found (pip install trimesh)"),
    }
}

#[test]
fn the_gpu_meshes_what_the_cpu_meshes() {
    if stegongp::gpu::test_context().is_none() {
        return;
    }
    let f = fixture();
    let (c, g) = (
        f.dir.path().join("on_cpu.ply"),
        f.dir.path().join("on_gpu.ply"),
    );
    let rc = mesh(&c, &["--device", "cpu"]);
    let rg = mesh(&g, &["--device", "gpu"]);
    assert_eq!(rg["device"]["kind"], "gpu");
    let (mc, mg) = (read_ply(&c), read_ply(&g));
    // The device sums in another order: a lattice point within rounding of the threshold
    // may fall on the other side, nothing more.
    let (nc, ng) = (mc.triangles.len() as f64, mg.triangles.len() as f64);
    eprintln!("cpu {nc} triangles, gpu {ng}; {rc} {rg}");
    assert!(
        (nc - ng).abs() <= 0.002 * nc,
        "cpu {nc}, gpu {ng} triangles"
    );
    let mean = |m: &Mesh| {
        let n = m.positions.len() as f64;
        [0, 1, 2].map(|d| m.positions.iter().map(|p| p[d] as f64).sum::<f64>() / n)
    };
    let (a, b) = (mean(&mc), mean(&mg));
    let cell = cell(&rc) as f64;
    assert!(
        (0..3).all(|d| (a[d] - b[d]).abs() < 0.01 * cell),
        "{a:?} vs {b:?}"
    );
    assert!(edges(&mg).closed_and_oriented());
}

/// `stegongp mesh MODEL --out OUT --json EXTRA…` that succeeds with an empty mesh: its
/// report and what it said on standard error.
fn empty_mesh(name: &str, extra: &[&str]) -> (Value, String) {
    let f = fixture();
    let out = f.dir.path().join(name);
    let mut args = vec![
        "mesh",
        path_str(&f.model),
        "--out",
        path_str(&out),
        "--json",
    ];
    args.extend_from_slice(extra);
    let o = stegongp(&args);
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    let report: Value = serde_json::from_str(&stdout_ok(&o)).expect("one JSON report");
    let m = read_ply(&out);
    assert!(m.positions.is_empty() && m.triangles.is_empty());
    assert_eq!(report["triangles"], 0);
    (report, err)
}

#[test]
fn a_threshold_above_everything_gives_an_empty_mesh_and_says_so() {
    // Evaluated, never crossed: the largest density met is in the report and the message,
    // which proposes a threshold below it.
    let (r, err) = empty_mesh("empty.ply", &["--threshold", "1e9"]);
    let max = r["max_density"].as_f64().expect("a number") as f32;
    assert!(r["evaluated_points"].as_u64().unwrap() > 0, "{r}");
    assert!(max.is_finite() && max < 1e9, "{r}");
    assert!(
        err.contains("no surface")
            && err.contains("--threshold 1000000000")
            && err.contains(&format!("--threshold below {max}")),
        "{err}"
    );
}

#[test]
fn a_box_with_no_occupied_cell_evaluates_nothing_and_says_so() {
    // Outside the model's box altogether: every lattice point masked, nothing evaluated,
    // so there is no largest density (null, not NaN) and no threshold to propose.
    let (r, err) = empty_mesh("nowhere.ply", &["--box", "5,5,5,6,6,6"]);
    assert_eq!(r["evaluated_points"], 0, "{r}");
    assert!(r["max_density"].is_null(), "{r}");
    assert!(
        err.contains("no surface")
            && err.contains("no density was evaluated")
            && err.contains("Leave --box out")
            && !err.contains("--threshold"),
        "{err}"
    );
}

#[test]
fn bad_input_is_refused_and_nothing_is_written() {
    let f = fixture();
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("m.ply");
    let model = path_str(&f.model);
    // Not a model.
    let junk = d.path().join("junk.ingp");
    std::fs::write(&junk, b"not a model at all").unwrap();
    fails_naming(
        &stegongp(&["mesh", path_str(&junk), "--out", path_str(&out)]),
        &["junk.ingp"],
    );
    // An output the program cannot write: a missing folder, a wrong extension, a folder
    // it may not write into.
    let missing = d.path().join("nowhere").join("m.ply");
    fails_naming(
        &stegongp(&["mesh", model, "--out", path_str(&missing)]),
        &["does not exist"],
    );
    fails_naming(
        &stegongp(&["mesh", model, "--out", path_str(&d.path().join("m.stl"))]),
        &[".ply or .obj"],
    );
    let ro = d.path().join("ro");
    std::fs::create_dir(&ro).unwrap();
    // SAFETY: geteuid has no preconditions and cannot fail.
    let is_root = unsafe { libc::geteuid() } == 0;
    if !is_root {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o555)).unwrap();
        fails_naming(
            &stegongp(&[
                "mesh",
                model,
                "--out",
                path_str(&ro.join("m.ply")),
                "--resolution",
                "32",
            ]),
            &["m.ply"],
        );
    }
    // A folder in the output's place: the rename fails, naming it.
    let taken = d.path().join("taken.ply");
    std::fs::create_dir(&taken).unwrap();
    fails_naming(
        &stegongp(&[
            "mesh",
            model,
            "--out",
            path_str(&taken),
            "--resolution",
            "32",
        ]),
        &["taken.ply"],
    );
    // A lattice beyond the memory: refused at once, with the estimate.
    let t = std::time::Instant::now();
    fails_naming(
        &stegongp(&[
            "mesh",
            model,
            "--out",
            path_str(&out),
            "--resolution",
            "65536",
        ]),
        &["GiB", "--resolution 65536"],
    );
    assert!(t.elapsed().as_secs_f64() < 20.0);
    // A box that is not one.
    fails_naming(
        &stegongp(&["mesh", model, "--out", path_str(&out), "--box", "0,0,0,1,1"]),
        &["--box"],
    );
    fails_naming(
        &stegongp(&[
            "mesh",
            model,
            "--out",
            path_str(&out),
            "--box",
            "0,0,0,1,-1,1",
        ]),
        &["--box", "below"],
    );
    // A cap the mesh passes: nothing written.
    fails_naming(
        &stegongp(&[
            "mesh",
            model,
            "--out",
            path_str(&out),
            "--max-triangles",
            "10",
        ]),
        &["passed 10 triangles"],
    );
    let left: Vec<_> = std::fs::read_dir(d.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert!(
        left.iter()
            .all(|n| n == "junk.ingp" || n == "ro" || n == "taken.ply"),
        "left behind: {left:?}"
    );
    assert!(std::fs::read_dir(&ro).unwrap().next().is_none());
    assert!(std::fs::read_dir(&taken).unwrap().next().is_none());
}
