//! The messages between the page and the reconstruction worker: `{json, …typed arrays}`,
//! the JSON holding the small fields ([`ToWorker`], [`FromWorker`]), the arrays the bulk
//! (checkpoint, images, the result file, rigged avatars).

use std::rc::Rc;

use getavatar_core::body::body_fit::fit::BodyFit;
use getavatar_core::body::skinning::BodyParams;
use getavatar_core::generator::network::GeneratorConfig;
use getavatar_core::generator::rigging::RiggedArrays;
use getavatar_core::reconstruction::inversion::{InversionOptions, StepReport};
use getavatar_core::util::profile::StageProfile;
use serde::{Deserialize, Serialize};
use wasm_bindgen::prelude::*;

use super::job::{Compute, InversionJob, StartChoice};

/// The page's message to the worker (the `json` field).
#[derive(Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub(super) enum ToWorker {
    /// Run an inversion; the arrays `target_rgb`, `target_mask`, and optionally `checkpoint`,
    /// `discriminator`, `encoder` and `photo_rgb` (the projection's photo) come with it.
    Start(Box<JobMeta>),
    /// The model files the next jobs use, sent ahead of the job in a message of their own
    /// (arrays `checkpoint`, `discriminator`, `encoder`: the ones the worker does not hold yet).
    Files,
    /// Stop the running inversion at its next step (or skip measuring its result).
    Cancel,
    /// The page shows the result handed over before its figures: measure it now (not while
    /// the page rigs it, which would share the adapter with it).
    Measure,
    /// Generate a new identity on the worker's CPU for the page's Generate (the array
    /// `checkpoint` comes with it unless the worker holds it).
    Generate(GenerateMeta),
    /// An avatar's texture field at the canonical points of the array `points` (3 floats
    /// each), on the worker's CPU: the page's New texture, texture bakes and per-pixel texture
    /// view on a software adapter (`checkpoint` as above; a reconstruction's file as the array
    /// `result`).
    Colours(ColoursMeta),
    /// Get ready for the page's first Generate on a software adapter, while the page is idle:
    /// the body's context, the model (the array `checkpoint` unless kept) and the canonical
    /// pose's posed grid (seconds the first Generate of a fresh worker paid).
    Warm(WarmMeta),
}

/// A call to the worker (Generate, Colours, Warm): its id for the answer, the model's config,
/// whether the worker holds the checkpoint already (else it comes as the array `checkpoint`),
/// and what is asked.
#[derive(Serialize, Deserialize)]
pub(super) struct CallMeta<T> {
    pub(super) id: u64,
    pub(super) cfg: GeneratorConfig,
    pub(super) checkpoint_kept: bool,
    pub(super) ask: T,
}

/// A [`ToWorker::Warm`] call: nothing asked but getting ready.
pub(super) type WarmMeta = CallMeta<()>;

/// A [`ToWorker::Colours`] call: whose texture field.
pub(super) type ColoursMeta = CallMeta<WorkerField>;

/// A [`ToWorker::Generate`] call: a new identity (or texture) as the page's Generate has it.
pub(super) type GenerateMeta = CallMeta<Identity>;

/// A generated identity: its seeds and ψ under the model's config.
#[derive(Clone, Copy, Serialize, Deserialize)]
pub(super) struct Identity {
    pub(super) seeds: (u64, u64),
    pub(super) psi: f32,
}

/// Whose texture field [`ToWorker::Colours`] asks for.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WorkerField {
    /// A generated identity's: the model's styles of these seeds and ψ.
    Seeds { seeds: (u64, u64), psi: f32 },
    /// A reconstruction's: its file (the array `result`), `key` naming it for the worker's cache.
    Result { key: u64 },
}

/// An [`InversionJob`] without its arrays.
#[derive(Serialize, Deserialize)]
pub(super) struct JobMeta {
    pub(super) cfg: GeneratorConfig,
    /// The checkpoint (the discriminator) is the previous job's: the page sends each file once.
    pub(super) checkpoint_kept: bool,
    pub(super) discriminator_kept: bool,
    pub(super) encoder_kept: bool,
    pub(super) options: InversionOptions,
    pub(super) preview_every: usize,
    pub(super) start: StartChoice,
    pub(super) start_note: String,
    pub(super) compute: Compute,
    pub(super) world_to_camera: [f32; 16],
    pub(super) body: BodyParams,
    pub(super) res: usize,
    pub(super) projection: Option<ProjectionMeta>,
    pub(super) measure_after_result: bool,
    pub(super) figures: bool,
}

/// A [`ProjectionSource`] without its arrays (`photo_rgb`, `photo_mask`).
#[derive(Serialize, Deserialize)]
pub(super) struct ProjectionMeta {
    pub(super) fit: BodyFit,
    pub(super) width: usize,
    pub(super) height: usize,
    pub(super) mask_width: usize,
    pub(super) mask_height: usize,
    pub(super) res: usize,
    pub(super) num_betas: usize,
}

/// The worker's messages to the page (the `json` field).
#[derive(Serialize, Deserialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub(super) enum FromWorker {
    Started {
        start: String,
        candidates: usize,
        perceptual: bool,
        millis: f64,
        device: String,
        note: String,
        garment: String,
        garment_codes: super::job::GarmentCounts,
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
    /// With the array `bytes`: the reconstruction file, and the avatar the worker rigged from
    /// it (the arrays of [`rigged_arrays`]). IoU and PSNR at the photo's camera (None: not
    /// finite).
    Finished {
        iou: Option<f32>,
        psnr: Option<f32>,
        figures_ms: f64,
        file_ms: f64,
        /// Milliseconds of the worker's extraction and rigging.
        rig_ms: f64,
        /// Cancelled after this many steps (the result is the last preview's state).
        stopped_at: Option<usize>,
        /// The figures follow (`Figures`): IoU and PSNR are None here.
        measuring: bool,
        /// The photo's body fit refined on the start's outline.
        refit: Option<Box<getavatar_core::body::body_fit::fit::BodyFit>>,
    },
    /// A result's figures after the result (`Finished { measuring: true }`), with the arrays
    /// `rgb` and `mask` (the render they come from) unless `error` says why there are none.
    Figures {
        iou: Option<f32>,
        psnr: Option<f32>,
        millis: f64,
        error: Option<String>,
    },
    Failed {
        message: String,
    },
    Cancelled,
    /// This worker has no WebGPU device: the page runs the reconstruction itself.
    Unavailable {
        message: String,
    },
    /// With the arrays of [`rigged_arrays`]: the avatar of `Generate` `id`, extracted and rigged,
    /// in `millis` (the model's loading included), by stage.
    Generated {
        id: u64,
        millis: f64,
        stages: Option<StageProfile>,
    },
    /// With the array `colors` (linear RGB, 3 floats per point): the answer to `Colours` `id`.
    Coloured {
        id: u64,
        millis: f64,
    },
    /// `Warm` `id` is done, in `millis`; how the worker had its body context, in words
    /// (`super::kept_context`).
    Warmed {
        id: u64,
        millis: f64,
        body_context: String,
    },
    /// `Generate`, `Colours` or `Warm` `id` failed.
    CallFailed {
        id: u64,
        message: String,
    },
    /// The worker's module stopped (a panic): it is gone; the next reconstruction starts a new one.
    Fatal {
        message: String,
    },
}

/// The model files: a checkpoint's, a discriminator's and an encoder's bytes.
#[derive(Clone, Default)]
pub(super) struct ModelFiles {
    pub(super) checkpoint: Option<Rc<Vec<u8>>>,
    pub(super) discriminator: Option<Rc<Vec<u8>>>,
    pub(super) encoder: Option<Rc<Vec<u8>>>,
}

impl ModelFiles {
    pub(super) const NAMES: [&'static str; 3] = ["checkpoint", "discriminator", "encoder"];

    pub(super) fn of(job: &InversionJob) -> Self {
        Self {
            checkpoint: job.checkpoint.clone(),
            discriminator: job.discriminator.clone(),
            encoder: job.encoder.clone(),
        }
    }

    pub(super) fn slot(&mut self, name: &str) -> &mut Option<Rc<Vec<u8>>> {
        match name {
            "checkpoint" => &mut self.checkpoint,
            "discriminator" => &mut self.discriminator,
            _ => &mut self.encoder,
        }
    }
}

/// `{json, …arrays}`.
/// A message and the buffers it hands over (moved, not copied: the arrays are made for it).
pub(super) struct Message {
    pub(super) data: JsValue,
    pub(super) transfer: js_sys::Array,
}

pub(super) fn object(json: &str, arrays: &[(&str, JsValue)]) -> Message {
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

pub(super) fn message_of<T: Serialize>(m: &T, arrays: &[(&str, JsValue)]) -> Message {
    // Our own enums of plain fields serialise.
    object(&serde_json::to_string(m).unwrap_or_else(|e| format!("{{\"error\":\"{e}\"}}")), arrays)
}

/// A message's JSON part (the one field every message has).
pub(super) fn json_of(data: &JsValue) -> Result<String, String> {
    field(data, "json").and_then(|j| j.as_string()).ok_or_else(|| "a message without its `json` field".to_string())
}

pub(super) fn field(data: &JsValue, name: &str) -> Option<JsValue> {
    js_sys::Reflect::get(data, &name.into()).ok().filter(|v| !v.is_undefined() && !v.is_null())
}

/// A message's `name` field as floats: a `Float32Array` copied once into wasm memory (or any
/// array-like, converted first).
pub(super) fn f32_array(data: &JsValue, name: &str) -> Option<Vec<f32>> {
    field(data, name)
        .map(|v| v.dyn_into::<js_sys::Float32Array>().unwrap_or_else(|v| js_sys::Float32Array::new(&v)).to_vec())
}

/// A message's `name` field as bytes: a `Uint8Array` copied once into wasm memory (or any
/// array-like, converted first). `Uint8Array::new` on a typed array copies it element by
/// element: 35+ ms of the UI thread for a reconstruction's 11.5 MB file on SwiftShader.
pub(super) fn u8_array(data: &JsValue, name: &str) -> Option<Vec<u8>> {
    field(data, name)
        .map(|v| v.dyn_into::<js_sys::Uint8Array>().unwrap_or_else(|v| js_sys::Uint8Array::new(&v)).to_vec())
}

/// The fields of a rigged avatar in a message (each a typed array made for it, so moved).
pub(super) fn rigged_arrays(a: &RiggedArrays) -> Vec<(&'static str, JsValue)> {
    let f = |v: &[f32]| JsValue::from(js_sys::Float32Array::from(v));
    let u = |v: &[u32]| JsValue::from(js_sys::Uint32Array::from(v));
    vec![
        ("rig_positions", f(&a.positions)),
        ("rig_faces", u(&a.faces)),
        ("rig_attributes", f(&a.attributes)),
        ("rig_normals", f(&a.normals)),
        ("rig_colors", f(&a.colors)),
        ("rig_edge_a", u(&a.edge_a)),
        ("rig_edge_b", u(&a.edge_b)),
        ("rig_edge_t", f(&a.edge_t)),
        ("rig_body_vertex", u(&a.body_vertex)),
    ]
}

/// Elements of a typed array copied into wasm memory between two of the page's checkpoints
/// (1 MB of floats or indices, 2 MB of bytes): one copy of a whole 11.5 MB result file held
/// the UI thread 40–100 ms on SwiftShader.
const COPY_SLICE_BYTES: u32 = 1 << 20;

/// `len` elements copied by `copy(start, end, into)` in slices of `per` elements, with a
/// checkpoint ([`getavatar_core::util::cooperative`]) after each: the page's time slicing
/// gives the thread back between them. The result is reserved at once and zeroed a slice at
/// a time: a zeroed 11.5 MB vector alone held the UI thread 20–30 ms in a job's first result.
async fn copy_in_slices<T: Copy + Default>(len: u32, per: u32, copy: impl Fn(u32, u32, &mut [T])) -> Vec<T> {
    let mut out = Vec::with_capacity(len as usize);
    let mut start = 0;
    while start < len {
        let end = start.saturating_add(per.max(1)).min(len);
        out.resize(end as usize, T::default());
        copy(start, end, &mut out[start as usize..]);
        start = end;
        getavatar_core::util::cooperative::checkpoint().await;
    }
    out
}

/// `v` copied out of wasm memory into a new `Uint8Array` in slices, with a checkpoint after
/// each (the page's side of a large array it sends: the checkpoint, a result file).
pub(super) async fn js_u8_sliced(v: &[u8]) -> js_sys::Uint8Array {
    let a = js_sys::Uint8Array::new_with_length(v.len() as u32);
    let per = 2 * COPY_SLICE_BYTES as usize;
    for (k, c) in v.chunks(per).enumerate() {
        let s = (k * per) as u32;
        a.subarray(s, s + c.len() as u32).copy_from(c);
        getavatar_core::util::cooperative::checkpoint().await;
    }
    a
}

/// [`js_u8_sliced`] for floats (a bake's points).
pub(super) async fn js_f32_sliced(v: &[f32]) -> js_sys::Float32Array {
    let a = js_sys::Float32Array::new_with_length(v.len() as u32);
    let per = COPY_SLICE_BYTES as usize / 4;
    for (k, c) in v.chunks(per).enumerate() {
        let s = (k * per) as u32;
        a.subarray(s, s + c.len() as u32).copy_from(c);
        getavatar_core::util::cooperative::checkpoint().await;
    }
    a
}

/// [`u8_array`] in slices (the page's copy of a result file).
pub(super) async fn u8_array_sliced(data: &JsValue, name: &str) -> Option<Vec<u8>> {
    let a = field(data, name)?.dyn_into::<js_sys::Uint8Array>().unwrap_or_else(|v| js_sys::Uint8Array::new(&v));
    Some(copy_in_slices(a.length(), 2 * COPY_SLICE_BYTES, |s, e, into| a.subarray(s, e).copy_to(into)).await)
}

/// [`f32_array`] in slices (the page's copy of a bake's colours).
pub(super) async fn f32_array_sliced(data: &JsValue, name: &str) -> Option<Vec<f32>> {
    let a = field(data, name)?.dyn_into::<js_sys::Float32Array>().unwrap_or_else(|v| js_sys::Float32Array::new(&v));
    Some(copy_in_slices(a.length(), COPY_SLICE_BYTES / 4, |s, e, into| a.subarray(s, e).copy_to(into)).await)
}

async fn u32_array_sliced(data: &JsValue, name: &str) -> Option<Vec<u32>> {
    let a = field(data, name)?.dyn_into::<js_sys::Uint32Array>().unwrap_or_else(|v| js_sys::Uint32Array::new(&v));
    Some(copy_in_slices(a.length(), COPY_SLICE_BYTES / 4, |s, e, into| a.subarray(s, e).copy_to(into)).await)
}

/// The rigged avatar of a message ([`rigged_arrays`]), copied in slices on the page, or the
/// name of a missing field.
pub(super) async fn rigged_of(data: &JsValue) -> Result<RiggedArrays, &'static str> {
    let f = |name: &'static str| async move { f32_array_sliced(data, name).await.ok_or(name) };
    let u = |name: &'static str| async move { u32_array_sliced(data, name).await.ok_or(name) };
    Ok(RiggedArrays {
        positions: f("rig_positions").await?,
        faces: u("rig_faces").await?,
        attributes: f("rig_attributes").await?,
        normals: f("rig_normals").await?,
        colors: f("rig_colors").await?,
        edge_a: u("rig_edge_a").await?,
        edge_b: u("rig_edge_b").await?,
        edge_t: f("rig_edge_t").await?,
        body_vertex: u("rig_body_vertex").await?,
    })
}
