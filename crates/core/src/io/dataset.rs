//! The training dataset in the reference code's layout (native only: feature `dataset`).
//!
//! ```text
//! DIR/dataset.json                 {"labels": {"<subject>/<view>.png": [98 floats], ...}}
//! DIR/<subject>/<view>.png         RGBA, sRGB colours on white, alpha = mask
//! DIR/<subject>/<view>_normal.png  RGB world-space normals (n+1)·127.5, background (128,128,128)
//! ```
//! A label is 16 world-to-camera numbers (row-major 4×4, OpenGL camera, fov 49.13°), then
//! 3 global orientation + 69 body pose (SMPL axis-angle) + 10 betas. The format is described
//! in `docs/dataset.md`. Normal maps are optional for a whole dataset (transfer learning on
//! RGB-only data), never for part of one.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::Mat4;

use crate::body::skinning::BodyParams;
use crate::io::scan::{parse_mtl, parse_obj, Scan, ScanError, SmplParams};
use crate::render::camera::{from_row_major, to_row_major};
use crate::render::rasterize::{RenderedViews, Texture};

/// Name of the labels file in a dataset directory.
pub const LABELS_FILE: &str = "dataset.json";
/// Numbers per label: 16 camera + 3 global orient + 69 body pose + 10 betas.
pub const LABEL_LEN: usize = 98;
/// Betas stored per label.
pub const LABEL_BETAS: usize = 10;

/// Dataset errors; each names the file or labels entry at fault.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: {msg}")]
    Labels { path: PathBuf, msg: String },
    #[error("label `{entry}`: {msg}")]
    Label { entry: String, msg: String },
    #[error("{path}: {msg}")]
    Image { path: PathBuf, msg: String },
    #[error("{path}: {source}")]
    Scan { path: PathBuf, source: ScanError },
}

/// One image's label.
#[derive(Clone, Debug, PartialEq)]
pub struct Label {
    pub world_to_camera: Mat4,
    pub global_orient: [f32; 3],
    pub body_pose: [f32; 69],
    pub betas: [f32; LABEL_BETAS],
}

impl Label {
    pub fn new(world_to_camera: Mat4, body: &BodyParams) -> Self {
        let theta = body.theta();
        let mut betas = [0.0; LABEL_BETAS];
        for (b, v) in betas.iter_mut().zip(&body.betas) {
            *b = *v;
        }
        Self {
            world_to_camera,
            global_orient: std::array::from_fn(|i| theta[i]),
            body_pose: std::array::from_fn(|i| theta[3 + i]),
            betas,
        }
    }

    /// The 98 numbers in file order.
    pub fn to_floats(&self) -> Vec<f32> {
        let mut v = Vec::with_capacity(LABEL_LEN);
        v.extend_from_slice(&to_row_major(self.world_to_camera));
        v.extend_from_slice(&self.global_orient);
        v.extend_from_slice(&self.body_pose);
        v.extend_from_slice(&self.betas);
        v
    }

    /// Parse the 98 numbers of `entry`; wrong counts and non-finite values are errors naming it.
    pub fn from_floats(entry: &str, v: &[f32]) -> Result<Self, DatasetError> {
        let err = |msg: String| DatasetError::Label { entry: entry.to_string(), msg };
        if v.len() != LABEL_LEN {
            return Err(err(format!(
                "{} numbers, expected {LABEL_LEN} (16 world-to-camera + 3 global orient + 69 body pose + 10 betas)",
                v.len()
            )));
        }
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            return Err(err(format!("number {i} is not finite")));
        }
        // The length is checked above: the fixed-size copies below cannot go out of range.
        let m = from_row_major(&std::array::from_fn(|i| v[i]));
        if (m.row(3) - glam::Vec4::W).abs().max_element() > 1e-4 {
            return Err(err(format!("the camera matrix's last row is {:?}, expected [0, 0, 0, 1]", m.row(3))));
        }
        Ok(Self {
            world_to_camera: m,
            global_orient: std::array::from_fn(|i| v[16 + i]),
            body_pose: std::array::from_fn(|i| v[19 + i]),
            betas: std::array::from_fn(|i| v[88 + i]),
        })
    }

    /// The body parameters of the label (no translation: labels are in the body frame).
    pub fn body_params(&self) -> BodyParams {
        BodyParams::from_split(&self.global_orient, &self.body_pose, &self.betas)
    }

    /// The camera and body of this label, as the renderers take them.
    pub fn view(&self) -> crate::render::camera::View {
        crate::render::camera::View { world_to_camera: self.world_to_camera, body: self.body_params() }
    }
}

/// `{"labels": {...}}` with entries sorted by name.
pub fn labels_to_json(entries: &[(String, Label)]) -> String {
    let map: BTreeMap<&str, Vec<f32>> = entries.iter().map(|(k, l)| (k.as_str(), l.to_floats())).collect();
    serde_json::json!({ "labels": map }).to_string()
}

/// Parse a labels file's text (`path` only names it in errors). Entries come back sorted.
pub fn parse_labels(path: &Path, text: &str) -> Result<Vec<(String, Label)>, DatasetError> {
    let lerr = |msg: String| DatasetError::Labels { path: path.to_path_buf(), msg };
    let v: serde_json::Value = serde_json::from_str(text).map_err(|e| lerr(format!("not JSON: {e}")))?;
    let labels = v.get("labels").ok_or_else(|| lerr("no `labels` key".into()))?;
    let obj = labels.as_object().ok_or_else(|| lerr("`labels` is not an object".into()))?;
    let mut out = Vec::with_capacity(obj.len());
    for (name, val) in obj {
        let arr = val
            .as_array()
            .ok_or_else(|| DatasetError::Label { entry: name.clone(), msg: "not an array of numbers".into() })?;
        let floats: Vec<f32> = arr
            .iter()
            .map(|x| x.as_f64().map(|f| f as f32))
            .collect::<Option<_>>()
            .ok_or_else(|| DatasetError::Label { entry: name.clone(), msg: "contains a non-number".into() })?;
        out.push((name.clone(), Label::from_floats(name, &floats)?));
    }
    out.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(out)
}

/// The `<view>_normal.png` name that goes with `<view>.png`.
pub fn normal_name(image: &str) -> String {
    match image.strip_suffix(".png") {
        Some(stem) => format!("{stem}_normal.png"),
        None => format!("{image}_normal.png"),
    }
}

/// Encode rendered views as the dataset's RGBA image (alpha = mask) and RGB normal map.
pub fn encode_views(v: &RenderedViews) -> Result<(Vec<u8>, Vec<u8>), PngEncodeError> {
    let rgba: Vec<u8> = v.rgb.chunks_exact(3).zip(&v.mask).flat_map(|(c, m)| [c[0], c[1], c[2], *m]).collect();
    Ok((encode_png(v.size, v.size, 4, &rgba)?, encode_png(v.size, v.size, 3, &v.normal)?))
}

/// Why pixels could not be encoded as PNG.
#[derive(Debug, thiserror::Error)]
pub enum PngEncodeError {
    #[error("{0} channels per pixel (1–4 are supported)")]
    Channels(usize),
    #[error("{len} bytes of pixels for a {width}×{height} image of {channels} channels")]
    Pixels { width: usize, height: usize, channels: usize, len: usize },
    #[error(transparent)]
    Png(#[from] png::EncodingError),
}

/// Encode 8-bit pixels (1–4 channels, row-major from the top) as PNG; a pixel buffer of the
/// wrong length or a size PNG cannot hold is an error.
pub fn encode_png(width: usize, height: usize, channels: usize, pixels: &[u8]) -> Result<Vec<u8>, PngEncodeError> {
    let color = match channels {
        1 => png::ColorType::Grayscale,
        2 => png::ColorType::GrayscaleAlpha,
        3 => png::ColorType::Rgb,
        4 => png::ColorType::Rgba,
        _ => return Err(PngEncodeError::Channels(channels)),
    };
    if width.checked_mul(height).and_then(|n| n.checked_mul(channels)) != Some(pixels.len()) {
        return Err(PngEncodeError::Pixels { width, height, channels, len: pixels.len() });
    }
    let (Ok(w), Ok(h)) = (u32::try_from(width), u32::try_from(height)) else {
        return Err(PngEncodeError::Pixels { width, height, channels, len: pixels.len() });
    };
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, w, h);
    enc.set_color(color);
    enc.set_depth(png::BitDepth::Eight);
    let mut writer = enc.write_header()?;
    writer.write_image_data(pixels)?;
    writer.finish()?;
    Ok(out)
}

/// A decoded 8-bit image.
#[derive(Clone, Debug, PartialEq)]
pub struct Image8 {
    pub width: usize,
    pub height: usize,
    /// 1 (grey), 2 (grey + alpha), 3 (RGB) or 4 (RGBA).
    pub channels: usize,
    pub pixels: Vec<u8>,
}

/// Refuse a PNG whose palette (PLTE) length is not a multiple of 3: the png crate (0.17 and
/// 0.18.1) panics on one while expanding it (image-rs/image-png#694, fixed upstream after
/// 0.18.1; found here by the `photo` fuzz target). Other bytes pass unchanged.
fn check_png_palette(bytes: &[u8]) -> Result<(), String> {
    const SIGNATURE: &[u8] = b"\x89PNG\r\n\x1a\n";
    let Some(mut rest) = bytes.strip_prefix(SIGNATURE) else { return Ok(()) };
    while rest.len() >= 8 {
        let len = u32::from_be_bytes([rest[0], rest[1], rest[2], rest[3]]) as usize;
        let kind = &rest[4..8];
        if kind == b"PLTE" && len % 3 != 0 {
            return Err(format!("is a PNG with a malformed palette ({len} bytes, not a multiple of 3)"));
        }
        if kind == b"IDAT" || kind == b"IEND" {
            break;
        }
        // Length, type, data and checksum.
        match rest.get(12usize.saturating_add(len)..) {
            Some(r) => rest = r,
            None => break,
        }
    }
    Ok(())
}

/// Decode a PNG (any bit depth, palettes expanded, 16-bit reduced to 8).
pub fn decode_png(bytes: &[u8]) -> Result<Image8, String> {
    check_png_palette(bytes).map_err(|e| format!("not a usable PNG: it {e}"))?;
    let mut dec = png::Decoder::new(std::io::Cursor::new(bytes));
    dec.set_transformations(png::Transformations::normalize_to_color8());
    let mut reader = dec.read_info().map_err(|e| format!("not a PNG: {e}"))?;
    // The header's size is checked before the pixel buffer is allocated (a 100-byte file may
    // claim 1026 × 771 million pixels: found by the `photo` fuzz target).
    let (w, h) = (reader.info().width as u64, reader.info().height as u64);
    if w * h > MAX_PHOTO_PIXELS {
        return Err(format!("a {w}×{h} PNG is over the {} MP limit", MAX_PHOTO_PIXELS / 1_000_000));
    }
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).map_err(|e| format!("corrupt PNG: {e}"))?;
    buf.truncate(info.buffer_size());
    let channels = match info.color_type {
        png::ColorType::Grayscale => 1,
        png::ColorType::GrayscaleAlpha => 2,
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        png::ColorType::Indexed => return Err("unexpanded palette".into()),
    };
    Ok(Image8 { width: info.width as usize, height: info.height as usize, channels, pixels: buf })
}

pub use crate::body::body_fit::framing::MAX_PHOTO_PIXELS;

/// Decode a photo (PNG or JPEG, the format guessed from its bytes). Its size is read from the
/// header and checked against [`MAX_PHOTO_PIXELS`] before any pixel buffer is allocated, and
/// the decoder's own allocations are capped, so a small file claiming a huge image is refused
/// at once. Errors read after the file's name ("photo.png is not a PNG or JPEG image (…)").
pub fn decode_photo(bytes: &[u8]) -> Result<image::DynamicImage, String> {
    let reader = || {
        image::ImageReader::new(std::io::Cursor::new(bytes))
            .with_guessed_format()
            .map_err(|e| format!("cannot be read ({e})"))
    };
    let (w, h) = reader()?.into_dimensions().map_err(|e| format!("is not a PNG or JPEG image ({e})"))?;
    if w == 0 || h == 0 {
        return Err(format!("is empty ({w}×{h} pixels)"));
    }
    if (w as u64) * (h as u64) > MAX_PHOTO_PIXELS {
        return Err(format!("is {w}×{h} pixels, over the {} MP limit", MAX_PHOTO_PIXELS / 1_000_000));
    }
    check_png_palette(bytes)?;
    let mut r = reader()?;
    let mut limits = image::Limits::default();
    // 16-bit RGBA of the largest accepted photo, plus the decoder's scratch.
    limits.max_alloc = Some(MAX_PHOTO_PIXELS * 8 + (64 << 20));
    r.limits(limits);
    r.decode().map_err(|e| format!("is not a readable PNG or JPEG image ({e})"))
}

/// One training example.
#[derive(Clone, Debug)]
pub struct Sample {
    pub name: String,
    pub size: usize,
    /// sRGB colours in [0, 1], `size²·3`, row-major from the top.
    pub rgb: Vec<f32>,
    /// Mask in [0, 1], `size²`.
    pub mask: Vec<f32>,
    /// World-space normals in [−1, 1], `size²·3` (zero vector on background), if the dataset has them.
    pub normal: Option<Vec<f32>>,
    pub label: Label,
}

/// A dataset directory opened for reading.
#[derive(Clone, Debug)]
pub struct Dataset {
    pub root: PathBuf,
    pub entries: Vec<(String, Label)>,
    /// Image side in pixels (all images are square and this size).
    pub resolution: usize,
    /// Whether every image has a `_normal.png` (false: none has).
    pub has_normals: bool,
}

fn read(path: &Path) -> Result<Vec<u8>, DatasetError> {
    std::fs::read(path).map_err(|source| DatasetError::Io { path: path.to_path_buf(), source })
}

// Scans on disk: the input of `trainer prepare` and of the training's scan terms (paper
// Sec. 5: one folder per subject with its OBJ, MTL, textures and body fit `smpl.json`).

/// Subject folders (sorted by name) of a scans directory: those holding an `.obj` (the
/// first by name when several).
pub fn find_scans(scans: &Path) -> Result<Vec<(String, PathBuf)>, DatasetError> {
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| DatasetError::Io { path, source }
    };
    let mut out = Vec::new();
    for e in std::fs::read_dir(scans).map_err(io(scans))? {
        let e = e.map_err(io(scans))?;
        let dir = e.path();
        if !e.file_type().map_err(io(&dir))?.is_dir() {
            continue;
        }
        let mut objs = Vec::new();
        for f in std::fs::read_dir(&dir).map_err(io(&dir))? {
            let p = f.map_err(io(&dir))?.path();
            if p.extension().is_some_and(|x| x.eq_ignore_ascii_case("obj")) {
                objs.push(p);
            }
        }
        objs.sort();
        if let Some(obj) = objs.into_iter().next() {
            out.push((e.file_name().to_string_lossy().into_owned(), obj));
        }
    }
    out.sort();
    Ok(out)
}

fn read_text(path: &Path) -> Result<String, DatasetError> {
    std::fs::read_to_string(path).map_err(|source| DatasetError::Io { path: path.to_path_buf(), source })
}

/// Load a scan: the OBJ, its MTL files (next to it) and their textures (PNG or JPEG).
pub fn load_scan(obj_path: &Path) -> Result<Scan, DatasetError> {
    let dir = obj_path.parent().unwrap_or(Path::new("."));
    let scan_err = |path: &Path| {
        let path = path.to_path_buf();
        move |source| DatasetError::Scan { path, source }
    };
    let mesh = parse_obj(&read_text(obj_path)?).map_err(scan_err(obj_path))?;
    let mut materials = Vec::new();
    for lib in &mesh.mtllibs {
        let p = dir.join(lib);
        materials.extend(parse_mtl(&read_text(&p)?).map_err(scan_err(&p))?);
    }
    let mut textures = Vec::new();
    let mut colors = Vec::new();
    for name in &mesh.materials {
        // Faces without `usemtl` use the only material when there is exactly one.
        let m =
            materials.iter().find(|m| &m.name == name).or(if materials.len() == 1 { materials.first() } else { None });
        colors.push(m.map_or(glam::Vec3::splat(0.8), |m| m.kd));
        let tex = match m.and_then(|m| m.map_kd.as_ref()) {
            Some(file) => Some(load_texture(&dir.join(file))?),
            None => None,
        };
        textures.push(tex);
    }
    if mesh.uvs.is_empty() && textures.iter().any(Option::is_some) {
        return Err(DatasetError::Image {
            path: obj_path.to_path_buf(),
            msg: "textured material but the OBJ has no texture coordinates (vt)".into(),
        });
    }
    Ok(Scan { mesh, textures, colors })
}

/// A scan's texture image (PNG or JPEG, by content), as sRGB 8-bit RGB.
fn load_texture(path: &Path) -> Result<Texture, DatasetError> {
    let bad = |msg: String| DatasetError::Image { path: path.to_path_buf(), msg };
    let img = image::load_from_memory(&read(path)?).map_err(|e| bad(format!("texture: {e}")))?.to_rgb8();
    Texture::from_srgb8(img.width() as usize, img.height() as usize, 3, img.as_raw())
        .ok_or_else(|| bad("texture is empty".into()))
}

/// A subject's body fit: `<smpl_dir>/<subject>.json` where given and present, else
/// `smpl.json` next to its OBJ.
pub fn load_body_fit(subject: &str, obj: &Path, smpl_dir: Option<&Path>) -> Result<SmplParams, DatasetError> {
    let mut candidates = vec![obj.parent().unwrap_or(Path::new(".")).join("smpl.json")];
    if let Some(d) = smpl_dir {
        candidates.insert(0, d.join(format!("{subject}.json")));
    }
    let Some(path) = candidates.iter().find(|p| p.is_file()) else {
        let looked = candidates.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", ");
        return Err(DatasetError::Labels { path: obj.to_path_buf(), msg: format!("no body fit: looked for {looked}") });
    };
    SmplParams::from_json(&read_text(path)?).map_err(|source| DatasetError::Scan { path: path.clone(), source })
}

impl Dataset {
    /// Open `root`: parse and validate `dataset.json`, check that every image (and either
    /// every normal map or none) exists, and read the resolution from the first image.
    pub fn open(root: &Path) -> Result<Self, DatasetError> {
        let lpath = root.join(LABELS_FILE);
        let text = String::from_utf8(read(&lpath)?)
            .map_err(|_| DatasetError::Labels { path: lpath.clone(), msg: "not UTF-8".into() })?;
        let entries = parse_labels(&lpath, &text)?;
        if entries.is_empty() {
            return Err(DatasetError::Labels { path: lpath, msg: "no labels".into() });
        }
        let mut with_normals = 0;
        for (name, _) in &entries {
            let p = root.join(name);
            if !p.is_file() {
                return Err(DatasetError::Image { path: p, msg: "listed in dataset.json but missing".into() });
            }
            if root.join(normal_name(name)).is_file() {
                with_normals += 1;
            }
        }
        let partial = with_normals != 0 && with_normals != entries.len();
        if let Some(missing) = entries.iter().find(|(n, _)| partial && !root.join(normal_name(n)).is_file()) {
            return Err(DatasetError::Image {
                path: root.join(normal_name(&missing.0)),
                msg: format!("missing, but {with_normals} of {} images have normal maps", entries.len()),
            });
        }
        let first = root.join(&entries[0].0);
        let img = decode_png(&read(&first)?).map_err(|msg| DatasetError::Image { path: first.clone(), msg })?;
        if img.width != img.height {
            return Err(DatasetError::Image {
                path: first,
                msg: format!("{}×{} is not square", img.width, img.height),
            });
        }
        Ok(Self { root: root.to_path_buf(), entries, resolution: img.width, has_normals: with_normals > 0 })
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Load example `i`: decode and validate its images (size, channels).
    pub fn load(&self, i: usize) -> Result<Sample, DatasetError> {
        let (name, label) = &self.entries[i];
        let size = self.resolution;
        let path = self.root.join(name);
        let bad = |path: &Path, msg: String| DatasetError::Image { path: path.to_path_buf(), msg };
        let img = decode_png(&read(&path)?).map_err(|m| bad(&path, m))?;
        if img.width != size || img.height != size {
            return Err(bad(&path, format!("{}×{}, expected {size}×{size}", img.width, img.height)));
        }
        if img.channels != 4 && img.channels != 2 {
            return Err(bad(&path, "no alpha channel (the alpha channel is the mask)".into()));
        }
        let c = img.channels;
        let mut rgb = Vec::with_capacity(size * size * 3);
        let mut mask = Vec::with_capacity(size * size);
        for p in img.pixels.chunks_exact(c) {
            if c == 4 {
                rgb.extend(p[..3].iter().map(|&x| x as f32 / 255.0));
            } else {
                rgb.extend([p[0] as f32 / 255.0; 3]);
            }
            mask.push(p[c - 1] as f32 / 255.0);
        }
        let normal = if self.has_normals {
            let npath = self.root.join(normal_name(name));
            let n = decode_png(&read(&npath)?).map_err(|m| bad(&npath, m))?;
            if n.width != size || n.height != size || n.channels < 3 {
                return Err(bad(
                    &npath,
                    format!("{}×{}×{}, expected {size}×{size} RGB", n.width, n.height, n.channels),
                ));
            }
            Some(
                n.pixels
                    .chunks_exact(n.channels)
                    .flat_map(|p| [p[0], p[1], p[2]].map(|x| x as f32 / 127.5 - 1.0))
                    .collect(),
            )
        } else {
            None
        };
        Ok(Sample { name: name.clone(), size, rgb, mask, normal, label: label.clone() })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn label() -> Label {
        let cam = crate::render::camera::OrbitCamera { yaw: 1.0, pitch: 0.05, ..Default::default() };
        let mut body = BodyParams { betas: vec![0.5; 12], ..BodyParams::default() };
        body.pose[4] = glam::Vec3::new(0.3, 0.0, 0.0);
        Label::new(cam.world_to_camera(), &body)
    }

    #[test]
    fn label_round_trip_through_json() {
        let l = label();
        assert_eq!(l.to_floats().len(), LABEL_LEN);
        let json = labels_to_json(&[("s/000.png".into(), l.clone())]);
        let back = parse_labels(Path::new("x.json"), &json).unwrap();
        assert_eq!(back.len(), 1);
        assert_eq!(back[0].0, "s/000.png");
        let m = back[0].1.world_to_camera;
        assert!((m - l.world_to_camera).abs_diff_eq(Mat4::ZERO, 1e-6));
        assert_eq!(back[0].1.body_pose[9], 0.3, "left knee x is θ[12] = body_pose[9]");
        assert_eq!(back[0].1.betas, [0.5; 10]);
        assert_eq!(back[0].1.body_params().pose[4].x, 0.3);
    }

    #[test]
    fn labels_with_a_wrong_count_are_rejected_naming_the_entry() {
        let mut v = label().to_floats();
        v.pop();
        let json = serde_json::json!({"labels": {"good/000.png": label().to_floats(), "subj/007.png": v}}).to_string();
        let e = parse_labels(Path::new("d/dataset.json"), &json).unwrap_err().to_string();
        assert!(e.contains("subj/007.png") && e.contains("97 numbers, expected 98"), "{e}");
        let json = serde_json::json!({"label": {}}).to_string();
        assert!(parse_labels(Path::new("d/dataset.json"), &json).unwrap_err().to_string().contains("no `labels` key"));
        let mut v = label().to_floats();
        v[15] = 2.0;
        let e = Label::from_floats("a.png", &v).unwrap_err().to_string();
        assert!(e.contains("last row"), "{e}");
    }

    #[test]
    fn png_round_trip() {
        let px: Vec<u8> = (0..4 * 3 * 2).map(|i| i as u8 * 7).collect();
        let img = decode_png(&encode_png(3, 2, 4, &px).unwrap()).unwrap();
        assert_eq!((img.width, img.height, img.channels), (3, 2, 4));
        assert_eq!(img.pixels, px);
        assert!(decode_png(b"not a png").unwrap_err().contains("not a PNG"));
        // A tiny file whose header claims 1026 × 771 million pixels (the `photo` fuzz target's
        // find, rewritten with valid checksums: fuzzing builds of the png crate skip them) is
        // refused before anything is allocated.
        let crash = include_bytes!(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../fuzz/regressions/photo/png-header-claims-2-TB-valid-crc"
        ));
        assert!(decode_png(crash).unwrap_err().contains("over the 40 MP limit"));
        assert!(decode_photo(crash).unwrap_err().contains("over the 40 MP limit"));
        let ok = decode_photo(&encode_png(3, 2, 4, &px).unwrap()).unwrap();
        assert_eq!((ok.width(), ok.height()), (3, 2));
        assert!(decode_photo(b"").unwrap_err().contains("is not a PNG or JPEG image"));
        // The fuzzer's second find: a palette of 158 bytes panicked inside the png crate.
        // Rewritten with valid checksums (fuzzing builds of the png crate skip them).
        let crash = include_bytes!(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../fuzz/regressions/photo/png-palette-not-a-multiple-of-3-valid-crc"
        ));
        assert!(decode_photo(crash).unwrap_err().contains("malformed palette (158 bytes"));
        assert!(decode_png(crash).unwrap_err().contains("malformed palette (158 bytes"));
        assert_eq!(normal_name("a/001.png"), "a/001_normal.png");
    }
}
