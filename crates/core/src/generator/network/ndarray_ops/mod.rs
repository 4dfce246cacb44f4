//! The networks' heaviest operations on burn's NdArray CPU backend, each as a single operation
//! with its own backward pass (burn's backend-extension mechanism): the one convolution
//! ([`super::layers::conv2d_same`]), the bias and leaky ReLU that follow it
//! ([`super::layers::bias_lrelu`]) and the discriminators' 2×2 average pooling.
//!
//! Written with tensor ops, the im2col convolution stacks k² shifted copies of the input,
//! reshapes them into row-major columns and multiplies; under autodiff each of those steps
//! records its own backward, so a training step spent more time copying (stack, reshape,
//! zero-padded slice gradients) than multiplying (docs/benchmarks.md, "Where a CPU
//! adversarial step goes"). Here the forward pass is, per sample, one im2col into a
//! contiguous buffer and one `sgemm`; the backward pass is `sgemm`s for ∂w (summed over the
//! batch when the weight is shared) and for the columns' gradient, folded back into ∂x
//! (col2im). The columns are rebuilt in the backward pass rather than kept, so the tape holds
//! only `x` and `w`. Natively the samples of a batch run on the CPU cores side by side (burn's
//! NdArray backend itself is built single-threaded here); each sample's values are the same for
//! any number of threads. Results equal the tensor-op im2col's up to float summation order.
//!
//! burn-ndarray's `avg_pool2d` and its backward are written for any kernel, stride and
//! padding and walked 10 % of a CPU training step once the convolution was one operation;
//! [`NdArrayOpsBackend::avg_pool2x2`] is the 2×2, stride-2 case as two plain loops. Likewise
//! the bias add, leaky ReLU and gain after each convolution were four element-wise tensor
//! ops (and a mask) each way; [`NdArrayOpsBackend::bias_lrelu`] is one pass each way. The
//! synthesis network's 2× upsampling, in tensor ops, narrows, concatenates, interleaves and
//! reshapes each axis; with 256² texture detail planes its copies (and their gradients'
//! slices) took a fifth of a CPU training step (docs/benchmarks.md), so [`NdArrayOpsBackend::upsample2`]
//! is one separable pass each way. The triplane lookup under autodiff (`triplane`'s row
//! table) rebuilt a table of every plane's 2×2 neighbourhoods at each call, and its gradient
//! as large, for a few thousand points; [`NdArrayOpsBackend::triplane_bilinear`] reads and
//! scatters only the texels the points touch.

// burn marks NdArray deprecated in favour of burn-flex; it is still this project's CPU backend
// (measured against it: docs/benchmarks.md, "Training", the step time the same, its values
// not checked against NdArray's).
#![allow(deprecated)]

use std::borrow::Cow;

use burn::backend::ndarray::NdArrayTensor;
use burn::backend::tensor::FloatTensor;
use burn::backend::{backend_extension, Backend, Dispatch, NdArray, TensorMetadata};
use burn::tensor::{Tensor, TensorData};

/// The operations, for NdArray and autodiff over it. Calling one with a tensor of another
/// backend panics, so [`super::layers`] and [`super::discriminator`] only route NdArray
/// tensors here.
#[cfg_attr(feature = "autodiff", backend_extension(NdArray, Autodiff))]
#[cfg_attr(not(feature = "autodiff"), backend_extension(NdArray))]
pub trait NdArrayOpsBackend: Backend {
    /// `conv2d_same`: `x` `[B, in, H, W]`, `weight` `[B or 1, out, in, k, k]` (k odd, stride 1,
    /// zero padding k/2) → `[B, out, H, W]`.
    fn conv2d_same(x: FloatTensor<Self>, weight: FloatTensor<Self>) -> FloatTensor<Self>;
    /// 2×2 average pooling with stride 2: `[B, C, H, W]` → `[B, C, H/2, W/2]` (an odd last
    /// row or column is dropped, as burn's `avg_pool2d` drops it).
    fn avg_pool2x2(x: FloatTensor<Self>) -> FloatTensor<Self>;
    /// `lrelu(x + bias) · √2` (slope 0.2, StyleGAN's gain): `x` `[B, C, H, W]`, `bias` `[C]`.
    fn bias_lrelu(x: FloatTensor<Self>, bias: FloatTensor<Self>) -> FloatTensor<Self>;
    /// The synthesis network's 2× bilinear upsampling (`synthesis::upsample2`): `[B, C, H, W]`
    /// → `[B, C, 2H, 2W]`, each output the 0.75 / 0.25 blend of its input and the nearer
    /// neighbour, clamped at the borders.
    fn upsample2(x: FloatTensor<Self>) -> FloatTensor<Self>;
    /// The triplane lookup (`triplane::sample_triplanes`) at texel coordinates: `planes`
    /// `[B, 3·C, R, R]`, `texels` `[B, N, 3]` (a point's box coordinates mapped to texels,
    /// `align_corners = false`) → `[B, N, C]`, the sum over the three planes of the bilinear
    /// sample, zero outside.
    fn triplane_bilinear(planes: FloatTensor<Self>, texels: FloatTensor<Self>) -> FloatTensor<Self>;
}

/// [`NdArrayOpsBackend::conv2d_same`] on tensors (NdArray's, or autodiff over NdArray).
pub fn conv2d_same(x: Tensor<4>, weight: Tensor<5>) -> Tensor<4> {
    Tensor::from_dispatch(<Dispatch as NdArrayOpsBackend>::conv2d_same(x.into_dispatch(), weight.into_dispatch()))
}

/// [`NdArrayOpsBackend::avg_pool2x2`] on tensors.
pub fn avg_pool2x2(x: Tensor<4>) -> Tensor<4> {
    Tensor::from_dispatch(<Dispatch as NdArrayOpsBackend>::avg_pool2x2(x.into_dispatch()))
}

/// [`NdArrayOpsBackend::bias_lrelu`] on tensors.
pub fn bias_lrelu(x: Tensor<4>, bias: Tensor<1>) -> Tensor<4> {
    Tensor::from_dispatch(<Dispatch as NdArrayOpsBackend>::bias_lrelu(x.into_dispatch(), bias.into_dispatch()))
}

/// [`NdArrayOpsBackend::upsample2`] on tensors.
pub fn upsample2(x: Tensor<4>) -> Tensor<4> {
    Tensor::from_dispatch(<Dispatch as NdArrayOpsBackend>::upsample2(x.into_dispatch()))
}

/// [`NdArrayOpsBackend::triplane_bilinear`] on tensors.
pub fn triplane_bilinear(planes: Tensor<4>, texels: Tensor<3>) -> Tensor<3> {
    Tensor::from_dispatch(<Dispatch as NdArrayOpsBackend>::triplane_bilinear(
        planes.into_dispatch(),
        texels.into_dispatch(),
    ))
}

/// Leaky ReLU's negative slope and StyleGAN's gain, as [`super::layers::lrelu_gain`] uses them.
const SLOPE: f32 = 0.2;
const GAIN: f32 = std::f32::consts::SQRT_2;

/// `lrelu(x + bias[c]) · gain` over `[B, C, plane]`.
pub fn bias_lrelu_forward(channels: usize, plane: usize, x: &[f32], bias: &[f32]) -> Vec<f32> {
    let mut y = vec![0.0; x.len()];
    for (i, (ys, xs)) in y.chunks_mut(plane).zip(x.chunks(plane)).enumerate() {
        let b = bias[i % channels];
        for (y, x) in ys.iter_mut().zip(xs) {
            let t = x + b;
            *y = t * if t > 0.0 { GAIN } else { SLOPE * GAIN };
        }
    }
    y
}

/// The gradients of `x` and `bias` given the forward output `y` and its gradient `dy`.
pub fn bias_lrelu_backward(channels: usize, plane: usize, y: &[f32], dy: &[f32]) -> (Vec<f32>, Vec<f32>) {
    let mut dx = vec![0.0; dy.len()];
    let mut db = vec![0.0f32; channels];
    for (i, ((dxs, ys), gs)) in dx.chunks_mut(plane).zip(y.chunks(plane)).zip(dy.chunks(plane)).enumerate() {
        for ((d, y), g) in dxs.iter_mut().zip(ys).zip(gs) {
            *d = g * if *y > 0.0 { GAIN } else { SLOPE * GAIN };
        }
        db[i % channels] += lane_sum(dxs);
    }
    (dx, db)
}

/// A sum in eight interleaved partial sums (vectorisable, and more accurate than one running
/// sum over a whole plane).
fn lane_sum(v: &[f32]) -> f32 {
    let mut lanes = [0.0f32; 8];
    let chunks = v.chunks_exact(8);
    let tail: f32 = chunks.remainder().iter().sum();
    for c in chunks {
        for (l, x) in lanes.iter_mut().zip(c) {
            *l += x;
        }
    }
    lanes.iter().sum::<f32>() + tail
}

/// A convolution's sizes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ConvDims {
    pub batch: usize,
    pub c_in: usize,
    pub c_out: usize,
    pub h: usize,
    pub w: usize,
    pub k: usize,
    /// One weight for the whole batch (`[1, out, in, k, k]`) rather than one per sample.
    pub shared: bool,
}

impl ConvDims {
    fn of(x: &[usize], weight: &[usize]) -> Self {
        Self { batch: x[0], c_in: x[1], c_out: weight[1], h: x[2], w: x[3], k: weight[3], shared: weight[0] == 1 }
    }
    fn hw(&self) -> usize {
        self.h * self.w
    }
    /// Rows of the column matrix: (in, ky, kx), the weight's order.
    fn taps(&self) -> usize {
        self.c_in * self.k * self.k
    }
    fn weight_len(&self) -> usize {
        self.c_out * self.taps()
    }
    /// Sample `n`'s weight matrix `[out, in·k·k]` within the weight buffer.
    fn weight_of<'a>(&self, weight: &'a [f32], n: usize) -> &'a [f32] {
        let s = if self.shared { 0 } else { n * self.weight_len() };
        &weight[s..s + self.weight_len()]
    }
}

/// im2col of one sample `x_n` `[in, H, W]` into `cols` `[in·k·k, H·W]` (zero padding),
/// replacing what `cols` held (each value written once: the buffer is never zero-filled first).
fn im2col(d: &ConvDims, x_n: &[f32], cols: &mut Vec<f32>) {
    let (h, w, k, pad) = (d.h, d.w, d.k, d.k / 2);
    cols.clear();
    cols.reserve(d.taps() * h * w);
    let zeros = |cols: &mut Vec<f32>, n: usize| cols.extend(std::iter::repeat_n(0.0, n));
    for c in 0..d.c_in {
        let plane = &x_n[c * h * w..(c + 1) * h * w];
        for ky in 0..k {
            for kx in 0..k {
                // Output x reads input x + kx − pad: valid for x in [x0, x1).
                let x0 = pad.saturating_sub(kx);
                let x1 = (w + pad).saturating_sub(kx).min(w);
                for y in 0..h {
                    let sy = y + ky;
                    if sy < pad || sy - pad >= h || x0 >= x1 {
                        zeros(cols, w);
                        continue;
                    }
                    let src = &plane[(sy - pad) * w..(sy - pad + 1) * w];
                    zeros(cols, x0);
                    cols.extend_from_slice(&src[x0 + kx - pad..x1 + kx - pad]);
                    zeros(cols, w - x1);
                }
            }
        }
    }
}

/// The adjoint of [`im2col`]: adds the columns' gradient `cols` into `dx_n` `[in, H, W]`.
fn col2im(d: &ConvDims, cols: &[f32], dx_n: &mut [f32]) {
    let (h, w, k, pad) = (d.h, d.w, d.k, d.k / 2);
    for c in 0..d.c_in {
        let plane = &mut dx_n[c * h * w..(c + 1) * h * w];
        for ky in 0..k {
            for kx in 0..k {
                let row = &cols[((c * k + ky) * k + kx) * h * w..][..h * w];
                let x0 = pad.saturating_sub(kx);
                let x1 = (w + pad).saturating_sub(kx).min(w);
                for y in 0..h {
                    let sy = y + ky;
                    if sy < pad || sy - pad >= h || x0 >= x1 {
                        continue;
                    }
                    let dst = &mut plane[(sy - pad) * w + x0 + kx - pad..(sy - pad) * w + x1 + kx - pad];
                    for (a, g) in dst.iter_mut().zip(&row[y * w + x0..y * w + x1]) {
                        *a += g;
                    }
                }
            }
        }
    }
}

/// `c (m×n) = alpha·a (m×k) · b (k×n) + beta·c`, each operand given by its row and column strides.
#[allow(clippy::too_many_arguments)]
fn gemm(m: usize, k: usize, n: usize, a: (&[f32], isize, isize), b: (&[f32], isize, isize), beta: f32, c: &mut [f32]) {
    debug_assert!(c.len() >= m * n);
    // SAFETY: the callers pass buffers of at least the extents the strides address: `a` covers
    // m×k, `b` k×n and `c` m×n elements (row-major `c`, checked above), as the shapes in
    // `ConvDims` give them.
    unsafe {
        matrixmultiply::sgemm(
            m,
            k,
            n,
            1.0,
            a.0.as_ptr(),
            a.1,
            a.2,
            b.0.as_ptr(),
            b.1,
            b.2,
            beta,
            c.as_mut_ptr(),
            n as isize,
            1,
        );
    }
}

/// `f(n, out_n, scratch)` for each sample `n` of a batch, `out_n` being the sample's
/// `out.len() / batch` values of `out`. Natively the samples are spread over the CPU cores
/// (each thread with its own `scratch`), in the browser they run one after another. Each
/// sample's values depend only on that sample, so they are the same for any number of threads.
fn for_samples(batch: usize, out: &mut [f32], f: impl Fn(usize, &mut [f32], &mut Vec<f32>) + Sync) {
    if batch == 0 {
        return;
    }
    for_parts(out, out.len() / batch, 8, f);
}

/// `f(n, part_n, scratch)` for each consecutive part of `out` `per` values long (the last one
/// shorter where `per` does not divide it), natively on up to `max_threads` CPU cores, in the
/// browser one after another.
fn for_parts(out: &mut [f32], per: usize, max_threads: usize, f: impl Fn(usize, &mut [f32], &mut Vec<f32>) + Sync) {
    #[cfg(not(target_arch = "wasm32"))]
    let threads = {
        let parts = out.len().div_ceil(per.max(1)).max(1);
        std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1).clamp(1, max_threads).min(parts)
    };
    #[cfg(target_arch = "wasm32")]
    let threads = {
        let _ = max_threads;
        1
    };
    let mut shares: Vec<Vec<(usize, &mut [f32])>> = (0..threads).map(|_| Vec::new()).collect();
    for (n, out_n) in out.chunks_mut(per.max(1)).enumerate() {
        shares[n % threads].push((n, out_n));
    }
    let work = |share: Vec<(usize, &mut [f32])>| {
        let mut scratch = Vec::new();
        for (n, out_n) in share {
            f(n, out_n, &mut scratch);
        }
    };
    if threads == 1 {
        shares.into_iter().for_each(work);
        return;
    }
    std::thread::scope(|sc| {
        let work = &work;
        let handles: Vec<_> = shares.into_iter().map(|share| sc.spawn(move || work(share))).collect();
        // A worker's panic is a bug: re-raise it here rather than leave its part unwritten.
        for h in handles {
            h.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic));
        }
    });
}

/// Output pixels per part of a one-sample convolution's product in [`forward`].
const CONV_COLUMNS_PER_PART: usize = 1024;

/// The forward pass on plain buffers: `x` `[B, in, H, W]`, `weight` `[B or 1, out, in, k, k]`
/// → `[B, out, H, W]`.
pub fn forward(d: &ConvDims, x: &[f32], weight: &[f32]) -> Vec<f32> {
    let (hw, taps) = (d.hw(), d.taps());
    let mut y = vec![0.0; d.batch * d.c_out * hw];
    if d.batch == 1 && hw >= 2 * CONV_COLUMNS_PER_PART {
        // One sample (a generation): the product in column blocks over the cores (each block
        // packs only its share of the columns), each value summed as in one product.
        let mut cols = Vec::new();
        im2col(d, &x[..d.c_in * hw], &mut cols);
        let (w, m, nb) = (d.weight_of(weight, 0), d.c_out, CONV_COLUMNS_PER_PART);
        let mut blocks = vec![0.0; m * hw];
        for_parts(&mut blocks, m * nb, 16, |part, block, _| {
            let width = block.len() / m;
            gemm(m, taps, width, (w, taps as isize, 1), (&cols[part * nb..], hw as isize, 1), 0.0, block);
        });
        for (part, block) in blocks.chunks(m * nb).enumerate() {
            let width = block.len() / m;
            for (row, src) in block.chunks_exact(width).enumerate() {
                y[row * hw + part * nb..][..width].copy_from_slice(src);
            }
        }
        return y;
    }
    for_samples(d.batch, &mut y, |n, y_n, cols| {
        im2col(d, &x[n * d.c_in * hw..(n + 1) * d.c_in * hw], cols);
        gemm(d.c_out, taps, hw, (d.weight_of(weight, n), taps as isize, 1), (cols, hw as isize, 1), 0.0, y_n);
    });
    y
}

/// The backward pass on plain buffers: given `dy` `[B, out, H, W]`, the gradients of `x` and
/// of `weight` (each only when asked for; ∂w shaped like `weight`, summed over the batch in
/// sample order when it is shared).
pub fn backward(
    d: &ConvDims,
    x: &[f32],
    weight: &[f32],
    dy: &[f32],
    want_x: bool,
    want_w: bool,
) -> (Option<Vec<f32>>, Option<Vec<f32>>) {
    let (hw, taps) = (d.hw(), d.taps());
    let dy_of = |n: usize| &dy[n * d.c_out * hw..(n + 1) * d.c_out * hw];
    let dw = want_w.then(|| {
        // ∂w_n = dy_n · colsᵀ, per sample; a shared weight's is their sum in sample order.
        let mut dw = vec![0.0; d.batch * d.weight_len()];
        for_samples(d.batch, &mut dw, |n, dw_n, cols| {
            im2col(d, &x[n * d.c_in * hw..(n + 1) * d.c_in * hw], cols);
            gemm(d.c_out, hw, taps, (dy_of(n), hw as isize, 1), (cols, 1, hw as isize), 0.0, dw_n);
        });
        if d.shared {
            let (sum, rest) = dw.split_at_mut(d.weight_len());
            for dw_n in rest.chunks(d.weight_len()) {
                for (s, g) in sum.iter_mut().zip(dw_n) {
                    *s += g;
                }
            }
            dw.truncate(d.weight_len());
        }
        dw
    });
    let dx = want_x.then(|| {
        // ∂cols = w_nᵀ · dy_n, folded back onto the input.
        let mut dx = vec![0.0; d.batch * d.c_in * hw];
        for_samples(d.batch, &mut dx, |n, dx_n, cols| {
            cols.resize(taps * hw, 0.0);
            gemm(taps, d.c_out, hw, (d.weight_of(weight, n), 1, taps as isize), (dy_of(n), hw as isize, 1), 0.0, cols);
            col2im(d, cols, dx_n);
        });
        dx
    });
    (dx, dw)
}

/// 2×2 average pooling of `[planes, H, W]` → `[planes, H/2, W/2]`.
pub fn pool_forward(planes: usize, h: usize, w: usize, x: &[f32]) -> Vec<f32> {
    let (ho, wo) = (h / 2, w / 2);
    let mut y = vec![0.0; planes * ho * wo];
    for p in 0..planes {
        for i in 0..ho {
            let r0 = &x[(p * h + 2 * i) * w..][..w];
            let r1 = &x[(p * h + 2 * i + 1) * w..][..w];
            let out = &mut y[(p * ho + i) * wo..][..wo];
            for (j, o) in out.iter_mut().enumerate() {
                *o = 0.25 * (r0[2 * j] + r0[2 * j + 1] + r1[2 * j] + r1[2 * j + 1]);
            }
        }
    }
    y
}

/// The adjoint of [`pool_forward`]: each output's gradient, a quarter to each of its four inputs.
pub fn pool_backward(planes: usize, h: usize, w: usize, dy: &[f32]) -> Vec<f32> {
    let (ho, wo) = (h / 2, w / 2);
    let mut dx = vec![0.0; planes * h * w];
    for p in 0..planes {
        for i in 0..ho {
            let g = &dy[(p * ho + i) * wo..][..wo];
            for r in [2 * i, 2 * i + 1] {
                let row = &mut dx[(p * h + r) * w..][..w];
                for (j, g) in g.iter().enumerate() {
                    row[2 * j] = 0.25 * g;
                    row[2 * j + 1] = 0.25 * g;
                }
            }
        }
    }
    dx
}

/// The two inputs of output `k` of a 2× upsampling along an axis of length `n`: its own input
/// `k / 2` (weight 0.75) and the nearer neighbour, clamped at the ends (weight 0.25).
fn up_taps(k: usize, n: usize) -> (usize, usize) {
    let i = k / 2;
    (i, if k % 2 == 0 { i.saturating_sub(1) } else { (i + 1).min(n - 1) })
}

/// 2× bilinear upsampling of `[planes, H, W]` → `[planes, 2H, 2W]`, along H then along W with
/// the same products and sums as `synthesis::upsample_dim` twice (so the same bits).
pub fn upsample2_forward(planes: usize, h: usize, w: usize, x: &[f32]) -> Vec<f32> {
    let (h2, w2) = (2 * h, 2 * w);
    let mut tall = vec![0.0f32; h2 * w];
    let mut y = vec![0.0f32; planes * h2 * w2];
    for p in 0..planes {
        let xp = &x[p * h * w..][..h * w];
        for (k, out) in tall.chunks_exact_mut(w).enumerate() {
            let (i, j) = up_taps(k, h);
            let (a, b) = (&xp[i * w..][..w], &xp[j * w..][..w]);
            for ((o, a), b) in out.iter_mut().zip(a).zip(b) {
                *o = a * 0.75 + b * 0.25;
            }
        }
        let yp = &mut y[p * h2 * w2..][..h2 * w2];
        for (out, src) in yp.chunks_exact_mut(w2).zip(tall.chunks_exact(w)) {
            for (k, o) in out.iter_mut().enumerate() {
                let (i, j) = up_taps(k, w);
                *o = src[i] * 0.75 + src[j] * 0.25;
            }
        }
    }
    y
}

/// The adjoint of [`upsample2_forward`]: each output's gradient back to its inputs with the
/// same weights, along W then along H.
pub fn upsample2_backward(planes: usize, h: usize, w: usize, dy: &[f32]) -> Vec<f32> {
    let (h2, w2) = (2 * h, 2 * w);
    let mut tall = vec![0.0f32; h2 * w];
    let mut dx = vec![0.0f32; planes * h * w];
    for p in 0..planes {
        tall.fill(0.0);
        let gp = &dy[p * h2 * w2..][..h2 * w2];
        for (acc, g) in tall.chunks_exact_mut(w).zip(gp.chunks_exact(w2)) {
            for (k, g) in g.iter().enumerate() {
                let (i, j) = up_taps(k, w);
                acc[i] += 0.75 * g;
                acc[j] += 0.25 * g;
            }
        }
        let dp = &mut dx[p * h * w..][..h * w];
        for (k, g) in tall.chunks_exact(w).enumerate() {
            let (i, j) = up_taps(k, h);
            for (r, wt) in [(i, 0.75f32), (j, 0.25)] {
                for (acc, g) in dp[r * w..][..w].iter_mut().zip(g) {
                    *acc += wt * g;
                }
            }
        }
    }
    dx
}

/// Sizes of a triplane lookup: batch, points per sample, channels per plane, plane side.
#[derive(Clone, Copy, Debug)]
pub struct TriplaneDims {
    pub batch: usize,
    pub points: usize,
    pub channels: usize,
    pub res: usize,
}

/// (horizontal, vertical) texel axes of the planes (x,y), (y,z), (x,z): `triplane::PLANE_AXES`.
const TRIPLANE_AXES: [[usize; 2]; 3] = [[0, 1], [1, 2], [0, 2]];

/// Each plane's bilinear stencil at point `(bi, ni)`: for plane k, the four texels' indices
/// into the `B·3·R·R` texels of all planes (None outside the plane) with their weights, and
/// the weights' derivatives along the plane's two axes (for the texel coordinates' gradient).
#[allow(clippy::type_complexity)]
fn triplane_stencil(
    d: &TriplaneDims,
    texels: &[f32],
    bi: usize,
    ni: usize,
    k: usize,
) -> ([(Option<usize>, f32, f32, f32); 4], [usize; 2]) {
    let t = &texels[(bi * d.points + ni) * 3..][..3];
    let [au, av] = TRIPLANE_AXES[k];
    let (u, v) = (t[au], t[av]);
    let (u0, v0) = (u.floor(), v.floor());
    let (fu, fv) = (u - u0, v - v0);
    let (gu, gv) = (-fu + 1.0, -fv + 1.0);
    let r = d.res as i64;
    let base = (bi * 3 + k) * d.res * d.res;
    let at = |y: f32, x: f32| -> Option<usize> {
        let (y, x) = (y as i64, x as i64);
        ((0..r).contains(&y) && (0..r).contains(&x)).then(|| base + (y * r + x) as usize)
    };
    // (texel, weight, ∂weight/∂u, ∂weight/∂v) in the row-table sampler's order.
    (
        [
            (at(v0, u0), gu * gv, -gv, -gu),
            (at(v0, u0 + 1.0), fu * gv, gv, -fu),
            (at(v0 + 1.0, u0), gu * fv, -fv, gu),
            (at(v0 + 1.0, u0 + 1.0), fu * fv, fv, fu),
        ],
        [au, av],
    )
}

/// Planes `[B·3, C, R, R]` (the tensors' layout) as `[B·3, R, R, C]`: each texel's channels
/// side by side, as the lookup reads and writes them (a texel's 16 channels in one cache line
/// instead of 16 lines a plane apart).
fn channels_last(d: &TriplaneDims, planes: &[f32]) -> Vec<f32> {
    let (c, plane) = (d.channels, d.res * d.res);
    let mut out = vec![0.0f32; planes.len()];
    for (p, src) in planes.chunks(c * plane).enumerate() {
        let dst = &mut out[p * c * plane..][..c * plane];
        for ch in 0..c {
            for (t, v) in src[ch * plane..][..plane].iter().enumerate() {
                dst[t * c + ch] = *v;
            }
        }
    }
    out
}

/// The inverse of [`channels_last`].
fn channels_first(d: &TriplaneDims, last: &[f32]) -> Vec<f32> {
    let (c, plane) = (d.channels, d.res * d.res);
    let mut out = vec![0.0f32; last.len()];
    for (p, src) in last.chunks(c * plane).enumerate() {
        let dst = &mut out[p * c * plane..][..c * plane];
        for (t, texel) in src.chunks(c).enumerate() {
            for (ch, v) in texel.iter().enumerate() {
                dst[ch * plane + t] = *v;
            }
        }
    }
    out
}

/// Points per part of [`triplane_forward`]'s work (a thread's share is whole parts).
const TRIPLANE_POINTS_PER_PART: usize = 4096;

/// The lookup's values `[B, N, C]`, natively in parts of [`TRIPLANE_POINTS_PER_PART`] points
/// over the CPU cores (a point's value does not depend on the part it is in).
pub fn triplane_forward(d: &TriplaneDims, planes: &[f32], texels: &[f32]) -> Vec<f32> {
    let c = d.channels;
    let last = channels_last(d, planes);
    let mut y = vec![0.0f32; d.batch * d.points * c];
    if c == 0 || d.points == 0 {
        return y;
    }
    for_parts(&mut y, TRIPLANE_POINTS_PER_PART * c, 16, |part, y_part, _| {
        for (i, out) in y_part.chunks_exact_mut(c).enumerate() {
            let q = part * TRIPLANE_POINTS_PER_PART + i;
            let (bi, ni) = (q / d.points, q % d.points);
            for k in 0..3 {
                let (stencil, _) = triplane_stencil(d, texels, bi, ni, k);
                for (texel, w, _, _) in stencil {
                    if let Some(t) = texel {
                        for (acc, p) in out.iter_mut().zip(&last[t * c..][..c]) {
                            *acc += w * p;
                        }
                    }
                }
            }
        }
    });
    y
}

/// The lookup's gradients for the planes and the texel coordinates, each only when asked
/// (each avatar of the batch on its own core natively; the sums run in the same order as one
/// thread's, so the values do not depend on the cores).
pub fn triplane_backward(
    d: &TriplaneDims,
    planes: &[f32],
    texels: &[f32],
    dy: &[f32],
    want_planes: bool,
    want_texels: bool,
) -> (Option<Vec<f32>>, Option<Vec<f32>>) {
    let (c, plane) = (d.channels, d.res * d.res);
    let dp = want_planes.then(|| {
        let mut acc = vec![0.0f32; d.batch * 3 * c * plane];
        for_samples(d.batch, &mut acc, |bi, acc_b, _| {
            let first = bi * 3 * plane;
            for ni in 0..d.points {
                let g = &dy[(bi * d.points + ni) * c..][..c];
                for k in 0..3 {
                    let (stencil, _) = triplane_stencil(d, texels, bi, ni, k);
                    for (texel, w, _, _) in stencil {
                        let Some(t) = texel else { continue };
                        for (a, g) in acc_b[(t - first) * c..][..c].iter_mut().zip(g) {
                            *a += w * g;
                        }
                    }
                }
            }
        });
        channels_first(d, &acc)
    });
    let dt = want_texels.then(|| {
        let last = channels_last(d, planes);
        let mut dt = vec![0.0f32; d.batch * d.points * 3];
        for_samples(d.batch, &mut dt, |bi, dt_b, _| {
            for ni in 0..d.points {
                let g = &dy[(bi * d.points + ni) * c..][..c];
                let t3 = &mut dt_b[ni * 3..][..3];
                for k in 0..3 {
                    let (stencil, [au, av]) = triplane_stencil(d, texels, bi, ni, k);
                    for (texel, _, dw_du, dw_dv) in stencil {
                        let Some(t) = texel else { continue };
                        let dot: f32 = g.iter().zip(&last[t * c..][..c]).map(|(g, p)| g * p).sum();
                        t3[au] += dw_du * dot;
                        t3[av] += dw_dv * dot;
                    }
                }
            }
        });
        dt
    });
    (dp, dt)
}

/// A `[B, C, H, W]` shape as (planes, H, W).
fn planes(shape: &[usize]) -> (usize, usize, usize) {
    (shape[0] * shape[1], shape[2], shape[3])
}

/// An NdArray float tensor's shape and values (borrowed when contiguous, as they nearly
/// always are; f64 tensors converted).
fn values(t: &NdArrayTensor) -> (Vec<usize>, Cow<'_, [f32]>) {
    match t {
        NdArrayTensor::F32(s) => {
            let view = s.view();
            let v = match view.to_slice() {
                Some(v) => Cow::Borrowed(v),
                None => Cow::Owned(view.iter().copied().collect()),
            };
            (s.shape().to_vec(), v)
        }
        NdArrayTensor::F64(s) => (s.shape().to_vec(), Cow::Owned(s.view().iter().map(|v| *v as f32).collect())),
        other => unreachable!("a float tensor of NdArray holds floats, not {:?}", other.dtype()),
    }
}

fn tensor(v: Vec<f32>, shape: Vec<usize>) -> NdArrayTensor {
    NdArrayTensor::from_data(TensorData::new(v, shape))
}

impl NdArrayOpsBackend for NdArray {
    fn conv2d_same(x: FloatTensor<Self>, weight: FloatTensor<Self>) -> FloatTensor<Self> {
        let ((xs, x), (ws, w)) = (values(&x), values(&weight));
        let d = ConvDims::of(&xs, &ws);
        tensor(forward(&d, &x, &w), vec![d.batch, d.c_out, d.h, d.w])
    }

    fn avg_pool2x2(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let (shape, x) = values(&x);
        let (p, h, w) = planes(&shape);
        tensor(pool_forward(p, h, w, &x), vec![shape[0], shape[1], h / 2, w / 2])
    }

    fn bias_lrelu(x: FloatTensor<Self>, bias: FloatTensor<Self>) -> FloatTensor<Self> {
        let ((shape, x), (_, b)) = (values(&x), values(&bias));
        let (c, plane) = (shape[1], shape[2..].iter().product());
        tensor(bias_lrelu_forward(c, plane, &x, &b), shape)
    }

    fn upsample2(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let (shape, x) = values(&x);
        let (p, h, w) = planes(&shape);
        tensor(upsample2_forward(p, h, w, &x), vec![shape[0], shape[1], 2 * h, 2 * w])
    }

    fn triplane_bilinear(planes: FloatTensor<Self>, texels: FloatTensor<Self>) -> FloatTensor<Self> {
        let ((ps, p), (ts, t)) = (values(&planes), values(&texels));
        let d = TriplaneDims::of(&ps, &ts);
        tensor(triplane_forward(&d, &p, &t), vec![d.batch, d.points, d.channels])
    }
}

impl TriplaneDims {
    /// From the planes' `[B, 3·C, R, R]` and the texel coordinates' `[B, N, 3]` shapes.
    fn of(planes: &[usize], texels: &[usize]) -> Self {
        Self { batch: planes[0], points: texels[1], channels: planes[1] / 3, res: planes[2] }
    }
}

#[cfg(feature = "autodiff")]
mod autodiff;

#[cfg(test)]
mod tests {
    use super::*;

    /// The upsampling against its definition (each output from its two taps), and its
    /// backward pass against the adjoint identity ⟨up(x), dy⟩ = ⟨x, up*(dy)⟩, exact for a
    /// linear map, on odd and even sizes and a 1-wide axis.
    #[test]
    fn upsample2_matches_its_definition_and_its_backward_is_the_adjoint() {
        for (planes, h, w) in [(2, 3, 4), (1, 1, 5), (3, 4, 1), (1, 2, 2)] {
            let x: Vec<f32> = (0..planes * h * w).map(|i| ((i * 37 % 11) as f32) - 5.0).collect();
            let y = upsample2_forward(planes, h, w, &x);
            assert_eq!(y.len(), planes * 4 * h * w);
            let at = |p: usize, r: usize, c: usize| x[(p * h + r) * w + c];
            for p in 0..planes {
                for r2 in 0..2 * h {
                    for c2 in 0..2 * w {
                        let ((ri, rj), (ci, cj)) = (up_taps(r2, h), up_taps(c2, w));
                        let want = 0.75 * (0.75 * at(p, ri, ci) + 0.25 * at(p, ri, cj))
                            + 0.25 * (0.75 * at(p, rj, ci) + 0.25 * at(p, rj, cj));
                        let got = y[(p * 2 * h + r2) * 2 * w + c2];
                        assert!((got - want).abs() < 1e-5, "{planes}×{h}×{w} at {p},{r2},{c2}: {got} vs {want}");
                    }
                }
            }
            // The first output row and column repeat the input's border (clamped taps).
            assert_eq!(y[0], x[0]);
            let dy: Vec<f32> = (0..y.len()).map(|i| ((i * 13 % 7) as f32) * 0.5 - 1.0).collect();
            let dx = upsample2_backward(planes, h, w, &dy);
            let lhs: f64 = y.iter().zip(&dy).map(|(a, b)| (*a as f64) * (*b as f64)).sum();
            let rhs: f64 = x.iter().zip(&dx).map(|(a, b)| (*a as f64) * (*b as f64)).sum();
            assert!((lhs - rhs).abs() < 1e-3 * lhs.abs().max(1.0), "{planes}×{h}×{w}: {lhs} vs {rhs}");
        }
    }

    /// `n` values in [−0.5, 0.5) per call from a linear congruential sequence started at `seed`.
    fn uniform_values(seed: u32) -> impl FnMut(usize) -> Vec<f32> {
        let mut s = seed;
        move |n| {
            (0..n)
                .map(|_| {
                    s = s.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                    (s >> 8) as f32 / (1u32 << 24) as f32 - 0.5
                })
                .collect()
        }
    }

    /// One sample's product in column blocks over the cores (a generation) gives, bit for
    /// bit, what the same sample gives as one product inside a batch, for a width that leaves
    /// a short last block.
    #[test]
    fn a_single_sample_in_column_blocks_equals_one_product() {
        let (h, w) = (40, 61);
        assert!(h * w >= 2 * CONV_COLUMNS_PER_PART && (h * w) % CONV_COLUMNS_PER_PART != 0);
        let one = ConvDims { batch: 1, c_in: 5, c_out: 7, h, w, k: 3, shared: true };
        let two = ConvDims { batch: 2, ..one };
        let mut rnd = uniform_values(3);
        let x = rnd(two.batch * two.c_in * h * w);
        let wt = rnd(one.weight_len());
        let alone = forward(&one, &x[..one.c_in * h * w], &wt);
        let batched = forward(&two, &x, &wt);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&alone), bits(&batched[..alone.len()]));
        assert!(alone.iter().any(|v| v.abs() > 0.1), "a product, not zeros");
    }

    /// The plain-buffer passes against a direct loop convolution and its finite differences.
    #[test]
    fn forward_and_backward_match_a_direct_convolution() {
        for (shared, k, h, w) in [(true, 3, 5, 4), (false, 3, 4, 6), (true, 1, 3, 3), (false, 5, 3, 2)] {
            let d = ConvDims { batch: 2, c_in: 3, c_out: 2, h, w, k, shared };
            let mut rnd = uniform_values(1);
            let x = rnd(d.batch * d.c_in * h * w);
            let wt = rnd(if shared { 1 } else { d.batch } * d.weight_len());
            let dy = rnd(d.batch * d.c_out * h * w);
            let direct = |x: &[f32], wt: &[f32]| {
                let mut y = vec![0.0f32; d.batch * d.c_out * h * w];
                let p = (k / 2) as isize;
                for n in 0..d.batch {
                    let wn = d.weight_of(wt, n);
                    for o in 0..d.c_out {
                        for yy in 0..h as isize {
                            for xx in 0..w as isize {
                                let mut acc = 0.0;
                                for c in 0..d.c_in {
                                    for ky in 0..k as isize {
                                        for kx in 0..k as isize {
                                            let (sy, sx) = (yy + ky - p, xx + kx - p);
                                            if sy >= 0 && sy < h as isize && sx >= 0 && sx < w as isize {
                                                acc += wn[((o * d.c_in + c) * k + ky as usize) * k + kx as usize]
                                                    * x[((n * d.c_in + c) * h + sy as usize) * w + sx as usize];
                                            }
                                        }
                                    }
                                }
                                y[((n * d.c_out + o) * h + yy as usize) * w + xx as usize] = acc;
                            }
                        }
                    }
                }
                y
            };
            let y = forward(&d, &x, &wt);
            for (a, b) in y.iter().zip(direct(&x, &wt)) {
                assert!((a - b).abs() < 1e-5, "{d:?}: {a} vs {b}");
            }
            // The loss Σ y·dy is linear in x and in w, so central differences are exact up to rounding.
            let loss = |x: &[f32], wt: &[f32]| -> f64 {
                direct(x, wt).iter().zip(&dy).map(|(a, b)| (*a as f64) * (*b as f64)).sum()
            };
            let (dx, dw) = backward(&d, &x, &wt, &dy, true, true);
            let (dx, dw) = (dx.unwrap(), dw.unwrap());
            let eps = 1e-2f32;
            // The loss's central difference along coordinate i of w (of_w) or of x.
            let central = |of_w: bool, i: usize| -> f64 {
                let (mut p, mut m) = if of_w { (wt.clone(), wt.clone()) } else { (x.clone(), x.clone()) };
                p[i] += eps;
                m[i] -= eps;
                let (lp, lm) = if of_w { (loss(&x, &p), loss(&x, &m)) } else { (loss(&p, &wt), loss(&m, &wt)) };
                (lp - lm) / (2.0 * eps as f64)
            };
            for (what, of_w, grads) in [("∂x", false, &dx), ("∂w", true, &dw)] {
                for (i, g) in grads.iter().enumerate() {
                    let fd = central(of_w, i);
                    assert!((*g as f64 - fd).abs() < 1e-3, "{d:?} {what}[{i}]: {g} vs {fd}");
                }
            }
            // Only what is asked for.
            assert_eq!(backward(&d, &x, &wt, &dy, false, true).0, None);
            assert_eq!(backward(&d, &x, &wt, &dy, true, false).1, None);
        }
    }
}
