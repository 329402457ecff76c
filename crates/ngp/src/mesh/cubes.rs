//! Marching cubes over a lattice fed one layer at a time, so that only two layers of
//! densities and their edges' vertex numbers are held however fine the lattice: each edge
//! that crosses the threshold gets one vertex, shared by every cell around it (welded),
//! placed by linear interpolation as instant-ngp's `gen_vertices` places it.

use super::Mesh;
use super::table::{edge_corners, sub, table};

/// No vertex on this edge.
const NONE: u32 = u32::MAX;

/// A lattice being meshed layer by layer (z ascending); lattice point `(x, y, z)` lies at
/// `origin + (x, y, z) · step`.
pub struct Cubes {
    nx: usize,
    ny: usize,
    threshold: f32,
    origin: [f32; 3],
    step: [f32; 3],
    max_triangles: usize,
    /// Layers pushed so far.
    layers: usize,
    prev: Vec<f32>,
    /// Vertex numbers of the x and y edges of the previous layer (`lo`) and the new one.
    lo_x: Vec<u32>,
    lo_y: Vec<u32>,
    hi_x: Vec<u32>,
    hi_y: Vec<u32>,
    /// Vertex numbers of the z edges between the two.
    z_edges: Vec<u32>,
    mesh: Mesh,
}

/// The mesh passed its triangle cap.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TooManyTriangles {
    pub cap: usize,
    /// Layers meshed when it did.
    pub layers: usize,
}

impl Cubes {
    pub fn new(
        nx: usize,
        ny: usize,
        threshold: f32,
        origin: [f32; 3],
        step: [f32; 3],
        max_triangles: usize,
    ) -> Self {
        let n = nx * ny;
        Cubes {
            nx,
            ny,
            threshold,
            origin,
            step,
            max_triangles,
            layers: 0,
            prev: vec![0.0; n],
            lo_x: vec![NONE; n],
            lo_y: vec![NONE; n],
            hi_x: vec![NONE; n],
            hi_y: vec![NONE; n],
            z_edges: vec![NONE; n],
            mesh: Mesh::default(),
        }
    }

    /// Bytes this holds for a lattice of `nx × ny` points a layer (the mesh aside).
    pub fn working_bytes(nx: usize, ny: usize) -> u64 {
        (nx * ny) as u64 * 4 * 6
    }

    /// Meshes the cells between the last layer and `layer` (`nx · ny` densities, x fastest).
    pub fn push_layer(&mut self, layer: &[f32]) -> Result<(), TooManyTriangles> {
        assert_eq!(layer.len(), self.nx * self.ny, "a layer of the lattice");
        let z = self.layers as f32;
        if self.layers == 0 {
            let (mut xs, mut ys) = (
                std::mem::take(&mut self.lo_x),
                std::mem::take(&mut self.lo_y),
            );
            self.layer_vertices(layer, z, &mut xs, &mut ys);
            (self.lo_x, self.lo_y) = (xs, ys);
        } else {
            let (mut xs, mut ys) = (
                std::mem::take(&mut self.hi_x),
                std::mem::take(&mut self.hi_y),
            );
            self.layer_vertices(layer, z, &mut xs, &mut ys);
            (self.hi_x, self.hi_y) = (xs, ys);
            self.z_vertices(layer, z - 1.0);
            self.cells(layer);
            std::mem::swap(&mut self.lo_x, &mut self.hi_x);
            std::mem::swap(&mut self.lo_y, &mut self.hi_y);
        }
        self.prev.copy_from_slice(layer);
        self.layers += 1;
        if self.mesh.triangles.len() > self.max_triangles {
            return Err(TooManyTriangles {
                cap: self.max_triangles,
                layers: self.layers,
            });
        }
        Ok(())
    }

    /// The mesh, its vertex normals the area-weighted mean of their triangles' normals
    /// (instant-ngp's), unit length.
    pub fn finish(mut self) -> Mesh {
        for n in &mut self.mesh.normals {
            let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            if l > 0.0 {
                *n = [n[0] / l, n[1] / l, n[2] / l];
            }
        }
        self.mesh
    }

    /// Where the threshold crosses between lattice values `f0` (at `a`) and `f1` (one step
    /// along `axis`).
    fn vertex(&mut self, a: [f32; 3], axis: usize, f0: f32, f1: f32) -> u32 {
        // Kept a thousandth of a cell off the lattice point: a masked neighbour (−10000)
        // puts the crossing a few millionths of a cell from it, where the vertices of two
        // edges from that point would round to one position and make a degenerate
        // triangle (which assimp, say, turns into a line).
        let t = (self.threshold - f0) / (f1 - f0);
        let t = if t.is_nan() {
            0.5
        } else {
            t.clamp(1e-3, 1.0 - 1e-3)
        };
        let mut p = [0.0; 3];
        for d in 0..3 {
            let c = if d == axis { a[d] + t } else { a[d] };
            p[d] = self.origin[d] + c * self.step[d];
        }
        let id = self.mesh.positions.len() as u32;
        self.mesh.positions.push(p);
        self.mesh.normals.push([0.0; 3]);
        id
    }

    fn layer_vertices(&mut self, layer: &[f32], z: f32, xs: &mut [u32], ys: &mut [u32]) {
        let (nx, ny, thr) = (self.nx, self.ny, self.threshold);
        xs.fill(NONE);
        ys.fill(NONE);
        for y in 0..ny {
            for x in 0..nx {
                let i = x + nx * y;
                let f0 = layer[i];
                let inside = f0 > thr;
                if x + 1 < nx && (layer[i + 1] > thr) != inside {
                    xs[i] = self.vertex([x as f32, y as f32, z], 0, f0, layer[i + 1]);
                }
                if y + 1 < ny && (layer[i + nx] > thr) != inside {
                    ys[i] = self.vertex([x as f32, y as f32, z], 1, f0, layer[i + nx]);
                }
            }
        }
    }

    fn z_vertices(&mut self, layer: &[f32], z: f32) {
        let thr = self.threshold;
        let mut zs = std::mem::take(&mut self.z_edges);
        zs.fill(NONE);
        for i in 0..self.nx * self.ny {
            let (f0, f1) = (self.prev[i], layer[i]);
            if (f0 > thr) != (f1 > thr) {
                let (x, y) = (i % self.nx, i / self.nx);
                zs[i] = self.vertex([x as f32, y as f32, z], 2, f0, f1);
            }
        }
        self.z_edges = zs;
    }

    /// The vertex of edge `e` of the cell at `(x, y)` of the current slice.
    #[inline]
    fn edge_vertex(&self, e: usize, x: usize, y: usize) -> u32 {
        let (c, _) = edge_corners(e);
        let (ox, oy, oz) = (c & 1, (c >> 1) & 1, (c >> 2) & 1);
        let i = (x + ox) + self.nx * (y + oy);
        match (e / 4, oz) {
            (0, 0) => self.lo_x[i],
            (0, _) => self.hi_x[i],
            (1, 0) => self.lo_y[i],
            (1, _) => self.hi_y[i],
            _ => self.z_edges[i],
        }
    }

    fn cells(&mut self, layer: &[f32]) {
        let (nx, ny, thr) = (self.nx, self.ny, self.threshold);
        let tab = table();
        for y in 0..ny.saturating_sub(1) {
            for x in 0..nx.saturating_sub(1) {
                let i = x + nx * y;
                let corners = [
                    self.prev[i],
                    self.prev[i + 1],
                    self.prev[i + nx],
                    self.prev[i + nx + 1],
                    layer[i],
                    layer[i + 1],
                    layer[i + nx],
                    layer[i + nx + 1],
                ];
                let mut case = 0usize;
                for (c, &f) in corners.iter().enumerate() {
                    if f > thr {
                        case |= 1 << c;
                    }
                }
                for tri in &tab.triangles[case] {
                    let ids = tri.map(|e| self.edge_vertex(e as usize, x, y));
                    debug_assert!(ids.iter().all(|&v| v != NONE), "a crossing edge's vertex");
                    self.triangle(ids);
                }
            }
        }
    }

    fn triangle(&mut self, ids: [u32; 3]) {
        let p = ids.map(|i| self.mesh.positions[i as usize]);
        let (u, v) = (sub(p[1], p[0]), sub(p[2], p[0]));
        let n = [
            u[1] * v[2] - u[2] * v[1],
            u[2] * v[0] - u[0] * v[2],
            u[0] * v[1] - u[1] * v[0],
        ];
        for i in ids {
            let a = &mut self.mesh.normals[i as usize];
            for d in 0..3 {
                a[d] += n[d];
            }
        }
        self.mesh.triangles.push(ids);
    }
}
