//! `trainer train` end to end on a tiny synthetic dataset: steps run and write checkpoints,
//! sample grids and metrics; resuming is bit-identical to not stopping; a SIGKILL at any moment
//! leaves a loadable checkpoint; transfer learning onto RGB-only data turns the normal
//! discriminator off.

#![allow(clippy::unwrap_used, clippy::expect_used)] // a test fails by panicking

use std::path::{Path, PathBuf};
use std::process::Command;

use getavatar_core::generator::checkpoint::{parse_safetensors, write_safetensors};

mod common;
use common::trainer;

fn ok(o: std::process::Output) -> String {
    assert!(o.status.success(), "{}\n{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// 2 synthetic subjects × 4 views at 16² (shared by the tests of this file).
fn dataset(root: &Path) -> PathBuf {
    let scans = root.join("scans");
    let data = root.join("data");
    ok(trainer(&["synth-scans", "--out", scans.to_str().unwrap(), "--count", "2", "--texture-size", "128"]));
    ok(trainer(&[
        "prepare",
        "--scans",
        scans.to_str().unwrap(),
        "--out",
        data.to_str().unwrap(),
        "--views",
        "4",
        "--res",
        "16",
    ]));
    data
}

/// `trainer eval` of the tiny config on 4 labels of `data`, with `extra` arguments.
fn eval(data: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec!["eval", "--data", data.to_str().unwrap(), "--config", "tiny", "--count", "4"];
    args.extend_from_slice(extra);
    trainer(&args)
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("getavatar-train-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A tiny training run (batch 2, a snapshot every step unless `extra` says otherwise).
fn train_output(data: &Path, out: &Path, steps: u64, extra: &[&str]) -> std::process::Output {
    let s = steps.to_string();
    let args = [
        "train",
        "--data",
        data.to_str().unwrap(),
        "--config",
        "tiny",
        "--out",
        out.to_str().unwrap(),
        "--batch",
        "2",
        "--steps",
        &s,
    ];
    let snapshot: &[&str] = if extra.contains(&"--snapshot-every") { &[] } else { &["--snapshot-every", "1"] };
    trainer(&[&args[..], snapshot, extra].concat())
}

fn train(data: &Path, out: &Path, steps: u64, extra: &[&str]) -> String {
    ok(train_output(data, out, steps, extra))
}

/// Each of `files` is byte-identical in folders `a` and `b` (`what` says why it should be).
fn same_files(a: &Path, b: &Path, files: &[&str], what: &str) {
    for f in files {
        assert_eq!(std::fs::read(a.join(f)).unwrap(), std::fs::read(b.join(f)).unwrap(), "{f}: {what}");
    }
}

#[test]
fn resume_is_bit_identical_and_outputs_are_complete() {
    let root = tmp("resume");
    let data = dataset(&root);
    let (a, b) = (root.join("a"), root.join("b"));
    train(&data, &a, 2, &[]);
    train(&data, &b, 1, &[]);
    let text = train(&data, &b, 2, &["--resume"]);
    assert!(text.contains("trained 1 steps"), "{text}");
    let ga = std::fs::read(a.join("generator.safetensors")).unwrap();
    let gb = std::fs::read(b.join("generator.safetensors")).unwrap();
    assert_eq!(ga, gb, "2 steps == 1 step + checkpoint + resume + 1 step");
    assert_eq!(
        std::fs::read(a.join("state.safetensors")).unwrap(),
        std::fs::read(b.join("state.safetensors")).unwrap()
    );
    // Outputs: metrics per step, sample grids, a loadable generator for `trainer sample`.
    let metrics = std::fs::read_to_string(a.join("metrics.jsonl")).unwrap();
    assert_eq!(metrics.lines().count(), 2);
    let first: serde_json::Value = serde_json::from_str(metrics.lines().next().unwrap()).unwrap();
    assert!(first["loss_g"].as_f64().unwrap().is_finite() && first["r1"].as_f64().is_some(), "{first}");
    assert!(a.join("samples_000002.png").is_file());
    let out = root.join("sample");
    let g = a.join("generator.safetensors");
    let sample = |extra: &[&str]| {
        let mut args = vec!["sample", "--config", "tiny", "--checkpoint", g.to_str().unwrap(), "--res", "64"];
        args.extend_from_slice(extra);
        args.extend_from_slice(&["--out", out.to_str().unwrap()]);
        trainer(&args)
    };
    let triangles = |text: &str| -> usize {
        let at = text.find(" triangles").unwrap_or_else(|| panic!("no triangle count: {text}"));
        text[..at]
            .rsplit(' ')
            .next()
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("no triangle count: {text}"))
    };
    let own = triangles(&ok(sample(&[])));
    assert!(out.join("rgb.png").is_file());
    // `--tet-res` extracts the same generator on another grid: a coarser grid, fewer
    // triangles; a grid beyond the cap is refused with the flag named.
    let coarse = triangles(&ok(sample(&["--tet-res", "12"])));
    assert!(0 < coarse && coarse < own, "{coarse} triangles on 12³, {own} on the config's 24³");
    let o = sample(&["--tet-res", "500"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("--tet-res 500") && err.contains("at most 192"), "{err}");
    // A fresh run never overwrites an existing one.
    let o = trainer(&["train", "--data", data.to_str().unwrap(), "--config", "tiny", "--out", a.to_str().unwrap()]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("--resume"));
    // A corrupt latest checkpoint: resume says so and continues from the previous one (step
    // 1 here), bit-identically: a's 1 → 3 equals b's 2 → 3.
    assert!(a.join("state.prev.safetensors").is_file(), "the checkpoint before the last is kept");
    let cut = std::fs::read(a.join("state.safetensors")).unwrap();
    std::fs::write(a.join("state.safetensors"), &cut[..cut.len() / 2]).unwrap();
    let o = train_output(&data, &a, 3, &["--resume"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success() && err.contains("resuming from the previous one") && err.contains("(step 1)"), "{err}");
    train(&data, &b, 3, &["--resume"]);
    assert_eq!(
        std::fs::read(a.join("state.safetensors")).unwrap(),
        std::fs::read(b.join("state.safetensors")).unwrap(),
        "1 + 2 steps after the fallback == 2 + 1 steps"
    );
    let _ = std::fs::remove_dir_all(&root);
}

/// A named config (`--cfg`) with a schedule equals the same flags run step by step with
/// `run.json` edited by hand between the parts, byte for byte; its run.json keeps the schedule.
#[test]
fn a_named_config_with_a_schedule_equals_stopping_and_editing_run_json() {
    let root = tmp("cfg");
    let data = dataset(&root);
    let (a, b) = (root.join("a"), root.join("b"));
    let cfg = root.join("c.toml");
    std::fs::write(
        &cfg,
        format!(
            "[train]\ndata = {:?}\nconfig = \"tiny\"\nbatch = 2\nsteps = 3\nsnapshot_every = 1\n\n\
             [[schedule]]\nafter_step = 1\nset = {{ lr_g = 0.001 }}\n\n\
             [[schedule]]\nafter_step = 2\nset = {{ ema_kimg = 0.05, generator = {{ tet_res = 20 }} }}\n",
            data.to_str().unwrap()
        ),
    )
    .unwrap();
    let text = ok(trainer(&["train", "--cfg", cfg.to_str().unwrap(), "--out", a.to_str().unwrap()]));
    assert_eq!(text.matches("the schedule changes the run's settings").count(), 2, "{text}");
    let run: serde_json::Value = serde_json::from_slice(&std::fs::read(a.join("run.json")).unwrap()).unwrap();
    assert_eq!(run["schedule"].as_array().map(Vec::len), Some(2), "{run}");

    let edit = |f: &dyn Fn(&mut serde_json::Value)| {
        let mut run: serde_json::Value = serde_json::from_slice(&std::fs::read(b.join("run.json")).unwrap()).unwrap();
        f(&mut run);
        std::fs::write(b.join("run.json"), serde_json::to_string_pretty(&run).unwrap()).unwrap();
    };
    train(&data, &b, 1, &[]);
    edit(&|r| r["lr_g"] = serde_json::json!(0.001));
    train(&data, &b, 2, &["--resume"]);
    edit(&|r| {
        r["ema_kimg"] = serde_json::json!(0.05);
        r["generator"]["tet_res"] = serde_json::json!(20);
    });
    train(&data, &b, 3, &["--resume"]);
    same_files(&a, &b, &["generator.safetensors"], "the schedule == stop, edit run.json, resume");
    let losses = |d: &Path| -> Vec<String> {
        let text = std::fs::read_to_string(d.join("metrics.jsonl")).unwrap();
        text.lines().map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["loss_g"].to_string()).collect()
    };
    assert_eq!(losses(&a), losses(&b), "the same G loss at each of the 3 steps");

    // A flag on the command line wins over the file's; a schedule that names a field run.json
    // lacks is refused before any step.
    let c = root.join("c");
    ok(trainer(&["train", "--cfg", cfg.to_str().unwrap(), "--out", c.to_str().unwrap(), "--steps", "1"]));
    assert_eq!(std::fs::read_to_string(c.join("metrics.jsonl")).unwrap().lines().count(), 1);
    std::fs::write(&cfg, "[train]\nconfig = \"tiny\"\n[[schedule]]\nafter_step = 1\nset = { lr_gg = 1 }\n").unwrap();
    refused(&data, &["--cfg", cfg.to_str().unwrap()], &root.join("d"), "no field `lr_gg`");
    let _ = std::fs::remove_dir_all(&root);
}

/// The `tiny` config trains 20 steps (R1 on steps 1 and 17): every step logged with finite
/// losses, the generated avatars keep their surface, and the result samples.
#[test]
fn tiny_trains_twenty_steps() {
    let root = tmp("twenty");
    let data = dataset(&root);
    let run = root.join("run");
    let text = train(&data, &run, 20, &["--snapshot-every", "10"]);
    assert!(text.contains("trained 20 steps"), "{text}");
    let metrics = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    let rows: Vec<serde_json::Value> = metrics.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(rows.len(), 20);
    for r in &rows {
        for k in ["loss_g", "loss_d", "eikonal", "cross_entropy"] {
            assert!(r[k].as_f64().is_some_and(f64::is_finite), "{k} in {r}");
        }
        assert!(r["triangles"].as_f64().unwrap() > 0.0, "a surface every step: {r}");
    }
    assert_eq!(rows.iter().filter(|r| r["r1"].as_f64().is_some()).count(), 2, "lazy R1 every 16 steps");
    assert!(run.join("samples_000010.png").is_file() && run.join("samples_000020.png").is_file());
    // `trainer eval` on the trained generator: figures in range; the data's own masks line up
    // with the posed bodies of their labels (the silhouette check itself is sound).
    let report = root.join("eval.json");
    let gen = run.join("generator.safetensors");
    let (gen_s, report_s) = (gen.to_str().unwrap(), report.to_str().unwrap());
    let images = root.join("eval_images");
    let text = ok(eval(&data, &["--checkpoint", gen_s, "--out", report_s, "--images", images.to_str().unwrap()]));
    assert!(text.contains("FID/KID: not computed"), "{text}");
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    let iou = r["mask_iou_mean"].as_f64().unwrap();
    assert!(iou > 0.0 && iou <= 1.0, "{r}");
    // Per-label figures average to the reported mean, and each label's image shows the same
    // IoU: its middle panel is white where both masks cover, red generated only, blue body only.
    let per = r["per_label"].as_array().unwrap();
    assert_eq!(per.len(), 4, "{r}");
    let mean = per.iter().map(|l| l["mask_iou"].as_f64().unwrap()).sum::<f64>() / 4.0;
    assert!((mean - iou).abs() < 1e-5, "{mean} vs {iou}");
    for (k, l) in per.iter().enumerate() {
        let dec = png::Decoder::new(std::io::BufReader::new(
            std::fs::File::open(images.join(format!("{k:02}.png"))).unwrap(),
        ));
        let mut reader = dec.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).unwrap();
        let (w, h) = (info.width as usize, info.height as usize);
        assert_eq!((w, h), (4 * 16, 16), "RGB | overlay | data | normal angle at the dataset's 16²");
        let (mut both, mut union) = (0, 0);
        for y in 0..h {
            for x in 16..32 {
                let p = &buf[(y * w + x) * 3..][..3];
                both += (p == [255, 255, 255]) as usize;
                union += (p != [0, 0, 0]) as usize;
            }
        }
        let from_image = if union == 0 { 1.0 } else { both as f64 / union as f64 };
        assert!((from_image - l["mask_iou"].as_f64().unwrap()).abs() < 1e-5, "label {k}: {from_image} vs {l}");
    }
    assert!(r["data_mask_iou_mean"].as_f64().unwrap() > 0.6, "{r}");
    let err = r["normal_error_deg"].as_f64().unwrap();
    assert!(err > 0.0 && err < 90.0, "{r}");
    // Its breakdown: the interior and outline means weighted by their shares are the mean.
    let b = &r["normal_error_breakdown"];
    let (share, inner, edge) =
        (b["interior_share"].as_f64().unwrap(), b["interior_deg"].as_f64().unwrap(), b["edge_deg"].as_f64().unwrap());
    assert!((0.0..=1.0).contains(&share) && b["median_deg"].as_f64().unwrap() < 90.0, "{b}");
    assert!((share * inner + (1.0 - share) * edge - err).abs() < 1e-3 * err.max(1.0), "{b} vs {err}");
    // With Inception weights (hash-generated stand-ins of the right shapes): FID and KID are
    // reported, and a bad weights file fails before any rendering with a message naming it.
    let weights = root.join("inception.safetensors");
    ok(trainer(&["inception-test-weights", "--out", weights.to_str().unwrap()]));
    let text = ok(eval(&data, &["--checkpoint", gen_s, "--inception", weights.to_str().unwrap(), "--out", report_s]));
    assert!(text.contains("FID "), "{text}");
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    let (fid, kid) = (r["fid"].as_f64().unwrap(), r["kid"].as_f64().unwrap());
    assert!(fid.is_finite() && fid > 0.0 && kid.is_finite(), "{r}");
    let junk = root.join("junk.safetensors");
    std::fs::write(&junk, b"not weights").unwrap();
    let o = eval(&data, &["--inception", junk.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("junk.safetensors") && err.contains("pt_inception"), "{err}");
    let o = trainer(&["eval", "--data", data.to_str().unwrap(), "--config", "tiny", "--count", "0"]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("--count"));
    let _ = std::fs::remove_dir_all(&root);
}

/// A full disk while checkpointing (here a file-size limit, `ulimit -f`, with SIGXFSZ
/// ignored so the write fails with EFBIG as on a full disk): the run stops with an error that
/// names the file and the cause, the previous checkpoint stays intact and loadable, and a
/// resume once there is room again ends bit-identical to an undisturbed run.
#[test]
fn a_full_disk_while_checkpointing_is_an_error_and_keeps_the_last_checkpoint() {
    let root = tmp("full");
    let data = dataset(&root);
    let (reference, out) = (root.join("reference"), root.join("run"));
    train(&data, &reference, 2, &[]);
    train(&data, &out, 1, &[]);
    let state = out.join("state.safetensors");
    let before = std::fs::read(&state).unwrap();
    // Room for the logs and plots, not for a checkpoint (KiB; the tiny state is larger).
    let limit_kib = 64;
    assert!(before.len() > limit_kib * 1024 * 2, "the tiny checkpoint is {} bytes", before.len());
    let o = Command::new("sh")
        .arg("-c")
        .arg(format!("trap '' XFSZ; ulimit -f {limit_kib}; exec \"$0\" \"$@\""))
        .arg(env!("CARGO_BIN_EXE_trainer"))
        .args(["train", "--data", data.to_str().unwrap(), "--config", "tiny", "--out", out.to_str().unwrap()])
        .args(["--batch", "2", "--steps", "2", "--snapshot-every", "1", "--resume"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "the write beyond the limit must fail the run: {err}");
    assert!(err.contains(".safetensors") && err.contains("File too large"), "{err}");
    assert_eq!(std::fs::read(&state).unwrap(), before, "the last checkpoint is untouched");
    assert_eq!(parse_safetensors(&before).unwrap().metadata["step"], "1");
    train(&data, &out, 2, &["--resume"]);
    assert_eq!(
        std::fs::read(reference.join("state.safetensors")).unwrap(),
        std::fs::read(&state).unwrap(),
        "resumed after the failed write == undisturbed"
    );
    let _ = std::fs::remove_dir_all(&root);
}

/// SIGKILL at 20 seeded random moments of a tiny run (during start-up, steps, and the
/// checkpoint, sample-grid and plot writes): after every kill a complete checkpoint loads
/// (the latest, or the one before it when the kill fell between the two renames), and every
/// chain of kills and resumes ends bit-identical to an undisturbed run of the same steps (a
/// chain ends when a resumed run reaches the last step before its kill).
#[test]
fn sigkill_at_random_moments_resumes_bit_identically() {
    const STEPS: u64 = 6;
    const KILLS: usize = 20;
    let root = tmp("kill");
    let data = dataset(&root);
    let reference = root.join("reference");
    train(&data, &reference, STEPS, &[]);
    let out = root.join("run");
    let steps = STEPS.to_string();
    let args = |resume: bool| {
        let mut v = vec!["train", "--data", data.to_str().unwrap(), "--config", "tiny", "--out", out.to_str().unwrap()];
        v.extend(["--batch", "2", "--steps", &steps, "--snapshot-every", "1"]);
        if resume {
            v.push("--resume");
        }
        v.into_iter().map(String::from).collect::<Vec<_>>()
    };
    // Kill moments: a fixed-seed LCG over 0.2 … 3.5 s after each start.
    let mut rng = 0x2545_f491_4f6c_dd1du64;
    let mut delay = || {
        rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        std::time::Duration::from_millis(200 + (rng >> 33) % 3300)
    };
    let (state, prev) = (out.join("state.safetensors"), out.join("state.prev.safetensors"));
    let step_of = |p: &Path| -> Option<u64> {
        let st = parse_safetensors(&std::fs::read(p).ok()?).ok()?;
        st.metadata["step"].parse().ok()
    };
    let (mut kills, mut chains) = (0, 0);
    while kills < KILLS {
        let resume = out.join("run.json").exists();
        let mut child = Command::new(env!("CARGO_BIN_EXE_trainer"))
            .args(args(resume))
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        let wait = delay();
        std::thread::sleep(wait);
        if let Some(status) = child.try_wait().unwrap() {
            // The run reached its end before this kill: this chain of kills and resumes is
            // complete, and must equal the undisturbed run; start another from scratch.
            assert!(status.success(), "a resumed run failed");
            assert_eq!(std::fs::read(reference.join("state.safetensors")).unwrap(), std::fs::read(&state).unwrap());
            chains += 1;
            std::fs::remove_dir_all(&out).unwrap();
            continue;
        }
        child.kill().unwrap(); // SIGKILL
        child.wait().unwrap();
        kills += 1;
        // A complete checkpoint is always there once the first one was written: the latest
        // or, if the kill fell between renaming it away and writing the new one, the previous.
        let latest = step_of(&state);
        eprintln!("kill {kills} after {wait:?}: latest checkpoint step {latest:?}, previous {:?}", step_of(&prev));
        if state.exists() {
            assert!(latest.is_some(), "kill {kills}: state.safetensors is torn");
        } else if prev.exists() {
            assert!(step_of(&prev).is_some(), "kill {kills}: state.prev.safetensors is torn");
        }
        let generator = out.join("generator.safetensors");
        if generator.exists() {
            assert!(step_of(&generator).is_some(), "kill {kills}: generator.safetensors is torn");
        }
    }
    let text = train(&data, &out, STEPS, &["--resume"]);
    assert!(text.contains("trained"), "{text}");
    eprintln!("{KILLS} kills over {} chains of kills and resumes, each equal to the undisturbed run", chains + 1);
    assert_eq!(
        std::fs::read(reference.join("state.safetensors")).unwrap(),
        std::fs::read(&state).unwrap(),
        "{KILLS} kills and resumes == one undisturbed run of {STEPS} steps"
    );
    assert_eq!(
        std::fs::read(reference.join("generator.safetensors")).unwrap(),
        std::fs::read(out.join("generator.safetensors")).unwrap()
    );
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn transfer_learning_onto_rgb_only_data_turns_the_normal_discriminator_off() {
    let root = tmp("transfer");
    let data = dataset(&root);
    let first = root.join("first");
    train(&data, &first, 1, &[]);
    // Remove the normal maps: an RGB-only dataset.
    for e in walk(&data) {
        if e.to_string_lossy().ends_with("_normal.png") {
            std::fs::remove_file(e).unwrap();
        }
    }
    let g = first.join("generator.safetensors");
    let text = train(&data, &root.join("second"), 1, &["--resume", g.to_str().unwrap()]);
    assert!(text.contains("initialised the generator from"), "{text}");
    assert!(text.contains("normal discriminator is off"), "{text}");
    let _ = std::fs::remove_dir_all(&root);
}

/// The reconstruction warm-up (not in the paper) pulls G towards each subject's views: its L1
/// falls, no discriminator is trained, and an adversarial run starts from its generator.
#[test]
fn reconstruction_warm_up_lowers_its_l1_and_hands_over_to_adversarial_training() {
    let root = tmp("recon");
    let data = dataset(&root);
    let run = root.join("recon");
    let text = train(&data, &run, 80, &["--objective", "reconstruction", "--snapshot-every", "40"]);
    assert!(text.contains("trained 80 steps"), "{text}");
    let metrics = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    let rows: Vec<serde_json::Value> = metrics.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(rows.len(), 80);
    assert!(rows.iter().all(|r| r["loss_d"].as_f64() == Some(0.0) && r["r1"].is_null()), "no D: {metrics}");
    let l1: Vec<f64> = rows.iter().map(|r| r["loss_g"].as_f64().unwrap()).collect();
    let (first, last) = (l1[..10].iter().sum::<f64>() / 10.0, l1[70..].iter().sum::<f64>() / 10.0);
    assert!(last < 0.8 * first, "L1 of steps 1–10 {first:.4}, of steps 71–80 {last:.4}");
    // Every snapshot logs G_ema's L1 on the sample grid's subjects against their data views;
    // it falls as the subjects are fitted.
    let fits: Vec<serde_json::Value> = std::fs::read_to_string(run.join("grid_l1.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let steps: Vec<u64> = fits.iter().map(|r| r["step"].as_u64().unwrap()).collect();
    assert_eq!(steps, [40, 80], "{fits:?}");
    let sum = |r: &serde_json::Value| -> f64 {
        ["rgb", "normal", "mask"]
            .iter()
            .map(|k| {
                let v = r[*k].as_f64().unwrap();
                assert!(v > 0.0 && v < 1.0, "{k} = {v}");
                v
            })
            .sum()
    };
    assert!(sum(&fits[1]) < sum(&fits[0]), "grid L1 did not fall: {fits:?}");
    let run_json = std::fs::read_to_string(run.join("run.json")).unwrap();
    assert!(run_json.contains("\"objective\": \"reconstruction\""), "{run_json}");
    let g = run.join("generator.safetensors");
    // The warm-up's generator carries its subjects' W codes as latent modes (the dataset has
    // 2 subjects; the tiny config's w_dim is 16); the paper's objective has none.
    let header = |p: &Path| -> serde_json::Value {
        let b = std::fs::read(p).unwrap();
        let n = u64::from_le_bytes(b[..8].try_into().unwrap()) as usize;
        serde_json::from_slice(&b[8..8 + n]).unwrap()
    };
    let h = header(&g);
    assert_eq!(h["latent_modes/geo"]["shape"], serde_json::json!([2, 16]), "{}", h["latent_modes/geo"]);
    assert_eq!(h["latent_modes/tex"]["shape"], serde_json::json!([2, 16]));
    // `trainer sample` truncates towards the nearest mode: at ψ = 0 that differs from w_avg,
    // at ψ = 1 (no truncation) both agree.
    let sample = |psi: &str, mean: bool| -> Vec<u8> {
        let out = root.join(format!("sample_{psi}_{mean}"));
        let mut args = vec!["sample", "--config", "tiny", "--checkpoint", g.to_str().unwrap(), "--seed-geo", "5"];
        args.extend(["--psi", psi, "--res", "48", "--out", out.to_str().unwrap()]);
        if mean {
            args.push("--mean-truncation");
        }
        ok(trainer(&args));
        assert_eq!(&std::fs::read(out.join("avatar.glb")).unwrap()[..4], b"glTF");
        std::fs::read(out.join("normal.png")).unwrap()
    };
    assert_ne!(sample("0", false), sample("0", true), "ψ = 0: nearest mode vs w_avg");
    assert_eq!(sample("1", false), sample("1", true), "ψ = 1: no truncation either way");
    // Without --psi, a checkpoint with modes samples at ψ = 0 (its subjects).
    let out = root.join("sample_default_psi");
    ok(trainer(&[
        "sample",
        "--config",
        "tiny",
        "--checkpoint",
        g.to_str().unwrap(),
        "--seed-geo",
        "5",
        "--res",
        "48",
        "--out",
        out.to_str().unwrap(),
    ]));
    assert_eq!(std::fs::read(out.join("normal.png")).unwrap(), sample("0", false), "default ψ with modes is 0");
    // `--subject K,M`: subject K's geometry with subject M's colours (same mask, other RGB);
    // out-of-range indices and checkpoints without modes are refused by name.
    let subject = |spec: &str, ckpt: &Path| {
        let out = root.join(format!("subject_{}", spec.replace(',', "_")));
        let args = ["sample", "--config", "tiny", "--checkpoint", ckpt.to_str().unwrap(), "--subject", spec];
        (trainer(&[&args[..], &["--res", "48", "--out", out.to_str().unwrap()]].concat()), out)
    };
    let read = |dir: &Path, f: &str| std::fs::read(dir.join(f)).unwrap();
    let (o, own) = subject("0", &g);
    ok(o);
    let (o, swapped) = subject("0,1", &g);
    ok(o);
    assert_eq!(read(&own, "mask.png"), read(&swapped, "mask.png"), "the geometry is subject 0's in both");
    assert_ne!(read(&own, "rgb.png"), read(&swapped, "rgb.png"), "subject 1's colours");
    let (o, _) = subject("0,2", &g);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("2 subjects"), "{err}");
    // `trainer eval --subject-codes` renders each label at its own subject's codes and
    // measures the L1 against the data: on the training data at `--count 4` it is the
    // snapshot grid's figure (same labels, same weights), so a checkpoint can be measured on
    // another run's grid.
    let report = root.join("subject_codes.json");
    let ckpt = ["--checkpoint", g.to_str().unwrap(), "--subject-codes", "--out", report.to_str().unwrap()];
    let text = ok(eval(&data, &ckpt));
    assert!(text.contains("reconstruction L1 against the data"), "{text}");
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    for k in ["rgb", "normal", "mask"] {
        let (got, grid) = (r["reconstruction_l1"][k].as_f64().unwrap(), fits[1][k].as_f64().unwrap());
        assert!((got - grid).abs() <= 1e-4 + 0.01 * grid, "{k}: eval {got} against the grid's {grid}");
    }
    let subjects: Vec<u64> =
        r["per_label"].as_array().unwrap().iter().map(|l| l["subject"].as_u64().unwrap()).collect();
    assert_eq!(subjects, [0, 0, 1, 1], "{r}");
    // `--supersample 2` renders at twice the size and box-filters, as `prepare` makes the
    // data: the same labels and subjects, a report that says so, figures that differ from the
    // point-sampled ones but stay near them; 0 and 5 samples are refused by name.
    let ss_report = root.join("subject_codes_ss2.json");
    let ss_args = ["--checkpoint", g.to_str().unwrap(), "--subject-codes", "--supersample", "2"];
    let text = ok(eval(&data, &[&ss_args[..], &["--out", ss_report.to_str().unwrap()]].concat()));
    assert!(text.contains("(2×2 samples per pixel)"), "{text}");
    let rs: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&ss_report).unwrap()).unwrap();
    assert_eq!((rs["supersample"].as_u64(), r["supersample"].as_u64()), (Some(2), Some(1)), "{rs}");
    assert_eq!(rs["resolution"], r["resolution"], "compared at the data's resolution");
    let (point, filtered) =
        (r["reconstruction_l1"]["mask"].as_f64().unwrap(), rs["reconstruction_l1"]["mask"].as_f64().unwrap());
    assert!(filtered != point && (filtered - point).abs() < 0.5 * point, "mask L1 {point} → {filtered}");
    for bad in ["0", "5"] {
        let o = eval(&data, &["--checkpoint", g.to_str().unwrap(), "--supersample", bad]);
        assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("--supersample"), "{bad}");
    }
    // Seeded evaluations report no reconstruction figure; a checkpoint without codes, a
    // dataset with more subjects than codes and a ψ with the flag are refused.
    let seeded: serde_json::Value = {
        ok(eval(&data, &["--checkpoint", g.to_str().unwrap(), "--out", report.to_str().unwrap()]));
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap()
    };
    assert!(seeded["reconstruction_l1"].is_null() && seeded["per_label"][0]["subject"].is_null(), "{seeded}");
    let o = eval(&data, &["--subject-codes"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("needs a checkpoint with latent modes"), "{err}");
    let o = eval(&data, &["--checkpoint", g.to_str().unwrap(), "--subject-codes", "--psi", "0.5"]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("--psi"), "a ψ with the flag");
    let scans3 = root.join("scans3");
    ok(trainer(&["synth-scans", "--out", scans3.to_str().unwrap(), "--count", "3", "--texture-size", "128"]));
    let data3 = root.join("data3");
    let prep = ["prepare", "--scans", scans3.to_str().unwrap(), "--out", data3.to_str().unwrap()];
    ok(trainer(&[&prep[..], &["--views", "1", "--res", "16"]].concat()));
    let o = eval(&data3, &["--checkpoint", g.to_str().unwrap(), "--subject-codes"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("holds 3 subjects but the checkpoint has codes for 2"), "{err}");
    // `trainer variety` at ψ = 0: every seed renders one of the 2 subjects, so each seed pair
    // is as far apart as the subjects are, or identical.
    let vdir = root.join("variety");
    let args = ["variety", "--config", "tiny", "--checkpoint", g.to_str().unwrap(), "--psi", "0", "--count", "4"];
    let text = ok(trainer(&[&args[..], &["--res", "32", "--out", vdir.to_str().unwrap()]].concat()));
    assert!(text.contains("median ratio seeds / subjects"), "{text}");
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(vdir.join("variety.json")).unwrap()).unwrap();
    assert_eq!((v["seeds"]["pairs"].as_u64(), v["subjects"]["pairs"].as_u64()), (Some(6), Some(1)), "{v}");
    let between = v["subject_distances"][0].as_f64().unwrap();
    assert!(between > 0.0, "{v}");
    for d in v["seed_distances"].as_array().unwrap() {
        let d = d.as_f64().unwrap();
        assert!(d == 0.0 || (d - between).abs() < 1e-6, "seed pair at {d}, subjects at {between}");
    }
    let sheet = getavatar_core::io::dataset::decode_png(&std::fs::read(vdir.join("seeds.png")).unwrap()).unwrap();
    assert_eq!((sheet.width, sheet.height), (4 * 32, 32));
    // Each render on its own too: the sheet's first tile is seeds/000.png.
    let one = getavatar_core::io::dataset::decode_png(&std::fs::read(vdir.join("seeds/000.png")).unwrap()).unwrap();
    assert_eq!((one.width, one.height), (32, 32));
    let tile = |y: usize| sheet.pixels[y * 4 * 32 * sheet.channels..][..32 * sheet.channels].to_vec();
    let row = |y: usize| one.pixels[y * 32 * one.channels..][..32 * one.channels].to_vec();
    assert!((0..32).all(|y| tile(y) == row(y)), "seeds/000.png is the sheet's first tile");
    assert!(vdir.join("seeds/003.png").exists() && vdir.join("subjects/001.png").exists());
    let text = train(&data, &root.join("adv"), 1, &["--resume", g.to_str().unwrap()]);
    assert!(header(&root.join("adv").join("generator.safetensors")).get("latent_modes/geo").is_none());
    assert!(text.contains("initialised the generator from"), "{text}");
    let adv = std::fs::read_to_string(root.join("adv").join("metrics.jsonl")).unwrap();
    let row: serde_json::Value = serde_json::from_str(adv.lines().next().unwrap()).unwrap();
    assert!(row["loss_d"].as_f64().unwrap() > 0.0, "{row}");
    assert!(row["reconstruction"].is_null(), "the paper's objective has no anchor: {row}");
    let (o, _) = subject("0", &root.join("adv").join("generator.safetensors"));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("latent modes"), "{err}");

    // The anchored adversarial run renders the subjects at the warm-up's latents: its
    // reconstruction L1 starts where the warm-up ended, not where a fresh generator starts.
    let o = trainer(&[
        "train",
        "--data",
        data.to_str().unwrap(),
        "--out",
        root.join("bad").to_str().unwrap(),
        "--objective",
        "reconstruction",
        "--lambda-reconstruction",
        "1",
    ]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("anchor of adversarial runs"), "{o:?}");
    let anchored = root.join("anchored");
    let text = train(&data, &anchored, 2, &["--resume", g.to_str().unwrap(), "--lambda-reconstruction", "1"]);
    assert!(text.contains("trained 2 steps"), "{text}");
    let rows: Vec<serde_json::Value> = std::fs::read_to_string(anchored.join("metrics.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let rec = rows[0]["reconstruction"].as_f64().expect("anchor L1 logged");
    assert!(rows[0]["loss_d"].as_f64().unwrap() > 0.0, "{:?}", rows[0]);
    assert!(rec < 0.8 * first && rec < 1.5 * last, "anchor L1 {rec:.4}; warm-up from {first:.4} to {last:.4}");
    let o = trainer(&[
        "train",
        "--data",
        data.to_str().unwrap(),
        "--out",
        anchored.to_str().unwrap(),
        "--resume",
        "--lambda-reconstruction",
        "3",
    ]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("keeps its settings"), "{o:?}");
    let _ = std::fs::remove_dir_all(&root);
}

/// `trainer train --data DATA --config tiny --out OUT EXTRA…` fails with `needle` in stderr.
fn refused(data: &Path, extra: &[&str], out: &Path, needle: &str) {
    let mut args = vec!["train", "--data", data.to_str().unwrap(), "--config", "tiny", "--out", out.to_str().unwrap()];
    args.extend_from_slice(extra);
    let o = trainer(&args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains(needle), "{extra:?}: {err}");
}

fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}

/// `--views N` (reconstruction terms): stored in run.json, refused where it has no effect or
/// conflicts with a continued run.
#[test]
fn views_per_subject_is_validated_and_kept_in_the_run() {
    let root = tmp("views");
    let data = dataset(&root);
    let run = root.join("recon");
    let text = train(&data, &run, 2, &["--objective", "reconstruction", "--views", "3"]);
    assert!(text.contains("trained 2 steps"), "{text}");
    let rc: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("run.json")).unwrap()).unwrap();
    assert_eq!(rc["views_per_subject"], 3, "{rc}");
    let rows = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    assert_eq!(rows.lines().count(), 2);
    let refused = |extra: &[&str], out: &Path, needle: &str| refused(&data, extra, out, needle);
    refused(&["--objective", "reconstruction", "--views", "0"], &root.join("zero"), "at least 1");
    refused(&["--views", "2"], &root.join("adv"), "reconstruction terms");
    refused(&["--resume", "--views", "4"], &run, "keeps its settings");
    // Every flag that fixes a run setting is refused, and named, where it differs from the
    // continued run's (before, --batch, --seed, --r1-gamma, --objective and --lambda-scan were
    // silently ignored), and accepted where it equals it.
    for (flag, value) in [
        ("--batch", "8"),
        ("--seed", "7"),
        ("--r1-gamma", "20"),
        ("--objective", "adversarial"),
        ("--lambda-scan", "0.5"),
        ("--lambda-reconstruction", "1"),
        ("--lr-g", "0.001"),
        ("--lr-d", "0.001"),
    ] {
        refused(&["--resume", flag, value], &run, &format!("{flag} {value} differs from the run's"));
    }
    let o = trainer(&[
        "train",
        "--data",
        data.to_str().unwrap(),
        "--config",
        "demo",
        "--out",
        run.to_str().unwrap(),
        "--resume",
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("--config demo differs from the run's tiny"), "{err}");
    let same = ["--resume", "--views", "3", "--objective", "reconstruction", "--seed", "0", "--r1-gamma", "10"];
    let text = train(&data, &run, 3, &same);
    assert!(text.contains("trained 1 steps") || text.contains("trained 1 step"), "{text}");
    // The learning rates: the objective's defaults, or the flags' values, kept in run.json.
    assert_eq!((rc["lr_g"].as_f64(), rc["lr_d"].as_f64()), (Some(0.0005), Some(0.002)), "{rc}");
    refused(&["--lr-g", "0"], &root.join("lr0"), "--lr-g must be a finite learning rate > 0, got 0");
    let ttur = root.join("ttur");
    train(&data, &ttur, 1, &["--lr-g", "0.0003", "--lr-d", "0.004"]);
    let rc: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(ttur.join("run.json")).unwrap()).unwrap();
    assert_eq!((rc["lr_g"].as_f64(), rc["lr_d"].as_f64()), (Some(0.0003), Some(0.004)), "{rc}");
    let _ = std::fs::remove_dir_all(&root);
}

/// `--texture-res` (texture detail blocks, not in the paper): kept in run.json's generator
/// config, validated, refused where a continued run differs, and a `--resume FILE` generator
/// with coarser texture planes grows into it; `trainer variety` then takes the checkpoint's
/// own config for `--config tiny`.
#[test]
fn texture_res_grows_a_saved_generator_and_is_kept_in_the_run() {
    let root = tmp("texres");
    let data = dataset(&root);
    let (coarse, fine) = (root.join("coarse"), root.join("fine"));
    train(&data, &coarse, 1, &["--objective", "reconstruction"]);
    let init = coarse.join("generator.safetensors");
    let text = train(
        &data,
        &fine,
        1,
        &["--objective", "reconstruction", "--texture-res", "32", "--resume", init.to_str().unwrap()],
    );
    assert!(text.contains("initialised the generator from"), "{text}");
    let rc: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(fine.join("run.json")).unwrap()).unwrap();
    assert_eq!(rc["generator"]["texture_res"], 32, "{rc}");
    let refused = |extra: &[&str], out: &Path, needle: &str| refused(&data, extra, out, needle);
    refused(&["--resume", "--texture-res", "64"], &fine, "--texture-res 64 differs from the run's 32");
    refused(&["--resume", "--texture-res", "32"], &coarse, "--texture-res 32 differs from the run's (none)");
    refused(&["--texture-res", "24"], &root.join("bad"), "--texture-res 24: config field `texture_res`");
    // Without --texture-res, a checkpoint's own finer texture planes are kept (the shipped
    // demo model resumes as it is)…
    let fine_init = fine.join("generator.safetensors");
    let kept = root.join("kept");
    let text = train(&data, &kept, 1, &["--objective", "reconstruction", "--resume", fine_init.to_str().unwrap()]);
    assert!(text.contains("initialised the generator from"), "{text}");
    let rc: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(kept.join("run.json")).unwrap()).unwrap();
    assert_eq!(rc["generator"]["texture_res"], 32, "{rc}");
    // …and a checkpoint with finer texture planes than a --texture-res asked cannot shrink.
    let finer = root.join("finer");
    let grow = ["--objective", "reconstruction", "--texture-res", "64", "--resume", fine_init.to_str().unwrap()];
    train(&data, &finer, 1, &grow);
    let finer_init = finer.join("generator.safetensors");
    refused(&["--texture-res", "32", "--resume", finer_init.to_str().unwrap()], &root.join("shrink"), "texture_res");
    // --geometry-res grows the geometry planes the same way, keeping the file's texture
    // planes; a continued run and a later --resume FILE keep both.
    let geo = root.join("geo");
    let grow = ["--objective", "reconstruction", "--geometry-res", "32", "--resume", fine_init.to_str().unwrap()];
    train(&data, &geo, 1, &grow);
    let rc: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(geo.join("run.json")).unwrap()).unwrap();
    assert_eq!(
        (rc["generator"]["texture_res"].clone(), rc["generator"]["geometry_res"].clone()),
        (32.into(), 32.into())
    );
    refused(&["--resume", "--geometry-res", "64"], &geo, "--geometry-res 64 differs from the run's 32");
    refused(&["--geometry-res", "24"], &root.join("badgeo"), "--geometry-res 24: config field `geometry_res`");
    let geo_init = geo.join("generator.safetensors");
    let geo_kept = root.join("geo_kept");
    train(&data, &geo_kept, 1, &["--objective", "reconstruction", "--resume", geo_init.to_str().unwrap()]);
    let rc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(geo_kept.join("run.json")).unwrap()).unwrap();
    assert_eq!(rc["generator"]["geometry_res"], 32, "{rc}");
    // --train-only: a stage that trains one part (here the detail block's learned constant)
    // and leaves every other weight as the file had it; kept in run.json, checked against
    // the generator's parameter names, and fixed on --resume.
    let only = root.join("only");
    let constant = "synthesis.texture_detail.0.constant";
    let stage = ["--objective", "reconstruction", "--train-only", constant, "--resume", fine_init.to_str().unwrap()];
    let text = train(&data, &only, 3, &stage);
    assert!(text.contains("(--train-only synthesis.texture_detail.0.constant)"), "{text}");
    let rc: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(only.join("run.json")).unwrap()).unwrap();
    assert_eq!(rc["train_only"], constant, "{rc}");
    let tensors = |p: &Path| {
        getavatar_core::generator::checkpoint::parse_safetensors(&std::fs::read(p).unwrap()).unwrap().tensors
    };
    let (before, after) = (tensors(&fine_init), tensors(&only.join("generator.safetensors")));
    let mut moved = Vec::new();
    for (name, (_, a)) in &before {
        // w_avg is a running mean of the mapping's outputs, not a weight: it is tracked.
        if name.contains("w_avg") {
            continue;
        }
        let b = &after.get(name).unwrap_or_else(|| panic!("{name} missing")).1;
        // Relative: the EMA's update of an unchanged weight rounds (the mapping's weights
        // are stored 1/lr_mul = 100× larger).
        let d = a.iter().zip(b).map(|(x, y)| (x - y).abs() / x.abs().max(1e-3)).fold(0f32, f32::max);
        if d > 1e-5 {
            moved.push(name.clone());
        }
    }
    assert_eq!(moved, [constant], "only the constant moves");
    refused(
        &["--train-only", "synthesis.nothing", "--objective", "reconstruction"],
        &root.join("none"),
        "no generator parameter",
    );
    refused(&["--resume", "--train-only", "mapping_tex"], &only, "--train-only mapping_tex differs from the run's");
    let v = root.join("variety");
    let o = trainer(&[
        "variety",
        "--config",
        "tiny",
        "--checkpoint",
        fine_init.to_str().unwrap(),
        "--count",
        "2",
        "--res",
        "16",
        "--out",
        v.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let _ = std::fs::remove_dir_all(&root);
}

/// `--lambda-texture-swap` and `--latent-spread` (reconstruction terms, not in the paper):
/// the swap term logged every step, both kept in run.json, refused where they have no effect,
/// out of range, or when a continued run differs.
#[test]
fn texture_swap_and_latent_spread_are_logged_and_validated() {
    let root = tmp("swap");
    let data = dataset(&root);
    let run = root.join("recon");
    let args = ["--objective", "reconstruction", "--lambda-texture-swap", "0.5", "--latent-spread", "0.7"];
    let text = train(&data, &run, 2, &args);
    assert!(text.contains("trained 2 steps"), "{text}");
    let rc: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("run.json")).unwrap()).unwrap();
    assert_eq!(rc["lambda_texture_swap"], 0.5, "{rc}");
    assert!((rc["latent_spread"].as_f64().unwrap() - 0.7).abs() < 1e-6, "{rc}");
    // Without --latent-spread-geo the geometry takes --latent-spread: nothing is written.
    assert!(rc.get("latent_spread_geo").is_none(), "{rc}");
    for line in std::fs::read_to_string(run.join("metrics.jsonl")).unwrap().lines() {
        let r: serde_json::Value = serde_json::from_str(line).unwrap();
        let (swap, rec) = (r["texture_swap"].as_f64().unwrap(), r["reconstruction"].as_f64().unwrap());
        assert!(swap > 0.0 && swap < 1.0, "{r}");
        // loss_g = image L1 + 0.5 · swap L1 (no scan terms).
        assert!((r["loss_g"].as_f64().unwrap() - (rec + 0.5 * swap)).abs() < 1e-4, "{r}");
    }
    let refused = |extra: &[&str], out: &Path, needle: &str| refused(&data, extra, out, needle);
    refused(&["--lambda-texture-swap", "0.5"], &root.join("adv"), "reconstruction terms");
    refused(&["--objective", "reconstruction", "--lambda-texture-swap=-1"], &root.join("neg"), "≥ 0");
    refused(&["--resume", "--lambda-texture-swap", "2"], &run, "keeps its settings");
    refused(&["--latent-spread", "0.7"], &root.join("adv2"), "reconstruction terms");
    refused(&["--objective", "reconstruction", "--latent-spread", "1.5"], &root.join("far"), "in [0, 1]");
    refused(&["--resume", "--latent-spread", "0.3"], &run, "keeps its settings");
    refused(&["--resume", "--latent-spread-geo", "1"], &run, "keeps its settings");
    refused(&["--latent-spread-geo", "1"], &root.join("adv3"), "reconstruction terms");
    refused(&["--objective", "reconstruction", "--latent-spread-geo=-0.5"], &root.join("neg2"), "in [0, 1]");
    // A geometry spread of its own is kept in run.json beside the texture's.
    let geo = root.join("geo");
    let text = train(
        &data,
        &geo,
        1,
        &["--objective", "reconstruction", "--latent-spread", "0.25", "--latent-spread-geo", "1"],
    );
    assert!(text.contains("trained 1 steps"), "{text}");
    let rc: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(geo.join("run.json")).unwrap()).unwrap();
    assert!((rc["latent_spread"].as_f64().unwrap() - 0.25).abs() < 1e-6, "{rc}");
    assert_eq!(rc["latent_spread_geo"], 1.0, "{rc}");
    let _ = std::fs::remove_dir_all(&root);
}

/// `--scans` (reconstruction terms, not in the paper): the canonical-space scan terms and
/// the face term are logged and lower their texture errors; the settings are kept in
/// run.json and checked.
#[test]
fn scan_terms_are_logged_kept_in_the_run_and_lower_the_texture_error() {
    let root = tmp("scans");
    let data = dataset(&root);
    let scans = root.join("scans");
    let run = root.join("recon");
    let scan_args = ["--objective", "reconstruction", "--scans", scans.to_str().unwrap()];
    let text = train(&data, &run, 40, &[&scan_args[..], &["--lambda-face", "1", "--snapshot-every", "20"]].concat());
    assert!(text.contains("scan terms: 16384 points from each of 2 scans"), "{text}");
    assert!(text.contains("face term: 4096 face points from each of 2 scans"), "{text}");
    let rc: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("run.json")).unwrap()).unwrap();
    assert_eq!(rc["scans"], scans.display().to_string(), "{rc}");
    assert_eq!((&rc["lambda_scan"], &rc["lambda_face"]), (&1.0.into(), &1.0.into()), "{rc}");
    let rows = |run: &Path| -> Vec<serde_json::Value> {
        let text = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
        text.lines().map(|l| serde_json::from_str(l).unwrap()).collect()
    };
    let rows = rows(&run);
    for key in ["scan_texture", "face_texture"] {
        let v: Vec<f64> = rows.iter().map(|r| r[key].as_f64().unwrap_or_else(|| panic!("{key} logged"))).collect();
        let (first, last) = (v[..5].iter().sum::<f64>() / 5.0, v[35..].iter().sum::<f64>() / 5.0);
        assert!(last < 0.8 * first, "{key} of steps 1–5 {first:.4}, of steps 36–40 {last:.4}");
    }
    assert!(rows.iter().all(|r| r["scan_sdf"].as_f64().is_some_and(|v| v.is_finite() && v >= 0.0)));
    // The face term alone: the surface pool is not drawn and its terms are not logged.
    let text =
        train(&data, &root.join("face"), 1, &[&scan_args[..], &["--lambda-scan", "0", "--lambda-face", "2"]].concat());
    assert!(text.contains("face term: 4096") && !text.contains("scan terms:"), "{text}");
    let row = std::fs::read_to_string(root.join("face").join("metrics.jsonl")).unwrap();
    assert!(row.contains("\"scan_texture\":null") && row.contains("\"face_texture\":"), "{row}");
    // Without --scans nothing is logged.
    train(&data, &root.join("plain"), 1, &["--objective", "reconstruction"]);
    let row = std::fs::read_to_string(root.join("plain").join("metrics.jsonl")).unwrap();
    assert!(row.contains("\"scan_texture\":null") && !row.contains("face_texture"), "{row}");

    let refused = |extra: &[&str], out: &Path, needle: &str| refused(&data, extra, out, needle);
    refused(&["--scans", scans.to_str().unwrap()], &root.join("adv"), "reconstruction terms");
    let empty = root.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    refused(
        &["--objective", "reconstruction", "--scans", empty.to_str().unwrap()],
        &root.join("none"),
        "no scan of subject",
    );
    refused(&["--resume", "--scans", empty.to_str().unwrap()], &run, "keeps its settings");
    refused(&["--objective", "reconstruction", "--lambda-face", "1"], &root.join("noscans"), "--scans DIR");
    refused(&[&scan_args[..], &["--lambda-face=-1"]].concat(), &root.join("negface"), "≥ 0");
    refused(&["--resume", "--lambda-face", "0.5"], &run, "keeps its settings");
    let _ = std::fs::remove_dir_all(&root);
}

/// `--lr-codes` (reconstruction only, not in the paper): the subjects' learned codes live in
/// the training state (a resume continues them bit-identically), move the generator file's
/// latent modes off the fixed latents' codes, and a run started from that file goes on from
/// them; the setting is kept in run.json and refused where it has no effect.
#[test]
fn learned_subject_codes_resume_exactly_and_carry_over_through_the_generator_file() {
    let root = tmp("codes");
    let data = dataset(&root);
    let recon = ["--objective", "reconstruction"];
    let (a, b) = (root.join("a"), root.join("b"));
    let with_codes = [&recon[..], &["--lr-codes", "0.05"]].concat();
    train(&data, &a, 2, &with_codes);
    train(&data, &b, 1, &with_codes);
    let text = train(&data, &b, 2, &["--resume"]);
    assert!(text.contains("trained 1 steps"), "{text}");
    same_files(&a, &b, &["state.safetensors", "generator.safetensors"], "2 steps == 1 + resume + 1");
    let rc: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(a.join("run.json")).unwrap()).unwrap();
    assert!((rc["lr_codes"].as_f64().unwrap() - 0.05).abs() < 1e-6, "{rc}");
    let tensors = |p: &Path| parse_safetensors(&std::fs::read(p).unwrap()).unwrap().tensors;
    let state = tensors(&a.join("state.safetensors"));
    let (shape, codes) = &state["codes/geo"];
    assert_eq!(shape[0], 2, "one code per subject");
    assert!(codes.iter().any(|v| v.abs() > 1e-3), "two steps at rate 0.05 move the codes");
    assert!(
        state.contains_key("adam_codes/geo/m"),
        "the codes' Adam moments are kept: {:?}",
        state.keys().collect::<Vec<_>>()
    );
    // The average beside G_ema trails the codes; with StyleGAN's ramp-up (the half-life at
    // most 5 % of the images seen) it stays close to them in the first steps.
    let ema = &state["codes_ema/geo"].1;
    let norm = |v: &[f32]| v.iter().map(|x| x * x).sum::<f32>().sqrt();
    let lag: Vec<f32> = ema.iter().zip(codes).map(|(e, c)| e - c).collect();
    assert!(norm(&lag) > 0.0 && norm(&lag) < 0.1 * norm(codes), "ema − codes {} codes {}", norm(&lag), norm(codes));

    // From a's generator file: with learned codes the offsets start at its modes, so the
    // modes hardly move in one step at a tiny rate; with fixed codes they fall back to the
    // mapping of the fixed latents, off a's modes by the learned offsets.
    let modes = |p: &Path| {
        let t = tensors(&p.join("generator.safetensors"));
        [t["latent_modes/geo"].1.clone(), t["latent_modes/tex"].1.clone()].concat()
    };
    let init = a.join("generator.safetensors");
    let from = |out: &Path, extra: &[&str]| {
        let args = [&recon[..], &["--lr-g", "1e-9", "--resume", init.to_str().unwrap()], extra].concat();
        train(&data, out, 1, &args)
    };
    let text = from(&root.join("d"), &["--lr-codes", "1e-9"]);
    assert!(text.contains("subjects' codes from the latent modes of"), "{text}");
    let (ma, md, me) = (modes(&a), modes(&root.join("d")), {
        from(&root.join("e"), &[]);
        modes(&root.join("e"))
    });
    let max_diff = |x: &[f32], y: &[f32]| x.iter().zip(y).map(|(p, q)| (p - q).abs()).fold(0.0f32, f32::max);
    assert!(max_diff(&ma, &md) < 1e-3, "carried over: {}", max_diff(&ma, &md));
    assert!(max_diff(&ma, &me) > 1e-2, "fixed codes differ from the learned: {}", max_diff(&ma, &me));

    // `lr_codes_geo_mul` 0 in run.json: only the texture codes learn from then on.
    let t = root.join("tex_only");
    train(&data, &t, 1, &with_codes);
    let before = tensors(&t.join("state.safetensors"));
    let rc_path = t.join("run.json");
    let mut rc: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&rc_path).unwrap()).unwrap();
    assert_eq!(rc["lr_codes_geo_mul"], 1.0, "{rc}");
    rc["lr_codes_geo_mul"] = 0.0.into();
    std::fs::write(&rc_path, serde_json::to_string(&rc).unwrap()).unwrap();
    train(&data, &t, 2, &["--resume"]);
    let after = tensors(&t.join("state.safetensors"));
    assert_eq!(before["codes/geo"].1, after["codes/geo"].1, "the geometry codes stay");
    assert_ne!(before["codes/tex"].1, after["codes/tex"].1, "the texture codes learn");

    let refused = |extra: &[&str], out: &Path, needle: &str| refused(&data, extra, out, needle);
    refused(&["--lr-codes", "0.01"], &root.join("adv"), "--objective reconstruction");
    refused(&["--objective", "reconstruction", "--lr-codes=-1"], &root.join("neg"), "≥ 0");
    refused(&["--resume", "--lr-codes", "0.1"], &a, "keeps its settings");
    let _ = std::fs::remove_dir_all(&root);
}

/// `--codes-wplus`: the learned texture codes are W+ (one offset per texture style layer).
/// They resume bit-identically, the generator file carries them as `latent_modes/tex_layers`
/// (the subjects' W codes stay the fixed latents' mapping), a W+ run started from that file
/// goes on from them, and a W run cannot hold them (it starts at the fixed codes).
#[test]
fn wplus_subject_codes_resume_exactly_and_travel_as_layer_offsets() {
    let root = tmp("codes_wplus");
    let data = dataset(&root);
    let wplus = ["--objective", "reconstruction", "--lr-codes", "0.05", "--codes-wplus"];
    let (a, b) = (root.join("a"), root.join("b"));
    train(&data, &a, 2, &wplus);
    train(&data, &b, 1, &wplus);
    train(&data, &b, 2, &["--resume"]);
    same_files(&a, &b, &["state.safetensors", "generator.safetensors"], "2 steps == 1 + resume + 1");
    let tensors = |p: &Path| parse_safetensors(&std::fs::read(p).unwrap()).unwrap().tensors;
    let state = tensors(&a.join("state.safetensors"));
    let (geo_shape, _) = &state["codes/geo"];
    let (tex_shape, tex) = &state["codes/tex"];
    let w = geo_shape[1];
    assert_eq!(tex_shape[0], 2, "one code per subject");
    assert!(tex_shape[1] > w && tex_shape[1] % w == 0, "W+: several layers of w_dim: {tex_shape:?}");
    let layers = tex_shape[1] / w;
    // Layers differ: the finest texture layers get other gradients than the first.
    let layer = |l: usize| tex[l * w..(l + 1) * w].to_vec();
    assert!(layer(0) != layer(layers - 1), "each layer moves on its own");
    assert!(tex.iter().any(|v| v.abs() > 1e-3), "two steps at rate 0.05 move the codes");

    let file = tensors(&a.join("generator.safetensors"));
    let (shape, offsets) = &file["latent_modes/tex_layers"];
    assert_eq!(shape, &vec![2, layers, w], "the file's layer offsets");
    // The file's modes are G_ema's codes with the averaged offsets.
    let ema = &state["codes_ema/tex"].1;
    assert_eq!(offsets, ema, "the layer offsets are the averaged codes");

    // From a's file: a W+ run starts at its layer offsets (one step at a tiny rate keeps
    // them); a W run cannot hold them and starts at the fixed codes, without layers.
    let init = a.join("generator.safetensors");
    let from = |out: &Path, extra: &[&str]| {
        let args =
            [&["--objective", "reconstruction", "--lr-g", "1e-9", "--resume", init.to_str().unwrap()][..], extra]
                .concat();
        train(&data, out, 1, &args)
    };
    let text = from(&root.join("d"), &["--lr-codes", "1e-9", "--codes-wplus"]);
    assert!(text.contains("subjects' codes from the latent modes of"), "{text}");
    let d = tensors(&root.join("d").join("generator.safetensors"));
    let max_diff = |x: &[f32], y: &[f32]| x.iter().zip(y).map(|(p, q)| (p - q).abs()).fold(0.0f32, f32::max);
    assert!(max_diff(&d["latent_modes/tex_layers"].1, offsets) < 1e-3, "carried over");
    let text = from(&root.join("e"), &["--lr-codes", "1e-9"]);
    assert!(text.contains("start at the fixed ones"), "{text}");
    assert!(!tensors(&root.join("e").join("generator.safetensors")).contains_key("latent_modes/tex_layers"));

    // The file samples a subject with its layers (`sample --subject`).
    let out = root.join("sample");
    ok(trainer(&[
        "sample",
        "--config",
        "tiny",
        "--checkpoint",
        init.to_str().unwrap(),
        "--subject",
        "1",
        "--res",
        "32",
        "--out",
        out.to_str().unwrap(),
    ]));

    let refused = |extra: &[&str], out: &Path, needle: &str| refused(&data, extra, out, needle);
    refused(&["--objective", "reconstruction", "--codes-wplus"], &root.join("no_rate"), "--lr-codes");
    let _ = std::fs::remove_dir_all(&root);
}

/// `trainer fit-codes` (not in the paper): W+ texture codes of a checkpoint's subjects fitted
/// to their data views with the generator frozen. The fitted file carries them as layer
/// offsets, renders its subjects closer to their data (`eval --subject-codes`) with the
/// geometry untouched, resumes bit-identically, and refuses a checkpoint without subjects.
#[test]
fn fit_codes_brings_the_subjects_colours_closer_and_resumes_exactly() {
    let root = tmp("fit_codes");
    let data = dataset(&root);
    let run = root.join("run");
    train(&data, &run, 1, &["--objective", "reconstruction"]);
    let g = run.join("generator.safetensors");
    let fit = |out: &Path, steps: &str, extra: &[&str]| {
        ok(trainer(
            &[
                &[
                    "fit-codes",
                    "--config",
                    "tiny",
                    "--checkpoint",
                    g.to_str().unwrap(),
                    "--data",
                    data.to_str().unwrap(),
                    "--out",
                    out.to_str().unwrap(),
                    "--steps",
                    steps,
                    "--batch",
                    "2",
                    "--points",
                    "256",
                    "--snapshot-every",
                    "10",
                ][..],
                // The codes' rate unless `extra` gives one.
                if extra.contains(&"--lr") { &[] } else { &["--lr", "0.1"] },
                extra,
            ]
            .concat(),
        ))
    };
    // A fit into `out` with `extra` that is refused with `needle` in its error.
    let refused_fit = |out: &Path, extra: &[&str], needle: &str| {
        let (g, data, out) = (g.to_str().unwrap(), data.to_str().unwrap(), out.to_str().unwrap());
        let args = ["fit-codes", "--config", "tiny", "--checkpoint", g, "--data", data, "--out", out];
        let o = trainer(&[&args[..], extra].concat());
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && err.contains(needle), "{err}");
    };
    let (a, b) = (root.join("a"), root.join("b"));
    let text = fit(&a, "30", &[]);
    assert!(text.contains("fitted the texture codes of 2 subjects in 30 steps"), "{text}");
    // b stops at 20 and resumes to 30 (a state written at 20); the same as a's 30 in one go.
    let resumed = |a: &Path, b: &Path, extra: &[&str]| {
        fit(b, "20", extra);
        let text = fit(b, "30", extra);
        assert!(text.contains("resuming the fit at step 20"), "{text}");
        same_files(a, b, &["state.safetensors", "generator.safetensors"], "30 == 20 + resume + 10");
    };
    resumed(&a, &b, &[]);
    // The texture-swap term (on by default) is logged beside the L1.
    let rows = std::fs::read_to_string(a.join("metrics.jsonl")).unwrap();
    let row: serde_json::Value = serde_json::from_str(rows.lines().next().unwrap()).unwrap();
    assert!(row["swap"].as_f64().is_some_and(|v| v > 0.0), "{row}");
    let fitted = a.join("generator.safetensors");
    let file = parse_safetensors(&std::fs::read(&fitted).unwrap()).unwrap();
    let meta = &file.metadata;
    assert_eq!(meta.get("step").map(String::as_str), Some("1"), "the input's training step carries over: {meta:?}");
    assert_eq!(meta.get("fit_codes_steps").map(String::as_str), Some("30"), "{meta:?}");
    let t = file.tensors;
    let (shape, layers) = &t["latent_modes/tex_layers"];
    assert_eq!(shape.len(), 3);
    assert_eq!(shape[0], 2, "{shape:?}");
    assert!(layers.iter().any(|v| v.abs() > 0.05), "the codes moved");
    // The subjects at their codes, against the data: the colours closer, the shape the same.
    let l1 = |ckpt: &Path| -> serde_json::Value {
        let out = root.join(format!("eval_{}.json", ckpt.parent().unwrap().file_name().unwrap().to_str().unwrap()));
        let args = ["--checkpoint", ckpt.to_str().unwrap(), "--subject-codes", "--out", out.to_str().unwrap()];
        ok(eval(&data, &args));
        serde_json::from_str::<serde_json::Value>(&std::fs::read_to_string(&out).unwrap()).unwrap()["reconstruction_l1"]
            .clone()
    };
    let (before, after) = (l1(&g), l1(&fitted));
    let f = |v: &serde_json::Value, k: &str| v[k].as_f64().unwrap();
    assert!(f(&after, "rgb") < 0.9 * f(&before, "rgb"), "RGB L1 {} → {}", f(&before, "rgb"), f(&after, "rgb"));
    assert_eq!(f(&after, "mask"), f(&before, "mask"), "the texture codes leave the geometry");
    // With the texture branch learning too (`--lr-texture`): it resumes exactly (G and its
    // optimiser in the state), the file's weights change, the geometry does not.
    let (c, d) = (root.join("c"), root.join("d"));
    let tex = ["--lr-texture", "0.002"];
    fit(&c, "30", &tex);
    resumed(&c, &d, &tex);
    let tuned = c.join("generator.safetensors");
    let weights = |p: &Path, name: &str| parse_safetensors(&std::fs::read(p).unwrap()).unwrap().tensors[name].1.clone();
    let dec = "decoders.to_rgb.weight";
    assert_ne!(weights(&tuned, dec), weights(&fitted, dec), "the texture decoder learnt");
    let sdf = "decoders.sdf.out.weight";
    assert_eq!(weights(&tuned, sdf), weights(&fitted, sdf), "the SDF head did not");
    let both = l1(&tuned);
    assert_eq!(f(&both, "mask"), f(&before, "mask"), "the geometry stays");
    assert!(f(&both, "rgb") < 0.9 * f(&before, "rgb"), "RGB L1 {} → {}", f(&before, "rgb"), f(&both, "rgb"));
    let png = std::fs::read(a.join("compare.png")).unwrap();
    let img = image::load_from_memory(&png).unwrap();
    assert_eq!((img.width(), img.height()), (3 * 16, 2 * 16), "data | before | after per subject");
    // The face term (`--scans --lambda-face`): the L1 at points of the scans' faces is logged
    // and falls; off, it is logged as null.
    assert!(rows.contains("\"face\":null"), "no face term by default");
    let e = root.join("e");
    let scans = root.join("scans");
    let text = fit(&e, "30", &[&tex[..], &["--scans", scans.to_str().unwrap(), "--lambda-face", "1"]].concat());
    assert!(text.contains("face term: 4096 face points from each of 2 scans"), "{text}");
    // The logged face L1's means over steps 1–5 and 26–30 of a 30-step fit in `dir`.
    let face_means = |dir: &Path| {
        let rows = std::fs::read_to_string(dir.join("metrics.jsonl")).unwrap();
        let face: Vec<f64> = rows
            .lines()
            .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["face"].as_f64().unwrap())
            .collect();
        (face[..5].iter().sum::<f64>() / 5.0, face[25..].iter().sum::<f64>() / 5.0)
    };
    let (first, last) = face_means(&e);
    assert!(last < 0.8 * first, "face L1 of steps 1–5 {first:.4}, of steps 26–30 {last:.4}");
    refused_fit(&root.join("noscans"), &["--lambda-face", "1"], "--lambda-face needs --scans");
    // Finer texture planes (`--texture-res`): the file grows a detail block, which learns,
    // its subjects' W+ codes get the block's two layers, the geometry stays, and the fit
    // resumes exactly.
    let grow = [&tex[..], &["--texture-res", "32"]].concat();
    let (f, h) = (root.join("f"), root.join("h"));
    fit(&f, "30", &grow);
    resumed(&f, &h, &grow);
    let grown = f.join("generator.safetensors");
    let file = parse_safetensors(&std::fs::read(&grown).unwrap()).unwrap();
    let cfg: serde_json::Value = serde_json::from_str(&file.metadata["config"]).unwrap();
    assert_eq!(cfg["texture_res"], 32, "{cfg}");
    let (layers, _) = &file.tensors["latent_modes/tex_layers"];
    assert_eq!(layers[1], shape[1] + 2, "the detail block's conv and to-texture layers");
    let block = &file.tensors["synthesis.texture_detail.0.to_texture.weight"].1;
    assert!(block.iter().any(|&v| v != 0.0), "the new block's output layer learnt from zero");
    assert_eq!(weights(&grown, sdf), weights(&fitted, sdf), "the geometry stays");
    refused_fit(&root.join("nolr"), &["--texture-res", "32"], "--lr-texture");
    // A face plane (`--face-res`), learning alone (`--face-only`, the codes kept with
    // `--lr 0`): the file grows one with the body's face window, only its weights change, the
    // face L1 falls, and the fit resumes exactly.
    let face_fit = [
        "--lr",
        "0",
        "--lr-texture",
        "0.05",
        "--face-res",
        "16",
        "--face-only",
        "--lambda-texture-swap",
        "0",
        "--scans",
        scans.to_str().unwrap(),
        "--lambda-face",
        "1",
    ];
    let (fp, fq) = (root.join("fp"), root.join("fq"));
    fit(&fp, "30", &face_fit);
    resumed(&fp, &fq, &face_fit);
    let faced = fp.join("generator.safetensors");
    let file = parse_safetensors(&std::fs::read(&faced).unwrap()).unwrap();
    let cfg: serde_json::Value = serde_json::from_str(&file.metadata["config"]).unwrap();
    assert_eq!(cfg["face"]["res"], 16, "{cfg}");
    let input = parse_safetensors(&std::fs::read(&g).unwrap()).unwrap().tensors;
    for (name, (_, values)) in &file.tensors {
        match input.get(name) {
            Some((_, before)) => assert_eq!(values, before, "{name} is not the face plane's"),
            None => assert!(name.starts_with("face.") || name.starts_with("latent_modes/"), "{name}"),
        }
    }
    assert!(file.tensors["face.constant"].1.iter().any(|&v| v != 0.0), "the face plane learnt from zero");
    let (first, last) = face_means(&fp);
    assert!(last < 0.9 * first, "face-plane fit: face L1 of steps 1–5 {first:.4}, of steps 26–30 {last:.4}");
    refused_fit(&root.join("noface_lr"), &["--face-res", "16"], "--lr-texture");
    refused_fit(&root.join("noface"), &["--lr-texture", "0.05", "--face-only"], "give --face-res");

    // Surfaces of another dataset in --out are refused, by name.
    let other = root.join("other");
    std::fs::create_dir_all(&other).unwrap();
    let mut pools = parse_safetensors(&std::fs::read(a.join("surfaces.safetensors")).unwrap()).unwrap();
    pools.metadata.insert("subjects".into(), "3".into());
    let tensors: Vec<_> = pools.tensors.into_iter().map(|(k, (s, v))| (k, s, v)).collect();
    std::fs::write(other.join("surfaces.safetensors"), write_safetensors(&pools.metadata, &tensors).unwrap()).unwrap();
    refused_fit(&other, &[], "surfaces of another fit");

    let o = trainer(&["fit-codes", "--config", "tiny", "--random-weights", "--data", data.to_str().unwrap(), "--out"])
        .status;
    assert!(!o.success(), "--out needs a value");
    let o = trainer(&[
        "fit-codes",
        "--config",
        "tiny",
        "--random-weights",
        "--data",
        data.to_str().unwrap(),
        "--out",
        root.join("none").to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("latent modes"), "{err}");
    let _ = std::fs::remove_dir_all(&root);
}

/// `trainer fit-mapping` (not in the paper): the texture mapping refitted so that its codes
/// lie near the subjects' texture codes. The printed figures show the codes closer to the
/// subjects after than before, with both subjects drawn; only the texture mapping's weights
/// (and its w_avg) change in the file, so the subjects and every seed's geometry render as
/// before; a file without subjects is refused.
#[test]
fn fit_mapping_brings_the_seeds_texture_codes_near_the_subjects_and_changes_nothing_else() {
    let root = tmp("fit_mapping");
    let data = dataset(&root);
    let run = root.join("run");
    train(&data, &run, 1, &["--objective", "reconstruction"]);
    let g = run.join("generator.safetensors");
    let out = root.join("fm");
    let text = ok(trainer(&[
        "fit-mapping",
        "--config",
        "tiny",
        "--checkpoint",
        g.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--steps",
        "400",
        "--batch",
        "64",
        "--spread",
        "0.2",
    ]));
    let row = |name: &str| -> (f64, usize) {
        let line = text.lines().find(|l| l.starts_with(&format!("| {name} |"))).unwrap_or_else(|| panic!("{text}"));
        let cells: Vec<&str> = line.split('|').map(str::trim).collect();
        let median: f64 = cells[2].split_whitespace().next().unwrap().parse().unwrap();
        let covered: usize = cells[4].split_whitespace().next().unwrap().parse().unwrap();
        (median, covered)
    };
    let (before, after) = (row("before"), row("after"));
    assert!(after.0 < 0.7 * before.0 && after.0 < 0.5, "median distance {} → {}: {text}", before.0, after.0);
    assert_eq!(after.1, 2, "both subjects drawn: {text}");
    let rows = std::fs::read_to_string(out.join("metrics.jsonl")).unwrap();
    assert_eq!(rows.lines().count(), 400);
    let (a, b) = (
        parse_safetensors(&std::fs::read(&g).unwrap()).unwrap(),
        parse_safetensors(&std::fs::read(out.join("generator.safetensors")).unwrap()).unwrap(),
    );
    assert_eq!(a.tensors.keys().collect::<Vec<_>>(), b.tensors.keys().collect::<Vec<_>>());
    for (name, (_, v)) in &a.tensors {
        if name.starts_with("mapping_tex.") {
            assert_ne!(v, &b.tensors[name].1, "{name} refitted");
        } else {
            assert_eq!(v, &b.tensors[name].1, "{name} untouched");
        }
    }
    assert_eq!(b.metadata.get("fit_mapping_steps").map(String::as_str), Some("400"));
    assert_eq!(b.metadata.get("step"), a.metadata.get("step"), "the input's records carry over");
    let o =
        trainer(&["fit-mapping", "--config", "tiny", "--random-weights", "--out", root.join("none").to_str().unwrap()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("latent modes"), "{err}");
    let _ = std::fs::remove_dir_all(&root);
}
