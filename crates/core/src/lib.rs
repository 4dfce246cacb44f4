//! # getavatar-core
//!
//! The shared core of GETAvatar (Zhang et al., ICCV 2023), compiled natively and to wasm32.
//! One folder per concept of the paper; read them in this order:
//!
//! | paper | module |
//! |-------|--------|
//! | Sec. 3 SMPL body, eq. 1–2 skinning, named poses, motions; photo/video → body fit | [`body`] |
//! | Sec. 4.2 template SDF, inverse skinning; 4.3 tet grid and DMTet (CPU reference) | [`geometry`] |
//! | Sec. 4 generator: networks, fields, normal field, DMTet on GPU, rigging, losses (feature `generator`/`wgpu`) | `generator` |
//! | Sec. 4.4 camera, rasterize / interpolate / antialias (CPU and differentiable) | [`render`] |
//! | Sec. 5.4 photo → avatar: encoder, W+ inversion and PTI, photo projection | [`reconstruction`] |
//! | .glb, .vrm, .vrma downloads and the texture atlas | [`export`] |
//! | file formats as bytes: .npz, scans, named tensors, the dataset | [`io`] |
//! | seeded randomness, stage timings, yielding to the browser | [`util`] |
//!
//! Conventions (metres, y up, camera looks down −Z, (n+1)/2 normal maps, Da-pose) are in
//! `docs/conventions.md`. Shared code never blocks, touches files or spawns threads: it takes
//! bytes in and gives bytes out, so the browser app and the native trainer call it alike.

pub mod body;
pub mod export;
#[cfg(any(feature = "generator", feature = "wgpu"))]
pub mod generator;
pub mod geometry;
pub mod io;
pub mod reconstruction;
pub mod render;
pub mod util;

pub use body::body_model::{BodyModel, BodyModelError, JOINT_NAMES, NUM_JOINTS};
pub use body::skinning::{pose_body, BodyParams, PosedBody};
/// The burn version the networks are written against, re-exported for callers.
#[cfg(any(feature = "generator", feature = "wgpu"))]
pub use burn;
pub use render::camera::OrbitCamera;
