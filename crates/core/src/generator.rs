//! The generator G (paper Sec. 4): latents → triplanes → SDF (template + residual) in canonical
//! space, evaluated at posed-space tet grid vertices carried to canonical space by inverse
//! skinning → DMTet in posed space → textured mesh with the normal field (eq. 4).
//!
//! Tensor work (networks) runs on the caller's burn `Device`; grid bookkeeping, inverse
//! skinning and marching tetrahedra run on the CPU (`geometry`).

use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};
use glam::Vec3;

use crate::body_model::BodyModel;
use crate::geometry::inverse_skinning::canonical_body;
use crate::geometry::template_sdf::OUTSIDE_VALUE;
use crate::geometry::tet_grid::{REFERENCE_BOX_CENTER, REFERENCE_BOX_SIZE};
use crate::geometry::{marching_tets, InverseSkinning, TemplateSdf, TetGrid, TriMesh};
use crate::network::decoders::{Decoders, SDF_RESIDUAL_MAX};
use crate::network::init::{latent, Rng};
use crate::network::mapping::{truncate_toward_modes, truncate_toward_subject, MappingNetwork};
use crate::network::synthesis::{TriplaneSynthesis, Triplanes};
use crate::network::triplane::sample_triplanes;
use crate::network::GeneratorConfig;
use crate::skinning::{pose_body, BodyParams, PosedBody};

#[derive(Module, Debug)]
pub struct Generator {
    pub mapping_geo: MappingNetwork,
    pub mapping_tex: MappingNetwork,
    pub synthesis: TriplaneSynthesis,
    pub decoders: Decoders,
}

/// Whether the parameter at checkpoint path `name` (e.g. `decoders.texture.out.weight`)
/// belongs to the texture branch: the w_tex mapping network, the backbone's to-texture
/// layers, the texture decoder and its RGB head. Only the RGB image depends on them; the
/// shared backbone and everything geometric are outside it. Training may give this branch its
/// own learning rate (`optim::Adam::step_scaled`).
pub fn is_texture_param(name: &str) -> bool {
    name.starts_with("mapping_tex.")
        || name.contains(".to_texture.")
        || name.starts_with("decoders.texture.")
        || name.starts_with("decoders.to_rgb.")
}

/// Whether the parameter at checkpoint path `name` belongs to the heads that place the
/// surface: the SDF-residual and DMTet-offset decoders.
pub fn is_geometry_head_param(name: &str) -> bool {
    name.starts_with("decoders.sdf.") || name.starts_with("decoders.offset.")
}

/// Modes of the latent space in W, `[K, w_dim]` per branch (e.g. the codes of the training
/// subjects of a reconstruction warm-up), for multi-modal truncation
/// ([`Generator::styles_with`]). Checkpoints may carry them (`checkpoint::load_latent_modes`).
#[derive(Clone, Debug)]
pub struct LatentModes {
    pub geo: Tensor<2>,
    pub tex: Tensor<2>,
    /// How ψ pairs the two branches' modes (stored in the checkpoint).
    pub pairing: ModePairing,
}

/// Truncation ψ used where the user sets none, for a generator with these latent modes
/// (`None`: a checkpoint without modes, truncating towards w_avg): 0 with modes, i.e. the
/// training subjects' own codes (a reconstruction warm-up has only been trained there; between
/// them it renders blends), else StyleGAN's customary 0.7.
pub fn default_psi(modes: Option<&LatentModes>) -> f32 {
    if modes.is_some() {
        0.0
    } else {
        0.7
    }
}

/// How multi-modal truncation picks the modes of the two branches.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ModePairing {
    /// One subject for both, the one whose geometry mode is nearest to w_geo
    /// ([`truncate_toward_subject`]): for generators whose colours are tied to their geometry
    /// code (a reconstruction warm-up without the texture-swap term).
    #[default]
    Subject,
    /// Each branch towards its own nearest mode ([`truncate_toward_modes`]): for generators
    /// trained with the texture-swap term, whose colours follow the texture code, so a seed
    /// pair gives one subject's geometry with another's colours.
    Branch,
}

impl ModePairing {
    /// The checkpoint metadata value.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Subject => "subject",
            Self::Branch => "branch",
        }
    }

    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "subject" => Some(Self::Subject),
            "branch" => Some(Self::Branch),
            _ => None,
        }
    }
}

impl LatentModes {
    pub fn count(&self) -> usize {
        self.geo.dims()[0]
    }

    /// Subject `geo`'s geometry code and subject `tex`'s texture code, `[1, w_dim]` each
    /// (re-texturing one training subject with another's colours); None out of range.
    pub fn subject(&self, geo: usize, tex: usize) -> Option<(Tensor<2>, Tensor<2>)> {
        let k = self.count();
        (geo < k && tex < k).then(|| (self.geo.clone().narrow(0, geo, 1), self.tex.clone().narrow(0, tex, 1)))
    }
}

/// Per-layer styles (W+): `[B, n, w_dim]` each.
#[derive(Clone, Debug)]
pub struct Styles {
    pub geo: Tensor<3>,
    pub tex: Tensor<3>,
}

impl Generator {
    /// A generator with deterministic random weights from `seed`.
    pub fn new(cfg: &GeneratorConfig, seed: u64, device: &Device) -> Self {
        let mut rng = Rng::new(seed, 1);
        let mapping = |rng: &mut Rng| {
            MappingNetwork::new(rng, cfg.z_dim, cfg.w_dim, cfg.mapping_layers, cfg.mapping_lr_mul, device)
        };
        Self {
            mapping_geo: mapping(&mut rng),
            mapping_tex: mapping(&mut rng),
            synthesis: TriplaneSynthesis::new(&mut rng, cfg, device),
            decoders: Decoders::new(&mut rng, cfg, device),
        }
    }

    /// Number of per-layer styles: (geometry: backbone + 2 decoder layers, texture: to-texture
    /// layers + 2 decoder layers + to-RGB).
    pub fn num_ws(&self) -> (usize, usize) {
        (self.synthesis.num_ws_geo() + 2, self.synthesis.num_ws_tex() + 3)
    }

    /// Map latents to W+ styles with truncation ψ towards w_avg. `z_geo`, `z_tex`: `[B, z_dim]`.
    pub fn styles(&self, z_geo: Tensor<2>, z_tex: Tensor<2>, psi: f32) -> Styles {
        self.styles_with(z_geo, z_tex, psi, None)
    }

    /// Like [`Generator::styles`]; with `modes`, ψ truncates towards the training subjects'
    /// codes instead of w_avg (multi-modal truncation): both branches towards the subject whose
    /// geometry mode is nearest to w_geo ([`truncate_toward_subject`]), or each branch towards
    /// its own nearest mode ([`truncate_toward_modes`]), as `modes.pairing` says.
    pub fn styles_with(&self, z_geo: Tensor<2>, z_tex: Tensor<2>, psi: f32, modes: Option<&LatentModes>) -> Styles {
        let (wg, wt) = (self.mapping_geo.forward(z_geo), self.mapping_tex.forward(z_tex));
        let (wg, wt) = match modes {
            Some(m) if m.pairing == ModePairing::Branch => {
                (truncate_toward_modes(wg, &m.geo, psi), truncate_toward_modes(wt, &m.tex, psi))
            }
            Some(m) => truncate_toward_subject(wg, wt, &m.geo, &m.tex, psi),
            None => (self.mapping_geo.truncate(wg, psi), self.mapping_tex.truncate(wt, psi)),
        };
        self.styles_from_w(wg, wt)
    }

    /// Styles from W codes `[B, w_dim]` per branch (each repeated over its layers), e.g. a
    /// training subject's modes (`LatentModes::subject`).
    pub fn styles_from_w(&self, w_geo: Tensor<2>, w_tex: Tensor<2>) -> Styles {
        let (ng, nt) = self.num_ws();
        Styles {
            geo: w_geo.unsqueeze_dim::<3>(1).repeat_dim(1, ng),
            tex: w_tex.unsqueeze_dim::<3>(1).repeat_dim(1, nt),
        }
    }

    pub fn triplanes(&self, s: &Styles) -> Triplanes {
        let (ng, nt) = self.num_ws();
        self.synthesis.forward(s.geo.clone().narrow(1, 0, ng - 2), s.tex.clone().narrow(1, 0, nt - 3))
    }

    fn w(ws: &Tensor<3>, i: usize) -> Tensor<2> {
        let [b, _, d] = ws.dims();
        ws.clone().narrow(1, i, 1).reshape([b, d])
    }

    /// SDF residual and DMTet offsets at canonical points `[B, N, 3]` → (`[B, N]`, `[B, N, 3]`).
    pub fn geometry_fields(&self, planes: &Triplanes, s: &Styles, points: Tensor<3>) -> (Tensor<2>, Tensor<3>) {
        let (ng, _) = self.num_ws();
        let feat = sample_triplanes(planes.geometry.clone(), points);
        let residual = self.decoders.sdf_residual(feat.clone(), Self::w(&s.geo, ng - 2));
        let [b, n, _] = residual.dims();
        let offset = self.decoders.vertex_offset(feat, Self::w(&s.geo, ng - 1));
        (residual.reshape([b, n]), offset)
    }

    /// SDF residual only, `[B, N]`.
    pub fn sdf_residual(&self, planes: &Triplanes, s: &Styles, points: Tensor<3>) -> Tensor<2> {
        let (ng, _) = self.num_ws();
        let feat = sample_triplanes(planes.geometry.clone(), points);
        let r = self.decoders.sdf_residual(feat, Self::w(&s.geo, ng - 2));
        let [b, n, _] = r.dims();
        r.reshape([b, n])
    }

    /// Colours `[B, N, 3]` in [0, 1] at canonical points.
    pub fn texture_field(&self, planes: &Triplanes, s: &Styles, points: Tensor<3>) -> Tensor<3> {
        let (_, nt) = self.num_ws();
        let feat = sample_triplanes(planes.texture.clone(), points);
        self.decoders.rgb(feat, Self::w(&s.tex, nt - 1))
    }
}

/// What generation needs about the body, prepared once per body model and config.
pub struct BodyContext {
    pub model: BodyModel,
    /// Canonical body: Da-pose, β = 0.
    pub canonical: PosedBody,
    pub template: TemplateSdf,
    pub grid: TetGrid,
    /// Whether each grid vertex lies on the box boundary.
    pub boundary: Vec<bool>,
}

impl BodyContext {
    pub fn new(model: BodyModel, cfg: &GeneratorConfig) -> Self {
        let canonical = canonical_body(&model);
        let min = REFERENCE_BOX_CENTER - Vec3::splat(REFERENCE_BOX_SIZE / 2.0);
        let template =
            TemplateSdf::from_mesh(&canonical.vertices, &model.faces, cfg.template_res, min, REFERENCE_BOX_SIZE, 3);
        let grid = TetGrid::reference(cfg.tet_res);
        let boundary = grid.boundary_flags();
        Self { model, canonical, template, grid, boundary }
    }
}

/// A generated, posed, coloured avatar mesh.
#[derive(Clone, Debug)]
pub struct Avatar {
    /// Posed mesh; `mesh.attributes` holds each vertex's canonical coordinates.
    pub mesh: TriMesh,
    /// Posed-space unit normals from the normal field (∇SDF rotated by skinning, eq. 4).
    pub normals: Vec<Vec3>,
    /// Linear RGB in [0, 1] from the texture field at the canonical coordinates.
    pub colors: Vec<Vec3>,
}

/// Grid vertices where the generator's geometry fields are evaluated: |template SDF| below
/// the residual bound (`SDF_RESIDUAL_MAX`) plus two tet edges, off the box boundary, and not
/// `guarded` (space the pose vacated, see `inverse_skinning::guarded_template`: there the
/// canonical point lies inside another body part, whose learned residual would turn the
/// vacated space inside and leave floating fragments). Farther out the SDF has the template's
/// sign whatever the residual and no sign-changing edge reaches (the template is ~1-Lipschitz),
/// so residual and offsets are 0 there: same surface, a fraction of the decoder work.
pub fn field_band(ctx: &BodyContext, template: &[f32], guarded: &[bool]) -> Vec<u32> {
    let reach = field_reach(ctx);
    (0..template.len())
        .filter(|&i| {
            template[i].abs() < reach
                && !ctx.boundary.get(i).copied().unwrap_or(true)
                && !guarded.get(i).copied().unwrap_or(false)
        })
        .map(|i| i as u32)
        .collect()
}

/// Longest tet edge of the grid of `ctx`.
fn grid_edge(ctx: &BodyContext) -> f32 {
    REFERENCE_BOX_SIZE / ctx.grid.res.max(1) as f32 * 3f32.sqrt()
}

/// |template SDF| below which [`field_band`] evaluates the fields.
fn field_reach(ctx: &BodyContext) -> f32 {
    SDF_RESIDUAL_MAX + 2.0 * grid_edge(ctx)
}

/// Posed-space distance from the body beyond which [`PosedGrid`] skips un-warping a grid
/// vertex (`InverseSkinning::canonical_templates`): past the field band by the un-warp slack
/// and one more edge, and deeper than any body part is thick, so those vertices are outside,
/// off the band and on no sign-changing edge either way.
pub fn far_from_body(ctx: &BodyContext) -> f32 {
    field_reach(ctx) + crate::geometry::inverse_skinning::UNWARP_SLACK + grid_edge(ctx)
}

fn to_tensor3(points: &[Vec3], device: &Device) -> Tensor<3> {
    let flat: Vec<f32> = points.iter().flat_map(|p| p.to_array()).collect();
    Tensor::from_data(TensorData::new(flat, [1, points.len(), 3]), device)
}

/// Read a tensor back to the CPU. Browsers cannot block, so on wasm32 this awaits the GPU;
/// natively it reads synchronously (so [`block_on_ready`] can drive the whole pipeline).
async fn read<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    #[cfg(target_arch = "wasm32")]
    let data = t.into_data_async().await.ok();
    #[cfg(not(target_arch = "wasm32"))]
    let data = t.try_into_data().ok();
    data.and_then(|d| d.try_into_vec::<f32>().ok()).unwrap_or_default()
}

/// Run a future whose awaits all complete immediately (native readbacks are synchronous).
#[cfg(not(target_arch = "wasm32"))]
pub fn block_on_ready<F: std::future::Future>(fut: F) -> F::Output {
    let mut fut = std::pin::pin!(fut);
    let mut cx = std::task::Context::from_waker(std::task::Waker::noop());
    loop {
        if let std::task::Poll::Ready(v) = fut.as_mut().poll(&mut cx) {
            return v;
        }
    }
}

/// Latent vectors of the seeds, as `[1, z_dim]` tensors.
pub fn seed_latents(cfg: &GeneratorConfig, seed_geo: u64, seed_tex: u64, device: &Device) -> (Tensor<2>, Tensor<2>) {
    let z = |s: u64| Tensor::from_data(TensorData::new(latent(s, cfg.z_dim), [1, cfg.z_dim]), device);
    (z(seed_geo), z(seed_tex))
}

/// Generate the avatar of styles `s` in the pose/shape `params` (paper's exact mode: DMTet
/// is run in posed space on the inverse-skinned grid). Native, blocking.
#[cfg(not(target_arch = "wasm32"))]
pub fn generate_avatar(g: &Generator, ctx: &BodyContext, s: &Styles, params: &BodyParams, device: &Device) -> Avatar {
    block_on_ready(generate_avatar_async(g, ctx, s, params, device))
}

/// The tet grid under one body pose (paper eq. 2): each posed-space grid vertex carried to
/// canonical space by SMPL-guided inverse skinning, and the template SDF there.
pub struct PosedGrid {
    pub canonical: Vec<Vec3>,
    pub template: Vec<f32>,
    /// Grid vertices where the generator's fields are evaluated (`generator::field_band`).
    pub band: Vec<u32>,
}

impl PosedGrid {
    /// Inverse-skin every grid vertex of `ctx` under `inv` (split over the CPU cores natively),
    /// except those farther than [`far_from_body`] from the posed body.
    pub fn new(ctx: &BodyContext, inv: &InverseSkinning) -> Self {
        Self::with_far(ctx, inv, far_from_body(ctx))
    }

    /// [`PosedGrid::new`] with the far-vertex distance `far` (`f32::INFINITY`: un-warp all).
    pub fn with_far(ctx: &BodyContext, inv: &InverseSkinning, far: f32) -> Self {
        let verts = &ctx.grid.vertices;
        let map = |chunk: &[Vec3]| -> Vec<(Vec3, f32, bool)> { inv.canonical_templates(&ctx.template, chunk, far) };
        #[cfg(not(target_arch = "wasm32"))]
        let mapped: Vec<(Vec3, f32, bool)> = {
            let threads = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1).clamp(1, 8);
            let chunk = verts.len().div_ceil(threads).max(1);
            std::thread::scope(|sc| {
                let handles: Vec<_> = verts.chunks(chunk).map(|c| sc.spawn(move || map(c))).collect();
                handles.into_iter().flat_map(|h| h.join().unwrap_or_default()).collect()
            })
        };
        #[cfg(target_arch = "wasm32")]
        let mapped = map(verts);
        let guarded: Vec<bool> = mapped.iter().map(|m| m.2).collect();
        let (canonical, template): (Vec<Vec3>, Vec<f32>) = mapped.into_iter().map(|(c, t, _)| (c, t)).unzip();
        let band = field_band(ctx, &template, &guarded);
        Self { canonical, template, band }
    }
}

/// [`generate_avatar`] for any platform (awaits GPU readbacks in the browser).
pub async fn generate_avatar_async(
    g: &Generator,
    ctx: &BodyContext,
    s: &Styles,
    params: &BodyParams,
    device: &Device,
) -> Avatar {
    let planes = g.triplanes(s);
    let posed = pose_body(&ctx.model, params);
    let inv = InverseSkinning::new(&ctx.model, &posed, &ctx.canonical);
    let PosedGrid { canonical: canon, template, band } = PosedGrid::new(ctx, &inv);
    let n = canon.len();
    let (mut residual, mut offset) = (vec![0.0f32; n], vec![0.0f32; 3 * n]);
    if !band.is_empty() {
        let pts: Vec<Vec3> = band.iter().map(|&i| canon[i as usize]).collect();
        let (r, o) = g.geometry_fields(&planes, s, to_tensor3(&pts, device));
        let (r, o) = (read(r).await, read(o).await);
        for (k, &i) in band.iter().enumerate() {
            let i = i as usize;
            residual[i] = r[k];
            offset[3 * i..3 * i + 3].copy_from_slice(&o[3 * k..3 * k + 3]);
        }
    }
    // Grid vertices on the box boundary are empty, so every surface is closed.
    let sdf: Vec<f32> = template
        .iter()
        .zip(&residual)
        .zip(&ctx.boundary)
        .map(|((t, r), &b)| if b { OUTSIDE_VALUE } else { t + r })
        .collect();
    let positions: Vec<Vec3> =
        ctx.grid.vertices.iter().enumerate().map(|(i, p)| *p + Vec3::from_slice(&offset[3 * i..3 * i + 3])).collect();
    // Only the outer surface: closed pockets inside the avatar (a grid vertex or two whose SDF
    // stayed positive inside the body, e.g. where the thighs meet in sitting poses) are never
    // seen and would only pollute the exported mesh.
    let (mesh, _) = marching_tets(&positions, &ctx.grid.tets, &sdf, &canon).without_cavities();
    if mesh.vertices.is_empty() {
        return Avatar { mesh, normals: Vec::new(), colors: Vec::new() };
    }

    // Normal field: central differences of the full SDF around each canonical coordinate.
    let h = 0.5 * ctx.template.cell;
    let mut probes = Vec::with_capacity(mesh.attributes.len() * 6);
    for c in &mesh.attributes {
        for d in [Vec3::X, Vec3::NEG_X, Vec3::Y, Vec3::NEG_Y, Vec3::Z, Vec3::NEG_Z] {
            probes.push(*c + d * h);
        }
    }
    let r = read(g.sdf_residual(&planes, s, to_tensor3(&probes, device))).await;
    let f: Vec<f32> = probes.iter().zip(&r).map(|(p, r)| ctx.template.sample(*p) + r).collect();
    let normals = mesh
        .vertices
        .iter()
        .enumerate()
        .map(|(i, v)| {
            let k = 6 * i;
            let grad = Vec3::new(f[k] - f[k + 1], f[k + 2] - f[k + 3], f[k + 4] - f[k + 5]).normalize_or_zero();
            let (_, body_vertex) = inv.to_canonical(*v);
            (inv.rotation(body_vertex) * grad).normalize_or_zero()
        })
        .collect();
    let colors = recolor_async(g, &planes, s, &mesh.attributes, device).await;
    Avatar { mesh, normals, colors }
}

/// Colours of the texture field at canonical points (re-texturing keeps the geometry).
pub async fn recolor_async(
    g: &Generator,
    planes: &Triplanes,
    s: &Styles,
    canonical: &[Vec3],
    device: &Device,
) -> Vec<Vec3> {
    if canonical.is_empty() {
        return Vec::new();
    }
    read(g.texture_field(planes, s, to_tensor3(canonical, device)))
        .await
        .chunks_exact(3)
        .map(Vec3::from_slice)
        .collect()
}

/// An avatar extracted once in the canonical pose and rigged to the body: the interactive
/// fast path. Each vertex follows its nearest canonical body vertex's skinning transform,
/// so re-posing is LBS (no network, no extraction).
#[derive(Clone, Debug)]
pub struct RiggedAvatar {
    /// Canonical (Da-pose) mesh; `attributes` = canonical coordinates.
    pub canonical: Avatar,
    /// Nearest canonical body vertex of each avatar vertex.
    pub body_vertex: Vec<u32>,
}

impl RiggedAvatar {
    /// Rig an avatar generated in the canonical pose (`params` = Da-pose, β = 0).
    pub fn new(canonical: Avatar, ctx: &BodyContext) -> Self {
        let tree = crate::spatial::KdTree::new(&ctx.canonical.vertices);
        let body_vertex =
            canonical.mesh.vertices.iter().map(|v| tree.nearest(*v).map_or(0, |(i, _)| i as u32)).collect();
        Self { canonical, body_vertex }
    }

    /// Vertices and normals in the pose/shape of `posed` (from `pose_body`).
    pub fn repose(&self, ctx: &BodyContext, posed: &PosedBody) -> (Vec<Vec3>, Vec<Vec3>) {
        let mut cache: std::collections::HashMap<u32, (glam::Mat4, glam::Mat3)> = std::collections::HashMap::new();
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
pub fn repose_transform(ctx: &BodyContext, posed: &PosedBody, i: usize) -> (glam::Mat4, glam::Mat3) {
    let shape = posed.shaped[i] - ctx.model.v_template[i];
    let m =
        posed.vertex_transforms[i] * glam::Mat4::from_translation(shape) * ctx.canonical.vertex_transforms[i].inverse();
    let r = crate::geometry::inverse_skinning::nearest_rotation(
        glam::Mat3::from_mat4(posed.vertex_transforms[i])
            * glam::Mat3::from_mat4(ctx.canonical.vertex_transforms[i]).inverse(),
    );
    (m, r)
}

/// Generate in the canonical pose and rig (the fast path's one-off cost).
pub async fn generate_rigged_async(g: &Generator, ctx: &BodyContext, s: &Styles, device: &Device) -> RiggedAvatar {
    let params = BodyParams { pose: crate::pose_library::da_pose(), ..Default::default() };
    let a = generate_avatar_async(g, ctx, s, &params, device).await;
    RiggedAvatar::new(a, ctx)
}
