//! Input encodings: the multi-resolution hash grid (with per-level index functions given as
//! data) and spherical harmonics for view directions.

pub mod grid;
pub mod index;
pub mod layout;
pub mod reach;
pub mod sh;
pub mod sip;

pub use index::{IndexFn, LevelIndex, LevelIndices, check_indices, reference_indices};
pub use layout::{GridConfig, GridLayout, LevelInfo};
