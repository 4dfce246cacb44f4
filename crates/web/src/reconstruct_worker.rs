//! The reconstruction worker: the inversion's steps each run a backward pass of
//! hundreds of kernel launches in one call (160–360 ms of the UI thread per step, seconds of
//! kernel compiles on the first), which no slicing can split. So the page hands the inversion
//! to a dedicated worker: a second instance of this same wasm module (`www/reconstruct_worker.js`)
//! with its own WebGPU device, the embedded body model and the checkpoint's bytes. It reports
//! its start, steps and previews as it goes, and its result as a reconstruction file (the
//! "Save reconstruction" format: tuned generator, codes, photo), which the page rigs exactly
//! as "Open reconstruction…" does. Where a worker cannot have WebGPU (or cannot start), the
//! page runs the reconstruction itself, as before.
//!
//! Both sides are here: [`start`] on the page, [`reconstruct_worker_message`] in the worker.
//! Messages are `{json, …typed arrays}`: the JSON holds the small fields (see [`ToWorker`] and
//! [`FromWorker`]), the arrays the bulk (checkpoint, images, the result file).

use std::cell::{Cell, RefCell};
use std::rc::Rc;

use eframe::egui;
use getavatar_core::body::body_fit::fit::BodyFit;
use getavatar_core::body::body_fit::landmarks::SegmentationMask;
use getavatar_core::body::body_model::BodyModel;
use getavatar_core::body::skinning::BodyParams;
use getavatar_core::burn::tensor::wgpu::WgpuSetup;
use getavatar_core::burn::tensor::Device;
use getavatar_core::generator::checkpoint::save_inverted_async;
use getavatar_core::generator::network::GeneratorConfig;
use getavatar_core::generator::pipeline::BodyContext;
use getavatar_core::reconstruction::inversion::{InversionOptions, InversionTarget, StepReport};
use getavatar_core::render::camera::View;
use glam::Mat4;
use serde::{Deserialize, Serialize};
use wasm_bindgen::prelude::*;
use wasm_bindgen::JsCast;

use crate::platform::{js_message, now_ms};
use crate::reconstruct::{
    invert, rig_saved, run_on_page, Compute, InversionJob, Preview, Progress, Progressing, ProjectionSource,
    ReconstructEvent, ReconstructRequest, ReconstructTask, StartChoice,
};

/// The worker's script, next to the page (`cargo xtask build-web` copies `www/` into dist/).
const WORKER_URL: &str = "./reconstruct_worker.js";

/// An idle worker is ended after this long: it holds its own GPU memory (the inversion's pool
/// of buffers, which only ending the worker gives back); a reconstruction soon after reuses it
/// (its device, body context, model files and compiled kernels).
const IDLE_RELEASE_MS: i32 = 120_000;

#[wasm_bindgen]
extern "C" {
    /// The browser's `Worker` (declared here rather than through web-sys features, which would
    /// rebuild web-sys and everything above it).
    #[wasm_bindgen(js_name = Worker)]
    type JsWorker;
    #[wasm_bindgen(constructor, js_class = "Worker", catch)]
    fn new(url: &str, options: &JsValue) -> Result<JsWorker, JsValue>;
    #[wasm_bindgen(method, js_class = "Worker", js_name = postMessage, catch)]
    fn post_message(this: &JsWorker, message: &JsValue, transfer: &js_sys::Array) -> Result<(), JsValue>;
    #[wasm_bindgen(method, js_class = "Worker", setter = onmessage)]
    fn set_onmessage(this: &JsWorker, f: &js_sys::Function);
    #[wasm_bindgen(method, js_class = "Worker", setter = onerror)]
    fn set_onerror(this: &JsWorker, f: &js_sys::Function);
    #[wasm_bindgen(method, js_class = "Worker")]
    fn terminate(this: &JsWorker);
}

/// The page's message to the worker (the `json` field).
#[derive(Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
enum ToWorker {
    /// Run an inversion; the arrays `target_rgb`, `target_mask`, and optionally `checkpoint`,
    /// `discriminator`, `encoder` and `photo_rgb` (the projection's photo) come with it.
    Start(Box<JobMeta>),
    /// The model files the next jobs use, sent ahead of the job in a message of their own
    /// (arrays `checkpoint`, `discriminator`, `encoder`: the ones the worker does not hold yet).
    Files,
    /// Stop the running inversion at its next step.
    Cancel,
}

/// An [`InversionJob`] without its arrays.
#[derive(Serialize, Deserialize)]
struct JobMeta {
    cfg: GeneratorConfig,
    /// The checkpoint (the discriminator) is the previous job's: the page sends each file once.
    checkpoint_kept: bool,
    discriminator_kept: bool,
    encoder_kept: bool,
    options: InversionOptions,
    preview_every: usize,
    start: StartChoice,
    compute: Compute,
    world_to_camera: [f32; 16],
    body: BodyParams,
    res: usize,
    projection: Option<ProjectionMeta>,
}

/// A [`ProjectionSource`] without its arrays (`photo_rgb`, `photo_mask`).
#[derive(Serialize, Deserialize)]
struct ProjectionMeta {
    fit: BodyFit,
    width: usize,
    height: usize,
    mask_width: usize,
    mask_height: usize,
    res: usize,
    num_betas: usize,
}

/// The worker's messages to the page (the `json` field).
#[derive(Serialize, Deserialize)]
#[serde(tag = "event", rename_all = "snake_case")]
enum FromWorker {
    Started {
        start: String,
        candidates: usize,
        perceptual: bool,
        millis: f64,
        device: String,
        note: String,
    },
    Step {
        report: StepReport,
        done: usize,
        total: usize,
        elapsed_ms: f64,
    },
    /// With the arrays `rgb` and `mask`.
    Preview {
        done: usize,
    },
    /// With the array `bytes`: the reconstruction file. IoU and PSNR at the photo's camera
    /// (None: not finite).
    Finished {
        iou: Option<f32>,
        psnr: Option<f32>,
        figures_ms: f64,
        file_ms: f64,
        /// Cancelled after this many steps (the result is the last preview's state).
        stopped_at: Option<usize>,
    },
    Failed {
        message: String,
    },
    Cancelled,
    /// This worker has no WebGPU device: the page runs the reconstruction itself.
    Unavailable {
        message: String,
    },
    /// The worker's module stopped (a panic): it is gone; the next reconstruction starts a new one.
    Fatal {
        message: String,
    },
}

// ---------------------------------------------------------------------------------------------
// The page's side.

/// The model files: a checkpoint's, a discriminator's and an encoder's bytes.
#[derive(Clone, Default)]
struct ModelFiles {
    checkpoint: Option<Rc<Vec<u8>>>,
    discriminator: Option<Rc<Vec<u8>>>,
    encoder: Option<Rc<Vec<u8>>>,
}

impl ModelFiles {
    const NAMES: [&'static str; 3] = ["checkpoint", "discriminator", "encoder"];

    fn of(job: &InversionJob) -> Self {
        Self {
            checkpoint: job.checkpoint.clone(),
            discriminator: job.discriminator.clone(),
            encoder: job.encoder.clone(),
        }
    }

    fn slot(&mut self, name: &str) -> &mut Option<Rc<Vec<u8>>> {
        match name {
            "checkpoint" => &mut self.checkpoint,
            "discriminator" => &mut self.discriminator,
            _ => &mut self.encoder,
        }
    }
}

/// The page's worker and the reconstruction it runs.
struct Client {
    worker: JsWorker,
    running: RefCell<Option<Running>>,
    /// The model files the worker holds (sent with an earlier job).
    sent: RefCell<ModelFiles>,
    _onmessage: Closure<dyn FnMut(JsValue)>,
    _onerror: Closure<dyn FnMut(JsValue)>,
}

/// A reconstruction handed to the worker.
struct Running {
    task: ReconstructTask,
    repaint: egui::Context,
    t0: f64,
    /// Kept to run it on the page if the worker turns out to have no WebGPU.
    fallback: Option<ReconstructRequest>,
    cfg: GeneratorConfig,
    ctx: Rc<BodyContext>,
    device: Device,
}

thread_local! {
    static CLIENT: RefCell<Option<Rc<Client>>> = const { RefCell::new(None) };
    /// A worker could not run a reconstruction here (why): later ones run on the page.
    static NO_WORKER: RefCell<Option<String>> = const { RefCell::new(None) };
    /// Jobs handed to a worker so far: an idle release applies only if none came since.
    static JOBS: Cell<u64> = const { Cell::new(0) };
}

/// End the worker if it is still idle after [`IDLE_RELEASE_MS`].
fn release_when_idle() {
    let job = JOBS.with(Cell::get);
    let release = Closure::once_into_js(move || {
        let idle = CLIENT.with(|c| c.borrow().as_ref().is_some_and(|c| c.running.borrow().is_none()));
        if idle && JOBS.with(Cell::get) == job {
            drop_client();
        }
    });
    let scheduled = crate::platform::set_timeout(release.unchecked_ref(), IDLE_RELEASE_MS);
    if scheduled.is_err() {
        // Without a timer the worker stays until the page closes; nothing is lost.
        web_sys::console::warn_1(&JsValue::from_str("the reconstruction worker cannot schedule its release"));
    }
}

/// Hand `req` to the worker (started on first use); its events arrive on `task`. `Err(req)`:
/// no worker can run it, run it on the page.
pub fn start(
    req: ReconstructRequest,
    task: ReconstructTask,
    repaint: egui::Context,
) -> Result<(), Box<ReconstructRequest>> {
    if NO_WORKER.with(|n| n.borrow().is_some()) {
        return Err(Box::new(req));
    }
    let client = match client() {
        Ok(c) => c,
        Err(e) => {
            worker_unusable(format!("the reconstruction worker cannot start: {e}"));
            return Err(Box::new(req));
        }
    };
    let worker_task = task.clone();
    let weak = Rc::downgrade(&client);
    task.on_cancel(move || {
        if let Some(c) = weak.upgrade() {
            if c.running.borrow().as_ref().is_some_and(|r| r.task.same(&worker_task)) {
                let m = message_of(&ToWorker::Cancel, &[]);
                let _ = c.worker.post_message(&m.data, &m.transfer);
            }
        }
    });
    JOBS.with(|j| j.set(j.get() + 1));
    let posted_task = task.clone();
    let (cfg, ctx, device) = (req.job.cfg.clone(), req.ctx.clone(), req.device.clone());
    *client.running.borrow_mut() = Some(Running { task, repaint, t0: now_ms(), fallback: Some(req), cfg, ctx, device });
    wasm_bindgen_futures::spawn_local(hand_over(client, posted_task));
    Ok(())
}

/// Post the running job to the worker, not in the frame that asked: the model files (≈ 7 MB
/// copied, once per worker), then the job and its photo, each in a task of its own (together
/// with the frame they held the UI thread ≈ 100 ms on SwiftShader's page). A job cancelled
/// before it is posted ends here; a worker that refuses it hands it to the page.
async fn hand_over(client: Rc<Client>, task: ReconstructTask) {
    for files in [true, false] {
        crate::task::yield_to_browser().await;
        let message = {
            let running = client.running.borrow();
            let Some(r) = running.as_ref().filter(|r| r.task.same(&task)) else { return };
            let Some(req) = r.fallback.as_ref() else { return };
            if r.task.cancelled() {
                drop(running);
                if let Some(r) = client.running.borrow_mut().take() {
                    r.task.push(ReconstructEvent::Cancelled, &r.repaint);
                }
                release_when_idle();
                return;
            }
            if files {
                files_message(&req.job, &client)
            } else {
                start_message(&req.job, &client)
                    .map(Some)
                    .map_err(|e| format!("the reconstruction cannot be handed to its worker: {e}"))
            }
        };
        let posted = match message {
            Ok(None) => Ok(()),
            Ok(Some(m)) => client
                .worker
                .post_message(&m.data, &m.transfer)
                .map_err(|e| format!("the reconstruction worker refused the job: {}", js_message(&e))),
            Err(e) => Err(e),
        };
        if let Err(why) = posted {
            return fall_back_to_page(why);
        }
    }
}

/// From now on reconstructions run on the page (said once in the console).
fn worker_unusable(why: String) {
    web_sys::console::warn_1(&JsValue::from_str(&format!("{why}; reconstructions run on the page")));
    NO_WORKER.with(|n| *n.borrow_mut() = Some(why));
    drop_client();
}

fn drop_client() {
    if let Some(c) = CLIENT.with(|c| c.borrow_mut().take()) {
        c.worker.terminate();
    }
}

/// The page's worker, started on first use.
fn client() -> Result<Rc<Client>, String> {
    if let Some(c) = CLIENT.with(|c| c.borrow().clone()) {
        return Ok(c);
    }
    let options = js_sys::Object::new();
    js_sys::Reflect::set(&options, &"type".into(), &"module".into()).map_err(|e| js_message(&e))?;
    js_sys::Reflect::set(&options, &"name".into(), &"getavatar reconstruction".into()).map_err(|e| js_message(&e))?;
    let worker = JsWorker::new(WORKER_URL, &options).map_err(|e| js_message(&e))?;
    let onmessage = Closure::<dyn FnMut(JsValue)>::new(|e: JsValue| {
        let data = js_sys::Reflect::get(&e, &"data".into()).unwrap_or(JsValue::UNDEFINED);
        on_message(data);
    });
    // The worker's script failed to load or threw outside a job: no worker from now on.
    let onerror = Closure::<dyn FnMut(JsValue)>::new(|e: JsValue| {
        let msg = js_sys::Reflect::get(&e, &"message".into()).ok().and_then(|m| m.as_string());
        unavailable(msg.unwrap_or_else(|| "the worker's script did not load".into()));
    });
    worker.set_onmessage(onmessage.as_ref().unchecked_ref());
    worker.set_onerror(onerror.as_ref().unchecked_ref());
    let c = Rc::new(Client {
        worker,
        running: RefCell::new(None),
        sent: RefCell::new(ModelFiles::default()),
        _onmessage: onmessage,
        _onerror: onerror,
    });
    CLIENT.with(|slot| *slot.borrow_mut() = Some(c.clone()));
    Ok(c)
}

/// Whether the worker holds `file` (the page sent that very file before).
fn holds(held: &Option<Rc<Vec<u8>>>, file: &Rc<Vec<u8>>) -> bool {
    held.as_ref().is_some_and(|h| Rc::ptr_eq(h, file))
}

/// The model files of `job` the worker does not hold yet (`None`: it holds both).
fn files_message(job: &InversionJob, client: &Client) -> Result<Option<Message>, String> {
    let mut sent = client.sent.borrow_mut();
    let mut wanted = ModelFiles::of(job);
    let mut arrays: Vec<(&str, JsValue)> = Vec::new();
    for name in ModelFiles::NAMES {
        let held = sent.slot(name);
        if let Some(b) = wanted.slot(name).clone() {
            if !holds(held, &b) {
                arrays.push((name, js_sys::Uint8Array::from(&b[..]).into()));
                *held = Some(b);
            }
        }
    }
    if arrays.is_empty() {
        return Ok(None);
    }
    let json = serde_json::to_string(&ToWorker::Files).map_err(|e| e.to_string())?;
    Ok(Some(object(&json, &arrays)))
}

/// The job as the worker's `Start` message: its settings and photo, and the model files
/// only where the worker lacks them (`files_message` went first, so normally none).
fn start_message(job: &InversionJob, client: &Client) -> Result<Message, String> {
    let t = &job.target;
    let same = |file: &Option<Rc<Vec<u8>>>, held: &Option<Rc<Vec<u8>>>| file.as_ref().is_some_and(|f| holds(held, f));
    let sent = client.sent.borrow().clone();
    let checkpoint_kept = same(&job.checkpoint, &sent.checkpoint);
    let discriminator_kept = same(&job.discriminator, &sent.discriminator);
    let encoder_kept = same(&job.encoder, &sent.encoder);
    let meta = JobMeta {
        cfg: job.cfg.clone(),
        checkpoint_kept,
        discriminator_kept,
        encoder_kept,
        options: job.options.clone(),
        preview_every: job.preview_every,
        start: job.start,
        compute: job.compute,
        world_to_camera: t.view.world_to_camera.to_cols_array(),
        body: t.view.body.clone(),
        res: t.res,
        projection: job.projection.as_ref().map(|p| ProjectionMeta {
            fit: p.fit.clone(),
            width: p.width,
            height: p.height,
            mask_width: p.mask.width,
            mask_height: p.mask.height,
            res: p.res,
            num_betas: p.num_betas,
        }),
    };
    let mut arrays: Vec<(&str, JsValue)> = vec![
        ("target_rgb", js_sys::Float32Array::from(&t.rgb[..]).into()),
        ("target_mask", js_sys::Float32Array::from(&t.mask[..]).into()),
    ];
    if let (Some(b), false) = (&job.checkpoint, checkpoint_kept) {
        arrays.push(("checkpoint", js_sys::Uint8Array::from(&b[..]).into()));
    }
    if let (Some(b), false) = (&job.discriminator, discriminator_kept) {
        arrays.push(("discriminator", js_sys::Uint8Array::from(&b[..]).into()));
    }
    if let (Some(b), false) = (&job.encoder, encoder_kept) {
        arrays.push(("encoder", js_sys::Uint8Array::from(&b[..]).into()));
    }
    if let Some(p) = &job.projection {
        arrays.push(("photo_rgb", js_sys::Float32Array::from(&p.rgb[..]).into()));
        arrays.push(("photo_mask", js_sys::Float32Array::from(&p.mask.data[..]).into()));
    }
    *client.sent.borrow_mut() = ModelFiles::of(job);
    let json = serde_json::to_string(&ToWorker::Start(Box::new(meta))).map_err(|e| e.to_string())?;
    Ok(object(&json, &arrays))
}

/// `{json, …arrays}`.
/// A message and the buffers it hands over (moved, not copied: the arrays are made for it).
struct Message {
    data: JsValue,
    transfer: js_sys::Array,
}

fn object(json: &str, arrays: &[(&str, JsValue)]) -> Message {
    let o = js_sys::Object::new();
    let transfer = js_sys::Array::new();
    // Setting a field of a fresh plain object cannot fail.
    let _ = js_sys::Reflect::set(&o, &"json".into(), &json.into());
    for (k, v) in arrays {
        let _ = js_sys::Reflect::set(&o, &(*k).into(), v);
        if let Ok(b) = js_sys::Reflect::get(v, &"buffer".into()) {
            transfer.push(&b);
        }
    }
    Message { data: o.into(), transfer }
}

fn message_of<T: Serialize>(m: &T, arrays: &[(&str, JsValue)]) -> Message {
    // Our own enums of plain fields serialise.
    object(&serde_json::to_string(m).unwrap_or_else(|e| format!("{{\"error\":\"{e}\"}}")), arrays)
}

/// A message's JSON part (the one field every message has).
fn json_of(data: &JsValue) -> Result<String, String> {
    field(data, "json").and_then(|j| j.as_string()).ok_or_else(|| "a message without its `json` field".to_string())
}

fn field(data: &JsValue, name: &str) -> Option<JsValue> {
    js_sys::Reflect::get(data, &name.into()).ok().filter(|v| !v.is_undefined() && !v.is_null())
}

fn f32_array(data: &JsValue, name: &str) -> Option<Vec<f32>> {
    field(data, name).map(|v| js_sys::Float32Array::new(&v).to_vec())
}

fn u8_array(data: &JsValue, name: &str) -> Option<Vec<u8>> {
    field(data, name).map(|v| js_sys::Uint8Array::new(&v).to_vec())
}

/// A message from the worker.
fn on_message(data: JsValue) {
    let Some(client) = CLIENT.with(|c| c.borrow().clone()) else { return };
    let event = match json_of(&data).and_then(|j| serde_json::from_str::<FromWorker>(&j).map_err(|e| e.to_string())) {
        Ok(e) => e,
        Err(e) => FromWorker::Failed { message: format!("the reconstruction worker's message is unreadable: {e}") },
    };
    let mut slot = client.running.borrow_mut();
    let Some(r) = slot.as_mut() else { return };
    match event {
        FromWorker::Started { start, candidates, perceptual, millis, device, note } => {
            r.fallback = None;
            let e = ReconstructEvent::Started { start, candidates, perceptual, millis, in_worker: true, device, note };
            r.task.push(e, &r.repaint);
        }
        FromWorker::Step { report, done, total, elapsed_ms } => {
            let p = Progress { report, done, total, elapsed_ms };
            r.task.push(ReconstructEvent::Step(Box::new(p)), &r.repaint);
        }
        FromWorker::Preview { done } => {
            if let (Some(rgb), Some(mask)) = (f32_array(&data, "rgb"), f32_array(&data, "mask")) {
                r.task.push(ReconstructEvent::Preview(Box::new(Preview { rgb, mask, done })), &r.repaint);
            }
        }
        FromWorker::Finished { iou, psnr, figures_ms, file_ms, stopped_at } => {
            let Some(r) = slot.take() else { return };
            match u8_array(&data, "bytes") {
                Some(bytes) => {
                    let fit = (iou.unwrap_or(f32::NAN), psnr.unwrap_or(f32::NAN));
                    wasm_bindgen_futures::spawn_local(finish(r, bytes, fit, (figures_ms, file_ms), stopped_at));
                    release_when_idle();
                }
                None => {
                    r.task.push(ReconstructEvent::Failed("the reconstruction worker sent no result".into()), &r.repaint)
                }
            }
        }
        FromWorker::Failed { message } => {
            r.task.push(ReconstructEvent::Failed(format!("the reconstruction failed: {message}")), &r.repaint);
            *slot = None;
            release_when_idle();
        }
        FromWorker::Cancelled => {
            r.task.push(ReconstructEvent::Cancelled, &r.repaint);
            *slot = None;
            release_when_idle();
        }
        FromWorker::Unavailable { message } => {
            drop(slot);
            unavailable(message);
        }
        FromWorker::Fatal { message } => {
            r.task.push(ReconstructEvent::Failed(format!("the reconstruction stopped: {message}")), &r.repaint);
            *slot = None;
            drop(slot);
            drop_client();
        }
    }
}

/// The worker cannot reconstruct here: the running job (if it has not started there) runs on
/// the page, and so do later ones.
fn unavailable(why: String) {
    fall_back_to_page(format!("the reconstruction worker has no WebGPU device ({why})"));
}

/// The worker is unusable (`why`): the running job, if it has not started there, runs on the
/// page, and so do later ones.
fn fall_back_to_page(why: String) {
    let running = CLIENT.with(|c| c.borrow().as_ref().and_then(|c| c.running.borrow_mut().take()));
    worker_unusable(why.clone());
    let Some(r) = running else { return };
    match r.fallback {
        Some(req) => run_on_page(req, r.task, r.repaint),
        None => r.task.push(ReconstructEvent::Failed(format!("the reconstruction stopped: {why}")), &r.repaint),
    }
}

/// The worker's result on the page: rigged as "Open reconstruction…" does, with its figures.
async fn finish(
    r: Running,
    bytes: Vec<u8>,
    fit: (f32, f32),
    (figures_ms, file_ms): (f64, f64),
    stopped_at: Option<usize>,
) {
    // Not in the task that copied the file out of the message.
    crate::task::yield_to_browser().await;
    let t = now_ms();
    let event = match rig_saved(bytes, "the reconstruction", &r.cfg, &r.ctx, &r.device).await {
        Ok(mut done) => {
            done.fit = Some(fit);
            done.stopped_at = stopped_at;
            done.millis = now_ms() - r.t0;
            let rig_ms = now_ms() - t;
            done.finish_ms = figures_ms + file_ms + rig_ms;
            done.finish_detail = format!(
                "worker: final figures {:.1} s, result file {:.1} s; page: rigging {:.1} s",
                figures_ms / 1000.0,
                file_ms / 1000.0,
                rig_ms / 1000.0
            );
            ReconstructEvent::Finished(Box::new(done))
        }
        Err(e) => ReconstructEvent::Failed(format!("the reconstruction failed: {e}")),
    };
    r.task.push(event, &r.repaint);
}

// ---------------------------------------------------------------------------------------------
// The worker's side.

/// What the worker keeps between reconstructions: the body's context (its devices are
/// kept in [`WEBGPU`]).
struct WorkerState {
    ctx: Rc<BodyContext>,
    cfg: GeneratorConfig,
}

thread_local! {
    static STATE: RefCell<Option<Rc<WorkerState>>> = const { RefCell::new(None) };
    /// The worker's WebGPU device and its adapter in words, or why there is none (asked once).
    static WEBGPU: RefCell<Option<Result<(Device, String, bool), String>>> = const { RefCell::new(None) };
    /// The model files of the last job (the page sends each once).
    static FILES: RefCell<Option<ModelFiles>> = const { RefCell::new(None) };
    static CANCEL: Cell<bool> = const { Cell::new(false) };
}

/// Whether this module runs in a worker (no `window`).
pub fn in_worker() -> bool {
    web_sys::window().is_none()
}

/// Post a message to the page (the worker's global `postMessage`).
fn post(m: &FromWorker, arrays: &[(&str, JsValue)]) {
    let global = js_sys::global();
    let posted = js_sys::Reflect::get(&global, &"postMessage".into())
        .and_then(|f| f.dyn_into::<js_sys::Function>())
        .and_then(|f| {
            let m = message_of(m, arrays);
            f.call2(&global, &m.data, &m.transfer)
        });
    if let Err(e) = posted {
        web_sys::console::error_1(&JsValue::from_str(&format!(
            "the reconstruction worker cannot post: {}",
            js_message(&e)
        )));
    }
}

/// A panic in the worker: tell the page before the module aborts.
pub fn post_fatal(message: &str) {
    post(&FromWorker::Fatal { message: message.to_string() }, &[]);
}

/// JS (the worker's script): a message from the page.
#[wasm_bindgen]
pub fn reconstruct_worker_message(data: JsValue) {
    match json_of(&data).and_then(|j| serde_json::from_str::<ToWorker>(&j).map_err(|e| e.to_string())) {
        Ok(ToWorker::Cancel) => CANCEL.with(|c| c.set(true)),
        Ok(ToWorker::Files) => FILES.with(|f| {
            let mut f = f.borrow_mut();
            let f = f.get_or_insert_with(ModelFiles::default);
            for name in ModelFiles::NAMES {
                if let Some(b) = u8_array(&data, name) {
                    *f.slot(name) = Some(Rc::new(b));
                }
            }
        }),
        Ok(ToWorker::Start(meta)) => {
            CANCEL.with(|c| c.set(false));
            wasm_bindgen_futures::spawn_local(run_job(*meta, data));
        }
        Err(e) => post(&FromWorker::Failed { message: format!("the worker cannot read the job: {e}") }, &[]),
    }
}

/// In the worker, progress goes to the page and Cancel comes from it.
struct ToPage;

impl Progressing for ToPage {
    fn push(&self, e: ReconstructEvent) {
        match e {
            ReconstructEvent::Started { start, candidates, perceptual, millis, device, note, .. } => {
                post(&FromWorker::Started { start, candidates, perceptual, millis, device, note }, &[])
            }
            ReconstructEvent::Step(p) => {
                let Progress { report, done, total, elapsed_ms } = *p;
                post(&FromWorker::Step { report, done, total, elapsed_ms }, &[])
            }
            ReconstructEvent::Preview(p) => post(
                &FromWorker::Preview { done: p.done },
                &[
                    ("rgb", js_sys::Float32Array::from(&p.rgb[..]).into()),
                    ("mask", js_sys::Float32Array::from(&p.mask[..]).into()),
                ],
            ),
            // The outcome is the job's own message.
            _ => {}
        }
    }
    fn cancelled(&self) -> bool {
        CANCEL.with(Cell::get)
    }
}

async fn run_job(meta: JobMeta, data: JsValue) {
    let state = match state(&meta.cfg).await {
        Ok(s) => s,
        Err(message) => return post(&FromWorker::Unavailable { message }, &[]),
    };
    let device = match device(meta.compute).await {
        Ok(d) => d,
        Err(message) => return post(&FromWorker::Unavailable { message }, &[]),
    };
    match job(meta, &data, &state, &device).await {
        Ok(Some((bytes, (iou, psnr), figures_ms, file_ms, stopped_at))) => {
            let finite = |x: f32| Some(x).filter(|x| x.is_finite());
            let m = FromWorker::Finished { iou: finite(iou), psnr: finite(psnr), figures_ms, file_ms, stopped_at };
            post(&m, &[("bytes", js_sys::Uint8Array::from(&bytes[..]).into())]);
        }
        Ok(None) => post(&FromWorker::Cancelled, &[]),
        Err(message) => post(&FromWorker::Failed { message }, &[]),
    }
}

/// The result file, IoU and PSNR, milliseconds of the final figures and of the file, and the
/// steps done when cancelled.
type Outcome = (Vec<u8>, (f32, f32), f64, f64, Option<usize>);

async fn job(
    meta: JobMeta,
    data: &JsValue,
    state: &WorkerState,
    device: &(Device, String),
) -> Result<Option<Outcome>, String> {
    let (Some(rgb), Some(mask)) = (f32_array(data, "target_rgb"), f32_array(data, "target_mask")) else {
        return Err("the job came without its photo".into());
    };
    let view = View { world_to_camera: Mat4::from_cols_array(&meta.world_to_camera), body: meta.body };
    let projection = match meta.projection {
        Some(p) => {
            let missing = "the job came without the projection's photo";
            let rgb = f32_array(data, "photo_rgb").ok_or(missing)?;
            let mask = f32_array(data, "photo_mask").ok_or(missing)?;
            let mask = SegmentationMask { width: p.mask_width, height: p.mask_height, data: mask };
            let (width, height, res, num_betas) = (p.width, p.height, p.res, p.num_betas);
            Some(ProjectionSource { fit: p.fit, rgb, width, height, mask, res, num_betas })
        }
        None => None,
    };
    // A file sent now, or the one kept from an earlier job.
    let file = |name: &str, kept: bool| {
        FILES.with(|f| {
            let mut f = f.borrow_mut();
            let s = f.get_or_insert_with(ModelFiles::default).slot(name);
            if !kept {
                *s = u8_array(data, name).map(Rc::new);
            }
            s.clone()
        })
    };
    let checkpoint = file("checkpoint", meta.checkpoint_kept);
    let discriminator = file("discriminator", meta.discriminator_kept);
    let encoder = file("encoder", meta.encoder_kept);
    if meta.checkpoint_kept && checkpoint.is_none() {
        return Err("the worker lost the model's file".into());
    }
    let job = InversionJob {
        checkpoint,
        discriminator,
        cfg: meta.cfg,
        target: InversionTarget { view, res: meta.res, rgb, mask },
        projection,
        options: meta.options,
        preview_every: meta.preview_every,
        start: meta.start,
        encoder,
        compute: meta.compute,
    };
    let Some(inv) = invert(&job, &state.ctx, &device.0, &device.1, &ToPage).await? else { return Ok(None) };
    let t = now_ms();
    let photo = match &job.projection {
        Some(source) => {
            crate::task::yield_to_browser().await;
            source.crop().map(|p| p.source_photo())
        }
        None => None,
    };
    let mut extra = std::collections::BTreeMap::new();
    extra.insert("inversion/source".into(), "the GETAvatar web app".into());
    let bytes = save_inverted_async(&inv.generator, &job.cfg, &inv.styles, photo.as_ref(), &extra)
        .await
        .map_err(|e| format!("cannot write the result: {e}"))?;
    Ok(Some((bytes, inv.fit, inv.finish_ms, now_ms() - t, inv.stopped_at)))
}

/// The worker's body context, made on its first job (and again for another config).
async fn state(cfg: &GeneratorConfig) -> Result<Rc<WorkerState>, String> {
    if let Some(s) = STATE.with(|s| s.borrow().clone()).filter(|s| &s.cfg == cfg) {
        return Ok(s);
    }
    let body = BodyModel::default_body().map_err(|e| format!("the embedded body model: {e}"))?;
    let ctx = Rc::new(BodyContext::new_async(body, cfg).await);
    let s = Rc::new(WorkerState { ctx, cfg: cfg.clone() });
    STATE.with(|slot| *slot.borrow_mut() = Some(s.clone()));
    Ok(s)
}

/// The autodiff device `compute` asks for (`Err`: WebGPU asked for and the worker has none).
/// `Auto` is WebGPU (and the page's device where the worker has none): even on a software
/// adapter (SwiftShader) it is the faster of the two today. NdArray in this wasm module (one
/// thread, no SIMD, optimised for size) took over 4 minutes for a W+ step at 64² where
/// SwiftShader takes 1–2.5 (docs/benchmarks.md); `Cpu` is there to measure it.
/// Also the device in words, for the status.
#[allow(deprecated)] // burn 0.22 marks NdArray deprecated in favour of flex; the project's CPU backend.
async fn device(compute: Compute) -> Result<(Device, String), String> {
    if compute == Compute::Cpu {
        return Ok((Device::ndarray().autodiff(), "CPU (burn NdArray in the worker)".into()));
    }
    if WEBGPU.with(|w| w.borrow().is_none()) {
        let made = webgpu_device().await;
        WEBGPU.with(|w| *w.borrow_mut() = Some(made));
    }
    let webgpu = WEBGPU.with(|w| w.borrow().clone()).unwrap_or_else(|| Err("no WebGPU device".into()));
    let (d, name, software) = webgpu?;
    Ok((d, format!("WebGPU{}: {name}", if software { " (a software adapter)" } else { "" })))
}

/// burn's autodiff device on a WebGPU device of the worker's own (with the adapter's limits,
/// as the page's: burn's kernels need more storage buffers per stage than the defaults), the
/// adapter in words, and whether it is a CPU (software) one.
async fn webgpu_device() -> Result<(Device, String, bool), String> {
    use eframe::egui_wgpu::wgpu;
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = wgpu::Backends::BROWSER_WEBGPU;
    let instance = wgpu::Instance::new(desc);
    let adapter = instance
        .request_adapter(&wgpu::RequestAdapterOptions::default())
        .await
        .map_err(|e| format!("no WebGPU adapter in the worker: {e}"))?;
    let (device, queue) = adapter
        .request_device(&wgpu::DeviceDescriptor {
            label: Some("getavatar reconstruction worker"),
            required_features: adapter.features() - wgpu::Features::MAPPABLE_PRIMARY_BUFFERS,
            required_limits: adapter.limits(),
            ..Default::default()
        })
        .await
        .map_err(|e| format!("no WebGPU device in the worker: {e}"))?;
    let info = adapter.get_info();
    let software = info.device_type == wgpu::DeviceType::Cpu;
    // Browsers may hide the adapter's name.
    let name = match info.name.as_str() {
        "" => format!("{:?} adapter", info.device_type),
        n => format!("{n} ({:?})", info.device_type),
    };
    let setup = WgpuSetup { instance, adapter, device, queue, backend: info.backend };
    let device = Device::wgpu_options()
        .setup(setup)
        .init()
        .map_err(|e| format!("burn cannot use the worker's WebGPU device: {e:?}"))?;
    Ok((device.autodiff(), name, software))
}
