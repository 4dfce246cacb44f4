//! What the body fit observes ([`FitInput`]): a detector's landmarks and person mask in the
//! reference camera's NDC of a photo's crop ([`Framing`]).

use glam::Vec3;

use super::error::FitError;
use super::framing::Framing;
use super::init::camera_axes;
use super::landmarks::{PoseResult, SegmentationMask, NUM_LANDMARKS, VISIBLE};
use super::options::FitOptions;
use crate::body::body_model::BodyModel;

/// What the fit observes, in the reference camera's NDC of a [`Framing`].
#[derive(Clone, Debug)]
pub struct FitInput {
    pub framing: Framing,
    /// Per MediaPipe landmark: NDC position and visibility.
    pub points: Vec<([f32; 2], f32)>,
    /// MediaPipe's world landmarks in camera axes, if the detector gave them.
    pub world: Option<Vec<Vec3>>,
    /// The person mask in the crop, `silhouette_size²`, 0..1.
    pub mask: Option<Vec<f32>>,
    /// Degrees clockwise the photo was turned for the detection ([`super::turn`]): the
    /// framing and the points are of the turned photo.
    pub rotation: u16,
}

/// The landmarks of the hands, as (left, right) pairs: wrist, pinky, index, thumb.
pub const HAND_SWAP: [(usize, usize); 4] = [(15, 16), (17, 18), (19, 20), (21, 22)];

impl FitInput {
    /// Whether the detector's hand sides are in doubt: one wrist hidden, the other seen.
    /// A hand that crosses the body (arms folded, a hand on the far shoulder) seen from the
    /// side is often given the hidden hand's label.
    pub fn hands_in_doubt(&self) -> bool {
        let seen = |l: usize| self.points[l].1 >= VISIBLE;
        self.points.len() == NUM_LANDMARKS && seen(15) != seen(16)
    }

    /// The same observations with the hands' sides swapped ([`HAND_SWAP`]).
    pub fn with_hands_swapped(&self) -> Self {
        let mut out = self.clone();
        for (a, b) in HAND_SWAP {
            out.points.swap(a, b);
            if let Some(w) = out.world.as_mut() {
                w.swap(a, b);
            }
        }
        out
    }

    /// From a detector result on a `width × height` photo and, optionally, a person mask
    /// (any resolution, covering the photo); without one, the result's own
    /// `segmentationMask` is used when it has one.
    pub fn from_detection(
        result: &PoseResult,
        width: usize,
        height: usize,
        mask: Option<&SegmentationMask>,
        model: &BodyModel,
        options: &FitOptions,
    ) -> Result<Self, FitError> {
        result.validate()?;
        let framing = Framing::from_landmarks(&result.pose_landmarks, width, height, model)?;
        Self::framed(result, framing, mask, options)
    }

    /// From a detector result seen through a given crop of its photo (a video's frames share
    /// one crop, so that the camera, and with it the root's path, is the same in all of them).
    pub fn framed(
        result: &PoseResult,
        framing: Framing,
        mask: Option<&SegmentationMask>,
        options: &FitOptions,
    ) -> Result<Self, FitError> {
        result.validate()?;
        let (width, height) = (framing.photo_width, framing.photo_height);
        let points = result
            .pose_landmarks
            .iter()
            .map(|l| (framing.to_ndc([l.x * width as f32, l.y * height as f32]), l.visibility))
            .collect();
        let world = result.pose_world_landmarks.as_ref().map(|w| w.iter().map(camera_axes).collect());
        let mask = match mask.or(result.segmentation_mask.as_ref()) {
            Some(m) if m.data.len() != m.width * m.height || m.data.is_empty() => {
                return Err(FitError::MaskSize { got: m.data.len(), width: m.width, height: m.height });
            }
            Some(m) => Some(framing.resample_mask(&m.data, m.width, m.height, options.silhouette_size)),
            None => None,
        };
        Ok(Self { framing, points, world, mask, rotation: result.rotation })
    }
}
