//! The network configuration instant-ngp stores at the top level of a snapshot: its
//! `configs/nerf/base.json` as loaded (16×2 as it was before 2023-02-23; 8×4 today differs only
//! in the two encoding keys), plus the `optimize_matrix_params` / `optimize_non_matrix_params`
//! flags the testbed writes into the leaf optimizer on every training step. Numbers keep the
//! types the JSON parser gave them: text with a point or exponent is a double, plain
//! non-negative integers are unsigned.

use super::msgpack::{d, map, s, u};
use crate::encoding::layout::GridConfig;
use rmpv::Value;

/// The full top-level config (everything except the `snapshot` key).
pub fn network_config(grid: &GridConfig) -> Vec<(&'static str, Value)> {
    vec![
        ("loss", map(vec![("otype", s("Huber"))])),
        ("optimizer", optimizer()),
        ("encoding", encoding(grid)),
        ("network", mlp(1)),
        ("dir_encoding", dir_encoding()),
        ("rgb_network", mlp(2)),
        ("distortion_map", distortion_map()),
        ("envmap", envmap()),
    ]
}

/// The network's optimizer: Adam, decayed exponentially, under an EMA of the weights.
fn optimizer() -> Value {
    let adam = map(vec![
        ("otype", s("Adam")),
        ("learning_rate", d(1e-2)),
        ("beta1", d(0.9)),
        ("beta2", d(0.99)),
        ("epsilon", d(1e-15)),
        ("l2_reg", d(1e-6)),
        ("optimize_matrix_params", Value::Boolean(true)),
        ("optimize_non_matrix_params", Value::Boolean(true)),
    ]);
    map(vec![
        ("otype", s("Ema")),
        ("decay", d(0.95)),
        (
            "nested",
            map(vec![
                ("otype", s("ExponentialDecay")),
                ("decay_start", u(20000)),
                ("decay_interval", u(10000)),
                ("decay_base", d(0.33)),
                ("nested", adam),
            ]),
        ),
    ])
}

/// The position encoding: `grid`'s hash grid.
fn encoding(grid: &GridConfig) -> Value {
    map(vec![
        ("otype", s("HashGrid")),
        ("n_levels", u(grid.n_levels as u64)),
        ("n_features_per_level", u(grid.n_features as u64)),
        ("log2_hashmap_size", u(grid.log2_hashmap_size as u64)),
        ("base_resolution", u(grid.base_resolution as u64)),
    ])
}

/// A 64-neuron ReLU MLP with `hidden` hidden layers (1 for density, 2 for colour).
fn mlp(hidden: u64) -> Value {
    map(vec![
        ("otype", s("FullyFusedMLP")),
        ("activation", s("ReLU")),
        ("output_activation", s("None")),
        ("n_neurons", u(64)),
        ("n_hidden_layers", u(hidden)),
    ])
}

/// The direction encoding: degree-4 spherical harmonics of the direction, the density
/// network's other outputs as they are.
fn dir_encoding() -> Value {
    map(vec![
        ("otype", s("Composite")),
        (
            "nested",
            Value::Array(vec![
                map(vec![
                    ("n_dims_to_encode", u(3)),
                    ("otype", s("SphericalHarmonics")),
                    ("degree", u(4)),
                ]),
                map(vec![("otype", s("Identity"))]),
            ]),
        ),
    ])
}

/// The lens distortion map's settings, as `base.json` has them.
fn distortion_map() -> Value {
    map(vec![
        ("resolution", Value::Array(vec![u(32), u(32)])),
        (
            "optimizer",
            map(vec![
                ("otype", s("ExponentialDecay")),
                ("decay_start", u(10000)),
                ("decay_interval", u(5000)),
                ("decay_end", u(25000)),
                ("decay_base", d(0.33)),
                (
                    "nested",
                    map(vec![
                        ("otype", s("Adam")),
                        ("learning_rate", d(1e-4)),
                        ("beta1", d(0.9)),
                        ("beta2", d(0.99)),
                        ("epsilon", d(1e-8)),
                    ]),
                ),
            ]),
        ),
    ])
}

/// The environment map's loss and optimizer, as `base.json` has them.
fn envmap() -> Value {
    let adam = map(vec![
        ("otype", s("Adam")),
        ("learning_rate", d(1e-2)),
        ("beta1", d(0.9)),
        ("beta2", d(0.99)),
        ("beta3", d(0.9)),
        ("beta_shampoo", d(0.0)),
        ("epsilon", d(1e-10)),
        ("identity", d(0.0001)),
        ("cg_on_momentum", Value::Boolean(false)),
        ("frobenius_normalization", Value::Boolean(true)),
        ("l2_reg", d(1e-10)),
    ]);
    map(vec![
        ("loss", map(vec![("otype", s("RelativeL2"))])),
        (
            "optimizer",
            map(vec![
                ("otype", s("Ema")),
                ("decay", d(0.99)),
                (
                    "nested",
                    map(vec![
                        ("otype", s("ExponentialDecay")),
                        ("decay_start", u(10000)),
                        ("decay_interval", u(5000)),
                        ("decay_base", d(0.33)),
                        ("nested", adam),
                    ]),
                ),
            ]),
        ),
    ])
}
