//! Joint-angle limits of the fit: knees and elbows bend one way, and not sideways.
//!
//! SMPLify's angle prior penalises `exp(s · θ_axis)²` for the knees' x and the elbows' y
//! rotation. An L2 on the third axis (neither the hinge's nor the bone's, about which the
//! limb may twist) keeps them from bending sideways, which a hidden forearm otherwise does to
//! reach a misplaced wrist. With this body's rest frames (T-pose, every joint frame aligned
//! with the world axes, as SMPL's) the axes are SMPL's, checked below by posing the body: a
//! positive x rotation takes the ankle behind the knee, the elbows' flexion brings the wrists
//! in front of the body, and each bone lies along its hinge's remaining axis.

#[cfg(any(feature = "generator", feature = "wgpu"))]
use burn::tensor::Tensor;
use glam::Vec3;

use crate::body::body_model::NUM_JOINTS;
#[cfg(any(feature = "generator", feature = "wgpu"))]
use crate::render::diff::{body_model::joint_index, matrix};

/// A hinge joint: the axis it bends about and the sign of a natural bend.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hinge {
    /// Index into `body_model::JOINT_NAMES`.
    pub joint: usize,
    /// 0 = x, 1 = y, 2 = z (of the joint's local axis-angle vector).
    pub axis: usize,
    /// +1 where a natural bend is a positive rotation, −1 where it is negative.
    pub bend: f32,
    /// The axis of a sideways bend, which the joint does not have (neither the hinge's axis
    /// nor the bone's, about which the limb twists): z for both, the bones lying along x
    /// (arms) and y (legs) in the rest pose.
    pub side: usize,
}

/// Knees flex about +x; the left elbow about −y, the right elbow about +y.
pub const HINGES: [Hinge; 4] = [
    Hinge { joint: 4, axis: 0, bend: 1.0, side: 2 },
    Hinge { joint: 5, axis: 0, bend: 1.0, side: 2 },
    Hinge { joint: 18, axis: 1, bend: -1.0, side: 2 },
    Hinge { joint: 19, axis: 1, bend: 1.0, side: 2 },
];

/// The collar bones (SMPL's `left_collar`, `right_collar`): the clavicles move little (some
/// 20–30° of elevation and protraction in a person), so [`super::options::FitWeights::collar`]
/// holds them stiffer than θ's plain L2. Left free, a fit reaches a misread or hidden arm by
/// turning a collar 0.5–1.3 rad and then bends the spine and the standing knee to keep the
/// torso's landmarks.
pub const COLLARS: [usize; 2] = [13, 14];

/// A range of one rotation component that a body's joint stays within (radians, of the
/// joint's local axis-angle vector; with one component dominant it is that rotation).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Range {
    /// Index into `body_model::JOINT_NAMES`.
    pub joint: usize,
    /// 0 = x, 1 = y, 2 = z.
    pub axis: usize,
    pub lo: f32,
    pub hi: f32,
}

/// Rotations people have little of, which a fit otherwise uses to explain depth the image
/// leaves in doubt: the twist of the thighs about the hip (internal/external rotation, some
/// 40–45° each way) and of the shins about the knee (a few degrees with the knee straight).
/// Left free, the fit of a sideways bend seen from behind turned a thigh 76° about its axis
/// and the shin 63° more (PA-MPJPE 102.6 mm; 74.0 with the ranges, docs/benchmarks.md). The
/// ankles', neck's and head's sideways tilts were tried too and cost the video fit 2 mm.
pub const RANGES: [Range; 4] = [
    Range { joint: 1, axis: 1, lo: -0.8, hi: 0.8 },
    Range { joint: 2, axis: 1, lo: -0.8, hi: 0.8 },
    Range { joint: 4, axis: 1, lo: -0.35, hi: 0.35 },
    Range { joint: 5, axis: 1, lo: -0.35, hi: 0.35 },
];

/// Σ over [`RANGES`] of the squared excess beyond the range (0 inside it), of θ₁…θ₂₃ as the
/// fit holds them (`[23, 3]`, the root's row left out).
#[cfg(any(feature = "generator", feature = "wgpu"))]
pub fn range_term(body_pose: Tensor<2>) -> Tensor<1> {
    let dev = body_pose.device();
    let n = RANGES.len();
    let idx: Vec<usize> = RANGES.iter().map(|r| (r.joint - 1) * 3 + r.axis).collect();
    let a = body_pose.reshape([(NUM_JOINTS - 1) * 3, 1]).select(0, joint_index(&idx, &dev));
    let hi = matrix(RANGES.iter().map(|r| r.hi).collect(), n, 1, &dev);
    let lo = matrix(RANGES.iter().map(|r| r.lo).collect(), n, 1, &dev);
    let (over, under) = ((a.clone() - hi).clamp_min(0.0), (lo - a).clamp_min(0.0));
    (over.clone() * over + under.clone() * under).sum().reshape([1])
}

/// SMPLify's angle prior on the hinges: Σ exp(−bend · θ_axis)², about 1 per straight joint,
/// growing exponentially with hyperextension and vanishing with natural flexion.
pub fn hinge_penalty(pose: &[Vec3; NUM_JOINTS]) -> f32 {
    HINGES.iter().map(|h| (-h.bend * pose[h.joint][h.axis]).exp().powi(2)).sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::body::body_model::BodyModel;
    use crate::body::skinning::{pose_body, BodyParams};

    fn joints(bends: &[(usize, usize, f32)]) -> [Vec3; NUM_JOINTS] {
        let model = BodyModel::default_body().unwrap();
        let mut params = BodyParams::default();
        for &(j, axis, angle) in bends {
            params.pose[j][axis] = angle;
        }
        pose_body(&model, &params).kinematics.posed_joints
    }

    /// A natural bend of each hinge moves the next joint (ankle, wrist) the way a body bends:
    /// the ankle backwards (−z) and up, the wrist forwards (+z).
    #[test]
    fn natural_bends_move_the_limbs_the_way_bodies_bend() {
        let rest = joints(&[]);
        for h in HINGES {
            let child = match h.joint {
                4 => 7,
                5 => 8,
                18 => 20,
                _ => 21,
            };
            let bent = joints(&[(h.joint, h.axis, 0.8 * h.bend)]);
            let moved = bent[child] - rest[child];
            if h.joint <= 5 {
                assert!(moved.z < -0.1 && moved.y > 0.03, "knee {}: ankle moved {moved}", h.joint);
            } else {
                assert!(moved.z > 0.1, "elbow {}: wrist moved {moved}", h.joint);
            }
            // The bone lies along the axis that is neither the hinge's nor the side's.
            let bone = (joints(&[])[child] - rest[h.joint]).to_array();
            assert!(h.side != h.axis && bone[h.axis].abs() < 0.03 && bone[h.side].abs() < 0.03, "{h:?}: bone {bone:?}");
            // Hyperextension is the other way round, and costs more than the straight limb.
            let mut straight = [Vec3::ZERO; NUM_JOINTS];
            let base = hinge_penalty(&straight);
            straight[h.joint][h.axis] = 0.8 * h.bend;
            assert!(hinge_penalty(&straight) < base - 0.7, "a natural bend is cheaper");
            straight[h.joint][h.axis] = -0.8 * h.bend;
            assert!(hinge_penalty(&straight) > base + 3.0, "hyperextension is dearer");
        }
    }

    /// The ranges' axes are the rotations the comment names: a hip's y turns the thigh about
    /// itself (the knee stays, a bent knee's ankle swings sideways); inside the ranges nothing
    /// is paid, beyond them the squared excess.
    #[test]
    #[cfg(all(feature = "ndarray", any(feature = "generator", feature = "wgpu")))]
    fn ranges_limit_the_legs_twists_and_nothing_else() {
        let bent = joints(&[(4, 0, 1.2)]);
        let twisted = joints(&[(4, 0, 1.2), (1, 1, 0.8)]);
        assert!((twisted[4] - bent[4]).length() < 0.02, "the knee moved {}", twisted[4] - bent[4]);
        let swing = twisted[7] - bent[7];
        assert!(swing.x.abs() > 0.2 && swing.y.abs() < 0.1, "the ankle moved {swing}");

        // The term as the fit computes it, on θ₁…θ₂₃.
        #[allow(deprecated)]
        let dev = burn::tensor::Device::ndarray();
        let term = |rows: &[(usize, usize, f32)]| {
            let mut theta = vec![0.0f32; (NUM_JOINTS - 1) * 3];
            for &(j, axis, v) in rows {
                theta[(j - 1) * 3 + axis] = v;
            }
            let t = range_term(matrix(theta, NUM_JOINTS - 1, 3, &dev));
            t.into_data().convert::<f32>().try_to_vec::<f32>().expect("floats")[0]
        };
        assert_eq!(term(&[]), 0.0);
        assert_eq!(term(&[(1, 1, 0.7), (5, 1, -0.3)]), 0.0, "inside the ranges");
        // The fit of a sideways bend seen from behind, before the ranges: thigh 1.33, shin 1.11.
        let expected = (1.33f32 - 0.8).powi(2) + (1.11f32 - 0.35).powi(2);
        assert!((term(&[(1, 1, 1.33), (4, 1, 1.11)]) - expected).abs() < 1e-5);
        assert!((term(&[(2, 1, -1.33)]) - (1.33f32 - 0.8).powi(2)).abs() < 1e-5, "the other way");
        // Bends the ranges do not name (a knee's flexion, a shoulder) cost nothing.
        assert_eq!(term(&[(4, 0, 2.0), (16, 2, -1.5)]), 0.0);
    }
}
