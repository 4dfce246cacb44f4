//! # getavatar-core
//!
//! The shared core of GETAvatar (Zhang et al., ICCV 2023), compiled natively and to wasm32.
//! Each module is one stage of the paper; read them in this order:
//!
//! | paper                                   | module |
//! |-----------------------------------------|--------|
//! | Sec. 3, SMPL body model (layout, β)     | [`body_model`] (+ [`npz`] for the file format) |
//! | the body's surface landmarks (nose, eyes, ears, heels, toes as vertices) | [`body_surface`] |
//! | Sec. 3 eq. 1, LBS; eq. 2 blended transforms | [`skinning`] |
//! | canonical "Da-pose", named poses        | [`pose_library`] |
//! | Sec. 4.4 camera                         | [`camera`] |
//! | Sec. 4.2 template SDF, inverse skinning (eq. 2); 4.3 DMTet; eq. 4 normals | [`geometry`] |
//! | nearest-vertex search for inverse skinning | [`spatial`] |
//! | maps keyed by mesh ids (a fast hasher, for DMTet's edges and the rigging) | [`id_map`] |
//! | Sec. 4.1 mapping, triplane synthesis, decoders (burn; feature `generator`/`wgpu`) | `network` |
//! | Sec. 4 generator end to end (triplanes → SDF → DMTet → textured posed mesh) | `generator` |
//! | Sec. 4.2 SDF = template + residual, DMTet offsets on the grid's field band | `fields` (+ `geometry::posed_grid`) |
//! | eq. 4 normal field (∇SDF rotated by skinning) | `normal_field` |
//! | re-posing an extracted avatar by LBS (the app's fast path) | `rigging` |
//! | tensor read-backs as `Result` (never empty vectors) | `readback` |
//! | tensors by name (checkpoints, optimiser state) | [`named_tensor`] |
//! | Sec. 4.4 rendering (nvdiffrast-style rasterize / interpolate, CPU reference) | [`rasterize`] |
//! | Sec. 4.3–4.5 differentiable DMTet, interpolate, antialias (burn tensors) | `diff` |
//! | Sec. 4.5 objective: adversarial, R1 (finite differences), eikonal, SDF cross-entropy | `losses` (+ `network::discriminator`) |
//! | mesh download (.glb): textured, skinned, animated | [`gltf_export`] |
//! | VRM 1.0 avatars (.vrm) and VRM animations (.vrma); the SMPL joints as humanoid bones | [`vrm_export`], [`humanoid`] |
//! | motion clips (built-in keyframed, SMPL/AMASS .npz) | [`motion`] |
//! | texture atlas (the body's UVs transferred, own charts off the body) and the bake | [`uv_atlas`] |
//! | Sec. 5 data: scans (OBJ), procedural textures, dataset cameras and labels | [`scan`], `dataset` (feature `dataset`) |
//! | seeded randomness, identical on every platform | [`rng`] |
//! | colour encoding (exact sRGB curve, scalar and tensor) | [`colour`] |
//! | Sec. 5.4 single-image reconstruction: W+ inversion, pivotal tuning (feature `autodiff`; native and browser) | `inversion` |
//! | the photo's colours projected onto the reconstruction (product) | [`photo_projection`] |
//! | photo → body (product, not in the paper): MediaPipe landmarks → SMPL joints | [`body_fit`] |
//!
//! Conventions (metres, y up, camera looks down −Z, (n+1)/2 normal maps, Da-pose) are in
//! `docs/conventions.md`. Shared code never blocks, touches files or spawns threads: it takes
//! bytes in and gives bytes out, so the browser app and the native trainer call it alike.

pub mod body_fit;
pub mod body_model;
pub mod body_surface;
pub mod camera;
#[cfg(any(feature = "generator", feature = "wgpu"))]
pub mod checkpoint;
pub mod colour;
pub mod cooperative;
#[cfg(feature = "dataset")]
pub mod dataset;
#[cfg(any(feature = "generator", feature = "wgpu"))]
pub mod diff;
#[cfg(any(feature = "generator", feature = "wgpu"))]
pub mod dmtet_gpu;
#[cfg(any(feature = "generator", feature = "wgpu"))]
pub mod encoder;
#[cfg(any(feature = "generator", feature = "wgpu"))]
pub mod fields;
#[cfg(any(feature = "generator", feature = "wgpu"))]
pub mod generator;
pub mod geometry;
pub mod gltf_export;
pub mod humanoid;
pub mod id_map;
#[cfg(all(feature = "autodiff", any(feature = "generator", feature = "wgpu")))]
pub mod inversion;
#[cfg(any(feature = "generator", feature = "wgpu"))]
pub mod losses;
pub mod motion;
pub mod named_tensor;
#[cfg(any(feature = "generator", feature = "wgpu"))]
pub mod network;
#[cfg(any(feature = "generator", feature = "wgpu"))]
pub mod normal_field;
pub mod npz;
#[cfg(all(feature = "autodiff", any(feature = "generator", feature = "wgpu")))]
pub mod optim;
pub mod photo_projection;
pub mod pose_library;
pub mod profile;
pub mod rasterize;
#[cfg(any(feature = "generator", feature = "wgpu"))]
pub mod readback;
#[cfg(any(feature = "generator", feature = "wgpu"))]
pub mod rigging;
pub mod rng;
pub mod scan;
pub mod skin_export;
pub mod skinning;
pub mod spatial;
pub mod uv_atlas;
pub mod vrm_export;

pub use body_model::{BodyModel, BodyModelError, JOINT_NAMES, NUM_JOINTS};
/// The burn version the networks are written against, re-exported for callers.
#[cfg(any(feature = "generator", feature = "wgpu"))]
pub use burn;
pub use camera::OrbitCamera;
pub use skinning::{pose_body, BodyParams, PosedBody};
