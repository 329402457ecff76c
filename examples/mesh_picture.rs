//! A picture of a mesh that `stegongp mesh` wrote, to look at it without a mesh viewer: a
//! small z-buffered rasteriser, vertex colours lit by a light over the viewer's shoulder.
//!
//! cargo run --release --example mesh_picture -- MESH.ply OUT.png [--size 800]
//!     [--azimuth 30] [--elevation 25] [--up y|z] [--normals]
//!
//! `--up y` for the default axes (instant-ngp's: the data's z is its y), `--up z` for
//! `--axes dataset`; `--normals` paints the normals instead of the colours.

use ply_rs_bw::parser::Parser;
use ply_rs_bw::ply::{DefaultElement, Property};
use std::path::PathBuf;
use stegongp::synth::scene::{cross, dot, sub};

type V = [f32; 3];

fn norm(a: V) -> V {
    let l = dot(a, a).sqrt().max(1e-20);
    a.map(|v| v / l)
}

struct Mesh {
    p: Vec<V>,
    n: Vec<V>,
    c: Vec<V>,
    t: Vec<[usize; 3]>,
}

fn read(path: &PathBuf) -> Mesh {
    let f = std::fs::File::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let ply = Parser::<DefaultElement>::new()
        .read_ply(&mut std::io::BufReader::new(f))
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let num = |e: &DefaultElement, k: &str| match e.get(k) {
        Some(Property::Float(v)) => *v,
        Some(Property::UChar(v)) => *v as f32 / 255.0,
        _ => 0.0,
    };
    let mut m = Mesh {
        p: vec![],
        n: vec![],
        c: vec![],
        t: vec![],
    };
    for v in &ply.payload["vertex"] {
        m.p.push([num(v, "x"), num(v, "y"), num(v, "z")]);
        m.n.push([num(v, "nx"), num(v, "ny"), num(v, "nz")]);
        m.c.push([num(v, "red"), num(v, "green"), num(v, "blue")]);
    }
    for f in &ply.payload["face"] {
        if let Some(Property::ListInt(l)) = f.get("vertex_indices") {
            m.t.push([l[0] as usize, l[1] as usize, l[2] as usize]);
        }
    }
    m
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let flag = |name: &str, default: &str| -> String {
        args.iter()
            .position(|a| a == name)
            .and_then(|i| args.get(i + 1).cloned())
            .unwrap_or_else(|| default.to_string())
    };
    let (input, out) = (PathBuf::from(&args[0]), PathBuf::from(&args[1]));
    let size: usize = flag("--size", "800").parse().unwrap();
    let az = flag("--azimuth", "30").parse::<f32>().unwrap().to_radians();
    let el = flag("--elevation", "25")
        .parse::<f32>()
        .unwrap()
        .to_radians();
    let up_z = flag("--up", "y") == "z";
    let normals = args.iter().any(|a| a == "--normals");
    let m = read(&input);
    // The mesh in a frame whose third axis is up.
    let lift = |v: V| if up_z { v } else { [v[2], v[0], v[1]] };
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for &p in &m.p {
        let q = lift(p);
        for d in 0..3 {
            lo[d] = lo[d].min(q[d]);
            hi[d] = hi[d].max(q[d]);
        }
    }
    let centre = [0, 1, 2].map(|d| 0.5 * (lo[d] + hi[d]));
    let radius = 0.5 * dot(sub(hi, lo), sub(hi, lo)).sqrt().max(1e-6);
    // An orthographic camera looking at the centre from (azimuth, elevation).
    let back = [el.cos() * az.cos(), el.cos() * az.sin(), el.sin()];
    let right = norm(cross([0.0, 0.0, 1.0], back));
    let up = cross(back, right);
    let light = norm([
        back[0] + 0.3 * right[0] + 0.5 * up[0],
        back[1] + 0.3 * right[1] + 0.5 * up[1],
        back[2] + 0.3 * right[2] + 0.5 * up[2],
    ]);
    let s = size as f32 / (2.1 * radius);
    let screen = |v: V| {
        let q = sub(lift(v), centre);
        [
            size as f32 * 0.5 + dot(q, right) * s,
            size as f32 * 0.5 - dot(q, up) * s,
            dot(q, back),
        ]
    };
    let mut depth = vec![f32::NEG_INFINITY; size * size];
    let mut rgb = vec![255u8; size * size * 3];
    for t in &m.t {
        let q = t.map(|i| screen(m.p[i]));
        let (x0, x1) = (
            q.iter().map(|v| v[0]).fold(f32::INFINITY, f32::min),
            q.iter().map(|v| v[0]).fold(f32::NEG_INFINITY, f32::max),
        );
        let (y0, y1) = (
            q.iter().map(|v| v[1]).fold(f32::INFINITY, f32::min),
            q.iter().map(|v| v[1]).fold(f32::NEG_INFINITY, f32::max),
        );
        let area =
            (q[1][0] - q[0][0]) * (q[2][1] - q[0][1]) - (q[2][0] - q[0][0]) * (q[1][1] - q[0][1]);
        if area.abs() < 1e-12 {
            continue;
        }
        for y in
            (y0.floor().max(0.0) as usize)..=(y1.ceil().min(size as f32 - 1.0).max(0.0) as usize)
        {
            for x in (x0.floor().max(0.0) as usize)
                ..=(x1.ceil().min(size as f32 - 1.0).max(0.0) as usize)
            {
                let (px, py) = (x as f32 + 0.5, y as f32 + 0.5);
                let w = [
                    ((q[1][0] - px) * (q[2][1] - py) - (q[2][0] - px) * (q[1][1] - py)) / area,
                    ((q[2][0] - px) * (q[0][1] - py) - (q[0][0] - px) * (q[2][1] - py)) / area,
                    ((q[0][0] - px) * (q[1][1] - py) - (q[1][0] - px) * (q[0][1] - py)) / area,
                ];
                if w.iter().any(|&v| v < 0.0) {
                    continue;
                }
                let z = w[0] * q[0][2] + w[1] * q[1][2] + w[2] * q[2][2];
                let i = y * size + x;
                if z <= depth[i] {
                    continue;
                }
                depth[i] = z;
                let mix = |a: &Vec<V>| {
                    [0, 1, 2].map(|d| w[0] * a[t[0]][d] + w[1] * a[t[1]][d] + w[2] * a[t[2]][d])
                };
                let n = norm(lift(mix(&m.n)));
                let c = if normals {
                    n.map(|v| 0.5 + 0.5 * v)
                } else {
                    // Two-sided: a face seen from behind is lit as its front.
                    let l = dot(n, light).abs();
                    mix(&m.c).map(|v| v * (0.45 + 0.55 * l))
                };
                for d in 0..3 {
                    rgb[i * 3 + d] = (c[d] * 255.0).clamp(0.0, 255.0) as u8;
                }
            }
        }
    }
    let f = std::fs::File::create(&out).unwrap_or_else(|e| panic!("{}: {e}", out.display()));
    let mut enc = png::Encoder::new(std::io::BufWriter::new(f), size as u32, size as u32);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    enc.write_header().unwrap().write_image_data(&rgb).unwrap();
    eprintln!("{} triangles → {}", m.t.len(), out.display());
}
