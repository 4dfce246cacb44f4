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
