//! What an inversion explains (the photo at its camera and body pose) and its settings
//! (presets, the learning-rate schedule).

use serde::{Deserialize, Serialize};

use crate::body::body_fit::fit::BodyFit;
use crate::body::body_fit::landmarks::SegmentationMask;
use crate::generator::readback::ReadbackError;
use crate::render::camera::{reference_fov_y, View};

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
    #[error("refining the body fit on the first guess's outline: {0}")]
    Refit(String),
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
    /// Fractions of the PTI steps with [`lr_schedule`]'s warm-up and cosine ramp-down (0 and
    /// 0: a constant rate, as the PTI paper tunes; the presets warm up and ramp down a higher
    /// rate, which at full rate from its first step throws the weights off).
    pub pti_warmup: f32,
    pub pti_rampdown: f32,
    /// Factor on `pti_lr` for the texture branch's weights (`generator::is_texture_param`; 1).
    /// Only the image's colours depend on them, so a rate that would throw the geometry off
    /// (3e-3 moves the mask IoU by 0.06 in five steps) draws a garment's stripes in 60 steps.
    pub pti_texture_lr_mul: f32,
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
    /// Steps of the body fit's refinement on the start's clothed outline before the codes
    /// move ([`super::start::refit_to_start`]; a photo's fit only, 0: off).
    pub refit_steps: usize,
    /// Weigh the encoder file's garment codes against the encoder's guess before the refit
    /// ([`crate::reconstruction::garment_codes`]; an encoder file without them: nothing).
    /// `instant` only: its rule was chosen on `instant`'s avatars, and from the code it chose
    /// for the long dress `fast` exported 0.9 dB less than from the guess
    /// (docs/benchmarks.md, "Garment codes after the guess").
    pub garments: bool,
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
            pti_warmup: 0.0,
            pti_rampdown: 0.0,
            pti_texture_lr_mul: 1.0,
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
            refit_steps: REFIT_STEPS,
            garments: false,
        }
    }
}

impl InversionOptions {
    /// `full` (200 W+ and 350 PTI steps), `fast` (60 + 60, locality every 4 steps, the
    /// silhouette at [`FAST_SILHOUETTE`]) or
    /// `instant` (no steps: the start, the encoder's guess with the garment codes weighed, is
    /// the avatar): what the app's
    /// quality preset picks. Both presets that tune do PTI at 1e-3, warmed up and ramped down,
    /// with the texture branch at 10× ([`InversionOptions::scheduled_pti`]).
    pub fn preset(name: &str) -> Option<Self> {
        match name {
            "instant" => Some(Self { steps: 0, pti_steps: 0, garments: true, ..Self::default() }),
            "full" => Some(Self::default().scheduled_pti()),
            "fast" => Some(
                Self { steps: 60, pti_steps: 60, locality_every: 4, silhouette: FAST_SILHOUETTE, ..Self::default() }
                    .scheduled_pti(),
            ),
            _ => None,
        }
    }

    /// PTI at 1e-3 on phase 1's schedule (10 steps' warm-up, cosine ramp-down over the last
    /// quarter) instead of the default constant 3e-4, whose end-to-end curve still climbs after
    /// 350 steps, and the texture branch at 10× that rate: against the same schedule with no
    /// factor, `fast` gains +0.9 to +2.7 dB at the true camera and +0.1 to +1.7 dB end to end
    /// on three photos, `full` +4.2 dB end to end on one (docs/benchmarks.md, "PTI's rate").
    /// A constant 3e-3 on every weight jumps by up to 2 dB between steps.
    pub fn scheduled_pti(self) -> Self {
        Self { pti_lr: 1e-3, pti_warmup: 0.05, pti_rampdown: 0.25, pti_texture_lr_mul: 10.0, ..self }
    }
}

/// `fast`'s silhouette weight (the default 1): with 60 W+ steps from the encoder's guess the
/// outline is what lags (the guess of a long dress has trousers). At 10, on three photos at
/// the true camera and end to end, the mask IoU gains +0.014 to +0.039 and the masked PSNR
/// +0.2 to +2.2 dB against 1; 3 and 30 gain less (docs/benchmarks.md, "`fast`'s silhouette").
pub const FAST_SILHOUETTE: f32 = 10.0;

/// Steps of the body fit's refinement on the first guess's outline (every preset): end to end
/// on three photos the first avatar's mask IoU goes from 0.86–0.89 to 0.90–0.93
/// (docs/benchmarks.md, "The body refitted on the start's outline").
pub const REFIT_STEPS: usize = 60;

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
