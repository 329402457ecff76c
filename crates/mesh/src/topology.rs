//! What a mesh's edges say about its surface: closed or not, consistently oriented or not,
//! its Euler characteristic (2 for a sphere, 0 for a torus), and its connected pieces, each
//! a surface of its own whose characteristic says its genus.

use super::Mesh;
use std::collections::HashMap;

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct EdgeReport {
    pub edges: usize,
    /// Edges of one triangle only: holes and cracks.
    pub boundary: usize,
    /// Edges of more than two triangles.
    pub non_manifold: usize,
    /// Edges whose two triangles run them the same way: the orientation flips there.
    pub flipped: usize,
}

impl EdgeReport {
    /// Every edge between two triangles that run it in opposite directions.
    pub fn closed_and_oriented(&self) -> bool {
        self.boundary == 0 && self.non_manifold == 0 && self.flipped == 0
    }
}

pub fn edges(mesh: &Mesh) -> EdgeReport {
    // Per undirected edge: how often it runs low → high and high → low.
    let mut runs: HashMap<(u32, u32), (u32, u32)> =
        HashMap::with_capacity(mesh.triangles.len() * 2);
    for t in &mesh.triangles {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            let e = runs.entry((a.min(b), a.max(b))).or_default();
            if a < b {
                e.0 += 1;
            } else {
                e.1 += 1;
            }
        }
    }
    let mut r = EdgeReport {
        edges: runs.len(),
        ..Default::default()
    };
    for &(up, down) in runs.values() {
        match up + down {
            1 => r.boundary += 1,
            2 if up != 1 => r.flipped += 1,
            2 => {}
            _ => r.non_manifold += 1,
        }
    }
    r
}

/// V − E + F over the vertices that triangles use.
pub fn euler_characteristic(mesh: &Mesh) -> i64 {
    let mut used = vec![false; mesh.positions.len()];
    for t in &mesh.triangles {
        for &v in t {
            used[v as usize] = true;
        }
    }
    let v = used.iter().filter(|&&u| u).count() as i64;
    v - edges(mesh).edges as i64 + mesh.triangles.len() as i64
}

/// Six times the signed volume the triangles enclose: positive when they face outwards.
pub fn signed_volume(mesh: &Mesh) -> f64 {
    let mut v = 0.0f64;
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| mesh.positions[i as usize].map(f64::from));
        v += a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
            + a[2] * (b[0] * c[1] - b[1] * c[0]);
    }
    v / 6.0
}

/// The mesh's connected components (triangles joined through shared vertices), each a mesh
/// of its own with the vertices its triangles use (renumbered in their first order, with
/// their normals and colours where the mesh has them), most triangles first. A closed
/// surface's component has χ = 2 − 2 × genus ([`euler_characteristic`]).
pub fn components(mesh: &Mesh) -> Vec<Mesh> {
    // Union–find over the vertices, by the triangles' edges.
    let mut parent: Vec<u32> = (0..mesh.positions.len() as u32).collect();
    fn root(parent: &mut [u32], mut v: u32) -> u32 {
        while parent[v as usize] != v {
            let up = parent[parent[v as usize] as usize];
            parent[v as usize] = up;
            v = up;
        }
        v
    }
    for t in &mesh.triangles {
        for k in 1..3 {
            let (a, b) = (root(&mut parent, t[0]), root(&mut parent, t[k]));
            if a != b {
                parent[a.max(b) as usize] = a.min(b);
            }
        }
    }
    // One mesh a root, in the order of the triangles; each vertex's new index in its mesh.
    let mut piece_of_root: HashMap<u32, usize> = HashMap::new();
    let mut new_index = vec![u32::MAX; mesh.positions.len()];
    let mut pieces: Vec<Mesh> = Vec::new();
    for t in &mesh.triangles {
        let r = root(&mut parent, t[0]);
        let i = *piece_of_root.entry(r).or_insert_with(|| {
            pieces.push(Mesh::default());
            pieces.len() - 1
        });
        let piece = &mut pieces[i];
        let tri = t.map(|v| {
            let v = v as usize;
            if new_index[v] == u32::MAX {
                new_index[v] = piece.positions.len() as u32;
                piece.positions.push(mesh.positions[v]);
                if let Some(n) = mesh.normals.get(v) {
                    piece.normals.push(*n);
                }
                if let Some(c) = mesh.colours.get(v) {
                    piece.colours.push(*c);
                }
            }
            new_index[v]
        });
        piece.triangles.push(tri);
    }
    pieces.sort_by_key(|p| std::cmp::Reverse(p.triangles.len()));
    pieces
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tetrahedron(offset: f32) -> Mesh {
        Mesh {
            positions: vec![
                [offset, 0.0, 0.0],
                [offset + 1.0, 0.0, 0.0],
                [offset, 1.0, 0.0],
                [offset, 0.0, 1.0],
            ],
            // Outward: each face counter-clockwise seen from outside.
            triangles: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
            ..Default::default()
        }
    }

    /// A torus of `n` × `m` quads (two triangles each) around the z axis: V = nm,
    /// E = 3nm, F = 2nm, so χ = 0.
    fn torus(n: usize, m: usize) -> Mesh {
        let mut mesh = Mesh::default();
        for i in 0..n {
            let a = i as f32 / n as f32 * std::f32::consts::TAU;
            for j in 0..m {
                let b = j as f32 / m as f32 * std::f32::consts::TAU;
                let rho = 1.0 + 0.3 * b.cos();
                mesh.positions
                    .push([rho * a.cos(), rho * a.sin(), 0.3 * b.sin()]);
            }
        }
        let at = |i: usize, j: usize| ((i % n) * m + j % m) as u32;
        for i in 0..n {
            for j in 0..m {
                let (p, q, r, s) = (at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1));
                mesh.triangles.push([p, q, r]);
                mesh.triangles.push([p, r, s]);
            }
        }
        mesh
    }

    #[test]
    fn a_tetrahedron_is_a_sphere_and_a_quad_torus_has_genus_one() {
        let t = tetrahedron(0.0);
        assert!(edges(&t).closed_and_oriented());
        assert_eq!(euler_characteristic(&t), 2);
        assert!(signed_volume(&t) > 0.0);
        let r = torus(6, 4);
        let e = edges(&r);
        assert!(e.closed_and_oriented(), "{e:?}");
        assert_eq!(
            (r.positions.len(), e.edges, r.triangles.len()),
            (24, 72, 48)
        );
        assert_eq!(euler_characteristic(&r), 0);
        // Open the torus along one ring of quads: a cylinder (χ = 0 still) with two
        // boundary circles of 4 edges each.
        let mut open = r.clone();
        open.triangles.truncate(2 * 5 * 4);
        assert_eq!(edges(&open).boundary, 8);
    }

    #[test]
    fn components_split_a_mesh_by_shared_vertices_largest_first() {
        // A tetrahedron (4 triangles), then a torus (48), then an unused vertex, then
        // another tetrahedron: three components, the torus first, the unused vertex in none.
        let mut m = tetrahedron(-5.0);
        let r = torus(6, 4);
        let base = m.positions.len() as u32;
        m.positions.extend(&r.positions);
        m.triangles
            .extend(r.triangles.iter().map(|t| t.map(|v| v + base)));
        m.positions.push([9.0, 9.0, 9.0]);
        let last = tetrahedron(5.0);
        let base = m.positions.len() as u32;
        m.positions.extend(&last.positions);
        m.triangles
            .extend(last.triangles.iter().map(|t| t.map(|v| v + base)));
        m.normals = m.positions.iter().map(|p| [p[0], 0.0, 0.0]).collect();
        let pieces = components(&m);
        assert_eq!(pieces.len(), 3);
        assert_eq!(
            pieces.iter().map(|p| p.triangles.len()).collect::<Vec<_>>(),
            [48, 4, 4]
        );
        assert_eq!(
            pieces.iter().map(euler_characteristic).collect::<Vec<_>>(),
            [0, 2, 2]
        );
        // Each keeps its own vertices, normals alongside, oriented as before.
        assert_eq!(pieces[0].positions.len(), 24);
        assert!(pieces.iter().all(|p| p.normals.len() == p.positions.len()));
        assert!(pieces.iter().all(|p| edges(p).closed_and_oriented()));
        assert_eq!(pieces[1].positions[0][0], -5.0);
        assert_eq!(pieces[2].positions[0][0], 5.0);
        assert!(pieces.iter().all(|p| {
            p.normals
                .iter()
                .zip(&p.positions)
                .all(|(n, q)| n[0] == q[0])
        }));
        // A mesh of no triangle has no component.
        assert!(components(&Mesh::default()).is_empty());
    }
}
