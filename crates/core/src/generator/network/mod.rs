//! The generator networks (paper Sec. 4.1, StyleGAN2-style), written once on burn's
//! device-dispatched `Tensor<D>`: the `Device` chosen at run time (NdArray on CPU, Wgpu
//! natively and in the browser) decides where they run.
//!
//! - [`config`]: sizes (`paper`, `demo`, `tiny` presets), all config values
//! - [`ndarray_ops`]: the convolution on NdArray as one operation with its own backward pass
//! - [`cube_ops`]: generation's element-wise chains as single kernels on wgpu/WebGPU
//! - [`layers`]: equalised-lr fully connected layers, modulated convs and modulated FCs
//! - [`mapping`]: z → w mapping networks with tracked w_avg and truncation ψ
//! - [`synthesis`]: the triplane backbone (w_geo) with to-geometry (w_geo) / to-texture (w_tex) outputs
//! - [`triplane`]: plane sampling at canonical points (xy, yz, xz; bilinear; summed)
//! - [`face_plane`]: a fine texture-feature plane over the canonical face alone (not in the paper)
//! - [`generator_network`]: all of the above as the generator's one module, and its styles (W+)
//! - [`decoders`]: SDF residual, DMTet offset and texture decoders, to-RGB
//! - [`discriminator`]: the camera-conditioned StyleGAN2 residual discriminator (RGB, normal, mask)
//!
//! Weights are initialised from a seed by our own RNG on the CPU, so every backend starts from
//! bit-identical parameters.

pub mod config;
#[cfg(feature = "wgpu")]
pub mod cube_ops;
pub mod decoders;
pub mod discriminator;
pub mod face_plane;
pub mod generator_network;
pub mod init;
pub mod layers;
pub mod mapping;
#[cfg(feature = "ndarray")]
pub mod ndarray_ops;
pub mod synthesis;
pub mod triplane;

pub use config::GeneratorConfig;
