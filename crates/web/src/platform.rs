//! Browser services the app needs: a clock, fetching URLs, file downloads and JS error
//! messages (web-sys only, no app state).

use std::rc::Rc;

use wasm_bindgen::prelude::*;
use wasm_bindgen::JsCast;
use wasm_bindgen_futures::JsFuture;

thread_local! {
    /// The global scope's timer: the page's, or the reconstruction worker's
    /// (`crate::reconstruct::worker`), which has no `window`.
    static PERFORMANCE: Option<web_sys::Performance> =
        js_sys::Reflect::get(&js_sys::global(), &JsValue::from_str("performance")).ok().and_then(|p| p.dyn_into().ok());
}

/// Milliseconds since the page (or worker) started (`performance.now()`); 0 where the browser
/// has no performance timer.
/// Whether this module runs in a worker (no `window`): the reconstruction worker.
pub fn in_worker() -> bool {
    web_sys::window().is_none()
}

pub fn now_ms() -> f64 {
    PERFORMANCE.with(|p| p.as_ref().map(|p| p.now()).unwrap_or(0.0))
}

/// Call `f` after `ms` milliseconds (`setTimeout(f, ms)`; 0: the next task) on the global
/// scope, the page's or a worker's.
pub fn set_timeout(f: &js_sys::Function, ms: i32) -> Result<(), JsValue> {
    let global = js_sys::global();
    let set_timeout: js_sys::Function = js_sys::Reflect::get(&global, &JsValue::from_str("setTimeout"))?.dyn_into()?;
    set_timeout.call2(&global, f, &JsValue::from(ms))?;
    Ok(())
}

/// A JS exception's message (an `Error`'s, a thrown string, or the value's debug form).
pub fn js_message(e: &JsValue) -> String {
    e.dyn_ref::<js_sys::Error>()
        .map(|e| String::from(e.message()))
        .or_else(|| e.as_string())
        .unwrap_or_else(|| format!("{e:?}"))
}

/// Fetch a URL's bytes (relative to the page, or absolute; blob and data URLs too).
pub async fn fetch_bytes(url: &str) -> Result<Vec<u8>, String> {
    let window = web_sys::window().ok_or("no window")?;
    let resp = wasm_bindgen_futures::JsFuture::from(window.fetch_with_str(url))
        .await
        .map_err(|e| format!("{url}: {}", js_message(&e)))?;
    let resp: web_sys::Response = resp.dyn_into().map_err(|_| "fetch did not return a Response".to_string())?;
    if !resp.ok() {
        return Err(format!("nothing at {url} (HTTP {})", resp.status()));
    }
    let buf = wasm_bindgen_futures::JsFuture::from(resp.array_buffer().map_err(|e| js_message(&e))?)
        .await
        .map_err(|e| format!("reading {url}: {}", js_message(&e)))?;
    Ok(js_sys::Uint8Array::new(&buf).to_vec())
}

/// Offer `bytes` to the user as a file download.
pub fn download_bytes(name: &str, bytes: &[u8], mime: &str) -> Result<(), String> {
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

/// The ids of the page's hidden file inputs (made by [`install_file_input`]): photos,
/// motion files, reconstructions and videos.
pub const PHOTO_INPUT_ID: &str = "getavatar_photo_input";
pub const MOTION_INPUT_ID: &str = "getavatar_motion_input";
pub const RECONSTRUCTION_INPUT_ID: &str = "getavatar_reconstruction_input";
pub const VIDEO_INPUT_ID: &str = "getavatar_video_input";

/// Add a hidden `<input type=file>` (`id`, accepting `accept`) behind an "Open…" button;
/// each chosen file's bytes go to `on_file(name, bytes)`, an unreadable one's error to
/// `on_error`.
pub fn install_file_input(
    document: &web_sys::Document,
    id: &str,
    accept: &str,
    on_file: impl Fn(String, Vec<u8>) + 'static,
    on_error: impl Fn(String) + 'static,
) -> Result<(), JsValue> {
    let input: web_sys::HtmlInputElement = document.create_element("input")?.dyn_into()?;
    input.set_type("file");
    input.set_id(id);
    input.set_accept(accept);
    input.style().set_property("display", "none")?;
    let on_file = Rc::new(on_file);
    let on_error = Rc::new(on_error);
    let target = input.clone();
    let handler = Closure::<dyn FnMut()>::new(move || {
        let Some(file) = target.files().and_then(|f| f.get(0)) else { return };
        // The same file chosen again must fire `change` again.
        target.set_value("");
        let (on_file, on_error) = (on_file.clone(), on_error.clone());
        wasm_bindgen_futures::spawn_local(async move {
            let name = file.name();
            match JsFuture::from(file.array_buffer()).await {
                Ok(buf) => on_file(name, js_sys::Uint8Array::new(&buf).to_vec()),
                Err(e) => on_error(format!("cannot read {name}: {}", js_message(&e))),
            }
        });
    });
    input.add_event_listener_with_callback("change", handler.as_ref().unchecked_ref())?;
    // The input lives as long as the page.
    handler.forget();
    document.body().ok_or("no <body>")?.append_child(&input)?;
    Ok(())
}

/// Open the browser's file chooser of input `id` (needs a recent user gesture, e.g. the
/// button's click).
pub fn open_file_picker(id: &str) -> Result<(), String> {
    let document = web_sys::window().and_then(|w| w.document()).ok_or("no document")?;
    let input: web_sys::HtmlElement = document
        .get_element_by_id(id)
        .ok_or("the page has no file input")?
        .dyn_into()
        .map_err(|_| "the file input is not an element".to_string())?;
    input.click();
    Ok(())
}
