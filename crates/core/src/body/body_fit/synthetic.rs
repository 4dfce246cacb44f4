//! Synthetic detections for tests and benchmarks: what a perfect MediaPipe would report for a
//! posed body photographed by a known camera (reference intrinsics), with Gaussian noise
//! added: image landmarks at the projected joints and surface points, world landmarks at the
//! joints in camera axes around the hips (MediaPipe's axes: x right, y down, z away), and
//! the body's mask. Landmarks the fit has no body point for (hands, mouth, inner/outer
//! eyes) are reported at the pelvis with visibility 0.
//!
//! [`unseen_poses`] are poses outside the pose library and `synth-scans`' draws, for the fit's
//! round-trip test and `trainer bench fit`.

use std::f32::consts::{FRAC_PI_2, PI};

use glam::{Mat4, Vec3};

use super::landmarks::{Landmark, PoseResult, JOINT_LANDMARKS, NUM_LANDMARKS};
use super::metrics::body_mask;
use super::surface::{surface_landmarks, SurfaceError};
use crate::body::body_model::BodyModel;
use crate::body::skinning::{pose_body, BodyParams};
use crate::render::camera::{project_to_pixel, reference_fov_y, OrbitCamera};
use crate::util::rng::Rng;

/// A synthetic photo's detection and mask.
#[derive(Clone, Debug)]
pub struct SyntheticDetection {
    pub result: PoseResult,
    /// The body's mask in the photo, row-major `size²`, 0 or 1.
    pub mask: Vec<f32>,
    pub size: usize,
}

/// Detections of `params` seen through `world_to_camera` in a `size`² photo; `pixel_noise`
/// (pixels) and `world_noise` (metres) are the standard deviations of the added noise.
pub fn detect(
    model: &BodyModel,
    params: &BodyParams,
    world_to_camera: Mat4,
    size: usize,
    pixel_noise: f32,
    world_noise: f32,
    rng: &mut Rng,
) -> Result<SyntheticDetection, SurfaceError> {
    let posed = pose_body(model, params);
    let mut points: Vec<Option<Vec3>> = vec![None; NUM_LANDMARKS];
    for m in JOINT_LANDMARKS {
        points[m.landmark] = Some(posed.kinematics.posed_joints[m.joint]);
    }
    for s in surface_landmarks(model)? {
        points[s.landmark] = Some(posed.vertices[s.vertex as usize]);
    }
    let cam = |p: Vec3| world_to_camera.transform_point3(p);
    let hips = (cam(posed.kinematics.posed_joints[1]) + cam(posed.kinematics.posed_joints[2])) / 2.0;
    let mut image = Vec::with_capacity(NUM_LANDMARKS);
    let mut world = Vec::with_capacity(NUM_LANDMARKS);
    for p in &points {
        let (p, seen) = match p {
            Some(p) => (*p, true),
            None => (posed.kinematics.posed_joints[0], false),
        };
        // Behind the camera: reported at the image centre, not seen.
        let (px, visibility) = match (project_to_pixel(world_to_camera, p, size), seen) {
            (Some(px), true) => (px, 1.0),
            (px, _) => (px.unwrap_or(glam::Vec2::splat(size as f32 / 2.0)), 0.0),
        };
        let (nx, ny) = (rng.normal() * pixel_noise, rng.normal() * pixel_noise);
        image.push(Landmark { x: (px.x + nx) / size as f32, y: (px.y + ny) / size as f32, z: 0.0, visibility });
        let c = cam(p) - hips + Vec3::new(rng.normal(), rng.normal(), rng.normal()) * world_noise;
        world.push(Landmark { x: c.x, y: -c.y, z: -c.z, visibility });
    }
    let proj = Mat4::perspective_rh_gl(reference_fov_y(), 1.0, 0.1, 100.0) * world_to_camera;
    let mask = body_mask(&posed.vertices, &model.faces, proj, size);
    Ok(SyntheticDetection {
        result: PoseResult {
            pose_landmarks: image,
            pose_world_landmarks: Some(world),
            segmentation_mask: None,
            rotation: 0,
        },
        mask,
        size,
    })
}

/// A pose from (SMPL joint index, axis-angle) pairs.
fn pose(joints: &[(usize, [f32; 3])], orient: [f32; 3], betas: &[f32]) -> BodyParams {
    let mut p = BodyParams { betas: betas.to_vec(), ..BodyParams::default() };
    p.pose[0] = Vec3::from_array(orient);
    for (j, r) in joints {
        p.pose[*j] = Vec3::from_array(*r);
    }
    p
}

/// Poses outside the pose library and `synth-scans`' draws (SMPL joint indices: 1/2 hips,
/// 4/5 knees, 7/8 ankles, 3/6/9 spine, 15 head, 16/17 shoulders, 18/19 elbows).
pub fn unseen_poses() -> Vec<(&'static str, BodyParams)> {
    vec![
        (
            "squat",
            pose(
                &[
                    (1, [-1.3, 0.0, 0.1]),
                    (2, [-1.3, 0.0, -0.1]),
                    (4, [2.0, 0.0, 0.0]),
                    (5, [2.0, 0.0, 0.0]),
                    (7, [-0.6, 0.0, 0.0]),
                    (8, [-0.6, 0.0, 0.0]),
                    (3, [0.35, 0.0, 0.0]),
                    (16, [0.0, -1.2, -0.2]),
                    (17, [0.0, 1.2, 0.2]),
                ],
                [0.0, 0.3, 0.0],
                &[0.8, -0.5],
            ),
        ),
        (
            "lunge",
            pose(
                &[
                    (1, [-1.2, 0.0, 0.0]),
                    (4, [1.3, 0.0, 0.0]),
                    (2, [0.5, 0.0, 0.0]),
                    (5, [1.2, 0.0, 0.0]),
                    (16, [0.0, 0.0, -1.2]),
                    (17, [0.0, 0.0, 1.2]),
                ],
                [0.0, -0.5, 0.0],
                &[-0.6, 0.4, 0.3],
            ),
        ),
        (
            "kick",
            pose(
                &[
                    (2, [-1.4, 0.0, 0.0]),
                    (5, [0.2, 0.0, 0.0]),
                    (4, [0.1, 0.0, 0.0]),
                    (16, [0.0, 0.0, -0.3]),
                    (17, [0.0, 0.3, 0.5]),
                    (3, [-0.2, 0.0, 0.0]),
                ],
                [0.0, 1.1, 0.0],
                &[0.0, 0.0, 1.0],
            ),
        ),
        (
            "twisted_torso",
            pose(
                &[
                    (3, [0.0, 0.35, 0.0]),
                    (6, [0.0, 0.3, 0.0]),
                    (9, [0.0, 0.25, 0.0]),
                    (16, [0.0, -0.6, -1.0]),
                    (18, [0.0, -1.0, 0.0]),
                    (17, [0.0, 0.3, 1.1]),
                    (15, [0.0, -0.3, 0.0]),
                    (1, [-0.3, 0.0, 0.0]),
                ],
                [0.0, 2.6, 0.0],
                &[0.5],
            ),
        ),
        (
            "arms_crossed",
            pose(
                &[
                    (16, [0.0, -1.0, -1.1]),
                    (18, [0.0, -1.9, 0.0]),
                    (17, [0.0, 1.0, 1.1]),
                    (19, [0.0, 1.9, 0.0]),
                    (1, [0.0, 0.0, 0.15]),
                    (2, [0.0, 0.0, -0.15]),
                ],
                [0.05, -0.2, 0.0],
                &[-1.0, 0.0, 0.0, 0.5],
            ),
        ),
    ]
}

/// A wider set of poses outside the pose library for the real-detector fixtures, each seen
/// from the front, 40° and 90° to its left and from behind ([`WIDE_YAWS`]): jumps, kneeling,
/// bends, twists and a turned walk (SMPL joints as in [`unseen_poses`]; 20/21 wrists).
pub fn wide_poses() -> Vec<(&'static str, BodyParams)> {
    vec![
        (
            "jumping_jack",
            pose(
                &[(1, [0.0, 0.0, 0.4]), (2, [0.0, 0.0, -0.4]), (16, [0.0, 0.0, 0.9]), (17, [0.0, 0.0, -0.9])],
                [0.0, 0.0, 0.0],
                &[0.3, 0.2],
            ),
        ),
        (
            "sitting_arms_crossed",
            pose(
                &[
                    (1, [-1.5, 0.0, 0.1]),
                    (2, [-1.5, 0.0, -0.1]),
                    (4, [1.5, 0.0, 0.0]),
                    (5, [1.5, 0.0, 0.0]),
                    (16, [0.0, -1.0, -1.1]),
                    (18, [0.0, -1.9, 0.0]),
                    (17, [0.0, 1.0, 1.1]),
                    (19, [0.0, 1.9, 0.0]),
                ],
                [0.0, 0.0, 0.0],
                &[0.5, -0.3],
            ),
        ),
        (
            "one_leg_arms_up",
            pose(
                &[(2, [-1.6, 0.0, 0.0]), (5, [1.8, 0.0, 0.0]), (16, [0.0, 0.0, 1.3]), (17, [0.0, 0.0, -1.3])],
                [0.0, 0.0, 0.0],
                &[-0.4, 0.6],
            ),
        ),
        (
            "turned_walk",
            pose(
                &[
                    (1, [-0.5, 0.0, 0.0]),
                    (4, [0.2, 0.0, 0.0]),
                    (2, [0.35, 0.0, 0.0]),
                    (5, [0.6, 0.0, 0.0]),
                    (16, [0.0, 0.0, -1.25]),
                    (18, [0.0, -0.4, 0.0]),
                    (17, [0.0, 0.0, 1.25]),
                    (19, [0.0, 0.4, 0.0]),
                ],
                [0.0, 0.8, 0.0],
                &[0.2, -0.8],
            ),
        ),
        (
            "side_reach",
            pose(
                &[
                    (3, [0.0, 0.0, 0.25]),
                    (6, [0.0, 0.0, 0.2]),
                    (9, [0.0, 0.0, 0.15]),
                    (17, [0.0, 0.0, -1.7]),
                    (16, [0.0, 0.0, -1.2]),
                    (1, [0.0, 0.0, 0.2]),
                    (2, [0.0, 0.0, -0.2]),
                ],
                [0.0, 0.0, 0.0],
                &[1.0, 0.0, 0.5],
            ),
        ),
        (
            "crouch_twist",
            pose(
                &[
                    (1, [-0.9, 0.0, 0.1]),
                    (2, [-0.9, 0.0, -0.1]),
                    (4, [1.2, 0.0, 0.0]),
                    (5, [1.2, 0.0, 0.0]),
                    (3, [0.2, 0.4, 0.0]),
                    (6, [0.0, 0.3, 0.0]),
                    (16, [0.0, -1.1, 0.0]),
                    (17, [0.0, 1.1, 0.0]),
                ],
                [0.0, 0.0, 0.0],
                &[-0.8],
            ),
        ),
        (
            "kneel",
            pose(
                &[
                    (1, [0.1, 0.0, 0.0]),
                    (4, [1.6, 0.0, 0.0]),
                    (2, [-1.5, 0.0, 0.0]),
                    (5, [1.5, 0.0, 0.0]),
                    (16, [0.0, 0.0, -1.3]),
                    (17, [0.0, -0.3, 0.5]),
                    (19, [0.0, 1.2, 0.0]),
                ],
                [0.0, 0.0, 0.0],
                &[0.0, 0.9],
            ),
        ),
        (
            "lean_forward",
            pose(
                &[(1, [-0.6, 0.0, 0.0]), (2, [-0.6, 0.0, 0.0]), (15, [-0.4, 0.0, 0.0]), (16, [0.0, 0.3, 0.0])],
                [0.6, 0.0, 0.0],
                &[0.6, 0.3, -0.5],
            ),
        ),
    ]
}

/// The camera yaws of [`wide_poses`]' fixtures, radians: front, 40° and 90° to the body's
/// left, behind.
pub const WIDE_YAWS: [f32; 4] = [0.0, 2.0 * PI / 9.0, FRAC_PI_2, PI];

/// The camera of a [`wide_poses`] fixture at `yaw`.
pub fn wide_camera(yaw: f32) -> TestCamera {
    TestCamera { yaw, pitch: 0.05, radius: 2.5 }
}

/// One camera per [`unseen_poses`] entry (yaw, pitch in radians, radius in metres), looking
/// slightly off the body's centre.
#[derive(Clone, Copy, Debug)]
pub struct TestCamera {
    pub yaw: f32,
    pub pitch: f32,
    pub radius: f32,
}

impl TestCamera {
    pub fn camera(&self) -> OrbitCamera {
        OrbitCamera {
            yaw: self.yaw,
            pitch: self.pitch,
            radius: self.radius,
            target: Vec3::new(0.05, -0.25, 0.0),
            ..OrbitCamera::default()
        }
    }
}

pub const UNSEEN_POSE_CAMERAS: [TestCamera; 5] = [
    TestCamera { yaw: 0.3, pitch: 0.05, radius: 2.3 },
    TestCamera { yaw: -0.6, pitch: -0.05, radius: 2.6 },
    TestCamera { yaw: 1.2, pitch: 0.1, radius: 2.2 },
    TestCamera { yaw: 0.4, pitch: 0.0, radius: 3.0 },
    TestCamera { yaw: 0.0, pitch: 0.08, radius: 2.4 },
];

/// The fixed camera that films [`dance`] (tests, `trainer body-photos --dance`).
pub const DANCE_CAMERA: TestCamera = TestCamera { yaw: 0.3, pitch: 0.05, radius: 3.2 };

/// A 2-second dance outside the pose library and the built-in clips, for the video path's
/// test with known truth: a squat, a jump with a sharp quarter turn to the body's left (over
/// frames 24…28 at 30 fps), a landing with a side step, the arms swinging sideways and
/// forward throughout; the root's translation is the body's path (metres).
pub fn dance(frames: usize, fps: f32) -> Vec<BodyParams> {
    let smooth = |x: f32| {
        let x = x.clamp(0.0, 1.0);
        x * x * (3.0 - 2.0 * x)
    };
    (0..frames)
        .map(|k| {
            let t = k as f32 / fps;
            let mut p = BodyParams { betas: vec![0.4, -0.3], ..BodyParams::default() };
            // Squat down and up over the first 0.8 s, again after landing.
            let squat =
                (PI * (t / 0.8).min(1.0)).sin().max(0.0) * 0.8 + (PI * ((t - 1.3) / 0.7).clamp(0.0, 1.0)).sin() * 0.5;
            p.pose[1] = Vec3::new(-1.1 * squat, 0.0, 0.1);
            p.pose[2] = Vec3::new(-1.1 * squat, 0.0, -0.1);
            p.pose[4] = Vec3::new(1.7 * squat, 0.0, 0.0);
            p.pose[5] = Vec3::new(1.7 * squat, 0.0, 0.0);
            p.pose[7] = Vec3::new(-0.5 * squat, 0.0, 0.0);
            p.pose[8] = Vec3::new(-0.5 * squat, 0.0, 0.0);
            p.pose[3] = Vec3::new(0.3 * squat, 0.0, 0.0);
            // Arms: sideways from down to near level and forward, elbows bending.
            let swing = 0.5 - 0.5 * (2.0 * PI * 1.2 * t).cos();
            let fwd = 0.5 * (2.0 * PI * 0.9 * t).sin();
            p.pose[16] = Vec3::new(fwd, 0.0, -1.2 + 1.0 * swing);
            p.pose[17] = Vec3::new(-fwd, 0.0, 1.2 - 1.0 * swing);
            p.pose[18] = Vec3::new(0.0, -0.3 - 0.8 * swing, 0.0);
            p.pose[19] = Vec3::new(0.0, 0.3 + 0.8 * (1.0 - swing), 0.0);
            p.pose[15] = Vec3::new(0.15 * fwd, 0.3 * fwd, 0.0);
            // The turn, over 4 frames, mid-jump.
            let turn = smooth((t * fps - 24.0) / 4.0);
            p.pose[0] = Vec3::new(0.0, FRAC_PI_2 * turn, 0.0);
            // The path: down with the squat, up in the jump (0.75…1.15 s), a side step after.
            let jump = ((t - 0.75) / 0.4).clamp(0.0, 1.0);
            let y = -0.3 * squat + 4.0 * 0.22 * jump * (1.0 - jump);
            p.transl = Vec3::new(0.35 * smooth((t - 1.2) / 0.5), y, 0.1 * smooth(t / 2.0));
            p
        })
        .collect()
}
