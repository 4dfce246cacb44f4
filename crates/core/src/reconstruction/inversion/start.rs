//! Where the inversion starts: the encoder's guess, or the latent mode (or w_avg) whose
//! render explains the photo best.

use std::sync::Arc;

use burn::module::Module;
use burn::tensor::Device;

use super::target::*;
use crate::body::body_fit::fit::BodyFit;
use crate::body::body_fit::refit::{refit_on_outline, RefitOptions};
use crate::generator::pipeline::{BodyContext, Generator, LatentModes, Styles};
use crate::generator::readback::read_f32;
use crate::generator::rigging::{generate_rigged_async, RiggedAvatar};
use crate::render::diff::avatar::{render_avatars_async, PosedGridCache};

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

/// The photo's body fit refined on the start's clothed outline
/// ([`crate::body::body_fit::refit`]): the start's avatar generated in the canonical pose and
/// rigged, its outline fitted to the person mask of `target` (the photo in `fit`'s crop) from
/// `fit`, and `target`'s camera and body replaced by the refined fit's. The bare body fitted
/// to a clothed person comes out broad and the avatar built on it broader still; fitted with
/// the avatar's own outline it comes in. The avatar is generated on the generator's
/// `device`, the fit runs on `fit_device` (an autodiff device; the browser's worker fits on
/// the CPU, as the page fits the photo). Returns the refined fit and the rigged avatar (the
/// avatar itself when no step follows).
#[allow(clippy::too_many_arguments)]
pub async fn refit_to_start(
    g: &Generator,
    ctx: &BodyContext,
    styles: &Styles,
    fit: &BodyFit,
    target: &mut InversionTarget,
    steps: usize,
    device: &Device,
    fit_device: &Device,
) -> Result<(BodyFit, RiggedAvatar), InversionError> {
    target.validate()?;
    let rigged = generate_rigged_async(g, ctx, styles, device).await?;
    refit_to_rigged(rigged, ctx, fit, target, steps, fit_device).await
}

/// [`refit_to_start`] on the start's avatar already generated and rigged.
pub async fn refit_to_rigged(
    rigged: RiggedAvatar,
    ctx: &BodyContext,
    fit: &BodyFit,
    target: &mut InversionTarget,
    steps: usize,
    fit_device: &Device,
) -> Result<(BodyFit, RiggedAvatar), InversionError> {
    target.validate()?;
    if rigged.canonical.mesh.faces.is_empty() {
        return Err(InversionError::EmptySurface);
    }
    let options = RefitOptions { steps, ..RefitOptions::default() };
    let model = Arc::new(ctx.model.clone());
    let outline = rigged.outline_mesh(ctx);
    let refit = refit_on_outline(model, fit, &target.mask, target.res, &outline, &options, fit_device)
        .await
        .map_err(|e| InversionError::Refit(e.to_string()))?;
    let mut body = refit.body_params();
    body.betas.truncate(target.view.body.betas.len());
    target.view = crate::render::camera::View { world_to_camera: refit.world_to_camera(), body };
    Ok((refit, rigged))
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
/// silhouette), with each candidate's loss. Renders without gradients: the generator's
/// parameters untracked, so that on an autodiff device no candidate's forward pass leaves a
/// graph behind (one is kept until a backward pass: 85 MB per candidate on the demo model,
/// 5.9 GB over its 65, which ended the browser worker's 4 GB).
/// The read-backs are awaited (every platform; `block_on_ready` natively).
pub async fn choose_start_async(
    g: &Generator,
    ctx: &BodyContext,
    target: &InversionTarget,
    candidates: &[StartCandidate],
    device: &Device,
) -> Result<(usize, Vec<f32>), InversionError> {
    target.validate()?;
    let g = &g.clone().no_grad();
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

/// [`image_loss`] of a render given as CHW RGB and mask in [−1, 1].
fn image_loss_cpu(t: &InversionTarget, rgb_chw: &[f32], mask: &[f32]) -> f32 {
    let r2 = t.res * t.res;
    let rgb: Vec<f32> = (0..3 * r2).map(|i| (rgb_chw[(i % 3) * r2 + i / 3] + 1.0) * 0.5).collect();
    let mask: Vec<f32> = mask.iter().map(|m| (m + 1.0) * 0.5).collect();
    super::figures::image_loss(t, &rgb, &mask)
}
