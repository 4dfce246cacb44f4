//! A photo turned by quarter turns so that the person in it is upright: the detector reads a
//! person lying or upside down on the turned photo, the fit and everything after it work on
//! that photo (an upright person, as the framing and the data assume), and the turn relates
//! the fit's camera back to the photo as taken ([`clip_to_original`]). Degrees clockwise, one
//! of 0, 90, 180, 270 (`rotation` in kp.json and fit.json; docs/conventions.md).

use glam::{Mat4, Vec4};

/// The quarter turns a photo may be turned by, degrees clockwise.
pub const TURNS: [u16; 4] = [0, 90, 180, 270];

/// A turn that is not a quarter turn.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("`rotation` is {0}°: a photo is turned by 0, 90, 180 or 270 degrees")]
pub struct TurnError(pub u16);

/// `deg` if it is one of [`TURNS`].
pub fn check(deg: u16) -> Result<u16, TurnError> {
    if TURNS.contains(&deg) {
        Ok(deg)
    } else {
        Err(TurnError(deg))
    }
}

/// The size of a `width × height` photo turned by `deg`.
pub fn turned_size(deg: u16, width: usize, height: usize) -> (usize, usize) {
    if deg % 180 == 0 {
        (width, height)
    } else {
        (height, width)
    }
}

/// Where a point of the original photo (pixels, continuous: the top-left corner is (0, 0),
/// the bottom-right (width, height)) lands in the photo turned by `deg`.
pub fn point_to_turned(deg: u16, width: usize, height: usize, [x, y]: [f32; 2]) -> [f32; 2] {
    let (w, h) = (width as f32, height as f32);
    match deg {
        90 => [h - y, x],
        180 => [w - x, h - y],
        270 => [y, w - x],
        _ => [x, y],
    }
}

/// Where a point of the turned photo lands in the photo as taken (`width × height`, the
/// original's size): [`point_to_turned`] undone.
pub fn point_to_original(deg: u16, width: usize, height: usize, p: [f32; 2]) -> [f32; 2] {
    let (tw, th) = turned_size(deg, width, height);
    point_to_turned((360 - deg % 360) % 360, tw, th, p)
}

/// A row-major `width × height` image of `channels` values per pixel turned by `deg`:
/// the pixels and the turned size.
pub fn turn_image<T: Copy>(
    data: &[T],
    width: usize,
    height: usize,
    channels: usize,
    deg: u16,
) -> (Vec<T>, usize, usize) {
    let (tw, th) = turned_size(deg, width, height);
    if deg % 360 == 0 {
        return (data.to_vec(), width, height);
    }
    let mut out = Vec::with_capacity(data.len());
    for ty in 0..th {
        for tx in 0..tw {
            // The turned pixel (tx, ty) → the original pixel it shows.
            let (x, y) = match deg {
                90 => (ty, height - 1 - tx),
                180 => (width - 1 - tx, height - 1 - ty),
                _ => (width - 1 - ty, tx),
            };
            let o = (y * width + x) * channels;
            out.extend_from_slice(&data[o..o + channels]);
        }
    }
    (out, tw, th)
}

/// Clip space of the photo turned by `deg` → clip space of the photo as taken (a rotation of
/// x and y before the perspective divide): `clip_to_original(deg) * fit.photo_view_proj()`
/// draws the fitted body on the original photo.
pub fn clip_to_original(deg: u16) -> Mat4 {
    // NDC: x right, y up. Turned clockwise by 90°, the turned photo's (x', y') is the
    // original's (−y', x'); by 180°, (−x', −y'); by 270°, (y', −x').
    let (c0, c1) = match deg {
        90 => (Vec4::new(0.0, 1.0, 0.0, 0.0), Vec4::new(-1.0, 0.0, 0.0, 0.0)),
        180 => (Vec4::new(-1.0, 0.0, 0.0, 0.0), Vec4::new(0.0, -1.0, 0.0, 0.0)),
        270 => (Vec4::new(0.0, -1.0, 0.0, 0.0), Vec4::new(1.0, 0.0, 0.0, 0.0)),
        _ => (Vec4::X, Vec4::Y),
    };
    Mat4::from_cols(c0, c1, Vec4::Z, Vec4::W)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Pixel centre (x, y) of a `w × h` photo → NDC.
    fn ndc(w: usize, h: usize, [x, y]: [f32; 2]) -> [f32; 2] {
        [2.0 * x / w as f32 - 1.0, 1.0 - 2.0 * y / h as f32]
    }

    #[test]
    fn a_turned_image_shows_each_pixel_where_the_point_map_puts_it() {
        let (w, h) = (5usize, 3usize);
        let data: Vec<u32> = (0..(w * h) as u32).collect();
        for deg in TURNS {
            let (t, tw, th) = turn_image(&data, w, h, 1, deg);
            assert_eq!((tw, th), turned_size(deg, w, h));
            for y in 0..h {
                for x in 0..w {
                    let [tx, ty] = point_to_turned(deg, w, h, [x as f32 + 0.5, y as f32 + 0.5]);
                    let back = point_to_original(deg, w, h, [tx, ty]);
                    assert!((back[0] - x as f32 - 0.5).abs() < 1e-6 && (back[1] - y as f32 - 0.5).abs() < 1e-6);
                    let (tx, ty) = (tx.floor() as usize, ty.floor() as usize);
                    assert_eq!(t[ty * tw + tx], data[y * w + x], "{deg}°: pixel ({x}, {y})");
                }
            }
        }
    }

    #[test]
    fn turning_a_photo_clockwise_by_90_puts_its_top_on_the_right() {
        // A 2 × 1 photo: [a b] turned 90° clockwise is a column [a; b]; its top (y = 0) is
        // the turned photo's right edge.
        let (t, tw, th) = turn_image(&[1u8, 2], 2, 1, 1, 90);
        assert_eq!((t, tw, th), (vec![1, 2], 1, 2));
        assert_eq!(point_to_turned(90, 2, 1, [1.0, 0.0]), [1.0, 1.0]);
    }

    #[test]
    fn the_turned_photos_clip_space_maps_onto_the_originals() {
        let (w, h) = (640usize, 480usize);
        for deg in TURNS {
            let (tw, th) = turned_size(deg, w, h);
            let m = clip_to_original(deg);
            for p in [[10.0, 20.0], [600.0, 50.0], [320.0, 240.0], [33.0, 470.0]] {
                let t = point_to_turned(deg, w, h, p);
                let [x, y] = ndc(tw, th, t);
                // A clip point with w = 2 (before the divide).
                let c = m * Vec4::new(2.0 * x, 2.0 * y, 0.3, 2.0);
                let want = ndc(w, h, p);
                assert!((c.x / c.w - want[0]).abs() < 1e-5 && (c.y / c.w - want[1]).abs() < 1e-5, "{deg}° {p:?}");
            }
        }
    }

    #[test]
    fn only_quarter_turns_are_accepted() {
        assert_eq!(check(270), Ok(270));
        assert_eq!(
            check(45).unwrap_err().to_string(),
            "`rotation` is 45°: a photo is turned by 0, 90, 180 or 270 degrees"
        );
    }
}
