//! The lattice a mesh is sampled on, and the march over it in slabs of layers: a slab's
//! positions go to the density function together (one large batch for any device), then its
//! layers go through the cubes one by one, so that memory holds one slab and two layers
//! however fine the lattice.

use super::Mesh;
use super::cubes::{Cubes, TooManyTriangles};
use ngp::error::{Error, Result};
use ngp::occupancy::{
    GRID_SIZE, MIN_OPTICAL_THICKNESS, N_CELLS, OccupancyGrid, cell_along, mip_from_distance,
    mip_from_pos, morton3d, morton3d_invert, pow2,
};
use rayon::prelude::*;

/// What instant-ngp's `grid_samples_half_to_float` gives a lattice point whose occupancy
/// cell holds less than the minimum optical thickness: no surface there.
pub const MASKED: f32 = -10000.0;

/// Lattice points a slab evaluates at most (positions 24 MiB, densities 8 MiB).
pub const SLAB_POINTS: usize = 1 << 21;

/// Points along each axis of a box of ngp space, sampled at both ends.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lattice {
    pub min: [f32; 3],
    pub max: [f32; 3],
    pub res: [usize; 3],
}

impl Lattice {
    /// `resolution` points along the box's longest side and the others in proportion,
    /// each rounded up to a multiple of 16 (instant-ngp's `get_marching_cubes_res`, at
    /// least 16).
    pub fn new(min: [f32; 3], max: [f32; 3], resolution: u32) -> Result<Self> {
        let side = [max[0] - min[0], max[1] - min[1], max[2] - min[2]];
        if !side.iter().all(|&s| s.is_finite() && s > 0.0) {
            return Err(Error::Config(format!(
                "the box {min:?}–{max:?} is empty: every side must be longer than 0"
            )));
        }
        if resolution < 2 {
            return Err(Error::Config(format!(
                "resolution {resolution}: at least 2 points a side"
            )));
        }
        let longest = side.iter().cloned().fold(0.0f32, f32::max);
        let scale = resolution as f32 / longest;
        let res = side.map(|s| (((s * scale + 0.5) as usize).max(1)).next_multiple_of(16));
        Ok(Lattice { min, max, res })
    }

    pub fn points(&self) -> u64 {
        self.res.iter().map(|&r| r as u64).product()
    }

    /// The distance between neighbouring points along each axis.
    pub fn step(&self) -> [f32; 3] {
        [0, 1, 2].map(|d| (self.max[d] - self.min[d]) / (self.res[d] - 1) as f32)
    }

    /// The ngp-space coordinates of the points along each axis: point `(x, y, z)` lies at
    /// `(c[0][x], c[1][y], c[2][z])`.
    pub fn coordinates(&self) -> [Vec<f32>; 3] {
        let s = self.step();
        [0, 1, 2].map(|d| {
            (0..self.res[d])
                .map(|i| self.min[d] + i as f32 * s[d])
                .collect()
        })
    }

    /// Layers a slab of `points` holds (at least one).
    pub fn slab_layers(&self, points: usize) -> usize {
        (points / (self.res[0] * self.res[1])).clamp(1, self.res[2])
    }

    /// Bytes the march holds besides the mesh: a slab's positions, densities and values,
    /// and the cubes' two layers.
    pub fn working_bytes(&self) -> u64 {
        let layer = (self.res[0] * self.res[1]) as u64;
        let slab = layer * self.slab_layers(SLAB_POINTS) as u64;
        slab * (12 + 4 + 4 + 4) + Cubes::working_bytes(self.res[0], self.res[1])
    }
}

/// The part of the model's box whose occupancy cells hold at least the minimum optical
/// thickness (the cells [`march`] samples), grown by one cell each way so that the
/// lattice's outermost points fall in empty cells and a closed surface stays closed;
/// `None` when no cell does. Each cascade counts only where it is the one read (outside
/// the next finer one).
pub fn occupied_box(grid: &OccupancyGrid) -> Option<([f32; 3], [f32; 3])> {
    occupied_box_within(grid, grid.max_cascade())
}

/// [`occupied_box`] of cascades `0..=cascade` only, within cascade `cascade`'s cube (a
/// capture's object without the background that fills the outer cascades).
pub fn occupied_box_within(grid: &OccupancyGrid, cascade: u32) -> Option<([f32; 3], [f32; 3])> {
    let max_cascade = grid.max_cascade();
    let last = cascade.min(max_cascade) as usize;
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for c in 0..=last {
        let s = (c as f32).exp2();
        let cell = s / GRID_SIZE as f32;
        let cells = &grid.density[c * N_CELLS..(c + 1) * N_CELLS];
        for (m, _) in cells
            .iter()
            .enumerate()
            .filter(|&(_, &d)| d >= MIN_OPTICAL_THICKNESS)
        {
            let m = m as u32;
            let ijk = [
                morton3d_invert(m),
                morton3d_invert(m >> 1),
                morton3d_invert(m >> 2),
            ];
            let corner = ijk.map(|i| (i as f32 / GRID_SIZE as f32 - 0.5) * s + 0.5);
            let centre = corner.map(|v| v + 0.5 * cell);
            if mip_from_pos(centre, max_cascade) != c as u32 {
                continue;
            }
            for d in 0..3 {
                lo[d] = lo[d].min(corner[d] - cell);
                hi[d] = hi[d].max(corner[d] + 2.0 * cell);
            }
        }
    }
    if lo[0] > hi[0] {
        return None;
    }
    // Not past the cascade's cube (the model's box for the last).
    let h = 0.5 * (last as f32).exp2();
    Some((lo.map(|v| v.max(0.5 - h)), hi.map(|v| v.min(0.5 + h))))
}

/// Whether the occupancy grid calls the cell of a lattice point empty, as instant-ngp reads
/// it (the cascade the point falls in, the cell's optical thickness below the minimum; a
/// point outside the grid is empty), for every point of a lattice. Read from tables made
/// per axis: a point's coordinates are its axes' own, so each coordinate's distance from
/// the centre and its cell at each cascade are worked out once instead of at each of the
/// lattice's points.
struct AxisMask<'a> {
    grid: &'a OccupancyGrid,
    max_cascade: u32,
    /// Per axis, each coordinate's distance from the centre.
    apart: [Vec<f32>; 3],
    /// Per axis, each coordinate's cell along it at each cascade (cascade-major), spread
    /// into its bits of a Morton code, or [`AxisMask::OUTSIDE`] off the cascade's grid.
    bits: [Vec<u32>; 3],
}

impl<'a> AxisMask<'a> {
    /// Above any Morton code of a 128³ grid, and so is any code OR-ed with it.
    const OUTSIDE: u32 = u32::MAX;

    fn new(grid: &'a OccupancyGrid, coords: &[Vec<f32>; 3]) -> Self {
        let max_cascade = grid.max_cascade();
        let bits = [0, 1, 2].map(|d| {
            (0..=max_cascade)
                .flat_map(|mip| {
                    let s = pow2(-(mip as i32));
                    coords[d].iter().map(move |&p| {
                        cell_along(p, s).map_or(Self::OUTSIDE, |i| {
                            let mut ijk = [0; 3];
                            ijk[d] = i;
                            morton3d(ijk[0], ijk[1], ijk[2])
                        })
                    })
                })
                .collect()
        });
        AxisMask {
            grid,
            max_cascade,
            apart: [0, 1, 2].map(|d| coords[d].iter().map(|&p| (p - 0.5).abs()).collect()),
            bits,
        }
    }

    #[inline]
    fn masked(&self, x: usize, y: usize, z: usize) -> bool {
        let m = self.apart[0][x].max(self.apart[1][y]).max(self.apart[2][z]);
        let mip = mip_from_distance(m, self.max_cascade) as usize;
        let cell = self.bits[0][mip * self.apart[0].len() + x]
            | self.bits[1][mip * self.apart[1].len() + y]
            | self.bits[2][mip * self.apart[2].len() + z];
        cell == Self::OUTSIDE
            || self.grid.density[mip * N_CELLS + cell as usize] < MIN_OPTICAL_THICKNESS
    }
}

/// What [`march`] made.
#[derive(Debug)]
pub struct MeshedLattice {
    pub mesh: Mesh,
    /// Lattice points whose density was evaluated (the others were masked).
    pub evaluated: u64,
}

/// Meshes `lattice` where the raw density crosses `threshold`: `density` gives the raw
/// density output at ngp-space positions; points in cells `mask` calls empty, and the
/// lattice's outermost points, are [`MASKED`] without being evaluated (instant-ngp
/// evaluates the outermost ones too, and leaves a surface the box cuts open). Fails when the mesh passes `max_triangles`.
/// `progress` hears the layers done.
pub fn march(
    lattice: &Lattice,
    mask: Option<&OccupancyGrid>,
    threshold: f32,
    max_triangles: usize,
    density: impl FnMut(&[[f32; 3]]) -> Result<Vec<f32>>,
    progress: impl FnMut(usize),
) -> Result<MeshedLattice> {
    march_in_slabs(
        lattice,
        mask,
        threshold,
        max_triangles,
        SLAB_POINTS,
        density,
        progress,
    )
}

/// [`march`] in slabs of about `slab_points` points.
fn march_in_slabs(
    lattice: &Lattice,
    mask: Option<&OccupancyGrid>,
    threshold: f32,
    max_triangles: usize,
    slab_points: usize,
    mut density: impl FnMut(&[[f32; 3]]) -> Result<Vec<f32>>,
    mut progress: impl FnMut(usize),
) -> Result<MeshedLattice> {
    let [nx, ny, nz] = lattice.res;
    let layer = nx * ny;
    let mut cubes = Cubes::new(
        nx,
        ny,
        threshold,
        lattice.min,
        lattice.step(),
        max_triangles,
    );
    let per_slab = lattice.slab_layers(slab_points);
    let coords = lattice.coordinates();
    let mask = mask.map(|g| AxisMask::new(g, &coords));
    let mut values = Vec::new();
    let mut evaluated = 0u64;
    for z0 in (0..nz).step_by(per_slab) {
        let n_layers = per_slab.min(nz - z0);
        // Rows of the slab in parallel: the points to evaluate and where they go.
        let rows: Vec<(Vec<u32>, Vec<[f32; 3]>)> = (0..n_layers * ny)
            .into_par_iter()
            .map(|r| {
                let (y, z) = (r % ny, z0 + r / ny);
                let mut at = Vec::new();
                let mut pos = Vec::new();
                // The lattice's outermost points count as empty, so that a surface the box
                // cuts is capped there: every mesh is closed.
                if y == 0 || y + 1 == ny || z == 0 || z + 1 == nz {
                    return (at, pos);
                }
                for x in 1..nx - 1 {
                    if mask.as_ref().is_none_or(|m| !m.masked(x, y, z)) {
                        at.push((r * nx + x) as u32);
                        pos.push([coords[0][x], coords[1][y], coords[2][z]]);
                    }
                }
                (at, pos)
            })
            .collect();
        let pos: Vec<[f32; 3]> = rows.iter().flat_map(|(_, p)| p.iter().copied()).collect();
        let d = if pos.is_empty() {
            Vec::new()
        } else {
            density(&pos)?
        };
        if d.len() != pos.len() {
            return Err(Error::Other(format!(
                "{} densities for {} positions",
                d.len(),
                pos.len()
            )));
        }
        evaluated += pos.len() as u64;
        drop(pos);
        values.clear();
        values.resize(n_layers * layer, MASKED);
        let mut k = 0;
        for (at, _) in &rows {
            for &i in at {
                values[i as usize] = d[k];
                k += 1;
            }
        }
        for l in 0..n_layers {
            cubes
                .push_layer(&values[l * layer..(l + 1) * layer])
                .map_err(|e| too_many(e, nz))?;
            progress(z0 + l + 1);
        }
    }
    Ok(MeshedLattice {
        mesh: cubes.finish(),
        evaluated,
    })
}

fn too_many(e: TooManyTriangles, layers: usize) -> Error {
    Error::Other(format!(
        "the mesh passed {} triangles after {} of {} layers (about {} MiB so far); nothing \
         was written. Raise the cap, lower the resolution or raise the threshold",
        e.cap,
        e.layers,
        layers,
        Mesh::bytes_for(e.cap as u64) >> 20
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::topology::{edges, euler_characteristic, signed_volume};

    /// A ball of radius `r` around `c`: raw density `10 (r − |p − c|) / r + 2.5`, crossing
    /// the default threshold on the sphere.
    fn ball(c: [f32; 3], r: f32) -> impl Fn(&[[f32; 3]]) -> Result<Vec<f32>> {
        move |pos| {
            Ok(pos
                .iter()
                .map(|p| {
                    let d = ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2) + (p[2] - c[2]).powi(2))
                        .sqrt();
                    10.0 * (r - d) / r + 2.5
                })
                .collect())
        }
    }

    #[test]
    fn the_axis_tables_mask_what_each_point_would() {
        use ngp::occupancy::cell_at;
        let mut grid = OccupancyGrid::new(5);
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        for d in grid.density.iter_mut() {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1);
            *d = if state >> 63 == 0 { 0.0 } else { 1.0 };
        }
        let rule = |p: [f32; 3]| {
            let mip = mip_from_pos(p, grid.max_cascade());
            match cell_at(p, mip) {
                Some(i) => {
                    grid.density[mip as usize * N_CELLS + i as usize] < MIN_OPTICAL_THICKNESS
                }
                None => true,
            }
        };
        // Past the grid on every side; across every cascade's edge; one through the
        // centre itself (0.1875 + 5/16 = 0.5), where frexp's exponent of 0 is 0.
        for (lo, hi, res) in [
            ([-9.0, -8.0, -8.6], [9.0, 9.1, 8.2], 96),
            ([-1.3, 0.2, -0.7], [2.2, 0.9, 1.6], 80),
            ([0.1875; 3], [1.125; 3], 16),
        ] {
            let l = Lattice::new(lo, hi, res).unwrap();
            let coords = l.coordinates();
            let mask = AxisMask::new(&grid, &coords);
            let mut empty = 0;
            for z in 0..l.res[2] {
                for y in 0..l.res[1] {
                    for x in 0..l.res[0] {
                        let p = [coords[0][x], coords[1][y], coords[2][z]];
                        let s = l.step();
                        let at = [x, y, z].map(|i| i as f32);
                        assert_eq!(p, [0, 1, 2].map(|d| l.min[d] + at[d] * s[d]));
                        assert_eq!(
                            mask.masked(x, y, z),
                            rule(p),
                            "point {p:?} of {lo:?}–{hi:?}"
                        );
                        empty += usize::from(rule(p));
                    }
                }
            }
            assert!(
                empty > 0 && (empty as u64) < l.points(),
                "{empty} of {}",
                l.points()
            );
        }
        assert!(
            Lattice::new([0.1875; 3], [1.125; 3], 16)
                .unwrap()
                .coordinates()[0]
                .contains(&0.5)
        );
    }

    #[test]
    fn resolution_follows_instant_ngp() {
        let l = Lattice::new([0.0; 3], [1.0, 0.5, 0.25], 256).unwrap();
        assert_eq!(l.res, [256, 128, 64]);
        let l = Lattice::new([0.0; 3], [1.0, 0.51, 0.01], 100).unwrap();
        assert_eq!(l.res, [112, 64, 16]);
        assert!(Lattice::new([0.0; 3], [1.0, 0.0, 1.0], 64).is_err());
        assert!(Lattice::new([0.0; 3], [1.0; 3], 1).is_err());
    }

    #[test]
    fn a_ball_is_closed_oriented_and_on_its_sphere() {
        let (c, r) = ([0.52, 0.47, 0.5], 0.3);
        let l = Lattice::new([0.1; 3], [0.9; 3], 48).unwrap();
        let m = march(&l, None, 2.5, usize::MAX, ball(c, r), |_| {})
            .unwrap()
            .mesh;
        assert!(m.triangles.len() > 1000);
        let e = edges(&m);
        assert!(e.closed_and_oriented(), "{e:?}");
        assert_eq!(euler_characteristic(&m), 2);
        // Outward: positive volume near the ball's, normals away from the centre.
        let v = signed_volume(&m);
        let exact = 4.0 / 3.0 * std::f64::consts::PI * (r as f64).powi(3);
        assert!((v / exact - 1.0).abs() < 0.02, "{v} vs {exact}");
        for (p, n) in m.positions.iter().zip(&m.normals) {
            let d = [p[0] - c[0], p[1] - c[1], p[2] - c[2]];
            let dist = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            // The field is linear along the radius, so a vertex is off the sphere only by
            // interpolating along an edge across the sphere's curvature: step² / 8r.
            let step = l.step()[0];
            assert!(
                (dist - r).abs() < step * step / (4.0 * r),
                "vertex {p:?} at {dist}"
            );
            assert!((d[0] * n[0] + d[1] * n[1] + d[2] * n[2]) / dist > 0.9);
        }
    }

    #[test]
    fn slabs_do_not_change_the_mesh() {
        let f = ball([0.5; 3], 0.33);
        let l = Lattice::new([0.0; 3], [1.0; 3], 64).unwrap();
        let whole = march(&l, None, 2.5, usize::MAX, &f, |_| {}).unwrap().mesh;
        assert_eq!(l.slab_layers(SLAB_POINTS), 64);
        for per in [1, 5] {
            let mut calls = 0;
            let sliced = march_in_slabs(
                &l,
                None,
                2.5,
                usize::MAX,
                64 * 64 * per,
                |p| {
                    calls += 1;
                    f(p)
                },
                |_| {},
            )
            .unwrap()
            .mesh;
            // A slab of the outermost layers only (z 0 or 63) has nothing to evaluate and
            // asks for no densities.
            assert_eq!(calls, if per == 1 { 62 } else { 64usize.div_ceil(per) });
            assert_eq!(sliced, whole, "slabs of {per} layers");
        }
    }

    #[test]
    fn a_surface_the_box_cuts_is_capped() {
        let l = Lattice::new([0.0; 3], [1.0; 3], 32).unwrap();
        let out = march(
            &l,
            None,
            2.5,
            usize::MAX,
            |p| Ok(vec![9.0; p.len()]),
            |_| {},
        )
        .unwrap();
        assert_eq!(out.evaluated, 30 * 30 * 30);
        assert!(edges(&out.mesh).closed_and_oriented());
        assert_eq!(euler_characteristic(&out.mesh), 2);
        assert!(signed_volume(&out.mesh) > 0.0);
    }

    #[test]
    fn a_cap_stops_the_march() {
        let l = Lattice::new([0.0; 3], [1.0; 3], 64).unwrap();
        let e = march(&l, None, 2.5, 100, ball([0.5; 3], 0.3), |_| {}).unwrap_err();
        assert!(e.to_string().contains("passed 100 triangles"), "{e}");
    }

    #[test]
    fn masked_cells_are_not_evaluated_and_close_the_surface() {
        // A grid with one occupied block of cells; the field is dense everywhere, so the
        // surface is the block's boundary.
        let mut grid = OccupancyGrid::new(1);
        grid.density.fill(0.0);
        for m in 0..N_CELLS as u32 {
            let ijk = [
                morton3d_invert(m),
                morton3d_invert(m >> 1),
                morton3d_invert(m >> 2),
            ];
            if ijk.iter().all(|&i| (40..80).contains(&i)) {
                grid.density[m as usize] = 1.0;
            }
        }
        let (lo, hi) = occupied_box(&grid).unwrap();
        let g = 1.0 / GRID_SIZE as f32;
        for d in 0..3 {
            assert!((lo[d] - 39.0 * g).abs() < 1e-6 && (hi[d] - 81.0 * g).abs() < 1e-6);
        }
        let l = Lattice::new(lo, hi, 64).unwrap();
        let out = march(
            &l,
            Some(&grid),
            2.5,
            usize::MAX,
            |p| Ok(vec![50.0; p.len()]),
            |_| {},
        )
        .unwrap();
        assert!(out.evaluated < l.points() * 9 / 10 && out.evaluated > l.points() / 2);
        assert!(edges(&out.mesh).closed_and_oriented());
        assert_eq!(euler_characteristic(&out.mesh), 2);
        assert_eq!(occupied_box_within(&grid, 0), Some((lo, hi)));
        // An empty grid: no box.
        grid.density.fill(0.0);
        assert!(occupied_box(&grid).is_none());
    }
}
