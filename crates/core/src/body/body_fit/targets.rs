//! What the fit's terms compare the body with, as tensors ([`Observations`]): the landmark
//! rows of the joints and surface points, the detector's 3D bone directions and the symmetry
//! rows of hidden limbs. Built once per fit, and again when a re-fit holds limbs a person
//! corrected ([`super::correction`]).

use burn::tensor::{Device, Int, Tensor};
use glam::Vec3;

use super::bones::{bone_rows, BONES};
use super::init::posed_joints;
use super::input::FitInput;
use super::landmarks::{JOINT_LANDMARKS, TORSO_LANDMARKS, VISIBLE};
use super::surface::SurfaceLandmark;
use crate::body::body_model::BodyModel;
use crate::body::skinning::BodyParams;
use crate::render::diff::body_model::joint_index;
use crate::render::diff::matrix;

/// Observations of one kind of body point (joints or surface vertices) as tensors.
pub(super) struct Targets {
    pub observed: Tensor<2>,
    /// Weight × visibility, `[N, 1]`; `torso` masks rows for stage 1.
    pub weight: Tensor<2>,
    pub torso_weight: Tensor<2>,
    pub weight_sum: f32,
    pub torso_sum: f32,
}

impl Targets {
    fn new(rows: &[(usize, f32)], input: &FitInput, device: &Device) -> Self {
        let n = rows.len();
        let mut obs = Vec::with_capacity(n * 2);
        let (mut w, mut tw) = (Vec::with_capacity(n), Vec::with_capacity(n));
        for &(l, weight) in rows {
            let (p, vis) = input.points[l];
            obs.extend_from_slice(&p);
            // Occluded landmarks still count, by their visibility: the detector's guess for a
            // hidden arm beats the prior's T-pose arm.
            let c = weight * vis;
            w.push(c);
            tw.push(if TORSO_LANDMARKS.contains(&l) { c } else { 0.0 });
        }
        let (weight_sum, torso_sum) = (w.iter().sum(), tw.iter().sum());
        Self {
            observed: matrix(obs, n, 2, device),
            weight: matrix(w, n, 1, device),
            torso_weight: matrix(tw, n, 1, device),
            weight_sum,
            torso_sum,
        }
    }
}

/// Bones (parent joint, child joint) with their observed world direction `[N, 3]` and
/// weight `[N, 1]`.
pub(super) type BoneTargets = (Vec<usize>, Vec<usize>, Tensor<2>, Tensor<2>);

/// Hidden limb joints (rows of θ₁…θ₂₃), their seen counterparts' rows and the term's weight
/// per row ([`mirror_rows`]).
pub(super) type SymmetryRows = (Tensor<1, Int>, Tensor<1, Int>, Tensor<2>);

/// Everything the fit's data and direction terms compare the body with.
pub(super) struct Observations {
    pub joints: Targets,
    /// The SMPL joint of each row of `joints`.
    pub joint_ids: Vec<usize>,
    pub points: Targets,
    pub bones: Option<BoneTargets>,
    pub symmetry: Option<SymmetryRows>,
}

impl Observations {
    /// The observations of `input` for a fit starting at `init` seen through `cam` (the
    /// bone term's leg readings depend on the start); no symmetry rows for the joints in
    /// `held` (limbs a person placed, [`super::correction`]).
    #[allow(clippy::too_many_arguments)] // the fit's parts, each needed once
    pub fn new(
        model: &BodyModel,
        input: &FitInput,
        surface_marks: &[SurfaceLandmark],
        init: &BodyParams,
        cam: Vec3,
        bones_lifted: f32,
        held: &[usize],
        device: &Device,
    ) -> Self {
        let joint_rows: Vec<(usize, f32)> = JOINT_LANDMARKS.iter().map(|m| (m.landmark, m.weight)).collect();
        let point_rows: Vec<(usize, f32)> = surface_marks.iter().map(|s| (s.landmark, s.weight)).collect();
        let bones = {
            let rows = bone_rows(&posed_joints(model, init), cam, input, bones_lifted);
            let n = rows.len();
            (n > 0).then(|| {
                (
                    rows.iter().map(|r| r.bone.0).collect(),
                    rows.iter().map(|r| r.bone.1).collect(),
                    matrix(rows.iter().flat_map(|r| r.direction.to_array()).collect(), n, 3, device),
                    matrix(rows.iter().map(|r| r.weight).collect(), n, 1, device),
                )
            })
        };
        let rows: Vec<_> = mirror_rows(|l| input.points[l].1).into_iter().filter(|r| !held.contains(&r.0)).collect();
        let symmetry = (!rows.is_empty()).then(|| {
            (
                joint_index(&rows.iter().map(|r| r.0 - 1).collect::<Vec<_>>(), device),
                joint_index(&rows.iter().map(|r| r.1 - 1).collect::<Vec<_>>(), device),
                matrix(rows.iter().map(|r| r.2).collect(), rows.len(), 1, device),
            )
        });
        Self {
            joints: Targets::new(&joint_rows, input, device),
            joint_ids: JOINT_LANDMARKS.iter().map(|m| m.joint).collect(),
            points: Targets::new(&point_rows, input, device),
            bones,
            symmetry,
        }
    }
}

/// The symmetry term's rows (joint, counterpart joint, weight): the parent joint of a bone
/// whose far-end landmark the detector did not see (visibility below [`VISIBLE`]) while it
/// saw its counterpart's ([`BONES`]`[i ^ 2]`), weighted by how hidden and how seen.
pub(super) fn mirror_rows(visibility: impl Fn(usize) -> f32) -> Vec<(usize, usize, f32)> {
    BONES
        .iter()
        .enumerate()
        .filter_map(|(i, &(j, _, _, l))| {
            let (cj, _, _, cl) = BONES[i ^ 2];
            let hidden = (1.0 - visibility(l) / VISIBLE).clamp(0.0, 1.0);
            let seen = ((visibility(cl) - VISIBLE) / (1.0 - VISIBLE)).clamp(0.0, 1.0);
            (hidden * seen > 0.0).then_some((j, cj, hidden * seen))
        })
        .collect()
}
