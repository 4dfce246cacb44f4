//! Forward kinematics and linear blend skinning (paper Sec. 3 and eq. 1), plus the
//! per-vertex blended transforms that SMPL-guided inverse skinning (eq. 2) needs.
//!
//! θ is SMPL's: 24 axis-angle vectors (radians) in joint-local, world-aligned rest frames;
//! joint 0 is the global orientation.

use glam::{Mat3, Mat4, Quat, Vec3};
use serde::{Deserialize, Serialize};

use crate::body::body_model::{BodyModel, NUM_JOINTS, NUM_POSE_FEATURES};

/// Body parameters: pose θ (24 axis-angle vectors, radians), shape β, translation (metres).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BodyParams {
    /// θ: `pose[0]` is the global orientation, `pose[1..24]` the body pose (SMPL order).
    pub pose: [Vec3; NUM_JOINTS],
    /// β: shape coefficients (any length; truncated/zero-padded to the model's B).
    pub betas: Vec<f32>,
    /// Global translation, metres.
    pub transl: Vec3,
}

impl Default for BodyParams {
    fn default() -> Self {
        Self { pose: [Vec3::ZERO; NUM_JOINTS], betas: Vec::new(), transl: Vec3::ZERO }
    }
}

impl BodyParams {
    /// θ as SMPL's flat 72-vector.
    pub fn theta(&self) -> [f32; NUM_JOINTS * 3] {
        let mut t = [0.0; NUM_JOINTS * 3];
        for (j, r) in self.pose.iter().enumerate() {
            t[j * 3..j * 3 + 3].copy_from_slice(&r.to_array());
        }
        t
    }
    /// From SMPL's split layout: global orientation (3), body pose (69), betas; no translation.
    pub fn from_split(global_orient: &[f32], body_pose: &[f32], betas: &[f32]) -> Self {
        let mut theta = [0.0f32; NUM_JOINTS * 3];
        theta[..3].copy_from_slice(&global_orient[..3]);
        theta[3..].copy_from_slice(&body_pose[..(NUM_JOINTS - 1) * 3]);
        let mut p = BodyParams { betas: betas.to_vec(), ..BodyParams::default() };
        p.set_theta(&theta);
        p
    }

    /// Set θ from SMPL's flat 72-vector.
    pub fn set_theta(&mut self, theta: &[f32; NUM_JOINTS * 3]) {
        for j in 0..NUM_JOINTS {
            self.pose[j] = Vec3::new(theta[j * 3], theta[j * 3 + 1], theta[j * 3 + 2]);
        }
    }
}

/// Rotation matrix of an axis-angle vector (Rodrigues' formula).
pub fn axis_angle_to_matrix(r: Vec3) -> Mat3 {
    let angle = r.length();
    if angle < 1e-12 {
        return Mat3::IDENTITY;
    }
    Mat3::from_axis_angle(r / angle, angle)
}

/// Axis-angle (radians) → unit quaternion.
pub fn axis_angle_to_quat(v: Vec3) -> Quat {
    let a = v.length();
    if a < 1e-12 {
        Quat::IDENTITY
    } else {
        Quat::from_axis_angle(v / a, a)
    }
}

/// Unit quaternion → axis-angle, angle in [0, π].
pub fn quat_to_axis_angle(q: Quat) -> Vec3 {
    let q = if q.w < 0.0 { -q } else { q }.normalize();
    let (axis, angle) = q.to_axis_angle();
    if angle.abs() < 1e-9 {
        Vec3::ZERO
    } else {
        axis * angle
    }
}

/// Output of [`forward_kinematics`].
#[derive(Clone, Debug)]
pub struct Kinematics {
    /// Rest joint locations (after shape), metres.
    pub rest_joints: [Vec3; NUM_JOINTS],
    /// Posed joint locations (after pose and translation), metres.
    pub posed_joints: [Vec3; NUM_JOINTS],
    /// Per-joint skinning transforms `A_k`: rest space → posed space
    /// (world transform of joint k composed with the inverse rest transform).
    pub skinning: [Mat4; NUM_JOINTS],
    /// Per-joint rotation matrices R(θ_k) (local).
    pub local_rotations: [Mat3; NUM_JOINTS],
}

/// Forward kinematics along the kinematic tree for rest joints `rest_joints` and pose.
pub fn forward_kinematics(
    parents: &[i32; NUM_JOINTS],
    rest_joints: &[Vec3; NUM_JOINTS],
    params: &BodyParams,
) -> Kinematics {
    let mut world = [Mat4::IDENTITY; NUM_JOINTS];
    let mut local_rotations = [Mat3::IDENTITY; NUM_JOINTS];
    for j in 0..NUM_JOINTS {
        let r = axis_angle_to_matrix(params.pose[j]);
        local_rotations[j] = r;
        let p = parents[j];
        let rel = if p < 0 { rest_joints[j] } else { rest_joints[j] - rest_joints[p as usize] };
        let local = Mat4::from_cols(r.x_axis.extend(0.0), r.y_axis.extend(0.0), r.z_axis.extend(0.0), rel.extend(1.0));
        world[j] = if p < 0 { Mat4::from_translation(params.transl) * local } else { world[p as usize] * local };
    }
    let mut skinning = [Mat4::IDENTITY; NUM_JOINTS];
    let mut posed_joints = [Vec3::ZERO; NUM_JOINTS];
    for j in 0..NUM_JOINTS {
        posed_joints[j] = world[j].w_axis.truncate();
        skinning[j] = world[j] * Mat4::from_translation(-rest_joints[j]);
    }
    Kinematics { rest_joints: *rest_joints, posed_joints, skinning, local_rotations }
}

/// Blend joint transforms with one vertex's skin weights: `T_v = Σ_k w_vk A_k`.
pub fn blend_transform(weights: &[f32; NUM_JOINTS], skinning: &[Mat4; NUM_JOINTS]) -> Mat4 {
    let mut m = Mat4::ZERO;
    for (w, a) in weights.iter().zip(skinning) {
        if *w != 0.0 {
            m += *a * *w;
        }
    }
    m
}

/// A posed body: the result of [`pose_body`].
#[derive(Clone, Debug)]
pub struct PosedBody {
    /// Vertices with shape applied, in the rest pose (before pose correctives).
    pub shaped: Vec<Vec3>,
    /// Posed vertices, metres.
    pub vertices: Vec<Vec3>,
    /// Per-vertex blended transforms (rest → posed), for inverse skinning.
    pub vertex_transforms: Vec<Mat4>,
    pub kinematics: Kinematics,
}

/// SMPL's forward pass: shape blend shapes, joint regression, pose correctives, FK, LBS.
pub fn pose_body(model: &BodyModel, params: &BodyParams) -> PosedBody {
    let shaped = model.shaped_vertices(&params.betas);
    let rest_joints = model.regress_joints(&shaped);
    let kin = forward_kinematics(&model.parents, &rest_joints, params);

    let mut rest = shaped.clone();
    if model.has_pose_correctives() {
        let mut feat = [0.0f32; NUM_POSE_FEATURES];
        for j in 1..NUM_JOINTS {
            let m = kin.local_rotations[j] - Mat3::IDENTITY;
            // Row-major 3x3 as in SMPL.
            let rm = m.transpose().to_cols_array();
            feat[(j - 1) * 9..j * 9].copy_from_slice(&rm);
        }
        // Only the joints that turn contribute (a zero feature adds exactly nothing): the rest
        // pose (an export's bind pose) skips all 4.3 M products, the Da-pose all but the hips'.
        let turned: Vec<usize> =
            (0..NUM_JOINTS - 1).filter(|&j| feat[j * 9..(j + 1) * 9].iter().any(|f| *f != 0.0)).collect();
        if !turned.is_empty() {
            for (i, v) in rest.iter_mut().enumerate() {
                let mut d = [0.0f32; 3];
                for (c, dc) in d.iter_mut().enumerate() {
                    let row = &model.posedirs[(i * 3 + c) * NUM_POSE_FEATURES..][..NUM_POSE_FEATURES];
                    for &j in &turned {
                        *dc += row[j * 9..(j + 1) * 9]
                            .iter()
                            .zip(&feat[j * 9..(j + 1) * 9])
                            .map(|(a, b)| a * b)
                            .sum::<f32>();
                    }
                }
                *v += Vec3::from_array(d);
            }
        }
    }

    let mut vertices = Vec::with_capacity(rest.len());
    let mut vertex_transforms = Vec::with_capacity(rest.len());
    for (v, w) in rest.iter().zip(&model.weights) {
        let t = blend_transform(w, &kin.skinning);
        vertices.push(t.transform_point3(*v));
        vertex_transforms.push(t);
    }
    PosedBody { shaped, vertices, vertex_transforms, kinematics: kin }
}

/// Per-vertex area-weighted normals of a triangle mesh (unit length; zero for isolated vertices).
pub fn vertex_normals(vertices: &[Vec3], faces: &[[u32; 3]]) -> Vec<Vec3> {
    let mut n = vec![Vec3::ZERO; vertices.len()];
    for f in faces {
        let [a, b, c] = f.map(|i| vertices[i as usize]);
        let fn_ = (b - a).cross(c - a);
        for &i in f {
            n[i as usize] += fn_;
        }
    }
    n.into_iter().map(|v| v.normalize_or_zero()).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rodrigues_matches_known_rotations() {
        let r = axis_angle_to_matrix(Vec3::new(0.0, 0.0, std::f32::consts::FRAC_PI_2));
        let v = r * Vec3::X;
        assert!((v - Vec3::Y).length() < 1e-6, "{v}");
        assert_eq!(axis_angle_to_matrix(Vec3::ZERO), Mat3::IDENTITY);
    }

    /// Pose correctives over the turned joints only give SMPL's dense sum over all 207
    /// features, and none at all in the rest pose.
    #[test]
    fn pose_correctives_skip_only_unturned_joints() {
        let mut model = crate::body::body_model::BodyModel::default_body().unwrap();
        let mut rng = crate::util::rng::Rng::new(7, 1);
        model.posedirs =
            rng.normals(model.num_vertices() * 3 * NUM_POSE_FEATURES).into_iter().map(|x| x * 1e-3).collect();
        let mut p = BodyParams::default();
        for j in [1, 5, 16, 20] {
            p.pose[j] = Vec3::new(0.3, -0.2, 0.1 * j as f32);
        }
        let posed = pose_body(&model, &p);
        let kin = forward_kinematics(&model.parents, &model.regress_joints(&posed.shaped), &p);
        let mut feat = [0.0f32; NUM_POSE_FEATURES];
        for j in 1..NUM_JOINTS {
            feat[(j - 1) * 9..j * 9]
                .copy_from_slice(&(kin.local_rotations[j] - Mat3::IDENTITY).transpose().to_cols_array());
        }
        let mut worst = 0.0f32;
        for (i, (s, v)) in posed.shaped.iter().zip(&posed.vertices).enumerate() {
            let d = Vec3::from_array(std::array::from_fn(|c| {
                model.posedirs[(i * 3 + c) * NUM_POSE_FEATURES..][..NUM_POSE_FEATURES]
                    .iter()
                    .zip(&feat)
                    .map(|(a, b)| a * b)
                    .sum()
            }));
            let dense = blend_transform(&model.weights[i], &kin.skinning).transform_point3(*s + d);
            worst = worst.max((dense - *v).length());
        }
        assert!(worst < 1e-6, "{worst} m from the dense sum");
        // The rest pose: the shaped vertices, untouched by the (random) correctives.
        let rest = pose_body(&model, &BodyParams::default());
        let moved = rest.shaped.iter().zip(&rest.vertices).map(|(a, b)| (*a - *b).length()).fold(0.0f32, f32::max);
        assert!(moved < 1e-6, "{moved}");
    }

    #[test]
    fn fk_of_a_two_bone_chain() {
        // Root at origin, child at +x 1m; rotate the root 90° about z: child goes to +y.
        let mut parents = [0i32; NUM_JOINTS];
        parents[0] = -1;
        let mut rest = [Vec3::ZERO; NUM_JOINTS];
        rest[1] = Vec3::X;
        let mut p = BodyParams::default();
        p.pose[0] = Vec3::new(0.0, 0.0, std::f32::consts::FRAC_PI_2);
        p.transl = Vec3::new(0.0, 0.0, 2.0);
        let k = forward_kinematics(&parents, &rest, &p);
        assert!((k.posed_joints[1] - Vec3::new(0.0, 1.0, 2.0)).length() < 1e-6);
        // The skinning transform maps the rest child joint onto its posed location.
        assert!((k.skinning[1].transform_point3(rest[1]) - k.posed_joints[1]).length() < 1e-6);
    }
}
