//! A video's detections → a motion clip: one body shape for the whole clip, then one fit per
//! frame warm-started from the previous frame's, all through one crop of the frame so that
//! the camera stays put and the root's path is the body's own.
//!
//! 1. **Crop**: the median of the frames' own crops ([`Framing::from_landmarks`]): the
//!    reference camera on it is the video's camera for every frame.
//! 2. **Shape**: β from full fits of a few frames spread over the clip (the best-seen frame in
//!    each of [`VideoFitOptions::shape_frames`] equal parts), averaged; held from then on.
//! 3. **Frames**: the first frame with a person gets a full fit (shape held), every later one
//!    starts from its predecessor's pose and camera ([`BodyFitter::warm_start`]) and runs
//!    [`VideoFitOptions::warm_iterations`] steps, optionally pulled towards the predecessor's
//!    θ ([`VideoFitOptions::temporal`]). A frame without a readable person is lost.
//! 4. **Motion** ([`VideoFitter::finish`]): lost frames filled, θ and the root smoothed by a
//!    centred Gaussian ([`super::temporal`]), resampled to [`MOTION_FPS`], the root's path
//!    starting at the origin (camera axes: x right, y up, the body facing +z towards the camera).

use std::sync::Arc;

use burn::tensor::Device;
use glam::{Mat3, Quat, Vec3};

use super::fit::{BodyFitter, FitError, FitInput, FitOptions, FitState};
use super::framing::Framing;
use super::landmarks::{PoseResult, VISIBLE};
use super::options::{BoneForm, FitWeights};
use super::temporal::{fill_lost, smooth, PoseFrame};
use crate::body::body_model::BodyModel;
use crate::body::motion::{resample, Motion, MAX_FRAMES, MOTION_FPS};
use crate::body::skinning::{axis_angle_to_quat, quat_to_axis_angle};

/// Settings of a video's fit.
#[derive(Clone, Debug, PartialEq)]
pub struct VideoFitOptions {
    /// The full fits: the shape frames' and the first frame's.
    pub fit: FitOptions,
    /// Steps (torso, body, silhouette) of every later frame's warm-started fit.
    pub warm_iterations: [usize; 3],
    /// Term weights of the warm-started fits: the bone term reads the detector's depth as a
    /// floor ([`BoneForm::DepthFloor`], weight 30: on the real detector's reading of the dance
    /// in `tests/tests/video_motion.rs`, PA-MPJPE mean 45.6 → 42.2 mm and worst 63.3 → 56.7 mm
    /// against the cold fit's form, before the collars' prior; docs/benchmarks.md).
    pub warm_weights: FitWeights,
    /// Frames fitted in full for the clip's β.
    pub shape_frames: usize,
    /// Weight (per radian²) of the pull of a frame's θ towards its predecessor's.
    pub temporal: f32,
    /// Standard deviation, frames at the video's rate, of the smoothing after the fit
    /// (0: none).
    pub smoothing: f32,
    /// The root's depth (its distance along the camera's axis, which one view measures only
    /// from the body's size in the image) is smoothed this many times wider (4: the root's
    /// path on the dance of `tests/tests/video_motion.rs` went from 11.4 to 6.7 cm on the real
    /// detector's reading, from 8.3 to 5.1 cm on the synthetic one; docs/benchmarks.md).
    pub depth_smoothing_factor: f32,
}

impl Default for VideoFitOptions {
    fn default() -> Self {
        Self {
            fit: FitOptions::default(),
            warm_iterations: [10, 60, 0],
            warm_weights: FitWeights { bones: 30.0, bones_form: BoneForm::DepthFloor, ..FitWeights::default() },
            shape_frames: 3,
            temporal: 0.0,
            smoothing: 1.5,
            depth_smoothing_factor: 4.0,
        }
    }
}

/// A clip's detections: one MediaPipe result per frame (`None` where no person was found).
#[derive(Clone, Debug)]
pub struct VideoDetections {
    pub results: Vec<Option<PoseResult>>,
    /// Frame size, pixels.
    pub width: usize,
    pub height: usize,
    /// Frames per second of `results` (the video's rate over the frame stride).
    pub fps: f32,
}

#[derive(Debug, thiserror::Error)]
pub enum VideoError {
    #[error("no person was found in any of the {0} frames")]
    NoPerson(usize),
    #[error("the clip has no frames")]
    Empty,
    #[error("the frame rate {0} is not in (0, 1000] frames per second")]
    FrameRate(f32),
    #[error("frame {frame}: {source}")]
    Frame { frame: usize, source: FitError },
}

/// Where a video's fit stands.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VideoProgress {
    /// Fits done (shape frames, then frames) and their total.
    pub done: usize,
    pub total: usize,
    /// Frames fitted so far (after the shape), and how many of them were lost.
    pub frames: usize,
    pub lost: usize,
}

/// The clip's motion and what the fit found on the way.
#[derive(Clone, Debug)]
pub struct VideoMotion {
    pub motion: Motion,
    /// The clip's body shape.
    pub betas: Vec<f32>,
    /// Frames (of the detections) without a readable person, filled in from their neighbours.
    pub lost: Vec<usize>,
    /// Frames fitted (fewer than detected when cancelled).
    pub frames: usize,
}

/// The crop shared by a clip's frames: the median centre and side of the frames' own crops.
pub fn clip_framing(det: &VideoDetections, model: &BodyModel) -> Result<Framing, VideoError> {
    let crops: Vec<Framing> = det
        .results
        .iter()
        .flatten()
        .filter_map(|r| Framing::from_landmarks(&r.pose_landmarks, det.width, det.height, model).ok())
        .collect();
    if crops.is_empty() {
        return Err(VideoError::NoPerson(det.results.len()));
    }
    let median = |f: &dyn Fn(&Framing) -> f32| {
        let mut v: Vec<f32> = crops.iter().map(f).collect();
        v.sort_by(f32::total_cmp);
        v[v.len() / 2]
    };
    Ok(Framing {
        photo_width: det.width,
        photo_height: det.height,
        centre: [median(&|c| c.centre[0]), median(&|c| c.centre[1])],
        side: median(&|c| c.side),
    })
}

/// A clip's fit, one frame at a time (the app awaits [`VideoFitter::step`] between frames to
/// show progress and to cancel; [`VideoFitter::finish`] makes the motion of the frames done).
pub struct VideoFitter {
    model: Arc<BodyModel>,
    options: VideoFitOptions,
    device: Device,
    inputs: Vec<Option<FitInput>>,
    fps: f32,
    /// Frames to fit in full for β, and the β of those done.
    shape_frames: Vec<usize>,
    shapes: Vec<Vec<f32>>,
    /// Per frame fitted: the fit and the detector's 3D torso orientation ([`torso_frame`]).
    states: Vec<Option<(FitState, Option<Quat>)>>,
}

impl VideoFitter {
    /// Prepare the fit on `device` (an autodiff device). Frames whose result cannot be fitted
    /// (no torso, a malformed result) are lost, not errors; a clip without any person is one.
    pub fn new(
        model: Arc<BodyModel>,
        det: &VideoDetections,
        options: VideoFitOptions,
        device: &Device,
    ) -> Result<Self, VideoError> {
        if det.results.is_empty() {
            return Err(VideoError::Empty);
        }
        if !(det.fps > 0.0 && det.fps <= 1000.0) {
            return Err(VideoError::FrameRate(det.fps));
        }
        let framing = clip_framing(det, &model)?;
        let inputs: Vec<Option<FitInput>> = det
            .results
            .iter()
            .map(|r| {
                let r = r.as_ref()?;
                let torso = [11, 12, 23, 24]
                    .iter()
                    .filter(|&&l| r.pose_landmarks.get(l).is_some_and(|p| p.visibility >= VISIBLE))
                    .count();
                (torso >= 2)
                    .then(|| FitInput::framed(r, framing, r.segmentation_mask.as_ref(), &options.fit).ok())
                    .flatten()
            })
            .collect();
        let seen = |k: usize| inputs[k].as_ref().map_or(0, |i| i.points.iter().filter(|p| p.1 >= VISIBLE).count());
        let n = inputs.len();
        let parts = options.shape_frames.max(1).min(n);
        let mut shape_frames: Vec<usize> = (0..parts)
            .filter_map(|p| (p * n / parts..(p + 1) * n / parts).filter(|&k| seen(k) > 0).max_by_key(|&k| seen(k)))
            .collect();
        shape_frames.dedup();
        if shape_frames.is_empty() {
            return Err(VideoError::NoPerson(n));
        }
        Ok(Self {
            model,
            options,
            device: device.clone(),
            states: Vec::with_capacity(n),
            inputs,
            fps: det.fps,
            shape_frames,
            shapes: Vec::new(),
        })
    }

    /// Fits in all: the shape frames' and every frame's.
    pub fn total(&self) -> usize {
        self.shape_frames.len() + self.inputs.len()
    }

    fn progress(&self) -> VideoProgress {
        VideoProgress {
            done: self.shapes.len() + self.states.len(),
            total: self.total(),
            frames: self.states.len(),
            lost: self.states.iter().filter(|s| s.is_none()).count(),
        }
    }

    /// The next fit (a shape frame's, then a frame's); `None` when every frame is done.
    pub async fn step(&mut self) -> Result<Option<VideoProgress>, VideoError> {
        if self.shapes.len() < self.shape_frames.len() {
            let k = self.shape_frames[self.shapes.len()];
            let input = self.inputs[k].clone().ok_or(VideoError::NoPerson(self.inputs.len()))?;
            let fitted = self.fit(input, None, false).await.map_err(|source| VideoError::Frame { frame: k, source })?;
            self.shapes.push(fitted.params.betas);
            return Ok(Some(self.progress()));
        }
        let k = self.states.len();
        if k >= self.inputs.len() {
            return Ok(None);
        }
        let previous = self.states.iter().rev().flatten().next().cloned();
        let state = match self.inputs[k].clone() {
            // A frame the fit cannot place (too few landmarks) is lost, like one without a person.
            Some(input) => match self.fit(input.clone(), previous, true).await {
                Ok(s) => Some((s, torso_frame(&input))),
                Err(FitError::TooFew(_)) => None,
                Err(source) => return Err(VideoError::Frame { frame: k, source }),
            },
            None => None,
        };
        self.states.push(state);
        Ok(Some(self.progress()))
    }

    /// The clip's β: the mean of the shape frames'.
    pub fn betas(&self) -> Vec<f32> {
        let nb = self.options.fit.num_betas;
        let mut b = vec![0.0f32; nb];
        for s in &self.shapes {
            for (a, x) in b.iter_mut().zip(s) {
                *a += x / self.shapes.len() as f32;
            }
        }
        b
    }

    /// One frame's fit: full from the start, or warm from `previous`; the clip's β held when
    /// `hold`.
    async fn fit(
        &self,
        input: FitInput,
        previous: Option<(FitState, Option<Quat>)>,
        hold: bool,
    ) -> Result<FitState, FitError> {
        let warm = previous.is_some();
        let (previous, previous_torso) = match previous {
            Some((s, t)) => (Some(s), t),
            None => (None, None),
        };
        let mut options = self.options.fit.clone();
        if warm {
            options.iterations = self.options.warm_iterations;
            options.weights = self.options.warm_weights.clone();
        }
        let torso = torso_frame(&input);
        let mut fitter = BodyFitter::new(self.model.clone(), input, options, &self.device)?;
        match previous {
            Some(mut p) => {
                p.params.betas = self.betas();
                // The turn since the previous frame, as the detector's 3D torso saw it, put on
                // the previous frame's fitted turn: a quick turn is past the warm fit's reach.
                if let (Some(before), Some(now)) = (previous_torso, torso) {
                    let turn = now * before.inverse();
                    p.params.pose[0] = quat_to_axis_angle(turn * axis_angle_to_quat(p.params.pose[0]));
                }
                fitter.warm_start(&p, self.options.temporal);
            }
            None if hold => fitter.hold_shape(&self.betas()),
            None => {}
        }
        fitter.run().await?;
        fitter.state().await
    }

    /// Change the smoothing of [`VideoFitter::finish`] (standard deviation, frames; 0: none).
    pub fn set_smoothing(&mut self, sigma: f32) {
        self.options.smoothing = sigma;
    }

    /// The motion of the frames fitted so far, named `name`.
    pub fn finish(&self, name: &str) -> Result<VideoMotion, VideoError> {
        let frames: Vec<Option<PoseFrame>> = self
            .states
            .iter()
            .map(|s| s.as_ref().map(|(s, _)| PoseFrame { pose: s.params.pose, trans: s.camera }))
            .collect();
        let filled = fill_lost(&frames).ok_or(VideoError::NoPerson(frames.len()))?;
        let mut smoothed = smooth(&filled, self.options.smoothing);
        let depth_sigma = self.options.smoothing * self.options.depth_smoothing_factor;
        if depth_sigma > self.options.smoothing {
            for (s, d) in smoothed.iter_mut().zip(smooth(&filled, depth_sigma)) {
                s.trans.z = d.trans.z;
            }
        }
        let start = smoothed[0].trans;
        let poses: Vec<_> = smoothed.iter().map(|f| f.pose).collect();
        let trans: Vec<_> = smoothed.iter().map(|f| f.trans - start).collect();
        let (mut poses, mut trans) = resample(&poses, &trans, self.fps, MOTION_FPS);
        let mut notes = Vec::new();
        let lost: Vec<usize> = (0..frames.len()).filter(|&k| frames[k].is_none()).collect();
        if !lost.is_empty() {
            notes.push(format!(
                "{} of {} frames without a readable person, filled in from their neighbours",
                lost.len(),
                frames.len()
            ));
        }
        if (self.fps - MOTION_FPS).abs() > 1e-3 {
            notes.push(format!("resampled from {} fps to {MOTION_FPS} fps", self.fps));
        }
        if poses.len() > MAX_FRAMES {
            notes.push(format!("cut to the first {MAX_FRAMES} frames"));
            poses.truncate(MAX_FRAMES);
            trans.truncate(MAX_FRAMES);
        }
        Ok(VideoMotion {
            motion: Motion { name: name.to_string(), poses, trans, looping: false, notes },
            betas: self.betas(),
            lost,
            frames: frames.len(),
        })
    }
}

/// The torso's orientation in the detector's 3D landmarks (camera axes): x from the right
/// hip to the left, y from the hips' middle up to the shoulders' (made orthogonal), z their
/// cross product; `None` without world landmarks or with a torso landmark unseen.
pub fn torso_frame(input: &FitInput) -> Option<Quat> {
    let world = input.world.as_ref()?;
    if [11, 12, 23, 24].iter().any(|&l| input.points.get(l).is_none_or(|p| p.1 < VISIBLE)) {
        return None;
    }
    let x = (world[23] - world[24]).normalize_or_zero();
    let up = (world[11] + world[12] - world[23] - world[24]) / 2.0;
    let y = (up - x * up.dot(x)).normalize_or_zero();
    let z = x.cross(y);
    if x == Vec3::ZERO || y == Vec3::ZERO {
        return None;
    }
    Some(Quat::from_mat3(&Mat3::from_cols(x, y, z)).normalize())
}
