//! The networks' element-wise chains as single GPU kernels on burn's cubecl backend (wgpu
//! natively, WebGPU in the browser), for generation: tensors that record no gradients.
//!
//! Without burn's `fusion` feature (tried and dropped, docs/benchmarks.md: it compiles fused
//! kernels for each new shape) every tensor op is its own kernel launch, and in the browser
//! each launch from wasm costs 0.05–0.2 ms of host time. A new identity's synthesis launched
//! 356 kernels, most of them one multiply or add each. Four kernels take the chains
//! that the networks repeat:
//!
//! - [`fully_connected`]: `act(x·Wᵀ·gain + b·bias_mul)`, the mapping layers and the style
//!   affines (was: weight scale, matmul, bias scale, add, and four for leaky ReLU and gain);
//! - [`modulate`]: StyleGAN2's weight modulation and demodulation, `W ⊙ s` scaled to unit norm
//!   per (sample, output) (was: seven element-wise ops and a reduction);
//! - [`bias_lrelu`]: the bias add, leaky ReLU and gain after a convolution or linear layer (was
//!   five ops);
//! - [`upsample2`]: the synthesis's 2× bilinear upsampling, with the skip sum that follows it
//!   (was ten gathers, scalings and adds).
//!
//! Each computes what the tensor ops compute, in the same order per value (the matrix products
//! sum in their own order), so results agree to float rounding; `tests/tests/backends.rs`
//! compares generation on wgpu with NdArray's. Gradients still go through the tensor ops:
//! every wrapper here returns `None` for a tensor that records gradients, or one not on a
//! cubecl device, and the caller runs its tensor-op version.

use burn::backend::tensor::FloatTensor;
use burn::backend::{backend_extension, Backend, DispatchDevice, TensorMetadata};
use burn::tensor::{DType, Shape, Tensor};
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::tensor::CubeTensor;
use burn_cubecl::CubeBackend;
use cubecl::prelude::*;
use cubecl::zspace::metadata::Metadata;
use cubecl::{calculate_cube_count_elemwise, CubeDim};

const SQRT2: f32 = std::f32::consts::SQRT_2;

/// Leaky ReLU (slope 0.2) with StyleGAN's gain √2, as `layers::lrelu_gain`.
#[cube]
fn lrelu_gain(y: f32) -> f32 {
    let mut v = y;
    if v < 0.0 {
        v *= 0.2;
    }
    v * SQRT2
}

#[cube(launch)]
fn fully_connected_kernel(
    x: &[f32],
    weight: &[f32],
    bias: &[f32],
    out: &mut [f32],
    rows: usize,
    d_in: usize,
    d_out: usize,
    gain: f32,
    bias_mul: f32,
    activation: u32,
) {
    let pos = ABSOLUTE_POS;
    if pos >= rows * d_out {
        terminate!();
    }
    let row = pos / d_out;
    let o = pos % d_out;
    let mut acc = 0.0f32;
    for k in 0..d_in {
        acc += x[row * d_in + k] * weight[o * d_in + k];
    }
    let mut y = acc * gain + bias[o] * bias_mul;
    if activation == 1 {
        y = lrelu_gain(y);
    }
    out[pos] = y;
}

#[cube(launch)]
fn modulate_kernel(
    weight: &[f32],
    styles: &[f32],
    out: &mut [f32],
    batch: usize,
    c_out: usize,
    c_in: usize,
    taps: usize,
    style_gain: f32,
    demodulate: u32,
) {
    let pos = ABSOLUTE_POS;
    if pos >= batch * c_out {
        terminate!();
    }
    let b = pos / c_out;
    let o = pos % c_out;
    let w_base = o * c_in * taps;
    let out_base = pos * c_in * taps;
    let mut d = 1.0f32;
    if demodulate == 1 {
        let mut sum = 0.0f32;
        for i in 0..c_in {
            let s = styles[b * c_in + i] * style_gain;
            for t in 0..taps {
                let v = weight[w_base + i * taps + t] * s;
                sum += v * v;
            }
        }
        d = 1.0f32 / f32::sqrt(sum + 1e-8);
    }
    for i in 0..c_in {
        let s = styles[b * c_in + i] * style_gain;
        for t in 0..taps {
            let v = weight[w_base + i * taps + t] * s;
            // Channels-last: (sample, output, tap, input).
            if demodulate == 1 {
                out[out_base + t * c_in + i] = v * d;
            } else {
                out[out_base + t * c_in + i] = v;
            }
        }
    }
}

/// Element-wise over the buffer of a dense `x` (any order of its dimensions in memory: a
/// convolution's output is channels-last); `out` has `x`'s layout, so a following convolution
/// takes it without a copy. The channel of buffer position `p` is `(p / channel_stride) % channels`.
#[cube(launch)]
fn bias_lrelu_kernel(
    x: &[f32],
    bias: &[f32],
    out: &mut [f32],
    len: usize,
    channels: usize,
    channel_stride: usize,
    activation: u32,
) {
    let pos = ABSOLUTE_POS;
    if pos >= len {
        terminate!();
    }
    let mut y = x[pos] + bias[(pos / channel_stride) % channels];
    if activation == 1 {
        y = lrelu_gain(y);
    }
    out[pos] = y;
}

/// `x` `[B, C, H, W]`, `skip` and `out` `[B, C, 2H, 2W]`, each with any strides; `pos` walks
/// the output's elements in (b, c, y, x) order.
#[cube(launch)]
fn upsample2_kernel(
    x: &cubecl::prelude::Tensor<f32>,
    skip: &cubecl::prelude::Tensor<f32>,
    out: &mut cubecl::prelude::Tensor<f32>,
    add_skip: u32,
) {
    let pos = ABSOLUTE_POS;
    let (c, h, w) = (x.shape(1), x.shape(2), x.shape(3));
    let (h2, w2) = (2 * h, 2 * w);
    if pos >= x.shape(0) * c * h2 * w2 {
        terminate!();
    }
    let ox = pos % w2;
    let oy = (pos / w2) % h2;
    let (n, ch) = (pos / (w2 * h2 * c), (pos / (w2 * h2)) % c);
    let base = n * x.stride(0) + ch * x.stride(1);
    let (sy, sx) = (x.stride(2), x.stride(3));
    // Own source row/column and its neighbour on the side the output sample lies (clamped).
    let iy = oy / 2;
    let mut jy = iy;
    if oy % 2 == 0 {
        if iy > 0 {
            jy = iy - 1;
        }
    } else if iy + 1 < h {
        jy = iy + 1;
    }
    let ix = ox / 2;
    let mut jx = ix;
    if ox % 2 == 0 {
        if ix > 0 {
            jx = ix - 1;
        }
    } else if ix + 1 < w {
        jx = ix + 1;
    }
    // Rows first, then columns, as `synthesis::upsample_dim` twice.
    let a = x[base + iy * sy + ix * sx] * 0.75 + x[base + jy * sy + ix * sx] * 0.25;
    let b = x[base + iy * sy + jx * sx] * 0.75 + x[base + jy * sy + jx * sx] * 0.25;
    let mut y = a * 0.75 + b * 0.25;
    if add_skip == 1 {
        y += skip[n * skip.stride(0) + ch * skip.stride(1) + oy * skip.stride(2) + ox * skip.stride(3)];
    }
    let at = n * out.stride(0) + ch * out.stride(1) + oy * out.stride(2) + ox * out.stride(3);
    out[at] = y;
}

/// The kernels, for burn's cubecl backend only.
#[backend_extension(Cube)]
pub trait CubeOpsBackend: Backend {
    /// `act(x·Wᵀ·gain + bias·bias_mul)`: `x` `[rows, in]`, `weight` `[out, in]`, `bias` `[out]`.
    fn fully_connected(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        gain: f32,
        bias_mul: f32,
        activation: bool,
    ) -> FloatTensor<Self>;
    /// `weight` `[out, in, taps…]` modulated by `styles·style_gain` (`[B, in]`), demodulated
    /// per (sample, output) when asked → `[B, out, in, taps…]`.
    fn modulate(
        weight: FloatTensor<Self>,
        styles: FloatTensor<Self>,
        style_gain: f32,
        demodulate: bool,
    ) -> FloatTensor<Self>;
    /// `act(x + bias[c])`, `c` the index along `channel_dim`; the result keeps `x`'s memory
    /// layout where `x` is dense.
    fn bias_lrelu(
        x: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        channel_dim: usize,
        activation: bool,
    ) -> FloatTensor<Self>;
    /// 2× bilinear upsampling of `[B, C, H, W]` (half-pixel centres, edges clamped) plus `skip`
    /// (`[B, C, 2H, 2W]`) when `add_skip`.
    fn upsample2(x: FloatTensor<Self>, skip: FloatTensor<Self>, add_skip: bool) -> FloatTensor<Self>;
}

/// A contiguous output tensor of `dtype` on `like`'s device.
pub(crate) fn empty_contiguous(like: &CubeTensor, shape: Shape, dtype: DType) -> CubeTensor {
    // At least one element: a zero-sized buffer is not a valid binding.
    let handle = like.client.empty(shape.num_elements().max(1) * dtype.size());
    CubeTensor::new_contiguous(like.client.clone(), like.device.clone(), shape, handle, dtype)
}

/// Whether `t`'s elements fill its buffer exactly once, in some order of its dimensions: what
/// an element-wise kernel may walk as a flat buffer, keeping the layout.
fn is_dense(t: &CubeTensor) -> bool {
    !t.meta.is_tiled() && t.is_contiguous_buffer() && t.is_nonoverlapping()
}

/// One unit per element of `n` (≥ 1): the launch's cube dimension and count.
pub(crate) fn grid(t: &CubeTensor, n: usize) -> (CubeCount, CubeDim) {
    let dim = CubeDim::new(&t.client, n);
    (calculate_cube_count_elemwise(&t.client, n, dim), dim)
}

impl CubeOpsBackend for CubeBackend {
    fn fully_connected(
        x: CubeTensor,
        weight: CubeTensor,
        bias: CubeTensor,
        gain: f32,
        bias_mul: f32,
        activation: bool,
    ) -> CubeTensor {
        let (x, weight, bias) = (into_contiguous(x), into_contiguous(weight), into_contiguous(bias));
        let [rows, d_in] = x.shape().dims();
        let d_out = weight.shape()[0];
        let out = empty_contiguous(&x, Shape::new([rows, d_out]), DType::F32);
        let (count, dim) = grid(&x, rows * d_out);
        fully_connected_kernel::launch(
            &x.client.clone(),
            count,
            dim,
            x.into_buffer_arg(),
            weight.into_buffer_arg(),
            bias.into_buffer_arg(),
            out.clone().into_buffer_arg(),
            rows,
            d_in,
            d_out,
            gain,
            bias_mul,
            activation as u32,
        );
        out
    }

    fn modulate(weight: CubeTensor, styles: CubeTensor, style_gain: f32, demodulate: bool) -> CubeTensor {
        let (weight, styles) = (into_contiguous(weight), into_contiguous(styles));
        let wdims = weight.shape();
        let (c_out, c_in) = (wdims[0], wdims[1]);
        let taps = wdims.num_elements() / (c_out * c_in).max(1);
        let batch = styles.shape()[0];
        // [B, out, in, taps…] stored as [B, out, taps…, in]: what burn's convolution reads
        // (channels-last), so it needs no copy of the weight.
        let mut dims = vec![batch];
        dims.extend(wdims.iter().copied());
        let mut strides = vec![0usize; dims.len()];
        let mut step = c_in;
        for d in (3..dims.len()).rev() {
            strides[d] = step;
            step *= dims[d];
        }
        (strides[2], strides[1], strides[0]) = (1, step, step * c_out);
        let handle = weight.client.empty(batch * step * c_out * std::mem::size_of::<f32>());
        let meta = Metadata::new(Shape::from(dims), strides);
        let out = CubeTensor::new(weight.client.clone(), handle, meta, weight.device.clone(), DType::F32);
        let (count, dim) = grid(&weight, batch * c_out);
        modulate_kernel::launch(
            &weight.client.clone(),
            count,
            dim,
            weight.into_buffer_arg(),
            styles.into_buffer_arg(),
            out.clone().into_buffer_arg(),
            batch,
            c_out,
            c_in,
            taps,
            style_gain,
            demodulate as u32,
        );
        out
    }

    fn bias_lrelu(x: CubeTensor, bias: CubeTensor, channel_dim: usize, activation: bool) -> CubeTensor {
        let bias = into_contiguous(bias);
        let x = if is_dense(&x) { x } else { into_contiguous(x) };
        let channels = bias.shape().num_elements();
        let channel_stride = x.meta.strides()[channel_dim];
        let len = x.shape().num_elements();
        let handle = x.client.empty(len * std::mem::size_of::<f32>());
        let out = CubeTensor::new(x.client.clone(), handle, (*x.meta).clone(), x.device.clone(), DType::F32);
        let (count, dim) = grid(&x, len);
        bias_lrelu_kernel::launch(
            &x.client.clone(),
            count,
            dim,
            x.into_buffer_arg(),
            bias.into_buffer_arg(),
            out.clone().into_buffer_arg(),
            len,
            channels,
            channel_stride.max(1),
            activation as u32,
        );
        out
    }

    fn upsample2(x: CubeTensor, skip: CubeTensor, add_skip: bool) -> CubeTensor {
        let [b, c, h, w] = x.shape().dims();
        // Features for the next convolution: channels-last, which it reads without a copy.
        // The skip sums (the triplanes in the making): row-major, which the plane sampling
        // reads without a copy.
        let (h2, w2) = (2 * h, 2 * w);
        let strides = if add_skip { vec![c * h2 * w2, h2 * w2, w2, 1] } else { vec![h2 * w2 * c, 1, w2 * c, c] };
        let meta = Metadata::new(Shape::new([b, c, h2, w2]), strides);
        let handle = x.client.empty(b * c * 4 * h * w * std::mem::size_of::<f32>());
        let out = CubeTensor::new(x.client.clone(), handle, meta, x.device.clone(), DType::F32);
        // Without a skip the kernel never reads it: any tensor of the device will do.
        let skip = if add_skip { skip } else { x.clone() };
        let (count, dim) = grid(&x, b * c * 4 * h * w);
        upsample2_kernel::launch(
            &x.client.clone(),
            count,
            dim,
            x.into_tensor_arg(),
            skip.into_tensor_arg(),
            out.clone().into_tensor_arg(),
            add_skip as u32,
        );
        out
    }
}

/// Whether `t` can go through the kernels: on a cubecl device, f32, not empty, recording no
/// gradients.
/// `Some(autodiff)` says whether it is an (untracked) tensor of an autodiff device, whose
/// result goes back to that device.
fn eligible<const D: usize>(t: &Tensor<D>) -> Option<bool> {
    #[cfg(feature = "autodiff")]
    if t.is_tracked() {
        return None;
    }
    // Empty tensors (a decoder on no points) keep the tensor ops: a launch needs ≥ 1 unit.
    if t.dtype() != DType::F32 || t.shape().num_elements() == 0 {
        return None;
    }
    let device = t.device();
    let autodiff = device.is_autodiff();
    matches!(device.inner().as_dispatch(), DispatchDevice::Cube(_)).then_some(autodiff)
}

/// Runs `op` on the inner tensors when every flag is eligible and they agree, re-attaching the
/// result to the autodiff device where the inputs were on one.
fn run<const D: usize>(flags: &[Option<bool>], op: impl FnOnce() -> Tensor<D>) -> Option<Tensor<D>> {
    let first = (*flags.first()?)?;
    if flags.iter().any(|f| *f != Some(first)) {
        return None;
    }
    let y = op();
    Some(if first { y.autodiff() } else { y })
}

/// [`CubeOpsBackend::fully_connected`] on tensors, or `None` where it does not apply.
pub fn fully_connected(
    x: &Tensor<2>,
    weight: &Tensor<2>,
    bias: &Tensor<1>,
    gain: f32,
    bias_mul: f32,
    activation: bool,
) -> Option<Tensor<2>> {
    run(&[eligible(x), eligible(weight), eligible(bias)], || {
        Tensor::from_dispatch(<burn::backend::Dispatch as CubeOpsBackend>::fully_connected(
            x.clone().inner().into_dispatch(),
            weight.clone().inner().into_dispatch(),
            bias.clone().inner().into_dispatch(),
            gain,
            bias_mul,
            activation,
        ))
    })
}

/// [`CubeOpsBackend::modulate`] on tensors: `weight` `[out, in, taps…]` (rank `D`), `styles`
/// `[B, in]` → rank `D + 1`.
pub fn modulate<const D: usize, const D1: usize>(
    weight: &Tensor<D>,
    styles: &Tensor<2>,
    style_gain: f32,
    demodulate: bool,
) -> Option<Tensor<D1>> {
    debug_assert_eq!(D + 1, D1);
    run(&[eligible(weight), eligible(styles)], || {
        Tensor::from_dispatch(<burn::backend::Dispatch as CubeOpsBackend>::modulate(
            weight.clone().inner().into_dispatch(),
            styles.clone().inner().into_dispatch(),
            style_gain,
            demodulate,
        ))
    })
}

/// [`CubeOpsBackend::bias_lrelu`] on tensors: `bias` along dimension `channel_dim` of `x`.
pub fn bias_lrelu<const D: usize>(
    x: &Tensor<D>,
    bias: &Tensor<1>,
    channel_dim: usize,
    activation: bool,
) -> Option<Tensor<D>> {
    run(&[eligible(x), eligible(bias)], || {
        Tensor::from_dispatch(<burn::backend::Dispatch as CubeOpsBackend>::bias_lrelu(
            x.clone().inner().into_dispatch(),
            bias.clone().inner().into_dispatch(),
            channel_dim,
            activation,
        ))
    })
}

/// [`CubeOpsBackend::upsample2`] on tensors, plus `skip` when given.
pub fn upsample2(x: &Tensor<4>, skip: Option<&Tensor<4>>) -> Option<Tensor<4>> {
    let mut flags = vec![eligible(x)];
    flags.extend(skip.map(eligible));
    run(&flags, || {
        let x_inner = x.clone().inner();
        let skip_inner = skip.map_or_else(|| x_inner.clone(), |s| s.clone().inner());
        Tensor::from_dispatch(<burn::backend::Dispatch as CubeOpsBackend>::upsample2(
            x_inner.into_dispatch(),
            skip_inner.into_dispatch(),
            skip.is_some(),
        ))
    })
}
