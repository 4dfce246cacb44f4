//! Motion clips: the AMASS-format round trip (a file written by numpy,
//! tests/fixtures/motion/make_amass.py), bad motion files, and the built-in clips' motion.

use std::collections::BTreeMap;

use getavatar_core::body::body_model::BodyModel;
use getavatar_core::body::motion::{Motion, MotionError, MAX_FRAMES, MOTION_FPS};
use getavatar_core::body::skinning::axis_angle_to_quat as quat;
use getavatar_core::body::skinning::{pose_body, BodyParams};
use getavatar_core::io::npz::{write_npz, NpyArray};
use glam::{Quat, Vec3};

const FIXTURE: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/motion/amass_sample");

#[test]
fn amass_file_plays_the_same_poses_joint_by_joint() {
    let bytes = std::fs::read(format!("{FIXTURE}.npz")).expect("fixture npz");
    let truth: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(format!("{FIXTURE}.json")).expect("fixture json")).unwrap();
    let theta: Vec<Vec<f32>> = serde_json::from_value(truth["theta"].clone()).unwrap();
    let trans: Vec<Vec<f32>> = serde_json::from_value(truth["trans"].clone()).unwrap();
    let m = Motion::from_amass_npz(&bytes, "sample").expect("load");
    // 31 frames at 60 fps = 0.5 s → 16 frames at 30 fps; frame k is the file's frame 2k.
    assert_eq!(m.len(), 16);
    let notes = m.notes.join("; ");
    assert!(notes.contains("SMPL-H") && notes.contains("betas") && notes.contains("60 fps"), "{notes}");
    let model = BodyModel::default_body().unwrap();
    let up = Quat::from_rotation_x(-std::f32::consts::FRAC_PI_2);
    let start = up * Vec3::from_slice(&trans[0]);
    let mut worst = 0.0f32;
    for k in 0..m.len() {
        let src = &theta[2 * k];
        let file_pose: Vec<Vec3> = (0..24).map(|j| Vec3::from_slice(&src[3 * j..3 * j + 3])).collect();
        for (j, (got, want)) in m.poses[k].iter().zip(&file_pose).enumerate().skip(1) {
            assert!((*got - *want).length() < 1e-5, "frame {k} joint {j}: {got} vs {want}");
        }
        let root = quat(m.poses[k][0]);
        let want = up * quat(file_pose[0]);
        assert!(root.dot(want).abs() > 1.0 - 1e-6, "frame {k}: root {root} vs {want}");
        let t = m.trans[k];
        let want_t = up * Vec3::from_slice(&trans[2 * k]) - start;
        assert!((t - want_t).length() < 1e-5, "frame {k}: trans {t} vs {want_t}");
        // Joint by joint: the loaded frame's posed joints are the file's, turned z-up → y-up.
        let ours = pose_body(&model, &m.params(k, &[])).kinematics.posed_joints;
        let mut fp = BodyParams::default();
        fp.pose.copy_from_slice(&file_pose);
        let theirs = pose_body(&model, &fp).kinematics.posed_joints;
        for (a, b) in ours.iter().zip(&theirs) {
            worst = worst.max(((*a - ours[0]) - up * (*b - theirs[0])).length());
        }
    }
    assert!(worst < 1e-4, "posed joints differ by {worst} m");
}

fn npz(arrays: Vec<(&str, NpyArray)>) -> Vec<u8> {
    let map: BTreeMap<String, NpyArray> = arrays.into_iter().map(|(k, v)| (k.to_string(), v)).collect();
    write_npz(&map).unwrap()
}

#[test]
fn bad_motion_files_are_errors_that_say_why() {
    let ok_poses = |n: usize| NpyArray::f64(vec![n, 72], vec![0.1; n * 72]);
    let ok_trans = |n: usize| NpyArray::f64(vec![n, 3], vec![0.0; n * 3]);
    let fps = |f: f64| NpyArray::f64(vec![], vec![f]);
    let err = |b: Vec<u8>| Motion::from_amass_npz(&b, "bad").unwrap_err();
    assert!(matches!(err(b"not a zip".to_vec()), MotionError::Npz(_)));
    let e = err(npz(vec![("trans", ok_trans(4)), ("mocap_framerate", fps(30.0))]));
    assert!(e.to_string().contains("`poses`"), "{e}");
    let e = err(npz(vec![
        ("poses", NpyArray::f64(vec![4, 70], vec![0.0; 280])),
        ("trans", ok_trans(4)),
        ("mocap_framerate", fps(30.0)),
    ]));
    assert!(e.to_string().contains("N×72"), "{e}");
    let e = err(npz(vec![("poses", ok_poses(4)), ("trans", ok_trans(5)), ("mocap_framerate", fps(30.0))]));
    assert!(e.to_string().contains("`trans`"), "{e}");
    let mut nan = vec![0.0; 4 * 72];
    nan[3 * 72 + 10] = f64::NAN;
    let e = err(npz(vec![
        ("poses", NpyArray::f64(vec![4, 72], nan)),
        ("trans", ok_trans(4)),
        ("mocap_framerate", fps(30.0)),
    ]));
    assert!(e.to_string().contains("frame 3"), "{e}");
    let e = err(npz(vec![("poses", ok_poses(4)), ("trans", ok_trans(4)), ("mocap_framerate", fps(0.0))]));
    assert!(matches!(e, MotionError::FrameRate(_)), "{e}");
    let e = err(npz(vec![("poses", ok_poses(0)), ("trans", ok_trans(0)), ("mocap_framerate", fps(30.0))]));
    assert!(matches!(e, MotionError::Empty), "{e}");
    // 100 k frames at 120 fps (833 s): cut at the documented cap, and said so.
    let m = Motion::from_amass_npz(
        &npz(vec![("poses", ok_poses(100_000)), ("trans", ok_trans(100_000)), ("mocap_frame_rate", fps(120.0))]),
        "long",
    )
    .expect("long file");
    assert_eq!(m.len(), MAX_FRAMES);
    assert!(m.notes.iter().any(|n| n.contains("cut")), "{:?}", m.notes);
    assert!(matches!(Motion::builtin("moonwalk"), Err(MotionError::UnknownClip(_))));
    // A tiny file claiming 10⁹ frames (and one claiming a shape whose size overflows) errors
    // at once, allocating nothing.
    for shape in ["(1000000000, 72)", "(18446744073709551615, 72)"] {
        let header = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': {shape}, }}");
        let mut npy = b"\x93NUMPY\x01\x00".to_vec();
        npy.extend_from_slice(&(header.len() as u16).to_le_bytes());
        npy.extend_from_slice(header.as_bytes());
        npy.extend_from_slice(&[0u8; 64]);
        let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
        zip.start_file("poses.npy", zip::write::SimpleFileOptions::default()).unwrap();
        std::io::Write::write_all(&mut zip, &npy).unwrap();
        let bytes = zip.finish().unwrap().into_inner();
        assert!(bytes.len() < 1024, "{} bytes", bytes.len());
        let t = std::time::Instant::now();
        let e = Motion::from_amass_npz(&bytes, "claims").unwrap_err();
        assert!(e.to_string().contains("truncated") && t.elapsed().as_secs_f32() < 1.0, "{e}");
    }
}

fn joints(m: &Motion, k: usize) -> [Vec3; 24] {
    let model = BodyModel::default_body().unwrap();
    pose_body(&model, &m.params(k, &[])).kinematics.posed_joints
}

#[test]
fn builtin_clips_move_as_named_and_smoothly() {
    for name in getavatar_core::body::motion::BUILTIN_CLIPS {
        let m = Motion::builtin(name).unwrap();
        assert!(m.len() >= 30, "{name}: {} frames", m.len());
        assert!(m.poses.iter().flatten().all(|v| v.is_finite() && v.length() <= std::f32::consts::PI + 1e-4));
        // Smooth: no frame-to-frame rotation step (any joint) is more than 3× the clip's
        // typical step, across the loop seam too.
        let steps: Vec<f32> = (0..m.len() - if m.looping { 0 } else { 1 })
            .map(|k| {
                let (a, b) = (&m.poses[k], &m.poses[(k + 1) % m.len()]);
                (0..24).map(|j| quat(a[j]).angle_between(quat(b[j]))).fold(0.0, f32::max)
            })
            .collect();
        let mut sorted = steps.clone();
        sorted.sort_by(f32::total_cmp);
        let median = sorted[sorted.len() / 2];
        let max = sorted[sorted.len() - 1];
        assert!(max <= 3.0 * median.max(0.01), "{name}: step max {max} vs median {median}");
    }
    // Walk: the feet take turns in front (z is forward), the pelvis bobs.
    let walk = Motion::builtin("walk").unwrap();
    let (a, b) = (joints(&walk, 0), joints(&walk, walk.len() / 2));
    assert!(a[7].z - a[8].z > 0.15 && b[8].z - b[7].z > 0.15, "ankles {} {} / {} {}", a[7], a[8], b[7], b[8]);
    // Turn: a full turn about the vertical, facing backwards half way.
    let turn = Motion::builtin("turn").unwrap();
    let facing = |k: usize| quat(turn.poses[k][0]) * Vec3::Z;
    assert!(
        facing(0).dot(Vec3::Z) > 0.99
            && facing(turn.len() / 2).dot(Vec3::Z) < -0.99
            && facing(turn.len() - 1).dot(Vec3::Z) > 0.99
    );
    assert!((turn.duration() - 4.0).abs() < 1e-3);
    // Wave: the right hand is above the head and swings sideways by more than 15 cm.
    let wave = Motion::builtin("wave").unwrap();
    let xs: Vec<f32> = (0..wave.len()).map(|k| joints(&wave, k)[21].x).collect();
    let head = joints(&wave, 0)[15].y;
    assert!((0..wave.len()).all(|k| joints(&wave, k)[21].y > head), "the waving hand is up");
    let span = xs.iter().cloned().fold(f32::MIN, f32::max) - xs.iter().cloned().fold(f32::MAX, f32::min);
    assert!(span > 0.15, "the hand swings {span} m");
    assert_eq!(walk.len() as f32, (1.1 * MOTION_FPS).round());
}

#[test]
fn a_written_amass_file_reads_back_as_the_same_clip() {
    let walk = Motion::builtin("walk").unwrap();
    let mut clip = walk.clone();
    for (k, t) in clip.trans.iter_mut().enumerate() {
        *t += Vec3::new(0.02 * k as f32, 0.0, -0.01 * k as f32);
    }
    let bytes = clip.to_amass_npz(Some(&[0.5, -0.2])).unwrap();
    let back = Motion::from_amass_npz(&bytes, "walk").unwrap();
    assert_eq!(back.len(), clip.len());
    for k in 0..clip.len() {
        for j in 0..24 {
            let (a, b) = (quat(clip.poses[k][j]), quat(back.poses[k][j]));
            assert!(a.dot(b).abs() > 1.0 - 1e-6, "frame {k} joint {j}: {a} vs {b}");
        }
        let want = clip.trans[k] - clip.trans[0];
        assert!((back.trans[k] - want).length() < 1e-5, "frame {k}: {} vs {want}", back.trans[k]);
    }
    // Joint positions agree too, so the z-up turn went onto the root and back.
    assert!((joints(&back, 7)[7] - joints(&clip, 7)[7] + clip.trans[0]).length() < 1e-4);
    assert!(matches!(Motion { poses: vec![], trans: vec![], ..walk }.to_amass_npz(None), Err(MotionError::Empty)));
}
