//! Analytic geometry and procedural materials: spheres, axis-aligned boxes, vertical
//! cylinders and discs, convex polygons of the x–z plane extruded along y (prisms), and
//! tori lying flat (axis z), shaded with Lambert + ambient under one directional light, with shadows. World
//! coordinates are Blender's: z up, metres, everything inside |x|,|y|,|z| < 1.3.

pub type V3 = [f32; 3];

pub use ngp::geometry::normalize_by_reciprocal as normalize;
pub use ngp::geometry::scale as mul;
pub use ngp::geometry::{add, cross, dot, sub};

/// How a surface is coloured at a hit point (world position, normal).
#[derive(Clone, Copy, Debug)]
pub enum Material {
    Solid(V3),
    /// Checkerboard of two colours with a cell size.
    Checker(V3, V3, f32),
    /// Hue stripes along z with a frequency.
    HueStripes(f32),
    /// Hue from the angle around the z axis plus dark helix lines.
    Helix,
    /// Grid lines of a colour on a base colour.
    Grid(V3, V3, f32),
    /// Hue gradient along x (the text scene).
    HueAlongX(f32, f32),
    /// Walls of a room: hue by the angle around z, a checkerboard of a cell size on top.
    Walls(f32),
    /// The inside of a furnished room, as fine as a photographed one: brick walls (each
    /// brick its own shade), a plank floor at `floor` (z) with grain, a tiled ceiling at
    /// `ceiling`.
    Interior {
        floor: f32,
        ceiling: f32,
    },
}

#[derive(Clone, Copy, Debug)]
pub enum Shape {
    Sphere {
        c: V3,
        r: f32,
    },
    Box {
        lo: V3,
        hi: V3,
    },
    /// Vertical cylinder with caps, axis along z.
    Cylinder {
        c: V3,
        r: f32,
        z0: f32,
        z1: f32,
    },
    /// A convex polygon of the x–z plane (points `[x, z]`, counter-clockwise, a triangle
    /// repeating its last point) extruded along y from `y0` to `y1`: the face is seen from
    /// −y, like the text. Build it with [`prism`], which fixes the winding.
    Prism {
        pts: [[f32; 2]; 4],
        y0: f32,
        y1: f32,
    },
    /// A torus lying flat: its axis along z through `c`, the tube's centre line a circle of
    /// radius `major` in the plane z = c.z, the tube of radius `minor` (< `major`, so that
    /// it has a hole).
    Torus {
        c: V3,
        major: f32,
        minor: f32,
    },
}

/// An extruded convex polygon of 3 or 4 points `[x, z]` (either winding) between `y0` and
/// `y1`; a triangle is `[a, b, c, c]`.
pub fn prism(mut pts: [[f32; 2]; 4], y0: f32, y1: f32) -> Shape {
    let area: f32 = (0..4)
        .map(|i| {
            let (a, b) = (pts[i], pts[(i + 1) % 4]);
            a[0] * b[1] - b[0] * a[1]
        })
        .sum();
    if area < 0.0 {
        pts.reverse();
    }
    Shape::Prism {
        pts,
        y0: y0.min(y1),
        y1: y0.max(y1),
    }
}

#[derive(Clone, Copy, Debug)]
pub struct Object {
    pub shape: Shape,
    pub material: Material,
    pub specular: f32,
}

pub struct Scene {
    pub objects: Vec<Object>,
    /// Bounding box of the objects, for a quick miss test.
    pub lo: V3,
    pub hi: V3,
    pub light: V3,
    /// What a ray that misses every object sees: nothing (transparent), or the inside of an
    /// enclosing box, shown at its albedo (no light, no shadow: it is the far background of
    /// a captured scene, and would otherwise shadow everything it encloses).
    pub backdrop: Option<(Shape, Material)>,
    /// Fine texture over every surface, 0 (none, the default) to 1: albedo times a
    /// three-octave value noise of the world position (cells of 20, 10 and 5 cm), the small
    /// blobs and specks of a real surface that feature detectors such as SIFT find, where the
    /// flat colours and regular patterns of the materials give them few.
    pub grain: f32,
}

pub struct Hit {
    pub t: f32,
    pub p: V3,
    pub n: V3,
    pub obj: usize,
}

pub(crate) fn hsv(h: f32, s: f32, v: f32) -> V3 {
    let h = h.rem_euclid(1.0) * 6.0;
    let i = h.floor();
    let f = h - i;
    let (p, q, t) = (v * (1.0 - s), v * (1.0 - s * f), v * (1.0 - s * (1.0 - f)));
    match i as i32 {
        0 => [v, t, p],
        1 => [q, v, p],
        2 => [p, v, t],
        3 => [p, q, v],
        4 => [t, p, v],
        _ => [v, p, q],
    }
}

fn slab(o: V3, inv: V3, lo: V3, hi: V3) -> Option<(f32, f32, usize, usize)> {
    let (mut t0, mut t1) = (f32::NEG_INFINITY, f32::INFINITY);
    let (mut a0, mut a1) = (0, 0);
    for k in 0..3 {
        let mut a = (lo[k] - o[k]) * inv[k];
        let mut b = (hi[k] - o[k]) * inv[k];
        if a > b {
            std::mem::swap(&mut a, &mut b);
        }
        if a > t0 {
            t0 = a;
            a0 = k;
        }
        if b < t1 {
            t1 = b;
            a1 = k;
        }
    }
    (t0 <= t1 && t1 > 0.0).then_some((t0, t1, a0, a1))
}

impl Shape {
    /// Nearest hit with t > eps: (t, outward normal).
    pub fn intersect(&self, o: V3, d: V3, inv: V3) -> Option<(f32, V3)> {
        const EPS: f32 = 1e-4;
        match *self {
            Shape::Sphere { c, r } => {
                let oc = sub(o, c);
                let b = dot(oc, d);
                let disc = b * b - (dot(oc, oc) - r * r);
                if disc < 0.0 {
                    return None;
                }
                let s = disc.sqrt();
                let t = if -b - s > EPS {
                    -b - s
                } else if -b + s > EPS {
                    -b + s
                } else {
                    return None;
                };
                Some((t, normalize(sub(add(o, mul(d, t)), c))))
            }
            Shape::Box { lo, hi } => {
                let (t0, t1, a0, a1) = slab(o, inv, lo, hi)?;
                let (t, axis, outside) = if t0 > EPS {
                    (t0, a0, true)
                } else if t1 > EPS {
                    (t1, a1, false)
                } else {
                    return None;
                };
                let mut n = [0.0; 3];
                n[axis] = if outside {
                    -d[axis].signum()
                } else {
                    d[axis].signum()
                };
                Some((t, n))
            }
            Shape::Cylinder { c, r, z0, z1 } => {
                let mut best: Option<(f32, V3)> = None;
                let (ox, oy) = (o[0] - c[0], o[1] - c[1]);
                let a = d[0] * d[0] + d[1] * d[1];
                if a > 1e-12 {
                    let b = ox * d[0] + oy * d[1];
                    let disc = b * b - a * (ox * ox + oy * oy - r * r);
                    if disc >= 0.0 {
                        let s = disc.sqrt();
                        for t in [(-b - s) / a, (-b + s) / a] {
                            let z = o[2] + t * d[2];
                            if t > EPS && z >= z0 && z <= z1 && best.is_none_or(|(bt, _)| t < bt) {
                                let p = add(o, mul(d, t));
                                best = Some((t, normalize([p[0] - c[0], p[1] - c[1], 0.0])));
                            }
                        }
                    }
                }
                for (zc, nz) in [(z0, -1.0f32), (z1, 1.0)] {
                    let t = (zc - o[2]) * inv[2];
                    if t > EPS && t.is_finite() {
                        let p = add(o, mul(d, t));
                        let (dx, dy) = (p[0] - c[0], p[1] - c[1]);
                        if dx * dx + dy * dy <= r * r && best.is_none_or(|(bt, _)| t < bt) {
                            best = Some((t, [0.0, 0.0, nz]));
                        }
                    }
                }
                best
            }
            Shape::Prism { pts, y0, y1 } => {
                // Cyrus–Beck: the ray enters at the latest entering plane, leaves at the
                // earliest leaving one; planes are the two caps and the polygon's edges.
                let (mut t0, mut t1) = (f32::NEG_INFINITY, f32::INFINITY);
                let (mut n0, mut n1) = ([0.0f32; 3], [0.0f32; 3]);
                if d[1] == 0.0 {
                    if o[1] < y0 || o[1] > y1 {
                        return None;
                    }
                } else {
                    let (a, b) = ((y0 - o[1]) * inv[1], (y1 - o[1]) * inv[1]);
                    (t0, n0, t1, n1) = if a < b {
                        (a, [0.0, -1.0, 0.0], b, [0.0, 1.0, 0.0])
                    } else {
                        (b, [0.0, 1.0, 0.0], a, [0.0, -1.0, 0.0])
                    };
                }
                for i in 0..4 {
                    let (a, b) = (pts[i], pts[(i + 1) % 4]);
                    let e = [b[0] - a[0], b[1] - a[1]];
                    let len = (e[0] * e[0] + e[1] * e[1]).sqrt();
                    if len < 1e-9 {
                        continue;
                    }
                    // Outward normal of a counter-clockwise edge in (x, z). Every edge moves
                    // out by 1e-5 so that rays along a seam between two prisms (a fan's
                    // triangles) hit one of them.
                    let n = [e[1] / len, -e[0] / len];
                    let num = n[0] * (o[0] - a[0]) + n[1] * (o[2] - a[1]) - 1e-5;
                    let den = n[0] * d[0] + n[1] * d[2];
                    if den == 0.0 {
                        if num > 0.0 {
                            return None;
                        }
                        continue;
                    }
                    let t = -num / den;
                    if den < 0.0 {
                        if t > t0 {
                            t0 = t;
                            n0 = [n[0], 0.0, n[1]];
                        }
                    } else if t < t1 {
                        t1 = t;
                        n1 = [n[0], 0.0, n[1]];
                    }
                }
                if t0 > t1 || t1 <= EPS {
                    None
                } else if t0 > EPS {
                    Some((t0, n0))
                } else {
                    Some((t1, n1))
                }
            }
            Shape::Torus { c, major, minor } => torus_hit(c, major, minor, o, d, EPS),
        }
    }
}

/// The torus's signed distance (exact) and its gradient (the outward unit normal on the
/// surface): the distance from the tube's centre circle, less the tube's radius.
fn torus_field(c: V3, major: f32, minor: f32, p: V3) -> (f32, V3) {
    let q = sub(p, c);
    let rho = (q[0] * q[0] + q[1] * q[1]).sqrt();
    // On the axis every direction is nearest; any will do (the axis is never on the surface).
    let (ux, uy) = if rho > 1e-12 {
        (q[0] / rho, q[1] / rho)
    } else {
        (1.0, 0.0)
    };
    let (w, h) = (rho - major, q[2]);
    let len = (w * w + h * h).sqrt();
    let n = if len > 1e-12 {
        [ux * w / len, uy * w / len, h / len]
    } else {
        [0.0, 0.0, 1.0]
    };
    (len - minor, n)
}

/// A ray's first hit on a torus past `eps`, by sphere tracing the exact signed distance
/// from where the ray enters the torus's bounding sphere: every step moves by the distance
/// to the surface, so it never passes through it (from inside the tube too, by the
/// distance's absolute value). A quartic's roots in f32 lose the grazing hits this keeps.
fn torus_hit(c: V3, major: f32, minor: f32, o: V3, d: V3, eps: f32) -> Option<(f32, V3)> {
    let bound = major + minor;
    let oc = sub(o, c);
    let b = dot(oc, d);
    let disc = b * b - (dot(oc, oc) - bound * bound);
    if disc < 0.0 {
        return None;
    }
    let s = disc.sqrt();
    let (t_in, t_out) = (-b - s, -b + s);
    if t_out <= eps {
        return None;
    }
    let mut t = t_in.max(eps);
    // The tolerance of a hit, relative to the torus's size.
    let tol = 1e-5 * bound;
    for _ in 0..256 {
        let (dist, n) = torus_field(c, major, minor, add(o, mul(d, t)));
        if dist.abs() < tol {
            return Some((t, n));
        }
        t += dist.abs();
        if t > t_out {
            return None;
        }
    }
    None
}

impl Shape {
    /// The distance from `p` to the shape's surface, negative inside: what a test measures
    /// a mesh against.
    pub fn signed_distance(&self, p: V3) -> f32 {
        // Signed distances along each direction of a box-like extent, combined as a box's.
        let boxed = |out: &[f32]| {
            let inner = out.iter().cloned().fold(f32::NEG_INFINITY, f32::max);
            if inner <= 0.0 {
                inner
            } else {
                out.iter().map(|v| v.max(0.0).powi(2)).sum::<f32>().sqrt()
            }
        };
        match *self {
            Shape::Sphere { c, r } => dot(sub(p, c), sub(p, c)).sqrt() - r,
            Shape::Box { lo, hi } => boxed(&[0, 1, 2].map(|k| (lo[k] - p[k]).max(p[k] - hi[k]))),
            Shape::Cylinder { c, r, z0, z1 } => {
                let radial = ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2)).sqrt() - r;
                boxed(&[radial, (z0 - p[2]).max(p[2] - z1)])
            }
            Shape::Prism { pts, y0, y1 } => {
                let q = [p[0], p[2]];
                // Signed distance to the convex polygon: the largest edge-plane distance
                // inside; the nearest edge segment outside.
                let (mut plane, mut seg) = (f32::NEG_INFINITY, f32::INFINITY);
                for i in 0..4 {
                    let (a, b) = (pts[i], pts[(i + 1) % 4]);
                    let e = [b[0] - a[0], b[1] - a[1]];
                    let len2 = e[0] * e[0] + e[1] * e[1];
                    if len2 < 1e-18 {
                        continue;
                    }
                    let w = [q[0] - a[0], q[1] - a[1]];
                    plane = plane.max((e[1] * w[0] - e[0] * w[1]) / len2.sqrt());
                    let t = ((w[0] * e[0] + w[1] * e[1]) / len2).clamp(0.0, 1.0);
                    seg = seg.min(((w[0] - t * e[0]).powi(2) + (w[1] - t * e[1]).powi(2)).sqrt());
                }
                let planar = if plane > 0.0 { seg } else { plane };
                boxed(&[planar, (y0 - p[1]).max(p[1] - y1)])
            }
            Shape::Torus { c, major, minor } => torus_field(c, major, minor, p).0,
        }
    }
}

impl Scene {
    /// The signed distance from `p` to the union of the scene's objects (the backdrop
    /// aside), negative inside one: exact outside, and inside as deep as the deepest
    /// object's.
    pub fn signed_distance(&self, p: V3) -> f32 {
        self.objects
            .iter()
            .map(|o| o.shape.signed_distance(p))
            .fold(f32::INFINITY, f32::min)
    }
}

impl Material {
    pub fn albedo(&self, p: V3) -> V3 {
        match *self {
            Material::Solid(c) => c,
            Material::Checker(a, b, s) => {
                let k = (p[0] / s).floor() as i32
                    + (p[1] / s).floor() as i32
                    + (p[2] / s).floor() as i32;
                if k.rem_euclid(2) == 0 { a } else { b }
            }
            Material::HueStripes(f) => hsv(p[2] * f, 0.75, 0.95),
            Material::Helix => {
                let ang = p[1].atan2(p[0]) / std::f32::consts::TAU;
                let line = ((ang * 6.0 + p[2] * 4.0).rem_euclid(1.0) < 0.18) as i32 as f32;
                mul(hsv(ang + 0.1, 0.6, 0.9), 1.0 - 0.7 * line)
            }
            Material::Grid(base, line, s) => {
                let on = (0..3).any(|k| (p[k] / s).rem_euclid(1.0) < 0.12);
                if on { line } else { base }
            }
            Material::HueAlongX(lo, hi) => hsv(0.8 * (p[0] - lo) / (hi - lo), 0.8, 0.95),
            Material::Walls(s) => {
                let k = (p[0] / s).floor() as i32
                    + (p[1] / s).floor() as i32
                    + (p[2] / s).floor() as i32;
                let v = if k.rem_euclid(2) == 0 { 0.9 } else { 0.55 };
                hsv(p[1].atan2(p[0]) / std::f32::consts::TAU, 0.45, v)
            }
            Material::Interior { floor, ceiling } => interior(p, floor, ceiling),
        }
    }
}

/// A number in [0, 1) for an integer cell (a few rounds of an integer mix).
fn cell_hash(i: i32, j: i32, salt: u32) -> f32 {
    let mut h = (i as u32).wrapping_mul(0x8da6_b343) ^ (j as u32).wrapping_mul(0xd816_3841);
    h ^= salt.wrapping_mul(0xcb1a_b31f);
    h ^= h >> 13;
    h = h.wrapping_mul(0x5bd1_e995);
    h ^= h >> 15;
    (h >> 8) as f32 / (1u32 << 24) as f32
}

/// [`Material::Interior`]'s albedo at a point of the room's box.
fn interior(p: V3, floor: f32, ceiling: f32) -> V3 {
    if p[2] <= floor + 1e-3 {
        // Planks 0.3 m wide along x, each its own tone, with grain along its length.
        let plank = (p[1] / 0.3).floor() as i32;
        let piece = ((p[0] + 1.7 * cell_hash(plank, 0, 7)) / 2.1).floor() as i32;
        let tone = 0.6 + 0.4 * cell_hash(plank, piece, 1);
        let grain = 0.85 + 0.15 * (p[0] * 23.0 + 9.0 * cell_hash(plank, piece, 2)).sin();
        let seam = ((p[1] / 0.3).rem_euclid(1.0) < 0.04) as i32 as f32;
        return mul([0.62, 0.42, 0.26], tone * grain * (1.0 - 0.6 * seam));
    }
    if p[2] >= ceiling - 1e-3 {
        let on = (p[0] / 0.6).rem_euclid(1.0) < 0.05 || (p[1] / 0.6).rem_euclid(1.0) < 0.05;
        return if on {
            [0.6, 0.6, 0.62]
        } else {
            [0.88, 0.88, 0.85]
        };
    }
    // Bricks 0.6 × 0.25 m, every other row offset by half a brick, 3 cm of mortar; `u` runs
    // along whichever wall the point is on (the other coordinate is that wall's constant).
    let u = p[0] + p[1];
    let row = (p[2] / 0.25).floor() as i32;
    let shifted = u / 0.6 + 0.5 * (row & 1) as f32;
    let col = shifted.floor() as i32;
    let mortar = shifted.rem_euclid(1.0) < 0.05 || (p[2] / 0.25).rem_euclid(1.0) < 0.12;
    if mortar {
        return [0.7, 0.68, 0.64];
    }
    let h = cell_hash(col, row, 3);
    hsv(
        0.02 + 0.08 * h,
        0.45 + 0.3 * cell_hash(col, row, 4),
        0.45 + 0.4 * h,
    )
}

impl Scene {
    pub fn new(objects: Vec<Object>, light: V3) -> Self {
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for o in &objects {
            let (a, b) = match o.shape {
                Shape::Sphere { c, r } => (sub(c, [r; 3]), add(c, [r; 3])),
                Shape::Box { lo, hi } => (lo, hi),
                Shape::Cylinder { c, r, z0, z1 } => {
                    ([c[0] - r, c[1] - r, z0], [c[0] + r, c[1] + r, z1])
                }
                Shape::Prism { pts, y0, y1 } => {
                    let (mut a, mut b) = (
                        [f32::INFINITY, y0, f32::INFINITY],
                        [f32::NEG_INFINITY, y1, f32::NEG_INFINITY],
                    );
                    for p in pts {
                        a[0] = a[0].min(p[0]);
                        a[2] = a[2].min(p[1]);
                        b[0] = b[0].max(p[0]);
                        b[2] = b[2].max(p[1]);
                    }
                    (a, b)
                }
                Shape::Torus { c, major, minor } => {
                    let e = [major + minor, major + minor, minor];
                    (sub(c, e), add(c, e))
                }
            };
            for k in 0..3 {
                lo[k] = lo[k].min(a[k]);
                hi[k] = hi[k].max(b[k]);
            }
        }
        Scene {
            objects,
            lo,
            hi,
            light: normalize(light),
            backdrop: None,
            grain: 0.0,
        }
    }

    pub fn intersect(&self, o: V3, d: V3) -> Option<Hit> {
        let inv = [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]];
        slab(o, inv, self.lo, self.hi)?;
        let mut best: Option<Hit> = None;
        for (i, ob) in self.objects.iter().enumerate() {
            if let Some((t, n)) = ob.shape.intersect(o, d, inv)
                && best.as_ref().is_none_or(|b| t < b.t)
            {
                best = Some(Hit {
                    t,
                    p: add(o, mul(d, t)),
                    n,
                    obj: i,
                });
            }
        }
        best
    }

    /// Colour seen along a ray, or `None` for background.
    pub fn shade(&self, o: V3, d: V3) -> Option<V3> {
        let Some(h) = self.intersect(o, d) else {
            let (shape, material) = self.backdrop.as_ref()?;
            let inv = [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]];
            let (t, _) = shape.intersect(o, d, inv)?;
            let p = add(o, mul(d, t));
            return Some(self.grained(material.albedo(p), p));
        };
        let ob = &self.objects[h.obj];
        let albedo = self.grained(ob.material.albedo(h.p), h.p);
        let ndl = dot(h.n, self.light).max(0.0);
        let lit = if ndl > 0.0
            && self
                .intersect(add(h.p, mul(h.n, 1e-3)), self.light)
                .is_some()
        {
            0.0
        } else {
            ndl
        };
        let mut c = mul(albedo, 0.35 + 0.65 * lit);
        if ob.specular > 0.0 && lit > 0.0 {
            let r = sub(mul(h.n, 2.0 * dot(h.n, self.light)), self.light);
            let s = ob.specular * dot(r, mul(d, -1.0)).max(0.0).powi(24);
            c = add(c, [s; 3]);
        }
        Some([c[0].min(1.0), c[1].min(1.0), c[2].min(1.0)])
    }
}

impl Scene {
    /// `albedo` with the scene's [`Scene::grain`] at `p`.
    fn grained(&self, albedo: V3, p: V3) -> V3 {
        if self.grain <= 0.0 {
            return albedo;
        }
        let n = 0.5 * value_noise(mul(p, 5.0), 11)
            + 0.3 * value_noise(mul(p, 10.0), 12)
            + 0.2 * value_noise(mul(p, 20.0), 13);
        mul(albedo, 1.0 - self.grain + 2.0 * self.grain * n)
    }
}

/// Smooth value noise in [0, 1): random values at the integer lattice, blended with a
/// smoothstep between them.
fn value_noise(p: V3, salt: u32) -> f32 {
    let f = p.map(f32::floor);
    let t = [0, 1, 2].map(|k| {
        let x = p[k] - f[k];
        x * x * (3.0 - 2.0 * x)
    });
    let (i, j, k) = (f[0] as i32, f[1] as i32, f[2] as i32);
    let v = |a: i32, b: i32, c: i32| {
        cell_hash(
            i + a,
            j + b,
            salt ^ ((k + c) as u32).wrapping_mul(0x9e37_79b9),
        )
    };
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let x00 = lerp(v(0, 0, 0), v(1, 0, 0), t[0]);
    let x10 = lerp(v(0, 1, 0), v(1, 1, 0), t[0]);
    let x01 = lerp(v(0, 0, 1), v(1, 0, 1), t[0]);
    let x11 = lerp(v(0, 1, 1), v(1, 1, 1), t[0]);
    lerp(lerp(x00, x10, t[1]), lerp(x01, x11, t[1]), t[2])
}

/// The object scene: a checkered platform with a striped sphere, a gridded box, a helix
/// cylinder and a small glossy sphere.
pub fn object_scene() -> Scene {
    let objs = vec![
        Object {
            shape: Shape::Cylinder {
                c: [0.0, 0.0, 0.0],
                r: 1.15,
                z0: -0.75,
                z1: -0.62,
            },
            material: Material::Checker([0.92, 0.9, 0.85], [0.25, 0.3, 0.45], 0.23),
            specular: 0.0,
        },
        Object {
            shape: Shape::Sphere {
                c: [0.38, 0.3, -0.2],
                r: 0.42,
            },
            material: Material::HueStripes(2.5),
            specular: 0.5,
        },
        Object {
            shape: Shape::Box {
                lo: [-0.85, -0.55, -0.62],
                hi: [-0.25, 0.05, -0.02],
            },
            material: Material::Grid([0.95, 0.75, 0.2], [0.5, 0.15, 0.1], 0.15),
            specular: 0.0,
        },
        Object {
            shape: Shape::Cylinder {
                c: [0.25, -0.55, 0.0],
                r: 0.2,
                z0: -0.62,
                z1: 0.55,
            },
            material: Material::Helix,
            specular: 0.0,
        },
        Object {
            shape: Shape::Sphere {
                c: [-0.45, 0.55, -0.42],
                r: 0.2,
            },
            material: Material::Solid([0.2, 0.75, 0.35]),
            specular: 0.8,
        },
        Object {
            shape: Shape::Box {
                lo: [-0.15, 0.5, -0.62],
                hi: [0.2, 0.85, -0.3],
            },
            material: Material::Checker([0.85, 0.2, 0.3], [0.95, 0.95, 0.95], 0.09),
            specular: 0.0,
        },
    ];
    Scene::new(objs, [0.5, -0.4, 0.8])
}

/// The shapes scene: a ball, a box and a torus lying flat, apart, nothing else, whose
/// surfaces a test knows exactly ([`Scene::signed_distance`]): a mesh of a model trained on
/// it is measured against them, and the torus's hole (0.42 across, seen through from the
/// views above and below the horizon) gives the mesh a surface of genus 1.
pub fn shapes_scene() -> Scene {
    let objs = vec![
        Object {
            shape: Shape::Sphere {
                c: [-0.5, 0.15, 0.05],
                r: 0.5,
            },
            material: Material::HueStripes(2.5),
            specular: 0.0,
        },
        Object {
            shape: Shape::Box {
                lo: [0.2, -0.55, -0.45],
                hi: [0.9, 0.25, 0.35],
            },
            material: Material::Grid([0.95, 0.75, 0.2], [0.3, 0.15, 0.6], 0.2),
            specular: 0.0,
        },
        // Beside the box (0.10 above its face y = 0.25, two cells of a 64 lattice) and the
        // ball (0.15 from it), inside |x|, |y| < 1.3 (y up to 1.29).
        Object {
            shape: Shape::Torus {
                c: [0.4, 0.82, 0.0],
                major: 0.34,
                minor: 0.13,
            },
            material: Material::Checker([0.3, 0.75, 0.45], [0.92, 0.92, 0.95], 0.12),
            specular: 0.0,
        },
    ];
    Scene::new(objs, [0.5, -0.4, 0.8])
}

/// The object scene inside a room: walls at `half_size` around the origin, the floor half
/// as far below. Cameras stand inside the room, so the walls are a background far
/// from the object that every view shows (the layout of a real capture).
pub fn room_scene(half_size: f32) -> Scene {
    let mut s = object_scene();
    s.backdrop = Some((
        Shape::Box {
            lo: [-half_size, -half_size, -0.5 * half_size],
            hi: [half_size, half_size, half_size],
        },
        Material::Walls(half_size / 3.0),
    ));
    s
}

/// Furniture of a [`furnished_room`]: boxes (cupboards, chests, a sofa) and cylinders
/// (lamps, pillars, bins) standing on the floor between the cameras' circle (`clear`) and
/// the walls (`walls`), each with a fine texture of its own, drawn from `seed`.
fn furniture(clear: f32, walls: f32, floor: f32, seed: u64) -> Vec<Object> {
    let mut rng = ngp::rng::Pcg32::new(seed, 0xf0_7217);
    let mut u = move |a: f32, b: f32| a + (b - a) * rng.next_f32();
    (0..16)
        .map(|i| {
            let ang = (i as f32 + u(0.0, 0.6)) / 16.0 * std::f32::consts::TAU;
            let r = u(clear, 0.8 * walls);
            let (x, y) = (r * ang.cos(), r * ang.sin());
            let colour =
                |u: &mut dyn FnMut(f32, f32) -> f32| hsv(u(0.0, 1.0), u(0.2, 0.8), u(0.4, 0.95));
            let material = match i % 4 {
                0 => Material::Checker(colour(&mut u), colour(&mut u), u(0.08, 0.25)),
                1 => Material::Grid(colour(&mut u), colour(&mut u), u(0.15, 0.4)),
                2 => Material::HueStripes(u(2.0, 7.0)),
                _ => Material::Solid(colour(&mut u)),
            };
            let shape = if i % 3 == 2 {
                Shape::Cylinder {
                    c: [x, y, 0.0],
                    r: u(0.15, 0.7),
                    z0: floor,
                    z1: floor + u(0.8, 4.5),
                }
            } else {
                let (hx, hy) = (u(0.4, 1.8), u(0.4, 1.8));
                Shape::Box {
                    lo: [x - hx, y - hy, floor],
                    hi: [x + hx, y + hy, floor + u(0.5, 3.0)],
                }
            };
            Object {
                shape,
                material,
                specular: 0.0,
            }
        })
        .collect()
}

/// The object scene on a pedestal in a furnished room, like an indoor 360° capture (an
/// object on a table in the middle of a room): brick walls at `walls` around the origin,
/// a plank floor 2.5 m below the object's platform, a ceiling, and furniture between the
/// cameras' circle (`clear`) and the walls ([`furniture`]). Every surface has detail a few
/// pixels across, which a model must resolve before its rays can end on it.
pub fn furnished_room(walls: f32, clear: f32, seed: u64) -> Scene {
    let mut s = object_scene();
    let floor = -2.5;
    let ceiling = floor + 0.6 * walls;
    let mut objects = std::mem::take(&mut s.objects);
    objects.push(Object {
        shape: Shape::Cylinder {
            c: [0.0, 0.0, 0.0],
            r: 0.35,
            z0: floor,
            z1: -0.75,
        },
        material: Material::HueStripes(5.0),
        specular: 0.0,
    });
    objects.extend(furniture(clear, walls, floor, seed));
    let mut room = Scene::new(objects, s.light);
    room.backdrop = Some((
        Shape::Box {
            lo: [-walls, -walls, floor],
            hi: [walls, walls, ceiling],
        },
        Material::Interior { floor, ceiling },
    ));
    room
}

/// 3D text: each line of glyphs stands upright in the x–z plane (readable from −y), every
/// run of filled glyph cells an extruded box, coloured along x.
pub fn text_scene(lines: &[Vec<char>]) -> Scene {
    use super::font::{GLYPH_H, GLYPH_W, glyph};
    let cols = lines.iter().map(|l| l.len()).max().unwrap_or(1).max(1);
    let cell_cols = cols * (GLYPH_W + 1) - 1;
    let cell_rows = lines.len() * (GLYPH_H + 2) - 2;
    // Fit into |x| ≤ 1.15 and |z| ≤ 0.9.
    let s = (2.3 / cell_cols as f32).min(1.8 / cell_rows as f32);
    let (x0, z0) = (-(cell_cols as f32) * s / 2.0, cell_rows as f32 * s / 2.0);
    let depth = (0.35f32).min(4.0 * s);
    let mut objs = Vec::new();
    for (li, line) in lines.iter().enumerate() {
        let pad = (cols - line.len()) * (GLYPH_W + 1) / 2;
        for (ci, &ch) in line.iter().enumerate() {
            let g = glyph(ch).expect("validated");
            for (r, row) in g.iter().enumerate() {
                let bytes = row.as_bytes();
                let mut c = 0;
                while c < GLYPH_W {
                    if bytes[c] != b'#' {
                        c += 1;
                        continue;
                    }
                    let start = c;
                    while c < GLYPH_W && bytes[c] == b'#' {
                        c += 1;
                    }
                    let gx = (pad + ci * (GLYPH_W + 1) + start) as f32;
                    let gz = (li * (GLYPH_H + 2) + r) as f32;
                    objs.push(Object {
                        shape: Shape::Box {
                            lo: [x0 + gx * s, -depth / 2.0, z0 - (gz + 1.0) * s],
                            hi: [x0 + (gx + (c - start) as f32) * s, depth / 2.0, z0 - gz * s],
                        },
                        material: Material::HueAlongX(x0, -x0),
                        specular: 0.0,
                    });
                }
            }
        }
    }
    Scene::new(objs, [0.3, -0.6, 0.75])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn signed_distances_are_exact_on_simple_points() {
        let close = |a: f32, b: f32| (a - b).abs() < 1e-5;
        let ball = Shape::Sphere {
            c: [1.0, 0.0, 0.0],
            r: 0.5,
        };
        assert!(close(ball.signed_distance([1.0, 0.0, 0.0]), -0.5));
        assert!(close(ball.signed_distance([1.0, 2.0, 0.0]), 1.5));
        let cube = Shape::Box {
            lo: [0.0; 3],
            hi: [1.0; 3],
        };
        assert!(close(cube.signed_distance([0.5, 0.5, 0.9]), -0.1));
        assert!(close(cube.signed_distance([2.0, 2.0, 0.5]), 2f32.sqrt()));
        let can = Shape::Cylinder {
            c: [0.0; 3],
            r: 1.0,
            z0: 0.0,
            z1: 2.0,
        };
        assert!(close(can.signed_distance([0.0, 0.0, 1.8]), -0.2));
        assert!(close(can.signed_distance([3.0, 0.0, 3.0]), 5f32.sqrt()));
        // A unit square prism along y from 0 to 1.
        let p = prism([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], 0.0, 1.0);
        assert!(close(p.signed_distance([0.5, 0.5, 0.8]), -0.2));
        assert!(close(p.signed_distance([2.0, 0.5, 0.5]), 1.0));
        assert!(close(p.signed_distance([2.0, 2.0, 2.0]), 3f32.sqrt()));
        // A torus of radii 1 and 0.25 about (0, 0, 1): the tube's centre, the hole's centre,
        // above the tube, and off the tube's rim at 45°.
        let ring = Shape::Torus {
            c: [0.0, 0.0, 1.0],
            major: 1.0,
            minor: 0.25,
        };
        assert!(close(ring.signed_distance([0.0, 1.0, 1.0]), -0.25));
        assert!(close(ring.signed_distance([0.0, 0.0, 1.0]), 0.75));
        assert!(close(ring.signed_distance([1.0, 0.0, 2.0]), 0.75));
        let h = 0.5f32.sqrt();
        assert!(close(ring.signed_distance([2.0 * h, 2.0 * h, 1.0]), 0.75));
        assert!(close(ring.signed_distance([0.0, -1.4, 1.3]), 0.25));
        let s = shapes_scene();
        assert!(close(s.signed_distance([-0.5, 0.15, 0.05]), -0.5));
        assert!(s.signed_distance([0.0, 0.0, 1.5]) > 0.5);
        // The torus's tube and hole.
        assert!(close(s.signed_distance([0.4, 0.82 + 0.34, 0.0]), -0.13));
        assert!(close(s.signed_distance([0.4, 0.82, 0.0]), 0.34 - 0.13));
    }

    /// The shapes stay apart (no two surfaces within 0.08, the torus being 0.10 from the
    /// box: two cells of the mesh test's lattice) and inside |x|, |y|, |z| < 1.3.
    #[test]
    fn the_shapes_scene_keeps_its_shapes_apart_and_inside() {
        let s = shapes_scene();
        assert_eq!(s.objects.len(), 3);
        assert!(
            (0..3).all(|k| s.lo[k] > -1.3 && s.hi[k] < 1.3),
            "{:?} {:?}",
            s.lo,
            s.hi
        );
        // On a 0.02 grid over the scene's bounds: no point within 0.04 of two shapes.
        let n = 130;
        for i in 0..n {
            for j in 0..n {
                for k in 0..n / 2 {
                    let p = [
                        -1.3 + 2.6 * i as f32 / n as f32,
                        -1.3 + 2.6 * j as f32 / n as f32,
                        -0.65 + 1.3 * k as f32 / (n / 2) as f32,
                    ];
                    let near = s
                        .objects
                        .iter()
                        .filter(|o| o.shape.signed_distance(p) < 0.04)
                        .count();
                    assert!(near < 2, "{p:?} is near two shapes");
                }
            }
        }
    }

    #[test]
    fn a_ray_through_the_torus_hole_misses_and_one_into_the_tube_hits_it() {
        let c = [0.3, -0.2, 0.5];
        let ring = Shape::Torus {
            c,
            major: 1.0,
            minor: 0.25,
        };
        let hit = |o: V3, d: V3| {
            let d = normalize(d);
            ring.intersect(o, d, [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]])
        };
        // Down the axis, and slanted through the hole: misses.
        assert!(hit(add(c, [0.0, 0.0, 3.0]), [0.0, 0.0, -1.0]).is_none());
        assert!(hit(add(c, [0.2, 0.1, 3.0]), [-0.1, 0.05, -1.0]).is_none());
        // Beside the ring altogether.
        assert!(hit(add(c, [1.3, 0.0, 3.0]), [0.0, 0.0, -1.0]).is_none());
        // Straight down onto the tube's top: t = 3 − 0.25, normal +z.
        let (t, n) = hit(add(c, [1.0, 0.0, 3.0]), [0.0, 0.0, -1.0]).expect("the tube");
        assert!((t - 2.75).abs() < 1e-4, "{t}");
        assert!(dot(n, [0.0, 0.0, 1.0]) > 0.9999, "{n:?}");
        // Along x in the ring's plane, from outside: the outer rim at x = 1.25, normal −x
        // (facing the ray); off-centre in y, the hit and normal still on the tube.
        let (t, n) = hit(add(c, [-3.0, 0.0, 0.0]), [1.0, 0.0, 0.0]).expect("the rim");
        assert!((t - (3.0 - 1.25)).abs() < 1e-4, "{t}");
        assert!(dot(n, [-1.0, 0.0, 0.0]) > 0.9999, "{n:?}");
        let o = add(c, [0.1, -3.0, 0.15]);
        let (t, n) = hit(o, [0.0, 1.0, 0.0]).expect("the tube, off-centre");
        // The tube's section at x = 0.1 is a circle only in the torus's own (ρ, z) plane;
        // check the hit against the exact distance and the normal against the gradient.
        let p = add(o, mul([0.0, 1.0, 0.0], t));
        assert!(ring.signed_distance(p).abs() < 1e-4, "{p:?}");
        let q = sub(p, c);
        let rho = (q[0] * q[0] + q[1] * q[1]).sqrt();
        let want = normalize([q[0] / rho * (rho - 1.0), q[1] / rho * (rho - 1.0), q[2]]);
        assert!(dot(n, want) > 0.9999, "{n:?} {want:?}");
        assert!(n[1] < 0.0, "faces the ray: {n:?}");
        // From inside the tube: it leaves through the wall, normal along the ray.
        let (t, n) = hit(add(c, [1.0, 0.0, 0.0]), [0.0, 0.0, 1.0]).expect("from inside");
        assert!((t - 0.25).abs() < 1e-4, "{t}");
        assert!(n[2] > 0.9999, "{n:?}");
        // A scene with the torus: a ray through the hole sees nothing.
        let s = shapes_scene();
        assert!(s.intersect([0.4, 0.82, 3.0], [0.0, 0.0, -1.0]).is_none());
        let h = s
            .intersect([0.4 + 0.34, 0.82, 3.0], [0.0, 0.0, -1.0])
            .expect("its tube");
        assert!((h.t - (3.0 - 0.13)).abs() < 1e-4 && h.obj == 2, "{}", h.t);
    }
}
