//! Rigging a generated avatar to the body (the interactive fast path): an avatar extracted
//! once in the canonical pose, each vertex following its nearest canonical body vertex's
//! skinning transform, so re-posing is LBS (paper eq. 1) with no network and no extraction.
//! [`repose_transform`] is the one definition of that transform; the web viewer's vertex
//! shader applies the same matrices on the GPU.

use glam::{Mat3, Mat4};

use crate::generator::Avatar;
use crate::geometry::inverse_skinning::nearest_rotation;
use crate::geometry::BodyContext;
use crate::gltf_export::{write_glb_full, ExportError, ExportMesh};
use crate::motion::Motion;
use crate::skin_export::{motion_clip, smpl_skin};
use crate::skinning::{pose_body, BodyParams, PosedBody};

/// An avatar extracted in the canonical pose and rigged to the body.
#[derive(Clone, Debug)]
pub struct RiggedAvatar {
    /// Canonical (Da-pose) mesh; `attributes` = canonical coordinates.
    pub canonical: Avatar,
    /// Nearest canonical body vertex of each avatar vertex.
    pub body_vertex: Vec<u32>,
}

impl RiggedAvatar {
    /// Rig an avatar generated in the canonical pose (Da-pose, β = 0).
    pub fn new(canonical: Avatar, ctx: &BodyContext) -> Self {
        let tree = crate::spatial::KdTree::new(&ctx.canonical.vertices);
        let body_vertex =
            canonical.mesh.vertices.iter().map(|v| tree.nearest(*v).map_or(0, |(i, _)| i as u32)).collect();
        Self { canonical, body_vertex }
    }

    /// Vertices and normals in the pose/shape of `posed` (from `pose_body`).
    pub fn repose(&self, ctx: &BodyContext, posed: &PosedBody) -> (Vec<glam::Vec3>, Vec<glam::Vec3>) {
        let mut cache: std::collections::HashMap<u32, (Mat4, Mat3)> = std::collections::HashMap::new();
        let mut verts = Vec::with_capacity(self.body_vertex.len());
        let mut normals = Vec::with_capacity(self.body_vertex.len());
        for ((v, n), &b) in self.canonical.mesh.vertices.iter().zip(&self.canonical.normals).zip(&self.body_vertex) {
            let (m, r) = *cache.entry(b).or_insert_with(|| repose_transform(ctx, posed, b as usize));
            verts.push(m.transform_point3(*v));
            normals.push((r * *n).normalize_or_zero());
        }
        (verts, normals)
    }
}

/// The transform that re-poses canonical points rigged to body vertex `i` into the pose/shape
/// of `posed` — the posed blended transform, the shape offset, and the inverse canonical
/// transform — and the rotation for normals (nearest to the linear part, paper eq. 4). Used
/// by [`RiggedAvatar::repose`] on the CPU and by the web viewer's GPU skinning.
pub fn repose_transform(ctx: &BodyContext, posed: &PosedBody, i: usize) -> (Mat4, Mat3) {
    let shape = posed.shaped[i] - ctx.model.v_template[i];
    let m = posed.vertex_transforms[i] * Mat4::from_translation(shape) * ctx.canonical.vertex_transforms[i].inverse();
    let r = nearest_rotation(
        Mat3::from_mat4(posed.vertex_transforms[i]) * Mat3::from_mat4(ctx.canonical.vertex_transforms[i]).inverse(),
    );
    (m, r)
}

impl RiggedAvatar {
    /// Vertices and normals in the body's rest pose (T-pose, θ = 0) at shape `betas`: the
    /// bind pose of an animated export (see [`crate::gltf_export`]).
    pub fn bind_pose(&self, ctx: &BodyContext, betas: &[f32]) -> (Vec<glam::Vec3>, Vec<glam::Vec3>) {
        let rest = BodyParams { betas: betas.to_vec(), ..BodyParams::default() };
        self.repose(ctx, &pose_body(&ctx.model, &rest))
    }

    /// The avatar as an animated .glb: bound in the rest pose, showing `params` (pose, shape,
    /// translation), with one animation per motion. Colours: the texture image `texture`
    /// (PNG bytes) at `uvs` when given, else the avatar's vertex colours.
    pub fn animated_glb(
        &self,
        ctx: &BodyContext,
        params: &BodyParams,
        motions: &[Motion],
        texture: Option<(&[glam::Vec2], &[u8])>,
        name: &str,
    ) -> Result<Vec<u8>, ExportError> {
        let (positions, normals) = self.bind_pose(ctx, &params.betas);
        let weights = self.body_vertex.iter().map(|b| &ctx.model.weights[*b as usize]);
        let skin = smpl_skin(&ctx.model, params, weights);
        let clips: Vec<_> = motions.iter().map(motion_clip).collect();
        let mesh = ExportMesh {
            positions,
            normals,
            colors: self.canonical.colors.clone(),
            uvs: texture.map_or(Vec::new(), |t| t.0.to_vec()),
            indices: self.canonical.mesh.faces.clone(),
            name: name.to_string(),
        };
        write_glb_full(&mesh, texture.map(|t| t.1), Some(&skin), &clips)
    }
}
