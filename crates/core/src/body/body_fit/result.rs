//! The fitted body ([`BodyFit`], `fit.json`): pose, shape and camera, with what they were
//! fitted to and how well.

use glam::{Mat3, Mat4, Quat, Vec3};
use serde::{Deserialize, Serialize};

use super::framing::{Framing, MAX_PHOTO_PIXELS};
use super::options::FitOptions;
use crate::body::body_model::NUM_JOINTS;
use crate::body::skinning::{axis_angle_to_matrix, BodyParams};

/// Clip planes of the fit's camera, metres.
pub(crate) const NEAR: f32 = 0.1;
pub(crate) const FAR: f32 = 100.0;

/// The fitted body: pose, shape and camera, with what it was fitted to and how well.
/// `fit.json` of `trainer fit-pose` and the app's "Download fit".
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BodyFit {
    /// `getavatar-body-fit/1`.
    pub format: String,
    /// θ₀, axis-angle, radians (upright: the turn about the vertical is in the camera).
    pub global_orient: [f32; 3],
    /// θ₁…θ₂₃, 69 numbers.
    pub body_pose: Vec<f32>,
    pub betas: Vec<f32>,
    /// World → camera, 16 numbers row-major (the dataset label layout), reference
    /// intrinsics (`fov_y`) on the square crop of `framing`.
    pub camera: [f32; 16],
    /// Vertical field of view, radians.
    pub fov_y: f32,
    pub framing: Framing,
    /// Every landmark: where it was seen, where the fitted body puts it (photo pixels).
    pub keypoints: Vec<FitKeypoint>,
    pub residuals: FitResiduals,
    /// The landmark → joint/vertex table used.
    pub table: Vec<FitTarget>,
    /// Landmarks the detector did not see (visibility < 0.5) or put off the person
    /// (`off_person`); the fit ignores them.
    pub missing: Vec<String>,
    /// Landmarks the detector saw where the person mask shows no person, with the rest of
    /// their limb ([`super::input::off_person`]): taken as the detector's errors.
    #[serde(default)]
    pub off_person: Vec<String>,
    /// Landmarks the fit took with their sides swapped (`"left_wrist↔right_wrist"`, …):
    /// the detector's labels of a hidden hand and a seen one, when swapping them explained
    /// the photo better ([`HAND_SWAP`]). `keypoints` report the swapped labels.
    #[serde(default)]
    pub relabelled: Vec<String>,
    /// Limbs a person corrected before this fit (`"left arm"`, …): their landmarks disagreed
    /// with the correction, so the fit held the limb where the person put it and left those
    /// landmarks out of `residuals` ([`super::correction`]).
    #[serde(default)]
    pub held: Vec<String>,
    pub options: FitOptions,
    /// Degrees clockwise the photo was turned to read the person upright ([`super::turn`]):
    /// `camera`, `framing` and `keypoints` are of the turned photo;
    /// [`BodyFit::original_photo_view_proj`] draws on the photo as taken.
    #[serde(default)]
    pub rotation: u16,
}

pub const BODY_FIT_FORMAT: &str = "getavatar-body-fit/1";

/// The fit's own parameters: θ with the body's whole turn in it (not yet split into the
/// camera, as [`BodyFit`] has it) and the camera's translation (world → camera).
#[derive(Clone, Debug, PartialEq)]
pub struct FitState {
    pub params: BodyParams,
    pub camera: Vec3,
}

/// One landmark of [`BodyFit::keypoints`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FitKeypoint {
    pub name: String,
    /// Detected, photo pixels.
    pub observed: [f32; 2],
    /// The fitted body's joint or surface point, projected, photo pixels (absent for
    /// landmarks the fit has no body point for).
    pub fitted: Option<[f32; 2]>,
    pub visibility: f32,
}

/// One row of [`BodyFit::table`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FitTarget {
    pub landmark: String,
    /// SMPL joint name, for joint landmarks.
    pub joint: Option<String>,
    /// Body vertex, for surface landmarks.
    pub vertex: Option<u32>,
    pub weight: f32,
}

/// How well the fit explains what it saw.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FitResiduals {
    /// Visibility-weighted mean distance between detected and fitted keypoints, photo pixels.
    pub mean_px: f32,
    /// `mean_px` over the fitted body's height in the photo.
    pub relative_to_height: f32,
    /// IoU of the fitted body's mask and the person mask (threshold ½), when there was one.
    pub mask_iou: Option<f32>,
    /// Final loss of each stage (`null` for a stage that did not run).
    pub stage_loss: [Option<f32>; 3],
}

impl BodyFit {
    pub fn to_json(&self) -> Result<String, serde_json::Error> {
        serde_json::to_string_pretty(self)
    }

    /// Parse and check a fit.json: its format, 69 pose numbers, at most 300 betas, finite
    /// numbers, a field of view in (0, π), an invertible camera, and a framing of a non-empty
    /// photo of at most 40 MP with a positive crop side (what the inversion and the export
    /// compute with).
    pub fn from_json(text: &str) -> Result<Self, String> {
        let fit: BodyFit = serde_json::from_str(text).map_err(|e| e.to_string())?;
        fit.validate()?;
        Ok(fit)
    }

    pub fn validate(&self) -> Result<(), String> {
        if self.format != BODY_FIT_FORMAT {
            return Err(format!("`format` is {:?}, expected {BODY_FIT_FORMAT:?}", self.format));
        }
        if self.body_pose.len() != (NUM_JOINTS - 1) * 3 {
            return Err(format!("`body_pose` has {} numbers, expected {}", self.body_pose.len(), (NUM_JOINTS - 1) * 3));
        }
        if self.betas.len() > 300 {
            return Err(format!("`betas` has {} numbers (at most 300)", self.betas.len()));
        }
        let numbers = [
            ("global_orient", &self.global_orient[..]),
            ("body_pose", &self.body_pose[..]),
            ("betas", &self.betas[..]),
            ("camera", &self.camera[..]),
            ("fov_y", &[self.fov_y][..]),
            ("framing.centre", &self.framing.centre[..]),
            ("framing.side", &[self.framing.side][..]),
        ];
        for (name, v) in numbers {
            if let Some(i) = v.iter().position(|x| !x.is_finite()) {
                return Err(format!("`{name}[{i}]` is not a finite number"));
            }
        }
        if !(self.fov_y > 0.0 && self.fov_y < std::f32::consts::PI) {
            return Err(format!("`fov_y` {} is not in (0, π)", self.fov_y));
        }
        let det = self.world_to_camera().determinant();
        if !det.is_finite() || det.abs() < 1e-6 {
            return Err("`camera` is not an invertible matrix".into());
        }
        let (w, h) = (self.framing.photo_width, self.framing.photo_height);
        if w == 0 || h == 0 || (w as u64) * (h as u64) > MAX_PHOTO_PIXELS {
            return Err(format!("`framing` is of a {w}×{h} photo (1 pixel … {} MP)", MAX_PHOTO_PIXELS / 1_000_000));
        }
        if self.framing.side <= 0.0 {
            return Err(format!("`framing.side` {} is not positive", self.framing.side));
        }
        super::turn::check(self.rotation).map_err(|e| e.to_string())?;
        Ok(())
    }

    /// The fitted body as body parameters (no translation).
    pub fn body_params(&self) -> BodyParams {
        BodyParams::from_split(&self.global_orient, &self.body_pose, &self.betas)
    }

    /// This fit with another pose and shape (the app's pose controls after the fit), seen
    /// through the same camera: the start of a corrected re-fit ([`super::correction`]).
    pub fn with_params(&self, params: &BodyParams) -> Self {
        let theta = params.theta();
        Self {
            global_orient: [theta[0], theta[1], theta[2]],
            body_pose: theta[3..].to_vec(),
            betas: params.betas.clone(),
            ..self.clone()
        }
    }

    /// World → camera.
    pub fn world_to_camera(&self) -> Mat4 {
        crate::render::camera::from_row_major(&self.camera)
    }

    /// World → OpenGL clip space of the whole photo: the fit's camera on its square crop,
    /// the crop placed in the photo by the framing (for overlays and masks in the photo).
    pub fn photo_view_proj(&self) -> Mat4 {
        let proj = Mat4::perspective_rh_gl(self.fov_y, 1.0, NEAR, FAR);
        self.framing.crop_to_photo_clip() * proj * self.world_to_camera()
    }

    /// World → OpenGL clip space of the photo as taken, before it was turned for the
    /// detection: [`Self::photo_view_proj`] with the turn undone (the camera rolled about its
    /// axis by `rotation`).
    pub fn original_photo_view_proj(&self) -> Mat4 {
        super::turn::clip_to_original(self.rotation) * self.photo_view_proj()
    }
}

/// Split a global orientation into a turn about +y (moved into the camera) and an upright
/// remainder: with `Y` the turn, posed points satisfy `p(Y·R') = Y·p(R') + (I − Y)·j₀`
/// (SMPL rotates about the root joint `j₀`), so the camera becomes `M · [Y | (I − Y) j₀]`.
pub fn upright(orient: Vec3, root: Vec3, world_to_camera: Mat4) -> (Vec3, Mat4) {
    let r = axis_angle_to_matrix(orient);
    let fwd = r * Vec3::Z;
    let yaw = fwd.x.atan2(fwd.z);
    let y = Mat3::from_rotation_y(yaw);
    let rest = Quat::from_mat3(&(y.transpose() * r)).normalize().to_scaled_axis();
    let turn = Mat4::from_translation(root) * Mat4::from_mat3(y) * Mat4::from_translation(-root);
    (rest, world_to_camera * turn)
}
