//! The marching-cubes case table, derived here from the cube's geometry instead of copied:
//! for each of the 256 inside/outside patterns of a cell's corners, the triangles that
//! separate them, every triangle wound counter-clockwise seen from the empty side (its
//! normal points out of the surface).
//!
//! Each face of the cell decides its own segments from its four corners alone (an
//! ambiguous face, two diagonal corners inside, cuts each inside corner off on its own), so
//! two cells that share a face draw the same segments there, run in opposite directions:
//! the mesh has no cracks and one orientation. The segments of a cell chain into closed
//! loops, each fanned into triangles.

use ngp::geometry::{cross, dot, sub};
use std::sync::OnceLock;

/// Corner `c` of a cell sits at offset `(c & 1, c >> 1 & 1, c >> 2 & 1)`.
pub fn corner_offset(c: usize) -> [usize; 3] {
    [c & 1, (c >> 1) & 1, (c >> 2) & 1]
}

/// Edge `axis * 4 + k` runs along `axis` from the corner with that coordinate 0; `k` holds
/// the other two coordinates (the lower axis in bit 0).
pub fn edge_corners(e: usize) -> (usize, usize) {
    let axis = e / 4;
    let k = e % 4;
    let (u, v) = others(axis);
    let base = ((k & 1) << u) | (((k >> 1) & 1) << v);
    (base, base | (1 << axis))
}

/// The two axes other than `axis`, lower first.
fn others(axis: usize) -> (usize, usize) {
    match axis {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    }
}

/// The edge between two corners that differ in one coordinate.
fn edge_between(a: usize, b: usize) -> usize {
    let axis = (a ^ b).trailing_zeros() as usize;
    let lo = a & b;
    let (u, v) = others(axis);
    axis * 4 + ((lo >> u) & 1) + (((lo >> v) & 1) << 1)
}

/// The triangles of every case: `TRIANGLES[case]` lists edge triples, `case` having bit `c`
/// set where corner `c` is inside (denser than the threshold).
pub struct Table {
    pub triangles: Vec<Vec<[u8; 3]>>,
}

pub fn table() -> &'static Table {
    static TABLE: OnceLock<Table> = OnceLock::new();
    TABLE.get_or_init(|| Table {
        triangles: (0..256).map(case_triangles).collect(),
    })
}

type V = [f32; 3];

fn corner_pos(c: usize) -> V {
    let o = corner_offset(c);
    [o[0] as f32, o[1] as f32, o[2] as f32]
}

fn mean(cs: &[usize]) -> V {
    let mut m = [0.0; 3];
    for &c in cs {
        let p = corner_pos(c);
        for d in 0..3 {
            m[d] += p[d] / cs.len() as f32;
        }
    }
    m
}

fn edge_mid(e: usize) -> V {
    let (a, b) = edge_corners(e);
    let (pa, pb) = (corner_pos(a), corner_pos(b));
    [
        0.5 * (pa[0] + pb[0]),
        0.5 * (pa[1] + pb[1]),
        0.5 * (pa[2] + pb[2]),
    ]
}

/// The segment from edge `p` to edge `q` of a face with outward normal `n_face`, directed
/// so that the empty side (`to_empty`, in the face) lies on its left seen from outside the
/// cell: then the loops run counter-clockwise around the surface's outward normal.
fn directed(p: usize, q: usize, to_empty: V, n_face: V) -> (usize, usize) {
    let t = cross(to_empty, n_face);
    if dot(sub(edge_mid(q), edge_mid(p)), t) > 0.0 {
        (p, q)
    } else {
        (q, p)
    }
}

/// The directed segments of `case` on the six faces.
fn segments(case: usize) -> Vec<(usize, usize)> {
    let inside = |c: usize| case >> c & 1 == 1;
    let mut segs = Vec::new();
    for axis in 0..3 {
        let (u, v) = others(axis);
        for side in 0..2 {
            // The face's corners in a cycle.
            let q: Vec<usize> = [(0, 0), (1, 0), (1, 1), (0, 1)]
                .iter()
                .map(|&(a, b)| (side << axis) | (a << u) | (b << v))
                .collect();
            let mut n_face = [0.0; 3];
            n_face[axis] = if side == 1 { 1.0 } else { -1.0 };
            let ins: Vec<bool> = q.iter().map(|&c| inside(c)).collect();
            let n_in = ins.iter().filter(|&&b| b).count();
            if n_in == 0 || n_in == 4 {
                continue;
            }
            let edge = |i: usize| edge_between(q[i % 4], q[(i + 1) % 4]);
            if n_in == 2 && ins[0] == ins[2] {
                // Ambiguous: cut each inside corner off on its own.
                let centre = mean(&q);
                for i in (0..4).filter(|&i| ins[i]) {
                    let to_empty = sub(centre, corner_pos(q[i]));
                    segs.push(directed(edge(i + 3), edge(i), to_empty, n_face));
                }
            } else {
                let crossing: Vec<usize> = (0..4).filter(|&i| ins[i] != ins[(i + 1) % 4]).collect();
                let (cin, cout): (Vec<usize>, Vec<usize>) = q.iter().partition(|&&c| inside(c));
                let to_empty = sub(mean(&cout), mean(&cin));
                segs.push(directed(
                    edge(crossing[0]),
                    edge(crossing[1]),
                    to_empty,
                    n_face,
                ));
            }
        }
    }
    segs
}

/// The triangles of one case: its segments chained into loops, each loop fanned.
fn case_triangles(case: usize) -> Vec<[u8; 3]> {
    let mut next = [usize::MAX; 12];
    for (p, q) in segments(case) {
        assert_eq!(next[p], usize::MAX, "case {case}: edge {p} leaves twice");
        next[p] = q;
    }
    let mut seen = [false; 12];
    let mut tris = Vec::new();
    for start in 0..12 {
        if next[start] == usize::MAX || seen[start] {
            continue;
        }
        let mut lp = Vec::new();
        let mut e = start;
        while !seen[e] {
            seen[e] = true;
            lp.push(e);
            e = next[e];
            assert_ne!(e, usize::MAX, "case {case}: an open loop");
        }
        assert_eq!(e, start, "case {case}: loops cross");
        let loop_tris = triangulate(&lp).unwrap_or_else(|| panic!("case {case}: no triangulation"));
        tris.extend(loop_tris.iter().map(|t| t.map(|e| e as u8)));
    }
    tris
}

/// The two faces of the cell that edge `e` lies on, as (axis, side).
fn faces_of(e: usize) -> [(usize, usize); 2] {
    let (c, _) = edge_corners(e);
    let (u, v) = others(e / 4);
    [(u, (c >> u) & 1), (v, (c >> v) & 1)]
}

fn share_a_face(a: usize, b: usize) -> bool {
    let (fa, fb) = (faces_of(a), faces_of(b));
    fa.iter().any(|f| fb.contains(f))
}

/// Triangles of a loop (in its order, so they keep its orientation) whose inner edges
/// never join two vertices on one face of the cell: the neighbour across that face could
/// draw the same edge, which would then border four triangles. A fan from the first vertex
/// that allows it, else a split along any allowed diagonal.
fn triangulate(lp: &[usize]) -> Option<Vec<[usize; 3]>> {
    let n = lp.len();
    if n == 3 {
        return Some(vec![[lp[0], lp[1], lp[2]]]);
    }
    for apex in 0..n {
        let ok = (2..n - 1).all(|k| !share_a_face(lp[apex], lp[(apex + k) % n]));
        if ok {
            return Some(
                (1..n - 1)
                    .map(|k| [lp[apex], lp[(apex + k) % n], lp[(apex + k + 1) % n]])
                    .collect(),
            );
        }
    }
    for i in 0..n {
        for k in 2..n - 1 {
            let j = (i + k) % n;
            if share_a_face(lp[i], lp[j]) {
                continue;
            }
            let first: Vec<usize> = (0..=k).map(|m| lp[(i + m) % n]).collect();
            let second: Vec<usize> = (k..=n).map(|m| lp[(i + m) % n]).collect();
            if let (Some(mut a), Some(b)) = (triangulate(&first), triangulate(&second)) {
                a.extend(b);
                return Some(a);
            }
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn edges_join_neighbouring_corners_and_round_trip() {
        for e in 0..12 {
            let (a, b) = edge_corners(e);
            assert_eq!((a ^ b).count_ones(), 1);
            assert_eq!(edge_between(a, b), e);
            assert_eq!(edge_between(b, a), e);
        }
    }

    #[test]
    fn every_case_has_closed_loops_and_its_complement_the_mirror() {
        let t = table();
        assert!(t.triangles[0].is_empty() && t.triangles[255].is_empty());
        for case in 1..255usize {
            let tris = &t.triangles[case];
            assert!(!tris.is_empty(), "case {case}");
            // Every triangle uses crossing edges only.
            for tri in tris {
                for &e in tri {
                    let (a, b) = edge_corners(e as usize);
                    assert_ne!(case >> a & 1, case >> b & 1, "case {case} edge {e}");
                }
            }
            // The complement separates the same corners; its segments on unambiguous faces
            // run the other way, so the two surfaces face opposite directions.
            assert!(!t.triangles[255 - case].is_empty());
        }
        let most = t.triangles.iter().map(Vec::len).max().unwrap();
        assert!(most <= 5, "{most} triangles in one case");
    }

    #[test]
    fn no_inner_edge_lies_on_a_face_of_the_cell() {
        for (case, tris) in table().triangles.iter().enumerate() {
            let mut count = std::collections::HashMap::new();
            for t in tris {
                for k in 0..3 {
                    let (a, b) = (t[k] as usize, t[(k + 1) % 3] as usize);
                    *count.entry((a.min(b), a.max(b))).or_insert(0) += 1;
                }
            }
            for (&(a, b), &c) in &count {
                // An edge of two triangles is inside the cell; it must not lie in a face.
                if c == 2 {
                    assert!(!share_a_face(a, b), "case {case}: edges {a}, {b}");
                }
            }
        }
    }

    #[test]
    fn a_cut_corner_faces_away_from_it() {
        // Corner 0 alone inside: one triangle on edges 0 (x), 4 (y), 8 (z), whose normal
        // points to +(1, 1, 1).
        let tris = &table().triangles[1];
        assert_eq!(tris.len(), 1);
        let p: Vec<V> = tris[0].iter().map(|&e| edge_mid(e as usize)).collect();
        let n = cross(sub(p[1], p[0]), sub(p[2], p[0]));
        assert!(dot(n, [1.0, 1.0, 1.0]) > 0.0, "{n:?}");
        // Corner 0 alone outside: the normal points at it.
        let tris = &table().triangles[254];
        let p: Vec<V> = tris[0].iter().map(|&e| edge_mid(e as usize)).collect();
        let n = cross(sub(p[1], p[0]), sub(p[2], p[0]));
        assert!(dot(n, [1.0, 1.0, 1.0]) < 0.0, "{n:?}");
    }
}
