//! Geometry of the multi-resolution grid, computed exactly as tiny-cuda-nn does
//! (float32 throughout; see instant-ngp-spec.md §1.2–1.3 and §6).

use crate::error::{Error, Result};

/// The hash-grid hyper-parameters a snapshot stores. `per_level_scale` is not among them:
/// instant-ngp recomputes it from the aabb scale (spec §1.1).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GridConfig {
    pub n_levels: u32,
    pub n_features: u32,
    pub log2_hashmap_size: u32,
    pub base_resolution: u32,
}

impl Default for GridConfig {
    /// The Instant-NGP / StegoNGP paper configuration: 16 levels × 2 features, T = 2^19.
    fn default() -> Self {
        GridConfig {
            n_levels: 16,
            n_features: 2,
            log2_hashmap_size: 19,
            base_resolution: 16,
        }
    }
}

impl GridConfig {
    /// Today's instant-ngp `base.json`: 8 levels × 4 features.
    pub fn base_json_2023() -> Self {
        GridConfig {
            n_levels: 8,
            n_features: 4,
            ..Default::default()
        }
    }

    pub fn validate(&self) -> Result<()> {
        if !(1..=32).contains(&self.n_levels) {
            return Err(Error::Config(format!(
                "n_levels must be in 1..=32, got {}",
                self.n_levels
            )));
        }
        if ![1, 2, 4, 8].contains(&self.n_features) {
            return Err(Error::Config(format!(
                "n_features_per_level must be 1, 2, 4 or 8, got {}",
                self.n_features
            )));
        }
        if !(8..=26).contains(&self.log2_hashmap_size) {
            return Err(Error::Config(format!(
                "log2_hashmap_size must be in 8..=26, got {}",
                self.log2_hashmap_size
            )));
        }
        if !(2..=1024).contains(&self.base_resolution) {
            return Err(Error::Config(format!(
                "base_resolution must be in 2..=1024, got {}",
                self.base_resolution
            )));
        }
        Ok(())
    }

    /// Width of the encoding's output (`L·F`).
    pub fn n_output_dims(&self) -> usize {
        (self.n_levels * self.n_features) as usize
    }
}

/// One level of the grid.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LevelInfo {
    pub level: u32,
    /// `exp2(l·log2 b)·N_min − 1`, float32.
    pub scale: f32,
    /// `ceil(scale) + 1` vertices per axis.
    pub resolution: u32,
    /// Number of table entries of this level (`hashmap_size`).
    pub size: u32,
    /// Offset of this level's first entry in the grid table (in entries, not floats).
    pub offset: u32,
    /// Dense levels index `x + y·res + z·res²`; the others hash (spec §1.3).
    pub dense: bool,
}

/// All levels of a grid for a given aabb scale.
#[derive(Clone, Debug, PartialEq)]
pub struct GridLayout {
    pub config: GridConfig,
    pub per_level_scale: f32,
    pub levels: Vec<LevelInfo>,
    /// Total entries over all levels; parameters = entries × F.
    pub n_entries: u32,
}

fn next_multiple(v: u64, m: u64) -> u64 {
    v.div_ceil(m) * m
}

/// instant-ngp's `b = exp(log(2048·aabb_scale / N_min) / (L − 1))` in float32.
pub fn per_level_scale(config: &GridConfig, aabb_scale: u32) -> f32 {
    if config.n_levels <= 1 {
        return 1.0;
    }
    let desired = 2048.0f32 * aabb_scale as f32 / config.base_resolution as f32;
    (desired.ln() / (config.n_levels - 1) as f32).exp()
}

impl GridLayout {
    pub fn new(config: GridConfig, aabb_scale: u32) -> Result<Self> {
        config.validate()?;
        let b = per_level_scale(&config, aabb_scale);
        let log2b = b.log2();
        let t = 1u64 << config.log2_hashmap_size;
        let mut levels = Vec::with_capacity(config.n_levels as usize);
        let mut offset: u64 = 0;
        for l in 0..config.n_levels {
            let scale = (l as f32 * log2b).exp2() * config.base_resolution as f32 - 1.0;
            let resolution = scale.ceil() as u32 + 1;
            let cube = (resolution as u64).pow(3).min((1u64 << 31) - 1);
            let dense_size = next_multiple(cube, 8);
            let size = dense_size.min(t);
            // tcnn hashes iff the table is smaller than the dense stride (res³).
            let dense = size >= (resolution as u64).pow(3);
            levels.push(LevelInfo {
                level: l,
                scale,
                resolution,
                size: size as u32,
                offset: offset as u32,
                dense,
            });
            offset += size;
        }
        if offset * config.n_features as u64 > u32::MAX as u64 {
            return Err(Error::Config("grid too large".into()));
        }
        Ok(GridLayout {
            config,
            per_level_scale: b,
            levels,
            n_entries: offset as u32,
        })
    }

    /// Number of trainable grid parameters (`entries × F`).
    pub fn n_params(&self) -> usize {
        self.n_entries as usize * self.config.n_features as usize
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_config_matches_spec_table() {
        let g = GridLayout::new(GridConfig::default(), 1).unwrap();
        assert_eq!(g.per_level_scale.to_bits(), 0x3fb0e285);
        let res: Vec<u32> = g.levels.iter().map(|l| l.resolution).collect();
        assert_eq!(
            res,
            [
                16, 23, 31, 43, 59, 81, 112, 154, 213, 295, 407, 562, 777, 1073, 1483, 2048
            ]
        );
        let sizes: Vec<u32> = g.levels.iter().take(6).map(|l| l.size).collect();
        assert_eq!(sizes, [4096, 12168, 29792, 79512, 205384, 524288]);
        let offs: Vec<u32> = g.levels.iter().map(|l| l.offset).collect();
        assert_eq!(offs[5], 330952);
        assert_eq!(offs[15], 5573832);
        assert!(g.levels[..5].iter().all(|l| l.dense));
        assert!(g.levels[5..].iter().all(|l| !l.dense));
        assert_eq!(g.n_entries, 6_098_120);
        assert_eq!(g.n_params(), 12_196_240);
        assert!((g.levels[0].scale - 15.0).abs() < 1e-5);
        assert!((g.levels[15].scale - 2046.999).abs() < 1e-2);
    }

    #[test]
    fn base_json_2023_config() {
        let g = GridLayout::new(GridConfig::base_json_2023(), 1).unwrap();
        assert_eq!(g.per_level_scale, 2.0);
        let res: Vec<u32> = g.levels.iter().map(|l| l.resolution).collect();
        assert_eq!(res, [16, 32, 64, 128, 256, 512, 1024, 2048]);
        assert_eq!(g.levels.iter().filter(|l| l.dense).count(), 3);
        assert_eq!(g.n_params(), 11_681_792);
    }

    #[test]
    fn rejects_bad_config() {
        let mut c = GridConfig {
            n_features: 3,
            ..Default::default()
        };
        assert!(GridLayout::new(c, 1).is_err());
        c = GridConfig::default();
        c.n_levels = 0;
        assert!(GridLayout::new(c, 1).is_err());
    }
}
