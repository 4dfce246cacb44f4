//! The generator G (paper Sec. 4): latents → triplanes → SDF (template + residual) in canonical
//! space, evaluated at posed-space tet grid vertices carried to canonical space by inverse
//! skinning → DMTet in posed space → textured mesh with the normal field (eq. 4).
//!
//! Tensor work (networks) runs on the caller's burn `Device`; grid bookkeeping and inverse
//! skinning run on the CPU (`geometry`), and so does marching tetrahedra, except for a new
//! identity on a GPU, which is extracted there (`dmtet_gpu`). The geometry fields on the
//! grid are `fields`, the normal field `normal_field`, the rigged fast path `rigging`, the
//! latent modes of multi-modal truncation `network::mapping`.

use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};
use glam::{Mat3, Vec3};

use crate::body_model::BodyModel;
use crate::cooperative::checkpoint;
use crate::dmtet_gpu;
use crate::fields::{aligned_points, band_fields, points_tensor};
use crate::geometry::{marching_tets, InverseSkinning, PosedGrid, TriMesh};
use crate::network::decoders::Decoders;
use crate::network::face_plane::FacePlane;
use crate::network::init::{latent, Rng};
use crate::network::layers::is_ndarray;
use crate::network::mapping::{nearest_mode, truncate_toward_modes, truncate_toward_subject, MappingNetwork};
use crate::network::synthesis::{TriplaneSynthesis, Triplanes};
use crate::network::triplane::sample_triplanes;
use crate::network::GeneratorConfig;
use crate::normal_field;
use crate::profile;
#[cfg(not(target_arch = "wasm32"))]
use crate::readback::block_on_ready;
use crate::readback::{read_f32, ReadbackError};
use crate::rigging::RiggedAvatar;
use crate::skinning::{pose_body, BodyParams};

pub use crate::geometry::BodyContext;
pub use crate::network::mapping::{default_psi, LatentModes, ModePairing};

#[derive(Module, Debug)]
pub struct Generator {
    pub mapping_geo: MappingNetwork,
    pub mapping_tex: MappingNetwork,
    pub synthesis: TriplaneSynthesis,
    pub decoders: Decoders,
    /// The face plane (`GeneratorConfig::face`; not in the paper), added to the texture
    /// features on the canonical face.
    pub face: Option<FacePlane>,
}

/// Whether the parameter at checkpoint path `name` (e.g. `decoders.texture.out.weight`)
/// belongs to the texture branch: the w_tex mapping network, the backbone's to-texture
/// layers, the texture detail blocks, the face plane, the texture decoder and its RGB head. Only the RGB image depends on them; the
/// shared backbone and everything geometric are outside it. Training may give this branch its
/// own learning rate (`optim::Adam::step_scaled`).
pub fn is_texture_param(name: &str) -> bool {
    name.starts_with("mapping_tex.")
        || name.contains(".to_texture.")
        || name.starts_with("synthesis.texture_detail.")
        || is_face_param(name)
        || name.starts_with("decoders.texture.")
        || name.starts_with("decoders.to_rgb.")
}

/// Whether the parameter at checkpoint path `name` belongs to the face plane.
pub fn is_face_param(name: &str) -> bool {
    name.starts_with("face.")
}

/// Whether the parameter at checkpoint path `name` belongs to the heads that place the
/// surface: the SDF-residual and DMTet-offset decoders.
pub fn is_geometry_head_param(name: &str) -> bool {
    name.starts_with("decoders.sdf.") || name.starts_with("decoders.offset.")
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
            // Drawn last: configs without a face plane initialise as before.
            face: cfg.face.as_ref().map(|f| FacePlane::new(&mut rng, cfg, f, device)),
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
    /// With per-layer texture modes (`modes.tex_layers`), the texture styles also get
    /// (1 − ψ) of the chosen texture mode's layer offsets.
    pub fn styles_with(&self, z_geo: Tensor<2>, z_tex: Tensor<2>, psi: f32, modes: Option<&LatentModes>) -> Styles {
        let (wg, wt) = (self.mapping_geo.forward(z_geo), self.mapping_tex.forward(z_tex));
        // The texture mode each row goes to, where the modes have layer offsets to add.
        let tex_mode = modes.and_then(|m| {
            let layers = m.tex_layers.as_ref().filter(|_| psi != 1.0)?;
            let k = match m.pairing {
                ModePairing::Branch => nearest_mode(&wt, &m.tex),
                ModePairing::Subject => nearest_mode(&wg, &m.geo),
            };
            Some(layers.clone().select(0, k))
        });
        let (wg, wt) = match modes {
            Some(m) if m.pairing == ModePairing::Branch => {
                (truncate_toward_modes(wg, &m.geo, psi), truncate_toward_modes(wt, &m.tex, psi))
            }
            Some(m) => truncate_toward_subject(wg, wt, &m.geo, &m.tex, psi),
            None => (self.mapping_geo.truncate(wg, psi), self.mapping_tex.truncate(wt, psi)),
        };
        let s = self.styles_from_w(wg, wt);
        match tex_mode {
            Some(layers) => Styles { tex: s.tex + layers * (1.0 - psi), geo: s.geo },
            None => s,
        }
    }

    /// `modes` of this generator's checkpoint before it grew texture detail blocks
    /// (`checkpoint::load_generator_growing`): the new blocks' style layers, which come after
    /// the file's detail blocks and before the 3 decoder layers, get zero offsets, so every
    /// subject renders as before. Modes without layer offsets, or with this generator's
    /// count, are returned as they are; more layers than this generator has is an error.
    pub fn grown_modes(&self, modes: LatentModes) -> Result<LatentModes, String> {
        let Some(layers) = &modes.tex_layers else { return Ok(modes) };
        let [k, have, w] = layers.dims();
        let (_, nt) = self.num_ws();
        if have == nt {
            return Ok(modes);
        }
        if have > nt || have < 3 {
            return Err(format!("texture mode offsets of {have} layers; this generator has {nt}"));
        }
        let zeros = Tensor::zeros([k, nt - have, w], &layers.device());
        let at = have - 3;
        let grown = Tensor::cat(vec![layers.clone().narrow(1, 0, at), zeros, layers.clone().narrow(1, at, 3)], 1);
        Ok(LatentModes { tex_layers: Some(grown), ..modes })
    }

    /// The styles of training subject `geo`'s geometry mode and subject `tex`'s texture mode
    /// (with its layer offsets, where the modes have them): a subject as trained, or re-textured
    /// with another's colours. None out of range.
    pub fn subject_styles(&self, modes: &LatentModes, geo: usize, tex: usize) -> Option<Styles> {
        let (wg, wt) = modes.subject(geo, tex)?;
        let s = self.styles_from_w(wg, wt);
        Some(match &modes.tex_layers {
            Some(l) => Styles { tex: s.tex + l.clone().narrow(0, tex, 1), geo: s.geo },
            None => s,
        })
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

    /// [`Generator::triplanes`] with a checkpoint after each synthesis block (the browser).
    pub async fn triplanes_async(&self, s: &Styles) -> Triplanes {
        let (ng, nt) = self.num_ws();
        self.synthesis.forward_async(s.geo.clone().narrow(1, 0, ng - 2), s.tex.clone().narrow(1, 0, nt - 3)).await
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
        let mut feat = sample_triplanes(planes.texture.clone(), points.clone());
        if let Some(face) = &self.face {
            feat = feat + face.features(points, Self::w(&s.tex, nt - 3));
        }
        self.decoders.rgb(feat, Self::w(&s.tex, nt - 1))
    }
}

impl BodyContext {
    /// The context of `model` at the template and grid resolutions of `cfg`.
    pub fn new(model: BodyModel, cfg: &GeneratorConfig) -> Self {
        Self::with_resolution(model, cfg.template_res, cfg.tet_res)
    }

    /// [`BodyContext::new`] with checkpoints (`cooperative`), for the browser.
    pub async fn new_async(model: BodyModel, cfg: &GeneratorConfig) -> Self {
        Self::with_resolution_async(model, cfg.template_res, cfg.tet_res).await
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

/// Latent vectors of the seeds, as `[1, z_dim]` tensors.
pub fn seed_latents(cfg: &GeneratorConfig, seed_geo: u64, seed_tex: u64, device: &Device) -> (Tensor<2>, Tensor<2>) {
    let z = |s: u64| Tensor::from_data(TensorData::new(latent(s, cfg.z_dim), [1, cfg.z_dim]), device);
    (z(seed_geo), z(seed_tex))
}

/// Generate the avatar of styles `s` in the pose/shape `params` (paper's exact mode: DMTet
/// is run in posed space on the inverse-skinned grid). Native, blocking.
#[cfg(not(target_arch = "wasm32"))]
pub fn generate_avatar(
    g: &Generator,
    ctx: &BodyContext,
    s: &Styles,
    params: &BodyParams,
    device: &Device,
) -> Result<Avatar, ReadbackError> {
    block_on_ready(generate_avatar_async(g, ctx, s, params, device))
}

/// [`generate_avatar`] for any platform (awaits GPU readbacks in the browser).
pub async fn generate_avatar_async(
    g: &Generator,
    ctx: &BodyContext,
    s: &Styles,
    params: &BodyParams,
    device: &Device,
) -> Result<Avatar, ReadbackError> {
    // Checkpoints between the stages (`cooperative`): in the browser each is a slice of the
    // UI thread's time.
    // Stage marks for `profile` (no-ops unless a caller records).
    profile::stage("synthesis");
    let planes = g.triplanes_async(s).await;
    checkpoint().await;
    profile::stage("posed grid");
    // A new identity is generated in the canonical pose, whose inverse skinning and grid are
    // the same every time (kept in `ctx`).
    let canonical_pose = params.pose == crate::pose_library::da_pose()
        && params.betas.iter().all(|b| *b == 0.0)
        && params.transl == Vec3::ZERO;
    let (posed_inv, posed_grid);
    let (inv, grid) = if canonical_pose {
        let inv = ctx.canonical_inverse();
        (inv, ctx.canonical_grid_async(inv).await)
    } else {
        posed_inv = InverseSkinning::new(&ctx.model, &pose_body(&ctx.model, params), &ctx.canonical);
        checkpoint().await;
        posed_grid = PosedGrid::new_async(ctx, &posed_inv).await;
        (&posed_inv, &posed_grid)
    };
    profile::stage("grid decode");
    let band_points: Vec<Vec3> = grid.band.iter().map(|&i| grid.canonical[i as usize]).collect();
    // Padded (`POINT_ALIGN`): only the rows of `band` are read.
    let band_points = points_tensor(&aligned_points(&band_points), device);
    // Only the outer surface: closed pockets inside the avatar (a grid vertex or two whose SDF
    // stayed positive inside the body, e.g. where the thighs meet in sitting poses) are never
    // seen and would only pollute the exported mesh.
    // On a GPU, a new identity's surface is extracted there (its topology is made once per
    // device); other poses would need a topology of their own per pose (tens of ms of host
    // work), more than the CPU reference costs, and NdArray runs everything on the host anyway.
    let surface = if canonical_pose && !is_ndarray(device) {
        let topology = ctx.canonical_dmtet.get_or_make(device, device_topology(ctx, grid, device)).await;
        surface_on_device(g, ctx, &planes, s, band_points, &topology).await?
    } else {
        surface_on_host(g, ctx, &planes, s, band_points, grid, device).await?
    };
    let SurfaceFields { mesh, gradients, colors } = surface;
    let normals = mesh
        .vertices
        .iter()
        .zip(&gradients)
        .map(|(v, gradient)| {
            // The canonical pose is its own canonical space: no rotation (and no search for
            // the nearest body vertex, ≈ 1 µs per vertex).
            let rotation = if canonical_pose { Mat3::IDENTITY } else { inv.rotation(inv.to_canonical(*v).1) };
            normal_field::posed_normal(rotation, *gradient)
        })
        .collect();
    Ok(Avatar { mesh, normals, colors })
}

/// An extracted outer surface with the canonical SDF gradient and the colour of each vertex.
struct SurfaceFields {
    mesh: TriMesh,
    gradients: Vec<Vec3>,
    colors: Vec<Vec3>,
}

/// The surface by the CPU reference (NdArray: the networks run on the host anyway): the
/// band's fields read back, marching tets on the host, then the normal and texture fields at
/// the vertices, read back together. Two read-backs.
async fn surface_on_host(
    g: &Generator,
    ctx: &BodyContext,
    planes: &Triplanes,
    s: &Styles,
    band_points: Tensor<3>,
    grid: &PosedGrid,
    device: &Device,
) -> Result<SurfaceFields, ReadbackError> {
    let fields = band_fields(g, planes, s, band_points, &grid.band, grid.canonical.len()).await?;
    let sdf = fields.sdf(&grid.template, &ctx.boundary);
    let positions = fields.positions(&ctx.grid.vertices);
    checkpoint().await;
    profile::stage("DMTet");
    let (mesh, _) = marching_tets(&positions, &ctx.grid.tets, &sdf, &grid.canonical).without_cavities();
    if mesh.vertices.is_empty() {
        return Ok(SurfaceFields { mesh, gradients: Vec::new(), colors: Vec::new() });
    }
    checkpoint().await;
    profile::stage("normals & colours");
    // Normal field (eq. 4) and texture field at each vertex's canonical coordinate, read back
    // together (one GPU→CPU transfer): rows of (∇SDF x, y, z, r, g, b).
    // Padded (`POINT_ALIGN`); the rows past the mesh's vertices are dropped below.
    let canonical = aligned_points(&mesh.attributes);
    let n = canonical.len();
    let points = points_tensor(&canonical, device);
    let grad =
        normal_field::sdf_gradient(g, planes, s, &ctx.template, points.clone().reshape([n, 3]), &canonical, device);
    let rgb = g.texture_field(planes, s, points).reshape([n, 3]);
    let both = read_f32(Tensor::cat(vec![grad, rgb], 1)).await?;
    let rows = both.chunks_exact(6).take(mesh.vertices.len());
    let (gradients, colors) = rows.map(|r| (Vec3::from_slice(&r[..3]), Vec3::from_slice(&r[3..]))).unzip();
    Ok(SurfaceFields { mesh, gradients, colors })
}

/// `grid`'s DMTet topology uploaded to `device`.
async fn device_topology(ctx: &BodyContext, grid: &PosedGrid, device: &Device) -> dmtet_gpu::DeviceTopology {
    let topology = dmtet_gpu::DmtetTopology::new_async(&ctx.grid, &ctx.boundary, &grid.template, &grid.band).await;
    topology.upload(&ctx.grid, &grid.canonical, device)
}

/// The surface as device work (`dmtet_gpu`): the band's fields stay on the device, marching
/// tets runs there (one read-back: the counts), the normal and texture fields are evaluated
/// at the vertices there, and everything comes back in one read-back. The template's part of
/// the gradient is added on the host (it is a CPU grid).
async fn surface_on_device(
    g: &Generator,
    ctx: &BodyContext,
    planes: &Triplanes,
    s: &Styles,
    band_points: Tensor<3>,
    topology: &dmtet_gpu::DeviceTopology,
) -> Result<SurfaceFields, ReadbackError> {
    let band = crate::fields::band_rows(g, planes, s, band_points);
    profile::stage("DMTet");
    let surface = dmtet_gpu::extract(topology, band).await?;
    if surface.vertex_count == 0 {
        return Ok(SurfaceFields { mesh: TriMesh::default(), gradients: Vec::new(), colors: Vec::new() });
    }
    profile::stage("normals & colours");
    // Slices between the launches (the browser: ≈ 25 ms of host time each on SwiftShader).
    checkpoint().await;
    let canonical = surface.canonical();
    let n = canonical.dims()[0];
    let h = normal_field::probe_step(&ctx.template);
    let grad = normal_field::residual_gradient(g, planes, s, h, canonical.clone());
    checkpoint().await;
    let rgb = g.texture_field(planes, s, canonical.unsqueeze_dim::<3>(0)).reshape([n, 3]);
    let width = dmtet_gpu::SURFACE_COLUMNS + 6;
    let faces_len = surface.faces.dims()[0] * 3;
    let rows = Tensor::cat(vec![surface.rows, grad, rgb], 1).reshape([n * width]);
    let all = read_f32(Tensor::cat(vec![rows, surface.faces.reshape([faces_len])], 0)).await?;
    let (rows, faces) = all.split_at(n * width);
    let mesh = dmtet_gpu::mesh_from_rows(topology, rows, width, faces, surface.vertex_count);
    let mut gradients = Vec::with_capacity(surface.vertex_count);
    let mut colors = Vec::with_capacity(surface.vertex_count);
    for (row, c) in rows.chunks_exact(width).zip(&mesh.attributes) {
        let residual = Vec3::from_slice(&row[dmtet_gpu::SURFACE_COLUMNS..dmtet_gpu::SURFACE_COLUMNS + 3]);
        gradients.push(residual + normal_field::template_gradient(&ctx.template, *c, h));
        colors.push(Vec3::from_slice(&row[dmtet_gpu::SURFACE_COLUMNS + 3..]));
    }
    let (mesh, _, kept) = mesh.without_cavities_mapped();
    if let Some(kept) = kept {
        gradients = kept.iter().map(|&i| gradients[i as usize]).collect();
        colors = kept.iter().map(|&i| colors[i as usize]).collect();
    }
    Ok(SurfaceFields { mesh, gradients, colors })
}

/// The surface sizes (in [`crate::fields::POINT_ALIGN`] multiples) whose normal- and
/// texture-field kernels [`warm_surface_kernels`] compiles: the demo model's avatars have
/// 5,000–9,000 surface vertices, padded to 21–36 multiples.
pub const WARM_SURFACE_MULTIPLES: std::ops::RangeInclusive<usize> = 16..=40;

/// Compile the kernels of the surface fields (normal field and texture field at the DMTet
/// vertices) for every padded surface size in [`WARM_SURFACE_MULTIPLES`], one size per
/// checkpoint, results dropped. The matrix-multiply kernels are chosen by the batch's size,
/// and a size class the start-up generation did not meet compiled a ≈ 110 ms kernel in the
/// first generation of another avatar on the software-GPU test machine (the 100 ms long-task bound
/// is 100 ms). For the page's idle time after the model loads.
pub async fn warm_surface_kernels(
    g: &Generator,
    ctx: &BodyContext,
    planes: &Triplanes,
    s: &Styles,
    device: &Device,
) -> Result<(), ReadbackError> {
    let h = normal_field::probe_step(&ctx.template);
    for k in WARM_SURFACE_MULTIPLES {
        let n = k * crate::fields::POINT_ALIGN;
        let points = points_tensor(&vec![Vec3::ZERO; n], device);
        let grad = normal_field::residual_gradient(g, planes, s, h, points.clone().reshape([n, 3]));
        let rgb = g.texture_field(planes, s, points).reshape([n, 3]);
        // One value read back: the work and its compiles are done before the next size.
        read_f32(Tensor::cat(vec![grad, rgb], 1).sum()).await?;
        checkpoint().await;
    }
    Ok(())
}

/// Colours of the texture field at canonical points (re-texturing keeps the geometry).
pub async fn recolor_async(
    g: &Generator,
    planes: &Triplanes,
    s: &Styles,
    canonical: &[Vec3],
    device: &Device,
) -> Result<Vec<Vec3>, ReadbackError> {
    if canonical.is_empty() {
        return Ok(Vec::new());
    }
    // Padded (`POINT_ALIGN`), as the generation's colours are: the same kernels.
    let rgb = read_f32(g.texture_field(planes, s, points_tensor(&aligned_points(canonical), device))).await?;
    Ok(rgb.chunks_exact(3).take(canonical.len()).map(Vec3::from_slice).collect())
}

/// Generate in the canonical pose and rig (the fast path's one-off cost).
pub async fn generate_rigged_async(
    g: &Generator,
    ctx: &BodyContext,
    s: &Styles,
    device: &Device,
) -> Result<RiggedAvatar, ReadbackError> {
    let params = BodyParams { pose: crate::pose_library::da_pose(), ..Default::default() };
    let a = generate_avatar_async(g, ctx, s, &params, device).await?;
    checkpoint().await;
    profile::stage("rigging");
    Ok(RiggedAvatar::new(a, ctx))
}
