//! Differentiable versions of the rendering and extraction stages, on burn tensors (paper
//! Sec. 4.3–4.5: gradients reach the SDF, the DMTet offsets and the texture/normal fields
//! through rendered images). The split follows nvdiffrast:
//!
//! - discrete decisions (which tet edges the surface crosses, which triangle covers which
//!   pixel, which pixel pairs straddle a silhouette) are made on the CPU from detached
//!   values ([`crate::geometry::marching_tets`], [`crate::render::rasterize::rasterize`]);
//! - everything continuous is recomputed with tensor ops from those decisions, so autodiff
//!   differentiates it: DMTet vertex positions from grid positions and SDF values
//!   ([`dmtet::surface_points`]), perspective-correct barycentrics from clip-space positions
//!   ([`rasterize::interpolate`]), and silhouette-edge blending ([`rasterize::antialias`]).
//!
//! [`avatar`] (feature `autodiff`, native and wasm32) puts them together: generated avatars rendered to RGB, normal
//! and mask images under dataset labels, with the geometry regularisers;
//! [`scan_supervision`] (feature `train`, not in the paper) the reconstruction warm-up's
//! canonical-space texture and SDF terms from the training scans.
//!
//! The functions are backend-agnostic (`Tensor<D>` on any `Device`); gradients need a device
//! with autodiff (`Device::autodiff()`, feature `train`).

#[cfg(feature = "autodiff")]
pub mod avatar;
pub mod body_model;
pub mod dmtet;
pub mod rasterize;
#[cfg(feature = "train")]
pub mod scan_supervision;

use burn::tensor::{Device, Int, Tensor, TensorData};

/// An index tensor from `u32` indices.
pub fn index_tensor(idx: &[u32], device: &Device) -> Tensor<1, Int> {
    let v: Vec<i64> = idx.iter().map(|&i| i as i64).collect();
    Tensor::from_data(TensorData::new(v, [idx.len()]), device)
}

/// A `[n, c]` float tensor from row-major data.
pub fn matrix(data: Vec<f32>, n: usize, c: usize, device: &Device) -> Tensor<2> {
    Tensor::from_data(TensorData::new(data, [n, c]), device)
}
