//! The data commands end to end: `trainer synth-scans` → `trainer prepare` → the core
//! dataset reader; label round trip (a known 3D point projects onto the rendered pixel);
//! broken subjects are reported by name without stopping the run; re-runs resume.

#![allow(clippy::unwrap_used, clippy::expect_used)] // a test fails by panicking

use std::path::Path;

use getavatar_core::io::dataset::Dataset;
use getavatar_core::render::camera::project_to_pixel;
use glam::{Vec2, Vec3};

mod common;
use common::{tmp, trainer};

/// A small cube (edge `e`) centred at `c` as OBJ text, with UVs and a material.
fn cube_obj(c: Vec3, e: f32) -> String {
    let mut s = String::from("mtllib cube.mtl\nusemtl m\nvt 0 0\n");
    for k in 0..8 {
        let p = c + Vec3::new(
            if k & 1 == 0 { -e } else { e },
            if k & 2 == 0 { -e } else { e },
            if k & 4 == 0 { -e } else { e },
        ) * 0.5;
        s += &format!("v {} {} {}\n", p.x, p.y, p.z);
    }
    for q in [[1, 5, 7, 3], [2, 4, 8, 6], [1, 2, 6, 5], [3, 7, 8, 4], [1, 3, 4, 2], [5, 6, 8, 7]] {
        s += &format!("f {}/1 {}/1 {}/1 {}/1\n", q[0], q[1], q[2], q[3]);
    }
    s
}

fn write_subject(root: &Path, name: &str, obj: &str, mtl: &str, smpl: &str) {
    let d = root.join(name);
    std::fs::create_dir_all(&d).unwrap();
    std::fs::write(d.join(format!("{name}.obj")), obj).unwrap();
    std::fs::write(d.join("cube.mtl"), mtl).unwrap();
    std::fs::write(d.join("smpl.json"), smpl).unwrap();
}

fn smpl_json(scale: f32, transl: Vec3) -> String {
    serde_json::json!({
        "global_orient": [0.0, 0.0, 0.0], "body_pose": vec![0.0; 69], "betas": vec![0.0; 10],
        "transl": transl.to_array(), "scale": scale
    })
    .to_string()
}

#[test]
fn prepare_labels_project_known_points_onto_their_pixels_and_bad_subjects_are_named() {
    let root = tmp("prepare");
    let (scans, out) = (root.join("scans"), root.join("out"));
    // Subject `a`: a 4 cm cube at P (body frame), stored scaled and translated in the scan frame.
    let p = Vec3::new(0.12, -0.3, 0.05);
    let (scale, transl) = (1.3, Vec3::new(0.1, 0.02, -0.05));
    let smpl = smpl_json(scale, transl);
    write_subject(&scans, "a", &cube_obj((p + transl) * scale, 0.04 * scale), "newmtl m\nKd 0.9 0.1 0.1\n", &smpl);
    // `b`: a face index out of range. `c`: a texture that does not exist.
    write_subject(&scans, "b", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "newmtl m\n", &smpl);
    write_subject(&scans, "c", &cube_obj(p, 0.04), "newmtl m\nmap_Kd missing.jpeg\n", &smpl);

    let args = ["prepare", "--scans", scans.to_str().unwrap(), "--out", out.to_str().unwrap()];
    let run = |extra: &[&str]| trainer(&[&args[..], extra].concat());
    let o = run(&["--views", "6", "--res", "128", "--threads", "2"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "broken subjects make the run fail at the end");
    assert!(err.contains("2 of 3 subjects failed"), "{err}");
    assert!(err.contains("b: ") && err.contains("out of range"), "{err}");
    assert!(err.contains("c: ") && err.contains("missing.jpeg"), "{err}");

    // The good subject's data is complete and its labels project P onto the cube's pixels.
    let ds = Dataset::open(&out).unwrap();
    assert_eq!(ds.len(), 6);
    assert!(ds.has_normals);
    assert_eq!(ds.resolution, 128);
    for i in 0..ds.len() {
        let s = ds.load(i).unwrap();
        let (mut sum, mut w) = (Vec2::ZERO, 0.0);
        for y in 0..128 {
            for x in 0..128 {
                let m = s.mask[y * 128 + x];
                sum += m * Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
                w += m;
            }
        }
        assert!(w > 4.0, "{}: cube visible ({w} px)", s.name);
        let centroid = sum / w;
        let want = project_to_pixel(s.label.world_to_camera, p, 128).expect("in front");
        assert!(
            (centroid - want).length() < 0.5,
            "{}: mask centroid {centroid} vs projected label point {want}",
            s.name
        );
        // The cube is looked at: it sits near the image centre (vertical centre protocol).
        assert!((want - Vec2::splat(64.0)).length() < 12.0, "{want}");
        // Untextured red material (Kd) on the cube's pixels.
        let k = (want.y as usize) * 128 + want.x as usize;
        assert!(s.rgb[3 * k] > 0.9 && s.rgb[3 * k + 1] < 0.4, "{:?}", &s.rgb[3 * k..3 * k + 3]);
        assert!(s.label.body_pose.iter().all(|x| *x == 0.0));
    }

    // Re-run: `a` is skipped (resumable), the broken ones are tried again and named again.
    let o = run(&["--views", "6", "--res", "128"]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("1 subjects were already done"), "{text}");
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn synth_scans_then_prepare_gives_a_readable_dataset() {
    let root = tmp("synth");
    let (scans, out) = (root.join("scans"), root.join("ds"));
    let o = trainer(&["synth-scans", "--out", scans.to_str().unwrap(), "--count", "2", "--texture-size", "256"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for f in ["mesh.obj", "material.mtl", "texture.png", "smpl.json"] {
        assert!(scans.join("0001").join(f).is_file(), "{f}");
    }
    let first = std::fs::read(scans.join("0001/mesh.obj")).unwrap();
    // Re-running skips finished scans; a fresh directory with the same seed is identical.
    let o = trainer(&["synth-scans", "--out", scans.to_str().unwrap(), "--count", "2", "--texture-size", "256"]);
    assert!(String::from_utf8_lossy(&o.stdout).contains("(2 already there)"));
    let again = root.join("again");
    let o = trainer(&[
        "synth-scans",
        "--out",
        again.to_str().unwrap(),
        "--count",
        "2",
        "--texture-size",
        "256",
        "--threads",
        "1",
    ]);
    assert!(o.status.success());
    assert_eq!(std::fs::read(again.join("0001/mesh.obj")).unwrap(), first, "deterministic whatever --threads is");

    let o = trainer(&[
        "prepare",
        "--scans",
        scans.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--views",
        "3",
        "--res",
        "64",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let ds = Dataset::open(&out).unwrap();
    assert_eq!(ds.len(), 6);
    for i in 0..ds.len() {
        let s = ds.load(i).unwrap();
        let cover = s.mask.iter().sum::<f32>() / (64.0 * 64.0);
        assert!((0.03..0.5).contains(&cover), "{}: a person covers {cover} of the image", s.name);
        // Normal maps: unit normals on the body, zero vector on the background.
        let n = s.normal.as_ref().unwrap();
        let lens: Vec<f32> = (0..64 * 64)
            .filter(|&k| s.mask[k] == 1.0)
            .map(|k| Vec3::new(n[3 * k], n[3 * k + 1], n[3 * k + 2]).length())
            .collect();
        let mean = lens.iter().sum::<f32>() / lens.len() as f32;
        // (Supersampled pixels average a few unit normals, so some are slightly shorter.)
        let unit = lens.iter().filter(|l| (**l - 1.0).abs() < 0.02).count() as f32 / lens.len() as f32;
        assert!(
            (mean - 1.0).abs() < 0.05 && unit > 0.6 && lens.iter().all(|l| *l > 0.3 && *l < 1.01),
            "mean |n| {mean}, {unit} unit"
        );
        assert!(n[..3].iter().all(|x| x.abs() < 0.01));
        // Labels carry the scan's pose (not the zero pose).
        assert!(s.label.body_pose.iter().any(|x| x.abs() > 0.01));
    }
    let _ = std::fs::remove_dir_all(&root);
}
