//! Pinhole cameras in the paper code's convention: OpenGL (camera looks down −Z, y up),
//! vertical field of view 2·atan(16/35) ≈ 49.13°, near 0.1 m, orbiting the subject.

use glam::{Mat4, Vec3};
use serde::{Deserialize, Serialize};

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
}
