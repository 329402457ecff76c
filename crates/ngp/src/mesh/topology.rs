//! What a mesh's edges say about its surface: closed or not, consistently oriented or not,
//! and its Euler characteristic (2 for a sphere, 0 for a torus).

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
