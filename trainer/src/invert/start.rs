//! Where `trainer invert`'s codes start and how the first avatar is shown: the encoder's guess
//! (or the latent-mode search), rendered on the body as first fitted, then on the body
//! refitted to its outline.

use anyhow::{Context, Result};
use getavatar_core::body::body_fit::fit::BodyFit;
use getavatar_core::burn::tensor::Device;
use getavatar_core::generator::network::GeneratorConfig;
use getavatar_core::generator::pipeline::{BodyContext, Generator, LatentModes, Styles};
use getavatar_core::generator::readback::block_on_ready;
use getavatar_core::generator::rigging::RiggedAvatar;
use getavatar_core::reconstruction::garment_codes::{choose_garment_async, GarmentCandidate, GarmentCodes};
use getavatar_core::reconstruction::inversion::{
    choose_start_async, encoder_start, refit_to_rigged, refit_to_start, start_candidates, InversionOptions,
    InversionTarget,
};

use super::{load_encoder_arg, render_at, rgba, view_metrics, InvertArgs, RefitMetrics, ViewMetrics};
use crate::atomic::write_atomic;
use crate::model_io::write_png;

/// The start at the input camera: the first avatar (the body as first fitted) and, with a
/// photo's fit and `refit_steps`, the start again on the body refitted to its outline.
pub(super) struct StartViews {
    pub(super) first_avatar: ViewMetrics,
    pub(super) seconds_to_first_avatar: f64,
    /// At the body the steps start from, with its render (RGB, mask).
    pub(super) at_start: ViewMetrics,
    pub(super) rgb: Vec<f32>,
    pub(super) mask: Vec<f32>,
    pub(super) refit: Option<RefitMetrics>,
    /// The refit's (or the garment choice's) rigged start (exported as it is when no step follows).
    pub(super) rigged_start: Option<RiggedAvatar>,
    pub(super) garments: Option<GarmentMetrics>,
}

/// The garment codes weighed against the encoder's guess (metrics.json's `garments`).
#[derive(serde::Serialize)]
pub(super) struct GarmentMetrics {
    /// The chosen code's name; null when the guess's own geometry stayed.
    chosen: Option<String>,
    seconds: f64,
    /// Each candidate at the first fit's camera, the guess first.
    candidates: Vec<GarmentCandidate>,
}

/// Render the start as the first avatar (`input_view_first.png`, seconds from `t0`), weigh the
/// garment codes against it (`styles` takes the chosen geometry), refit the photo's body fit
/// on its outline (`target` takes the refitted camera and body), render it again
/// (`input_view_start.png`).
#[allow(clippy::too_many_arguments)]
pub(super) fn start_views(
    a: &InvertArgs,
    g: &Generator,
    ctx: &BodyContext,
    styles: &mut Styles,
    garment_codes: Option<&GarmentCodes>,
    photo_fit: Option<&BodyFit>,
    target: &mut InversionTarget,
    opts: &InversionOptions,
    dev: &Device,
    t0: std::time::Instant,
) -> Result<StartViews> {
    let (mut rgb, mut mask) = render_at(g, ctx, styles, &target.view, target.res, dev)?;
    let first_avatar = view_metrics(target, &rgb, &mask);
    let seconds_to_first_avatar = t0.elapsed().as_secs_f64();
    write_png(&a.out.join("input_view_first.png"), &rgba(&rgb, &mask), target.res, 4)?;
    eprintln!(
        "first avatar after {seconds_to_first_avatar:.1} s: mask IoU {:.3}, masked PSNR {:.2} dB",
        first_avatar.mask_iou, first_avatar.psnr_db
    );
    let (garments, mut rigged_garment) = match garment_codes.filter(|_| opts.garments) {
        Some(codes) => {
            let t = std::time::Instant::now();
            let choice = block_on_ready(choose_garment_async(g, ctx, target, styles, codes, dev))
                .context("weighing the garment codes")?;
            let seconds = t.elapsed().as_secs_f64();
            let guess = &choice.candidates[0];
            match &choice.chosen {
                Some(name) => {
                    let c = choice.candidates.iter().find(|c| &c.name == name).unwrap_or(guess);
                    eprintln!(
                        "garment code `{name}` chosen over the guess's geometry in {seconds:.1} s: mask IoU {:.3} → {:.3}, image loss {} → {}",
                        guess.mask_iou, c.mask_iou, loss_text(guess.loss), loss_text(c.loss)
                    );
                }
                None if choice.candidates.len() == 1 => eprintln!(
                    "the guess's geometry kept: its outline overlaps the person (mask IoU {:.3}), no garment code weighed ({seconds:.1} s)",
                    guess.mask_iou
                ),
                None => {
                    let weighed = choice.candidates.iter().skip(1).filter(|c| c.loss.is_some()).count();
                    eprintln!(
                        "the guess's geometry kept against {} garment codes, {weighed} of them with an outline that qualified ({seconds:.1} s)",
                        codes.len()
                    )
                }
            }
            if choice.chosen.is_some() {
                *styles = choice.styles;
            }
            let m = GarmentMetrics { chosen: choice.chosen, seconds, candidates: choice.candidates };
            (Some(m), Some(choice.rigged))
        }
        None => (None, None),
    };
    let changed = garments.as_ref().is_some_and(|m| m.chosen.is_some());
    let (refit, rigged_refit) = match (photo_fit, opts.refit_steps) {
        (Some(fit), steps) if steps > 0 => {
            refit_photo(a, g, ctx, styles, rigged_garment.take(), fit, target, steps, dev)?.unzip()
        }
        _ => (None, None),
    };
    let rigged_start = rigged_refit.or(rigged_garment);
    let at_start = if refit.is_some() || changed {
        (rgb, mask) = render_at(g, ctx, styles, &target.view, target.res, dev)?;
        let m = view_metrics(target, &rgb, &mask);
        eprintln!(
            "the start{} after {:.1} s: mask IoU {:.3}, masked PSNR {:.2} dB",
            if refit.is_some() { " on the refitted body" } else { "" },
            t0.elapsed().as_secs_f64(),
            m.mask_iou,
            m.psnr_db
        );
        m
    } else {
        first_avatar
    };
    write_png(&a.out.join("input_view_start.png"), &rgba(&rgb, &mask), target.res, 4)?;
    Ok(StartViews { first_avatar, seconds_to_first_avatar, at_start, rgb, mask, refit, rigged_start, garments })
}

/// A candidate's image loss as printed ("-" when its outline did not qualify).
fn loss_text(loss: Option<f32>) -> String {
    loss.map_or_else(|| "-".to_string(), |l| format!("{l:.4}"))
}

/// The start's name, codes, (a search) each candidate's loss, and the encoder file's garment codes.
pub(super) type FirstGuess = (String, Styles, Vec<(String, f32)>, Option<GarmentCodes>);

/// Where the codes start: the encoder's guess (`--encoder`, else the shipped one), or the
/// latent mode (or w_avg) that explains the image best; its name and the candidates' losses.
pub(super) fn first_guess(
    a: &InvertArgs,
    g: &Generator,
    modes: Option<&LatentModes>,
    ctx: &BodyContext,
    target: &InversionTarget,
    shipped: Option<&GeneratorConfig>,
    dev: &Device,
) -> Result<FirstGuess> {
    Ok(match load_encoder_arg(a, g, shipped, dev) {
        Some((enc, path, garments)) => {
            let styles = encoder_start(&enc, g, &ctx.model, target, dev)
                .with_context(|| format!("the encoder {}", path.display()))?;
            ("encoder".to_string(), styles, Vec::new(), garments)
        }
        None => {
            let cands = start_candidates(g, modes);
            let (best, losses) = block_on_ready(choose_start_async(g, ctx, target, &cands, dev))?;
            let all = cands.iter().zip(&losses).map(|(c, l)| (c.name.clone(), *l)).collect();
            (cands[best].name.clone(), cands[best].styles.clone(), all, None)
        }
    })
}

/// The photo's body fit refined on the guess's outline (`refit_to_start`; `rigged`: the guess's
/// avatar already generated and rigged), written to
/// `fit_refined.json`; `target` takes its camera and body. When it cannot be refined (the
/// guess has no surface) the fit stays as it was, and the message says why.
#[allow(clippy::too_many_arguments)]
fn refit_photo(
    a: &InvertArgs,
    g: &Generator,
    ctx: &BodyContext,
    styles: &Styles,
    rigged: Option<RiggedAvatar>,
    fit: &BodyFit,
    target: &mut InversionTarget,
    steps: usize,
    dev: &Device,
) -> Result<Option<(RefitMetrics, RiggedAvatar)>> {
    let t = std::time::Instant::now();
    let refined = match rigged {
        Some(rigged) => block_on_ready(refit_to_rigged(rigged, ctx, fit, target, steps, dev)),
        None => block_on_ready(refit_to_start(g, ctx, styles, fit, target, steps, dev, dev)),
    };
    let (refined, rigged) = match refined {
        Ok(r) => r,
        Err(e) => {
            eprintln!("the body fit was not refined on the guess's outline ({e}); it stays as fitted");
            return Ok(None);
        }
    };
    write_atomic(&a.out.join("fit_refined.json"), refined.to_json()?.as_bytes())?;
    let r = RefitMetrics {
        steps,
        seconds: t.elapsed().as_secs_f64(),
        betas_before: fit.betas.clone(),
        betas_after: refined.betas.clone(),
    };
    let b1 = |b: &[f32]| b.get(1).copied().unwrap_or(0.0);
    eprintln!(
        "body refitted on the guess's outline in {:.1} s: β₁ {:.2} → {:.2} (fit_refined.json)",
        r.seconds,
        b1(&fit.betas),
        b1(&refined.betas)
    );
    Ok(Some((r, rigged)))
}
