//! The face plane (not in the paper; `GeneratorConfig::face`): one texture-feature plane over
//! the canonical face, added to the texture triplanes' features before the texture decoder.
//!
//! Why: the triplanes span the whole 2.29 m canonical box, so even 128² texture planes have
//! 1.8 cm texels, and an eye is one texel. Worse, the front-facing (x, y) plane is shared by
//! the face and the back of the head (same x and y, other z): dark pupils there are dark
//! spots in the hair unless the other two planes cancel them. The face plane is fine (a 64²
//! plane over 17 cm has 2.7 mm texels) and reaches only points within `depth` behind the nose
//! tip. Every body's face sits at the same canonical place (inverse skinning removes the
//! shape's offsets), so the plane is a learned constant shared by all identities (eyes, brows,
//! nose, mouth), which a 1×1 modulated conv styled by w_tex adapts per identity (skin tone,
//! brows), as the texture detail blocks' constants do.
//!
//! A point's face features are the plane's bilinear sample at its (x, y) in the window, times
//! a weight that fades from 1 to 0 over the window's outer quarter and over the last 2 cm of
//! `depth`: no seam where the plane ends. The constant starts at zero, so a generator grown
//! with a face plane renders what it rendered before.

use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor};

use super::config::{FacePlaneConfig, GeneratorConfig};
use super::init::{full, Rng};
use super::layers::ModulatedConv2d;
use super::triplane::sample_triplanes;
use crate::body::body_model::BodyModel;
use crate::body::body_surface::{nose_on, SurfaceError};
use crate::geometry::inverse_skinning::canonical_body;
use crate::geometry::tet_grid::{REFERENCE_BOX_CENTER, REFERENCE_BOX_SIZE};

/// Fraction of the window's half-size over which the weight fades out at its edges.
const EDGE_FADE: f32 = 0.25;
/// Depth (metres) over which the weight fades out behind the face.
const DEPTH_FADE: f32 = 0.02;

/// The face plane of `model`'s canonical face at `res`² texels: around the face term's region
/// (`diff::scan_supervision::FaceRegion`: 7.5 cm either side of the nose, 7.5 cm below to
/// 8.5 cm above it), with the fades outside it, and 8 cm deep (the ears lie about 10 cm
/// behind the nose tip).
pub fn face_window(model: &BodyModel, res: usize) -> Result<FacePlaneConfig, SurfaceError> {
    let nose = nose_on(model, &canonical_body(model))?;
    Ok(FacePlaneConfig { res, center: [nose.x, nose.y + 0.005, nose.z], half_size: [0.095, 0.1], depth: 0.08 })
}

#[derive(Module, Debug)]
pub struct FacePlane {
    /// `[C, R, R]` texture features, shared by every identity; starts at zero.
    pub constant: Param<Tensor<3>>,
    /// 1×1, C → C, styled by w_tex (the texture decoder's first style): the identity's share.
    pub modulate: ModulatedConv2d,
    /// The window (`FacePlaneConfig`): centre x, y; nose-tip z; half width, height; depth.
    pub center_x: f32,
    pub center_y: f32,
    pub front_z: f32,
    pub half_x: f32,
    pub half_y: f32,
    pub depth: f32,
}

impl FacePlane {
    pub fn new(rng: &mut Rng, cfg: &GeneratorConfig, face: &FacePlaneConfig, device: &Device) -> Self {
        let c = cfg.plane_channels;
        Self {
            constant: Param::from_tensor(full([c, face.res, face.res], 0.0, device)),
            modulate: ModulatedConv2d::new(rng, cfg.w_dim, c, c, 1, false, false, device),
            center_x: face.center[0],
            center_y: face.center[1],
            front_z: face.center[2],
            half_x: face.half_size[0],
            half_y: face.half_size[1],
            depth: face.depth,
        }
    }

    /// The identities' planes `[B, C, R, R]` for texture styles `w` `[B, w_dim]`.
    pub fn planes(&self, w: Tensor<2>) -> Tensor<4> {
        let [b, _] = w.dims();
        let [c, r, _] = self.constant.dims();
        let x = self.constant.val().unsqueeze_dim::<4>(0).expand([b, c, r, r]);
        x.clone() + self.modulate.forward(x, w)
    }

    /// Face features `[B, N, C]` at canonical `points` `[B, N, 3]` (zero away from the face)
    /// for texture styles `w` `[B, w_dim]`.
    pub fn features(&self, points: Tensor<3>, w: Tensor<2>) -> Tensor<3> {
        let planes = self.planes(w);
        let [b, c, r, _] = planes.dims();
        let axis = |k: usize| points.clone().narrow(2, k, 1); // [B, N, 1]
        let u = (axis(0) - self.center_x) * (1.0 / self.half_x);
        let v = (axis(1) - self.center_y) * (1.0 / self.half_y);
        let edge = |t: Tensor<3>| (t.abs().neg() + 1.0).mul_scalar(1.0 / EDGE_FADE).clamp(0.0, 1.0);
        let behind = (axis(2) - (self.front_z - self.depth)).mul_scalar(1.0 / DEPTH_FADE).clamp(0.0, 1.0);
        let weight = edge(u.clone()) * edge(v.clone()) * behind; // [B, N, 1]
                                                                 // The window as the (x, y) plane of a triplane lookup whose other two planes are zero:
                                                                 // (u, v) ∈ [−1, 1]² is that plane's whole extent.
        let half_box = REFERENCE_BOX_SIZE / 2.0;
        let q = Tensor::cat(
            vec![
                u * half_box + REFERENCE_BOX_CENTER.x,
                v * half_box + REFERENCE_BOX_CENTER.y,
                axis(2).zeros_like() + REFERENCE_BOX_CENTER.z,
            ],
            2,
        );
        let three = Tensor::cat(vec![planes.clone(), planes.zeros_like(), planes.zeros_like()], 1); // [B, 3C, R, R]
        debug_assert_eq!(three.dims(), [b, 3 * c, r, r]);
        sample_triplanes(three, q) * weight
    }
}
