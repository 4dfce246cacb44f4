//! Photo → body: the SMPL pose, shape and camera that explain a
//! person's detected landmarks and mask, for the latent inversion that follows.
//!
//! - `bones`: the fit's 3D bone-direction term from the detector's world landmarks.
//! - [`correction`]: a re-fit that holds the limbs a person corrected.
//! - [`landmarks`]: MediaPipe Pose's 33 landmarks, their SMPL joints and the detector's
//!   result object (validated).
//! - [`limits`]: knees and elbows bend one way (SMPLify's angle prior, directions checked on
//!   this body).
//! - [`metrics`]: Procrustes alignment and PA-MPJPE, the fit's yardstick.
//! - [`options`]: the fit's settings (term weights, stages).
//! - [`refit`]: the fit refined on a generated avatar's clothed outline.
//! - `targets`: the landmarks, bone directions and symmetry rows as the fit's tensors.
//! - [`temporal`]: a video's per-frame fits as one motion (lost frames filled, smoothed
//!   without lag) and the yardsticks of a motion against its truth.
//! - [`video`]: a clip's detections → one body shape and a warm-started fit per frame.
//! - [`turn`]: a photo turned by quarter turns so that its person is upright, and the map
//!   back to the photo as taken.

#[cfg(all(feature = "autodiff", any(feature = "generator", feature = "wgpu")))]
mod bones;
#[cfg(all(feature = "autodiff", any(feature = "generator", feature = "wgpu")))]
pub mod correction;
#[cfg(all(feature = "autodiff", any(feature = "generator", feature = "wgpu")))]
pub mod error;
#[cfg(all(feature = "autodiff", any(feature = "generator", feature = "wgpu")))]
pub mod fit;
pub mod framing;
pub mod init;
#[cfg(all(feature = "autodiff", any(feature = "generator", feature = "wgpu")))]
pub mod input;
pub mod landmarks;
pub mod limits;
pub mod metrics;
pub mod options;
#[cfg(all(feature = "autodiff", any(feature = "generator", feature = "wgpu")))]
pub mod refit;
#[cfg(all(feature = "autodiff", any(feature = "generator", feature = "wgpu")))]
pub mod result;
/// The surface landmarks live with the body ([`crate::body::body_surface`]); this path stays.
pub use crate::body::body_surface as surface;
pub mod synthetic;
#[cfg(all(feature = "autodiff", any(feature = "generator", feature = "wgpu")))]
mod targets;
pub mod temporal;
pub mod turn;
#[cfg(all(feature = "autodiff", any(feature = "generator", feature = "wgpu")))]
pub mod video;
