//! The photo encoder: the inversion's first guess in one forward pass (E3DGE / GOAE's recipe
//! for 3D-aware GANs: an encoder trained on the generator's own renders).
//!
//! **Input** ([`EncoderInput`]): the image as the inversion sees it (the photo's framed crop,
//! [`InversionTarget`]) at [`EncoderConfig::res`]², composed on white with the person mask,
//! plus the mask itself and the fitted body rendered at the same camera: its camera-space
//! normals, its canonical (rest-pose) coordinates and its silhouette. The body channels tell
//! the encoder the pose, shape and camera, so it only has to explain the person's
//! appearance. 11 channels, values in [−1, 1], cut into 4×4 patches (space-to-depth) on the
//! CPU while the input is built, so the network starts at res/4 with a 1×1 convolution.
//!
//! **Network** ([`Encoder`]): the discriminator's residual blocks
//! ([`DiscriminatorBlock`]) from res/4 down to 4², a hidden fully connected layer, and a head
//! giving the W+ **offsets from w_avg** of both branches (`[B, n_geo, w_dim]`,
//! `[B, n_tex, w_dim]`). With `atoms > 0` each branch also has a dictionary of codes (the
//! trainer starts it at the checkpoint's training subjects', whose neighbourhoods the
//! generator draws best) and the offsets are a softmax-weighted mix of it plus the head's
//! residual. The head and the logits start at zero: an untrained encoder answers w_avg, or
//! the dictionary's mean.
//!
//! **File**: safetensors, `format = getavatar-encoder/1`, the [`EncoderConfig`] as JSON in the
//! metadata; the config's layer counts and w_dim must be the generator's ([`Encoder::check`]).

use std::collections::BTreeMap;

use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor, TensorData};
use glam::{Mat3, Vec3};
use serde::{Deserialize, Serialize};

use crate::body::body_model::BodyModel;
use crate::body::skinning::{pose_body, vertex_normals};
use crate::generator::checkpoint::{parse_safetensors, write_safetensors, CheckpointError, NamedTensor};
use crate::generator::network::discriminator::{Conv2dLayer, DiscriminatorBlock};
use crate::generator::network::init::{full, Rng};
use crate::generator::network::layers::FullyConnected;
use crate::generator::pipeline::{Generator, Styles};
use crate::render::camera::{OrbitCamera, View};
use crate::render::rasterize::{interpolate, rasterize};

pub const ENCODER_FORMAT: &str = "getavatar-encoder/1";
/// Input channels: RGB on white (3), person mask (1), body normals in camera space (3), body
/// canonical coordinates (3), body silhouette (1).
pub const INPUT_CHANNELS: usize = 11;
/// Side of the patches the input is cut into.
pub const PATCH: usize = 4;
/// Learning-rate multiplier of the dictionary logits (equalised learning rate).
const LOGIT_LR_MUL: f32 = 16.0;

/// The encoder's sizes, stored in its file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EncoderConfig {
    /// Input side, pixels (a multiple of 32).
    pub res: usize,
    /// Channels at res/4, res/8, …, 4 (one more entry than residual blocks).
    pub channels: Vec<usize>,
    /// Width of the hidden fully connected layer.
    pub hidden: usize,
    /// The generator's W+ layout: style layers per branch and w_dim.
    pub num_ws_geo: usize,
    pub num_ws_tex: usize,
    pub w_dim: usize,
    /// Codes in each branch's dictionary (0: none; the shipped encoder's are the
    /// checkpoint's training subjects' codes, learned further).
    #[serde(default)]
    pub atoms: usize,
}

impl EncoderConfig {
    /// The shipped size for a generator with `num_ws` = (geometry, texture) layers.
    pub fn for_generator(num_ws: (usize, usize), w_dim: usize) -> Self {
        Self {
            res: 128,
            channels: vec![64, 96, 128, 128],
            hidden: 192,
            num_ws_geo: num_ws.0,
            num_ws_tex: num_ws.1,
            w_dim,
            atoms: 0,
        }
    }

    /// A config read from a file: sizes a real encoder could have.
    pub fn validate(&self) -> Result<(), String> {
        if self.res % 32 != 0 || !(32..=512).contains(&self.res) {
            return Err(format!("res {} is not a multiple of 32 in 32..=512", self.res));
        }
        let blocks = (self.res / PATCH / 4).trailing_zeros() as usize;
        if !(self.res / PATCH / 4).is_power_of_two() || self.channels.len() != blocks + 1 {
            return Err(format!("{} channel entries for input {}: want {}", self.channels.len(), self.res, blocks + 1));
        }
        let sizes = self.channels.iter().copied().chain([self.hidden, self.w_dim]);
        if sizes.into_iter().any(|c| !(1..=1024).contains(&c)) {
            return Err("a channel count, hidden width or w_dim outside 1..=1024".into());
        }
        if !(1..=64).contains(&self.num_ws_geo) || !(1..=64).contains(&self.num_ws_tex) {
            return Err(format!("style layers {} / {} outside 1..=64", self.num_ws_geo, self.num_ws_tex));
        }
        if self.atoms > 1024 {
            return Err(format!("{} dictionary codes (at most 1024)", self.atoms));
        }
        Ok(())
    }

    /// Numbers in the network (None on overflow), checked against a file before allocating.
    pub fn num_params(&self) -> Option<usize> {
        let conv = |i: usize, o: usize, k: usize, bias: bool| Some(i * o * k * k + if bias { o } else { 0 });
        let mut n = conv(INPUT_CHANNELS * PATCH * PATCH, self.channels[0], 1, true)?;
        for w in self.channels.windows(2) {
            n += conv(w[0], w[0], 3, true)? + conv(w[0], w[1], 3, true)? + conv(w[0], w[1], 1, false)?;
        }
        let last = *self.channels.last()?;
        n = n.checked_add(last.checked_mul(16)?.checked_mul(self.hidden)? + self.hidden)?;
        let out = (self.num_ws_geo + self.num_ws_tex).checked_mul(self.w_dim)?;
        n = n.checked_add(self.hidden.checked_mul(out)? + out)?;
        if self.atoms > 0 {
            // Two logit layers and the two dictionaries.
            n = n.checked_add(2 * (self.hidden.checked_mul(self.atoms)? + self.atoms))?;
            n = n.checked_add(self.atoms.checked_mul(out)?)?;
        }
        Some(n)
    }
}

/// Why an encoder cannot be loaded or used.
#[derive(Debug, thiserror::Error)]
pub enum EncoderError {
    #[error("not an encoder file: {0}")]
    Format(String),
    #[error("the encoder was trained for a generator with {0}; this generator has {1}")]
    Generator(String, String),
    #[error("the encoder input: {0}")]
    Input(String),
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
}

/// The encoder network (module doc).
#[derive(Module, Debug)]
pub struct Encoder {
    pub from_patches: Conv2dLayer,
    pub blocks: Vec<DiscriminatorBlock>,
    pub hidden: FullyConnected,
    pub out: FullyConnected,
    /// Dictionary weights' logits per branch (with `atoms > 0`).
    pub logits_geo: Option<FullyConnected>,
    pub logits_tex: Option<FullyConnected>,
    /// The dictionaries: `[atoms, n_geo·w_dim]` and `[atoms, n_tex·w_dim]` offsets from w_avg.
    pub dict_geo: Option<Param<Tensor<2>>>,
    pub dict_tex: Option<Param<Tensor<2>>>,
    pub num_ws_geo: usize,
    pub num_ws_tex: usize,
    pub w_dim: usize,
}

impl Encoder {
    pub fn new(cfg: &EncoderConfig, seed: u64, device: &Device) -> Self {
        let mut rng = Rng::new(seed, 0xe2c0);
        let c = &cfg.channels;
        let from_patches =
            Conv2dLayer::new(&mut rng, INPUT_CHANNELS * PATCH * PATCH, c[0], 1, true, true, false, device);
        let blocks = c
            .windows(2)
            .map(|w| DiscriminatorBlock {
                conv0: Conv2dLayer::new(&mut rng, w[0], w[0], 3, true, true, false, device),
                conv1: Conv2dLayer::new(&mut rng, w[0], w[1], 3, true, true, true, device),
                skip: Conv2dLayer::new(&mut rng, w[0], w[1], 1, false, false, false, device),
            })
            .collect();
        let last = c[c.len() - 1];
        let hidden = FullyConnected::new(&mut rng, last * 16, cfg.hidden, 1.0, 0.0, true, device);
        let n_out = (cfg.num_ws_geo + cfg.num_ws_tex) * cfg.w_dim;
        let mut out = FullyConnected::new(&mut rng, cfg.hidden, n_out, 1.0, 0.0, false, device);
        // The head starts at zero: an untrained encoder answers w_avg.
        out.weight = Param::from_tensor(full([n_out, cfg.hidden], 0.0, device));
        // Logits start at zero (the dictionary's mean); the dictionaries at zero until
        // [`Encoder::with_dictionary`] sets them.
        let mut logits = || {
            (cfg.atoms > 0).then(|| {
                // A faster rate (lr_mul): a code is picked once its logit leads by a few units.
                let mut l = FullyConnected::new(&mut rng, cfg.hidden, cfg.atoms, LOGIT_LR_MUL, 0.0, false, device);
                l.weight = Param::from_tensor(full([cfg.atoms, cfg.hidden], 0.0, device));
                l
            })
        };
        let (logits_geo, logits_tex) = (logits(), logits());
        let dict =
            |n: usize| (cfg.atoms > 0).then(|| Param::from_tensor(full([cfg.atoms, n * cfg.w_dim], 0.0, device)));
        Self {
            from_patches,
            blocks,
            hidden,
            out,
            logits_geo,
            logits_tex,
            dict_geo: dict(cfg.num_ws_geo),
            dict_tex: dict(cfg.num_ws_tex),
            num_ws_geo: cfg.num_ws_geo,
            num_ws_tex: cfg.num_ws_tex,
            w_dim: cfg.w_dim,
        }
    }

    /// This encoder with its dictionaries set to `geo` `[atoms, n_geo·w_dim]` and `tex`
    /// `[atoms, n_tex·w_dim]` (offsets from w_avg, e.g. the training subjects' codes).
    pub fn with_dictionary(mut self, geo: Tensor<2>, tex: Tensor<2>) -> Result<Self, EncoderError> {
        let want = |d: &Option<Param<Tensor<2>>>| d.as_ref().map(|p| p.val().dims());
        if want(&self.dict_geo) != Some(geo.dims()) || want(&self.dict_tex) != Some(tex.dims()) {
            return Err(EncoderError::Input(format!(
                "dictionaries {:?} / {:?} for an encoder with {:?} / {:?}",
                geo.dims(),
                tex.dims(),
                want(&self.dict_geo),
                want(&self.dict_tex)
            )));
        }
        self.dict_geo = Some(Param::from_tensor(geo));
        self.dict_tex = Some(Param::from_tensor(tex));
        Ok(self)
    }

    /// W+ offsets from w_avg of patchified inputs `[B, 11·16, res/4, res/4]`:
    /// (`[B, n_geo, w_dim]`, `[B, n_tex, w_dim]`).
    pub fn forward(&self, x: Tensor<4>) -> (Tensor<3>, Tensor<3>) {
        let mut x = self.from_patches.forward(x);
        for b in &self.blocks {
            x = b.forward(x);
        }
        let [b, c, h, w] = x.dims();
        let hid = self.hidden.forward(x.reshape([b, c * h * w]));
        let y = self.out.forward(hid.clone());
        let (ng, nt, d) = (self.num_ws_geo, self.num_ws_tex, self.w_dim);
        let mut geo = y.clone().narrow(1, 0, ng * d);
        let mut tex = y.narrow(1, ng * d, nt * d);
        // Plus a softmax-weighted mix of each branch's dictionary.
        let mix = |l: &Option<FullyConnected>, dict: &Option<Param<Tensor<2>>>| {
            let (l, dict) = (l.as_ref()?, dict.as_ref()?);
            Some(burn::tensor::activation::softmax(l.forward(hid.clone()), 1).matmul(dict.val()))
        };
        if let Some(m) = mix(&self.logits_geo, &self.dict_geo) {
            geo = geo + m;
        }
        if let Some(m) = mix(&self.logits_tex, &self.dict_tex) {
            tex = tex + m;
        }
        (geo.reshape([b, ng, d]), tex.reshape([b, nt, d]))
    }

    /// The generator's styles for `inputs` (one per row): w_avg plus the predicted offsets.
    pub fn styles(&self, g: &Generator, inputs: &[&EncoderInput], device: &Device) -> Result<Styles, EncoderError> {
        self.check(g)?;
        let x = batch_tensor(inputs, device)?;
        let (og, ot) = self.forward(x);
        let avg = |t: Tensor<2>| t.unsqueeze_dim::<3>(1);
        Ok(Styles { geo: og + avg(g.mapping_geo.w_avg_tensor()), tex: ot + avg(g.mapping_tex.w_avg_tensor()) })
    }

    /// Whether this encoder's output fits `g`'s W+ layout.
    pub fn check(&self, g: &Generator) -> Result<(), EncoderError> {
        let (ng, nt) = g.num_ws();
        let w = g.mapping_geo.w_avg_tensor().dims()[1];
        if (ng, nt, w) != (self.num_ws_geo, self.num_ws_tex, self.w_dim) {
            let f = |a: usize, b: usize, c: usize| format!("{a} + {b} style layers of {c}");
            return Err(EncoderError::Generator(f(self.num_ws_geo, self.num_ws_tex, self.w_dim), f(ng, nt, w)));
        }
        Ok(())
    }

    pub fn config(&self) -> EncoderConfig {
        let mut channels = vec![self.from_patches.weight.dims()[0]];
        channels.extend(self.blocks.iter().map(|b| b.conv1.weight.dims()[0]));
        EncoderConfig {
            res: (PATCH * 4) << self.blocks.len(),
            channels,
            hidden: self.hidden.weight.dims()[0],
            num_ws_geo: self.num_ws_geo,
            num_ws_tex: self.num_ws_tex,
            w_dim: self.w_dim,
            atoms: self.dict_geo.as_ref().map_or(0, |d| d.val().dims()[0]),
        }
    }
}

/// An encoder file's bytes: its parameters and config (`extra` adds metadata, e.g. the steps).
pub fn save_encoder(
    params: &[NamedTensor],
    cfg: &EncoderConfig,
    extra: &BTreeMap<String, String>,
) -> Result<Vec<u8>, EncoderError> {
    let mut meta = extra.clone();
    meta.insert("format".into(), ENCODER_FORMAT.into());
    meta.insert("encoder".into(), serde_json::to_string(cfg).map_err(|e| EncoderError::Format(e.to_string()))?);
    Ok(write_safetensors(&meta, params)?)
}

/// The encoder in `bytes` (an encoder file, or a `train-encoder` state with its tensors under
/// `enc/`), on `device`.
pub fn load_encoder(bytes: &[u8], device: &Device) -> Result<Encoder, EncoderError> {
    let st = parse_safetensors(bytes)?;
    if st.metadata.get("format").map(String::as_str) != Some(ENCODER_FORMAT) {
        return Err(EncoderError::Format(format!("its format is not `{ENCODER_FORMAT}`")));
    }
    let text = st.metadata.get("encoder").ok_or_else(|| EncoderError::Format("no `encoder` config".into()))?;
    let cfg: EncoderConfig =
        serde_json::from_str(text).map_err(|e| EncoderError::Format(format!("the encoder config: {e}")))?;
    cfg.validate().map_err(|e| EncoderError::Format(format!("the encoder config: {e}")))?;
    let prefix = if st.tensors.keys().any(|k| k.starts_with("enc/")) { "enc/" } else { "" };
    let held: usize = st.tensors.iter().filter(|(k, _)| k.starts_with(prefix)).map(|(_, (_, v))| v.len()).sum();
    match cfg.num_params() {
        Some(need) if need <= held => {}
        _ => return Err(EncoderError::Format(format!("the config needs more numbers than the file's {held}"))),
    }
    Ok(crate::generator::checkpoint::load_params(Encoder::new(&cfg, 0, device), &st.tensors, prefix, device)?)
}

/// [`load_encoder`] for generator `g`: refused unless its output fits `g`'s W+ layout
/// ([`Encoder::check`]), so a file that cannot serve `g` is known before any photo.
pub fn load_encoder_for(bytes: &[u8], g: &Generator, device: &Device) -> Result<Encoder, EncoderError> {
    let e = load_encoder(bytes, device)?;
    e.check(g)?;
    Ok(e)
}

/// One image's encoder input: `INPUT_CHANNELS·PATCH²` channels at `(res/PATCH)²`, CHW.
#[derive(Clone, Debug, PartialEq)]
pub struct EncoderInput {
    pub res: usize,
    pub data: Vec<f32>,
}

/// The encoder's input channels before patchifying: `[11, res, res]` CHW in [−1, 1].
#[derive(Clone, Debug, PartialEq)]
pub struct EncoderImage {
    pub res: usize,
    pub data: Vec<f32>,
}

impl EncoderImage {
    /// The image (`src_res`² sRGB in [0, 1], HWC) with its person mask (`src_res`²) and the
    /// body of `view` rendered at its camera, at `res`².
    pub fn new(
        rgb: &[f32],
        mask: &[f32],
        src_res: usize,
        view: &View,
        model: &BodyModel,
        res: usize,
    ) -> Result<Self, EncoderError> {
        if rgb.len() != src_res * src_res * 3 || mask.len() != src_res * src_res || src_res == 0 {
            return Err(EncoderError::Input(format!(
                "{} RGB and {} mask values for a {src_res}² image",
                rgb.len(),
                mask.len()
            )));
        }
        let rgb = resample(rgb, src_res, 3, res);
        let mask = resample(mask, src_res, 1, res);
        let body = BodyMaps::render(model, view, res);
        Ok(Self::from_parts(&rgb, &mask, &body, res))
    }

    /// From images already at `res`²: RGB (HWC, [0, 1]) and mask, and the body's maps.
    pub fn from_parts(rgb: &[f32], mask: &[f32], body: &BodyMaps, res: usize) -> Self {
        let n = res * res;
        let mut data = vec![0.0; INPUT_CHANNELS * n];
        for k in 0..n {
            let m = mask[k].clamp(0.0, 1.0);
            for c in 0..3 {
                // Composed on white with the mask: the background never reaches the encoder.
                let v = rgb[3 * k + c].clamp(0.0, 1.0) * m + (1.0 - m);
                data[c * n + k] = 2.0 * v - 1.0;
                data[(4 + c) * n + k] = body.normal[3 * k + c];
                data[(7 + c) * n + k] = body.canonical[3 * k + c];
            }
            data[3 * n + k] = 2.0 * m - 1.0;
            data[10 * n + k] = 2.0 * body.mask[k] - 1.0;
        }
        Self { res, data }
    }

    /// Cut into `PATCH`² patches: channel `c·PATCH² + dy·PATCH + dx` at `(y, x)` is pixel
    /// `(PATCH·y + dy, PATCH·x + dx)` of channel c.
    pub fn patchify(&self) -> EncoderInput {
        let (r, p) = (self.res, PATCH);
        let s = r / p;
        let mut data = vec![0.0; self.data.len()];
        for c in 0..INPUT_CHANNELS {
            for y in 0..r {
                for x in 0..r {
                    let ch = c * p * p + (y % p) * p + x % p;
                    data[(ch * s + y / p) * s + x / p] = self.data[(c * r + y) * r + x];
                }
            }
        }
        EncoderInput { res: r, data }
    }
}

/// The fitted body at a view's camera: camera-space normals and canonical coordinates (both
/// `res²·3`, in [−1, 1], 0 off the body) and the silhouette (`res²`, [0, 1]).
#[derive(Clone, Debug, PartialEq)]
pub struct BodyMaps {
    pub normal: Vec<f32>,
    pub canonical: Vec<f32>,
    pub mask: Vec<f32>,
}

impl BodyMaps {
    pub fn render(model: &BodyModel, view: &View, res: usize) -> Self {
        let posed = pose_body(model, &view.body);
        let rot = Mat3::from_mat4(view.world_to_camera);
        let normals: Vec<Vec3> =
            vertex_normals(&posed.vertices, &model.faces).iter().map(|n| (rot * *n).normalize_or_zero()).collect();
        // The rest pose's coordinates scaled into [−1, 1] over the body's usual extent (arms out).
        let canon: Vec<Vec3> = posed
            .shaped
            .iter()
            .map(|v| Vec3::new(v.x / 0.9, (v.y + 0.3) / 1.0, v.z / 0.3).clamp(Vec3::splat(-1.0), Vec3::ONE))
            .collect();
        let vp = OrbitCamera::default().projection_gl(1.0) * view.world_to_camera;
        let clip: Vec<glam::Vec4> = posed.vertices.iter().map(|v| vp * v.extend(1.0)).collect();
        // 2×2 samples per pixel: coverage and attributes averaged over the covered samples.
        let hi = 2 * res;
        let r = rasterize(&clip, &model.faces, hi, hi);
        let (ni, ci) = (interpolate(&normals, &r, &model.faces), interpolate(&canon, &r, &model.faces));
        let n = res * res;
        let (mut normal, mut canonical, mut mask) = (vec![0.0; 3 * n], vec![0.0; 3 * n], vec![0.0; n]);
        for y in 0..res {
            for x in 0..res {
                let (mut ns, mut cs, mut cov) = (Vec3::ZERO, Vec3::ZERO, 0.0);
                for (sy, sx) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                    let k = (2 * y + sy) * hi + 2 * x + sx;
                    if let (Some(a), Some(b)) = (ni[k], ci[k]) {
                        ns += a.normalize_or_zero();
                        cs += b;
                        cov += 0.25;
                    }
                }
                let k = y * res + x;
                mask[k] = cov;
                // Attributes weighted by coverage: 0 off the body, as the channels' background.
                let (ns, cs) = (ns * 0.25, cs * 0.25);
                normal[3 * k..3 * k + 3].copy_from_slice(&ns.to_array());
                canonical[3 * k..3 * k + 3].copy_from_slice(&cs.to_array());
            }
        }
        Self { normal, canonical, mask }
    }
}

/// A square image (`src`², `c` channels, HWC) at `dst`²: the mean over each output pixel's
/// footprint when shrinking, bilinear when enlarging.
pub fn resample(v: &[f32], src: usize, c: usize, dst: usize) -> Vec<f32> {
    if src == dst {
        return v.to_vec();
    }
    let mut out = vec![0.0; dst * dst * c];
    let s = src as f32 / dst as f32;
    if s >= 1.0 {
        for y in 0..dst {
            let (y0, y1) = ((y as f32 * s) as usize, (((y + 1) as f32 * s).ceil() as usize).min(src));
            for x in 0..dst {
                let (x0, x1) = ((x as f32 * s) as usize, (((x + 1) as f32 * s).ceil() as usize).min(src));
                let count = ((y1 - y0) * (x1 - x0)).max(1) as f32;
                for ch in 0..c {
                    let mut acc = 0.0;
                    for yy in y0..y1 {
                        for xx in x0..x1 {
                            acc += v[(yy * src + xx) * c + ch];
                        }
                    }
                    out[(y * dst + x) * c + ch] = acc / count;
                }
            }
        }
    } else {
        let at = |p: f32| {
            let q = ((p + 0.5) * s - 0.5).clamp(0.0, (src - 1) as f32);
            let i = (q as usize).min(src.saturating_sub(2));
            (i, (q - i as f32).min(1.0))
        };
        for y in 0..dst {
            let (iy, fy) = at(y as f32);
            for x in 0..dst {
                let (ix, fx) = at(x as f32);
                for ch in 0..c {
                    let p = |yy: usize, xx: usize| v[((yy).min(src - 1) * src + xx.min(src - 1)) * c + ch];
                    let top = p(iy, ix) * (1.0 - fx) + p(iy, ix + 1) * fx;
                    let bot = p(iy + 1, ix) * (1.0 - fx) + p(iy + 1, ix + 1) * fx;
                    out[(y * dst + x) * c + ch] = top * (1.0 - fy) + bot * fy;
                }
            }
        }
    }
    out
}

/// Patchified inputs of one size stacked into `[B, 11·16, res/4, res/4]`.
pub fn batch_tensor(inputs: &[&EncoderInput], device: &Device) -> Result<Tensor<4>, EncoderError> {
    let first = inputs.first().ok_or_else(|| EncoderError::Input("no images".into()))?;
    let r = first.res;
    if inputs.iter().any(|i| i.res != r || i.data.len() != INPUT_CHANNELS * r * r) {
        return Err(EncoderError::Input("the batch's images differ in size".into()));
    }
    let data: Vec<f32> = inputs.iter().flat_map(|i| i.data.iter().copied()).collect();
    let s = r / PATCH;
    Ok(Tensor::from_data(TensorData::new(data, [inputs.len(), INPUT_CHANNELS * PATCH * PATCH, s, s]), device))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resample_keeps_means_and_constants() {
        let src: Vec<f32> = (0..16).map(|k| k as f32).collect();
        let down = resample(&src, 4, 1, 2);
        assert_eq!(down, vec![2.5, 4.5, 10.5, 12.5]);
        let up = resample(&[0.3; 4 * 3], 2, 3, 5);
        assert!(up.iter().all(|v| (v - 0.3).abs() < 1e-6));
    }

    #[test]
    fn patchify_places_each_pixel_once() {
        let res = 8;
        let data: Vec<f32> = (0..INPUT_CHANNELS * res * res).map(|k| k as f32).collect();
        let p = EncoderImage { res, data: data.clone() }.patchify();
        let mut sorted = p.data.clone();
        sorted.sort_by(f32::total_cmp);
        assert_eq!(sorted, data);
        // Pixel (5, 6) of channel 2 → channel 2·16 + 1·4 + 2 at (1, 1) of a 2×2 grid.
        let want = data[(2 * res + 5) * res + 6];
        assert_eq!(p.data[((2 * 16 + 4 + 2) * 2 + 1) * 2 + 1], want);
    }

    #[test]
    fn config_counts_match_the_network() {
        let cfg = EncoderConfig {
            res: 64,
            channels: vec![8, 12, 16],
            hidden: 10,
            num_ws_geo: 3,
            num_ws_tex: 4,
            w_dim: 6,
            atoms: 0,
        };
        cfg.validate().unwrap();
        #[allow(deprecated)]
        let dev = Device::ndarray();
        let e = Encoder::new(&cfg, 1, &dev);
        assert_eq!(e.config(), cfg);
        let n: usize = crate::generator::checkpoint::collect_params(&e).unwrap().iter().map(|(_, _, v)| v.len()).sum();
        assert_eq!(Some(n), cfg.num_params());
        let x = Tensor::<4>::ones([2, INPUT_CHANNELS * 16, 16, 16], &dev);
        let (g, t) = e.forward(x);
        assert_eq!(g.dims(), [2, 3, 6]);
        assert_eq!(t.dims(), [2, 4, 6]);
        // The head starts at zero.
        assert!(crate::generator::readback::read_f32_now(t).unwrap().iter().all(|v| *v == 0.0));
        // With dictionaries: their parameters counted, and an untrained encoder answers
        // each dictionary's mean.
        let cfg = EncoderConfig { atoms: 2, ..cfg };
        let e = Encoder::new(&cfg, 1, &dev);
        assert_eq!(e.config(), cfg);
        let n: usize = crate::generator::checkpoint::collect_params(&e).unwrap().iter().map(|(_, _, v)| v.len()).sum();
        assert_eq!(Some(n), cfg.num_params());
        let dict = |n: usize, v: f32| {
            let rows: Vec<f32> = (0..2).flat_map(|r| vec![v * (1 + 2 * r) as f32; n]).collect();
            Tensor::<2>::from_data(TensorData::new(rows, [2, n]), &dev)
        };
        let e = e.with_dictionary(dict(18, 1.0), dict(24, -0.5)).unwrap();
        let (g, t) = e.forward(Tensor::<4>::ones([1, INPUT_CHANNELS * 16, 16, 16], &dev));
        let read = |x: Tensor<3>| crate::generator::readback::read_f32_now(x).unwrap();
        assert!(read(g).iter().all(|v| (v - 2.0).abs() < 1e-6));
        assert!(read(t).iter().all(|v| (v + 1.0).abs() < 1e-6));
        assert!(Encoder::new(&cfg, 1, &dev).with_dictionary(dict(17, 1.0), dict(24, 1.0)).is_err());
    }

    #[test]
    fn a_saved_encoder_loads_back_and_bad_files_are_refused() {
        #[allow(deprecated)]
        let dev = Device::ndarray();
        let gcfg = crate::generator::network::GeneratorConfig::preset("tiny").unwrap();
        let g = Generator::new(&gcfg, 1, &dev);
        let (ng, nt) = g.num_ws();
        let cfg = EncoderConfig {
            res: 32,
            channels: vec![8, 8],
            hidden: 6,
            ..EncoderConfig::for_generator((ng, nt), gcfg.w_dim)
        };
        let e = Encoder::new(&cfg, 2, &dev);
        e.check(&g).unwrap();
        let params = crate::generator::checkpoint::collect_params(&e).unwrap();
        let bytes = save_encoder(&params, &cfg, &BTreeMap::new()).unwrap();
        let back = load_encoder(&bytes, &dev).unwrap();
        assert_eq!(back.config(), cfg);
        assert!(
            crate::generator::checkpoint::collect_params(&back).unwrap() == params,
            "the weights changed on the way"
        );
        // Not safetensors; another format; a config that needs more numbers than the file has.
        assert!(matches!(load_encoder(b"not an encoder", &dev), Err(EncoderError::Checkpoint(_))));
        let other = write_safetensors(&BTreeMap::from([("format".to_string(), "x".to_string())]), &params).unwrap();
        assert!(matches!(load_encoder(&other, &dev), Err(EncoderError::Format(_))));
        let big = EncoderConfig { hidden: 60, ..cfg.clone() };
        let lying = save_encoder(&params, &big, &BTreeMap::new()).unwrap();
        assert!(matches!(load_encoder(&lying, &dev), Err(EncoderError::Format(_))));
        // Another generator's layout is refused before any forward pass, and by the load for it.
        let wrong_cfg = EncoderConfig { num_ws_geo: ng + 1, ..cfg.clone() };
        let wrong = Encoder::new(&wrong_cfg, 2, &dev);
        let err = wrong.check(&g).unwrap_err();
        assert!(matches!(err, EncoderError::Generator(..)), "{err}");
        let wrong_bytes =
            save_encoder(&crate::generator::checkpoint::collect_params(&wrong).unwrap(), &wrong_cfg, &BTreeMap::new())
                .unwrap();
        assert!(load_encoder(&wrong_bytes, &dev).is_ok());
        let err = load_encoder_for(&wrong_bytes, &g, &dev).unwrap_err();
        assert!(matches!(err, EncoderError::Generator(..)), "{err}");
        assert!(matches!(load_encoder_for(b"not an encoder", &g, &dev), Err(EncoderError::Checkpoint(_))));
        assert_eq!(load_encoder_for(&bytes, &g, &dev).unwrap().config(), cfg);
    }
}
