//! The fit's starting point (SMPLify starts from a mean pose; this one starts nearer):
//!
//! - global orientation from the torso of MediaPipe's 3D world landmarks (shoulders and hips
//!   give left and up; forward follows), or, without them, facing the camera or turned away
//!   as the shoulders' order in the image says;
//! - shoulders, elbows, hips and knees from the world landmarks' bone directions: each upper
//!   bone turned onto its direction and twisted about it so the elbow or knee below bends
//!   about its hinge axis the natural way ([`super::limits::HINGES`]), then the hinge angle;
//! - camera translation from the torso: depth from the ratio of its 3D to its 2D size,
//!   x and y so the torso's centre projects where it was seen.
//!
//! World landmarks (x right, y down, z away from the camera, metres around the hips) are
//! turned into camera axes (x right, y up, z towards the viewer) by [`camera_axes`]. The fit's
//! camera looks down −Z with no rotation, so camera axes are world axes until the fit ends.

use glam::{Mat3, Quat, Vec3};

use super::landmarks::Landmark;
use super::limits::HINGES;
use crate::body::body_model::{BodyModel, NUM_JOINTS};
use crate::body::skinning::{forward_kinematics, BodyParams};
use crate::render::camera::reference_fov_y;

/// MediaPipe world landmark → camera axes.
pub fn camera_axes(l: &Landmark) -> Vec3 {
    Vec3::new(l.x, -l.y, -l.z)
}

/// One limb: the upper joint (shoulder, hip), the hinge joint below it (elbow, knee), the end
/// joint (wrist, ankle), and their MediaPipe landmarks.
struct Limb {
    joints: [usize; 3],
    landmarks: [usize; 3],
}

const LIMBS: [Limb; 4] = [
    Limb { joints: [16, 18, 20], landmarks: [11, 13, 15] },
    Limb { joints: [17, 19, 21], landmarks: [12, 14, 16] },
    Limb { joints: [1, 4, 7], landmarks: [23, 25, 27] },
    Limb { joints: [2, 5, 8], landmarks: [24, 26, 28] },
];

/// The global orientation whose body axes (left = +x, up = +y, forward = +z) match a torso's
/// left and up directions (camera axes).
pub fn torso_orientation(left: Vec3, up: Vec3) -> Vec3 {
    let y = up.normalize_or(Vec3::Y);
    let z = left.cross(y).normalize_or(Vec3::Z);
    let x = y.cross(z);
    Quat::from_mat3(&Mat3::from_cols(x, y, z)).normalize().to_scaled_axis()
}

/// Rotation taking unit vector `a` onto unit vector `b` by the smallest angle.
fn rotation_between(a: Vec3, b: Vec3) -> Quat {
    Quat::from_rotation_arc(a.normalize_or(Vec3::X), b.normalize_or(Vec3::X))
}

/// The initial pose from world landmarks (camera axes); the body's shape is `betas`.
pub fn pose_from_world(model: &BodyModel, world: &[Vec3], visibility: &[f32], betas: &[f32]) -> BodyParams {
    let mut params = BodyParams { betas: betas.to_vec(), ..BodyParams::default() };
    let at = |i: usize| world.get(i).copied().unwrap_or(Vec3::ZERO);
    let seen = |i: usize| visibility.get(i).is_some_and(|v| *v >= 0.05);
    let left = (at(11) - at(12)) + (at(23) - at(24));
    let up = (at(11) + at(12) - at(23) - at(24)) / 2.0;
    params.pose[0] = torso_orientation(left, up);
    let rest = model.regress_joints(&model.shaped_vertices(betas));
    for limb in &LIMBS {
        let [a, b, _] = limb.joints;
        let [la, lb, lc] = limb.landmarks;
        if !(seen(la) && seen(lb)) {
            continue;
        }
        let kin = forward_kinematics(&model.parents, &rest, &params);
        let world_rot = |j: usize| {
            let m = kin.skinning[j];
            Quat::from_mat3(&Mat3::from_mat4(m)).normalize()
        };
        let parent = world_rot(model.parents[a] as usize);
        let u0 = parent * (rest[b] - rest[a]).normalize_or(Vec3::X);
        let u = (at(lb) - at(la)).normalize_or(u0);
        let mut turn = rotation_between(u0, u);
        let hinge = HINGES.iter().find(|h| h.joint == b);
        let mut bend = 0.0;
        if let (Some(h), true) = (hinge, seen(lc)) {
            let v = (at(lc) - at(lb)).normalize_or(u);
            let angle = u.angle_between(v);
            if angle > 10f32.to_radians() {
                // Twist about u so the hinge axis (world, after the turn) points along
                // bend·(u × v): then a rotation by bend·angle about it takes u onto v.
                let mut axis = Vec3::ZERO;
                axis[h.axis] = 1.0;
                let hw = turn * parent * axis;
                let want = u.cross(v).normalize_or(Vec3::ZERO) * h.bend;
                let perp = (hw - hw.dot(u) * u).normalize_or(want);
                let phi = perp.cross(want).dot(u).atan2(perp.dot(want));
                turn = Quat::from_axis_angle(u, phi) * turn;
                bend = h.bend * angle;
            }
        }
        // Local rotation of the upper joint: parent⁻¹ · turn · parent.
        params.pose[a] = (parent.inverse() * turn * parent).normalize().to_scaled_axis();
        if let Some(h) = hinge {
            params.pose[b] = Vec3::ZERO;
            params.pose[b][h.axis] = bend;
        }
    }
    params
}

/// Without world landmarks: facing the camera when the person's left shoulder appears to the
/// right of the right shoulder (NDC x), turned away otherwise; arms and legs at rest.
pub fn pose_from_image(left_shoulder: [f32; 2], right_shoulder: [f32; 2], betas: &[f32]) -> BodyParams {
    let mut params = BodyParams { betas: betas.to_vec(), ..BodyParams::default() };
    if left_shoulder[0] < right_shoulder[0] {
        params.pose[0] = Vec3::new(0.0, std::f32::consts::PI, 0.0);
    }
    params
}

/// The camera translation (camera axes = world axes) that puts `joints` (posed, world) where
/// `observed` (NDC, with confidences) saw them: depth from the ratio of their 3D spread
/// across the view to their 2D spread, then x and y from the weighted centres. `None` with
/// fewer than two confident observations.
pub fn camera_translation(joints: &[Vec3], observed: &[([f32; 2], f32)]) -> Option<Vec3> {
    let pts: Vec<(Vec3, [f32; 2], f32)> =
        joints.iter().zip(observed).filter(|(_, (_, c))| *c > 0.0).map(|(j, (o, c))| (*j, *o, *c)).collect();
    if pts.len() < 2 {
        return None;
    }
    let wsum: f32 = pts.iter().map(|p| p.2).sum();
    let c3 = pts.iter().map(|p| p.0 * p.2).sum::<Vec3>() / wsum;
    let c2 = pts.iter().fold([0.0f32; 2], |acc, p| [acc[0] + p.1[0] * p.2, acc[1] + p.1[1] * p.2]);
    let c2 = [c2[0] / wsum, c2[1] / wsum];
    let (mut s3, mut s2) = (0.0f32, 0.0f32);
    for p in &pts {
        s3 += p.2 * (p.0 - c3).truncate().length();
        s2 += p.2 * ((p.1[0] - c2[0]).powi(2) + (p.1[1] - c2[1]).powi(2)).sqrt();
    }
    if s2 <= 1e-6 || s3 <= 1e-6 {
        return None;
    }
    let f = 1.0 / (reference_fov_y() / 2.0).tan();
    let depth = f * s3 / s2;
    let centre_cam = Vec3::new(c2[0] * depth / f, c2[1] * depth / f, -depth);
    Some(centre_cam - c3)
}

/// Posed joints of `params` (no translation).
pub fn posed_joints(model: &BodyModel, params: &BodyParams) -> [Vec3; NUM_JOINTS] {
    let rest = model.regress_joints(&model.shaped_vertices(&params.betas));
    forward_kinematics(&model.parents, &rest, params).posed_joints
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::body::body_fit::landmarks::NUM_LANDMARKS;
    use crate::body::body_fit::metrics::pa_mpjpe;

    /// World landmarks at the posed body's joints (camera axes) for the mapped landmarks.
    fn world_of(model: &BodyModel, params: &BodyParams) -> Vec<Vec3> {
        let j = posed_joints(model, params);
        let mut w = vec![Vec3::ZERO; NUM_LANDMARKS];
        for m in crate::body::body_fit::landmarks::JOINT_LANDMARKS {
            w[m.landmark] = j[m.joint];
        }
        w
    }

    #[test]
    fn the_initial_pose_recovers_limb_directions_and_turns() {
        let model = BodyModel::default_body().unwrap();
        let mut truth = BodyParams::default();
        truth.pose[0] = Vec3::new(0.1, 2.2, -0.05); // turned mostly away
        truth.pose[16] = Vec3::new(0.3, 0.2, -1.1); // left arm down and forward
        truth.pose[18] = Vec3::new(0.0, -1.2, 0.0); // left elbow bent
        truth.pose[17] = Vec3::new(-0.6, 0.0, 0.4);
        truth.pose[1] = Vec3::new(-1.0, 0.0, 0.1); // left thigh forward (kick)
        truth.pose[4] = Vec3::new(0.9, 0.0, 0.0); // knee bent
        truth.pose[5] = Vec3::new(0.4, 0.0, 0.0);
        let world = world_of(&model, &truth);
        let vis = vec![1.0; NUM_LANDMARKS];
        let init = pose_from_world(&model, &world, &vis, &[]);
        let (a, b) = (posed_joints(&model, &init), posed_joints(&model, &truth));
        // The mapped joints land on their landmarks up to the untouched spine and collars.
        let err = pa_mpjpe(&a, &b);
        assert!(err < 0.03, "PA-MPJPE of the initial pose {err} m");
        // Hinges bend the natural way.
        assert!(init.pose[18].y < -1.0 && init.pose[4].x > 0.8 && init.pose[5].x > 0.3, "{:?}", init.pose);
        // Turned away: the body's forward axis points away from the camera (−z).
        let fwd = crate::body::skinning::axis_angle_to_matrix(init.pose[0]) * Vec3::Z;
        assert!(fwd.z < -0.5, "{fwd}");
    }

    #[test]
    fn the_camera_translation_reproduces_depth_and_centre() {
        let model = BodyModel::default_body().unwrap();
        let j = posed_joints(&model, &BodyParams::default());
        let t = Vec3::new(0.1, 0.2, -2.3);
        let f = 1.0 / (reference_fov_y() / 2.0).tan();
        let obs: Vec<([f32; 2], f32)> = j
            .iter()
            .map(|p| {
                let c = *p + t;
                ([f * c.x / -c.z, f * c.y / -c.z], 1.0)
            })
            .collect();
        let idx = [16, 17, 1, 2];
        let got = camera_translation(&idx.map(|i| j[i]), &idx.map(|i| obs[i])).unwrap();
        assert!((got - t).length() < 0.02, "{got} vs {t}");
        assert_eq!(camera_translation(&j[..1], &obs[..1]), None);
    }
}
