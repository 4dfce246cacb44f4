//! Single-image reconstruction (paper Sec. 5.4): the generator's latent codes optimised so its
//! avatar, rendered at the photo's camera and fitted body pose, matches the photo; then pivotal
//! tuning (PTI, Roich et al. 2022) of the synthesis weights with the codes fixed.
//!
//! **Phase 1, W+ inversion.** Both branches' per-layer styles (`[1, n, w_dim]` each, W+) are
//! optimised by Adam (β = 0.9, 0.999) at `lr` with StyleGAN2's projector schedule (linear
//! warm-up over the first `warmup` of the steps, cosine ramp-down over the last `rampdown`).
//! The authors' script optimises Z+ for the texture only; here the geometry moves too (a
//! photo's clothes are not the template's), and the codes are W+ for both, held near their
//! start by `latent_reg · ‖w − w₀‖²` (mean over layers and dimensions). The start is the
//! checkpoint's latent mode (or w_avg) whose render explains the photo best ([`choose_start`]).
//!
//! **Phase 2, PTI.** The codes are frozen (the pivot); the synthesis backbone and decoders (not
//! the mapping networks) are tuned by Adam at `pti_lr` on the same image terms. PTI's locality
//! regulariser keeps the rest of the latent space: every `locality_every` steps a random code
//! `w_z` of each branch is pulled towards the pivot, `w_r = w_p + (w_z − w_p)·min(1, α/‖w_z −
//! w_p‖)`, and the tuned generator's render there is held to the original's (L2 + perceptual).
//!
//! **Terms** at the photo's camera, images in [−1, 1] as the discriminators see them
//! ([`crate::render::diff::avatar`]): masked RGB L1 + MSE (inside the person mask only: the photo's
//! background is not the renderer's), the silhouette (squared error of the antialiased mask vs
//! the person mask), a perceptual term, and the paper's eikonal and SDF cross-entropy
//! regularisers.
//!
//! **Perceptual term.** Every reference recipe downloads ImageNet VGG16 (LPIPS), impossible
//! here; random-weight networks are no substitute (LPIPS paper). As Deep Generative Prior's
//! `DiscriminatorLoss` does, the term is the L1 distance between multi-scale features of a
//! trained discriminator ([`Discriminator::features`]), the checkpoint's RGB discriminator,
//! both images composed on white with the person mask. Without a discriminator the term is
//! off and the report says so.
//!
//! The same code runs natively and in the browser: every read-back is awaited
//! ([`Inverter::step_async`]); natively [`Inverter::step`] runs it to completion at once.

use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use crate::body::body_fit::fit::BodyFit;
use crate::body::body_fit::landmarks::SegmentationMask;
use crate::generator::network::discriminator::Discriminator;
use crate::generator::optim::Adam;
use crate::generator::pipeline::{BodyContext, Generator, LatentModes, Styles};
#[cfg(not(target_arch = "wasm32"))]
use crate::generator::readback::block_on_ready;
use crate::generator::readback::{read_f32, ReadbackError};
use crate::render::camera::{reference_fov_y, View};
use crate::render::diff::avatar::{render_avatars_async, FakeViews, PosedGridCache};
use crate::util::cooperative::checkpoint;
use crate::util::rng::Rng;

/// What an inversion explains: one image at a known camera and body pose.
#[derive(Clone, Debug)]
pub struct InversionTarget {
    /// Camera and body pose/shape of the image (a dataset label, or the body fit's).
    pub view: View,
    /// Side of the square image, pixels.
    pub res: usize,
    /// sRGB colours in [0, 1], `res²·3`, row-major from the top.
    pub rgb: Vec<f32>,
    /// Person mask in [0, 1], `res²`.
    pub mask: Vec<f32>,
}

/// Why an inversion cannot run or stopped.
#[derive(Debug, thiserror::Error)]
pub enum InversionError {
    #[error("the target image must be square and at least 16 pixels wide, got {0}")]
    Resolution(usize),
    #[error("the target's {what} has {got} values, {res}² needs {want}")]
    Size { what: &'static str, got: usize, want: usize, res: usize },
    #[error("the target's {0} holds a value that is not finite or lies outside [0, 1]")]
    Range(&'static str),
    #[error("the person mask is empty: nothing to reconstruct")]
    EmptyMask,
    #[error("the generator's surface is empty at the photo's camera and pose")]
    EmptySurface,
    #[error("the fit's field of view {0:.4} rad is not the reference camera's {1:.4}")]
    FieldOfView(f32, f32),
    #[error("the photo has {got} values, {width}×{height} RGB needs {want}")]
    PhotoSize { got: usize, want: usize, width: usize, height: usize },
    #[error("the loss became {0} at step {1}")]
    NotFinite(f32, usize),
    #[error(transparent)]
    Readback(#[from] ReadbackError),
}

impl InversionTarget {
    /// A photo as the inversion sees it through its body fit: the photo (`width × height`
    /// sRGB in [0, 1], row-major RGB; any resolution, e.g. a preview, as long as it covers the
    /// photo the fit was made on) and the person mask (any resolution, covering the photo)
    /// resampled into the fit's crop at `res`² (white, and no person, outside the photo); the
    /// fit's camera, pose and shape (the first `num_betas` shape coefficients).
    pub fn from_photo(
        fit: &BodyFit,
        rgb: &[f32],
        width: usize,
        height: usize,
        mask: &SegmentationMask,
        res: usize,
        num_betas: usize,
    ) -> Result<Self, InversionError> {
        if (fit.fov_y - reference_fov_y()).abs() > 1e-3 {
            return Err(InversionError::FieldOfView(fit.fov_y, reference_fov_y()));
        }
        if rgb.len() != width * height * 3 || width == 0 || height == 0 {
            return Err(InversionError::PhotoSize { got: rgb.len(), want: width * height * 3, width, height });
        }
        if mask.data.len() != mask.width * mask.height || mask.data.is_empty() {
            let want = mask.width * mask.height;
            return Err(InversionError::Size { what: "person mask", got: mask.data.len(), want, res: mask.width });
        }
        let rgb = fit.framing.resample(rgb, width, height, 3, res, &[1.0, 1.0, 1.0]);
        let mask = fit.framing.resample_mask(&mask.data, mask.width, mask.height, res);
        let mut body = fit.body_params();
        body.betas.truncate(num_betas);
        let t = Self { view: View { world_to_camera: fit.world_to_camera(), body }, res, rgb, mask };
        t.validate()?;
        Ok(t)
    }

    /// The photo as the reconstructed avatar keeps it (its later bakes project it again).
    pub fn source_photo(&self) -> crate::reconstruction::photo_projection::SourcePhoto {
        crate::reconstruction::photo_projection::SourcePhoto {
            view: self.view.clone(),
            res: self.res,
            rgb: self.rgb.clone(),
            mask: self.mask.clone(),
        }
    }

    pub fn validate(&self) -> Result<(), InversionError> {
        let r = self.res;
        if r < 16 {
            return Err(InversionError::Resolution(r));
        }
        let check = |what, v: &[f32], c: usize| {
            if v.len() != r * r * c {
                return Err(InversionError::Size { what, got: v.len(), want: r * r * c, res: r });
            }
            if v.iter().any(|x| !x.is_finite() || *x < 0.0 || *x > 1.0) {
                return Err(InversionError::Range(what));
            }
            Ok(())
        };
        check("rgb", &self.rgb, 3)?;
        check("mask", &self.mask, 1)?;
        if self.mask.iter().all(|m| *m < 0.5) {
            return Err(InversionError::EmptyMask);
        }
        Ok(())
    }
}

/// The inversion's settings (plain data: the CLI and the app's automation take it as JSON).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct InversionOptions {
    /// W+ steps (the authors' script: 200).
    pub steps: usize,
    /// Adam learning rate of the codes (0.1).
    pub lr: f32,
    /// Fraction of the steps with a linear warm-up (0.05) and with the cosine ramp-down (0.25).
    pub warmup: f32,
    pub rampdown: f32,
    /// Weight of ‖w − w₀‖² (0.01).
    pub latent_reg: f32,
    /// PTI steps (PTI: at most 350).
    pub pti_steps: usize,
    /// PTI's Adam learning rate of the synthesis weights (3e-4).
    pub pti_lr: f32,
    /// PTI's locality regulariser: α (30), weight (1), every this many steps (1; 0 = off).
    pub locality_alpha: f32,
    pub locality_weight: f32,
    pub locality_every: usize,
    /// Term weights.
    pub rgb_l1: f32,
    pub rgb_mse: f32,
    pub silhouette: f32,
    pub perceptual: f32,
    pub eikonal: f32,
    pub cross_entropy: f32,
    /// Seed of the locality regulariser's random codes.
    pub seed: u64,
}

impl Default for InversionOptions {
    fn default() -> Self {
        Self {
            steps: 200,
            lr: 0.1,
            warmup: 0.05,
            rampdown: 0.25,
            latent_reg: 0.01,
            pti_steps: 350,
            pti_lr: 3e-4,
            locality_alpha: 30.0,
            locality_weight: 1.0,
            locality_every: 1,
            rgb_l1: 1.0,
            rgb_mse: 1.0,
            silhouette: 1.0,
            perceptual: 1.0,
            eikonal: 0.001,
            cross_entropy: 0.01,
            seed: 0,
        }
    }
}

impl InversionOptions {
    /// `full` (the defaults: 200 W+ and 350 PTI steps), `fast` (60 + 60, locality every 4
    /// steps) or `instant` (no steps: the start, the encoder's guess, is the avatar): what the
    /// app's quality preset picks.
    pub fn preset(name: &str) -> Option<Self> {
        match name {
            "instant" => Some(Self { steps: 0, pti_steps: 0, ..Self::default() }),
            "full" => Some(Self::default()),
            "fast" => Some(Self { steps: 60, pti_steps: 60, locality_every: 4, ..Self::default() }),
            _ => None,
        }
    }
}

/// Fewest steps of the learning-rate warm-up (with `warmup > 0`).
pub const MIN_WARMUP_STEPS: f32 = 10.0;

/// StyleGAN2 projector's learning-rate schedule at `step` of `steps`: linear warm-up over the
/// first `warmup` fraction, but at least [`MIN_WARMUP_STEPS`] steps (Adam's first steps move
/// every coordinate by about the learning rate whatever the gradient's size: at full rate they
/// throw a short run's codes off), cosine ramp-down over the last `rampdown` fraction.
pub fn lr_schedule(lr: f32, step: usize, steps: usize, warmup: f32, rampdown: f32) -> f32 {
    let t = (step as f32 + 0.5) / steps.max(1) as f32;
    let down = if rampdown > 0.0 { ((1.0 - t) / rampdown).min(1.0) } else { 1.0 };
    let down = 0.5 - 0.5 * (down * std::f32::consts::PI).cos();
    let warm_steps = (warmup * steps as f32).max(MIN_WARMUP_STEPS);
    let up = if warmup > 0.0 { ((step as f32 + 0.5) / warm_steps).min(1.0) } else { 1.0 };
    lr * down * up
}

/// The optimised codes (W+ per branch), a module so [`Adam`] updates them.
#[derive(Module, Debug)]
pub struct LatentCodes {
    pub geo: Param<Tensor<3>>,
    pub tex: Param<Tensor<3>>,
}

impl LatentCodes {
    pub fn new(s: &Styles) -> Self {
        Self {
            geo: Param::from_tensor(s.geo.clone().detach().require_grad()),
            tex: Param::from_tensor(s.tex.clone().detach().require_grad()),
        }
    }

    pub fn styles(&self) -> Styles {
        Styles { geo: self.geo.val(), tex: self.tex.val() }
    }
}

/// Which phase a step belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    Latent,
    Pivotal,
    Done,
}

/// The terms of one step (unweighted), for progress and metrics.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Terms {
    pub rgb_l1: f32,
    pub rgb_mse: f32,
    pub silhouette: f32,
    pub perceptual: Option<f32>,
    pub eikonal: f32,
    pub cross_entropy: f32,
    pub latent_reg: f32,
    pub locality: Option<f32>,
    /// The weighted total that was minimised.
    pub total: f32,
    /// IoU of the render's mask and the person mask (threshold ½).
    pub mask_iou: f32,
}

/// One step's report.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct StepReport {
    pub phase: Phase,
    /// Step within the phase (0-based).
    pub step: usize,
    pub lr: f32,
    pub terms: Terms,
}

/// A step's terms as tensors (`[1]` each), before their one read-back.
struct TermTensors {
    rgb_l1: Tensor<1>,
    rgb_mse: Tensor<1>,
    silhouette: Tensor<1>,
    perceptual: Option<Tensor<1>>,
    eikonal: Tensor<1>,
    cross_entropy: Tensor<1>,
    latent_reg: Option<Tensor<1>>,
    locality: Option<Tensor<1>>,
}

/// The target as tensors: RGB `[1, 3, R, R]` in [−1, 1], mask `[1, 1, R, R]` in [0, 1].
struct TargetTensors {
    rgb: Tensor<4>,
    mask: Tensor<4>,
    mask_sum: f32,
}

/// An inversion in progress: [`Inverter::step`] runs one step of the current phase.
pub struct Inverter<'a> {
    ctx: &'a BodyContext,
    target: InversionTarget,
    t: TargetTensors,
    opts: InversionOptions,
    device: Device,
    g: Generator,
    /// The generator before tuning (no gradients), for the locality regulariser.
    g0: Generator,
    disc: Option<Discriminator>,
    codes: LatentCodes,
    w0: Styles,
    adam_w: Adam,
    adam_g: Adam,
    phase: Phase,
    step: usize,
    grids: PosedGridCache,
    rng: Rng,
    /// The last step's render at the target's camera (RGB, mask; detached): the previews.
    last: Option<(Tensor<4>, Tensor<4>)>,
}

impl<'a> Inverter<'a> {
    /// An inversion of `target` by `g` (on an autodiff `device`) starting at `start`, with the
    /// perceptual term from `disc`'s features where given.
    pub fn new(
        g: Generator,
        ctx: &'a BodyContext,
        disc: Option<Discriminator>,
        target: InversionTarget,
        start: &Styles,
        opts: InversionOptions,
        device: &Device,
    ) -> Result<Self, InversionError> {
        target.validate()?;
        let r = target.res;
        let rgb: Vec<f32> = (0..3)
            .flat_map(|c| (0..r * r).map(move |k| (c, k)))
            .map(|(c, k)| target.rgb[3 * k + c] * 2.0 - 1.0)
            .collect();
        let t = TargetTensors {
            rgb: Tensor::from_data(TensorData::new(rgb, [1, 3, r, r]), device),
            mask: Tensor::from_data(TensorData::new(target.mask.clone(), [1, 1, r, r]), device),
            mask_sum: target.mask.iter().sum::<f32>().max(1.0),
        };
        let w0 = Styles { geo: start.geo.clone().detach(), tex: start.tex.clone().detach() };
        let phase = if opts.steps > 0 {
            Phase::Latent
        } else if opts.pti_steps > 0 {
            Phase::Pivotal
        } else {
            Phase::Done
        };
        Ok(Self {
            ctx,
            target,
            t,
            g0: g.clone().no_grad(),
            g,
            disc: disc.map(Module::no_grad),
            codes: LatentCodes::new(start),
            w0,
            adam_w: Adam::new(0.9, 0.999, 1e-8),
            adam_g: Adam::new(0.9, 0.999, 1e-8),
            phase,
            step: 0,
            grids: PosedGridCache::new(4),
            rng: Rng::new(opts.seed, 0x1771),
            last: None,
            opts,
            device: device.clone(),
        })
    }

    pub fn phase(&self) -> Phase {
        self.phase
    }

    /// Steps taken in the current phase.
    pub fn step_in_phase(&self) -> usize {
        self.step
    }

    /// Steps of both phases taken, and in all.
    pub fn progress(&self) -> (usize, usize) {
        let all = self.opts.steps + self.opts.pti_steps;
        let done = match self.phase {
            Phase::Latent => self.step,
            Phase::Pivotal => self.opts.steps + self.step,
            Phase::Done => all,
        };
        (done, all)
    }

    /// The current codes (detached).
    pub fn styles(&self) -> Styles {
        let s = self.codes.styles();
        Styles { geo: s.geo.detach(), tex: s.tex.detach() }
    }

    /// The current (tuned, after PTI) generator.
    pub fn generator(&self) -> &Generator {
        &self.g
    }

    pub fn target(&self) -> &InversionTarget {
        &self.target
    }

    pub fn has_perceptual(&self) -> bool {
        self.disc.is_some() && self.opts.perceptual > 0.0
    }

    /// Render the current avatar at the target's camera.
    #[cfg(not(target_arch = "wasm32"))]
    pub fn render(&self) -> Result<FakeViews, InversionError> {
        block_on_ready(self.render_async())
    }

    /// [`Inverter::render`], awaiting its read-backs.
    pub async fn render_async(&self) -> Result<FakeViews, InversionError> {
        self.render_with(&self.g, &self.styles()).await
    }

    /// The last step's render (before its update) as HWC sRGB and mask in [0, 1]: a preview
    /// that costs a read-back, not a render. `None` before the first step.
    pub async fn last_images_async(&self) -> Result<Option<(Vec<f32>, Vec<f32>)>, ReadbackError> {
        match &self.last {
            Some((rgb, mask)) => Ok(Some(images_async(rgb.clone(), mask.clone()).await?)),
            None => Ok(None),
        }
    }

    /// Generator `g`'s avatar of styles `s` at the target's camera and pose.
    async fn render_with(&self, g: &Generator, s: &Styles) -> Result<FakeViews, InversionError> {
        let view = std::slice::from_ref(&self.target.view);
        Ok(render_avatars_async(g, self.ctx, s, view, self.target.res, &self.grids, &self.device).await?)
    }

    /// The image terms of `f`: the weighted total and the unweighted parts (tensors, read
    /// back together at the end of the step).
    fn image_terms(&self, f: &FakeViews) -> (Tensor<1>, TermTensors) {
        let o = &self.opts;
        let (rgb, m, msum) = (self.t.rgb.clone(), self.t.mask.clone(), self.t.mask_sum);
        let d = (f.rgb.clone() - rgb.clone()) * 0.5; // in [0, 1] units
        let l1 = (d.clone().abs() * m.clone()).sum() / (3.0 * msum);
        let mse = (d.powf_scalar(2.0) * m.clone()).sum() / (3.0 * msum);
        let sil = ((f.mask.clone() + 1.0) * 0.5 - m.clone()).powf_scalar(2.0).mean();
        let mut total = l1.clone() * o.rgb_l1 + mse.clone() * o.rgb_mse + sil.clone() * o.silhouette;
        let mut perceptual = None;
        if let (Some(d), true) = (&self.disc, o.perceptual > 0.0) {
            // Both images on white with the person mask: the photo's background is not ours.
            let white = |x: Tensor<4>| x.clone() * m.clone() + (m.clone() * -1.0 + 1.0);
            let fa = d.features(white(f.rgb.clone()));
            let fb = d.features(white(rgb));
            let p = fa
                .into_iter()
                .zip(fb)
                .map(|(a, b)| (a - b.detach()).abs().mean())
                .reduce(|a, b| a + b)
                .unwrap_or_else(|| Tensor::zeros([1], &self.device));
            total = total + p.clone() * o.perceptual;
            perceptual = Some(p);
        }
        total = total + f.eikonal.clone() * o.eikonal + f.cross_entropy.clone() * o.cross_entropy;
        let parts = TermTensors {
            rgb_l1: l1,
            rgb_mse: mse,
            silhouette: sil,
            perceptual,
            eikonal: f.eikonal.clone(),
            cross_entropy: f.cross_entropy.clone(),
            latent_reg: None,
            locality: None,
        };
        (total, parts)
    }

    /// One step of the current phase; `None` once both phases are done. Native: runs at once.
    #[cfg(not(target_arch = "wasm32"))]
    pub fn step(&mut self) -> Result<Option<StepReport>, InversionError> {
        block_on_ready(self.step_async())
    }

    /// [`Inverter::step`], awaiting its read-backs (the browser's GPU).
    pub async fn step_async(&mut self) -> Result<Option<StepReport>, InversionError> {
        match self.phase {
            Phase::Done => Ok(None),
            Phase::Latent => self.latent_step().await.map(Some),
            Phase::Pivotal => self.pivotal_step().await.map(Some),
        }
    }

    async fn latent_step(&mut self) -> Result<StepReport, InversionError> {
        let o = self.opts.clone();
        let s = self.codes.styles();
        let f = self.render_with(&self.g, &s).await?;
        if f.triangles.iter().all(|&t| t == 0) {
            return Err(InversionError::EmptySurface);
        }
        let (mut total, mut parts) = self.image_terms(&f);
        let reg = (s.geo - self.w0.geo.clone()).powf_scalar(2.0).mean()
            + (s.tex - self.w0.tex.clone()).powf_scalar(2.0).mean();
        total = total + reg.clone() * o.latent_reg;
        parts.latent_reg = Some(reg);
        let terms = self.read_terms(parts, &f, &total).await?;
        let lr = lr_schedule(o.lr, self.step, o.steps, o.warmup, o.rampdown);
        // Checkpoints (`cooperative`) around the backward pass: in the browser a step's parts
        // are separate slices of the UI thread.
        checkpoint().await;
        let grads = total.backward();
        checkpoint().await;
        self.codes = self.adam_w.step(lr, self.codes.clone(), &grads);
        let report = StepReport { phase: Phase::Latent, step: self.step, lr, terms };
        self.advance();
        Ok(report)
    }

    async fn pivotal_step(&mut self) -> Result<StepReport, InversionError> {
        let o = self.opts.clone();
        let s = self.styles();
        let f = self.render_with(&self.g, &s).await?;
        if f.triangles.iter().all(|&t| t == 0) {
            return Err(InversionError::EmptySurface);
        }
        let (mut total, mut parts) = self.image_terms(&f);
        if o.locality_every > 0 && o.locality_weight > 0.0 && self.step % o.locality_every == 0 {
            let wr = self.locality_codes(&s).await?;
            let orig = self.render_with(&self.g0, &wr).await?;
            let tuned = self.render_with(&self.g, &wr).await?;
            // L2 + perceptual between the tuned and the original generator's renders, over the
            // whole image (both share the renderer's white background).
            let mut reg = (tuned.rgb.clone() - orig.rgb.clone().detach()).powf_scalar(2.0).mean()
                + (tuned.mask.clone() - orig.mask.clone().detach()).powf_scalar(2.0).mean();
            if let (Some(d), true) = (&self.disc, o.perceptual > 0.0) {
                let fa = d.features(tuned.rgb.clone());
                let fb = d.features(orig.rgb.clone().detach());
                for (a, b) in fa.into_iter().zip(fb) {
                    reg = reg + (a - b.detach()).abs().mean();
                }
            }
            total = total + reg.clone() * o.locality_weight;
            parts.locality = Some(reg);
        }
        let terms = self.read_terms(parts, &f, &total).await?;
        let lr = o.pti_lr;
        checkpoint().await;
        let grads = total.backward();
        checkpoint().await;
        // The synthesis backbone and decoders; the mapping networks get no gradient (the codes
        // are W+), so they stay as they are.
        self.g =
            self.adam_g.step_scaled(lr, self.g.clone(), &grads, &|name| if is_tuned_param(name) { 1.0 } else { 0.0 });
        let report = StepReport { phase: Phase::Pivotal, step: self.step, lr, terms };
        self.advance();
        Ok(report)
    }

    /// PTI's locality codes: per branch, a random code pulled to within α of the pivot.
    async fn locality_codes(&mut self, pivot: &Styles) -> Result<Styles, InversionError> {
        let z_dim = self.g.mapping_geo.z_dim();
        let z =
            |rng: &mut Rng, dev: &Device| Tensor::<2>::from_data(TensorData::new(rng.normals(z_dim), [1, z_dim]), dev);
        let zg = z(&mut self.rng, &self.device);
        let zt = z(&mut self.rng, &self.device);
        let wz = self.g0.styles(zg, zt, 1.0);
        let alpha = self.opts.locality_alpha;
        Ok(Styles {
            geo: pull_within(&pivot.geo, wz.geo, alpha).await?,
            tex: pull_within(&pivot.tex, wz.tex, alpha).await?,
        })
    }

    /// The step's terms and mask IoU, read back in one transfer (each read-back is a GPU
    /// round trip in the browser); keeps the render for the previews.
    async fn read_terms(&mut self, p: TermTensors, f: &FakeViews, total: &Tensor<1>) -> Result<Terms, InversionError> {
        let optional = [&p.perceptual, &p.latent_reg, &p.locality];
        let mut parts = vec![total.clone(), p.rgb_l1, p.rgb_mse, p.silhouette, p.eikonal, p.cross_entropy];
        parts.extend(optional.iter().filter_map(|t| (*t).clone()));
        let k = parts.len();
        let n = self.target.res * self.target.res;
        parts.push(f.mask.clone().narrow(0, 0, 1).reshape([n]));
        let v = read_f32(Tensor::cat(parts.into_iter().map(|t| t.detach()).collect(), 0)).await?;
        let mut opt = v[6..k].iter().copied();
        let mut next = |t: &Option<Tensor<1>>| t.as_ref().and_then(|_| opt.next());
        let (perceptual, latent_reg, locality) = (next(optional[0]), next(optional[1]), next(optional[2]));
        let mask: Vec<f32> = v[k..].iter().map(|m| (m + 1.0) * 0.5).collect();
        let terms = Terms {
            total: v[0],
            rgb_l1: v[1],
            rgb_mse: v[2],
            silhouette: v[3],
            eikonal: v[4],
            cross_entropy: v[5],
            perceptual,
            latent_reg: latent_reg.unwrap_or(0.0),
            locality,
            mask_iou: mask_iou(&mask, &self.target.mask),
        };
        if !terms.total.is_finite() {
            return Err(InversionError::NotFinite(terms.total, self.step));
        }
        self.last = Some((f.rgb.clone().detach(), f.mask.clone().detach()));
        Ok(terms)
    }

    fn advance(&mut self) {
        self.step += 1;
        match self.phase {
            Phase::Latent if self.step >= self.opts.steps => {
                self.step = 0;
                self.phase = if self.opts.pti_steps > 0 { Phase::Pivotal } else { Phase::Done };
            }
            Phase::Pivotal if self.step >= self.opts.pti_steps => {
                self.step = 0;
                self.phase = Phase::Done;
            }
            _ => {}
        }
    }
}

/// `w` moved towards `pivot` to within distance `alpha` (PTI's locality codes), detached.
async fn pull_within(pivot: &Tensor<3>, w: Tensor<3>, alpha: f32) -> Result<Tensor<3>, InversionError> {
    let d = w - pivot.clone();
    let dist = scalar(d.clone().powf_scalar(2.0).sum().sqrt()).await?;
    let k = if dist > alpha { alpha / dist } else { 1.0 };
    Ok((pivot.clone() + d * k).detach())
}

async fn scalar(t: Tensor<1>) -> Result<f32, InversionError> {
    Ok(read_f32(t).await?.first().copied().unwrap_or(f32::NAN))
}

/// Intersection over union of two masks thresholded at ½ (1 for two empty masks).
pub fn mask_iou(a: &[f32], b: &[f32]) -> f32 {
    crate::body::body_fit::metrics::mask_iou(a, b)
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

/// A candidate start: the codes and where they come from.
#[derive(Clone, Debug)]
pub struct StartCandidate {
    pub name: String,
    pub styles: Styles,
}

/// The photo encoder's first guess for `target` ([`crate::reconstruction::encoder`]): W+ styles of both
/// branches, without gradients; the start of the refinement, or the avatar itself (`instant`).
pub fn encoder_start(
    enc: &crate::reconstruction::encoder::Encoder,
    g: &Generator,
    model: &crate::body::body_model::BodyModel,
    target: &InversionTarget,
    device: &Device,
) -> Result<Styles, crate::reconstruction::encoder::EncoderError> {
    let res = enc.config().res;
    let image = crate::reconstruction::encoder::EncoderImage::new(
        &target.rgb,
        &target.mask,
        target.res,
        &target.view,
        model,
        res,
    )?;
    let s = enc.styles(g, &[&image.patchify()], device)?;
    Ok(Styles { geo: s.geo.detach(), tex: s.tex.detach() })
}

/// The start candidates of a checkpoint: w_avg of both branches, and each latent mode (the
/// training subjects' codes: their pairs, or with `pairing: branch` each geometry mode with
/// the w_avg texture and each texture mode with the w_avg geometry — the choice then combines
/// the best of each).
pub fn start_candidates(g: &Generator, modes: Option<&LatentModes>) -> Vec<StartCandidate> {
    let (ag, at) = (g.mapping_geo.w_avg_tensor(), g.mapping_tex.w_avg_tensor());
    let mut out = vec![StartCandidate { name: "w_avg".into(), styles: g.styles_from_w(ag.clone(), at.clone()) }];
    if let Some(m) = modes {
        for k in 0..m.count() {
            if let Some(styles) = g.subject_styles(m, k, k) {
                out.push(StartCandidate { name: format!("mode {k}"), styles });
            }
        }
    }
    out
}

/// The start whose render at the target's camera has the lowest image loss (RGB L1 + MSE +
/// silhouette), with each candidate's loss. Renders without gradients.
#[cfg(not(target_arch = "wasm32"))]
pub fn choose_start(
    g: &Generator,
    ctx: &BodyContext,
    target: &InversionTarget,
    candidates: &[StartCandidate],
    device: &Device,
) -> Result<(usize, Vec<f32>), InversionError> {
    block_on_ready(choose_start_async(g, ctx, target, candidates, device))
}

/// [`choose_start`], awaiting its read-backs.
pub async fn choose_start_async(
    g: &Generator,
    ctx: &BodyContext,
    target: &InversionTarget,
    candidates: &[StartCandidate],
    device: &Device,
) -> Result<(usize, Vec<f32>), InversionError> {
    target.validate()?;
    let grids = PosedGridCache::new(2);
    let mut losses = Vec::new();
    for c in candidates {
        let s = Styles { geo: c.styles.geo.clone().detach(), tex: c.styles.tex.clone().detach() };
        let view = std::slice::from_ref(&target.view);
        let f = render_avatars_async(g, ctx, &s, view, target.res, &grids, device).await?;
        let rgb: Vec<f32> = read_f32(f.rgb).await?;
        let mask: Vec<f32> = read_f32(f.mask).await?;
        losses.push(image_loss_cpu(target, &rgb, &mask));
    }
    let best = losses.iter().enumerate().min_by(|a, b| a.1.total_cmp(b.1)).map(|(i, _)| i).unwrap_or(0);
    Ok((best, losses))
}

/// The image terms (RGB L1 + MSE inside the person mask, silhouette squared error) of a render
/// given as CHW RGB and mask in [−1, 1], on the CPU.
fn image_loss_cpu(t: &InversionTarget, rgb_chw: &[f32], mask: &[f32]) -> f32 {
    let r2 = t.res * t.res;
    let (mut l1, mut mse, mut msum, mut sil) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    for k in 0..r2 {
        let m = t.mask[k] as f64;
        msum += m;
        for c in 0..3 {
            let d = ((rgb_chw[c * r2 + k] + 1.0) * 0.5 - t.rgb[3 * k + c]) as f64;
            l1 += m * d.abs();
            mse += m * d * d;
        }
        let s = ((mask[k] + 1.0) * 0.5 - t.mask[k]) as f64;
        sil += s * s;
    }
    let msum = msum.max(1.0);
    (l1 / (3.0 * msum) + mse / (3.0 * msum) + sil / r2 as f64) as f32
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
async fn images_async(rgb: Tensor<4>, mask: Tensor<4>) -> Result<(Vec<f32>, Vec<f32>), ReadbackError> {
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

/// Which parameters PTI tunes: all but the mapping networks.
pub fn is_tuned_param(name: &str) -> bool {
    !name.starts_with("mapping_")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn schedule_warms_up_holds_and_ramps_down() {
        let f = |s| lr_schedule(0.1, s, 200, 0.05, 0.25);
        assert!(f(0) < 0.01, "{}", f(0));
        assert!(f(4) < f(9) && f(9) < 0.1 + 1e-6);
        assert!((f(50) - 0.1).abs() < 1e-6 && (f(140) - 0.1).abs() < 1e-6);
        assert!(f(170) < 0.1 && f(199) < 0.001 && f(199) > 0.0, "{} {}", f(170), f(199));
        // A short run warms up over 10 steps all the same: its first step is small.
        let short = |s| lr_schedule(0.1, s, 3, 0.05, 0.25);
        assert!(short(0) < 0.006 && short(1) > short(0) && short(1) < 0.02, "{} {}", short(0), short(1));
    }

    #[test]
    fn psnr_of_known_error() {
        let a = vec![0.5f32; 12];
        let b = vec![0.6f32; 12];
        let p = masked_psnr(&a, &b, &[1.0; 4]);
        assert!((p - 20.0).abs() < 1e-3, "{p}");
        // Pixels outside the mask do not count.
        let mut c = b.clone();
        c[0] = 0.0;
        assert!((masked_psnr(&a, &c, &[0.0, 1.0, 1.0, 1.0]) - 20.0).abs() < 1e-3);
    }
}
