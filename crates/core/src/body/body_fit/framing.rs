//! Framing a photo the way the dataset is framed: a square crop (padded where it leaves the
//! photo) seen through the reference camera (fov 49.13°), scaled so the person's torso takes
//! the fraction of the image it takes in the data renders (camera 2.3 m away), centred on
//! the hips as the data camera looks at the body's middle, and enlarged where the person
//! would not fit. The fit then works in the reference camera's normalised device
//! coordinates (NDC: x right, y up, −1..1 across the crop), and the inversion renders the
//! same square.

use serde::{Deserialize, Serialize};

use super::landmarks::{Landmark, VISIBLE};
use crate::body::body_model::BodyModel;
use crate::render::camera::{reference_fov_y, REFERENCE_RADIUS};

/// Photos above this many pixels are refused (the app downscales above 4 MP before detecting).
pub const MAX_PHOTO_PIXELS: u64 = 40_000_000;

/// A square crop of a photo: its centre and side in photo pixels (x right, y down, pixel
/// centres at +0.5). It may extend past the photo's border (padding).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Framing {
    /// The photo's size, pixels.
    pub photo_width: usize,
    pub photo_height: usize,
    /// Crop centre, photo pixels.
    pub centre: [f32; 2],
    /// Crop side, photo pixels.
    pub side: f32,
}

/// Why a photo cannot be framed.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FramingError {
    #[error("the photo is empty ({0}×{1} pixels)")]
    EmptyPhoto(usize, usize),
    #[error("no torso found: the shoulders and hips are not visible")]
    NoTorso,
}

impl Framing {
    /// Photo pixel → NDC of the reference camera.
    pub fn to_ndc(&self, px: [f32; 2]) -> [f32; 2] {
        let h = self.side / 2.0;
        [(px[0] - self.centre[0]) / h, -(px[1] - self.centre[1]) / h]
    }

    /// NDC → photo pixel.
    pub fn to_photo(&self, ndc: [f32; 2]) -> [f32; 2] {
        let h = self.side / 2.0;
        [self.centre[0] + ndc[0] * h, self.centre[1] - ndc[1] * h]
    }

    /// Clip space of the crop → clip space of the whole photo (a 2D similarity applied
    /// before the perspective divide), so a body rendered through the fit's camera and this
    /// matrix lands on the photo.
    pub fn crop_to_photo_clip(&self) -> glam::Mat4 {
        use glam::Vec4;
        let (w, h) = (self.photo_width.max(1) as f32, self.photo_height.max(1) as f32);
        let (sx, sy) = (self.side / w, self.side / h);
        let (ox, oy) = (2.0 * self.centre[0] / w - 1.0, 1.0 - 2.0 * self.centre[1] / h);
        glam::Mat4::from_cols(
            Vec4::new(sx, 0.0, 0.0, 0.0),
            Vec4::new(0.0, sy, 0.0, 0.0),
            Vec4::Z,
            Vec4::new(ox, oy, 0.0, 1.0),
        )
    }

    /// The crop of a photo for a person's landmarks (`poseLandmarks`, normalised to the
    /// photo's size) and the body whose proportions define the dataset's framing.
    pub fn from_landmarks(
        landmarks: &[Landmark],
        width: usize,
        height: usize,
        model: &BodyModel,
    ) -> Result<Self, FramingError> {
        if width == 0 || height == 0 {
            return Err(FramingError::EmptyPhoto(width, height));
        }
        let px = |i: usize| {
            landmarks.get(i).filter(|l| l.visibility >= VISIBLE).map(|l| [l.x * width as f32, l.y * height as f32])
        };
        let mid = |a: Option<[f32; 2]>, b: Option<[f32; 2]>| match (a, b) {
            (Some(a), Some(b)) => Some([(a[0] + b[0]) / 2.0, (a[1] + b[1]) / 2.0]),
            (a, b) => a.or(b),
        };
        let shoulders = mid(px(11), px(12));
        let hips = mid(px(23), px(24));
        let (Some(s), Some(h)) = (shoulders, hips) else {
            return Err(FramingError::NoTorso);
        };
        let torso_px = ((s[0] - h[0]).powi(2) + (s[1] - h[1]).powi(2)).sqrt().max(1.0);
        let mut side = torso_px / torso_fraction(model);
        // Enlarge until every visible landmark (with room for the head above the face and
        // the soles below the heels) lies within 90 % of the half-side.
        let visible: Vec<[f32; 2]> = (0..landmarks.len()).filter_map(px).collect();
        let head_room = 0.35 * torso_px;
        for p in &visible {
            let dx = (p[0] - h[0]).abs();
            let up = (h[1] - p[1]) + head_room;
            let down = (p[1] - h[1]) + 0.05 * torso_px;
            side = side.max(2.0 * dx.max(up).max(down) / 0.9);
        }
        Ok(Self { photo_width: width, photo_height: height, centre: h, side })
    }

    /// A person mask covering the photo (`mask_width × mask_height` values, row-major,
    /// 0..1; any resolution, stretched over the photo) resampled to the crop at `size`²
    /// (4×4 samples per pixel, 0 outside the photo).
    pub fn resample_mask(&self, values: &[f32], mask_width: usize, mask_height: usize, size: usize) -> Vec<f32> {
        self.resample(values, mask_width, mask_height, 1, size, &[0.0])
    }

    /// An image covering the photo (`width × height` pixels of `channels` values, row-major;
    /// any resolution, stretched over the photo) resampled to the crop at `size`² (4×4 samples
    /// per pixel, `outside` where the crop leaves the photo): the photo as the inversion's
    /// camera sees it.
    pub fn resample(
        &self,
        values: &[f32],
        width: usize,
        height: usize,
        channels: usize,
        size: usize,
        outside: &[f32],
    ) -> Vec<f32> {
        let (w, h, c) = (width, height, channels.max(1));
        let (kx, ky) = (w as f32 / self.photo_width.max(1) as f32, h as f32 / self.photo_height.max(1) as f32);
        let mut out = vec![0.0f32; size * size * c];
        const SS: usize = 4;
        for (k, o) in out.chunks_exact_mut(c).enumerate() {
            let (x, y) = (k % size, k / size);
            for s in 0..SS * SS {
                let u = (x as f32 + (s % SS) as f32 / SS as f32 + 0.5 / SS as f32) / size as f32 * 2.0 - 1.0;
                let v = 1.0 - (y as f32 + (s / SS) as f32 / SS as f32 + 0.5 / SS as f32) / size as f32 * 2.0;
                let p = self.to_photo([u, v]);
                let p = [p[0] * kx, p[1] * ky];
                let inside = p[0] >= 0.0 && p[1] >= 0.0 && (p[0] as usize) < w && (p[1] as usize) < h;
                for (ch, o) in o.iter_mut().enumerate() {
                    *o += if inside {
                        values.get((p[1] as usize * w + p[0] as usize) * c + ch).copied().unwrap_or(0.0)
                    } else {
                        outside.get(ch).copied().unwrap_or(0.0)
                    };
                }
            }
            for o in o.iter_mut() {
                *o /= (SS * SS) as f32;
            }
        }
        out
    }
}

/// The torso's length (shoulders' midpoint to hips' midpoint of the rest body) as a fraction
/// of the data renders' image height.
pub fn torso_fraction(model: &BodyModel) -> f32 {
    let j = model.regress_joints(&model.v_template);
    // SMPL: 16/17 shoulders, 1/2 hips.
    let s = (j[16] + j[17]) / 2.0;
    let h = (j[1] + j[2]) / 2.0;
    let view_height = 2.0 * REFERENCE_RADIUS * (reference_fov_y() / 2.0).tan();
    (s - h).length() / view_height
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::body::body_fit::landmarks::NUM_LANDMARKS;

    #[test]
    fn a_person_is_framed_like_the_data_and_ndc_round_trips() {
        let model = BodyModel::default_body().unwrap();
        let f = torso_fraction(&model);
        assert!((0.15..0.35).contains(&f), "{f}");
        // A standing person: shoulders 200 px above the hips, face above, feet below.
        let mut marks = vec![Landmark { x: 0.5, y: 0.5, z: 0.0, visibility: 0.0 }; NUM_LANDMARKS];
        let (w, h) = (1000usize, 2000usize);
        let mut put = |i: usize, x: f32, y: f32| {
            marks[i] = Landmark { x: x / w as f32, y: y / h as f32, z: 0.0, visibility: 1.0 }
        };
        put(11, 560.0, 800.0);
        put(12, 440.0, 800.0);
        put(23, 540.0, 1000.0);
        put(24, 460.0, 1000.0);
        put(0, 500.0, 700.0);
        put(27, 520.0, 1400.0);
        let fr = Framing::from_landmarks(&marks, w, h, &model).unwrap();
        assert_eq!(fr.centre, [500.0, 1000.0]);
        // The torso sets the scale unless the feet need more room.
        let by_torso = 200.0 / f;
        let by_feet = 2.0 * (400.0 + 10.0) / 0.9;
        assert!((fr.side - by_torso.max(by_feet)).abs() < 1e-2, "{} vs {by_torso} / {by_feet}", fr.side);
        let p = [123.0, 1456.0];
        let back = fr.to_photo(fr.to_ndc(p));
        assert!((back[0] - p[0]).abs() < 1e-3 && (back[1] - p[1]).abs() < 1e-3);
        // Image up is NDC up.
        assert!(fr.to_ndc([500.0, 900.0])[1] > 0.0);
        // Crop clip space → photo clip space agrees with to_photo.
        let ndc = [0.3f32, -0.7];
        let c = fr.crop_to_photo_clip() * glam::Vec4::new(ndc[0] * 2.0, ndc[1] * 2.0, 0.5, 2.0);
        let px = [(c.x / c.w + 1.0) * 0.5 * w as f32, (1.0 - c.y / c.w) * 0.5 * h as f32];
        let want = fr.to_photo(ndc);
        assert!((px[0] - want[0]).abs() < 1e-2 && (px[1] - want[1]).abs() < 1e-2, "{px:?} vs {want:?}");
        // No torso: an error that says so.
        let mut hidden = marks.clone();
        hidden[23].visibility = 0.1;
        hidden[24].visibility = 0.1;
        assert_eq!(Framing::from_landmarks(&hidden, w, h, &model), Err(FramingError::NoTorso));
        assert_eq!(Framing::from_landmarks(&marks, 0, h, &model), Err(FramingError::EmptyPhoto(0, h)));
    }

    #[test]
    fn masks_are_resampled_into_the_crop_with_zero_padding() {
        // A 4×2 photo whose right half is the person; a crop centred on the photo's centre
        // twice as wide as the photo: the person fills the crop's x ∈ [½, ¾), y ∈ [¼, ¾).
        let fr = Framing { photo_width: 4, photo_height: 2, centre: [2.0, 1.0], side: 8.0 };
        let photo = [0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 1.0, 1.0];
        let m = fr.resample_mask(&photo, 4, 2, 8);
        for y in 0..8 {
            for x in 0..8 {
                let want = if (4..6).contains(&x) && (3..5).contains(&y) { 1.0 } else { 0.0 };
                assert_eq!(m[y * 8 + x], want, "({x}, {y})");
            }
        }
        // The same mask at twice the photo's resolution resamples the same.
        let fine: Vec<f32> = (0..16 * 4).map(|k| if k % 8 >= 4 { 1.0 } else { 0.0 }).collect();
        assert_eq!(fr.resample_mask(&fine, 8, 4, 8), m);
    }
}
