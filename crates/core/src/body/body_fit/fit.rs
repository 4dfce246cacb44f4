//! The body fit: SMPLify-style optimisation (Bogo et al. 2016, in SPIN's staging) of the
//! global orientation, body pose θ, shape β and camera translation that explain a person's
//! landmarks and mask seen through the reference camera of a [`Framing`].
//!
//! Stages, each with a fresh Adam (SPIN restarts its optimiser per stage):
//! 1. **torso**: orientation and camera translation from the shoulders and hips;
//! 2. **body**: everything, all landmarks: Geman–McClure robust reprojection of the joints
//!    ([`super::landmarks::JOINT_LANDMARKS`]) and surface points ([`super::surface`]),
//!    SMPLify's angle prior on elbows and knees and an L2 on their sideways bend, a stiffer
//!    L2 on the collars ([`super::limits`]), L2 priors on θ and β (no SMPL GMM is redistributable), the world
//!    landmarks' bone directions (3D limb directions, weakly: they decide what a single image
//!    cannot, e.g. which arm is in front; a leg bone whose 3D direction disagrees with how
//!    foreshortened its 2D landmarks show it loses that weight, the bones below it with it,
//!    and is lifted from its 2D landmarks instead, [`super::input::leg_readings`]; a leg whose
//!    thigh is so misread starts at rest) and, where an elbow or knee
//!    is hidden, its limb's
//!    chord (shoulder → wrist, hip → ankle: a hand across the chest or before its own
//!    shoulder, which a side view cannot tell), and a symmetry prior for hidden limbs (a
//!    joint whose bone the detector did not see is pulled towards the mirror image of its
//!    seen counterpart's rotation);
//! 3. **silhouette** (with a mask): the body's mask rendered by the differentiable
//!    rasteriser ([`crate::render::diff::rasterize`]: coverage + antialias, so silhouette edges get
//!    gradients) against the person mask, squared error, on top of stage 2's terms.
//!
//! When exactly one wrist is seen, the detector may have given the seen hand the hidden
//! one's label (crossed arms from the side): both labellings are fitted through stage 2 and
//! the one whose landmarks the body explains better (the data term) goes on
//! ([`FitInput::hands_in_doubt`], [`BodyFit::relabelled`]).
//!
//! A re-fit from a pose a person corrected ([`BodyFitter::correct_from`]) holds the limbs
//! they moved far from the detector's landmarks ([`super::correction`]).
//!
//! The fit starts from [`super::init`] and is deterministic (no random numbers). It runs
//! step by step ([`BodyFitter::step`], async: the silhouette stage reads the posed vertices
//! back to rasterise, which a browser must await), so callers show progress and can cancel.
//! At the end the body's turn about the vertical is moved into the camera, so the body
//! faces +z upright as in the data and the camera orbits it ([`BodyFit::camera`]).
//!
//! Units: reprojection residuals are measured in pixels of a 256² crop (NDC × 128), the
//! weights of [`FitWeights`] are relative to one such squared pixel.

use crate::util::cooperative::checkpoint;
use std::sync::Arc;

use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor};
use glam::{Mat4, Vec3, Vec4};

use super::bones::misread_legs_at_rest;
use super::correction;
pub use super::error::FitError;
use super::init::{camera_translation, pose_from_image, pose_from_world, posed_joints};
pub use super::input::{FitInput, HAND_SWAP};
use super::landmarks::{JOINT_LANDMARKS, LANDMARK_NAMES, NUM_LANDMARKS, TORSO_LANDMARKS, VISIBLE};
use super::limits::{range_term, COLLARS, HINGES};
use super::metrics::{body_mask, mask_iou};
pub use super::options::{BoneForm, FitOptions, FitWeights};
pub use super::result::{upright, FitState};
pub use super::result::{BodyFit, FitKeypoint, FitResiduals, FitTarget, BODY_FIT_FORMAT};
use super::result::{FAR, NEAR};
use super::surface::{surface_landmarks, SurfaceLandmark};
use super::targets::{Observations, Targets};
use crate::body::body_model::{BodyModel, JOINT_NAMES, NUM_JOINTS};
use crate::body::skinning::BodyParams;
use crate::generator::optim::Adam;
use crate::generator::readback::read_f32;
use crate::render::camera::{reference_fov_y, to_row_major};
use crate::render::diff::body_model::{joint_index, PosedSkeleton, Skeleton, VertexSet};
use crate::render::diff::{matrix, rasterize as diff_raster};

/// Residuals are in pixels of a crop this wide.
const UNIT_PX: f32 = 128.0;

/// Progress of one step.
#[derive(Clone, Debug, PartialEq)]
pub struct FitProgress {
    /// 0 torso, 1 body, 2 silhouette.
    pub stage: usize,
    /// Steps done, over all stages, and their total.
    pub done: usize,
    pub total: usize,
    pub loss: f32,
}

pub const STAGE_NAMES: [&str; 3] = ["torso", "body", "silhouette"];

/// The fitted quantities as a module, so [`Adam`] updates them.
#[derive(Module, Debug)]
struct FitParams {
    orient: Param<Tensor<2>>,
    body_pose: Param<Tensor<2>>,
    betas: Param<Tensor<2>>,
    camera: Param<Tensor<2>>,
}

/// The silhouette stage's vertices, faces and the faces' edges.
type SilhouetteMesh = (VertexSet, Arc<Vec<[u32; 3]>>, Arc<diff_raster::MeshEdges>);

/// The fit, one Adam step at a time.
pub struct BodyFitter {
    model: Arc<BodyModel>,
    input: FitInput,
    options: FitOptions,
    device: Device,
    skeleton: Skeleton,
    surface: VertexSet,
    surface_marks: Vec<SurfaceLandmark>,
    /// The silhouette stage's mesh: the body's every vertex, its faces and their edges (for
    /// the silhouette's pixel pairs), or an outline set by [`BodyFitter::refine_on_outline`].
    mesh: Option<SilhouetteMesh>,
    /// The landmarks, bone directions and symmetry rows the terms compare the body with.
    obs: Observations,
    params: FitParams,
    adam: Adam,
    stage: usize,
    step_in_stage: usize,
    done: usize,
    stage_loss: [Option<f32>; 3],
    /// The fit of the other hand labelling ([`FitInput::hands_in_doubt`]), stepped alongside
    /// through the torso and body stages; the one with the lower body-stage loss goes on.
    alternative: Option<Box<BodyFitter>>,
    /// This fit's input has the hands swapped.
    hands_swapped: bool,
    /// β held at its value (a video's shape, fitted once for the clip).
    shape_held: bool,
    /// A pull of θ `[24, 3]` towards a neighbouring frame's, and its weight (radians²).
    temporal: Option<(Tensor<2>, f32)>,
    /// Limbs a person corrected ([`BodyFitter::correct_from`]): the rows of θ₁…θ₂₃ held and
    /// the rotations they are held at `[N, 3]`.
    held: Option<(Tensor<1, burn::tensor::Int>, Tensor<2>)>,
    /// Those limbs, whose landmarks the fit leaves out.
    held_limbs: Vec<correction::Limb>,
}

impl BodyFitter {
    /// Prepare the fit on `device` (an autodiff device: `Device::autodiff()`).
    ///
    /// When the detector's hand sides are in doubt ([`FitInput::hands_in_doubt`]) both
    /// labellings are fitted through the body stage (twice the work there) and the one whose
    /// body-stage loss is lower goes on to the silhouette stage, as SMPLify fits both
    /// orientations of an ambiguous torso and keeps the better.
    pub fn new(model: Arc<BodyModel>, input: FitInput, options: FitOptions, device: &Device) -> Result<Self, FitError> {
        let alternative = if input.hands_in_doubt() {
            let mut alt = Self::single(model.clone(), input.with_hands_swapped(), options.clone(), device)?;
            alt.hands_swapped = true;
            Some(Box::new(alt))
        } else {
            None
        };
        let mut fitter = Self::single(model, input, options, device)?;
        fitter.alternative = alternative;
        Ok(fitter)
    }

    fn single(model: Arc<BodyModel>, input: FitInput, options: FitOptions, device: &Device) -> Result<Self, FitError> {
        if input.points.len() != NUM_LANDMARKS {
            return Err(FitError::TooFew(format!("{} landmarks, expected {NUM_LANDMARKS}", input.points.len())));
        }
        let seen = |l: usize| input.points[l].1 >= VISIBLE;
        let torso_seen = TORSO_LANDMARKS.iter().filter(|l| seen(**l)).count();
        if torso_seen < 2 {
            return Err(FitError::TooFew(
                "fewer than two of the shoulders and hips are visible; the torso cannot be placed".into(),
            ));
        }
        let skeleton = Skeleton::new(&model, options.num_betas, device);
        let surface_marks = surface_landmarks(&model)?;
        let surface_ids: Vec<u32> = surface_marks.iter().map(|s| s.vertex).collect();
        let surface = VertexSet::new(&model, &surface_ids, &skeleton, device);

        // Initial pose and camera.
        let betas0 = vec![0.0f32; skeleton.num_betas];
        let init = match &input.world {
            Some(world) => {
                let vis: Vec<f32> = input.points.iter().map(|p| p.1).collect();
                pose_from_world(&model, world, &vis, &betas0)
            }
            None => pose_from_image(input.points[11].0, input.points[12].0, &betas0),
        };
        let cam = initial_camera(&model, &input, &init);
        let (init, cam) = match misread_legs_at_rest(&model, &input, &init, cam) {
            Some(rest) => {
                let cam = initial_camera(&model, &input, &rest);
                (rest, cam)
            }
            None => (init, cam),
        };

        let obs =
            Observations::new(&model, &input, &surface_marks, &init, cam, options.weights.bones_lifted, &[], device);
        let theta: Vec<f32> = init.pose[1..].iter().flat_map(|v| v.to_array()).collect();
        let nb = skeleton.num_betas.max(1);
        let params = FitParams {
            orient: Param::from_tensor(matrix(init.pose[0].to_array().to_vec(), 1, 3, device).require_grad()),
            body_pose: Param::from_tensor(matrix(theta, NUM_JOINTS - 1, 3, device).require_grad()),
            betas: Param::from_tensor(matrix(vec![0.0; nb], 1, nb, device).require_grad()),
            camera: Param::from_tensor(matrix(cam.to_array().to_vec(), 1, 3, device).require_grad()),
        };
        Ok(Self {
            model,
            input,
            options,
            device: device.clone(),
            skeleton,
            surface,
            surface_marks,
            mesh: None,
            obs,
            params,
            adam: Adam::new(0.9, 0.999, 1e-8),
            stage: 0,
            step_in_stage: 0,
            done: 0,
            stage_loss: [None; 3],
            alternative: None,
            hands_swapped: false,
            shape_held: false,
            temporal: None,
            held: None,
            held_limbs: Vec::new(),
        })
    }

    /// Start again from `start` (the user's corrected pose and shape, e.g. the app's pose
    /// controls after a first fit): its θ and β become the parameters, the camera is placed
    /// on the torso again, and the stages run from the first.
    pub fn start_from(&mut self, start: &BodyParams) {
        let mut init = start.clone();
        init.betas.resize(self.skeleton.num_betas, 0.0);
        let cam = initial_camera(&self.model, &self.input, &init);
        self.restart(&init, cam);
    }

    /// Start again from `corrected`: this photo's fit with the pose and shape a person
    /// corrected (the app's pose controls after a fit; `trainer fit-pose --start`), seen through
    /// its own camera and with its hand labelling. Every limb it puts far from the detector's
    /// landmarks is the person's correction ([`correction::corrected_limbs`]): that limb's
    /// landmarks leave the fit and its joints are held at the corrected rotations. Returns the
    /// limbs held (also in [`BodyFit::held`]).
    pub fn correct_from(&mut self, corrected: &BodyFit) -> Vec<&'static str> {
        let state = correction::fit_state(corrected, &self.model);
        if corrected.relabelled.is_empty() == self.hands_swapped {
            self.input = self.input.with_hands_swapped();
            self.hands_swapped = !self.hands_swapped;
        }
        let limbs = correction::corrected_limbs(&self.model, &state, &self.input);
        let mut kept = self.input.clone();
        for l in limbs.iter().flat_map(|limb| limb.landmarks) {
            kept.points[*l].1 = 0.0;
        }
        let joints: Vec<usize> = limbs.iter().flat_map(|limb| limb.joints).collect();
        let (init, cam, lifted) = (&state.params, state.camera, self.options.weights.bones_lifted);
        let dev = self.device.clone();
        self.obs = Observations::new(&self.model, &kept, &self.surface_marks, init, cam, lifted, &joints, &dev);
        self.restart(init, cam);
        let dev = &dev;
        let rows: Vec<usize> = joints.iter().map(|j| j - 1).collect();
        let target = joints.iter().flat_map(|j| init.pose[*j].to_array()).collect();
        self.held = (!joints.is_empty()).then(|| (joint_index(&rows, dev), matrix(target, rows.len(), 3, dev)));
        self.held_limbs = limbs;
        self.held_limbs.iter().map(|l| l.name).collect()
    }

    /// Continue from a neighbouring frame's parameters as they are (camera included), with
    /// one hand labelling (the neighbour's says which arm is which), β held at `state`'s, and
    /// θ pulled towards `state`'s with `temporal` (0: no pull).
    pub fn warm_start(&mut self, state: &FitState, temporal: f32) {
        self.restart(&state.params, state.camera);
        self.shape_held = true;
        let all: Vec<f32> = state.params.pose.iter().flat_map(|v| v.to_array()).collect();
        self.temporal = (temporal > 0.0).then(|| (matrix(all, NUM_JOINTS, 3, &self.device), temporal));
    }

    /// `params` and `camera` become the parameters, and the stages run again from the first
    /// with one hand labelling (a given pose says which arm is which).
    fn restart(&mut self, params: &BodyParams, camera: Vec3) {
        let dev = &self.device;
        let nb = self.skeleton.num_betas.max(1);
        let theta: Vec<f32> = params.pose[1..].iter().flat_map(|v| v.to_array()).collect();
        let mut betas = params.betas.clone();
        betas.resize(nb, 0.0);
        self.params = FitParams {
            orient: Param::from_tensor(matrix(params.pose[0].to_array().to_vec(), 1, 3, dev).require_grad()),
            body_pose: Param::from_tensor(matrix(theta, NUM_JOINTS - 1, 3, dev).require_grad()),
            betas: Param::from_tensor(matrix(betas, 1, nb, dev).require_grad()),
            camera: Param::from_tensor(matrix(camera.to_array().to_vec(), 1, 3, dev).require_grad()),
        };
        self.adam = Adam::new(0.9, 0.999, 1e-8);
        (self.stage, self.step_in_stage, self.done, self.stage_loss) = (0, 0, 0, [None; 3]);
        self.alternative = None;
        (self.held, self.held_limbs) = (None, Vec::new());
    }

    /// Hold β at `betas` from now on (the clip's shape): the fit moves θ and the camera only.
    pub fn hold_shape(&mut self, betas: &[f32]) {
        let nb = self.skeleton.num_betas.max(1);
        let mut b = betas.to_vec();
        b.resize(nb, 0.0);
        self.params.betas = Param::from_tensor(matrix(b, 1, nb, &self.device).require_grad());
        self.shape_held = true;
        if let Some(alt) = self.alternative.as_mut() {
            alt.hold_shape(betas);
        }
    }

    /// From here on, the silhouette stage alone for `steps` steps on another mesh than the
    /// body: points at `rest` (rest pose, β = 0) following body vertices `body_vertex`, with
    /// `faces` (a generated avatar's clothed outline; [`super::refit`]). Every person pixel
    /// it leaves uncovered costs fully; β is held when `hold_shape`.
    pub fn refine_on_outline(
        &mut self,
        rest: &[Vec3],
        body_vertex: &[u32],
        faces: Vec<[u32; 3]>,
        steps: usize,
        hold_shape: bool,
    ) {
        let vertices = VertexSet::rigged(&self.model, rest, body_vertex, &self.skeleton, &self.device);
        let faces = Arc::new(faces);
        self.mesh = Some((vertices, faces.clone(), Arc::new(diff_raster::MeshEdges::new(&faces))));
        self.options.iterations = [0, 0, steps];
        self.options.weights.silhouette_uncovered = 1.0;
        self.shape_held = hold_shape;
        (self.stage, self.step_in_stage, self.done) = (2, 0, 0);
        self.adam = Adam::new(0.9, 0.999, 1e-8);
    }

    /// The current parameters.
    pub async fn state(&self) -> Result<FitState, FitError> {
        let orient = read_f32(self.params.orient.val()).await?;
        let body_pose = read_f32(self.params.body_pose.val()).await?;
        let betas = read_f32(self.params.betas.val()).await?;
        let cam = read_f32(self.params.camera.val()).await?;
        let betas = betas[..self.skeleton.num_betas].to_vec();
        Ok(FitState { params: BodyParams::from_split(&orient, &body_pose, &betas), camera: Vec3::from_slice(&cam) })
    }

    /// Steps of all stages (the silhouette stage only with a mask).
    pub fn total_steps(&self) -> usize {
        let [a, b, c] = self.options.iterations;
        a + b + if self.input.mask.is_some() { c } else { 0 }
    }

    fn stage_len(&self, stage: usize) -> usize {
        match stage {
            2 if self.input.mask.is_none() => 0,
            s => self.options.iterations.get(s).copied().unwrap_or(0),
        }
    }

    /// One Adam step; `None` when the fit is complete.
    pub async fn step(&mut self) -> Result<Option<FitProgress>, FitError> {
        while self.stage < 3 && self.step_in_stage >= self.stage_len(self.stage) {
            self.stage += 1;
            self.step_in_stage = 0;
            self.adam = Adam::new(0.9, 0.999, 1e-8);
            if self.stage == 2 {
                self.keep_better_hypothesis().await?;
            }
        }
        if self.stage >= 3 {
            return Ok(None);
        }
        // Checkpoints (`cooperative`) between the parts of a step: a silhouette step is ~100 ms
        // of work in the browser, whose UI thread it runs on.
        let loss = self.loss(self.stage).await?;
        let value = read_f32(loss.clone()).await?.first().copied().unwrap_or(f32::NAN);
        checkpoint().await;
        let grads = loss.backward();
        checkpoint().await;
        // A module clone shares its tensors; Adam returns the updated parameters.
        self.params = self.adam.step(self.options.learning_rate, self.params.clone(), &grads);
        self.stage_loss[self.stage] = Some(value);
        self.step_in_stage += 1;
        self.done += 1;
        if let (Some(alt), true) = (self.alternative.as_mut(), self.stage < 2) {
            // Boxed: an async fn cannot await itself unboxed. The alternative has none of its own.
            Box::pin(alt.step()).await?;
        }
        Ok(Some(FitProgress { stage: self.stage, done: self.done, total: self.total_steps(), loss: value }))
    }

    /// At the end of the body stage: go on with the hand labelling whose landmarks the body
    /// explains better (the data term alone: the priors' weights follow the visibilities,
    /// which the labellings swap, so their totals are not comparable).
    async fn keep_better_hypothesis(&mut self) -> Result<(), FitError> {
        // The alternative took a step with every step of this fit, so its body stage is done.
        let Some(mut alt) = self.alternative.take() else { return Ok(()) };
        // Checkpoints between the two: in the browser this runs on the UI thread, before the
        // first silhouette step.
        let mine = self.current_data_term().await?;
        checkpoint().await;
        let other = alt.current_data_term().await?;
        checkpoint().await;
        if other < mine {
            let (stage, step_in_stage, done) = (self.stage, self.step_in_stage, self.done);
            std::mem::swap(self, &mut *alt);
            (self.stage, self.step_in_stage, self.done) = (stage, step_in_stage, done);
            self.adam = Adam::new(0.9, 0.999, 1e-8);
        }
        Ok(())
    }

    /// The data term of the current parameters (no gradients kept).
    async fn current_data_term(&self) -> Result<f32, FitError> {
        let (theta, betas) = self.theta(1);
        let (theta, betas) = (theta.detach(), betas.detach());
        let posed = self.skeleton.forward(theta, &betas);
        let value = self.data_term(&posed, &betas, false).await;
        Ok(read_f32(value).await?.first().copied().unwrap_or(f32::INFINITY))
    }

    /// θ `[24, 3]` and β of the current parameters; in the torso stage only the orientation
    /// and camera carry gradients.
    fn theta(&self, stage: usize) -> (Tensor<2>, Tensor<2>) {
        let (pose, betas) = if stage == 0 {
            (self.params.body_pose.val().detach(), self.params.betas.val().detach())
        } else {
            (self.params.body_pose.val(), self.params.betas.val())
        };
        let betas = if self.shape_held { betas.detach() } else { betas };
        (Tensor::cat(vec![self.params.orient.val(), pose], 0), betas)
    }

    /// World points `[N, 3]` → NDC `[N, 2]` through the fit's camera (translation only).
    fn project(&self, points: Tensor<2>) -> Tensor<2> {
        let f = 1.0 / (reference_fov_y() / 2.0).tan();
        let c = points + self.params.camera.val();
        let depth = c.clone().narrow(1, 2, 1).neg().clamp_min(NEAR);
        c.narrow(1, 0, 2) * f / depth
    }

    /// Robust reprojection: Σ w·ρ(‖π(X) − x‖²) over rows, ρ Geman–McClure.
    fn reprojection(&self, ndc: Tensor<2>, t: &Targets, torso_only: bool) -> Tensor<1> {
        let sigma2 = self.options.weights.robust_sigma.powi(2);
        let e = (ndc - t.observed.clone()) * UNIT_PX;
        let e2 = (e.clone() * e).sum_dim(1);
        let rho = e2.clone() * sigma2 / (e2 + sigma2);
        let w = if torso_only { t.torso_weight.clone() } else { t.weight.clone() };
        (rho * w).sum().reshape([1])
    }

    /// The data term: robust reprojection of the joints (torso stage: the torso's only) and,
    /// after the torso stage, the surface points, per unit of landmark weight.
    async fn data_term(&self, posed: &PosedSkeleton, betas: &Tensor<2>, torso: bool) -> Tensor<1> {
        let joints = posed.joints.clone().select(0, joint_index(&self.obs.joint_ids, &self.device));
        let norm =
            if torso { self.obs.joints.torso_sum } else { self.obs.joints.weight_sum + self.obs.points.weight_sum };
        let mut loss = self.reprojection(self.project(joints), &self.obs.joints, torso);
        if !torso {
            let surface = self.surface.pose(posed, betas, &self.skeleton);
            loss = loss + self.reprojection(self.project(surface), &self.obs.points, false);
            checkpoint().await;
        }
        loss / norm.max(1e-6)
    }

    async fn loss(&mut self, stage: usize) -> Result<Tensor<1>, FitError> {
        let wts = self.options.weights.clone();
        let (theta, betas) = self.theta(stage);
        let posed = self.skeleton.forward(theta.clone(), &betas);
        let dev = self.device.clone();
        let torso = stage == 0;
        let mut loss = self.data_term(&posed, &betas, torso).await;
        if torso {
            return Ok(loss);
        }
        // Priors.
        let pose = self.params.body_pose.val();
        loss = loss + (pose.clone() * pose.clone()).sum().reshape([1]) * wts.pose;
        if wts.collar > 0.0 {
            let rows: Vec<usize> = COLLARS.iter().map(|j| j - 1).collect();
            let c = pose.clone().select(0, joint_index(&rows, &dev));
            loss = loss + (c.clone() * c).sum().reshape([1]) * wts.collar;
        }
        for h in HINGES {
            let a = pose.clone().narrow(0, h.joint - 1, 1).narrow(1, h.axis, 1).reshape([1]);
            let e = (a * -h.bend).exp();
            loss = loss + e.clone() * e * wts.hinge;
            let side = pose.clone().narrow(0, h.joint - 1, 1).narrow(1, h.side, 1).reshape([1]);
            loss = loss + side.clone() * side * wts.hinge_side;
        }
        if wts.ranges > 0.0 {
            loss = loss + range_term(pose.clone()) * wts.ranges;
        }
        if !self.shape_held {
            let b = self.params.betas.val();
            loss = loss + (b.clone() * b).sum().reshape([1]) * wts.betas;
        }
        if let Some((from, to, dirs, w)) = &self.obs.bones {
            let a = posed.joints.clone().select(0, joint_index(from, &dev));
            let c = posed.joints.clone().select(0, joint_index(to, &dev));
            let d = c - a;
            let len = (d.clone() * d.clone()).sum_dim(1).sqrt().clamp_min(1e-6);
            let unit = d / len;
            let term = match wts.bones_form {
                BoneForm::Direction => {
                    let diff = unit - dirs.clone();
                    (diff.clone() * diff).sum_dim(1)
                }
                BoneForm::DepthFloor => {
                    let detected = dirs.clone().narrow(1, 2, 1);
                    let side = detected.clone().sign();
                    let short = (detected * side.clone() - unit.narrow(1, 2, 1) * side).clamp_min(0.0);
                    short.clone() * short
                }
            };
            loss = loss + (term * w.clone()).sum().reshape([1]) * wts.bones;
        }
        if let (Some((hidden, seen, w)), true) = (&self.obs.symmetry, wts.symmetry > 0.0) {
            // The counterpart is detached: the seen limb is not pulled towards the hidden one.
            // Mirroring in the body's sagittal plane negates an axis-angle's y and z.
            let flip = matrix(vec![1.0, -1.0, -1.0], 1, 3, &dev);
            let target = pose.clone().select(0, seen.clone()).detach() * flip;
            let d = pose.clone().select(0, hidden.clone()) - target;
            loss = loss + ((d.clone() * d).sum_dim(1) * w.clone()).sum().reshape([1]) * wts.symmetry;
        }
        if let Some((rows, held)) = &self.held {
            let d = pose.clone().select(0, rows.clone()) - held.clone();
            loss = loss + (d.clone() * d).sum().reshape([1]) * correction::HOLD;
        }
        if let Some((previous, w)) = &self.temporal {
            let d = theta.clone() - previous.clone();
            loss = loss + (d.clone() * d).sum().reshape([1]) * *w;
        }
        if stage == 2 {
            if let Some(mask) = self.input.mask.clone() {
                loss = loss + self.silhouette(&posed, &betas, &mask).await? * wts.silhouette;
            }
        }
        Ok(loss)
    }

    /// Σ (rendered mask − person mask)² over the crop, in pixels of a 256² crop.
    async fn silhouette(
        &mut self,
        posed: &crate::render::diff::body_model::PosedSkeleton,
        betas: &Tensor<2>,
        mask: &[f32],
    ) -> Result<Tensor<1>, FitError> {
        let size = self.options.silhouette_size;
        let (model, skeleton, device) = (&self.model, &self.skeleton, &self.device);
        let (all, faces, edges) = self
            .mesh
            .get_or_insert_with(|| {
                let faces = Arc::new(model.faces.clone());
                (VertexSet::all(model, skeleton, device), faces.clone(), Arc::new(diff_raster::MeshEdges::new(&faces)))
            })
            .clone();
        // Every vertex is posed for the rasterizer without a gradient; the gradient flows only
        // through the silhouette edges' vertices (`antialias`), posed again below with one:
        // the backward pass then covers ~2k vertices instead of 6890 (a 70 ms task in the
        // browser, whose UI thread a step holds).
        let still = crate::render::diff::body_model::PosedSkeleton {
            joints: posed.joints.clone().detach(),
            transforms: posed.transforms.clone().detach(),
        };
        let clip_all = self.clip(all.pose(&still, &betas.clone().detach(), &self.skeleton)).detach();
        let host = read_f32(clip_all).await?;
        checkpoint().await;
        let clip_host: Vec<Vec4> = host.chunks_exact(4).map(Vec4::from_slice).collect();
        let raster = crate::render::rasterize::rasterize(&clip_host, &faces, size, size);
        let cov = diff_raster::Coverage::new(&raster, &faces);
        checkpoint().await;
        let pairs = diff_raster::silhouette_pairs_of(&raster, &clip_host, &faces, &edges);
        checkpoint().await;
        let dev = &self.device;
        let image = if cov.is_empty() {
            Tensor::<2>::zeros([size * size, 1], dev)
        } else {
            diff_raster::compose(&cov, Tensor::<2>::ones([cov.len(), 1], dev), &[0.0], dev)
        };
        let (ids, pairs) = pairs.compact();
        let image = if ids.is_empty() {
            image
        } else {
            let clip = self.clip(all.select(&ids).pose(posed, betas, &self.skeleton));
            diff_raster::antialias(image, &pairs, clip, size, size, dev)
        };
        let target = matrix(mask.to_vec(), size * size, 1, dev);
        let d = image - target;
        // Body outside the person costs fully; person the body leaves uncovered (clothes,
        // hair) costs `silhouette_uncovered` of that.
        let outside = d.clone().clamp_min(0.0);
        let uncovered = d.clamp_max(0.0);
        let k = self.options.weights.silhouette_uncovered;
        let scale = (2.0 * UNIT_PX / size as f32).powi(2);
        Ok(((outside.clone() * outside).sum() + (uncovered.clone() * uncovered).sum() * k).reshape([1]) * scale)
    }

    /// Clip positions `[N, 4]` of world points through the fit's camera (OpenGL projection).
    fn clip(&self, world: Tensor<2>) -> Tensor<2> {
        let f = 1.0 / (reference_fov_y() / 2.0).tan();
        let c = world + self.params.camera.val();
        let z = c.clone().narrow(1, 2, 1);
        let a = (FAR + NEAR) / (NEAR - FAR);
        let b = 2.0 * FAR * NEAR / (NEAR - FAR);
        Tensor::cat(vec![c.clone().narrow(1, 0, 2) * f, z.clone() * a + b, z.neg()], 1)
    }

    /// Run every remaining step.
    pub async fn run(&mut self) -> Result<(), FitError> {
        while self.step().await?.is_some() {}
        Ok(())
    }

    /// The result (after [`BodyFitter::run`], or early, with the current parameters).
    pub async fn finish(&self) -> Result<BodyFit, FitError> {
        let orient = read_f32(self.params.orient.val()).await?;
        let body_pose = read_f32(self.params.body_pose.val()).await?;
        let betas = read_f32(self.params.betas.val()).await?;
        let cam = read_f32(self.params.camera.val()).await?;
        let betas = betas[..self.skeleton.num_betas].to_vec();
        let mut params = BodyParams::from_split(&orient, &body_pose, &betas);
        let t = Vec3::from_slice(&cam);
        let model = &self.model;
        let posed = crate::body::skinning::pose_body(model, &params);
        // World → camera of the fit: translation only.
        let world_to_camera = Mat4::from_translation(t);
        let framing = self.input.framing;
        let f = 1.0 / (reference_fov_y() / 2.0).tan();
        let to_photo = |p: Vec3| {
            let c = world_to_camera.transform_point3(p);
            let depth = (-c.z).max(NEAR);
            framing.to_photo([f * c.x / depth, f * c.y / depth])
        };
        let mut fitted: Vec<Option<[f32; 2]>> = vec![None; NUM_LANDMARKS];
        for m in JOINT_LANDMARKS {
            fitted[m.landmark] = Some(to_photo(posed.kinematics.posed_joints[m.joint]));
        }
        for s in &self.surface_marks {
            fitted[s.landmark] = Some(to_photo(posed.vertices[s.vertex as usize]));
        }
        let mut keypoints = Vec::with_capacity(NUM_LANDMARKS);
        let (mut err, mut wsum) = (0.0f32, 0.0f32);
        for (l, (ndc, vis)) in self.input.points.iter().enumerate() {
            let observed = framing.to_photo(*ndc);
            let held = self.held_limbs.iter().any(|limb| limb.landmarks.contains(&l));
            if let (Some(p), true) = (fitted[l], *vis >= VISIBLE && !held) {
                err += vis * ((p[0] - observed[0]).powi(2) + (p[1] - observed[1]).powi(2)).sqrt();
                wsum += vis;
            }
            keypoints.push(FitKeypoint {
                name: LANDMARK_NAMES[l].into(),
                observed,
                fitted: fitted[l],
                visibility: *vis,
            });
        }
        let ys: Vec<f32> = posed.vertices.iter().map(|v| to_photo(*v)[1]).collect();
        let height =
            ys.iter().copied().fold(f32::NEG_INFINITY, f32::max) - ys.iter().copied().fold(f32::INFINITY, f32::min);
        let mean_px = if wsum > 0.0 { err / wsum } else { f32::NAN };
        let mask_iou = self.input.mask.as_ref().map(|m| {
            let size = self.options.silhouette_size;
            let proj = Mat4::perspective_rh_gl(reference_fov_y(), 1.0, NEAR, FAR) * world_to_camera;
            let fitted = body_mask(&posed.vertices, &model.faces, proj, size);
            mask_iou(&fitted, m)
        });
        // Move the body's turn about the vertical into the camera.
        let (orient, camera) = upright(params.pose[0], posed.kinematics.rest_joints[0], world_to_camera);
        params.pose[0] = orient;
        let table = JOINT_LANDMARKS
            .iter()
            .map(|m| FitTarget {
                landmark: LANDMARK_NAMES[m.landmark].into(),
                joint: Some(JOINT_NAMES[m.joint].into()),
                vertex: None,
                weight: m.weight,
            })
            .chain(self.surface_marks.iter().map(|s| FitTarget {
                landmark: LANDMARK_NAMES[s.landmark].into(),
                joint: None,
                vertex: Some(s.vertex),
                weight: s.weight,
            }))
            .collect();
        let missing = self
            .input
            .points
            .iter()
            .enumerate()
            .filter(|(_, p)| p.1 < VISIBLE)
            .map(|(l, _)| LANDMARK_NAMES[l].to_string())
            .collect();
        let theta = params.theta();
        Ok(BodyFit {
            format: BODY_FIT_FORMAT.into(),
            global_orient: [theta[0], theta[1], theta[2]],
            body_pose: theta[3..].to_vec(),
            betas,
            camera: to_row_major(camera),
            fov_y: reference_fov_y(),
            framing,
            keypoints,
            residuals: FitResiduals {
                mean_px,
                relative_to_height: mean_px / height.max(1.0),
                mask_iou,
                stage_loss: self.stage_loss,
            },
            table,
            missing,
            off_person: self.input.off_person.iter().map(|&l| LANDMARK_NAMES[l].to_string()).collect(),
            relabelled: if self.hands_swapped {
                HAND_SWAP.iter().map(|(a, b)| format!("{}↔{}", LANDMARK_NAMES[*a], LANDMARK_NAMES[*b])).collect()
            } else {
                Vec::new()
            },
            held: self.held_limbs.iter().map(|l| l.name.to_string()).collect(),
            options: self.options.clone(),
            rotation: self.input.rotation,
        })
    }
}

/// The camera translation that puts the visible torso joints of the body in pose `init`
/// on their landmarks (the reference distance when fewer than two are seen).
fn initial_camera(model: &BodyModel, input: &FitInput, init: &BodyParams) -> Vec3 {
    let posed = posed_joints(model, init);
    let (tj, to): (Vec<Vec3>, Vec<([f32; 2], f32)>) = JOINT_LANDMARKS
        .iter()
        .filter(|m| TORSO_LANDMARKS.contains(&m.landmark) && input.points[m.landmark].1 >= VISIBLE)
        .map(|m| (posed[m.joint], (input.points[m.landmark].0, 1.0)))
        .unzip();
    camera_translation(&tj, &to).unwrap_or(Vec3::new(0.0, 0.185, -crate::render::camera::REFERENCE_RADIUS))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::body::body_fit::framing::Framing;
    use crate::body::body_fit::targets::mirror_rows;
    use crate::body::skinning::axis_angle_to_matrix;

    #[test]
    fn the_upright_split_keeps_every_posed_point_in_view() {
        let model = BodyModel::default_body().unwrap();
        let mut params = BodyParams::default();
        params.pose[0] = Vec3::new(0.2, 2.0, -0.1);
        params.pose[16] = Vec3::new(0.0, 0.0, -1.0);
        let m = Mat4::from_translation(Vec3::new(0.1, 0.2, -2.4));
        let before = crate::body::skinning::pose_body(&model, &params);
        let (orient, cam) = upright(params.pose[0], before.kinematics.rest_joints[0], m);
        let mut turned = params.clone();
        turned.pose[0] = orient;
        let after = crate::body::skinning::pose_body(&model, &turned);
        for (a, b) in before.vertices.iter().zip(&after.vertices).step_by(97) {
            let (pa, pb) = (m.transform_point3(*a), cam.transform_point3(*b));
            assert!((pa - pb).length() < 1e-4, "{pa} vs {pb}");
        }
        // Upright: the body's forward axis has no sideways component left.
        let fwd = axis_angle_to_matrix(orient) * Vec3::Z;
        assert!(fwd.x.abs() < 1e-5 && fwd.z > 0.0, "{fwd}");
        assert_eq!(mask_iou(&[1.0, 1.0, 0.0, 0.0], &[1.0, 0.0, 1.0, 0.0]), 1.0 / 3.0);
    }

    /// The symmetry term's target: an axis-angle with y and z negated turns the counterpart
    /// limb into the mirror image (x negated) of the original, bone by bone.
    #[test]
    fn negating_y_and_z_mirrors_a_limb_in_the_sagittal_plane() {
        let model = BodyModel::default_body().unwrap();
        let mut params = BodyParams::default();
        let flip = |v: Vec3| Vec3::new(v.x, -v.y, -v.z);
        for (j, r) in [
            (16, Vec3::new(0.4, -0.9, -1.1)),
            (18, Vec3::new(0.1, -1.5, 0.2)),
            (1, Vec3::new(-0.9, 0.3, 0.7)),
            (4, Vec3::new(1.2, 0.1, 0.0)),
        ] {
            params.pose[j] = r;
        }
        for (j, c) in [(16, 17), (18, 19), (1, 2), (4, 5)] {
            params.pose[c] = flip(params.pose[j]);
        }
        let p = crate::body::skinning::pose_body(&model, &params).kinematics.posed_joints;
        for (a, b, ca, cb) in [(16, 18, 17, 19), (18, 20, 19, 21), (1, 4, 2, 5), (4, 7, 5, 8)] {
            let (u, v) = ((p[b] - p[a]).normalize(), (p[cb] - p[ca]).normalize());
            let mirrored = Vec3::new(-v.x, v.y, v.z);
            assert!(u.angle_between(mirrored) < 2f32.to_radians(), "{a}→{b}: {u} vs mirrored {mirrored}");
            // The bone has a sideways part for the mirror to flip.
            assert!(u.x.abs() > 0.15, "{a}→{b}: {u}");
        }
    }

    #[test]
    fn hidden_limbs_get_mirror_rows_and_hand_doubt_swaps_both_hands() {
        let mut vis = [1.0f32; NUM_LANDMARKS];
        assert!(mirror_rows(|l| vis[l]).is_empty(), "every limb seen: no prior");
        vis[13] = 0.1; // left elbow hidden: the left shoulder's rotation mirrors the right's
        vis[15] = 0.3; // left wrist half hidden: the left elbow's, less
        let rows = mirror_rows(|l| vis[l]);
        assert_eq!(rows.len(), 2);
        assert_eq!((rows[0].0, rows[0].1), (16, 17));
        assert!((rows[0].2 - 0.8).abs() < 1e-6 && (rows[1].2 - 0.4).abs() < 1e-6, "{rows:?}");
        vis[14] = 0.2; // both elbows hidden: nothing to mirror from
        assert!(mirror_rows(|l| vis[l]).iter().all(|r| r.0 != 16 && r.0 != 17));

        let framing = Framing::from_landmarks(
            &(0..NUM_LANDMARKS)
                .map(|i| super::super::landmarks::Landmark {
                    x: 0.5,
                    y: 0.1 + 0.8 * i as f32 / 33.0,
                    z: 0.0,
                    visibility: 1.0,
                })
                .collect::<Vec<_>>(),
            512,
            512,
            &BodyModel::default_body().unwrap(),
        )
        .unwrap();
        vis[16] = 0.2;
        let points: Vec<([f32; 2], f32)> = (0..NUM_LANDMARKS).map(|i| ([i as f32, 0.0], vis[i])).collect();
        let world = Some((0..NUM_LANDMARKS).map(|i| Vec3::splat(i as f32)).collect());
        let input = FitInput { framing, points, world, mask: None, rotation: 0, off_person: Vec::new() };
        assert!(!input.hands_in_doubt(), "both wrists hidden");
        let mut input = input;
        input.points[16].1 = 0.9;
        assert!(input.hands_in_doubt());
        let swapped = input.with_hands_swapped();
        for (a, b) in HAND_SWAP {
            assert_eq!((swapped.points[a], swapped.points[b]), (input.points[b], input.points[a]));
            let w = swapped.world.as_ref().unwrap();
            assert_eq!((w[a].x, w[b].x), (b as f32, a as f32));
        }
        assert_eq!(swapped.points[13], input.points[13], "elbows keep their labels");
    }
}
