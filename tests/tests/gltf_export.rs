//! glTF export: the .glb parses with the `gltf` crate and carries exactly the mesh given.

use getavatar_core::body_model::BodyModel;
use getavatar_core::gltf_export::{write_glb, ExportError, ExportMesh};
use getavatar_core::pose_library::PoseLibrary;
use getavatar_core::skinning::{pose_body, vertex_normals};
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

/// glTF's skinning as a viewer does it, from the file alone: node world matrices from the
/// animation's keyframe `frame` (rotation and translation channels), times the inverse bind
/// matrices, blended by JOINTS_0 / WEIGHTS_0 over the bind positions.
fn gltf_skinned_positions(bytes: &[u8], animation: usize, frame: usize) -> Vec<Vec3> {
    use glam::{Mat4, Quat};
    use gltf::animation::util::ReadOutputs;
    let doc = gltf::Gltf::from_slice(bytes).expect("valid glb");
    let blob = doc.blob.clone().expect("binary chunk");
    let get = |_: gltf::Buffer| Some(&blob[..]);
    let skin = doc.skins().next().expect("skin");
    let joints: Vec<usize> = skin.joints().map(|n| n.index()).collect();
    let ibm: Vec<Mat4> =
        skin.reader(get).read_inverse_bind_matrices().expect("ibm").map(|m| Mat4::from_cols_array_2d(&m)).collect();
    // Local transforms: the nodes' own, overridden by the animation's values at `frame`.
    let mut local: Vec<(Vec3, Quat)> = doc
        .nodes()
        .map(|n| {
            let (t, r, _) = n.transform().decomposed();
            (Vec3::from_array(t), Quat::from_array(r))
        })
        .collect();
    let anim = doc.animations().nth(animation).expect("animation");
    for ch in anim.channels() {
        let node = ch.target().node().index();
        match ch.reader(get).read_outputs().expect("outputs") {
            ReadOutputs::Rotations(r) => local[node].1 = Quat::from_array(r.into_f32().nth(frame).expect("frame")),
            ReadOutputs::Translations(t) => local[node].0 = Vec3::from_array(t.clone().nth(frame).expect("frame")),
            _ => panic!("unexpected channel"),
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
    let skin_m: Vec<Mat4> = joints.iter().zip(&ibm).map(|(j, b)| world(*j, &local, &parent) * *b).collect();
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
    use getavatar_core::motion::Motion;
    use getavatar_core::skin_export::animated_body_glb;
    use getavatar_core::skinning::BodyParams;
    let model = BodyModel::default_body().expect("body");
    let betas = vec![0.8, -0.5, 0.3];
    let shown = PoseLibrary::builtin().params("walking", &betas).expect("pose");
    let clips = [Motion::builtin("walk").unwrap(), Motion::builtin("wave").unwrap(), Motion::builtin("turn").unwrap()];
    let bytes = animated_body_glb(&model, &shown, &clips, "body").expect("export");
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
