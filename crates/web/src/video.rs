//! Motion from a video, in the page: the file's frames decoded by the browser
//! (`www/video_frames.js`: a `<video>` on a Blob URL, so the video never leaves the page),
//! MediaPipe Pose on each in its tracking mode in the detector worker, then the clip's fit of
//! `getavatar_core::body::body_fit::video` (one shape, each frame warm-started from the previous
//! one, smoothed) on the CPU backend, one frame per await so the page shows progress and
//! Cancel keeps the frames fitted so far.

use std::sync::Arc;

use eframe::egui;
use serde::Deserialize;
use wasm_bindgen::prelude::*;

use getavatar_core::body::body_fit::landmarks::PoseResult;
use getavatar_core::body::body_fit::video::{VideoDetections, VideoFitOptions, VideoFitter, VideoMotion};
use getavatar_core::BodyModel;

use crate::automation::PhotoSource;
use crate::platform::{fetch_bytes, js_message, now_ms};
use crate::task::{checkpoint, EventKind, Task, TaskEvent};
use crate::video_clip::{clip_name, eta_s, frame_times, DETECT_SIDE, MAX_BYTES};

#[wasm_bindgen(raw_module = "./video_frames.js")]
extern "C" {
    /// Open a video's bytes in the page: JSON `{width, height, seconds}` or `{error}`.
    #[wasm_bindgen(catch, js_name = openVideo)]
    async fn open_video(bytes: &js_sys::Uint8Array) -> Result<JsValue, JsValue>;
    /// MediaPipe Pose (tracking mode) on the frame shown at `seconds`: the detector's JSON.
    #[wasm_bindgen(catch, js_name = detectVideoAt)]
    async fn detect_video_at(seconds: f64, first: bool, max_side: u32) -> Result<JsValue, JsValue>;
    /// Let the open video go.
    #[wasm_bindgen(catch, js_name = closeVideo)]
    fn close_video() -> Result<(), JsValue>;
}

/// What the clip's making is doing.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    /// Decoding frames and finding the person in them.
    Reading,
    /// Fitting the body to them.
    Fitting,
}

/// How far it got.
#[derive(Clone, Copy, Debug)]
pub struct VideoStep {
    pub phase: Phase,
    /// Units done of this phase (frames read; fits done, shape frames first) and their total.
    pub done: usize,
    pub total: usize,
    /// Frames read so far, fitted so far, and without a readable person so far.
    pub read: usize,
    pub fitted: usize,
    pub lost: usize,
    /// Seconds this phase still needs at its pace so far.
    pub eta_s: f32,
}

/// The opened video.
#[derive(Clone, Debug)]
pub struct VideoInfo {
    pub name: String,
    pub width: usize,
    pub height: usize,
    pub seconds: f32,
    pub frames: usize,
}

/// A made clip and how it went.
pub struct VideoDone {
    pub video: VideoMotion,
    /// Cancelled during the fit: the clip holds the frames fitted before.
    pub cut: bool,
    pub read_ms: f64,
    pub fit_ms: f64,
}

pub enum VideoEvent {
    Opened(VideoInfo),
    Progress(VideoStep),
    Done(Box<VideoDone>),
    /// One sentence for the user; the app stays as it was.
    Failed(String),
    /// Cancelled before any frame was fitted: nothing kept.
    Cancelled,
}

impl TaskEvent for VideoEvent {
    fn kind(&self) -> EventKind {
        match self {
            VideoEvent::Progress(_) => EventKind::Latest,
            VideoEvent::Opened(_) => EventKind::Log,
            _ => EventKind::Outcome,
        }
    }
}

pub type VideoTask = Task<VideoEvent>;

/// `openVideo`'s answer.
#[derive(Deserialize)]
struct Opened {
    error: Option<String>,
    width: Option<usize>,
    height: Option<usize>,
    seconds: Option<f64>,
}

/// The fields of a frame's detection that are not MediaPipe's result.
#[derive(Deserialize)]
struct FrameHead {
    error: Option<String>,
    width: Option<usize>,
    height: Option<usize>,
}

/// Make a motion clip from the video at `source`, reading `fps` of its frames per second;
/// the fit runs on `device` (an autodiff device).
pub fn make_motion(
    source: PhotoSource,
    fps: u32,
    model: Arc<BodyModel>,
    device: getavatar_core::burn::tensor::Device,
    repaint: egui::Context,
) -> VideoTask {
    let task = VideoTask::default();
    let t = task.clone();
    wasm_bindgen_futures::spawn_local(async move {
        let outcome = run(source, fps, model, device, &t, &repaint).await;
        let closed = close_video().map_err(|e| format!("cannot close the video: {}", js_message(&e)));
        let event = match (outcome, closed) {
            (Err(e), _) | (Ok(_), Err(e)) => VideoEvent::Failed(e),
            (Ok(Some(done)), Ok(())) => VideoEvent::Done(Box::new(done)),
            (Ok(None), Ok(())) => VideoEvent::Cancelled,
        };
        t.push(event, &repaint);
    });
    task
}

async fn run(
    source: PhotoSource,
    fps: u32,
    model: Arc<BodyModel>,
    device: getavatar_core::burn::tensor::Device,
    task: &VideoTask,
    repaint: &egui::Context,
) -> Result<Option<VideoDone>, String> {
    let (name, bytes) = match source {
        PhotoSource::Bytes { name, bytes } => (name, bytes),
        PhotoSource::Url(url) => {
            let bytes = fetch_bytes(&url).await.map_err(|e| format!("cannot fetch the video: {e}"))?;
            (url, bytes)
        }
    };
    if bytes.len() > MAX_BYTES {
        return Err(format!(
            "{name} is {:.1} GB; the app reads video files up to {} GB",
            bytes.len() as f64 / 1e9,
            MAX_BYTES >> 30
        ));
    }
    let opened = open_video(&js_sys::Uint8Array::from(&bytes[..]))
        .await
        .map_err(|e| format!("{name}: the video could not be opened: {}", js_message(&e)))?;
    drop(bytes);
    let opened = opened.as_string().ok_or_else(|| format!("{name}: the video reader gave no answer"))?;
    let opened: Opened =
        serde_json::from_str(&opened).map_err(|e| format!("{name}: the video reader's answer: {e}"))?;
    if let Some(e) = opened.error {
        return Err(format!("{name}: {e}"));
    }
    let (width, height) = (opened.width.unwrap_or(0), opened.height.unwrap_or(0));
    let seconds = opened.seconds.unwrap_or(f64::INFINITY);
    let times = frame_times(&name, width, height, seconds, fps)?;
    let info = VideoInfo { name: name.clone(), width, height, seconds: seconds as f32, frames: times.len() };
    task.push(VideoEvent::Opened(info), repaint);

    let detections = match read_frames(&name, &times, fps, task, repaint).await? {
        Some(d) => d,
        None => return Ok(None),
    };
    fit_frames(&name, detections, model, device, task, repaint).await
}

/// Every frame at `times` through the detector, in order; `None` when cancelled.
async fn read_frames(
    name: &str,
    times: &[f64],
    fps: u32,
    task: &VideoTask,
    repaint: &egui::Context,
) -> Result<Option<(VideoDetections, f64)>, String> {
    let t0 = now_ms();
    let n = times.len();
    let mut results = Vec::with_capacity(n);
    let mut size = None;
    let mut first_miss: Option<String> = None;
    for (k, &t) in times.iter().enumerate() {
        if task.cancelled() {
            return Ok(None);
        }
        let answer = detect_video_at(t, k == 0, DETECT_SIDE)
            .await
            .map_err(|e| format!("{name}: the person detector failed: {}", js_message(&e)))?;
        let json = answer.as_string().ok_or_else(|| format!("{name}: the person detector gave no answer"))?;
        let head: FrameHead =
            serde_json::from_str(&json).map_err(|e| format!("{name}: the person detector's answer: {e}"))?;
        match head.error {
            // The detector itself is gone: no later frame can be read either.
            Some(e) if e.starts_with("the person detector") => return Err(format!("{name}: {e}")),
            Some(e) => {
                first_miss.get_or_insert(e);
                results.push(None);
            }
            None => {
                let r = PoseResult::from_json(&json).map_err(|e| format!("{name}: frame {k}: {e}"))?;
                size = size.or(head.width.zip(head.height));
                results.push(Some(r));
            }
        }
        let lost = results.iter().filter(|r| r.is_none()).count();
        let step = VideoStep {
            phase: Phase::Reading,
            done: k + 1,
            total: n,
            read: k + 1,
            fitted: 0,
            lost,
            eta_s: eta_s(k + 1, n, (now_ms() - t0) / 1000.0),
        };
        task.push(VideoEvent::Progress(step), repaint);
    }
    let Some((width, height)) = size else {
        let why = first_miss.map_or(String::new(), |e| format!(" ({e})"));
        return Err(format!("{name}: no person was found in any of its {n} frames read{why}"));
    };
    Ok(Some((VideoDetections { results, width, height, fps: fps as f32 }, now_ms() - t0)))
}

/// The clip's fit; when cancelled, the frames fitted so far (None if fewer than two).
async fn fit_frames(
    name: &str,
    (detections, read_ms): (VideoDetections, f64),
    model: Arc<BodyModel>,
    device: getavatar_core::burn::tensor::Device,
    task: &VideoTask,
    repaint: &egui::Context,
) -> Result<Option<VideoDone>, String> {
    let t0 = now_ms();
    let read = detections.results.len();
    let mut fitter = VideoFitter::new(model, &detections, VideoFitOptions::default(), &device)
        .map_err(|e| format!("{name}: {e}"))?;
    let mut fitted = 0;
    let mut cut = false;
    loop {
        checkpoint().await;
        if task.cancelled() {
            cut = true;
            break;
        }
        match fitter.step().await.map_err(|e| format!("{name}: the body fit failed: {e}"))? {
            Some(p) => {
                fitted = p.frames;
                let step = VideoStep {
                    phase: Phase::Fitting,
                    done: p.done,
                    total: p.total,
                    read,
                    fitted,
                    lost: p.lost,
                    eta_s: eta_s(p.done, p.total, (now_ms() - t0) / 1000.0),
                };
                task.push(VideoEvent::Progress(step), repaint);
            }
            None => break,
        }
    }
    if cut && fitted < 2 {
        return Ok(None);
    }
    let video = fitter.finish(&clip_name(name)).map_err(|e| format!("{name}: {e}"))?;
    Ok(Some(VideoDone { video, cut, read_ms, fit_ms: now_ms() - t0 }))
}
