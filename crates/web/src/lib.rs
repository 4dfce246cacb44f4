//! # getavatar-web
//!
//! The browser app: eframe/egui on wgpu with the WebGPU backend. It shows the posed body
//! (later: generated avatars), with pose, shape, camera and view controls and a .glb
//! download. Everything model-related comes from `getavatar-core`.
//!
//! - [`automation`]: URL parameters and the JS hook's commands (pure, tested natively)
//! - [`status`]: what `window.getavatar.status()` returns, one struct per panel (pure)
//! - `app` (wasm32): the egui application state and per-frame flow; `app::panels`, `app::texture_job`
//! - `generate` (wasm32): the generator on burn's wgpu backend sharing egui's WebGPU device
//! - `texture_field` (wasm32): an avatar's texture field and where its colours are computed
//!   (the worker's CPU on a software adapter, else the page's WebGPU device)
//! - `viewer` (wasm32): the wgpu render pass that draws RGB / normal / mask views
//! - `photo` (wasm32): the photo → body flow's tasks: MediaPipe Pose (`www/pose_detect.js`)
//!   and the body fit on the shared WebGPU device; the page's file input
//! - `reconstruct/` (wasm32): single-image reconstruction (encoder guess, W+ inversion, pivotal
//!   tuning) from the photo and its body fit: `job` (the steps), run in a dedicated worker
//!   (`worker_client` the page's side, `worker` the worker's, `protocol` their messages; its own
//!   WebGPU device, so no step holds the UI thread) or on the page where workers lack WebGPU
//! - [`video_clip`]: what "Motion from video…" accepts and which frames it reads (pure)
//! - `video` (wasm32): motion from a video: frames decoded in the page (`www/video_frames.js`),
//!   MediaPipe's tracking mode, the warm-started clip fit of `getavatar_core::body::body_fit::video`
//! - `task` (wasm32): background tasks' event queues, Cancel, yielding to the browser
//! - `platform` (wasm32): clock and file downloads
//! - `web` (wasm32): entry point owning the app, JS automation hook

pub mod automation;
pub mod status;
pub mod video_clip;

#[cfg(target_arch = "wasm32")]
mod app;
#[cfg(target_arch = "wasm32")]
mod generate;
#[cfg(target_arch = "wasm32")]
mod photo;
#[cfg(target_arch = "wasm32")]
mod platform;
#[cfg(target_arch = "wasm32")]
mod reconstruct;
#[cfg(target_arch = "wasm32")]
mod task;
#[cfg(target_arch = "wasm32")]
mod texture_field;
#[cfg(target_arch = "wasm32")]
mod video;
#[cfg(target_arch = "wasm32")]
mod viewer;
#[cfg(target_arch = "wasm32")]
mod web;
