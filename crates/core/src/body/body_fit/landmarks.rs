//! MediaPipe Pose (BlazePose, 33 landmarks) as the body fit's observations: the landmark
//! names, which landmarks correspond to which SMPL joints (and how much the fit trusts each),
//! and the detector's result object (`poseLandmarks`, `poseWorldLandmarks`) as its JavaScript
//! API returns it, parsed and validated.
//!
//! Sides: MediaPipe's "left" is the person's left, as SMPL's is. In a photo of a person
//! facing the camera the person's left shoulder (MediaPipe 11, SMPL 16) is on the image's
//! right (tested below with the reference camera).

use serde::{Deserialize, Serialize};

use crate::body::body_model::NUM_JOINTS;

/// Landmarks per detected person.
pub const NUM_LANDMARKS: usize = 33;

/// BlazePose's landmark names in index order.
pub const LANDMARK_NAMES: [&str; NUM_LANDMARKS] = [
    "nose",
    "left_eye_inner",
    "left_eye",
    "left_eye_outer",
    "right_eye_inner",
    "right_eye",
    "right_eye_outer",
    "left_ear",
    "right_ear",
    "mouth_left",
    "mouth_right",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_pinky",
    "right_pinky",
    "left_index",
    "right_index",
    "left_thumb",
    "right_thumb",
    "left_hip",
    "right_hip",
    "left_knee",
    "right_knee",
    "left_ankle",
    "right_ankle",
    "left_heel",
    "right_heel",
    "left_foot_index",
    "right_foot_index",
];

/// Landmarks at or above this visibility count as seen (framing, the torso check, the
/// reported residuals and missing landmarks).
pub const VISIBLE: f32 = 0.5;

/// The torso's landmarks: shoulders and hips.
pub const TORSO_LANDMARKS: [usize; 4] = [11, 12, 23, 24];

/// A MediaPipe landmark that corresponds to an SMPL joint, and the weight of its reprojection
/// term in the fit.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct JointLandmark {
    /// Index into [`LANDMARK_NAMES`].
    pub landmark: usize,
    /// Index into `body_model::JOINT_NAMES`.
    pub joint: usize,
    pub weight: f32,
}

/// Weight of the hip landmarks: MediaPipe places them near the skin at the hip's outside,
/// SMPL's hip joints sit deeper and lower (SPIN's SMPLify ignores them for the same reason).
pub const HIP_WEIGHT: f32 = 0.2;

/// The landmark → SMPL joint table of the fit (shoulders, elbows, wrists, hips, knees,
/// ankles; face, hand and foot landmarks lie on the body surface, not at joints).
pub const JOINT_LANDMARKS: [JointLandmark; 12] = [
    JointLandmark { landmark: 11, joint: 16, weight: 1.0 },
    JointLandmark { landmark: 12, joint: 17, weight: 1.0 },
    JointLandmark { landmark: 13, joint: 18, weight: 1.0 },
    JointLandmark { landmark: 14, joint: 19, weight: 1.0 },
    JointLandmark { landmark: 15, joint: 20, weight: 1.0 },
    JointLandmark { landmark: 16, joint: 21, weight: 1.0 },
    JointLandmark { landmark: 23, joint: 1, weight: HIP_WEIGHT },
    JointLandmark { landmark: 24, joint: 2, weight: HIP_WEIGHT },
    JointLandmark { landmark: 25, joint: 4, weight: 1.0 },
    JointLandmark { landmark: 26, joint: 5, weight: 1.0 },
    JointLandmark { landmark: 27, joint: 7, weight: 1.0 },
    JointLandmark { landmark: 28, joint: 8, weight: 1.0 },
];

/// One landmark as MediaPipe's JavaScript API returns it: `x`, `y` normalised to the image
/// width and height (origin top left) for `poseLandmarks`, metres around the hips' centre
/// for `poseWorldLandmarks`; `visibility` in [0, 1].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Landmark {
    pub x: f32,
    pub y: f32,
    #[serde(default)]
    pub z: f32,
    #[serde(default = "fully_visible")]
    pub visibility: f32,
}

fn fully_visible() -> f32 {
    1.0
}

/// MediaPipe Pose's result for one person (`kp.json` of `trainer fit-pose`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct PoseResult {
    pub pose_landmarks: Vec<Landmark>,
    #[serde(default)]
    pub pose_world_landmarks: Option<Vec<Landmark>>,
    /// The person mask (`enableSegmentation`), as the app's glue serialises it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub segmentation_mask: Option<SegmentationMask>,
    /// Degrees clockwise the photo was turned for the detector to read the person upright
    /// ([`super::turn`]); the landmarks and the mask are of the turned photo.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub rotation: u16,
}

fn is_zero(v: &u16) -> bool {
    *v == 0
}

/// A person mask: `width × height` probabilities in [0, 1], row-major from the top left.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SegmentationMask {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

/// A detector result that cannot be fitted, naming the field at fault.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum LandmarkError {
    #[error("not a MediaPipe Pose result: {0}")]
    Json(String),
    #[error("`{field}` has {got} landmarks, expected {NUM_LANDMARKS}")]
    Count { field: &'static str, got: usize },
    #[error("`{field}[{index}]` ({name}): {what} is not a finite number")]
    NotFinite { field: &'static str, index: usize, name: &'static str, what: &'static str },
    #[error("`poseLandmarks[{index}]` ({name}): visibility {value} is outside [0, 1]")]
    Visibility { index: usize, name: &'static str, value: f32 },
    #[error("`segmentationMask`: {0}")]
    Mask(String),
    #[error(transparent)]
    Turn(#[from] super::turn::TurnError),
}

impl PoseResult {
    /// Parse and validate the JSON of a MediaPipe Pose result.
    pub fn from_json(text: &str) -> Result<Self, LandmarkError> {
        let r: Self = serde_json::from_str(text).map_err(|e| LandmarkError::Json(e.to_string()))?;
        r.validate()?;
        Ok(r)
    }

    /// 33 landmarks in each list, finite coordinates, visibilities in [0, 1].
    pub fn validate(&self) -> Result<(), LandmarkError> {
        super::turn::check(self.rotation)?;
        let lists = std::iter::once(("poseLandmarks", &self.pose_landmarks))
            .chain(self.pose_world_landmarks.as_ref().map(|w| ("poseWorldLandmarks", w)));
        for (field, list) in lists {
            if list.len() != NUM_LANDMARKS {
                return Err(LandmarkError::Count { field, got: list.len() });
            }
            for (index, (l, name)) in list.iter().zip(LANDMARK_NAMES).enumerate() {
                for (what, v) in [("x", l.x), ("y", l.y), ("z", l.z), ("visibility", l.visibility)] {
                    if !v.is_finite() {
                        return Err(LandmarkError::NotFinite { field, index, name, what });
                    }
                }
                if field == "poseLandmarks" && !(0.0..=1.0).contains(&l.visibility) {
                    return Err(LandmarkError::Visibility { index, name, value: l.visibility });
                }
            }
        }
        if let Some(m) = &self.segmentation_mask {
            let want = m.width.checked_mul(m.height).filter(|n| *n > 0);
            if want != Some(m.data.len()) {
                return Err(LandmarkError::Mask(format!(
                    "{} values for {}×{} pixels",
                    m.data.len(),
                    m.width,
                    m.height
                )));
            }
            if let Some((i, v)) = m.data.iter().enumerate().find(|(_, v)| !(0.0..=1.0).contains(*v)) {
                return Err(LandmarkError::Mask(format!("value {v} at index {i} is outside [0, 1]")));
            }
        }
        Ok(())
    }

    /// The fit's 2D observation of every SMPL joint in [`JOINT_LANDMARKS`]: pixel position in
    /// an image of `width` × `height` and confidence (table weight × visibility); joints
    /// without a landmark get confidence 0.
    pub fn joint_observations(&self, width: usize, height: usize) -> [([f32; 2], f32); NUM_JOINTS] {
        let mut out = [([0.0; 2], 0.0); NUM_JOINTS];
        for m in JOINT_LANDMARKS {
            if let Some(l) = self.pose_landmarks.get(m.landmark) {
                out[m.joint] = ([l.x * width as f32, l.y * height as f32], m.weight * l.visibility);
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::body::body_model::{BodyModel, JOINT_NAMES};
    use crate::body::pose_library::PoseLibrary;
    use crate::body::skinning::pose_body;
    use crate::render::camera::{project_to_pixel, OrbitCamera};

    #[test]
    fn every_mapped_landmark_names_the_joint_on_the_same_side() {
        for m in JOINT_LANDMARKS {
            let (landmark, joint) = (LANDMARK_NAMES[m.landmark], JOINT_NAMES[m.joint]);
            let part = |n: &str| n.split_once('_').map(|(side, part)| (side.to_string(), part.to_string()));
            let (side_l, part_l) = part(landmark).unwrap();
            let (side_j, part_j) = part(joint).unwrap();
            assert_eq!(side_l, side_j, "{landmark} → {joint}");
            // wrist ↔ wrist, hip ↔ hip, …: the same body part, by name.
            assert_eq!(part_l, part_j, "{landmark} → {joint}");
        }
        let joints: std::collections::BTreeSet<usize> = JOINT_LANDMARKS.iter().map(|m| m.joint).collect();
        assert_eq!(joints.len(), JOINT_LANDMARKS.len(), "one landmark per joint");
    }

    /// MediaPipe labels a frontal person's left shoulder on the image's right; the body's
    /// left shoulder (SMPL 16, which landmark 11 maps to) must project there too.
    #[test]
    fn a_frontal_persons_left_side_is_on_the_image_right() {
        let model = BodyModel::default_body().unwrap();
        let body = pose_body(&model, &PoseLibrary::builtin().params("T", &[]).unwrap());
        let cam = OrbitCamera::default().world_to_camera();
        let size = 512;
        for m in JOINT_LANDMARKS {
            let px = project_to_pixel(cam, body.kinematics.posed_joints[m.joint], size).unwrap();
            let on_left_of_person = LANDMARK_NAMES[m.landmark].starts_with("left_");
            assert_eq!(px.x > size as f32 / 2.0, on_left_of_person, "{} at {px}", LANDMARK_NAMES[m.landmark]);
        }
    }

    fn result_json(n: usize, visibility: f32) -> String {
        let l = |k: usize| format!(r#"{{"x":{},"y":0.5,"z":0.0,"visibility":{visibility}}}"#, k as f32 / 40.0);
        let list = (0..n).map(l).collect::<Vec<_>>().join(",");
        format!(r#"{{"poseLandmarks":[{list}],"poseWorldLandmarks":[{list}]}}"#)
    }

    #[test]
    fn detector_results_are_validated_naming_the_field() {
        let r = PoseResult::from_json(&result_json(33, 0.9)).unwrap();
        let obs = r.joint_observations(400, 200);
        // Landmark 15 (left wrist, x = 15/40) → SMPL 20 at pixel (150, 100), full weight.
        assert_eq!(obs[20].0, [150.0, 100.0]);
        assert!((obs[20].1 - 0.9).abs() < 1e-6);
        assert!((obs[1].1 - 0.9 * HIP_WEIGHT).abs() < 1e-6, "hips are down-weighted");
        assert_eq!(obs[0].1, 0.0, "the pelvis has no landmark");
        assert_eq!(
            PoseResult::from_json(&result_json(17, 0.9)).unwrap_err(),
            LandmarkError::Count { field: "poseLandmarks", got: 17 }
        );
        let e = PoseResult::from_json(&result_json(33, 1.5)).unwrap_err().to_string();
        assert!(e.contains("visibility 1.5") && e.contains("nose"), "{e}");
        let e = PoseResult::from_json(r#"{"poseLandmarks": 3}"#).unwrap_err().to_string();
        assert!(e.starts_with("not a MediaPipe Pose result"), "{e}");
        let nan = result_json(33, 0.9).replacen(r#""y":0.5"#, r#""y":1e999"#, 1);
        assert!(PoseResult::from_json(&nan).is_err(), "overflowing numbers are refused");
        let with_mask = |m: &str| result_json(33, 0.9).replacen('{', &format!(r#"{{"segmentationMask":{m},"#), 1);
        let r = PoseResult::from_json(&with_mask(r#"{"width":2,"height":1,"data":[0.0,1.0]}"#)).unwrap();
        assert_eq!(r.segmentation_mask.unwrap().data, vec![0.0, 1.0]);
        let e = PoseResult::from_json(&with_mask(r#"{"width":2,"height":2,"data":[0.0,1.0]}"#)).unwrap_err();
        assert_eq!(e.to_string(), "`segmentationMask`: 2 values for 2×2 pixels");
        let e = PoseResult::from_json(&with_mask(r#"{"width":1,"height":1,"data":[2.0]}"#)).unwrap_err();
        assert!(e.to_string().contains("value 2 at index 0"), "{e}");
    }
}
