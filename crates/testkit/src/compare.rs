//! Comparing two sets of weights, the CPU engine's and the GPU's say, or a model's before
//! and after a step.

/// How many parameters two models hold differently.
pub fn n_different(a: &[f32], b: &[f32]) -> usize {
    assert_eq!(a.len(), b.len(), "weights of different sizes");
    a.iter().zip(b).filter(|(u, v)| u != v).count()
}

/// The largest distance between two models' parameters.
pub fn largest_distance(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len(), "weights of different sizes");
    a.iter()
        .zip(b)
        .map(|(u, v)| (u - v).abs())
        .fold(0f32, f32::max)
}
