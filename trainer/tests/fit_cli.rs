//! `trainer fit-pose` end to end: a synthetic detection of a body in an unseen pose (kick,
//! photographed from the side) written as the files a user has (photo PNG, MediaPipe's
//! result JSON, mask PNG) → fit.json: the fitted body's joints within 60 mm PA-MPJPE of the
//! truth, the camera, the table and the overlay; and bad input refused with one clear message.

#![allow(clippy::unwrap_used, clippy::expect_used)] // a test fails by panicking

use std::path::Path;

use getavatar_core::body::body_fit::fit::BodyFit;
use getavatar_core::body::body_fit::metrics::pa_mpjpe;
use getavatar_core::body::body_fit::synthetic::{detect, unseen_poses, wide_poses, UNSEEN_POSE_CAMERAS, WIDE_YAWS};
use getavatar_core::body::body_fit::turn;
use getavatar_core::body::skinning::pose_body;
use getavatar_core::io::dataset::{decode_png, encode_png};
use getavatar_core::util::rng::Rng;
use getavatar_core::{BodyModel, BodyParams};

mod common;
use common::{s, tmp, trainer};

#[test]
fn fit_pose_fits_a_synthetic_photo_and_refuses_bad_input() {
    let dir = tmp("fit-pose");
    let model = BodyModel::default_body().unwrap();
    let (name, truth) = unseen_poses().into_iter().nth(2).unwrap();
    assert_eq!(name, "kick");
    let cam = UNSEEN_POSE_CAMERAS[2].camera();
    // A non-square photo: the person in a 640 × 512 frame (the detection of a 512² render,
    // shifted right by 64 px, so framing and normalisation see a wide image).
    let size = 512;
    let det = detect(&model, &truth, cam.world_to_camera(), size, 2.0, 0.02, &mut Rng::new(4, 4)).unwrap();
    let (w, h) = (640usize, 512usize);
    let mut result = det.result.clone();
    for l in result.pose_landmarks.iter_mut() {
        l.x = (l.x * size as f32 + 64.0) / w as f32;
    }
    let mut photo = vec![0u8; w * h * 3];
    let mut mask = vec![0u8; w * h];
    for y in 0..h {
        for x in 0..w {
            let inside = x >= 64 && x < 64 + size && det.mask[y * size + x - 64] > 0.5;
            let c = if inside { [205, 170, 150] } else { [40, 45, 60] };
            photo[(y * w + x) * 3..][..3].copy_from_slice(&c);
            mask[y * w + x] = if inside { 255 } else { 0 };
        }
    }
    let (photo_p, mask_p, kp_p) = (dir.join("photo.png"), dir.join("mask.png"), dir.join("kp.json"));
    std::fs::write(&photo_p, encode_png(w, h, 3, &photo).unwrap()).unwrap();
    std::fs::write(&mask_p, encode_png(w, h, 1, &mask).unwrap()).unwrap();
    std::fs::write(&kp_p, serde_json::to_string(&result).unwrap()).unwrap();
    let (out, ov) = (dir.join("fit.json"), dir.join("overlay.png"));
    let args = ["fit-pose", "--image", s(&photo_p), "--keypoints", s(&kp_p), "--mask", s(&mask_p)];
    let run = trainer(&[&args[..], &["--out", s(&out), "--overlay", s(&ov)]].concat());
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(run.status.success(), "{}\n{}", stdout, String::from_utf8_lossy(&run.stderr));
    assert!(stdout.contains("mask IoU"), "{stdout}");

    let fit: BodyFit = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert_eq!(fit.format, "getavatar-body-fit/1");
    assert_eq!((fit.body_pose.len(), fit.betas.len(), fit.keypoints.len()), (69, 10, 33));
    assert_eq!(fit.table.len(), 12 + 9, "12 joint and 9 surface landmarks");
    assert_eq!((fit.framing.photo_width, fit.framing.photo_height), (w, h));
    let fitted = pose_body(&model, &fit.body_params()).kinematics.posed_joints;
    let err = pa_mpjpe(&fitted, &pose_body(&model, &truth).kinematics.posed_joints);
    assert!(err <= 0.060, "PA-MPJPE {:.1} mm", err * 1000.0);
    assert!(fit.residuals.mask_iou.unwrap() > 0.9, "{:?}", fit.residuals);
    assert!(fit.residuals.relative_to_height < 0.02, "{:?}", fit.residuals);
    // The left wrist's fitted keypoint lies where it was detected (photo pixels).
    let wrist = fit.keypoints.iter().find(|k| k.name == "left_wrist").unwrap();
    let f = wrist.fitted.unwrap();
    assert!((f[0] - wrist.observed[0]).hypot(f[1] - wrist.observed[1]) < 12.0, "{wrist:?}");
    // The overlay is the photo's size with the body tinted where the mask is.
    let img = decode_png(&std::fs::read(&ov).unwrap()).unwrap();
    assert_eq!((img.width, img.height), (w, h));
    let tinted = (0..w * h).filter(|k| img.pixels[k * img.channels + 2] > 150 && mask[*k] > 0).count();
    let person = mask.iter().filter(|m| **m > 0).count();
    assert!(tinted as f32 > 0.8 * person as f32, "{tinted} of {person} person pixels tinted");

    // The same person lying in the photo as taken (turned 90° counter-clockwise), detected
    // on the photo turned back upright (`rotation` 90, what the app's person finder writes):
    // the same fit on the turned photo, and the overlay drawn through the camera rolled back
    // lands on the person in the photo as taken.
    let (taken, tw, th) = turn::turn_image(&photo, w, h, 3, 270);
    let (taken_mask, _, _) = turn::turn_image(&mask, w, h, 1, 270);
    assert_eq!((tw, th), (h, w));
    let (taken_p, taken_mask_p, kp90_p) = (dir.join("taken.png"), dir.join("taken_mask.png"), dir.join("kp90.json"));
    std::fs::write(&taken_p, encode_png(tw, th, 3, &taken).unwrap()).unwrap();
    std::fs::write(&taken_mask_p, encode_png(tw, th, 1, &taken_mask).unwrap()).unwrap();
    let mut turned = result.clone();
    turned.rotation = 90;
    std::fs::write(&kp90_p, serde_json::to_string(&turned).unwrap()).unwrap();
    let (out90, ov90) = (dir.join("fit90.json"), dir.join("overlay90.png"));
    let args = ["fit-pose", "--image", s(&taken_p), "--keypoints", s(&kp90_p), "--mask", s(&taken_mask_p)];
    let run = trainer(&[&args[..], &["--out", s(&out90), "--overlay", s(&ov90)]].concat());
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let fit90: BodyFit = serde_json::from_str(&std::fs::read_to_string(&out90).unwrap()).unwrap();
    assert_eq!(fit90.rotation, 90);
    assert_eq!((fit90.framing.photo_width, fit90.framing.photo_height), (w, h), "the fit is of the turned photo");
    let same = fit90.body_pose.iter().zip(&fit.body_pose).chain(fit90.camera.iter().zip(&fit.camera));
    assert!(same.clone().all(|(a, b)| (a - b).abs() < 1e-4), "{:?}", same.collect::<Vec<_>>());
    let img = decode_png(&std::fs::read(&ov90).unwrap()).unwrap();
    assert_eq!((img.width, img.height), (tw, th), "the overlay is of the photo as taken");
    let tinted = (0..tw * th).filter(|k| img.pixels[k * img.channels + 2] > 150 && taken_mask[*k] > 0).count();
    let stray = (0..tw * th).filter(|k| img.pixels[k * img.channels + 2] > 150 && taken_mask[*k] == 0).count();
    assert!(
        tinted as f32 > 0.8 * person as f32 && (stray as f32) < 0.2 * person as f32,
        "{tinted} tinted on, {stray} off the person"
    );

    // Bad input: one clear message each, no fit written.
    let bad = |extra: &[&str], what: &str| {
        let o = dir.join("bad.json");
        let run = trainer(&[&["fit-pose", "--out", s(&o)][..], extra].concat());
        let err = String::from_utf8_lossy(&run.stderr).to_string();
        assert!(!run.status.success() && err.contains(what), "{extra:?}: {err}");
        assert!(!err.contains("panicked"), "{err}");
        assert!(!o.exists());
    };
    let junk = dir.join("junk.png");
    std::fs::write(&junk, [0x13u8, 0x37, 0, 1, 2, 3, 4, 5, 6, 7]).unwrap();
    bad(&["--image", s(&junk), "--keypoints", s(&kp_p)], "is not a PNG or JPEG image");
    let empty = dir.join("empty.png");
    std::fs::write(&empty, []).unwrap();
    bad(&["--image", s(&empty), "--keypoints", s(&kp_p)], "is not a PNG or JPEG image");
    let few = dir.join("few.json");
    let mut r17 = result.clone();
    r17.pose_landmarks.truncate(17);
    std::fs::write(&few, serde_json::to_string(&r17).unwrap()).unwrap();
    bad(&["--image", s(&photo_p), "--keypoints", s(&few)], "`poseLandmarks` has 17 landmarks, expected 33");
    let headless = dir.join("headless.json");
    let mut hidden = result.clone();
    for i in [11, 12, 23, 24] {
        hidden.pose_landmarks[i].visibility = 0.1;
    }
    std::fs::write(&headless, serde_json::to_string(&hidden).unwrap()).unwrap();
    bad(&["--image", s(&photo_p), "--keypoints", s(&headless)], "no torso found");
    bad(&["--image", s(&photo_p), "--keypoints", s(&dir.join("missing.json"))], "missing.json");
    let askew = dir.join("askew.json");
    std::fs::write(&askew, serde_json::to_string(&turned).unwrap().replace("\"rotation\":90", "\"rotation\":45"))
        .unwrap();
    bad(&["--image", s(&photo_p), "--keypoints", s(&askew)], "`rotation` is 45°");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The real detector: MediaPipe Pose's results (committed fixtures, made by
/// `tools/mediapipe_fixtures.mjs` in headless Chromium from `trainer body-photos`, through
/// the app's person finder) on the bare body in the unseen poses from two yaws →
/// `trainer fit-pose` with the detector's mask, PA-MPJPE against the pose that was rendered.
/// The target is PA-MPJPE ≤ 60 mm: the mean over the set, as the field reports it (HMR, SPIN
/// on 3DPW), is 44.9 mm, with the cases at 33–54 mm. Arms crossed is a detector error the fit
/// can only partly undo (MediaPipe guesses the hidden elbow; 53.8 mm from the front). So this
/// guards the set's mean ≤ 60 mm, nine of ten cases ≤ 60 mm and every case ≤ 68 mm.
#[test]
fn fit_pose_on_mediapipe_detections_recovers_the_rendered_poses() {
    let (dir, fixtures, model) = fixture_photos("fit-mediapipe", "");
    let mut report = Vec::new();
    let mut worst = 0.0f32;
    let mut errors = Vec::new();
    for (name, truth) in unseen_poses() {
        for k in 0..2 {
            let stem = format!("{name}_yaw{k}");
            let (fit, err) = fit_fixture(&dir, &fixtures, &stem, &model, &truth);
            worst = worst.max(err);
            errors.push(err);
            // Only a fit whose wrists disagree on visibility may swap the hands.
            let wrists_seen = [15, 16].map(|l| fit.keypoints[l].visibility >= 0.5);
            assert!(fit.relabelled.is_empty() || wrists_seen[0] != wrists_seen[1], "{stem}: {:?}", fit.relabelled);
            report.push(format!(
                "{stem}: PA-MPJPE {:.1} mm, keypoints {:.2} % of the height, mask IoU {:.3}",
                err * 1000.0,
                100.0 * fit.residuals.relative_to_height,
                fit.residuals.mask_iou.unwrap_or(f32::NAN)
            ));
        }
    }
    eprintln!("{}", report.join("\n"));
    let within = errors.iter().filter(|e| **e <= 0.060).count();
    let mean = errors.iter().sum::<f32>() / errors.len() as f32;
    eprintln!("PA-MPJPE over the set: {:.1} mm", mean * 1000.0);
    assert!(
        mean <= 0.060 && within >= 9 && worst <= 0.068,
        "mean {mean}, {within} of 10 within 60 mm, worst {worst}\n{}",
        report.join("\n")
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// The wider fixture set (made the same way): eight more poses outside the pose library
/// (jumping jack, sitting with crossed arms, one leg with arms up, a turned walk, a side
/// reach, a crouch with a twist, kneeling, leaning forward), each from the front, 40° and
/// 90° to the side and from behind. The goal is a mean PA-MPJPE ≤ 60 mm with no case over
/// 90 mm; measured: mean 51.2 mm, worst 87.7 mm (the raised knee from the front; the side
/// reach from its side 82.6). The side reach from its side is the one the shape prior
/// decided (`FitWeights::betas` 2; at 0.5 a freer β shortened the torso to explain its
/// lean in depth: 90.1 mm). Pose's first reading of it puts the near hand (at the waist, in
/// front of the torso) over the head with the far one (`misread/side_reach_view2`); the
/// person finder reads a photo with both hands in one place again mirrored, and that reading,
/// which has the hand lower, is the fixture (`www/pose_worker.js`, `secondOpinion`).
/// Kneeling from behind (MediaPipe reads the forward thigh as hanging down and its shin
/// as pointing at the camera) stays under 90 mm (71.3) through the misread thigh's handling
/// (`leg_readings`: the leg starts at rest, the shin inherits the doubt, the lifted directions),
/// the side reach from behind (72.7) through the legs' twist ranges. A single hard case
/// moves by up to ~13 mm when only the order of floating-point additions changes
/// (docs/benchmarks.md, "How far one case moves on its own"); the means move by tenths of a
/// millimetre. `FIT_ONLY=stem,stem` fits only those cases (with `FIT_DEBUG=1`, to look at one).
#[test]
fn fit_pose_on_the_wider_fixture_set_stays_within_its_measured_errors() {
    let (dir, fixtures, model) = fixture_photos("fit-wide", "");
    let mut report = Vec::new();
    let mut errors = Vec::new();
    for (name, truth) in wide_poses() {
        for k in 0..WIDE_YAWS.len() {
            let stem = format!("{name}_view{k}");
            if std::env::var("FIT_ONLY").is_ok_and(|o| !o.split(',').any(|x| x == stem)) {
                continue;
            }
            let (fit, err) = fit_fixture(&dir, &fixtures, &stem, &model, &truth);
            // Every reading's landmarks are on the person here (`misread/` has one that is not).
            assert!(fit.off_person.is_empty(), "{stem}: {:?} off the person", fit.off_person);
            errors.push(err);
            report.push(format!(
                "{stem}: PA-MPJPE {:.1} mm, keypoints {:.2} % of the height, mask IoU {:.3}",
                err * 1000.0,
                100.0 * fit.residuals.relative_to_height,
                fit.residuals.mask_iou.unwrap_or(f32::NAN)
            ));
        }
    }
    let mean = errors.iter().sum::<f32>() / errors.len() as f32;
    let worst = errors.iter().copied().fold(0.0f32, f32::max);
    eprintln!(
        "{}\nPA-MPJPE over the wider set: mean {:.1} mm, worst {:.1} mm",
        report.join("\n"),
        mean * 1000.0,
        worst * 1000.0
    );
    if std::env::var("FIT_ONLY").is_err() {
        assert!(mean <= 0.060 && worst <= 0.090, "mean {mean}, worst {worst}\n{}", report.join("\n"));
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Two readings MediaPipe got wrong, kept to hold the fit's answers to them (`misread/`: made
/// by earlier versions of the detector's pipeline from earlier renders of the same poses; the
/// third there, the side reach from its side, is `fit_pose_holds_a_limb_the_person_corrected`'s):
/// - the jumping jack from the front, its arms read over the head while its own person mask
///   shows them spread: the wrists and fingers lie 4.9–7.6 % of the photo's height off the
///   mask, so those limbs are taken as the detector's error and named missing, and the
///   silhouette places them (81.3 mm; 106.6 with the reading taken as it is; 62.0 with the
///   weaker shape prior of `FitWeights::betas` 0.5, which the fixture sets fit worse);
/// - crossed arms from 52° to the side, the seen hand given the other wrist's label: the fit's
///   two-labelling hypothesis swaps the hands back (39.6 mm; 58.7 without it).
#[test]
fn fit_pose_undoes_known_detector_misreadings() {
    let (dir, fixtures, model) = fixture_photos("fit-misread", "misread");
    let truth =
        |poses: Vec<(&'static str, BodyParams)>, name: &str| poses.into_iter().find(|(n, _)| *n == name).unwrap().1;

    let stem = "jumping_jack_view0";
    let (fit, err) = fit_fixture(&dir, &fixtures, stem, &model, &truth(wide_poses(), "jumping_jack"));
    for l in ["left_elbow", "left_wrist", "right_elbow", "right_wrist", "right_index"] {
        assert!(fit.off_person.iter().any(|o| o == l), "{stem}: {l} not off: {:?}", fit.off_person);
        assert!(fit.missing.iter().any(|o| o == l), "{stem}: {l} not missing: {:?}", fit.missing);
    }
    eprintln!("{stem}: PA-MPJPE {:.1} mm, off the person: {:?}", err * 1000.0, fit.off_person);
    assert!(err <= 0.090, "{stem}: PA-MPJPE {:.1} mm", err * 1000.0);

    let stem = "arms_crossed_yaw1";
    let (fit, err) = fit_fixture(&dir, &fixtures, stem, &model, &truth(unseen_poses(), "arms_crossed"));
    assert_eq!(fit.relabelled.first().map(String::as_str), Some("left_wrist↔right_wrist"), "{stem}");
    eprintln!("{stem}: PA-MPJPE {:.1} mm, relabelled: {:?}", err * 1000.0, fit.relabelled);
    assert!(err <= 0.050, "{stem}: PA-MPJPE {:.1} mm", err * 1000.0);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A person's correction of a misread limb holds (`fit-pose --start`; the app's pose controls,
/// then "Re-fit from this pose"). The side reach seen from its side as Pose first reads it
/// (`misread/side_reach_view2`, the reading before the person finder's mirrored second opinion
/// for two hands in one place): the near (left) hand, at the waist, read over the head with
/// the far one, and the fit follows it (106.1 mm).
/// - Started from its own fit.json the re-fit holds no limb and ends where the fit did.
/// - Started from that fit with the left arm's rotations set to the truth's (what a person does
///   with the pose controls), it holds the left arm, leaves out the arm's landmarks and ends
///   under 90 mm, with the wrist where the person put it rather than where it was read.
/// - A fit of another photo is refused with one message.
#[test]
fn fit_pose_holds_a_limb_the_person_corrected() {
    let (dir, fixtures, model) = fixture_photos("fit-correct", "misread");
    let truth = wide_poses().into_iter().find(|(n, _)| *n == "side_reach").unwrap().1;
    let stem = "side_reach_view2";
    let (fit, err) = fit_fixture(&dir, &fixtures, stem, &model, &truth);
    let own = dir.join("own.fit.json");
    std::fs::write(&own, fit.to_json().unwrap()).unwrap();
    let (again, err_again) = fit_fixture_from(&dir, &fixtures, stem, &model, &truth, Some(&own));
    eprintln!("{stem}: fit {:.1} mm, again from its own fit {:.1} mm", err * 1000.0, err_again * 1000.0);
    assert!(again.held.is_empty(), "{:?}", again.held);
    assert!((err_again - err).abs() < 0.005, "{err} → {err_again}");

    let mut corrected = fit.clone();
    for j in [16, 18, 20, 22] {
        corrected.body_pose[(j - 1) * 3..][..3].copy_from_slice(&truth.pose[j].to_array());
    }
    let start = dir.join("corrected.fit.json");
    std::fs::write(&start, corrected.to_json().unwrap()).unwrap();
    let (refit, err_refit) = fit_fixture_from(&dir, &fixtures, stem, &model, &truth, Some(&start));
    let wrist = |f: &BodyFit| {
        let k = f.keypoints.iter().find(|k| k.name == "left_wrist").unwrap();
        (k.fitted.unwrap(), k.observed)
    };
    let ((at, read), (first, _)) = (wrist(&refit), wrist(&fit));
    eprintln!(
        "{stem}: re-fit from the corrected left arm {:.1} mm, held {:?}; left wrist at {at:?}, read at {read:?}, first fit {first:?}",
        err_refit * 1000.0,
        refit.held
    );
    assert_eq!(refit.held, ["left arm"]);
    assert!(err_refit < 0.090 && err_refit < err - 0.010, "{err} → {err_refit}");
    // The wrist is held below where it was read (photo pixels, y down), by a tenth of the photo.
    assert!(at[1] - read[1] > 0.1 * fit.framing.photo_height as f32, "{at:?} vs {read:?}");

    let other = dir.join("other.fit.json");
    let mut moved = fit.clone();
    moved.framing.centre[0] += 40.0;
    std::fs::write(&other, moved.to_json().unwrap()).unwrap();
    let (kp, mask) = (fixtures.join(format!("{stem}.kp.json")), fixtures.join(format!("{stem}.mask.png")));
    let photo = dir.join(format!("{stem}.png"));
    let run =
        trainer(&["fit-pose", "--image", s(&photo), "--keypoints", s(&kp), "--mask", s(&mask), "--start", s(&other)]);
    let err_text = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success() && err_text.contains("another photo or detection"), "{err_text}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A clothed runner seen from its side (`fixtures/mediapipe/clothed/runner_side.*`: person 0006,
/// view 000 of `trainer synth-scans --count 12 --seed 1` + `prepare --views 4 --res 512 --seed
/// 1`, composited over a gradient by `tools/heldout_photos.mjs`, read by
/// `tools/mediapipe_fixtures.mjs`; the truth is the scan's `smpl.json`). Pose's first reading
/// (`runner_side.first.kp.json`) puts both legs together in the gap between them, off the
/// person's mask: the fit takes them as the detector's error and places the legs from the mask
/// alone. The person finder now reads the mirrored photo too (`www/pose_worker.js`,
/// `secondOpinion`), and its reading (`runner_side.kp.json`, `mirrored`) has the legs on the
/// person: nothing off the mask, and the fit within the first set's 60 mm.
#[test]
fn fit_pose_on_the_mirrored_reading_of_a_runner_keeps_its_legs() {
    let dir = tmp("fit-runner");
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/mediapipe/clothed");
    let model = BodyModel::default_body().unwrap();
    let smpl = std::fs::read_to_string(fixtures.join("runner_side.smpl.json")).unwrap();
    let truth = getavatar_core::io::scan::SmplParams::from_json(&smpl).unwrap().body_params();
    let tj = pose_body(&model, &truth).kinematics.posed_joints;
    let fit = |kp: &str| {
        let (photo, mask) = (fixtures.join("runner_side.png"), fixtures.join("runner_side.mask.png"));
        let kp_path = fixtures.join(format!("{kp}.kp.json"));
        let fit = fit_pose(&photo, &kp_path, &mask, &dir.join(format!("{kp}.fit.json")), None);
        let err = pa_mpjpe(&pose_body(&model, &fit.body_params()).kinematics.posed_joints, &tj);
        eprintln!(
            "{kp}: PA-MPJPE {:.1} mm, mask IoU {:.3}, off the person {:?}",
            err * 1000.0,
            fit.residuals.mask_iou.unwrap_or(f32::NAN),
            fit.off_person
        );
        (fit, err)
    };
    let (first, err_first) = fit("runner_side.first");
    assert!(first.off_person.iter().any(|l| l.contains("ankle")), "{:?}", first.off_person);
    let (mirrored, err) = fit("runner_side");
    assert!(mirrored.off_person.is_empty(), "{:?}", mirrored.off_person);
    // Measured: 143.5 mm (mask IoU 0.670) from the first reading, 41.5 mm (0.908) mirrored.
    assert!(err <= 0.060 && err < err_first - 0.050, "{err_first} → {err}");
    assert!(mirrored.residuals.mask_iou.is_some_and(|m| m >= 0.85), "{:?}", mirrored.residuals.mask_iou);
    let _ = std::fs::remove_dir_all(&dir);
}

/// `trainer fit-pose` on a photo, its MediaPipe reading and mask (from `start` when given),
/// writing `out`: the fit it wrote.
fn fit_pose(photo: &Path, kp: &Path, mask: &Path, out: &Path, start: Option<&Path>) -> BodyFit {
    let mut args = vec!["fit-pose", "--image", s(photo), "--keypoints", s(kp), "--mask", s(mask), "--out", s(out)];
    if let Some(start) = start {
        args.extend(["--start", s(start)]);
    }
    let run = trainer(&args);
    assert!(run.status.success(), "{}: {}", kp.display(), String::from_utf8_lossy(&run.stderr));
    serde_json::from_str(&std::fs::read_to_string(out).unwrap()).unwrap()
}

/// A fixture test's setup: `trainer body-photos` rendered into a new temporary folder `name`,
/// the fixtures' folder (`fixtures/mediapipe/SUB`) and the body model.
fn fixture_photos(name: &str, sub: &str) -> (std::path::PathBuf, std::path::PathBuf, BodyModel) {
    let dir = tmp(name);
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/mediapipe").join(sub);
    let run = trainer(&["body-photos", "--out", s(&dir)]);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    (dir, fixtures, BodyModel::default_body().unwrap())
}

/// `trainer fit-pose` on a committed MediaPipe fixture (`fixtures/STEM.kp.json`,
/// `STEM.mask.png`) of the photo `dir/STEM.png`: the fit and its PA-MPJPE against `truth`.
/// FIT_DEBUG=1 prints each joint's error after the Procrustes alignment.
fn fit_fixture(dir: &Path, fixtures: &Path, stem: &str, model: &BodyModel, truth: &BodyParams) -> (BodyFit, f32) {
    fit_fixture_from(dir, fixtures, stem, model, truth, None)
}

/// [`fit_fixture`] started from a fit.json (`--start`), written to `STEM.refit.json`.
fn fit_fixture_from(
    dir: &Path,
    fixtures: &Path,
    stem: &str,
    model: &BodyModel,
    truth: &BodyParams,
    start: Option<&Path>,
) -> (BodyFit, f32) {
    let out = dir.join(format!("{stem}.{}.json", if start.is_some() { "refit" } else { "fit" }));
    let (kp, mask) = (fixtures.join(format!("{stem}.kp.json")), fixtures.join(format!("{stem}.mask.png")));
    let fit = fit_pose(&dir.join(format!("{stem}.png")), &kp, &mask, &out, start);
    let fitted = pose_body(model, &fit.body_params()).kinematics.posed_joints;
    let tj = pose_body(model, truth).kinematics.posed_joints;
    let err = pa_mpjpe(&fitted, &tj);
    if std::env::var("FIT_DEBUG").is_ok() {
        let (sc, r, t) = getavatar_core::body::body_fit::metrics::procrustes(&fitted, &tj);
        let per: Vec<String> = fitted
            .iter()
            .zip(&tj)
            .enumerate()
            .map(|(j, (a, b))| {
                format!("{}:{:.0}", getavatar_core::JOINT_NAMES[j], ((sc * (r * *a) + t) - *b).length() * 1000.0)
            })
            .collect();
        eprintln!("{stem}: {}", per.join(" "));
    }
    (fit, err)
}
