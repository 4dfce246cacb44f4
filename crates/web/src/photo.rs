//! The photo → body flow's browser side (paper Sec. 3.4's inversion starts from it): a photo's
//! bytes go to MediaPipe Pose (`www/pose_detect.js`, called through wasm-bindgen), its
//! landmarks and person mask to `getavatar_core::body::body_fit` (burn with autodiff on NdArray,
//! [`fit_device`]; the shared WebGPU device on request). Both run as async tasks; the fit runs
//! in slices of Adam steps between frames, so the page stays live, shows progress and can
//! cancel between steps. [`refit`] refits the photo's body on a reconstruction's outline the
//! same way.
//!
//! Tasks report through a [`PhotoTask`]'s event queue (`crate::task`), which the app drains
//! every frame.

use std::cell::RefCell;
use std::rc::Rc;
use std::sync::Arc;

use eframe::egui;
use serde::Deserialize;
use wasm_bindgen::prelude::*;
use wasm_bindgen::JsCast;

use getavatar_core::body::body_fit::fit::{BodyFit, BodyFitter, FitInput, FitOptions, FitProgress};
use getavatar_core::body::body_fit::landmarks::PoseResult;
use getavatar_core::body::body_fit::metrics::body_mask_rect;
use getavatar_core::body::body_fit::refit::{finish_outline_refit, outline_refitter, RefitOptions};
use getavatar_core::body::skinning::pose_body;
use getavatar_core::burn::tensor::Device;
use getavatar_core::generator::pipeline::BodyContext;
use getavatar_core::generator::rigging::RiggedAvatar;
use getavatar_core::{BodyModel, BodyParams};

use crate::automation::PhotoSource;
use crate::platform::{fetch_bytes, js_message, now_ms};
use crate::task::{checkpoint, EventKind, Task, TaskEvent};

#[wasm_bindgen(raw_module = "./pose_detect.js")]
extern "C" {
    /// MediaPipe Pose on a photo's bytes, in a worker: a JSON string (the result, or
    /// `{"error": …}`); the photo is kept for [`photo_preview`] at most `preview_side` pixels
    /// on its long side.
    /// `person` ≥ 0 reads only that person (0 = the largest region); -1 searches them all.
    #[wasm_bindgen(catch, js_name = detectPose)]
    async fn detect_pose(bytes: &js_sys::Uint8Array, preview_side: u32, person: i32) -> Result<JsValue, JsValue>;
    /// The last detected photo, downscaled: `{width, height, data}` or null.
    #[wasm_bindgen(catch, js_name = photoPreview)]
    fn photo_preview() -> Result<JsValue, JsValue>;
}

/// Long side of the photo as the app shows it, pixels.
pub const PREVIEW_SIDE: u32 = 768;

/// A photo the detector found a person in.
pub struct Photo {
    /// File name (or URL) it came from.
    pub name: String,
    /// Size of the original photo, pixels.
    pub width: usize,
    pub height: usize,
    /// Size the detector ran at (the photo downscaled to at most 4 MP).
    pub detected: [usize; 2],
    pub result: PoseResult,
    /// The detector's result as it returned it (`kp.json` of "Download fit").
    pub json: String,
    /// The photo downscaled to at most [`PREVIEW_SIDE`].
    pub preview: egui::ColorImage,
    pub detect_ms: f64,
    /// People in the photo (selfie segmentation's regions), when it could tell.
    pub people: Option<usize>,
    /// Each person's box in the shown (turned) photo, normalised [x, y, w, h], largest first.
    pub persons: Vec<[f32; 4]>,
    /// The detected one of them (0 = the largest), None when read on the whole photo outside
    /// every region.
    pub person: Option<usize>,
    /// Whether the user chose that person (else the finder did).
    pub chosen: bool,
    /// Degrees clockwise the photo was turned to read the person upright: the preview, the
    /// sizes and the detection are of the turned photo.
    pub rotation: u16,
    /// Candidates the finder tried.
    pub tries: usize,
    /// The landmarks are Pose's reading of the mirrored photo: the first reading put limb
    /// landmarks off the person's mask or put both hands in one place (`www/pose_worker.js`,
    /// `secondOpinion`).
    pub mirrored: bool,
    /// The photo's bytes, to find another of its people.
    pub bytes: std::rc::Rc<Vec<u8>>,
}

/// What a task reports.
pub enum PhotoEvent {
    Detected(Box<Photo>),
    /// One sentence for the user; the app stays as it was.
    Failed(String),
    Progress(FitProgress),
    /// The fit, its time and its overlay.
    Fitted(Box<FittedView>),
    /// The overlay of a fit refined elsewhere (the reconstruction's refit on its guess's
    /// outline), which the app has already applied.
    Overlay(Box<FittedView>),
    /// The photo's fit refined on an avatar's outline ([`refit`]), its time and its overlay.
    Refitted(Box<FittedView>),
    Cancelled,
}

impl TaskEvent for PhotoEvent {
    fn kind(&self) -> EventKind {
        match self {
            PhotoEvent::Progress(_) => EventKind::Latest,
            _ => EventKind::Outcome,
        }
    }
}

/// A running detection or fit.
pub type PhotoTask = Task<PhotoEvent>;

/// The fields of `pose_detect.js`'s answer that are not MediaPipe's result.
#[derive(Deserialize)]
struct DetectorAnswer {
    error: Option<String>,
    width: Option<usize>,
    height: Option<usize>,
    #[serde(rename = "detectedWidth")]
    detected_width: Option<usize>,
    #[serde(rename = "detectedHeight")]
    detected_height: Option<usize>,
    people: Option<usize>,
    #[serde(default)]
    persons: Vec<PersonBox>,
    person: Option<usize>,
    #[serde(default)]
    rotation: u16,
    #[serde(default)]
    tries: usize,
    #[serde(default)]
    mirrored: bool,
}

/// A person's box, normalised to the photo.
#[derive(Deserialize)]
struct PersonBox {
    x: f32,
    y: f32,
    w: f32,
    h: f32,
}

/// Detect the person in a photo (PNG, JPEG or WebP; bytes, or a URL fetched first): the
/// finder's choice, or the `person`-th by size (0 = the largest) when given.
pub fn detect(source: PhotoSource, person: Option<usize>, repaint: egui::Context) -> PhotoTask {
    let task = PhotoTask::default();
    let t = task.clone();
    wasm_bindgen_futures::spawn_local(async move {
        let t0 = now_ms();
        let fetched = match source {
            PhotoSource::Bytes { name, bytes } => Ok((name, bytes)),
            PhotoSource::Url(url) => fetch_bytes(&url).await.map(|b| (url, b)),
        };
        let detected = match fetched {
            Ok((name, bytes)) => detect_async(bytes, name, person, t0).await,
            Err(e) => Err(format!("cannot fetch the photo: {e}")),
        };
        let event = match detected {
            Ok(p) => PhotoEvent::Detected(Box::new(p)),
            Err(e) => PhotoEvent::Failed(e),
        };
        t.push(event, &repaint);
    });
    task
}

async fn detect_async(bytes: Vec<u8>, name: String, person: Option<usize>, t0: f64) -> Result<Photo, String> {
    let array = js_sys::Uint8Array::from(&bytes[..]);
    let want = person.map_or(-1, |k| i32::try_from(k).unwrap_or(i32::MAX));
    let answer = detect_pose(&array, PREVIEW_SIDE, want)
        .await
        .map_err(|e| format!("the person detector failed: {}", js_message(&e)))?;
    let json = answer.as_string().ok_or("the person detector returned no answer")?;
    let head: DetectorAnswer =
        serde_json::from_str(&json).map_err(|e| format!("the person detector's answer is not JSON: {e}"))?;
    if let Some(e) = head.error {
        return Err(format!("{name}: {e}"));
    }
    let (Some(width), Some(height), Some(dw), Some(dh)) =
        (head.width, head.height, head.detected_width, head.detected_height)
    else {
        return Err("the person detector's answer has no photo size".into());
    };
    let result = PoseResult::from_json(&json).map_err(|e| format!("the person detector's answer: {e}"))?;
    let preview = preview_image()?;
    Ok(Photo {
        name,
        width,
        height,
        detected: [dw, dh],
        result,
        json,
        preview,
        detect_ms: now_ms() - t0,
        people: head.people,
        persons: head.persons.iter().map(|b| [b.x, b.y, b.w, b.h]).collect(),
        person: head.person,
        chosen: person.is_some(),
        rotation: head.rotation,
        tries: head.tries,
        mirrored: head.mirrored,
        bytes: std::rc::Rc::new(bytes),
    })
}

/// The last detected photo as an egui image.
fn preview_image() -> Result<egui::ColorImage, String> {
    let v = photo_preview().map_err(|e| format!("cannot read the photo back: {}", js_message(&e)))?;
    let get = |k: &str| js_sys::Reflect::get(&v, &JsValue::from_str(k)).map_err(|e| js_message(&e));
    let (w, h) = (get("width")?.as_f64(), get("height")?.as_f64());
    let data: js_sys::Uint8Array =
        get("data")?.dyn_into().map_err(|_| "the photo's pixels are not a Uint8Array".to_string())?;
    let (Some(w), Some(h)) = (w, h) else { return Err("the photo's preview has no size".into()) };
    let (w, h) = (w as usize, h as usize);
    let rgba = data.to_vec();
    if rgba.len() != w * h * 4 {
        return Err(format!("the photo's preview has {} bytes for {w}×{h} pixels", rgba.len()));
    }
    Ok(egui::ColorImage::from_rgba_unmultiplied([w, h], &rgba))
}

/// What a fit needs from the app.
pub struct FitRequest {
    pub model: Arc<BodyModel>,
    pub result: PoseResult,
    pub width: usize,
    pub height: usize,
    pub options: FitOptions,
    /// Start from this pose and shape (a re-fit after the user corrected joints), seen through
    /// the photo's last fit's camera when there is one: then a limb the user moved off its
    /// landmarks is held where they put it (`BodyFitter::correct_from`).
    pub start: Option<(BodyParams, Option<BodyFit>)>,
    /// An autodiff device (`Device::autodiff()`).
    pub device: Device,
    /// The size of the photo's preview, which the overlay covers.
    pub preview: [usize; 2],
}

/// A finished fit as the photo view shows it, made in the fit's task rather than in the frame
/// that receives it (posing and rasterizing the body there held the UI thread ~50 ms).
pub struct FittedView {
    pub fit: BodyFit,
    /// The fit's time in milliseconds.
    pub millis: f64,
    /// The fitted body's silhouette over the preview, tinted.
    pub body_image: egui::ColorImage,
    /// `window.getavatar.photoMasks()`'s JSON: the fitted body's and the person's masks.
    pub masks_json: String,
}

pub(crate) const BODY_TINT: [u8; 3] = [255, 150, 40];

/// The fitted body's tinted silhouette and the masks hook's JSON at the preview's size.
async fn overlay(
    fit: &BodyFit,
    model: &BodyModel,
    result: &PoseResult,
    [w, h]: [usize; 2],
) -> (egui::ColorImage, String) {
    let posed = pose_body(model, &fit.body_params());
    checkpoint().await;
    let mask = body_mask_rect(&posed.vertices, &model.faces, fit.photo_view_proj(), w, h);
    checkpoint().await;
    let image = tinted(&mask, w, h, BODY_TINT, 0.5);
    let person = result.segmentation_mask.as_ref().map(|m| bits(&resampled(&m.data, m.width, m.height, w, h)));
    let masks = serde_json::json!({ "width": w, "height": h, "body": bits(&mask), "person": person });
    (image, masks.to_string())
}

/// A mask covering the photo (`mw × mh`) resampled to `w × h` (nearest value).
pub(crate) fn resampled(values: &[f32], mw: usize, mh: usize, w: usize, h: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(w * h);
    for y in 0..h {
        let my = (((y as f32 + 0.5) / h as f32 * mh as f32) as usize).min(mh.saturating_sub(1));
        for x in 0..w {
            let mx = (((x as f32 + 0.5) / w as f32 * mw as f32) as usize).min(mw.saturating_sub(1));
            out.push(values.get(my * mw + mx).copied().unwrap_or(0.0));
        }
    }
    out
}

/// A `w × h` mask (0..1) as a tinted translucent image.
pub(crate) fn tinted(values: &[f32], w: usize, h: usize, tint: [u8; 3], alpha: f32) -> egui::ColorImage {
    let pixels = values
        .iter()
        .take(w * h)
        .map(|v| {
            let a = (v.clamp(0.0, 1.0) * alpha * 255.0).round() as u8;
            egui::Color32::from_rgba_unmultiplied(tint[0], tint[1], tint[2], a)
        })
        .collect();
    egui::ColorImage::new([w, h], pixels)
}

/// `'0'`/`'1'` per pixel (the masks hook's compact form).
fn bits(values: &[f32]) -> String {
    values.iter().map(|v| if *v >= 0.5 { '1' } else { '0' }).collect()
}

/// Where the browser runs the fit: NdArray (CPU) with autodiff. Its tensors are small (24
/// joints, 33 landmarks, one 128² mask), so GPU dispatches and read-backs cost more than the
/// arithmetic: see docs/benchmarks.md for the measured steps per second of both.
pub fn fit_device() -> Device {
    // The project's CPU backend (as natively); burn 0.22 marks it deprecated in favour of flex.
    #[allow(deprecated)]
    Device::ndarray().autodiff()
}

/// Fit the body to a detection, one step per await.
pub fn fit(req: FitRequest, repaint: egui::Context) -> PhotoTask {
    let task = PhotoTask::default();
    let t = task.clone();
    wasm_bindgen_futures::spawn_local(async move {
        let event = match fit_async(req, &t, &repaint).await {
            Ok(Some(view)) => PhotoEvent::Fitted(Box::new(view)),
            Ok(None) => PhotoEvent::Cancelled,
            Err(e) => PhotoEvent::Failed(format!("the body fit failed: {e}")),
        };
        t.push(event, &repaint);
    });
    task
}

async fn fit_async(
    req: FitRequest,
    task: &PhotoTask,
    repaint: &egui::Context,
) -> Result<Option<FittedView>, getavatar_core::body::body_fit::fit::FitError> {
    let t0 = now_ms();
    let model = req.model.clone();
    // Not in the frame that asked (its own work is a task already), and a slice each for the
    // input and the fitter (~30 ms each on the test machine).
    crate::task::yield_to_browser().await;
    let input = FitInput::from_detection(&req.result, req.width, req.height, None, &req.model, &req.options)?;
    checkpoint().await;
    let mut fitter = BodyFitter::new(req.model, input, req.options, &req.device)?;
    match &req.start {
        Some((params, Some(last))) => {
            fitter.correct_from(&last.with_params(params));
        }
        Some((params, None)) => fitter.start_from(params),
        None => {}
    }
    if !run_steps(&mut fitter, task, repaint).await? {
        return Ok(None);
    }
    let fit = fitter.finish().await?;
    checkpoint().await;
    let (body_image, masks_json) = overlay(&fit, &model, &req.result, req.preview).await;
    Ok(Some(FittedView { fit, millis: now_ms() - t0, body_image, masks_json }))
}

/// Step `fitter` to its end, reporting progress; false when the task was cancelled.
async fn run_steps(
    fitter: &mut BodyFitter,
    task: &PhotoTask,
    repaint: &egui::Context,
) -> Result<bool, getavatar_core::body::body_fit::fit::FitError> {
    loop {
        // On the CPU a step never waits for anything: give the page the thread back once the
        // slice is over (`task::SLICE_MS`), so it repaints, shows the progress and sees Cancel.
        checkpoint().await;
        if task.cancelled() {
            return Ok(false);
        }
        match fitter.step().await? {
            Some(p) => task.push(PhotoEvent::Progress(p), repaint),
            None => return Ok(true),
        }
    }
}

/// What [`refit`] refines: the photo's `fit` on an avatar's outline, against the person
/// `mask` of the fit's crop (`size`²).
pub struct RefitRequest {
    pub model: Arc<BodyModel>,
    pub fit: BodyFit,
    pub mask: Vec<f32>,
    pub size: usize,
    /// The avatar whose outline the body is fitted with, and the body context it was rigged in.
    pub rigged: RiggedAvatar,
    pub ctx: Rc<BodyContext>,
    pub options: RefitOptions,
    /// An autodiff device (`fit_device()`).
    pub device: Device,
    /// The photo's detection and preview size, which the overlay covers.
    pub result: PoseResult,
    pub preview: [usize; 2],
}

/// Refit the photo's body on an avatar's outline on the page, one step per await
/// (`body_fit::refit`): the reconstruction's guess is already rigged here, so the refit needs
/// no worker job. Ends in [`PhotoEvent::Refitted`] (or `Failed`, `Cancelled`).
pub fn refit(req: RefitRequest, repaint: egui::Context) -> PhotoTask {
    let task = PhotoTask::default();
    let t = task.clone();
    wasm_bindgen_futures::spawn_local(async move {
        let event = match refit_async(req, &t, &repaint).await {
            Ok(Some(view)) => PhotoEvent::Refitted(Box::new(view)),
            Ok(None) => PhotoEvent::Cancelled,
            Err(e) => PhotoEvent::Failed(format!("the body's refit on the guess's outline failed: {e}")),
        };
        t.push(event, &repaint);
    });
    task
}

async fn refit_async(
    req: RefitRequest,
    task: &PhotoTask,
    repaint: &egui::Context,
) -> Result<Option<FittedView>, getavatar_core::body::body_fit::fit::FitError> {
    let t0 = now_ms();
    crate::task::yield_to_browser().await;
    let outline = req.rigged.outline_mesh(&req.ctx);
    checkpoint().await;
    let mut fitter =
        outline_refitter(req.model.clone(), &req.fit, &req.mask, req.size, &outline, &req.options, &req.device).await?;
    if !run_steps(&mut fitter, task, repaint).await? {
        return Ok(None);
    }
    let fit = finish_outline_refit(&fitter, &req.fit).await?;
    let millis = now_ms() - t0;
    checkpoint().await;
    let (body_image, masks_json) = overlay(&fit, &req.model, &req.result, req.preview).await;
    Ok(Some(FittedView { fit, millis, body_image, masks_json }))
}

/// The overlay of `fit`, a fit refined elsewhere (the reconstruction's refit), made in a task
/// of its own ([`PhotoEvent::Overlay`]): posing and rasterizing the body is ~50 ms.
pub fn refined_overlay(
    fit: BodyFit,
    model: Arc<BodyModel>,
    result: PoseResult,
    preview: [usize; 2],
    repaint: egui::Context,
) -> PhotoTask {
    let task = PhotoTask::default();
    let t = task.clone();
    wasm_bindgen_futures::spawn_local(async move {
        crate::task::yield_to_browser().await;
        let (body_image, masks_json) = overlay(&fit, &model, &result, preview).await;
        t.push(PhotoEvent::Overlay(Box::new(FittedView { fit, millis: 0.0, body_image, masks_json })), &repaint);
    });
    task
}

thread_local! {
    /// The last fit's masks for `window.getavatar.photoMasks()` (JSON, "" before a fit).
    static MASKS: RefCell<String> = const { RefCell::new(String::new()) };
}

/// Set what `window.getavatar.photoMasks()` returns.
pub fn publish_masks(json: String) {
    MASKS.with(|m| *m.borrow_mut() = json);
}

/// JSON `{width, height, body, person}` of the last fit at the photo's preview size: the
/// fitted body's and the detector's person mask, one `'0'`/`'1'` per pixel from the top left
/// (`person` is null without a mask); `""` before a fit.
#[wasm_bindgen]
pub fn getavatar_photo_masks() -> String {
    MASKS.with(|m| m.borrow().clone())
}
