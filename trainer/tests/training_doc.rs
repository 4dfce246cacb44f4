//! docs/training.md's tiny chain, run as written: the newcomer's walkthrough (synth-scans →
//! prepare → train → eval → sample) must work on a fresh clone, so the commands are read
//! from the document itself and run in a temporary folder with this build's trainer.

#![allow(clippy::unwrap_used, clippy::expect_used)] // a test fails by panicking

use std::process::Command;

mod common;
use common::tmp;

/// The `trainer …` lines of the first ```sh block after the heading "## The tiny chain".
fn tiny_chain() -> Vec<Vec<String>> {
    let doc = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/training.md")).unwrap();
    let section = doc.split("## The tiny chain").nth(1).expect("the tiny chain's heading");
    let block = section.split("```sh").nth(1).and_then(|b| b.split("```").next()).expect("its sh block");
    block
        .lines()
        .map(str::trim)
        .filter(|l| l.starts_with("trainer "))
        .map(|l| l.split_whitespace().skip(1).map(str::to_string).collect())
        .collect()
}

#[test]
fn the_training_walkthrough_runs_as_documented() {
    let chain = tiny_chain();
    let commands: Vec<&str> = chain.iter().map(|c| c[0].as_str()).collect();
    assert_eq!(commands, ["synth-scans", "prepare", "train", "eval", "sample"], "the documented chain");
    let dir = tmp("training_doc");
    for args in &chain {
        let t = std::time::Instant::now();
        let out = Command::new(env!("CARGO_BIN_EXE_trainer")).args(args).current_dir(&dir).output().unwrap();
        assert!(out.status.success(), "trainer {}: {}", args.join(" "), String::from_utf8_lossy(&out.stderr));
        eprintln!("trainer {} ({:.1} s)", args[0], t.elapsed().as_secs_f64());
    }
    // What the document says each step writes.
    assert!(dir.join("data/scans").read_dir().unwrap().count() >= 4, "4 scans");
    assert!(dir.join("data/ds/dataset.json").is_file());
    assert!(dir.join("runs/tiny/generator.safetensors").is_file());
    assert!(dir.join("runs/tiny/metrics.jsonl").is_file());
    let eval: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("runs/tiny/eval.json")).unwrap()).unwrap();
    let iou = eval["mask_iou_mean"].as_f64().unwrap_or(f64::NAN);
    assert!(iou > 0.3 && iou <= 1.0, "eval.json's mask IoU {iou}: {eval}");
    for f in ["rgb.png", "normal.png", "mask.png", "avatar.glb"] {
        assert!(dir.join("runs/tiny/sample").join(f).is_file(), "sample wrote {f}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
