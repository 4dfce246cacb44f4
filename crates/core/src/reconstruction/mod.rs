//! A photo → an avatar (paper Sec. 5.4 and the product's additions).
//!
//! - [`encoder`]: the feed-forward first guess of the W+ codes from the framed photo and the
//!   fitted body (feature `generator`/`wgpu`)
//! - [`inversion`]: W+ optimisation and pivotal tuning (feature `autodiff`)
//! - [`photo_projection`]: the photo's colours projected onto the reconstruction

#[cfg(any(feature = "generator", feature = "wgpu"))]
pub mod encoder;
#[cfg(all(feature = "autodiff", any(feature = "generator", feature = "wgpu")))]
pub mod inversion;
pub mod photo_projection;
