//! How an index function fills a dense level: unused slots and colliding cells.

use ngp::encoding::{LevelIndex, LevelInfo};

#[derive(Clone, Debug, serde::Serialize)]
pub struct SlotOccupancy {
    pub level: u32,
    pub resolution: u32,
    pub size: u32,
    /// Vertices `[0, res)^3`, the cells the reference dense layout maps one-to-one.
    pub cells: u64,
    pub used_slots: u64,
    pub unused_slot_fraction: f64,
    /// Cells that share their slot with at least one other cell.
    pub colliding_cell_fraction: f64,
    pub max_cells_per_slot: u32,
}

pub fn slot_occupancy(index: &LevelIndex, level: &LevelInfo) -> SlotOccupancy {
    let r = level.resolution;
    let mut load = vec![0u32; level.size as usize];
    for z in 0..r {
        for y in 0..r {
            for x in 0..r {
                let i = index.index(x, y, z) as usize;
                if let Some(s) = load.get_mut(i) {
                    *s += 1;
                }
            }
        }
    }
    let cells = (r as u64).pow(3);
    let used = load.iter().filter(|&&c| c > 0).count() as u64;
    let colliding: u64 = load.iter().filter(|&&c| c > 1).map(|&c| c as u64).sum();
    SlotOccupancy {
        level: level.level,
        resolution: r,
        size: level.size,
        cells,
        used_slots: used,
        unused_slot_fraction: 1.0 - used as f64 / level.size as f64,
        colliding_cell_fraction: colliding as f64 / cells as f64,
        max_cells_per_slot: load.iter().copied().max().unwrap_or(0),
    }
}
