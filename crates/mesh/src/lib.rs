//! Meshes out of a model's density field, as instant-ngp's marching cubes makes them
//! (`src/marching_cubes.cu`, `Testbed::marching_cubes`): the raw density output (the
//! log-density, before its exponential) sampled on a lattice over a box, lattice points in
//! cells the occupancy grid calls empty set to −10000, the surface where it crosses the
//! threshold (2.5 by default), vertex colours from the colour network seen from outside the
//! box's centre, positions written back in the dataset's frame.
//!
//! The density is whatever the caller evaluates ([`lattice::march`] takes a function), so
//! that the same lattice runs on any device: this crate, like the engine it reads, knows
//! nothing of keys or devices.

pub mod colour;
mod cubes;
pub mod frame;
pub mod lattice;
pub mod obj;
pub mod ply;
pub mod table;
pub mod topology;

pub use cubes::TooManyTriangles;
pub use lattice::{Lattice, MeshedLattice, march};

/// A triangle mesh: welded vertices (one per lattice edge the surface crosses), unit
/// vertex normals pointing out of the surface (from dense to empty space), triangles wound
/// counter-clockwise seen from outside.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub positions: Vec<[f32; 3]>,
    pub normals: Vec<[f32; 3]>,
    /// One sRGB colour a vertex (empty until coloured).
    pub colours: Vec<[u8; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

impl Mesh {
    pub fn is_empty(&self) -> bool {
        self.triangles.is_empty()
    }

    /// Bytes a mesh of `triangles` triangles holds, at the ratio of vertices to triangles of
    /// a closed surface (one vertex for two triangles): the mesh half of a memory estimate.
    pub fn bytes_for(triangles: u64) -> u64 {
        // A triangle's three indices; half a vertex (position, normal, colour, and while
        // colouring its direction and network output).
        triangles * 12 + triangles.div_ceil(2) * (12 + 12 + 3 + 12 + 16)
    }
}
