//! `trainer export` end to end: an avatar from the shipped demo model with a baked texture,
//! built-in and AMASS clips, OBJ + MTL + PNG beside it; bad motion files and options are
//! errors that say why, and nothing is written for them.

#![allow(clippy::unwrap_used, clippy::expect_used)] // a test fails by panicking

use getavatar_core::body::motion::Motion;

mod common;
use common::{s, tmp, trainer};

/// The JSON chunk of a .glb.
fn glb_json(bytes: &[u8]) -> serde_json::Value {
    assert_eq!(&bytes[..4], b"glTF");
    let len = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
    serde_json::from_slice(&bytes[20..20 + len]).expect("glTF JSON")
}

#[test]
fn export_writes_a_textured_animated_avatar_and_refuses_bad_motions() {
    let dir = tmp("export");
    let amass = concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/fixtures/motion/amass_sample.npz");
    let out = dir.join("hero.glb");
    let run = trainer(&[
        "export",
        "--seed-geo",
        "1",
        "--seed-tex",
        "3",
        "--texture-res",
        "256",
        "--motion",
        "walk",
        "--motion",
        "wave",
        "--motion",
        amass,
        "--obj",
        "--out",
        s(&out),
    ]);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(stdout.contains("animations: walk") && stdout.contains("amass_sample"), "{stdout}");
    let json = glb_json(&std::fs::read(&out).unwrap());
    let names: Vec<&str> = json["animations"].as_array().unwrap().iter().map(|a| a["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["walk", "wave", "amass_sample"]);
    assert_eq!(json["skins"][0]["joints"].as_array().unwrap().len(), 24);
    assert_eq!(json["images"].as_array().map(Vec::len), Some(1), "one baked texture image");
    assert!(json["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"].is_object());
    // Looping clips end on their first frame again: walk has 33 frames + 1.
    let walk = Motion::builtin("walk").unwrap();
    let input = json["animations"][0]["samplers"][0]["input"].as_u64().unwrap() as usize;
    assert_eq!(json["accessors"][input]["count"].as_u64(), Some(walk.len() as u64 + 1));
    // OBJ + MTL + PNG beside it, the OBJ referencing the MTL and the MTL the PNG.
    let obj = std::fs::read_to_string(dir.join("hero.obj")).unwrap();
    assert!(obj.contains("mtllib hero.mtl") && obj.lines().any(|l| l.starts_with("vt ")));
    assert!(std::fs::read_to_string(dir.join("hero.mtl")).unwrap().contains("map_Kd hero.png"));
    assert_eq!(&std::fs::read(dir.join("hero.png")).unwrap()[..4], b"\x89PNG");

    // Bad motions: a missing file, an unknown clip, a file that is not an npz.
    let bad = |args: &[&str], expect: &str| export_refused(&dir.join("bad.glb"), &[], args, expect);
    bad(&["--texture-res", "0", "--motion", "moonwalk"], "neither a built-in clip");
    let junk = dir.join("junk.npz");
    std::fs::write(&junk, b"not a zip").unwrap();
    bad(&["--texture-res", "0", "--motion", s(&junk)], "junk.npz");
    bad(&["--texture-res", "8"], "--texture-res 8");
    bad(&["--static", "--frames-json", s(&dir.join("f.json"))], "--frames-json needs a skinned export");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn export_writes_vrm_and_one_vrma_per_motion_and_refuses_what_vrm_forbids() {
    let dir = tmp("export_vrm");
    let vrm = dir.join("body.vrm");
    let run = trainer(&["export", "--format", "vrm", "--body-only", "--skeleton", "humanoid", "--out", s(&vrm)]);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let json = glb_json(&std::fs::read(&vrm).unwrap());
    let ext = &json["extensions"]["VRMC_vrm"];
    assert_eq!(ext["specVersion"], "1.0");
    assert_eq!(ext["meta"]["avatarPermission"], "everyone", "the bare body is open");
    let hips = ext["humanoid"]["humanBones"]["hips"]["node"].as_u64().unwrap() as usize;
    assert_eq!(json["nodes"][hips]["name"], "Hips");
    assert!(json["animations"].is_null(), "no animations in a .vrm");

    let out = dir.join("motion.vrma");
    let run = trainer(&["export", "--format", "vrma", "--motion", "walk", "--motion", "wave", "--out", s(&out)]);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    for clip in ["walk", "wave"] {
        let json = glb_json(&std::fs::read(dir.join(format!("motion_{clip}.vrma"))).unwrap());
        assert_eq!(json["extensionsUsed"][0], "VRMC_vrm_animation");
        assert_eq!(json["animations"][0]["name"], clip);
        assert!(json["meshes"].is_null());
    }
    assert!(!out.exists(), "several clips: one file each, named after the clip");

    let bad = |args: &[&str], expect: &str| export_refused(&dir.join("bad.vrm"), &["--body-only"], args, expect);
    bad(&["--format", "vrm", "--motion", "walk"], "a .vrm holds no animations");
    bad(&["--format", "vrm", "--pose", "walking"], "rest T-pose");
    bad(&["--format", "vrma"], "needs at least one --motion");
    bad(&["--skeleton", "mixamo"], "smpl or humanoid");
    let _ = std::fs::remove_dir_all(&dir);
}

/// `trainer export --out target <first> <args>` fails with a message containing `expect`
/// and writes nothing.
fn export_refused(target: &std::path::Path, first: &[&str], args: &[&str], expect: &str) {
    let mut all = vec!["export", "--out", s(target)];
    all.extend_from_slice(first);
    all.extend_from_slice(args);
    let run = trainer(&all);
    let err = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success() && err.contains(expect), "{args:?}: {err}");
    assert!(!target.exists(), "nothing written for {args:?}");
}
