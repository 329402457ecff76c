//! Where every parameter of the NeRF model lives in the one flat parameter vector, in the
//! reference order: [density MLP] [colour MLP] [hash grid] (spec §2.5).

use crate::encoding::layout::{GridConfig, GridLayout};
use crate::error::Result;

/// Shape of a bias-free MLP. Matrices are row-major `out × in`; `n_in` and `n_out_padded`
/// are multiples of 16 as tcnn requires; padded output rows are stored (and never used).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MlpShape {
    pub n_in: usize,
    pub width: usize,
    pub n_hidden_layers: usize,
    pub n_out: usize,
    pub n_out_padded: usize,
}

impl MlpShape {
    pub fn new(n_in: usize, width: usize, n_hidden_layers: usize, n_out: usize) -> Self {
        MlpShape {
            n_in: n_in.div_ceil(16) * 16,
            width,
            n_hidden_layers,
            n_out,
            n_out_padded: n_out.div_ceil(16) * 16,
        }
    }

    /// `(rows = outputs, cols = inputs)` of each weight matrix, input layer first.
    pub fn matrices(&self) -> impl Iterator<Item = (usize, usize)> + use<> {
        let (width, n_in, n_out) = (self.width, self.n_in, self.n_out_padded);
        let hidden = self.n_hidden_layers.saturating_sub(1);
        std::iter::once((width, n_in))
            .chain(std::iter::repeat_n((width, width), hidden))
            .chain(std::iter::once((n_out, width)))
    }

    /// The weights' count, in closed form: every forward and backward pass checks it.
    pub fn n_params(&self) -> usize {
        let hidden = self.n_hidden_layers.saturating_sub(1);
        self.width * (self.n_in + hidden * self.width + self.n_out_padded)
    }
}

/// Everything that defines a model's architecture.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ModelConfig {
    pub grid: GridConfig,
    /// Power of two ≤ 128; 1 for NeRF-synthetic scenes.
    pub aabb_scale: u32,
}

impl Default for ModelConfig {
    fn default() -> Self {
        ModelConfig {
            grid: GridConfig::default(),
            aabb_scale: 1,
        }
    }
}

/// Number of SH coefficients for degree 4.
pub const SH_DIMS: usize = 16;
/// Density MLP outputs; output 0 is log-density, all 16 feed the colour MLP.
pub const DENSITY_OUT: usize = 16;

/// Offsets of every block of the flat parameter vector.
#[derive(Clone, Debug, PartialEq)]
pub struct NerfLayout {
    pub config: ModelConfig,
    pub grid: GridLayout,
    pub density_mlp: MlpShape,
    pub color_mlp: MlpShape,
    pub density_offset: usize,
    pub color_offset: usize,
    pub grid_offset: usize,
    pub n_params: usize,
}

impl NerfLayout {
    pub fn new(config: ModelConfig) -> Result<Self> {
        let grid = GridLayout::new(config.grid, config.aabb_scale)?;
        let density_mlp = MlpShape::new(config.grid.n_output_dims(), 64, 1, DENSITY_OUT);
        let color_mlp = MlpShape::new(DENSITY_OUT + SH_DIMS, 64, 2, 3);
        let density_offset = 0;
        let color_offset = density_mlp.n_params();
        let grid_offset = color_offset + color_mlp.n_params();
        let n_params = grid_offset + grid.n_params();
        Ok(NerfLayout {
            config,
            grid,
            density_mlp,
            color_mlp,
            density_offset,
            color_offset,
            grid_offset,
            n_params,
        })
    }

    /// The MLP weights (the "matrix" parameters that get L2 regularisation).
    pub fn n_mlp_params(&self) -> usize {
        self.grid_offset
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reference_parameter_counts() {
        let l = NerfLayout::new(ModelConfig::default()).unwrap();
        assert_eq!(l.density_mlp.n_params(), 3072);
        assert_eq!(l.color_mlp.n_params(), 7168);
        assert_eq!(l.color_offset, 3072);
        assert_eq!(l.grid_offset, 10240);
        assert_eq!(l.n_params, 12_206_480);
        let l8 = NerfLayout::new(ModelConfig {
            grid: GridConfig::base_json_2023(),
            aabb_scale: 1,
        })
        .unwrap();
        assert_eq!(l8.n_params, 11_692_032);
        assert_eq!(
            l.color_mlp.matrices().collect::<Vec<_>>(),
            vec![(64, 32), (64, 64), (16, 64)]
        );
    }

    #[test]
    fn the_closed_form_count_is_the_sum_over_the_matrices() {
        for (n_in, width, hidden, n_out) in [
            (32, 64, 1, 16),
            (19, 64, 2, 3),
            (32, 128, 4, 1),
            (5, 16, 0, 1),
        ] {
            let s = MlpShape::new(n_in, width, hidden, n_out);
            let sum: usize = s.matrices().map(|(r, c)| r * c).sum();
            assert_eq!(s.n_params(), sum, "{s:?}");
            assert_eq!(s.matrices().count(), hidden.max(1) + 1, "{s:?}");
        }
    }
}
