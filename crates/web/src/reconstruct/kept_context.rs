//! The worker's body context kept in the browser's Cache API, between workers (one ends after
//! two idle minutes) and visits: `getavatar_core::geometry::context_cache`'s bytes, the same
//! format the native trainer keeps on disk. A fresh worker reads them in a fraction of a
//! second where building the context (the template SDF and the canonical pose's posed grid)
//! takes 3–4 s of a 2-core machine. Bytes of another build, body or resolution, or damaged
//! ones, are refused by `context_cache::from_bytes` with the reason, built again and replaced;
//! a browser without the Cache API (an insecure origin) only pays the build. The status says
//! which happened (`Status::worker_body_context`).

use getavatar_core::body::body_model::BodyModel;
use getavatar_core::generator::network::GeneratorConfig;
use getavatar_core::generator::pipeline::BodyContext;
use getavatar_core::geometry::context_cache::{file_name, from_bytes, to_bytes};
use wasm_bindgen::prelude::*;
use wasm_bindgen::JsCast;
use wasm_bindgen_futures::JsFuture;

use crate::platform::{js_message, now_ms};

/// The Cache API cache that holds the contexts (one entry per body and resolution).
pub const CACHE_NAME: &str = "getavatar-body-context";

/// The body context of `model` at `cfg`'s resolutions with its canonical grid made, and how it
/// was had, in words for the status.
pub(super) async fn body_context(model: BodyModel, cfg: &GeneratorConfig) -> (BodyContext, String) {
    let (template_res, tet_res) = (cfg.template_res, cfg.tet_res);
    let key = format!("body_context/{}", file_name(&model, template_res, tet_res));
    let t0 = now_ms();
    let cache = open().await;
    let refused = match &cache {
        Ok(cache) => match read(cache, &key).await {
            Ok(Some(bytes)) => match from_bytes(model.clone(), &bytes, template_res, tet_res) {
                Ok(ctx) => {
                    let mb = bytes.len() as f64 / 1e6;
                    return (ctx, format!("read from the browser's cache in {:.0} ms ({mb:.1} MB)", now_ms() - t0));
                }
                Err(why) => Some(format!("the cached one was refused: {why}")),
            },
            Ok(None) => None,
            Err(why) => Some(format!("the cached one could not be read: {why}")),
        },
        Err(_) => None,
    };
    let t1 = now_ms();
    let ctx = BodyContext::new_async(model, cfg).await;
    ctx.canonical_grid_async(ctx.canonical_inverse()).await;
    let built = now_ms() - t1;
    let t2 = now_ms();
    let kept = match &cache {
        Ok(cache) => write(cache, &key, &ctx).await,
        Err(why) => Err(why.clone()),
    };
    let refused = match refused {
        Some(why) => format!(" ({why})"),
        None => String::new(),
    };
    let how = match kept {
        Ok(bytes) => format!(
            "built in {built:.0} ms{refused}, kept in the browser's cache ({:.1} MB in {:.0} ms)",
            bytes as f64 / 1e6,
            now_ms() - t2
        ),
        Err(why) => format!("built in {built:.0} ms{refused}; not kept: {why}"),
    };
    (ctx, how)
}

/// The worker's Cache API cache, or why there is none.
async fn open() -> Result<web_sys::Cache, String> {
    let caches = js_sys::Reflect::get(&js_sys::global(), &JsValue::from_str("caches"))
        .ok()
        .filter(|c| !c.is_undefined() && !c.is_null())
        .ok_or("the browser offers no Cache API here (it needs a secure origin: https or localhost)")?;
    let caches: web_sys::CacheStorage = caches.dyn_into().map_err(|_| "`caches` is not a CacheStorage")?;
    let cache = JsFuture::from(caches.open(CACHE_NAME))
        .await
        .map_err(|e| format!("the browser's cache cannot be opened: {}", js_message(&e)))?;
    cache.dyn_into().map_err(|_| "the browser's cache is not a Cache".into())
}

/// The bytes kept under `key`; None: nothing is.
async fn read(cache: &web_sys::Cache, key: &str) -> Result<Option<Vec<u8>>, String> {
    let found = JsFuture::from(cache.match_with_str(key)).await.map_err(|e| js_message(&e))?;
    if found.is_undefined() || found.is_null() {
        return Ok(None);
    }
    let response: web_sys::Response = found.dyn_into().map_err(|_| "the cache holds no response")?;
    let buffer =
        JsFuture::from(response.array_buffer().map_err(|e| js_message(&e))?).await.map_err(|e| js_message(&e))?;
    Ok(Some(js_sys::Uint8Array::new(&buffer).to_vec()))
}

/// Keep `ctx`'s bytes under `key` (replacing what was there) and drop the cache's other
/// entries (another body's or config's): their length.
async fn write(cache: &web_sys::Cache, key: &str, ctx: &BodyContext) -> Result<usize, String> {
    let bytes = to_bytes(ctx)?;
    let n = bytes.len();
    let array = js_sys::Uint8Array::from(&bytes[..]);
    drop(bytes);
    let response = web_sys::Response::new_with_opt_js_u8_array(Some(&array)).map_err(|e| js_message(&e))?;
    JsFuture::from(cache.put_with_str(key, &response))
        .await
        .map_err(|e| format!("the browser's cache refused it: {}", js_message(&e)))?;
    drop_others(cache, key).await.map_err(|e| format!("kept, but the older entries stay: {e}"))?;
    Ok(n)
}

/// Delete every entry of `cache` but `key`'s.
async fn drop_others(cache: &web_sys::Cache, key: &str) -> Result<(), String> {
    // The entry's URL as the cache stores it: `key` resolved against this worker's address.
    let ours = web_sys::Request::new_with_str(key).map_err(|e| js_message(&e))?.url();
    let keys = JsFuture::from(cache.keys()).await.map_err(|e| js_message(&e))?;
    for request in js_sys::Array::from(&keys).iter() {
        let request: web_sys::Request = request.dyn_into().map_err(|_| "a cache key is not a Request")?;
        if request.url() != ours {
            JsFuture::from(cache.delete_with_request(&request)).await.map_err(|e| js_message(&e))?;
        }
    }
    Ok(())
}
