//! The generator's geometry fields on the tet grid (paper Sec. 4.2): SDF = template SDF +
//! learned residual, and the DMTet vertex offsets, evaluated on the field band of a posed grid
//! (`geometry::posed_grid::field_band`) and zero elsewhere. Inference (`generator`) and
//! training (`diff::avatar`) both go through these functions, so the surface the app shows is
//! the surface training renders.

use burn::tensor::{Device, Tensor, TensorData};
use glam::Vec3;

use crate::generator::network::generator_network::{Generator, Styles};
use crate::generator::readback::{read_f32, ReadbackError};
use crate::geometry::template_sdf::OUTSIDE_VALUE;

/// Values of the geometry fields at every grid vertex (0 off the band).
#[derive(Clone, Debug, PartialEq)]
pub struct GridFields {
    /// SDF residual per grid vertex, metres.
    pub residual: Vec<f32>,
    /// DMTet offset per grid vertex, metres, `3·n` (x, y, z).
    pub offset: Vec<f32>,
}

impl GridFields {
    /// Fields of `n` grid vertices that are all zero (an untouched grid).
    pub fn zeros(n: usize) -> Self {
        Self { residual: vec![0.0; n], offset: vec![0.0; 3 * n] }
    }

    /// The full SDF: template + residual, and [`OUTSIDE_VALUE`] on the box boundary so every
    /// extracted surface is closed.
    pub fn sdf(&self, template: &[f32], boundary: &[bool]) -> Vec<f32> {
        template
            .iter()
            .zip(&self.residual)
            .zip(boundary)
            .map(|((t, r), &b)| if b { OUTSIDE_VALUE } else { t + r })
            .collect()
    }

    /// Grid vertex positions moved by their DMTet offsets.
    pub fn positions(&self, grid: &[Vec3]) -> Vec<Vec3> {
        grid.iter().enumerate().map(|(i, p)| *p + Vec3::from_slice(&self.offset[3 * i..3 * i + 3])).collect()
    }

    /// The offset of grid vertex `i`.
    pub fn offset_of(&self, i: usize) -> [f32; 3] {
        [self.offset[3 * i], self.offset[3 * i + 1], self.offset[3 * i + 2]]
    }
}

/// `[1, N, 3]` tensor of points.
pub fn points_tensor(points: &[Vec3], device: &Device) -> Tensor<3> {
    let flat: Vec<f32> = points.iter().flat_map(|p| p.to_array()).collect();
    Tensor::from_data(TensorData::new(flat, [1, points.len(), 3]), device)
}

/// Point batches that vary from avatar to avatar (a pose's band of grid vertices, a mesh's
/// vertices) are padded to a multiple of this before the networks see them. The GPU kernels'
/// compiled variants depend on a batch's size class (vector widths and bounds checks that
/// divide it), so a new vertex count could compile new kernels at a generation the user asked
/// for: a 0.5 s task in the browser. Multiples of 256 fall in the classes the warm-up compiled.
pub const POINT_ALIGN: usize = 256;

/// `points` padded to a multiple of [`POINT_ALIGN`] with copies of the first (values at the
/// padding are computed and ignored).
pub fn aligned_points(points: &[Vec3]) -> Vec<Vec3> {
    let mut out = points.to_vec();
    if let Some(&first) = points.first() {
        out.resize(points.len().div_ceil(POINT_ALIGN) * POINT_ALIGN, first);
    }
    out
}

/// The geometry fields of styles `s` (batch 1) at canonical points `[1, P, 3]`, from the
/// geometry planes `geometry` (`Triplanes::geometry`), as rows of
/// (residual, offset x, y, z), `[P, 4]`, left on the device.
pub fn band_rows(g: &Generator, geometry: &Tensor<4>, s: &Styles, points: Tensor<3>) -> Tensor<2> {
    let (r, o) = g.geometry_fields_of(geometry, s, points);
    let p = r.dims()[1];
    Tensor::cat(vec![r.unsqueeze_dim::<3>(2), o], 2).reshape([p, 4])
}

/// The geometry fields of styles `s` (batch 1) on a grid of `n` vertices: evaluated at the
/// canonical points `band_points` (`[1, |band|, 3]`, those of the grid vertices `band`), zero
/// elsewhere. Values only (nothing here is differentiated).
pub async fn band_fields(
    g: &Generator,
    geometry: &Tensor<4>,
    s: &Styles,
    band_points: Tensor<3>,
    band: &[u32],
    n: usize,
) -> Result<GridFields, ReadbackError> {
    let mut f = GridFields::zeros(n);
    if band.is_empty() {
        return Ok(f);
    }
    // One read-back for both fields.
    let both = read_f32(band_rows(g, geometry, s, band_points).detach()).await?;
    for (&i, row) in band.iter().zip(both.chunks_exact(4)) {
        let i = i as usize;
        f.residual[i] = row[0];
        f.offset[3 * i..3 * i + 3].copy_from_slice(&row[1..4]);
    }
    Ok(f)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn aligned_points_pad_to_a_multiple_with_the_first_point() {
        let p = |n: usize| (0..n).map(|i| Vec3::new(i as f32, 1.0, 2.0)).collect::<Vec<_>>();
        assert!(aligned_points(&[]).is_empty());
        for (n, want) in [(1, 256), (255, 256), (256, 256), (257, 512), (6348, 6400)] {
            let a = aligned_points(&p(n));
            assert_eq!(a.len(), want, "{n} points");
            assert_eq!(a[..n], p(n)[..], "the points themselves are kept");
            assert!(a[n..].iter().all(|q| *q == Vec3::new(0.0, 1.0, 2.0)), "padding is the first point");
        }
    }
}
