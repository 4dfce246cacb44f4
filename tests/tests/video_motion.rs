//! Motion from a video, against known truth: the body dancing a clip that is in neither the
//! pose library nor the built-in clips ([`dance`]: squat, jump with a sharp quarter turn,
//! side step, swinging arms), filmed by a fixed camera, detected per frame with noise,
//! fitted by the video path (one shape, warm-started frames, smoothing):
//! - every frame's PA-MPJPE ≤ 60 mm;
//! - the smoothing helps: the acceleration error is below that of the same fits unsmoothed;
//! - it does not lag: through the sharp turn the root's yaw is within 2 frames of the truth's;
//! - the root's path is within 10 cm of the truth's after scale alignment;
//! - frames without a person are filled in and reported; a clip without one is an error.
//!
//! The settings can be varied for measurements (docs/benchmarks.md, "Motion from a video"):
//! `VIDEO_WARM=10,60,0` (warm steps per stage), `VIDEO_SMOOTHING=1.5` (σ, frames),
//! `VIDEO_TEMPORAL=0` (pull towards the previous frame), `VIDEO_DEBUG=1` (per-frame yaw and
//! error), e.g. `VIDEO_SMOOTHING=0 VIDEO_TEMPORAL=5 cargo test --workspace --test video_motion -- --nocapture`.

use std::sync::Arc;

use getavatar_core::body_fit::landmarks::SegmentationMask;
use getavatar_core::body_fit::metrics::pa_mpjpe;
use getavatar_core::body_fit::synthetic::{dance, detect, TestCamera};
use getavatar_core::body_fit::temporal::{acceleration_error, lag_at_half_change};
use getavatar_core::body_fit::video::{VideoDetections, VideoError, VideoFitOptions, VideoFitter, VideoMotion};
use getavatar_core::readback::block_on_ready;
use getavatar_core::rng::Rng;
use getavatar_core::skinning::{axis_angle_to_quat, pose_body};
use getavatar_core::{BodyModel, BodyParams};
use glam::Vec3;

mod common;
use common::cpu;

const FPS: f32 = 30.0;
const FRAMES: usize = 60;
const SIZE: usize = 256;

fn camera() -> TestCamera {
    TestCamera { yaw: 0.3, pitch: 0.05, radius: 3.2 }
}

fn detections(model: &BodyModel, truth: &[BodyParams], lose: &[usize]) -> VideoDetections {
    let mut rng = Rng::new(64, 1);
    let view = camera().camera().world_to_camera();
    let results = truth
        .iter()
        .enumerate()
        .map(|(k, p)| {
            let det = detect(model, p, view, SIZE, 2.0, 0.02, &mut rng).unwrap();
            let mut r = det.result;
            r.segmentation_mask = Some(SegmentationMask { width: SIZE, height: SIZE, data: det.mask });
            (!lose.contains(&k)).then_some(r)
        })
        .collect();
    VideoDetections { results, width: SIZE, height: SIZE, fps: FPS }
}

fn run(model: &Arc<BodyModel>, det: &VideoDetections, options: VideoFitOptions) -> (VideoFitter, VideoMotion) {
    let mut fitter = VideoFitter::new(model.clone(), det, options, &cpu().autodiff()).unwrap();
    block_on_ready(async {
        while fitter.step().await?.is_some() {}
        Ok::<_, VideoError>(())
    })
    .unwrap();
    let motion = fitter.finish("dance").unwrap();
    (fitter, motion)
}

/// Joints in the camera's axes, root-relative, per frame.
fn camera_joints(model: &BodyModel, params: impl Iterator<Item = BodyParams>, to_camera: glam::Mat3) -> Vec<Vec<Vec3>> {
    params
        .map(|p| {
            let j = pose_body(model, &p).kinematics.posed_joints;
            j.iter().map(|x| to_camera * (*x - j[0])).collect()
        })
        .collect()
}

/// The root's yaw about the camera's vertical, unwrapped, relative to the first frame.
fn yaws(orients: impl Iterator<Item = glam::Quat>) -> Vec<f32> {
    let mut out: Vec<f32> = Vec::new();
    for q in orients {
        let f = q * Vec3::Z;
        let mut a = f.x.atan2(f.z);
        if let Some(&last) = out.last() {
            while a - last > std::f32::consts::PI {
                a -= 2.0 * std::f32::consts::PI;
            }
            while a - last < -std::f32::consts::PI {
                a += 2.0 * std::f32::consts::PI;
            }
        }
        out.push(a);
    }
    let first = out[0];
    out.iter().map(|a| a - first).collect()
}

#[test]
fn a_dance_filmed_from_one_camera_comes_back_as_its_motion() {
    let model = Arc::new(BodyModel::default_body().unwrap());
    let truth = dance(FRAMES, FPS);
    let lose = [40, 41];
    let det = detections(&model, &truth, &lose);
    let start = std::time::Instant::now();
    let mut options = VideoFitOptions::default();
    if let Ok(w) = std::env::var("VIDEO_WARM") {
        let v: Vec<usize> = w.split(',').map(|x| x.parse().unwrap()).collect();
        options.warm_iterations = [v[0], v[1], v[2]];
    }
    if let Ok(w) = std::env::var("VIDEO_SMOOTHING") {
        options.smoothing = w.parse().unwrap();
    }
    if let Ok(w) = std::env::var("VIDEO_TEMPORAL") {
        options.temporal = w.parse().unwrap();
    }
    let (mut fitter, video) = run(&model, &det, options);
    let seconds = start.elapsed().as_secs_f32();
    assert_eq!(video.lost, lose);
    assert_eq!(video.motion.len(), FRAMES);
    assert!(video.motion.notes.iter().any(|n| n.contains("2 of 60 frames")), "{:?}", video.motion.notes);
    fitter.set_smoothing(0.0);
    let raw = fitter.finish("dance").unwrap();

    let view = camera().camera().world_to_camera();
    let to_camera = glam::Mat3::from_mat4(view);
    let true_joints = camera_joints(&model, truth.iter().cloned(), to_camera);
    let betas = video.betas.clone();
    let fitted =
        |m: &VideoMotion| camera_joints(&model, (0..FRAMES).map(|k| m.motion.params(k, &betas)), glam::Mat3::IDENTITY);
    let (smoothed, unsmoothed) = (fitted(&video), fitted(&raw));

    let errors: Vec<f32> = smoothed.iter().zip(&true_joints).map(|(a, b)| pa_mpjpe(a, b)).collect();
    let worst = errors.iter().copied().fold(0.0f32, f32::max);
    let mean = errors.iter().sum::<f32>() / errors.len() as f32;
    let accel = acceleration_error(&smoothed, &true_joints);
    let accel_raw = acceleration_error(&unsmoothed, &true_joints);

    let true_yaw = yaws(truth.iter().map(|p| glam::Quat::from_mat3(&to_camera) * axis_angle_to_quat(p.pose[0])));
    let fit_yaw = yaws(video.motion.poses.iter().map(|p| axis_angle_to_quat(p[0])));
    let lag = lag_at_half_change(&fit_yaw, &true_yaw).expect("the turn is seen");
    if std::env::var_os("VIDEO_DEBUG").is_some() {
        for k in 0..FRAMES {
            let p = &video.motion.poses[k];
            eprintln!(
                "{k}: yaw {:.2} truth {:.2} error {:.1} mm; spine {:.2} {:.2} {:.2} hips {:.2} {:.2}",
                fit_yaw[k],
                true_yaw[k],
                errors[k] * 1000.0,
                p[3].y,
                p[6].y,
                p[9].y,
                p[1].y,
                p[2].y
            );
        }
    }

    // The root's path in the camera's axes (pelvis), both from their means, scale-aligned.
    let true_root: Vec<Vec3> =
        truth.iter().map(|p| view.transform_point3(pose_body(&model, p).kinematics.posed_joints[0])).collect();
    let fit_root: Vec<Vec3> = (0..FRAMES)
        .map(|k| {
            let p = video.motion.params(k, &betas);
            pose_body(&model, &p).kinematics.posed_joints[0]
        })
        .collect();
    let centre = |v: &[Vec3]| {
        let m = v.iter().copied().sum::<Vec3>() / v.len() as f32;
        v.iter().map(|x| *x - m).collect::<Vec<_>>()
    };
    let (g, r) = (centre(&true_root), centre(&fit_root));
    let scale =
        g.iter().zip(&r).map(|(a, b)| a.dot(*b)).sum::<f32>() / r.iter().map(|b| b.length_squared()).sum::<f32>();
    let path_error = g.iter().zip(&r).map(|(a, b)| (*a - *b * scale).length()).fold(0.0f32, f32::max);

    eprintln!(
        "video fit of {FRAMES} frames in {seconds:.1} s: PA-MPJPE mean {:.1} mm, worst {:.1} mm; accel error {:.2} mm/frame² \
         (unsmoothed {:.2}); lag at the turn {lag:.2} frames; root path within {:.1} cm (scale {scale:.2})",
        mean * 1000.0,
        worst * 1000.0,
        accel * 1000.0,
        accel_raw * 1000.0,
        path_error * 100.0
    );
    assert!(worst <= 0.060, "worst frame {} mm: {errors:?}", worst * 1000.0);
    assert!(accel < accel_raw, "smoothing made the acceleration error {accel} from {accel_raw}");
    assert!(lag.abs() <= 2.0, "the turn lags by {lag} frames");
    assert!(path_error <= 0.10, "root path off by {path_error} m");
}

#[test]
fn a_clip_without_a_person_or_without_frames_is_one_clear_error() {
    let model = Arc::new(BodyModel::default_body().unwrap());
    let dev = cpu().autodiff();
    let none = VideoDetections { results: vec![None; 5], width: 64, height: 64, fps: 30.0 };
    let e = VideoFitter::new(model.clone(), &none, VideoFitOptions::default(), &dev).err().unwrap();
    assert_eq!(e.to_string(), "no person was found in any of the 5 frames");
    let empty = VideoDetections { results: vec![], ..none.clone() };
    assert!(matches!(
        VideoFitter::new(model.clone(), &empty, VideoFitOptions::default(), &dev),
        Err(VideoError::Empty)
    ));
    let bad = VideoDetections { fps: 0.0, ..none };
    assert!(matches!(VideoFitter::new(model, &bad, VideoFitOptions::default(), &dev), Err(VideoError::FrameRate(_))));
}
