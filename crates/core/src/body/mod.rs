//! The body (paper Sec. 3): SMPL's layout and shape space, linear blend skinning, named
//! poses and motion clips, and the fit of a body to a photo's or a video's landmarks.
//!
//! - [`body_model`]: SMPL layout (24 joints, 6,890 vertices), β blend shapes, joint regressor
//! - [`body_surface`]: surface landmarks (nose, eyes, ears, heels, toes) as body vertices
//! - [`skinning`]: eq. 1 LBS and eq. 2 blended transforms; [`skinning::pose_body`]
//! - [`pose_library`]: the canonical Da-pose and named poses
//! - [`motion`]: motion clips (built-in keyframed, SMPL/AMASS .npz)
//! - [`humanoid`]: the SMPL joints as VRM humanoid bones
//! - [`body_fit`]: photo/video → body (MediaPipe landmarks → SMPL pose, shape, camera)

pub mod body_fit;
pub mod body_model;
pub mod body_surface;
pub mod humanoid;
pub mod motion;
pub mod pose_library;
pub mod skinning;
