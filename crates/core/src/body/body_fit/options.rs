//! The body fit's settings: term weights, stages, learning rate (plain data, serialised into
//! `fit.json` and accepted by the app's automation hook; no burn needed).

use serde::{Deserialize, Serialize};

/// Weights of the fit's terms (relative to one squared pixel of a 256² crop).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FitWeights {
    /// Geman–McClure scale σ, pixels of a 256² crop.
    pub robust_sigma: f32,
    /// L2 on the body pose θ₁…θ₂₃ (radians²).
    pub pose: f32,
    /// L2 (radians²) on the collars' rotation ([`super::limits::COLLARS`]), on top of `pose`.
    pub collar: f32,
    /// SMPLify's angle prior on elbows and knees.
    pub hinge: f32,
    /// L2 (radians²) on the sideways bend of elbows and knees: the rotation about the axis
    /// that is neither the hinge's nor the bone's, which these joints do not have.
    pub hinge_side: f32,
    /// Squared excess (radians²) of the thighs' and shins' twists beyond their ranges
    /// ([`super::limits::RANGES`]).
    pub ranges: f32,
    /// L2 on β. A single photo says little about shape, and a free β explains a limb or torso
    /// foreshortened in depth as a shorter one: at 2 the fixture sets' PA-MPJPE is 44.9 / 51.2 mm
    /// and their β error 0.75 against 46.6 / 53.4 mm and 0.97 at 0.5 (docs/benchmarks.md).
    pub betas: f32,
    /// Weight of the bone term: the detector's 3D bone directions (world landmarks), read as
    /// [`FitWeights::bones_form`] says.
    pub bones: f32,
    /// How the bone term reads the detector's directions.
    pub bones_form: BoneForm,
    /// Factor on `bones` for the leg bones lifted from their 2D landmarks where the detector
    /// misread their depth (`body_fit::input::leg_readings`).
    pub bones_lifted: f32,
    /// Squared difference (radians²) of a hidden limb's joint rotations to the mirror image
    /// of its seen counterpart's, scaled by how hidden the one and how seen the other is.
    pub symmetry: f32,
    /// Squared mask difference summed over the crop, per pixel of a 256² crop.
    pub silhouette: f32,
    /// Relative weight of person pixels the body leaves uncovered (clothes and hair widen a
    /// person beyond the body; body pixels outside the person weigh 1).
    pub silhouette_uncovered: f32,
}

impl Default for FitWeights {
    fn default() -> Self {
        Self {
            robust_sigma: 40.0,
            pose: 1.2,
            collar: 10.0,
            hinge: 1.0,
            hinge_side: 5.0,
            ranges: 20.0,
            betas: 2.0,
            bones: 10.0,
            bones_form: BoneForm::Direction,
            bones_lifted: 3.0,
            symmetry: 20.0,
            silhouette: 0.2,
            silhouette_uncovered: 0.45,
        }
    }
}

/// How the bone term compares a fitted bone with the detector's direction of it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BoneForm {
    /// Squared difference of the unit directions (a cold fit: the detector's directions also
    /// say where a limb the image leaves in doubt goes).
    #[default]
    Direction,
    /// Squared shortfall of the bone's depth part (its unit direction's component along the
    /// camera's axis) below the detector's, on the detector's side; a bone may leave the image
    /// plane further than the detector says, never less, and the image says the rest.
    /// MediaPipe's world landmarks flatten depth: a squatting thigh that comes 30 cm towards
    /// the camera reads as 6 cm. A warm-started video frame uses this form (the previous
    /// frame holds what the image leaves in doubt; [`super::video::VideoFitOptions`]).
    DepthFloor,
}

/// Settings of the fit.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FitOptions {
    /// β components fitted (0 keeps the mean shape).
    pub num_betas: usize,
    /// Adam steps of the torso, body and silhouette stages.
    pub iterations: [usize; 3],
    /// Adam's learning rate (radians, metres and β units per step, roughly).
    pub learning_rate: f32,
    /// Side of the silhouette stage's mask, pixels.
    pub silhouette_size: usize,
    pub weights: FitWeights,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self {
            num_betas: 10,
            iterations: [60, 300, 80],
            learning_rate: 0.02,
            silhouette_size: 128,
            weights: FitWeights::default(),
        }
    }
}
