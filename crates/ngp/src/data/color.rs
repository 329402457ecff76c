//! sRGB transfer functions with the reference's constants (`common_device.cuh`), so targets
//! and renders match instant-ngp bit for bit in f32 where it matters.

use std::sync::LazyLock;

/// sRGB (display) → linear light. Same branch point and exponent as instant-ngp.
#[inline]
pub fn srgb_to_linear(srgb: f32) -> f32 {
    if srgb <= 0.04045 {
        srgb / 12.92
    } else {
        ((srgb + 0.055) / 1.055).powf(2.4)
    }
}

/// Linear light → sRGB. The reference uses the truncated exponent 0.41666 (not 1/2.4);
/// we keep it so that our training targets equal the reference's.
#[inline]
pub fn linear_to_srgb(linear: f32) -> f32 {
    if linear < 0.003_130_8 {
        12.92 * linear
    } else {
        1.055 * linear.powf(0.41666) - 0.055
    }
}

/// Linear light → sRGB as instant-ngp's Python scripts encode it (`scripts/common.py`'s
/// `linear_to_srgb`, which `run.py` applies to the rendered and ground-truth images before
/// it scores them): the exact exponent 1/2.4 and the power branch only strictly above the
/// knee. In f64, so that scores do not depend on which of the two the CUDA side rounded.
#[inline]
pub fn linear_to_srgb_exact(linear: f64) -> f64 {
    if linear > 0.003_130_8 {
        1.055 * linear.powf(1.0 / 2.4) - 0.055
    } else {
        12.92 * linear
    }
}

/// `srgb_to_linear(i / 255)` for every 8-bit code: decoding stored pixels is a table lookup.
pub static SRGB8_TO_LINEAR: LazyLock<[f32; 256]> = LazyLock::new(|| {
    let mut t = [0.0f32; 256];
    for (i, v) in t.iter_mut().enumerate() {
        *v = srgb_to_linear(i as f32 * (1.0 / 255.0));
    }
    t
});

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transfer_functions() {
        assert_eq!(srgb_to_linear(0.0), 0.0);
        assert!((srgb_to_linear(1.0) - 1.0).abs() < 1e-6);
        // Linear branch below the knee.
        assert!((srgb_to_linear(0.04) - 0.04 / 12.92).abs() < 1e-9);
        // Middle grey: ((0.5+0.055)/1.055)^2.4 = 0.214041...
        assert!((srgb_to_linear(0.5) - 0.214_041_14).abs() < 1e-6);
        // Round trip is close (not exact: 0.41666 != 1/2.4).
        for i in 0..=100 {
            let x = i as f32 / 100.0;
            assert!((linear_to_srgb(srgb_to_linear(x)) - x).abs() < 2e-4, "{x}");
        }
        // The scripts' exact exponent: 0.5 → 1.055·0.5^(1/2.4) − 0.055 = 0.735356…, where
        // the truncated 0.41666 gives 0.735361…; the knee itself stays on the linear branch.
        assert!((linear_to_srgb_exact(0.5) - 0.735_356_983_052_449).abs() < 1e-12);
        assert!((linear_to_srgb(0.5) as f64 - 0.735_360_6).abs() < 1e-6);
        assert_eq!(linear_to_srgb_exact(0.003_130_8), 12.92 * 0.003_130_8);
        assert!((linear_to_srgb_exact(1.0) - 1.0).abs() < 1e-15);
        assert_eq!(SRGB8_TO_LINEAR[0], 0.0);
        assert_eq!(SRGB8_TO_LINEAR[128], srgb_to_linear(128.0 / 255.0));
    }
}
