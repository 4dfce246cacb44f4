//! Browser glue: the wasm entry point, the JS automation hook (`window.getavatar`), file
//! downloads and timing. Nothing here blocks; commands from JS are queued and applied by the
//! app at the start of its next frame.

use std::cell::RefCell;
use std::collections::VecDeque;

use eframe::egui;
use wasm_bindgen::prelude::*;
use wasm_bindgen::JsCast;

use crate::automation::{parse_command, parse_query, Action, Status};

thread_local! {
    static COMMANDS: RefCell<VecDeque<Result<Action, String>>> = RefCell::new(VecDeque::new());
    static STATUS: RefCell<String> = RefCell::new("{\"ready\":false}".to_string());
    static CONTEXT: RefCell<Option<egui::Context>> = const { RefCell::new(None) };
}

pub(crate) fn set_context(ctx: &egui::Context) {
    CONTEXT.with(|c| {
        if c.borrow().is_none() {
            *c.borrow_mut() = Some(ctx.clone());
        }
    });
}

pub(crate) fn take_commands() -> Vec<Result<Action, String>> {
    COMMANDS.with(|q| q.borrow_mut().drain(..).collect())
}

pub(crate) fn publish_status(status: &Status) {
    if let Ok(s) = serde_json::to_string(status) {
        STATUS.with(|st| *st.borrow_mut() = s);
    }
}

/// JS: queue a JSON command (see `automation::Command`); returns an error string for
/// malformed commands, otherwise "" (the command applies on the next frame).
#[wasm_bindgen]
pub fn getavatar_command(json: &str) -> String {
    let parsed = parse_command(json);
    let err = parsed.as_ref().err().cloned().unwrap_or_default();
    COMMANDS.with(|q| q.borrow_mut().push_back(parsed));
    CONTEXT.with(|c| {
        if let Some(ctx) = c.borrow().as_ref() {
            ctx.request_repaint();
        }
    });
    err
}

/// JS: the app's latest status as JSON (see `automation::Status`).
#[wasm_bindgen]
pub fn getavatar_status() -> String {
    STATUS.with(|s| s.borrow().clone())
}

pub(crate) fn now_ms() -> f64 {
    web_sys::window().and_then(|w| w.performance()).map(|p| p.now()).unwrap_or(0.0)
}

/// Offer `bytes` to the user as a file download.
pub(crate) fn download_bytes(name: &str, bytes: &[u8], mime: &str) -> Result<(), String> {
    let err = |e: JsValue| format!("{e:?}");
    let array = js_sys::Uint8Array::from(bytes);
    let parts = js_sys::Array::of1(&array);
    let opts = web_sys::BlobPropertyBag::new();
    opts.set_type(mime);
    let blob = web_sys::Blob::new_with_u8_array_sequence_and_options(&parts, &opts).map_err(err)?;
    let url = web_sys::Url::create_object_url_with_blob(&blob).map_err(err)?;
    let document = web_sys::window().and_then(|w| w.document()).ok_or("no document")?;
    let a: web_sys::HtmlAnchorElement =
        document.create_element("a").map_err(err)?.dyn_into().map_err(|_| "not an anchor".to_string())?;
    a.set_href(&url);
    a.set_download(name);
    a.click();
    // Revoke later: the download has started reading the blob by then.
    let revoke = Closure::once_into_js(move || {
        let _ = web_sys::Url::revoke_object_url(&url);
    });
    if let Some(w) = web_sys::window() {
        let _ = w.set_timeout_with_callback_and_timeout_and_arguments_0(revoke.unchecked_ref(), 60_000);
    }
    Ok(())
}

/// Entry point, called by `index.html` after the module loads.
#[wasm_bindgen(start)]
pub fn start() {
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

fn console_log(msg: &str) {
    web_sys::console::log_1(&JsValue::from_str(msg));
}

async fn run() -> Result<(), JsValue> {
    let window = web_sys::window().ok_or("no window")?;
    let document = window.document().ok_or("no document")?;
    let canvas: web_sys::HtmlCanvasElement =
        document.get_element_by_id("getavatar_canvas").ok_or("no #getavatar_canvas")?.dyn_into()?;
    let query = window.location().search().unwrap_or_default();
    let (actions, errors) = parse_query(&query);
    let options = eframe::WebOptions { wgpu_options: crate::app::wgpu_options(), ..Default::default() };
    eframe::WebRunner::new()
        .start(canvas, options, Box::new(move |cc| Ok(Box::new(crate::app::GetAvatarApp::new(cc, actions, errors)))))
        .await?;
    if let Some(el) = document.get_element_by_id("loading") {
        el.remove();
    }
    Ok(())
}
