//! The body model's forward pass on burn tensors (paper Sec. 3, eq. 1), differentiable in the
//! pose θ and the shape β: Rodrigues' formula, forward kinematics one level of the kinematic
//! tree at a time (SMPL's tree is 9 levels deep, so 9 small batched products instead of 24),
//! and linear blend skinning of any subset of the vertices. It is the twin of
//! [`crate::body::skinning::pose_body`] (same numbers up to rounding, tested), without the pose
//! correctives (the body fit never needs them; the open default body has none).
//!
//! Shapes: θ is `[24, 3]` (axis-angle rows, joint 0 the global orientation), β `[1, B]`.
//! The body stands at the origin (no translation; the fit moves the camera instead).

use burn::tensor::{Device, Int, Tensor};

use super::{index_tensor, matrix};
use crate::body::body_model::{BodyModel, NUM_JOINTS};

/// Rotation matrices `[N, 3, 3]` of axis-angle vectors `r` `[N, 3]`:
/// `R = I + (sin θ/θ)·[r]× + (2 sin²(θ/2)/θ²)·(r rᵀ − θ² I)`, which is smooth at `r = 0`
/// (the gradient there is `dR = [dr]×`).
pub fn rodrigues(r: Tensor<2>) -> Tensor<3> {
    let n = r.dims()[0];
    let theta2 = (r.clone() * r.clone()).sum_dim(1) + 1e-12;
    let theta = theta2.clone().sqrt();
    let a = theta.clone().sin() / theta.clone();
    let half = (theta * 0.5).sin();
    let b = half.clone() * half * 2.0 / theta2.clone();
    let col = |i: usize| r.clone().narrow(1, i, 1);
    let (x, y, z) = (col(0), col(1), col(2));
    let sq = x.clone() * x.clone() + y.clone() * y.clone() + z.clone() * z.clone();
    // b · (r rᵀ − |r|² I) + a · [r]× + I, entry by entry (row-major).
    let outer = |p: &Tensor<2>, q: &Tensor<2>| b.clone() * p.clone() * q.clone();
    let diag = |p: &Tensor<2>| outer(p, p) - b.clone() * sq.clone() + 1.0;
    let entries = vec![
        diag(&x),
        outer(&x, &y) - a.clone() * z.clone(),
        outer(&x, &z) + a.clone() * y.clone(),
        outer(&y, &x) + a.clone() * z.clone(),
        diag(&y),
        outer(&y, &z) - a.clone() * x.clone(),
        outer(&z, &x) - a.clone() * y.clone(),
        outer(&z, &y) + a.clone() * x.clone(),
        diag(&z),
    ];
    Tensor::cat(entries, 1).reshape([n, 3, 3])
}

/// The kinematic tree's constants on a device: rest joints at β = 0 and their shape
/// directions, and the joints grouped by depth.
#[derive(Clone, Debug)]
pub struct Skeleton {
    /// Rest joints at β = 0, `[24, 3]`.
    rest_joints: Tensor<2>,
    /// d(rest joints)/dβ, `[B, 72]` (`J_regressor · shapedirs`).
    joint_dirs: Tensor<2>,
    /// Joints of each tree level (level 0 = the root).
    levels: Vec<Vec<usize>>,
    parents: [i32; NUM_JOINTS],
    /// The number of β components used (≤ the model's).
    pub num_betas: usize,
}

/// Output of [`Skeleton::forward`].
#[derive(Clone, Debug)]
pub struct PosedSkeleton {
    /// Posed joint positions, `[24, 3]`.
    pub joints: Tensor<2>,
    /// Skinning transforms `A_k` (rest → posed) as rows `[R | t]` flattened, `[24, 12]`.
    pub transforms: Tensor<2>,
}

impl Skeleton {
    /// The skeleton of `model` with its first `num_betas` shape components (clamped to the
    /// model's count).
    pub fn new(model: &BodyModel, num_betas: usize, device: &Device) -> Self {
        let nb = num_betas.min(model.num_betas);
        let rest = model.regress_joints(&model.v_template);
        let mut dirs = vec![0.0f32; nb * NUM_JOINTS * 3];
        let nv = model.v_template.len();
        for j in 0..NUM_JOINTS {
            let row = &model.j_regressor[j * nv..(j + 1) * nv];
            for (v, &w) in row.iter().enumerate().filter(|(_, w)| **w != 0.0) {
                for c in 0..3 {
                    let s = &model.shapedirs[(v * 3 + c) * model.num_betas..][..nb];
                    for (b, sb) in s.iter().enumerate() {
                        dirs[b * NUM_JOINTS * 3 + j * 3 + c] += w * sb;
                    }
                }
            }
        }
        let mut depth = [0usize; NUM_JOINTS];
        for j in 0..NUM_JOINTS {
            let p = model.parents[j];
            depth[j] = if p < 0 { 0 } else { depth[p as usize] + 1 };
        }
        let mut levels = vec![Vec::new(); depth.iter().max().map_or(0, |d| d + 1)];
        for (j, d) in depth.iter().enumerate() {
            levels[*d].push(j);
        }
        let flat: Vec<f32> = rest.iter().flat_map(|v| v.to_array()).collect();
        Self {
            rest_joints: matrix(flat, NUM_JOINTS, 3, device),
            joint_dirs: matrix(dirs, nb.max(1), NUM_JOINTS * 3, device).narrow(0, 0, nb.max(1)),
            levels,
            parents: model.parents,
            num_betas: nb,
        }
    }

    /// Rest joints `[24, 3]` for β `[1, B]`.
    pub fn rest_joints(&self, betas: &Tensor<2>) -> Tensor<2> {
        if self.num_betas == 0 {
            return self.rest_joints.clone();
        }
        self.rest_joints.clone() + betas.clone().matmul(self.joint_dirs.clone()).reshape([NUM_JOINTS, 3])
    }

    /// Forward kinematics for θ `[24, 3]` and β `[1, B]`.
    pub fn forward(&self, theta: Tensor<2>, betas: &Tensor<2>) -> PosedSkeleton {
        let device = theta.device();
        let rest = self.rest_joints(betas);
        let local = rodrigues(theta);
        // World rotation and position per joint, filled level by level.
        let mut world_r: Vec<Option<Tensor<3>>> = vec![None; NUM_JOINTS];
        let mut world_p: Vec<Option<Tensor<2>>> = vec![None; NUM_JOINTS];
        for level in &self.levels {
            let idx = index_tensor(&level.iter().map(|&j| j as u32).collect::<Vec<_>>(), &device);
            let r_local = local.clone().select(0, idx.clone());
            let j_rest = rest.clone().select(0, idx);
            let n = level.len();
            let (r, p) = if self.parents[level[0]] < 0 {
                (r_local, j_rest)
            } else {
                let parent_of = |t: &[Option<Tensor<3>>]| {
                    Tensor::cat(level.iter().map(|&j| parent(t, self.parents[j])).collect(), 0)
                };
                let pr = parent_of(&world_r);
                let pp = Tensor::cat(level.iter().map(|&j| parent(&world_p, self.parents[j])).collect(), 0);
                let pidx: Vec<u32> = level.iter().map(|&j| self.parents[j] as u32).collect();
                let bone = j_rest - rest.clone().select(0, index_tensor(&pidx, &device));
                let offset = pr.clone().matmul(bone.reshape([n, 3, 1])).reshape([n, 3]);
                (pr.matmul(r_local), pp + offset)
            };
            for (k, &j) in level.iter().enumerate() {
                world_r[j] = Some(r.clone().narrow(0, k, 1));
                world_p[j] = Some(p.clone().narrow(0, k, 1));
            }
        }
        let take = |v: Vec<Option<Tensor<2>>>| Tensor::cat(v.into_iter().flatten().collect(), 0);
        let joints = take(world_p);
        let rots = Tensor::cat(world_r.into_iter().flatten().collect(), 0);
        // A_k = [R_k | p_k − R_k j_k]: posed = R_k (x − j_k) + p_k.
        let rj = rots.clone().matmul(rest.reshape([NUM_JOINTS, 3, 1])).reshape([NUM_JOINTS, 3]);
        let t = (joints.clone() - rj).reshape([NUM_JOINTS, 3, 1]);
        let transforms = Tensor::cat(vec![rots, t], 2).reshape([NUM_JOINTS, 12]);
        PosedSkeleton { joints, transforms }
    }
}

fn parent<const D: usize>(t: &[Option<Tensor<D>>], p: i32) -> Tensor<D> {
    // Levels are filled in order, so a parent is always present; SMPL trees are validated
    // on load (`BodyModel::from_arrays`: parents precede their children).
    t[p as usize].clone().unwrap_or_else(|| unreachable!("parent {p} filled by an earlier level"))
}

/// A subset of the body's vertices, ready for skinning: rest positions, shape directions and
/// skin weights on a device.
#[derive(Clone, Debug)]
pub struct VertexSet {
    /// Rest positions at β = 0, `[N, 3]`.
    template: Tensor<2>,
    /// Shape directions `[B, 3N]`.
    shape_dirs: Tensor<2>,
    /// Skin weights `[N, 24]`.
    weights: Tensor<2>,
    len: usize,
}

impl VertexSet {
    /// Vertices `ids` of `model` with the skeleton's β count.
    pub fn new(model: &BodyModel, ids: &[u32], skeleton: &Skeleton, device: &Device) -> Self {
        let rest: Vec<glam::Vec3> = ids.iter().map(|&i| model.v_template[i as usize]).collect();
        Self::rigged(model, &rest, ids, skeleton, device)
    }

    /// Points at `rest` (rest pose, β = 0) that follow body vertices `ids` (one each): their
    /// shape directions and skin weights, as a rigged avatar's vertices follow their nearest
    /// body vertex ([`crate::generator::rigging`]).
    pub fn rigged(model: &BodyModel, rest: &[glam::Vec3], ids: &[u32], skeleton: &Skeleton, device: &Device) -> Self {
        let nb = skeleton.num_betas;
        let n = ids.len();
        let template: Vec<f32> = rest.iter().flat_map(|p| p.to_array()).collect();
        let mut dirs = vec![0.0f32; nb.max(1) * 3 * n];
        for (k, &i) in ids.iter().enumerate() {
            for c in 0..3 {
                let s = &model.shapedirs[(i as usize * 3 + c) * model.num_betas..][..nb];
                for (b, sb) in s.iter().enumerate() {
                    dirs[b * 3 * n + k * 3 + c] = *sb;
                }
            }
        }
        let weights: Vec<f32> = ids.iter().flat_map(|&i| model.weights[i as usize]).collect();
        Self {
            template: matrix(template, n, 3, device),
            shape_dirs: matrix(dirs, nb.max(1), 3 * n, device).narrow(0, 0, nb.max(1)),
            weights: matrix(weights, n, NUM_JOINTS, device),
            len: n,
        }
    }

    /// Every vertex of `model`.
    pub fn all(model: &BodyModel, skeleton: &Skeleton, device: &Device) -> Self {
        let ids: Vec<u32> = (0..model.v_template.len() as u32).collect();
        Self::new(model, &ids, skeleton, device)
    }

    /// The vertices `ids` (indices into this set) as a set of their own.
    pub fn select(&self, ids: &[u32]) -> Self {
        let device = self.template.device();
        let idx = index_tensor(ids, &device);
        let [nb, n3] = self.shape_dirs.dims();
        let n = ids.len();
        Self {
            template: self.template.clone().select(0, idx.clone()),
            shape_dirs: self.shape_dirs.clone().reshape([nb, n3 / 3, 3]).select(1, idx.clone()).reshape([nb, 3 * n]),
            weights: self.weights.clone().select(0, idx),
            len: n,
        }
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Posed positions `[N, 3]` (eq. 1: `Σ_k w_k A_k (v + S β)`).
    pub fn pose(&self, posed: &PosedSkeleton, betas: &Tensor<2>, skeleton: &Skeleton) -> Tensor<2> {
        let n = self.len;
        let rest = if skeleton.num_betas == 0 {
            self.template.clone()
        } else {
            self.template.clone() + betas.clone().matmul(self.shape_dirs.clone()).reshape([n, 3])
        };
        let t = self.weights.clone().matmul(posed.transforms.clone()).reshape([n, 3, 4]);
        // Each row of the blended [R | t] times the homogeneous rest point, as a broadcast
        // product summed over the last axis: one pass over N·12 values, where a batched
        // 3×4 · 4×1 matmul is N small products (thousands of matmul calls on NdArray, the fit's
        // longest stretch in the browser with all vertices).
        let ones = Tensor::<2>::ones([n, 1], &rest.device());
        let homogeneous = Tensor::cat(vec![rest, ones], 1).reshape([n, 1, 4]);
        (t * homogeneous).sum_dim(2).reshape([n, 3])
    }
}

/// Indices as an `Int` tensor (re-exported for the fit's joint selections).
pub fn joint_index(ids: &[usize], device: &Device) -> Tensor<1, Int> {
    index_tensor(&ids.iter().map(|&j| j as u32).collect::<Vec<_>>(), device)
}
