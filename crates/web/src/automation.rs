//! The app's automation surface, shared by URL query parameters and the JS hook
//! (`window.getavatar.command({...})` / `window.getavatar.status()`), so browser tests can
//! drive the app and read its state without hunting for pixels.
//!
//! Pure Rust (no browser APIs): compiled and unit-tested natively.
//!
//! URL parameters (all optional):
//! `pose=<name>` · `yaw=<deg>` · `pitch=<deg>` · `radius=<m>` · `view=rgb|texture|normal|mask` ·
//! `res=512|1024` · `betas=<b0,b1,...>` · `<joint>=<x,y,z>` (SMPL joint name, axis-angle rad)
//! · `continuous=1` (render every frame).

use serde::{Deserialize, Serialize};

use getavatar_core::body::body_fit::options::FitOptions;
use getavatar_core::body::body_model::joint_index;

pub use crate::status::{MotionStatus, PhotoStatus, ReconstructStatus, Status, VideoStatus};

/// What the viewport shows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum ViewMode {
    /// Shaded colour.
    #[default]
    Rgb,
    /// The paper's RGB render (Sec. 4.4): the texture field queried at every covered pixel's
    /// canonical coordinate (rasterised on the GPU), unshaded. Shaded per-vertex colour is
    /// shown until the per-pixel image is ready, and for the bare body.
    Texture,
    /// World-space normals encoded (n+1)/2; background = zero vector (mid grey).
    Normal,
    /// Foreground mask: white body on black.
    Mask,
}

impl ViewMode {
    pub fn parse(s: &str) -> Option<Self> {
        match s.to_ascii_lowercase().as_str() {
            "rgb" | "shaded" => Some(Self::Rgb),
            "texture" | "albedo" => Some(Self::Texture),
            "normal" | "normals" => Some(Self::Normal),
            "mask" => Some(Self::Mask),
            _ => None,
        }
    }
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Rgb => "rgb",
            Self::Texture => "texture",
            Self::Normal => "normal",
            Self::Mask => "mask",
        }
    }
}

/// Render resolutions offered by the app (square).
pub const RESOLUTIONS: [u32; 2] = [512, 1024];

/// One instruction to the app. JSON form: `{"pose":"walking"}`, `{"joint":"left_elbow",
/// "value":[0,-1,0]}`, `{"yaw":30}`, `{"view":"mask"}`, `{"res":1024}`, `{"betas":[1,0]}`,
/// `{"reset_camera":true}`, `{"download":true}`, `{"generate":{"seed_geo":1,"seed_tex":2,"psi":0.7}}` (optionally
/// `"device":"auto"|"cpu"|"webgpu"`),
/// `{"retexture":{"seed_tex":3}}`, `{"show":"body"}`, `{"photo":{"url":"me.jpg"}}` (optionally
/// `"iterations":[60,300,80]`), `{"photo_fit":"cancel"|"refit"|"download"|"close"}`, `{"photo_fit":{"person":2}}` (fit the
/// photo's 2nd person by size),
/// `{"motion":{"clip":"walk","play":true,"time":0.5,"speed":1,"loop":true,"include":["walk"]}}`,
/// `{"download_animated":true}`, `{"texture_res":256}`, `{"texture_device":"auto"|"cpu"|"webgpu"}`,
/// `{"download_vrm":true}`, `{"download_vrma":true}`, `{"reconstruct":{"preset":"fast"}}` (optionally `"steps"`,
/// `"pti_steps"`, `"res"`, `"preview_every"`, `"perceptual"`, `"projection"`, `"start"`),
/// `{"reconstruct_cancel":true}`, `{"save_reconstruction":true}`, `{"video":{"url":"clip.webm","fps":10}}`,
/// `{"video_cancel":true}`,
/// `{"open_reconstruction":{"url":"inverted.safetensors"}}`. Photo bytes come through `window.getavatar.photo(uint8Array,
/// name)`, motion files through `window.getavatar.motion(uint8Array, name)`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged, deny_unknown_fields)]
pub enum Command {
    Pose {
        pose: String,
    },
    Joint {
        joint: String,
        value: [f32; 3],
    },
    View {
        view: String,
    },
    Res {
        res: u32,
    },
    Betas {
        betas: Vec<f32>,
    },
    ResetCamera {
        reset_camera: bool,
    },
    Download {
        download: bool,
    },
    Continuous {
        continuous: bool,
    },
    Generate {
        generate: GenerateArgs,
    },
    Retexture {
        retexture: GenerateArgs,
    },
    Show {
        show: String,
    },
    Photo {
        photo: PhotoArgs,
    },
    PhotoFit {
        photo_fit: PhotoFitArg,
    },
    Motion {
        motion: MotionArgs,
    },
    DownloadAnimated {
        download_animated: bool,
    },
    DownloadVrm {
        download_vrm: bool,
    },
    DownloadVrma {
        download_vrma: bool,
    },
    TextureRes {
        texture_res: usize,
    },
    TextureDevice {
        texture_device: Compute,
    },
    Reconstruct {
        reconstruct: ReconstructArgs,
    },
    ReconstructCancel {
        reconstruct_cancel: bool,
    },
    SaveReconstruction {
        save_reconstruction: bool,
    },
    OpenReconstruction {
        open_reconstruction: FileArgs,
    },
    Video {
        video: VideoArgs,
    },
    VideoCancel {
        video_cancel: bool,
    },
    /// Last: every field is optional, so it must not swallow the other shapes.
    Camera {
        yaw: Option<f32>,
        pitch: Option<f32>,
        radius: Option<f32>,
    },
}

/// A file by URL (relative to the page or absolute).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileArgs {
    pub url: String,
}

/// Seeds and truncation of a generation request (unset = keep the current value).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GenerateArgs {
    pub seed_geo: Option<u64>,
    pub seed_tex: Option<u64>,
    pub psi: Option<f32>,
    /// Where a new identity is generated (generate only; unset: `auto`): `cpu` in the
    /// reconstruction worker on burn's NdArray, `webgpu` on the page's WebGPU device, `auto`
    /// the first on a software adapter and the second on a hardware one.
    pub device: Option<Compute>,
}

/// A photo to reconstruct the body from, by URL (relative to the page or absolute).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhotoArgs {
    pub url: String,
    /// Adam steps of the fit's torso, body and silhouette stages (default: the fit's own).
    pub iterations: Option<[usize; 3]>,
    /// Fit settings (`body_fit::fit::FitOptions` as JSON, any subset of its fields); merged
    /// under `iterations`.
    pub options: Option<serde_json::Value>,
    /// Where the fit runs: "cpu" (burn NdArray, the default) or "webgpu" (burn wgpu on the
    /// page's WebGPU device; for comparisons: tests/e2e/bench_fit.mjs).
    pub device: Option<String>,
}

/// A reconstruction from the fitted photo: the quality preset (`instant`: the photo encoder's
/// guess, no steps; `fast`: 60 W+ + 60 PTI steps; `full`: 200 + 350) and overrides. With the
/// encoder's start and steps to run, the guess is shown as the avatar first, then refined.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReconstructArgs {
    pub preset: Option<String>,
    /// W+ and PTI steps (override the preset's).
    pub steps: Option<usize>,
    pub pti_steps: Option<usize>,
    /// Side of the square render the photo is compared with, pixels (32…256; default 128).
    pub res: Option<usize>,
    /// A preview every this many steps (default 5; 0 = only the final one).
    pub preview_every: Option<usize>,
    /// Use the shipped discriminator's perceptual term where it ships (default true).
    pub perceptual: Option<bool>,
    /// Project the photo's colours onto the result (default true).
    pub projection: Option<bool>,
    /// Where the codes start: `encoder` (default: the photo encoder's guess; without a usable
    /// encoder, `best` with a message), `best` (the model's subject, or the average, whose
    /// render explains the photo best; one render each) or `average` (w_avg, no search).
    pub start: Option<String>,
    /// Where the reconstruction worker computes: `auto` (default: WebGPU) or `webgpu`, or
    /// `cpu` (burn NdArray in the worker; slower in wasm today, for measurements).
    pub device: Option<String>,
}

/// Where a reconstruction's codes start.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StartChoice {
    /// The photo encoder's guess (one forward pass; `getavatar_core::reconstruction::encoder`); without a
    /// usable encoder, the search below, with a message.
    Encoder,
    /// The model's subject (or w_avg) whose render explains the photo best: one render each.
    Search,
    /// w_avg, no search.
    Average,
}

impl StartChoice {
    /// The start a stage runs from, and why it is not this one ("" when it is): the encoder's
    /// start without a usable encoder file (`encoder`: why not) is the search.
    pub fn or_search(self, encoder: Result<(), &str>) -> (StartChoice, String) {
        match (self, encoder) {
            (StartChoice::Encoder, Err(why)) => {
                (StartChoice::Search, format!("{why}: searched the model's subjects instead"))
            }
            (start, _) => (start, String::new()),
        }
    }

    /// A first stage's start in words (`why`: why the search runs instead of the encoder, or "").
    pub fn opening(self, why: &str) -> String {
        match self {
            StartChoice::Encoder => "the photo encoder's guess".into(),
            StartChoice::Search if why.is_empty() => "choosing the start among the model's subjects".into(),
            StartChoice::Search => format!("choosing the start among the model's subjects ({why})"),
            StartChoice::Average => "starting from the average".into(),
        }
    }
}

/// Which device the reconstruction worker computes on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Compute {
    /// The worker's WebGPU device on a hardware adapter (the page's where the worker has
    /// none), burn's NdArray in the worker on a software one, where that is many times the
    /// faster (docs/benchmarks.md).
    Auto,
    /// burn's NdArray in the worker.
    Cpu,
    /// The worker's own WebGPU device (for a generation: the page's).
    #[serde(rename = "webgpu")]
    WebGpu,
}

/// Most steps per phase a reconstruction may ask for.
pub const MAX_RECONSTRUCT_STEPS: usize = 2000;
/// The reconstruction's render sizes.
pub const RECONSTRUCT_RES: std::ops::RangeInclusive<usize> = 32..=256;
/// Its default render size and preview interval.
pub const DEFAULT_RECONSTRUCT_RES: usize = 128;
pub const DEFAULT_PREVIEW_EVERY: usize = 5;

/// The quality presets (`getavatar_core::reconstruction::inversion::InversionOptions::preset`).
pub const RECONSTRUCT_PRESETS: [&str; 3] = ["instant", "fast", "full"];

/// A validated reconstruction request.
#[derive(Clone, Debug, PartialEq)]
pub struct Reconstruction {
    pub preset: String,
    /// Steps per phase when not the preset's.
    pub steps: Option<usize>,
    pub pti_steps: Option<usize>,
    pub perceptual: bool,
    pub res: usize,
    pub preview_every: usize,
    pub projection: bool,
    pub start: StartChoice,
    pub compute: Compute,
}

impl ReconstructArgs {
    /// The request, or what is wrong with it.
    pub fn validate(self) -> Result<Reconstruction, String> {
        let preset = self.preset.unwrap_or_else(|| "fast".into());
        if !RECONSTRUCT_PRESETS.contains(&preset.as_str()) {
            return Err(format!("reconstruct: preset `{preset}` (instant, fast, full)"));
        }
        for n in [self.steps, self.pti_steps].into_iter().flatten() {
            if n > MAX_RECONSTRUCT_STEPS {
                return Err(format!("reconstruct: at most {MAX_RECONSTRUCT_STEPS} steps per phase"));
            }
        }
        let start = match self.start.as_deref() {
            None | Some("encoder") => StartChoice::Encoder,
            Some("best") => StartChoice::Search,
            Some("average") => StartChoice::Average,
            Some(other) => return Err(format!("reconstruct: start `{other}` (encoder, best, average)")),
        };
        let compute = match self.device.as_deref() {
            None | Some("auto") => Compute::Auto,
            Some("cpu") => Compute::Cpu,
            Some("webgpu") => Compute::WebGpu,
            Some(other) => return Err(format!("reconstruct: device `{other}` (auto, cpu, webgpu)")),
        };
        let res = self.res.unwrap_or(DEFAULT_RECONSTRUCT_RES);
        if !RECONSTRUCT_RES.contains(&res) {
            return Err(format!("reconstruct: res {res} (32…256)"));
        }
        Ok(Reconstruction {
            preset,
            steps: self.steps,
            pti_steps: self.pti_steps,
            perceptual: self.perceptual.unwrap_or(true),
            res,
            preview_every: self.preview_every.unwrap_or(DEFAULT_PREVIEW_EVERY),
            projection: self.projection.unwrap_or(true),
            start,
            compute,
        })
    }
}

/// Motion playback: choose a clip (a built-in's or a loaded file's name), play or pause,
/// jump to a time, set the speed and looping, and which clips the animated download holds.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MotionArgs {
    pub clip: Option<String>,
    pub play: Option<bool>,
    /// Seconds from the clip's start.
    pub time: Option<f32>,
    /// Playback speed (1 = real time), in (0, 4].
    pub speed: Option<f32>,
    #[serde(rename = "loop")]
    pub looping: Option<bool>,
    /// Clips the animated download holds (names); default: the one playing.
    pub include: Option<Vec<String>>,
}

/// Most playback speed.
pub const MAX_MOTION_SPEED: f32 = 4.0;

/// Where a photo comes from.
#[derive(Clone, Debug, PartialEq)]
pub enum PhotoSource {
    Url(String),
    /// A file chosen or dropped by the user (or handed over by the JS hook).
    Bytes {
        name: String,
        bytes: Vec<u8>,
    },
}

/// Most Adam steps per stage a command may ask for.
pub const MAX_FIT_ITERATIONS: usize = 5000;

/// What to do with the photo's fit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PhotoFitAction {
    Cancel,
    /// Find the person again and fit the `k`-th by size (1 = the largest) of the people seen.
    Person(usize),
    /// Fit again, starting from the current pose and shape (after the user corrected joints).
    Refit,
    /// Download `fit.json` and `kp.json`.
    Download,
    /// Put the photo away.
    Close,
}

/// `photo_fit`'s argument: a word, or which person to fit.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged, deny_unknown_fields)]
pub enum PhotoFitArg {
    Word(String),
    Person { person: usize },
}

/// The most people `{"photo_fit":{"person":k}}` may name.
pub const MAX_PEOPLE: usize = 64;

/// A command validated against the app's vocabulary.
#[derive(Clone, Debug, PartialEq)]
pub enum Action {
    Pose(String),
    Joint(usize, [f32; 3]),
    /// yaw, pitch in radians; radius in metres.
    Camera {
        yaw: Option<f32>,
        pitch: Option<f32>,
        radius: Option<f32>,
    },
    View(ViewMode),
    Res(u32),
    Betas(Vec<f32>),
    ResetCamera,
    Download,
    Continuous(bool),
    /// Generate a new avatar (geometry and texture).
    Generate(GenerateArgs),
    /// Keep the geometry, draw a new texture.
    Retexture(GenerateArgs),
    /// Show the avatar (`true`) or the bare body (`false`).
    ShowAvatar(bool),
    /// Detect the person in a photo and fit the body to it.
    Photo {
        source: PhotoSource,
        options: Option<FitOptions>,
        /// Fit on the WebGPU device instead of the CPU.
        on_gpu: bool,
    },
    PhotoFit(PhotoFitAction),
    Motion(MotionArgs),
    /// A motion file's bytes (SMPL/AMASS .npz) from the file picker, a drop or the JS hook.
    MotionFile {
        name: String,
        bytes: Vec<u8>,
    },
    /// Download the avatar (or body) as a skinned .glb with the chosen clips.
    DownloadAnimated,
    /// Download the avatar (or body) as a VRM 1.0 avatar.
    DownloadVrm,
    /// Download each chosen clip as a VRM animation (.vrma).
    DownloadVrma,
    /// Side of the avatar's baked texture in the downloads (0: vertex colours).
    TextureRes(usize),
    /// Where the texture field's colours (bakes, the per-pixel view) are computed: `Auto` in
    /// the worker on a software adapter, `Cpu` in the worker, `WebGpu` on the page.
    TextureDevice(Compute),
    /// Reconstruct an avatar from the fitted photo.
    Reconstruct(Reconstruction),
    /// Stop the running reconstruction (the avatar stays as it was).
    ReconstructCancel,
    /// Download the shown reconstruction as one file (tuned generator, codes, photo).
    SaveReconstruction,
    /// Open a saved reconstruction (the app's or `trainer invert`'s `inverted.safetensors`).
    OpenReconstruction(PhotoSource),
    /// Make a motion clip from a video, reading `fps` frames per second of it (None: the
    /// rate chosen in the panel).
    Video {
        source: PhotoSource,
        fps: Option<u32>,
    },
    /// Stop making the clip (the frames fitted so far become a shorter clip).
    VideoCancel,
}

/// `{"video":{"url":"clip.webm","fps":10}}`: motion from the video at `url` (default: the
/// rate chosen in the panel, at first [`crate::video_clip::DEFAULT_READ_FPS`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VideoArgs {
    pub url: String,
    pub fps: Option<u32>,
}

/// Texture sizes offered for the downloads (0: vertex colours, no texture).
pub const TEXTURE_RESOLUTIONS: [usize; 5] = [0, 256, 512, 1024, 2048];

fn finite(v: f32, what: &str) -> Result<f32, String> {
    if v.is_finite() {
        Ok(v)
    } else {
        Err(format!("{what}: not a finite number"))
    }
}

impl Command {
    /// Validate; angles given in degrees become radians.
    pub fn into_action(self) -> Result<Action, String> {
        Ok(match self {
            Command::Pose { pose } => Action::Pose(pose),
            Command::Joint { joint, value } => {
                let j = joint_index(&joint).ok_or_else(|| format!("unknown joint `{joint}` (use SMPL joint names)"))?;
                for v in value {
                    finite(v, &joint)?;
                }
                Action::Joint(j, value)
            }
            Command::Camera { yaw, pitch, radius } => Action::Camera {
                yaw: yaw.map(|d| finite(d, "yaw").map(f32::to_radians)).transpose()?,
                pitch: pitch.map(|d| finite(d, "pitch").map(f32::to_radians)).transpose()?,
                radius: radius.map(|r| finite(r, "radius")).transpose()?,
            },
            Command::View { view } => Action::View(
                ViewMode::parse(&view).ok_or_else(|| format!("unknown view `{view}` (rgb, texture, normal, mask)"))?,
            ),
            Command::Res { res } => {
                if !RESOLUTIONS.contains(&res) {
                    return Err(format!("unsupported resolution {res} (512 or 1024)"));
                }
                Action::Res(res)
            }
            Command::Betas { betas } => {
                for b in &betas {
                    finite(*b, "betas")?;
                }
                Action::Betas(betas)
            }
            Command::ResetCamera { .. } => Action::ResetCamera,
            Command::Download { .. } => Action::Download,
            Command::Continuous { continuous } => Action::Continuous(continuous),
            Command::Generate { generate } => Action::Generate(check_psi(generate)?),
            Command::Retexture { retexture } if retexture.device.is_some() => {
                return Err("`device` applies to generate only: a new texture is computed on the page".into())
            }
            Command::Retexture { retexture } => Action::Retexture(check_psi(retexture)?),
            Command::Show { show } => match show.as_str() {
                "avatar" => Action::ShowAvatar(true),
                "body" => Action::ShowAvatar(false),
                other => return Err(format!("show: `{other}` (avatar, body)")),
            },
            Command::Photo { photo } => {
                if photo.url.trim().is_empty() {
                    return Err("photo: empty url".into());
                }
                let mut options = match photo.options {
                    Some(v) => {
                        Some(serde_json::from_value::<FitOptions>(v).map_err(|e| format!("photo: options: {e}"))?)
                    }
                    None => None,
                };
                if let Some(it) = photo.iterations {
                    options.get_or_insert_with(FitOptions::default).iterations = it;
                }
                if let Some(o) = &options {
                    let it = o.iterations;
                    if it.iter().any(|n| *n > MAX_FIT_ITERATIONS) || it[0] + it[1] == 0 {
                        return Err(format!(
                            "photo: iterations {it:?} (each at most {MAX_FIT_ITERATIONS}, torso + body at least 1)"
                        ));
                    }
                    let sane = o.learning_rate.is_finite()
                        && o.learning_rate > 0.0
                        && (8..=512).contains(&o.silhouette_size)
                        && o.num_betas <= 16;
                    if !sane {
                        return Err("photo: options: learning_rate > 0, silhouette_size 8..=512, num_betas ≤ 16".into());
                    }
                }
                let on_gpu = match photo.device.as_deref() {
                    None | Some("cpu") => false,
                    Some("webgpu") => true,
                    Some(other) => return Err(format!("photo: device `{other}` (cpu, webgpu)")),
                };
                Action::Photo { source: PhotoSource::Url(photo.url), options, on_gpu }
            }
            Command::Motion { motion } => {
                if let Some(t) = motion.time {
                    if !(t.is_finite() && t >= 0.0) {
                        return Err(format!("motion: time {t} (seconds ≥ 0)"));
                    }
                }
                if let Some(v) = motion.speed {
                    if !(v.is_finite() && v > 0.0 && v <= MAX_MOTION_SPEED) {
                        return Err(format!("motion: speed {v} (0 < speed ≤ {MAX_MOTION_SPEED})"));
                    }
                }
                Action::Motion(motion)
            }
            Command::DownloadAnimated { .. } => Action::DownloadAnimated,
            Command::DownloadVrm { .. } => Action::DownloadVrm,
            Command::DownloadVrma { .. } => Action::DownloadVrma,
            Command::TextureRes { texture_res } => {
                if !TEXTURE_RESOLUTIONS.contains(&texture_res) {
                    return Err(format!(
                        "texture_res {texture_res} (one of {TEXTURE_RESOLUTIONS:?}; 0 = vertex colours)"
                    ));
                }
                Action::TextureRes(texture_res)
            }
            Command::TextureDevice { texture_device } => Action::TextureDevice(texture_device),
            Command::Reconstruct { reconstruct } => Action::Reconstruct(reconstruct.validate()?),
            Command::ReconstructCancel { .. } => Action::ReconstructCancel,
            Command::SaveReconstruction { .. } => Action::SaveReconstruction,
            Command::OpenReconstruction { open_reconstruction } => {
                if open_reconstruction.url.trim().is_empty() {
                    return Err("open_reconstruction: empty url".into());
                }
                Action::OpenReconstruction(PhotoSource::Url(open_reconstruction.url))
            }
            Command::Video { video } => {
                if video.url.trim().is_empty() {
                    return Err("video: empty url".into());
                }
                if let Some(f) = video.fps {
                    crate::video_clip::check_read_fps(f).map_err(|e| format!("video: {e}"))?;
                }
                Action::Video { source: PhotoSource::Url(video.url), fps: video.fps }
            }
            Command::VideoCancel { .. } => Action::VideoCancel,
            Command::PhotoFit { photo_fit: PhotoFitArg::Word(w) } => Action::PhotoFit(match w.as_str() {
                "cancel" => PhotoFitAction::Cancel,
                "refit" => PhotoFitAction::Refit,
                "download" => PhotoFitAction::Download,
                "close" => PhotoFitAction::Close,
                other => {
                    return Err(format!("photo_fit: `{other}` (cancel, refit, download, close, or {{\"person\": k}})"))
                }
            }),
            Command::PhotoFit { photo_fit: PhotoFitArg::Person { person } } => {
                if !(1..=MAX_PEOPLE).contains(&person) {
                    return Err(format!("photo_fit: person {person} (1 = the largest … {MAX_PEOPLE})"));
                }
                Action::PhotoFit(PhotoFitAction::Person(person))
            }
        })
    }
}

fn check_psi(a: GenerateArgs) -> Result<GenerateArgs, String> {
    if let Some(p) = a.psi {
        if !(0.0..=2.0).contains(&p) {
            return Err(format!("psi {p} outside 0..2"));
        }
    }
    Ok(a)
}

/// Parse a JSON command (from the JS hook).
pub fn parse_command(json: &str) -> Result<Action, String> {
    let cmd: Command = serde_json::from_str(json).map_err(|e| format!("bad command {json}: {e}"))?;
    cmd.into_action()
}

fn parse_floats(v: &str, what: &str) -> Result<Vec<f32>, String> {
    v.split(',')
        .filter(|s| !s.trim().is_empty())
        .map(|s| {
            s.trim().parse::<f32>().map_err(|_| format!("{what}: `{s}` is not a number")).and_then(|x| finite(x, what))
        })
        .collect()
}

/// Parse a URL query string (`?pose=walking&yaw=30`) into actions, in order.
/// Bad parameters are reported (one message each) and skipped.
pub fn parse_query(query: &str) -> (Vec<Action>, Vec<String>) {
    let mut actions = Vec::new();
    let mut errors = Vec::new();
    for pair in query.trim_start_matches('?').split('&').filter(|p| !p.is_empty()) {
        let (k, v) = pair.split_once('=').unwrap_or((pair, ""));
        let v = percent_decode(v);
        let num = |what: &str| {
            v.trim().parse::<f32>().map_err(|_| format!("{what}: `{v}` is not a number")).and_then(|x| finite(x, what))
        };
        let r: Result<Action, String> = match k {
            "pose" => Ok(Action::Pose(v.clone())),
            "yaw" => num("yaw").map(|d| Action::Camera { yaw: Some(d.to_radians()), pitch: None, radius: None }),
            "pitch" => num("pitch").map(|d| Action::Camera { yaw: None, pitch: Some(d.to_radians()), radius: None }),
            "radius" => num("radius").map(|r| Action::Camera { yaw: None, pitch: None, radius: Some(r) }),
            "view" => ViewMode::parse(&v)
                .map(Action::View)
                .ok_or_else(|| format!("unknown view `{v}` (rgb, texture, normal, mask)")),
            "res" => v
                .parse::<u32>()
                .map_err(|_| format!("res: `{v}` is not an integer"))
                .and_then(|r| Command::Res { res: r }.into_action()),
            "betas" => parse_floats(&v, "betas").map(Action::Betas),
            "continuous" => Ok(Action::Continuous(v == "1" || v == "true")),
            "seed_geo" | "seed_tex" | "generate" => {
                let seed = if k == "generate" {
                    Ok(None)
                } else {
                    v.parse::<u64>().map(Some).map_err(|_| format!("{k}: `{v}` is not a seed"))
                };
                seed.map(|s| {
                    Action::Generate(GenerateArgs {
                        seed_geo: if k == "seed_geo" { s } else { None },
                        seed_tex: if k == "seed_tex" { s } else { None },
                        ..Default::default()
                    })
                })
            }
            "psi" => num("psi")
                .and_then(|p| check_psi(GenerateArgs { psi: Some(p), ..Default::default() }))
                .map(Action::Generate),
            joint => match joint_index(joint) {
                Some(j) => parse_floats(&v, joint).and_then(|f| {
                    if f.len() == 3 {
                        Ok(Action::Joint(j, [f[0], f[1], f[2]]))
                    } else {
                        Err(format!("{joint}: expected 3 numbers (axis-angle), got {}", f.len()))
                    }
                }),
                None => Err(format!("unknown URL parameter `{joint}`")),
            },
        };
        match r {
            Ok(a) => actions.push(a),
            Err(e) => errors.push(e),
        }
    }
    (actions, errors)
}

fn percent_decode(s: &str) -> String {
    let bytes = s.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        match bytes[i] {
            b'+' => out.push(b' '),
            b'%' if i + 2 < bytes.len() => {
                let hex = std::str::from_utf8(&bytes[i + 1..i + 3]).ok().and_then(|h| u8::from_str_radix(h, 16).ok());
                match hex {
                    Some(b) => {
                        out.push(b);
                        i += 2;
                    }
                    None => out.push(b'%'),
                }
            }
            b => out.push(b),
        }
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_encoder_start_without_a_usable_file_is_the_search_and_says_why() {
        assert_eq!(StartChoice::Encoder.or_search(Ok(())), (StartChoice::Encoder, String::new()));
        let why = "models/encoder.safetensors cannot be used (bad)";
        let (start, note) = StartChoice::Encoder.or_search(Err(why));
        assert_eq!(start, StartChoice::Search);
        assert_eq!(note, format!("{why}: searched the model's subjects instead"));
        assert_eq!(StartChoice::Average.or_search(Err(why)), (StartChoice::Average, String::new()));
        assert_eq!(start.opening(why), format!("choosing the start among the model's subjects ({why})"));
        assert_eq!(StartChoice::Search.opening(""), "choosing the start among the model's subjects");
    }

    #[test]
    fn query_parameters_become_actions() {
        let (a, e) = parse_query("?pose=walking&yaw=90&view=mask&res=1024&betas=1,-0.5&left_elbow=0,-1.2,0");
        assert!(e.is_empty(), "{e:?}");
        assert_eq!(a[0], Action::Pose("walking".into()));
        match &a[1] {
            Action::Camera { yaw: Some(y), .. } => {
                assert!((y - std::f32::consts::FRAC_PI_2).abs() < 1e-6)
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(a[2], Action::View(ViewMode::Mask));
        assert_eq!(a[3], Action::Res(1024));
        assert_eq!(a[4], Action::Betas(vec![1.0, -0.5]));
        assert_eq!(a[5], Action::Joint(18, [0.0, -1.2, 0.0]));
    }

    #[test]
    fn reconstruct_commands_are_validated() {
        let r = parse_command(r#"{"reconstruct":{}}"#);
        assert_eq!(
            r,
            Ok(Action::Reconstruct(Reconstruction {
                preset: "fast".into(),
                steps: None,
                pti_steps: None,
                perceptual: true,
                res: DEFAULT_RECONSTRUCT_RES,
                preview_every: DEFAULT_PREVIEW_EVERY,
                projection: true,
                start: StartChoice::Encoder,
                compute: Compute::Auto,
            }))
        );
        let r =
            parse_command(r#"{"reconstruct":{"preset":"full","steps":3,"pti_steps":0,"res":64,"perceptual":false}}"#);
        match r {
            Ok(Action::Reconstruct(r)) => {
                assert_eq!(
                    (r.preset.as_str(), r.steps, r.pti_steps, r.res, r.perceptual),
                    ("full", Some(3), Some(0), 64, false)
                )
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(parse_command(r#"{"reconstruct_cancel":true}"#), Ok(Action::ReconstructCancel));
        assert_eq!(parse_command(r#"{"save_reconstruction":true}"#), Ok(Action::SaveReconstruction));
        assert_eq!(
            parse_command(r#"{"open_reconstruction":{"url":"inv.safetensors"}}"#),
            Ok(Action::OpenReconstruction(PhotoSource::Url("inv.safetensors".into())))
        );
        assert!(parse_command(r#"{"open_reconstruction":{"url":" "}}"#).is_err());
        assert!(parse_command(r#"{"open_reconstruction":{"path":"x"}}"#).is_err());
        for bad in [
            r#"{"reconstruct":{"preset":"best"}}"#,
            r#"{"reconstruct":{"res":8}}"#,
            r#"{"reconstruct":{"res":512}}"#,
            r#"{"reconstruct":{"device":"tpu"}}"#,
            r#"{"reconstruct":{"steps":99999}}"#,
            r#"{"reconstruct":{"lr":1}}"#,
            r#"{"reconstruct":{"start":"mode 3"}}"#,
        ] {
            assert!(parse_command(bad).is_err(), "{bad}");
        }
        match parse_command(r#"{"reconstruct":{"preset":"instant","start":"average","device":"cpu"}}"#) {
            Ok(Action::Reconstruct(r)) => {
                assert_eq!((r.preset.as_str(), r.start, r.compute), ("instant", StartChoice::Average, Compute::Cpu))
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn bad_parameters_are_reported_not_fatal() {
        let (a, e) = parse_query("res=300&view=xray&yaw=abc&left_knee=1,2&bogus=1&pose=T&yaw=NaN");
        assert_eq!(a, vec![Action::Pose("T".into())]);
        assert_eq!(e.len(), 6, "{e:?}");
        assert!(e.iter().any(|m| m.contains("xray")));
    }

    #[test]
    fn json_commands() {
        assert_eq!(parse_command(r#"{"pose":"sitting"}"#), Ok(Action::Pose("sitting".into())));
        assert_eq!(parse_command(r#"{"joint":"right_knee","value":[1.5,0,0]}"#), Ok(Action::Joint(5, [1.5, 0.0, 0.0])));
        assert_eq!(parse_command(r#"{"view":"normal"}"#), Ok(Action::View(ViewMode::Normal)));
        assert_eq!(parse_command(r#"{"view":"texture"}"#), Ok(Action::View(ViewMode::Texture)));
        assert_eq!(parse_command(r#"{"download":true}"#), Ok(Action::Download));
        assert_eq!(
            parse_command(r#"{"generate":{"seed_geo":3}}"#),
            Ok(Action::Generate(GenerateArgs { seed_geo: Some(3), ..Default::default() }))
        );
        assert_eq!(
            parse_command(r#"{"retexture":{"seed_tex":9}}"#),
            Ok(Action::Retexture(GenerateArgs { seed_tex: Some(9), ..Default::default() }))
        );
        assert_eq!(parse_command(r#"{"show":"body"}"#), Ok(Action::ShowAvatar(false)));
        assert!(parse_command(r#"{"generate":{"seed":3}}"#).is_err());
        assert!(parse_command(r#"{"generate":{"psi":7}}"#).is_err());
        assert_eq!(
            parse_command(r#"{"generate":{"seed_geo":4,"device":"cpu"}}"#),
            Ok(Action::Generate(GenerateArgs { seed_geo: Some(4), device: Some(Compute::Cpu), ..Default::default() }))
        );
        assert!(parse_command(r#"{"generate":{"device":"gpu"}}"#).is_err());
        assert_eq!(
            parse_command(r#"{"generate":{"device":"webgpu"}}"#),
            Ok(Action::Generate(GenerateArgs { device: Some(Compute::WebGpu), ..Default::default() }))
        );
        assert!(parse_command(r#"{"retexture":{"device":"cpu"}}"#).unwrap_err().contains("generate only"));
        assert!(parse_command(r#"{"joint":"elbow","value":[1,0,0]}"#).is_err());
        assert!(parse_command(r#"{"res":77}"#).is_err());
        // An unknown key is refused (not swallowed by the all-optional camera command), and
        // says what it was: the soak test's marker.
        assert!(parse_command(r#"{"soak_marker":7}"#).unwrap_err().contains(r#"{"soak_marker":7}"#));
        assert!(parse_command("nonsense").is_err());
        assert_eq!(
            parse_command(r#"{"photo":{"url":"p.png","iterations":[5,10,0]}}"#),
            Ok(Action::Photo {
                source: PhotoSource::Url("p.png".into()),
                options: Some(FitOptions { iterations: [5, 10, 0], ..FitOptions::default() }),
                on_gpu: false,
            })
        );
        assert_eq!(parse_command(r#"{"photo_fit":"refit"}"#), Ok(Action::PhotoFit(PhotoFitAction::Refit)));
        assert!(parse_command(r#"{"photo":{"url":""}}"#).is_err());
        assert!(parse_command(r#"{"photo":{"url":"p.png","iterations":[0,0,9]}}"#).is_err());
        assert!(parse_command(r#"{"photo":{"url":"p.png","iterations":[1,99999,0]}}"#).is_err());
        assert!(parse_command(r#"{"photo":{"path":"p.png"}}"#).is_err());
        assert!(parse_command(r#"{"photo_fit":"again"}"#).is_err());
        assert_eq!(parse_command(r#"{"photo_fit":{"person":2}}"#), Ok(Action::PhotoFit(PhotoFitAction::Person(2))));
        assert!(parse_command(r#"{"photo_fit":{"person":0}}"#).is_err());
        assert!(parse_command(r#"{"photo_fit":{"person":-1}}"#).is_err());
        assert!(parse_command(r#"{"photo_fit":{"who":1}}"#).is_err());
        let m = parse_command(r#"{"motion":{"clip":"walk","play":true,"time":0.5,"speed":2,"loop":false}}"#);
        assert_eq!(
            m,
            Ok(Action::Motion(MotionArgs {
                clip: Some("walk".into()),
                play: Some(true),
                time: Some(0.5),
                speed: Some(2.0),
                looping: Some(false),
                include: None
            }))
        );
        assert!(parse_command(r#"{"motion":{"speed":0}}"#).is_err());
        assert!(parse_command(r#"{"motion":{"time":-1}}"#).is_err());
        assert!(parse_command(r#"{"motion":{"tempo":1}}"#).is_err());
        assert_eq!(parse_command(r#"{"download_animated":true}"#), Ok(Action::DownloadAnimated));
        assert_eq!(parse_command(r#"{"download_vrm":true}"#), Ok(Action::DownloadVrm));
        assert_eq!(parse_command(r#"{"download_vrma":true}"#), Ok(Action::DownloadVrma));
        assert_eq!(parse_command(r#"{"texture_res":512}"#), Ok(Action::TextureRes(512)));
        assert!(parse_command(r#"{"texture_res":300}"#).is_err());
        assert_eq!(parse_command(r#"{"texture_device":"cpu"}"#), Ok(Action::TextureDevice(Compute::Cpu)));
        assert_eq!(parse_command(r#"{"texture_device":"webgpu"}"#), Ok(Action::TextureDevice(Compute::WebGpu)));
        assert!(parse_command(r#"{"texture_device":"gpu"}"#).is_err());
        assert!(matches!(
            parse_command(r#"{"photo":{"url":"p.png","device":"webgpu"}}"#),
            Ok(Action::Photo { on_gpu: true, options: None, .. })
        ));
        assert!(parse_command(r#"{"photo":{"url":"p.png","device":"tpu"}}"#).is_err());
        match parse_command(r#"{"photo":{"url":"p.png","options":{"weights":{"silhouette":0.05}}}}"#) {
            Ok(Action::Photo { options: Some(o), .. }) => {
                assert_eq!(o.weights.silhouette, 0.05);
                assert_eq!(o.iterations, FitOptions::default().iterations);
            }
            other => panic!("{other:?}"),
        }
        assert!(parse_command(r#"{"photo":{"url":"p.png","options":{"weights":{"silhouete":1}}}}"#).is_err());
        assert!(parse_command(r#"{"photo":{"url":"p.png","options":{"learning_rate":-1}}}"#).is_err());
    }

    #[test]
    fn video_commands_name_a_url_and_a_read_rate_offered() {
        assert_eq!(
            parse_command(r#"{"video":{"url":"clip.webm","fps":10}}"#),
            Ok(Action::Video { source: PhotoSource::Url("clip.webm".into()), fps: Some(10) })
        );
        assert_eq!(
            parse_command(r#"{"video":{"url":"clip.webm"}}"#),
            Ok(Action::Video { source: PhotoSource::Url("clip.webm".into()), fps: None })
        );
        assert_eq!(parse_command(r#"{"video_cancel":true}"#), Ok(Action::VideoCancel));
        for bad in [r#"{"video":{"url":" "}}"#, r#"{"video":{"url":"a.mp4","fps":24}}"#, r#"{"video":{"path":"a"}}"#] {
            assert!(parse_command(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn percent_decoding() {
        assert_eq!(percent_decode("one%5Fleg"), "one_leg");
        assert_eq!(percent_decode("a+b%"), "a b%");
    }
}
