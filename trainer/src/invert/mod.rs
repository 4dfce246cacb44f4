//! `trainer invert`: single-image reconstruction (paper Sec. 5.4, `getavatar_core::reconstruction::inversion`)
//! of a photo with its body fit (`--image --fit`), or of a dataset image with its true camera
//! and pose (`--data --entry`, which measures the inversion alone).
//!
//! DIR receives: `input.png` (the target as the inversion sees it, and its mask),
//! `input_view.png` (RGBA render at the input camera and resolution, alpha = the avatar's
//! mask), `comparison.png` (input | render | overlay), `back_view.png` (the exported avatar
//! at the opposite camera), `pose_<name>.png` (the exported avatar in three other poses, front
//! camera), `input_view_projected.png` (the exported avatar at the input camera), `avatar.glb` (skinned, textured, the
//! input's pose shown, the built-in `walk` clip), `inverted.safetensors` (the tuned generator
//! and the codes: `trainer sample --inverted DIR` reloads it), `steps.jsonl` (every step's
//! terms) and `metrics.json` (mask IoU and masked PSNR at the input camera after W+ and after
//! PTI, the back view's IoU and masked PSNR against the subject's own scan with `--scans`, whose
//! back is drawn to `back_view_truth.png` (mask) and `back_view_truth_rgb.png`, timings; with
//! `--pck`, PCK@0.1 of MediaPipe on the avatar at the photo's camera against the photo's
//! keypoints, its render in `pck/`).

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use getavatar_core::body::body_fit::fit::BodyFit;
use getavatar_core::body::body_fit::landmarks::PoseResult;
use getavatar_core::body::body_fit::turn;
use getavatar_core::body::body_model::BodyModel;
use getavatar_core::body::humanoid::SkeletonNames;
use getavatar_core::body::motion::Motion;
use getavatar_core::body::pose_library::PoseLibrary;
use getavatar_core::body::skinning::{pose_body, BodyParams};
use getavatar_core::burn::tensor::Device;
use getavatar_core::generator::checkpoint::parse_safetensors;
use getavatar_core::generator::checkpoint::{self, save_inverted};
use getavatar_core::generator::network::discriminator::Discriminator;
use getavatar_core::generator::network::GeneratorConfig;
use getavatar_core::generator::pipeline::{BodyContext, Generator, LatentModes, Styles};
use getavatar_core::generator::readback::block_on_ready;
use getavatar_core::generator::rigging::generate_rigged_async;
use getavatar_core::generator::rigging::{BakedTexture, RiggedAvatar};
use getavatar_core::io::dataset::{find_scans, load_body_fit, load_scan, Dataset};
use getavatar_core::io::scan::RenderableScan;
use getavatar_core::reconstruction::encoder::{load_encoder_for, Encoder};
use getavatar_core::reconstruction::garment_codes::GarmentCodes;
use getavatar_core::reconstruction::inversion::{
    comparison_image, mask_iou, masked_psnr, render_images, InversionOptions, InversionTarget, Inverter, Phase,
};
use getavatar_core::render::camera::{OrbitCamera, View};
use getavatar_core::render::diff::avatar::{render_avatars, PosedGridCache};
use getavatar_core::render::rasterize::{render_views_textured, Texture};
use glam::{Mat4, Vec3};
use serde::Serialize;

mod start;

use start::{encoder_guess, search_guess, start_views, StartViews};

use crate::atomic::write_atomic;
use crate::fit_pose::{load_mask, open_image};
use crate::model_io::{load_body, shipped_discriminator, shipped_encoder, snap_to_photo, write_png, GeneratorArgs};

#[derive(clap::Args, Debug)]
pub struct InvertArgs {
    #[command(flatten)]
    pub model: GeneratorArgs,
    /// A photo (PNG or JPEG) to reconstruct; needs `--fit` and a person mask (`--mask`, or
    /// `--keypoints` with MediaPipe's `segmentationMask`).
    #[arg(long, requires = "fit", conflicts_with = "data")]
    pub image: Option<PathBuf>,
    /// The photo's body fit (`trainer fit-pose` or the app's "Download fit").
    #[arg(long)]
    pub fit: Option<PathBuf>,
    /// Person mask PNG covering the photo (grey, or the alpha channel where it has one).
    #[arg(long)]
    pub mask: Option<PathBuf>,
    /// MediaPipe Pose's result JSON with a `segmentationMask` (used when there is no `--mask`).
    #[arg(long)]
    pub keypoints: Option<PathBuf>,
    /// A prepared dataset: invert one of its images at its true camera and pose.
    #[arg(long, requires = "entry")]
    pub data: Option<PathBuf>,
    /// The dataset entry, e.g. `0003/005.png`.
    #[arg(long)]
    pub entry: Option<String>,
    /// The dataset's scans (`synth-scans` output): the subject's own back view is rendered
    /// from its scan and compared with the avatar's (mask IoU in metrics.json).
    #[arg(long, requires = "data")]
    pub scans: Option<PathBuf>,
    /// instant (the encoder's guess, no optimisation), fast (60 W+ + 60 PTI steps) or full
    /// (200 + 350, the references' counts).
    #[arg(long, default_value = "full")]
    pub preset: String,
    /// The photo encoder giving the first guess (default: the shipped one, with the shipped
    /// demo model). A file that cannot be used is reported and the latent-mode search starts
    /// the inversion instead.
    #[arg(long, conflicts_with = "no_encoder")]
    pub encoder: Option<PathBuf>,
    /// Start from the latent-mode search (the best of w_avg and the training subjects' codes)
    /// instead of the encoder's guess.
    #[arg(long)]
    pub no_encoder: bool,
    /// W+ steps (overrides the preset).
    #[arg(long)]
    pub steps: Option<usize>,
    /// PTI steps (overrides the preset; 0 = W+ only).
    #[arg(long)]
    pub pti_steps: Option<usize>,
    /// The inversion's options as JSON (`InversionOptions`; fields not given keep the preset's).
    #[arg(long)]
    pub options: Option<String>,
    /// Render size: a photo's crop (default 256), or a dataset image box-filtered down to it
    /// (a divisor of its size; default: its own size).
    #[arg(long)]
    pub res: Option<usize>,
    /// The .glb's texture side (64…4096).
    #[arg(long, default_value_t = 512)]
    pub texture_res: usize,
    /// A trained RGB discriminator for the perceptual term: a training state
    /// (`RUN/state.safetensors`, its `d0`) or a discriminator file (default: the shipped
    /// demo model's, with the shipped demo model).
    #[arg(long, conflicts_with = "no_perceptual")]
    pub discriminator: Option<PathBuf>,
    /// Leave the perceptual term off.
    #[arg(long)]
    pub no_perceptual: bool,
    /// PCK@0.1 (the paper's pose metric) into metrics.json: MediaPipe on the avatar rendered
    /// at the photo's camera without the photo projected, against `--keypoints` (runs
    /// tools/mediapipe_fixtures.mjs in headless Chromium; about a minute).
    #[arg(long, requires = "keypoints", requires = "image")]
    pub pck: bool,
    /// Leave the photo's colours off the .glb's texture and the outline as generated (by
    /// default the outline is moved onto the photo's person, and the colours are projected
    /// onto the surface the photo sees and blended with the generated texture at grazing
    /// angles and on the hidden side).
    #[arg(long)]
    pub no_projection: bool,
    /// Body model .npz in the SMPL layout (default: the embedded open body).
    #[arg(long)]
    pub body: Option<PathBuf>,
    #[command(flatten)]
    pub backend: crate::backend::BackendArg,
    #[arg(long)]
    pub out: PathBuf,
}

/// What `metrics.json` holds.
#[derive(Serialize)]
struct InvertMetrics {
    source: String,
    res: usize,
    options: InversionOptions,
    start: String,
    start_losses: Vec<(String, f32)>,
    /// At the input camera: the start (the encoder's guess, or the chosen latent mode), on
    /// the body the steps start from (the refitted one, where the fit was refitted).
    at_start: ViewMetrics,
    /// The encoder file's garment codes weighed against its guess (`options.garments`).
    #[serde(skip_serializing_if = "Option::is_none")]
    garments: Option<start::GarmentMetrics>,
    /// The body fit's refinement on the guess's outline (a photo, `refit_steps` > 0).
    #[serde(skip_serializing_if = "Option::is_none")]
    refit: Option<RefitMetrics>,
    /// Seconds from the command's start to the first avatar: the start generated in the
    /// canonical pose, rigged, re-posed to the body as first fitted and rendered at the input
    /// camera (before the garment codes and the refit: what the app shows first).
    seconds_to_first_avatar: f64,
    /// At the input camera: that first avatar (vertex colours, 2×2 samples per pixel).
    first_avatar: ViewMetrics,
    /// Its generation and render by stage: milliseconds of host work and of GPU waits
    /// (`getavatar_core::util::profile`; the first generation includes the canonical pose's
    /// posed grid, kept for the rest of the run).
    first_avatar_stages: Vec<getavatar_core::util::profile::StageTime>,
    perceptual: bool,
    /// At the input camera: after W+ and after PTI.
    after_w: ViewMetrics,
    after_pti: Option<ViewMetrics>,
    /// The exported avatar (baked texture, skinned mesh) rendered at the input camera,
    /// without and with the photo's colours projected on.
    baked: ViewMetrics,
    projected: ViewMetrics,
    /// Mask IoU at the opposite camera vs the subject's scan (with `--scans`).
    back_view_iou: Option<f32>,
    /// Masked PSNR (dB, over the scan's back mask) of the exported avatar's back against the
    /// scan's albedo there (with `--scans`): how well the unseen side's colours are guessed.
    #[serde(skip_serializing_if = "Option::is_none")]
    back_view_psnr_db: Option<f32>,
    /// With `--pck`: the pose metric on the photo.
    #[serde(skip_serializing_if = "Option::is_none")]
    pck: Option<crate::pck::Pck>,
    /// Reading the photo, the body, the model and its discriminator, before the start.
    seconds_loading: f64,
    seconds_start: f64,
    seconds_per_w_step: f64,
    seconds_per_pti_step: Option<f64>,
    seconds_total: f64,
}

#[derive(Serialize)]
struct RefitMetrics {
    steps: usize,
    seconds: f64,
    betas_before: Vec<f32>,
    betas_after: Vec<f32>,
}

#[derive(Serialize, Clone, Copy)]
struct ViewMetrics {
    mask_iou: f32,
    psnr_db: f32,
}

/// The target, a name for it, and (with `--scans`) the subject's scan for the back view.
/// With a photo, its body fit.
type Loaded = (InversionTarget, String, Option<(getavatar_core::io::scan::Scan, RenderableScan)>, Option<BodyFit>);

fn load_target(a: &InvertArgs, model: &BodyModel) -> Result<Loaded> {
    if let (Some(data), Some(entry)) = (&a.data, &a.entry) {
        let ds = Dataset::open(data)?;
        let i = ds.entries.iter().position(|(p, _)| p == entry).with_context(|| {
            let some: Vec<&str> = ds.entries.iter().take(3).map(|(p, _)| p.as_str()).collect();
            format!("{} has no entry `{entry}` (entries look like {})", data.display(), some.join(", "))
        })?;
        let s = ds.load(i)?;
        let mut view = s.label.view();
        view.body.betas.truncate(model.num_betas);
        let scan = match &a.scans {
            Some(dir) => {
                let subject = entry.rsplit_once('/').map_or("", |(d, _)| d);
                let scans = find_scans(dir)?;
                let (_, obj) = scans
                    .iter()
                    .find(|(n, _)| n == subject)
                    .with_context(|| format!("{} has no scan of subject `{subject}`", dir.display()))?;
                let scan = load_scan(obj)?;
                let smpl = load_body_fit(subject, obj, None)?;
                let prepared = RenderableScan::new(&scan, &smpl);
                Some((scan, prepared))
            }
            None => None,
        };
        let (res, rgb, mask) = match a.res {
            Some(r) if r != s.size => {
                if r == 0 || s.size % r != 0 {
                    bail!("--res {r} must divide the dataset's image size {}", s.size);
                }
                (r, box_down(&s.rgb, s.size, 3, r), box_down(&s.mask, s.size, 1, r))
            }
            _ => (s.size, s.rgb, s.mask),
        };
        return Ok((InversionTarget { view, res, rgb, mask }, format!("{} {entry}", data.display()), scan, None));
    }
    let (Some(image), Some(fit_path)) = (&a.image, &a.fit) else {
        bail!("give a photo (--image PHOTO --fit fit.json) or a dataset image (--data DIR --entry NAME)");
    };
    let res = a.res.unwrap_or(256);
    if !(16..=1024).contains(&res) {
        bail!("--res must be between 16 and 1024 (got {res})");
    }
    let text = std::fs::read_to_string(fit_path).with_context(|| format!("reading {}", fit_path.display()))?;
    let fit = BodyFit::from_json(&text)
        .map_err(|e| anyhow::anyhow!("{} is not a usable fit.json: {e}", fit_path.display()))?;
    let photo = open_image(image)?;
    // A fit on the photo turned to read its person upright (fit.json's `rotation`) works on
    // the turned photo.
    let (w, h) = turn::turned_size(fit.rotation, photo.width() as usize, photo.height() as usize);
    if (w, h) != (fit.framing.photo_width, fit.framing.photo_height) {
        bail!(
            "{} is {w}×{h} pixels (turned by {}°) but the fit was made on a {}×{} photo",
            image.display(),
            fit.rotation,
            fit.framing.photo_width,
            fit.framing.photo_height
        );
    }
    let mask = match (&a.mask, &a.keypoints) {
        (Some(m), _) => crate::fit_pose::turned_mask(load_mask(m)?, fit.rotation),
        (None, Some(k)) => {
            let text = std::fs::read_to_string(k).with_context(|| format!("reading {}", k.display()))?;
            PoseResult::from_json(&text)
                .with_context(|| format!("{}", k.display()))?
                .segmentation_mask
                .with_context(|| format!("{} has no segmentationMask: give --mask", k.display()))?
        }
        (None, None) => bail!("a photo needs a person mask: --mask PNG, or --keypoints with a segmentationMask"),
    };
    let rgb: Vec<f32> = photo.to_rgb8().as_raw().iter().map(|v| *v as f32 / 255.0).collect();
    let (rgb, _, _) = turn::turn_image(&rgb, photo.width() as usize, photo.height() as usize, 3, fit.rotation);
    let target = InversionTarget::from_photo(&fit, &rgb, w, h, &mask, res, model.num_betas)
        .with_context(|| format!("{} with {}", image.display(), fit_path.display()))?;
    Ok((target, image.display().to_string(), None, Some(fit)))
}

/// A square image of `size`² pixels × `c` channels box-filtered to `r`² (`r` divides `size`).
fn box_down(v: &[f32], size: usize, c: usize, r: usize) -> Vec<f32> {
    let k = size / r;
    let mut out = vec![0.0f32; r * r * c];
    for y in 0..size {
        for x in 0..size {
            for ch in 0..c {
                out[((y / k) * r + x / k) * c + ch] += v[(y * size + x) * c + ch];
            }
        }
    }
    out.iter_mut().for_each(|o| *o /= (k * k) as f32);
    out
}

/// The photo encoder: `--encoder`, else the shipped one (`shipped` = the shipped generator's
/// config). None with `--no-encoder`, without one, or when it cannot be used (said once on
/// stderr: the latent-mode search starts the inversion instead).
fn load_encoder_arg(
    a: &InvertArgs,
    g: &Generator,
    shipped: Option<&GeneratorConfig>,
    dev: &Device,
) -> Option<(Encoder, PathBuf, Option<GarmentCodes>)> {
    if a.no_encoder {
        return None;
    }
    let path = a.encoder.clone().or_else(|| shipped.and_then(shipped_encoder))?;
    let loaded = std::fs::read(&path).map_err(anyhow::Error::from).and_then(|b| {
        let e = load_encoder_for(&b, g, dev)?;
        Ok((e, b))
    });
    match loaded {
        Ok((enc, bytes)) => {
            let codes = garment_codes_of(&bytes, &path, g);
            Some((enc, path, codes))
        }
        Err(e) => {
            eprintln!(
                "the encoder {} cannot be used ({e:#}); starting from the latent-mode search instead",
                path.display()
            );
            None
        }
    }
}

/// The RGB discriminator of a training state (`d0/…`, its run's config) or of a file written
/// by `trainer train-discriminator`.
fn load_discriminator(path: &Path, device: &Device) -> Result<Discriminator> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    checkpoint::load_discriminator(&bytes, device)
        .with_context(|| format!("loading the RGB discriminator of {}", path.display()))
}

/// RGBA bytes of a render (alpha = its mask).
fn rgba(rgb: &[f32], mask: &[f32]) -> Vec<u8> {
    mask.iter()
        .enumerate()
        .flat_map(|(k, m)| {
            let c = |i: usize| (rgb[3 * k + i].clamp(0.0, 1.0) * 255.0).round() as u8;
            [c(0), c(1), c(2), (m.clamp(0.0, 1.0) * 255.0).round() as u8]
        })
        .collect()
}

fn to_u8(v: &[f32]) -> Vec<u8> {
    v.iter().map(|x| (x.clamp(0.0, 1.0) * 255.0).round() as u8).collect()
}

/// Samples per pixel and axis of the renders measured (the first avatar, the exported one, the
/// scan's back): a dataset image at 128² is a 512² render at 2×2 box-filtered, 8×8 samples. With
/// 2×2 a pixel two samples cover reads as covered and an outline a quarter pixel wider.
pub(crate) const MEASURE_SS: usize = 8;

/// The exported avatar (the rigged mesh posed by `body`, its baked texture) rendered through
/// `view_proj` at `res`² with [`MEASURE_SS`]² samples per pixel: sRGB in [0, 1] and the mask.
fn render_baked(
    rigged: &RiggedAvatar,
    ctx: &BodyContext,
    tex: &BakedTexture,
    body: &BodyParams,
    view_proj: Mat4,
    res: usize,
) -> Result<(Vec<f32>, Vec<f32>)> {
    let (pos, nrm) = rigged.repose(ctx, &pose_body(&ctx.model, body));
    let at = |v: &[Vec3]| -> Vec<Vec3> { tex.atlas.source.iter().map(|i| v[*i as usize]).collect() };
    let uv: Vec<Vec3> = tex.atlas.uvs.iter().map(|u| u.extend(0.0)).collect();
    // The baked image as the renderer's texture (glTF's v points down, the lookup's up).
    let image = Texture::from_srgb8(tex.res, tex.res, 3, &tex.rgb).context("the baked texture is not res² RGB")?;
    let sample = |uvs: &[Vec3]| {
        Ok::<_, std::convert::Infallible>(uvs.iter().map(|u| image.sample(glam::Vec2::new(u.x, 1.0 - u.y))).collect())
    };
    let v = render_views_textured(&at(&pos), &tex.atlas.faces, &at(&nrm), &uv, view_proj, res, MEASURE_SS, sample)
        .unwrap_or_else(|never| match never {});
    Ok((v.rgb.iter().map(|c| *c as f32 / 255.0).collect(), v.mask.iter().map(|m| *m as f32 / 255.0).collect()))
}

/// `--pck`: the avatar with its plain texture rendered at the photo's camera, MediaPipe on it
/// against the photo's detection (in OUT/pck/).
fn photo_pck(
    a: &InvertArgs,
    rigged: &RiggedAvatar,
    ctx: &BodyContext,
    plain: &BakedTexture,
    body: &BodyParams,
    view_proj: Mat4,
) -> Result<crate::pck::Pck> {
    let (Some(kp), Some(fit)) = (&a.keypoints, &a.fit) else { bail!("--pck needs --keypoints and --fit") };
    let text = std::fs::read_to_string(kp).with_context(|| format!("reading {}", kp.display()))?;
    let photo = PoseResult::from_json(&text).with_context(|| format!("{}", kp.display()))?;
    let text = std::fs::read_to_string(fit).with_context(|| format!("reading {}", fit.display()))?;
    let fit = BodyFit::from_json(&text).map_err(|e| anyhow::anyhow!("{}: {e}", fit.display()))?;
    let res = crate::pck::RENDER_RES;
    let (rgb, mask) = render_baked(rigged, ctx, plain, body, view_proj, res)?;
    let p = crate::pck::render_pck(&a.out.join("pck"), &rgba(&rgb, &mask), res, &photo, &fit.framing)?;
    eprintln!(
        "PCK@0.1 on the photo: {:.3} of {} landmarks (within {:.1} px){}",
        p.pck_0_1,
        p.compared,
        p.threshold_px,
        if p.render_detected { "" } else { "; MediaPipe found no person in the render" }
    );
    Ok(p)
}

/// The garment codes in the encoder file `bytes` (read from `path`; None without any, or,
/// said on stderr, when they do not fit `g`: the guess then stands alone).
fn garment_codes_of(bytes: &[u8], path: &Path, g: &Generator) -> Option<GarmentCodes> {
    let codes = parse_safetensors(bytes)
        .map_err(anyhow::Error::from)
        .map(|st| GarmentCodes::from_safetensors(&st))
        .and_then(|c| match c {
            Some(c) => c.check(g).map(|()| Some(c)).map_err(anyhow::Error::from),
            None => Ok(None),
        });
    codes.unwrap_or_else(|e| {
        eprintln!("the garment codes in {} cannot be used ({e:#}); the encoder's guess stands alone", path.display());
        None
    })
}

/// The camera opposite `w2c` about the body's vertical axis (x = z = 0).
fn opposite(w2c: Mat4) -> Mat4 {
    w2c * Mat4::from_rotation_y(std::f32::consts::PI)
}

fn view_metrics(t: &InversionTarget, rgb: &[f32], mask: &[f32]) -> ViewMetrics {
    ViewMetrics { mask_iou: mask_iou(mask, &t.mask), psnr_db: masked_psnr(rgb, &t.rgb, &t.mask) }
}

fn render_at(
    g: &Generator,
    ctx: &BodyContext,
    s: &Styles,
    view: &View,
    res: usize,
    dev: &Device,
) -> Result<(Vec<f32>, Vec<f32>)> {
    let f = render_avatars(g, ctx, s, std::slice::from_ref(view), res, &PosedGridCache::new(2), dev)?;
    Ok(render_images(&f)?)
}

/// The body context (the template SDF, the tet grid and the canonical pose's posed grid: what
/// every generation needs, 0.7 s of work on 2 cores, or 0.2 s when an earlier command kept it:
/// `model_io::body_context`), made on threads of its own while
/// the photo (`load_target`), the discriminator and the encoder load (`--out` made, the
/// input written), the encoder runs and its guess's triplanes are made; with the seconds to
/// the end of the loading and the encoder's guess with its seconds and triplanes.
#[allow(clippy::type_complexity)]
fn load_with_context(
    a: &InvertArgs,
    model: &BodyModel,
    cfg: &GeneratorConfig,
    g: &Generator,
    shipped_g: bool,
    dev: &Device,
    t0: std::time::Instant,
) -> Result<(BodyContext, Loaded, Option<Discriminator>, f64, Option<(start::FirstGuess, f64, start::EarlyPlanes)>)> {
    std::thread::scope(|sc| {
        let ctx = sc.spawn(|| crate::model_io::body_context(model.clone(), cfg));
        let (target, source, scan, photo_fit) = load_target(a, model)?;
        target.validate()?;
        let disc = discriminator_arg(a, cfg, shipped_g, dev)?;
        std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
        write_png(&a.out.join("input.png"), &rgba(&target.rgb, &target.mask), target.res, 4)?;
        let seconds_loading = t0.elapsed().as_secs_f64();
        let ts = std::time::Instant::now();
        let guess = encoder_guess(a, g, model, &target, shipped_g.then_some(cfg), dev)?;
        let guess = guess.map(|guess| {
            let seconds = ts.elapsed().as_secs_f64();
            let early = start::early_planes(g, &guess.1);
            (guess, seconds, early)
        });
        let ctx = ctx.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic));
        Ok((ctx, (target, source, scan, photo_fit), disc, seconds_loading, guess))
    })
}

/// The body model and the generator (on the device with autodiff), loaded side by side: the
/// body context waits on both.
#[allow(clippy::type_complexity)]
fn load_body_and_generator(
    a: &InvertArgs,
) -> Result<(BodyModel, Device, (GeneratorConfig, Generator, Option<LatentModes>))> {
    let (model, loaded) = std::thread::scope(|sc| {
        let body = sc.spawn(|| load_body(&a.body));
        let loaded = a.backend.device().and_then(|dev| {
            let dev = dev.autodiff();
            a.model.load(&dev).map(|m| (dev, m))
        });
        (body.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic)), loaded)
    });
    let (model, (dev, generator)) = (model?, loaded?);
    Ok((model, dev, generator))
}

pub fn invert(a: &InvertArgs) -> Result<()> {
    let t0 = std::time::Instant::now();
    let opts = invert_options(a)?;
    if !(64..=4096).contains(&a.texture_res) {
        bail!("--texture-res must be between 64 and 4096 (got {})", a.texture_res);
    }
    let (model, dev, (cfg, g, modes)) = load_body_and_generator(a)?;
    // The shipped discriminator goes with the shipped generator only.
    let shipped_g = a.model.checkpoint.is_none() && !a.model.random;
    let (ctx, loaded, disc, seconds_loading, guess) = load_with_context(a, &model, &cfg, &g, shipped_g, &dev, t0)?;
    let (mut target, source, scan, photo_fit) = loaded;
    eprintln!(
        "loaded the photo, the body, the model and its discriminator in {seconds_loading:.2} s, the body context after {:.2} s",
        t0.elapsed().as_secs_f64()
    );
    // The start: the encoder's guess, or the latent mode (or w_avg) that explains the image best.
    let ((start, mut start_styles, start_losses, garment_codes), seconds_start, early) = match guess {
        Some((guess, seconds, early)) => (guess, seconds, Some(early)),
        None => {
            let ts = std::time::Instant::now();
            (search_guess(&g, modes.as_ref(), &ctx, &target, &dev)?, ts.elapsed().as_secs_f64(), None)
        }
    };
    eprintln!("start: {start} ({seconds_start:.2} s)");
    let codes = garment_codes.as_ref();
    let views =
        start_views(a, &g, &ctx, &mut start_styles, codes, photo_fit.as_ref(), &mut target, &opts, &dev, early, t0)?;
    let StartViews { first_avatar, seconds_to_first_avatar, at_start, rgb: rgb0, mask: mask0, .. } = views;
    let first_avatar_stages = views.first_avatar_stages;
    let (refit, rigged_start, garments) = (views.refit, views.rigged_start, views.garments);

    let mut inv = Inverter::new(g, &ctx, disc, target.clone(), &start_styles, opts.clone(), &dev)?;
    let perceptual = inv.has_perceptual();
    let (after_w, t_w, t_pti) = run_steps(&mut inv, &opts, &target, &a.out)?;
    let styles = inv.styles();
    let g = inv.generator().clone();

    // The input camera (RGBA at the input's resolution): with no step taken, the start's render.
    let (rgb, mask) = if opts.steps + opts.pti_steps == 0 {
        (rgb0, mask0)
    } else {
        render_at(&g, &ctx, &styles, &target.view, target.res, &dev)?
    };
    let final_m = view_metrics(&target, &rgb, &mask);
    write_png(&a.out.join("input_view.png"), &rgba(&rgb, &mask), target.res, 4)?;
    let r = target.res;
    let png = getavatar_core::io::dataset::encode_png(3 * r, r, 3, &comparison_image(&target, &rgb, &mask))?;
    write_atomic(&a.out.join("comparison.png"), &png)?;

    // The animatable avatar, its baked textures, and what it looks like at the input camera.
    let mut rigged = match rigged_start.filter(|_| opts.steps + opts.pti_steps == 0) {
        Some(r) => r,
        None => block_on_ready(generate_rigged_async(&g, &ctx, &styles, &dev))?,
    };
    if rigged.canonical.mesh.faces.is_empty() {
        bail!("the inverted generator produced an empty surface");
    }
    let photo = target.source_photo();
    // The outline onto the photo's person, as every later bake of the saved file does.
    if !a.no_projection {
        snap_to_photo(&mut rigged, &ctx, &photo);
    }
    let planes = g.triplanes(&styles);
    let bake = |photo| {
        block_on_ready(rigged.bake_texture_photo_async(&g, &planes, &styles, &ctx, a.texture_res, photo, &dev))
            .context("baking the texture")
    };
    let body = &target.view.body;
    let projection = rigged.photo_projection(&ctx, &photo);
    let plain = bake(None)?;
    let projected = bake(Some((&projection, body)))?;
    let proj = OrbitCamera::default().projection_gl(1.0);
    let vp = proj * target.view.world_to_camera;
    let (prgb, pmask) = render_baked(&rigged, &ctx, &plain, body, vp, r)?;
    let baked_m = view_metrics(&target, &prgb, &pmask);
    let (prgb, pmask) = render_baked(&rigged, &ctx, &projected, body, vp, r)?;
    let projected_m = view_metrics(&target, &prgb, &pmask);
    let pck = if a.pck { Some(photo_pck(a, &rigged, &ctx, &plain, body, vp)?) } else { None };
    write_png(&a.out.join("input_view_projected.png"), &rgba(&prgb, &pmask), r, 4)?;
    eprintln!(
        "exported avatar at the input camera: masked PSNR {:.2} dB, {:.2} dB with the photo projected",
        baked_m.psnr_db, projected_m.psnr_db
    );
    let tex = if a.no_projection { plain } else { projected };

    // The exported avatar from behind and in other poses (the rigged mesh re-posed and its
    // texture: what an engine shows, and milliseconds where a generation takes seconds).
    let back = opposite(target.view.world_to_camera);
    let (brgb, bmask) = render_baked(&rigged, &ctx, &tex, body, proj * back, r)?;
    write_png(&a.out.join("back_view.png"), &rgba(&brgb, &bmask), r, 4)?;
    let back_truth = match &scan {
        Some((scan, prepared)) => Some(back_view_truth(scan, prepared, proj * back, (&brgb, &bmask), r, &a.out)?),
        None => None,
    };
    write_pose_views(&rigged, &ctx, &tex, body, r, &a.out)?;

    let walk = Motion::builtin("walk")?;
    let glb =
        rigged.animated_glb(&ctx, &target.view.body, &[walk], Some(&tex), "inverted avatar", SkeletonNames::Smpl)?;
    write_atomic(&a.out.join("avatar.glb"), &glb)?;
    let mut extra = BTreeMap::new();
    extra.insert("inversion/source".into(), source.clone());
    extra.insert("inversion/options".into(), serde_json::to_string(&opts)?);
    write_atomic(
        &a.out.join("inverted.safetensors"),
        &save_inverted(&g, &cfg, &styles, (!a.no_projection).then_some(&photo), &extra)?,
    )?;

    let metrics = InvertMetrics {
        source,
        res: r,
        options: opts.clone(),
        start,
        start_losses,
        at_start,
        garments,
        refit,
        seconds_to_first_avatar,
        first_avatar,
        first_avatar_stages,
        perceptual,
        after_w: if opts.steps > 0 { after_w.unwrap_or(final_m) } else { at_start },
        after_pti: (opts.pti_steps > 0).then_some(final_m),
        baked: baked_m,
        projected: projected_m,
        back_view_iou: back_truth.map(|b| b.0),
        back_view_psnr_db: back_truth.map(|b| b.1),
        pck,
        seconds_loading,
        seconds_start,
        seconds_per_w_step: t_w.unwrap_or(0.0),
        seconds_per_pti_step: t_pti,
        seconds_total: t0.elapsed().as_secs_f64(),
    };
    write_atomic(&a.out.join("metrics.json"), serde_json::to_string_pretty(&metrics)?.as_bytes())?;
    println!(
        "wrote {}: mask IoU {:.3}, masked PSNR {:.2} dB at the input camera{}; {:.0} s",
        a.out.display(),
        final_m.mask_iou,
        final_m.psnr_db,
        back_truth.map_or(String::new(), |(i, p)| format!(", back view IoU {i:.3} and masked PSNR {p:.2} dB")),
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}

/// The preset's options with `--options` (JSON fields) and `--steps` / `--pti-steps` over them.
fn invert_options(a: &InvertArgs) -> Result<InversionOptions> {
    let mut opts = InversionOptions::preset(&a.preset)
        .with_context(|| format!("unknown --preset `{}` (instant, fast, full)", a.preset))?;
    if let Some(json) = &a.options {
        let mut v = serde_json::to_value(&opts)?;
        let over: serde_json::Value = serde_json::from_str(json).context("--options is not JSON")?;
        let (Some(base), Some(over)) = (v.as_object_mut(), over.as_object()) else {
            bail!("--options must be a JSON object")
        };
        for (k, x) in over {
            if !base.contains_key(k) {
                bail!("--options: unknown field `{k}`");
            }
            base.insert(k.clone(), x.clone());
        }
        opts = serde_json::from_value(v).context("--options")?;
    }
    if let Some(n) = a.steps {
        opts.steps = n;
    }
    if let Some(n) = a.pti_steps {
        opts.pti_steps = n;
    }
    Ok(opts)
}

/// The discriminator of the perceptual term: `--discriminator`, or the shipped one with the
/// shipped generator; none with `--no-perceptual`.
fn discriminator_arg(
    a: &InvertArgs,
    cfg: &GeneratorConfig,
    shipped_g: bool,
    dev: &Device,
) -> Result<Option<Discriminator>> {
    let d_path = match (&a.discriminator, a.no_perceptual) {
        (_, true) => None,
        (Some(p), _) => Some(p.clone()),
        (None, false) => shipped_g.then(|| shipped_discriminator(cfg)).flatten(),
    };
    let disc = d_path.as_deref().map(|p| load_discriminator(p, dev)).transpose()?;
    match (&disc, &d_path) {
        (Some(_), Some(p)) => eprintln!("perceptual term: the features of {}", p.display()),
        _ => eprintln!("no discriminator: the perceptual term is off"),
    }
    Ok(disc)
}

/// The inversion's steps with a progress bar and `steps.jsonl`: the figures after W+ (its
/// render written as `input_view_w.png`), seconds per W+ step and per PTI step.
fn run_steps(
    inv: &mut Inverter,
    opts: &InversionOptions,
    target: &InversionTarget,
    out: &Path,
) -> Result<(Option<ViewMetrics>, Option<f64>, Option<f64>)> {
    let (_, all) = inv.progress();
    let bar = crate::progress::bar(all as u64, "steps");
    let mut log = std::io::BufWriter::new(
        std::fs::File::create(out.join("steps.jsonl"))
            .with_context(|| format!("creating {}/steps.jsonl", out.display()))?,
    );
    let (mut after_w, mut t_w, mut t_pti) = (None, None, None);
    let tw = std::time::Instant::now();
    let mut tp = None;
    loop {
        if after_w.is_none() && opts.steps > 0 && inv.phase() != Phase::Latent {
            // The W+ result, before tuning.
            t_w = Some(tw.elapsed().as_secs_f64() / opts.steps.max(1) as f64);
            let (rgb, mask) = render_images(&inv.render()?)?;
            let m = view_metrics(target, &rgb, &mask);
            eprintln!("after W+: mask IoU {:.3}, masked PSNR {:.2} dB", m.mask_iou, m.psnr_db);
            write_png(&out.join("input_view_w.png"), &rgba(&rgb, &mask), target.res, 4)?;
            after_w = Some(m);
            tp = Some(std::time::Instant::now());
        }
        let Some(r) = inv.step()? else { break };
        let (phase, iou) = (if r.phase == Phase::Latent { "W+" } else { "PTI" }, r.terms.mask_iou);
        if r.restarted {
            bar.println(format!("{phase} step {}: mask IoU {iou:.3}, on from the best state at half the rate", r.step));
        }
        writeln!(log, "{}", serde_json::to_string(&r)?)?;
        log.flush()?; // every step on disk: a killed run leaves its log
        let (done, _) = inv.progress();
        bar.set_position(done as u64);
        bar.set_message(format!("{phase} loss {:.4} IoU {iou:.3}", r.terms.total));
    }
    log.flush()?;
    bar.finish_and_clear();
    if let Some(tp) = tp.filter(|_| opts.pti_steps > 0) {
        t_pti = Some(tp.elapsed().as_secs_f64() / opts.pti_steps as f64);
    }
    Ok((after_w, t_w, t_pti))
}

/// The mask IoU at the back camera against the scan's own render (written as
/// `back_view_truth.png`).
fn back_view_truth(
    scan: &getavatar_core::io::scan::Scan,
    prepared: &RenderableScan,
    vp: Mat4,
    (brgb, bmask): (&[f32], &[f32]),
    r: usize,
    out: &Path,
) -> Result<(f32, f32)> {
    let albedo = |attrs: &[Vec3]| Ok::<_, std::convert::Infallible>(attrs.iter().map(|x| scan.albedo(*x)).collect());
    let truth = render_views_textured(
        &prepared.vertices,
        &prepared.triangles,
        &prepared.normals,
        &prepared.attributes,
        vp,
        r,
        MEASURE_SS,
        albedo,
    )
    .unwrap_or_else(|never| match never {});
    let tm: Vec<f32> = truth.mask.iter().map(|m| *m as f32 / 255.0).collect();
    let trgb: Vec<f32> = truth.rgb.iter().map(|c| *c as f32 / 255.0).collect();
    write_png(&out.join("back_view_truth.png"), &to_u8(&tm), r, 1)?;
    write_png(&out.join("back_view_truth_rgb.png"), &rgba(&trgb, &tm), r, 4)?;
    Ok((mask_iou(bmask, &tm), masked_psnr(brgb, &trgb, &tm)))
}

/// The exported avatar in three library poses from the front (`pose_<name>.png`).
fn write_pose_views(
    rigged: &RiggedAvatar,
    ctx: &BodyContext,
    tex: &BakedTexture,
    body: &BodyParams,
    r: usize,
    out: &Path,
) -> Result<()> {
    let lib = PoseLibrary::builtin();
    let front = OrbitCamera::default().projection_gl(1.0) * OrbitCamera::default().world_to_camera();
    for name in ["walking", "arms_up", "sitting"] {
        let mut pose = lib.params(name, &body.betas)?;
        pose.betas = body.betas.clone();
        let (prgb, pmask) = render_baked(rigged, ctx, tex, &pose, front, r)?;
        write_png(&out.join(format!("pose_{name}.png")), &rgba(&prgb, &pmask), r, 4)?;
    }
    Ok(())
}
