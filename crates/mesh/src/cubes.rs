//! Marching cubes over a lattice fed one layer at a time, so that only two layers of
//! densities and their edges' vertex numbers are held however fine the lattice: each edge
//! that crosses the threshold gets one vertex, shared by every cell around it (welded),
//! placed by linear interpolation as instant-ngp's `gen_vertices` places it.
//!
//! A layer's rows are shared among threads in tasks of a few rows. Each task numbers the
//! vertices it finds from 0 and the tasks' numbers are then offset in row order, and the
//! triangles' normals are summed in row order after the tasks, so the mesh is the one a
//! single thread walking the rows makes, bit for bit. A row is skipped where no point of
//! the rows around it lies above the threshold: no edge there can cross it (most rows of a
//! fine lattice, whose points outside occupied cells are masked).

use super::Mesh;
use super::table::{edge_corners, table};
use ngp::geometry::sub;
use rayon::prelude::*;

/// No vertex on this edge.
const NONE: u32 = u32::MAX;

/// Rows of a layer one task takes: a 1024-point row is a few microseconds of work, so
/// eight of them outweigh a task's cost and still leave a layer 128 tasks to share.
const ROWS_PER_TASK: usize = 8;

/// Where the surface lies: the threshold, and the lattice's place in space.
#[derive(Clone, Copy)]
struct Surface {
    threshold: f32,
    origin: [f32; 3],
    step: [f32; 3],
}

impl Surface {
    #[inline]
    fn inside(&self, f: f32) -> bool {
        f > self.threshold
    }

    /// Where the threshold crosses between lattice values `f0` (at `a`) and `f1` (one step
    /// along `axis`).
    #[inline]
    fn crossing(&self, a: [f32; 3], axis: usize, f0: f32, f1: f32) -> [f32; 3] {
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
        p
    }
}

/// A lattice being meshed layer by layer (z ascending); lattice point `(x, y, z)` lies at
/// `origin + (x, y, z) · step`.
pub struct Cubes {
    nx: usize,
    ny: usize,
    surface: Surface,
    max_triangles: usize,
    rows_per_task: usize,
    /// Layers pushed so far.
    layers: usize,
    prev: Vec<f32>,
    /// Whether each row of the previous layer (`prev_hot`) and the new one holds a point
    /// above the threshold.
    prev_hot: Vec<bool>,
    hot: Vec<bool>,
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
            surface: Surface {
                threshold,
                origin,
                step,
            },
            max_triangles,
            rows_per_task: ROWS_PER_TASK,
            layers: 0,
            prev: vec![0.0; n],
            prev_hot: vec![false; ny],
            hot: vec![false; ny],
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
        (nx * ny) as u64 * 4 * 6 + 2 * ny as u64
    }

    /// Meshes the cells between the last layer and `layer` (`nx · ny` densities, x fastest).
    pub fn push_layer(&mut self, layer: &[f32]) -> Result<(), TooManyTriangles> {
        assert_eq!(layer.len(), self.nx * self.ny, "a layer of the lattice");
        let z = self.layers as f32;
        let surface = self.surface;
        self.hot
            .par_iter_mut()
            .zip(layer.par_chunks(self.nx))
            .for_each(|(hot, row)| *hot = row.iter().any(|&f| surface.inside(f)));
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
        std::mem::swap(&mut self.prev_hot, &mut self.hot);
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

    /// Appends the tasks' vertices to the mesh in task order; each task's first number and
    /// count.
    fn add_vertices(&mut self, found: Vec<Vec<[f32; 3]>>) -> Vec<(u32, usize)> {
        let mut firsts = Vec::with_capacity(found.len());
        for part in found {
            firsts.push((self.mesh.positions.len() as u32, part.len()));
            self.mesh
                .normals
                .resize(self.mesh.normals.len() + part.len(), [0.0; 3]);
            self.mesh.positions.extend(part);
        }
        firsts
    }

    /// Vertices on the x and y edges of `layer` (at height `z`), their numbers in `xs`, `ys`.
    fn layer_vertices(&mut self, layer: &[f32], z: f32, xs: &mut [u32], ys: &mut [u32]) {
        let (nx, ny, rows, s, hot) = (
            self.nx,
            self.ny,
            self.rows_per_task,
            self.surface,
            &self.hot,
        );
        let found: Vec<Vec<[f32; 3]>> = xs
            .par_chunks_mut(nx * rows)
            .zip(ys.par_chunks_mut(nx * rows))
            .enumerate()
            .map(|(t, (xs, ys))| {
                xs.fill(NONE);
                ys.fill(NONE);
                let mut found = Vec::new();
                for (r, (xr, yr)) in xs.chunks_mut(nx).zip(ys.chunks_mut(nx)).enumerate() {
                    let y = t * rows + r;
                    let along_x = hot[y];
                    let along_y = y + 1 < ny && (hot[y] || hot[y + 1]);
                    if !along_x && !along_y {
                        continue;
                    }
                    let row = &layer[y * nx..(y + 1) * nx];
                    let next = if along_y {
                        &layer[(y + 1) * nx..(y + 2) * nx]
                    } else {
                        &[][..]
                    };
                    for x in 0..nx {
                        let (f0, a) = (row[x], [x as f32, y as f32, z]);
                        let inside = s.inside(f0);
                        if along_x && x + 1 < nx && s.inside(row[x + 1]) != inside {
                            xr[x] = found.len() as u32;
                            found.push(s.crossing(a, 0, f0, row[x + 1]));
                        }
                        if along_y && s.inside(next[x]) != inside {
                            yr[x] = found.len() as u32;
                            found.push(s.crossing(a, 1, f0, next[x]));
                        }
                    }
                }
                found
            })
            .collect();
        let firsts = self.add_vertices(found);
        renumber(xs, nx * rows, &firsts);
        renumber(ys, nx * rows, &firsts);
    }

    /// Vertices on the z edges between the previous layer (at height `z`) and `layer`.
    fn z_vertices(&mut self, layer: &[f32], z: f32) {
        let mut zs = std::mem::take(&mut self.z_edges);
        let (nx, rows, s) = (self.nx, self.rows_per_task, self.surface);
        let (prev, prev_hot, hot) = (&self.prev, &self.prev_hot, &self.hot);
        let found: Vec<Vec<[f32; 3]>> = zs
            .par_chunks_mut(nx * rows)
            .enumerate()
            .map(|(t, zs)| {
                zs.fill(NONE);
                let mut found = Vec::new();
                for (r, zr) in zs.chunks_mut(nx).enumerate() {
                    let y = t * rows + r;
                    if !(prev_hot[y] || hot[y]) {
                        continue;
                    }
                    let (below, above) =
                        (&prev[y * nx..(y + 1) * nx], &layer[y * nx..(y + 1) * nx]);
                    for x in 0..nx {
                        let (f0, f1) = (below[x], above[x]);
                        if s.inside(f0) != s.inside(f1) {
                            zr[x] = found.len() as u32;
                            found.push(s.crossing([x as f32, y as f32, z], 2, f0, f1));
                        }
                    }
                }
                found
            })
            .collect();
        let firsts = self.add_vertices(found);
        renumber(&mut zs, nx * rows, &firsts);
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

    /// The triangles of the cells between the previous layer and `layer`.
    fn cells(&mut self, layer: &[f32]) {
        let (nx, rows, s) = (self.nx, self.rows_per_task, self.surface);
        let cell_rows = self.ny.saturating_sub(1);
        let tab = table();
        let this = &*self;
        let (p, h) = (&this.prev_hot, &this.hot);
        let found: Vec<Vec<[u32; 3]>> = (0..cell_rows.div_ceil(rows))
            .into_par_iter()
            .map(|t| {
                let mut found = Vec::new();
                for y in t * rows..((t + 1) * rows).min(cell_rows) {
                    if !(p[y] || p[y + 1] || h[y] || h[y + 1]) {
                        continue;
                    }
                    for x in 0..nx.saturating_sub(1) {
                        let i = x + nx * y;
                        let corners = [
                            this.prev[i],
                            this.prev[i + 1],
                            this.prev[i + nx],
                            this.prev[i + nx + 1],
                            layer[i],
                            layer[i + 1],
                            layer[i + nx],
                            layer[i + nx + 1],
                        ];
                        let mut case = 0usize;
                        for (c, &f) in corners.iter().enumerate() {
                            if s.inside(f) {
                                case |= 1 << c;
                            }
                        }
                        for tri in &tab.triangles[case] {
                            let ids = tri.map(|e| this.edge_vertex(e as usize, x, y));
                            debug_assert!(
                                ids.iter().all(|&v| v != NONE),
                                "a crossing edge's vertex"
                            );
                            found.push(ids);
                        }
                    }
                }
                found
            })
            .collect();
        for ids in found.into_iter().flatten() {
            self.triangle(ids);
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

/// Turns each task's vertex numbers (from 0, in `chunk` entries of `ids` a task) into the
/// mesh's, `firsts` being each task's first number and count.
fn renumber(ids: &mut [u32], chunk: usize, firsts: &[(u32, usize)]) {
    ids.par_chunks_mut(chunk)
        .zip(firsts)
        .filter(|&(_, &(first, count))| first != 0 && count != 0)
        .for_each(|(ids, &(first, _))| {
            for v in ids.iter_mut().filter(|v| **v != NONE) {
                *v += first;
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::topology::{edges, euler_characteristic};

    /// Two balls, one of them cut by a masked slab, in a lattice whose sides are not
    /// multiples of a task's rows; the outermost points masked, as the lattice masks them.
    fn field(n: [usize; 3]) -> impl Fn(usize, usize, usize) -> f32 {
        move |x, y, z| {
            if x == 0 || y == 0 || z == 0 || x + 1 == n[0] || y + 1 == n[1] || z + 1 == n[2] {
                return -10000.0;
            }
            if (20..23).contains(&y) && x > 25 {
                return -10000.0;
            }
            let ball = |c: [f32; 3], r: f32| {
                let d = [x as f32 - c[0], y as f32 - c[1], z as f32 - c[2]];
                10.0 * (r - (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()) / r + 2.5
            };
            ball([12.0, 11.0, 13.0], 7.3).max(ball([31.0, 24.0, 16.0], 6.1))
        }
    }

    fn mesh_of(n: [usize; 3], rows_per_task: usize) -> Mesh {
        let f = field(n);
        let mut cubes = Cubes::new(n[0], n[1], 2.5, [0.0; 3], [1.0; 3], usize::MAX);
        cubes.rows_per_task = rows_per_task;
        for z in 0..n[2] {
            let layer: Vec<f32> = (0..n[0] * n[1]).map(|i| f(i % n[0], i / n[0], z)).collect();
            cubes.push_layer(&layer).unwrap();
        }
        cubes.finish()
    }

    #[test]
    fn tasks_do_not_change_the_mesh() {
        let n = [41, 37, 30];
        // One task a layer is the single thread's walk over the rows.
        let single = mesh_of(n, n[1]);
        assert!(single.triangles.len() > 500);
        for rows in [1, 3, ROWS_PER_TASK] {
            assert_eq!(mesh_of(n, rows), single, "tasks of {rows} rows");
        }
    }

    #[test]
    fn every_crossing_edge_has_one_vertex_with_empty_rows_skipped() {
        let n = [41, 37, 30];
        let f = field(n);
        let inside = |x, y, z| f(x, y, z) > 2.5;
        let mut crossings = 0;
        for z in 0..n[2] {
            for y in 0..n[1] {
                for x in 0..n[0] {
                    let here = inside(x, y, z);
                    crossings += usize::from(x + 1 < n[0] && inside(x + 1, y, z) != here)
                        + usize::from(y + 1 < n[1] && inside(x, y + 1, z) != here)
                        + usize::from(z + 1 < n[2] && inside(x, y, z + 1) != here);
                }
            }
        }
        let m = mesh_of(n, ROWS_PER_TASK);
        assert_eq!(m.positions.len(), crossings);
        assert!(edges(&m).closed_and_oriented());
        // Two balls, the second cut in two by the masked slab: three closed pieces.
        assert_eq!(euler_characteristic(&m), 6);
    }
}
