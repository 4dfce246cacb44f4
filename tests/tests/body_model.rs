//! The open SMPL-layout body: file layout, kinematics semantics, skinning invariants.

use std::collections::HashMap;

use getavatar_core::body::body_model::{joint_index, BodyModel, NUM_JOINTS, SMPL_PARENTS};
use getavatar_core::body::pose_library::{da_pose, PoseLibrary, BUILTIN_POSE_NAMES};
use getavatar_core::body::skinning::{pose_body, BodyParams};
use getavatar_core::io::npz;
use glam::Vec3;

fn body() -> BodyModel {
    BodyModel::default_body().expect("embedded body loads")
}

fn j(name: &str) -> usize {
    joint_index(name).expect("joint name")
}

fn params_with(joint: &str, aa: Vec3) -> BodyParams {
    let mut p = BodyParams::default();
    p.pose[j(joint)] = aa;
    p
}

/// Indices of vertices skinned mostly to `joint` (weight > 0.9).
fn dominated_by(m: &BodyModel, joint: usize) -> Vec<usize> {
    (0..m.num_vertices()).filter(|&i| m.weights[i][joint] > 0.9).collect()
}

fn centroid(v: &[Vec3], idx: &[usize]) -> Vec3 {
    idx.iter().map(|&i| v[i]).sum::<Vec3>() / idx.len() as f32
}

#[test]
fn layout_matches_smpl() {
    let m = body();
    assert_eq!(m.parents, SMPL_PARENTS);
    assert!(m.num_betas >= 10, "B = {}", m.num_betas);
    assert_eq!(m.weights.len(), m.num_vertices());
    assert_eq!(m.j_regressor.len(), NUM_JOINTS * m.num_vertices());
    assert_eq!(m.ft.len(), m.faces.len());
    assert!(m.vt.iter().all(|uv| (0.0..=1.0).contains(&uv.x) && (0.0..=1.0).contains(&uv.y)));
    // Regressor rows are affine combinations (sum to 1) so joints move with translation.
    for k in 0..NUM_JOINTS {
        let s: f32 = m.j_regressor[k * m.num_vertices()..(k + 1) * m.num_vertices()].iter().sum();
        assert!((s - 1.0).abs() < 1e-4, "row {k} sums to {s}");
    }
}

#[test]
fn rest_frame_conventions() {
    let m = body();
    let joints = m.regress_joints(&m.v_template);
    let (lo, hi) = m.v_template.iter().fold((Vec3::MAX, Vec3::MIN), |(a, b), v| (a.min(*v), b.max(*v)));
    let height = hi.y - lo.y;
    assert!((1.5..1.9).contains(&height), "height {height} m (metres, y up)");
    // Left side on +x; arms horizontal along ±x (T-pose); feet in front (+z).
    assert!(joints[j("left_shoulder")].x > 0.1 && joints[j("right_shoulder")].x < -0.1);
    for (a, b) in [("left_shoulder", "left_wrist"), ("right_shoulder", "right_wrist")] {
        let d = (joints[j(b)] - joints[j(a)]).normalize();
        assert!(d.x.abs() > 0.99, "{a}->{b} not along x: {d}");
    }
    for (a, b) in [("left_hip", "left_ankle"), ("right_knee", "right_ankle")] {
        let d = (joints[j(b)] - joints[j(a)]).normalize();
        assert!(d.y < -0.99, "{a}->{b} not straight down: {d}");
    }
    assert!(joints[j("left_foot")].z > joints[j("left_ankle")].z + 0.05, "toes point +z");
    assert!((hi.x - 0.5 * (lo.x + hi.x) - (hi.x - lo.x) / 2.0).abs() < 1e-5);
    assert!(hi.x - lo.x > 1.3, "arm span {} m: arms should be horizontal", hi.x - lo.x);
}

#[test]
fn body_surface_is_closed_consistently_oriented_and_outward() {
    let m = body();
    let mut edges: HashMap<(u32, u32), i32> = HashMap::new();
    for f in &m.faces {
        for k in 0..3 {
            let (a, b) = (f[k], f[(k + 1) % 3]);
            *edges.entry((a, b)).or_default() += 1;
        }
    }
    for (&(a, b), &n) in &edges {
        assert_eq!(n, 1, "directed edge {a}->{b} used {n} times (non-manifold or flipped)");
        assert_eq!(edges.get(&(b, a)), Some(&1), "edge {a}-{b} is a boundary edge");
    }
    let vol: f32 = m
        .faces
        .iter()
        .map(|f| {
            let [a, b, c] = f.map(|i| m.v_template[i as usize]);
            a.dot(b.cross(c)) / 6.0
        })
        .sum();
    assert!((0.03..0.12).contains(&vol), "enclosed volume {vol} m^3 (positive = outward faces)");
}

#[test]
fn skin_weights_are_a_partition_of_unity() {
    let m = body();
    for (i, w) in m.weights.iter().enumerate() {
        assert!(w.iter().all(|x| *x >= 0.0), "vertex {i} has a negative weight");
        let s: f32 = w.iter().sum();
        assert!((s - 1.0).abs() < 1e-5, "vertex {i} weights sum to {s}");
    }
    // Every joint drives some vertices (collars only partially).
    for k in 0..NUM_JOINTS {
        assert!(m.weights.iter().any(|w| w[k] > 0.4), "joint {k} drives no vertex");
    }
}

#[test]
fn rest_pose_reproduces_the_template_exactly() {
    let m = body();
    let posed = pose_body(&m, &BodyParams::default());
    for (a, b) in posed.vertices.iter().zip(&m.v_template) {
        assert!((*a - *b).length() < 1e-6, "{a} vs {b}");
    }
}

#[test]
fn bone_lengths_are_preserved_under_any_pose() {
    let m = body();
    let lib = PoseLibrary::builtin();
    let rest = pose_body(&m, &BodyParams::default()).kinematics.posed_joints;
    let mut seed = 12345u64;
    let mut rnd = || {
        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((seed >> 33) as f32 / (1u64 << 31) as f32) * 2.0 - 1.0
    };
    let mut cases: Vec<BodyParams> = BUILTIN_POSE_NAMES.iter().map(|n| lib.params(n, &[]).expect("pose")).collect();
    for _ in 0..5 {
        let mut p = BodyParams::default();
        for r in p.pose.iter_mut() {
            *r = Vec3::new(rnd(), rnd(), rnd()) * 1.5;
        }
        p.transl = Vec3::new(rnd(), rnd(), rnd());
        cases.push(p);
    }
    for p in cases {
        let posed = pose_body(&m, &p).kinematics.posed_joints;
        for k in 1..NUM_JOINTS {
            let par = SMPL_PARENTS[k] as usize;
            let (l0, l1) = ((rest[k] - rest[par]).length(), (posed[k] - posed[par]).length());
            assert!((l0 - l1).abs() < 1e-5, "bone {par}->{k}: {l0} vs {l1}");
        }
    }
}

#[test]
fn one_joint_moves_only_its_vertices_and_descendants() {
    let m = body();
    let k = j("left_elbow");
    let mut affected = [false; NUM_JOINTS];
    affected[k] = true;
    for c in 0..NUM_JOINTS {
        if SMPL_PARENTS[c] >= 0 && affected[SMPL_PARENTS[c] as usize] {
            affected[c] = true;
        }
    }
    let posed = pose_body(&m, &params_with("left_elbow", Vec3::new(0.3, -1.0, 0.2)));
    let mut moved = 0;
    for (i, (a, b)) in posed.vertices.iter().zip(&m.v_template).enumerate() {
        let influenced: f32 = (0..NUM_JOINTS).filter(|&c| affected[c]).map(|c| m.weights[i][c]).sum();
        let d = (*a - *b).length();
        if influenced == 0.0 {
            assert!(d < 1e-6, "vertex {i} moved {d} m without weight on the elbow chain");
        } else if influenced > 0.5 {
            moved += 1;
        }
    }
    assert!(moved > 100, "only {moved} vertices follow the forearm");
}

#[test]
fn smpl_pose_semantics() {
    let m = body();
    let half_pi = std::f32::consts::FRAC_PI_2;
    // left_shoulder z = +π/2: the left arm points straight up.
    let p = pose_body(&m, &params_with("left_shoulder", Vec3::new(0.0, 0.0, half_pi)));
    let jj = &p.kinematics.posed_joints;
    let d = (jj[j("left_wrist")] - jj[j("left_shoulder")]).normalize();
    assert!(d.y > 0.99, "arm direction {d}");
    let hand = dominated_by(&m, j("left_hand"));
    assert!(centroid(&p.vertices, &hand).y > jj[j("left_shoulder")].y + 0.4);
    // right_knee x = +π/2: the right shin bends backwards (−z).
    let p = pose_body(&m, &params_with("right_knee", Vec3::new(half_pi, 0.0, 0.0)));
    let jj = &p.kinematics.posed_joints;
    let d = (jj[j("right_ankle")] - jj[j("right_knee")]).normalize();
    assert!(d.z < -0.99, "shin direction {d}");
    // left_hip z = +0.5: the left leg spreads outwards (+x).
    let p = pose_body(&m, &params_with("left_hip", Vec3::new(0.0, 0.0, 0.5)));
    let jj = &p.kinematics.posed_joints;
    let d = (jj[j("left_ankle")] - jj[j("left_hip")]).normalize();
    assert!((d.x - 0.5f32.sin()).abs() < 0.02 && d.y < 0.0, "leg direction {d}");
    // Da-pose spreads both legs symmetrically.
    let p = pose_body(&m, &BodyParams { pose: da_pose(), ..Default::default() });
    let jj = &p.kinematics.posed_joints;
    assert!((jj[j("left_ankle")].x + jj[j("right_ankle")].x).abs() < 2e-3, "asymmetric Da-pose");
    assert!(jj[j("left_ankle")].x > 0.4);
}

#[test]
fn shape_components_are_meaningful() {
    let m = body();
    let height = |betas: &[f32]| {
        let v = m.shaped_vertices(betas);
        let (lo, hi) = v.iter().fold((f32::MAX, f32::MIN), |(a, b), v| (a.min(v.y), b.max(v.y)));
        hi - lo
    };
    let names = &m.shape_names;
    let hi = names.iter().position(|n| n.starts_with("height")).expect("height component");
    let mut b = vec![0.0; m.num_betas];
    b[hi] = 2.0;
    let tall = height(&b);
    b[hi] = -2.0;
    let short = height(&b);
    assert!(tall - short > 0.1, "height component spans only {} m", tall - short);
    // Every component moves the surface by at least a centimetre somewhere.
    for k in 0..m.num_betas {
        let mut b = vec![0.0; m.num_betas];
        b[k] = 1.0;
        let moved =
            m.shaped_vertices(&b).iter().zip(&m.v_template).map(|(a, c)| (*a - *c).length()).fold(0.0, f32::max);
        assert!(moved > 0.01, "component {k} ({}) moves at most {moved} m", names[k]);
    }
    // Joints follow shape through the regressor.
    b = vec![0.0; m.num_betas];
    b[hi] = 2.0;
    let jt = m.regress_joints(&m.shaped_vertices(&b));
    let j0 = m.regress_joints(&m.v_template);
    assert!(jt[j("head")].y - jt[j("left_ankle")].y > j0[j("head")].y - j0[j("left_ankle")].y + 0.05);
}

#[test]
fn smpl_layout_round_trip_is_exact() {
    let m = body();
    let bytes = m.to_npz_bytes().expect("write");
    let back = BodyModel::from_npz_bytes(&bytes).expect("read");
    assert_eq!(m, back);
}

#[test]
fn malformed_files_give_errors_naming_the_key() {
    let m = body();
    let mut arrays = m.to_arrays();
    arrays.remove("J_regressor");
    let e = BodyModel::from_arrays(&arrays).unwrap_err().to_string();
    assert!(e.contains("J_regressor"), "{e}");

    let mut arrays = m.to_arrays();
    arrays.insert("weights".into(), npz::NpyArray::f32(vec![3, 24], vec![0.0; 72]));
    let e = BodyModel::from_arrays(&arrays).unwrap_err().to_string();
    assert!(e.contains("weights"), "{e}");

    let mut arrays = m.to_arrays();
    let nf = m.faces.len();
    arrays.insert("f".into(), npz::NpyArray::u32(vec![nf, 3], vec![u32::MAX; nf * 3]));
    let e = BodyModel::from_arrays(&arrays).unwrap_err().to_string();
    assert!(e.contains("`f`") && e.contains("out of range"), "{e}");

    let mut arrays = m.to_arrays();
    arrays.insert("kintree_table".into(), npz::NpyArray::i64(vec![2, 24], vec![5; 48]));
    assert!(BodyModel::from_arrays(&arrays).unwrap_err().to_string().contains("kintree_table"));

    // Truncated archives and garbage are errors, not panics.
    let bytes = m.to_npz_bytes().expect("write");
    assert!(BodyModel::from_npz_bytes(&bytes[..bytes.len() / 2]).is_err());
    assert!(BodyModel::from_npz_bytes(b"PK\x03\x04garbage").is_err());
    assert!(BodyModel::from_npz_bytes(&[]).is_err());
}

#[test]
fn a_float64_smpl_style_file_loads() {
    // Official SMPL files store float64 and the root parent as uint32::MAX; both load.
    let m = body();
    let mut arrays = m.to_arrays();
    let v = arrays["v_template"].to_f64();
    arrays.insert("v_template".into(), npz::NpyArray::f64(vec![m.num_vertices(), 3], v));
    arrays.remove("vt");
    arrays.remove("ft");
    let back = BodyModel::from_npz_bytes(&npz::write_npz(&arrays).expect("npz")).expect("loads");
    assert_eq!(back.v_template, m.v_template);
    assert!(back.vt.is_empty());
}
