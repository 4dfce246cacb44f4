//! Building blocks with StyleGAN2's equalised learning rate: weights are stored at N(0, 1/lr_mul)
//! and scaled at run time by `lr_mul / sqrt(fan_in)`.

use burn::module::{Module, Param};
use burn::tensor::activation::leaky_relu;
use burn::tensor::module::conv2d;
use burn::tensor::ops::{ConvOptions, PadMode};
use burn::tensor::{Device, Tensor};

use super::init::{full, randn, Rng};

const SQRT2: f32 = std::f32::consts::SQRT_2;

/// Leaky ReLU (slope 0.2) with StyleGAN's gain √2.
pub fn lrelu_gain<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    leaky_relu(x, 0.2) * SQRT2
}

/// Whether `device` (or the device an autodiff device wraps) is the NdArray CPU backend.
pub fn is_ndarray(device: &Device) -> bool {
    #[cfg(feature = "ndarray")]
    {
        #[allow(deprecated)]
        let cpu = Device::ndarray();
        device.clone().inner() == cpu
    }
    #[cfg(not(feature = "ndarray"))]
    {
        let _ = device;
        false
    }
}

/// Stride-1 "same" convolution with an odd `k`×`k` kernel per sample: `x` `[B, in, H, W]`,
/// `weight` `[B, out, in, k, k]` (or `[1, out, in, k, k]`, shared) → `[B, out, H, W]`.
///
/// The one convolution of the networks (StyleGAN2's modulated convs use per-sample weights,
/// the discriminators a shared one). On NdArray it is im2col + matmul as one operation with
/// its own backward pass ([`super::ndarray_ops`]): burn-ndarray's `conv2d` backward is
/// 25–35× slower at the sizes we train (see `trainer bench generator`). On GPU backends it is burn's
/// grouped `conv2d` for small convolutions and the same im2col + matmul for large ones
/// ([`GPU_IM2COL_MIN_MACS`]).
pub fn conv2d_same(x: Tensor<4>, weight: Tensor<5>) -> Tensor<4> {
    let [b, c_in, h, w] = x.dims();
    let [wb, c_out, _, k, _] = weight.dims();
    let pad = k / 2;
    #[cfg(feature = "ndarray")]
    if is_ndarray(&x.device()) {
        return super::ndarray_ops::conv2d_same(x, weight);
    }
    if b * c_out * c_in * k * k * h * w >= GPU_IM2COL_MIN_MACS {
        conv2d_im2col(x, weight, GPU_COLS_MAX_BYTES)
    } else if wb == 1 {
        conv2d(x, weight.reshape([c_out, c_in, k, k]), None, ConvOptions::new([1, 1], [pad, pad], [1, 1], 1))
    } else {
        let y = conv2d(
            x.reshape([1, b * c_in, h, w]),
            weight.reshape([b * c_out, c_in, k, k]),
            None,
            ConvOptions::new([1, 1], [pad, pad], [1, 1], b),
        );
        y.reshape([b, c_out, h, w])
    }
}

/// `lrelu(x + bias) · √2` over `[B, C, H, W]` with a `[C]` bias, or only the bias without
/// `activation`: what follows each convolution. On NdArray the activated form is one operation
/// with its own backward pass ([`super::ndarray_ops`]).
pub fn bias_lrelu(x: Tensor<4>, bias: Tensor<1>, activation: bool) -> Tensor<4> {
    #[cfg(feature = "wgpu")]
    if let Some(y) = super::cube_ops::bias_lrelu(&x, &bias, 1, activation) {
        return y;
    }
    #[cfg(feature = "ndarray")]
    if activation && is_ndarray(&x.device()) {
        return super::ndarray_ops::bias_lrelu(x, bias);
    }
    let c = bias.dims()[0];
    let y = x + bias.reshape([1, c, 1, 1]);
    if activation {
        lrelu_gain(y)
    } else {
        y
    }
}

/// From this many multiply-adds on, a convolution on a GPU backend goes through im2col and a
/// matmul. burn's wgpu backend has only its direct convolution kernel for dense f32
/// convolutions (its implicit GEMM needs f16 cooperative matrices): on an NVIDIA H200 it took
/// 9.4 ms for a 3×3, 512 → 512 channel convolution at 64², 83 % of the paper config's
/// generation (docs/benchmarks.md). The tiled matmul is far faster there, for k² slices and a
/// stack more launches and a k²-times larger intermediate. The demo config's convolutions
/// (at most 1.5 · 10⁸ multiply-adds) stay below the bound, so the browser keeps its launch
/// count.
pub const GPU_IM2COL_MIN_MACS: usize = 1 << 29;

/// The most bytes one im2col column matrix may take on a GPU backend: larger convolutions
/// go band by band of output rows. A storage buffer binding is limited (128 MiB under
/// WebGPU's defaults, less on some drivers), and the paper config's 256², 128-channel layers
/// would need 302 MB at once.
const GPU_COLS_MAX_BYTES: usize = 64 << 20;

/// `conv2d_same` as im2col (the k² shifted taps stacked) and a batched matmul, in tensor ops,
/// in bands of output rows whose f32 columns stay within `max_cols_bytes` (at least one row
/// per band). NdArray passes `usize::MAX` (one band: its results stay what they were), GPU
/// backends [`GPU_COLS_MAX_BYTES`].
pub fn conv2d_im2col(x: Tensor<4>, weight: Tensor<5>, max_cols_bytes: usize) -> Tensor<4> {
    let [b, c_in, h, w] = x.dims();
    let [wb, c_out, _, k, _] = weight.dims();
    let pad = k / 2;
    let band = (max_cols_bytes / (4 * b * c_in * k * k * w).max(1)).clamp(1, h.max(1));
    let xp = if pad > 0 { x.pad((pad, pad, pad, pad), PadMode::Constant(0.0)) } else { x };
    let wm = weight.reshape([wb, c_out, c_in * k * k]);
    let wm = if wb == b { wm } else { wm.expand([b, c_out, c_in * k * k]) };
    let mut bands: Vec<Tensor<4>> = (0..h)
        .step_by(band)
        .map(|y0| {
            let rows = band.min(h - y0);
            let mut taps = Vec::with_capacity(k * k);
            for dy in 0..k {
                for dx in 0..k {
                    taps.push(xp.clone().slice([0..b, 0..c_in, y0 + dy..y0 + dy + rows, dx..dx + w]));
                }
            }
            // [B, in, k·k, rows, W] → columns [B, in·k·k, rows·W] (the weight's (in, ky, kx) order).
            let cols = Tensor::<4>::stack::<5>(taps, 2).reshape([b, c_in * k * k, rows * w]);
            wm.clone().matmul(cols).reshape([b, c_out, rows, w])
        })
        .collect();
    if bands.len() == 1 {
        bands.remove(0)
    } else {
        Tensor::cat(bands, 2)
    }
}

/// Fully connected layer `y = x·(W·g)ᵀ + b·lr_mul`, g = lr_mul/√in.
#[derive(Module, Debug)]
pub struct FullyConnected {
    /// `[out, in]`
    pub weight: Param<Tensor<2>>,
    /// `[out]`
    pub bias: Param<Tensor<1>>,
    pub weight_gain: f32,
    pub lr_mul: f32,
    /// Apply leaky ReLU (with gain) after the affine map.
    pub activation: bool,
}

impl FullyConnected {
    pub fn new(
        rng: &mut Rng,
        d_in: usize,
        d_out: usize,
        lr_mul: f32,
        bias_init: f32,
        activation: bool,
        device: &Device,
    ) -> Self {
        Self {
            weight: Param::from_tensor(randn(rng, [d_out, d_in], 1.0 / lr_mul, device)),
            bias: Param::from_tensor(full([d_out], bias_init / lr_mul, device)),
            weight_gain: lr_mul / (d_in as f32).sqrt(),
            lr_mul,
            activation,
        }
    }

    /// `x`: `[B, in]` → `[B, out]`.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        #[cfg(feature = "wgpu")]
        if let Some(y) = super::cube_ops::fully_connected(
            &x,
            &self.weight.val(),
            &self.bias.val(),
            self.weight_gain,
            self.lr_mul,
            self.activation,
        ) {
            return y;
        }
        let w = self.weight.val() * self.weight_gain;
        // A product with 1 is exact and would cost a GPU launch (the style affines' case).
        let bias = if self.lr_mul == 1.0 { self.bias.val() } else { self.bias.val() * self.lr_mul };
        let y = x.matmul(w.transpose()) + bias.unsqueeze_dim::<2>(0);
        if self.activation {
            lrelu_gain(y)
        } else {
            y
        }
    }
}

/// StyleGAN2 modulated convolution with a style affine from w:
/// `W'_bo,i = W_o,i · s_b,i`, demodulated `W'' = W' / ‖W'_bo‖` when `demodulate`.
/// Batched through a grouped convolution (groups = batch).
#[derive(Module, Debug)]
pub struct ModulatedConv2d {
    pub affine: FullyConnected,
    /// `[out, in, k, k]`
    pub weight: Param<Tensor<4>>,
    /// `[out]`
    pub bias: Param<Tensor<1>>,
    pub kernel: usize,
    pub demodulate: bool,
    /// Leaky ReLU after the bias.
    pub activation: bool,
}

impl ModulatedConv2d {
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        rng: &mut Rng,
        w_dim: usize,
        c_in: usize,
        c_out: usize,
        kernel: usize,
        demodulate: bool,
        activation: bool,
        device: &Device,
    ) -> Self {
        Self {
            affine: FullyConnected::new(rng, w_dim, c_in, 1.0, 1.0, false, device),
            weight: Param::from_tensor(randn(rng, [c_out, c_in, kernel, kernel], 1.0, device)),
            bias: Param::from_tensor(full([c_out], 0.0, device)),
            kernel,
            demodulate,
            activation,
        }
    }

    /// `x`: `[B, in, H, W]`, `w`: `[B, w_dim]` → `[B, out, H, W]`.
    pub fn forward(&self, x: Tensor<4>, w: Tensor<2>) -> Tensor<4> {
        let [_, c_in, _, _] = x.dims();
        let [_, _, k, _] = self.weight.dims();
        let styles = self.affine.forward(w); // [B, in]
        let style_gain = 1.0 / ((c_in * k * k) as f32).sqrt();
        let weight: Tensor<5> = modulate(self.weight.val(), styles, style_gain, self.demodulate);
        bias_lrelu(conv2d_same(x, weight), self.bias.val(), self.activation)
    }
}

/// StyleGAN2's weight modulation: `weight` `[out, in, taps…]` (rank `D`) times the styles `[B, in]`
/// → `[B, out, in, taps…]` (rank `D1 = D + 1`). With `demodulate` each (sample, output) slice is
/// scaled to unit norm; without, the styles are first scaled by `style_gain` (the to-RGB layers
/// fold their fan-in gain into the styles). One kernel on wgpu for generation
/// ([`super::cube_ops`]).
fn modulate<const D: usize, const D1: usize>(
    weight: Tensor<D>,
    styles: Tensor<2>,
    style_gain: f32,
    demodulate: bool,
) -> Tensor<D1> {
    let gain = if demodulate { 1.0 } else { style_gain };
    #[cfg(feature = "wgpu")]
    if let Some(w) = super::cube_ops::modulate::<D, D1>(&weight, &styles, gain, demodulate) {
        return w;
    }
    let [b, c_in] = styles.dims();
    let styles = if demodulate { styles } else { styles * gain };
    let mut shape = [1usize; D1];
    (shape[0], shape[2]) = (b, c_in);
    let weight = weight.unsqueeze_dim::<D1>(0) * styles.reshape(shape); // [B, out, in, taps…]
    if demodulate {
        let taps: Vec<usize> = (2..D1).collect();
        let d = (weight.clone().powf_scalar(2.0).sum_dims(&taps) + 1e-8).sqrt().recip(); // [B, out, 1, …]
        weight * d
    } else {
        weight
    }
}

/// Modulated fully connected layer of the decoders (a 1×1 modulated conv on point sets):
/// `y_bn = x_bn · W'_bᵀ + bias`, `W'_b = W ⊙ s_b`, demodulated.
#[derive(Module, Debug)]
pub struct ModulatedLinear {
    pub affine: FullyConnected,
    /// `[out, in]`
    pub weight: Param<Tensor<2>>,
    /// `[out]`
    pub bias: Param<Tensor<1>>,
    pub demodulate: bool,
    pub activation: bool,
}

impl ModulatedLinear {
    pub fn new(
        rng: &mut Rng,
        w_dim: usize,
        d_in: usize,
        d_out: usize,
        demodulate: bool,
        activation: bool,
        device: &Device,
    ) -> Self {
        Self::with_weight_scale(rng, w_dim, d_in, d_out, demodulate, activation, 1.0, device)
    }

    /// Like [`ModulatedLinear::new`] with the initial weights scaled by `weight_scale`.
    #[allow(clippy::too_many_arguments)]
    pub fn with_weight_scale(
        rng: &mut Rng,
        w_dim: usize,
        d_in: usize,
        d_out: usize,
        demodulate: bool,
        activation: bool,
        weight_scale: f32,
        device: &Device,
    ) -> Self {
        Self {
            affine: FullyConnected::new(rng, w_dim, d_in, 1.0, 1.0, false, device),
            weight: Param::from_tensor(randn(rng, [d_out, d_in], weight_scale, device)),
            bias: Param::from_tensor(full([d_out], 0.0, device)),
            demodulate,
            activation,
        }
    }

    /// `x`: `[B, N, in]`, `w`: `[B, w_dim]` → `[B, N, out]`.
    pub fn forward(&self, x: Tensor<3>, w: Tensor<2>) -> Tensor<3> {
        let [_, _, d_in] = x.dims();
        let [d_out, _] = self.weight.dims();
        let styles = self.affine.forward(w); // [B, in]
        let weight: Tensor<3> = modulate(self.weight.val(), styles, 1.0 / (d_in as f32).sqrt(), self.demodulate);
        let y = x.matmul(weight.swap_dims(1, 2));
        #[cfg(feature = "wgpu")]
        if let Some(y) = super::cube_ops::bias_lrelu(&y, &self.bias.val(), 2, self.activation) {
            return y;
        }
        let y = y + self.bias.val().reshape([1, 1, d_out]);
        if self.activation {
            lrelu_gain(y)
        } else {
            y
        }
    }
}
