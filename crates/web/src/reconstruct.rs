//! Single-image reconstruction in the browser (paper Sec. 5.4, `getavatar_core::inversion`):
//! the photo, resampled into its body fit's crop, is explained by the generator's codes (W+)
//! and then by its tuned weights (PTI), all on the page's WebGPU device through burn with
//! autodiff. The task awaits one step at a time (each ends in GPU read-backs), yields to the
//! browser between steps so egui keeps drawing, reports every step's terms and a preview
//! (the step's own render, read back), and stops at the next step on Cancel, leaving the
//! app's avatar as it was. Its result is an ordinary avatar of the app: rigged to the body,
//! with its own (tuned) generator for the per-pixel texture and the bake, and the photo's
//! colours projected onto the surface the photo sees.
//!
//! The photo never leaves the page: the task fetches nothing (the model files were fetched at
//! start-up).

use std::rc::Rc;

use eframe::egui;
use getavatar_core::burn::module::Module;

use getavatar_core::burn::tensor::Device;
use getavatar_core::checkpoint::{load_discriminator, load_generator_and_modes, load_inverted};
use getavatar_core::generator::{generate_rigged_async, BodyContext, Generator, Styles};
use getavatar_core::inversion::{
    choose_start_async, mask_iou, masked_psnr, render_images_async, start_candidates, InversionOptions,
    InversionTarget, Inverter, Phase, StepReport,
};
use getavatar_core::network::GeneratorConfig;
use getavatar_core::photo_projection::SourcePhoto;
use getavatar_core::rigging::RiggedAvatar;

use crate::automation::PhotoSource;
use crate::generate::{Projected, TextureField};
use crate::platform::{fetch_bytes, now_ms};
use crate::task::{yield_to_browser, EventKind, Task, TaskEvent};

/// What a reconstruction needs from the app.
pub struct ReconstructRequest {
    /// The shipped checkpoint's bytes (None: the deterministic random weights).
    pub checkpoint: Option<Rc<Vec<u8>>>,
    /// The shipped RGB discriminator's bytes, for the perceptual term (None: the term is off).
    pub discriminator: Option<Rc<Vec<u8>>>,
    pub cfg: GeneratorConfig,
    pub ctx: Rc<BodyContext>,
    /// The photo at the fit's camera, at the inversion's resolution.
    pub target: InversionTarget,
    /// The same photo at a higher resolution for the colour projection (None: off), made
    /// when the finish needs it (a large resample: its own slice of the UI thread).
    pub projection: Option<Box<dyn FnOnce() -> Option<InversionTarget>>>,
    pub options: InversionOptions,
    /// A preview every this many steps (0: only the final one).
    pub preview_every: usize,
    /// Search the model's subjects (and w_avg) for the start; else start at w_avg.
    pub search_start: bool,
    /// An autodiff device (the page's WebGPU device under burn's autodiff).
    pub device: Device,
}

/// One step done.
pub struct Progress {
    pub report: StepReport,
    /// Steps done in both phases, and in all.
    pub done: usize,
    pub total: usize,
    /// Milliseconds since the first step began.
    pub elapsed_ms: f64,
}

/// A render at the photo's camera (HWC sRGB and mask in [0, 1], the target's resolution).
pub struct Preview {
    pub rgb: Vec<f32>,
    pub mask: Vec<f32>,
    /// Steps done when it was rendered.
    pub done: usize,
}

/// A finished reconstruction.
pub struct Reconstructed {
    /// The tuned generator (on the autodiff device, without gradients) and the codes.
    pub generator: Rc<Generator>,
    pub styles: Styles,
    /// Rigged to the body, vertex colours with the photo projected on.
    pub rigged: RiggedAvatar,
    /// The photo and its projection onto the avatar, for the bake and "Save reconstruction".
    pub projection: Option<Rc<Projected>>,
    /// At the photo's camera: the avatar's mask IoU with the person mask, masked PSNR (dB)
    /// (None for a reconstruction opened from its file).
    pub fit: Option<(f32, f32)>,
    /// The file it was opened from (None: reconstructed here).
    pub opened: Option<String>,
    /// Milliseconds in all, and of the finish (final render, extraction, rigging, projection).
    pub millis: f64,
    pub finish_ms: f64,
}

/// What a reconstruction reports.
pub enum ReconstructEvent {
    /// The start was chosen (its name, of how many candidates, in how many milliseconds
    /// with the model's loading) and the steps begin.
    Started {
        start: String,
        candidates: usize,
        perceptual: bool,
        millis: f64,
    },
    Step(Box<Progress>),
    Preview(Box<Preview>),
    Finished(Box<Reconstructed>),
    /// The reconstruction as a file ("Save reconstruction").
    Saved(Vec<u8>),
    /// One sentence for the user; the app stays as it was.
    Failed(String),
    Cancelled,
}

impl TaskEvent for ReconstructEvent {
    fn kind(&self) -> EventKind {
        match self {
            ReconstructEvent::Started { .. } | ReconstructEvent::Step(_) => EventKind::Log,
            ReconstructEvent::Preview(_) => EventKind::Latest,
            _ => EventKind::Outcome,
        }
    }
}

pub type ReconstructTask = Task<ReconstructEvent>;

/// Start a reconstruction; its events arrive on the returned task.
pub fn reconstruct(req: ReconstructRequest, repaint: egui::Context) -> ReconstructTask {
    let task = ReconstructTask::default();
    let t = task.clone();
    wasm_bindgen_futures::spawn_local(async move {
        let t0 = now_ms();
        let event = match run(req, &t, &repaint).await {
            Ok(Some(mut r)) => {
                r.millis = now_ms() - t0;
                ReconstructEvent::Finished(Box::new(r))
            }
            Ok(None) => ReconstructEvent::Cancelled,
            Err(e) => ReconstructEvent::Failed(format!("the reconstruction failed: {e}")),
        };
        t.push(event, &repaint);
    });
    task
}

async fn run(
    req: ReconstructRequest,
    task: &ReconstructTask,
    repaint: &egui::Context,
) -> Result<Option<Reconstructed>, String> {
    let t0 = now_ms();
    let dev = &req.device;
    // Not in the frame that asked (it resampled the photo): loading the model is a slice too.
    yield_to_browser().await;
    let (g, modes) = match &req.checkpoint {
        Some(bytes) => load_generator_and_modes(bytes, &req.cfg, dev).map_err(|e| format!("the model: {e}"))?,
        None => (Generator::new(&req.cfg, 0, dev), None),
    };
    yield_to_browser().await;
    let disc = match &req.discriminator {
        Some(bytes) => Some(load_discriminator(bytes, dev).map_err(|e| format!("the discriminator: {e}"))?),
        None => None,
    };
    let candidates = start_candidates(&g, modes.as_ref());
    yield_to_browser().await;
    if task.cancelled() {
        return Ok(None);
    }
    // Candidate 0 is w_avg.
    let best = if req.search_start {
        choose_start_async(&g, &req.ctx, &req.target, &candidates, dev).await.map_err(|e| e.to_string())?.0
    } else {
        0
    };
    let ctx = req.ctx.as_ref();
    let start = &candidates[best];
    let mut inv = Inverter::new(g, ctx, disc, req.target.clone(), &start.styles, req.options.clone(), dev)
        .map_err(|e| e.to_string())?;
    task.push(
        ReconstructEvent::Started {
            start: start.name.clone(),
            candidates: candidates.len(),
            perceptual: inv.has_perceptual(),
            millis: now_ms() - t0,
        },
        repaint,
    );
    let t_steps = now_ms();
    loop {
        // Hand the page a frame between steps: it repaints, shows progress and sees Cancel.
        yield_to_browser().await;
        if task.cancelled() {
            return Ok(None);
        }
        let Some(report) = inv.step_async().await.map_err(|e| e.to_string())? else { break };
        let (done, total) = inv.progress();
        let elapsed_ms = now_ms() - t_steps;
        task.push(ReconstructEvent::Step(Box::new(Progress { report, done, total, elapsed_ms })), repaint);
        if req.preview_every > 0 && done % req.preview_every == 0 && done < total {
            if let Some((rgb, mask)) = inv.last_images_async().await.map_err(|e| e.to_string())? {
                task.push(ReconstructEvent::Preview(Box::new(Preview { rgb, mask, done })), repaint);
            }
        }
    }
    debug_assert_eq!(inv.phase(), Phase::Done);

    // The result at the photo's camera: the final preview and the figures.
    let t_finish = now_ms();
    let (rgb, mask) =
        render_images_async(&inv.render_async().await.map_err(|e| e.to_string())?).await.map_err(|e| e.to_string())?;
    let t = &req.target;
    let (iou, psnr) = (mask_iou(&mask, &t.mask), masked_psnr(&rgb, &t.rgb, &t.mask));
    let (_, total) = inv.progress();
    task.push(ReconstructEvent::Preview(Box::new(Preview { rgb, mask, done: total })), repaint);
    yield_to_browser().await;
    if task.cancelled() {
        return Ok(None);
    }

    // The avatar: extracted, rigged, the photo's colours on what the photo sees.
    let g = inv.generator().clone().no_grad();
    let styles = inv.styles();
    let mut rigged = generate_rigged_async(&g, ctx, &styles, dev).await.map_err(|e| e.to_string())?;
    if rigged.canonical.mesh.faces.is_empty() {
        return Err("the reconstructed generator produced an empty surface".into());
    }
    let projection = match req.projection {
        Some(crop) => {
            yield_to_browser().await;
            let photo = crop();
            yield_to_browser().await;
            photo.map(|p| project(&mut rigged, ctx, p.source_photo()))
        }
        None => None,
    };
    Ok(Some(Reconstructed {
        generator: Rc::new(g),
        styles,
        rigged,
        projection,
        fit: Some((iou, psnr)),
        opened: None,
        millis: 0.0,
        finish_ms: now_ms() - t_finish,
    }))
}

/// The photo projected onto `rigged` (posed as the photo shows it); the viewport's vertex
/// colours show what the download's texture will.
fn project(rigged: &mut RiggedAvatar, ctx: &BodyContext, photo: SourcePhoto) -> Rc<Projected> {
    let projection = rigged.photo_projection(ctx, &photo);
    rigged.blend_photo_colors(ctx, &projection, &photo.view.body);
    Rc::new(Projected { photo, projection })
}

/// Open a saved reconstruction (`trainer invert`'s `inverted.safetensors` or the app's "Save
/// reconstruction"): its tuned generator and codes on `device`, extracted, rigged, and the
/// photo it was made from projected on again. Reported as a [`ReconstructEvent::Finished`]
/// with `opened` set, or [`ReconstructEvent::Failed`] with the reason.
pub fn open(
    source: PhotoSource,
    cfg: GeneratorConfig,
    ctx: Rc<BodyContext>,
    device: Device,
    repaint: egui::Context,
) -> ReconstructTask {
    let task = ReconstructTask::default();
    let t = task.clone();
    wasm_bindgen_futures::spawn_local(async move {
        let t0 = now_ms();
        let opened = async {
            let (name, bytes) = match source {
                PhotoSource::Bytes { name, bytes } => (name, bytes),
                PhotoSource::Url(url) => {
                    let b = fetch_bytes(&url).await.map_err(|e| format!("cannot fetch {url}: {e}"))?;
                    (url, b)
                }
            };
            let inv = load_inverted(&bytes, &cfg, &device)
                .map_err(|e| format!("{name} is not a reconstruction of this model: {e}"))?;
            drop(bytes);
            yield_to_browser().await;
            let mut rigged =
                generate_rigged_async(&inv.generator, &ctx, &inv.styles, &device).await.map_err(|e| e.to_string())?;
            if rigged.canonical.mesh.faces.is_empty() {
                return Err(format!("{name}: the reconstruction's generator produced an empty surface"));
            }
            let projection = inv.photo.map(|p| project(&mut rigged, &ctx, p));
            Ok::<_, String>(Reconstructed {
                generator: Rc::new(inv.generator),
                styles: inv.styles,
                rigged,
                projection,
                fit: None,
                opened: Some(name.clone()),
                millis: now_ms() - t0,
                finish_ms: 0.0,
            })
        };
        let event = match opened.await {
            Ok(r) => ReconstructEvent::Finished(Box::new(r)),
            Err(e) => ReconstructEvent::Failed(format!("cannot open the reconstruction: {e}")),
        };
        t.push(event, &repaint);
    });
    task
}

/// Save the shown reconstruction (`field`) as one file; reported as
/// [`ReconstructEvent::Saved`] or [`ReconstructEvent::Failed`].
pub fn save(field: Rc<TextureField>, cfg: GeneratorConfig, repaint: egui::Context) -> ReconstructTask {
    let task = ReconstructTask::default();
    let t = task.clone();
    wasm_bindgen_futures::spawn_local(async move {
        let event = match field.save_async(&cfg).await {
            Ok(bytes) => ReconstructEvent::Saved(bytes),
            Err(e) => ReconstructEvent::Failed(format!("cannot save the reconstruction: {e}")),
        };
        t.push(event, &repaint);
    });
    task
}
