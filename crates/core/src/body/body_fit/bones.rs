//! The 3D bone-direction term's rows: MediaPipe's world landmarks as limb directions, kept,
//! weakened or lifted from the 2D landmarks where the detector misread a leg's depth
//! ([`super::input::leg_readings`]), and the start of a leg whose thigh it misread.

use glam::Vec3;

use super::init::pose_from_world;
use super::input::{leg_readings, FitInput, MISREAD};
use crate::body::body_model::{BodyModel, NUM_JOINTS};
use crate::body::skinning::BodyParams;

/// Limb bones of the 3D direction term: (parent joint, child joint, landmarks). Ordered so
/// that bone `i ^ 2` is bone `i`'s left/right counterpart (the symmetry term's pairing).
pub(super) const BONES: [(usize, usize, usize, usize); 8] = [
    (16, 18, 11, 13),
    (18, 20, 13, 15),
    (17, 19, 12, 14),
    (19, 21, 14, 16),
    (1, 4, 23, 25),
    (4, 7, 25, 27),
    (2, 5, 24, 26),
    (5, 8, 26, 28),
];

/// The thighs of [`BONES`].
pub(super) const THIGHS: [(usize, usize, usize, usize); 2] = [BONES[4], BONES[6]];

/// Limb chords of the 3D direction term: (root joint, end joint, landmarks of root, middle
/// and end). When the middle (elbow, knee) is hidden, its bones' directions are the
/// detector's guesses, while the chord from a seen shoulder to a seen wrist still says where
/// the hand is: across the chest or before its own shoulder, which a side view cannot tell.
pub(super) const CHORDS: [(usize, usize, usize, usize, usize); 4] =
    [(16, 20, 11, 13, 15), (17, 21, 12, 14, 16), (1, 7, 23, 25, 27), (2, 8, 24, 26, 28)];

/// One row of the bone term: the body's bone (parent joint, child joint), the direction it
/// is pulled towards (camera axes) and the row's weight.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct BoneRow {
    pub bone: (usize, usize),
    pub direction: Vec3,
    pub weight: f32,
}

/// The bone term's rows for a fit starting at `posed` (β = 0) seen through `cam`: every bone
/// of [`BONES`] at the detector's direction, weighted by its ends' visibility and by how far
/// its depth reading holds ([`leg_readings`]); each limb's chord of [`CHORDS`], weighted by
/// how seen its ends are and how hidden its middle is; and the legs' bones lifted from their
/// 2D landmarks, at `lifted` times their weight. Empty without world landmarks.
pub(super) fn bone_rows(posed: &[Vec3; NUM_JOINTS], cam: Vec3, input: &FitInput, lifted: f32) -> Vec<BoneRow> {
    let Some(world) = input.world.as_ref() else {
        return Vec::new();
    };
    let vis = |l: usize| input.points[l].1;
    let readings = leg_readings(posed, cam, &input.points, world, &BONES);
    let detected = |from: usize, to: usize| (world[to] - world[from]).normalize_or(Vec3::ZERO);
    let row = |bone, direction, weight| BoneRow { bone, direction, weight };
    let lifted = BONES
        .iter()
        .zip(&readings)
        .filter_map(|(b, r)| r.lifted.map(|(d, w)| row((b.0, b.1), d, vis(b.2).min(vis(b.3)) * w * lifted)));
    BONES
        .iter()
        .zip(&readings)
        .map(|(b, r)| row((b.0, b.1), detected(b.2, b.3), vis(b.2).min(vis(b.3)) * r.agreement))
        .chain(CHORDS.iter().map(|c| row((c.0, c.1), detected(c.2, c.4), vis(c.2).min(vis(c.4)) * (1.0 - vis(c.3)))))
        .chain(lifted)
        .filter(|r| r.weight > 0.0)
        .collect()
}

/// The start `init` (from the world landmarks, seen through `cam`) with each leg whose thigh's
/// depth the detector misread ([`MISREAD`]) at rest, or `None` when no thigh is: its world
/// landmarks would start it in the wrong basin (kneeling seen from behind: the forward leg's
/// thigh read as hanging down, its shin as pointing at the camera).
pub(super) fn misread_legs_at_rest(
    model: &BodyModel,
    input: &FitInput,
    init: &BodyParams,
    cam: Vec3,
) -> Option<BodyParams> {
    let world = input.world.as_ref()?;
    let posed = super::init::posed_joints(model, init);
    let readings = leg_readings(&posed, cam, &input.points, world, &THIGHS);
    if readings.iter().all(|r| r.agreement >= MISREAD) {
        return None;
    }
    let mut vis: Vec<f32> = input.points.iter().map(|p| p.1).collect();
    for (b, r) in THIGHS.iter().zip(&readings) {
        if r.agreement < MISREAD {
            // An unseen knee leaves its limb at rest.
            vis[b.3] = 0.0;
        }
    }
    Some(pose_from_world(model, world, &vis, &init.betas))
}
