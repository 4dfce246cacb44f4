//! glTF 2.0 binary (.glb) export of triangle meshes (posed bodies, avatars), using the
//! `gltf-json` document types and the `gltf` crate's GLB container writer.

use std::borrow::Cow;

use glam::{Vec2, Vec3};
use gltf::json;
use json::validation::Checked::Valid;
use json::validation::USize64;

/// A mesh to export. `normals`, `colors` (linear RGB 0..1) and `uvs` are optional
/// (empty = absent); when present they have one entry per vertex.
#[derive(Clone, Debug, Default)]
pub struct ExportMesh {
    pub positions: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    pub colors: Vec<Vec3>,
    pub uvs: Vec<Vec2>,
    pub indices: Vec<[u32; 3]>,
    /// Name of the node/mesh in the file.
    pub name: String,
}

#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    #[error("mesh has no triangles")]
    Empty,
    #[error("attribute `{0}` has {1} entries, expected one per vertex ({2})")]
    AttributeLength(&'static str, usize, usize),
    #[error("triangle index {0} out of range (mesh has {1} vertices)")]
    Index(u32, usize),
    #[error("non-finite vertex data in `{0}`")]
    NonFinite(&'static str),
    #[error("cannot serialise glTF: {0}")]
    Serialize(String),
}

fn pad4(buf: &mut Vec<u8>) {
    while buf.len() % 4 != 0 {
        buf.push(0);
    }
}

/// Encode `mesh` as a .glb file (one scene, one node, one mesh primitive).
pub fn write_glb(mesh: &ExportMesh) -> Result<Vec<u8>, ExportError> {
    let n = mesh.positions.len();
    if mesh.indices.is_empty() || n == 0 {
        return Err(ExportError::Empty);
    }
    for (name, len) in [("normals", mesh.normals.len()), ("colors", mesh.colors.len()), ("uvs", mesh.uvs.len())] {
        if len != 0 && len != n {
            return Err(ExportError::AttributeLength(name, len, n));
        }
    }
    if let Some(bad) = mesh.indices.iter().flatten().find(|&&i| i as usize >= n) {
        return Err(ExportError::Index(*bad, n));
    }
    if mesh.positions.iter().any(|p| !p.is_finite()) {
        return Err(ExportError::NonFinite("positions"));
    }
    if mesh.normals.iter().any(|p| !p.is_finite()) {
        return Err(ExportError::NonFinite("normals"));
    }

    let mut root = json::Root::default();
    let mut bin: Vec<u8> = Vec::new();
    let buffer = root.push(json::Buffer {
        byte_length: USize64(0),
        extensions: None,
        extras: Default::default(),
        name: None,
        uri: None,
    });

    // Append one tightly packed attribute view + accessor.
    let push_attr = |root: &mut json::Root,
                     bytes: &[u8],
                     count: usize,
                     ty: json::accessor::Type,
                     ct: json::accessor::ComponentType,
                     target: json::buffer::Target,
                     min: Option<json::Value>,
                     max: Option<json::Value>,
                     bin: &mut Vec<u8>| {
        pad4(bin);
        let offset = bin.len();
        bin.extend_from_slice(bytes);
        let view = root.push(json::buffer::View {
            buffer,
            byte_length: USize64::from(bytes.len()),
            byte_offset: Some(USize64::from(offset)),
            byte_stride: None,
            extensions: None,
            extras: Default::default(),
            name: None,
            target: Some(Valid(target)),
        });
        root.push(json::Accessor {
            buffer_view: Some(view),
            byte_offset: None,
            count: USize64::from(count),
            component_type: Valid(json::accessor::GenericComponentType(ct)),
            extensions: None,
            extras: Default::default(),
            type_: Valid(ty),
            min,
            max,
            name: None,
            normalized: false,
            sparse: None,
        })
    };

    let f32_bytes = |v: &mut dyn Iterator<Item = f32>| -> Vec<u8> { v.flat_map(f32::to_le_bytes).collect() };
    use json::accessor::{ComponentType as CT, Type as Ty};
    use json::buffer::Target::{ArrayBuffer, ElementArrayBuffer};

    let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for p in &mesh.positions {
        lo = lo.min(*p);
        hi = hi.max(*p);
    }
    let mut attributes = std::collections::BTreeMap::new();
    let pos = push_attr(
        &mut root,
        &f32_bytes(&mut mesh.positions.iter().flat_map(|p| p.to_array())),
        n,
        Ty::Vec3,
        CT::F32,
        ArrayBuffer,
        Some(json::Value::from(lo.to_array().to_vec())),
        Some(json::Value::from(hi.to_array().to_vec())),
        &mut bin,
    );
    attributes.insert(Valid(json::mesh::Semantic::Positions), pos);
    if !mesh.normals.is_empty() {
        // Unit length is required by the spec; renormalise and replace degenerate ones.
        let unit: Vec<f32> = mesh
            .normals
            .iter()
            .flat_map(|v| {
                let u = v.normalize_or_zero();
                if u == Vec3::ZERO {
                    [0.0, 1.0, 0.0]
                } else {
                    u.to_array()
                }
            })
            .collect();
        let a = push_attr(
            &mut root,
            &f32_bytes(&mut unit.into_iter()),
            n,
            Ty::Vec3,
            CT::F32,
            ArrayBuffer,
            None,
            None,
            &mut bin,
        );
        attributes.insert(Valid(json::mesh::Semantic::Normals), a);
    }
    if !mesh.colors.is_empty() {
        let c = f32_bytes(&mut mesh.colors.iter().flat_map(|c| c.clamp(Vec3::ZERO, Vec3::ONE).to_array()));
        let a = push_attr(&mut root, &c, n, Ty::Vec3, CT::F32, ArrayBuffer, None, None, &mut bin);
        attributes.insert(Valid(json::mesh::Semantic::Colors(0)), a);
    }
    if !mesh.uvs.is_empty() {
        let a = push_attr(
            &mut root,
            &f32_bytes(&mut mesh.uvs.iter().flat_map(|c| c.to_array())),
            n,
            Ty::Vec2,
            CT::F32,
            ArrayBuffer,
            None,
            None,
            &mut bin,
        );
        attributes.insert(Valid(json::mesh::Semantic::TexCoords(0)), a);
    }
    let idx_bytes: Vec<u8> = mesh.indices.iter().flatten().flat_map(|i| i.to_le_bytes()).collect();
    let indices = push_attr(
        &mut root,
        &idx_bytes,
        mesh.indices.len() * 3,
        Ty::Scalar,
        CT::U32,
        ElementArrayBuffer,
        None,
        None,
        &mut bin,
    );
    pad4(&mut bin);
    root.buffers[0].byte_length = USize64::from(bin.len());

    let material = root.push(json::Material {
        pbr_metallic_roughness: json::material::PbrMetallicRoughness {
            base_color_factor: json::material::PbrBaseColorFactor([1.0, 1.0, 1.0, 1.0]),
            metallic_factor: json::material::StrengthFactor(0.0),
            roughness_factor: json::material::StrengthFactor(0.8),
            ..Default::default()
        },
        double_sided: false,
        name: Some("avatar".into()),
        ..Default::default()
    });
    let name = if mesh.name.is_empty() { "getavatar".to_string() } else { mesh.name.clone() };
    let gl_mesh = root.push(json::Mesh {
        extensions: None,
        extras: Default::default(),
        name: Some(name.clone()),
        primitives: vec![json::mesh::Primitive {
            attributes,
            extensions: None,
            extras: Default::default(),
            indices: Some(indices),
            material: Some(material),
            mode: Valid(json::mesh::Mode::Triangles),
            targets: None,
        }],
        weights: None,
    });
    let node = root.push(json::Node { mesh: Some(gl_mesh), name: Some(name), ..Default::default() });
    let scene = root.push(json::Scene { extensions: None, extras: Default::default(), name: None, nodes: vec![node] });
    root.scene = Some(scene);
    root.asset.generator = Some(format!("getavatar {}", env!("CARGO_PKG_VERSION")));

    let json_string = json::serialize::to_string(&root).map_err(|e| ExportError::Serialize(e.to_string()))?;
    let mut json_offset = json_string.len();
    while json_offset % 4 != 0 {
        json_offset += 1;
    }
    let glb = gltf::binary::Glb {
        header: gltf::binary::Header {
            magic: *b"glTF",
            version: 2,
            length: (12 + 8 + json_offset + 8 + bin.len()) as u32,
        },
        bin: Some(Cow::Owned(bin)),
        json: Cow::Owned(json_string.into_bytes()),
    };
    glb.to_vec().map_err(|e| ExportError::Serialize(e.to_string()))
}
