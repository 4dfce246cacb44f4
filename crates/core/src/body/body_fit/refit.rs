//! The body fit refined on a clothed outline: a fit made with the bare body against a
//! clothed person's mask comes out broad and off (the silhouette stage stretches the bare body
//! towards the clothes and hair), so once a generated avatar of the person exists, its pose,
//! shape and camera are fitted again with the avatar's own outline against the same mask,
//! starting from the fit and held near its pose ([`refit_on_outline`]).

use std::sync::Arc;

use burn::tensor::Device;
use glam::{Mat3, Vec3};

use super::error::FitError;
use super::fit::{BodyFit, BodyFitter, FitInput, FitState};
use crate::body::body_model::BodyModel;
use crate::body::skinning::{axis_angle_to_matrix, pose_body, BodyParams};
use crate::render::camera::reference_fov_y;
use crate::util::cooperative::checkpoint;

/// A mesh that follows the body: points at `rest` (rest pose, β = 0), each following body
/// vertex `body_vertex` (its shape directions and skin weights), with `faces`. A rigged
/// avatar is one (`RiggedAvatar::outline_mesh`); the body itself is another.
#[derive(Clone, Debug)]
pub struct OutlineMesh {
    pub rest: Vec<Vec3>,
    pub body_vertex: Vec<u32>,
    pub faces: Vec<[u32; 3]>,
}

/// How the refinement runs.
#[derive(Clone, Debug, PartialEq)]
pub struct RefitOptions {
    /// Adam steps of the silhouette stage on the outline.
    pub steps: usize,
    /// Pull of θ (all 24 joints) towards the fit's, per radian².
    pub hold_pose: f32,
    /// Keep β at the fit's.
    pub hold_shape: bool,
}

impl Default for RefitOptions {
    fn default() -> Self {
        Self { steps: 60, hold_pose: 5.0, hold_shape: false }
    }
}

impl FitInput {
    /// What `fit` was fitted to, as far as `fit.json` keeps it (the landmarks where they
    /// were seen, not the detector's 3D reading), with the person `mask` of the fit's crop at
    /// its options' `silhouette_size`².
    pub fn from_fit(fit: &BodyFit, mask: Vec<f32>) -> Self {
        let points = fit.keypoints.iter().map(|k| (fit.framing.to_ndc(k.observed), k.visibility)).collect();
        Self {
            framing: fit.framing,
            points,
            world: None,
            mask: Some(mask),
            rotation: fit.rotation,
            off_person: Vec::new(),
        }
    }
}

impl FitState {
    /// The fit's own parameters of a finished fit: the turn about the vertical that
    /// [`super::fit::upright`] moved into the camera taken back into θ₀, the camera a translation
    /// again. Fails on a camera that is not such a turn and translation.
    pub fn from_fit(fit: &BodyFit, model: &BodyModel) -> Result<Self, FitError> {
        let m = fit.world_to_camera();
        let y = Mat3::from_mat4(m);
        let yaw = (-y.x_axis.z).atan2(y.x_axis.x);
        if (y - Mat3::from_rotation_y(yaw)).to_cols_array().iter().any(|v| v.abs() > 1e-3) {
            return Err(FitError::Refit("the fit's camera is not a turn about the vertical".into()));
        }
        let mut params = fit.body_params();
        let r = y * axis_angle_to_matrix(params.pose[0]);
        params.pose[0] = glam::Quat::from_mat3(&r).normalize().to_scaled_axis();
        // World → camera was T(t) · T(j₀) · Y · T(−j₀): its translation is t + j₀ − Y j₀.
        let root =
            pose_body(model, &BodyParams { pose: Default::default(), ..params.clone() }).kinematics.rest_joints[0];
        let camera = m.w_axis.truncate() - root + y * root;
        Ok(Self { params, camera })
    }
}

/// A square `[from², 1]` mask box-sampled to `to²`.
fn resize_square(values: &[f32], from: usize, to: usize) -> Vec<f32> {
    if from == to {
        return values.to_vec();
    }
    const SS: usize = 4;
    let mut out = vec![0.0f32; to * to];
    for (k, o) in out.iter_mut().enumerate() {
        let (x, y) = (k % to, k / to);
        let mut sum = 0.0;
        for s in 0..SS * SS {
            let u = ((x as f32 + ((s % SS) as f32 + 0.5) / SS as f32) / to as f32 * from as f32) as usize;
            let v = ((y as f32 + ((s / SS) as f32 + 0.5) / SS as f32) / to as f32 * from as f32) as usize;
            sum += values[v.min(from - 1) * from + u.min(from - 1)];
        }
        *o = sum / (SS * SS) as f32;
    }
    out
}

/// `fit` refined with `outline` in place of the bare body: its silhouette at the fit's camera
/// against the person `mask` (the fit's crop, `size`² with `size` ≥ 16), the fit's landmarks
/// and priors as in its last stage, θ held near the fit's. `device` is an autodiff device.
pub async fn refit_on_outline(
    model: Arc<BodyModel>,
    fit: &BodyFit,
    mask: &[f32],
    size: usize,
    outline: &OutlineMesh,
    options: &RefitOptions,
    device: &Device,
) -> Result<BodyFit, FitError> {
    let mut fitter = outline_refitter(model, fit, mask, size, outline, options, device).await?;
    fitter.run().await?;
    finish_outline_refit(&fitter, fit).await
}

/// The fitter of [`refit_on_outline`], set up and not yet stepped: the caller steps it
/// (`BodyFitter::step`, e.g. in slices on a page) and ends with [`finish_outline_refit`].
/// Checkpoints (`cooperative`) between the parts of the set-up, which on a page runs on the UI
/// thread (the outline's edges and rigged vertex set are tens of milliseconds there).
pub async fn outline_refitter(
    model: Arc<BodyModel>,
    fit: &BodyFit,
    mask: &[f32],
    size: usize,
    outline: &OutlineMesh,
    options: &RefitOptions,
    device: &Device,
) -> Result<BodyFitter, FitError> {
    if size < 16 || mask.len() != size * size {
        return Err(FitError::MaskSize { got: mask.len(), width: size, height: size });
    }
    if outline.rest.len() != outline.body_vertex.len()
        || outline.body_vertex.iter().any(|&b| b as usize >= model.v_template.len())
        || outline.faces.iter().flatten().any(|&i| i as usize >= outline.rest.len())
    {
        return Err(FitError::Refit("the outline mesh's vertices, body vertices or faces do not match".into()));
    }
    if (fit.fov_y - reference_fov_y()).abs() > 1e-3 {
        return Err(FitError::Refit("the fit was not made with the reference camera".into()));
    }
    let fit_options = fit.options.clone();
    let state = FitState::from_fit(fit, &model)?;
    let input = FitInput::from_fit(fit, resize_square(mask, size, fit_options.silhouette_size));
    checkpoint().await;
    let mut fitter = BodyFitter::new(model, input, fit_options, device)?;
    fitter.warm_start(&state, options.hold_pose);
    checkpoint().await;
    fitter.refine_on_outline(
        &outline.rest,
        &outline.body_vertex,
        outline.faces.clone(),
        options.steps,
        options.hold_shape,
    );
    Ok(fitter)
}

/// The refined fit of an [`outline_refitter`] that has run, with what `fit` (the fit it
/// refines) was fitted to.
pub async fn finish_outline_refit(fitter: &BodyFitter, fit: &BodyFit) -> Result<BodyFit, FitError> {
    let mut out = fitter.finish().await?;
    // The fit's residuals are the bare body's; what it was fitted to stays the fit's.
    out.missing.clone_from(&fit.missing);
    out.off_person.clone_from(&fit.off_person);
    out.relabelled.clone_from(&fit.relabelled);
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::body::body_fit::fit::FitOptions;
    use crate::body::body_fit::synthetic::{detect, unseen_poses, UNSEEN_POSE_CAMERAS};
    use crate::generator::readback::block_on_ready;
    use crate::util::rng::Rng;

    /// A finished fit's camera holds the body's turn ([`super::super::fit::upright`]);
    /// [`FitState::from_fit`] takes it back: the same posed points through the same camera as
    /// the fitter's own parameters, and its input the same landmarks.
    #[test]
    fn a_finished_fit_gives_back_the_fitters_parameters() {
        let model = Arc::new(BodyModel::default_body().unwrap());
        #[allow(deprecated)]
        let dev = Device::ndarray().autodiff();
        let (_, truth) = unseen_poses().into_iter().find(|(n, _)| *n == "kick").unwrap();
        let cam = UNSEEN_POSE_CAMERAS[2].camera();
        let det = detect(&model, &truth, cam.world_to_camera(), 256, 1.0, 0.01, &mut Rng::new(3, 1)).unwrap();
        let opts = FitOptions { iterations: [10, 10, 0], ..FitOptions::default() };
        let input = FitInput::from_detection(&det.result, 256, 256, None, &model, &opts).unwrap();
        let mut fitter = BodyFitter::new(model.clone(), input.clone(), opts, &dev).unwrap();
        let (state, fit) = block_on_ready(async {
            fitter.run().await?;
            Ok::<_, FitError>((fitter.state().await?, fitter.finish().await?))
        })
        .unwrap();
        // A turn, which the fit moved into the camera.
        assert!(Mat3::from_mat4(fit.world_to_camera()).x_axis.x < 0.999, "{:?}", fit.camera);
        let back = FitState::from_fit(&fit, &model).unwrap();
        let posed = |s: &FitState| {
            let p = pose_body(&model, &s.params);
            p.vertices.iter().step_by(53).map(|v| *v + s.camera).collect::<Vec<_>>()
        };
        for (a, b) in posed(&state).iter().zip(posed(&back)) {
            assert!((*a - b).length() < 1e-4, "{a} vs {b}");
        }
        let again = FitInput::from_fit(&fit, vec![0.0; 16]);
        for (a, b) in input.points.iter().zip(&again.points) {
            assert!((a.0[0] - b.0[0]).abs() < 1e-5 && (a.0[1] - b.0[1]).abs() < 1e-5 && a.1 == b.1, "{a:?} vs {b:?}");
        }
        // A camera that is not a turn about the vertical is refused.
        let mut tilted = fit.clone();
        tilted.camera = crate::render::camera::to_row_major(fit.world_to_camera() * glam::Mat4::from_rotation_x(0.3));
        assert!(matches!(FitState::from_fit(&tilted, &model), Err(FitError::Refit(_))));
    }
}
