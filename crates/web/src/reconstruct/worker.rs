//! The worker's side of the reconstruction worker ([`super::worker_client`] is the page's):
//! [`reconstruct_worker_message`] receives a job, runs the inversion on the worker's own WebGPU
//! device (or NdArray) and posts its start, steps, previews, the result file and the avatar
//! rigged from it back to the page. On a software adapter it also generates the page's new
//! identities (`ToWorker::Generate`) and answers its texture-field queries (`ToWorker::Colours`:
//! new textures, bakes, the per-pixel view) on NdArray.

use std::cell::{Cell, RefCell};
use std::rc::Rc;

use getavatar_core::body::body_fit::landmarks::SegmentationMask;
use getavatar_core::body::body_model::BodyModel;
use getavatar_core::burn::tensor::wgpu::WgpuSetup;
use getavatar_core::burn::tensor::Device;
use getavatar_core::generator::checkpoint::load_generator_and_modes;
use getavatar_core::generator::checkpoint::{inverted_of, parse_safetensors_async, save_inverted_async};
use getavatar_core::generator::network::GeneratorConfig;
use getavatar_core::generator::pipeline::{seed_latents, BodyContext, Generator, LatentModes, Styles};
use getavatar_core::generator::rigging::{
    bake_queries, generate_rigged_async, generate_rigged_from_planes_async, RiggedArrays,
};
use getavatar_core::reconstruction::inversion::InversionTarget;
use getavatar_core::render::camera::View;
use glam::Mat4;
use wasm_bindgen::prelude::*;
use wasm_bindgen::JsCast;

use super::job::{
    invert, measure, Compute, InversionJob, Inverted, KnownGuess, Progress, Progressing, ProjectionSource,
    ReconstructEvent,
};
use super::protocol::{
    f32_array, json_of, message_of, rigged_arrays, u8_array, ColoursMeta, FromWorker, GenerateMeta, JobMeta,
    ModelFiles, ToWorker, WarmMeta, WorkerField,
};
use crate::platform::{js_message, now_ms};

/// What the worker keeps between reconstructions: the body's context (its devices are
/// kept in [`WEBGPU`]) and how it was had (read from the browser's cache or built).
struct WorkerState {
    ctx: Rc<BodyContext>,
    cfg: GeneratorConfig,
    how: String,
}

/// The worker's WebGPU device, its adapter in words and whether the adapter is a software one,
/// or why there is none.
type WebGpu = Result<(Device, String, bool), String>;

thread_local! {
    static STATE: RefCell<Option<Rc<WorkerState>>> = const { RefCell::new(None) };
    /// The worker's WebGPU device and its adapter in words, or why there is none (asked once).
    static WEBGPU: RefCell<Option<WebGpu>> = const { RefCell::new(None) };
    /// The model files of the last job (the page sends each once).
    static FILES: RefCell<Option<ModelFiles>> = const { RefCell::new(None) };
    static CANCEL: Cell<bool> = const { Cell::new(false) };
    /// The encoder's guess of the last job that showed it first (`figures` off), for the
    /// garment choice of the job after it.
    static GUESS: RefCell<Option<Rc<KnownGuess>>> = const { RefCell::new(None) };
    /// The page shows the result handed over: measure it (`ToWorker::Measure`).
    static MEASURE: Cell<bool> = const { Cell::new(false) };
    /// A warm-up (`ToWorker::Warm`) runs: other work waits for it rather than doing the same
    /// (the body's context, the model, the posed grid) beside it.
    static WARMING: Cell<bool> = const { Cell::new(false) };
}

/// Wait while a warm-up runs.
async fn after_warm_up() {
    while WARMING.with(Cell::get) {
        crate::task::sleep_ms(20).await;
    }
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
        Ok(ToWorker::Measure) => MEASURE.with(|m| m.set(true)),
        Ok(ToWorker::Files) => FILES.with(|f| {
            let mut f = f.borrow_mut();
            let f = f.get_or_insert_with(ModelFiles::default);
            for name in ModelFiles::NAMES {
                if let Some(b) = u8_array(&data, name) {
                    *f.slot(name) = Some(Rc::new(b));
                }
            }
        }),
        Ok(ToWorker::Generate(meta)) => wasm_bindgen_futures::spawn_local(generate_job(meta, data)),
        Ok(ToWorker::Colours(meta)) => wasm_bindgen_futures::spawn_local(colours_job(meta, data)),
        Ok(ToWorker::Warm(meta)) => wasm_bindgen_futures::spawn_local(warm_job(meta, data)),
        Ok(ToWorker::Start(meta)) => {
            CANCEL.with(|c| c.set(false));
            MEASURE.with(|m| m.set(false));
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
            ReconstructEvent::Started {
                start,
                candidates,
                perceptual,
                millis,
                device,
                note,
                garment,
                garment_codes,
                ..
            } => post(
                &FromWorker::Started { start, candidates, perceptual, millis, device, note, garment, garment_codes },
                &[],
            ),
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
    after_warm_up().await;
    let state = match state(&meta.cfg).await {
        Ok(s) => s,
        Err(message) => return post(&FromWorker::Unavailable { message }, &[]),
    };
    let device = match device(meta.compute).await {
        Ok(d) => d,
        Err(message) => return post(&FromWorker::Unavailable { message }, &[]),
    };
    let finite = |x: f32| Some(x).filter(|x| x.is_finite());
    match job(meta, &data, &state, &device).await {
        Ok(Some(Outcome { bytes, inv, file_ms, rigged, rig_ms })) => {
            let (iou, psnr) = inv.fit.unwrap_or((f32::NAN, f32::NAN));
            let m = FromWorker::Finished {
                iou: finite(iou),
                psnr: finite(psnr),
                figures_ms: inv.finish_ms,
                file_ms,
                rig_ms,
                stopped_at: inv.stopped_at,
                measuring: inv.unmeasured.is_some(),
                refit: inv.refit.clone().map(Box::new),
            };
            let mut arrays = rigged_arrays(&rigged);
            drop(rigged);
            arrays.push(("bytes", js_sys::Uint8Array::from(&bytes[..]).into()));
            drop(bytes);
            post(&m, &arrays);
            // Measured once the page has shown it (Cancel: not at all).
            if let Some((inv, target)) = inv.unmeasured {
                while !MEASURE.with(Cell::get) {
                    if CANCEL.with(Cell::get) {
                        return;
                    }
                    crate::task::sleep_ms(50).await;
                }
                let t = now_ms();
                match measure(&inv, &target).await {
                    Ok(((iou, psnr), p)) => post(
                        &FromWorker::Figures {
                            iou: finite(iou),
                            psnr: finite(psnr),
                            millis: now_ms() - t,
                            error: None,
                        },
                        &[
                            ("rgb", js_sys::Float32Array::from(&p.rgb[..]).into()),
                            ("mask", js_sys::Float32Array::from(&p.mask[..]).into()),
                        ],
                    ),
                    Err(e) => {
                        let m = FromWorker::Figures { iou: None, psnr: None, millis: now_ms() - t, error: Some(e) };
                        post(&m, &[])
                    }
                }
            }
        }
        Ok(None) => post(&FromWorker::Cancelled, &[]),
        Err(message) => post(&FromWorker::Failed { message }, &[]),
    }
}

/// A job's result.
struct Outcome<'a> {
    /// The result file.
    bytes: Vec<u8>,
    /// The inversion's outcome (figures, or the inverter that measures them after the file
    /// is sent).
    inv: Inverted<'a>,
    /// Milliseconds of the file.
    file_ms: f64,
    /// The avatar extracted and rigged here, so the page shows it without a generation of its
    /// own (on a software adapter the page's WebGPU device takes 10+ s for it; the worker's
    /// NdArray a few), and its milliseconds.
    rigged: RiggedArrays,
    rig_ms: f64,
}

async fn job<'a>(
    meta: JobMeta,
    data: &JsValue,
    state: &'a WorkerState,
    device: &(Device, String),
) -> Result<Option<Outcome<'a>>, String> {
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
    let file = |name: &str, kept: bool| file(data, name, kept);
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
        start_note: meta.start_note,
        encoder,
        compute: meta.compute,
        measure_after_result: meta.measure_after_result,
        figures: meta.figures,
    };
    let known = GUESS.with(|g| g.borrow_mut().take());
    let Some(mut inv) = invert(&job, &state.ctx, &device.0, &device.1, &ToPage, true, known.as_deref()).await? else {
        return Ok(None);
    };
    let t = now_ms();
    let rigged = match inv.rigged.take() {
        Some(rigged) => rigged,
        None => generate_rigged_async(&inv.generator, &state.ctx, &inv.styles, &device.0)
            .await
            .map_err(|e| format!("cannot extract the avatar: {e}"))?,
    };
    if rigged.canonical.mesh.faces.is_empty() {
        return Err("the reconstructed generator produced an empty surface".into());
    }
    let rig_ms = now_ms() - t;
    // The guess shown first: the job after it weighs the garment codes against the same avatar.
    if !job.figures && job.options.steps + job.options.pti_steps == 0 {
        let codes = KnownGuess::codes_of(&inv.styles).await?;
        let checkpoint = job.checkpoint.clone();
        GUESS.with(|g| *g.borrow_mut() = Some(Rc::new(KnownGuess { checkpoint, codes, rigged: rigged.clone() })));
    }
    let rigged = rigged.to_arrays();
    let t = now_ms();
    let photo = match inv.projection(&job) {
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
    Ok(Some(Outcome { bytes, inv, file_ms: now_ms() - t, rigged, rig_ms }))
}

/// A model file sent with `data` now, or the one kept from an earlier job (`kept`).
fn file(data: &JsValue, name: &str, kept: bool) -> Option<Rc<Vec<u8>>> {
    FILES.with(|f| {
        let mut f = f.borrow_mut();
        let s = f.get_or_insert_with(ModelFiles::default).slot(name);
        if !kept {
            *s = u8_array(data, name).map(Rc::new);
        }
        s.clone()
    })
}

/// The page's Generate on this worker's CPU: the avatar, or why not.
async fn generate_job(meta: GenerateMeta, data: JsValue) {
    after_warm_up().await;
    let id = meta.id;
    match generate(meta, &data).await {
        Ok((rigged, millis, stages)) => post(&FromWorker::Generated { id, millis, stages }, &rigged_arrays(&rigged)),
        Err(message) => post(&FromWorker::CallFailed { id, message }, &[]),
    }
}

/// Get ready for the page's first Generate: the body's context, the model, the canonical
/// pose's posed grid (kept for the worker's life).
async fn warm_job(meta: WarmMeta, data: JsValue) {
    let (id, t0) = (meta.id, now_ms());
    WARMING.with(|w| w.set(true));
    let warmed = async {
        let state = state(&meta.cfg).await?;
        model(&meta.cfg, meta.checkpoint_kept, &data)?;
        Ok::<_, String>(state.how.clone())
    };
    let warmed = warmed.await;
    WARMING.with(|w| w.set(false));
    match warmed {
        Ok(body_context) => post(&FromWorker::Warmed { id, millis: now_ms() - t0, body_context }, &[]),
        Err(message) => post(&FromWorker::CallFailed { id, message }, &[]),
    }
}

/// The page's texture-field query on this worker's CPU (a New texture, a bake, the per-pixel
/// view): the colours, or why not.
async fn colours_job(meta: ColoursMeta, data: JsValue) {
    after_warm_up().await;
    let id = meta.id;
    let t0 = now_ms();
    match colours(meta, &data).await {
        Ok(rgb) => {
            let colors: JsValue = js_sys::Float32Array::from(&rgb[..]).into();
            post(&FromWorker::Coloured { id, millis: now_ms() - t0 }, &[("colors", colors)])
        }
        Err(message) => post(&FromWorker::CallFailed { id, message }, &[]),
    }
}

/// The page's model on NdArray here: its generator and latent modes.
type Model = Rc<(Generator, Option<LatentModes>)>;

/// A loaded model with the config and file it came from.
type LoadedModel = (GeneratorConfig, Rc<Vec<u8>>, Model);

thread_local! {
    /// The page's model as last loaded, with the file and config it came from (loading it
    /// took a few hundred ms of every Generate and texture call).
    static MODEL: RefCell<Option<LoadedModel>> = const { RefCell::new(None) };
}

/// The generator of the page's model on NdArray here, and its latent modes (loaded once per
/// file the page sends).
#[allow(deprecated)] // burn 0.22 marks NdArray deprecated in favour of flex; the project's CPU backend.
fn model(cfg: &GeneratorConfig, kept: bool, data: &JsValue) -> Result<Model, String> {
    let checkpoint = file(data, "checkpoint", kept).ok_or("the worker lost the model's file")?;
    let cached = MODEL.with(|m| {
        m.borrow().as_ref().filter(|(c, b, _)| c == cfg && Rc::ptr_eq(b, &checkpoint)).map(|(_, _, m)| m.clone())
    });
    if let Some(m) = cached {
        return Ok(m);
    }
    let loaded =
        Rc::new(load_generator_and_modes(&checkpoint, cfg, &Device::ndarray()).map_err(|e| format!("the model: {e}"))?);
    MODEL.with(|m| *m.borrow_mut() = Some((cfg.clone(), checkpoint, loaded.clone())));
    Ok(loaded)
}

/// The styles of seeds and ψ.
#[allow(deprecated)] // burn 0.22 marks NdArray deprecated in favour of flex; the project's CPU backend.
fn styles(g: &Generator, modes: Option<&LatentModes>, cfg: &GeneratorConfig, seeds: (u64, u64), psi: f32) -> Styles {
    let (zg, zt) = seed_latents(cfg, seeds.0, seeds.1, &Device::ndarray());
    g.styles_with(zg, zt, psi, modes)
}

/// A texture field on NdArray: the field's generator, styles and triplanes, kept for the
/// next query of the same field (a bake follows a generation; the per-pixel view asks again
/// on every change of view).
struct CachedField {
    field: WorkerField,
    cfg: GeneratorConfig,
    generator: Field,
    styles: Styles,
    planes: getavatar_core::generator::network::synthesis::Triplanes,
}

/// A texture field's generator: the page's model's, or a reconstruction's tuned one.
enum Field {
    Model(Model),
    Tuned(Box<Generator>),
}

impl Field {
    fn get(&self) -> &Generator {
        match self {
            Field::Model(m) => &m.0,
            Field::Tuned(g) => g,
        }
    }
}

thread_local! {
    static FIELD: RefCell<Option<Rc<CachedField>>> = const { RefCell::new(None) };
}

/// The texture field `meta` names: the cached one, or built from the model (seeds) or the
/// reconstruction's file (the array `result`).
#[allow(deprecated)] // burn 0.22 marks NdArray deprecated in favour of flex; the project's CPU backend.
async fn field(meta: &ColoursMeta, data: &JsValue) -> Result<Rc<CachedField>, String> {
    // The model (also kept for later calls when only a reconstruction's file is asked about).
    let model = match meta.ask {
        WorkerField::Seeds { .. } => Some(model(&meta.cfg, meta.checkpoint_kept, data)?),
        WorkerField::Result { .. } => {
            let _ = file(data, "checkpoint", meta.checkpoint_kept);
            None
        }
    };
    let cached = FIELD.with(|f| f.borrow().clone()).filter(|c| {
        c.field == meta.ask
            && c.cfg == meta.cfg
            && match (&c.generator, &model) {
                // Another model (a new file) draws other avatars from the same seeds.
                (Field::Model(a), Some(b)) => Rc::ptr_eq(a, b),
                (Field::Tuned(_), None) => true,
                _ => false,
            }
    });
    if let Some(c) = cached {
        return Ok(c);
    }
    let (generator, styles) = match (&meta.ask, model) {
        (WorkerField::Seeds { seeds, psi }, Some(m)) => {
            let s = styles(&m.0, m.1.as_ref(), &meta.cfg, *seeds, *psi);
            (Field::Model(m), s)
        }
        _ => {
            let bytes = u8_array(data, "result").ok_or("the call came without the reconstruction's file")?;
            let st = parse_safetensors_async(&bytes).await.map_err(|e| format!("the reconstruction's file: {e}"))?;
            let inv = inverted_of(st, &meta.cfg, &Device::ndarray())
                .map_err(|e| format!("the reconstruction's file: {e}"))?;
            (Field::Tuned(Box::new(inv.generator)), inv.styles)
        }
    };
    crate::task::yield_to_browser().await;
    let planes = generator.get().triplanes_async(&styles).await;
    let c = Rc::new(CachedField { field: meta.ask.clone(), cfg: meta.cfg.clone(), generator, styles, planes });
    FIELD.with(|f| *f.borrow_mut() = Some(c.clone()));
    Ok(c)
}

/// The texture field at the points of `data`'s array `points`, as linear RGB floats (in the
/// bake's batches, so a 1024² bake's half a million points never share one tensor).
#[allow(deprecated)] // burn 0.22 marks NdArray deprecated in favour of flex; the project's CPU backend.
async fn colours(meta: ColoursMeta, data: &JsValue) -> Result<Vec<f32>, String> {
    let flat = f32_array(data, "points").ok_or("the request came without its points")?;
    if flat.len() % 3 != 0 || flat.iter().any(|x| !x.is_finite()) {
        return Err(format!("{} numbers are not points", flat.len()));
    }
    let points: Vec<glam::Vec3> = flat.chunks_exact(3).map(|c| glam::Vec3::new(c[0], c[1], c[2])).collect();
    drop(flat);
    let f = field(&meta, data).await?;
    let colors = bake_queries(f.generator.get(), &f.planes, &f.styles, &points, &Device::ndarray())
        .await
        .map_err(|e| format!("the texture field: {e}"))?;
    Ok(colors.iter().flat_map(|c| c.to_array()).collect())
}

/// A new identity, extracted and rigged on burn's NdArray in this worker (a software WebGPU
/// adapter's page takes 8–10 s for it, mostly DMTet's GPU wait; docs/benchmarks.md), its
/// milliseconds (the model's loading included) and its stages.
#[allow(deprecated)] // burn 0.22 marks NdArray deprecated in favour of flex; the project's CPU backend.
async fn generate(
    meta: GenerateMeta,
    data: &JsValue,
) -> Result<(RiggedArrays, f64, Option<getavatar_core::util::profile::StageProfile>), String> {
    use getavatar_core::util::profile;
    let t0 = now_ms();
    let state = state(&meta.cfg).await?;
    let dev = Device::ndarray();
    let m = model(&meta.cfg, meta.checkpoint_kept, data)?;
    crate::task::yield_to_browser().await;
    profile::start(now_ms);
    profile::stage("mapping");
    let styles = styles(&m.0, m.1.as_ref(), &meta.cfg, meta.ask.seeds, meta.ask.psi);
    profile::stage("synthesis");
    let planes = m.0.triplanes_async(&styles).await;
    let rigged = generate_rigged_from_planes_async(&m.0, &state.ctx, &styles, &planes, &dev).await;
    let stages = profile::finish();
    let rigged = rigged.map_err(|e| format!("generation failed: {e}"))?;
    if rigged.canonical.mesh.faces.is_empty() {
        return Err("the generator produced an empty surface".into());
    }
    // This avatar's texture field, for the bake or view that may follow.
    let field = WorkerField::Seeds { seeds: meta.ask.seeds, psi: meta.ask.psi };
    let c = CachedField { field, cfg: meta.cfg.clone(), generator: Field::Model(m), styles, planes };
    FIELD.with(|f| *f.borrow_mut() = Some(Rc::new(c)));
    Ok((rigged.to_arrays(), now_ms() - t0, stages))
}

/// The worker's body context with its canonical grid, had on its first job (and again for
/// another config): read from the browser's cache, or built and kept there.
async fn state(cfg: &GeneratorConfig) -> Result<Rc<WorkerState>, String> {
    if let Some(s) = STATE.with(|s| s.borrow().clone()).filter(|s| &s.cfg == cfg) {
        return Ok(s);
    }
    let body = BodyModel::default_body().map_err(|e| format!("the embedded body model: {e}"))?;
    let (ctx, how) = super::kept_context::body_context(body, cfg).await;
    web_sys::console::info_1(&JsValue::from_str(&format!("the worker's body context: {how}")));
    let s = Rc::new(WorkerState { ctx: Rc::new(ctx), cfg: cfg.clone(), how });
    STATE.with(|slot| *slot.borrow_mut() = Some(s.clone()));
    Ok(s)
}

/// The autodiff device `compute` asks for (`Err`: WebGPU asked for and the worker has none),
/// and the device in words, for the status. `Auto` is the worker's WebGPU device on a
/// hardware adapter and burn's NdArray in the worker on a software one (SwiftShader, what a
/// machine without a usable GPU gets): there NdArray in this wasm module (the networks' own
/// CPU operations, SIMD, the tensor crates optimised for speed) takes 2–3 s per W+ or PTI step
/// where SwiftShader takes 35–115 s, and finishes in a sixth of the time (docs/benchmarks.md,
/// "CPU against WebGPU in the worker"). Without a WebGPU device in the worker `Auto` is
/// refused, and the page runs the job on its own device.
#[allow(deprecated)] // burn 0.22 marks NdArray deprecated in favour of flex; the project's CPU backend.
async fn device(compute: Compute) -> Result<(Device, String), String> {
    let cpu = || Device::ndarray().autodiff();
    if compute == Compute::Cpu {
        return Ok((cpu(), "CPU (burn NdArray in the worker)".into()));
    }
    if WEBGPU.with(|w| w.borrow().is_none()) {
        let made = webgpu_device().await;
        WEBGPU.with(|w| *w.borrow_mut() = Some(made));
    }
    let webgpu = WEBGPU.with(|w| w.borrow().clone()).unwrap_or_else(|| Err("no WebGPU device".into()));
    let (d, name, software) = webgpu?;
    if software && compute == Compute::Auto {
        return Ok((cpu(), format!("CPU (burn NdArray in the worker; the WebGPU adapter is a software one: {name})")));
    }
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
