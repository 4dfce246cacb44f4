//! Browser glue: the wasm entry point, which owns the app, and the JS automation hook
//! (`window.getavatar`). Nothing here blocks; commands from JS are queued and applied by the
//! app at the start of its next frame.

use std::cell::RefCell;
use std::collections::VecDeque;

use eframe::egui;
use wasm_bindgen::prelude::*;
use wasm_bindgen::JsCast;

use crate::app::GetAvatarApp;
use crate::automation::{parse_command, parse_query, Action, PhotoSource, Status};
use crate::platform::now_ms;

thread_local! {
    static COMMANDS: RefCell<VecDeque<Result<Action, String>>> = const { RefCell::new(VecDeque::new()) };
    static STATUS: RefCell<String> = RefCell::new("{\"ready\":false}".to_string());
    static CONTEXT: RefCell<Option<egui::Context>> = const { RefCell::new(None) };
}

fn set_context(ctx: &egui::Context) {
    CONTEXT.with(|c| {
        if c.borrow().is_none() {
            *c.borrow_mut() = Some(ctx.clone());
        }
    });
}

fn take_commands() -> Vec<Result<Action, String>> {
    COMMANDS.with(|q| q.borrow_mut().drain(..).collect())
}

fn publish_status(status: &Status) -> Result<(), String> {
    let s = serde_json::to_string(status).map_err(|e| format!("status not serialisable: {e}"))?;
    STATUS.with(|st| *st.borrow_mut() = s);
    Ok(())
}

/// The app as the page runs it: each frame applies the queued automation commands, draws
/// the app's frame and publishes its status for `getavatar_status()`.
struct WebApp {
    app: GetAvatarApp,
}

impl eframe::App for WebApp {
    fn ui(&mut self, ui: &mut egui::Ui, frame: &mut eframe::Frame) {
        set_context(ui.ctx());
        for cmd in take_commands() {
            match cmd {
                Ok(a) => self.app.apply(a),
                Err(e) => self.app.report(e),
            }
        }
        self.app.frame(ui, frame);
        if let Err(e) = publish_status(self.app.status(now_ms())) {
            console_log(&e);
        }
    }
}

/// JS: queue a JSON command (see `automation::Command`); returns an error string for
/// malformed commands, otherwise "" (the command applies on the next frame).
#[wasm_bindgen]
pub fn getavatar_command(json: &str) -> String {
    let parsed = parse_command(json);
    let err = parsed.as_ref().err().cloned().unwrap_or_default();
    COMMANDS.with(|q| q.borrow_mut().push_back(parsed));
    request_repaint();
    err
}

/// JS: hand the app a photo's bytes (as the file picker does); `name` is shown with it.
#[wasm_bindgen]
pub fn getavatar_photo(bytes: Vec<u8>, name: String) {
    queue_photo(name, bytes);
}

fn queue_photo(name: String, bytes: Vec<u8>) {
    let action = Action::Photo { source: PhotoSource::Bytes { name, bytes }, options: None, on_gpu: false };
    COMMANDS.with(|q| q.borrow_mut().push_back(Ok(action)));
    request_repaint();
}

/// JS: hand the app a motion file's bytes (SMPL/AMASS .npz), as "Load motion…" does.
#[wasm_bindgen]
pub fn getavatar_motion(bytes: Vec<u8>, name: String) {
    queue_motion(name, bytes);
}

fn queue_motion(name: String, bytes: Vec<u8>) {
    COMMANDS.with(|q| q.borrow_mut().push_back(Ok(Action::MotionFile { name, bytes })));
    request_repaint();
}

/// JS: hand the app a video's bytes, as "Motion from video…" does (read at the panel's rate).
#[wasm_bindgen]
pub fn getavatar_video(bytes: Vec<u8>, name: String) {
    queue_video(name, bytes);
}

fn queue_video(name: String, bytes: Vec<u8>) {
    let action = Action::Video { source: PhotoSource::Bytes { name, bytes }, fps: None };
    COMMANDS.with(|q| q.borrow_mut().push_back(Ok(action)));
    request_repaint();
}

fn queue_reconstruction(name: String, bytes: Vec<u8>) {
    let action = Action::OpenReconstruction(PhotoSource::Bytes { name, bytes });
    COMMANDS.with(|q| q.borrow_mut().push_back(Ok(action)));
    request_repaint();
}

fn request_repaint() {
    CONTEXT.with(|c| {
        if let Some(ctx) = c.borrow().as_ref() {
            ctx.request_repaint();
        }
    });
}

/// JS: the app's latest status as JSON (see `automation::Status`).
#[wasm_bindgen]
pub fn getavatar_status() -> String {
    STATUS.with(|s| s.borrow().clone())
}

extern "C" {
    /// The static constructors (cubecl registers its IR dialects with `inventory`), which
    /// wasm-ld synthesises.
    fn __wasm_call_ctors();
}

/// Entry point, called by `index.html` after the module loads.
#[wasm_bindgen(start)]
pub fn start() {
    // Run the static constructors once, here. Without an explicit call, wasm-ld treats the
    // module as a "command" and wraps EVERY export in a call to them, so each call from JS
    // (a frame, a promise callback of a GPU read-back, the status) re-ran all of cubecl's
    // registrations: most of the main thread's time in a browser CPU profile of a retexture.
    // SAFETY: called once, first, before any code that reads what they register.
    unsafe { __wasm_call_ctors() };
    if crate::platform::in_worker() {
        // The reconstruction worker (`www/reconstruct_worker.js`): no app, only its jobs. Its
        // steps need no slicing (nothing to draw), but its checkpoints still let Cancel in.
        crate::task::install_time_slicing(crate::task::WORKER_SLICE_MS);
        std::panic::set_hook(Box::new(|info| crate::reconstruct::worker::post_fatal(&info.to_string())));
        return;
    }
    // Long CPU stages of core run in slices between frames (no task over 100 ms).
    crate::task::install_time_slicing(crate::task::SLICE_MS);
    // With panic = abort a panic stops the app for good: say so over the canvas (the page's
    // `getavatarFatal`, which offers a reload) and in the console, never a frozen canvas.
    std::panic::set_hook(Box::new(|info| {
        let msg = format!("The app stopped: {info}");
        web_sys::console::error_1(&JsValue::from_str(&msg));
        show_fatal(&msg);
    }));
    console_log("getavatar: starting");
    wasm_bindgen_futures::spawn_local(async {
        if let Err(e) = run().await {
            let msg = format!("getavatar failed to start: {e:?}");
            console_log(&msg);
            if let Some(el) = web_sys::window().and_then(|w| w.document()).and_then(|d| d.get_element_by_id("loading"))
            {
                el.set_text_content(Some(&msg));
            }
        }
    });
}

/// The page's message over the canvas for what the app cannot recover from
/// (`window.getavatarFatal` in index.html: the message and a Reload button).
fn show_fatal(msg: &str) {
    let Some(window) = web_sys::window() else { return };
    if let Ok(f) = js_sys::Reflect::get(&window, &JsValue::from_str("getavatarFatal")) {
        if let Some(f) = f.dyn_ref::<js_sys::Function>() {
            let _ = f.call1(&JsValue::NULL, &JsValue::from_str(msg));
        }
    }
}

fn console_log(msg: &str) {
    web_sys::console::log_1(&JsValue::from_str(msg));
}

async fn run() -> Result<(), JsValue> {
    let window = web_sys::window().ok_or("no window")?;
    let document = window.document().ok_or("no document")?;
    let canvas: web_sys::HtmlCanvasElement =
        document.get_element_by_id("getavatar_canvas").ok_or("no #getavatar_canvas")?.dyn_into()?;
    // An unreadable URL is reported in the panel; the app starts without its parameters.
    let (actions, errors) = match window.location().search() {
        Ok(query) => parse_query(&query),
        Err(e) => (Vec::new(), vec![format!("cannot read the page's URL parameters: {e:?}")]),
    };
    // The hidden file input behind "Open photo…"; chosen files queue like the hook's photos.
    let report = |e: String| {
        COMMANDS.with(|q| q.borrow_mut().push_back(Err(e)));
        request_repaint();
    };
    let photos = "image/png,image/jpeg,image/webp";
    crate::platform::install_file_input(&document, crate::platform::PHOTO_INPUT_ID, photos, queue_photo, report)?;
    // "Load motion…": SMPL/AMASS .npz files.
    crate::platform::install_file_input(&document, crate::platform::MOTION_INPUT_ID, ".npz", queue_motion, report)?;
    // "Motion from video…": any video the browser can decode.
    crate::platform::install_file_input(&document, crate::platform::VIDEO_INPUT_ID, "video/*", queue_video, report)?;
    // "Open reconstruction…": a saved reconstruction (.safetensors).
    let recon = crate::platform::RECONSTRUCTION_INPUT_ID;
    crate::platform::install_file_input(&document, recon, ".safetensors", queue_reconstruction, report)?;
    let options = eframe::WebOptions { wgpu_options: wgpu_options(), ..Default::default() };
    eframe::WebRunner::new()
        .start(
            canvas,
            options,
            Box::new(move |cc| Ok(Box::new(WebApp { app: GetAvatarApp::new(cc, actions, errors) }))),
        )
        .await?;
    if let Some(el) = document.get_element_by_id("loading") {
        el.remove();
    }
    Ok(())
}

/// The egui wgpu configuration: WebGPU, and a device with the adapter's own limits
/// (burn kernels need more storage buffers per stage than wgpu's defaults).
fn wgpu_options() -> eframe::egui_wgpu::WgpuConfiguration {
    use eframe::egui_wgpu::{self, wgpu, WgpuSetup, WgpuSetupCreateNew};
    let mut create = WgpuSetupCreateNew::without_display_handle();
    create.instance_descriptor.backends = wgpu::Backends::BROWSER_WEBGPU;
    create.device_descriptor = std::sync::Arc::new(|adapter: &wgpu::Adapter| wgpu::DeviceDescriptor {
        label: Some("getavatar device"),
        required_features: adapter.features() - wgpu::Features::MAPPABLE_PRIMARY_BUFFERS,
        required_limits: adapter.limits(),
        ..Default::default()
    });
    egui_wgpu::WgpuConfiguration { wgpu_setup: WgpuSetup::CreateNew(create), ..Default::default() }
}
