//! File formats read and written as bytes (shared code never touches files).
//!
//! - [`npz`]: NumPy .npz/.npy (SMPL, AMASS)
//! - [`scan`]: 3D scans (OBJ + MTL + textures + fitted body) and their renders
//! - [`named_tensor`]: tensors by name (checkpoints, optimiser state)
//! - [`dataset`]: the training data's cameras and labels (feature `dataset`)

#[cfg(feature = "dataset")]
pub mod dataset;
#[cfg(any(feature = "ndarray", feature = "autodiff", feature = "wgpu"))]
pub mod named_tensor;
pub mod npz;
pub mod scan;
