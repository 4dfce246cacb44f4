//! Cameras and rendering (paper Sec. 4.4), modelled on nvdiffrast's primitives.
//!
//! - [`camera`]: the orbit camera (the dataset protocol's views)
//! - [`rasterize`]: rasterize / interpolate on the CPU (the reference)
//! - [`diff`]: differentiable DMTet, interpolate, antialias on burn tensors (Sec. 4.3–4.5)
//! - [`colour`]: the exact sRGB curve, scalar and tensor

pub mod camera;
pub mod colour;
#[cfg(any(feature = "generator", feature = "wgpu"))]
pub mod diff;
pub mod rasterize;
