//! Input encodings: the multi-resolution hash grid (with pluggable per-level index
//! functions) and spherical harmonics for view directions.

pub mod grid;
pub mod index;
pub mod layout;
pub mod reach;
pub mod sh;

pub use index::{LevelIndex, LevelIndices, ReferenceIndex, reference_indices};
pub use layout::{GridConfig, GridLayout, LevelInfo};
