//! "Reconstruct from photo": open or drop a photo, MediaPipe finds the person, the body is
//! fitted to it (progress, Cancel). The photo is shown with the detected keypoints, the
//! person mask and the fitted body drawn over it through the fit's own camera; the fit
//! becomes the app's pose and shape, so the pose controls can correct any joint and "Re-fit
//! from this pose" starts the fit again from there. "Download fit" writes `fit.json` and
//! `kp.json`, the files of `trainer fit-pose`.

use std::cell::RefCell;
use std::rc::Rc;

use eframe::egui;
use egui::{Color32, Pos2, Rect, Stroke};

use getavatar_core::body::body_fit::correction::LIMBS;
use getavatar_core::body::body_fit::fit::{BodyFit, FitOptions, STAGE_NAMES};
use getavatar_core::body::body_fit::landmarks::{PoseResult, JOINT_LANDMARKS, VISIBLE};
use getavatar_core::body::body_model::JOINT_NAMES;

use super::GetAvatarApp;
use crate::automation::{Action, PhotoFitAction, PhotoSource};
use crate::photo::{self, resampled, tinted, FitRequest, FittedView, Photo, PhotoEvent, PhotoTask};
use crate::platform::download_bytes;

/// MediaPipe Pose's skeleton as drawn over the photo (landmark index pairs).
const CONNECTIONS: [(usize, usize); 20] = [
    (11, 12),
    (11, 23),
    (12, 24),
    (23, 24),
    (11, 13),
    (13, 15),
    (12, 14),
    (14, 16),
    (23, 25),
    (25, 27),
    (27, 29),
    (29, 31),
    (27, 31),
    (24, 26),
    (26, 28),
    (28, 30),
    (30, 32),
    (28, 32),
    (0, 11),
    (0, 12),
];

const PERSON_TINT: [u8; 3] = [70, 150, 255];

#[derive(Clone, Copy, PartialEq, Eq)]
enum TaskKind {
    Detect,
    Fit,
}

/// A dropped file once read: its name and bytes, or why it could not be read.
type DroppedFile = Result<(String, Vec<u8>), String>;

/// The photo panel's state.
pub(super) struct PhotoPanel {
    task: Option<(TaskKind, PhotoTask)>,
    /// A photo (and the person to read in it) that waits for the running detection.
    queued: Option<(PhotoSource, Option<FitOptions>, bool, Option<usize>)>,
    /// Fit settings asked for with the photo (automation), else the fit's defaults, and
    /// whether to fit on the WebGPU device.
    options: Option<FitOptions>,
    on_gpu: bool,
    photo: Option<Photo>,
    image: Option<egui::TextureHandle>,
    person: Option<egui::TextureHandle>,
    body: Option<egui::TextureHandle>,
    fit: Option<BodyFit>,
    /// A fit whose overlay is shown, applied to the app's pose and shape on the next frame
    /// (with its time in ms): re-binding the avatar to a new shape is a frame's work of its own.
    to_apply: Option<(BodyFit, f64)>,
    /// Dropped files once read (or why they could not be).
    dropped: Rc<RefCell<Vec<DroppedFile>>>,
    pub(super) visible: bool,
    show_mask: bool,
    show_body: bool,
    show_keypoints: bool,
}

impl Default for PhotoPanel {
    fn default() -> Self {
        Self {
            task: None,
            queued: None,
            options: None,
            on_gpu: false,
            photo: None,
            image: None,
            person: None,
            body: None,
            fit: None,
            to_apply: None,
            dropped: Default::default(),
            visible: false,
            show_mask: false,
            show_body: true,
            show_keypoints: true,
        }
    }
}

impl PhotoPanel {
    pub(super) fn has_photo(&self) -> bool {
        self.photo.is_some()
    }

    /// A detection or fit is running.
    pub(super) fn busy(&self) -> bool {
        self.task.is_some()
    }

    /// The detected photo and its body fit, once both exist.
    pub(super) fn fitted(&self) -> Option<(&Photo, &BodyFit)> {
        Some((self.photo.as_ref()?, self.fit.as_ref()?))
    }
}

impl GetAvatarApp {
    /// Apply a photo action (widgets and automation).
    pub(super) fn apply_photo(&mut self, action: Action) {
        match action {
            Action::Photo { source, options, on_gpu } => self.open_photo(source, options, on_gpu, None),
            Action::PhotoFit(PhotoFitAction::Person(k)) => self.choose_person(k),
            Action::PhotoFit(PhotoFitAction::Cancel) => match &self.photo.task {
                Some((_, t)) => t.cancel(),
                None => self.messages.push("no photo fit is running".into()),
            },
            Action::PhotoFit(PhotoFitAction::Refit) => {
                let start = (self.params.clone(), self.photo.fit.clone());
                self.start_fit(Some(start));
            }
            Action::PhotoFit(PhotoFitAction::Download) => self.download_fit(),
            Action::PhotoFit(PhotoFitAction::Close) => {
                if let Some((_, t)) = self.photo.task.take() {
                    t.cancel();
                }
                self.recon.cancel();
                self.photo = PhotoPanel::default();
                self.status.photo = Default::default();
                photo::publish_masks(String::new());
            }
            _ => {}
        }
    }

    /// Fit the `k`-th person by size (1 = the largest) of the shown photo: the finder reads
    /// that person again (turning the photo if it must) and the fit starts over.
    fn choose_person(&mut self, k: usize) {
        let Some(p) = &self.photo.photo else {
            self.messages.push("open a photo first".into());
            return;
        };
        if k == 0 || k > p.persons.len() {
            let n = p.persons.len();
            self.messages.push(format!("there is no person {k} in the photo ({n} seen)"));
            return;
        }
        let source = PhotoSource::Bytes { name: p.name.clone(), bytes: p.bytes.as_ref().clone() };
        let (options, on_gpu) = (self.photo.options.clone(), self.photo.on_gpu);
        self.open_photo(source, options, on_gpu, Some(k - 1));
    }

    fn open_photo(&mut self, source: PhotoSource, options: Option<FitOptions>, on_gpu: bool, person: Option<usize>) {
        match &self.photo.task {
            // One detection at a time (the detector keeps the last photo for its preview).
            Some((TaskKind::Detect, _)) => {
                self.photo.queued = Some((source, options, on_gpu, person));
                return;
            }
            Some((TaskKind::Fit, t)) => t.cancel(),
            None => {}
        }
        let ctx = self.ctx.clone();
        self.status.photo.name = match &source {
            PhotoSource::Url(u) => u.clone(),
            PhotoSource::Bytes { name, .. } => name.clone(),
        };
        self.status.photo.state = "detecting".into();
        self.status.photo.message = "looking for the person…".into();
        self.photo.options = options;
        self.photo.on_gpu = on_gpu;
        self.photo.task = Some((TaskKind::Detect, photo::detect(source, person, ctx)));
    }

    /// Fit the body to the current photo's detection (from `start` for a re-fit).
    fn start_fit(&mut self, start: Option<(getavatar_core::BodyParams, Option<BodyFit>)>) {
        let Some(p) = &self.photo.photo else {
            self.messages.push("open a photo first".into());
            return;
        };
        let ctx = self.ctx.clone();
        let Some(body) = self.body.as_ref() else {
            self.fail_photo("no body model to fit".into());
            return;
        };
        if let Some((_, t)) = self.photo.task.take() {
            t.cancel();
        }
        let model = body.clone();
        let options = self.photo.options.clone().unwrap_or_default();
        let device = match (self.photo.on_gpu, self.engine.as_ref()) {
            (false, _) => photo::fit_device(),
            (true, Some(e)) => e.device().clone().autodiff(),
            (true, None) => {
                self.fail_photo("no WebGPU device for burn: the fit runs on the CPU only".into());
                return;
            }
        };
        let req = FitRequest {
            model,
            result: p.result.clone(),
            width: p.width,
            height: p.height,
            options,
            start,
            device,
            preview: p.preview.size,
        };
        self.status.photo.state = "fitting".into();
        self.status.photo.steps_done = 0;
        self.photo.task = Some((TaskKind::Fit, photo::fit(req, ctx)));
    }

    fn fail_photo(&mut self, message: String) {
        self.status.photo.state = "failed".into();
        self.status.photo.failures += 1;
        self.status.photo.message = message.clone();
        self.messages.push(message);
    }

    /// The fit refined by the reconstruction (on its guess's outline) in place of the photo's,
    /// its overlay redrawn (unless a detection or fit runs, which brings its own); the one it
    /// replaces.
    pub(super) fn replace_photo_fit(&mut self, fit: BodyFit) -> Option<BodyFit> {
        if let (Some(p), Some(model), None) = (&self.photo.photo, &self.body, &self.photo.task) {
            let (result, preview) = (p.result.clone(), p.preview.size);
            let task = photo::refined_overlay(fit.clone(), model.clone(), result, preview, self.ctx.clone());
            self.photo.task = Some((TaskKind::Fit, task));
        }
        self.photo.fit.replace(fit)
    }

    /// A fit refined on the page ([`photo::refit`]) in place of the photo's, with the overlay
    /// it brings; the one it replaces.
    pub(super) fn install_refitted_fit(&mut self, view: photo::FittedView, ctx: &egui::Context) -> Option<BodyFit> {
        self.show_fit_overlay(view.body_image, view.masks_json, ctx);
        self.photo.fit.replace(view.fit)
    }

    fn show_fit_overlay(&mut self, body_image: egui::ColorImage, masks_json: String, ctx: &egui::Context) {
        self.photo.body = Some(ctx.load_texture("fitted body", body_image, egui::TextureOptions::LINEAR));
        photo::publish_masks(masks_json);
    }

    /// Drain the running task's events; start what they lead to.
    pub(super) fn poll_photo(&mut self, ctx: &egui::Context) {
        if let Some((fit, ms)) = self.photo.to_apply.take() {
            self.apply_fit(fit, ms);
        }
        let Some((_, task)) = self.photo.task.clone() else {
            if let Some((s, o, g, k)) = self.photo.queued.take() {
                self.open_photo(s, o, g, k);
            }
            return;
        };
        for event in task.drain() {
            match event {
                PhotoEvent::Progress(p) => {
                    let s = &mut self.status.photo;
                    s.stage = STAGE_NAMES.get(p.stage).copied().unwrap_or("").into();
                    (s.steps_done, s.steps_total, s.loss) = (p.done, p.total, p.loss);
                }
                PhotoEvent::Detected(p) => self.photo_detected(*p, ctx),
                PhotoEvent::Fitted(view) => self.photo_fitted(*view, ctx),
                PhotoEvent::Overlay(view) | PhotoEvent::Refitted(view) => {
                    self.show_fit_overlay(view.body_image, view.masks_json, ctx)
                }
                PhotoEvent::Failed(e) => self.fail_photo(e),
                PhotoEvent::Cancelled => {
                    self.status.photo.state = "cancelled".into();
                    self.status.photo.message = "fit cancelled".into();
                }
            }
        }
        // A detection that succeeded has started its fit, a new task; the drained one ends here.
        if task.finished() && self.photo.task.as_ref().is_some_and(|(_, t)| t.same(&task)) {
            self.photo.task = None;
        }
    }

    fn photo_detected(&mut self, p: Photo, ctx: &egui::Context) {
        let [w, h] = p.preview.size;
        self.photo.image = Some(ctx.load_texture("photo", p.preview.clone(), egui::TextureOptions::LINEAR));
        self.photo.person = p.result.segmentation_mask.as_ref().map(|m| {
            let img = tinted(&resampled(&m.data, m.width, m.height, w, h), w, h, PERSON_TINT, 0.45);
            ctx.load_texture("person mask", img, egui::TextureOptions::LINEAR)
        });
        self.photo.body = None;
        self.photo.fit = None;
        self.photo.visible = true;
        let missing = missing_joints(&p.result);
        let s = &mut self.status.photo;
        (s.width, s.height, s.detect_ms) = (p.width, p.height, p.detect_ms as f32);
        [s.detected_width, s.detected_height] = p.detected;
        s.missing_joints = missing.clone();
        s.held.clear();
        s.people = p.people;
        s.person = p.person.map(|k| k + 1);
        s.persons = p.persons.clone();
        s.rotation = p.rotation;
        s.tries = p.tries;
        s.mirrored = p.mirrored;
        let who = who_was_found(&p);
        s.message = if missing.is_empty() {
            format!("{who}; fitting the body…")
        } else {
            format!("{who}; only part of the person is visible ({} not seen); fitting the rest…", missing.join(", "))
        };
        s.name = p.name.clone();
        self.photo.photo = Some(p);
        photo::publish_masks(String::new());
        self.photo.task = None;
        self.start_fit(None);
    }

    /// A finished fit: its overlay now (made in the fit's task), the rest on the next frame.
    fn photo_fitted(&mut self, view: FittedView, ctx: &egui::Context) {
        self.photo.body = Some(ctx.load_texture("fitted body", view.body_image, egui::TextureOptions::LINEAR));
        // The masks hook (`window.getavatar.photoMasks()`): the person's and the fitted body's.
        photo::publish_masks(view.masks_json);
        self.photo.to_apply = Some((view.fit, view.millis));
        ctx.request_repaint();
    }

    /// The fit becomes the app's pose and shape, seen from the photo's side.
    fn apply_fit(&mut self, fit: BodyFit, ms: f64) {
        self.params = fit.body_params();
        self.pose_name = "photo fit".into();
        self.mesh_dirty = true;
        let eye = fit.world_to_camera().inverse().transform_point3(glam::Vec3::ZERO);
        self.camera.yaw = eye.x.atan2(eye.z);
        self.camera = self.camera.clamped();
        self.render_dirty = true;
        let s = &mut self.status.photo;
        s.state = "fitted".into();
        s.fits += 1;
        s.fit_ms = ms as f32;
        s.mean_px = fit.residuals.mean_px;
        s.relative_to_height = fit.residuals.relative_to_height;
        s.mask_iou = fit.residuals.mask_iou;
        s.message = format!(
            "fitted in {:.1} s: keypoints within {:.1} px ({:.1} % of the height){}",
            ms / 1000.0,
            fit.residuals.mean_px,
            fit.residuals.relative_to_height * 100.0,
            fit.residuals.mask_iou.map(|i| format!(", mask IoU {i:.2}")).unwrap_or_default()
        );
        if !s.missing_joints.is_empty() {
            s.message += &format!("; not seen: {}", s.missing_joints.join(", "));
        }
        if !fit.off_person.is_empty() {
            s.message += &format!(
                "; the detector put {} off the person: fitted to the person's outline instead",
                fit.off_person.join(", ")
            );
        }
        if let Some(p) = &self.photo.photo {
            if p.people.is_some_and(|n| n > 1) || p.rotation != 0 {
                s.message += &format!("; {}", who_was_found(p));
            }
        }
        if !fit.relabelled.is_empty() {
            s.message += "; the detector's left and right hands were swapped back";
        }
        if !fit.held.is_empty() {
            s.message += &format!("; held where you put it, against the detector: {}", fit.held.join(", "));
        }
        s.held = fit.held.clone();
        self.photo.fit = Some(fit);
    }

    fn download_fit(&mut self) {
        let (Some(fit), Some(p)) = (&self.photo.fit, &self.photo.photo) else {
            self.messages.push("no fit to download yet".into());
            return;
        };
        let json = match fit.to_json() {
            Ok(j) => j,
            Err(e) => {
                self.messages.push(format!("fit.json: {e}"));
                return;
            }
        };
        let r = download_bytes("fit.json", json.as_bytes(), "application/json")
            .and_then(|()| download_bytes("kp.json", p.json.as_bytes(), "application/json"));
        match r {
            Ok(()) => self.status.photo.fit_downloads += 1,
            Err(e) => self.messages.push(format!("download failed: {e}")),
        }
    }

    /// A file dropped on the page opens by its kind (the first, if several): its bytes are
    /// read asynchronously, then opened like a chosen file.
    pub(super) fn take_dropped(&mut self, ctx: &egui::Context) {
        let arrived: Vec<_> = self.photo.dropped.borrow_mut().drain(..).collect();
        for r in arrived {
            match r {
                // Motion files go to the motion player, videos make clips, reconstructions become
                // the avatar, the rest is a photo.
                Ok((name, bytes)) if name.to_ascii_lowercase().ends_with(".npz") => {
                    self.apply(Action::MotionFile { name, bytes })
                }
                // Videos become motion clips.
                Ok((name, bytes)) if crate::video_clip::is_video_name(&name) => {
                    self.apply(Action::Video { source: PhotoSource::Bytes { name, bytes }, fps: None })
                }
                // Saved reconstructions open as the avatar.
                Ok((name, bytes)) if name.to_ascii_lowercase().ends_with(".safetensors") => {
                    self.apply(Action::OpenReconstruction(PhotoSource::Bytes { name, bytes }))
                }
                Ok((name, bytes)) => self.apply(Action::Photo {
                    source: PhotoSource::Bytes { name, bytes },
                    options: None,
                    on_gpu: false,
                }),
                Err(e) => self.fail_photo(e),
            }
        }
        let Some(file) = ctx.input(|i| i.raw.dropped_files.first().cloned()) else { return };
        let (slot, repaint) = (self.photo.dropped.clone(), ctx.clone());
        wasm_bindgen_futures::spawn_local(async move {
            let name = file.path().display().to_string();
            let name = if name.is_empty() { "dropped file".to_string() } else { name };
            let r = file.bytes_async().await.map(|b| (name.clone(), b)).map_err(|e| format!("cannot read {name}: {e}"));
            slot.borrow_mut().push(r);
            repaint.request_repaint();
        });
    }

    /// The side panel's section.
    pub(super) fn photo_section(&mut self, ui: &mut egui::Ui) {
        ui.strong("Reconstruct from photo");
        ui.horizontal(|ui| {
            let open =
                ui.button("Open photo…").on_hover_text("PNG, JPEG or WebP of one person; or drop it on the page");
            let r = open.rect;
            self.status.open_photo_button = [r.min.x, r.min.y, r.width(), r.height()];
            if open.clicked() {
                if let Err(e) = crate::platform::open_file_picker(crate::platform::PHOTO_INPUT_ID) {
                    self.messages.push(format!("cannot open the file chooser: {e}"));
                }
            }
            if self.photo.task.is_some() {
                super::busy_indicator(ui);
                if ui.button("Cancel").clicked() {
                    self.apply(Action::PhotoFit(PhotoFitAction::Cancel));
                }
            }
        });
        let s = &self.status.photo;
        if s.state == "fitting" && s.steps_total > 0 {
            let frac = s.steps_done as f32 / s.steps_total as f32;
            ui.add(
                egui::ProgressBar::new(frac)
                    .text(format!("{} stage · step {}/{} · loss {:.3}", s.stage, s.steps_done, s.steps_total, s.loss)),
            );
        }
        if !s.message.is_empty() {
            ui.label(egui::RichText::new(&s.message).small());
        }
        if self.photo.photo.is_some() {
            ui.horizontal_wrapped(|ui| {
                ui.checkbox(&mut self.photo.visible, "photo");
                ui.checkbox(&mut self.photo.show_keypoints, "keypoints");
                ui.checkbox(&mut self.photo.show_mask, "person mask");
                ui.checkbox(&mut self.photo.show_body, "fitted body");
            });
            ui.horizontal(|ui| {
                let idle = self.photo.task.is_none();
                if ui
                    .add_enabled(idle, egui::Button::new("Re-fit from this pose"))
                    .on_hover_text("correct joints with the pose controls below, then fit again from there")
                    .clicked()
                {
                    self.apply(Action::PhotoFit(PhotoFitAction::Refit));
                }
                if ui
                    .add_enabled(self.photo.fit.is_some(), egui::Button::new("⬇ Download fit"))
                    .on_hover_text("fit.json (pose, shape, camera, residuals) and kp.json (the detection)")
                    .clicked()
                {
                    self.apply(Action::PhotoFit(PhotoFitAction::Download));
                }
                if ui.button("Close").clicked() {
                    self.apply(Action::PhotoFit(PhotoFitAction::Close));
                }
            });
            self.reconstruct_section(ui);
        } else {
            ui.label(egui::RichText::new("drop a photo anywhere on the page").small());
        }
        self.reconstruction_files(ui, self.photo.photo.is_none());
    }

    /// The photo with its overlays, fitted into `ui`'s space.
    pub(super) fn photo_view(&mut self, ui: &mut egui::Ui) {
        let (Some(image), Some(p)) = (&self.photo.image, &self.photo.photo) else { return };
        let avail = ui.available_rect_before_wrap();
        let [pw, ph] = p.preview.size;
        let k = (avail.width() / pw as f32).min(avail.height() / ph as f32);
        let rect = Rect::from_center_size(avail.center(), egui::vec2(pw as f32 * k, ph as f32 * k));
        let response = ui.allocate_rect(avail, egui::Sense::click());
        self.status.photo_view = [rect.min.x, rect.min.y, rect.width(), rect.height()];
        let uv = Rect::from_min_max(Pos2::ZERO, Pos2::new(1.0, 1.0));
        let painter = ui.painter_at(avail);
        painter.image(image.id(), rect, uv, Color32::WHITE);
        if self.photo.show_mask {
            if let Some(t) = &self.photo.person {
                painter.image(t.id(), rect, uv, Color32::WHITE);
            }
        }
        if self.photo.show_body {
            if let Some(t) = &self.photo.body {
                painter.image(t.id(), rect, uv, Color32::WHITE);
            }
        }
        // Every person seen, numbered by size; a click on another one fits that one.
        if p.persons.len() > 1 {
            let boxes: Vec<Rect> = p
                .persons
                .iter()
                .map(|b| {
                    let at = |u: f32, v: f32| Pos2::new(rect.min.x + u * rect.width(), rect.min.y + v * rect.height());
                    Rect::from_min_max(at(b[0], b[1]), at(b[0] + b[2], b[1] + b[3]))
                })
                .collect();
            let hover = response.hover_pos();
            for (k, b) in boxes.iter().enumerate() {
                let fitted = p.person == Some(k);
                let hot = !fitted && hover.is_some_and(|h| b.contains(h));
                let colour = match (fitted, hot) {
                    (true, _) => Color32::from_rgb(255, 150, 40),
                    (false, true) => Color32::WHITE,
                    (false, false) => Color32::from_rgb(120, 200, 255),
                };
                painter.rect_stroke(
                    *b,
                    4.0,
                    Stroke::new(if fitted { 2.5 } else { 1.5 }, colour),
                    egui::StrokeKind::Outside,
                );
                painter.text(
                    b.min + egui::vec2(4.0, 2.0),
                    egui::Align2::LEFT_TOP,
                    format!("{}", k + 1),
                    egui::FontId::proportional(16.0),
                    colour,
                );
            }
            if let Some(at) = response.interact_pointer_pos().filter(|_| response.clicked()) {
                // The smallest box under the click (a person in front of a larger one).
                let hit = (0..boxes.len())
                    .filter(|k| boxes[*k].contains(at))
                    .min_by(|a, b| boxes[*a].area().total_cmp(&boxes[*b].area()));
                if let Some(k) = hit.filter(|k| p.person != Some(*k)) {
                    self.apply(Action::PhotoFit(PhotoFitAction::Person(k + 1)));
                    return;
                }
            }
            response.on_hover_text("click a person to fit that one");
        }
        if !self.photo.show_keypoints {
            return;
        }
        // Photo pixels → screen.
        let sx = rect.width() / p.width as f32;
        let sy = rect.height() / p.height as f32;
        let at = |q: [f32; 2]| Pos2::new(rect.min.x + q[0] * sx, rect.min.y + q[1] * sy);
        let lm = &p.result.pose_landmarks;
        // A limb the fit held where the user put it: its landmarks are drawn as unseen.
        let held: Vec<usize> = self.photo.fit.as_ref().map_or_else(Vec::new, |fit| {
            LIMBS.iter().filter(|l| fit.held.iter().any(|h| h == l.name)).flat_map(|l| l.landmarks.to_vec()).collect()
        });
        let seen = |i: usize| lm[i].visibility >= VISIBLE && !held.contains(&i);
        let px = |i: usize| at([lm[i].x * p.width as f32, lm[i].y * p.height as f32]);
        for (a, b) in CONNECTIONS {
            let c = if seen(a) && seen(b) { Color32::from_rgb(90, 220, 120) } else { Color32::from_gray(150) };
            painter.line_segment([px(a), px(b)], Stroke::new(2.0, c));
        }
        for i in 0..lm.len() {
            let c = if seen(i) { Color32::from_rgb(60, 200, 90) } else { Color32::from_gray(140) };
            painter.circle_filled(px(i), 3.5, c);
        }
        if let Some(fit) = &self.photo.fit {
            for (i, kp) in fit.keypoints.iter().enumerate() {
                if let (Some(f), false) = (kp.fitted, held.contains(&i)) {
                    let (o, f) = (at(kp.observed), at(f));
                    painter.line_segment([o, f], Stroke::new(1.0, Color32::WHITE));
                    painter.circle_stroke(f, 3.0, Stroke::new(1.5, Color32::from_rgb(255, 150, 40)));
                }
            }
        }
    }
}

/// "person found", or who of the people seen was found and how ("3 people; fitted the
/// largest that could be read, the 2nd by size; read with the photo turned 180°").
fn who_was_found(p: &Photo) -> String {
    let ordinal = |k: usize| {
        let suffix = match (k % 10, k % 100) {
            (_, 11..=13) => "th",
            (1, _) => "st",
            (2, _) => "nd",
            (3, _) => "rd",
            _ => "th",
        };
        format!("{k}{suffix}")
    };
    let mut who = match (p.people, p.person) {
        (Some(n), Some(k)) if n > 1 && p.chosen => {
            format!("{n} people; fitted the {} by size, as chosen", ordinal(k + 1))
        }
        (Some(n), Some(0)) if n > 1 => format!("{n} people; fitted the largest"),
        (Some(n), Some(k)) if n > 1 => {
            format!("{n} people; fitted the largest that could be read, the {} by size", ordinal(k + 1))
        }
        (Some(n), None) if n > 1 => format!("{n} people; fitted a person read on the whole photo"),
        _ => "person found".into(),
    };
    if p.rotation != 0 {
        who += &format!("; read with the photo turned {}°", p.rotation);
    }
    who
}

/// SMPL joints whose landmark the detector did not see.
fn missing_joints(r: &PoseResult) -> Vec<String> {
    JOINT_LANDMARKS
        .iter()
        .filter(|m| r.pose_landmarks.get(m.landmark).is_none_or(|l| l.visibility < VISIBLE))
        .map(|m| JOINT_NAMES[m.joint].replace('_', " "))
        .collect()
}
