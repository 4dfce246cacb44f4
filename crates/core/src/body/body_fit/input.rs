//! What the body fit observes ([`FitInput`]): a detector's landmarks and person mask in the
//! reference camera's NDC of a photo's crop ([`Framing`]).

use glam::Vec3;

use super::error::FitError;
use super::framing::Framing;
use super::init::camera_axes;
use super::landmarks::{PoseResult, SegmentationMask, NUM_LANDMARKS, VISIBLE};
use super::options::FitOptions;
use crate::body::body_model::{BodyModel, NUM_JOINTS};
use crate::render::camera::reference_fov_y;

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
    /// Landmarks the detector saw where the person mask has no person ([`off_person`]):
    /// detector errors, taken as unseen (visibility 0 in `points`).
    pub off_person: Vec<usize>,
}

/// How far outside the person mask, as a fraction of the crop's side, a seen landmark may lie
/// before the fit takes it as the detector's error. On the photo fixtures, the only landmarks
/// this far out are a jumping jack's arms that MediaPipe put over the head (2.6–7.6 % of the
/// photo's height from the mask that shows them spread; with the arms taken as unseen the fit
/// follows the mask: 106.6 → 73.4 mm); every other landmark of the 42 fixtures is within
/// 1.5 %.
pub const OFF_PERSON: f32 = 0.03;

/// Per limb: its end landmarks (wrist and fingers, ankle and foot) and the landmarks a
/// misplaced end puts in doubt with it (the elbow or knee, and the ends).
const LIMBS: [(&[usize], &[usize]); 4] = [
    (&[15, 17, 19, 21], &[13, 15, 17, 19, 21]),
    (&[16, 18, 20, 22], &[14, 16, 18, 20, 22]),
    (&[27, 29, 31], &[25, 27, 29, 31]),
    (&[28, 30, 32], &[26, 28, 30, 32]),
];

/// The seen landmarks (visibility ≥ [`VISIBLE`]) inside the photo that lie farther than
/// [`OFF_PERSON`] of the crop from every person pixel (mask ≥ 0.5) of `mask`, the crop's
/// `size`² mask. None when the mask has no person pixel (it says nothing then), nor for
/// landmarks outside the photo (the mask does not reach there).
pub fn off_person(points: &[([f32; 2], f32)], framing: &Framing, mask: &[f32], size: usize) -> Vec<usize> {
    let person: Vec<(f32, f32)> = mask
        .iter()
        .enumerate()
        .filter(|(_, v)| **v >= 0.5)
        .map(|(k, _)| ((k % size) as f32 + 0.5, (k / size) as f32 + 0.5))
        .collect();
    if person.is_empty() || size == 0 {
        return Vec::new();
    }
    let limit = (OFF_PERSON * size as f32).powi(2);
    let in_photo = |ndc: [f32; 2]| {
        let p = framing.to_photo(ndc);
        p[0] >= 0.0 && p[1] >= 0.0 && p[0] <= framing.photo_width as f32 && p[1] <= framing.photo_height as f32
    };
    points
        .iter()
        .enumerate()
        .filter(|(_, (ndc, vis))| *vis >= VISIBLE && in_photo(*ndc))
        .filter(|(_, (ndc, _))| {
            let (x, y) = ((ndc[0] + 1.0) / 2.0 * size as f32, (1.0 - ndc[1]) / 2.0 * size as f32);
            person.iter().all(|(px, py)| (px - x).powi(2) + (py - y).powi(2) > limit)
        })
        .map(|(l, _)| l)
        .collect()
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
        let mut points: Vec<([f32; 2], f32)> = result
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
        let mut off =
            mask.as_ref().map_or_else(Vec::new, |m| off_person(&points, &framing, m, options.silhouette_size));
        // A hand or foot off the person puts its whole limb in doubt: the detector placed the
        // limb, and its middle with it, where the person is not.
        for (ends, limb) in LIMBS {
            if ends.iter().any(|l| off.contains(l)) {
                off.extend(limb.iter().filter(|l| points[**l].1 >= VISIBLE));
            }
        }
        off.sort_unstable();
        off.dedup();
        for &l in &off {
            points[l].1 = 0.0;
        }
        Ok(Self { framing, points, world, mask, rotation: result.rotation, off_person: off })
    }
}

/// The in-plane fractions of a leg bone (MediaPipe's 3D direction against its own 2D landmarks)
/// within which the bone's 3D direction keeps its whole weight, and beyond which it has none.
pub const LEG_FORESHORTENING: (f32, f32) = (0.2, 0.4);

/// How far MediaPipe's 3D direction of leg bone `b` agrees with its own 2D landmarks about how
/// much the bone lies in the image plane: 1 while the two in-plane fractions are within
/// [`LEG_FORESHORTENING`]`.0` of each other, falling to 0 at `.1`. The 2D fraction is the
/// bone's length between its landmarks against the body's bone (β = 0, `posed`) at the initial
/// camera's depth (`cam`), `farther` metres deeper (a shin below a thigh lifted away from the
/// camera is seen smaller). Where they part, the detector has misread the bone's depth (a shin
/// on the ground seen from behind, a raised thigh seen from the front), and the 2D landmarks
/// with the bone's length place it ([`leg_readings`]). Arms keep their weight: crossed
/// forearms are short in 2D where MediaPipe's direction is right.
fn leg_foreshortening_agreement(
    posed: &[Vec3; NUM_JOINTS],
    cam: Vec3,
    points: &[([f32; 2], f32)],
    world: &[Vec3],
    b: (usize, usize, usize, usize),
    farther: f32,
) -> f32 {
    const LEG_JOINTS: [usize; 4] = [1, 2, 4, 5];
    let len = (posed[b.1] - posed[b.0]).length();
    let depth = -(0.5 * (posed[b.0] + posed[b.1]) + cam).z + farther;
    if !LEG_JOINTS.contains(&b.0) || depth <= 0.0 || len <= 0.0 {
        return 1.0;
    }
    let f = 1.0 / (reference_fov_y() / 2.0).tan();
    let (p, q) = (points[b.2].0, points[b.3].0);
    let in_2d = ((q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2)).sqrt() / (f * len / depth);
    let d = (world[b.3] - world[b.2]).normalize_or(Vec3::ZERO);
    let in_3d = (d.x * d.x + d.y * d.y).sqrt();
    let (agree, apart) = LEG_FORESHORTENING;
    let gap = (in_2d.min(1.0) - in_3d).abs();
    (1.0 - (gap - agree) / (apart - agree)).clamp(0.0, 1.0)
}

/// The depth component of MediaPipe's unit direction from which its sign is trusted fully; a
/// bone the detector reads nearly in the image plane says little about which way it leaves it.
pub const LIFT_SIGN_SURE: f32 = 0.25;

/// A thigh whose [`leg_foreshortening_agreement`] is below this has had its depth misread:
/// its leg's world landmarks do not place the initial pose, and the bones below it inherit
/// the doubt ([`leg_readings`]).
pub const MISREAD: f32 = 0.5;

/// One bone's reading for the 3D direction term: how far MediaPipe's own direction is kept
/// (`agreement`: its own [`leg_foreshortening_agreement`] times the bone's above it) and,
/// where it is not, the direction lifted from the 2D landmarks with its weight.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct BoneReading {
    pub agreement: f32,
    pub lifted: Option<(Vec3, f32)>,
}

/// The bones' readings for the 3D direction term, for `bones` in order from the hips and
/// shoulders down (a thigh before its shin).
///
/// A bone below one whose depth the detector misread starts at a misplaced joint, so its
/// direction inherits that doubt (its agreement is multiplied by the one above). Leg bones
/// are lifted from their 2D landmarks (Taylor 2000, under perspective): a bone's upper end
/// lies on its landmark's ray at the initial body's depth (`posed` at β = 0 through the
/// initial camera `cam`) or where the bone above it was lifted to; its lower end where its
/// landmark's ray lies one body bone length from there, on the nearer or farther of the two
/// such points as MediaPipe's 3D direction says (the whole length in the image plane where the
/// landmarks lie farther apart than that). A bone is lifted where the detector's own direction
/// disagrees with its foreshortening, weighted by that disagreement times how sure the
/// detector's sign of depth is ([`LIFT_SIGN_SURE`]); a lifted thigh moves its shin's depth, and
/// so the foreshortening its shin is judged by. Arms keep the detector's directions.
pub(super) fn leg_readings(
    posed: &[Vec3; NUM_JOINTS],
    cam: Vec3,
    points: &[([f32; 2], f32)],
    world: &[Vec3],
    bones: &[(usize, usize, usize, usize)],
) -> Vec<BoneReading> {
    let f = 1.0 / (reference_fov_y() / 2.0).tan();
    let ray = |p: [f32; 2]| Vec3::new(p[0] / f, p[1] / f, -1.0);
    let mut ends: [Option<Vec3>; NUM_JOINTS] = [None; NUM_JOINTS];
    let mut kept = [1.0f32; NUM_JOINTS];
    bones
        .iter()
        .map(|&b| {
            let init_depth = -(posed[b.0] + cam).z;
            let upper = ends[b.0].unwrap_or(ray(points[b.2].0) * init_depth);
            let own = leg_foreshortening_agreement(posed, cam, points, world, b, -upper.z - init_depth);
            let agreement = own * kept[b.0];
            kept[b.1] = agreement;
            let len = (posed[b.1] - posed[b.0]).length();
            let detected = (world[b.3] - world[b.2]).normalize_or(Vec3::ZERO);
            let weight = (1.0 - own) * (detected.z.abs() / LIFT_SIGN_SURE).min(1.0);
            if weight <= 0.0 || upper.z >= 0.0 || len <= 0.0 {
                return BoneReading { agreement, lifted: None };
            }
            let r = ray(points[b.3].0).normalize();
            // |t r − upper| = len: t = r·upper ± √((r·upper)² − |upper|² + len²); farther is larger t.
            let along = r.dot(upper);
            let half = (along * along - upper.length_squared() + len * len).max(0.0).sqrt();
            let t = if detected.z < 0.0 { along + half } else { along - half };
            let d = (r * t - upper).normalize_or(Vec3::ZERO);
            if d == Vec3::ZERO {
                return BoneReading { agreement, lifted: None };
            }
            ends[b.1] = Some(upper + d * len);
            BoneReading { agreement, lifted: Some((d, weight)) }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::body::body_fit::init::posed_joints;
    use crate::body::skinning::BodyParams;

    /// A 100² photo framed whole, its mask (at 100² in the crop) a person's column at
    /// x 40…60: a landmark on it, one just beside it, one far off it, one hidden far off it,
    /// one outside the photo.
    #[test]
    fn landmarks_far_from_the_person_mask_are_off_and_take_their_limb_with_them() {
        let framing = Framing { photo_width: 100, photo_height: 100, centre: [50.0, 50.0], side: 100.0 };
        let size = 100;
        let mask: Vec<f32> = (0..size * size).map(|k| if (40..60).contains(&(k % size)) { 1.0 } else { 0.0 }).collect();
        let at = |x: f32, y: f32, vis: f32| (framing.to_ndc([x, y]), vis);
        let mut points = vec![at(50.0, 50.0, 1.0); NUM_LANDMARKS];
        points[11] = at(62.0, 30.0, 1.0); // 2 px beside the column: within 3 % of the crop
        points[15] = at(85.0, 20.0, 1.0); // the left wrist 25 px off: off
        points[16] = at(90.0, 20.0, 0.1); // hidden: not judged
        points[27] = at(-30.0, 50.0, 1.0); // outside the photo: the mask says nothing there
        assert_eq!(off_person(&points, &framing, &mask, size), vec![15]);
        // An empty mask says nothing.
        assert!(off_person(&points, &framing, &vec![0.0; size * size], size).is_empty());

        // Through `framed`: the wrist's limb (elbow, fingers) is taken as unseen with it.
        let landmark = |(ndc, vis): ([f32; 2], f32)| {
            let p = framing.to_photo(ndc);
            super::super::landmarks::Landmark { x: p[0] / 100.0, y: p[1] / 100.0, z: 0.0, visibility: vis }
        };
        let result = PoseResult {
            pose_landmarks: points.iter().copied().map(landmark).collect(),
            pose_world_landmarks: None,
            segmentation_mask: None,
            rotation: 0,
        };
        let m = SegmentationMask { width: size, height: size, data: mask };
        let options = FitOptions { silhouette_size: size, ..FitOptions::default() };
        let input = FitInput::framed(&result, framing, Some(&m), &options).unwrap();
        assert_eq!(input.off_person, vec![13, 15, 17, 19, 21]);
        assert!(input.off_person.iter().all(|&l| input.points[l].1 == 0.0));
        assert_eq!(input.points[11].1, 1.0);
        assert_eq!(input.points[16].1, 0.1);
    }

    /// The body at rest (β = 0) 3 m before the reference camera, its joints, the camera's
    /// translation and the projection's focal factor.
    fn rest_body_in_view() -> ([Vec3; NUM_JOINTS], Vec3, f32) {
        let model = BodyModel::default_body().unwrap();
        let posed = posed_joints(&model, &BodyParams::default());
        (posed, Vec3::new(0.0, -0.3, -3.0), 1.0 / (reference_fov_y() / 2.0).tan())
    }

    /// A point of the body's frame in NDC through the camera translation `cam`.
    fn project(p: Vec3, cam: Vec3, f: f32) -> [f32; 2] {
        let c = p + cam;
        [f * c.x / -c.z, f * c.y / -c.z]
    }

    #[test]
    fn a_leg_bone_whose_depth_disagrees_with_its_foreshortening_loses_its_3d_weight() {
        let (posed, cam, f) = rest_body_in_view();
        let project = |p: Vec3| project(p, cam, f);
        // The left thigh (hip 1 → knee 4; landmarks 23 → 25) seen at its whole length.
        let thigh = (1, 4, 23, 25);
        let mut points = vec![([0.0f32; 2], 1.0f32); NUM_LANDMARKS];
        points[23].0 = project(posed[1]);
        points[25].0 = project(posed[4]);
        let agreement = |toward_camera_deg: f32| {
            let mut world = vec![Vec3::ZERO; NUM_LANDMARKS];
            let a = toward_camera_deg.to_radians();
            world[25] = Vec3::new(0.0, -a.cos(), a.sin());
            leg_foreshortening_agreement(&posed, cam, &points, &world, thigh, 0.0)
        };
        // In the image plane, as the 2D length says; 30° towards the camera (in-plane 0.87);
        // 46° (0.7: halfway); 60° (0.5: beyond).
        assert!((agreement(0.0) - 1.0).abs() < 1e-3, "{}", agreement(0.0));
        assert!((agreement(30.0) - 1.0).abs() < 1e-3, "{}", agreement(30.0));
        assert!((agreement(45.57) - 0.5).abs() < 0.05, "{}", agreement(45.57));
        assert!(agreement(60.0) < 1e-3, "{}", agreement(60.0));
        // Arms keep their weight whatever the disagreement.
        let mut world = vec![Vec3::ZERO; NUM_LANDMARKS];
        world[13] = Vec3::Z;
        assert_eq!(leg_foreshortening_agreement(&posed, cam, &points, &world, (16, 18, 11, 13), 0.0), 1.0);
    }

    #[test]
    fn a_foreshortened_leg_bone_is_lifted_from_its_landmarks_on_the_detected_side() {
        let (posed, cam, f) = rest_body_in_view();
        let project = |p: Vec3| project(p, cam, f);
        // The left thigh turned 65° away from the camera about the hip (a leg stepping forward
        // seen from behind): its 2D landmarks show 42 % of its length.
        let thigh = (1, 4, 23, 25);
        let len = (posed[4] - posed[1]).length();
        let a = 65f32.to_radians();
        let truth = Vec3::new(0.0, -a.cos(), -a.sin());
        let mut points = vec![([0.0f32; 2], 1.0f32); NUM_LANDMARKS];
        points[23].0 = project(posed[1]);
        points[25].0 = project(posed[1] + truth * len);
        let lift = |detected: Vec3| {
            let mut world = vec![Vec3::ZERO; NUM_LANDMARKS];
            world[25] = detected;
            leg_readings(&posed, cam, &points, &world, &[thigh])[0].lifted
        };
        // The detector reads it 25° away (in-plane 0.91): lifted to the truth, fully weighted.
        let (d, w) = lift(Vec3::new(0.0, -25f32.to_radians().cos(), -25f32.to_radians().sin())).unwrap();
        assert!((d - truth).length() < 0.06 && (d.length() - 1.0).abs() < 1e-4, "{d} against {truth}");
        assert!(w > 0.9, "{w}");
        // Read 25° towards the camera: the knee on the same ray, nearer the camera, as the
        // detector's sign says (under perspective not the mirror image: the ray converges).
        let (d, _) = lift(Vec3::new(0.0, -25f32.to_radians().cos(), 25f32.to_radians().sin())).unwrap();
        let knee = posed[1] + cam + d * len;
        let seen = Vec3::from((points[25].0[0] / f, points[25].0[1] / f, -1.0)).normalize();
        assert!(d.z > 0.8 && knee.normalize().dot(seen) > 0.9999, "{d}");
        // Read 5° away: the sign is in doubt and the weight small.
        let (_, w) = lift(Vec3::new(0.0, -5f32.to_radians().cos(), -5f32.to_radians().sin())).unwrap();
        assert!(w < 0.4, "{w}");
        // Read as foreshortened as it is: the detector's direction keeps its weight, no lift.
        assert!(lift(truth).is_none());
    }
}
