//! Rigging a generated avatar to the body (the interactive fast path): an avatar extracted
//! once in the canonical pose, each vertex following its nearest canonical body vertex's
//! skinning transform, so re-posing is LBS (paper eq. 1) with no network and no extraction.
//! [`repose_transform`] is the one definition of that transform; the web viewer's vertex
//! shader applies the same matrices on the GPU.

use glam::{Mat3, Mat4};

use crate::body::body_fit::refit::OutlineMesh;
use crate::body::humanoid::SkeletonNames;
use crate::body::motion::Motion;
use crate::body::skinning::{pose_body, BodyParams, PosedBody};
use crate::export::gltf_export::{write_glb_full, ExportError, ExportMesh};
use crate::export::skin_export::{motion_clip, smpl_skin, vrm_frame, vrm_rest_skin};
use crate::export::uv_atlas::{
    bake_image_async, texel_points_async, transfer_body_uvs_async, AtlasError, BodyUvs, UvAtlas,
};
use crate::export::vrm_export::{write_vrm, VrmMeta};
use crate::generator::network::synthesis::Triplanes;
use crate::generator::pipeline::{recolor_async, Avatar, Generator, Styles};
use crate::generator::readback::ReadbackError;
use crate::geometry::inverse_skinning::nearest_rotation;
use crate::geometry::BodyContext;
use crate::reconstruction::photo_projection::{PhotoProjection, SourcePhoto};
use crate::reconstruction::silhouette_snap::{
    body_vertex_parts, silhouette_offsets_async, OutlineParts, SnapReport, NO_PART,
};
use crate::util::cooperative::checkpoint;
use burn::tensor::Device;

/// An avatar extracted in the canonical pose and rigged to the body.
#[derive(Clone, Debug)]
pub struct RiggedAvatar {
    /// Canonical (Da-pose) mesh; `attributes` = canonical coordinates.
    pub canonical: Avatar,
    /// Nearest canonical body vertex of each avatar vertex.
    pub body_vertex: Vec<u32>,
    /// The bind pose at one shape, computed ahead ([`RiggedAvatar::keep_bind_pose_async`]).
    /// Only [`RiggedAvatar::snap_to_photo`] changes `canonical`'s geometry after rigging (and
    /// drops it); re-texturing changes its colours only.
    bind: Option<BindPose>,
}

/// Vertices and normals in the rest pose at shape `betas`.
#[derive(Clone, Debug)]
struct BindPose {
    betas: Vec<f32>,
    positions: Vec<glam::Vec3>,
    normals: Vec<glam::Vec3>,
}

impl RiggedAvatar {
    /// Rig an avatar generated in the canonical pose (Da-pose, β = 0). The nearest body
    /// vertices come from the canonical inverse skinning's k-d tree, which every new identity
    /// has already built (`BodyContext::canonical_inverse`), not from a tree per avatar.
    pub fn new(canonical: Avatar, ctx: &BodyContext) -> Self {
        let inv = ctx.canonical_inverse();
        let body_vertex =
            canonical.mesh.vertices.iter().map(|v| inv.nearest_body_vertex(*v).map_or(0, |i| i as u32)).collect();
        Self { canonical, body_vertex, bind: None }
    }

    /// Vertices and normals in the pose/shape of `posed` (from `pose_body`).
    pub fn repose(&self, ctx: &BodyContext, posed: &PosedBody) -> (Vec<glam::Vec3>, Vec<glam::Vec3>) {
        let mut cache: crate::geometry::id_map::IdMap<u32, (Mat4, Mat3)> = Default::default();
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
    /// bind pose of an animated export (see [`crate::export::gltf_export`]).
    /// The one kept by [`RiggedAvatar::keep_bind_pose_async`] when `betas` are its shape.
    pub fn bind_pose(&self, ctx: &BodyContext, betas: &[f32]) -> (Vec<glam::Vec3>, Vec<glam::Vec3>) {
        if let Some(b) = self.bind.as_ref().filter(|b| b.betas == betas) {
            return (b.positions.clone(), b.normals.clone());
        }
        let rest = BodyParams { betas: betas.to_vec(), ..BodyParams::default() };
        self.repose(ctx, &pose_body(&ctx.model, &rest))
    }

    /// The avatar as the body fit's outline ([`crate::body::body_fit::refit`]): its vertices
    /// in the rest pose at β = 0, each following its nearest body vertex, and its faces.
    pub fn outline_mesh(&self, ctx: &BodyContext) -> OutlineMesh {
        let (rest, _) = self.bind_pose(ctx, &vec![0.0; ctx.model.num_betas]);
        OutlineMesh { rest, body_vertex: self.body_vertex.clone(), faces: self.canonical.mesh.faces.clone() }
    }

    /// Compute the bind pose at `betas` now, in slices, and keep it for
    /// [`RiggedAvatar::bind_pose`]: the browser's viewer asks for it inside a frame (its mesh
    /// upload), where the body's shaping and the re-pose would block the UI thread.
    pub async fn keep_bind_pose_async(&mut self, ctx: &BodyContext, betas: &[f32]) {
        let rest = pose_body(&ctx.model, &BodyParams { betas: betas.to_vec(), ..BodyParams::default() });
        checkpoint().await;
        let (positions, normals) = self.repose(ctx, &rest);
        self.bind = Some(BindPose { betas: betas.to_vec(), positions, normals });
    }

    /// The mesh to export from per-avatar-vertex `positions` and `normals`: with a baked
    /// texture, the atlas' vertices (seams split) with their UVs, else the avatar's own with
    /// its vertex colours; and the avatar vertex each exported vertex copies. A texture
    /// baked for another mesh (a bake that finished after the avatar changed) is refused.
    fn export_mesh(
        &self,
        positions: Vec<glam::Vec3>,
        normals: Vec<glam::Vec3>,
        texture: Option<&BakedTexture>,
        name: &str,
    ) -> Result<(ExportMesh, Vec<u32>), ExportError> {
        match texture {
            Some(t) => {
                self.check_atlas(&t.atlas)?;
                let src = &t.atlas.source;
                let mesh = ExportMesh {
                    positions: src.iter().map(|v| positions[*v as usize]).collect(),
                    normals: src.iter().map(|v| normals[*v as usize]).collect(),
                    colors: Vec::new(),
                    uvs: t.atlas.uvs.clone(),
                    indices: t.atlas.faces.clone(),
                    name: name.to_string(),
                };
                Ok((mesh, src.clone()))
            }
            None => {
                let mesh = ExportMesh {
                    positions,
                    normals,
                    colors: self.canonical.colors.clone(),
                    uvs: Vec::new(),
                    indices: self.canonical.mesh.faces.clone(),
                    name: name.to_string(),
                };
                Ok((mesh, (0..self.body_vertex.len() as u32).collect()))
            }
        }
    }

    /// Whether `atlas` was built for this avatar's mesh: every atlas vertex copies one of its
    /// vertices, and atlas triangle t's corners copy avatar triangle t's.
    fn check_atlas(&self, atlas: &UvAtlas) -> Result<(), ExportError> {
        let (faces, n) = (&self.canonical.mesh.faces, self.body_vertex.len());
        let mismatch = |what: String| Err(ExportError::TextureMismatch(what));
        if atlas.faces.len() != faces.len() || atlas.uvs.len() != atlas.source.len() {
            return mismatch(format!(
                "its atlas has {} triangles and {} UVs for {} vertices, the avatar {} triangles",
                atlas.faces.len(),
                atlas.uvs.len(),
                atlas.source.len(),
                faces.len()
            ));
        }
        if let Some(v) = atlas.source.iter().find(|v| **v as usize >= n) {
            return mismatch(format!("its atlas copies vertex {v}, the avatar has {n}"));
        }
        let corners = |af: &[u32; 3]| af.map(|a| atlas.source.get(a as usize).copied());
        match atlas.faces.iter().zip(faces).position(|(af, f)| corners(af) != f.map(Some)) {
            Some(t) => mismatch(format!("its triangle {t} copies other vertices than the avatar's triangle {t}")),
            None => Ok(()),
        }
    }

    /// The avatar as a static .glb in the pose/shape of `params`, textured when `texture` is
    /// given.
    pub fn posed_glb(
        &self,
        ctx: &BodyContext,
        params: &BodyParams,
        texture: Option<&BakedTexture>,
        name: &str,
    ) -> Result<Vec<u8>, ExportError> {
        let (positions, normals) = self.repose(ctx, &pose_body(&ctx.model, params));
        let (mesh, _) = self.export_mesh(positions, normals, texture, name)?;
        write_glb_full(&mesh, texture.map(|t| t.png.as_slice()), None, &[])
    }

    /// The avatar as an animated .glb: bound in the rest pose, showing `params` (pose, shape,
    /// translation), with one animation per motion; textured when `texture` is given, else
    /// vertex-coloured; the joints' nodes named by `names`.
    pub fn animated_glb(
        &self,
        ctx: &BodyContext,
        params: &BodyParams,
        motions: &[Motion],
        texture: Option<&BakedTexture>,
        name: &str,
        names: SkeletonNames,
    ) -> Result<Vec<u8>, ExportError> {
        let (mesh, skin) = self.skinned_mesh(ctx, params, texture, name, names)?;
        let clips: Vec<_> = motions.iter().map(motion_clip).collect();
        write_glb_full(&mesh, texture.map(|t| t.png.as_slice()), Some(&skin), &clips)
    }

    /// The mesh bound in the rest pose at `params.betas` and its skin showing `params`.
    fn skinned_mesh(
        &self,
        ctx: &BodyContext,
        params: &BodyParams,
        texture: Option<&BakedTexture>,
        name: &str,
        names: SkeletonNames,
    ) -> Result<(ExportMesh, crate::export::gltf_export::ExportSkin), ExportError> {
        let (positions, normals) = self.bind_pose(ctx, &params.betas);
        let (mesh, source) = self.export_mesh(positions, normals, texture, name)?;
        let weights = source.iter().map(|v| &ctx.model.weights[self.body_vertex[*v as usize] as usize]);
        Ok((mesh, smpl_skin(&ctx.model, params, weights, names)))
    }

    /// Where the avatar stands in VRM's frame at shape `betas`: the body's frame
    /// ([`vrm_frame`]), but with the avatar's own lowest rest vertex at y = 0 (its shoes
    /// reach below the body's soles).
    pub fn vrm_frame(
        &self,
        ctx: &BodyContext,
        betas: &[f32],
    ) -> Result<crate::export::skin_export::VrmFrame, ExportError> {
        let mut frame = vrm_frame(&ctx.model, betas)?;
        let lowest = self.bind_pose(ctx, betas).0.iter().map(|v| v.y).fold(f32::INFINITY, f32::min);
        if !lowest.is_finite() {
            return Err(ExportError::Empty);
        }
        frame.offset = glam::Vec3::new(0.0, -lowest, 0.0);
        Ok(frame)
    }

    /// The avatar as a VRM 1.0 file: the body's rest T-pose at shape `betas`, its lowest
    /// vertex at y = 0, the humanoid bone map, `meta`'s licence; textured when `texture` is
    /// given. No animations (VRM keeps them in `.vrma` files).
    pub fn vrm(
        &self,
        ctx: &BodyContext,
        betas: &[f32],
        texture: Option<&BakedTexture>,
        meta: &VrmMeta,
        names: SkeletonNames,
    ) -> Result<Vec<u8>, ExportError> {
        let frame = self.vrm_frame(ctx, betas)?;
        let rest = BodyParams { betas: betas.to_vec(), ..BodyParams::default() };
        let (mut mesh, skin) = self.skinned_mesh(ctx, &rest, texture, &meta.name, names)?;
        for p in &mut mesh.positions {
            *p += frame.offset;
        }
        let skin = vrm_rest_skin(skin, &frame);
        write_vrm(&mesh, texture.map(|t| t.png.as_slice()), &skin, meta, frame.eyes_from_head)
    }
}

/// An avatar's texture baked into its atlas ([`crate::export::uv_atlas`]).
#[derive(Clone, Debug)]
pub struct BakedTexture {
    pub atlas: UvAtlas,
    /// Side of the square image, texels.
    pub res: usize,
    /// sRGB 8-bit RGB, row-major from the top left.
    pub rgb: Vec<u8>,
    /// The same image as PNG.
    pub png: Vec<u8>,
    /// Texels the charts cover.
    pub covered: usize,
}

#[derive(Debug, thiserror::Error)]
pub enum BakeError {
    #[error("texture atlas: {0}")]
    Atlas(#[from] AtlasError),
    #[error("texture field: {0}")]
    Readback(#[from] ReadbackError),
    #[error("cannot encode the texture PNG: {0}")]
    Png(String),
    #[error("texture resolution {0} (64…4096)")]
    Resolution(usize),
    #[error("{0} texture colours (or some not finite) for {1} texels")]
    Colours(usize, usize),
}

/// Texture-field queries per batch (bounds the decoder's activations). Every batch of a bake
/// has exactly this many points, the last padded: the GPU then compiles one set of kernels for
/// every bake, which the app compiles while the model loads ([`warm_bake_kernels`]). A new
/// shape compiles new matmul kernels: single tasks of 0.2–0.4 s in the browser.
pub const BAKE_BATCH: usize = 16_384;

/// Texture-field colours at `points`, in batches of [`BAKE_BATCH`] (the last padded).
pub async fn bake_queries(
    g: &Generator,
    planes: &Triplanes,
    s: &Styles,
    points: &[glam::Vec3],
    device: &Device,
) -> Result<Vec<glam::Vec3>, ReadbackError> {
    let mut colors = Vec::with_capacity(points.len());
    for chunk in points.chunks(BAKE_BATCH) {
        let mut batch = chunk.to_vec();
        batch.resize(BAKE_BATCH, chunk[0]);
        let c = recolor_async(g, planes, s, &batch, device).await?;
        colors.extend_from_slice(&c[..chunk.len()]);
    }
    Ok(colors)
}

/// Compile the bake's kernels: one batch of texture-field queries, its colours dropped.
pub async fn warm_bake_kernels(
    g: &Generator,
    planes: &Triplanes,
    s: &Styles,
    device: &Device,
) -> Result<(), ReadbackError> {
    recolor_async(g, planes, s, &vec![glam::Vec3::ZERO; BAKE_BATCH], device).await.map(|_| ())
}

/// 8-bit RGB as PNG bytes.
pub fn encode_rgb_png(rgb: &[u8], w: usize, h: usize) -> Result<Vec<u8>, String> {
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, w as u32, h as u32);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        enc.set_source_srgb(png::SrgbRenderingIntent::Perceptual);
        let mut wr = enc.write_header().map_err(|e| e.to_string())?;
        wr.write_image_data(rgb).map_err(|e| e.to_string())?;
    }
    Ok(out)
}

impl RiggedAvatar {
    /// The atlas of this avatar (the body's UVs transferred, own charts where it leaves the
    /// body).
    pub fn atlas(&self, ctx: &BodyContext) -> Result<UvAtlas, AtlasError> {
        crate::util::cooperative::run_blocking(self.atlas_async(ctx))
    }

    /// [`RiggedAvatar::atlas`] in slices ([`crate::util::cooperative`]), for the browser.
    pub async fn atlas_async(&self, ctx: &BodyContext) -> Result<UvAtlas, AtlasError> {
        let body = BodyUvs::new(&ctx.canonical.vertices, &ctx.model.faces, &ctx.model.vt, &ctx.model.ft)?;
        checkpoint().await;
        transfer_body_uvs_async(&self.canonical.mesh.vertices, &self.canonical.mesh.faces, &body).await
    }

    /// The projection of `photo` (the photo a reconstruction was made from) onto this avatar
    /// posed as the photo shows it; bakes take it with `photo.view.body`. Snap the outline
    /// first ([`RiggedAvatar::snap_to_photo`]) as every reconstruction does.
    pub fn photo_projection(&self, ctx: &BodyContext, photo: &SourcePhoto) -> PhotoProjection {
        let (posed, _) = self.repose(ctx, &pose_body(&ctx.model, &photo.view.body));
        photo.projection(&posed, &self.canonical.mesh.faces)
    }

    /// Move this avatar's outline at the photo's camera onto the photo's person
    /// ([`crate::reconstruction::silhouette_snap`], its longer reach kept within each vertex's
    /// part of `body`): the moves found in the pose the photo shows
    /// (`body`, posed from `photo.view.body`), carried back to the canonical mesh. Drops a kept
    /// bind pose.
    pub fn snap_to_photo(&mut self, ctx: &BodyContext, body: &PosedBody, photo: &SourcePhoto) -> SnapReport {
        crate::util::cooperative::run_blocking(self.snap_to_photo_async(ctx, body, photo))
    }

    /// [`RiggedAvatar::snap_to_photo`] in slices ([`crate::util::cooperative`]), for the
    /// browser's UI thread.
    pub async fn snap_to_photo_async(
        &mut self,
        ctx: &BodyContext,
        body: &PosedBody,
        photo: &SourcePhoto,
    ) -> SnapReport {
        let (posed, _) = self.repose(ctx, body);
        checkpoint().await;
        let body_parts = body_vertex_parts(&ctx.model.weights);
        let vertex_parts =
            self.body_vertex.iter().map(|&b| body_parts.get(b as usize).copied().unwrap_or(NO_PART)).collect();
        let parts = OutlineParts::new(vertex_parts, &body.vertices, &ctx.model.faces, &body_parts, photo);
        checkpoint().await;
        let (moves, report) = silhouette_offsets_async(&posed, &self.canonical.mesh.faces, photo, Some(&parts)).await;
        checkpoint().await;
        // Posed → canonical through each vertex's re-pose transform, inverted.
        let mut cache: crate::geometry::id_map::IdMap<u32, Mat4> = Default::default();
        for ((v, d), &b) in self.canonical.mesh.vertices.iter_mut().zip(moves).zip(&self.body_vertex) {
            let back = *cache.entry(b).or_insert_with(|| repose_transform(ctx, body, b as usize).0.inverse());
            *v += back.transform_vector3(d);
        }
        self.bind = None;
        report
    }

    /// Bake the texture field (styles `s`, triplanes `planes`) into a `res²` atlas image: each
    /// covered texel's canonical point is queried (the paper's per-pixel colour), the rest
    /// dilated.
    pub async fn bake_texture_async(
        &self,
        g: &Generator,
        planes: &Triplanes,
        s: &Styles,
        ctx: &BodyContext,
        res: usize,
        device: &Device,
    ) -> Result<BakedTexture, BakeError> {
        self.bake_texture_photo_async(g, planes, s, ctx, res, None, device).await
    }

    /// [`RiggedAvatar::bake_texture_async`] with a photo's colours projected on
    /// ([`crate::reconstruction::photo_projection`]): each texel's surface point, posed in the body pose
    /// `photo.1` the photo shows, blends in what the photo sees there.
    #[allow(clippy::too_many_arguments)]
    pub async fn bake_texture_photo_async(
        &self,
        g: &Generator,
        planes: &Triplanes,
        s: &Styles,
        ctx: &BodyContext,
        res: usize,
        photo: Option<(&PhotoProjection, &BodyParams)>,
        device: &Device,
    ) -> Result<BakedTexture, BakeError> {
        let plan = self.bake_plan_async(ctx, res).await?;
        let colors = bake_queries(g, planes, s, &plan.points, device).await?;
        self.bake_finish_async(ctx, plan, colors, photo).await
    }

    /// A bake's first stage: the atlas, its covered texels and each one's canonical point,
    /// where the texture field is queried (on any device, or in another thread: the browser's
    /// worker on a software adapter); [`RiggedAvatar::bake_finish_async`] takes the colours.
    pub async fn bake_plan_async(&self, ctx: &BodyContext, res: usize) -> Result<BakePlan, BakeError> {
        if !(64..=4096).contains(&res) {
            return Err(BakeError::Resolution(res));
        }
        let atlas = self.atlas_async(ctx).await?;
        let canon: Vec<glam::Vec3> = atlas.source.iter().map(|v| self.canonical.mesh.attributes[*v as usize]).collect();
        let (texels, points) = texel_points_async(&atlas, &canon, res).await;
        checkpoint().await;
        Ok(BakePlan { atlas, res, texels, points })
    }

    /// A bake's last stage: the texture field's linear RGB at `plan.points` (one per point),
    /// the photo's projection blended in (a reconstruction's), dilated into the image.
    pub async fn bake_finish_async(
        &self,
        ctx: &BodyContext,
        plan: BakePlan,
        mut colors: Vec<glam::Vec3>,
        photo: Option<(&PhotoProjection, &BodyParams)>,
    ) -> Result<BakedTexture, BakeError> {
        let BakePlan { atlas, res, texels, points } = plan;
        if colors.len() != points.len() || colors.iter().any(|c| !c.is_finite()) {
            return Err(BakeError::Colours(colors.len(), points.len()));
        }
        if let Some((projection, params)) = photo {
            let (pos, nrm) = self.repose(ctx, &pose_body(&ctx.model, params));
            let per_atlas =
                |v: &[glam::Vec3]| -> Vec<glam::Vec3> { atlas.source.iter().map(|i| v[*i as usize]).collect() };
            let (_, posed) = texel_points_async(&atlas, &per_atlas(&pos), res).await;
            let (_, normals) = texel_points_async(&atlas, &per_atlas(&nrm), res).await;
            let normals: Vec<glam::Vec3> = normals.iter().map(|n| n.normalize_or_zero()).collect();
            checkpoint().await;
            projection.blend_async(&points, &posed, &normals, &mut colors).await;
            checkpoint().await;
        }
        let rgb = bake_image_async(res, &texels, &colors).await;
        let png = encode_rgb_png(&rgb, res, res).map_err(BakeError::Png)?;
        Ok(BakedTexture { atlas, res, rgb, png, covered: texels.len() })
    }
}

/// A bake between its stages ([`RiggedAvatar::bake_plan_async`]): the atlas, the covered
/// texels (indices into the `res²` image) and the canonical point of each, where the texture
/// field is to be queried.
#[derive(Clone, Debug)]
pub struct BakePlan {
    pub atlas: UvAtlas,
    pub res: usize,
    pub texels: Vec<u32>,
    pub points: Vec<glam::Vec3>,
}

/// Generate in the canonical pose and rig (the fast path's one-off cost).
pub async fn generate_rigged_async(
    g: &crate::generator::pipeline::Generator,
    ctx: &BodyContext,
    s: &crate::generator::pipeline::Styles,
    device: &Device,
) -> Result<RiggedAvatar, crate::generator::readback::ReadbackError> {
    let params = crate::body::skinning::BodyParams { pose: crate::body::pose_library::da_pose(), ..Default::default() };
    let a = crate::generator::pipeline::generate_avatar_async(g, ctx, s, &params, device).await?;
    crate::util::cooperative::checkpoint().await;
    crate::util::profile::stage("rigging");
    Ok(RiggedAvatar::new(a, ctx))
}

/// [`generate_rigged_async`] from the triplanes of `s` computed already.
pub async fn generate_rigged_from_planes_async(
    g: &Generator,
    ctx: &BodyContext,
    s: &Styles,
    planes: &Triplanes,
    device: &Device,
) -> Result<RiggedAvatar, ReadbackError> {
    let params = crate::body::skinning::BodyParams { pose: crate::body::pose_library::da_pose(), ..Default::default() };
    let a = crate::generator::pipeline::generate_avatar_from_planes_async(g, ctx, s, planes, &params, device).await?;
    crate::util::cooperative::checkpoint().await;
    crate::util::profile::stage("rigging");
    Ok(RiggedAvatar::new(a, ctx))
}

/// A [`RiggedAvatar`] as flat arrays, for handing it between threads that share no memory
/// (the browser's reconstruction worker rigs the result it sends to the page): 3 floats per
/// vertex for `positions`, `attributes` (canonical coordinates), `normals`, `colors`; 3
/// indices per triangle; per vertex its grid edge (`edge_a`, `edge_b`, `edge_t`) and its
/// rigging body vertex. [`RiggedAvatar::from_arrays`] checks every length and index.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RiggedArrays {
    pub positions: Vec<f32>,
    pub faces: Vec<u32>,
    pub attributes: Vec<f32>,
    pub normals: Vec<f32>,
    pub colors: Vec<f32>,
    pub edge_a: Vec<u32>,
    pub edge_b: Vec<u32>,
    pub edge_t: Vec<f32>,
    pub body_vertex: Vec<u32>,
}

/// Why [`RiggedArrays`] are not a rigged avatar.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RiggedArraysError {
    #[error("`{0}` has {1} numbers, expected {2}")]
    Length(&'static str, usize, usize),
    #[error("triangle corner {0} is out of range (the avatar has {1} vertices)")]
    Face(u32, usize),
    #[error("body vertex {0} is out of range (the body has {1})")]
    BodyVertex(u32, usize),
    #[error("`{0}` holds a value that is not finite")]
    NonFinite(&'static str),
    #[error("the avatar has no triangles")]
    Empty,
}

fn flat(v: &[glam::Vec3]) -> Vec<f32> {
    v.iter().flat_map(|p| p.to_array()).collect()
}

fn vec3s(name: &'static str, a: &[f32], n: usize) -> Result<Vec<glam::Vec3>, RiggedArraysError> {
    if a.len() != 3 * n {
        return Err(RiggedArraysError::Length(name, a.len(), 3 * n));
    }
    if a.iter().any(|x| !x.is_finite()) {
        return Err(RiggedArraysError::NonFinite(name));
    }
    Ok(a.chunks_exact(3).map(|c| glam::Vec3::new(c[0], c[1], c[2])).collect())
}

impl RiggedAvatar {
    /// The avatar as flat arrays (without its kept bind pose, which the receiver recomputes).
    pub fn to_arrays(&self) -> RiggedArrays {
        let (m, edges) = (&self.canonical.mesh, &self.canonical.mesh.edges);
        RiggedArrays {
            positions: flat(&m.vertices),
            faces: m.faces.iter().flatten().copied().collect(),
            attributes: flat(&m.attributes),
            normals: flat(&self.canonical.normals),
            colors: flat(&self.canonical.colors),
            edge_a: edges.iter().map(|e| e.0).collect(),
            edge_b: edges.iter().map(|e| e.1).collect(),
            edge_t: edges.iter().map(|e| e.2).collect(),
            body_vertex: self.body_vertex.clone(),
        }
    }

    /// The avatar [`RiggedAvatar::to_arrays`] made, checked against `ctx`'s body: every array
    /// one entry per vertex (or per triangle corner), every index in range, every number
    /// finite. The attributes and the edges may be absent (empty), as in a mesh without them.
    pub fn from_arrays(a: RiggedArrays, ctx: &BodyContext) -> Result<Self, RiggedArraysError> {
        use RiggedArraysError as E;
        if a.positions.len() % 3 != 0 {
            return Err(E::Length("positions", a.positions.len(), a.positions.len() / 3 * 3));
        }
        let n = a.positions.len() / 3;
        let vertices = vec3s("positions", &a.positions, n)?;
        let normals = vec3s("normals", &a.normals, n)?;
        let colors = vec3s("colors", &a.colors, n)?;
        let attributes = match a.attributes.is_empty() {
            true => Vec::new(),
            false => vec3s("attributes", &a.attributes, n)?,
        };
        if a.faces.is_empty() {
            return Err(E::Empty);
        }
        if a.faces.len() % 3 != 0 {
            return Err(E::Length("faces", a.faces.len(), a.faces.len() / 3 * 3));
        }
        if let Some(v) = a.faces.iter().find(|v| **v as usize >= n) {
            return Err(E::Face(*v, n));
        }
        if a.body_vertex.len() != n {
            return Err(E::Length("body_vertex", a.body_vertex.len(), n));
        }
        let nb = ctx.model.num_vertices();
        if let Some(b) = a.body_vertex.iter().find(|b| **b as usize >= nb) {
            return Err(E::BodyVertex(*b, nb));
        }
        let ne = if a.edge_a.is_empty() { 0 } else { n };
        for (name, len) in [("edge_a", a.edge_a.len()), ("edge_b", a.edge_b.len()), ("edge_t", a.edge_t.len())] {
            if len != ne {
                return Err(E::Length(name, len, ne));
            }
        }
        if a.edge_t.iter().any(|t| !t.is_finite()) {
            return Err(E::NonFinite("edge_t"));
        }
        let edges = a.edge_a.iter().zip(&a.edge_b).zip(&a.edge_t).map(|((x, y), t)| (*x, *y, *t)).collect();
        let faces = a.faces.chunks_exact(3).map(|f| [f[0], f[1], f[2]]).collect();
        let mesh = crate::geometry::dmtet::TriMesh { vertices, faces, attributes, edges };
        Ok(Self { canonical: Avatar { mesh, normals, colors }, body_vertex: a.body_vertex, bind: None })
    }
}
