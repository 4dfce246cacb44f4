//! The Inception-v3 feature extractor of FID: the `pt_inception-2015-12-05` network as
//! pytorch-fid builds it (`FIDInceptionA/C/E_1/E_2` blocks, torchvision's `BasicConv2d` with
//! batch norm ε = 0.001), up to the 2048-d pool3 features.
//!
//! Input handling follows pytorch-fid: images in [0, 1] are resized to 299² by bilinear
//! interpolation with `align_corners = false` (no antialiasing) and mapped to [−1, 1].
//!
//! Weights: the standard `pt_inception-2015-12-05-6726825d.pth` converted to safetensors
//! (`tools/convert_inception.py`; keys as in the PyTorch state dict, e.g.
//! `Mixed_5b.branch1x1.conv.weight`, `Mixed_5b.branch1x1.bn.running_var`). Batch norm is
//! folded into the convolutions at load time. Forward only (no gradients), any burn device.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{bail, Context, Result};
use getavatar_core::burn::tensor::module::{avg_pool2d, conv2d, max_pool2d};
use getavatar_core::burn::tensor::ops::{AvgPoolOptions, ConvOptions, MaxPoolOptions};
use getavatar_core::burn::tensor::{Device, Tensor, TensorData};
use getavatar_core::generator::checkpoint::parse_safetensors_lenient;

/// Side of the network's input.
pub const INPUT_SIZE: usize = 299;
/// Length of the pool3 feature vector.
pub const FEATURE_DIM: usize = 2048;
const BN_EPS: f32 = 0.001;

/// One `BasicConv2d` (conv without bias, batch norm, ReLU) of the architecture.
#[derive(Clone, Debug, PartialEq)]
pub struct ConvSpec {
    /// State-dict prefix, e.g. `Mixed_6b.branch7x7_2`.
    pub name: String,
    pub c_in: usize,
    pub c_out: usize,
    /// Kernel (height, width).
    pub kernel: [usize; 2],
    pub stride: usize,
    /// Padding (height, width).
    pub pad: [usize; 2],
}

fn spec(name: String, c_in: usize, c_out: usize, kernel: [usize; 2], stride: usize, pad: [usize; 2]) -> ConvSpec {
    ConvSpec { name, c_in, c_out, kernel, stride, pad }
}

/// The Mixed blocks: (name, kind, input channels, kind parameter).
#[derive(Clone, Copy, Debug, PartialEq)]
enum Kind {
    /// FIDInceptionA with `pool_features`.
    A(usize),
    B,
    /// FIDInceptionC with `channels_7x7`.
    C(usize),
    D,
    /// FIDInceptionE_1 (average pool branch) / E_2 (max pool branch).
    E {
        max_pool: bool,
    },
}

const BLOCKS: [(&str, Kind, usize); 11] = [
    ("Mixed_5b", Kind::A(32), 192),
    ("Mixed_5c", Kind::A(64), 256),
    ("Mixed_5d", Kind::A(64), 288),
    ("Mixed_6a", Kind::B, 288),
    ("Mixed_6b", Kind::C(128), 768),
    ("Mixed_6c", Kind::C(160), 768),
    ("Mixed_6d", Kind::C(160), 768),
    ("Mixed_6e", Kind::C(192), 768),
    ("Mixed_7a", Kind::D, 768),
    ("Mixed_7b", Kind::E { max_pool: false }, 1280),
    ("Mixed_7c", Kind::E { max_pool: true }, 2048),
];

fn block_specs(p: &str, kind: Kind, c: usize) -> Vec<ConvSpec> {
    let n = |s: &str| format!("{p}.{s}");
    match kind {
        Kind::A(pool) => vec![
            spec(n("branch1x1"), c, 64, [1, 1], 1, [0, 0]),
            spec(n("branch5x5_1"), c, 48, [1, 1], 1, [0, 0]),
            spec(n("branch5x5_2"), 48, 64, [5, 5], 1, [2, 2]),
            spec(n("branch3x3dbl_1"), c, 64, [1, 1], 1, [0, 0]),
            spec(n("branch3x3dbl_2"), 64, 96, [3, 3], 1, [1, 1]),
            spec(n("branch3x3dbl_3"), 96, 96, [3, 3], 1, [1, 1]),
            spec(n("branch_pool"), c, pool, [1, 1], 1, [0, 0]),
        ],
        Kind::B => vec![
            spec(n("branch3x3"), c, 384, [3, 3], 2, [0, 0]),
            spec(n("branch3x3dbl_1"), c, 64, [1, 1], 1, [0, 0]),
            spec(n("branch3x3dbl_2"), 64, 96, [3, 3], 1, [1, 1]),
            spec(n("branch3x3dbl_3"), 96, 96, [3, 3], 2, [0, 0]),
        ],
        Kind::C(c7) => vec![
            spec(n("branch1x1"), c, 192, [1, 1], 1, [0, 0]),
            spec(n("branch7x7_1"), c, c7, [1, 1], 1, [0, 0]),
            spec(n("branch7x7_2"), c7, c7, [1, 7], 1, [0, 3]),
            spec(n("branch7x7_3"), c7, 192, [7, 1], 1, [3, 0]),
            spec(n("branch7x7dbl_1"), c, c7, [1, 1], 1, [0, 0]),
            spec(n("branch7x7dbl_2"), c7, c7, [7, 1], 1, [3, 0]),
            spec(n("branch7x7dbl_3"), c7, c7, [1, 7], 1, [0, 3]),
            spec(n("branch7x7dbl_4"), c7, c7, [7, 1], 1, [3, 0]),
            spec(n("branch7x7dbl_5"), c7, 192, [1, 7], 1, [0, 3]),
            spec(n("branch_pool"), c, 192, [1, 1], 1, [0, 0]),
        ],
        Kind::D => vec![
            spec(n("branch3x3_1"), c, 192, [1, 1], 1, [0, 0]),
            spec(n("branch3x3_2"), 192, 320, [3, 3], 2, [0, 0]),
            spec(n("branch7x7x3_1"), c, 192, [1, 1], 1, [0, 0]),
            spec(n("branch7x7x3_2"), 192, 192, [1, 7], 1, [0, 3]),
            spec(n("branch7x7x3_3"), 192, 192, [7, 1], 1, [3, 0]),
            spec(n("branch7x7x3_4"), 192, 192, [3, 3], 2, [0, 0]),
        ],
        Kind::E { .. } => vec![
            spec(n("branch1x1"), c, 320, [1, 1], 1, [0, 0]),
            spec(n("branch3x3_1"), c, 384, [1, 1], 1, [0, 0]),
            spec(n("branch3x3_2a"), 384, 384, [1, 3], 1, [0, 1]),
            spec(n("branch3x3_2b"), 384, 384, [3, 1], 1, [1, 0]),
            spec(n("branch3x3dbl_1"), c, 448, [1, 1], 1, [0, 0]),
            spec(n("branch3x3dbl_2"), 448, 384, [3, 3], 1, [1, 1]),
            spec(n("branch3x3dbl_3a"), 384, 384, [1, 3], 1, [0, 1]),
            spec(n("branch3x3dbl_3b"), 384, 384, [3, 1], 1, [1, 0]),
            spec(n("branch_pool"), c, 192, [1, 1], 1, [0, 0]),
        ],
    }
}

/// Every `BasicConv2d` of the network up to pool3, in forward order (94 of them).
pub fn conv_specs() -> Vec<ConvSpec> {
    let mut v = vec![
        spec("Conv2d_1a_3x3".into(), 3, 32, [3, 3], 2, [0, 0]),
        spec("Conv2d_2a_3x3".into(), 32, 32, [3, 3], 1, [0, 0]),
        spec("Conv2d_2b_3x3".into(), 32, 64, [3, 3], 1, [1, 1]),
        spec("Conv2d_3b_1x1".into(), 64, 80, [1, 1], 1, [0, 0]),
        spec("Conv2d_4a_3x3".into(), 80, 192, [3, 3], 1, [0, 0]),
    ];
    for (p, kind, c) in BLOCKS {
        v.extend(block_specs(p, kind, c));
    }
    v
}

/// The parameters a weights file must hold: (key, shape), five per convolution.
pub fn parameter_shapes() -> Vec<(String, Vec<usize>)> {
    conv_specs()
        .into_iter()
        .flat_map(|s| {
            let w = (format!("{}.conv.weight", s.name), vec![s.c_out, s.c_in, s.kernel[0], s.kernel[1]]);
            std::iter::once(w).chain(
                ["weight", "bias", "running_mean", "running_var"]
                    .into_iter()
                    .map(move |b| (format!("{}.bn.{b}", s.name), vec![s.c_out])),
            )
        })
        .collect()
}

/// A convolution with its batch norm folded in, followed by ReLU.
struct FoldedConv {
    weight: Tensor<4>,
    bias: Tensor<1>,
    options: ConvOptions<2>,
}

impl FoldedConv {
    fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        getavatar_core::burn::tensor::activation::relu(conv2d(
            x,
            self.weight.clone(),
            Some(self.bias.clone()),
            self.options.clone(),
        ))
    }
}

/// The loaded network.
pub struct Inception {
    convs: BTreeMap<String, FoldedConv>,
    device: Device,
}

fn max3s2(x: Tensor<4>) -> Tensor<4> {
    max_pool2d(x, MaxPoolOptions::new([3, 3]).with_stride([2, 2]))
}

fn avg3_same(x: Tensor<4>) -> Tensor<4> {
    avg_pool2d(x, AvgPoolOptions::new([3, 3]).with_stride([1, 1]).with_padding([1, 1]).with_count_include_pad(false))
}

fn max3_same(x: Tensor<4>) -> Tensor<4> {
    max_pool2d(x, MaxPoolOptions::new([3, 3]).with_stride([1, 1]).with_padding([1, 1]))
}

impl Inception {
    /// Load a safetensors weights file (see the module docs for its layout).
    pub fn load(path: &Path, device: &Device) -> Result<Self> {
        let bytes = std::fs::read(path).with_context(|| format!("reading Inception weights {}", path.display()))?;
        Self::from_bytes(&bytes, device).with_context(|| {
            format!(
                "{} is not the pt_inception-2015-12-05 network as safetensors (convert the .pth with tools/convert_inception.py)",
                path.display()
            )
        })
    }

    /// Build from safetensors bytes; every parameter of [`parameter_shapes`] must be present
    /// with its shape (extra keys such as `fc.weight` are ignored).
    pub fn from_bytes(bytes: &[u8], device: &Device) -> Result<Self> {
        let st = parse_safetensors_lenient(bytes)?;
        let get = |k: &str, shape: &[usize]| -> Result<&Vec<f32>> {
            let (s, v) = st.tensors.get(k).with_context(|| format!("missing tensor `{k}`"))?;
            if s.as_slice() != shape {
                bail!("tensor `{k}` has shape {s:?}, expected {shape:?}");
            }
            Ok(v)
        };
        let mut convs = BTreeMap::new();
        for s in conv_specs() {
            let [kh, kw] = s.kernel;
            let w = get(&format!("{}.conv.weight", s.name), &[s.c_out, s.c_in, kh, kw])?;
            let bn = |b: &str| get(&format!("{}.bn.{b}", s.name), &[s.c_out]);
            let (gamma, beta, mean, var) = (bn("weight")?, bn("bias")?, bn("running_mean")?, bn("running_var")?);
            let per_out = s.c_in * kh * kw;
            let mut wf = w.clone();
            let mut bias = vec![0f32; s.c_out];
            for o in 0..s.c_out {
                if var[o] < 0.0 || !var[o].is_finite() {
                    bail!("`{}.bn.running_var` has an invalid value {}", s.name, var[o]);
                }
                let scale = gamma[o] / (var[o] + BN_EPS).sqrt();
                wf[o * per_out..(o + 1) * per_out].iter_mut().for_each(|x| *x *= scale);
                bias[o] = beta[o] - mean[o] * scale;
            }
            let conv = FoldedConv {
                weight: Tensor::from_data(TensorData::new(wf, [s.c_out, s.c_in, kh, kw]), device),
                bias: Tensor::from_data(TensorData::new(bias, [s.c_out]), device),
                options: ConvOptions::new([s.stride, s.stride], s.pad, [1, 1], 1),
            };
            convs.insert(s.name.clone(), conv);
        }
        Ok(Self { convs, device: device.clone() })
    }

    fn c(&self, block: &str, name: &str, x: Tensor<4>) -> Tensor<4> {
        let key = if block.is_empty() { name.to_string() } else { format!("{block}.{name}") };
        // Every key used below is one of `conv_specs`, all of which `from_bytes` loaded.
        self.convs[&key].forward(x)
    }

    fn block(&self, p: &str, kind: Kind, x: Tensor<4>) -> Tensor<4> {
        let c = |n: &str, x: Tensor<4>| self.c(p, n, x);
        let parts = match kind {
            Kind::A(_) => vec![
                c("branch1x1", x.clone()),
                c("branch5x5_2", c("branch5x5_1", x.clone())),
                c("branch3x3dbl_3", c("branch3x3dbl_2", c("branch3x3dbl_1", x.clone()))),
                c("branch_pool", avg3_same(x)),
            ],
            Kind::B => vec![
                c("branch3x3", x.clone()),
                c("branch3x3dbl_3", c("branch3x3dbl_2", c("branch3x3dbl_1", x.clone()))),
                max3s2(x),
            ],
            Kind::C(_) => {
                let b7 = c("branch7x7_3", c("branch7x7_2", c("branch7x7_1", x.clone())));
                let mut d = c("branch7x7dbl_1", x.clone());
                for k in 2..=5 {
                    d = c(&format!("branch7x7dbl_{k}"), d);
                }
                vec![c("branch1x1", x.clone()), b7, d, c("branch_pool", avg3_same(x))]
            }
            Kind::D => vec![
                c("branch3x3_2", c("branch3x3_1", x.clone())),
                c("branch7x7x3_4", c("branch7x7x3_3", c("branch7x7x3_2", c("branch7x7x3_1", x.clone())))),
                max3s2(x),
            ],
            Kind::E { max_pool } => {
                let b3 = c("branch3x3_1", x.clone());
                let b3 = Tensor::cat(vec![c("branch3x3_2a", b3.clone()), c("branch3x3_2b", b3)], 1);
                let d = c("branch3x3dbl_2", c("branch3x3dbl_1", x.clone()));
                let d = Tensor::cat(vec![c("branch3x3dbl_3a", d.clone()), c("branch3x3dbl_3b", d)], 1);
                let pooled = if max_pool { max3_same(x.clone()) } else { avg3_same(x.clone()) };
                vec![c("branch1x1", x), b3, d, c("branch_pool", pooled)]
            }
        };
        Tensor::cat(parts, 1)
    }

    /// pool3 features of a batch already at 299² and in [−1, 1]: `[N, 3, 299, 299]` → `[N, 2048]`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<2> {
        let mut x = self.c("", "Conv2d_1a_3x3", x);
        x = self.c("", "Conv2d_2a_3x3", x);
        x = max3s2(self.c("", "Conv2d_2b_3x3", x));
        x = self.c("", "Conv2d_3b_1x1", x);
        x = max3s2(self.c("", "Conv2d_4a_3x3", x));
        for (p, kind, _) in BLOCKS {
            x = self.block(p, kind, x);
        }
        let [n, c, h, w] = x.dims();
        x.reshape([n, c, h * w]).mean_dim(2).reshape([n, c])
    }

    /// pool3 features of images in [0, 1] (each `3·h·w`, channel-major, any size), resized
    /// to 299² as pytorch-fid does; processed `batch` at a time.
    pub fn features(&self, images: &[ImageChw], batch: usize) -> Result<Vec<Vec<f32>>> {
        let mut out = Vec::with_capacity(images.len());
        for chunk in images.chunks(batch.max(1)) {
            let mut data = Vec::with_capacity(chunk.len() * 3 * INPUT_SIZE * INPUT_SIZE);
            for im in chunk {
                if im.data.len() != 3 * im.height * im.width || im.height == 0 || im.width == 0 {
                    bail!("image of {}×{} with {} values (expected 3·h·w)", im.width, im.height, im.data.len());
                }
                let r = resize_bilinear(&im.data, 3, im.height, im.width, INPUT_SIZE, INPUT_SIZE);
                data.extend(r.into_iter().map(|v| 2.0 * v - 1.0));
            }
            let x =
                Tensor::<4>::from_data(TensorData::new(data, [chunk.len(), 3, INPUT_SIZE, INPUT_SIZE]), &self.device);
            let f = self
                .forward(x)
                .into_data()
                .convert::<f32>()
                .try_to_vec::<f32>()
                .map_err(|e| anyhow::anyhow!("{e:?}"))?;
            out.extend(f.chunks_exact(FEATURE_DIM).map(|c| c.to_vec()));
        }
        Ok(out)
    }
}

/// An RGB image, channel-major (`[3, height, width]`), values in [0, 1].
#[derive(Clone, Debug)]
pub struct ImageChw {
    pub data: Vec<f32>,
    pub height: usize,
    pub width: usize,
}

impl ImageChw {
    /// From interleaved row-major RGB (`h·w·3`, as the dataset stores it).
    pub fn from_interleaved(rgb: &[f32], height: usize, width: usize) -> Self {
        let n = height * width;
        let mut data = vec![0.0; 3 * n];
        for p in 0..n.min(rgb.len() / 3) {
            for c in 0..3 {
                data[c * n + p] = rgb[3 * p + c];
            }
        }
        Self { data, height, width }
    }
}

/// Bilinear resize of a `[c, h, w]` image to `[c, oh, ow]` with PyTorch's
/// `F.interpolate(mode="bilinear", align_corners=False)` sampling (no antialiasing).
pub fn resize_bilinear(src: &[f32], c: usize, h: usize, w: usize, oh: usize, ow: usize) -> Vec<f32> {
    // Source coordinate of output index `d`: (d + 0.5)·in/out − 0.5, clamped at 0.
    let taps = |n_in: usize, n_out: usize| -> Vec<(usize, usize, f32)> {
        let scale = n_in as f32 / n_out as f32;
        (0..n_out)
            .map(|d| {
                let s = (scale * (d as f32 + 0.5) - 0.5).max(0.0);
                let i0 = (s.floor() as usize).min(n_in - 1);
                let i1 = if i0 < n_in - 1 { i0 + 1 } else { i0 };
                (i0, i1, s - i0 as f32)
            })
            .collect()
    };
    let (ty, tx) = (taps(h, oh), taps(w, ow));
    let mut out = vec![0f32; c * oh * ow];
    for ch in 0..c {
        let plane = &src[ch * h * w..(ch + 1) * h * w];
        for (oy, &(y0, y1, ly)) in ty.iter().enumerate() {
            for (ox, &(x0, x1, lx)) in tx.iter().enumerate() {
                let top = (1.0 - lx) * plane[y0 * w + x0] + lx * plane[y0 * w + x1];
                let bot = (1.0 - lx) * plane[y1 * w + x0] + lx * plane[y1 * w + x1];
                out[ch * oh * ow + oy * ow + ox] = (1.0 - ly) * top + ly * bot;
            }
        }
    }
    out
}

/// FNV-1a of a tensor name: the seed of its hash-generated values.
fn fnv1a(s: &str) -> u32 {
    s.bytes().fold(0x811C_9DC5u32, |h, b| (h ^ b as u32).wrapping_mul(0x0100_0193))
}

/// `n` values in [−1, 1): murmur3's fmix32 of (i·0x9E3779B9) xor fnv1a(name), as
/// `hash_uniform` in tools/inception_weights.py.
pub fn hash_uniform(name: &str, n: usize) -> Vec<f64> {
    let seed = fnv1a(name);
    (0..n as u32)
        .map(|i| {
            let mut h = i.wrapping_mul(0x9E37_79B9) ^ seed;
            h ^= h >> 16;
            h = h.wrapping_mul(0x85EB_CA6B);
            h ^= h >> 13;
            h = h.wrapping_mul(0xC2B2_AE35);
            h ^= h >> 16;
            h as f64 / 4294967296.0 * 2.0 - 1.0
        })
        .collect()
}

fn hash_tensor(name: &str, shape: &[usize]) -> Vec<f32> {
    let u = hash_uniform(name, shape.iter().product());
    let map = |f: &dyn Fn(f64) -> f64| u.iter().map(|&x| f(x) as f32).collect::<Vec<f32>>();
    if name.ends_with("conv.weight") {
        let fan_in: usize = shape[1..].iter().product();
        let a = 3f64.sqrt() * (2.0 / fan_in as f64).sqrt();
        map(&|x| x * a)
    } else if name.ends_with("bn.weight") {
        map(&|x| 1.0 + 0.2 * x)
    } else if name.ends_with("bn.bias") || name.ends_with("bn.running_mean") {
        map(&|x| 0.1 * x)
    } else {
        map(&|x| 1.0 + 0.5 * x)
    }
}

/// Deterministic stand-in weights (He-scaled hash values, batch norm near identity) with
/// the network's exact keys and shapes, as `tools/inception_weights.py reference` builds
/// them for pytorch-fid. For testing the FID pipeline only: not a trained network.
pub fn hashed_weights() -> Vec<(String, Vec<usize>, Vec<f32>)> {
    parameter_shapes().into_iter().map(|(k, s)| (k.clone(), s.clone(), hash_tensor(&k, &s))).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_architecture_has_the_reference_parameter_count() {
        // pytorch-fid's FIDInceptionV3 up to pool3: 94 BasicConv2d, 21,820,000 parameters
        // (convolutions and batch-norm affine/statistics; the 1008-way fc excluded).
        let specs = conv_specs();
        assert_eq!(specs.len(), 94);
        let total: usize = parameter_shapes().iter().map(|(_, s)| s.iter().product::<usize>()).sum();
        assert_eq!(total, 21_820_000);
    }

    #[test]
    fn resize_matches_pytorch_on_a_ramp() {
        // 2 → 4 upsampling of [0, 1]: PyTorch gives [0, 0.25, 0.75, 1] (align_corners=False).
        let r = resize_bilinear(&[0.0, 1.0], 1, 1, 2, 1, 4);
        assert_eq!(r, vec![0.0, 0.25, 0.75, 1.0]);
        // 4 → 2 downsampling averages neighbours: [0.5, 2.5] from [0, 1, 2, 3].
        let r = resize_bilinear(&[0.0, 1.0, 2.0, 3.0], 1, 1, 4, 1, 2);
        assert_eq!(r, vec![0.5, 2.5]);
    }

    #[test]
    fn a_missing_or_misshapen_tensor_is_a_clear_error() {
        #[allow(deprecated)]
        let dev = Device::ndarray();
        let bytes = getavatar_core::generator::checkpoint::write_safetensors(
            &Default::default(),
            &[("Conv2d_1a_3x3.conv.weight".into(), vec![32, 3, 3, 2], vec![0.0; 32 * 3 * 3 * 2])],
        )
        .unwrap();
        let e = format!("{:#}", Inception::from_bytes(&bytes, &dev).err().expect("must fail"));
        assert!(e.contains("Conv2d_1a_3x3.conv.weight") && e.contains("[32, 3, 3, 3]"), "{e}");
        let e = format!("{:#}", Inception::from_bytes(b"junk", &dev).err().expect("must fail"));
        assert!(e.contains("safetensors") || e.contains("header"), "{e}");
    }

    /// pool3 features equal pytorch-fid's `InceptionV3` (run by tools/inception_weights.py
    /// on the same hash-generated weights and 64×40 inputs, so resizing is exercised too).
    #[test]
    fn features_match_pytorch_fid() {
        #[allow(deprecated)]
        let dev = Device::ndarray();
        let tensors: Vec<(String, Vec<usize>, Vec<f32>)> =
            parameter_shapes().into_iter().map(|(k, s)| (k.clone(), s.clone(), hash_tensor(&k, &s))).collect();
        let net = Inception::from_bytes(
            &getavatar_core::generator::checkpoint::write_safetensors(&Default::default(), &tensors).unwrap(),
            &dev,
        )
        .expect("hash weights load");
        let fixture =
            std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/inception_reference.safetensors"))
                .expect("fixture");
        let st = getavatar_core::generator::checkpoint::parse_safetensors(&fixture).expect("fixture parses");
        let (shape, want) = &st.tensors["features"];
        assert_eq!(shape, &vec![2, FEATURE_DIM]);
        let (h, w) = (64, 40);
        let x: Vec<f32> = hash_uniform("input", 2 * 3 * h * w).iter().map(|&u| (u as f32) * 0.5 + 0.5).collect();
        let images: Vec<ImageChw> =
            x.chunks_exact(3 * h * w).map(|c| ImageChw { data: c.to_vec(), height: h, width: w }).collect();
        let got = net.features(&images, 2).expect("features");
        let scale = want.iter().fold(0f32, |m, v| m.max(v.abs()));
        let mut worst = 0f32;
        for (i, f) in got.iter().enumerate() {
            for (a, b) in f.iter().zip(&want[i * FEATURE_DIM..(i + 1) * FEATURE_DIM]) {
                worst = worst.max((a - b).abs());
            }
        }
        assert!(worst < 1e-3 * scale, "max |Δ| {worst} vs feature scale {scale}");
        // Different inputs give different features (the comparison is not vacuous).
        let d: f32 = got[0].iter().zip(&got[1]).map(|(a, b)| (a - b).abs()).sum::<f32>() / FEATURE_DIM as f32;
        assert!(d > 1e-3 * scale, "features of the two inputs differ by only {d}");
    }
}
