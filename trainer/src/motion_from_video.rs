//! `trainer motion-from-video`: a clip of a person → an SMPL/AMASS motion file (`poses` N×72,
//! `trans`, `mocap_framerate` 30) that `export --motion` and the app play.
//!
//! The frames are decoded by ffmpeg (`ffprobe` for the size, rate and length; `cargo xtask
//! setup` installs both from Debian), every `--stride`-th kept and scaled to at most
//! [`MAX_SIDE`] pixels; MediaPipe Pose runs on them in its tracking mode through
//! `tools/mediapipe_fixtures.mjs --video` (the app's detector worker in headless Chromium; a
//! frame the tracker finds nobody in is lost, filled in from its neighbours), or the program
//! named by `GETAVATAR_MEDIAPIPE` (called with the frames' folder and `--video`; it writes
//! `<frame>.kp.json` next to each `<frame>.jpg` it finds a person in). `--keypoints` skips both and reads the detections from a
//! `getavatar-video-keypoints/1` file (what `--keypoints-out` writes):
//!
//! ```text
//! {"format":"getavatar-video-keypoints/1","width":W,"height":H,"fps":F}
//! {"frame":0,"result":{"poseLandmarks":[…],"poseWorldLandmarks":[…]}}
//! {"frame":1,"result":null}
//! ```
//!
//! The fit is [`getavatar_core::body::body_fit::video`]: one shape, a warm-started fit per frame,
//! lost frames filled in, smoothed.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use getavatar_core::body::body_fit::landmarks::PoseResult;
use getavatar_core::body::body_fit::video::{VideoDetections, VideoFitOptions, VideoFitter};
use getavatar_core::generator::readback::block_on_ready;
use serde::{Deserialize, Serialize};

use crate::model_io::load_body;

/// Frames are scaled to at most this many pixels on their long side before detection.
pub const MAX_SIDE: usize = 1280;
/// The format tag of a video keypoints file.
pub const KEYPOINTS_FORMAT: &str = "getavatar-video-keypoints/1";

#[derive(clap::Args, Debug)]
pub struct MotionFromVideoArgs {
    #[command(flatten)]
    pub backend: crate::backend::BackendArg,
    /// The clip (anything ffmpeg decodes: MP4, WebM, MOV, …).
    #[arg(long, required_unless_present = "keypoints", conflicts_with = "keypoints")]
    pub video: Option<PathBuf>,
    /// Detections instead of a video: a `getavatar-video-keypoints/1` file.
    #[arg(long)]
    pub keypoints: Option<PathBuf>,
    /// The motion file (.npz); by default the video's name with `.npz`.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Keep every n-th frame (2 halves the work; the motion is resampled to 30 fps).
    #[arg(long, default_value_t = 1)]
    pub stride: usize,
    /// Longest clip accepted, seconds.
    #[arg(long, default_value_t = 60.0)]
    pub max_seconds: f32,
    /// Also write the detections, to fit again without MediaPipe (`--keypoints`).
    #[arg(long)]
    pub keypoints_out: Option<PathBuf>,
    /// Smoothing over time: standard deviation in frames (0: none).
    #[arg(long, default_value_t = VideoFitOptions::default().smoothing)]
    pub smoothing: f32,
    /// Body model .npz in the SMPL layout (default: the embedded open body).
    #[arg(long)]
    pub body: Option<PathBuf>,
}

/// The first line of a keypoints file.
#[derive(Serialize, Deserialize, Debug)]
struct Header {
    format: String,
    width: usize,
    height: usize,
    fps: f32,
}

/// Every later line.
#[derive(Serialize, Deserialize, Debug)]
struct FrameLine {
    frame: usize,
    result: Option<PoseResult>,
}

pub fn motion_from_video(args: &MotionFromVideoArgs) -> Result<()> {
    if args.stride == 0 {
        bail!("--stride must be at least 1");
    }
    let source = args.video.as_ref().or(args.keypoints.as_ref()).context("give --video or --keypoints")?;
    let name =
        source.file_stem().and_then(|s| s.to_str()).unwrap_or("video").trim_end_matches(".keypoints").to_string();
    let start = Instant::now();
    let det = match (&args.video, &args.keypoints) {
        (Some(video), _) => detect_video(video, args.stride, args.max_seconds)?,
        (None, Some(kp)) => read_keypoints(kp, args.stride)?,
        (None, None) => bail!("give --video or --keypoints"),
    };
    let detect_s = start.elapsed().as_secs_f32();
    if let Some(path) = &args.keypoints_out {
        write_keypoints(path, &det)?;
        println!("wrote {}", path.display());
    }
    let seen = det.results.iter().filter(|r| r.is_some()).count();
    println!(
        "{} frames at {:.2} fps, {}×{}; a person in {seen} of them{}",
        det.results.len(),
        det.fps,
        det.width,
        det.height,
        if args.video.is_some() { format!(" (detection {detect_s:.1} s)") } else { String::new() }
    );

    let model = Arc::new(load_body(&args.body)?);
    let device = args.backend.device()?.autodiff();
    let options = VideoFitOptions { smoothing: args.smoothing, ..VideoFitOptions::default() };
    let fit_start = Instant::now();
    let mut fitter = VideoFitter::new(model, &det, options, &device)?;
    let bar = crate::progress::bar(fitter.total() as u64, "fits");
    block_on_ready(async {
        while let Some(p) = fitter.step().await? {
            bar.set_position(p.done as u64);
            bar.set_message(format!("frame {}/{}, {} lost", p.frames, det.results.len(), p.lost));
        }
        Ok::<_, anyhow::Error>(())
    })?;
    bar.finish_and_clear();
    let fit_s = fit_start.elapsed().as_secs_f32();
    let video = fitter.finish(&name)?;
    let out = args.out.clone().unwrap_or_else(|| source.with_extension("npz"));
    let bytes = video.motion.to_amass_npz(Some(&video.betas))?;
    crate::atomic::write_atomic(&out, &bytes)?;
    println!(
        "wrote {}: {} frames at 30 fps ({:.2} s) from {} video frames; fit {fit_s:.1} s ({:.2} video frames/s){}",
        out.display(),
        video.motion.len(),
        video.motion.duration(),
        video.frames,
        video.frames as f32 / fit_s.max(1e-6),
        if video.lost.is_empty() {
            String::new()
        } else {
            format!("; no person in frames {:?}, filled in from their neighbours", video.lost)
        }
    );
    Ok(())
}

/// A keypoints file, every `stride`-th frame.
fn read_keypoints(path: &Path, stride: usize) -> Result<VideoDetections> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut lines = text.lines().filter(|l| !l.trim().is_empty());
    let header: Header = serde_json::from_str(lines.next().context("the keypoints file is empty")?)
        .with_context(|| format!("{}: the first line is not a {KEYPOINTS_FORMAT} header", path.display()))?;
    if header.format != KEYPOINTS_FORMAT {
        bail!("{}: format {:?}, expected {KEYPOINTS_FORMAT}", path.display(), header.format);
    }
    let mut results = Vec::new();
    for (i, line) in lines.enumerate() {
        let f: FrameLine = serde_json::from_str(line).with_context(|| format!("{}: line {}", path.display(), i + 2))?;
        if f.frame != i {
            bail!("{}: line {} is frame {}, expected frame {i}", path.display(), i + 2, f.frame);
        }
        if i % stride == 0 {
            results.push(f.result);
        }
    }
    Ok(VideoDetections { results, width: header.width, height: header.height, fps: header.fps / stride as f32 })
}

fn write_keypoints(path: &Path, det: &VideoDetections) -> Result<()> {
    let mut out = Vec::new();
    let header = Header { format: KEYPOINTS_FORMAT.into(), width: det.width, height: det.height, fps: det.fps };
    writeln!(out, "{}", serde_json::to_string(&header)?)?;
    for (frame, r) in det.results.iter().enumerate() {
        let mut result = r.clone();
        if let Some(r) = result.as_mut() {
            r.segmentation_mask = None;
        }
        writeln!(out, "{}", serde_json::to_string(&FrameLine { frame, result })?)?;
    }
    crate::atomic::write_atomic(path, &out)
}

/// What ffprobe says of a video's first video stream.
struct Probe {
    width: usize,
    height: usize,
    fps: f32,
    seconds: f32,
}

fn probe(video: &Path) -> Result<Probe> {
    if std::fs::metadata(video).with_context(|| format!("reading {}", video.display()))?.len() == 0 {
        bail!("{} is empty (0 bytes)", video.display());
    }
    let out = Command::new("ffprobe")
        .args(["-v", "error", "-select_streams", "v:0", "-show_entries", "stream=width,height,avg_frame_rate,duration"])
        .args(["-show_entries", "format=duration", "-of", "json"])
        .arg(video)
        .output()
        .context("running ffprobe (install ffmpeg: `apt install ffmpeg`, or `cargo xtask setup`)")?;
    let bad = || format!("{} is not a video ffmpeg can read", video.display());
    if !out.status.success() {
        bail!("{}: {}", bad(), String::from_utf8_lossy(&out.stderr).trim());
    }
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).with_context(bad)?;
    let stream = v["streams"].get(0).with_context(|| format!("{} has no video stream", video.display()))?;
    let num = |x: &serde_json::Value| x.as_u64().map(|n| n as usize).or_else(|| x.as_str()?.parse().ok());
    let secs = |x: &serde_json::Value| x.as_str().and_then(|s| s.parse::<f32>().ok());
    let rate = stream["avg_frame_rate"].as_str().unwrap_or("0/0");
    let fps = match rate.split_once('/') {
        Some((a, b)) => a.parse::<f32>().unwrap_or(0.0) / b.parse::<f32>().unwrap_or(0.0),
        None => rate.parse().unwrap_or(0.0),
    };
    let (Some(width), Some(height)) = (num(&stream["width"]), num(&stream["height"])) else { bail!("{}", bad()) };
    if !fps.is_finite() || fps <= 0.0 {
        bail!("{}: no frame rate ({rate})", bad());
    }
    let seconds = secs(&stream["duration"]).or_else(|| secs(&v["format"]["duration"])).unwrap_or(0.0);
    Ok(Probe { width, height, fps, seconds })
}

/// Decode every `stride`-th frame into PNGs and run MediaPipe on them.
fn detect_video(video: &Path, stride: usize, max_seconds: f32) -> Result<VideoDetections> {
    let p = probe(video)?;
    if p.seconds > max_seconds {
        bail!(
            "{} is {:.0} s long; at most {max_seconds:.0} s are fitted (cut the part you want, e.g. \
             `ffmpeg -ss 0:10 -t 20 -i in.mp4 part.mp4`, or raise --max-seconds)",
            video.display(),
            p.seconds
        );
    }
    let dir = tempfile::tempdir().context("creating a folder for the frames")?;
    let scale = MAX_SIDE as f32 / p.width.max(p.height) as f32;
    let (w, h) = if scale < 1.0 {
        // Even sizes, as the encoders like them.
        ((p.width as f32 * scale / 2.0).round() as usize * 2, (p.height as f32 * scale / 2.0).round() as usize * 2)
    } else {
        (p.width, p.height)
    };
    let filter = format!("select=not(mod(n\\,{stride})),scale={w}:{h}");
    let out = Command::new("ffmpeg")
        .args(["-v", "error", "-nostdin", "-i"])
        .arg(video)
        .args(["-vf", &filter, "-fps_mode", "passthrough"])
        // JPEG (quality 2 of 31): a minute of frames stays around 200 MB where PNGs take GBs.
        .args(["-q:v", "2"])
        .arg(dir.path().join("frame_%06d.jpg"))
        .output()
        .context("running ffmpeg (install it: `apt install ffmpeg`, or `cargo xtask setup`)")?;
    if !out.status.success() {
        bail!("decoding {}: {}", video.display(), String::from_utf8_lossy(&out.stderr).trim());
    }
    let mut frames: Vec<String> = std::fs::read_dir(dir.path())?
        .filter_map(|e| e.ok()?.file_name().into_string().ok())
        .filter(|n| n.ends_with(".jpg"))
        .collect();
    frames.sort();
    if frames.is_empty() {
        bail!("{} has no frames ffmpeg could decode", video.display());
    }
    eprintln!("running MediaPipe on {} frames", frames.len());
    // The frames in order through Pose's tracking mode (`--video`; a stand-in may ignore it).
    let out = crate::pck::detector(dir.path())?.arg("--video").output().context(
        "running MediaPipe (node and Chromium, as `cargo xtask test` installs them, or GETAVATAR_MEDIAPIPE)",
    )?;
    let stderr = String::from_utf8_lossy(&out.stderr);
    let mut results = Vec::with_capacity(frames.len());
    for f in &frames {
        let kp = dir.path().join(f.replace(".jpg", ".kp.json"));
        if !kp.is_file() {
            results.push(None);
            continue;
        }
        let text = std::fs::read_to_string(&kp).with_context(|| format!("reading {}", kp.display()))?;
        let mut r = PoseResult::from_json(&text).with_context(|| format!("{}", kp.display()))?;
        let mask = dir.path().join(f.replace(".jpg", ".mask.png"));
        if mask.is_file() {
            r.segmentation_mask = Some(crate::fit_pose::load_mask(&mask)?);
        }
        results.push(Some(r));
    }
    // The script exits 1 naming the frames it found no one in; with nothing found and no
    // frame named, the detector itself failed.
    if !out.status.success() && results.iter().all(|r| r.is_none()) && !stderr.contains("frame_") {
        bail!("MediaPipe failed ({}): {}", out.status, stderr.trim());
    }
    Ok(VideoDetections { results, width: w, height: h, fps: p.fps / stride as f32 })
}
