//! SMPL-guided inverse skinning (paper Sec. 4.2, eq. 2): a posed-space point x_d is carried to
//! canonical space with the blended transform of its nearest posed body vertex i (K = 1):
//!
//! `x_c = T_cano,i · (T_obs,i⁻¹ · x_d − δ_i)`
//!
//! where T_obs,i is vertex i's LBS transform in the observed pose/shape, δ_i its shape
//! (and pose-corrective) offset, and T_cano,i its transform in the canonical Da-pose with β = 0.
//! Normals go the other way with the rotation nearest to lin(T_obs,i) · lin(T_cano,i)⁻¹ (eq. 4).

use glam::{Mat3, Mat4, Vec3};

use crate::body::body_model::BodyModel;
use crate::body::pose_library::da_pose;
use crate::body::skinning::{pose_body, BodyParams, PosedBody};
use crate::geometry::spatial::KdTree;

pub struct InverseSkinning {
    tree: KdTree,
    /// Per body vertex: T_obs⁻¹.
    inv_obs: Vec<Mat4>,
    /// Per body vertex: shape offset δ in the rest pose.
    offsets: Vec<Vec3>,
    /// Per body vertex: T_cano.
    cano: Vec<Mat4>,
    /// Per body vertex: T_obs (rotations for normals are computed on demand: only the
    /// vertices nearest to surface points need them).
    obs: Vec<Mat4>,
}

/// The canonical body: Da-pose, β = 0.
pub fn canonical_body(model: &BodyModel) -> PosedBody {
    pose_body(model, &BodyParams { pose: da_pose(), ..Default::default() })
}

impl InverseSkinning {
    /// Prepare for the observed body `posed` (from `pose_body(model, params)`), mapping into
    /// the canonical body `canonical` (from [`canonical_body`]).
    pub fn new(model: &BodyModel, posed: &PosedBody, canonical: &PosedBody) -> Self {
        let tree = KdTree::new(&posed.vertices);
        let inv_obs: Vec<Mat4> = posed.vertex_transforms.iter().map(|t| t.inverse()).collect();
        let offsets: Vec<Vec3> = posed.shaped.iter().zip(&model.v_template).map(|(s, t)| *s - *t).collect();
        Self { tree, inv_obs, offsets, cano: canonical.vertex_transforms.clone(), obs: posed.vertex_transforms.clone() }
    }

    /// The observed body's vertex nearest to `x_d` (`None` for a body without vertices).
    pub fn nearest_body_vertex(&self, x_d: Vec3) -> Option<usize> {
        self.tree.nearest(x_d).map(|(i, _)| i)
    }

    /// Canonical position of posed point `x_d`, and the index of the body vertex used.
    pub fn to_canonical(&self, x_d: Vec3) -> (Vec3, usize) {
        let (x_c, i, _) = self.to_canonical_with_distance(x_d);
        (x_c, i)
    }

    /// [`InverseSkinning::to_canonical`] plus the posed-space distance from `x_d` to the body
    /// vertex used (its nearest).
    pub fn to_canonical_with_distance(&self, x_d: Vec3) -> (Vec3, usize, f32) {
        self.unwarp(x_d, self.tree.nearest(x_d))
    }

    fn unwarp(&self, x_d: Vec3, nearest: Option<(usize, f32)>) -> (Vec3, usize, f32) {
        let Some((i, d2)) = nearest else { return (x_d, 0, f32::INFINITY) };
        let rest = self.inv_obs[i].transform_point3(x_d) - self.offsets[i];
        (self.cano[i].transform_point3(rest), i, d2.max(0.0).sqrt())
    }

    /// Canonical position of posed grid point `x_d`, the body template's SDF there guarded
    /// against un-warps into another body part ([`guarded_template`]), and whether the guard
    /// fired (the point lies in space the pose vacated: the generator's residual must not be
    /// added there, see `generator::field_band`).
    pub fn canonical_template(&self, template: &crate::geometry::TemplateSdf, x_d: Vec3) -> (Vec3, f32, bool) {
        self.canonical_templates(template, &[x_d], f32::INFINITY)[0]
    }

    /// [`InverseSkinning::canonical_template`] of every point of `points`; each nearest-vertex
    /// search starts from the previous point's answer, which for points in a coherent order
    /// (tet-grid vertices in raster order) is close: the same values, a fraction of the time.
    /// Points with no posed body vertex within `far` are not un-warped: they get
    /// `(x_d, far, false)`. Their template SDF would be positive and at least `far` minus the
    /// body mesh's vertex spacing, so for `far` beyond every band and edge that depends on the
    /// value (`generator::PosedGrid`) the surface is the same; the exact search there is the
    /// costliest (the whole body lies at similar distances). `f32::INFINITY` un-warps all.
    pub fn canonical_templates(
        &self,
        template: &crate::geometry::TemplateSdf,
        points: &[Vec3],
        far: f32,
    ) -> Vec<(Vec3, f32, bool)> {
        let mut hint = None;
        points
            .iter()
            .map(|&x_d| {
                let nearest = if far.is_finite() {
                    let n = self.tree.nearest_within(x_d, far, hint);
                    hint = n.map(|n| n.0).or(hint);
                    return self.canonical_template_near(template, x_d, n, far);
                } else {
                    match hint {
                        Some(h) => self.tree.nearest_from(x_d, h),
                        None => self.tree.nearest(x_d),
                    }
                };
                hint = nearest.map(|n| n.0);
                let (c, _, d) = self.unwarp(x_d, nearest);
                let t = template.sample(c);
                let g = guarded_template(t, d);
                (c, g, g != t)
            })
            .collect()
    }

    /// [`InverseSkinning::canonical_templates`] of one point `x_d` whose nearest posed body
    /// vertex within `far` (finite) is known: its index and squared distance, or none.
    pub fn canonical_template_near(
        &self,
        template: &crate::geometry::TemplateSdf,
        x_d: Vec3,
        nearest: Option<(usize, f32)>,
        far: f32,
    ) -> (Vec3, f32, bool) {
        if nearest.is_none() {
            return (x_d, far, false);
        }
        let (c, _, d) = self.unwarp(x_d, nearest);
        let t = template.sample(c);
        let g = guarded_template(t, d);
        (c, g, g != t)
    }

    /// The posed body's vertices, which the nearest-vertex searches run over.
    pub fn posed_vertices(&self) -> &[Vec3] {
        self.tree.points()
    }

    /// Rotation taking canonical-space directions at body vertex `i` into posed space.
    pub fn rotation(&self, i: usize) -> Mat3 {
        match (self.obs.get(i), self.cano.get(i)) {
            (Some(o), Some(c)) => nearest_rotation(Mat3::from_mat4(*o) * Mat3::from_mat4(*c).inverse()),
            _ => Mat3::IDENTITY,
        }
    }
}

/// The rotation nearest to `m` (orthogonal polar factor, by Higham's iteration). Blended LBS
/// transforms are not rigid; normals must be rotated, not sheared (paper eq. 4).
pub fn nearest_rotation(m: Mat3) -> Mat3 {
    let mut r = m;
    for _ in 0..20 {
        let det = r.determinant();
        if det.abs() < 1e-12 {
            return Mat3::IDENTITY;
        }
        let next = (r + r.inverse().transpose()) * 0.5;
        let done = (next - r).to_cols_array().iter().map(|x| x.abs()).fold(0.0, f32::max) < 1e-7;
        r = next;
        if done {
            break;
        }
    }
    r
}

/// Slack of [`guarded_template`], metres: body-mesh vertex spacing plus template sampling error.
pub const UNWARP_SLACK: f32 = 0.05;

/// The template SDF `t` at an un-warped point, checked against the posed-space distance `d`
/// to the body vertex that un-warped it. That vertex's blended transform is nearly rigid, so
/// the canonical point keeps distance ≈ d to the canonical vertex, and a correct un-warp has
/// |t| ≈ d. A point with d > |t| + slack was carried next to or into another body part: it
/// lies in space the pose vacated (where the canonical arms were, in an arms-up pose), at
/// least d from the posed body and outside it, so it gets +d. Without this, K = 1 inverse
/// skinning leaves floating fragments there: of the template itself where t < 0, and of the
/// learned residual (clothing near the other part's canonical surface) where t is small.
pub fn guarded_template(t: f32, d: f32) -> f32 {
    if d > t.abs() + UNWARP_SLACK {
        d
    } else {
        t
    }
}
