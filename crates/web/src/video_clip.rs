//! What "Motion from video…" accepts and which frames it reads: the limits a video must meet
//! (one sentence for the user when it does not) and the times of the frames read. Pure Rust,
//! tested natively; the browser side is `crate::video`.

/// Longest video read, seconds (as `trainer motion-from-video --max-seconds`'s default).
pub const MAX_SECONDS: f32 = 60.0;
/// Longest side of a video read, pixels (1440p; a 4K clip is refused, not silently slowed).
pub const MAX_SIDE: usize = 2560;
/// Frames of the video read per second offered, and the default.
pub const READ_FPS: [u32; 3] = [10, 15, 30];
pub const DEFAULT_READ_FPS: u32 = 15;
/// Largest frame handed to the person detector, pixels on the long side (it reads at most
/// 384² anyway; the fit's crop is in the frame's own pixels).
pub const DETECT_SIDE: u32 = 960;
/// Largest video file read into the page, bytes.
pub const MAX_BYTES: usize = 1 << 30;

/// File names the app takes for videos (a drop goes by its name).
pub fn is_video_name(name: &str) -> bool {
    let n = name.to_ascii_lowercase();
    [".mp4", ".m4v", ".webm", ".mov", ".mkv", ".ogv"].iter().any(|e| n.ends_with(e))
}

/// `fps` is one of [`READ_FPS`].
pub fn check_read_fps(fps: u32) -> Result<u32, String> {
    if READ_FPS.contains(&fps) {
        Ok(fps)
    } else {
        Err(format!("fps {fps} (one of {READ_FPS:?} frames read per second of video)"))
    }
}

/// A `seconds`-long video of `width × height` read at `fps`: the times (seconds) of the frames
/// read, each in the middle of its 1/fps slot, or why the video is not taken.
pub fn frame_times(name: &str, width: usize, height: usize, seconds: f64, fps: u32) -> Result<Vec<f64>, String> {
    check_read_fps(fps)?;
    if width == 0 || height == 0 {
        return Err(format!("{name} has no picture (an audio file?)"));
    }
    if !seconds.is_finite() {
        return Err(format!(
            "{name} does not say how long it is (some recorders leave it out); save it again, \
             e.g. `ffmpeg -i in.webm -c copy out.webm`"
        ));
    }
    if seconds > MAX_SECONDS as f64 + 0.5 {
        let (m, s) = ((seconds / 60.0).floor(), seconds % 60.0);
        return Err(format!(
            "{name} is {m:.0}:{s:02.0} long; the app reads at most {MAX_SECONDS:.0} s of video: cut the part \
             you want first (e.g. `ffmpeg -ss 0:10 -t 20 -i in.mp4 part.mp4`)"
        ));
    }
    if width.max(height) > MAX_SIDE {
        return Err(format!(
            "{name} is {width}×{height}; the app reads videos up to {MAX_SIDE} pixels on the long side \
             (1440p): save it at 1080p first (e.g. `ffmpeg -i in.mp4 -vf scale=-2:1080 out.mp4`)"
        ));
    }
    let n = (seconds * fps as f64).floor() as usize;
    if n < 2 {
        return Err(format!("{name} is {seconds:.2} s long: too short for a motion (2 frames at {fps} fps)"));
    }
    Ok((0..n).map(|k| (k as f64 + 0.5) / fps as f64).collect())
}

/// Seconds left at the pace so far: `done` of `total` units took `elapsed_s`.
pub fn eta_s(done: usize, total: usize, elapsed_s: f64) -> f32 {
    if done == 0 || done >= total {
        return 0.0;
    }
    (elapsed_s / done as f64 * (total - done) as f64) as f32
}

/// A video's file name without folders and extension (the clip's name).
pub fn clip_name(name: &str) -> String {
    let file = name.rsplit(['/', '\\']).next().unwrap_or(name);
    let stem = file.rsplit_once('.').map_or(file, |(s, _)| s);
    if stem.is_empty() {
        "video".into()
    } else {
        stem.to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_two_second_clip_at_ten_fps_reads_twenty_frames_in_the_middle_of_their_slots() {
        let t = frame_times("a.webm", 320, 240, 2.0, 10).unwrap();
        assert_eq!(t.len(), 20);
        assert!((t[0] - 0.05).abs() < 1e-9 && (t[19] - 1.95).abs() < 1e-9);
    }

    #[test]
    fn long_huge_silent_endless_or_tiny_videos_are_refused_with_one_sentence() {
        let long = frame_times("long.webm", 64, 64, 1200.0, 15).unwrap_err();
        assert!(long.contains("20:00 long") && long.contains("60 s"), "{long}");
        let big = frame_times("4k.webm", 3840, 2160, 1.0, 15).unwrap_err();
        assert!(big.contains("3840×2160") && big.contains("2560"), "{big}");
        assert!(frame_times("a.m4a", 0, 0, 3.0, 15).unwrap_err().contains("no picture"));
        assert!(frame_times("a.webm", 64, 64, f64::INFINITY, 15).unwrap_err().contains("how long"));
        assert!(frame_times("a.webm", 64, 64, 0.1, 15).unwrap_err().contains("too short"));
        assert!(frame_times("a.webm", 64, 64, 2.0, 12).unwrap_err().contains("fps 12"));
        // A minute and a fraction of a frame is still a minute.
        assert_eq!(frame_times("a.webm", 1920, 1080, 60.2, 30).unwrap().len(), 1806);
    }

    #[test]
    fn names_and_pace() {
        assert!(is_video_name("Me Dancing.MOV") && is_video_name("x.webm") && !is_video_name("x.npz"));
        assert_eq!(clip_name("C:\\clips\\salsa.mp4"), "salsa");
        assert_eq!(clip_name(".mp4"), "video");
        assert_eq!(eta_s(5, 20, 10.0), 30.0);
        assert_eq!(eta_s(0, 20, 10.0), 0.0);
    }
}
