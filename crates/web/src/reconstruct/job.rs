//! The reconstruction itself, the same on the page and in the worker: the body context, the
//! start (encoder guess or latent modes), the inversion's steps, the figures, the rig.

use std::rc::Rc;

use eframe::egui;
use getavatar_core::burn::module::Module;
use getavatar_core::generator::rigging::generate_rigged_async;

use getavatar_core::body::body_fit::fit::BodyFit;
use getavatar_core::body::body_fit::landmarks::SegmentationMask;
use getavatar_core::body::skinning::pose_body;
use getavatar_core::burn::tensor::Device;
use getavatar_core::generator::checkpoint::{
    inverted_of, load_discriminator, load_generator_and_modes, parse_safetensors_async, take_inverted_photo,
};
use getavatar_core::generator::network::GeneratorConfig;
use getavatar_core::generator::pipeline::{BodyContext, Generator, Styles};
use getavatar_core::generator::rigging::{RiggedArrays, RiggedAvatar};
use getavatar_core::reconstruction::encoder::load_encoder;
use getavatar_core::reconstruction::garment_codes::{choose_garment_async, GarmentCodes};
use getavatar_core::reconstruction::inversion::{
    choose_start_async, encoder_start, mask_iou, masked_psnr, refit_to_rigged, refit_to_start, render_images_async,
    start_candidates, InversionOptions, InversionTarget, Inverter, StartCandidate, StepReport,
};
use getavatar_core::reconstruction::photo_projection::SourcePhoto;

use crate::automation::PhotoSource;
pub use crate::automation::{Compute, StartChoice};
use crate::platform::{fetch_bytes, now_ms};
use crate::task::{yield_to_browser, EventKind, Task, TaskEvent};
use crate::texture_field::{FieldModel, Projected, TextureField};

/// What the inversion runs on: plain data, so that it can be handed to the reconstruction
/// worker (`super::worker`) as well as run on the page.
pub struct InversionJob {
    /// The shipped checkpoint's bytes (None: the deterministic random weights).
    pub checkpoint: Option<Rc<Vec<u8>>>,
    /// The shipped RGB discriminator's bytes, for the perceptual term (None: the term is off).
    pub discriminator: Option<Rc<Vec<u8>>>,
    pub cfg: GeneratorConfig,
    /// The photo at the fit's camera, at the inversion's resolution.
    pub target: InversionTarget,
    /// The photo for the colour projection (None: off), cropped when the finish needs it.
    pub projection: Option<ProjectionSource>,
    pub options: InversionOptions,
    /// A preview every this many steps (0: only the final one).
    pub preview_every: usize,
    /// Where the codes start.
    pub start: StartChoice,
    /// The shipped photo encoder's bytes (None: none ships; `StartChoice::Encoder` then
    /// searches the model's subjects and says so).
    pub encoder: Option<Rc<Vec<u8>>>,
    /// Where the worker computes (the page's fallback always uses the page's WebGPU device).
    pub compute: Compute,
    /// In the worker, a job without steps hands its result over before it renders it at the
    /// photo's camera for the figures (a whole forward pass: 20 s on SwiftShader), so the
    /// avatar is on screen sooner; the figures follow ([`ReconstructEvent::Measured`]).
    pub measure_after_result: bool,
    /// Whether a job without steps measures its result at all (false: the encoder's guess
    /// shown before a stage that refits the body and measures its own result).
    pub figures: bool,
}

/// The photo as the app holds it, with its body fit and person mask: the colour projection's
/// crop is made from it at the finish (a large resample, so only when it is needed).
#[derive(Clone, Debug)]
pub struct ProjectionSource {
    pub fit: BodyFit,
    /// `width × height` sRGB in [0, 1], row-major RGB.
    pub rgb: Vec<f32>,
    pub width: usize,
    pub height: usize,
    pub mask: SegmentationMask,
    /// Side of the crop, pixels.
    pub res: usize,
    pub num_betas: usize,
}

impl ProjectionSource {
    /// The photo in the fit's crop at `res`² (None where it cannot be made: no projection).
    pub fn crop(&self) -> Option<InversionTarget> {
        InversionTarget::from_photo(&self.fit, &self.rgb, self.width, self.height, &self.mask, self.res, self.num_betas)
            .ok()
    }
}

/// What a reconstruction needs from the app.
pub struct ReconstructRequest {
    pub job: InversionJob,
    pub ctx: Rc<BodyContext>,
    /// The page's WebGPU device (the app's generator's): the worker's result is rigged on it,
    /// a reconstruction on the page runs on it under burn's autodiff.
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
    /// The tuned generator (on the page's device, without gradients) and the codes, or the
    /// worker's file they are built from when first used.
    pub model: FieldModel,
    /// The result's file where the page has it (the worker's, or one opened): the worker
    /// computes the field's colours from it on a software adapter.
    pub file: Option<Rc<Vec<u8>>>,
    /// Rigged to the body, vertex colours with the photo projected on.
    pub rigged: RiggedAvatar,
    /// The photo and its projection onto the avatar, for the bake and "Save reconstruction".
    pub projection: Option<Rc<Projected>>,
    /// The photo's body fit refined on the start's outline (None: not refined): the app's
    /// body and photo fit become it.
    pub refit: Option<BodyFit>,
    /// At the photo's camera: the avatar's mask IoU with the person mask, masked PSNR (dB)
    /// (None for a reconstruction opened from its file).
    pub fit: Option<(f32, f32)>,
    /// The file it was opened from (None: reconstructed here).
    pub opened: Option<String>,
    /// Milliseconds in all, and of the finish (final render, extraction, rigging, projection).
    pub millis: f64,
    pub finish_ms: f64,
    /// Where the finish's time went (one line for the status; empty if not measured).
    pub finish_detail: String,
    /// Cancelled after this many steps: the result is the state at the last preview.
    pub stopped_at: Option<usize>,
    /// Its figures (`fit`) follow as a [`ReconstructEvent::Measured`], the task's outcome.
    pub measuring: bool,
}

/// The figures of a result that was shown before it was measured.
pub struct Measured {
    /// Mask IoU and masked PSNR (dB) at the photo's camera and the render they come from, or
    /// why there are none.
    pub figures: Result<((f32, f32), Preview), String>,
    /// Milliseconds of the render and its read-back.
    pub millis: f64,
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
        /// In the reconstruction worker (else on the page).
        in_worker: bool,
        /// The device the steps run on, in words ("CPU (NdArray) …", "WebGPU …").
        device: String,
        /// Why the start is not the one asked for ("" when it is).
        note: String,
        /// The garment code whose geometry the start took ("" when the guess's own stayed); how
        /// many the encoder file carries and how many were weighed (none when the guess's
        /// outline already overlaps the person well).
        garment: String,
        garment_codes: (usize, usize),
    },
    Step(Box<Progress>),
    Preview(Box<Preview>),
    /// The avatar; the task's outcome unless its figures follow (`measuring`).
    Finished(Box<Reconstructed>),
    Measured(Box<Measured>),
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
            ReconstructEvent::Finished(r) if r.measuring => EventKind::Log,
            _ => EventKind::Outcome,
        }
    }
}

pub type ReconstructTask = Task<ReconstructEvent>;

/// Where a running inversion reports its progress and learns of Cancel.
pub(crate) trait Progressing {
    fn push(&self, e: ReconstructEvent);
    fn cancelled(&self) -> bool;
}

/// A reconstruction on the page reports to its task.
struct OnPage<'a> {
    task: &'a ReconstructTask,
    repaint: &'a egui::Context,
}

impl Progressing for OnPage<'_> {
    fn push(&self, e: ReconstructEvent) {
        self.task.push(e, self.repaint);
    }
    fn cancelled(&self) -> bool {
        self.task.cancelled()
    }
}

/// Run the whole reconstruction on the page (the UI thread, in slices between steps).
pub(crate) fn run_on_page(req: ReconstructRequest, t: ReconstructTask, repaint: egui::Context) {
    wasm_bindgen_futures::spawn_local(async move {
        let t0 = now_ms();
        let out = OnPage { task: &t, repaint: &repaint };
        let event = match run(req, &out).await {
            Ok(Some(mut r)) => {
                r.millis = now_ms() - t0;
                ReconstructEvent::Finished(Box::new(r))
            }
            Ok(None) => ReconstructEvent::Cancelled,
            Err(e) => ReconstructEvent::Failed(format!("the reconstruction failed: {e}")),
        };
        t.push(event, &repaint);
    });
}

async fn run(req: ReconstructRequest, out: &dyn Progressing) -> Result<Option<Reconstructed>, String> {
    let (job, dev) = (&req.job, &req.device.clone().autodiff());
    let Some(mut inv) = invert(job, &req.ctx, dev, "WebGPU (the page's device)", out, false).await? else {
        return Ok(None);
    };
    let t_finish = now_ms();
    // The avatar: extracted, rigged, the photo's colours on what the photo sees.
    let ctx = req.ctx.as_ref();
    let mut rigged = match inv.rigged.take() {
        Some(rigged) => rigged,
        None => generate_rigged_async(&inv.generator, ctx, &inv.styles, dev).await.map_err(|e| e.to_string())?,
    };
    if rigged.canonical.mesh.faces.is_empty() {
        return Err("the reconstructed generator produced an empty surface".into());
    }
    let projection = match inv.projection(job) {
        Some(source) => {
            yield_to_browser().await;
            match source.crop() {
                Some(p) => Some(project(&mut rigged, ctx, p.source_photo()).await),
                None => None,
            }
        }
        None => None,
    };
    Ok(Some(Reconstructed {
        model: FieldModel::Built(Rc::new(inv.generator), inv.styles),
        file: None,
        rigged,
        projection,
        refit: inv.refit,
        fit: inv.fit,
        opened: None,
        millis: 0.0,
        finish_ms: inv.finish_ms + now_ms() - t_finish,
        finish_detail: format!(
            "page: final figures {:.1} s, rigging {:.1} s",
            inv.finish_ms / 1000.0,
            (now_ms() - t_finish) / 1000.0
        ),
        stopped_at: inv.stopped_at,
        measuring: false,
    }))
}

/// The inversion's outcome: the tuned generator (without gradients) and codes, and how well
/// they explain the photo at its camera.
pub(crate) struct Inverted<'a> {
    pub generator: Generator,
    pub styles: Styles,
    /// Mask IoU with the person mask, masked PSNR (dB); None while `unmeasured`.
    pub fit: Option<(f32, f32)>,
    /// The inverter and its target, when the figures were left for after the result
    /// ([`InversionJob::measure_after_result`]): [`measure`] them.
    pub unmeasured: Option<(Inverter<'a>, InversionTarget)>,
    /// Milliseconds of the final preview and figures (the last step's render read back).
    pub finish_ms: f64,
    /// Cancelled after this many steps (None: all done).
    pub stopped_at: Option<usize>,
    /// The photo's body fit refined on the start's outline (None: not refined).
    pub refit: Option<BodyFit>,
    /// The start's avatar, rigged by the garment choice or the refit, when it is the result
    /// (no step ran): the finish rigs it without generating it again.
    pub rigged: Option<RiggedAvatar>,
}

impl Inverted<'_> {
    /// The job's photo for the projection, with the refined fit's camera and body.
    pub(crate) fn projection(&self, job: &InversionJob) -> Option<ProjectionSource> {
        let src = job.projection.clone()?;
        Some(match &self.refit {
            Some(fit) => ProjectionSource { fit: fit.clone(), ..src },
            None => src,
        })
    }
}

/// The inversion itself (start, W+ and PTI steps, the final figures, which a job without
/// steps leaves for later where `defer` and it asks): `Ok(None)` when cancelled.
pub(crate) async fn invert<'a>(
    job: &InversionJob,
    ctx: &'a BodyContext,
    dev: &Device,
    device_label: &str,
    out: &dyn Progressing,
    defer: bool,
) -> Result<Option<Inverted<'a>>, String> {
    let t0 = now_ms();
    // Not in the frame that asked (it resampled the photo): loading the model is a slice too.
    yield_to_browser().await;
    let (g, modes) = match &job.checkpoint {
        Some(bytes) => load_generator_and_modes(bytes, &job.cfg, dev).map_err(|e| format!("the model: {e}"))?,
        None => (Generator::new(&job.cfg, 0, dev), None),
    };
    yield_to_browser().await;
    let disc = match &job.discriminator {
        Some(bytes) => Some(load_discriminator(bytes, dev).map_err(|e| format!("the discriminator: {e}"))?),
        None => None,
    };
    yield_to_browser().await;
    if out.cancelled() {
        return Ok(None);
    }
    let (start, candidates, mut note) = choose_start(job, &g, modes.as_ref(), ctx, dev).await?;
    // The garment codes are weighed on the body as first fitted, then the body is refitted on
    // the chosen outline (the order `trainer invert` follows).
    let (start, mut rigged, garment) = choose_garment(job, &g, ctx, start, dev).await?;
    let (garment, garment_codes) = garment.unwrap_or_else(|why| {
        note = format!("{note}{}{why}", if note.is_empty() { "" } else { "; " });
        (String::new(), (0, 0))
    });
    // The photo's body fit refined on the start's outline (a photo's job; the fit on the CPU).
    let mut target = job.target.clone();
    let refit = match (&job.projection, job.options.refit_steps) {
        (Some(src), steps) if steps > 0 => {
            #[allow(deprecated)] // burn 0.22 marks NdArray deprecated in favour of flex; the project's CPU backend.
            let cpu = Device::ndarray().autodiff();
            let refitted = match rigged.take() {
                Some(r) => refit_to_rigged(r, ctx, &src.fit, &mut target, steps, &cpu).await,
                None => refit_to_start(&g, ctx, &start.styles, &src.fit, &mut target, steps, dev, &cpu).await,
            };
            match refitted {
                Ok((fit, r)) => {
                    rigged = Some(r);
                    Some(fit)
                }
                Err(e) => {
                    note =
                        format!("{note}{}the body fit stays as fitted ({e})", if note.is_empty() { "" } else { "; " });
                    None
                }
            }
        }
        _ => None,
    };
    yield_to_browser().await;
    let mut inv = Inverter::new(g, ctx, disc, target.clone(), &start.styles, job.options.clone(), dev)
        .map_err(|e| e.to_string())?;
    out.push(ReconstructEvent::Started {
        start: start.name.clone(),
        candidates,
        perceptual: inv.has_perceptual(),
        millis: now_ms() - t0,
        in_worker: crate::platform::in_worker(),
        device: device_label.to_string(),
        note,
        garment,
        garment_codes,
    });
    let t_steps = now_ms();
    let mut stopped_at = None;
    loop {
        // Hand the page a frame between steps: it repaints, shows progress and sees Cancel.
        yield_to_browser().await;
        if out.cancelled() {
            // Cancel keeps the last preview's state as the avatar (nothing done: no avatar).
            match inv.progress().0 {
                0 => return Ok(None),
                done => {
                    stopped_at = Some(done);
                    break;
                }
            }
        }
        let Some(report) = inv.step_async().await.map_err(|e| e.to_string())? else { break };
        let (done, total) = inv.progress();
        let elapsed_ms = now_ms() - t_steps;
        out.push(ReconstructEvent::Step(Box::new(Progress { report, done, total, elapsed_ms })));
        if job.preview_every > 0 && done % job.preview_every == 0 && done < total {
            if let Some((rgb, mask)) = inv.last_images_async().await.map_err(|e| e.to_string())? {
                out.push(ReconstructEvent::Preview(Box::new(Preview { rgb, mask, done })));
            }
        }
    }

    let t_finish = now_ms();
    let (generator, styles) = (inv.generator().clone().no_grad(), inv.styles());
    // A step changed the codes or the weights: the start's avatar is not the result.
    let rigged = rigged.filter(|_| inv.progress().0 == 0);
    if !job.figures && inv.progress().0 == 0 {
        let unmeasured = None;
        return Ok(Some(Inverted {
            generator,
            styles,
            fit: None,
            unmeasured,
            finish_ms: 0.0,
            stopped_at,
            refit,
            rigged,
        }));
    }
    if defer && job.measure_after_result && inv.progress().0 == 0 {
        let unmeasured = Some((inv, target));
        return Ok(Some(Inverted {
            generator,
            styles,
            fit: None,
            unmeasured,
            finish_ms: 0.0,
            stopped_at,
            refit,
            rigged,
        }));
    }
    let (fit, preview) = measure(&inv, &target).await?;
    out.push(ReconstructEvent::Preview(Box::new(preview)));
    yield_to_browser().await;
    if stopped_at.is_none() && out.cancelled() {
        return Ok(None);
    }
    let finish_ms = now_ms() - t_finish;
    Ok(Some(Inverted { generator, styles, fit: Some(fit), unmeasured: None, finish_ms, stopped_at, refit, rigged }))
}

/// The result at the photo's camera: mask IoU and masked PSNR (dB) against `t`, and the render
/// as a preview. From the last step's render (the codes and weights before that step's
/// update), which costs a read-back; a render of its own would be another forward pass, as
/// long as a W+ step in the browser (82 s of a 330 s reconstruction on SwiftShader), so only
/// a job without steps makes one. `trainer invert` renders the final state.
pub(crate) async fn measure(inv: &Inverter<'_>, t: &InversionTarget) -> Result<((f32, f32), Preview), String> {
    let (rgb, mask) = match inv.last_images_async().await.map_err(|e| e.to_string())? {
        Some(images) => images,
        None => render_images_async(&inv.render_async().await.map_err(|e| e.to_string())?)
            .await
            .map_err(|e| e.to_string())?,
    };
    let fit = (mask_iou(&mask, &t.mask), masked_psnr(&rgb, &t.rgb, &t.mask));
    Ok((fit, Preview { rgb, mask, done: inv.progress().0 }))
}

/// The encoder's guess's name as a start.
const ENCODER_GUESS: &str = "the encoder's guess";

/// The start the job asks for: the candidate, how many were weighed, and why it is not the
/// one asked for ("" when it is). A missing or unreadable encoder falls back to the search.
async fn choose_start(
    job: &InversionJob,
    g: &Generator,
    modes: Option<&getavatar_core::generator::pipeline::LatentModes>,
    ctx: &BodyContext,
    dev: &Device,
) -> Result<(StartCandidate, usize, String), String> {
    let mut note = String::new();
    if job.start == StartChoice::Encoder {
        let guess = match &job.encoder {
            Some(bytes) => load_encoder(bytes, dev)
                .and_then(|enc| encoder_start(&enc, g, &ctx.model, &job.target, dev))
                .map_err(|e| format!("the photo encoder cannot be used ({e})")),
            None => Err("no photo encoder ships with this build".to_string()),
        };
        match guess {
            Ok(styles) => return Ok((StartCandidate { name: ENCODER_GUESS.into(), styles }, 1, note)),
            Err(why) => note = format!("{why}: searched the model's subjects instead"),
        }
    }
    let mut candidates = start_candidates(g, modes);
    let n = candidates.len();
    // Candidate 0 is w_avg.
    let best = if job.start == StartChoice::Average {
        0
    } else {
        choose_start_async(g, ctx, &job.target, &candidates, dev).await.map_err(|e| e.to_string())?.0
    };
    Ok((candidates.swap_remove(best), n, note))
}

/// What the garment choice gives: the start (with the chosen code's geometry), its avatar
/// rigged where the choice made it, and the code's name ("" when the guess's own geometry
/// stays) with how many codes the file carries and how many were weighed, or why the codes
/// could not be used (the guess then stays).
type GarmentOutcome = (StartCandidate, Option<RiggedAvatar>, Result<(String, (usize, usize)), String>);

/// The encoder file's garment codes weighed against the encoder's guess
/// ([`getavatar_core::reconstruction::garment_codes`], `options.garments`) at the job's
/// camera and body.
async fn choose_garment(
    job: &InversionJob,
    g: &Generator,
    ctx: &BodyContext,
    start: StartCandidate,
    dev: &Device,
) -> Result<GarmentOutcome, String> {
    let none = (String::new(), (0, 0));
    let bytes = match &job.encoder {
        Some(bytes) if job.options.garments && job.start == StartChoice::Encoder && start.name == ENCODER_GUESS => {
            bytes
        }
        _ => return Ok((start, None, Ok(none))),
    };
    let codes = match parse_safetensors_async(bytes).await {
        Ok(st) => GarmentCodes::from_safetensors(&st),
        Err(e) => return Ok((start, None, Err(format!("the garment codes cannot be read ({e})")))),
    };
    let Some(codes) = codes else { return Ok((start, None, Ok(none))) };
    if let Err(e) = codes.check(g) {
        return Ok((start, None, Err(format!("the garment codes cannot be used ({e})"))));
    }
    let choice =
        choose_garment_async(g, ctx, &job.target, &start.styles, None, &codes, dev).await.map_err(|e| e.to_string())?;
    let counts = (codes.len(), choice.candidates.len() - 1);
    Ok(match choice.chosen {
        Some(name) => (StartCandidate { styles: choice.styles, ..start }, Some(choice.rigged), Ok((name, counts))),
        None => (start, Some(choice.rigged), Ok((String::new(), counts))),
    })
}

/// The photo projected onto `rigged` (posed as the photo shows it); the viewport's vertex
/// colours show what the download's texture will. In slices of the UI thread: the body
/// posed once, as the photo shows it; the avatar re-posed; its depth at the photo's camera;
/// the photo's mask and linear colours; the blend (itself sliced: the samples, then each of
/// the colour shift's grids); the bind pose at the photo's shape.
async fn project(rigged: &mut RiggedAvatar, ctx: &BodyContext, photo: SourcePhoto) -> Rc<Projected> {
    yield_to_browser().await;
    let body = pose_body(&ctx.model, &photo.view.body);
    yield_to_browser().await;
    let (posed, normals) = rigged.repose(ctx, &body);
    yield_to_browser().await;
    let projection = photo.projection_async(&posed, &rigged.canonical.mesh.faces).await;
    yield_to_browser().await;
    projection.blend_async(&rigged.canonical.mesh.vertices, &posed, &normals, &mut rigged.canonical.colors).await;
    // The bind pose at the photo's shape (the fit gave the app that shape), for the viewer's
    // upload, which would otherwise compute it inside a frame.
    yield_to_browser().await;
    rigged.keep_bind_pose_async(ctx, &photo.view.body.betas).await;
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
            let mut r = rig_saved(bytes, None, &name, &cfg, &ctx, &device).await?;
            r.opened = Some(name);
            r.millis = now_ms() - t0;
            Ok::<_, String>(r)
        };
        let event = match opened.await {
            Ok(r) => ReconstructEvent::Finished(Box::new(r)),
            Err(e) => ReconstructEvent::Failed(format!("cannot open the reconstruction: {e}")),
        };
        t.push(event, &repaint);
    });
    task
}

/// A reconstruction's file (`name`: where it came from, for messages) as the app's avatar:
/// its generator and codes on `device`, extracted and rigged (or `rigged`, the avatar the
/// reconstruction worker made from the same file), its photo projected on.
pub(crate) async fn rig_saved(
    bytes: Vec<u8>,
    rigged: Option<RiggedArrays>,
    name: &str,
    cfg: &GeneratorConfig,
    ctx: &BodyContext,
    device: &Device,
) -> Result<Reconstructed, String> {
    // Parsing (a copy of every weight) runs in slices, building the generator in one (its
    // milliseconds go into the finish detail, which the browser e2e prints). With the worker's
    // avatar the generator is built when first used (the texture view, the bake), not here.
    let not_one = |e| format!("{name} is not a reconstruction of this model: {e}");
    let bytes = Rc::new(bytes);
    let mut st = parse_safetensors_async(&bytes).await.map_err(not_one)?;
    yield_to_browser().await;
    let t = crate::platform::now_ms();
    let (mut rigged, model, photo) = match rigged {
        Some(a) => {
            // The photo's pixels are moved out of the parsed file (the generator does not
            // need them), then checked; the avatar's arrays in a task of their own.
            let photo = take_inverted_photo(&mut st).map_err(not_one)?;
            yield_to_browser().await;
            let rigged = RiggedAvatar::from_arrays(a, ctx).map_err(|e| format!("{name}: the worker's avatar: {e}"))?;
            let st = Rc::new(st);
            (rigged, FieldModel::File { st, bytes: bytes.clone(), cfg: cfg.clone(), device: device.clone() }, photo)
        }
        None => {
            let inv = inverted_of(st, cfg, device).map_err(not_one)?;
            yield_to_browser().await;
            let rigged =
                generate_rigged_async(&inv.generator, ctx, &inv.styles, device).await.map_err(|e| e.to_string())?;
            (rigged, FieldModel::Built(Rc::new(inv.generator), inv.styles), inv.photo)
        }
    };
    let detail = match &model {
        FieldModel::File { .. } => "its generator is built when first used".to_string(),
        FieldModel::Built(..) => format!("building and extracting it {:.0} ms", crate::platform::now_ms() - t),
    };
    if rigged.canonical.mesh.faces.is_empty() {
        return Err(format!("{name}: the reconstruction's generator produced an empty surface"));
    }
    let projection = match photo {
        Some(p) => Some(project(&mut rigged, ctx, p).await),
        None => None,
    };
    Ok(Reconstructed {
        model,
        file: Some(bytes),
        rigged,
        projection,
        refit: None,
        fit: None,
        opened: None,
        millis: 0.0,
        finish_ms: 0.0,
        finish_detail: detail,
        stopped_at: None,
        measuring: false,
    })
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
