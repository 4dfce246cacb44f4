//! `trainer train-encoder` and the encoder's use by `trainer invert` (tiny generator, a few
//! pairs and steps): resuming is bit-identical to not stopping; `invert --preset instant`
//! starts from the encoder and optimises nothing; an unusable encoder file is reported once
//! and the latent-mode search starts the inversion instead; `garment-codes` adds an
//! inversion's geometry codes to an encoder file, which invert then weighs.
#![allow(clippy::unwrap_used, clippy::expect_used)] // a test fails by panicking

mod common;

use common::{s, tmp, trainer};
use std::path::Path;

fn ok(o: std::process::Output) -> std::process::Output {
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    o
}

fn train_encoder(out: &Path, steps: u64) -> std::process::Output {
    train_encoder_with(out, steps, &[])
}

fn train_encoder_with(out: &Path, steps: u64, extra: &[&str]) -> std::process::Output {
    let steps = steps.to_string();
    let base = [
        "train-encoder",
        "--config",
        "tiny",
        "--random-weights",
        "--pairs",
        "8",
        "--batch",
        "2",
        "--snapshot-every",
        "1",
        "--steps",
        &steps,
        "--out",
        s(out),
    ];
    trainer(&[&base[..], extra].concat())
}

fn log_lines(dir: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(dir.join("log.jsonl")).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}

fn metrics(dir: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(dir.join("metrics.json")).unwrap()).unwrap()
}

/// `encoder_best.safetensors` in `dir` records (safetensors metadata) the lowest `key` of the log.
fn assert_best_is_lowest(dir: &Path, log: &[serde_json::Value], key: &str) {
    let lowest = log.iter().map(|l| l[key].as_f64().unwrap()).fold(f64::INFINITY, f64::min);
    let best = std::fs::read(dir.join("encoder_best.safetensors")).unwrap();
    let n = u64::from_le_bytes(best[..8].try_into().unwrap()) as usize;
    let header: serde_json::Value = serde_json::from_slice(&best[8..8 + n]).unwrap();
    let kept: f64 = header["__metadata__"][key].as_str().unwrap().parse().unwrap();
    assert_eq!(kept, lowest, "{header}");
}

#[test]
fn train_encoder_resumes_bit_identically_and_invert_starts_from_it() {
    let root = tmp("encoder");
    let (a, b) = (root.join("a"), root.join("b"));
    // 8 pairs: 2 shards of 4, the second held out.
    ok(train_encoder(&a, 2));
    for f in ["pairs/shard_0000.bin", "pairs/shard_0001.safetensors", "encoder.safetensors", "state.safetensors"] {
        assert!(a.join(f).is_file(), "{f} missing");
    }
    assert!(a.join("snapshots/step_000002.png").is_file());
    let log = log_lines(&a);
    assert_eq!(log.len(), 2);
    // The untrained head answers w_avg: the first figures are near w_avg's, and finite.
    for l in &log {
        let (e, e0) = (l["held_out_mse"].as_f64().unwrap(), l["held_out_mse_w_avg"].as_f64().unwrap());
        assert!(e.is_finite() && e0 > 0.0 && e < 10.0 * e0, "{l}");
    }
    // The best snapshot by held-out error is kept beside the latest, its error in the metadata.
    assert_best_is_lowest(&a, &log, "held_out_mse");
    // 1 step, stop, rerun to 2 steps == 2 steps at once (the pairs are rendered again in
    // the other directory: rendering is deterministic too).
    ok(train_encoder(&b, 1));
    let o = ok(train_encoder(&b, 2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("resuming"), "{}", String::from_utf8_lossy(&o.stderr));
    for f in [
        "pairs/shard_0000.bin",
        "pairs/shard_0001.safetensors",
        "encoder.safetensors",
        "encoder_best.safetensors",
        "state.safetensors",
    ] {
        assert!(std::fs::read(a.join(f)).unwrap() == std::fs::read(b.join(f)).unwrap(), "{f} differs after resuming");
    }

    // `invert --preset instant` from this encoder: one generation at the start, no steps.
    let (scans, data, inv) = (root.join("scans"), root.join("data"), root.join("inv"));
    ok(trainer(&["synth-scans", "--out", s(&scans), "--count", "1", "--seed", "1", "--texture-size", "128"]));
    ok(trainer(&["prepare", "--scans", s(&scans), "--out", s(&data), "--views", "1", "--res", "64"]));
    let base = ["invert", "--config", "tiny", "--random-weights", "--data", s(&data), "--entry", "0000/000.png"];
    let quick = ["--preset", "instant", "--texture-res", "64"];
    let enc = a.join("encoder.safetensors");
    let o = ok(trainer(&[&base[..], &quick[..], &["--encoder", s(&enc), "--out", s(&inv)]].concat()));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("start: encoder"), "{err}");
    let m = metrics(&inv);
    assert_eq!(m["start"], "encoder");
    assert_eq!(m["options"]["steps"], 0);
    assert!(m["after_pti"].is_null(), "{m}");
    // With no optimisation the W+ result is the start.
    assert_eq!(m["after_w"], m["at_start"]);
    let iou = m["at_start"]["mask_iou"].as_f64().unwrap();
    assert!((0.2..=1.0).contains(&iou), "{m}");
    let t = m["seconds_to_first_avatar"].as_f64().unwrap();
    assert!(t > 0.0 && t <= m["seconds_total"].as_f64().unwrap(), "{m}");
    // The first avatar is the guess rigged and re-posed, drawn before the start's exact
    // per-pose render; `instant` exports it with its outline moved onto the photo's person
    // (`silhouette_snap`), which overlaps the person at least as well.
    let iou = |m: &serde_json::Value, k: &str| m[k]["mask_iou"].as_f64().unwrap();
    assert!(iou(&m, "baked") >= iou(&m, "first_avatar") - 1e-3, "{m}");
    let stages: Vec<&str> =
        m["first_avatar_stages"].as_array().unwrap().iter().map(|s| s["stage"].as_str().unwrap()).collect();
    assert!(stages.contains(&"synthesis") && stages.last() == Some(&"render"), "{stages:?}");
    // Without the projection the outline is left as generated: the export is the first avatar.
    let plain = root.join("inv_plain");
    ok(trainer(&[&base[..], &quick[..], &["--encoder", s(&enc), "--no-projection", "--out", s(&plain)]].concat()));
    let p = metrics(&plain);
    assert!((iou(&p, "first_avatar") - iou(&p, "baked")).abs() < 1e-6, "{p}");
    let steps = std::fs::read_to_string(inv.join("steps.jsonl")).unwrap();
    assert_eq!(steps.lines().count(), 0, "instant optimises nothing");
    for f in ["input_view_first.png", "input_view_start.png", "input_view.png", "avatar.glb", "inverted.safetensors"] {
        assert!(inv.join(f).is_file(), "{f} missing");
    }

    // An unusable encoder file: one message naming it, and the latent-mode search instead.
    let bad = root.join("bad.safetensors");
    std::fs::write(&bad, b"not an encoder").unwrap();
    let inv2 = root.join("inv2");
    let o = ok(trainer(&[&base[..], &quick[..], &["--encoder", s(&bad), "--out", s(&inv2)]].concat()));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("bad.safetensors") && err.contains("cannot be used") && err.contains("latent-mode search"),
        "{err}"
    );
    assert_eq!(err.matches("cannot be used").count(), 1, "{err}");
    assert_ne!(metrics(&inv2)["start"], "encoder");

    // Garment codes: the instant inversion's geometry codes added to the encoder file; invert
    // weighs them after the guess (none when the guess's outline already fits the person).
    // The code is the guess's own geometry here, so it explains nothing better: the guess stays.
    let with = root.join("with_garments.safetensors");
    let o = ok(trainer(&["garment-codes", "--encoder", s(&enc), "--from", s(&inv), "--out", s(&with)]));
    assert!(
        String::from_utf8_lossy(&o.stdout).contains("with 1 garment codes"),
        "{}",
        String::from_utf8_lossy(&o.stdout)
    );
    let inv3 = root.join("inv3");
    ok(trainer(&[&base[..], &quick[..], &["--encoder", s(&with), "--out", s(&inv3)]].concat()));
    let m = metrics(&inv3);
    let cands = m["garments"]["candidates"].as_array().unwrap();
    assert_eq!(cands[0]["name"], "guess", "{m}");
    assert!(cands.len() == 1 || (cands.len() == 2 && cands[1]["name"] == "inv"), "{m}");
    assert!(m["garments"]["chosen"].is_null(), "{m}");
    assert_eq!(m["at_start"], metrics(&inv)["at_start"], "the guess stays as it was");
    // `{"garments":false}`: nothing weighed.
    let inv4 = root.join("inv4");
    let off = ["--options", r#"{"garments":false}"#, "--encoder", s(&with), "--out", s(&inv4)];
    ok(trainer(&[&base[..], &quick[..], &off[..]].concat()));
    assert!(metrics(&inv4).get("garments").is_none());
    // Bad input: one clear error each.
    let x = root.join("x.safetensors");
    let o = trainer(&["garment-codes", "--encoder", s(&bad), "--from", s(&inv), "--out", s(&x)]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("bad.safetensors"), "{err}");
    let nowhere = root.join("nowhere");
    let o = trainer(&["garment-codes", "--encoder", s(&enc), "--from", s(&nowhere), "--out", s(&x)]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("nowhere"), "{err}");
    assert!(!x.exists());
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn render_parts_make_the_pairs_one_process_makes_and_init_starts_from_given_weights() {
    let root = tmp("encoder_parts");
    let (one, parts, further) = (root.join("one"), root.join("parts"), root.join("further"));
    // 0/1 is every shard, as a single process renders them; 0/2 then 1/2 render half each.
    ok(train_encoder_with(&one, 1, &["--render-part", "0/1"]));
    ok(train_encoder_with(&parts, 1, &["--render-part", "0/2"]));
    assert!(parts.join("pairs/shard_0000.safetensors").is_file());
    assert!(!parts.join("pairs/shard_0001.safetensors").exists(), "part 0/2 rendered shard 1");
    assert!(!parts.join("state.safetensors").exists(), "a render part trained");
    ok(train_encoder_with(&parts, 1, &["--render-part", "1/2"]));
    for f in
        ["pairs/shard_0000.bin", "pairs/shard_0000.safetensors", "pairs/shard_0001.bin", "pairs/shard_0001.safetensors"]
    {
        assert!(std::fs::read(one.join(f)).unwrap() == std::fs::read(parts.join(f)).unwrap(), "{f} differs");
    }
    // Train one step on the parts' pairs; a new run started from those weights logs, as its
    // step 0, exactly the held-out error they had.
    ok(train_encoder(&parts, 1));
    let trained = log_lines(&parts)[0]["held_out_mse"].as_f64().unwrap();
    std::fs::create_dir_all(&further).unwrap();
    std::fs::rename(one.join("pairs"), further.join("pairs")).unwrap();
    let init = parts.join("encoder.safetensors");
    let o = ok(train_encoder_with(&further, 1, &["--init", s(&init)]));
    assert!(String::from_utf8_lossy(&o.stderr).contains("starting from the weights"));
    let log = log_lines(&further);
    assert_eq!((log[0]["step"].as_u64(), log[0]["held_out_mse"].as_f64()), (Some(0), Some(trained)), "{log:?}");
    assert_eq!(log[1]["step"], 1);
    // Bad input: one clear error each.
    let o = train_encoder_with(&root.join("x"), 1, &["--render-part", "2/2"]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("0 <= K < N"));
    let bad = root.join("bad.safetensors");
    std::fs::write(&bad, b"not an encoder").unwrap();
    std::fs::remove_file(further.join("state.safetensors")).unwrap();
    let o = train_encoder_with(&further, 2, &["--init", s(&bad)]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("bad.safetensors"));
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn the_image_term_on_scans_chooses_the_kept_encoder_and_resumes_bit_identically() {
    let root = tmp("encoder_image");
    let (scans, data) = (root.join("scans"), root.join("data"));
    ok(trainer(&["synth-scans", "--out", s(&scans), "--count", "8", "--seed", "3", "--texture-size", "128"]));
    ok(trainer(&["prepare", "--scans", s(&scans), "--out", s(&data), "--views", "2", "--res", "64"]));
    let (a, b) = (root.join("a"), root.join("b"));
    let with = ["--image-data", s(&data)];
    let o = ok(train_encoder_with(&a, 3, &with));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("6 training and 2 held-out subjects"), "{err}");
    let log = log_lines(&a);
    assert_eq!(log.len(), 3);
    for l in &log {
        let (img, iou) = (l["held_out_image"].as_f64().unwrap(), l["held_out_iou"].as_f64().unwrap());
        assert!(img.is_finite() && img > 0.0 && (0.0..=1.0).contains(&iou), "{l}");
        assert!(l["train_image"].as_f64().unwrap().is_finite(), "{l}");
    }
    // With scans the kept encoder is the one with the lowest held-out image loss.
    assert_best_is_lowest(&a, &log, "held_out_image");
    // 2 steps, stop, rerun to 3 == 3 at once.
    ok(train_encoder_with(&b, 2, &with));
    ok(train_encoder_with(&b, 3, &with));
    for f in ["encoder.safetensors", "encoder_best.safetensors", "state.safetensors"] {
        assert!(std::fs::read(a.join(f)).unwrap() == std::fs::read(b.join(f)).unwrap(), "{f} differs after resuming");
    }
    let figures = |d: &Path| -> Vec<serde_json::Value> {
        let mut log = log_lines(d);
        log.iter_mut().for_each(|l| l.as_object_mut().unwrap().retain(|k, _| k != "seconds_per_step"));
        log
    };
    assert_eq!(figures(&a), figures(&b), "the figures differ after resuming");
    // A folder that is not a dataset: one error naming it.
    let o = train_encoder_with(&root.join("c"), 1, &["--image-data", s(&scans)]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("--image-data") && err.contains("dataset.json"), "{err}");
    for w in ["--image-weight=-1", "--image-weight=nan"] {
        let o = train_encoder_with(&root.join("d"), 1, &["--image-data", s(&data), w]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && err.contains("--image-weight must be"), "{w}: {err}");
    }
    let _ = std::fs::remove_dir_all(&root);
}
