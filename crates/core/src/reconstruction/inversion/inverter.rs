//! The inversion's optimiser: W+ codes, then pivotal tuning, one awaited step at a time.

use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use super::figures::*;
use super::target::*;
use crate::generator::network::discriminator::Discriminator;
use crate::generator::optim::Adam;
use crate::generator::pipeline::{is_texture_param, BodyContext, Generator, Styles};
#[cfg(not(target_arch = "wasm32"))]
use crate::generator::readback::block_on_ready;
use crate::generator::readback::{read_f32, ReadbackError};
use crate::render::diff::avatar::{render_avatars_async, FakeViews, PosedGridCache};
use crate::util::cooperative::checkpoint;
use crate::util::rng::Rng;

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
    /// This step's render showed a collapse ([`COLLAPSED_IOU`]): it made no update, and the
    /// phase goes on from its best state at half the rate.
    #[serde(default)]
    pub restarted: bool,
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
    /// The W+ codes with the lowest loss so far, that loss ([`DIVERGED`]) and their mask IoU
    /// ([`COLLAPSED_IOU`]).
    best: Option<(f32, Styles, f32)>,
    /// PTI's weights with the lowest image loss so far (the locality term left out: it is
    /// not every step's), that loss ([`DIVERGED`]) and their mask IoU ([`COLLAPSED_IOU`]).
    best_g: Option<(f32, Generator, f32)>,
    /// Each phase's guard against a collapse ([`COLLAPSED_IOU`]).
    w_guard: CollapseGuard,
    pti_guard: CollapseGuard,
}

/// A phase's state for [`COLLAPSED_IOU`]: the highest mask IoU since the phase's start or its
/// last restart, the factor on its rate (halved at each restart) and the step of the last
/// restart (the warm-up starts again there).
#[derive(Clone, Copy, Debug)]
struct CollapseGuard {
    best_iou: f32,
    rate: f32,
    restarted_at: Option<usize>,
}

impl CollapseGuard {
    fn new() -> Self {
        Self { best_iou: 0.0, rate: 1.0, restarted_at: None }
    }

    /// Whether a step's mask IoU `iou` shows a collapse; otherwise it counts towards the best.
    fn collapsed(&mut self, iou: f32) -> bool {
        if iou >= self.best_iou - COLLAPSED_IOU {
            self.best_iou = self.best_iou.max(iou);
            return false;
        }
        true
    }

    /// A restart at `step` from a state whose mask IoU was `iou`: half the rate from here.
    fn restart(&mut self, step: usize, iou: f32) {
        *self = Self { best_iou: iou, rate: self.rate * 0.5, restarted_at: Some(step) };
    }

    /// The factor on the phase's scheduled rate at `step`.
    fn rate_at(&self, step: usize) -> f32 {
        let rewarm = self.restarted_at.map_or(1.0, |at| ((step - at) as f32 / MIN_WARMUP_STEPS).min(1.0));
        self.rate * rewarm
    }
}

/// A W+ run whose last step's loss is more than this factor above the lowest it reached has
/// diverged late (Adam at the full learning rate can throw the codes off in one step, and the
/// run does not come back: on one held-out image the mask IoU fell from 0.95 to 0.89 after
/// step 130 of 200): it ends on the codes of its lowest loss instead. A settled run keeps its
/// last codes. PTI ends the same way on the weights of its lowest image loss (at a rate of 3e-3
/// one end-to-end run fell from 15.5 to 14.2 dB in its last ten steps).
pub const DIVERGED: f32 = 1.05;

/// A step whose render's mask IoU lies more than this below the highest its phase reached has
/// collapsed: the codes (W+) or the weights (PTI) go back to those of the phase's lowest loss so
/// far, Adam starts afresh, and the rest of the phase goes at half the rate (warmed up again
/// over [`MIN_WARMUP_STEPS`]); the step itself makes no update. On one held-out image `fast`'s
/// PTI at 1e-3 (the texture branch at 10×) took the mask IoU from 0.966 to 0.735 in 18 steps
/// and ended at 0.957, below where it started; with the restart it ended at 0.975. 200 W+ steps
/// at 0.1 dip by up to 0.28 and end up to 0.07 below their best. Settled runs dip by at most
/// 0.030 (`fast`'s W+ and PTI; 11 of 12 held-out images) and 0.028 (350 PTI steps at 3e-4, four
/// of six; docs/benchmarks.md, "The guard against a collapse").
pub const COLLAPSED_IOU: f32 = 0.04;

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
            best: None,
            best_g: None,
            w_guard: CollapseGuard::new(),
            pti_guard: CollapseGuard::new(),
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
        if self.w_guard.collapsed(terms.mask_iou) {
            if let Some((_, styles, iou)) = &self.best {
                // This step's gradients belong to the collapsed codes: no update.
                self.codes = LatentCodes::new(styles);
                self.adam_w = Adam::new(0.9, 0.999, 1e-8);
                self.w_guard.restart(self.step, *iou);
                let report = StepReport { phase: Phase::Latent, step: self.step, lr: 0.0, terms, restarted: true };
                self.advance();
                return Ok(report);
            }
        }
        let lr = lr_schedule(o.lr, self.step, o.steps, o.warmup, o.rampdown) * self.w_guard.rate_at(self.step);
        // Checkpoints (`cooperative`) around the backward pass: in the browser a step's parts
        // are separate slices of the UI thread.
        checkpoint().await;
        let grads = total.backward();
        checkpoint().await;
        if self.best.as_ref().is_none_or(|(b, _, _)| terms.total < *b) {
            self.best = Some((terms.total, self.styles(), terms.mask_iou));
        }
        self.codes = self.adam_w.step(lr, self.codes.clone(), &grads);
        if self.step + 1 == o.steps {
            if let Some((b, styles, _)) = self.best.take() {
                if terms.total > b * DIVERGED {
                    self.codes = LatentCodes::new(&styles);
                }
            }
        }
        let report = StepReport { phase: Phase::Latent, step: self.step, lr, terms, restarted: false };
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
        let image_loss = terms.total - terms.locality.unwrap_or(0.0) * o.locality_weight;
        if self.pti_guard.collapsed(terms.mask_iou) {
            if let Some((_, g, iou)) = &self.best_g {
                // This step's gradients belong to the collapsed weights: no update.
                self.g = g.clone();
                self.adam_g = Adam::new(0.9, 0.999, 1e-8);
                self.pti_guard.restart(self.step, *iou);
                let report = StepReport { phase: Phase::Pivotal, step: self.step, lr: 0.0, terms, restarted: true };
                self.advance();
                return Ok(report);
            }
        }
        let lr = lr_schedule(o.pti_lr, self.step, o.pti_steps, o.pti_warmup, o.pti_rampdown)
            * self.pti_guard.rate_at(self.step);
        checkpoint().await;
        let grads = total.backward();
        checkpoint().await;
        if self.best_g.as_ref().is_none_or(|(b, _, _)| image_loss < *b) {
            // A module clone shares its tensors (Adam returns new ones): no copy of the weights.
            self.best_g = Some((image_loss, self.g.clone(), terms.mask_iou));
        }
        // The synthesis backbone and decoders; the mapping networks get no gradient (the codes
        // are W+), so they stay as they are.
        let tex = o.pti_texture_lr_mul;
        let factor = |name: &str| match (is_tuned_param(name), is_texture_param(name)) {
            (false, _) => 0.0,
            (true, true) => tex,
            (true, false) => 1.0,
        };
        self.g = self.adam_g.step_scaled(lr, self.g.clone(), &grads, &factor);
        if self.step + 1 == o.pti_steps {
            if let Some((b, g, _)) = self.best_g.take() {
                if image_loss > b * DIVERGED {
                    self.g = g;
                }
            }
        }
        let report = StepReport { phase: Phase::Pivotal, step: self.step, lr, terms, restarted: false };
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

/// Which parameters PTI tunes: all but the mapping networks.
pub fn is_tuned_param(name: &str) -> bool {
    !name.starts_with("mapping_")
}
