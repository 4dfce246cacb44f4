//! glTF 2.0 binary (.glb) export of triangle meshes (posed bodies, avatars), using the
//! `gltf-json` document types and the `gltf` crate's GLB container writer.
//!
//! [`write_glb`] writes a static mesh; [`write_glb_full`] adds a base-colour texture image, a
//! skin (the 24 SMPL joints as nodes named as SMPL, inverse bind matrices, JOINTS_0 /
//! WEIGHTS_0 with up to 4 influences) and animations (each joint's rotation and the root's
//! translation per frame, LINEAR = slerp between frames).
//!
//! The bind pose is the body's rest pose (T-pose, θ = 0) at the avatar's shape: the joints'
//! world transforms there are pure translations, so glTF's skinning
//! `Σ w_j · world_j(θ) · IBM_j` is exactly SMPL's linear blend skinning (paper eq. 1) of the
//! rest-pose vertices. A bind in the canonical Da-pose would blend differently where the
//! pelvis and thigh weights mix (the two bind transforms differ there), so the avatar is
//! un-posed to the rest pose for the file and the nodes carry the pose shown.

use std::borrow::Cow;

use glam::{Mat4, Quat, Vec2, Vec3};
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
    #[error("skin: {0}")]
    Skin(String),
    #[error("animation `{0}`: {1}")]
    Clip(String, String),
    #[error("the baked texture belongs to another mesh: {0}")]
    TextureMismatch(String),
}

/// A skeleton and skin weights for [`write_glb_full`] (SMPL layout: parents precede
/// children). `ExportMesh::positions` / `normals` are then the bind (rest-pose) ones.
#[derive(Clone, Debug, Default)]
pub struct ExportSkin {
    /// Joint names (node names), one per joint.
    pub names: Vec<String>,
    /// Parent of each joint (−1 for the root).
    pub parents: Vec<i32>,
    /// Joint positions in the rest (bind) pose, metres.
    pub rest_joints: Vec<Vec3>,
    /// The pose the file shows: each joint's local rotation.
    pub pose: Vec<Quat>,
    /// Root translation of the pose shown (added to the root's rest position).
    pub translation: Vec3,
    /// Per vertex: up to 4 joint indices and their weights (summing to 1).
    pub joints: Vec<[u8; 4]>,
    pub weights: Vec<[f32; 4]>,
}

/// An animation for a skinned export: per frame, every joint's local rotation and the root's
/// translation, at `fps` frames per second.
#[derive(Clone, Debug, Default)]
pub struct ExportClip {
    pub name: String,
    pub fps: f32,
    pub rotations: Vec<Vec<Quat>>,
    pub translations: Vec<Vec3>,
}

/// Append `bytes` (4-byte aligned) to the binary chunk as one buffer view.
fn push_view(
    root: &mut json::Root,
    bin: &mut Vec<u8>,
    buffer: json::Index<json::Buffer>,
    bytes: &[u8],
    target: Option<json::buffer::Target>,
) -> json::Index<json::buffer::View> {
    pad4(bin);
    let offset = bin.len();
    bin.extend_from_slice(bytes);
    root.push(json::buffer::View {
        buffer,
        byte_length: USize64::from(bytes.len()),
        byte_offset: Some(USize64::from(offset)),
        byte_stride: None,
        extensions: None,
        extras: Default::default(),
        name: None,
        target: target.map(Valid),
    })
}

/// An accessor over a whole tightly packed view.
fn push_accessor(
    root: &mut json::Root,
    view: json::Index<json::buffer::View>,
    count: usize,
    ty: json::accessor::Type,
    ct: json::accessor::ComponentType,
    min: Option<json::Value>,
    max: Option<json::Value>,
) -> json::Index<json::Accessor> {
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
}

fn pad4(buf: &mut Vec<u8>) {
    while buf.len() % 4 != 0 {
        buf.push(0);
    }
}

/// Encode `mesh` as a .glb file (one scene, one node, one mesh primitive).
pub fn write_glb(mesh: &ExportMesh) -> Result<Vec<u8>, ExportError> {
    write_glb_full(mesh, None, None, &[])
}

fn check_skin(skin: &ExportSkin, n: usize, clips: &[ExportClip]) -> Result<(), ExportError> {
    let nj = skin.names.len();
    let bad = |m: String| Err(ExportError::Skin(m));
    if nj == 0 || nj > 255 {
        return bad(format!("{nj} joints (1…255 supported)"));
    }
    if skin.parents.len() != nj || skin.rest_joints.len() != nj || skin.pose.len() != nj {
        return bad("names, parents, rest joints and pose differ in length".into());
    }
    for (j, p) in skin.parents.iter().enumerate() {
        if (j == 0) != (*p < 0) || *p >= j as i32 {
            return bad(format!("joint {j}'s parent {p}: the root must be first and parents precede children"));
        }
    }
    if skin.joints.len() != n || skin.weights.len() != n {
        return bad(format!(
            "{} joint rows and {} weight rows for {n} vertices",
            skin.joints.len(),
            skin.weights.len()
        ));
    }
    if skin.joints.iter().flatten().any(|j| *j as usize >= nj) {
        return bad("a vertex names a joint that does not exist".into());
    }
    if let Some(i) = skin.weights.iter().position(|w| {
        let s: f32 = w.iter().sum();
        w.iter().any(|x| !x.is_finite() || *x < 0.0) || (s - 1.0).abs() > 1e-3
    }) {
        return bad(format!("vertex {i}'s weights {:?} are not ≥ 0 summing to 1", skin.weights[i]));
    }
    if skin.rest_joints.iter().any(|p| !p.is_finite()) || skin.pose.iter().any(|q| !q.is_finite()) {
        return bad("non-finite joint data".into());
    }
    for c in clips {
        let err = |m: String| Err(ExportError::Clip(c.name.clone(), m));
        if c.rotations.is_empty() || c.rotations.len() != c.translations.len() {
            return err(format!(
                "{} rotation frames and {} translation frames",
                c.rotations.len(),
                c.translations.len()
            ));
        }
        if !(c.fps > 0.0 && c.fps.is_finite()) {
            return err(format!("frame rate {}", c.fps));
        }
        if c.rotations.iter().any(|f| f.len() != nj || f.iter().any(|q| !q.is_finite())) {
            return err(format!("every frame needs {nj} finite rotations"));
        }
        if c.translations.iter().any(|t| !t.is_finite()) {
            return err("non-finite translation".into());
        }
    }
    Ok(())
}

/// Encode `mesh` as a .glb file with, optionally, a base-colour texture (PNG bytes, sRGB;
/// the mesh needs UVs, and its vertex colours are then left out, as glTF would multiply
/// them), a skin, and animations (which need the skin).
pub fn write_glb_full(
    mesh: &ExportMesh,
    base_color_png: Option<&[u8]>,
    skin: Option<&ExportSkin>,
    clips: &[ExportClip],
) -> Result<Vec<u8>, ExportError> {
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
    if base_color_png.is_some() && mesh.uvs.len() != n {
        return Err(ExportError::AttributeLength("uvs (needed by the texture)", mesh.uvs.len(), n));
    }
    if mesh.uvs.iter().any(|p| !p.is_finite()) {
        return Err(ExportError::NonFinite("uvs"));
    }
    match skin {
        Some(skin) => check_skin(skin, n, clips)?,
        None if !clips.is_empty() => return Err(ExportError::Skin("animations need a skin".into())),
        None => {}
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

    // One tightly packed vertex-attribute (or index) view + accessor.
    let push_attr = |root: &mut json::Root,
                     bytes: &[u8],
                     count: usize,
                     ty: json::accessor::Type,
                     ct: json::accessor::ComponentType,
                     target: json::buffer::Target,
                     min: Option<json::Value>,
                     max: Option<json::Value>,
                     bin: &mut Vec<u8>| {
        let view = push_view(root, bin, buffer, bytes, Some(target));
        push_accessor(root, view, count, ty, ct, min, max)
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
    if !mesh.colors.is_empty() && base_color_png.is_none() {
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
    if let Some(skin) = skin {
        let j: Vec<u8> = skin.joints.iter().flatten().copied().collect();
        let a = push_attr(&mut root, &j, n, Ty::Vec4, CT::U8, ArrayBuffer, None, None, &mut bin);
        attributes.insert(Valid(json::mesh::Semantic::Joints(0)), a);
        // Exactly normalised in f32: the largest weight takes the rounding.
        let w: Vec<f32> = skin
            .weights
            .iter()
            .flat_map(|w| {
                let s: f32 = w.iter().sum();
                let mut u = w.map(|x| x / s);
                let big = (0..4).max_by(|a, b| u[*a].total_cmp(&u[*b])).unwrap_or(0);
                u[big] = 0.0;
                u[big] = 1.0 - u.iter().sum::<f32>();
                u
            })
            .collect();
        let a = push_attr(
            &mut root,
            &f32_bytes(&mut w.into_iter()),
            n,
            Ty::Vec4,
            CT::F32,
            ArrayBuffer,
            None,
            None,
            &mut bin,
        );
        attributes.insert(Valid(json::mesh::Semantic::Weights(0)), a);
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
    // Skin data, animation data and the image go into the same buffer (no view targets).
    let push_data = |root: &mut json::Root,
                     bytes: &[u8],
                     count: usize,
                     ty: json::accessor::Type,
                     min: Option<json::Value>,
                     max: Option<json::Value>,
                     bin: &mut Vec<u8>| {
        let view = push_view(root, bin, buffer, bytes, None);
        push_accessor(root, view, count, ty, CT::F32, min, max)
    };
    let texture = match base_color_png {
        Some(png) => {
            let view = push_view(&mut root, &mut bin, buffer, png, None);
            let image = root.push(json::Image {
                buffer_view: Some(view),
                mime_type: Some(json::image::MimeType("image/png".into())),
                uri: None,
                extensions: None,
                extras: Default::default(),
                name: Some("base_color".into()),
            });
            let sampler = root.push(json::texture::Sampler {
                mag_filter: Some(Valid(json::texture::MagFilter::Linear)),
                min_filter: Some(Valid(json::texture::MinFilter::LinearMipmapLinear)),
                wrap_s: Valid(json::texture::WrappingMode::ClampToEdge),
                wrap_t: Valid(json::texture::WrappingMode::ClampToEdge),
                ..Default::default()
            });
            Some(root.push(json::Texture {
                sampler: Some(sampler),
                source: image,
                extensions: None,
                extras: Default::default(),
                name: None,
            }))
        }
        None => None,
    };

    let name = if mesh.name.is_empty() { "getavatar".to_string() } else { mesh.name.clone() };
    // Joint nodes, the skin and the animations.
    let mut scene_nodes = Vec::new();
    let mut skin_index = None;
    if let Some(skin) = skin {
        let nj = skin.names.len();
        let first = root.nodes.len() as u32;
        let local = |j: usize, root_t: Vec3| -> Vec3 {
            match skin.parents[j] {
                p if p < 0 => skin.rest_joints[j] + root_t,
                p => skin.rest_joints[j] - skin.rest_joints[p as usize],
            }
        };
        for j in 0..nj {
            let children: Vec<json::Index<json::Node>> =
                (0..nj).filter(|c| skin.parents[*c] == j as i32).map(|c| json::Index::new(first + c as u32)).collect();
            let q = skin.pose[j].normalize();
            root.push(json::Node {
                name: Some(skin.names[j].clone()),
                translation: Some(local(j, skin.translation).to_array()),
                rotation: Some(json::scene::UnitQuaternion([q.x, q.y, q.z, q.w])),
                children: (!children.is_empty()).then_some(children),
                ..Default::default()
            });
        }
        let ibm: Vec<f32> = skin.rest_joints.iter().flat_map(|p| Mat4::from_translation(-*p).to_cols_array()).collect();
        let ibm = push_data(&mut root, &f32_bytes(&mut ibm.into_iter()), nj, Ty::Mat4, None, None, &mut bin);
        let joints: Vec<json::Index<json::Node>> = (0..nj).map(|j| json::Index::new(first + j as u32)).collect();
        skin_index = Some(root.push(json::Skin {
            inverse_bind_matrices: Some(ibm),
            joints,
            skeleton: Some(json::Index::new(first)),
            name: Some("smpl".into()),
            extensions: None,
            extras: Default::default(),
        }));
        scene_nodes.push(json::Index::new(first));
        for clip in clips {
            let frames = clip.rotations.len();
            let times: Vec<f32> = (0..frames).map(|k| k as f32 / clip.fps).collect();
            let t_max = times[frames - 1];
            let input = push_data(
                &mut root,
                &f32_bytes(&mut times.into_iter()),
                frames,
                Ty::Scalar,
                Some(json::Value::from(vec![0.0f32])),
                Some(json::Value::from(vec![t_max])),
                &mut bin,
            );
            let mut samplers = Vec::new();
            let mut channels = Vec::new();
            let mut channel = |samplers: &mut Vec<json::animation::Sampler>,
                               output: json::Index<json::Accessor>,
                               node: u32,
                               path: json::animation::Property| {
                samplers.push(json::animation::Sampler {
                    input,
                    interpolation: Valid(json::animation::Interpolation::Linear),
                    output,
                    extensions: None,
                    extras: Default::default(),
                });
                channels.push(json::animation::Channel {
                    sampler: json::Index::new(samplers.len() as u32 - 1),
                    target: json::animation::Target {
                        node: json::Index::new(node),
                        path: Valid(path),
                        extensions: None,
                        extras: Default::default(),
                    },
                    extensions: None,
                    extras: Default::default(),
                });
            };
            for j in 0..nj {
                // Consecutive quaternions in one hemisphere: slerp takes the short way.
                let mut prev = Quat::IDENTITY;
                let q: Vec<f32> = clip
                    .rotations
                    .iter()
                    .flat_map(|f| {
                        let mut q = f[j].normalize();
                        if q.dot(prev) < 0.0 {
                            q = -q;
                        }
                        prev = q;
                        q.to_array()
                    })
                    .collect();
                let out = push_data(&mut root, &f32_bytes(&mut q.into_iter()), frames, Ty::Vec4, None, None, &mut bin);
                channel(&mut samplers, out, first + j as u32, json::animation::Property::Rotation);
            }
            let t: Vec<f32> = clip.translations.iter().flat_map(|t| local(0, *t).to_array()).collect();
            let out = push_data(&mut root, &f32_bytes(&mut t.into_iter()), frames, Ty::Vec3, None, None, &mut bin);
            channel(&mut samplers, out, first, json::animation::Property::Translation);
            root.push(json::Animation {
                channels,
                samplers,
                name: Some(clip.name.clone()),
                extensions: None,
                extras: Default::default(),
            });
        }
    }
    pad4(&mut bin);
    root.buffers[0].byte_length = USize64::from(bin.len());

    let material = root.push(json::Material {
        pbr_metallic_roughness: json::material::PbrMetallicRoughness {
            base_color_factor: json::material::PbrBaseColorFactor([1.0, 1.0, 1.0, 1.0]),
            base_color_texture: texture.map(|index| json::texture::Info {
                index,
                tex_coord: 0,
                extensions: None,
                extras: Default::default(),
            }),
            metallic_factor: json::material::StrengthFactor(0.0),
            roughness_factor: json::material::StrengthFactor(0.8),
            ..Default::default()
        },
        double_sided: false,
        name: Some("avatar".into()),
        ..Default::default()
    });
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
    let node = root.push(json::Node { mesh: Some(gl_mesh), name: Some(name), skin: skin_index, ..Default::default() });
    scene_nodes.insert(0, node);
    let scene = root.push(json::Scene { extensions: None, extras: Default::default(), name: None, nodes: scene_nodes });
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
