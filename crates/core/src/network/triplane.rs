//! Triplane lookup (paper Sec. 4.1): features of a canonical point are the SUM of bilinear
//! samples from the planes (x,y), (y,z) and (x,z), zero outside. Points are first normalised
//! into the canonical box (centre (0, −0.185, 0), edge 2.29 m) → [−1, 1]³.

use burn::tensor::ops::{GridSampleOptions, GridSamplePaddingMode, InterpolateMode};
use burn::tensor::Tensor;

use crate::geometry::tet_grid::{REFERENCE_BOX_CENTER, REFERENCE_BOX_SIZE};

/// Sample `planes` (`[B, 3·C, R, R]`) at canonical `points` (`[B, N, 3]`, metres) → `[B, N, C]`.
pub fn sample_triplanes(planes: Tensor<4>, points: Tensor<3>) -> Tensor<3> {
    let [b, c3, r, _] = planes.dims();
    let [_, n, _] = points.dims();
    let c = c3 / 3;
    let device = points.device();
    let center = Tensor::<1>::from_floats(REFERENCE_BOX_CENTER.to_array(), &device).reshape([1, 1, 3]);
    let q = (points - center) * (2.0 / REFERENCE_BOX_SIZE);
    let coord = |k: usize| q.clone().narrow(2, k, 1); // [B, N, 1]
    let (x, y, z) = (coord(0), coord(1), coord(2));
    let opts = GridSampleOptions::new(InterpolateMode::Bilinear)
        .with_padding_mode(GridSamplePaddingMode::Zeros)
        .with_align_corners(false);
    let mut sum: Option<Tensor<4>> = None;
    for (k, (u, v)) in [(x.clone(), y.clone()), (y, z.clone()), (x, z)].into_iter().enumerate() {
        let plane = planes.clone().narrow(1, k * c, c).reshape([b, c, r, r]);
        let grid = Tensor::cat(vec![u, v], 2).reshape([b, n, 1, 2]);
        let s = plane.grid_sample_2d(grid, opts.clone()); // [B, C, N, 1]
        sum = Some(match sum {
            Some(acc) => acc + s,
            None => s,
        });
    }
    match sum {
        Some(s) => s.reshape([b, c, n]).swap_dims(1, 2),
        None => unreachable!("three planes"),
    }
}
