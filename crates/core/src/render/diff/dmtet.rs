//! Differentiable DMTet vertex positions (Shen et al. 2021, as in the paper's Sec. 4.3): the
//! surface vertex on grid edge (a, b) is `p = (x_a·s_b − x_b·s_a) / (s_b − s_a)`, a function
//! of the (offset) grid positions x and the SDF values s, so gradients reach both. Topology
//! comes from [`crate::geometry::marching_tets`] run on detached values.

use burn::tensor::{Device, Tensor};

use super::index_tensor;
use crate::geometry::TriMesh;

/// Indices of each surface vertex's grid edge, as tensors (built once per extraction).
#[derive(Clone, Debug)]
pub struct EdgeIndex {
    pub a: Vec<u32>,
    pub b: Vec<u32>,
}

impl EdgeIndex {
    pub fn new(mesh: &TriMesh) -> Self {
        Self { a: mesh.edges.iter().map(|e| e.0).collect(), b: mesh.edges.iter().map(|e| e.1).collect() }
    }
}

/// Surface vertices `[M, C]` interpolated from per-grid-vertex values `values` `[N, C]` (grid
/// positions, canonical coordinates, …) at the zero crossings of `sdf` `[N]`. Differentiable in
/// both. `values` of several kinds can share one call by concatenating columns.
pub fn surface_points(edges: &EdgeIndex, values: Tensor<2>, sdf: Tensor<1>, device: &Device) -> Tensor<2> {
    let (ia, ib) = (index_tensor(&edges.a, device), index_tensor(&edges.b, device));
    let (sa, sb) = (sdf.clone().select(0, ia.clone()), sdf.select(0, ib.clone()));
    let t = (sa.clone() / (sa - sb)).unsqueeze_dim::<2>(1);
    let (xa, xb) = (values.clone().select(0, ia), values.select(0, ib));
    xa.clone() + (xb - xa) * t
}
