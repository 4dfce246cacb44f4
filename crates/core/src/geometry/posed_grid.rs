//! The tet grid under one body pose (paper eq. 2) and the band where the generator's fields
//! are evaluated: what generation needs about the body ([`BodyContext`], prepared once per
//! body model and config), each posed-space grid vertex carried to canonical space by
//! SMPL-guided inverse skinning ([`PosedGrid`]), and the grid vertices near enough to the body
//! for the SDF residual to matter ([`field_band`]).

use glam::Vec3;

use super::inverse_skinning::{canonical_body, InverseSkinning, UNWARP_SLACK};
use super::spatial::{scatter_nearest, Lattice, NONE_WITHIN};
use super::template_sdf::TemplateSdf;
use super::tet_grid::{TetGrid, REFERENCE_BOX_CENTER, REFERENCE_BOX_SIZE};
use crate::body::body_model::BodyModel;
use crate::body::skinning::PosedBody;
#[cfg(target_arch = "wasm32")]
use crate::util::cooperative::checkpoint;
use crate::util::cooperative::run_blocking;

/// Bound of the generator's SDF residual on top of the template SDF, metres: loose dresses,
/// coats and hair reach about this far from the body. The residual decoder is softly bounded
/// to it (`network::decoders`), so farther out the SDF has the template's sign.
pub const SDF_RESIDUAL_MAX: f32 = 0.2;

/// What generation needs about the body, prepared once per body model and grid resolution.
pub struct BodyContext {
    pub model: BodyModel,
    /// Canonical body: Da-pose, β = 0.
    pub canonical: PosedBody,
    pub template: TemplateSdf,
    pub grid: TetGrid,
    /// Whether each grid vertex lies on the box boundary.
    pub boundary: Vec<bool>,
    /// The grid under the canonical body itself (Da-pose, β = 0), made on first use: every
    /// new identity is generated there, and its inverse skinning is the same each time
    /// ([`BodyContext::canonical_grid_async`]).
    canonical_grid: std::sync::OnceLock<PosedGrid>,
    /// The canonical body's inverse skinning (into itself), made on first use
    /// ([`BodyContext::canonical_inverse`]).
    canonical_inverse: std::sync::OnceLock<InverseSkinning>,
    /// The canonical grid's DMTet topology on each device that extracted a surface there
    /// (`crate::generator::dmtet_gpu::DeviceTopology`).
    #[cfg(any(feature = "generator", feature = "wgpu"))]
    pub canonical_dmtet: super::per_device::PerDevice,
}

impl BodyContext {
    /// The grid under the canonical body ([`PosedGrid::new_async`] with `inv`, which must be
    /// the canonical pose's inverse skinning), computed once and kept.
    pub async fn canonical_grid_async(&self, inv: &InverseSkinning) -> &PosedGrid {
        if let Some(grid) = self.canonical_grid.get() {
            return grid;
        }
        let grid = PosedGrid::new_async(self, inv).await;
        // Another task may have filled it meanwhile: the same values, either is kept.
        self.canonical_grid.get_or_init(|| grid)
    }

    /// The inverse skinning of the canonical body into itself, computed once and kept: what
    /// every new identity, generated in the canonical pose, needs (a k-d tree over the body's
    /// vertices and their inverse transforms, ≈ 10 ms of host time per identity otherwise).
    pub fn canonical_inverse(&self) -> &InverseSkinning {
        self.canonical_inverse.get_or_init(|| InverseSkinning::new(&self.model, &self.canonical, &self.canonical))
    }

    /// The context of `model` for a template SDF of `template_res`³ cells and a tet grid of
    /// `tet_res`³ cubes (a generator config's `template_res` and `tet_res`).
    pub fn with_resolution(model: BodyModel, template_res: usize, tet_res: usize) -> Self {
        run_blocking(Self::with_resolution_async(model, template_res, tet_res))
    }

    /// [`BodyContext::with_resolution`] with checkpoints (the template SDF is about a second
    /// of work in the browser).
    pub async fn with_resolution_async(model: BodyModel, template_res: usize, tet_res: usize) -> Self {
        let canonical = canonical_body(&model);
        let min = REFERENCE_BOX_CENTER - Vec3::splat(REFERENCE_BOX_SIZE / 2.0);
        let template =
            TemplateSdf::from_mesh_async(&canonical.vertices, &model.faces, template_res, min, REFERENCE_BOX_SIZE, 3);
        // Natively the tet grid is built on a thread of its own meanwhile.
        #[cfg(not(target_arch = "wasm32"))]
        let (template, (grid, boundary)) = std::thread::scope(|sc| {
            let grid = sc.spawn(|| {
                let grid = TetGrid::reference(tet_res);
                let boundary = grid.boundary_flags();
                (grid, boundary)
            });
            let template = run_blocking(template);
            (template, grid.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic)))
        });
        #[cfg(target_arch = "wasm32")]
        let (template, grid, boundary) = {
            let template = template.await;
            checkpoint().await;
            let grid = TetGrid::reference(tet_res);
            let boundary = grid.boundary_flags();
            (template, grid, boundary)
        };
        Self::assemble(model, canonical, template, grid, boundary)
    }

    /// The context of its parts (`canonical` from [`canonical_body`] of `model`, `grid` and
    /// `boundary` from [`TetGrid::reference`]), the canonical grid still to be made.
    pub(crate) fn assemble(
        model: BodyModel,
        canonical: PosedBody,
        template: TemplateSdf,
        grid: TetGrid,
        boundary: Vec<bool>,
    ) -> Self {
        Self {
            model,
            canonical,
            template,
            grid,
            boundary,
            canonical_grid: std::sync::OnceLock::new(),
            canonical_inverse: std::sync::OnceLock::new(),
            #[cfg(any(feature = "generator", feature = "wgpu"))]
            canonical_dmtet: Default::default(),
        }
    }

    /// This context with its canonical grid already made (`context_cache`: what
    /// [`BodyContext::canonical_grid_async`] made for the same body and grid before).
    pub(crate) fn with_canonical_grid(self, grid: PosedGrid) -> Self {
        // A fresh context's lock is empty: the set cannot fail.
        let _ = self.canonical_grid.set(grid);
        self
    }

    /// The canonical grid when it has been made.
    pub fn canonical_grid_made(&self) -> Option<&PosedGrid> {
        self.canonical_grid.get()
    }

    /// Longest tet edge of the grid.
    fn grid_edge(&self) -> f32 {
        REFERENCE_BOX_SIZE / self.grid.res.max(1) as f32 * 3f32.sqrt()
    }

    /// |template SDF| below which [`field_band`] evaluates the fields.
    fn field_reach(&self) -> f32 {
        SDF_RESIDUAL_MAX + 2.0 * self.grid_edge()
    }
}

/// Grid vertices where the generator's geometry fields are evaluated: |template SDF| below
/// the residual bound ([`SDF_RESIDUAL_MAX`]) plus two tet edges, off the box boundary, and not
/// `guarded` (space the pose vacated, see `inverse_skinning::guarded_template`: there the
/// canonical point lies inside another body part, whose learned residual would turn the
/// vacated space inside and leave floating fragments). Farther out the SDF has the template's
/// sign whatever the residual and no sign-changing edge reaches (the template is ~1-Lipschitz),
/// so residual and offsets are 0 there: same surface, a fraction of the decoder work.
pub fn field_band(ctx: &BodyContext, template: &[f32], guarded: &[bool]) -> Vec<u32> {
    let reach = ctx.field_reach();
    (0..template.len())
        .filter(|&i| {
            template[i].abs() < reach
                && !ctx.boundary.get(i).copied().unwrap_or(true)
                && !guarded.get(i).copied().unwrap_or(false)
        })
        .map(|i| i as u32)
        .collect()
}

/// Posed-space distance from the body beyond which [`PosedGrid`] skips un-warping a grid
/// vertex (`InverseSkinning::canonical_templates`): past the field band by the un-warp slack
/// and one more edge, and deeper than any body part is thick, so those vertices are outside,
/// off the band and on no sign-changing edge either way.
pub fn far_from_body(ctx: &BodyContext) -> f32 {
    ctx.field_reach() + UNWARP_SLACK + ctx.grid_edge()
}

/// Grid vertices un-warped between two checkpoints in the browser (~1 ms of work).
#[cfg(target_arch = "wasm32")]
const VERTICES_PER_SLICE: usize = 512;

/// The tet grid under one body pose (paper eq. 2): each posed-space grid vertex carried to
/// canonical space by SMPL-guided inverse skinning, and the template SDF there.
pub struct PosedGrid {
    pub canonical: Vec<Vec3>,
    pub template: Vec<f32>,
    /// Grid vertices where the generator's fields are evaluated ([`field_band`]).
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
        run_blocking(Self::with_far_async(ctx, inv, far))
    }

    /// [`PosedGrid::new`] for any host: natively split over the CPU cores as a whole; in the
    /// browser in slices with a `checkpoint` after each (the grid is ~0.8 s of work there).
    pub async fn new_async(ctx: &BodyContext, inv: &InverseSkinning) -> Self {
        Self::with_far_async(ctx, inv, far_from_body(ctx)).await
    }

    async fn with_far_async(ctx: &BodyContext, inv: &InverseSkinning, far: f32) -> Self {
        let verts = &ctx.grid.vertices;
        let n = ctx.grid.res + 1;
        // With a finite reach, each grid vertex's nearest posed body vertex comes from
        // scattering the body's vertices over the lattice (`spatial::scatter_nearest`: the k-d
        // tree's answers for an order of magnitude less work); then the un-warp.
        let lattice = far.is_finite().then(|| Lattice::of(verts, n, ctx.grid.min, ctx.grid.cell())).flatten();
        let nearest = match &lattice {
            Some(lattice) => Some(nearest_body_vertices(lattice, inv, far).await),
            None => None,
        };
        let map = |start: usize, chunk: &[Vec3]| -> Vec<(Vec3, f32, bool)> {
            match &nearest {
                Some(near) => chunk
                    .iter()
                    .zip(near.0[start..].iter().zip(&near.1[start..]))
                    .map(|(x, (&i, &d))| {
                        let nearest = (i != NONE_WITHIN).then_some((i as usize, d));
                        inv.canonical_template_near(&ctx.template, *x, nearest, far)
                    })
                    .collect(),
                None => inv.canonical_templates(&ctx.template, chunk, far),
            }
        };
        #[cfg(not(target_arch = "wasm32"))]
        let mapped: Vec<(Vec3, f32, bool)> = {
            let threads = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1).clamp(1, 16);
            let chunk = verts.len().div_ceil(threads).max(1);
            let map = &map;
            std::thread::scope(|sc| {
                let handles: Vec<_> =
                    verts.chunks(chunk).enumerate().map(|(i, c)| sc.spawn(move || map(i * chunk, c))).collect();
                // A worker's panic is a bug: re-raise it here rather than drop its chunk of
                // the grid (which would misalign every later index).
                handles
                    .into_iter()
                    .flat_map(|h| h.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic)))
                    .collect()
            })
        };
        #[cfg(target_arch = "wasm32")]
        let mapped = {
            let mut all = Vec::with_capacity(verts.len());
            for (i, c) in verts.chunks(VERTICES_PER_SLICE).enumerate() {
                all.extend(map(i * VERTICES_PER_SLICE, c));
                checkpoint().await;
            }
            all
        };
        let guarded: Vec<bool> = mapped.iter().map(|m| m.2).collect();
        let (canonical, template): (Vec<Vec3>, Vec<f32>) = mapped.into_iter().map(|(c, t, _)| (c, t)).unzip();
        let band = field_band(ctx, &template, &guarded);
        Self { canonical, template, band }
    }
}

/// Body vertices scattered over the lattice between two checkpoints in the browser (~1 ms).
#[cfg(target_arch = "wasm32")]
const BODY_VERTICES_PER_SLICE: usize = 64;

/// Per grid vertex (`lattice`), the nearest of `inv`'s posed body vertices closer than `far`,
/// as [`scatter_nearest`]'s index and squared-distance slots: natively the grid's z-slices in
/// slabs over the CPU cores, in the browser the body's vertices in slices.
async fn nearest_body_vertices(lattice: &Lattice, inv: &InverseSkinning, far: f32) -> (Vec<u32>, Vec<f32>) {
    let n = lattice.n;
    let body = inv.posed_vertices();
    let (mut index, mut dist2) = (vec![NONE_WITHIN; n * n * n], vec![far * far; n * n * n]);
    #[cfg(not(target_arch = "wasm32"))]
    {
        let threads = std::thread::available_parallelism().map(|t| t.get()).unwrap_or(1).clamp(1, 16);
        let slab = n.div_ceil(threads).max(1);
        std::thread::scope(|sc| {
            let parts = index.chunks_mut(n * n * slab).zip(dist2.chunks_mut(n * n * slab));
            for (s, (idx, d2)) in parts.enumerate() {
                sc.spawn(move || scatter_nearest(lattice, body, 0, far, s * slab, idx, d2));
            }
        });
    }
    #[cfg(target_arch = "wasm32")]
    for (b, batch) in body.chunks(BODY_VERTICES_PER_SLICE).enumerate() {
        scatter_nearest(lattice, batch, b * BODY_VERTICES_PER_SLICE, far, 0, &mut index, &mut dist2);
        checkpoint().await;
    }
    (index, dist2)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::cooperative::run_blocking;

    /// The kept canonical grid is the one [`PosedGrid::new`] makes for the canonical body, and
    /// it is made once.
    #[test]
    fn the_canonical_grid_is_computed_once_and_equals_a_fresh_one() {
        let ctx = BodyContext::with_resolution(BodyModel::default_body().unwrap(), 24, 16);
        let inv = InverseSkinning::new(&ctx.model, &ctx.canonical, &ctx.canonical);
        let fresh = PosedGrid::new(&ctx, &inv);
        let kept = run_blocking(ctx.canonical_grid_async(&inv));
        assert!(!kept.band.is_empty());
        assert_eq!((&kept.band, &kept.template), (&fresh.band, &fresh.template));
        assert!(kept.canonical.iter().zip(&fresh.canonical).all(|(a, b)| a.to_array() == b.to_array()));
        let again = run_blocking(ctx.canonical_grid_async(&inv));
        assert!(std::ptr::eq(kept, again), "the second call reuses the first's grid");
    }
}
