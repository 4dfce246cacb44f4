//! MediaPipe landmarks that lie on the body's surface rather than at a joint (nose, eyes,
//! ears, heels, toes): each is a vertex of the body, picked geometrically on the open rest
//! body (T-pose, facing +z, left = +x) so that any body in the SMPL layout gets its own:
//!
//! - nose: the most forward vertex of the head's midline (|x| < 1 cm, above the neck);
//! - eyes: the most forward vertex 3.2 cm either side of the midline, 3.5 cm above the nose;
//! - ears: the outermost head vertex (|x|) within 2 cm of the nose's height behind the face;
//! - heels: the rearmost vertex of each foot below the ankle;
//! - toes (`foot_index`): the foremost vertex of each foot below the ankle.
//!
//! Hand landmarks (pinky, index, thumb) and the mouth are not used: the wrists already pin
//! the hands, and the mouth moves with the face.

use glam::Vec3;

use crate::body::body_model::{joint_index, BodyModel};
use crate::body::skinning::PosedBody;

/// A surface landmark: the MediaPipe index and the weight of its reprojection term.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct SurfaceLandmark {
    /// Index into [`crate::body::body_fit::landmarks::LANDMARK_NAMES`].
    pub landmark: usize,
    /// The body vertex it corresponds to.
    pub vertex: u32,
    pub weight: f32,
}

/// Face landmarks weigh less than joints (they turn the head, nothing else); feet weigh as
/// much as the ankles.
const FACE_WEIGHT: f32 = 0.5;
const FOOT_WEIGHT: f32 = 1.0;

/// The body has no vertex where a rule looks (not a human body in the SMPL layout).
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("the body has no vertex for the landmark `{0}` (is it a human body, T-pose, facing +z?)")]
pub struct SurfaceError(pub &'static str);

/// Where the nose landmark's vertex lies on `body`, a posed body of `model` (e.g. its
/// canonical Da-pose body, `inverse_skinning::canonical_body`).
pub fn nose_on(model: &BodyModel, body: &PosedBody) -> Result<Vec3, SurfaceError> {
    let nose = surface_landmarks(model)?.into_iter().find(|l| l.landmark == 0).ok_or(SurfaceError("nose"))?.vertex;
    body.vertices.get(nose as usize).copied().ok_or(SurfaceError("nose"))
}

/// The surface landmarks of `model`, picked by the rules of the module documentation.
pub fn surface_landmarks(model: &BodyModel) -> Result<Vec<SurfaceLandmark>, SurfaceError> {
    let v = &model.v_template;
    let joints = model.regress_joints(v);
    let joint = |name: &str| joint_index(name).map(|j| joints[j]).unwrap_or(Vec3::ZERO);
    let (neck, head) = (joint("neck"), joint("head"));
    // The best vertex by `score` among those passing `keep`.
    let best = |name: &'static str, keep: &dyn Fn(Vec3) -> bool, score: &dyn Fn(Vec3) -> f32| {
        v.iter()
            .enumerate()
            .filter(|(_, p)| keep(**p))
            .max_by(|a, b| score(*a.1).total_cmp(&score(*b.1)))
            .map(|(i, _)| i as u32)
            .ok_or(SurfaceError(name))
    };
    let above_neck = |p: Vec3| p.y > neck.y + 0.03 && p.x.abs() < 0.15;
    let nose = best("nose", &|p| above_neck(p) && p.x.abs() < 0.01, &|p| p.z)?;
    let nose_p = v[nose as usize];
    let eye = |name, side: f32| {
        let target = Vec3::new(side * 0.032, nose_p.y + 0.035, 0.0);
        best(name, &|p| above_neck(p) && (p.x - target.x).abs() < 0.008 && (p.y - target.y).abs() < 0.008, &|p| p.z)
    };
    let ear = |name, side: f32| {
        best(name, &|p| above_neck(p) && (p.y - nose_p.y).abs() < 0.02 && p.z < head.z + 0.03, &|p| side * p.x)
    };
    let foot = |name, side: f32, forward: f32| {
        let ankle = joint(if side > 0.0 { "left_ankle" } else { "right_ankle" });
        best(name, &|p| p.y < ankle.y - 0.02 && p.x * side > 0.0 && (p.x - ankle.x).abs() < 0.08, &|p| forward * p.z)
    };
    let face = |landmark, vertex| SurfaceLandmark { landmark, vertex, weight: FACE_WEIGHT };
    let feet = |landmark, vertex| SurfaceLandmark { landmark, vertex, weight: FOOT_WEIGHT };
    Ok(vec![
        face(0, nose),
        face(2, eye("left_eye", 1.0)?),
        face(5, eye("right_eye", -1.0)?),
        face(7, ear("left_ear", 1.0)?),
        face(8, ear("right_ear", -1.0)?),
        feet(29, foot("left_heel", 1.0, -1.0)?),
        feet(30, foot("right_heel", -1.0, -1.0)?),
        feet(31, foot("left_foot_index", 1.0, 1.0)?),
        feet(32, foot("right_foot_index", -1.0, 1.0)?),
    ])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::body::body_fit::landmarks::LANDMARK_NAMES;

    #[test]
    fn surface_landmarks_sit_where_their_names_say() {
        let model = BodyModel::default_body().unwrap();
        let marks = surface_landmarks(&model).unwrap();
        let at = |name: &str| {
            let m = marks.iter().find(|m| LANDMARK_NAMES[m.landmark] == name).unwrap();
            model.v_template[m.vertex as usize]
        };
        let joints = model.regress_joints(&model.v_template);
        let head = joints[joint_index("head").unwrap()];
        let (nose, le, re, lear, rear) = (at("nose"), at("left_eye"), at("right_eye"), at("left_ear"), at("right_ear"));
        for (name, p) in [("nose", nose), ("left_eye", le), ("right_eye", re), ("left_ear", lear), ("right_ear", rear)]
        {
            eprintln!("{name}: {p} (head joint {head})");
        }
        // The face: nose in front of the head joint on the midline, eyes above it on their
        // sides, ears wider than the eyes and behind them; left = +x.
        assert!(nose.x.abs() < 0.01 && nose.z > head.z + 0.05, "{nose}");
        assert!(le.x > 0.02 && re.x < -0.02 && le.y > nose.y && re.y > nose.y);
        assert!(le.z < nose.z && le.z > head.z + 0.03);
        assert!(lear.x > le.x + 0.03 && rear.x < re.x - 0.03, "{lear} {rear}");
        assert!(lear.z < le.z - 0.05 && (lear.y - nose.y).abs() < 0.03);
        // The feet: heels behind the ankles, toes well in front, on the ground.
        for side in ["left", "right"] {
            let ankle = joints[joint_index(&format!("{side}_ankle")).unwrap()];
            let (heel, toe) = (at(&format!("{side}_heel")), at(&format!("{side}_foot_index")));
            eprintln!("{side}: ankle {ankle} heel {heel} toe {toe}");
            assert!(heel.z < ankle.z - 0.02 && toe.z > ankle.z + 0.1, "{side}: {heel} {toe}");
            assert!(heel.y < ankle.y && toe.y < ankle.y);
            assert_eq!(heel.x > 0.0, side == "left");
        }
    }
}
