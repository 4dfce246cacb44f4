//! The SMPL skeleton as a humanoid: each of the 24 joints' VRM 1.0 humanoid bone
//! (`VRMC_vrm.humanoid`, also the bones of a `.vrma`) and its common humanoid node name
//! (`Hips`, `Spine`, `LeftUpLeg`, … as Mixamo-style rigs name them, so retargeting tools map
//! a plain .glb by name). The table is documented in `docs/conventions.md`.
//!
//! SMPL's left is the body's own left: +x in the rest pose (facing +z, y up), which is VRM's
//! left too, so no joint changes side.

use crate::body::body_model::NUM_JOINTS;

/// One joint's humanoid names.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct HumanoidBone {
    /// SMPL's joint name ([`crate::body::body_model::JOINT_NAMES`]).
    pub smpl: &'static str,
    /// VRM 1.0's humanoid bone, where one fits: SMPL's `left_hand`/`right_hand` (the
    /// knuckles, ending the hand) has no VRM bone and stays an unmapped node.
    pub vrm: Option<&'static str>,
    /// The common humanoid node name.
    pub node: &'static str,
}

const fn bone(smpl: &'static str, vrm: Option<&'static str>, node: &'static str) -> HumanoidBone {
    HumanoidBone { smpl, vrm, node }
}

/// Per SMPL joint (in SMPL's order), its humanoid names.
pub const HUMANOID_BONES: [HumanoidBone; NUM_JOINTS] = [
    bone("pelvis", Some("hips"), "Hips"),
    bone("left_hip", Some("leftUpperLeg"), "LeftUpLeg"),
    bone("right_hip", Some("rightUpperLeg"), "RightUpLeg"),
    bone("spine1", Some("spine"), "Spine"),
    bone("left_knee", Some("leftLowerLeg"), "LeftLeg"),
    bone("right_knee", Some("rightLowerLeg"), "RightLeg"),
    bone("spine2", Some("chest"), "Spine1"),
    bone("left_ankle", Some("leftFoot"), "LeftFoot"),
    bone("right_ankle", Some("rightFoot"), "RightFoot"),
    bone("spine3", Some("upperChest"), "Spine2"),
    bone("left_foot", Some("leftToes"), "LeftToeBase"),
    bone("right_foot", Some("rightToes"), "RightToeBase"),
    bone("neck", Some("neck"), "Neck"),
    bone("left_collar", Some("leftShoulder"), "LeftShoulder"),
    bone("right_collar", Some("rightShoulder"), "RightShoulder"),
    bone("head", Some("head"), "Head"),
    bone("left_shoulder", Some("leftUpperArm"), "LeftArm"),
    bone("right_shoulder", Some("rightUpperArm"), "RightArm"),
    bone("left_elbow", Some("leftLowerArm"), "LeftForeArm"),
    bone("right_elbow", Some("rightLowerArm"), "RightForeArm"),
    bone("left_wrist", Some("leftHand"), "LeftHand"),
    bone("right_wrist", Some("rightHand"), "RightHand"),
    bone("left_hand", None, "LeftHandMiddle1"),
    bone("right_hand", None, "RightHandMiddle1"),
];

/// The humanoid bones VRM 1.0 requires.
pub const VRM_REQUIRED_BONES: [&str; 15] = [
    "hips",
    "spine",
    "head",
    "leftUpperLeg",
    "leftLowerLeg",
    "leftFoot",
    "rightUpperLeg",
    "rightLowerLeg",
    "rightFoot",
    "leftUpperArm",
    "leftLowerArm",
    "leftHand",
    "rightUpperArm",
    "rightLowerArm",
    "rightHand",
];

/// How the skeleton's nodes are named in an exported .glb.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum SkeletonNames {
    /// SMPL's joint names (`pelvis`, `left_hip`, …): what SMPL tools expect.
    #[default]
    Smpl,
    /// Common humanoid names (`Hips`, `LeftUpLeg`, …): what retargeting tools map by name.
    Humanoid,
}

impl SkeletonNames {
    /// The 24 node names, in SMPL's joint order.
    pub fn names(self) -> Vec<String> {
        HUMANOID_BONES
            .iter()
            .map(|b| match self {
                Self::Smpl => b.smpl,
                Self::Humanoid => b.node,
            })
            .map(str::to_string)
            .collect()
    }

    /// `smpl` or `humanoid`.
    pub fn parse(s: &str) -> Result<Self, String> {
        match s {
            "smpl" => Ok(Self::Smpl),
            "humanoid" => Ok(Self::Humanoid),
            other => Err(format!("skeleton `{other}`: smpl or humanoid")),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::body::body_model::{joint_index, BodyModel, JOINT_NAMES, SMPL_PARENTS};

    #[test]
    fn the_table_follows_smpls_joint_order_and_covers_every_required_vrm_bone() {
        for (b, name) in HUMANOID_BONES.iter().zip(JOINT_NAMES) {
            assert_eq!(b.smpl, name);
        }
        for req in VRM_REQUIRED_BONES {
            assert_eq!(HUMANOID_BONES.iter().filter(|b| b.vrm == Some(req)).count(), 1, "{req}");
        }
        let mut vrm: Vec<_> = HUMANOID_BONES.iter().filter_map(|b| b.vrm).collect();
        let n = vrm.len();
        vrm.sort_unstable();
        vrm.dedup();
        assert_eq!(vrm.len(), n, "a VRM bone named twice");
    }

    /// VRM's parent of each bone (its humanoid spec) is the SMPL parent's bone.
    #[test]
    fn each_vrm_bones_parent_is_its_smpl_parents_bone() {
        let vrm_parent = |b: &str| -> Option<&str> {
            Some(match b {
                "hips" => return None,
                "spine" | "leftUpperLeg" | "rightUpperLeg" => "hips",
                "chest" => "spine",
                "upperChest" => "chest",
                "neck" | "leftShoulder" | "rightShoulder" => "upperChest",
                "head" => "neck",
                "leftLowerLeg" => "leftUpperLeg",
                "rightLowerLeg" => "rightUpperLeg",
                "leftFoot" => "leftLowerLeg",
                "rightFoot" => "rightLowerLeg",
                "leftToes" => "leftFoot",
                "rightToes" => "rightFoot",
                "leftUpperArm" => "leftShoulder",
                "rightUpperArm" => "rightShoulder",
                "leftLowerArm" => "leftUpperArm",
                "rightLowerArm" => "rightUpperArm",
                "leftHand" => "leftLowerArm",
                "rightHand" => "rightLowerArm",
                other => panic!("unexpected bone {other}"),
            })
        };
        for (j, b) in HUMANOID_BONES.iter().enumerate() {
            let Some(v) = b.vrm else { continue };
            let parent = usize::try_from(SMPL_PARENTS[j]).ok().and_then(|p| HUMANOID_BONES[p].vrm);
            assert_eq!(parent, vrm_parent(v), "{v}");
        }
    }

    /// Left bones lie at +x (the body's left when it faces +z) in the rest pose.
    #[test]
    fn left_bones_are_on_the_bodys_left() {
        let model = BodyModel::default_body().unwrap();
        let joints = model.regress_joints(&model.v_template);
        let nose = crate::body::body_surface::surface_landmarks(&model).unwrap()[0].vertex;
        let head = joints[joint_index("head").unwrap()];
        assert!(model.v_template[nose as usize].z > head.z + 0.05, "the body faces +z");
        for (b, p) in HUMANOID_BONES.iter().zip(joints) {
            let side = if b.node.starts_with("Left") {
                1.0
            } else if b.node.starts_with("Right") {
                -1.0
            } else {
                continue;
            };
            assert!(p.x * side > 0.02, "{} at {p}", b.smpl);
            assert!(b.vrm.is_none_or(|v| v.starts_with(if side > 0.0 { "left" } else { "right" })), "{b:?}");
        }
    }

    #[test]
    fn skeleton_names_parse() {
        assert_eq!(SkeletonNames::parse("humanoid"), Ok(SkeletonNames::Humanoid));
        assert_eq!(SkeletonNames::Humanoid.names()[16], "LeftArm");
        assert_eq!(SkeletonNames::Smpl.names()[0], "pelvis");
        assert!(SkeletonNames::parse("mixamo").is_err());
    }
}
