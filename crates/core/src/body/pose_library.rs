//! Named poses in a small, documented JSON format (`assets/poses/poses.json`).
//!
//! ```json
//! { "format": "getavatar-poses/1",
//!   "poses": { "Da": { "description": "...", "global_orient": [0,0,0],
//!                      "joints": { "left_hip": [0, 0, 0.5], "right_hip": [0, 0, -0.5] } } } }
//! ```
//! Each joint value is an SMPL axis-angle vector in radians; unlisted joints are zero.

use std::collections::BTreeMap;

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::body::body_model::{joint_index, NUM_JOINTS};
use crate::body::skinning::BodyParams;

/// The built-in pose library.
pub const BUILTIN_POSES_JSON: &str =
    include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/../../assets/poses/poses.json"));

/// Names of the built-in poses, in display order.
pub const BUILTIN_POSE_NAMES: [&str; 8] = ["T", "A", "Da", "standing", "walking", "sitting", "one_leg", "arms_up"];

/// Canonical pose of the generator (paper code's "Da-pose"): hips abducted ±0.5 rad.
pub fn da_pose() -> [Vec3; NUM_JOINTS] {
    let mut p = [Vec3::ZERO; NUM_JOINTS];
    p[1] = Vec3::new(0.0, 0.0, 0.5);
    p[2] = Vec3::new(0.0, 0.0, -0.5);
    p
}

#[derive(Debug, thiserror::Error)]
pub enum PoseError {
    #[error("pose file is not valid JSON of the getavatar-poses/1 format: {0}")]
    Json(#[from] serde_json::Error),
    #[error("unsupported pose format `{0}` (expected getavatar-poses/1)")]
    Format(String),
    #[error("pose `{pose}`: unknown joint `{joint}` (use SMPL joint names)")]
    UnknownJoint { pose: String, joint: String },
    #[error("pose `{pose}`: joint `{joint}` has a non-finite value")]
    NonFinite { pose: String, joint: String },
    #[error("no pose named `{0}`")]
    NotFound(String),
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PoseEntry {
    #[serde(default)]
    pub description: String,
    #[serde(default)]
    pub global_orient: [f32; 3],
    #[serde(default)]
    pub joints: BTreeMap<String, [f32; 3]>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PoseFile {
    pub format: String,
    #[serde(default)]
    pub convention: String,
    pub poses: BTreeMap<String, PoseEntry>,
}

/// A validated set of named poses.
#[derive(Clone, Debug)]
pub struct PoseLibrary {
    poses: BTreeMap<String, ([Vec3; NUM_JOINTS], String)>,
}

impl PoseLibrary {
    pub fn builtin() -> Self {
        // The built-in file is tested; fall back to an empty library rather than panic.
        Self::from_json(BUILTIN_POSES_JSON).unwrap_or(Self { poses: BTreeMap::new() })
    }

    pub fn from_json(text: &str) -> Result<Self, PoseError> {
        let file: PoseFile = serde_json::from_str(text)?;
        if file.format != "getavatar-poses/1" {
            return Err(PoseError::Format(file.format));
        }
        let mut poses = BTreeMap::new();
        for (name, entry) in file.poses {
            let mut p = [Vec3::ZERO; NUM_JOINTS];
            p[0] = Vec3::from_array(entry.global_orient);
            for (joint, v) in &entry.joints {
                let j = joint_index(joint)
                    .ok_or_else(|| PoseError::UnknownJoint { pose: name.clone(), joint: joint.clone() })?;
                if v.iter().any(|x| !x.is_finite()) {
                    return Err(PoseError::NonFinite { pose: name.clone(), joint: joint.clone() });
                }
                p[j] = Vec3::from_array(*v);
            }
            if !p[0].is_finite() {
                return Err(PoseError::NonFinite { pose: name.clone(), joint: "global_orient".into() });
            }
            poses.insert(name, (p, entry.description));
        }
        Ok(Self { poses })
    }

    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.poses.keys().map(String::as_str)
    }

    pub fn description(&self, name: &str) -> Option<&str> {
        self.poses.get(name).map(|(_, d)| d.as_str())
    }

    /// θ of a named pose (24 axis-angle vectors).
    pub fn pose(&self, name: &str) -> Result<[Vec3; NUM_JOINTS], PoseError> {
        self.poses.get(name).map(|(p, _)| *p).ok_or_else(|| PoseError::NotFound(name.to_string()))
    }

    /// Body parameters for a named pose with the given shape.
    pub fn params(&self, name: &str, betas: &[f32]) -> Result<BodyParams, PoseError> {
        Ok(BodyParams { pose: self.pose(name)?, betas: betas.to_vec(), transl: Vec3::ZERO })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtin_library_has_all_documented_poses() {
        let lib = PoseLibrary::from_json(BUILTIN_POSES_JSON).expect("builtin parses");
        for n in BUILTIN_POSE_NAMES {
            assert!(lib.pose(n).is_ok(), "missing {n}");
        }
        assert_eq!(lib.pose("Da").expect("Da"), da_pose());
        assert_eq!(lib.pose("T").expect("T"), [Vec3::ZERO; NUM_JOINTS]);
    }

    #[test]
    fn bad_pose_files_are_errors() {
        let e = PoseLibrary::from_json(r#"{"format":"getavatar-poses/1","poses":{"x":{"joints":{"elbow":[0,0,1]}}}}"#)
            .unwrap_err();
        assert!(e.to_string().contains("elbow"), "{e}");
        assert!(PoseLibrary::from_json(r#"{"format":"other","poses":{}}"#).is_err());
        assert!(PoseLibrary::from_json("[").is_err());
        assert!(PoseLibrary::builtin().pose("nope").is_err());
    }
}
