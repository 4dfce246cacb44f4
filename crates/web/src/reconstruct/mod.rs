//! Single-image reconstruction in the browser (paper Sec. 5.4, `getavatar_core::reconstruction::inversion`):
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
//!
//! - [`job`]: the reconstruction's steps (shared by the page and the worker)
//! - [`worker_client`]: the page's side of the reconstruction worker (which also generates
//!   the page's new identities and its texture-field queries on a software WebGPU adapter)
//! - [`worker`]: the worker's side
//! - [`protocol`]: the messages between them
//! - [`kept_context`]: the worker's body context kept in the browser's Cache API

use eframe::egui;

mod job;
mod kept_context;
mod protocol;
pub mod worker;
mod worker_client;

use job::run_on_page;
pub use job::{
    open, save, InversionJob, Measured, Preview, ProjectionSource, ReconstructEvent, ReconstructRequest,
    ReconstructTask, Reconstructed,
};
pub use protocol::WorkerField;
pub use worker_client::{colours_in_worker, generate_in_worker, warm_worker};

/// Start a reconstruction; its events arrive on the returned task. It runs in the
/// reconstruction worker (its own WebGPU device, off the UI thread), or on the page
/// where the browser gives workers no WebGPU.
pub fn reconstruct(req: ReconstructRequest, repaint: egui::Context) -> ReconstructTask {
    let task = ReconstructTask::default();
    match worker_client::start(req, task.clone(), repaint.clone()) {
        Ok(()) => {}
        Err(req) => run_on_page(*req, task.clone(), repaint),
    }
    task
}
