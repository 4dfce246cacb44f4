//! Pinhole cameras in the paper code's convention: OpenGL (camera looks down −Z, y up),
//! vertical field of view 2·atan(16/35) ≈ 49.13°, near 0.1 m, orbiting the subject.

use glam::{Mat4, Vec3};
use serde::{Deserialize, Serialize};

use crate::body::skinning::BodyParams;

/// Vertical field of view of the reference code, radians: 2·atan(16/35).
pub fn reference_fov_y() -> f32 {
    2.0 * (16.0f32 / 35.0).atan()
}

/// Camera radius of the data protocol, metres.
pub const REFERENCE_RADIUS: f32 = 2.3;

/// An orbit camera around `target`: azimuth (yaw) about +y, elevation (pitch), radius.
/// yaw = 0, pitch = 0 puts the camera on +z looking at the body's front.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct OrbitCamera {
    /// Azimuth about +y, radians (positive turns the camera towards +x).
    pub yaw: f32,
    /// Elevation, radians (positive looks down from above).
    pub pitch: f32,
    /// Distance to the target, metres.
    pub radius: f32,
    /// Look-at point, metres.
    pub target: Vec3,
    /// Vertical field of view, radians.
    pub fov_y: f32,
    /// Near plane, metres.
    pub near: f32,
    /// Far plane, metres.
    pub far: f32,
}

impl Default for OrbitCamera {
    fn default() -> Self {
        Self {
            yaw: 0.0,
            pitch: 0.0,
            radius: REFERENCE_RADIUS,
            target: Vec3::new(0.0, -0.185, 0.0),
            fov_y: reference_fov_y(),
            near: 0.1,
            far: 100.0,
        }
    }
}

impl OrbitCamera {
    /// Camera centre in world space.
    pub fn eye(&self) -> Vec3 {
        let (sy, cy) = self.yaw.sin_cos();
        let (sp, cp) = self.pitch.sin_cos();
        self.target + self.radius * Vec3::new(sy * cp, sp, cy * cp)
    }

    /// World-to-camera matrix (the dataset label's 16 numbers).
    pub fn world_to_camera(&self) -> Mat4 {
        Mat4::look_at_rh(self.eye(), self.target, Vec3::Y)
    }

    /// OpenGL clip-space projection (depth in −1..1).
    pub fn projection_gl(&self, aspect: f32) -> Mat4 {
        Mat4::perspective_rh_gl(self.fov_y, aspect, self.near, self.far)
    }

    /// WebGPU/wgpu clip-space projection (depth in 0..1).
    pub fn projection_wgpu(&self, aspect: f32) -> Mat4 {
        Mat4::perspective_rh(self.fov_y, aspect, self.near, self.far)
    }

    /// Keep the parameters in a usable range (radius > near, |pitch| < 89°).
    pub fn clamped(mut self) -> Self {
        let lim = 89f32.to_radians();
        self.pitch = self.pitch.clamp(-lim, lim);
        self.radius = self.radius.clamp(0.3, 20.0);
        self.yaw = self.yaw.rem_euclid(std::f32::consts::TAU);
        self
    }
}

/// The data-rendering camera protocol of the paper code (`trainer prepare`): radius 2.3,
/// fov 49.13°, azimuth uniform in [0, 2π), elevation ~ N(0, σ = 0.1 rad) clamped to
/// ±[`DATA_ELEVATION_CLAMP`], looking at the subject's vertical centre on the y axis.
pub const DATA_ELEVATION_STD: f32 = 0.1;
/// Elevations are clamped to ±3σ.
pub const DATA_ELEVATION_CLAMP: f32 = 0.3;

/// Draw one camera of the data protocol looking at `(0, centre_y, 0)`.
pub fn sample_data_camera(rng: &mut crate::util::rng::Rng, centre_y: f32) -> OrbitCamera {
    let yaw = rng.uniform() * std::f32::consts::TAU;
    let pitch = (rng.normal() * DATA_ELEVATION_STD).clamp(-DATA_ELEVATION_CLAMP, DATA_ELEVATION_CLAMP);
    OrbitCamera { yaw, pitch, target: Vec3::new(0.0, centre_y, 0.0), ..OrbitCamera::default() }
}

/// A 4×4 matrix as 16 numbers, row-major (the dataset label layout).
pub fn to_row_major(m: Mat4) -> [f32; 16] {
    m.transpose().to_cols_array()
}

/// Inverse of [`to_row_major`].
pub fn from_row_major(v: &[f32; 16]) -> Mat4 {
    Mat4::from_cols_array(v).transpose()
}

/// Pixel coordinates (x right, y down, pixel centres at +0.5) of a world point seen through a
/// world-to-camera matrix with the reference intrinsics in a `size`² image; `None` behind
/// the camera.
pub fn project_to_pixel(world_to_camera: Mat4, point: Vec3, size: usize) -> Option<glam::Vec2> {
    let p = world_to_camera.transform_point3(point);
    if p.z >= 0.0 {
        return None;
    }
    let f = 1.0 / (reference_fov_y() / 2.0).tan();
    let (nx, ny) = (f * p.x / -p.z, f * p.y / -p.z);
    Some(glam::Vec2::new((nx + 1.0) * 0.5 * size as f32, (1.0 - ny) * 0.5 * size as f32))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_camera_looks_down_minus_z_at_the_body() {
        let c = OrbitCamera::default();
        assert!((c.eye() - Vec3::new(0.0, -0.185, 2.3)).length() < 1e-6);
        // The target projects to the image centre, in front of the camera (negative z).
        let p = c.world_to_camera().transform_point3(c.target);
        assert!(p.x.abs() < 1e-6 && p.y.abs() < 1e-6 && (p.z + 2.3).abs() < 1e-5);
        assert!((reference_fov_y().to_degrees() - 49.134).abs() < 1e-2);
        // A point at the top of the view frustum maps to NDC y = 1.
        let top = c.target + Vec3::Y * (c.fov_y / 2.0).tan() * c.radius;
        let clip = c.projection_wgpu(1.0) * c.world_to_camera() * top.extend(1.0);
        assert!((clip.y / clip.w - 1.0).abs() < 1e-4);
    }

    #[test]
    fn row_major_round_trip_and_pixel_projection() {
        let c = OrbitCamera { yaw: 0.7, pitch: -0.1, ..OrbitCamera::default() };
        let m = c.world_to_camera();
        let r = to_row_major(m);
        // Row-major: the translation is the last entry of the first three rows.
        assert_eq!(r[3], m.w_axis.x);
        assert_eq!(from_row_major(&r), m);
        // The target projects to the image centre.
        let p = project_to_pixel(m, c.target, 128).unwrap();
        assert!((p - glam::Vec2::splat(64.0)).length() < 1e-3, "{p}");
        // Same as the OpenGL projection.
        let q = c.target + Vec3::new(0.2, 0.3, -0.1);
        let clip = c.projection_gl(1.0) * m * q.extend(1.0);
        let want = glam::Vec2::new((clip.x / clip.w + 1.0) * 64.0, (1.0 - clip.y / clip.w) * 64.0);
        assert!((project_to_pixel(m, q, 128).unwrap() - want).length() < 1e-3);
    }
}

/// One rendering of a posed body: the camera (world → camera, the dataset label's 16 numbers)
/// and the body pose and shape it sees. A dataset label is one (`dataset::Label::view`); the
/// training renderer and inversion take views, not files' labels.
#[derive(Clone, Debug, PartialEq)]
pub struct View {
    pub world_to_camera: Mat4,
    pub body: BodyParams,
}
