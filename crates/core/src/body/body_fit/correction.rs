//! A re-fit from a pose a person corrected (the app's pose controls, then "Re-fit from this
//! pose"; `trainer fit-pose --start`). The corrected fit, seen through its own camera, is the
//! start ([`fit_state`]); a limb it puts far from the detector's landmarks ([`corrected_limbs`])
//! is the person's correction of a misreading: the re-fit drops that limb's landmarks and
//! holds its joints at the person's rotations ([`HOLD`]). Without that the misread landmarks
//! pull the limb back: seen from its side, MediaPipe reads a hand at the waist over the head
//! with the other one, and the fit started from the true pose still ends at 94 mm PA-MPJPE
//! (docs/benchmarks.md, "Body fit").

use glam::{Mat3, Quat, Vec3};

use super::init::posed_joints;
use super::input::FitInput;
use super::landmarks::{JOINT_LANDMARKS, VISIBLE};
use super::result::{BodyFit, FitState, NEAR};
use crate::body::body_model::BodyModel;
use crate::body::skinning::axis_angle_to_matrix;
use crate::render::camera::reference_fov_y;

/// A limb a person can correct: its name, the joints whose rotations pose it (shoulder or
/// hip to hand or foot) and its landmarks from the elbow or knee down.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Limb {
    pub name: &'static str,
    pub joints: [usize; 4],
    pub landmarks: &'static [usize],
}

pub const LIMBS: [Limb; 4] = [
    Limb { name: "left arm", joints: [16, 18, 20, 22], landmarks: &[13, 15, 17, 19, 21] },
    Limb { name: "right arm", joints: [17, 19, 21, 23], landmarks: &[14, 16, 18, 20, 22] },
    Limb { name: "left leg", joints: [1, 4, 7, 10], landmarks: &[25, 27, 29, 31] },
    Limb { name: "right leg", joints: [2, 5, 8, 11], landmarks: &[26, 28, 30, 32] },
];

/// How far, as a fraction of the crop's side, a start may put a limb's elbow or wrist (knee or
/// ankle) from where the detector saw it before the limb counts as corrected: about 10 % of
/// the body's height. A fit leaves its landmarks within 2 % of the height on average
/// (`fit_cli`), so an untouched limb stays with its landmarks, while correcting a misread
/// limb moves its hand by tens of centimetres.
pub const CORRECTED: f32 = 0.08;

/// The weight of the pull of a held limb's joint rotations towards the person's, per radian²
/// (as the symmetry term's, `FitWeights::symmetry`).
pub const HOLD: f32 = 20.0;

/// The fit's own parameters for `fit`: the turn its camera holds put back into θ₀, and the
/// camera's translation that leaves every posed point where `fit`'s camera sees it. With `C`
/// the camera's rotation and `j₀` the root joint, `p(C·R) = C·p(R) + (I − C)·j₀`.
pub fn fit_state(fit: &BodyFit, model: &BodyModel) -> FitState {
    let camera = fit.world_to_camera();
    let turn = Mat3::from_mat4(camera);
    let mut params = fit.body_params();
    let root = posed_joints(model, &params)[0];
    params.pose[0] = Quat::from_mat3(&(turn * axis_angle_to_matrix(params.pose[0]))).normalize().to_scaled_axis();
    let translation = camera.w_axis.truncate() - root + turn * root;
    FitState { params, camera: translation }
}

/// The limbs that `state` puts farther than [`CORRECTED`] of the crop from one of their seen
/// joint landmarks (elbow, wrist, knee, ankle) of `input`.
pub fn corrected_limbs(model: &BodyModel, state: &FitState, input: &FitInput) -> Vec<Limb> {
    let joints = posed_joints(model, &state.params);
    let f = 1.0 / (reference_fov_y() / 2.0).tan();
    let ndc = |p: Vec3| {
        let c = p + state.camera;
        let depth = (-c.z).max(NEAR);
        [f * c.x / depth, f * c.y / depth]
    };
    LIMBS
        .into_iter()
        .filter(|limb| {
            JOINT_LANDMARKS.iter().filter(|m| limb.landmarks.contains(&m.landmark)).any(|m| {
                let (seen, vis) = input.points[m.landmark];
                let p = ndc(joints[m.joint]);
                // NDC spans the crop's side twice.
                vis >= VISIBLE && (p[0] - seen[0]).hypot(p[1] - seen[1]) / 2.0 > CORRECTED
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::body::body_fit::framing::Framing;
    use crate::body::body_fit::options::FitOptions;
    use crate::body::body_fit::result::{upright, FitResiduals, BODY_FIT_FORMAT};
    use crate::body::skinning::{pose_body, BodyParams};
    use crate::render::camera::to_row_major;
    use glam::Mat4;

    /// `fit_state` undoes `upright`: the body posed with the state's θ₀, moved by its
    /// translation, lands where the fit's camera sees the upright body, point for point.
    #[test]
    fn the_fit_state_sees_every_point_where_the_fit_does() {
        let model = BodyModel::default_body().unwrap();
        let mut params = BodyParams::default();
        params.pose[0] = Vec3::new(0.3, -1.4, 0.2);
        params.pose[18] = Vec3::new(0.1, -0.9, 0.4);
        params.betas = vec![0.8, -0.5, 0.0, 0.3];
        let m = Mat4::from_translation(Vec3::new(0.05, 0.2, -2.6));
        let root = pose_body(&model, &params).kinematics.rest_joints[0];
        let (orient, camera) = upright(params.pose[0], root, m);
        let mut shown = params.clone();
        shown.pose[0] = orient;
        let framing = Framing { photo_width: 512, photo_height: 512, centre: [256.0, 256.0], side: 512.0 };
        let theta = shown.theta();
        let fit = BodyFit {
            format: BODY_FIT_FORMAT.into(),
            global_orient: [theta[0], theta[1], theta[2]],
            body_pose: theta[3..].to_vec(),
            betas: shown.betas.clone(),
            camera: to_row_major(camera),
            fov_y: reference_fov_y(),
            framing,
            keypoints: Vec::new(),
            residuals: FitResiduals { mean_px: 0.0, relative_to_height: 0.0, mask_iou: None, stage_loss: [None; 3] },
            table: Vec::new(),
            missing: Vec::new(),
            off_person: Vec::new(),
            relabelled: Vec::new(),
            held: Vec::new(),
            options: FitOptions::default(),
            rotation: 0,
        };
        let state = fit_state(&fit, &model);
        assert!(
            (state.params.pose[0] - params.pose[0]).length() < 1e-4,
            "{} vs {}",
            state.params.pose[0],
            params.pose[0]
        );
        let seen = pose_body(&model, &fit.body_params());
        let own = pose_body(&model, &state.params);
        for (a, b) in seen.vertices.iter().zip(&own.vertices).step_by(53) {
            let (pa, pb) = (camera.transform_point3(*a), *b + state.camera);
            assert!((pa - pb).length() < 1e-4, "{pa} vs {pb}");
        }
    }
}
