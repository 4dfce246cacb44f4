//! Mapping network z → w (8 FC layers in the paper, leaky ReLU, lr multiplier 0.01) with the
//! tracked average w_avg used by the truncation trick: w' = w_avg + ψ·(w − w_avg), and the
//! multi-modal variants towards the nearest of several modes ([`truncate_toward_modes`]) and,
//! for a (w_geo, w_tex) pair, towards one training subject's pair ([`truncate_toward_subject`]).

use burn::module::{Module, Param};
use burn::tensor::{Device, Int, Tensor};

use super::init::{full, Rng};
use super::layers::FullyConnected;

#[derive(Module, Debug)]
pub struct MappingNetwork {
    pub layers: Vec<FullyConnected>,
    /// Running mean of w (`[w_dim]`); not trained by gradients.
    pub w_avg: Param<Tensor<1>>,
}

impl MappingNetwork {
    pub fn new(rng: &mut Rng, z_dim: usize, w_dim: usize, num_layers: usize, lr_mul: f32, device: &Device) -> Self {
        let layers = (0..num_layers.max(1))
            .map(|i| FullyConnected::new(rng, if i == 0 { z_dim } else { w_dim }, w_dim, lr_mul, 0.0, true, device))
            .collect();
        Self { layers, w_avg: Param::from_tensor(full([w_dim], 0.0, device)).set_require_grad(false) }
    }

    /// `z`: `[B, z_dim]` → w `[B, w_dim]` (z normalised to unit second moment first).
    pub fn forward(&self, z: Tensor<2>) -> Tensor<2> {
        let norm = (z.clone().powf_scalar(2.0).mean_dim(1) + 1e-8).sqrt().recip();
        let mut x = z * norm;
        for l in &self.layers {
            x = l.forward(x);
        }
        x
    }

    /// Width of the latent z.
    pub fn z_dim(&self) -> usize {
        self.layers.first().map_or(0, |l| l.weight.dims()[1])
    }

    /// w_avg as a `[1, w_dim]` row (no gradients).
    pub fn w_avg_tensor(&self) -> Tensor<2> {
        self.w_avg.val().detach().unsqueeze_dim::<2>(0)
    }

    /// Track the running mean: `w_avg ← β·w_avg + (1 − β)·mean_batch(w)` (no gradients).
    pub fn track_w_avg(mut self, w: Tensor<2>, beta: f32) -> Self {
        let mean = w.detach().mean_dim(0).reshape([self.w_avg.dims()[0]]);
        let avg = self.w_avg.val().detach() * beta + mean * (1.0 - beta);
        self.w_avg = Param::from_tensor(avg).set_require_grad(false);
        self
    }

    /// Truncation trick towards `w_avg` with strength ψ (1 = none, 0 = the average).
    pub fn truncate(&self, w: Tensor<2>, psi: f32) -> Tensor<2> {
        if psi == 1.0 {
            return w;
        }
        let avg = self.w_avg.val().unsqueeze_dim::<2>(0);
        avg.clone() + (w - avg) * psi
    }
}

/// Multi-modal truncation (Mokady et al. 2022, "Self-Distilled StyleGAN"): each row of `w`
/// `[B, w_dim]` moves towards its nearest mode `c` (Euclidean in W) of `modes` `[K, w_dim]`:
/// w' = c + ψ·(w − c). Where the data has distinct modes (garment types, colour schemes), the
/// mean that ordinary truncation pulls towards is a blend that no subject looks like.
pub fn truncate_toward_modes(w: Tensor<2>, modes: &Tensor<2>, psi: f32) -> Tensor<2> {
    if psi == 1.0 {
        return w;
    }
    let c = modes.clone().select(0, nearest_mode(&w, modes));
    c.clone() + (w - c) * psi
}

/// Index `[B]` of the nearest row of `modes` `[K, w_dim]` (Euclidean) to each row of `w`.
pub fn nearest_mode(w: &Tensor<2>, modes: &Tensor<2>) -> Tensor<1, Int> {
    let [b, _] = w.dims();
    // ‖w − c‖² up to the per-row constant ‖w‖²: ‖c‖² − 2 w·c, `[B, K]`.
    let cc = modes.clone().powf_scalar(2.0).sum_dim(1).reshape([1, modes.dims()[0]]);
    let d = cc - w.clone().matmul(modes.clone().transpose()) * 2.0;
    d.argmin(1).reshape([b])
}

/// Multi-modal truncation of a (w_geo, w_tex) pair towards one *subject*: the mode index `k`
/// nearest to `w_geo` among `geo_modes`, then w_geo' = g_k + ψ·(w_geo − g_k) and
/// w_tex' = t_k + ψ·(w_tex − t_k). Row k of `geo_modes` and `tex_modes` are the two codes of
/// one training subject. The texture planes are the backbone's features (styled by w_geo)
/// projected by w_tex, so a subject's texture code only reproduces its garments together with
/// its own geometry code; truncating each branch towards its own nearest mode pairs codes of
/// different subjects and renders blends.
pub fn truncate_toward_subject(
    w_geo: Tensor<2>,
    w_tex: Tensor<2>,
    geo_modes: &Tensor<2>,
    tex_modes: &Tensor<2>,
    psi: f32,
) -> (Tensor<2>, Tensor<2>) {
    if psi == 1.0 {
        return (w_geo, w_tex);
    }
    let k = nearest_mode(&w_geo, geo_modes);
    let (cg, ct) = (geo_modes.clone().select(0, k.clone()), tex_modes.clone().select(0, k));
    (cg.clone() + (w_geo - cg) * psi, ct.clone() + (w_tex - ct) * psi)
}

/// Modes of the latent space in W, `[K, w_dim]` per branch (e.g. the codes of the training
/// subjects of a reconstruction warm-up), for multi-modal truncation
/// ([`crate::generator::pipeline::Generator::styles_with`]). Checkpoints may carry them (`checkpoint::load_latent_modes`).
#[derive(Clone, Debug)]
pub struct LatentModes {
    pub geo: Tensor<2>,
    pub tex: Tensor<2>,
    /// Per-layer offsets of the texture modes, `[K, n_tex_ws, w_dim]` (learned W+ subject
    /// codes, `trainer train --codes-wplus`): texture mode k's styles are row k of `tex` on
    /// every layer plus row k of these; truncation with ψ keeps (1 − ψ) of them. None: the
    /// modes are W codes.
    pub tex_layers: Option<Tensor<3>>,
    /// How ψ pairs the two branches' modes (stored in the checkpoint).
    pub pairing: ModePairing,
}

/// Truncation ψ used where the user sets none, for a generator with these latent modes
/// (`None`: a checkpoint without modes, truncating towards w_avg): 0 with modes, i.e. the
/// training subjects' own codes (a reconstruction warm-up has only been trained there; between
/// them it renders blends), else StyleGAN's customary 0.7.
pub fn default_psi(modes: Option<&LatentModes>) -> f32 {
    if modes.is_some() {
        0.0
    } else {
        0.7
    }
}

/// How multi-modal truncation picks the modes of the two branches.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ModePairing {
    /// One subject for both, the one whose geometry mode is nearest to w_geo
    /// ([`truncate_toward_subject`]): for generators whose colours are tied to their geometry
    /// code (a reconstruction warm-up without the texture-swap term).
    #[default]
    Subject,
    /// Each branch towards its own nearest mode ([`truncate_toward_modes`]): for generators
    /// trained with the texture-swap term, whose colours follow the texture code, so a seed
    /// pair gives one subject's geometry with another's colours.
    Branch,
}

impl ModePairing {
    /// The checkpoint metadata value.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Subject => "subject",
            Self::Branch => "branch",
        }
    }

    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "subject" => Some(Self::Subject),
            "branch" => Some(Self::Branch),
            _ => None,
        }
    }
}

impl LatentModes {
    pub fn count(&self) -> usize {
        self.geo.dims()[0]
    }

    /// Subject `geo`'s geometry code and subject `tex`'s texture code, `[1, w_dim]` each
    /// (re-texturing one training subject with another's colours); None out of range.
    pub fn subject(&self, geo: usize, tex: usize) -> Option<(Tensor<2>, Tensor<2>)> {
        let k = self.count();
        (geo < k && tex < k).then(|| (self.geo.clone().narrow(0, geo, 1), self.tex.clone().narrow(0, tex, 1)))
    }
}
