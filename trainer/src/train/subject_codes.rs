//! Learned subject codes (not in the paper; Bojanowski et al. 2018, "Optimizing the Latent
//! Space of Generative Networks", GLO): in a reconstruction run each training subject's W code
//! per branch is the mapping of its fixed latent ([`super::reconstruction::subject_latents`])
//! plus a learned offset, trained by the same L1 as the generator (`run.json` `lr_codes`,
//! `--lr-codes`). With the offsets at zero the codes are those of a run without them.
//!
//! Why it was tried: the fixed codes are random points of W that the mapping network (at
//! StyleGAN's lr × 0.01) barely moves. A W+ inversion of one data view with the shipped
//! generator frozen draws stripes that the subject's own code renders as a smear
//! (`assets/models/codes_vs_network.png`), so the network can render more than the fixed
//! codes ask of it. What it gave (the MODEL_CARD's git history): one learned W per branch at rate
//! 0.01 for 225 steps, from a run's state at step 125, left v1's grid worse than that state
//! (RGB L1 0.0095 against 0.0090, mask 0.0064 against 0.0051), though its own grid was still
//! falling when the averaged codes came in; the inversion moves each layer's w on its own,
//! which one W per branch cannot.
//!
//! The offsets are saved in the training state with an exponential moving average beside
//! G_ema's (the same decay: G_ema with the current offsets renders each subject as a
//! generator some 60 steps older would at codes it was not trained with), and the generator
//! file carries G_ema's codes, moved by the averaged offsets, as its latent modes (what
//! sampling truncates towards and `eval --subject-codes` renders).

use anyhow::Result;
use getavatar_core::burn;
use getavatar_core::burn::module::{Module, Param};
use getavatar_core::burn::tensor::{Device, Int, Tensor, TensorData};
use getavatar_core::generator::pipeline::{Generator, LatentModes, Styles};
use getavatar_core::generator::readback::read_f32_now;

/// Per-subject offsets: `geo` in W, `[subjects, w_dim]`; `tex` in W, `[subjects, w_dim]`, or
/// with `codes_wplus` in W+, one offset per texture style layer, `[subjects, layers · w_dim]`
/// (layer-major within a row).
#[derive(Module, Debug)]
pub struct SubjectCodes {
    pub geo: Param<Tensor<2>>,
    pub tex: Param<Tensor<2>>,
}

impl SubjectCodes {
    /// Offsets `geo` (`[subjects, w_dim]`) and `tex` (`[subjects, tex_layers · w_dim]`),
    /// row-major, as trainable parameters.
    pub fn from_values(
        subjects: usize,
        w_dim: usize,
        tex_layers: usize,
        geo: Vec<f32>,
        tex: Vec<f32>,
        device: &Device,
    ) -> Self {
        let p =
            |v: Vec<f32>, w: usize| Param::from_tensor(Tensor::from_data(TensorData::new(v, [subjects, w]), device));
        Self { geo: p(geo, w_dim), tex: p(tex, tex_layers * w_dim) }
    }

    /// Zero offsets: every subject at its fixed latent's code.
    pub fn zeros(subjects: usize, w_dim: usize, tex_layers: usize, device: &Device) -> Self {
        let (g, t) = (vec![0.0; subjects * w_dim], vec![0.0; subjects * tex_layers * w_dim]);
        Self::from_values(subjects, w_dim, tex_layers, g, t, device)
    }

    /// The offsets that move the fixed codes `fixed` onto `modes` (a generator file's latent
    /// modes, e.g. a run started from a checkpoint trained with learned codes), with
    /// `tex_layers` texture offsets per subject (1: W codes; the generator's texture style
    /// count: W+). None where the file holds another number of subjects, or per-layer texture
    /// modes that W codes cannot hold.
    pub fn reaching(
        modes: &LatentModes,
        fixed: &LatentModes,
        tex_layers: usize,
        device: &Device,
    ) -> Result<Option<Self>> {
        let [n, w] = fixed.geo.dims();
        if modes.geo.dims() != [n, w] || modes.tex.dims() != [n, w] {
            return Ok(None);
        }
        let diff = |a: &Tensor<2>, b: &Tensor<2>| -> Result<Vec<f32>> {
            let (a, b) = (read_f32_now(a.clone())?, read_f32_now(b.clone())?);
            Ok(a.iter().zip(&b).map(|(x, y)| x - y).collect())
        };
        let tex_w = diff(&modes.tex, &fixed.tex)?;
        let tex = match (&modes.tex_layers, tex_layers) {
            (None, 1) => tex_w,
            (Some(_), 1) => return Ok(None),
            (layers, l) => {
                let extra = match layers {
                    Some(t) if t.dims() == [n, l, w] => read_f32_now(t.clone())?,
                    Some(_) => return Ok(None),
                    None => vec![0.0; n * l * w],
                };
                // Each subject's W offset on every layer, plus the file's layer offsets.
                (0..n * l * w).map(|i| tex_w[(i / (l * w)) * w + i % w] + extra[i]).collect()
            }
        };
        Ok(Some(Self::from_values(n, w, tex_layers, diff(&modes.geo, &fixed.geo)?, tex, device)))
    }

    /// The same offsets on `device` (for the EMA copy beside G_ema).
    pub fn copy_to(&self, device: &Device) -> Result<Self> {
        let [n, w] = self.geo.dims();
        let v = |p: &Param<Tensor<2>>| read_f32_now(p.val().detach());
        Ok(Self::from_values(n, w, self.tex_layers(), v(&self.geo)?, v(&self.tex)?, device))
    }

    /// Number of subjects.
    pub fn count(&self) -> usize {
        self.geo.dims()[0]
    }

    /// Texture offsets per subject: 1 (W codes) or the texture style count (W+).
    pub fn tex_layers(&self) -> usize {
        self.tex.dims()[1] / self.geo.dims()[1]
    }

    /// The offsets of `subjects` (`[B, w_dim]` and `[B, tex_layers · w_dim]`), tracked for
    /// the update.
    pub fn select(&self, subjects: &[usize]) -> (Tensor<2>, Tensor<2>) {
        (rows(self.geo.val(), subjects), rows(self.tex.val(), subjects))
    }

    /// The offsets of `subjects` as untracked tensors on `device`.
    pub fn values_of(&self, subjects: &[usize], device: &Device) -> Result<(Tensor<2>, Tensor<2>)> {
        let (geo, tex) = self.values_on(device)?;
        Ok((rows(geo, subjects), rows(tex, subjects)))
    }

    /// All offsets as untracked tensors on `device` (for the saved modes and the sample grid).
    pub fn values_on(&self, device: &Device) -> Result<(Tensor<2>, Tensor<2>)> {
        let t = |p: &Param<Tensor<2>>| -> Result<Tensor<2>> {
            Ok(Tensor::from_data(TensorData::new(read_f32_now(p.val().detach())?, p.dims()), device))
        };
        Ok((t(&self.geo)?, t(&self.tex)?))
    }
}

/// Rows `subjects` of `t` (`[subjects, k]` → `[B, k]`).
fn rows(t: Tensor<2>, subjects: &[usize]) -> Tensor<2> {
    let idx: Vec<i64> = subjects.iter().map(|&s| s as i64).collect();
    let n = idx.len();
    let device = t.device();
    t.select(0, Tensor::<1, Int>::from_data(TensorData::new(idx, [n]), &device))
}

/// The W codes `[B, w_dim]` per branch of subjects with fixed latents `zg`, `zt` under `g`:
/// the mappings, plus the subjects' learned offsets `(geo, tex)` where given (the texture
/// offsets only where they are W codes; W+ ones go onto the styles, [`with_layer_offsets`]).
pub(crate) fn subject_ws(
    g: &Generator,
    zg: Tensor<2>,
    zt: Tensor<2>,
    offsets: Option<(Tensor<2>, Tensor<2>)>,
) -> (Tensor<2>, Tensor<2>) {
    let (wg, wt) = (g.mapping_geo.forward(zg), g.mapping_tex.forward(zt));
    match offsets {
        Some((og, ot)) if ot.dims() == wt.dims() => (wg + og, wt + ot),
        Some((og, _)) => (wg + og, wt),
        None => (wg, wt),
    }
}

/// `styles` with W+ texture offsets `tex` (`[B, layers · w_dim]`) added, layer by layer;
/// unchanged for W offsets (which [`subject_ws`] already added) or none.
pub(crate) fn with_layer_offsets(styles: Styles, tex: Option<Tensor<2>>) -> Styles {
    let [b, n, w] = styles.tex.dims();
    match tex {
        Some(t) if t.dims()[1] == n * w && n > 1 => Styles { tex: styles.tex + t.reshape([b, n, w]), geo: styles.geo },
        _ => styles,
    }
}

/// The per-layer texture offsets of W+ codes as latent modes' `tex_layers` (`[subjects,
/// layers, w_dim]`); None for W codes.
pub(crate) fn layer_modes(tex: &Tensor<2>, w_dim: usize) -> Option<Tensor<3>> {
    let [n, k] = tex.dims();
    (k > w_dim).then(|| tex.clone().reshape([n, k / w_dim, w_dim]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use getavatar_core::generator::network::GeneratorConfig;
    use getavatar_core::generator::optim::Adam;

    fn rows(t: Tensor<2>) -> Vec<Vec<f32>> {
        let [_, w] = t.dims();
        read_f32_now(t).unwrap().chunks(w).map(<[f32]>::to_vec).collect()
    }

    /// A step on one subject's L1 moves that subject's offsets (towards lowering it) and
    /// leaves the undrawn subjects' rows where they were; zero offsets add nothing.
    #[test]
    fn an_update_moves_the_drawn_subjects_codes_only() {
        #[allow(deprecated)]
        let plain = Device::ndarray();
        let dev = plain.clone().autodiff();
        let cfg = GeneratorConfig::tiny();
        let g = Generator::new(&cfg, 0, &dev);
        let codes = SubjectCodes::zeros(3, cfg.w_dim, 1, &dev);
        let z = |s: u64| {
            Tensor::<2>::from_data(
                TensorData::new(getavatar_core::util::rng::Rng::new(s, 0).normals(cfg.z_dim), [1, cfg.z_dim]),
                &dev,
            )
        };
        let (w0, _) = subject_ws(&g, z(1), z(2), None);
        let (w1, t1) = subject_ws(&g, z(1), z(2), Some(codes.select(&[1])));
        assert_eq!(rows(w0.clone()), rows(w1.clone()), "zero offsets leave the codes as they are");
        // Pull subject 1's codes towards a target 1 unit above the current one per element.
        let target = w0.detach() + 1.0;
        let loss = (w1 - target).abs().mean() + t1.abs().mean();
        let grads = loss.backward();
        let mut adam = Adam::new(0.9, 0.99, 1e-8);
        let moved = adam.step(0.01, codes, &grads);
        let (geo, tex) = moved.values_on(&plain).unwrap();
        let (geo, tex) = (rows(geo), rows(tex));
        for s in [0, 2] {
            assert!(geo[s].iter().chain(&tex[s]).all(|v| *v == 0.0), "subject {s} was not drawn: {:?}", &geo[s][..4]);
        }
        // Adam's first step moves every element of the drawn row by the rate, towards the target.
        assert!(geo[1].iter().all(|v| (v - 0.01).abs() < 1e-4), "geo row 1: {:?}", &geo[1][..4]);
    }
}
