//! `trainer motion-from-video` end to end on a synthetic dance (the body filmed by a fixed
//! camera, tests/video_motion.rs's clip): from a keypoints file, and from an MP4 that ffmpeg
//! encodes here and the command decodes, with a stand-in detector (`GETAVATAR_MEDIAPIPE`)
//! that answers each frame with that frame's synthetic detection. The motion file reads back
//! as the clip's length, turns with the dancer and jumps with her; bad input is refused with
//! one message each.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::os::unix::fs::PermissionsExt;
use std::path::Path;

use getavatar_core::body::body_fit::synthetic::{dance, detect, DANCE_CAMERA};
use getavatar_core::body::motion::Motion;
use getavatar_core::body::skinning::{axis_angle_to_quat, pose_body};
use getavatar_core::io::dataset::encode_png;
use getavatar_core::util::rng::Rng;
use getavatar_core::BodyModel;
use glam::Vec3;

mod common;
use common::{s, tmp};

const FRAMES: usize = 60;
const SIZE: usize = 256;

/// The root's turn about the vertical from the first frame to the last, radians.
fn turn(m: &Motion) -> f32 {
    let yaw = |k: usize| {
        let f = axis_angle_to_quat(m.poses[k][0]) * Vec3::Z;
        f.x.atan2(f.z)
    };
    yaw(m.len() - 1) - yaw(0)
}

fn run(args: &[&str], detector: Option<&Path>) -> std::process::Output {
    let mut c = std::process::Command::new(env!("CARGO_BIN_EXE_trainer"));
    c.arg("motion-from-video").args(args);
    if let Some(d) = detector {
        c.env("GETAVATAR_MEDIAPIPE", d);
    }
    c.output().unwrap()
}

#[test]
fn a_filmed_dance_becomes_a_motion_file_from_keypoints_and_from_the_video() {
    let root = tmp("motion-video");
    let model = BodyModel::default_body().unwrap();
    let view = DANCE_CAMERA.camera().world_to_camera();
    let mut rng = Rng::new(7, 1);
    let truth = dance(FRAMES, 30.0);
    let dets: Vec<_> = truth.iter().map(|p| detect(&model, p, view, SIZE, 2.0, 0.02, &mut rng).unwrap()).collect();

    // Keypoints file: a header, one line per frame; frame 30 has no person.
    let mut lines =
        vec![format!(r#"{{"format":"getavatar-video-keypoints/1","width":{SIZE},"height":{SIZE},"fps":30}}"#)];
    for (k, d) in dets.iter().enumerate() {
        let result = if k == 30 { "null".to_string() } else { serde_json::to_string(&d.result).unwrap() };
        lines.push(format!(r#"{{"frame":{k},"result":{result}}}"#));
    }
    let kp = root.join("dance.keypoints.jsonl");
    std::fs::write(&kp, lines.join("\n")).unwrap();
    let out = root.join("from_kp.npz");
    let o = run(&["--keypoints", s(&kp), "--out", s(&out)], None);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}{stdout}", String::from_utf8_lossy(&o.stderr));
    assert!(stdout.contains("a person in 59 of them") && stdout.contains("frames [30]"), "{stdout}");
    let m = Motion::from_amass_npz(&std::fs::read(&out).unwrap(), "dance").unwrap();
    assert_eq!(m.len(), FRAMES);
    // The dancer turns a quarter to her left (the fit sees 1.2…1.6 rad of it from the side).
    let t = turn(&m);
    assert!((1.0..1.8).contains(&t), "turned {t} rad");
    // She jumps: the pelvis rises above its first height by > 10 cm mid-clip (truth 22 cm
    // above the squat's low), and squats lower than it by > 10 cm at first.
    let pelvis: Vec<f32> =
        (0..m.len()).map(|k| pose_body(&model, &m.params(k, &[])).kinematics.posed_joints[0].y).collect();
    let (high, low) = (
        pelvis[20..35].iter().copied().fold(f32::MIN, f32::max),
        pelvis[..20].iter().copied().fold(f32::MAX, f32::min),
    );
    assert!(high - low > 0.25 && pelvis[0] - low > 0.1, "pelvis heights {pelvis:?}");

    // The video: each frame drawn as the body's silhouette, encoded as MP4, stride 2.
    let frames = root.join("frames");
    std::fs::create_dir_all(&frames).unwrap();
    for (k, d) in dets.iter().enumerate() {
        let px: Vec<u8> = d.mask.iter().flat_map(|m| if *m > 0.5 { [200, 160, 140] } else { [60, 60, 70] }).collect();
        std::fs::write(frames.join(format!("{k:03}.png")), encode_png(SIZE, SIZE, 3, &px).unwrap()).unwrap();
    }
    let video = root.join("dance.mp4");
    let enc = std::process::Command::new("ffmpeg")
        .args(["-v", "error", "-y", "-framerate", "30", "-i"])
        .arg(frames.join("%03d.png"))
        .args(["-c:v", "mpeg4", "-q:v", "3", "-pix_fmt", "yuv420p"])
        .arg(&video)
        .output()
        .expect("ffmpeg (cargo xtask setup installs it)");
    assert!(enc.status.success(), "{}", String::from_utf8_lossy(&enc.stderr));
    // The stand-in detector: decoded frame i (frame_<i+1>.jpg) is video frame 2i; it finds
    // no one in frame_000008.jpg, and says so as the real script does.
    let answers = root.join("answers");
    std::fs::create_dir_all(&answers).unwrap();
    for i in 0..FRAMES / 2 {
        if i != 7 {
            std::fs::write(
                answers.join(format!("frame_{:06}.kp.json", i + 1)),
                serde_json::to_string(&dets[2 * i].result).unwrap(),
            )
            .unwrap();
        }
    }
    let detector = root.join("detector.sh");
    let script = format!(
        "#!/bin/sh\nfor f in \"$1\"/*.jpg; do n=$(basename \"$f\" .jpg); \
         if [ -f '{a}'/$n.kp.json ]; then cp '{a}'/$n.kp.json \"$1/$n.kp.json\"; else echo \"$n.jpg: no person\" >&2; miss=1; fi; done\n\
         exit ${{miss:-0}}\n",
        a = s(&answers)
    );
    std::fs::write(&detector, script).unwrap();
    std::fs::set_permissions(&detector, std::fs::Permissions::from_mode(0o755)).unwrap();
    let (out_v, kp_out) = (root.join("from_video.npz"), root.join("written.jsonl"));
    let o = run(
        &["--video", s(&video), "--stride", "2", "--out", s(&out_v), "--keypoints-out", s(&kp_out)],
        Some(&detector),
    );
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}{stdout}", String::from_utf8_lossy(&o.stderr));
    assert!(
        stdout.contains("30 frames at 15.00 fps, 256×256; a person in 29 of them") && stdout.contains("frames [7]"),
        "{stdout}"
    );
    let mv = Motion::from_amass_npz(&std::fs::read(&out_v).unwrap(), "dance").unwrap();
    // 30 frames at 15 fps span 29/15 s: 59 frames at 30 fps.
    assert_eq!(mv.len(), 59);
    let t = turn(&mv);
    assert!((1.0..1.8).contains(&t), "turned {t} rad");
    // The written detections read back to the same motion.
    let again = root.join("again.npz");
    let o = run(&["--keypoints", s(&kp_out), "--out", s(&again)], None);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let m2 = Motion::from_amass_npz(&std::fs::read(&again).unwrap(), "dance").unwrap();
    assert_eq!(m2.len(), mv.len());
    assert!((turn(&m2) - t).abs() < 1e-3);

    // Bad input: one message each.
    let fail = |args: &[&str], detector: Option<&Path>, want: &str| {
        let o = run(args, detector);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && err.contains(want), "{args:?}: wanted {want:?} in {err}");
        assert!(!err.contains("panicked"), "{err}");
    };
    let empty = root.join("empty.mp4");
    std::fs::write(&empty, b"").unwrap();
    fail(&["--video", s(&empty)], None, "is empty (0 bytes)");
    let text = root.join("notes.mp4");
    std::fs::write(&text, b"not a video at all").unwrap();
    fail(&["--video", s(&text)], None, "is not a video ffmpeg can read");
    fail(&["--video", s(&video), "--max-seconds", "1"], Some(&detector), "at most 1 s are fitted");
    let blind = root.join("blind.sh");
    std::fs::write(
        &blind,
        "#!/bin/sh\nfor f in \"$1\"/*.jpg; do echo \"$(basename $f): no person\" >&2; done\nexit 1\n",
    )
    .unwrap();
    std::fs::set_permissions(&blind, std::fs::Permissions::from_mode(0o755)).unwrap();
    fail(&["--video", s(&video), "--stride", "6"], Some(&blind), "no person was found in any of the 10 frames");
    std::fs::write(&kp, "{\"format\":\"something-else\",\"width\":1,\"height\":1,\"fps\":30}\n").unwrap();
    fail(&["--keypoints", s(&kp)], None, "expected getavatar-video-keypoints/1");
}
