//! Downloads: the avatar as a textured, skinned, animated .glb or a VRM 1.0 .vrm, motions
//! as .vrma.
//!
//! - [`gltf_export`]: avatars and bodies as .glb (textured, skinned, animated)
//! - [`vrm_export`]: VRM 1.0 avatars and VRM animations
//! - [`skin_export`]: the skeleton and skin weights as a glTF skin, motions as glTF clips
//! - [`uv_atlas`]: texture atlas (the body's UVs transferred, own charts off the body), bake

pub mod gltf_export;
pub mod skin_export;
pub mod uv_atlas;
pub mod vrm_export;
