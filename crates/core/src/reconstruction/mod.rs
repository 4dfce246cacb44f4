//! A photo → an avatar (paper Sec. 5.4 and the product's additions).
//!
//! - [`encoder`]: the feed-forward first guess of the W+ codes from the framed photo and the
//!   fitted body (feature `generator`/`wgpu`)
//! - [`garment_codes`]: W+ geometry codes of dresses and skirts, weighed against the guess's
//!   geometry at the photo's camera (feature `autodiff`)
//! - [`inversion`]: W+ optimisation and pivotal tuning (feature `autodiff`)
//! - [`photo_projection`]: the photo's colours projected onto the reconstruction
//! - [`silhouette_snap`]: the avatar's outline moved onto the photo's person, before the projection

#[cfg(any(feature = "generator", feature = "wgpu"))]
pub mod encoder;
#[cfg(all(feature = "autodiff", any(feature = "generator", feature = "wgpu")))]
pub mod garment_codes;
#[cfg(all(feature = "autodiff", any(feature = "generator", feature = "wgpu")))]
pub mod inversion;
pub mod photo_projection;
pub mod silhouette_snap;
