//! The generator G (paper Sec. 4): latents → triplanes → SDF (template + residual) in canonical
//! space, evaluated at posed-space tet grid vertices carried to canonical space by inverse
//! skinning → DMTet in posed space → textured mesh with the normal field (eq. 4).
//!
//! Tensor work (networks) runs on the caller's burn `Device`; grid bookkeeping and inverse
//! skinning run on the CPU (`geometry`), and so does marching tetrahedra, except for a new
//! identity on a GPU, which is extracted there (`dmtet_gpu`). The geometry fields on the
//! grid are `fields`, the normal field `normal_field`, the rigged fast path `rigging`, the
//! latent modes of multi-modal truncation `network::mapping`.

use burn::tensor::{Device, Tensor, TensorData};
use glam::{Mat3, Vec3};

use crate::body::body_model::BodyModel;
use crate::body::skinning::{pose_body, BodyParams};
use crate::generator::dmtet_gpu;
use crate::generator::fields::{aligned_points, band_fields, points_tensor};
use crate::generator::network::init::latent;
use crate::generator::network::layers::is_ndarray;
use crate::generator::network::synthesis::Triplanes;
use crate::generator::network::GeneratorConfig;
use crate::generator::normal_field;
#[cfg(not(target_arch = "wasm32"))]
use crate::generator::readback::block_on_ready;
use crate::generator::readback::{read_f32, ReadbackError};
use crate::geometry::{marching_tets, InverseSkinning, PosedGrid, TriMesh};
use crate::util::cooperative::checkpoint;
use crate::util::profile;

pub use crate::generator::network::generator_network::{
    is_face_param, is_geometry_head_param, is_texture_param, Generator, Styles,
};
pub use crate::generator::network::mapping::{default_psi, LatentModes, ModePairing};
pub use crate::geometry::BodyContext;

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
    generate_avatar_from_planes_async(g, ctx, s, &planes, params, device).await
}

/// [`generate_avatar_async`] from the triplanes of `s` computed already (a caller that keeps
/// them for later texture-field queries).
pub async fn generate_avatar_from_planes_async(
    g: &Generator,
    ctx: &BodyContext,
    s: &Styles,
    planes: &Triplanes,
    params: &BodyParams,
    device: &Device,
) -> Result<Avatar, ReadbackError> {
    profile::stage("posed grid");
    // A new identity is generated in the canonical pose, whose inverse skinning and grid are
    // the same every time (kept in `ctx`).
    let canonical_pose = params.pose == crate::body::pose_library::da_pose()
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
    let band_points = band_points_tensor(grid, device);
    // Only the outer surface: closed pockets inside the avatar (a grid vertex or two whose SDF
    // stayed positive inside the body, e.g. where the thighs meet in sitting poses) are never
    // seen and would only pollute the exported mesh.
    // On a GPU, a new identity's surface is extracted there (its topology is made once per
    // device); other poses would need a topology of their own per pose (tens of ms of host
    // work), more than the CPU reference costs, and NdArray runs everything on the host anyway.
    let surface = if canonical_pose && !is_ndarray(device) {
        let topology = ctx.canonical_dmtet.get_or_make(device, device_topology(ctx, grid, device)).await;
        surface_on_device(g, ctx, planes, s, band_points, &topology).await?
    } else {
        surface_on_host(g, ctx, planes, s, band_points, grid, device).await?
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

/// The canonical points of `grid`'s band as a `[1, P, 3]` tensor, padded (`POINT_ALIGN`): only
/// the rows of `band` are read.
fn band_points_tensor(grid: &PosedGrid, device: &Device) -> Tensor<3> {
    let points: Vec<Vec3> = grid.band.iter().map(|&i| grid.canonical[i as usize]).collect();
    points_tensor(&aligned_points(&points), device)
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
    let mesh = mesh_on_host(g, ctx, &planes.geometry, s, band_points, grid).await?;
    if mesh.vertices.is_empty() {
        return Ok(SurfaceFields { mesh, gradients: Vec::new(), colors: Vec::new() });
    }
    checkpoint().await;
    profile::stage("normals & colours");
    let (gradients, colors) = vertex_fields(g, ctx, planes, s, &mesh, device).await?;
    Ok(SurfaceFields { mesh, gradients, colors })
}

/// The outer surface by the CPU reference, without its vertices' fields: the band's fields
/// read back, marching tets on the host.
async fn mesh_on_host(
    g: &Generator,
    ctx: &BodyContext,
    geometry: &Tensor<4>,
    s: &Styles,
    band_points: Tensor<3>,
    grid: &PosedGrid,
) -> Result<TriMesh, ReadbackError> {
    let fields = band_fields(g, geometry, s, band_points, &grid.band, grid.canonical.len()).await?;
    let sdf = fields.sdf(&grid.template, &ctx.boundary);
    let positions = fields.positions(&ctx.grid.vertices);
    checkpoint().await;
    profile::stage("DMTet");
    Ok(marching_tets(&positions, &ctx.grid.tets, &sdf, &grid.canonical).without_cavities().0)
}

/// The canonical SDF gradient (normal field, eq. 4) and the texture field's colour at each
/// vertex of `mesh` (its `attributes`, canonical coordinates), read back together (one
/// GPU→CPU transfer): rows of (∇SDF x, y, z, r, g, b).
async fn vertex_fields(
    g: &Generator,
    ctx: &BodyContext,
    planes: &Triplanes,
    s: &Styles,
    mesh: &TriMesh,
    device: &Device,
) -> Result<(Vec<Vec3>, Vec<Vec3>), ReadbackError> {
    // Padded (`POINT_ALIGN`); the rows past the mesh's vertices are dropped below.
    let canonical = aligned_points(&mesh.attributes);
    let n = canonical.len();
    let points = points_tensor(&canonical, device);
    let grad =
        normal_field::sdf_gradient(g, planes, s, &ctx.template, points.clone().reshape([n, 3]), &canonical, device);
    let rgb = g.texture_field(planes, s, points).reshape([n, 3]);
    let both = read_f32(Tensor::cat(vec![grad, rgb], 1)).await?;
    let rows = both.chunks_exact(6).take(mesh.vertices.len());
    Ok(rows.map(|r| (Vec3::from_slice(&r[..3]), Vec3::from_slice(&r[3..]))).unzip())
}

/// A new identity's outer surface in the canonical pose (Da-pose, β = 0) from its geometry
/// planes alone: no texture planes and no normal or texture field at its vertices (about a
/// third of a generation of the shipped model on the CPU). For a caller that judges the outline first
/// ([`crate::reconstruction::garment_codes`]); [`CanonicalGeometry::vertex_fields_async`] adds
/// the rest. By the CPU reference on every device (as [`generate_avatar_async`] on NdArray).
pub struct CanonicalGeometry {
    /// Canonical-pose mesh; `attributes` = canonical coordinates.
    pub mesh: TriMesh,
}

/// [`CanonicalGeometry`] of styles `s`: the geometry planes, the band's fields, marching tets.
pub async fn canonical_geometry_async(
    g: &Generator,
    ctx: &BodyContext,
    s: &Styles,
    device: &Device,
) -> Result<CanonicalGeometry, ReadbackError> {
    profile::stage("synthesis");
    let geometry = g.geometry_planes_async(s).await;
    checkpoint().await;
    profile::stage("posed grid");
    let grid = ctx.canonical_grid_async(ctx.canonical_inverse()).await;
    profile::stage("grid decode");
    let band_points = band_points_tensor(grid, device);
    let mesh = mesh_on_host(g, ctx, &geometry, s, band_points, grid).await?;
    Ok(CanonicalGeometry { mesh })
}

impl CanonicalGeometry {
    /// The unit normals (the canonical pose needs no rotation) and colours of the surface's
    /// vertices for styles `s` (the ones it was made with): the whole synthesis, then the
    /// normal and texture fields at the vertices (one read-back).
    pub async fn vertex_fields_async(
        &self,
        g: &Generator,
        ctx: &BodyContext,
        s: &Styles,
        device: &Device,
    ) -> Result<(Vec<Vec3>, Vec<Vec3>), ReadbackError> {
        if self.mesh.vertices.is_empty() {
            return Ok((Vec::new(), Vec::new()));
        }
        profile::stage("synthesis");
        let planes = g.triplanes_async(s).await;
        checkpoint().await;
        profile::stage("normals & colours");
        let (gradients, colors) = vertex_fields(g, ctx, &planes, s, &self.mesh, device).await?;
        let normals = gradients.into_iter().map(|gr| normal_field::posed_normal(Mat3::IDENTITY, gr)).collect();
        Ok((normals, colors))
    }
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
    let band = crate::generator::fields::band_rows(g, &planes.geometry, s, band_points);
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

/// The surface sizes (in [`crate::generator::fields::POINT_ALIGN`] multiples) whose normal- and
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
        let n = k * crate::generator::fields::POINT_ALIGN;
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
