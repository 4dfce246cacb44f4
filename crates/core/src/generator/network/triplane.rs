//! Triplane lookup (paper Sec. 4.1): features of a canonical point are the SUM of bilinear
//! samples from the planes (x,y), (y,z) and (x,z), zero outside. Points are first normalised
//! into the canonical box (centre (0, −0.185, 0), edge 2.29 m) → [−1, 1]³.
//!
//! Sampling follows `grid_sample_2d` (bilinear, zero padding, `align_corners = false`), but is
//! written as one row lookup per point and plane so that autodiff stays cheap: each plane is
//! padded with a ring of zeros and rearranged into a table whose row (y, x) holds the 2×2 texel
//! neighbourhood starting at (y, x); a point selects its row (`Tensor::select`, whose backward
//! is a row scatter-add) and weights the four texels. burn's generic `grid_sample_2d` under
//! autodiff instead expands per-channel gather indices and masks, which cost about half of a
//! training step on NdArray. Without autodiff the GPU backends' native `grid_sample_2d` kernels
//! are faster, so inference keeps them there ([`sample_triplanes`] picks by device). On NdArray
//! the lookup is one operation (`ndarray_ops::triplane_bilinear`) with its own backward pass,
//! which touches only the texels the points read (the row table costs O(R²·C) per call, about
//! half of a training step with 256² texture planes), and its forward pass runs on all the CPU
//! cores, also for inference.

use burn::tensor::ops::{GridSampleOptions, GridSamplePaddingMode, InterpolateMode};
use burn::tensor::{Int, Tensor, TensorData};

use crate::geometry::tet_grid::{REFERENCE_BOX_CENTER, REFERENCE_BOX_SIZE};

/// (horizontal, vertical) point axes of the planes (x,y), (y,z), (x,z), as `grid_sample_2d`'s
/// grid (x → width, y → height).
const PLANE_AXES: [[i64; 3]; 2] = [[0, 1, 0], [1, 2, 2]];

/// Sample `planes` (`[B, 3·C, R, R]`) at canonical `points` (`[B, N, 3]`, metres) → `[B, N, C]`:
/// the row-table lookup when gradients are recorded, the native kernel otherwise (on the
/// inner backend for untracked tensors of an autodiff device); the values are the same.
pub fn sample_triplanes(planes: Tensor<4>, points: Tensor<3>) -> Tensor<3> {
    #[cfg(feature = "autodiff")]
    if planes.is_autodiff() || points.is_autodiff() {
        if planes.is_tracked() || points.is_tracked() {
            // On the CPU one operation with its own backward pass (`ndarray_ops`).
            #[cfg(feature = "ndarray")]
            if super::layers::is_ndarray(&planes.device()) {
                let r = planes.dims()[2];
                return super::ndarray_ops::triplane_bilinear(planes, texel_coordinates(points, r));
            }
            return sample_triplanes_rows(planes, points);
        }
        return sample_triplanes_untracked(planes.inner(), points.inner()).autodiff();
    }
    sample_triplanes_untracked(planes, points)
}

/// [`sample_triplanes`] without gradients: on NdArray the lookup's own forward pass, spread
/// over the CPU cores (burn-ndarray's `grid_sample_2d` runs on one core, and took most of a
/// CPU generation's field queries); elsewhere the backend's `grid_sample_2d`.
fn sample_triplanes_untracked(planes: Tensor<4>, points: Tensor<3>) -> Tensor<3> {
    #[cfg(feature = "ndarray")]
    if super::layers::is_ndarray(&planes.device()) {
        let r = planes.dims()[2];
        return super::ndarray_ops::triplane_bilinear(planes, texel_coordinates(points, r));
    }
    sample_triplanes_native(planes, points)
}

/// Normalised box coordinates in [−1, 1]³ of canonical points.
fn box_coordinates(points: Tensor<3>) -> Tensor<3> {
    let center = Tensor::<1>::from_floats(REFERENCE_BOX_CENTER.to_array(), &points.device()).reshape([1, 1, 3]);
    (points - center) * (2.0 / REFERENCE_BOX_SIZE)
}

/// Texel coordinates of canonical points on planes of side `r` (`align_corners = false`:
/// −1 ↦ −0.5, 1 ↦ R − 0.5), `[B, N, 3]`.
fn texel_coordinates(points: Tensor<3>, r: usize) -> Tensor<3> {
    (box_coordinates(points) + 1.0) * (r as f64 / 2.0) - 0.5
}

/// [`sample_triplanes`] with the backend's `grid_sample_2d`, plane by plane.
pub fn sample_triplanes_native(planes: Tensor<4>, points: Tensor<3>) -> Tensor<3> {
    let [b, c3, r, _] = planes.dims();
    let [_, n, _] = points.dims();
    let c = c3 / 3;
    let q = box_coordinates(points);
    let axis = |k: i64| q.clone().narrow(2, k as usize, 1); // [B, N, 1]
    let opts = GridSampleOptions::new(InterpolateMode::Bilinear)
        .with_padding_mode(GridSamplePaddingMode::Zeros)
        .with_align_corners(false);
    let sampled = |k: usize| {
        let plane = planes.clone().narrow(1, k * c, c).reshape([b, c, r, r]);
        let grid = Tensor::cat(vec![axis(PLANE_AXES[0][k]), axis(PLANE_AXES[1][k])], 2).reshape([b, n, 1, 2]);
        plane.grid_sample_2d(grid, opts.clone()) // [B, C, N, 1]
    };
    let sum = sampled(0) + sampled(1) + sampled(2);
    sum.reshape([b, c, n]).swap_dims(1, 2)
}

/// [`sample_triplanes`] as one row select per point and plane (see the module notes).
pub fn sample_triplanes_rows(planes: Tensor<4>, points: Tensor<3>) -> Tensor<3> {
    let [b, c3, r, _] = planes.dims();
    let [_, n, _] = points.dims();
    let c = c3 / 3;
    let device = points.device();
    // Neighbourhood table: [B·3·(R+1)², 4·C]; row ((b·3 + k)·(R+1) + y)·(R+1) + x holds the
    // padded texels (y, x), (y, x+1), (y+1, x), (y+1, x+1) of plane k, i.e. the unpadded
    // texels (y−1.., x−1..).
    let s = r + 1;
    let padded = planes.reshape([b * 3, c, r, r]).pad((1, 1, 1, 1), 0.0); // [B·3, C, R+2, R+2]
    let corner = |dy: usize, dx: usize| padded.clone().slice([0..b * 3, 0..c, dy..dy + s, dx..dx + s]);
    let table = Tensor::stack::<5>(vec![corner(0, 0), corner(0, 1), corner(1, 0), corner(1, 1)], 1) // [B·3, 4, C, S, S]
        .reshape([b * 3, 4 * c, s * s])
        .swap_dims(1, 2)
        .reshape([b * 3 * s * s, 4 * c]);

    // Texel coordinates (align_corners = false: −1 ↦ −0.5, 1 ↦ R − 0.5) per plane, [B, N, 3].
    let t = texel_coordinates(points, r);
    let axis =
        |a: [i64; 3]| t.clone().select(2, Tensor::<1, Int>::from_data(TensorData::new(a.to_vec(), [3]), &device));
    let (u, v) = (axis(PLANE_AXES[0]), axis(PLANE_AXES[1]));
    let (u0, v0) = (u.clone().detach().floor(), v.clone().detach().floor());
    let (fu, fv) = (u - u0.clone(), v - v0.clone());
    // A point whose neighbourhood lies wholly outside the plane reads zeros: weight 0 and any
    // valid row. Inside, the zero ring supplies the missing texels at the border.
    let inside =
        |x0: &Tensor<3>| x0.clone().greater_equal_elem(-1.0).bool_and(x0.clone().lower_equal_elem(r as f64 - 1.0));
    let valid = inside(&u0).bool_and(inside(&v0)).float(); // [B, N, 3]
    let (gu, gv) = (fu.clone().neg() + 1.0, fv.clone().neg() + 1.0);
    let weights = Tensor::stack::<4>(vec![gu.clone() * gv.clone(), fu.clone() * gv, gu * fv.clone(), fu * fv], 3)
        * valid.unsqueeze_dim::<4>(3); // [B, N, 3, 4]

    let col = (u0 + 1.0).clamp(0.0, r as f64).int();
    let row = (v0 + 1.0).clamp(0.0, r as f64).int();
    let plane_base: Vec<i64> =
        (0..b as i64).flat_map(|bi| (0..3).map(move |k| (bi * 3 + k) * (s * s) as i64)).collect();
    let base = Tensor::<3, Int>::from_data(TensorData::new(plane_base, [b, 1, 3]), &device);
    let idx = (row * s as i64 + col + base).reshape([b * n * 3]);
    let rows = table.select(0, idx).reshape([b, n, 3, 4, c]);
    (rows * weights.unsqueeze_dim::<5>(4)).reshape([b, n, 12, c]).sum_dim(2).reshape([b, n, c])
}
