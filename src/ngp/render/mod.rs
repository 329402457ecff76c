//! Ray marching through the occupancy grid, volume compositing (forward and backward), and
//! rendering whole images.

pub mod composite;
pub mod image;
pub mod march;
