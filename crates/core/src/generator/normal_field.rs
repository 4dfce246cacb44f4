//! The normal field (paper eq. 4): the gradient of the full SDF (template + residual) at a
//! surface point's canonical coordinate, by central differences, rotated to posed space by the
//! rotation of the body vertex's skinning transform (nearest to its linear part: normals are
//! rotated, not sheared). One implementation for inference (`generator`, per mesh vertex) and
//! training (`diff::avatar`, per pixel, differentiable).

use burn::tensor::{Device, Tensor, TensorData};
use glam::{Mat3, Vec3};

use crate::generator::network::generator_network::{Generator, Styles};
use crate::generator::network::synthesis::Triplanes;
use crate::geometry::TemplateSdf;

/// Directions of the central-difference probes, in the order ±x, ±y, ±z.
pub const PROBE_DIRECTIONS: [Vec3; 6] = [Vec3::X, Vec3::NEG_X, Vec3::Y, Vec3::NEG_Y, Vec3::Z, Vec3::NEG_Z];

/// Step of the central differences: half a template cell (finer than the template's own
/// trilinear cells would resolve, coarser than float noise).
pub fn probe_step(template: &TemplateSdf) -> f32 {
    0.5 * template.cell
}

/// ∇SDF `[P, 3]` at canonical points (`points` as a `[P, 3]` tensor, `values` the same points
/// on the host): central differences of the residual through the network (differentiable in
/// the residual and in `points`) plus those of the template (a constant).
pub fn sdf_gradient(
    g: &Generator,
    planes: &Triplanes,
    s: &Styles,
    template: &TemplateSdf,
    points: Tensor<2>,
    values: &[Vec3],
    device: &Device,
) -> Tensor<2> {
    let h = probe_step(template);
    let grad_template: Vec<f32> = values.iter().flat_map(|c| template_gradient(template, *c, h).to_array()).collect();
    residual_gradient(g, planes, s, h, points)
        + Tensor::from_data(TensorData::new(grad_template, [values.len(), 3]), device)
}

/// The residual's part of [`sdf_gradient`]: central differences of step `h` through the
/// network at `points` (`[P, 3]`), device work only (the GPU's DMTet pass adds the template's
/// part on the host, after its one read-back).
pub fn residual_gradient(g: &Generator, planes: &Triplanes, s: &Styles, h: f32, points: Tensor<2>) -> Tensor<2> {
    let p = points.dims()[0];
    let steps: Vec<f32> = PROBE_DIRECTIONS.iter().flat_map(|d| (*d * h).to_array()).collect();
    let steps = Tensor::<3>::from_data(TensorData::new(steps, [1, 6, 3]), &points.device());
    let probes = points.unsqueeze_dim::<3>(1).repeat_dim(1, 6) + steps;
    let r = g.sdf_residual(planes, s, probes.reshape([1, p * 6, 3])).reshape([p, 3, 2]);
    (r.clone().narrow(2, 0, 1) - r.narrow(2, 1, 1)).reshape([p, 3]) * (1.0 / (2.0 * h))
}

/// ∇ of the template SDF at `c` by central differences of step `h`.
pub fn template_gradient(template: &TemplateSdf, c: Vec3, h: f32) -> Vec3 {
    let f = |d: Vec3| template.sample(c + d * h) - template.sample(c - d * h);
    Vec3::new(f(Vec3::X), f(Vec3::Y), f(Vec3::Z)) / (2.0 * h)
}

/// Posed-space unit normal from a canonical SDF gradient and the skinning rotation.
pub fn posed_normal(rotation: Mat3, gradient: Vec3) -> Vec3 {
    (rotation * gradient.normalize_or_zero()).normalize_or_zero()
}

/// Tensor form of [`posed_normal`]: gradients `[P, 3]`, rotations `[P, 3, 3]` (row-major) →
/// unit normals `[P, 3]`, differentiable.
pub fn posed_normals(rotations: Tensor<3>, gradients: Tensor<2>) -> Tensor<2> {
    let p = gradients.dims()[0];
    let unit = gradients.clone() / (gradients.powf_scalar(2.0).sum_dim(1) + 1e-12).sqrt();
    let n = rotations.matmul(unit.unsqueeze_dim::<3>(2)).reshape([p, 3]);
    n.clone() / (n.powf_scalar(2.0).sum_dim(1) + 1e-12).sqrt()
}
