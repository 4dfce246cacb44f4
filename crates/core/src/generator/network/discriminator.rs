//! The discriminators of the paper's adversarial objective (Sec. 4.5): StyleGAN2's residual
//! discriminator, conditioned on the camera (the 16 world-to-camera numbers) through a small
//! mapping network and a projection head. GETAvatar trains three of them: on RGB images,
//! on normal maps and on masks (`in_channels` 3, 3 and 1).
//!
//! Differences from StyleGAN2-ADA, stated: downsampling is a 2×2 average pool after the conv
//! (StyleGAN2 blurs with a [1, 3, 3, 1] FIR filter before a strided conv), and the camera
//! mapping has `mapping_layers` layers (the reference uses its default of 8 on 512-d).

use burn::module::{Module, Param};
use burn::tensor::module::avg_pool2d;
use burn::tensor::ops::AvgPoolOptions;
use burn::tensor::{Device, Tensor};
use serde::{Deserialize, Serialize};

use super::init::{full, randn, Rng};
use super::layers::{bias_lrelu, conv2d_same, lrelu_gain, FullyConnected};

/// Discriminator sizes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DiscriminatorConfig {
    /// Input resolution (power of two ≥ 8).
    pub resolution: usize,
    /// Channels at resolution r: min(channel_base / r, channel_max).
    pub channel_base: usize,
    pub channel_max: usize,
    /// Camera conditioning: label size (16) and projection size.
    pub c_dim: usize,
    pub cmap_dim: usize,
    pub mapping_layers: usize,
    /// Minibatch-standard-deviation group size (≤; reduced to divide the batch).
    pub mbstd_group: usize,
}

impl DiscriminatorConfig {
    pub fn new(resolution: usize, channel_base: usize, channel_max: usize) -> Self {
        Self { resolution, channel_base, channel_max, c_dim: 16, cmap_dim: 64, mapping_layers: 2, mbstd_group: 4 }
    }

    pub fn channels(&self, res: usize) -> usize {
        (self.channel_base / res.max(1)).clamp(1, self.channel_max.max(1))
    }

    /// A config read from a file: a power-of-two resolution in 8…4096, at least one channel,
    /// label and projection sizes in 1…1024, at most 16 mapping layers, a group size in
    /// 1…64 (a `channel_max` of 0 once reached `clamp(1, 0)`: the `checkpoint` fuzz target).
    pub fn validate(&self) -> Result<(), String> {
        if !(self.resolution.is_power_of_two() && (8..=4096).contains(&self.resolution)) {
            return Err(format!("resolution {} is not a power of two in 8..=4096", self.resolution));
        }
        let checks = [
            ("channel_base", self.channel_base, 1, usize::MAX),
            ("channel_max", self.channel_max, 1, usize::MAX),
            ("c_dim", self.c_dim, 1, 1024),
            ("cmap_dim", self.cmap_dim, 1, 1024),
            ("mapping_layers", self.mapping_layers, 0, 16),
            ("mbstd_group", self.mbstd_group, 1, 64),
        ];
        for (name, v, lo, hi) in checks {
            if !(lo..=hi).contains(&v) {
                return Err(format!("{name} {v} is outside {lo}..={hi}"));
            }
        }
        Ok(())
    }

    /// How many numbers [`Discriminator::new`] allocates for this config (None on overflow):
    /// loaders compare it with what a file holds before building anything, so a config
    /// claiming a huge network in a small file is refused.
    pub fn num_params(&self, in_channels: usize) -> Option<usize> {
        let conv = |cin: usize, cout: usize, k: usize, bias: bool| {
            cin.checked_mul(cout)?.checked_mul(k * k)?.checked_add(if bias { cout } else { 0 })
        };
        let fc = |d_in: usize, d_out: usize| d_in.checked_mul(d_out)?.checked_add(d_out);
        if !self.resolution.is_power_of_two() || self.resolution < 8 {
            return None;
        }
        let mut n = conv(in_channels, self.channels(self.resolution), 1, true)?;
        let mut res = self.resolution;
        while res > 4 {
            let (cin, cout) = (self.channels(res), self.channels(res / 2));
            for part in [conv(cin, cin, 3, true)?, conv(cin, cout, 3, true)?, conv(cin, cout, 1, false)?] {
                n = n.checked_add(part)?;
            }
            res /= 2;
        }
        let c4 = self.channels(4);
        let mut d = self.c_dim;
        for _ in 0..self.mapping_layers.max(1) {
            n = n.checked_add(fc(d, self.cmap_dim)?)?;
            d = self.cmap_dim;
        }
        for part in [conv(c4 + 1, c4, 3, true)?, fc(c4.checked_mul(16)?, c4)?, fc(c4, self.cmap_dim)?] {
            n = n.checked_add(part)?;
        }
        Some(n)
    }
}

/// 2× downsampling: 2×2 average pooling (on NdArray one operation with its own backward,
/// [`super::ndarray_ops`]).
fn down2(x: Tensor<4>) -> Tensor<4> {
    #[cfg(feature = "ndarray")]
    if super::layers::is_ndarray(&x.device()) {
        return super::ndarray_ops::avg_pool2x2(x);
    }
    avg_pool2d(x, AvgPoolOptions::new([2, 2]))
}

/// Equalised-learning-rate convolution (`k`×`k`, same padding), optional bias, leaky ReLU
/// with gain, optional 2× downsampling after the conv.
#[derive(Module, Debug)]
pub struct Conv2dLayer {
    /// `[out, in, k, k]`
    pub weight: Param<Tensor<4>>,
    /// `[out]` (absent on skip connections)
    pub bias: Option<Param<Tensor<1>>>,
    pub gain: f32,
    pub activation: bool,
    pub down: bool,
}

impl Conv2dLayer {
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        rng: &mut Rng,
        c_in: usize,
        c_out: usize,
        k: usize,
        use_bias: bool,
        activation: bool,
        down: bool,
        device: &Device,
    ) -> Self {
        Self {
            weight: Param::from_tensor(randn(rng, [c_out, c_in, k, k], 1.0, device)),
            bias: use_bias.then(|| Param::from_tensor(full([c_out], 0.0, device))),
            gain: 1.0 / ((c_in * k * k) as f32).sqrt(),
            activation,
            down,
        }
    }

    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let mut y = conv2d_same(x, (self.weight.val() * self.gain).unsqueeze_dim(0));
        // Pooling commutes with the per-channel bias, so the bias and activation go together
        // after it.
        if self.down {
            y = down2(y);
        }
        match &self.bias {
            Some(b) => bias_lrelu(y, b.val(), self.activation),
            None if self.activation => lrelu_gain(y),
            None => y,
        }
    }
}

/// Residual block: two 3×3 convs (the second downsamples) plus a 1×1 downsampled skip,
/// summed with gain √½.
#[derive(Module, Debug)]
pub struct DiscriminatorBlock {
    pub conv0: Conv2dLayer,
    pub conv1: Conv2dLayer,
    pub skip: Conv2dLayer,
}

impl DiscriminatorBlock {
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let s = self.skip.forward(down2(x.clone()));
        let y = self.conv1.forward(self.conv0.forward(x));
        (s + y) * std::f32::consts::FRAC_1_SQRT_2
    }
}

/// A conditional StyleGAN2 residual discriminator: image `[B, C, R, R]` + camera `[B, 16]` →
/// logits `[B, 1]`.
#[derive(Module, Debug)]
pub struct Discriminator {
    pub from_image: Conv2dLayer,
    pub blocks: Vec<DiscriminatorBlock>,
    pub epilogue_conv: Conv2dLayer,
    pub epilogue_fc: FullyConnected,
    pub out: FullyConnected,
    pub mapping: Vec<FullyConnected>,
    pub mbstd_group: usize,
    pub cmap_dim: usize,
    /// The input resolution it was built for.
    pub resolution: usize,
}

impl Discriminator {
    pub fn new(cfg: &DiscriminatorConfig, in_channels: usize, seed: u64, device: &Device) -> Self {
        assert!(cfg.resolution.is_power_of_two() && cfg.resolution >= 8, "resolution must be a power of two ≥ 8");
        let mut rng = Rng::new(seed, 0xd15c);
        let top = cfg.channels(cfg.resolution);
        let from_image = Conv2dLayer::new(&mut rng, in_channels, top, 1, true, true, false, device);
        let mut blocks = Vec::new();
        let mut res = cfg.resolution;
        while res > 4 {
            let (cin, cout) = (cfg.channels(res), cfg.channels(res / 2));
            blocks.push(DiscriminatorBlock {
                conv0: Conv2dLayer::new(&mut rng, cin, cin, 3, true, true, false, device),
                conv1: Conv2dLayer::new(&mut rng, cin, cout, 3, true, true, true, device),
                skip: Conv2dLayer::new(&mut rng, cin, cout, 1, false, false, false, device),
            });
            res /= 2;
        }
        let c4 = cfg.channels(4);
        let mut mapping = Vec::new();
        let mut d = cfg.c_dim;
        for _ in 0..cfg.mapping_layers.max(1) {
            mapping.push(FullyConnected::new(&mut rng, d, cfg.cmap_dim, 1.0, 0.0, true, device));
            d = cfg.cmap_dim;
        }
        Self {
            from_image,
            blocks,
            epilogue_conv: Conv2dLayer::new(&mut rng, c4 + 1, c4, 3, true, true, false, device),
            epilogue_fc: FullyConnected::new(&mut rng, c4 * 16, c4, 1.0, 0.0, true, device),
            out: FullyConnected::new(&mut rng, c4, cfg.cmap_dim, 1.0, 0.0, false, device),
            mapping,
            mbstd_group: cfg.mbstd_group,
            cmap_dim: cfg.cmap_dim,
            resolution: cfg.resolution,
        }
    }

    /// The image's features after the input layer and after each residual block (resolutions
    /// R, R/2, …, 4): the multi-scale features of the inversion's perceptual term (Deep
    /// Generative Prior's `DiscriminatorLoss`), without the camera-conditioned head. An image
    /// larger than the discriminator's resolution by an integer factor is box-filtered down to
    /// it first, so the features are those of the scales it was trained at.
    pub fn features(&self, img: Tensor<4>) -> Vec<Tensor<4>> {
        let size = img.dims()[3];
        let img = if size > self.resolution && size % self.resolution == 0 {
            let k = size / self.resolution;
            avg_pool2d(img, AvgPoolOptions::new([k, k]))
        } else {
            img
        };
        let mut x = self.from_image.forward(img);
        let mut out = vec![x.clone()];
        for b in &self.blocks {
            x = b.forward(x);
            out.push(x.clone());
        }
        out
    }

    /// Logits `[B, 1]` of images `[B, C, R, R]` (values in [−1, 1]) under cameras `c` `[B, 16]`.
    pub fn forward(&self, img: Tensor<4>, c: Tensor<2>) -> Tensor<2> {
        let mut x = self.from_image.forward(img);
        for b in &self.blocks {
            x = b.forward(x);
        }
        let x = minibatch_std(x, self.mbstd_group);
        let x = self.epilogue_conv.forward(x);
        let [b, ch, h, w] = x.dims();
        let x = self.epilogue_fc.forward(x.reshape([b, ch * h * w]));
        let x = self.out.forward(x);
        // Camera embedding: 2nd-moment normalised, then the mapping layers.
        let mut cm = c.clone() * (c.powf_scalar(2.0).mean_dim(1) + 1e-8).sqrt().recip();
        for l in &self.mapping {
            cm = l.forward(cm);
        }
        (x * cm).sum_dim(1) * (1.0 / (self.cmap_dim as f32).sqrt())
    }
}

/// StyleGAN's minibatch standard deviation layer (one extra feature map): the std over groups
/// of `g` samples (g reduced to divide the batch), averaged over channels and pixels.
pub fn minibatch_std(x: Tensor<4>, group: usize) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    let g = (1..=group.min(b)).rev().find(|g| b % g == 0).unwrap_or(1);
    let y = x.clone().reshape([g, b / g, c, h, w]);
    let y = y.clone() - y.mean_dim(0);
    let y = (y.powf_scalar(2.0).mean_dim(0) + 1e-8).sqrt(); // [1, b/g, c, h, w]
    let y = y.reshape([b / g, c * h * w]).mean_dim(1); // [b/g, 1]
    let y = y.reshape([1, b / g, 1, 1]).repeat_dim(0, g).reshape([b, 1, 1, 1]).repeat_dim(2, h).repeat_dim(3, w);
    Tensor::cat(vec![x, y], 1)
}
