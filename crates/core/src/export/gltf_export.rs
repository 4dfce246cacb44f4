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

/// A glTF document being written: the JSON root and its one binary buffer (the GLB's BIN
/// chunk). The steps of [`write_glb_full`] and of the VRM files ([`crate::export::vrm_export`]) push
/// into it in the order the file lists them.
pub(crate) struct GlbBuilder {
    pub(crate) root: json::Root,
    bin: Vec<u8>,
    buffer: json::Index<json::Buffer>,
}

use json::accessor::{ComponentType as CT, Type as Ty};

fn f32_bytes(v: impl Iterator<Item = f32>) -> Vec<u8> {
    v.flat_map(f32::to_le_bytes).collect()
}

impl GlbBuilder {
    pub(crate) fn new() -> Self {
        let mut root = json::Root::default();
        let buffer = root.push(json::Buffer {
            byte_length: USize64(0),
            extensions: None,
            extras: Default::default(),
            name: None,
            uri: None,
        });
        Self { root, bin: Vec::new(), buffer }
    }

    /// Append `bytes` (4-byte aligned) to the binary chunk as one buffer view.
    fn view(&mut self, bytes: &[u8], target: Option<json::buffer::Target>) -> json::Index<json::buffer::View> {
        pad4(&mut self.bin);
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        self.root.push(json::buffer::View {
            buffer: self.buffer,
            byte_length: USize64::from(bytes.len()),
            byte_offset: Some(USize64::from(offset)),
            byte_stride: None,
            extensions: None,
            extras: Default::default(),
            name: None,
            target: target.map(Valid),
        })
    }

    /// A view of `bytes` and an accessor over all of it (tightly packed).
    #[allow(clippy::too_many_arguments)]
    fn accessor(
        &mut self,
        bytes: &[u8],
        count: usize,
        ty: json::accessor::Type,
        ct: json::accessor::ComponentType,
        target: Option<json::buffer::Target>,
        min: Option<json::Value>,
        max: Option<json::Value>,
    ) -> json::Index<json::Accessor> {
        let view = self.view(bytes, target);
        self.root.push(json::Accessor {
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

    /// A vertex attribute (an array-buffer view).
    fn attribute(
        &mut self,
        values: impl Iterator<Item = f32>,
        n: usize,
        ty: json::accessor::Type,
    ) -> json::Index<json::Accessor> {
        self.accessor(&f32_bytes(values), n, ty, CT::F32, Some(json::buffer::Target::ArrayBuffer), None, None)
    }

    /// Skin, animation or other non-vertex f32 data (no view target).
    fn data(
        &mut self,
        values: impl Iterator<Item = f32>,
        count: usize,
        ty: json::accessor::Type,
        min: Option<json::Value>,
        max: Option<json::Value>,
    ) -> json::Index<json::Accessor> {
        self.accessor(&f32_bytes(values), count, ty, CT::F32, None, min, max)
    }

    /// The primitive's vertex attributes: positions (with bounds), unit normals, vertex
    /// colours (left out under a texture, which glTF would multiply by them), UVs, and the
    /// skin's joints and weights.
    fn vertex_attributes(
        &mut self,
        mesh: &ExportMesh,
        textured: bool,
        skin: Option<&ExportSkin>,
    ) -> std::collections::BTreeMap<json::validation::Checked<json::mesh::Semantic>, json::Index<json::Accessor>> {
        use json::mesh::Semantic;
        let n = mesh.positions.len();
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        for p in &mesh.positions {
            lo = lo.min(*p);
            hi = hi.max(*p);
        }
        let mut attributes = std::collections::BTreeMap::new();
        let pos = self.accessor(
            &f32_bytes(mesh.positions.iter().flat_map(|p| p.to_array())),
            n,
            Ty::Vec3,
            CT::F32,
            Some(json::buffer::Target::ArrayBuffer),
            Some(json::Value::from(lo.to_array().to_vec())),
            Some(json::Value::from(hi.to_array().to_vec())),
        );
        attributes.insert(Valid(Semantic::Positions), pos);
        if !mesh.normals.is_empty() {
            // Unit length is required by the spec; renormalise and replace degenerate ones.
            let unit = mesh.normals.iter().flat_map(|v| {
                let u = v.normalize_or_zero();
                if u == Vec3::ZERO {
                    [0.0, 1.0, 0.0]
                } else {
                    u.to_array()
                }
            });
            attributes.insert(Valid(Semantic::Normals), self.attribute(unit, n, Ty::Vec3));
        }
        if !mesh.colors.is_empty() && !textured {
            let c = mesh.colors.iter().flat_map(|c| c.clamp(Vec3::ZERO, Vec3::ONE).to_array());
            attributes.insert(Valid(Semantic::Colors(0)), self.attribute(c, n, Ty::Vec3));
        }
        if !mesh.uvs.is_empty() {
            let uv = mesh.uvs.iter().flat_map(|c| c.to_array());
            attributes.insert(Valid(Semantic::TexCoords(0)), self.attribute(uv, n, Ty::Vec2));
        }
        if let Some(skin) = skin {
            let j: Vec<u8> = skin.joints.iter().flatten().copied().collect();
            let a = self.accessor(&j, n, Ty::Vec4, CT::U8, Some(json::buffer::Target::ArrayBuffer), None, None);
            attributes.insert(Valid(Semantic::Joints(0)), a);
            // Exactly normalised in f32: the largest weight takes the rounding.
            let w = skin.weights.iter().flat_map(|w| {
                let s: f32 = w.iter().sum();
                let mut u = w.map(|x| x / s);
                let big = (0..4).max_by(|a, b| u[*a].total_cmp(&u[*b])).unwrap_or(0);
                u[big] = 0.0;
                u[big] = 1.0 - u.iter().sum::<f32>();
                u
            });
            attributes.insert(Valid(Semantic::Weights(0)), self.attribute(w, n, Ty::Vec4));
        }
        attributes
    }

    /// The triangle indices (an element-array view).
    fn indices(&mut self, mesh: &ExportMesh) -> json::Index<json::Accessor> {
        let bytes: Vec<u8> = mesh.indices.iter().flatten().flat_map(|i| i.to_le_bytes()).collect();
        self.accessor(
            &bytes,
            mesh.indices.len() * 3,
            Ty::Scalar,
            CT::U32,
            Some(json::buffer::Target::ElementArrayBuffer),
            None,
            None,
        )
    }

    /// A PNG image in the buffer, its sampler (linear, mipmapped, clamped) and the texture.
    pub(crate) fn png_texture(&mut self, png: &[u8], name: &str) -> json::Index<json::Texture> {
        let view = self.view(png, None);
        let image = self.root.push(json::Image {
            buffer_view: Some(view),
            mime_type: Some(json::image::MimeType("image/png".into())),
            uri: None,
            extensions: None,
            extras: Default::default(),
            name: Some(name.into()),
        });
        let sampler = self.root.push(json::texture::Sampler {
            mag_filter: Some(Valid(json::texture::MagFilter::Linear)),
            min_filter: Some(Valid(json::texture::MinFilter::LinearMipmapLinear)),
            wrap_s: Valid(json::texture::WrappingMode::ClampToEdge),
            wrap_t: Valid(json::texture::WrappingMode::ClampToEdge),
            ..Default::default()
        });
        self.root.push(json::Texture {
            sampler: Some(sampler),
            source: image,
            extensions: None,
            extras: Default::default(),
            name: None,
        })
    }

    /// The skeleton's joints as nodes (one per joint, parents before children, the pose shown
    /// as their local transforms); returns the node index of joint 0 (joint j is node
    /// `first + j`).
    pub(crate) fn joint_nodes(&mut self, skin: &ExportSkin) -> u32 {
        let nj = skin.names.len();
        let first = self.root.nodes.len() as u32;
        for j in 0..nj {
            let children: Vec<json::Index<json::Node>> =
                (0..nj).filter(|c| skin.parents[*c] == j as i32).map(|c| json::Index::new(first + c as u32)).collect();
            let q = skin.pose[j].normalize();
            self.root.push(json::Node {
                name: Some(skin.names[j].clone()),
                translation: Some(skin.local_translation(j, skin.translation).to_array()),
                rotation: Some(json::scene::UnitQuaternion([q.x, q.y, q.z, q.w])),
                children: (!children.is_empty()).then_some(children),
                ..Default::default()
            });
        }
        first
    }

    /// The glTF skin over joint nodes `first..`: inverse bind matrices of the rest pose.
    fn skin(&mut self, skin: &ExportSkin, first: u32) -> json::Index<json::Skin> {
        let nj = skin.names.len();
        let ibm = skin.rest_joints.iter().flat_map(|p| Mat4::from_translation(-*p).to_cols_array());
        let ibm = self.data(ibm, nj, Ty::Mat4, None, None);
        let joints: Vec<json::Index<json::Node>> = (0..nj).map(|j| json::Index::new(first + j as u32)).collect();
        self.root.push(json::Skin {
            inverse_bind_matrices: Some(ibm),
            joints,
            skeleton: Some(json::Index::new(first)),
            name: Some("smpl".into()),
            extensions: None,
            extras: Default::default(),
        })
    }

    /// One animation: every joint's rotation and the root's translation per frame, LINEAR.
    pub(crate) fn animation(&mut self, clip: &ExportClip, skin: &ExportSkin, first: u32) {
        let nj = skin.names.len();
        let frames = clip.rotations.len();
        let times: Vec<f32> = (0..frames).map(|k| k as f32 / clip.fps).collect();
        let t_max = times[frames - 1];
        let input = self.data(
            times.into_iter(),
            frames,
            Ty::Scalar,
            Some(json::Value::from(vec![0.0f32])),
            Some(json::Value::from(vec![t_max])),
        );
        let mut samplers = Vec::new();
        let mut channels = Vec::new();
        let mut channel = |output: json::Index<json::Accessor>, node: u32, path: json::animation::Property| {
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
            let out = self.data(q.into_iter(), frames, Ty::Vec4, None, None);
            channel(out, first + j as u32, json::animation::Property::Rotation);
        }
        let t = clip.translations.iter().flat_map(|t| skin.local_translation(0, *t).to_array());
        let out = self.data(t, frames, Ty::Vec3, None, None);
        channel(out, first, json::animation::Property::Translation);
        self.root.push(json::Animation {
            channels,
            samplers,
            name: Some(clip.name.clone()),
            extensions: None,
            extras: Default::default(),
        });
    }

    /// The mesh (one primitive, one PBR material: white or the base-colour texture,
    /// metallic 0, roughness 0.8) and its node, skinned by `skin` when given.
    fn mesh_node(
        &mut self,
        mesh: &ExportMesh,
        attributes: std::collections::BTreeMap<
            json::validation::Checked<json::mesh::Semantic>,
            json::Index<json::Accessor>,
        >,
        indices: json::Index<json::Accessor>,
        texture: Option<json::Index<json::Texture>>,
        skin: Option<json::Index<json::Skin>>,
    ) -> json::Index<json::Node> {
        let material = self.root.push(json::Material {
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
        let name = if mesh.name.is_empty() { "getavatar".to_string() } else { mesh.name.clone() };
        let gl_mesh = self.root.push(json::Mesh {
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
        self.root.push(json::Node { mesh: Some(gl_mesh), name: Some(name), skin, ..Default::default() })
    }

    /// The scene of `nodes`, the generator string and the buffer's length; then the JSON
    /// (as `serde_json`'s value, for extensions the `gltf-json` types do not know) and the
    /// binary chunk.
    pub(crate) fn finish(mut self, nodes: Vec<json::Index<json::Node>>) -> (json::Root, Vec<u8>) {
        pad4(&mut self.bin);
        self.root.buffers[0].byte_length = USize64::from(self.bin.len());
        let scene = self.root.push(json::Scene { extensions: None, extras: Default::default(), name: None, nodes });
        self.root.scene = Some(scene);
        self.root.asset.generator = Some(format!("getavatar {}", env!("CARGO_PKG_VERSION")));
        (self.root, self.bin)
    }
}

impl ExportSkin {
    /// Joint `j`'s translation relative to its parent (the root's: its rest position plus
    /// `root_translation`).
    pub(crate) fn local_translation(&self, j: usize, root_translation: Vec3) -> Vec3 {
        match self.parents[j] {
            p if p < 0 => self.rest_joints[j] + root_translation,
            p => self.rest_joints[j] - self.rest_joints[p as usize],
        }
    }
}

fn pad4(buf: &mut Vec<u8>) {
    while buf.len() % 4 != 0 {
        buf.push(0);
    }
}

/// A GLB container of a JSON document (any serialisable form: `gltf-json`'s root, or a
/// `serde_json` value with extensions added) and its binary chunk.
pub(crate) fn glb_bytes(json: &impl serde::Serialize, bin: Vec<u8>) -> Result<Vec<u8>, ExportError> {
    let json_string = serde_json::to_string(json).map_err(|e| ExportError::Serialize(e.to_string()))?;
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

/// Encode `mesh` as a .glb file (one scene, one node, one mesh primitive).
pub fn write_glb(mesh: &ExportMesh) -> Result<Vec<u8>, ExportError> {
    write_glb_full(mesh, None, None, &[])
}

pub(crate) fn check_skin(skin: &ExportSkin, n: usize, clips: &[ExportClip]) -> Result<(), ExportError> {
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

/// Check `mesh` (and the skin and clips given with it) for what a valid file needs.
fn check_mesh(
    mesh: &ExportMesh,
    base_color_png: Option<&[u8]>,
    skin: Option<&ExportSkin>,
    clips: &[ExportClip],
) -> Result<(), ExportError> {
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
        Some(skin) => check_skin(skin, n, clips),
        None if !clips.is_empty() => Err(ExportError::Skin("animations need a skin".into())),
        None => Ok(()),
    }
}

/// The mesh's node (and, with a skin, its joint nodes and the glTF skin) written into `b`;
/// the scene's nodes, mesh first. Shared by the .glb and the .vrm.
pub(crate) fn push_mesh(
    b: &mut GlbBuilder,
    mesh: &ExportMesh,
    base_color_png: Option<&[u8]>,
    skin: Option<&ExportSkin>,
    clips: &[ExportClip],
) -> Result<(Vec<json::Index<json::Node>>, Option<u32>), ExportError> {
    check_mesh(mesh, base_color_png, skin, clips)?;
    let attributes = b.vertex_attributes(mesh, base_color_png.is_some(), skin);
    let indices = b.indices(mesh);
    let texture = base_color_png.map(|png| b.png_texture(png, "base_color"));
    let mut scene_nodes = Vec::new();
    let mut skin_index = None;
    let mut first_joint = None;
    if let Some(skin) = skin {
        let first = b.joint_nodes(skin);
        skin_index = Some(b.skin(skin, first));
        scene_nodes.push(json::Index::new(first));
        for clip in clips {
            b.animation(clip, skin, first);
        }
        first_joint = Some(first);
    }
    scene_nodes.insert(0, b.mesh_node(mesh, attributes, indices, texture, skin_index));
    Ok((scene_nodes, first_joint))
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
    let mut b = GlbBuilder::new();
    let (nodes, _) = push_mesh(&mut b, mesh, base_color_png, skin, clips)?;
    let (root, bin) = b.finish(nodes);
    glb_bytes(&root, bin)
}
