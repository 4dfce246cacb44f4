//! "Reconstruct avatar": after the photo's body fit, the avatar is reconstructed from the
//! photo (`crate::reconstruct`) with a quality preset. The photo encoder's guess comes first
//! (`instant`: one forward pass and one generation) and is shown as the avatar; `fast` and
//! `full` then refine it from that guess with a progress bar (phase, step, loss, ETA) and a
//! live preview (photo | current render | overlay, at the inversion's camera). Cancel keeps
//! the last preview's state as the avatar (before any step: the avatar as it was). The result
//! replaces the shown avatar: the pose and camera controls, motion playback and the downloads
//! work on it right away.

use std::rc::Rc;

use eframe::egui;

use getavatar_core::body::body_fit::fit::BodyFit;
use getavatar_core::body::body_fit::refit::RefitOptions;
use getavatar_core::reconstruction::inversion::{comparison_image, InversionOptions, InversionTarget, Phase};

use super::GetAvatarApp;
use crate::automation::{Action, ReconstructArgs, ReconstructStatus, Reconstruction, StartChoice, RECONSTRUCT_PRESETS};
use crate::photo::{self, PhotoEvent, PhotoTask, RefitRequest};
use crate::platform::{download_bytes, open_file_picker, RECONSTRUCTION_INPUT_ID};
use crate::reconstruct::{
    open, reconstruct, save, InversionJob, Measured, Preview, ProjectionSource, ReconstructEvent, ReconstructRequest,
    ReconstructTask, Reconstructed,
};
use crate::status::StageStart;
use crate::texture_field::TextureField;

/// Side of the photo crop that the colour projection samples, pixels.
const PROJECTION_RES: usize = 512;

/// The reconstruction's state in the app.
pub(super) struct ReconstructPanel {
    task: Option<ReconstructTask>,
    /// What the running (or last) reconstruction explains: the photo at its camera.
    target: Option<InversionTarget>,
    /// Photo | render | overlay of the latest preview.
    preview: Option<egui::TextureHandle>,
    /// The quality preset the button uses.
    preset: String,
    /// W+ steps done and their milliseconds (the phases' step times).
    latent: (usize, f64),
    /// The refinement to run once the encoder's guess is shown (None: none follows).
    refine: Option<Reconstruction>,
    /// When "Reconstruct" was pressed (ms, the page's clock), for the time to the first avatar.
    t_click: f64,
    /// The result being measured after it was shown is the first avatar (else a later stage's).
    measuring_first: bool,
    /// The body's refit on the guess's outline, running on the page, and the stage that
    /// follows it.
    refit: Option<PhotoTask>,
    after_refit: Option<Reconstruction>,
    /// The stage after a finished page refit, started on the next frame (the frame that
    /// installs the refitted body re-poses the avatar, tens of milliseconds on the UI thread).
    pending: Option<Reconstruction>,
    /// The body was refitted on the page: the stage that follows does not refit.
    refitted_on_page: bool,
}

impl Default for ReconstructPanel {
    fn default() -> Self {
        Self {
            task: None,
            target: None,
            preview: None,
            preset: "fast".into(),
            latent: (0, 0.0),
            refine: None,
            t_click: 0.0,
            measuring_first: true,
            refit: None,
            after_refit: None,
            pending: None,
            refitted_on_page: false,
        }
    }
}

impl ReconstructPanel {
    pub(super) fn running(&self) -> bool {
        self.task.is_some() || self.refit.is_some() || self.pending.is_some()
    }

    /// Stop the running reconstruction (it reports its cancellation); no refinement follows.
    pub(super) fn cancel(&mut self) -> bool {
        self.refine = None;
        self.after_refit = None;
        self.pending = None;
        if let Some(t) = &self.refit {
            t.cancel();
            return true;
        }
        match &self.task {
            Some(t) => {
                t.cancel();
                true
            }
            None => false,
        }
    }
}

impl GetAvatarApp {
    pub(super) fn apply_reconstruct(&mut self, action: Action) {
        match action {
            Action::Reconstruct(r) => self.start_reconstruct(r),
            // Between the page's refit and the stage after it: nothing runs to report it.
            Action::ReconstructCancel if self.recon.pending.is_some() => {
                self.recon.cancel();
                self.cancelled_at_the_guess();
            }
            Action::ReconstructCancel if !self.recon.cancel() => {
                self.messages.push("no reconstruction is running".into());
            }
            Action::SaveReconstruction => self.save_reconstruction(),
            Action::OpenReconstruction(source) => self.open_reconstruction(source),
            _ => {}
        }
    }

    /// Download the shown reconstruction as one file (the tuned generator, its codes and the
    /// photo): `trainer export --inverted` and "Open reconstruction…" take it.
    fn save_reconstruction(&mut self) {
        if self.recon.running() {
            self.messages.push("a reconstruction is running: wait for it or cancel it first".into());
            return;
        }
        let Some(field) = self.field.clone().filter(|f| f.is_reconstruction()) else {
            self.messages.push("the shown avatar is not a reconstruction: reconstruct one from a photo first".into());
            return;
        };
        let Some(engine) = self.engine.as_ref() else {
            self.messages.push("the generator is not available (no WebGPU device for burn)".into());
            return;
        };
        let cfg = match engine.model_files() {
            Ok(f) => f.cfg,
            Err(e) => {
                self.messages.push(format!("cannot save yet: {e}"));
                return;
            }
        };
        self.status.reconstruct.message = "saving the reconstruction…".into();
        self.recon.task = Some(save(field, cfg, self.ctx.clone()));
    }

    /// Open a saved reconstruction as the shown avatar (the previous one stays if it fails).
    fn open_reconstruction(&mut self, source: crate::automation::PhotoSource) {
        if self.recon.running() {
            self.messages.push("a reconstruction is running: wait for it or cancel it first".into());
            return;
        }
        let Some(engine) = self.engine.as_mut() else {
            self.fail_reconstruct("the generator is not available (no WebGPU device for burn)".into());
            return;
        };
        let cfg = match engine.model_files() {
            Ok(f) => f.cfg,
            Err(e) => {
                self.fail_reconstruct(format!("cannot open a reconstruction yet: {e}"));
                return;
            }
        };
        let ctx = match engine.body_context() {
            Ok(c) => c,
            Err(e) => {
                self.fail_reconstruct(format!("cannot open a reconstruction yet: {e}"));
                return;
            }
        };
        let device = engine.device().clone();
        let s = &mut self.status.reconstruct;
        s.state = "opening".into();
        s.message = "opening the reconstruction…".into();
        self.recon.task = Some(open(source, cfg, ctx, device, self.ctx.clone()));
    }

    fn fail_reconstruct(&mut self, message: String) {
        self.recon.refine = None;
        self.recon.after_refit = None;
        self.recon.pending = None;
        let s = &mut self.status.reconstruct;
        s.state = "failed".into();
        s.message = message.clone();
        self.messages.push(message);
    }

    fn start_reconstruct(&mut self, r: Reconstruction) {
        if self.recon.running() {
            self.messages.push("a reconstruction is running: cancel it first".into());
            return;
        }
        self.recon.t_click = crate::platform::now_ms();
        self.recon.refitted_on_page = false;
        // The quality buttons show the preset that runs (an automation command names its own).
        self.recon.preset = r.preset.clone();
        self.start_stage(r, true);
    }

    /// Start one stage: with the encoder's start and steps to run, the `first` stage is the
    /// guess alone (shown as the avatar) and the refinement follows from the same guess.
    fn start_stage(&mut self, r: Reconstruction, first: bool) {
        let Some((p, fit)) = self.photo.fitted() else {
            self.fail_reconstruct("open a photo and let the body fit finish first".into());
            return;
        };
        let Some(mask) = p.result.segmentation_mask.clone() else {
            self.fail_reconstruct("the detector found no person mask in this photo: a reconstruction needs one".into());
            return;
        };
        let (Some(engine), Some(body)) = (self.engine.as_mut(), self.body.as_ref()) else {
            self.fail_reconstruct("the generator is not available (no WebGPU device for burn)".into());
            return;
        };
        let files = match engine.model_files() {
            Ok(f) => f,
            Err(e) => {
                self.fail_reconstruct(format!("cannot reconstruct yet: {e}"));
                return;
            }
        };
        let ctx = match engine.body_context() {
            Ok(c) => c,
            Err(e) => {
                self.fail_reconstruct(format!("cannot reconstruct yet: {e}"));
                return;
            }
        };
        let device = engine.device().clone();
        // The photo as the app holds it (downscaled to at most 768 pixels), which covers the
        // photo the fit was made on.
        let [w, h] = p.preview.size;
        let rgb: Vec<f32> =
            p.preview.pixels.iter().flat_map(|c| [c.r(), c.g(), c.b()]).map(|v| v as f32 / 255.0).collect();
        let crop = |res| InversionTarget::from_photo(fit, &rgb, w, h, &mask, res, body.num_betas);
        let target = match crop(r.res) {
            Ok(t) => t,
            Err(e) => {
                self.fail_reconstruct(format!("the photo cannot be reconstructed: {e}"));
                return;
            }
        };
        // The projection's crop is made when the finish needs it (a 512² resample).
        let projection = r.projection.then(|| ProjectionSource {
            fit: fit.clone(),
            rgb,
            width: w,
            height: h,
            mask,
            res: PROJECTION_RES,
            num_betas: body.num_betas,
        });
        let Some(mut options) = InversionOptions::preset(&r.preset) else {
            self.fail_reconstruct(format!("unknown quality preset `{}` (instant, fast, full)", r.preset));
            return;
        };
        if let Some(n) = r.steps {
            options.steps = n;
        }
        if let Some(n) = r.pti_steps {
            options.pti_steps = n;
        }
        if !first && self.recon.refitted_on_page {
            options.refit_steps = 0;
        }
        // The encoder's guess first, as an avatar of its own (unmeasured, on the body as
        // first fitted), then the stage that refits the body on the guess's outline and
        // refines from it. (Without an encoder the start is the search: one stage.)
        let refits = options.refit_steps > 0 && projection.is_some();
        let guess_first = first
            && r.start == StartChoice::Encoder
            && files.encoder.is_ok()
            && (refits || options.steps + options.pti_steps > 0);
        self.recon.refine = guess_first.then(|| r.clone());
        if guess_first {
            // Shown at once: the garment codes are weighed by the stage after it.
            (options.steps, options.pti_steps, options.refit_steps, options.garments) = (0, 0, 0, false);
        }
        let mut note = String::new();
        let discriminator = match (r.perceptual, files.discriminator) {
            (true, Ok(d)) => Some(d),
            (true, Err(why)) => {
                note = format!(" (perceptual term off: {why})");
                None
            }
            (false, _) => None,
        };
        if discriminator.is_none() {
            options.perceptual = 0.0;
        }
        let s = &mut self.status.reconstruct;
        // The encoder's start without a usable encoder file is the search, and says why.
        let why = files.encoder.as_ref().err().map_or("", String::as_str);
        let (start, start_note) = r.start.or_search(files.encoder.as_ref().map(|_| ()).map_err(String::as_str));
        let opening = start.opening(if start_note.is_empty() { "" } else { why });
        let refines = options.steps + options.pti_steps > 0;
        let (garments, note) = (options.garments, &note);
        let message = s.stage_message(&StageStart { first, refits, garments, refines, opening: &opening, note });
        let steps_total = options.steps + options.pti_steps;
        *s = if first {
            ReconstructStatus {
                state: "starting".into(),
                message,
                preset: r.preset.clone(),
                steps_total,
                res: r.res,
                done: s.done,
                opened: s.opened,
                saved: s.saved,
                saved_bytes: s.saved_bytes,
                has_photo: s.has_photo,
                ..ReconstructStatus::default()
            }
        } else {
            // The refinement keeps the first avatar's figures.
            ReconstructStatus { state: "starting".into(), message, steps_total, steps_done: 0, ..s.clone() }
        };
        let job = InversionJob {
            checkpoint: files.checkpoint,
            discriminator,
            cfg: files.cfg,
            target: target.clone(),
            projection,
            options,
            preview_every: r.preview_every,
            start,
            start_note,
            encoder: files.encoder.ok(),
            compute: r.compute,
            // The guess alone (`instant`): on screen before its figures.
            measure_after_result: self.recon.refine.is_none() && steps_total == 0,
            figures: !guess_first,
        };
        let req = ReconstructRequest { job, ctx, device };
        self.recon.target = Some(target);
        self.recon.preview = None;
        self.recon.latent = (0, 0.0);
        self.recon.task = Some(reconstruct(req, self.ctx.clone()));
    }

    /// Drain the reconstruction's events; install its result.
    pub(super) fn poll_reconstruct(&mut self, ctx: &egui::Context) {
        self.poll_refit(ctx);
        let Some(task) = self.recon.task.clone() else { return };
        for event in task.drain() {
            match event {
                ReconstructEvent::Started {
                    start,
                    candidates,
                    perceptual,
                    millis,
                    in_worker,
                    device,
                    note,
                    garment,
                    garment_codes,
                } => {
                    let s = &mut self.status.reconstruct;
                    let of = if candidates > 1 { format!(" (best of {candidates})") } else { String::new() };
                    let raw_note = note.clone();
                    let note = if note.is_empty() { String::new() } else { format!(" — {note}") };
                    let with = match (garment.as_str(), garment_codes.codes, garment_codes.weighed) {
                        (_, 0, _) => String::new(),
                        (_, _, 0) => " (its outline fits the person: no garment code weighed)".to_string(),
                        ("", _, n) => format!(" (its outline kept against {n} garment codes)"),
                        (code, _, n) => format!(" with the outline of garment code `{code}` (the best of {n})"),
                    };
                    s.message = format!(
                        "starting from {start}{with}{of}; perceptual term {}; {} on {device}{note}",
                        if perceptual { "on" } else { "off" },
                        if in_worker { "in a worker" } else { "on the page" }
                    );
                    (s.start, s.candidates, s.perceptual) = (start, candidates, perceptual);
                    s.start_note = raw_note;
                    (s.garment, s.garment_codes, s.garments_weighed) =
                        (garment, garment_codes.codes, garment_codes.weighed);
                    s.garment_guess_reused = garment_codes.guess_reused;
                    s.start_ms = millis as f32;
                    s.runs_in = if in_worker { "worker" } else { "page" }.into();
                    s.device = device;
                    s.state = "latent".into();
                }
                ReconstructEvent::Step(p) => {
                    let s = &mut self.status.reconstruct;
                    s.losses.push(p.report.terms.total);
                    s.step_mask_iou = p.report.terms.mask_iou;
                    s.restarts += usize::from(p.report.restarted);
                    (s.steps_done, s.steps_total) = (p.done, p.total);
                    s.ms_per_step = (p.elapsed_ms / p.done.max(1) as f64) as f32;
                    if p.report.phase == Phase::Latent {
                        self.recon.latent = (p.done, p.elapsed_ms);
                        s.ms_per_latent_step = s.ms_per_step;
                    } else {
                        let (n, ms) = self.recon.latent;
                        s.ms_per_pivotal_step = ((p.elapsed_ms - ms) / (p.done - n).max(1) as f64) as f32;
                    }
                    s.eta_s = s.ms_per_step * (p.total - p.done.min(p.total)) as f32 / 1000.0;
                    s.state = match p.report.phase {
                        Phase::Latent => "latent",
                        Phase::Pivotal => "pivotal",
                        Phase::Done => "finishing",
                    }
                    .into();
                    if p.done >= p.total {
                        s.state = "finishing".into();
                        s.message = "extracting, rigging and colouring the avatar…".into();
                    }
                }
                ReconstructEvent::Preview(pv) => self.show_preview(ctx, &pv),
                ReconstructEvent::Finished(r) => self.reconstructed(*r),
                ReconstructEvent::Measured(m) => self.measured(ctx, *m),
                ReconstructEvent::Saved(bytes) => {
                    let name = format!("getavatar_{}.safetensors", self.avatar_name);
                    match download_bytes(&name, &bytes, "application/octet-stream") {
                        Ok(()) => {
                            let s = &mut self.status.reconstruct;
                            (s.saved, s.saved_bytes) = (s.saved + 1, bytes.len());
                            s.message = format!("saved {name} ({:.1} MB)", bytes.len() as f64 / 1e6);
                        }
                        Err(e) => self.messages.push(format!("download failed: {e}")),
                    }
                }
                ReconstructEvent::Failed(e) => self.fail_reconstruct(e),
                ReconstructEvent::Cancelled => {
                    let s = &mut self.status.reconstruct;
                    s.state = "cancelled".into();
                    s.message = if s.first_avatar_ms > 0.0 {
                        "cancelled before the first step: the avatar is the encoder's guess".into()
                    } else {
                        "cancelled: the avatar is as it was".into()
                    };
                }
            }
        }
        if task.finished() && self.recon.task.as_ref().is_some_and(|t| t.same(&task)) {
            self.recon.task = None;
        }
    }

    /// A finished stage: its avatar becomes the app's, the status says what it was, and the
    /// refinement that waits for the guess (if any) starts.
    fn reconstructed(&mut self, r: Reconstructed) {
        let refine = self.recon.refine.take();
        self.use_refined_fit(r.refit.as_ref());
        self.status.avatar_vertices = r.rigged.canonical.mesh.vertices.len();
        self.rigged = Some(r.rigged);
        let has_photo = r.projection.is_some();
        self.field = Some(Rc::new(TextureField::reconstructed(r.model, r.projection, r.file)));
        // The bake belongs to the previous avatar.
        self.baked = None;
        self.show_avatar = true;
        self.mesh_dirty = true;
        self.avatar_dirty = true;
        self.avatar_name = "reconstruction".into();
        let s = &mut self.status.reconstruct;
        s.state = "done".into();
        s.has_photo = has_photo;
        s.eta_s = 0.0;
        match (&r.opened, r.fit) {
            (Some(name), _) => {
                s.opened += 1;
                s.message = format!(
                    "opened {name} in {:.0} s{}",
                    r.millis / 1000.0,
                    if has_photo { ", with its photo projected on" } else { " (it keeps no photo)" }
                );
            }
            (None, _) if r.measuring => {
                let since_click = (crate::platform::now_ms() - self.recon.t_click) as f32;
                self.recon.measuring_first = s.first_avatar_ms == 0.0;
                if self.recon.measuring_first {
                    s.first_avatar_ms = since_click;
                }
                s.state = "measuring".into();
                (s.finish_ms, s.finish_detail) = (r.finish_ms as f32, r.finish_detail.clone());
                let what =
                    if self.recon.measuring_first { s.first_avatar_name() } else { "on the refitted body".into() };
                s.message = format!("{what} in {:.1} s; measuring it at the photo's camera…", since_click / 1000.0);
            }
            (None, fit) => {
                let (iou, psnr) = fit.unwrap_or((f32::NAN, f32::NAN));
                let since_click = (crate::platform::now_ms() - self.recon.t_click) as f32;
                if s.first_avatar_ms == 0.0 {
                    (s.first_avatar_ms, s.first_mask_iou, s.first_psnr_db) = (since_click, iou, psnr);
                }
                (s.mask_iou, s.psnr_db, s.total_ms) = (iou, psnr, since_click);
                s.finish_ms = r.finish_ms as f32;
                s.finish_detail = r.finish_detail.clone();
                let figures = format!("mask IoU {iou:.2}, masked PSNR {psnr:.1} dB at the photo's camera");
                match (r.stopped_at, &refine) {
                    (Some(k), _) => {
                        s.state = "cancelled".into();
                        s.stopped_at = k;
                        s.message = format!(
                            "cancelled after {k} of {} steps: the avatar is the last preview ({figures})",
                            s.steps_total
                        );
                    }
                    (None, Some(_)) => {
                        s.state = "starting".into();
                        let figures = if iou.is_finite() { format!(" ({figures})") } else { String::new() };
                        s.message = format!(
                            "the encoder's guess in {:.1} s{figures}; refining it (the body first)…",
                            since_click / 1000.0
                        );
                    }
                    (None, None) => {
                        s.done += 1;
                        let done = format!("reconstructed in {:.0} s: {figures} (last step)", since_click / 1000.0);
                        s.message = s.with_start_note(done);
                    }
                }
            }
        }
        if let Some(next) = refine {
            if r.stopped_at.is_none() && r.opened.is_none() {
                self.after_guess(next);
            }
        }
    }

    /// The guess is on screen: refit the body on its outline here on the page (the guess is
    /// rigged here already), then run `next`; or run `next` at once, which refits in the
    /// worker where the page cannot.
    fn after_guess(&mut self, next: Reconstruction) {
        match self.page_refit(&next) {
            Ok(Some(task)) => {
                self.recon.refit = Some(task);
                self.recon.after_refit = Some(next);
                let s = &mut self.status.reconstruct;
                s.state = "refitting".into();
                s.message = format!(
                    "the encoder's guess in {:.1} s; fitting the body to its outline…",
                    s.first_avatar_ms / 1000.0
                );
            }
            Ok(None) => self.start_stage(next, false),
            Err(why) => {
                self.messages.push(format!("the body's refit cannot run on the page ({why}): the worker refits it"));
                self.start_stage(next, false);
            }
        }
    }

    /// The refit of the photo's body on the shown guess's outline, when `next` refits and
    /// keeps the guess's outline. A stage that weighs the garment codes (`instant`) refits in
    /// the worker instead: the codes are weighed on the body as first fitted and the body is
    /// refitted on the chosen outline, the order `trainer invert` measures.
    fn page_refit(&self, next: &Reconstruction) -> Result<Option<PhotoTask>, String> {
        let Some(options) = InversionOptions::preset(&next.preset) else { return Ok(None) };
        if options.refit_steps == 0 || !next.projection || options.garments {
            return Ok(None);
        }
        let (Some(rigged), Some(target), Some(model), Some((p, fit))) =
            (&self.rigged, &self.recon.target, &self.body, self.photo.fitted())
        else {
            return Ok(None);
        };
        let ctx = self.engine.as_ref().ok_or("no generator")?.body_context()?;
        let req = RefitRequest {
            model: model.clone(),
            fit: fit.clone(),
            mask: target.mask.clone(),
            size: target.res,
            rigged: rigged.clone(),
            ctx,
            options: RefitOptions { steps: options.refit_steps, ..RefitOptions::default() },
            device: photo::fit_device(),
            result: p.result.clone(),
            preview: p.preview.size,
        };
        Ok(Some(photo::refit(req, self.ctx.clone())))
    }

    fn cancelled_at_the_guess(&mut self) {
        let s = &mut self.status.reconstruct;
        s.state = "cancelled".into();
        s.message = "cancelled before the first step: the avatar is the encoder's guess".into();
    }

    /// Drain the page's refit: its progress, then the refitted body (the stage after it
    /// starts on the next frame).
    fn poll_refit(&mut self, ctx: &egui::Context) {
        if let Some(next) = self.recon.pending.take() {
            self.start_stage(next, false);
        }
        let Some(task) = self.recon.refit.clone() else { return };
        for event in task.drain() {
            match event {
                PhotoEvent::Progress(p) => {
                    let s = &mut self.status.reconstruct;
                    s.message = format!(
                        "the encoder's guess in {:.1} s; fitting the body to its outline ({} of {} steps)…",
                        s.first_avatar_ms / 1000.0,
                        p.done,
                        p.total
                    );
                }
                PhotoEvent::Refitted(view) => {
                    let Some(next) = self.recon.after_refit.take() else { continue };
                    let since_click = (crate::platform::now_ms() - self.recon.t_click) as f32;
                    let millis = view.millis as f32;
                    let fit = view.fit.clone();
                    let before = self.install_refitted_fit(*view, ctx);
                    self.refined_fit_applied(&fit, before.as_ref());
                    let s = &mut self.status.reconstruct;
                    (s.refit_on, s.refit_ms, s.refitted_avatar_ms) = ("page".into(), millis, since_click);
                    self.recon.refitted_on_page = true;
                    self.recon.pending = Some(next);
                }
                PhotoEvent::Failed(why) => {
                    // The worker can still refit it: the stage runs with its own refit.
                    self.messages.push(format!("{why}: the worker refits it"));
                    if let Some(next) = self.recon.after_refit.take() {
                        self.start_stage(next, false);
                    }
                }
                PhotoEvent::Cancelled => self.cancelled_at_the_guess(),
                PhotoEvent::Detected(_) | PhotoEvent::Fitted(_) | PhotoEvent::Overlay(_) => {}
            }
        }
        if task.finished() && self.recon.refit.as_ref().is_some_and(|t| t.same(&task)) {
            self.recon.refit = None;
        }
    }

    /// The photo's body fit refined on the guess's outline (in the worker) becomes the app's:
    /// the body, the photo's fit (a refinement that follows starts from it) and the status.
    fn use_refined_fit(&mut self, fit: Option<&BodyFit>) {
        let Some(fit) = fit else { return };
        let before = self.replace_photo_fit(fit.clone());
        self.refined_fit_applied(fit, before.as_ref());
        let s = &mut self.status.reconstruct;
        s.refit_on = "worker".into();
        s.refitted_avatar_ms = (crate::platform::now_ms() - self.recon.t_click) as f32;
    }

    /// The body and the status follow a refined fit that replaced `before`.
    fn refined_fit_applied(&mut self, fit: &BodyFit, before: Option<&BodyFit>) {
        let b1 = |f: &BodyFit| f.betas.get(1).copied().unwrap_or(0.0);
        self.status.reconstruct.refit_beta1 = [before.map_or(f32::NAN, b1), b1(fit)];
        self.params = fit.body_params();
        self.mesh_dirty = true;
        self.render_dirty = true;
    }

    /// A render at the photo's camera beside the photo, in the panel.
    fn show_preview(&mut self, ctx: &egui::Context, pv: &Preview) {
        let Some(t) = &self.recon.target else { return };
        let bytes = comparison_image(t, &pv.rgb, &pv.mask);
        let img = egui::ColorImage::from_rgb([3 * t.res, t.res], &bytes);
        self.recon.preview = Some(ctx.load_texture("reconstruction preview", img, egui::TextureOptions::LINEAR));
        self.status.reconstruct.previews += 1;
        self.status.reconstruct.preview_step = pv.done;
    }

    /// The figures of an avatar shown before it was measured (`instant` in the worker).
    fn measured(&mut self, ctx: &egui::Context, m: Measured) {
        let s = &mut self.status.reconstruct;
        (s.state, s.done) = ("done".into(), s.done + 1);
        s.total_ms = (crate::platform::now_ms() - self.recon.t_click) as f32;
        s.finish_ms += m.millis as f32;
        s.finish_detail = format!("{}; worker, after it: figures {:.1} s", s.finish_detail, m.millis / 1000.0);
        let first = s.first_avatar_ms / 1000.0;
        // The guess shown first, or (after it) the guess on the body refitted to its outline.
        let name = s.first_avatar_name();
        let what = match self.recon.measuring_first {
            true => format!("{name} in {first:.1} s"),
            false => format!("{name} in {first:.1} s, then on the body refitted to its outline"),
        };
        match m.figures {
            Ok(((iou, psnr), preview)) => {
                (s.mask_iou, s.psnr_db) = (iou, psnr);
                if self.recon.measuring_first {
                    (s.first_mask_iou, s.first_psnr_db) = (iou, psnr);
                }
                s.message = s.with_start_note(format!(
                    "{what}: mask IoU {iou:.2}, masked PSNR {psnr:.1} dB at the photo's camera"
                ));
                self.show_preview(ctx, &preview);
            }
            Err(why) => s.message = s.with_start_note(format!("{what} ({why})")),
        }
    }

    /// The reconstruction's part of the photo section (once the body is fitted).
    pub(super) fn reconstruct_section(&mut self, ui: &mut egui::Ui) {
        ui.separator();
        ui.strong("Reconstruct avatar");
        let ready = self.photo.fitted().is_some() && !self.photo.busy();
        ui.horizontal(|ui| {
            ui.label("quality");
            for p in RECONSTRUCT_PRESETS {
                ui.radio_value(&mut self.recon.preset, p.to_string(), p);
            }
        });
        ui.horizontal(|ui| {
            let running = self.recon.running();
            let go = ui.add_enabled(ready && !running, egui::Button::new("Reconstruct")).on_hover_text(
                "instant: the photo encoder's guess (seconds); fast: the guess, then 60 + 60 refining steps; \
                     full: then 200 latent + 350 tuning steps (the references' counts)",
            );
            if go.clicked() {
                let args = ReconstructArgs { preset: Some(self.recon.preset.clone()), ..Default::default() };
                match args.validate() {
                    Ok(r) => self.apply(Action::Reconstruct(r)),
                    Err(e) => self.messages.push(e),
                }
            }
            if running {
                super::busy_indicator(ui);
                if ui.button("Cancel").on_hover_text("stop; the avatar is the last preview").clicked() {
                    self.apply(Action::ReconstructCancel);
                }
            }
        });
        let s = &self.status.reconstruct;
        if self.recon.running() && s.steps_total > 0 {
            let phase = if s.state == "pivotal" { "tuning" } else { "latent" };
            let loss = s.losses.last().copied().unwrap_or(f32::NAN);
            let text = if s.steps_done == 0 {
                "choosing the start…".to_string()
            } else {
                let restarts = match s.restarts {
                    0 => String::new(),
                    n => format!(" · restarted {n}× at half the rate"),
                };
                format!(
                    "{phase} · step {}/{} · loss {loss:.3}{restarts} · ETA {}",
                    s.steps_done,
                    s.steps_total,
                    eta(s.eta_s)
                )
            };
            ui.add(egui::ProgressBar::new(s.steps_done as f32 / s.steps_total as f32).text(text));
        }
        if !s.message.is_empty() {
            ui.label(egui::RichText::new(&s.message).small());
        }
        if let Some(t) = &self.recon.preview {
            let w = ui.available_width().min(3.0 * 128.0);
            ui.image((t.id(), egui::vec2(w, w / 3.0)));
            ui.label(egui::RichText::new("photo · render · overlay").small());
        }
    }
}

impl GetAvatarApp {
    /// "Open reconstruction…" and "Save reconstruction" (the reconstruction's own file); with
    /// `show_message`, the reconstruction's message too (the photo section shows it otherwise).
    pub(super) fn reconstruction_files(&mut self, ui: &mut egui::Ui, show_message: bool) {
        let idle = !self.recon.running();
        let saveable = idle && self.field.as_ref().is_some_and(|f| f.is_reconstruction());
        ui.horizontal(|ui| {
            let open = ui
                .add_enabled(idle, egui::Button::new("Open reconstruction…"))
                .on_hover_text("a saved reconstruction (.safetensors, also `trainer invert`'s inverted.safetensors)");
            if open.clicked() {
                if let Err(e) = open_file_picker(RECONSTRUCTION_INPUT_ID) {
                    self.messages.push(format!("cannot open the file chooser: {e}"));
                }
            }
            if ui
                .add_enabled(saveable, egui::Button::new("⬇ Save reconstruction"))
                .on_hover_text(
                    "the tuned generator, its codes and the photo: reopen it here, or `trainer export --inverted`",
                )
                .clicked()
            {
                self.apply(Action::SaveReconstruction);
            }
        });
        let s = &self.status.reconstruct;
        if show_message && !s.message.is_empty() {
            ui.label(egui::RichText::new(&s.message).small());
        }
    }
}

/// Seconds as "1 min 20 s" / "12 s".
fn eta(s: f32) -> String {
    let s = s.max(0.0).round() as u64;
    if s >= 60 {
        format!("{} min {:02} s", s / 60, s % 60)
    } else {
        format!("{s} s")
    }
}
