//! The body's skeleton and skin weights as a glTF skin, and motions as glTF clips: what
//! [`crate::export::gltf_export::write_glb_full`] needs to write an animatable avatar or body, and
//! [`crate::export::vrm_export`] a VRM avatar or a VRM animation (in VRM's frame: [`vrm_frame`]).

use glam::{Quat, Vec3};

use crate::body::body_model::{joint_index, BodyModel, NUM_JOINTS};
use crate::body::humanoid::SkeletonNames;
use crate::body::motion::{Motion, MOTION_FPS};
use crate::body::skinning::{axis_angle_to_quat as quat, pose_body, BodyParams};
use crate::export::gltf_export::{write_glb_full, ExportClip, ExportError, ExportMesh, ExportSkin};
use crate::export::vrm_export::{write_vrm, write_vrma, VrmMeta};

/// The 4 largest of a vertex's joint weights, renormalised to sum to 1 (glTF's JOINTS_0 /
/// WEIGHTS_0). Unused slots name joint 0 with weight 0.
pub fn top4(weights: &[f32; NUM_JOINTS]) -> ([u8; 4], [f32; 4]) {
    // The 4 largest by insertion (larger first, ties to the lower joint): no sort of all 24
    // per vertex, which an avatar's upload does for ~10k vertices in a frame.
    let mut order = [usize::MAX; 4];
    for j in 0..NUM_JOINTS {
        let beats = |k: usize| order[k] == usize::MAX || weights[j].total_cmp(&weights[order[k]]).is_gt();
        if let Some(k) = (0..4).find(|&k| beats(k)) {
            order.copy_within(k..3, k + 1);
            order[k] = j;
        }
    }
    let mut joints = [0u8; 4];
    let mut w = [0.0f32; 4];
    for k in 0..4 {
        let j = order[k];
        if weights[j] > 0.0 {
            joints[k] = j as u8;
            w[k] = weights[j];
        }
    }
    let s: f32 = w.iter().sum();
    if s > 0.0 {
        w = w.map(|x| x / s);
    } else {
        w = [1.0, 0.0, 0.0, 0.0];
    }
    (joints, w)
}

/// The body's skeleton as a glTF skin: rest (bind) joints at shape `params.betas`, the pose
/// shown `params.pose` / `params.transl`, and per exported vertex the 4 largest weights of
/// `vertex_weights` (the body's own rows, or for an avatar its rigging body vertex's); the
/// joints' nodes named by `names`.
pub fn smpl_skin<'a>(
    model: &BodyModel,
    params: &BodyParams,
    vertex_weights: impl Iterator<Item = &'a [f32; NUM_JOINTS]>,
    names: SkeletonNames,
) -> ExportSkin {
    let rest = model.regress_joints(&model.shaped_vertices(&params.betas));
    let (joints, weights) = vertex_weights.map(top4).unzip();
    ExportSkin {
        names: names.names(),
        parents: model.parents.to_vec(),
        rest_joints: rest.to_vec(),
        pose: params.pose.iter().map(|v| quat(*v)).collect(),
        translation: params.transl,
        joints,
        weights,
    }
}

/// A motion as a glTF clip (every joint's rotation and the root translation per frame). A
/// looping motion gets its first frame again at the end, so a viewer's loop (which jumps from
/// the last key to the first) interpolates across the seam like any other frame.
pub fn motion_clip(motion: &Motion) -> ExportClip {
    let mut rotations: Vec<Vec<Quat>> = motion.poses.iter().map(|p| p.iter().map(|v| quat(*v)).collect()).collect();
    let mut translations = motion.trans.clone();
    if motion.looping && !rotations.is_empty() {
        rotations.push(rotations[0].clone());
        translations.push(translations[0]);
    }
    ExportClip { name: motion.name.clone(), fps: MOTION_FPS, rotations, translations }
}

/// The bare body's rest-pose mesh at shape `betas`.
fn rest_body_mesh(model: &BodyModel, betas: &[f32], name: &str) -> ExportMesh {
    let rest = pose_body(model, &BodyParams { betas: betas.to_vec(), ..BodyParams::default() });
    let normals = crate::body::skinning::vertex_normals(&rest.vertices, &model.faces);
    ExportMesh {
        positions: rest.vertices,
        normals,
        colors: Vec::new(),
        uvs: Vec::new(),
        indices: model.faces.clone(),
        name: name.to_string(),
    }
}

/// The bare body as an animated .glb (bound in the rest pose at `params.betas`, showing
/// `params`, one animation per motion), its joints named by `names`.
pub fn animated_body_glb(
    model: &BodyModel,
    params: &BodyParams,
    motions: &[Motion],
    name: &str,
    names: SkeletonNames,
) -> Result<Vec<u8>, ExportError> {
    let mesh = rest_body_mesh(model, &params.betas, name);
    let skin = smpl_skin(model, params, model.weights.iter(), names);
    let clips: Vec<_> = motions.iter().map(motion_clip).collect();
    write_glb_full(&mesh, None, Some(&skin), &clips)
}

/// Where a body of shape `betas` stands in VRM's frame: its rest pose (T-pose, facing +z)
/// moved by `offset` so that its lowest vertex (the soles) is at y = 0, and the midpoint of
/// its eyes (the surface landmarks) from its head joint, for the look-at.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VrmFrame {
    pub offset: Vec3,
    pub eyes_from_head: Vec3,
}

/// The [`VrmFrame`] of `model` at shape `betas`.
pub fn vrm_frame(model: &BodyModel, betas: &[f32]) -> Result<VrmFrame, ExportError> {
    let rest = pose_body(model, &BodyParams { betas: betas.to_vec(), ..BodyParams::default() });
    let floor = rest.vertices.iter().map(|v| v.y).fold(f32::INFINITY, f32::min);
    let marks = crate::body::body_surface::surface_landmarks(model).map_err(|e| ExportError::Skin(e.to_string()))?;
    // MediaPipe's left and right eye (landmarks 2 and 5).
    let eye = |landmark| marks.iter().find(|m| m.landmark == landmark).map(|m| rest.vertices[m.vertex as usize]);
    let head = joint_index("head").map(|j| rest.kinematics.rest_joints[j]);
    let (Some(l), Some(r), Some(head)) = (eye(2), eye(5), head) else {
        return Err(ExportError::Skin("the body has no eyes or head joint for the look-at".into()));
    };
    if !floor.is_finite() {
        return Err(ExportError::NonFinite("body vertices"));
    }
    Ok(VrmFrame { offset: Vec3::new(0.0, -floor, 0.0), eyes_from_head: (l + r) * 0.5 - head })
}

/// `skin` (bound at a body's rest pose) showing its rest pose, moved by `frame.offset`: what
/// a `.vrm` or `.vrma` holds.
pub fn vrm_rest_skin(mut skin: ExportSkin, frame: &VrmFrame) -> ExportSkin {
    for p in &mut skin.rest_joints {
        *p += frame.offset;
    }
    skin.pose = vec![Quat::IDENTITY; skin.names.len()];
    skin.translation = Vec3::ZERO;
    skin
}

/// The bare body at shape `betas` as a VRM 1.0 avatar (rest T-pose, soles at 0).
pub fn body_vrm(
    model: &BodyModel,
    betas: &[f32],
    meta: &VrmMeta,
    names: SkeletonNames,
) -> Result<Vec<u8>, ExportError> {
    let frame = vrm_frame(model, betas)?;
    let mut mesh = rest_body_mesh(model, betas, &meta.name);
    for p in &mut mesh.positions {
        *p += frame.offset;
    }
    let rest = BodyParams { betas: betas.to_vec(), ..BodyParams::default() };
    let skin = vrm_rest_skin(smpl_skin(model, &rest, model.weights.iter(), names), &frame);
    write_vrm(&mesh, None, &skin, meta, frame.eyes_from_head)
}

/// A motion as a VRM animation on the skeleton of `model` at shape `betas` (in VRM's
/// frame: the same skeleton as that body's or avatar's `.vrm`, so three-vrm plays it there
/// unscaled).
pub fn motion_vrma(
    model: &BodyModel,
    betas: &[f32],
    motion: &Motion,
    names: SkeletonNames,
) -> Result<Vec<u8>, ExportError> {
    let frame = vrm_frame(model, betas)?;
    let rest = BodyParams { betas: betas.to_vec(), ..BodyParams::default() };
    let skin = vrm_rest_skin(smpl_skin(model, &rest, std::iter::empty(), names), &frame);
    write_vrma(&skin, &motion_clip(motion))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn top4_keeps_the_largest_weights_renormalised() {
        let mut w = [0.0f32; NUM_JOINTS];
        (w[3], w[7], w[1], w[9], w[12]) = (0.4, 0.3, 0.15, 0.1, 0.05);
        let (j, x) = top4(&w);
        assert_eq!(j, [3, 7, 1, 9]);
        let s = 0.95;
        for (a, b) in x.iter().zip([0.4 / s, 0.3 / s, 0.15 / s, 0.1 / s]) {
            assert!((a - b).abs() < 1e-6, "{x:?}");
        }
        let mut one = [0.0f32; NUM_JOINTS];
        one[5] = 1.0;
        assert_eq!(top4(&one), ([5, 0, 0, 0], [1.0, 0.0, 0.0, 0.0]));
    }

    #[test]
    fn top4_picks_what_sorting_all_weights_picks_ties_included() {
        let mut rng = crate::util::rng::Rng::new(4, 4);
        for case in 0..2000 {
            // Few distinct values, many ties and zeros.
            let w: [f32; NUM_JOINTS] = std::array::from_fn(|_| (rng.uniform() * 4.0).floor() / 8.0);
            let mut order: Vec<usize> = (0..NUM_JOINTS).collect();
            order.sort_by(|a, b| w[*b].total_cmp(&w[*a]).then(a.cmp(b)));
            let want: Vec<u8> = order[..4].iter().map(|&j| if w[j] > 0.0 { j as u8 } else { 0 }).collect();
            assert_eq!(top4(&w).0.to_vec(), want, "case {case}: {w:?}");
        }
    }
}
