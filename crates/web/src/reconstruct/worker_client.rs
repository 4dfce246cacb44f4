//! The page's side of the reconstruction worker: the inversion's steps each run a backward
//! pass of hundreds of kernel launches in one call (160–360 ms of the UI thread per step,
//! seconds of kernel compiles on the first), which no slicing can split. So the page hands the
//! inversion to a dedicated worker: a second instance of this same wasm module
//! (`www/reconstruct_worker.js`) with its own WebGPU device, the embedded body model and the
//! checkpoint's bytes ([`super::worker`]). It reports its start, steps and previews as it goes,
//! and its result as a reconstruction file (the "Save reconstruction" format: tuned generator,
//! codes, photo) with the avatar it rigged from it, which the page opens as "Open
//! reconstruction…" does, on that avatar instead of a generation of its own. Where a worker
//! cannot have WebGPU (or cannot start), the page runs the reconstruction itself.

use std::cell::{Cell, RefCell};
use std::rc::Rc;

use eframe::egui;
use getavatar_core::burn::tensor::Device;
use getavatar_core::generator::network::GeneratorConfig;
use getavatar_core::generator::pipeline::BodyContext;
use getavatar_core::generator::rigging::RiggedArrays;
use getavatar_core::util::profile::StageProfile;
use wasm_bindgen::prelude::*;
use wasm_bindgen::JsCast;

use super::job::{
    rig_saved, run_on_page, InversionJob, Measured, Preview, Progress, ReconstructEvent, ReconstructRequest,
    ReconstructTask,
};
use super::protocol::{
    f32_array, f32_array_sliced, js_f32_sliced, js_u8_sliced, json_of, message_of, object, rigged_of, u8_array_sliced,
    CallMeta, FromWorker, Identity, JobMeta, Message, ModelFiles, ProjectionMeta, ToWorker, WorkerField,
};
use crate::platform::{js_message, now_ms};

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

/// The page's worker and the reconstruction it runs.
struct Client {
    worker: JsWorker,
    running: RefCell<Option<Running>>,
    /// The model files the worker holds (sent with an earlier job).
    sent: RefCell<ModelFiles>,
    /// The worker has answered: its script runs, so an error from it now is a crash.
    heard: Cell<bool>,
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

/// A result the worker handed over before measuring it: the page rigs and shows it, then the
/// worker renders it for the figures (`ToWorker::Measure`), which end the task.
struct Measuring {
    task: ReconstructTask,
    repaint: egui::Context,
    /// The page has shown the avatar.
    shown: bool,
    /// The figures, when they came before the avatar was shown (the worker stopped).
    figures: Option<Measured>,
}

thread_local! {
    static CLIENT: RefCell<Option<Rc<Client>>> = const { RefCell::new(None) };
    static MEASURING: RefCell<Option<Measuring>> = const { RefCell::new(None) };
    /// A worker could not run a reconstruction here (why): later ones run on the page.
    static NO_WORKER: RefCell<Option<String>> = const { RefCell::new(None) };
    /// Jobs handed to a worker so far: an idle release applies only if none came since.
    static JOBS: Cell<u64> = const { Cell::new(0) };
    /// Generations and new textures handed to the worker ([`generate_in_worker`],
    /// [`colours_in_worker`]): their ids and where their answer goes.
    static GENERATIONS: RefCell<Vec<(u64, AnswerSlot)>> = const { RefCell::new(Vec::new()) };
}

/// The worker's answer to a call (its message, parsed, and the message with its arrays), or
/// why there is none.
type Answer = Result<(FromWorker, JsValue), String>;
type AnswerSlot = Rc<RefCell<Option<Answer>>>;

/// A new identity from the worker: its rigged avatar, milliseconds and stages, or why none.
pub type WorkerGeneration = Result<(RiggedArrays, f64, Option<StageProfile>), String>;

/// Generate a new identity in the worker (started on first use) on its CPU, for the page's
/// Generate on a software WebGPU adapter. `Err`: the worker cannot (none here, busy with a
/// reconstruction, stopped, or the generation failed); the page generates it itself.
pub async fn generate_in_worker(
    cfg: &GeneratorConfig,
    checkpoint: &Rc<Vec<u8>>,
    seeds: (u64, u64),
    psi: f32,
) -> WorkerGeneration {
    let ask = |id, checkpoint_kept| {
        ToWorker::Generate(CallMeta { id, cfg: cfg.clone(), checkpoint_kept, ask: Identity { seeds, psi } })
    };
    match call(ask, checkpoint, Vec::new()).await? {
        (FromWorker::Generated { millis, stages, .. }, data) => {
            let arrays =
                rigged_of(&data).await.map_err(|missing| format!("the worker sent its avatar without `{missing}`"))?;
            Ok((arrays, millis, stages))
        }
        _ => Err("the worker answered Generate with another message".into()),
    }
}

/// The texture field of `field` (a generated identity's seeds and ψ, or a reconstruction's
/// file `result`) at canonical `points`, computed in the worker on its CPU (a new texture, a
/// bake, the per-pixel view): linear RGB per point and the milliseconds. `Err` as for
/// [`generate_in_worker`].
pub async fn colours_in_worker(
    cfg: &GeneratorConfig,
    checkpoint: &Rc<Vec<u8>>,
    field: &WorkerField,
    result: Option<&Rc<Vec<u8>>>,
    points: &[glam::Vec3],
) -> Result<(Vec<glam::Vec3>, f64), String> {
    let flat: Vec<f32> = points.iter().flat_map(|p| p.to_array()).collect();
    let mut arrays = vec![("points", JsValue::from(js_f32_sliced(&flat).await))];
    drop(flat);
    match (field, result) {
        (WorkerField::Result { .. }, Some(bytes)) => {
            arrays.push(("result", js_u8_sliced(bytes).await.into()));
        }
        (WorkerField::Result { .. }, None) => return Err("the reconstruction's file is not on the page".into()),
        (WorkerField::Seeds { .. }, _) => {}
    }
    let field = field.clone();
    let ask = |id, checkpoint_kept| ToWorker::Colours(CallMeta { id, cfg: cfg.clone(), checkpoint_kept, ask: field });
    match call(ask, checkpoint, arrays).await? {
        (FromWorker::Coloured { millis, .. }, data) => {
            let rgb = f32_array_sliced(&data, "colors").await.ok_or("the worker sent no colours")?;
            if rgb.len() != 3 * points.len() || rgb.iter().any(|x| !x.is_finite()) {
                return Err(format!("the worker sent {} colour values for {} points", rgb.len(), points.len()));
            }
            Ok((rgb.chunks_exact(3).map(|c| glam::Vec3::new(c[0], c[1], c[2])).collect(), millis))
        }
        _ => Err("the worker answered Colours with another message".into()),
    }
}

/// Start the worker and have it get ready for Generate (the body's context, the model, the
/// canonical posed grid) while the page is idle: its milliseconds and how it had the body's
/// context (read from the browser's cache or built), or why not.
pub async fn warm_worker(cfg: &GeneratorConfig, checkpoint: &Rc<Vec<u8>>) -> Result<(f64, String), String> {
    let ask = |id, checkpoint_kept| ToWorker::Warm(CallMeta { id, cfg: cfg.clone(), checkpoint_kept, ask: () });
    match call(ask, checkpoint, Vec::new()).await? {
        (FromWorker::Warmed { millis, body_context, .. }, _) => Ok((millis, body_context)),
        _ => Err("the worker answered Warm with another message".into()),
    }
}

/// Ask the worker (`ask(id, whether it holds the checkpoint)`, with `arrays`, and the
/// checkpoint where it lacks it) and await its answer.
async fn call(
    ask: impl FnOnce(u64, bool) -> ToWorker,
    checkpoint: &Rc<Vec<u8>>,
    mut arrays: Vec<(&str, JsValue)>,
) -> Answer {
    if let Some(why) = NO_WORKER.with(|n| n.borrow().clone()) {
        return Err(why);
    }
    let client = client()?;
    // The checkpoint's copy is sliced, so the worker may have ended or taken a
    // reconstruction meanwhile: both are checked after it.
    let checkpoint_kept = holds(&client.sent.borrow().checkpoint, checkpoint);
    if !checkpoint_kept {
        arrays.push(("checkpoint", js_u8_sliced(checkpoint).await.into()));
    }
    if !CLIENT.with(|c| c.borrow().as_ref().is_some_and(|now| Rc::ptr_eq(now, &client))) {
        return Err("the worker stopped".into());
    }
    if client.running.borrow().is_some() {
        return Err("the worker is reconstructing".into());
    }
    let id = JOBS.with(|j| {
        j.set(j.get() + 1);
        j.get()
    });
    let json = serde_json::to_string(&ask(id, checkpoint_kept)).map_err(|e| e.to_string())?;
    let m = object(&json, &arrays);
    client.worker.post_message(&m.data, &m.transfer).map_err(|e| js_message(&e))?;
    client.sent.borrow_mut().checkpoint = Some(checkpoint.clone());
    drop(client);
    let slot: AnswerSlot = Rc::default();
    GENERATIONS.with(|g| g.borrow_mut().push((id, slot.clone())));
    let answer = loop {
        if let Some(a) = slot.borrow_mut().take() {
            break a;
        }
        crate::task::sleep_ms(20).await;
    };
    release_when_idle();
    answer
}

/// The answer to call `id` (from the worker, or its end).
fn answered(id: u64, answer: Answer) {
    let slot = GENERATIONS.with(|g| {
        let mut g = g.borrow_mut();
        g.iter().position(|(i, _)| *i == id).map(|k| g.swap_remove(k).1)
    });
    if let Some(slot) = slot {
        *slot.borrow_mut() = Some(answer);
    }
}

/// End the worker if it is still idle after [`IDLE_RELEASE_MS`].
fn release_when_idle() {
    let job = JOBS.with(Cell::get);
    let release = Closure::once_into_js(move || {
        let idle = CLIENT.with(|c| c.borrow().as_ref().is_some_and(|c| c.running.borrow().is_none()))
            && MEASURING.with(|m| m.borrow().is_none())
            && GENERATIONS.with(|g| g.borrow().is_empty());
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
        // Shown and being measured: the avatar stays, without its figures.
        if MEASURING.with(|m| m.borrow().as_ref().is_some_and(|m| m.task.same(&worker_task))) {
            tell_worker(&ToWorker::Cancel);
            measured(Measured { figures: Err("not measured: cancelled".into()), millis: 0.0 });
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
    for (id, _) in GENERATIONS.with(|g| g.borrow().clone()) {
        answered(id, Err("the worker stopped".into()));
    }
    if MEASURING.with(|m| m.borrow().is_some()) {
        measured(Measured { figures: Err("not measured: the worker stopped".into()), millis: 0.0 });
    }
}

/// The figures of the result being measured: its task's outcome once the avatar is shown.
fn measured(m: Measured) {
    let Some(mut ms) = MEASURING.with(|s| s.borrow_mut().take()) else { return };
    if ms.shown {
        ms.task.push(ReconstructEvent::Measured(Box::new(m)), &ms.repaint);
    } else {
        ms.figures = Some(m);
        MEASURING.with(|s| *s.borrow_mut() = Some(ms));
    }
}

/// The page has shown the result being measured (`rigged`: else it failed, which ended the
/// task): the worker measures it now (or not at all).
fn shown(task: &ReconstructTask, rigged: bool) {
    let Some(mut ms) = MEASURING.with(|s| s.borrow_mut().take()).filter(|m| m.task.same(task)) else { return };
    if !rigged {
        return tell_worker(&ToWorker::Cancel);
    }
    ms.shown = true;
    match ms.figures.take() {
        Some(m) => ms.task.push(ReconstructEvent::Measured(Box::new(m)), &ms.repaint),
        None => {
            MEASURING.with(|s| *s.borrow_mut() = Some(ms));
            tell_worker(&ToWorker::Measure);
        }
    }
}

/// A message without arrays to the worker, if there is one (else nothing waits for it).
fn tell_worker(m: &ToWorker) {
    if let Some(c) = CLIENT.with(|c| c.borrow().clone()) {
        let m = message_of(m, &[]);
        if let Err(e) = c.worker.post_message(&m.data, &m.transfer) {
            // The worker is gone: its `onerror` or the next job says so.
            web_sys::console::warn_1(&JsValue::from_str(&format!("the reconstruction worker: {}", js_message(&e))));
        }
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
    // The worker's script failed to load, or the worker crashed.
    let onerror = Closure::<dyn FnMut(JsValue)>::new(|e: JsValue| {
        let msg = js_sys::Reflect::get(&e, &"message".into()).ok().and_then(|m| m.as_string());
        worker_error(msg.unwrap_or_else(|| "the worker's script did not load".into()));
    });
    worker.set_onmessage(onmessage.as_ref().unchecked_ref());
    worker.set_onerror(onerror.as_ref().unchecked_ref());
    let c = Rc::new(Client {
        worker,
        running: RefCell::new(None),
        sent: RefCell::new(ModelFiles::default()),
        heard: Cell::new(false),
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
        start_note: job.start_note.clone(),
        compute: job.compute,
        world_to_camera: t.view.world_to_camera.to_cols_array(),
        body: t.view.body.clone(),
        res: t.res,
        measure_after_result: job.measure_after_result,
        figures: job.figures,
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

/// A message from the worker.
fn on_message(data: JsValue) {
    let Some(client) = CLIENT.with(|c| c.borrow().clone()) else { return };
    client.heard.set(true);
    let event = match json_of(&data).and_then(|j| serde_json::from_str::<FromWorker>(&j).map_err(|e| e.to_string())) {
        Ok(e) => e,
        Err(e) => FromWorker::Failed { message: format!("the reconstruction worker's message is unreadable: {e}") },
    };
    match event {
        FromWorker::Generated { id, .. } | FromWorker::Coloured { id, .. } | FromWorker::Warmed { id, .. } => {
            return answered(id, Ok((event, data)))
        }
        FromWorker::CallFailed { id, message } => return answered(id, Err(message)),
        _ => {}
    }
    if let FromWorker::Figures { iou, psnr, millis, error } = event {
        let images = f32_array(&data, "rgb").zip(f32_array(&data, "mask"));
        let figures = match (error, images) {
            (Some(e), _) => Err(format!("not measured: {e}")),
            (None, None) => Err("not measured: the worker sent no render".into()),
            (None, Some((rgb, mask))) => {
                let fit = (iou.unwrap_or(f32::NAN), psnr.unwrap_or(f32::NAN));
                Ok((fit, Preview { rgb, mask, done: 0 }))
            }
        };
        return measured(Measured { figures, millis });
    }
    // The worker stopped while it measured a result already handed over.
    if matches!(event, FromWorker::Fatal { .. }) && client.running.borrow().is_none() {
        return drop_client();
    }
    // Without a reconstruction, a failure is a call the worker could not read (no id to
    // answer): the calls waiting get it rather than waiting for ever.
    if let (FromWorker::Failed { message }, true) = (&event, client.running.borrow().is_none()) {
        for (id, _) in GENERATIONS.with(|g| g.borrow().clone()) {
            answered(id, Err(message.clone()));
        }
        return;
    }
    let mut slot = client.running.borrow_mut();
    let Some(r) = slot.as_mut() else { return };
    match event {
        FromWorker::Started { start, candidates, perceptual, millis, device, note, garment, garment_codes } => {
            r.fallback = None;
            let e = ReconstructEvent::Started {
                start,
                candidates,
                perceptual,
                millis,
                in_worker: true,
                device,
                note,
                garment,
                garment_codes,
            };
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
        FromWorker::Finished { iou, psnr, figures_ms, file_ms, rig_ms, stopped_at, measuring, refit } => {
            let Some(r) = slot.take() else { return };
            let fit = (!measuring).then(|| (iou.unwrap_or(f32::NAN), psnr.unwrap_or(f32::NAN)));
            if measuring {
                let (task, repaint) = (r.task.clone(), r.repaint.clone());
                let m = Measuring { task, repaint, shown: false, figures: None };
                MEASURING.with(|s| *s.borrow_mut() = Some(m));
            }
            // The arrays are copied out of the message in `finish`, in slices.
            let result =
                WorkerResult { data, fit, stopped_at, refit: refit.map(|f| *f), ms: (figures_ms, file_ms, rig_ms) };
            wasm_bindgen_futures::spawn_local(finish(r, result));
            release_when_idle();
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
        FromWorker::Figures { .. }
        | FromWorker::Generated { .. }
        | FromWorker::Coloured { .. }
        | FromWorker::Warmed { .. }
        | FromWorker::CallFailed { .. } => {}
        FromWorker::Fatal { message } => {
            r.task.push(ReconstructEvent::Failed(format!("the reconstruction stopped: {message}")), &r.repaint);
            *slot = None;
            drop(slot);
            drop_client();
        }
    }
}

/// An error from the worker outside a job's own handling. Before it ever answered, its script
/// did not load: no worker from now on ([`unavailable`]). After, it crashed (a wasm trap, e.g.
/// out of its 4 GB): the running job fails saying so, not taken over by the page (on a
/// software adapter 16× slower there), and the next job or call starts a fresh worker.
fn worker_error(why: String) {
    let Some(client) = CLIENT.with(|c| c.borrow().clone()) else { return };
    if !client.heard.get() {
        return unavailable(why);
    }
    let running = client.running.borrow_mut().take();
    drop(client);
    let why = format!("the reconstruction worker stopped ({why})");
    web_sys::console::warn_1(&JsValue::from_str(&format!("{why}; the next job starts a new one")));
    drop_client();
    if let Some(r) = running {
        r.task.push(ReconstructEvent::Failed(format!("{why}; Reconstruct again starts a new one")), &r.repaint);
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

/// What the worker hands over at the end of a job.
struct WorkerResult {
    /// The message with the result file (`bytes`) and the avatar the worker rigged from it.
    data: JsValue,
    /// Its figures (None: they follow).
    fit: Option<(f32, f32)>,
    stopped_at: Option<usize>,
    refit: Option<getavatar_core::body::body_fit::fit::BodyFit>,
    /// Milliseconds of the worker's final figures, result file, rigging.
    ms: (f64, f64, f64),
}

/// The worker's result on the page: opened as "Open reconstruction…" does, on the avatar the
/// worker rigged, with its figures (None: they follow).
async fn finish(r: Running, w: WorkerResult) {
    let WorkerResult { data, fit, stopped_at, refit, ms: (figures_ms, file_ms, worker_rig_ms) } = w;
    // Not in the task that received the message.
    crate::task::yield_to_browser().await;
    let copied = async {
        let bytes = u8_array_sliced(&data, "bytes").await.ok_or("the reconstruction worker sent no result")?;
        let rigged = rigged_of(&data)
            .await
            .map_err(|missing| format!("the reconstruction worker sent its avatar without `{missing}`"))?;
        Ok::<_, String>((bytes, rigged))
    };
    let (bytes, rigged) = match copied.await {
        Ok(c) => c,
        Err(e) => {
            r.task.push(ReconstructEvent::Failed(e), &r.repaint);
            return shown(&r.task, false);
        }
    };
    drop(data);
    let t = now_ms();
    let event = match rig_saved(bytes, Some(rigged), "the reconstruction", &r.cfg, &r.ctx, &r.device).await {
        Ok(mut done) => {
            (done.fit, done.measuring) = (fit, fit.is_none());
            (done.stopped_at, done.refit) = (stopped_at, refit);
            done.millis = now_ms() - r.t0;
            let rig_ms = now_ms() - t;
            done.finish_ms = figures_ms + file_ms + rig_ms;
            let build = std::mem::take(&mut done.finish_detail);
            // A guess shown before it is measured (`InversionJob::figures` off) has no figures.
            let figures = match fit {
                Some((iou, _)) if iou.is_finite() => format!("final figures {:.1} s, ", figures_ms / 1000.0),
                _ => String::new(),
            };
            done.finish_ms += worker_rig_ms;
            done.finish_detail = format!(
                "worker: {figures}rigging {:.1} s, result file {:.1} s; page: the avatar {:.1} s ({build})",
                worker_rig_ms / 1000.0,
                file_ms / 1000.0,
                rig_ms / 1000.0
            );
            ReconstructEvent::Finished(Box::new(done))
        }
        Err(e) => ReconstructEvent::Failed(format!("the reconstruction failed: {e}")),
    };
    let rigged = matches!(event, ReconstructEvent::Finished(_));
    r.task.push(event, &r.repaint);
    shown(&r.task, rigged);
}
