//! Where `trainer invert`'s codes start and how the first avatar is shown: the encoder's guess
//! (or the latent-mode search), rendered on the body as first fitted, then on the body
//! refitted to its outline.

use anyhow::{Context, Result};
use getavatar_core::body::body_fit::fit::BodyFit;
use getavatar_core::body::body_model::BodyModel;
use getavatar_core::burn::module::Module;
use getavatar_core::burn::tensor::Device;
use getavatar_core::generator::network::synthesis::Triplanes;
use getavatar_core::generator::network::GeneratorConfig;
use getavatar_core::generator::pipeline::{BodyContext, Generator, LatentModes, Styles};
use getavatar_core::generator::readback::block_on_ready;
use getavatar_core::generator::rigging::{generate_rigged_async, generate_rigged_from_planes_async, RiggedAvatar};
use getavatar_core::reconstruction::garment_codes::{
    choose_garment_async, render_rigged, GarmentCandidate, GarmentCodes, WEIGH_SS,
};
use getavatar_core::reconstruction::inversion::{
    choose_start_async, encoder_start, refit_to_rigged, refit_to_start, start_candidates, InversionOptions,
    InversionTarget,
};
use getavatar_core::util::profile::{self, StageTime};

use super::{load_encoder_arg, render_at, rgba, view_metrics, InvertArgs, RefitMetrics, ViewMetrics};
use crate::atomic::write_atomic;
use crate::model_io::write_png;

/// The start at the input camera: the first avatar (the body as first fitted) and, with a
/// photo's fit and `refit_steps`, the start again on the body refitted to its outline.
pub(super) struct StartViews {
    pub(super) first_avatar: ViewMetrics,
    pub(super) seconds_to_first_avatar: f64,
    /// The first avatar's generation and render by stage (`util::profile`).
    pub(super) first_avatar_stages: Vec<StageTime>,
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

/// The start's triplanes made beside the body context ([`early_planes`]), with their
/// milliseconds.
pub(super) struct EarlyPlanes {
    pub(super) planes: Triplanes,
    pub(super) ms: f64,
}

/// The triplanes of `styles` on the device without autodiff, as the first avatar needs them:
/// the synthesis needs no body, so it runs while the body context is still being built.
pub(super) fn early_planes(g: &Generator, styles: &Styles) -> EarlyPlanes {
    let t = std::time::Instant::now();
    let s = Styles { geo: styles.geo.clone().inner(), tex: styles.tex.clone().inner() };
    let planes = g.valid().triplanes(&s);
    EarlyPlanes { planes, ms: t.elapsed().as_secs_f64() * 1e3 }
}

/// The first avatar: the start generated (from `early` where its triplanes were made already),
/// rigged and rendered at the input camera (`input_view_first.png`, seconds from `t0`). Then weigh the garment codes against it
/// (`styles` takes the chosen geometry), refit the photo's body fit on its outline (`target`
/// takes the refitted camera and body), and render the start through the exact per-pose path
/// there (`input_view_start.png`).
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
    early: Option<EarlyPlanes>,
    t0: std::time::Instant,
) -> Result<StartViews> {
    // The first avatar is what the app shows first and what `instant` exports: the guess
    // generated in the canonical pose, rigged, re-posed to the photo's body.
    // Renders without gradients: the generator and the codes on the device without autodiff
    // (the same values, without autodiff's dispatch; `styles` gets the chosen codes back with
    // autodiff at the end).
    let fit_dev = dev;
    let (dev, g) = (&dev.clone().inner(), &g.valid());
    let styles_out = styles;
    let styles = &mut Styles { geo: styles_out.geo.clone().inner(), tex: styles_out.tex.clone().inner() };
    profile::start(crate::bench::clock_ms);
    let guess = match &early {
        Some(early) => block_on_ready(generate_rigged_from_planes_async(g, ctx, styles, &early.planes, dev)),
        None => block_on_ready(generate_rigged_async(g, ctx, styles, dev)),
    };
    // Drawn with 2×2 samples (as the garment codes are weighed); its figures come from a
    // render with `MEASURE_SS` samples after the clock, as the exported avatar's do.
    profile::stage("render");
    let (rgb, mask) = match &guess {
        Ok(guess) => render_rigged(guess, ctx, target, WEIGH_SS),
        Err(_) => (Vec::new(), Vec::new()),
    };
    let mut stages = profile::finish().context("the stage recording was lost")?;
    if let Some(early) = &early {
        // Made beside the body context: not on the way to the first avatar unless the context
        // came first.
        let synthesis = StageTime { stage: "synthesis".into(), host_ms: early.ms, ..Default::default() };
        stages.stages.insert(0, synthesis);
    }
    let guess = guess.context("generating the guess")?;
    let seconds_to_first_avatar = t0.elapsed().as_secs_f64();
    write_png(&a.out.join("input_view_first.png"), &rgba(&rgb, &mask), target.res, 4)?;
    let (rgb, mask) = render_rigged(&guess, ctx, target, super::MEASURE_SS);
    let first_avatar = view_metrics(target, &rgb, &mask);
    let beside = if early.is_some() { " beside the body context" } else { "" };
    let by_stage: Vec<String> = stages
        .stages
        .iter()
        .map(|s| {
            let note = if s.stage == "synthesis" { beside } else { "" };
            format!("{} {:.0}{note}", s.stage, s.host_ms + s.gpu_wait_ms)
        })
        .collect();
    eprintln!(
        "first avatar after {seconds_to_first_avatar:.2} s: mask IoU {:.3}, masked PSNR {:.2} dB (ms: {})",
        first_avatar.mask_iou,
        first_avatar.psnr_db,
        by_stage.join(", ")
    );
    let (garments, mut rigged_garment) = match garment_codes.filter(|_| opts.garments) {
        Some(codes) => {
            let t = std::time::Instant::now();
            let choice = block_on_ready(choose_garment_async(g, ctx, target, styles, Some(guess), codes, dev))
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
        None => (None, Some(guess)),
    };
    let changed = garments.as_ref().is_some_and(|m| m.chosen.is_some());
    let (refit, rigged_refit) = match (photo_fit, opts.refit_steps) {
        (Some(fit), steps) if steps > 0 => {
            refit_photo(a, g, ctx, styles, rigged_garment.take(), fit, target, steps, (dev, fit_dev))?.unzip()
        }
        _ => (None, None),
    };
    let rigged_start = rigged_refit.or(rigged_garment);
    // At the body and camera the steps start from, through the exact per-pose path (paper eq. 2)
    // that the steps optimise.
    let (rgb, mask) = render_at(g, ctx, styles, &target.view, target.res, dev)?;
    let at_start = view_metrics(target, &rgb, &mask);
    eprintln!(
        "the start{}{} after {:.1} s: mask IoU {:.3}, masked PSNR {:.2} dB",
        if changed { " with the chosen garment" } else { "" },
        if refit.is_some() { " on the refitted body" } else { "" },
        t0.elapsed().as_secs_f64(),
        at_start.mask_iou,
        at_start.psnr_db
    );
    write_png(&a.out.join("input_view_start.png"), &rgba(&rgb, &mask), target.res, 4)?;
    *styles_out = Styles { geo: styles.geo.clone().autodiff(), tex: styles.tex.clone().autodiff() };
    Ok(StartViews {
        first_avatar,
        seconds_to_first_avatar,
        first_avatar_stages: stages.stages,
        at_start,
        rgb,
        mask,
        refit,
        rigged_start,
        garments,
    })
}

/// A candidate's image loss as printed ("-" when its outline did not qualify).
fn loss_text(loss: Option<f32>) -> String {
    loss.map_or_else(|| "-".to_string(), |l| format!("{l:.4}"))
}

/// The start's name, codes, (a search) each candidate's loss, and the encoder file's garment codes.
pub(super) type FirstGuess = (String, Styles, Vec<(String, f32)>, Option<GarmentCodes>);

/// The encoder's guess (`--encoder`, or the shipped encoder with the shipped generator); None
/// without an encoder, or, said on stderr, when the file cannot be used.
pub(super) fn encoder_guess(
    a: &InvertArgs,
    g: &Generator,
    model: &BodyModel,
    target: &InversionTarget,
    shipped: Option<&GeneratorConfig>,
    dev: &Device,
) -> Result<Option<FirstGuess>> {
    let Some((enc, path, garments)) = load_encoder_arg(a, g, shipped, dev) else { return Ok(None) };
    let styles =
        encoder_start(&enc, g, model, target, dev).with_context(|| format!("the encoder {}", path.display()))?;
    Ok(Some(("encoder".to_string(), styles, Vec::new(), garments)))
}

/// The latent mode (or w_avg) that explains the image best.
pub(super) fn search_guess(
    g: &Generator,
    modes: Option<&LatentModes>,
    ctx: &BodyContext,
    target: &InversionTarget,
    dev: &Device,
) -> Result<FirstGuess> {
    let cands = start_candidates(g, modes);
    let (best, losses) = block_on_ready(choose_start_async(g, ctx, target, &cands, dev))?;
    let all = cands.iter().zip(&losses).map(|(c, l)| (c.name.clone(), *l)).collect();
    Ok((cands[best].name.clone(), cands[best].styles.clone(), all, None))
}

/// The photo's body fit refined on the guess's outline (`refit_to_start`; `rigged`: the guess's
/// avatar already generated and rigged; the guess generated on `dev`, the fit optimised on
/// `fit_dev`, which records gradients), written to
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
    (dev, fit_dev): (&Device, &Device),
) -> Result<Option<(RefitMetrics, RiggedAvatar)>> {
    let t = std::time::Instant::now();
    let refined = match rigged {
        Some(rigged) => block_on_ready(refit_to_rigged(rigged, ctx, fit, target, steps, fit_dev)),
        None => block_on_ready(refit_to_start(g, ctx, styles, fit, target, steps, dev, fit_dev)),
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
