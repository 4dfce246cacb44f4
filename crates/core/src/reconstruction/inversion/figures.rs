//! The inversion's figures on read-back images: mask IoU, masked PSNR, the comparison strip.

use burn::tensor::Tensor;

use super::target::*;
#[cfg(not(target_arch = "wasm32"))]
use crate::generator::readback::block_on_ready;
use crate::generator::readback::{read_f32, ReadbackError};
use crate::render::diff::avatar::FakeViews;

/// Intersection over union of two masks thresholded at ½ (1 for two empty masks).
pub fn mask_iou(a: &[f32], b: &[f32]) -> f32 {
    crate::body::body_fit::metrics::mask_iou(a, b)
}

/// The inversion's image terms on the CPU, as its start and the garment codes are weighed:
/// masked RGB L1 + MSE (means over the person mask's pixels and channels) plus the
/// silhouette's mean squared error, from a render's sRGB (HWC) and coverage in [0, 1].
pub fn image_loss(t: &InversionTarget, rgb: &[f32], mask: &[f32]) -> f32 {
    let (mut l1, mut mse, mut msum, mut sil) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    for k in 0..t.res * t.res {
        let m = t.mask[k] as f64;
        msum += m;
        for c in 0..3 {
            let d = (rgb[3 * k + c] - t.rgb[3 * k + c]) as f64;
            l1 += m * d.abs();
            mse += m * d * d;
        }
        let s = (mask[k] - t.mask[k]) as f64;
        sil += s * s;
    }
    let msum = msum.max(1.0);
    (l1 / (3.0 * msum) + mse / (3.0 * msum) + sil / (t.res * t.res) as f64) as f32
}

/// PSNR (dB) of two sRGB images in [0, 1] (`res²·3`) over the pixels where `mask ≥ ½`.
pub fn masked_psnr(a: &[f32], b: &[f32], mask: &[f32]) -> f32 {
    let (mut se, mut n) = (0.0f64, 0usize);
    for (k, m) in mask.iter().enumerate() {
        if *m >= 0.5 {
            for c in 0..3 {
                let d = (a[3 * k + c] - b[3 * k + c]) as f64;
                se += d * d;
            }
            n += 3;
        }
    }
    if n == 0 {
        return f32::INFINITY;
    }
    let mse = (se / n as f64).max(1e-12);
    (10.0 * (1.0 / mse).log10()) as f32
}

/// A render as HWC sRGB in [0, 1] and a mask in [0, 1] (the first image of `f`).
#[cfg(not(target_arch = "wasm32"))]
pub fn render_images(f: &FakeViews) -> Result<(Vec<f32>, Vec<f32>), ReadbackError> {
    block_on_ready(render_images_async(f))
}

/// [`render_images`], awaiting its read-backs.
pub async fn render_images_async(f: &FakeViews) -> Result<(Vec<f32>, Vec<f32>), ReadbackError> {
    images_async(f.rgb.clone(), f.mask.clone()).await
}

/// The first image of an RGB `[B, 3, H, W]` and a mask `[B, 1, H, W]` batch (both in [−1, 1])
/// as HWC sRGB and mask in [0, 1].
pub(super) async fn images_async(rgb: Tensor<4>, mask: Tensor<4>) -> Result<(Vec<f32>, Vec<f32>), ReadbackError> {
    let [_, _, h, w] = rgb.dims();
    let n = h * w;
    let chw = read_f32(rgb.narrow(0, 0, 1)).await?;
    let rgb = (0..n)
        .flat_map(|k| (0..3).map(move |c| (c, k)))
        .map(|(c, k)| ((chw[c * n + k] + 1.0) * 0.5).clamp(0.0, 1.0))
        .collect();
    let mask = read_f32(mask.narrow(0, 0, 1)).await?.iter().map(|m| ((m + 1.0) * 0.5).clamp(0.0, 1.0)).collect();
    Ok((rgb, mask))
}

/// Input | render | overlay side by side (RGB8, `3·res × res`): the render over the input
/// where the avatar is, the input dimmed outside the person mask. `rgb`, `mask`: the render
/// as HWC sRGB and mask in [0, 1] at the target's resolution.
pub fn comparison_image(t: &InversionTarget, rgb: &[f32], mask: &[f32]) -> Vec<u8> {
    let r = t.res;
    let mut out = vec![0u8; r * 3 * r * 3];
    for y in 0..r {
        for x in 0..r {
            let k = y * r + x;
            let m = mask.get(k).copied().unwrap_or(0.0);
            for c in 0..3 {
                let (inp, ren) = (t.rgb[3 * k + c], rgb.get(3 * k + c).copied().unwrap_or(1.0));
                let dimmed = inp * (0.35 + 0.65 * t.mask[k]);
                let over = m * ren + (1.0 - m) * dimmed;
                for (panel, v) in [inp, ren, over].into_iter().enumerate() {
                    out[(y * 3 * r + panel * r + x) * 3 + c] = (v.clamp(0.0, 1.0) * 255.0).round() as u8;
                }
            }
        }
    }
    out
}
