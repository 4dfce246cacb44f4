//! PCK@0.1 of a reconstruction on its photo — the paper's pose metric (Sec. 4.1) on the
//! product's own output: MediaPipe Pose (the app's detector, run headless in Chromium by
//! `tools/mediapipe_fixtures.mjs`, the script the fit fixtures are made with) on the avatar
//! rendered at the photo's camera without the photo projected, against the photo's own
//! detection (`--keypoints`), both in the photo's pixels.
//!
//! The detector is `node tools/mediapipe_fixtures.mjs DIR` from this repository (it needs the
//! browser set-up that `cargo xtask test` installs), or the program named by
//! `GETAVATAR_MEDIAPIPE` (called with DIR; it must write `DIR/render.kp.json` for
//! `DIR/render.png`).

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{bail, Context, Result};
use getavatar_core::body::body_fit::framing::Framing;
use getavatar_core::body::body_fit::landmarks::PoseResult;
use getavatar_core::body::body_fit::metrics::pck;
use serde::Serialize;

/// The render's side, pixels (MediaPipe reads people well from about 256 up).
pub const RENDER_RES: usize = 512;
/// PCK's distance threshold over the person's size.
pub const THRESHOLD: f32 = 0.1;
/// The grey the render is composited over (a photo has no alpha).
const GREY: f32 = 120.0 / 255.0;

/// `metrics.json`'s `pck`.
#[derive(Serialize, Clone, Debug)]
pub struct Pck {
    /// Share of the photo's seen landmarks that the render's detection puts within
    /// `threshold_px` (0 when the detector found no one in the render).
    pub pck_0_1: f32,
    /// Landmarks compared (those the photo's detection saw).
    pub compared: usize,
    /// 0.1 × the person's size in the photo, pixels.
    pub threshold_px: f32,
    /// Whether the detector found a person in the render.
    pub render_detected: bool,
}

/// The detector's command for `dir`.
pub(crate) fn detector(dir: &Path) -> Result<Command> {
    if let Some(program) = std::env::var_os("GETAVATAR_MEDIAPIPE") {
        let mut c = Command::new(program);
        c.arg(dir);
        return Ok(c);
    }
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tools/mediapipe_fixtures.mjs");
    if !script.is_file() {
        bail!("PCK needs the repository's tools/mediapipe_fixtures.mjs ({} is missing)", script.display());
    }
    let mut c = Command::new("node");
    c.arg(script).arg(dir);
    Ok(c)
}

/// MediaPipe on `rgba` (a `res`² render, alpha = the avatar) composited over grey, in `dir`:
/// its result, or None when it found no person.
fn detect_render(dir: &Path, rgba: &[u8], res: usize) -> Result<Option<PoseResult>> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let rgb: Vec<u8> = rgba
        .chunks_exact(4)
        .flat_map(|p| {
            let a = p[3] as f32 / 255.0;
            let c = |v: u8| ((v as f32 / 255.0 * a + GREY * (1.0 - a)) * 255.0).round() as u8;
            [c(p[0]), c(p[1]), c(p[2])]
        })
        .collect();
    let png = getavatar_core::io::dataset::encode_png(res, res, 3, &rgb)?;
    crate::atomic::write_atomic(&dir.join("render.png"), &png)?;
    let kp = dir.join("render.kp.json");
    let _ = std::fs::remove_file(&kp);
    let out = detector(dir)?.output().context(
        "running MediaPipe for PCK (node and Chromium, as `cargo xtask test` installs them, or GETAVATAR_MEDIAPIPE)",
    )?;
    let stderr = String::from_utf8_lossy(&out.stderr);
    if kp.is_file() {
        let text = std::fs::read_to_string(&kp).with_context(|| format!("reading {}", kp.display()))?;
        return Ok(Some(PoseResult::from_json(&text).with_context(|| format!("{}", kp.display()))?));
    }
    // The script names a photo it found no person in and exits 1; anything else is a failure.
    if stderr.contains("render.png:") {
        return Ok(None);
    }
    bail!("MediaPipe for PCK failed ({}): {}", out.status, stderr.trim())
}

/// PCK@0.1 of `render` (RGBA, `res`², the crop of `framing` seen through the reference camera)
/// against `photo` (the photo's detection, normalised to the photo `framing` frames), running
/// the detector in `dir`.
pub fn render_pck(dir: &Path, render: &[u8], res: usize, photo: &PoseResult, framing: &Framing) -> Result<Pck> {
    let (w, h) = (framing.photo_width as f32, framing.photo_height as f32);
    let reference: Vec<([f32; 2], f32)> =
        photo.pose_landmarks.iter().map(|l| ([l.x * w, l.y * h], l.visibility)).collect();
    let found = detect_render(dir, render, res)?;
    // Render-normalised (the crop) → NDC → photo pixels.
    let test: Option<Vec<([f32; 2], f32)>> = found.map(|r| {
        r.pose_landmarks.iter().map(|l| (framing.to_photo([2.0 * l.x - 1.0, 1.0 - 2.0 * l.y]), l.visibility)).collect()
    });
    let Some((share, compared, limit)) = pck(&reference, test.as_deref(), THRESHOLD) else {
        bail!("the photo's detection saw fewer than two landmarks: no PCK");
    };
    Ok(Pck { pck_0_1: share, compared, threshold_px: limit, render_detected: test.is_some() })
}
