//! Differentiable rendering of generated avatars for training (paper Sec. 4.2–4.5): for each
//! sample's body pose and camera label, the generator's SDF on the inverse-skinned posed-space
//! tet grid → DMTet surface (differentiable in SDF and offsets) → rasterised → per pixel: the
//! texture field at the pixel's canonical coordinate (RGB), the normal field (∇SDF by central
//! differences, rotated by the skinning rotation, eq. 4) and the antialiased mask; plus the
//! geometry regularisers (eikonal on the visible surface points, SDF cross-entropy over the
//! sign-changing tet edges).
//!
//! Image conventions for the discriminators (all `[B, C, R, R]` in [−1, 1]): RGB sRGB-encoded
//! (texture field output through [`crate::render::colour::encode_srgb_tensor`], the curve of the data
//! and the app) on white; normals in world space with the zero
//! vector on background; mask 2·coverage − 1.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use burn::tensor::{Device, IndexingUpdateOp, Tensor, TensorData};
use glam::{Mat3, Vec3, Vec4};

use super::dmtet::{surface_points, EdgeIndex};
use super::rasterize::{antialias, compose, interpolate, silhouette_pairs, Coverage};
use super::{index_tensor, matrix};
use crate::body::skinning::{pose_body, BodyParams};
use crate::generator::fields::{band_fields, GridFields};
use crate::generator::losses::{eikonal_loss, sdf_cross_entropy};
use crate::generator::network::synthesis::Triplanes;
use crate::generator::normal_field::{posed_normals, sdf_gradient};
use crate::generator::pipeline::{BodyContext, Generator, Styles};
#[cfg(not(target_arch = "wasm32"))]
use crate::generator::readback::block_on_ready;
use crate::generator::readback::{read_f32, ReadbackError};
use crate::geometry::inverse_skinning::InverseSkinning;
use crate::geometry::{marching_tets, PosedGrid, TriMesh};
use crate::render::camera::{OrbitCamera, View};
use crate::render::colour::encode_srgb_tensor;
use crate::render::rasterize::rasterize;

/// Rendered fakes and regularisers of a batch.
pub struct FakeViews {
    pub rgb: Tensor<4>,
    pub normal: Tensor<4>,
    pub mask: Tensor<4>,
    /// Mean eikonal loss over the batch's visible surface points.
    pub eikonal: Tensor<1>,
    /// Mean SDF cross-entropy over the batch's sign-changing edges.
    pub cross_entropy: Tensor<1>,
    /// Triangles extracted per sample (0 = empty surface: its images are background).
    pub triangles: Vec<usize>,
    /// With [`render_avatar_views_async`]: the RGB images of the same surfaces coloured
    /// by the texture field of the other styles (same layout as `rgb`).
    pub rgb_retextured: Option<Tensor<4>>,
    /// The triplanes of the batch's avatars (`[B, 3·C, R, R]`, with gradients), for terms
    /// that evaluate the fields elsewhere (the scan and face terms) without a second synthesis.
    pub planes: Triplanes,
    /// Per rendered view (in the images' order): the covered pixels and their canonical
    /// surface points, where the RGB image is the texture field (None: nothing covered).
    pub surfaces: Vec<Option<PixelSurface>>,
}

/// The surface a view sees: covered pixel indices (`y·res + x`) and each one's canonical
/// point (`[P, 3]`, with gradients through the geometry). A covered pixel's RGB is the texture
/// field at its point (no shading; only the mask is antialiased), so with the geometry fixed
/// the RGB term's texture gradient needs only these points (`trainer fit-codes`).
#[derive(Clone, Debug)]
pub struct PixelSurface {
    pub pixels: Vec<u32>,
    pub canonical: Tensor<2>,
}

fn vec3_tensor(v: &[Vec3], device: &Device) -> Tensor<2> {
    matrix(v.iter().flat_map(|p| p.to_array()).collect(), v.len(), 3, device)
}

fn styles_of(s: &Styles, b: usize) -> Styles {
    Styles { geo: s.geo.clone().narrow(0, b, 1), tex: s.tex.clone().narrow(0, b, 1) }
}

/// Posed grids memoised per body pose: a dataset has one pose per subject and many views, and
/// the nearest-vertex search of inverse skinning is the renderer's largest CPU cost.
pub struct PosedGridCache {
    map: Mutex<HashMap<Vec<u32>, Arc<PosedGrid>>>,
    capacity: usize,
}

impl Default for PosedGridCache {
    fn default() -> Self {
        Self::new(1024)
    }
}

impl PosedGridCache {
    /// A cache holding at most `capacity` poses (it starts over when full).
    pub fn new(capacity: usize) -> Self {
        Self { map: Mutex::new(HashMap::new()), capacity: capacity.max(1) }
    }

    /// The posed grid of `body` (pose, shape and translation), computed on first use.
    pub fn get(&self, ctx: &BodyContext, body: &BodyParams, inv: &InverseSkinning) -> Arc<PosedGrid> {
        crate::util::cooperative::run_blocking(self.get_async(ctx, body, inv))
    }

    /// [`PosedGridCache::get`] with the grid computed in slices (`cooperative`) in the browser.
    pub async fn get_async(&self, ctx: &BodyContext, body: &BodyParams, inv: &InverseSkinning) -> Arc<PosedGrid> {
        let key: Vec<u32> = body
            .pose
            .iter()
            .flat_map(|r| r.to_array())
            .chain(body.betas.iter().copied())
            .chain(body.transl.to_array())
            .map(f32::to_bits)
            .collect();
        if let Some(g) = self.map.lock().ok().and_then(|m| m.get(&key).cloned()) {
            return g;
        }
        let g = Arc::new(PosedGrid::new_async(ctx, inv).await);
        if let Ok(mut m) = self.map.lock() {
            if m.len() >= self.capacity {
                m.clear();
            }
            m.insert(key, g.clone());
        }
        g
    }

    pub fn len(&self) -> usize {
        self.map.lock().map(|m| m.len()).unwrap_or(0)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// `[H·W, C]` image → `[1, C, H, W]`.
fn to_nchw(img: Tensor<2>, res: usize) -> Tensor<4> {
    let c = img.dims()[1];
    img.reshape([res, res, c]).permute([2, 0, 1]).unsqueeze_dim::<4>(0)
}

/// Render the generated avatars of `styles` (batch B) under `views` (B entries: camera and body
/// pose) at `res`², with posed grids from `grids`. Native: reads intermediate values back
/// synchronously ([`render_avatars_async`] is the browser's).
#[cfg(not(target_arch = "wasm32"))]
pub fn render_avatars(
    g: &Generator,
    ctx: &BodyContext,
    styles: &Styles,
    views: &[View],
    res: usize,
    grids: &PosedGridCache,
    device: &Device,
) -> Result<FakeViews, ReadbackError> {
    block_on_ready(render_avatars_async(g, ctx, styles, views, res, grids, device))
}

/// [`render_avatars`] on any platform: the read-backs it needs are awaited.
pub async fn render_avatars_async(
    g: &Generator,
    ctx: &BodyContext,
    styles: &Styles,
    views: &[View],
    res: usize,
    grids: &PosedGridCache,
    device: &Device,
) -> Result<FakeViews, ReadbackError> {
    let views: Vec<Vec<View>> = views.iter().map(|v| vec![v.clone()]).collect();
    render_avatar_views_async(g, ctx, styles, None, &views, res, grids, device).await
}

/// Render avatar b of `styles` (batch B) under each view of `views[b]` at `res`²: one surface
/// per avatar (triplanes, inverse skinning, DMTet, surface fields), rasterised and shaded per
/// view, so several views of one avatar cost little more than one. The avatar's body pose and
/// shape are those of `views[b][0]`; the other views contribute their cameras only. The
/// images come out view by view in order (batch Σ|views[b]|); the eikonal term is the mean over
/// views, the cross-entropy the mean over avatars.
#[cfg(not(target_arch = "wasm32"))]
pub fn render_avatar_views(
    g: &Generator,
    ctx: &BodyContext,
    styles: &Styles,
    views: &[Vec<View>],
    res: usize,
    grids: &PosedGridCache,
    device: &Device,
) -> Result<FakeViews, ReadbackError> {
    block_on_ready(render_avatar_views_async(g, ctx, styles, None, views, res, grids, device))
}

/// [`render_avatar_views`], and with `retexture` (batch B styles) also the RGB of each surface
/// of `styles` coloured by the texture field of `retexture` (its triplanes and texture styles)
/// at the same canonical pixel coordinates, held constant (`FakeViews::rgb_retextured`). The
/// texture-swap term of the reconstruction warm-up uses it: geometry from one code, colours
/// that must follow the texture code alone.
///
/// The read-backs (band fields, clip-space positions, pixel coordinates) are awaited, so the
/// browser's GPU is never blocked on.
#[allow(clippy::too_many_arguments)]
pub async fn render_avatar_views_async(
    g: &Generator,
    ctx: &BodyContext,
    styles: &Styles,
    retexture: Option<&Styles>,
    views: &[Vec<View>],
    res: usize,
    grids: &PosedGridCache,
    device: &Device,
) -> Result<FakeViews, ReadbackError> {
    let n = ctx.grid.vertices.len();
    let mut out = Gathered::default();
    // Stage timings on stderr with GETAVATAR_PROFILE set (native only: no clock on wasm32).
    #[cfg(not(target_arch = "wasm32"))]
    let t0 = std::env::var_os("GETAVATAR_PROFILE").is_some().then(std::time::Instant::now);
    let lap = |_what: &str| {
        #[cfg(not(target_arch = "wasm32"))]
        if let Some(t0) = t0 {
            eprintln!("    {:>8.3} s  render: {_what}", t0.elapsed().as_secs_f64());
        }
    };
    let mut all_planes = Vec::new();
    for (b, cams) in views.iter().enumerate() {
        let s = styles_of(styles, b);
        let planes = g.triplanes(&s);
        all_planes.push(planes.clone());
        let Some(first) = cams.first() else { continue };
        let re = retexture.map(|r| {
            let r = styles_of(r, b);
            (g.triplanes(&r), r)
        });
        lap("triplanes");
        crate::util::cooperative::checkpoint().await;
        // Inverse skinning of the posed-space grid (eq. 2).
        let posed = pose_body(&ctx.model, &first.body);
        let inv = InverseSkinning::new(&ctx.model, &posed, &ctx.canonical);
        let grid = grids.get_async(ctx, &first.body, &inv).await;
        let canon = &grid.canonical;
        let canon_t = vec3_tensor(canon, device);
        lap("posed grid");
        crate::util::cooperative::checkpoint().await;
        // Pass 1, values only: the fields on the whole band decide the topology.
        let fields = if grid.band.is_empty() {
            GridFields::zeros(n)
        } else {
            let band_pts = canon_t.clone().select(0, index_tensor(&grid.band, device)).unsqueeze_dim::<3>(0);
            let planes_c =
                Triplanes { geometry: planes.geometry.clone().detach(), texture: planes.texture.clone().detach() };
            let s_c = Styles { geo: s.geo.clone().detach(), tex: s.tex.clone().detach() };
            band_fields(g, &planes_c.geometry, &s_c, band_pts, &grid.band, n).await?
        };
        let sdf_v = fields.sdf(&grid.template, &ctx.boundary);
        let pos_v = fields.positions(&ctx.grid.vertices);
        lap("band fields (values)");
        crate::util::cooperative::checkpoint().await;
        let mesh = marching_tets(&pos_v, &ctx.grid.tets, &sdf_v, canon);
        out.triangles.extend(cams.iter().map(|_| mesh.faces.len()));
        lap("marching tets");
        crate::util::cooperative::checkpoint().await;
        if mesh.faces.is_empty() {
            let bg = |v: f32, c: usize| Tensor::<4>::ones([1, c, res, res], device) * v;
            for _ in cams {
                out.surfaces.push(None);
                out.rgbs.push(bg(1.0, 3));
                out.normals.push(bg(0.0, 3));
                out.masks.push(bg(-1.0, 1));
                if re.is_some() {
                    out.retextured.push(bg(1.0, 3));
                }
            }
            continue;
        }
        let edges = EdgeIndex::new(&mesh);

        // Pass 2, with gradients (see [`surface_fields`]).
        let (sdf, positions) =
            surface_fields(g, &planes, &s, &canon_t, &fields, &grid.band, &edges, (&sdf_v, &pos_v), device);
        lap("surface fields (gradients)");
        crate::util::cooperative::checkpoint().await;
        let (ia, ib) = (index_tensor(&edges.a, device), index_tensor(&edges.b, device));
        out.ce.push(sdf_cross_entropy(sdf.clone().select(0, ia), sdf.clone().select(0, ib)));
        let verts = surface_points(&edges, positions, sdf.clone(), device);
        let vcanon = surface_points(&edges, canon_t, sdf, device);
        let nv = mesh.vertices.len();
        // Per-vertex skinning rotation (nearest body vertex), interpolated per pixel below.
        let rot: Vec<f32> = mesh
            .vertices
            .iter()
            .flat_map(|v| {
                let r: Mat3 = inv.rotation(inv.to_canonical(*v).1);
                r.transpose().to_cols_array() // row-major
            })
            .collect();
        let rot = matrix(rot, nv, 9, device);
        let ones = Tensor::<2>::ones([nv, 1], device);
        lap("surface");
        crate::util::cooperative::checkpoint().await;

        let surf = Surface { mesh: &mesh, verts, vcanon, rot, ones };
        for view in cams {
            render_view(g, ctx, (&planes, &s), re.as_ref(), &surf, view, res, device, &mut out, &lap).await?;
        }
    }
    let mean = |v: Vec<Tensor<1>>| {
        let k = v.len().max(1) as f32;
        v.into_iter().reduce(|a, b| a + b).map(|t| t / k).unwrap_or_else(|| Tensor::zeros([1], device))
    };
    Ok(FakeViews {
        rgb: Tensor::cat(out.rgbs, 0),
        normal: Tensor::cat(out.normals, 0),
        mask: Tensor::cat(out.masks, 0),
        eikonal: mean(out.eik),
        cross_entropy: mean(out.ce),
        triangles: out.triangles,
        rgb_retextured: (!out.retextured.is_empty()).then(|| Tensor::cat(out.retextured, 0)),
        planes: Triplanes {
            geometry: Tensor::cat(all_planes.iter().map(|p| p.geometry.clone()).collect(), 0),
            texture: Tensor::cat(all_planes.into_iter().map(|p| p.texture).collect(), 0),
        },
        surfaces: out.surfaces,
    })
}

/// What the views of a batch render to, gathered in order.
#[derive(Default)]
struct Gathered {
    rgbs: Vec<Tensor<4>>,
    normals: Vec<Tensor<4>>,
    masks: Vec<Tensor<4>>,
    eik: Vec<Tensor<1>>,
    ce: Vec<Tensor<1>>,
    triangles: Vec<usize>,
    retextured: Vec<Tensor<4>>,
    surfaces: Vec<Option<PixelSurface>>,
}

/// One avatar's extracted surface as the views render it: the DMTet mesh (topology, CPU),
/// its posed and canonical vertices with gradients, per-vertex skinning rotations (row-major
/// 3×3) and a column of ones (for coverage).
struct Surface<'a> {
    mesh: &'a TriMesh,
    verts: Tensor<2>,
    vcanon: Tensor<2>,
    rot: Tensor<2>,
    ones: Tensor<2>,
}

/// Pass 2 of the fields, with gradients: only the endpoints of sign-changing edges reach the
/// losses (surface points, cross-entropy), so the fields are re-evaluated there alone; the
/// values equal pass 1's (`sdf_v`, `pos_v`), the rest of the grid is constant.
#[allow(clippy::too_many_arguments)]
fn surface_fields(
    g: &Generator,
    planes: &Triplanes,
    s: &Styles,
    canon_t: &Tensor<2>,
    fields: &GridFields,
    band: &[u32],
    edges: &EdgeIndex,
    (sdf_v, pos_v): (&[f32], &[Vec3]),
    device: &Device,
) -> (Tensor<1>, Tensor<2>) {
    let n = pos_v.len();
    let mut in_band = vec![false; n];
    for &i in band {
        in_band[i as usize] = true;
    }
    let mut seen = vec![false; n];
    let mut ends: Vec<u32> = Vec::new();
    for &i in edges.a.iter().chain(&edges.b) {
        if in_band[i as usize] && !seen[i as usize] {
            seen[i as usize] = true;
            ends.push(i);
        }
    }
    let mut sdf = Tensor::<1>::from_data(TensorData::new(sdf_v.to_vec(), [n]), device);
    let pos_flat: Vec<f32> = pos_v.iter().flat_map(|p| p.to_array()).collect();
    let mut positions = Tensor::<2>::from_data(TensorData::new(pos_flat, [n, 3]), device);
    if !ends.is_empty() {
        let m = ends.len();
        let idx = index_tensor(&ends, device);
        let pts = canon_t.clone().select(0, idx.clone()).unsqueeze_dim::<3>(0);
        let (r, o) = g.geometry_fields(planes, s, pts);
        let r0: Vec<f32> = ends.iter().map(|&i| fields.residual[i as usize]).collect();
        let o0: Vec<f32> = ends.iter().flat_map(|&i| fields.offset_of(i as usize)).collect();
        let dr = r.reshape([m]) - Tensor::<1>::from_data(TensorData::new(r0, [m]), device);
        let d_o = o.reshape([m, 3]) - Tensor::<2>::from_data(TensorData::new(o0, [m, 3]), device);
        sdf = sdf.select_assign(0, idx.clone(), dr, IndexingUpdateOp::Add);
        positions = positions.select_assign(0, idx, d_o, IndexingUpdateOp::Add);
    }
    (sdf, positions)
}

/// One view of one avatar's surface: rasterised, RGB from the texture field (and the
/// retexturing styles' where given), normals from the normal field (eq. 4), the antialiased
/// mask; appended to `out` (background images where nothing is covered).
#[allow(clippy::too_many_arguments)]
async fn render_view(
    g: &Generator,
    ctx: &BodyContext,
    (planes, s): (&Triplanes, &Styles),
    re: Option<&(Triplanes, Styles)>,
    surf: &Surface<'_>,
    view: &View,
    res: usize,
    device: &Device,
    out: &mut Gathered,
    lap: &dyn Fn(&str),
) -> Result<(), ReadbackError> {
    let proj = OrbitCamera::default().projection_gl(1.0);
    let nv = surf.mesh.vertices.len();
    // Camera and rasterisation.
    let vp = proj * view.world_to_camera;
    let m = matrix(vp.transpose().to_cols_array().to_vec(), 4, 4, device); // rows of vp
    let clip = Tensor::cat(vec![surf.verts.clone(), Tensor::ones([nv, 1], device)], 1).matmul(m.transpose());
    let clip_v: Vec<Vec4> = read_f32(clip.clone()).await?.chunks_exact(4).map(Vec4::from_slice).collect();
    let r = rasterize(&clip_v, &surf.mesh.faces, res, res);
    let cov = Coverage::new(&r, &surf.mesh.faces);
    if cov.is_empty() {
        let bg = |v: f32, c: usize| Tensor::<4>::ones([1, c, res, res], device) * v;
        out.surfaces.push(None);
        out.rgbs.push(bg(1.0, 3));
        out.normals.push(bg(0.0, 3));
        if re.is_some() {
            out.retextured.push(bg(1.0, 3));
        }
        // Keep the silhouette path alive (zero contribution) for a consistent graph.
        out.masks.push(bg(-1.0, 1) + surf.ones.clone().sum().reshape([1, 1, 1, 1]) * 0.0);
        return Ok(());
    }
    lap("rasterize");
    crate::util::cooperative::checkpoint().await;
    let p = cov.len();
    let pix_canon = interpolate(&cov, clip.clone(), surf.vcanon.clone(), device); // [P, 3]
    out.surfaces.push(Some(PixelSurface { pixels: cov.pixels.clone(), canonical: pix_canon.clone() }));

    // RGB: texture field at each pixel's canonical coordinate.
    let color = g.texture_field(planes, s, pix_canon.clone().unsqueeze_dim::<3>(0)).reshape([p, 3]);
    let color = encode_srgb_tensor(color);
    let rgb = compose(&cov, color * 2.0 - 1.0, &[1.0, 1.0, 1.0], device);
    if let Some((rp, rs)) = re {
        let c = g.texture_field(rp, rs, pix_canon.clone().detach().unsqueeze_dim::<3>(0)).reshape([p, 3]);
        let c = encode_srgb_tensor(c);
        out.retextured.push(to_nchw(compose(&cov, c * 2.0 - 1.0, &[1.0, 1.0, 1.0], device), res));
    }

    lap("texture field");

    crate::util::cooperative::checkpoint().await;
    // Normal field (eq. 4): ∇(template + residual) at each pixel's canonical point,
    // rotated to posed space by the interpolated skinning rotation.
    let pc: Vec<Vec3> = read_f32(pix_canon.clone()).await?.chunks_exact(3).map(Vec3::from_slice).collect();
    let grad = sdf_gradient(g, planes, s, &ctx.template, pix_canon, &pc, device);
    out.eik.push(eikonal_loss(grad.clone()));
    let rpix = interpolate(&cov, clip.clone().detach(), surf.rot.clone(), device).reshape([p, 3, 3]);
    let nworld = posed_normals(rpix, grad);
    let normal = compose(&cov, nworld, &[0.0, 0.0, 0.0], device);

    lap("normal field");

    crate::util::cooperative::checkpoint().await;
    // Mask with silhouette gradients.
    let cover = compose(&cov, interpolate(&cov, clip.clone(), surf.ones.clone(), device), &[0.0], device);
    let mask = antialias(cover, &silhouette_pairs(&r, &clip_v, &surf.mesh.faces), clip, res, res, device);
    lap("antialiased mask");
    crate::util::cooperative::checkpoint().await;
    out.rgbs.push(to_nchw(rgb, res));
    out.normals.push(to_nchw(normal, res));
    out.masks.push(to_nchw(mask * 2.0 - 1.0, res));
    Ok(())
}
