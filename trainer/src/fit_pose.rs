//! `trainer fit-pose`: the app's photo → body fit from MediaPipe Pose's landmarks, scriptable
//! (`kp.json` is the detector's result object as its JavaScript API returns it), and
//! `trainer bench fit`: the fit's time per stage and accuracy on synthetic detections.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use crate::model_io::load_body;
use anyhow::{bail, Context, Result};
use getavatar_core::body::body_fit::fit::{BodyFit, BodyFitter, FitInput, FitOptions, STAGE_NAMES};
use getavatar_core::body::body_fit::landmarks::{PoseResult, SegmentationMask};
use getavatar_core::body::body_fit::metrics::{body_mask, mask_iou, pa_mpjpe};
use getavatar_core::body::body_fit::synthetic::{
    dance, detect, unseen_poses, wide_camera, wide_poses, DANCE_CAMERA, UNSEEN_POSE_CAMERAS, WIDE_YAWS,
};
use getavatar_core::body::body_fit::turn;
use getavatar_core::body::body_model::BodyModel;
use getavatar_core::body::skinning::pose_body;
use getavatar_core::burn::tensor::Device;
use getavatar_core::generator::readback::block_on_ready;
use getavatar_core::util::rng::Rng;

#[derive(clap::Args, Debug)]
pub struct FitPoseArgs {
    #[command(flatten)]
    pub backend: crate::backend::BackendArg,
    /// The photo (PNG or JPEG): its size maps the normalised landmarks to pixels.
    #[arg(long)]
    pub image: PathBuf,
    /// MediaPipe Pose's result: `poseLandmarks`, `poseWorldLandmarks`, optional
    /// `segmentationMask` ({width, height, data}).
    #[arg(long)]
    pub keypoints: PathBuf,
    /// A person mask PNG (grey, or the alpha channel where it has one), any size covering the
    /// photo; overrides the result's `segmentationMask`.
    #[arg(long)]
    pub mask: Option<PathBuf>,
    #[arg(long, default_value = "fit.json")]
    pub out: PathBuf,
    /// Also draw the fitted body and keypoints over the photo into this PNG.
    #[arg(long)]
    pub overlay: Option<PathBuf>,
    /// Adam steps of the torso, body and silhouette stages.
    #[arg(long, value_delimiter = ',', num_args = 3, default_values_t = FitOptions::default().iterations)]
    pub iterations: Vec<usize>,
    /// β components to fit (0 keeps the mean shape).
    #[arg(long, default_value_t = FitOptions::default().num_betas)]
    pub betas: usize,
    /// Body model .npz in the SMPL layout (default: the embedded open body).
    #[arg(long)]
    pub body: Option<PathBuf>,
    /// Fit again from this fit.json of the same photo with its pose corrected (edit its
    /// `body_pose`, or the app's pose controls then "Download fit"): a limb it puts far from
    /// the detector's landmarks is held where it is and those landmarks are left out.
    #[arg(long)]
    pub start: Option<PathBuf>,
}

pub(crate) fn open_image(path: &std::path::Path) -> Result<image::DynamicImage> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    getavatar_core::io::dataset::decode_photo(&bytes).map_err(|e| anyhow::anyhow!("{} {e}", path.display()))
}

pub(crate) fn load_mask(path: &std::path::Path) -> Result<SegmentationMask> {
    let img = open_image(path)?;
    let (width, height) = (img.width() as usize, img.height() as usize);
    let data: Vec<f32> = if img.color().has_alpha() && img.to_rgba8().pixels().any(|p| p[3] < 255) {
        img.to_rgba8().pixels().map(|p| p[3] as f32 / 255.0).collect()
    } else {
        img.to_luma8().pixels().map(|p| p[0] as f32 / 255.0).collect()
    };
    Ok(SegmentationMask { width, height, data })
}

/// Run a fit to the end with a progress bar.
fn run_fit(
    model: Arc<BodyModel>,
    input: FitInput,
    options: FitOptions,
    start: Option<&BodyFit>,
    device: &Device,
) -> Result<BodyFit> {
    let mut fitter = BodyFitter::new(model, input, options, device)?;
    if let Some(start) = start {
        fitter.correct_from(start);
    }
    let bar = crate::progress::bar(fitter.total_steps() as u64, "steps");
    let fit = block_on_ready(async {
        while let Some(p) = fitter.step().await? {
            bar.set_position(p.done as u64);
            bar.set_message(format!("{} loss {:.3}", STAGE_NAMES[p.stage], p.loss));
        }
        fitter.finish().await
    })?;
    bar.finish_and_clear();
    Ok(fit)
}

pub fn fit_pose(args: &FitPoseArgs) -> Result<()> {
    let photo = open_image(&args.image)?;
    let text =
        std::fs::read_to_string(&args.keypoints).with_context(|| format!("reading {}", args.keypoints.display()))?;
    let result = PoseResult::from_json(&text).with_context(|| format!("{}", args.keypoints.display()))?;
    // A detection on the photo turned to read its person upright: the fit works on the
    // turned photo (the landmarks' frame), the overlay goes back onto the photo as taken.
    let (w, h) = turn::turned_size(result.rotation, photo.width() as usize, photo.height() as usize);
    let mask = args.mask.as_deref().map(load_mask).transpose()?.map(|m| turned_mask(m, result.rotation));
    let model = Arc::new(load_body(&args.body)?);
    let [a, b, c] = args.iterations[..] else { bail!("--iterations takes three numbers: torso,body,silhouette") };
    let options = FitOptions { iterations: [a, b, c], num_betas: args.betas, ..FitOptions::default() };
    let input = FitInput::from_detection(&result, w, h, mask.as_ref(), &model, &options)?;
    let start = match &args.start {
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
            let fit = BodyFit::from_json(&text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
            if fit.rotation != result.rotation {
                bail!(
                    "{}: a fit of the photo turned by {}°, the detection is turned by {}°",
                    path.display(),
                    fit.rotation,
                    result.rotation
                );
            }
            let (a, b) = (fit.framing, input.framing);
            let moved = (a.centre[0] - b.centre[0]).hypot(a.centre[1] - b.centre[1]).max((a.side - b.side).abs());
            if (a.photo_width, a.photo_height) != (b.photo_width, b.photo_height) || moved > 1.0 {
                bail!(
                    "{}: a fit of another photo or detection (its crop differs from this detection's)",
                    path.display()
                );
            }
            Some(fit)
        }
        None => None,
    };
    let device = args.backend.device()?.autodiff();
    let fit = run_fit(model.clone(), input, options, start.as_ref(), &device)?;
    crate::atomic::write_atomic(&args.out, fit.to_json()?.as_bytes())?;
    let r = &fit.residuals;
    println!(
        "wrote {}: mean keypoint error {:.1} px ({:.2} % of the body's height){}{}{}{}{}",
        args.out.display(),
        r.mean_px,
        100.0 * r.relative_to_height,
        r.mask_iou.map_or(String::new(), |i| format!(", mask IoU {i:.3}")),
        if fit.missing.is_empty() { String::new() } else { format!("; not seen: {}", fit.missing.join(", ")) },
        if fit.off_person.is_empty() {
            String::new()
        } else {
            format!(
                "; put off the person's mask by the detector, fitted to the mask instead: {}",
                fit.off_person.join(", ")
            )
        },
        if fit.relabelled.is_empty() {
            String::new()
        } else {
            format!("; hands swapped back: {}", fit.relabelled.join(", "))
        },
        if fit.held.is_empty() {
            String::new()
        } else {
            format!("; held where the start puts them, against the detector: {}", fit.held.join(", "))
        }
    );
    if let Some(path) = &args.overlay {
        let png = overlay(&photo.to_rgb8(), &model, &fit)?;
        crate::atomic::write_atomic(path, &png)?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

/// A person mask of the photo as taken, turned as the detection turned the photo.
pub(crate) fn turned_mask(m: SegmentationMask, deg: u16) -> SegmentationMask {
    let (data, width, height) = turn::turn_image(&m.data, m.width, m.height, 1, deg);
    SegmentationMask { width, height, data }
}

/// The photo as taken with the fitted body tinted over it, detected keypoints (green) joined
/// to the fitted ones (red); a fit on a turned photo is drawn through its camera rolled back.
fn overlay(photo: &image::RgbImage, model: &BodyModel, fit: &BodyFit) -> Result<Vec<u8>> {
    let (w, h) = (photo.width() as usize, photo.height() as usize);
    let view_proj = fit.original_photo_view_proj();
    let back = |p: [f32; 2]| turn::point_to_original(fit.rotation, w, h, p);
    let posed = pose_body(model, &fit.body_params());
    let clip: Vec<glam::Vec4> = posed.vertices.iter().map(|v| view_proj * v.extend(1.0)).collect();
    let raster = getavatar_core::render::rasterize::rasterize(&clip, &model.faces, w, h);
    let mut px: Vec<u8> = photo.as_raw().clone();
    for (k, t) in raster.triangle.iter().enumerate() {
        if *t >= 0 {
            for (c, tint) in [60.0f32, 120.0, 255.0].iter().enumerate() {
                px[k * 3 + c] = (0.55 * px[k * 3 + c] as f32 + 0.45 * tint) as u8;
            }
        }
    }
    let r = (w.max(h) / 200).max(2) as i64;
    let mut dot = |p: [f32; 2], colour: [u8; 3]| {
        for dy in -r..=r {
            for dx in -r..=r {
                let (x, y) = (p[0] as i64 + dx, p[1] as i64 + dy);
                if x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h {
                    let k = (y as usize * w + x as usize) * 3;
                    px[k..k + 3].copy_from_slice(&colour);
                }
            }
        }
    };
    for kp in fit.keypoints.iter().filter(|k| k.visibility >= 0.5) {
        let observed = back(kp.observed);
        if let Some(f) = kp.fitted.map(back) {
            for s in 0..=16 {
                let t = s as f32 / 16.0;
                let q = [observed[0] + t * (f[0] - observed[0]), observed[1] + t * (f[1] - observed[1])];
                dot(q, [255, 255, 0]);
            }
            dot(f, [230, 30, 30]);
        }
        dot(observed, [30, 220, 30]);
    }
    Ok(getavatar_core::io::dataset::encode_png(w, h, 3, &px)?)
}

#[derive(clap::Args, Debug)]
pub struct BenchFitArgs {
    #[command(flatten)]
    pub backend: crate::backend::BackendArg,
    /// Photo size of the synthetic detections, pixels.
    #[arg(long, default_value_t = 512)]
    pub size: usize,
}

/// Fit every synthetic unseen pose; print per-stage time per step, total time, PA-MPJPE and
/// mask IoU, and the ratios of the stages' step times (measured in this run).
pub fn bench_fit(args: &BenchFitArgs) -> Result<()> {
    let model = Arc::new(BodyModel::default_body()?);
    let device = args.backend.device()?.autodiff();
    let options = FitOptions::default();
    println!(
        "body fit, backend {}, photo {}², iterations torso/body/silhouette {:?}, silhouette {}²",
        args.backend.backend, args.size, options.iterations, options.silhouette_size
    );
    println!("| pose | torso ms/step | body ms/step | silhouette ms/step | total s | PA-MPJPE mm | IoU |");
    println!("|---|---|---|---|---|---|---|");
    let mut rng = Rng::new(20, 1);
    let mut sums = [0.0f64; 3];
    for ((name, truth), cam) in unseen_poses().into_iter().zip(UNSEEN_POSE_CAMERAS.map(|c| c.camera())) {
        let det = detect(&model, &truth, cam.world_to_camera(), args.size, 2.0, 0.02, &mut rng)?;
        let mask = SegmentationMask { width: args.size, height: args.size, data: det.mask.clone() };
        let input = FitInput::from_detection(&det.result, args.size, args.size, Some(&mask), &model, &options)?;
        let mut fitter = BodyFitter::new(model.clone(), input, options.clone(), &device)?;
        let mut per_stage = [(0.0f64, 0usize); 3];
        let start = Instant::now();
        let fit = block_on_ready(async {
            loop {
                let t = Instant::now();
                let Some(p) = fitter.step().await? else { break };
                per_stage[p.stage].0 += t.elapsed().as_secs_f64();
                per_stage[p.stage].1 += 1;
            }
            fitter.finish().await
        })?;
        let total = start.elapsed().as_secs_f64();
        let ms: Vec<f64> = per_stage.iter().map(|(t, n)| 1000.0 * t / (*n).max(1) as f64).collect();
        for (s, m) in sums.iter_mut().zip(&ms) {
            *s += m;
        }
        let fitted = pose_body(&model, &fit.body_params());
        let err = pa_mpjpe(&fitted.kinematics.posed_joints, &pose_body(&model, &truth).kinematics.posed_joints);
        let iou = mask_iou(&body_mask(&fitted.vertices, &model.faces, fit.photo_view_proj(), args.size), &det.mask);
        println!(
            "| {name} | {:.2} | {:.2} | {:.2} | {total:.2} | {:.1} | {iou:.3} |",
            ms[0],
            ms[1],
            ms[2],
            err * 1000.0
        );
    }
    println!(
        "ratios (mean step times): body/torso {:.2}, silhouette/body {:.2}",
        sums[1] / sums[0].max(1e-9),
        sums[2] / sums[1].max(1e-9)
    );
    Ok(())
}

/// Yaws (radians, added to each unseen pose's own camera) of the bare-body photos.
pub const BODY_PHOTO_YAWS: [f32; 2] = [0.0, -0.9];

/// The bare body in every unseen pose from each of [`BODY_PHOTO_YAWS`] (`<pose>_yaw<k>.png`)
/// and in every wider-set pose from each of [`WIDE_YAWS`] (`<pose>_view<k>.png`):
/// skin-coloured, Lambert-shaded (a light from the upper left of the camera plus ambient),
/// white background, `size`² PNGs. The input of the real-detector
/// fixtures (`tools/mediapipe_fixtures.mjs` runs MediaPipe on them).
pub fn body_photos(out: &std::path::Path, size: usize) -> Result<Vec<PathBuf>> {
    let model = BodyModel::default_body()?;
    let mut written = Vec::new();
    for (name, params) in wide_poses() {
        for (k, yaw) in WIDE_YAWS.iter().enumerate() {
            let png = body_photo(&model, &params, wide_camera(*yaw).camera(), size)?;
            let path = out.join(format!("{name}_view{k}.png"));
            crate::atomic::write_atomic(&path, &png)?;
            written.push(path);
        }
    }
    for ((name, params), base) in unseen_poses().into_iter().zip(UNSEEN_POSE_CAMERAS) {
        for (k, dyaw) in BODY_PHOTO_YAWS.iter().enumerate() {
            let cam = getavatar_core::body::body_fit::synthetic::TestCamera { yaw: base.yaw + dyaw, ..base }.camera();
            let png = body_photo(&model, &params, cam, size)?;
            let path = out.join(format!("{name}_yaw{k}.png"));
            crate::atomic::write_atomic(&path, &png)?;
            written.push(path);
        }
    }
    Ok(written)
}

/// The first `frames` frames of the synthetic [`dance`] at 30 fps as bare-body photos
/// (`dance_000.png`, …), filmed by [`DANCE_CAMERA`]; the number written.
pub fn dance_photos(out: &std::path::Path, size: usize, frames: usize) -> Result<usize> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let model = BodyModel::default_body()?;
    let bar = crate::progress::bar(frames as u64, "frames");
    for (k, params) in dance(frames, 30.0).iter().enumerate() {
        let png = body_photo(&model, params, DANCE_CAMERA.camera(), size)?;
        crate::atomic::write_atomic(&out.join(format!("dance_{k:03}.png")), &png)?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(frames)
}

/// One bare-body photo (PNG bytes).
pub fn body_photo(
    model: &BodyModel,
    params: &getavatar_core::BodyParams,
    cam: getavatar_core::OrbitCamera,
    size: usize,
) -> Result<Vec<u8>> {
    let posed = pose_body(model, params);
    let normals = getavatar_core::body::skinning::vertex_normals(&posed.vertices, &model.faces);
    let eye = cam.eye();
    let to_cam = (eye - cam.target).normalize();
    let light = (to_cam + glam::Vec3::new(-0.4, 0.6, 0.0)).normalize();
    let skin = glam::Vec3::new(0.62, 0.42, 0.32);
    let colours: Vec<glam::Vec3> = normals.iter().map(|n| skin * (0.35 + 0.75 * n.dot(light).max(0.0))).collect();
    let view_proj = cam.projection_gl(1.0) * cam.world_to_camera();
    let r = getavatar_core::render::rasterize::render_views(
        &posed.vertices,
        &model.faces,
        &normals,
        &colours,
        view_proj,
        size,
        2,
    );
    Ok(getavatar_core::io::dataset::encode_png(size, size, 3, &r.rgb)?)
}
