//! # getavatar-core
//!
//! The shared core of GETAvatar (Zhang et al., ICCV 2023), compiled natively and to wasm32.
//! Each module is one stage of the paper; read them in this order:
//!
//! | paper                                   | module |
//! |-----------------------------------------|--------|
//! | Sec. 3, SMPL body model (layout, β)     | [`body_model`] (+ [`npz`] for the file format) |
//! | Sec. 3 eq. 1, LBS; eq. 2 blended transforms | [`skinning`] |
//! | canonical "Da-pose", named poses        | [`pose_library`] |
//! | Sec. 4.4 camera                         | [`camera`] |
//! | Sec. 4.2 template SDF, inverse skinning (eq. 2); 4.3 DMTet; eq. 4 normals | [`geometry`] |
//! | nearest-vertex search for inverse skinning | [`spatial`] |
//! | mesh download (.glb)                    | [`gltf_export`] |
//!
//! Conventions (metres, y up, camera looks down −Z, (n+1)/2 normal maps, Da-pose) are in
//! `docs/conventions.md`. Shared code never blocks, touches files or spawns threads: it takes
//! bytes in and gives bytes out, so the browser app and the native trainer call it alike.

pub mod body_model;
pub mod camera;
pub mod geometry;
pub mod gltf_export;
pub mod npz;
pub mod pose_library;
pub mod skinning;
pub mod spatial;

pub use body_model::{BodyModel, BodyModelError, JOINT_NAMES, NUM_JOINTS};
pub use camera::OrbitCamera;
pub use skinning::{pose_body, BodyParams, PosedBody};
