//! A generated 3D logo: extruded, flat-coloured geometric shapes — a frame (a ring, a
//! shield outline or a polygon outline) around a filled plate, and a motif standing out in
//! front of it (a star, stacked chevrons or a cross) — in the x–z plane, read from −y like
//! the text scene. Everything is drawn from a seed: which frame and motif, their
//! proportions, rotation and colours, so different seeds give different logos (the paper
//! hides two Blender-made logos; these stand in for them, and copy nobody's mark).
//!
//! Every piece is a convex prism ([`super::scene::prism`]): curved outlines are polygons
//! of many segments, filled shapes are fans of triangles, outlines bands of trapezoids.

use super::scene::{Material, Object, Scene, hsv, prism};
use ngp::rng::Pcg32;
use std::f32::consts::{PI, TAU};

/// The frame around the plate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Frame {
    /// A circle (48 segments).
    Ring,
    /// A heater shield: flat top, sides curving to a point below.
    Shield,
    /// A regular polygon of `n` sides (6 or 8), a flat side on top.
    Polygon(u32),
}

/// The motif in front of the plate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Motif {
    /// `points` points, inner radius `inner` × the outer one.
    Star { points: u32, inner: f32 },
    /// `n` chevrons pointing up, stacked.
    Chevrons { n: u32 },
    /// A plus sign, turned by 45° when `diagonal` (a saltire).
    Cross { diagonal: bool },
}

/// Everything the seed decides.
#[derive(Clone, Debug, PartialEq)]
pub struct Logo {
    pub frame: Frame,
    pub motif: Motif,
    /// Hue (0–1) of the frame; the motif and plate take hues at fixed offsets from it.
    pub hue: f32,
    /// Turn of the motif, radians (stars only: the other motifs stay upright).
    pub turn: f32,
    /// Width of the frame's band, as a fraction of its radius.
    pub band: f32,
}

/// Outer radius of the frame (the logo spans about ±1 m, like the text).
const RADIUS: f32 = 1.0;
/// Depths along y (−y faces the front cameras): the plate is thin and set back, the frame
/// thicker, the motif stands out in front of both.
const PLATE_Y: (f32, f32) = (-0.04, 0.12);
const FRAME_Y: (f32, f32) = (-0.14, 0.16);
const MOTIF_Y: (f32, f32) = (-0.3, 0.08);

impl Logo {
    /// The logo of a seed (deterministic).
    pub fn from_seed(seed: u64) -> Logo {
        let mut rng = Pcg32::new(seed, 0x10_60);
        let frame = match rng.below(4) {
            0 => Frame::Ring,
            1 => Frame::Shield,
            2 => Frame::Polygon(6),
            _ => Frame::Polygon(8),
        };
        let motif = match rng.below(4) {
            0 | 1 => Motif::Star {
                points: 5 + rng.below(4),
                inner: 0.4 + 0.15 * rng.next_f32(),
            },
            2 => Motif::Chevrons {
                n: 2 + rng.below(2),
            },
            _ => Motif::Cross {
                diagonal: rng.below(2) == 1,
            },
        };
        let hue = rng.next_f32();
        let turn = (rng.next_f32() - 0.5) * 0.4;
        let band = 0.13 + 0.07 * rng.next_f32();
        Logo {
            frame,
            motif,
            hue,
            turn,
            band,
        }
    }

    /// A short description, e.g. `ring + 6-point star`.
    pub fn describe(&self) -> String {
        let frame = match self.frame {
            Frame::Ring => "ring".to_string(),
            Frame::Shield => "shield".to_string(),
            Frame::Polygon(n) => format!("{n}-gon"),
        };
        let motif = match self.motif {
            Motif::Star { points, .. } => format!("{points}-point star"),
            Motif::Chevrons { n } => format!("{n} chevrons"),
            Motif::Cross { diagonal: false } => "cross".to_string(),
            Motif::Cross { diagonal: true } => "saltire".to_string(),
        };
        format!("{frame} + {motif}")
    }

    /// The frame's outline, counter-clockwise in (x, z), centred on the origin.
    fn outline(&self) -> Vec<[f32; 2]> {
        match self.frame {
            Frame::Ring => (0..48)
                .map(|i| {
                    let a = i as f32 / 48.0 * TAU;
                    [RADIUS * a.cos(), RADIUS * a.sin()]
                })
                .collect(),
            Frame::Polygon(n) => (0..n)
                .map(|i| {
                    // A flat side on top: vertices at half a step from the vertical.
                    let a = PI / 2.0 + PI / n as f32 + i as f32 / n as f32 * TAU;
                    [RADIUS * a.cos(), RADIUS * a.sin()]
                })
                .collect(),
            Frame::Shield => {
                // Flat top at z = 0.85, straight sides down to z = 0.1, then arcs (as
                // segments) meeting at the point (0, −1).
                let (w, top, knee) = (0.82 * RADIUS, 0.85 * RADIUS, 0.1 * RADIUS);
                let mut p = vec![[-w, top], [-w, knee]];
                let n = 8;
                for i in 1..n {
                    // A quadratic curve from (−w, knee) through control (−w, −0.55) to the
                    // point: convex, so the outline stays convex.
                    let t = i as f32 / n as f32;
                    let (a, b, c) = ([-w, knee], [-w, -0.55 * RADIUS], [0.0, -RADIUS]);
                    let q = |k: usize| {
                        (1.0 - t).powi(2) * a[k] + 2.0 * t * (1.0 - t) * b[k] + t * t * c[k]
                    };
                    p.push([q(0), q(1)]);
                }
                p.push([0.0, -RADIUS]);
                let right: Vec<[f32; 2]> = p.iter().rev().skip(1).map(|q| [-q[0], q[1]]).collect();
                p.extend(right);
                p
            }
        }
    }

    /// The logo's pieces.
    pub fn objects(&self) -> Vec<Object> {
        let outline = self.outline();
        let frame_colour = hsv(self.hue, 0.75, 0.85);
        let plate_colour = hsv(self.hue + 0.08, 0.25, 0.97);
        let motif_colour = hsv(self.hue + 0.45, 0.85, 0.9);
        let mut objs = Vec::new();
        let mut add = |pts: [[f32; 2]; 4], y: (f32, f32), c: [f32; 3], specular: f32| {
            objs.push(Object {
                shape: prism(pts, y.0, y.1),
                material: Material::Solid(c),
                specular,
            });
        };
        let n = outline.len();
        let inner: Vec<[f32; 2]> = outline
            .iter()
            .map(|p| [p[0] * (1.0 - self.band), p[1] * (1.0 - self.band)])
            .collect();
        for i in 0..n {
            let j = (i + 1) % n;
            // The band: a trapezoid per edge between the outline and its inner copy.
            add(
                [outline[i], outline[j], inner[j], inner[i]],
                FRAME_Y,
                frame_colour,
                0.35,
            );
            // The plate: a fan of triangles inside the band.
            add(
                [[0.0, 0.0], inner[i], inner[j], inner[j]],
                PLATE_Y,
                plate_colour,
                0.0,
            );
        }
        // The motif fits in the plate: radius r about a centre nudged up in a shield.
        let r = 0.62 * RADIUS * (1.0 - self.band) / 0.85;
        let cz = if self.frame == Frame::Shield {
            0.08
        } else {
            0.0
        };
        let rot = |p: [f32; 2], a: f32| {
            let (s, c) = a.sin_cos();
            [c * p[0] - s * p[1], s * p[0] + c * p[1] + cz]
        };
        match self.motif {
            Motif::Star { points, inner } => {
                let k = points as f32;
                for i in 0..points {
                    let a = PI / 2.0 + self.turn + i as f32 / k * TAU;
                    let d = PI / k;
                    let at = |ang: f32, rad: f32| rot([rad * ang.cos(), rad * ang.sin()], 0.0);
                    add(
                        [
                            [0.0, cz],
                            at(a - d, r * inner),
                            at(a, r),
                            at(a + d, r * inner),
                        ],
                        MOTIF_Y,
                        motif_colour,
                        0.2,
                    );
                }
            }
            Motif::Chevrons { n } => {
                // Arms from (±w, z) up to (0, z + h), `t` thick (vertically), stacked.
                let (w, h) = (0.8 * r, 0.45 * r);
                let t = 0.28 * r;
                let gap = 0.2 * r;
                let total = h + t + (n - 1) as f32 * (t + gap);
                for k in 0..n {
                    let z = -total / 2.0 + k as f32 * (t + gap) + cz;
                    add(
                        [[-w, z], [0.0, z + h], [0.0, z + h + t], [-w, z + t]],
                        MOTIF_Y,
                        motif_colour,
                        0.2,
                    );
                    add(
                        [[0.0, z + h], [w, z], [w, z + t], [0.0, z + h + t]],
                        MOTIF_Y,
                        motif_colour,
                        0.2,
                    );
                }
            }
            Motif::Cross { diagonal } => {
                let a = if diagonal { PI / 4.0 } else { 0.0 };
                let (l, t) = (0.85 * r, 0.22 * r);
                // The horizontal bar whole, the vertical one in two halves around it.
                add(
                    [
                        rot([-l, -t], a),
                        rot([l, -t], a),
                        rot([l, t], a),
                        rot([-l, t], a),
                    ],
                    MOTIF_Y,
                    motif_colour,
                    0.2,
                );
                for s in [-1.0f32, 1.0] {
                    add(
                        [
                            rot([-t, s * t], a),
                            rot([t, s * t], a),
                            rot([t, s * l], a),
                            rot([-t, s * l], a),
                        ],
                        MOTIF_Y,
                        motif_colour,
                        0.2,
                    );
                }
            }
        }
        objs
    }

    pub fn scene(&self) -> Scene {
        Scene::new(self.objects(), [0.3, -0.6, 0.75])
    }
}

/// The logo scene of a seed.
pub fn logo_scene(seed: u64) -> Scene {
    Logo::from_seed(seed).scene()
}
