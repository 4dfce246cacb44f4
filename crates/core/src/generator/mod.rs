//! The generator G (paper Sec. 4) and what trains it; burn, on the caller's `Device`.
//!
//! - [`network`]: mapping, triplane synthesis, decoders, discriminator (Sec. 4.1)
//! - [`pipeline`]: latents → triplanes → SDF → inverse skinning → DMTet → textured posed mesh
//! - [`fields`]: SDF = template + residual and DMTet offsets on the grid's field band (Sec. 4.2)
//! - [`normal_field`]: eq. 4 normals (∇SDF rotated by skinning)
//! - [`dmtet_gpu`]: marching tetrahedra's compaction on the GPU for a new identity
//! - [`rigging`]: re-posing an extracted avatar by LBS (the app's fast path)
//! - [`losses`]: Sec. 4.5 objective (adversarial, R1, eikonal, SDF cross-entropy)
//! - [`optim`]: Adam with per-group learning rates (feature `autodiff`)
//! - [`checkpoint`]: weights and optimiser state as safetensors
//! - [`readback`]: tensor read-backs as `Result`, never empty vectors

pub mod checkpoint;
pub mod dmtet_gpu;
pub mod fields;
pub mod losses;
pub mod network;
pub mod normal_field;
#[cfg(feature = "autodiff")]
pub mod optim;
pub mod pipeline;
pub mod readback;
pub mod rigging;
