//! `trainer invert` end to end on a dataset image (tiny generator, a few steps): every output
//! is written and readable, the metrics are consistent with the renders, `trainer sample
//! --inverted` reloads the result, and bad input is refused with a reason.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;
use common::{s, tmp, trainer};

fn png_size(path: &std::path::Path) -> (u32, u32, png::ColorType) {
    let d = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
    let r = d.read_info().unwrap();
    let i = r.info();
    (i.width, i.height, i.color_type)
}

/// The bytes of a .glb's first image (its base-colour PNG).
fn glb_image(glb: &[u8]) -> Vec<u8> {
    assert_eq!(&glb[..4], b"glTF");
    let json_len = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
    let json: serde_json::Value = serde_json::from_slice(&glb[20..20 + json_len]).unwrap();
    let bin = &glb[20 + json_len + 8..];
    let view = &json["bufferViews"][json["images"][0]["bufferView"].as_u64().unwrap() as usize];
    let (off, len) = (view["byteOffset"].as_u64().unwrap_or(0) as usize, view["byteLength"].as_u64().unwrap() as usize);
    bin[off..off + len].to_vec()
}

#[test]
fn invert_a_dataset_image_writes_a_reloadable_avatar() {
    let root = tmp("invert");
    let (scans, data, out) = (root.join("scans"), root.join("data"), root.join("inv"));
    let ok = |o: std::process::Output| {
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        o
    };
    ok(trainer(&["synth-scans", "--out", s(&scans), "--count", "1", "--seed", "1", "--texture-size", "128"]));
    ok(trainer(&["prepare", "--scans", s(&scans), "--out", s(&data), "--views", "2", "--res", "64"]));
    let base = ["invert", "--config", "tiny", "--random-weights", "--data", s(&data)];
    let o = ok(trainer(
        &[
            &base[..],
            &["--entry", "0000/000.png", "--scans", s(&scans), "--steps", "4", "--pti-steps", "2"],
            &["--texture-res", "64", "--out", s(&out)],
        ]
        .concat(),
    ));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("mask IoU"), "{stdout}");
    for f in [
        "input.png",
        "input_view.png",
        "input_view_w.png",
        "input_view_projected.png",
        "comparison.png",
        "back_view.png",
        "back_view_truth.png",
        "back_view_truth_rgb.png",
        "pose_walking.png",
        "pose_arms_up.png",
        "pose_sitting.png",
        "avatar.glb",
        "inverted.safetensors",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    // The input view is RGBA at the input's resolution; the comparison is three panels.
    assert_eq!(png_size(&out.join("input_view.png")), (64, 64, png::ColorType::Rgba));
    assert_eq!(png_size(&out.join("comparison.png")).0, 192);
    let steps = std::fs::read_to_string(out.join("steps.jsonl")).unwrap();
    let lines: Vec<serde_json::Value> = steps.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(lines.len(), 6);
    assert_eq!(lines.iter().filter(|l| l["phase"] == "latent").count(), 4);
    assert_eq!(lines.iter().filter(|l| l["phase"] == "pivotal").count(), 2);
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap();
    let iou = m["after_pti"]["mask_iou"].as_f64().unwrap();
    assert!((0.3..=1.0).contains(&iou), "{m}");
    let back = m["back_view_iou"].as_f64().unwrap();
    assert!((0.3..=1.0).contains(&back), "{m}");
    // The back's colours against the scan's: a finite PSNR in a plausible range.
    let back_psnr = m["back_view_psnr_db"].as_f64().unwrap();
    assert!(back_psnr > 5.0 && back_psnr < 60.0, "{m}");
    assert!(m["after_w"]["psnr_db"].as_f64().unwrap() > 5.0);
    assert_eq!(m["perceptual"], false);
    // The photo projected onto the exported avatar brings it closer to the photo.
    let (baked, projected) = (m["baked"]["psnr_db"].as_f64().unwrap(), m["projected"]["psnr_db"].as_f64().unwrap());
    assert!(projected > baked, "projection: {baked} → {projected} dB");
    // The final IoU is the input view's own: recompute it from the PNGs (alpha vs mask).
    let read_alpha = |p: &std::path::Path| -> Vec<f32> {
        let d = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(p).unwrap()));
        let mut r = d.read_info().unwrap();
        let mut buf = vec![0; r.output_buffer_size()];
        r.next_frame(&mut buf).unwrap();
        buf.chunks_exact(4).map(|c| c[3] as f32 / 255.0).collect()
    };
    let (a, b) = (read_alpha(&out.join("input_view.png")), read_alpha(&out.join("input.png")));
    let (mut i, mut u) = (0, 0);
    for (x, y) in a.iter().zip(&b) {
        i += (*x >= 0.5 && *y >= 0.5) as usize;
        u += (*x >= 0.5 || *y >= 0.5) as usize;
    }
    assert!((i as f64 / u as f64 - iou).abs() < 0.02, "IoU from PNGs {} vs metrics {iou}", i as f64 / u as f64);
    // The .glb is a skinned, animated glTF.
    let glb = std::fs::read(out.join("avatar.glb")).unwrap();
    assert_eq!(&glb[..4], b"glTF");
    let json_len = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
    let json: serde_json::Value = serde_json::from_slice(&glb[20..20 + json_len]).unwrap();
    assert_eq!(json["skins"][0]["joints"].as_array().unwrap().len(), 24);
    assert_eq!(json["animations"][0]["name"], "walk");
    assert_eq!(json["images"].as_array().unwrap().len(), 1);
    // `sample --inverted` reloads the tuned generator and codes.
    let smp = root.join("sample");
    ok(trainer(&["sample", "--config", "tiny", "--inverted", s(&out), "--res", "64", "--out", s(&smp)]));
    assert!(smp.join("rgb.png").is_file());
    let o = trainer(&["sample", "--config", "demo", "--inverted", s(&out), "--out", s(&smp)]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("tiny"), "{}", String::from_utf8_lossy(&o.stderr));
    // `export --inverted` reloads it with the photo it was made from: shown in the photo's
    // pose by default, its texture is the one `invert` baked (the photo projected again),
    // byte for byte; without the projection it is another image.
    let (exp, plain) = (root.join("exported.glb"), root.join("plain.glb"));
    let args = ["export", "--config", "tiny", "--inverted", s(&out), "--texture-res", "64"];
    let o = ok(trainer(&[&args[..], &["--motion", "walk", "--out", s(&exp)]].concat()));
    assert!(String::from_utf8_lossy(&o.stdout).contains("inverted avatar"), "{}", String::from_utf8_lossy(&o.stdout));
    ok(trainer(&[&args[..], &["--no-projection", "--out", s(&plain)]].concat()));
    let image = |p: &std::path::Path| glb_image(&std::fs::read(p).unwrap());
    let invert_tex = image(&out.join("avatar.glb"));
    assert_eq!(&invert_tex[..4], b"\x89PNG");
    assert!(image(&exp) == invert_tex, "export --inverted baked another texture than invert");
    assert!(image(&plain) != invert_tex, "--no-projection changed nothing");
    let o = trainer(&["export", "--config", "tiny", "--inverted", s(&root.join("nowhere")), "--out", s(&plain)]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("nowhere") && !e.contains("panicked"), "{e}");

    // Bad input, each refused with its reason.
    let err = |args: &[&str]| {
        let o = trainer(args);
        assert!(!o.status.success(), "{args:?} succeeded");
        String::from_utf8_lossy(&o.stderr).into_owned()
    };
    let e = err(&[&base[..], &["--entry", "9999/000.png", "--out", s(&out)]].concat());
    assert!(e.contains("no entry `9999/000.png`") && e.contains("0000/000.png"), "{e}");
    let e = err(&[&base[..], &["--entry", "0000/000.png", "--options", "{\"stepz\": 3}", "--out", s(&out)]].concat());
    assert!(e.contains("unknown field `stepz`"), "{e}");
    let e = err(&[&base[..], &["--entry", "0000/000.png", "--preset", "slow", "--out", s(&out)]].concat());
    assert!(e.contains("unknown --preset"), "{e}");
    let photo = data.join("0000/000.png");
    let e = err(&["invert", "--image", s(&photo), "--out", s(&out)]);
    assert!(e.contains("--fit"), "{e}");
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn a_trained_discriminator_resumes_and_gives_the_inversion_its_perceptual_term() {
    let root = tmp("invert-d");
    let (scans, data, d, out) = (root.join("scans"), root.join("data"), root.join("d"), root.join("inv"));
    let ok = |o: std::process::Output| {
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        o
    };
    ok(trainer(&["synth-scans", "--out", s(&scans), "--count", "1", "--seed", "2", "--texture-size", "128"]));
    ok(trainer(&["prepare", "--scans", s(&scans), "--out", s(&data), "--views", "2", "--res", "32"]));
    let train = |steps: &str| {
        ok(trainer(&[
            "train-discriminator",
            "--config",
            "tiny",
            "--random-weights",
            "--data",
            s(&data),
            "--out",
            s(&d),
            "--steps",
            steps,
            "--batch",
            "2",
            "--snapshot-every",
            "2",
        ]))
    };
    train("3");
    let log = std::fs::read_to_string(d.join("metrics.jsonl")).unwrap();
    assert_eq!(log.lines().count(), 3);
    // Lazy R1 on the first step (every 16), not on the second.
    let l: Vec<serde_json::Value> = log.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert!(l[0]["r1"].as_f64().unwrap() >= 0.0 && l[1]["r1"].is_null(), "{log}");
    let o = train("4");
    assert!(String::from_utf8_lossy(&o.stderr).contains("resuming from"), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(std::fs::read_to_string(d.join("metrics.jsonl")).unwrap().lines().count(), 4);
    let invert = ["invert", "--config", "tiny", "--random-weights", "--data", s(&data), "--entry", "0000/000.png"];
    let quick = ["--steps", "2", "--pti-steps", "1", "--texture-res", "64", "--out", s(&out)];
    let d_file = d.join("discriminator.safetensors");
    ok(trainer(&[&invert[..], &quick, &["--discriminator", s(&d_file)]].concat()));
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(m["perceptual"], true);
    let steps = std::fs::read_to_string(out.join("steps.jsonl")).unwrap();
    let first: serde_json::Value = serde_json::from_str(steps.lines().next().unwrap()).unwrap();
    assert!(first["terms"]["perceptual"].as_f64().unwrap() > 0.0, "{first}");
    // Not a discriminator: refused with the reason.
    let o = trainer(&[&invert[..], &quick, &["--discriminator", s(&out.join("inverted.safetensors"))]].concat());
    assert!(!o.status.success());
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("neither a training state nor a discriminator"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let _ = std::fs::remove_dir_all(&root);
}

/// `--pck`: the photo's detection against the detector's reading of the avatar rendered at the
/// photo's camera, in the photo's pixels. A stand-in detector (`GETAVATAR_MEDIAPIPE`) answers
/// with the photo's own landmarks moved into the render's crop (PCK 1: the crop → photo map
/// is right), then with no person (PCK 0, said).
#[test]
fn pck_compares_the_renders_detection_with_the_photos_in_photo_pixels() {
    use getavatar_core::body::body_fit::fit::BodyFit;
    use getavatar_core::body::body_fit::synthetic::{detect, unseen_poses, UNSEEN_POSE_CAMERAS};
    use getavatar_core::io::dataset::encode_png;
    use getavatar_core::util::rng::Rng;
    use getavatar_core::BodyModel;
    use std::os::unix::fs::PermissionsExt;

    let root = tmp("invert-pck");
    let model = BodyModel::default_body().unwrap();
    let (_, truth) = unseen_poses().into_iter().next().unwrap();
    let size = 256;
    let det =
        detect(&model, &truth, UNSEEN_POSE_CAMERAS[0].camera().world_to_camera(), size, 0.0, 0.0, &mut Rng::new(1, 1))
            .unwrap();
    let photo: Vec<u8> = det.mask.iter().flat_map(|m| if *m > 0.5 { [200, 160, 140] } else { [60, 60, 70] }).collect();
    let mask: Vec<u8> = det.mask.iter().map(|m| if *m > 0.5 { 255 } else { 0 }).collect();
    let (photo_p, mask_p, kp_p, fit_p) =
        (root.join("photo.png"), root.join("mask.png"), root.join("kp.json"), root.join("fit.json"));
    std::fs::write(&photo_p, encode_png(size, size, 3, &photo).unwrap()).unwrap();
    std::fs::write(&mask_p, encode_png(size, size, 1, &mask).unwrap()).unwrap();
    std::fs::write(&kp_p, serde_json::to_string(&det.result).unwrap()).unwrap();
    let fit = ["fit-pose", "--image", s(&photo_p), "--keypoints", s(&kp_p), "--mask", s(&mask_p)];
    let o = trainer(&[&fit[..], &["--iterations", "10", "10", "0", "--out", s(&fit_p)]].concat());
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let framing = BodyFit::from_json(&std::fs::read_to_string(&fit_p).unwrap()).unwrap().framing;

    // The photo's landmarks in the render's crop (normalised), as the stand-in's answer.
    let mut in_crop = det.result.clone();
    in_crop.segmentation_mask = None;
    for l in in_crop.pose_landmarks.iter_mut() {
        let ndc = framing.to_ndc([l.x * size as f32, l.y * size as f32]);
        (l.x, l.y) = ((ndc[0] + 1.0) / 2.0, (1.0 - ndc[1]) / 2.0);
    }
    let answer = root.join("answer.kp.json");
    std::fs::write(&answer, serde_json::to_string(&in_crop).unwrap()).unwrap();
    let stand_in = |name: &str, body: &str| {
        let p = root.join(name);
        std::fs::write(&p, format!("#!/bin/sh\n{body}\n")).unwrap();
        std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o755)).unwrap();
        p
    };
    let reads =
        stand_in("reads.sh", &format!("test -f \"$1/render.png\" && cp '{}' \"$1/render.kp.json\"", s(&answer)));
    let blind = stand_in("blind.sh", "echo \"render.png: no person found in the photo\" >&2; exit 1");
    let run = |detector: &std::path::Path, out: &std::path::Path| {
        let args = ["invert", "--config", "tiny", "--image", s(&photo_p), "--fit", s(&fit_p), "--mask", s(&mask_p)];
        let more = ["--keypoints", s(&kp_p), "--pck", "--preset", "instant", "--res", "32", "--texture-res", "64"];
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_trainer"))
            .args(args)
            .args(more)
            .args(["--out", s(out)])
            .env("GETAVATAR_MEDIAPIPE", detector)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let m: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap();
        assert_eq!(png_size(&out.join("pck/render.png")), (512, 512, png::ColorType::Rgb));
        // The first avatar (the guess rigged, on the body as first fitted) comes before the
        // body's refit on its outline, which `instant` runs on a photo.
        let first = m["seconds_to_first_avatar"].as_f64().unwrap();
        let refit = m["refit"]["seconds"].as_f64().unwrap_or(0.0);
        assert!(first > 0.0 && first + refit <= m["seconds_total"].as_f64().unwrap(), "{m}");
        assert!(out.join("input_view_first.png").is_file());
        m["pck"].clone()
    };
    let seen = det.result.pose_landmarks.iter().filter(|l| l.visibility >= 0.5).count() as u64;
    let p = run(&reads, &root.join("reads"));
    assert_eq!(
        (p["pck_0_1"].as_f64(), p["compared"].as_u64(), p["render_detected"].as_bool()),
        (Some(1.0), Some(seen), Some(true)),
        "{p}"
    );
    let t = p["threshold_px"].as_f64().unwrap();
    assert!(t > 10.0 && t < 0.1 * size as f64 * 1.5, "0.1 × the person's size in a {size}² photo: {t}");
    let p = run(&blind, &root.join("blind"));
    assert_eq!((p["pck_0_1"].as_f64(), p["render_detected"].as_bool()), (Some(0.0), Some(false)), "{p}");
    let _ = std::fs::remove_dir_all(&root);
}
