//! Generator checkpoints as safetensors files with the config embedded.
//!
//! Layout: the standard safetensors container (8-byte little-endian header length, JSON header,
//! raw little-endian data). Each float parameter of the [`Generator`] is stored under its module
//! path (e.g. `synthesis.blocks.2.convs.0.weight`) as F32. `__metadata__` holds
//! `format = "getavatar-generator/1"`, `config` (the `GeneratorConfig` as JSON) and any extra
//! entries (kimg, …). Loading checks the config against the one requested and names the
//! first differing field; every parameter's name and shape is checked.

use std::collections::BTreeMap;

use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor, TensorData};

use crate::generator::network::GeneratorConfig;
use crate::generator::pipeline::{Generator, LatentModes, ModePairing};
#[cfg(not(target_arch = "wasm32"))]
use crate::generator::readback::read_f32_now;
use crate::generator::readback::ReadbackError;
use crate::reconstruction::photo_projection::SourcePhoto;

pub const FORMAT: &str = "getavatar-generator/1";

use crate::io::named_tensor::{map_named, visit_named, MapNamed, VisitNamed};
pub use crate::io::named_tensor::{unique_name, NamedTensor};

/// Names of the optional latent modes (`[K, w_dim]` each) in a generator checkpoint.
pub const MODES_GEO: &str = "latent_modes/geo";
pub const MODES_TEX: &str = "latent_modes/tex";
/// Optional per-layer offsets of the texture modes (`[K, n_tex_ws, w_dim]`,
/// `LatentModes::tex_layers`).
pub const MODES_TEX_LAYERS: &str = "latent_modes/tex_layers";
/// Metadata key: how ψ pairs the branches' modes (`subject` or `branch`, see
/// [`ModePairing`]); absent in older checkpoints: `subject`.
pub const MODES_PAIRING: &str = "latent_modes/pairing";

#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error("not a safetensors checkpoint: {0}")]
    Format(String),
    #[error("checkpoint was saved for config `{saved}` but `{requested}` was requested: {detail}")]
    ConfigMismatch { saved: String, requested: String, detail: String },
    #[error("checkpoint parameter `{0}`: {1}")]
    Param(String, String),
    #[error(transparent)]
    Readback(#[from] ReadbackError),
}

fn fmt_err(m: impl Into<String>) -> CheckpointError {
    CheckpointError::Format(m.into())
}

/// Serialise generator `g` (built with `cfg`) to safetensors bytes. Native only: it reads
/// parameters back synchronously.
#[cfg(not(target_arch = "wasm32"))]
pub fn save_generator(
    g: &Generator,
    cfg: &GeneratorConfig,
    extra: &BTreeMap<String, String>,
) -> Result<Vec<u8>, CheckpointError> {
    save_generator_with_modes(g, cfg, None, extra)
}

/// A generator file's metadata (`extra`, the format, the config) and parameters.
#[cfg(not(target_arch = "wasm32"))]
fn generator_entries(
    g: &Generator,
    cfg: &GeneratorConfig,
    extra: &BTreeMap<String, String>,
) -> Result<(BTreeMap<String, String>, Vec<NamedTensor>), CheckpointError> {
    let mut meta = extra.clone();
    meta.insert("format".into(), FORMAT.into());
    meta.insert("config".into(), serde_json::to_string(cfg).map_err(|e| fmt_err(format!("config: {e}")))?);
    Ok((meta, collect_params(g)?))
}

/// [`save_generator`] plus the latent modes for multi-modal truncation ([`MODES_GEO`],
/// [`MODES_TEX`]).
#[cfg(not(target_arch = "wasm32"))]
pub fn save_generator_with_modes(
    g: &Generator,
    cfg: &GeneratorConfig,
    modes: Option<&LatentModes>,
    extra: &BTreeMap<String, String>,
) -> Result<Vec<u8>, CheckpointError> {
    let (mut meta, mut tensors) = generator_entries(g, cfg, extra)?;
    if let Some(m) = modes {
        meta.insert(MODES_PAIRING.into(), m.pairing.as_str().into());
        for (name, t) in [(MODES_GEO, &m.geo), (MODES_TEX, &m.tex)] {
            let shape = t.dims().to_vec();
            tensors.push((name.to_string(), shape, read_f32_now(t.clone()).map_err(|e| e.context(name))?));
        }
        if let Some(t) = &m.tex_layers {
            let shape = t.dims().to_vec();
            tensors.push((
                MODES_TEX_LAYERS.into(),
                shape,
                read_f32_now(t.clone()).map_err(|e| e.context(MODES_TEX_LAYERS))?,
            ));
        }
    }
    write_safetensors(&meta, &tensors)
}

/// Tensor names of an inverted avatar's codes (W+, `[1, n, w_dim]` per branch), saved with
/// the pivotally tuned generator ([`save_inverted`]).
pub const INVERTED_GEO: &str = "inversion/w_geo";
pub const INVERTED_TEX: &str = "inversion/w_tex";
/// The photo it was made from (optional): metadata `inversion/photo` (JSON: `world_to_camera`
/// as 16 column-major numbers, `body`, `res`) and tensors `[res, res, 3]` sRGB / `[res, res]`
/// mask in [0, 1].
pub const INVERTED_PHOTO: &str = "inversion/photo";
pub const INVERTED_PHOTO_RGB: &str = "inversion/photo_rgb";
pub const INVERTED_PHOTO_MASK: &str = "inversion/photo_mask";

/// An inverted avatar (`trainer invert`'s `inverted.safetensors`, the app's "Save
/// reconstruction"): the tuned generator, its codes and, where kept, the photo it was made
/// from (so its bakes project the photo's colours again).
pub struct InvertedAvatar {
    pub generator: Generator,
    pub styles: crate::generator::pipeline::Styles,
    pub photo: Option<SourcePhoto>,
}

#[derive(serde::Serialize, serde::Deserialize)]
struct PhotoMeta {
    world_to_camera: [f32; 16],
    body: crate::body::skinning::BodyParams,
    res: usize,
}

/// The file's metadata and the entries beyond the generator's (codes and photo).
fn inverted_entries(
    codes: [(Vec<usize>, Vec<f32>); 2],
    photo: Option<&SourcePhoto>,
    meta: &mut BTreeMap<String, String>,
    tensors: &mut Vec<NamedTensor>,
) -> Result<(), CheckpointError> {
    for (name, (shape, data)) in [INVERTED_GEO, INVERTED_TEX].into_iter().zip(codes) {
        tensors.push((name.to_string(), shape, data));
    }
    if let Some(p) = photo {
        p.validate().map_err(fmt_err)?;
        let m = PhotoMeta {
            world_to_camera: p.view.world_to_camera.to_cols_array(),
            body: p.view.body.clone(),
            res: p.res,
        };
        meta.insert(INVERTED_PHOTO.into(), serde_json::to_string(&m).map_err(|e| fmt_err(format!("photo: {e}")))?);
        tensors.push((INVERTED_PHOTO_RGB.into(), vec![p.res, p.res, 3], p.rgb.clone()));
        tensors.push((INVERTED_PHOTO_MASK.into(), vec![p.res, p.res], p.mask.clone()));
    }
    Ok(())
}

/// An inverted avatar as one file: the (tuned) generator `g` of `cfg`, its codes `s` and the
/// photo it was made from. Native (synchronous read-backs); the browser uses
/// [`save_inverted_async`].
#[cfg(not(target_arch = "wasm32"))]
pub fn save_inverted(
    g: &Generator,
    cfg: &GeneratorConfig,
    s: &crate::generator::pipeline::Styles,
    photo: Option<&SourcePhoto>,
    extra: &BTreeMap<String, String>,
) -> Result<Vec<u8>, CheckpointError> {
    crate::generator::readback::block_on_ready(save_inverted_async(g, cfg, s, photo, extra))
}

/// [`save_inverted`] with awaited read-backs (the browser's WebGPU device).
pub async fn save_inverted_async(
    g: &Generator,
    cfg: &GeneratorConfig,
    s: &crate::generator::pipeline::Styles,
    photo: Option<&SourcePhoto>,
    extra: &BTreeMap<String, String>,
) -> Result<Vec<u8>, CheckpointError> {
    let mut meta = extra.clone();
    meta.insert("format".into(), FORMAT.into());
    meta.insert("config".into(), serde_json::to_string(cfg).map_err(|e| fmt_err(format!("config: {e}")))?);
    let mut tensors = collect_params_async(g).await?;
    let mut codes = Vec::new();
    for (name, t) in [(INVERTED_GEO, &s.geo), (INVERTED_TEX, &s.tex)] {
        let data = crate::generator::readback::read_f32(t.clone()).await.map_err(|e| e.context(name))?;
        codes.push((t.dims().to_vec(), data));
    }
    let codes: [(Vec<usize>, Vec<f32>); 2] = codes.try_into().map_err(|_| fmt_err("two code tensors"))?;
    inverted_entries(codes, photo, &mut meta, &mut tensors)?;
    write_safetensors(&meta, &tensors)
}

/// The generator, codes and photo of an inverted avatar ([`save_inverted`]); the codes must
/// match the generator's style counts, the photo its own size.
pub fn load_inverted(
    bytes: &[u8],
    requested: &GeneratorConfig,
    device: &Device,
) -> Result<InvertedAvatar, CheckpointError> {
    inverted_of(parse_safetensors(bytes)?, requested, device)
}

/// [`load_inverted`] from the parsed file (the browser parses and builds in separate slices
/// of the UI thread).
pub fn inverted_of(
    mut st: SafeTensors,
    requested: &GeneratorConfig,
    device: &Device,
) -> Result<InvertedAvatar, CheckpointError> {
    let photo = take_inverted_photo(&mut st)?;
    let (generator, styles) = inverted_codes(&st, requested, device)?;
    Ok(InvertedAvatar { generator, styles, photo })
}

/// An inverted avatar's tuned generator and W+ codes from the parsed file, without its photo
/// (which [`take_inverted_photo`] may already have taken out).
pub fn inverted_codes(
    st: &SafeTensors,
    requested: &GeneratorConfig,
    device: &Device,
) -> Result<(Generator, crate::generator::pipeline::Styles), CheckpointError> {
    let generator = generator_of(st, requested, device)?;
    let (ng, nt) = generator.num_ws();
    let code = |name: &str, n: usize| -> Result<Tensor<3>, CheckpointError> {
        let (shape, data) =
            st.tensors.get(name).ok_or_else(|| fmt_err(format!("{name} missing: not an inverted avatar")))?;
        if shape[..] != [1, n, requested.w_dim] {
            return Err(fmt_err(format!(
                "{name} has shape {shape:?}, the generator needs [1, {n}, {}]",
                requested.w_dim
            )));
        }
        Ok(Tensor::from_data(TensorData::new(data.clone(), [1, n, requested.w_dim]), device))
    };
    let styles = crate::generator::pipeline::Styles { geo: code(INVERTED_GEO, ng)?, tex: code(INVERTED_TEX, nt)? };
    Ok((generator, styles))
}

/// The photo an inverted avatar's file keeps (None: it keeps none), taken out of the parsed
/// file (its pixels moved, not copied) without building its generator: host memory only, no
/// device work (the browser reads it from the worker's result before it needs that generator).
pub fn take_inverted_photo(st: &mut SafeTensors) -> Result<Option<SourcePhoto>, CheckpointError> {
    Ok(match st.metadata.get(INVERTED_PHOTO) {
        None => None,
        Some(text) => {
            let m: PhotoMeta =
                serde_json::from_str(text).map_err(|e| fmt_err(format!("{INVERTED_PHOTO} metadata: {e}")))?;
            let mut take = |name: &str, shape: &[usize]| -> Result<Vec<f32>, CheckpointError> {
                let (s, d) = st.tensors.remove(name).ok_or_else(|| fmt_err(format!("{name} missing")))?;
                if s[..] != shape[..] {
                    return Err(fmt_err(format!("{name} has shape {s:?}, expected {shape:?}")));
                }
                Ok(d)
            };
            let res = m.res;
            if !(16..=4096).contains(&res) {
                return Err(fmt_err(format!("{INVERTED_PHOTO}: crop of {res} pixels (16…4096)")));
            }
            let p = SourcePhoto {
                view: crate::render::camera::View {
                    world_to_camera: glam::Mat4::from_cols_array(&m.world_to_camera),
                    body: m.body,
                },
                res,
                rgb: take(INVERTED_PHOTO_RGB, &[res, res, 3])?,
                mask: take(INVERTED_PHOTO_MASK, &[res, res])?,
            };
            p.validate().map_err(|e| fmt_err(format!("{INVERTED_PHOTO}: {e}")))?;
            Some(p)
        }
    })
}

/// The RGB discriminator (`d0/…`) of a training state (its config in the `run` metadata) or
/// of a discriminator file (`trainer train-discriminator`: the config in `discriminator`): the
/// inversion's perceptual term uses its features.
pub fn load_discriminator(
    bytes: &[u8],
    device: &Device,
) -> Result<crate::generator::network::discriminator::Discriminator, CheckpointError> {
    use crate::generator::network::discriminator::{Discriminator, DiscriminatorConfig};
    let st = parse_safetensors(bytes)?;
    let cfg: DiscriminatorConfig = if let Some(run) = st.metadata.get("run") {
        let v: serde_json::Value = serde_json::from_str(run).map_err(|e| fmt_err(format!("the run metadata: {e}")))?;
        serde_json::from_value(v["discriminator"].clone())
            .map_err(|e| fmt_err(format!("the run's discriminator config: {e}")))?
    } else if let Some(c) = st.metadata.get("discriminator") {
        serde_json::from_str(c).map_err(|e| fmt_err(format!("the discriminator config: {e}")))?
    } else {
        return Err(fmt_err("neither a training state nor a discriminator file"));
    };
    cfg.validate().map_err(|e| fmt_err(format!("the discriminator config: {e}")))?;
    // Nothing is allocated for a network the file cannot hold.
    let held: usize = st.tensors.iter().filter(|(k, _)| k.starts_with("d0/")).map(|(_, (_, v))| v.len()).sum();
    match cfg.num_params(3) {
        Some(need) if need <= held => {}
        need => {
            return Err(fmt_err(format!(
                "the discriminator config needs {} numbers, the file holds {held}",
                need.map_or("more than 2⁶⁴".to_string(), |n| n.to_string())
            )))
        }
    }
    load_params(Discriminator::new(&cfg, 3, 0, device), &st.tensors, "d0/", device)
}

/// The latent modes a generator checkpoint carries (None for checkpoints without them).
/// Both branches must be present, `[K, w_dim]` with the same K ≥ 1 and the config's w_dim.
pub fn load_latent_modes(bytes: &[u8], device: &Device) -> Result<Option<LatentModes>, CheckpointError> {
    latent_modes_of(&parse_safetensors(bytes)?, device)
}

fn latent_modes_of(st: &SafeTensors, device: &Device) -> Result<Option<LatentModes>, CheckpointError> {
    let w_dim = checkpoint_config(st)?.w_dim;
    let get = |name: &str| st.tensors.get(name);
    match (get(MODES_GEO), get(MODES_TEX)) {
        (None, None) => Ok(None),
        (Some((sg, vg)), Some((stx, vt))) => {
            let ok = |s: &Vec<usize>| s.len() == 2 && s[0] >= 1 && s[1] == w_dim;
            if !(ok(sg) && ok(stx) && sg[0] == stx[0]) {
                return Err(CheckpointError::Param(
                    MODES_GEO.into(),
                    format!("latent modes of shapes {sg:?} and {stx:?}, expected [K, {w_dim}] both"),
                ));
            }
            let t =
                |s: &Vec<usize>, v: &Vec<f32>| Tensor::<2>::from_data(TensorData::new(v.clone(), [s[0], s[1]]), device);
            let pairing = match st.metadata.get(MODES_PAIRING) {
                None => ModePairing::default(),
                Some(v) => ModePairing::parse(v).ok_or_else(|| {
                    fmt_err(format!("metadata `{MODES_PAIRING}` is {v:?}, expected \"subject\" or \"branch\""))
                })?,
            };
            let tex_layers = match get(MODES_TEX_LAYERS) {
                None => None,
                Some((s, v)) => {
                    if !(s.len() == 3 && s[0] == sg[0] && s[1] >= 1 && s[2] == w_dim) {
                        return Err(CheckpointError::Param(
                            MODES_TEX_LAYERS.into(),
                            format!("shape {s:?}, expected [{}, layers, {w_dim}]", sg[0]),
                        ));
                    }
                    Some(Tensor::<3>::from_data(TensorData::new(v.clone(), [s[0], s[1], s[2]]), device))
                }
            };
            Ok(Some(LatentModes { geo: t(sg, vg), tex: t(stx, vt), tex_layers, pairing }))
        }
        (None, Some(_)) | (Some(_), None) => {
            Err(CheckpointError::Param(MODES_GEO.into(), "only one branch's latent modes present".into()))
        }
    }
}

/// The parsed container: metadata and named (shape, values).
pub struct SafeTensors {
    pub metadata: BTreeMap<String, String>,
    pub tensors: BTreeMap<String, (Vec<usize>, Vec<f32>)>,
}

pub fn parse_safetensors(bytes: &[u8]) -> Result<SafeTensors, CheckpointError> {
    crate::util::cooperative::run_blocking(parse(bytes, false))
}

/// [`parse_safetensors`] in slices of about a megabyte of weights
/// ([`crate::util::cooperative`]): the browser's page parses a reconstruction's file.
pub async fn parse_safetensors_async(bytes: &[u8]) -> Result<SafeTensors, CheckpointError> {
    parse(bytes, false).await
}

/// Like [`parse_safetensors`], but tensors of other dtypes (e.g. PyTorch's I64
/// `num_batches_tracked` counters in converted state dicts) are skipped instead of refused.
pub fn parse_safetensors_lenient(bytes: &[u8]) -> Result<SafeTensors, CheckpointError> {
    crate::util::cooperative::run_blocking(parse(bytes, true))
}

async fn parse(bytes: &[u8], skip_other_dtypes: bool) -> Result<SafeTensors, CheckpointError> {
    /// Bytes of weights decoded between checkpoints.
    const SLICE_BYTES: usize = 1 << 20;
    // The safetensors crate validates the header (length, JSON, offsets contiguous and within
    // the file, shape × dtype = bytes with overflow checks) before anything is allocated.
    let metadata = header_metadata(bytes)?;
    let file = safetensors::SafeTensors::deserialize(bytes).map_err(|e| fmt_err(e.to_string()))?;
    let mut out = SafeTensors { metadata, tensors: BTreeMap::new() };
    let mut decoded = 0;
    for (name, view) in file.iter() {
        if view.dtype() != safetensors::Dtype::F32 {
            if skip_other_dtypes {
                continue;
            }
            return Err(CheckpointError::Param(name.into(), format!("dtype {} (only F32 is supported)", view.dtype())));
        }
        // A large tensor (a photo, a plane's weights) is decoded in slices of its own.
        let mut vals = Vec::with_capacity(view.data().len() / 4);
        for piece in view.data().chunks(SLICE_BYTES) {
            vals.extend(piece.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])));
            decoded += piece.len();
            if decoded >= SLICE_BYTES {
                decoded = 0;
                crate::util::cooperative::checkpoint().await;
            }
        }
        out.tensors.insert(name.to_string(), (view.shape().to_vec(), vals));
    }
    Ok(out)
}

/// The string metadata of a safetensors file, from its validated header alone (no tensor is
/// decoded).
fn header_metadata(bytes: &[u8]) -> Result<BTreeMap<String, String>, CheckpointError> {
    let (_, header) = safetensors::SafeTensors::read_metadata(bytes).map_err(|e| fmt_err(e.to_string()))?;
    Ok(header.metadata().iter().flatten().map(|(k, v)| (k.clone(), v.clone())).collect())
}

/// Read the config embedded in a checkpoint.
pub fn checkpoint_config(st: &SafeTensors) -> Result<GeneratorConfig, CheckpointError> {
    config_of_metadata(&st.metadata)
}

fn config_of_metadata(metadata: &BTreeMap<String, String>) -> Result<GeneratorConfig, CheckpointError> {
    if metadata.get("format").map(String::as_str) != Some(FORMAT) {
        return Err(fmt_err(format!("metadata `format` is {:?}, expected {FORMAT}", metadata.get("format"))));
    }
    let c = metadata.get("config").ok_or_else(|| fmt_err("metadata lacks `config`"))?;
    serde_json::from_str(c).map_err(|e| fmt_err(format!("embedded config: {e}")))
}

fn config_difference(a: &GeneratorConfig, b: &GeneratorConfig) -> String {
    let (ja, jb) = (serde_json::to_value(a), serde_json::to_value(b));
    let mut diffs = Vec::new();
    if let (Ok(serde_json::Value::Object(oa)), Ok(serde_json::Value::Object(ob))) = (&ja, &jb) {
        for (k, va) in oa {
            match ob.get(k) {
                Some(vb) if vb == va || k == "name" => {}
                Some(vb) => diffs.push(format!("{k} {va} vs {vb}")),
                None => diffs.push(format!("{k} {va} vs (absent)")),
            }
        }
    }
    if diffs.is_empty() {
        "same sizes, different name".into()
    } else {
        diffs.join(", ")
    }
}

struct Load<'a> {
    tensors: &'a BTreeMap<String, (Vec<usize>, Vec<f32>)>,
    device: Device,
    error: Option<CheckpointError>,
    used: usize,
    /// Parameters under these path prefixes may be missing from the file: they keep the
    /// model's own initialisation (a grown generator's new blocks).
    keep_missing: &'a [&'a str],
}

impl MapNamed for Load<'_> {
    fn map<const D: usize>(&mut self, name: String, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let want = param.val().dims().to_vec();
        match self.tensors.get(&name) {
            Some((shape, vals)) if *shape == want => {
                self.used += 1;
                let t = Tensor::<D>::from_data(TensorData::new(vals.clone(), shape.clone()), &self.device);
                // Keep the parameter trainable (a leaf that requires gradients) on autodiff devices.
                let rg = param.val().is_require_grad();
                param.map(|_| if rg { t.require_grad() } else { t })
            }
            Some((shape, _)) => {
                self.error
                    .get_or_insert(CheckpointError::Param(name, format!("shape {shape:?}, model expects {want:?}")));
                param
            }
            None if self.keep_missing.iter().any(|p| name.starts_with(p)) => param,
            None => {
                self.error.get_or_insert(CheckpointError::Param(name, "missing from the checkpoint".into()));
                param
            }
        }
    }
}

/// Load a generator of config `requested` from checkpoint bytes.
pub fn load_generator(
    bytes: &[u8],
    requested: &GeneratorConfig,
    device: &Device,
) -> Result<Generator, CheckpointError> {
    generator_of(&parse_safetensors(bytes)?, requested, device)
}

/// [`load_generator`] and [`load_latent_modes`] from one parse of the file.
pub fn load_generator_and_modes(
    bytes: &[u8],
    requested: &GeneratorConfig,
    device: &Device,
) -> Result<(Generator, Option<LatentModes>), CheckpointError> {
    let st = parse_safetensors(bytes)?;
    let g = generator_of(&st, requested, device)?;
    let modes = latent_modes_of(&st, device)?;
    if let Some(layers) = modes.as_ref().and_then(|m| m.tex_layers.as_ref()) {
        let n = g.num_ws().1;
        if layers.dims()[1] != n {
            return Err(CheckpointError::Param(
                MODES_TEX_LAYERS.into(),
                format!("{} texture layers, the generator has {n}", layers.dims()[1]),
            ));
        }
    }
    Ok((g, modes))
}

fn generator_of(st: &SafeTensors, requested: &GeneratorConfig, device: &Device) -> Result<Generator, CheckpointError> {
    let saved = checkpoint_config(st)?;
    if saved != *requested {
        return Err(CheckpointError::ConfigMismatch {
            saved: saved.name.clone(),
            requested: requested.name.clone(),
            detail: config_difference(&saved, requested),
        });
    }
    // A file's config sizes the model before any weight is read: refuse absurd sizes first.
    requested.validate().map_err(|e| fmt_err(format!("config: {e}")))?;
    // Every weight is loaded below (a missing one is an error): no random draws for them.
    let g = crate::generator::network::init::placeholder_weights(|| Generator::new(requested, 0, device));
    load_into(g, st, &[], device)
}

/// `cfg`, or the config saved in checkpoint `bytes` where that is `cfg` with other
/// resolutions: detail planes (`GeneratorConfig::texture_res` and `geometry_res`, which only
/// the synthesis's detail blocks depend on), a face plane (`face`) or tet grid (`tet_res`, which no weight depends
/// on: the file's surface is extracted on its own grid). The config to load and save such a
/// file under. Where the files differ in more, or `bytes` is no generator file, `cfg` (and
/// loading reports why).
pub fn config_with_saved_resolutions(bytes: &[u8], cfg: &GeneratorConfig) -> GeneratorConfig {
    // The header alone: the caller parses the whole file to load it.
    match header_metadata(bytes).and_then(|m| config_of_metadata(&m)) {
        Ok(saved) if with_resolutions_of(cfg, &saved) == saved && saved.validate().is_ok() => saved,
        _ => cfg.clone(),
    }
}

/// `cfg` with the detail planes (`texture_res`, `geometry_res`), the face plane (`face`) and
/// the tet grid (`tet_res`) of `other`.
fn with_resolutions_of(cfg: &GeneratorConfig, other: &GeneratorConfig) -> GeneratorConfig {
    GeneratorConfig {
        texture_res: other.texture_res,
        geometry_res: other.geometry_res,
        face: other.face.clone(),
        tet_res: other.tet_res,
        ..cfg.clone()
    }
}

/// A generator of config `requested` from a checkpoint saved with coarser detail planes:
/// the same config but a smaller `texture_res` and/or `geometry_res` (e.g. the paper's
/// planes, none), no face plane where `requested` has one, and any tet grid (`tet_res`).
/// Every saved weight is loaded; the detail blocks and face plane the file lacks keep their
/// initialisation (the generator built with `seed`), whose output layers (the face plane's
/// constant) are zero, so the grown generator renders what the saved one rendered, up to the
/// bilinear upsampling of the grown planes.
pub fn load_generator_growing(
    bytes: &[u8],
    requested: &GeneratorConfig,
    seed: u64,
    device: &Device,
) -> Result<Generator, CheckpointError> {
    let st = parse_safetensors(bytes)?;
    let saved = checkpoint_config(&st)?;
    let same_but_res = GeneratorConfig { name: saved.name.clone(), ..with_resolutions_of(requested, &saved) };
    if same_but_res != saved
        || requested.texture_plane_res() < saved.texture_plane_res()
        || requested.geometry_plane_res() < saved.geometry_plane_res()
        || (saved.face.is_some() && saved.face != requested.face)
    {
        return Err(CheckpointError::ConfigMismatch {
            saved: saved.name.clone(),
            requested: requested.name.clone(),
            detail: config_difference(&saved, requested),
        });
    }
    requested.validate().map_err(|e| fmt_err(format!("config: {e}")))?;
    let grown = ["synthesis.texture_detail.", "synthesis.geometry_detail.", "face."];
    load_into(Generator::new(requested, seed, device), &st, &grown, device)
}

/// Load `st`'s weights into `g` (see [`Load`]); every tensor of the file but the latent modes
/// and an inversion's codes must be used.
fn load_into(
    g: Generator,
    st: &SafeTensors,
    keep_missing: &[&str],
    device: &Device,
) -> Result<Generator, CheckpointError> {
    let mut l = Load { tensors: &st.tensors, device: device.clone(), error: None, used: 0, keep_missing };
    let g = map_named(g, &mut l);
    if let Some(e) = l.error {
        return Err(e);
    }
    let modes = st
        .tensors
        .keys()
        .filter(|k| {
            [
                MODES_GEO,
                MODES_TEX,
                MODES_TEX_LAYERS,
                INVERTED_GEO,
                INVERTED_TEX,
                INVERTED_PHOTO_RGB,
                INVERTED_PHOTO_MASK,
            ]
            .contains(&k.as_str())
        })
        .count();
    if l.used + modes != st.tensors.len() {
        return Err(fmt_err(format!("{} tensors in the file, {} used by the model", st.tensors.len(), l.used)));
    }
    Ok(g)
}

/// Every float parameter of `module` as (name by module path, shape, values). Native only.
#[cfg(not(target_arch = "wasm32"))]
pub fn collect_params<M: Module>(module: &M) -> Result<Vec<NamedTensor>, CheckpointError> {
    crate::generator::readback::block_on_ready(collect_params_async(module))
}

/// [`collect_params`] with awaited read-backs (every platform; the browser's device).
pub async fn collect_params_async<M: Module>(module: &M) -> Result<Vec<NamedTensor>, CheckpointError> {
    /// The parameters flattened (the visitor cannot await), read back afterwards.
    struct Flat {
        out: Vec<(String, Vec<usize>, Tensor<1>)>,
    }
    impl VisitNamed for Flat {
        fn visit<const D: usize>(&mut self, name: String, param: &Param<Tensor<D>>) {
            let tensor = param.val();
            let shape = tensor.dims().to_vec();
            let n = shape.iter().product::<usize>();
            self.out.push((name, shape, tensor.reshape([n])));
        }
    }
    let mut f = Flat { out: Vec::new() };
    visit_named(module, &mut f);
    if f.out.is_empty() {
        return Ok(Vec::new());
    }
    // One read-back of all of them, concatenated on the device (one per parameter cost the
    // browser tens of seconds on an emulated GPU).
    let flat = Tensor::cat(f.out.iter().map(|(_, _, t)| t.clone().detach()).collect(), 0);
    let all = crate::generator::readback::read_f32(flat)
        .await
        .map_err(|e| CheckpointError::Readback(e.context("the parameters")))?;
    let mut out = Vec::with_capacity(f.out.len());
    let mut at = 0;
    for (name, shape, _) in f.out {
        let n = shape.iter().product::<usize>();
        let data = all.get(at..at + n).ok_or_else(|| fmt_err(format!("{name}: the read-back is short")))?.to_vec();
        at += n;
        out.push((name, shape, data));
    }
    Ok(out)
}

/// Replace `module`'s parameters with the tensors named `prefix + name` (all must be present
/// with matching shapes).
pub fn load_params<M: Module>(
    module: M,
    tensors: &BTreeMap<String, (Vec<usize>, Vec<f32>)>,
    prefix: &str,
    device: &Device,
) -> Result<M, CheckpointError> {
    let sub: BTreeMap<String, (Vec<usize>, Vec<f32>)> =
        tensors.iter().filter_map(|(k, v)| k.strip_prefix(prefix).map(|rest| (rest.to_string(), v.clone()))).collect();
    let mut l = Load { tensors: &sub, device: device.clone(), error: None, used: 0, keep_missing: &[] };
    let m = map_named(module, &mut l);
    match l.error {
        Some(e) => Err(e),
        None => Ok(m),
    }
}

/// Serialise named F32 tensors and string metadata as safetensors bytes, deterministically
/// (metadata and tensors in name order), so that identical training states give identical
/// files. The safetensors crate's own serializer orders the metadata by a randomly seeded hash
/// map; what it parses (and validates) is this same container. A tensor whose shape does not
/// match its values is an error.
pub fn write_safetensors(
    metadata: &BTreeMap<String, String>,
    tensors: &[NamedTensor],
) -> Result<Vec<u8>, CheckpointError> {
    let mut header = serde_json::Map::new();
    let meta: serde_json::Map<String, serde_json::Value> =
        metadata.iter().map(|(k, v)| (k.clone(), serde_json::Value::from(v.clone()))).collect();
    header.insert("__metadata__".into(), meta.into());
    let mut sorted: Vec<&(String, Vec<usize>, Vec<f32>)> = tensors.iter().collect();
    sorted.sort_by(|a, b| a.0.cmp(&b.0));
    let mut offset = 0usize;
    for (name, shape, data) in &sorted {
        let n = shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d));
        if n != Some(data.len()) {
            return Err(CheckpointError::Param(name.clone(), format!("shape {shape:?} but {} values", data.len())));
        }
        let end = offset + data.len() * 4;
        header
            .insert(name.clone(), serde_json::json!({ "dtype": "F32", "shape": shape, "data_offsets": [offset, end] }));
        offset = end;
    }
    let mut h = serde_json::Value::Object(header).to_string().into_bytes();
    while h.len() % 8 != 0 {
        h.push(b' ');
    }
    let mut out = Vec::with_capacity(8 + h.len() + offset);
    out.extend_from_slice(&(h.len() as u64).to_le_bytes());
    out.extend_from_slice(&h);
    for (_, _, data) in &sorted {
        for x in data {
            out.extend_from_slice(&x.to_le_bytes());
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A safetensors file whose header is `json`, followed by `data`.
    fn file(json: &str, data: &[u8]) -> Vec<u8> {
        let mut out = (json.len() as u64).to_le_bytes().to_vec();
        out.extend_from_slice(json.as_bytes());
        out.extend_from_slice(data);
        out
    }

    #[test]
    fn hostile_headers_are_refused_without_overflow_or_allocation() {
        let huge = 1u64 << 62;
        let cases = [
            // shape product × 4 overflows usize.
            format!(r#"{{"a":{{"dtype":"F32","shape":[{huge},{huge}],"data_offsets":[0,0]}}}}"#),
            // a shape that claims far more than the file holds.
            r#"{"a":{"dtype":"F32","shape":[1000000000],"data_offsets":[0,8]}}"#.to_string(),
            // offsets past the end, reversed, or overlapping.
            r#"{"a":{"dtype":"F32","shape":[2],"data_offsets":[0,4096]}}"#.to_string(),
            r#"{"a":{"dtype":"F32","shape":[0],"data_offsets":[8,0]}}"#.to_string(),
            r#"{"a":{"dtype":"F32","shape":[2],"data_offsets":[0,8]},"b":{"dtype":"F32","shape":[2],"data_offsets":[4,12]}}"#.to_string(),
            // not JSON, not an object.
            "{\"a\":".to_string(),
            "[1, 2]".to_string(),
        ];
        for json in &cases {
            assert!(parse_safetensors(&file(json, &[0u8; 8])).is_err(), "accepted {json}");
        }
        // A header length beyond the file, or beyond usize.
        let mut lie = u64::MAX.to_le_bytes().to_vec();
        lie.extend_from_slice(b"{}");
        assert!(parse_safetensors(&lie).is_err());
        assert!(parse_safetensors(&[1, 2, 3]).is_err());
    }

    /// The size check before building a discriminator counts exactly what `new` allocates,
    /// and a small file whose config claims a huge network is refused at once.
    #[test]
    fn discriminator_configs_are_checked_against_the_file() {
        use crate::generator::network::discriminator::{Discriminator, DiscriminatorConfig};
        #[allow(deprecated)]
        let dev = Device::ndarray();
        for cfg in [DiscriminatorConfig::new(8, 64, 8), DiscriminatorConfig::new(64, 2048, 64)] {
            let d = Discriminator::new(&cfg, 3, 0, &dev);
            assert_eq!(cfg.num_params(3), Some(d.num_params()), "{cfg:?}");
        }
        let huge = DiscriminatorConfig { c_dim: usize::MAX / 2, ..DiscriminatorConfig::new(8, 64, 8) };
        assert_eq!(huge.num_params(3), None);
        // The `checkpoint` fuzz target's find: channel_max 0 panicked in clamp(1, 0).
        let crash = include_bytes!(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../fuzz/regressions/checkpoint/discriminator-channel-max-0"
        ));
        let err = load_discriminator(crash, &dev).err().unwrap().to_string();
        assert!(err.contains("channel_max 0 is outside 1..="), "{err}");
        let meta: BTreeMap<String, String> = [(
            "discriminator".to_string(),
            r#"{"resolution":4096,"channel_base":1048576,"channel_max":65536,"c_dim":16,"cmap_dim":64,"mapping_layers":2,"mbstd_group":4}"#.to_string(),
        )]
        .into();
        let bytes = write_safetensors(&meta, &[("d0/x".into(), vec![2], vec![0.0; 2])]).unwrap();
        let t0 = std::time::Instant::now();
        let err = load_discriminator(&bytes, &dev).err().unwrap().to_string();
        assert!(err.contains("the file holds 2"), "{err}");
        assert!(t0.elapsed().as_secs_f32() < 1.0);
    }

    #[test]
    fn tensors_and_metadata_round_trip() {
        let meta: BTreeMap<String, String> = [("format".to_string(), "x".to_string())].into();
        let tensors = vec![
            ("b.weight".to_string(), vec![2, 3], vec![1.0, -2.0, 3.5, 0.0, 5.0, f32::MIN_POSITIVE]),
            ("a".to_string(), vec![1], vec![7.0]),
        ];
        let bytes = write_safetensors(&meta, &tensors).unwrap();
        // Deterministic: the same input gives the same bytes (bit-identical resumes).
        assert_eq!(bytes, write_safetensors(&meta, &tensors).unwrap());
        let st = parse_safetensors(&bytes).unwrap();
        assert_eq!(st.metadata, meta);
        for (name, shape, vals) in &tensors {
            assert_eq!(st.tensors[name], (shape.clone(), vals.clone()), "{name}");
        }
        // A tensor whose shape does not match its values is refused, not written.
        assert!(write_safetensors(&meta, &[("c".into(), vec![4], vec![1.0])]).is_err());
    }

    /// An inverted avatar's file keeps the generator, the codes and the photo exactly; a
    /// photo whose stored size or values do not fit is refused with the reason.
    #[test]
    fn inverted_avatars_round_trip_with_their_photo() {
        #[allow(deprecated)]
        let dev = Device::ndarray();
        let cfg = GeneratorConfig::tiny();
        let g = Generator::new(&cfg, 3, &dev);
        let (ng, nt) = g.num_ws();
        let codes = |n: usize, o: f32| {
            let v: Vec<f32> = (0..n * cfg.w_dim).map(|k| (k as f32 * 0.37 + o).sin()).collect();
            Tensor::<3>::from_data(TensorData::new(v, [1, n, cfg.w_dim]), &dev)
        };
        let s = crate::generator::pipeline::Styles { geo: codes(ng, 0.0), tex: codes(nt, 1.0) };
        let res = 16;
        let mut body = crate::body::skinning::BodyParams { betas: vec![0.3, -0.2, 0.1], ..Default::default() };
        body.pose[16].z = -1.1;
        body.transl.y = 0.05;
        let photo = SourcePhoto {
            view: crate::render::camera::View {
                world_to_camera: crate::render::camera::OrbitCamera { yaw: 0.4, ..Default::default() }
                    .world_to_camera(),
                body,
            },
            res,
            rgb: (0..res * res * 3).map(|k| (k % 7) as f32 / 6.0).collect(),
            mask: (0..res * res).map(|k| (k % 3 == 0) as u8 as f32).collect(),
        };
        let extra = BTreeMap::new();
        let bytes = save_inverted(&g, &cfg, &s, Some(&photo), &extra).unwrap();
        let inv = load_inverted(&bytes, &cfg, &dev).unwrap();
        assert_eq!(inv.photo.as_ref(), Some(&photo));
        let read = |t: &Tensor<3>| read_f32_now(t.clone()).unwrap();
        assert_eq!(read(&inv.styles.geo), read(&s.geo));
        assert_eq!(read(&inv.styles.tex), read(&s.tex));
        assert_eq!(collect_params(&inv.generator).unwrap(), collect_params(&g).unwrap());
        // Without a photo: none comes back.
        let bare = save_inverted(&g, &cfg, &s, None, &extra).unwrap();
        assert!(load_inverted(&bare, &cfg, &dev).unwrap().photo.is_none());
        // A photo mask of the wrong size, or a colour outside [0, 1]: refused.
        let mut st = parse_safetensors(&bytes).unwrap();
        let mut tensors: Vec<NamedTensor> =
            st.tensors.iter().map(|(k, (sh, d))| (k.clone(), sh.clone(), d.clone())).collect();
        for t in tensors.iter_mut().filter(|t| t.0 == INVERTED_PHOTO_MASK) {
            *t = (t.0.clone(), vec![res, res - 1], vec![0.5; res * (res - 1)]);
        }
        let e = load_inverted(&write_safetensors(&st.metadata, &tensors).unwrap(), &cfg, &dev).err().unwrap();
        assert!(e.to_string().contains("photo_mask has shape [16, 15]"), "{e}");
        st.tensors.get_mut(INVERTED_PHOTO_RGB).unwrap().1[5] = 3.0;
        let tensors: Vec<NamedTensor> =
            st.tensors.iter().map(|(k, (sh, d))| (k.clone(), sh.clone(), d.clone())).collect();
        let e = load_inverted(&write_safetensors(&st.metadata, &tensors).unwrap(), &cfg, &dev).err().unwrap();
        assert!(e.to_string().contains("outside [0, 1]"), "{e}");
    }
}
