//! Decoders on triplane features (paper Sec. 4.1–4.2): two modulated FCs each (hidden width
//! `decoder_hidden`, leaky ReLU, then linear), one w per layer.
//! - SDF residual (1), styled by w_geo; added to the body template SDF. Its output layer is
//!   not demodulated and starts small (`SDF_INIT_SCALE`), so G starts from the body; it is
//!   softly bounded to ±`SDF_RESIDUAL_MAX` (R·tanh(x/R), the identity for small x), so clothing
//!   and hair live within that distance of the body and the SDF's sign is the template's
//!   farther away (training evaluates the decoders only in that band, `diff::avatar`).
//! - DMTet vertex offset (3), its own MLP on w_geo, squashed to tanh(·) · ¼ grid cell (the
//!   reference's tanh(·)/90 in its normalised box is about a quarter of its cell).
//! - Texture feature (`texture_features`) styled by w_tex, then to-RGB (linear, no demod) and
//!   a sigmoid.

use burn::module::Module;
use burn::tensor::activation::{sigmoid, tanh};
use burn::tensor::{Device, Tensor};

use super::config::GeneratorConfig;
use super::init::Rng;
use super::layers::ModulatedLinear;
use crate::geometry::tet_grid::REFERENCE_BOX_SIZE;

/// Initial scale of the output weights of the SDF-residual and DMTet-offset decoders: the
/// untrained residual and offsets are millimetres, so training (and the untrained demo
/// weights) start from the body template on the regular grid.
pub const SDF_INIT_SCALE: f32 = 0.001;

pub use crate::geometry::posed_grid::SDF_RESIDUAL_MAX;

/// Overshoot of the colour sigmoid (EG3D's 0.001).
const RGB_EPS: f32 = 0.001;

#[derive(Module, Debug)]
pub struct Decoder {
    pub hidden: ModulatedLinear,
    pub out: ModulatedLinear,
}

impl Decoder {
    fn new(rng: &mut Rng, w_dim: usize, d_in: usize, hidden: usize, d_out: usize, device: &Device) -> Self {
        Self {
            hidden: ModulatedLinear::new(rng, w_dim, d_in, hidden, true, true, device),
            out: ModulatedLinear::new(rng, w_dim, hidden, d_out, true, false, device),
        }
    }

    /// A decoder whose output layer is not demodulated and starts with weights scaled by
    /// `init_scale`: its initial output is small (the SDF residual starts near the body).
    fn new_small_output(
        rng: &mut Rng,
        w_dim: usize,
        d_in: usize,
        hidden: usize,
        d_out: usize,
        init_scale: f32,
        device: &Device,
    ) -> Self {
        let hidden = ModulatedLinear::new(rng, w_dim, d_in, hidden, true, true, device);
        let out = ModulatedLinear::with_weight_scale(
            rng,
            w_dim,
            hidden.weight.dims()[0],
            d_out,
            false,
            false,
            init_scale,
            device,
        );
        Self { hidden, out }
    }

    /// `x`: `[B, N, in]`, `w0`, `w1`: `[B, w_dim]` → `[B, N, out]`.
    pub fn forward(&self, x: Tensor<3>, w0: Tensor<2>, w1: Tensor<2>) -> Tensor<3> {
        self.out.forward(self.hidden.forward(x, w0), w1)
    }
}

#[derive(Module, Debug)]
pub struct Decoders {
    pub sdf: Decoder,
    pub offset: Decoder,
    pub texture: Decoder,
    pub to_rgb: ModulatedLinear,
    pub tet_res: usize,
}

impl Decoders {
    pub fn new(rng: &mut Rng, cfg: &GeneratorConfig, device: &Device) -> Self {
        let (c, h) = (cfg.plane_channels, cfg.decoder_hidden);
        Self {
            sdf: Decoder::new_small_output(rng, cfg.w_dim, c, h, 1, SDF_INIT_SCALE, device),
            offset: Decoder::new_small_output(rng, cfg.w_dim, c, h, 3, SDF_INIT_SCALE, device),
            texture: Decoder::new(rng, cfg.w_dim, c, h, cfg.texture_features, device),
            to_rgb: ModulatedLinear::new(rng, cfg.w_dim, cfg.texture_features, 3, false, false, device),
            tet_res: cfg.tet_res,
        }
    }

    /// SDF residual `[B, N, 1]` (metres, within ±`SDF_RESIDUAL_MAX`) from geometry features.
    pub fn sdf_residual(&self, feat: Tensor<3>, w: Tensor<2>) -> Tensor<3> {
        tanh(self.sdf.forward(feat, w.clone(), w) * (1.0 / SDF_RESIDUAL_MAX)) * SDF_RESIDUAL_MAX
    }

    /// DMTet vertex offsets `[B, N, 3]` (metres), each component below a quarter grid cell so
    /// tets cannot invert.
    pub fn vertex_offset(&self, feat: Tensor<3>, w: Tensor<2>) -> Tensor<3> {
        tanh(self.offset.forward(feat, w.clone(), w)) * (REFERENCE_BOX_SIZE / (4.0 * self.tet_res as f32))
    }

    /// Colours `[B, N, 3]` in [0, 1] from texture features: EG3D's output activation
    /// `sigmoid(x)·(1 + 2ε) − ε` (ε = 0.001, so 0 and 1 are reached), clamped to [0, 1]. A plain
    /// clamp of the linear output would have zero gradient wherever a colour saturates, and
    /// saturated texels could never recover.
    pub fn rgb(&self, feat: Tensor<3>, w_tex: Tensor<2>) -> Tensor<3> {
        let f = self.texture.forward(feat, w_tex.clone(), w_tex.clone());
        let rgb = self.to_rgb.forward(f, w_tex);
        (sigmoid(rgb) * (1.0 + 2.0 * RGB_EPS) - RGB_EPS).clamp(0.0, 1.0)
    }
}
