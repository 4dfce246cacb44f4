//! The one colour encoding of the project: the exact sRGB transfer curve (IEC 61966-2-1).
//!
//! The texture field gives linear RGB in [0, 1]. Everything a person or a discriminator sees is
//! sRGB-encoded with the curve below: the dataset's PNGs, the CPU renderer, the training
//! renderer's RGB images (tensor form, [`encode_srgb_tensor`]), the scan terms and the app's
//! viewer (its WGSL shader repeats the same two branches, `crates/web/src/viewer.rs`). A second
//! curve anywhere (e.g. γ 1/2.2) shows trained colours too dark by up to 8/255 in the darks.

use glam::Vec3;

/// Linear values at or below this are encoded by the linear segment.
pub const LINEAR_KNEE: f32 = 0.003_130_8;
/// Encoded values at or below this are decoded by the linear segment.
pub const ENCODED_KNEE: f32 = 0.040_45;

/// sRGB encoding of one linear channel, clamped to [0, 1].
pub fn encode_srgb(x: f32) -> f32 {
    let x = x.clamp(0.0, 1.0);
    if x <= LINEAR_KNEE {
        12.92 * x
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    }
}

/// Linear value of one sRGB-encoded channel in [0, 1].
pub fn decode_srgb(x: f32) -> f32 {
    if x <= ENCODED_KNEE {
        x / 12.92
    } else {
        ((x + 0.055) / 1.055).powf(2.4)
    }
}

/// Entries of [`decode_srgb_fast`]'s table over [0, 1].
const DECODE_TABLE: usize = 4096;

/// [`decode_srgb`] from a table with linear interpolation, for whole images: `powf` is a
/// software call on wasm (a 512² photo's decode took 70 ms of the UI thread). Within 1e-6 of
/// the exact curve over [0, 1] (its second derivative is at most 3: the interpolation error is
/// below 3 / (8 · 4096²)); values outside [0, 1] are clamped.
pub fn decode_srgb_fast(x: f32) -> f32 {
    static TABLE: std::sync::OnceLock<Vec<f32>> = std::sync::OnceLock::new();
    let t = TABLE.get_or_init(|| (0..=DECODE_TABLE).map(|i| decode_srgb(i as f32 / DECODE_TABLE as f32)).collect());
    let u = x.clamp(0.0, 1.0) * DECODE_TABLE as f32;
    let i = (u as usize).min(DECODE_TABLE - 1);
    let f = u - i as f32;
    t[i] + (t[i + 1] - t[i]) * f
}

/// sRGB encoding of a linear colour (each channel clamped to [0, 1]).
pub fn linear_to_srgb(c: Vec3) -> Vec3 {
    Vec3::new(encode_srgb(c.x), encode_srgb(c.y), encode_srgb(c.z))
}

/// Linear colour of an sRGB-encoded one.
pub fn srgb_to_linear(c: Vec3) -> Vec3 {
    Vec3::new(decode_srgb(c.x), decode_srgb(c.y), decode_srgb(c.z))
}

/// [`encode_srgb`] element-wise on a tensor, differentiable (the gradient of each branch; the
/// power branch is evaluated at max(x, knee), so no infinite slope at 0 reaches autodiff).
#[cfg(any(feature = "generator", feature = "wgpu"))]
pub fn encode_srgb_tensor<const D: usize>(x: burn::tensor::Tensor<D>) -> burn::tensor::Tensor<D> {
    let x = x.clamp(0.0, 1.0);
    let low = x.clone() * 12.92;
    let high = x.clone().clamp_min(LINEAR_KNEE).powf_scalar(1.0 / 2.4) * 1.055 - 0.055;
    high.mask_where(x.lower_equal_elem(LINEAR_KNEE), low)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_curve_has_its_reference_values_and_inverts() {
        // Reference points of IEC 61966-2-1 (8-bit values of linear 0.5, 0.2, 0.01, 0.001).
        for (lin, byte) in [(0.5f32, 188.0f32), (0.2, 124.0), (0.01, 25.0), (0.001, 3.0), (0.0, 0.0), (1.0, 255.0)] {
            assert_eq!((encode_srgb(lin) * 255.0).round(), byte, "linear {lin}");
        }
        for i in 0..=1000 {
            let x = i as f32 / 1000.0;
            assert!((decode_srgb(encode_srgb(x)) - x).abs() < 1e-5, "{x}");
        }
        // Continuous at the knee.
        assert!((12.92 * LINEAR_KNEE - (1.055 * LINEAR_KNEE.powf(1.0 / 2.4) - 0.055)).abs() < 1e-6);
        let clamped = linear_to_srgb(Vec3::new(-1.0, 2.0, 0.5));
        assert!((clamped - Vec3::new(0.0, 1.0, encode_srgb(0.5))).abs().max_element() < 1e-6, "{clamped}");
    }

    #[test]
    fn the_decode_table_follows_the_curve() {
        let mut worst = 0.0f32;
        for i in 0..=100_000 {
            let x = i as f32 / 100_000.0;
            worst = worst.max((decode_srgb_fast(x) - decode_srgb(x)).abs());
        }
        assert!(worst < 1e-6, "worst {worst}");
        assert_eq!((decode_srgb_fast(-0.5), decode_srgb_fast(1.5)), (0.0, decode_srgb(1.0)));
    }

    #[cfg(feature = "generator")]
    #[test]
    fn the_tensor_form_equals_the_scalar_form() {
        use burn::tensor::{Device, Tensor, TensorData};
        #[allow(deprecated)]
        let dev = Device::ndarray();
        let xs: Vec<f32> = (0..=400).map(|i| i as f32 / 400.0).chain([-0.5, 1.5, 0.001, 0.003]).collect();
        let n = xs.len();
        let t = encode_srgb_tensor(Tensor::<1>::from_data(TensorData::new(xs.clone(), [n]), &dev));
        let got = t.into_data().try_to_vec::<f32>().unwrap();
        for (x, y) in xs.iter().zip(&got) {
            assert!((encode_srgb(*x) - y).abs() < 1e-6, "{x}: {} vs {y}", encode_srgb(*x));
        }
    }
}
