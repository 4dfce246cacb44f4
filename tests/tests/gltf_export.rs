//! glTF export: the .glb parses with the `gltf` crate and carries exactly the mesh given.

use getavatar_core::body::body_model::BodyModel;
use getavatar_core::body::humanoid::SkeletonNames;
use getavatar_core::body::pose_library::PoseLibrary;
use getavatar_core::body::skinning::{pose_body, vertex_normals};
use getavatar_core::export::gltf_export::{write_glb, ExportError, ExportMesh};
use glam::Vec3;

fn posed_body_mesh() -> ExportMesh {
    let m = BodyModel::default_body().expect("body");
    let p = pose_body(&m, &PoseLibrary::builtin().params("walking", &[]).expect("pose"));
    ExportMesh {
        normals: vertex_normals(&p.vertices, &m.faces),
        colors: vec![Vec3::new(0.6, 0.4, 0.3); p.vertices.len()],
        uvs: Vec::new(),
        positions: p.vertices,
        indices: m.faces.clone(),
        name: "walking".into(),
    }
}

#[test]
fn glb_round_trips_through_the_gltf_reader() {
    let mesh = posed_body_mesh();
    let bytes = write_glb(&mesh).expect("export");
    assert_eq!(&bytes[..4], b"glTF");
    assert_eq!(bytes.len() % 4, 0);
    let doc = gltf::Gltf::from_slice(&bytes).expect("valid glb");
    let blob = doc.blob.clone().expect("binary chunk");
    let prim = doc.meshes().next().expect("mesh").primitives().next().expect("primitive");
    let reader = prim.reader(|_| Some(&blob[..]));
    let pos: Vec<[f32; 3]> = reader.read_positions().expect("positions").collect();
    assert_eq!(pos.len(), mesh.positions.len());
    for (a, b) in pos.iter().zip(&mesh.positions) {
        assert_eq!(Vec3::from_array(*a), *b);
    }
    let idx: Vec<u32> = reader.read_indices().expect("indices").into_u32().collect();
    assert_eq!(idx, mesh.indices.iter().flatten().copied().collect::<Vec<_>>());
    let normals: Vec<[f32; 3]> = reader.read_normals().expect("normals").collect();
    assert!(normals.iter().all(|n| (Vec3::from_array(*n).length() - 1.0).abs() < 1e-5));
    let bounds = prim.bounding_box();
    let lo = mesh.positions.iter().fold(Vec3::MAX, |a, p| a.min(*p));
    assert_eq!(Vec3::from_array(bounds.min), lo);
}

#[test]
fn bad_meshes_are_errors() {
    let mut mesh = posed_body_mesh();
    mesh.normals.pop();
    assert!(matches!(write_glb(&mesh), Err(ExportError::AttributeLength("normals", ..))));
    let mut mesh = posed_body_mesh();
    mesh.indices.push([0, 1, 99_999_999]);
    assert!(matches!(write_glb(&mesh), Err(ExportError::Index(99_999_999, _))));
    let mut mesh = posed_body_mesh();
    mesh.positions[3].x = f32::NAN;
    assert!(matches!(write_glb(&mesh), Err(ExportError::NonFinite("positions"))));
    assert!(matches!(write_glb(&ExportMesh::default()), Err(ExportError::Empty)));
}

/// Every node's world matrix as a viewer computes it from the file alone: the nodes' own
/// transforms, overridden by animation `a`'s values at keyframe `k` when `at` is `Some((a, k))`.
fn node_world_matrices(bytes: &[u8], at: Option<(usize, usize)>) -> Vec<glam::Mat4> {
    use glam::{Mat4, Quat};
    use gltf::animation::util::ReadOutputs;
    let doc = gltf::Gltf::from_slice(bytes).expect("valid glb");
    let blob = doc.blob.clone().expect("binary chunk");
    let get = |_: gltf::Buffer| Some(&blob[..]);
    let mut local: Vec<(Vec3, Quat)> = doc
        .nodes()
        .map(|n| {
            let (t, r, _) = n.transform().decomposed();
            (Vec3::from_array(t), Quat::from_array(r))
        })
        .collect();
    if let Some((animation, frame)) = at {
        let anim = doc.animations().nth(animation).expect("animation");
        for ch in anim.channels() {
            let node = ch.target().node().index();
            match ch.reader(get).read_outputs().expect("outputs") {
                ReadOutputs::Rotations(r) => local[node].1 = Quat::from_array(r.into_f32().nth(frame).expect("frame")),
                ReadOutputs::Translations(t) => local[node].0 = Vec3::from_array(t.clone().nth(frame).expect("frame")),
                _ => panic!("unexpected channel"),
            }
        }
    }
    let mut parent = vec![None; local.len()];
    for n in doc.nodes() {
        for c in n.children() {
            parent[c.index()] = Some(n.index());
        }
    }
    fn world(i: usize, local: &[(Vec3, Quat)], parent: &[Option<usize>]) -> Mat4 {
        let m = Mat4::from_rotation_translation(local[i].1, local[i].0);
        match parent[i] {
            Some(p) => world(p, local, parent) * m,
            None => m,
        }
    }
    (0..local.len()).map(|i| world(i, &local, &parent)).collect()
}

/// glTF's skinning as a viewer does it, from the file alone: node world matrices from the
/// animation's keyframe `frame` (rotation and translation channels), times the inverse bind
/// matrices, blended by JOINTS_0 / WEIGHTS_0 over the bind positions.
fn gltf_skinned_positions(bytes: &[u8], animation: usize, frame: usize) -> Vec<Vec3> {
    skinned_positions_at(bytes, Some((animation, frame)))
}

fn skinned_positions_at(bytes: &[u8], at: Option<(usize, usize)>) -> Vec<Vec3> {
    use glam::Mat4;
    let doc = gltf::Gltf::from_slice(bytes).expect("valid glb");
    let blob = doc.blob.clone().expect("binary chunk");
    let get = |_: gltf::Buffer| Some(&blob[..]);
    let skin = doc.skins().next().expect("skin");
    let joints: Vec<usize> = skin.joints().map(|n| n.index()).collect();
    let ibm: Vec<Mat4> =
        skin.reader(get).read_inverse_bind_matrices().expect("ibm").map(|m| Mat4::from_cols_array_2d(&m)).collect();
    let world = node_world_matrices(bytes, at);
    let skin_m: Vec<Mat4> = joints.iter().zip(&ibm).map(|(j, b)| world[*j] * *b).collect();
    let prim = doc.meshes().next().expect("mesh").primitives().next().expect("primitive");
    let r = prim.reader(get);
    let pos: Vec<Vec3> = r.read_positions().expect("positions").map(Vec3::from_array).collect();
    let js: Vec<[u16; 4]> = r.read_joints(0).expect("joints").into_u16().collect();
    let ws: Vec<[f32; 4]> = r.read_weights(0).expect("weights").into_f32().collect();
    pos.iter()
        .zip(js.iter().zip(&ws))
        .map(|(p, (j, w))| (0..4).map(|k| skin_m[j[k] as usize].transform_point3(*p) * w[k]).sum())
        .collect()
}

#[test]
fn animated_body_plays_the_projects_lbs() {
    use getavatar_core::body::motion::Motion;
    use getavatar_core::body::skinning::BodyParams;
    use getavatar_core::export::skin_export::animated_body_glb;
    let model = BodyModel::default_body().expect("body");
    let betas = vec![0.8, -0.5, 0.3];
    let shown = PoseLibrary::builtin().params("walking", &betas).expect("pose");
    let clips = [Motion::builtin("walk").unwrap(), Motion::builtin("wave").unwrap(), Motion::builtin("turn").unwrap()];
    let bytes = animated_body_glb(&model, &shown, &clips, "body", SkeletonNames::Smpl).expect("export");
    let doc = gltf::Gltf::from_slice(&bytes).expect("valid glb");
    let names: Vec<String> = doc.nodes().filter_map(|n| n.name().map(str::to_string)).collect();
    for j in getavatar_core::JOINT_NAMES {
        assert!(names.iter().any(|n| n == j), "joint node {j} in {names:?}");
    }
    assert_eq!(
        doc.animations().map(|a| a.name().unwrap_or("").to_string()).collect::<Vec<_>>(),
        ["walk", "wave", "turn"]
    );
    let mut worst = 0.0f32;
    for (a, clip) in clips.iter().enumerate() {
        for frame in [0, clip.len() / 3, clip.len() - 1] {
            let ours = pose_body(&model, &BodyParams { betas: betas.clone(), ..clip.params(frame, &betas) }).vertices;
            let theirs = gltf_skinned_positions(&bytes, a, frame);
            for (p, q) in ours.iter().zip(&theirs) {
                worst = worst.max((*p - *q).length());
            }
        }
    }
    // The only difference: glTF keeps each vertex's 4 largest weights.
    assert!(worst <= 0.005, "glTF skinning vs the project's LBS: worst {:.2} mm", worst * 1000.0);
    eprintln!("glTF skinning vs LBS: worst {:.3} mm over 3 clips × 3 frames", worst * 1000.0);
}

/// The JSON chunk of a .glb as a value (for the extensions the `gltf` crate does not read).
fn glb_json(bytes: &[u8]) -> serde_json::Value {
    let glb = gltf::binary::Glb::from_slice(bytes).expect("glb");
    serde_json::from_slice(&glb.json).expect("json")
}

#[test]
fn the_body_as_vrm_stands_in_t_pose_on_the_floor_with_every_humanoid_bone_on_its_side() {
    use getavatar_core::body::humanoid::{HUMANOID_BONES, VRM_REQUIRED_BONES};
    use getavatar_core::body::skinning::BodyParams;
    use getavatar_core::export::skin_export::body_vrm;
    use getavatar_core::export::vrm_export::{AvatarOrigin, VrmMeta, VRM_LICENSE_URL};
    let model = BodyModel::default_body().expect("body");
    let betas = vec![0.8, -0.5, 0.3];
    let meta = VrmMeta { name: "body".into(), origin: AvatarOrigin::Body };
    let bytes = body_vrm(&model, &betas, &meta, SkeletonNames::Humanoid).expect("vrm");
    let doc = gltf::Gltf::from_slice(&bytes).expect("valid glb");
    assert_eq!(doc.animations().count(), 0, "a .vrm holds no animations");
    let json = glb_json(&bytes);
    assert_eq!(json["extensionsUsed"], serde_json::json!(["VRMC_vrm"]));
    let vrm = &json["extensions"]["VRMC_vrm"];
    assert_eq!(vrm["specVersion"], "1.0");
    assert_eq!(vrm["meta"]["licenseUrl"], VRM_LICENSE_URL);
    let bones = vrm["humanoid"]["humanBones"].as_object().expect("humanBones");
    for req in VRM_REQUIRED_BONES {
        assert!(bones.contains_key(req), "required bone {req}");
    }
    // Rest pose: soles at 0, and the file's skinning at rest leaves every vertex in place.
    let rest = pose_body(&model, &BodyParams { betas: betas.clone(), ..BodyParams::default() }).vertices;
    let floor = rest.iter().map(|v| v.y).fold(f32::INFINITY, f32::min);
    let skinned = skinned_positions_at(&bytes, None);
    let lowest = skinned.iter().map(|v| v.y).fold(f32::INFINITY, f32::min);
    assert!(lowest.abs() < 1e-5, "soles at {lowest} m");
    for (p, q) in skinned.iter().zip(&rest) {
        assert!((*p - (*q - Vec3::Y * floor)).length() < 1e-5, "{p} vs {q}");
    }
    // Each bone's node sits at the project's rest joint (moved to the floor), named as a
    // humanoid, left bones at +x: the body's left as it faces +z.
    let world = node_world_matrices(&bytes, None);
    let joints = model.regress_joints(&model.shaped_vertices(&betas));
    for (j, b) in HUMANOID_BONES.iter().enumerate() {
        let Some(v) = b.vrm else { continue };
        let node = bones[v]["node"].as_u64().expect("node") as usize;
        assert_eq!(doc.nodes().nth(node).and_then(|n| n.name().map(str::to_string)).as_deref(), Some(b.node));
        let p = world[node].w_axis.truncate();
        assert!((p - (joints[j] - Vec3::Y * floor)).length() < 1e-5, "{v} at {p}");
        if v.starts_with("left") {
            assert!(p.x > 0.02, "{v} on the left (+x): {p}");
        } else if v.starts_with("right") {
            assert!(p.x < -0.02, "{v} on the right (−x): {p}");
        }
        assert!(
            world[node].to_scale_rotation_translation().1.angle_between(glam::Quat::IDENTITY) < 1e-6,
            "{v} unrotated"
        );
    }
    let look = &vrm["lookAt"]["offsetFromHeadBone"];
    let (y, z) = (look[1].as_f64().expect("y"), look[2].as_f64().expect("z"));
    assert!(y > 0.0 && y < 0.15 && z > 0.04 && z < 0.15, "the eyes above and in front of the head joint: {look}");
    let first = &vrm["firstPerson"]["meshAnnotations"][0];
    let first_person = first["node"].as_u64().expect("node") as usize;
    assert!(doc.nodes().nth(first_person).and_then(|n| n.mesh()).is_some(), "the first-person mesh is the avatar's");
}

#[test]
fn a_vrma_clip_moves_the_skeleton_as_the_projects_forward_kinematics() {
    use getavatar_core::body::motion::Motion;
    use getavatar_core::body::skinning::BodyParams;
    use getavatar_core::export::skin_export::motion_vrma;
    let model = BodyModel::default_body().expect("body");
    let betas = vec![-0.4, 0.6];
    let walk = Motion::builtin("walk").unwrap();
    let bytes = motion_vrma(&model, &betas, &walk, SkeletonNames::Smpl).expect("vrma");
    let doc = gltf::Gltf::from_slice(&bytes).expect("valid glb");
    assert_eq!(doc.meshes().count(), 0);
    assert_eq!(doc.animations().count(), 1);
    let json = glb_json(&bytes);
    let ext = &json["extensions"]["VRMC_vrm_animation"];
    assert_eq!(ext["specVersion"], "1.0");
    let hips = ext["humanoid"]["humanBones"]["hips"]["node"].as_u64().expect("hips") as usize;
    let rest = pose_body(&model, &BodyParams { betas: betas.clone(), ..BodyParams::default() }).vertices;
    let floor = rest.iter().map(|v| v.y).fold(f32::INFINITY, f32::min);
    assert!(node_world_matrices(&bytes, None)[hips].w_axis.y > 0.5, "T-pose rest: hips above the floor");
    let mut worst = 0.0f32;
    for frame in [0, walk.len() / 2, walk.len() - 1] {
        let ours = pose_body(&model, &walk.params(frame, &betas)).kinematics.posed_joints;
        let world = node_world_matrices(&bytes, Some((0, frame)));
        for (j, p) in ours.iter().enumerate() {
            worst = worst.max((world[hips + j].w_axis.truncate() - (*p - Vec3::Y * floor)).length());
        }
    }
    assert!(worst < 1e-4, "joints vs forward kinematics: worst {worst} m");
}

#[test]
fn a_vrm_refuses_a_skin_that_is_not_in_its_rest_pose() {
    use getavatar_core::export::skin_export::{smpl_skin, vrm_frame, vrm_rest_skin};
    use getavatar_core::export::vrm_export::{write_vrm, AvatarOrigin, VrmMeta};
    let model = BodyModel::default_body().expect("body");
    let walking = PoseLibrary::builtin().params("walking", &[]).expect("pose");
    let mesh = posed_body_mesh();
    let meta = VrmMeta { name: "x".into(), origin: AvatarOrigin::Photo };
    let skin = smpl_skin(&model, &walking, model.weights.iter(), SkeletonNames::Smpl);
    let err = write_vrm(&mesh, None, &skin, &meta, Vec3::ZERO).expect_err("posed skin");
    assert!(err.to_string().contains("rest pose"), "{err}");
    let frame = vrm_frame(&model, &[]).expect("frame");
    let rest = vrm_rest_skin(skin, &frame);
    assert!(write_vrm(&mesh, None, &rest, &meta, Vec3::ZERO).is_ok());
}

#[test]
fn a_humanoid_skeleton_names_the_joints_as_retargeting_tools_expect() {
    use getavatar_core::body::skinning::BodyParams;
    use getavatar_core::export::skin_export::animated_body_glb;
    let model = BodyModel::default_body().expect("body");
    let bytes = animated_body_glb(&model, &BodyParams::default(), &[], "body", SkeletonNames::Humanoid).expect("glb");
    let doc = gltf::Gltf::from_slice(&bytes).expect("valid glb");
    let world = node_world_matrices(&bytes, None);
    let node = |name: &str| doc.nodes().find(|n| n.name() == Some(name)).map(|n| n.index());
    for name in ["Hips", "Spine", "Spine1", "Spine2", "Neck", "Head", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase"]
    {
        assert!(node(name).is_some(), "{name}");
    }
    assert!(node("pelvis").is_none());
    let (left_arm, right_arm) = (node("LeftArm").expect("LeftArm"), node("RightArm").expect("RightArm"));
    assert!(world[left_arm].w_axis.x > 0.1 && world[right_arm].w_axis.x < -0.1, "LeftArm on the body's left (+x)");
    let (hand, fore) = (node("LeftHand").expect("LeftHand"), node("LeftForeArm").expect("LeftForeArm"));
    assert!(world[hand].w_axis.x > world[fore].w_axis.x, "the hand beyond the forearm");
}
