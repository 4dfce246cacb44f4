//! SMPL-guided inverse skinning (paper Sec. 4.2, eq. 2): a posed-space point x_d is carried to
//! canonical space with the blended transform of its nearest posed body vertex i (K = 1):
//!
//! `x_c = T_cano,i · (T_obs,i⁻¹ · x_d − δ_i)`
//!
//! where T_obs,i is vertex i's LBS transform in the observed pose/shape, δ_i its shape
//! (and pose-corrective) offset, and T_cano,i its transform in the canonical Da-pose with β = 0.
//! Normals go the other way with the rotation nearest to lin(T_obs,i) · lin(T_cano,i)⁻¹ (eq. 4).

use glam::{Mat3, Mat4, Vec3};

use crate::body_model::BodyModel;
use crate::pose_library::da_pose;
use crate::skinning::{pose_body, BodyParams, PosedBody};
use crate::spatial::KdTree;

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

    /// Canonical position of posed point `x_d`, and the index of the body vertex used.
    pub fn to_canonical(&self, x_d: Vec3) -> (Vec3, usize) {
        let Some((i, _)) = self.tree.nearest(x_d) else { return (x_d, 0) };
        let rest = self.inv_obs[i].transform_point3(x_d) - self.offsets[i];
        (self.cano[i].transform_point3(rest), i)
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
