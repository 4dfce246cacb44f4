//! Why a fit cannot run (the input's and the fit's errors in one type).

use super::framing::FramingError;
use super::landmarks::LandmarkError;
use crate::body::body_surface::SurfaceError;
use crate::generator::readback::ReadbackError;

/// Why a fit cannot run.
#[derive(Debug, thiserror::Error)]
pub enum FitError {
    #[error(transparent)]
    Landmarks(#[from] LandmarkError),
    #[error(transparent)]
    Framing(#[from] FramingError),
    #[error(transparent)]
    Surface(#[from] SurfaceError),
    #[error(transparent)]
    Readback(#[from] ReadbackError),
    #[error("the mask has {got} values, its size {width}×{height} needs {}", width * height)]
    MaskSize { got: usize, width: usize, height: usize },
    #[error("too few landmarks to fit: {0}")]
    TooFew(String),
    #[error("the fit cannot be refined: {0}")]
    Refit(String),
}
