//! The photo's colours projected onto the reconstructed avatar (beyond the paper, on by
//! default): users of single-image methods ask above all for a sharp front and a plausible
//! back. Each surface point of the avatar, posed as in the photo, that the photo's camera sees
//! (depth test against the avatar's own depth buffer) takes the photo's colour there (the photo
//! sharpened first, [`PREFILTER`], so that the lookups give its detail back); the
//! weight falls to 0 at grazing angles (`cos θ` between the normal and the direction to the
//! camera from [`GRAZING`] to [`FACING`]) and beyond the person mask's border; the border's
//! mixed pixels (mask below [`OWN_COLOUR`], part background) take the colours just inside it,
//! carried a few pixels past the mask ([`reach`]) for an avatar a little wider than the
//! person. The hidden side keeps the generated texture, shifted towards the photo's tone
//! ([`colour_shift`], estimated from the colours just inside the border: the back of a pink
//! dress is pink, not the generator's beige). Known limit: what hangs behind the body in the
//! photo (a ponytail over the upper back) tints the front at the same height too.
//!
//! Colours are linear RGB (the texture field's); the photo is sRGB and decoded here.

use glam::{Mat4, Vec2, Vec3, Vec4};

use crate::export::uv_atlas::NEIGHBOURS_8;
use crate::render::camera::{OrbitCamera, View};
use crate::render::rasterize::{rasterize_async, Texture};
use crate::util::cooperative::checkpoint;

/// `cos θ` below which the photo has no weight, and above which it has full weight. The
/// silhouette's points face the camera at `cos θ` near 0 and show there in the photo: with the
/// border's colours carried in from the inside ([`extend_from_interior`]) they take the photo's
/// colours up to the grazing angle itself (masked PSNR at the photo's camera +2.4 dB on the
/// benchmark's slim person against a falloff from 0.2 to 0.55; docs/benchmarks.md).
pub const GRAZING: f32 = 0.0;
pub const FACING: f32 = 0.3;
/// Mask value from which a pixel of the person's border keeps its own colour in the photo:
/// below it the pixel is taken as mixed with the background and takes the colours just inside
/// ([`extend_from_interior`]). A border pixel the person covers (hair at the side of a head, a
/// thin arm's edge, a shoe's dark outline) is the person's colour; filling it from inside drew
/// a head's dark hair in its face's colour. Chosen on the `instant` benchmark's 12 people,
/// checked on 32 validation people (docs/benchmarks.md, "The photo's projection").
pub const OWN_COLOUR: f32 = 0.65;
/// The photo's sharpening before the bake looks it up ([`prefilter`]: each axis filtered by
/// `[−a, 1 + 2a, −a]` with this `a`). A texel takes the photo bilinearly at its projection and
/// a pixel of a render averages the texels it covers, so the photo comes back through a tent
/// and a box: each pixel mixed an eighth with each neighbour along each axis, and again through
/// the texture's own bilinear lookups; stripes two pixels wide lost half their contrast.
/// `a = ¼` undoes the first to within an eighth at every frequency. On the `instant`
/// benchmark's 12 people 0.15 and 0.2 scored highest (within 0.02 dB), 0.2 above 0.25 end to
/// end and above 0.3 at the app's 256² crop (docs/benchmarks.md, "The photo's projection").
pub const PREFILTER: f32 = 0.2;
/// Rows of the photo handled between two checkpoints of [`PhotoProjection::new_async`]'s steps.
const BAND_ROWS: usize = 64;
/// How far (pixels) the photo's colours are carried beyond the person mask: a 32nd of the crop,
/// at least 2, so that an avatar a little wider than the person takes the person's colours at
/// its edge rather than the generated ones.
pub fn reach(res: usize) -> usize {
    (res / 32).max(2)
}

/// A point is visible when it lies at most this far (metres, along the view axis) behind the
/// depth buffer's surface.
pub const DEPTH_TOLERANCE: f32 = 0.015;

/// The photo a reconstruction was made from, kept with the inverted avatar (its file,
/// `checkpoint::save_inverted`) so that every later bake of that avatar — `trainer export
/// --inverted`, the app opening the file — projects the same colours: the camera and body pose
/// of the photo's crop at the reference projection, and the crop itself.
#[derive(Clone, Debug, PartialEq)]
pub struct SourcePhoto {
    pub view: View,
    /// Side of the square crop, pixels.
    pub res: usize,
    /// sRGB in [0, 1], `res²·3`, row-major from the top.
    pub rgb: Vec<f32>,
    /// Person mask in [0, 1], `res²`.
    pub mask: Vec<f32>,
}

impl SourcePhoto {
    /// Sizes and values checked (a file may hold anything): one sentence on failure.
    pub fn validate(&self) -> Result<(), String> {
        let r = self.res;
        if !(16..=4096).contains(&r) {
            return Err(format!("the photo crop is {r} pixels wide (16…4096)"));
        }
        for (what, v, c) in [("colours", &self.rgb, 3), ("mask", &self.mask, 1)] {
            if v.len() != r * r * c {
                return Err(format!("the photo's {what} hold {} values, {r}² needs {}", v.len(), r * r * c));
            }
            if v.iter().any(|x| !x.is_finite() || !(0.0..=1.0).contains(x)) {
                return Err(format!("the photo's {what} hold a value outside [0, 1]"));
            }
        }
        if !self.view.world_to_camera.is_finite() || self.view.world_to_camera.determinant().abs() < 1e-12 {
            return Err("the photo's camera is not a finite, invertible transform".into());
        }
        Ok(())
    }

    /// The projection of this photo onto a surface (`vertices`, `faces`) posed as the photo
    /// shows it, through the reference camera's projection.
    pub fn projection(&self, vertices: &[Vec3], faces: &[[u32; 3]]) -> PhotoProjection {
        crate::util::cooperative::run_blocking(self.projection_async(vertices, faces))
    }

    /// [`SourcePhoto::projection`] in slices ([`crate::util::cooperative`]), for the browser.
    pub async fn projection_async(&self, vertices: &[Vec3], faces: &[[u32; 3]]) -> PhotoProjection {
        let proj = OrbitCamera::default().projection_gl(1.0);
        PhotoProjection::new_async(self.view.world_to_camera, proj, self.res, &self.rgb, &self.mask, vertices, faces)
            .await
    }
}

/// A photo ready to be projected: the camera, the image and the avatar's depth buffer.
pub struct PhotoProjection {
    res: usize,
    view: Mat4,
    view_proj: Mat4,
    /// The photo, linear-light (bilinear lookups): the border's mixed pixels filled from inside
    /// ([`own_colour_pixels`]) and sharpened for the lookups ([`PREFILTER`]), what the seen
    /// surface takes.
    photo: Texture,
    /// The same with every border pixel filled from inside the eroded mask, the colours the
    /// colour shift is estimated from: a border pixel the person covers still holds a little
    /// background, which carried to the hidden side lightened the back of a photo of a person
    /// over white (1.3–1.8 dB lower on one benchmark person after `fast` and `full`).
    photo_inside: Texture,
    /// The photo's weight per pixel ([`extend_from_interior`]), `res²`.
    mask: Vec<f32>,
    /// View-space depth (−z, metres) of the avatar per pixel; +∞ where uncovered.
    depth: Vec<f32>,
}

/// The 3×3 minimum of a `res²` mask, 0 outside it (and where it holds fewer values): a row
/// pass then a column pass (the window is separable).
/// A checkpoint every [`BAND_ROWS`] rows.
async fn erode3(mask: &[f32], res: usize) -> Vec<f32> {
    let at = |k: usize| mask.get(k).copied().unwrap_or(0.0);
    let mut rows = vec![0.0f32; res * res];
    for y in 0..res {
        if y % BAND_ROWS == BAND_ROWS - 1 {
            checkpoint().await;
        }
        for x in 0..res {
            let k = y * res + x;
            let left = if x == 0 { 0.0 } else { at(k - 1) };
            let right = if x + 1 == res { 0.0 } else { at(k + 1) };
            rows[k] = at(k).min(left).min(right);
        }
    }
    let mut out = vec![0.0f32; res * res];
    for y in 0..res {
        if y % BAND_ROWS == BAND_ROWS - 1 {
            checkpoint().await;
        }
        for x in 0..res {
            let k = y * res + x;
            let up = if y == 0 { 0.0 } else { rows[k - res] };
            let down = if y + 1 == res { 0.0 } else { rows[k + res] };
            out[k] = rows[k].min(up).min(down);
        }
    }
    out
}

/// The pixels whose colour in the photo is the person's alone (≥ ½ where so): those of the
/// mask's 3×3 erosion `eroded` (≥ ½), and the border's pixels the person covers (mask ≥
/// [`OWN_COLOUR`]).
fn own_colour_pixels(mask: &[f32], eroded: &[f32]) -> Vec<f32> {
    eroded.iter().zip(mask).map(|(e, m)| if *m >= OWN_COLOUR { 1.0 } else { *e }).collect()
}

/// The photo's colours where they are the person's alone, carried outwards: pixels of the
/// eroded mask (`interior ≥ ½`) keep theirs; every other pixel within `reach` steps (8-connected)
/// of them takes the mean of its already-filled neighbours, pass by pass, so the person's border
/// pixels (mixed with the background) and up to `reach` pixels beyond it hold the colours just
/// inside instead. Returns each pixel's weight: 1 on the person (`mask ≥ ½`) once filled,
/// `1 − s/(reach + 1)` at `s` steps outside it, 0 further out and where nothing reached.
/// (The bake's `uv_atlas::dilate_ring` fills the same way but everywhere; here the fill stops
/// `reach` steps off the person and only the last pass's neighbours are visited.)
/// A checkpoint after each pass.
async fn extend_from_interior(
    colours: &mut [Vec3],
    mask: &[f32],
    interior: &[f32],
    res: usize,
    reach: usize,
) -> Vec<f32> {
    let neighbours = move |k: usize| {
        let (x, y) = ((k % res) as i64, (k / res) as i64);
        NEIGHBOURS_8.iter().filter_map(move |(dx, dy)| {
            let (u, v) = (usize::try_from(x + *dx as i64).ok()?, usize::try_from(y + *dy as i64).ok()?);
            (u < res && v < res).then_some(v * res + u)
        })
    };
    let n = res * res;
    let mut filled: Vec<bool> = (0..n).map(|k| interior.get(k).is_some_and(|m| *m >= 0.5)).collect();
    let mut weight: Vec<f32> = filled.iter().map(|f| if *f { 1.0 } else { 0.0 }).collect();
    checkpoint().await;
    // Steps outside the person of each filled pixel.
    let mut outside = vec![0usize; n];
    // Each pass looks only at the unfilled neighbours of the pixels the last one filled.
    let mut last: Vec<usize> = (0..n).filter(|k| filled[*k]).collect();
    let mut seen = vec![false; n];
    while !last.is_empty() {
        checkpoint().await;
        let mut candidates = Vec::new();
        for k in last.drain(..) {
            for j in neighbours(k) {
                if !filled[j] && !seen[j] {
                    seen[j] = true;
                    candidates.push(j);
                }
            }
        }
        let mut next = Vec::new();
        for k in candidates {
            seen[k] = false;
            let (mut sum, mut count, mut steps) = (Vec3::ZERO, 0usize, usize::MAX);
            for j in neighbours(k).filter(|j| filled[*j]) {
                sum += colours[j];
                count += 1;
                steps = steps.min(outside[j]);
            }
            let on_person = mask.get(k).is_some_and(|m| *m >= 0.5);
            let steps = if on_person { 0 } else { steps.saturating_add(1) };
            if count > 0 && steps <= reach {
                next.push((k, sum / count as f32, steps));
            }
        }
        for (k, c, steps) in next {
            filled[k] = true;
            colours[k] = c;
            outside[k] = steps;
            weight[k] = 1.0 - steps as f32 / (reach + 1) as f32;
            last.push(k);
        }
    }
    weight
}

/// The photo sharpened for its bilinear lookups: each axis filtered by `[−a, 1 + 2a, −a]`,
/// the results clamped to [0, 1] (an edge's overshoot cut off). A row pass then a column pass;
/// a checkpoint every [`BAND_ROWS`] rows of each.
async fn prefilter(t: &[Vec3], res: usize, a: f32) -> Vec<Vec3> {
    async fn pass(t: &[Vec3], res: usize, a: f32, step: usize) -> Vec<Vec3> {
        let mut out = Vec::with_capacity(t.len());
        for k in 0..t.len() {
            if k % (BAND_ROWS * res) == BAND_ROWS * res - 1 {
                checkpoint().await;
            }
            // The neighbours along the pass's axis, the edge pixel standing in beyond the crop.
            let at_edge = if step == 1 { (k % res == 0, k % res + 1 == res) } else { (k < res, k + res >= t.len()) };
            let lo = if at_edge.0 { t[k] } else { t[k - step] };
            let hi = if at_edge.1 { t[k] } else { t[k + step] };
            out.push((t[k] * (1.0 + 2.0 * a) - (lo + hi) * a).clamp(Vec3::ZERO, Vec3::ONE));
        }
        out
    }
    if a <= 0.0 || t.len() != res * res {
        return t.to_vec();
    }
    let rows = pass(t, res, a, 1).await;
    pass(&rows, res, a, res).await
}

impl PhotoProjection {
    /// A photo (`rgb` sRGB `res²·3`, `mask` `res²`, both in [0, 1]) seen through `world_to_camera`
    /// and `proj` (OpenGL clip), and the avatar's posed surface as that camera sees it. Two
    /// slices ([`crate::util::cooperative`]: the depth buffer; the mask and the photo's linear
    /// colours); `run_blocking` runs it at once.
    pub async fn new_async(
        world_to_camera: Mat4,
        proj: Mat4,
        res: usize,
        rgb: &[f32],
        mask: &[f32],
        vertices: &[Vec3],
        faces: &[[u32; 3]],
    ) -> Self {
        let view_proj = proj * world_to_camera;
        let clip: Vec<Vec4> = vertices.iter().map(|v| view_proj * v.extend(1.0)).collect();
        let r = rasterize_async(&clip, faces, res, res).await;
        // Checkpoints between the steps, and within each every BAND_ROWS rows (a whole step
        // on a 512² photo took 25–55 ms in the browser, on its UI thread).
        checkpoint().await;
        let inv_proj = proj.inverse();
        let mut depth = Vec::with_capacity(res * res);
        for band in (0..res * res).step_by(BAND_ROWS * res) {
            depth.extend((band..(band + BAND_ROWS * res).min(res * res)).map(|k| {
                if r.triangle[k] < 0 {
                    return f32::INFINITY;
                }
                let (x, y) = (k % res, k / res);
                let ndc = Vec4::new(
                    (x as f32 + 0.5) / res as f32 * 2.0 - 1.0,
                    1.0 - (y as f32 + 0.5) / res as f32 * 2.0,
                    r.depth[k],
                    1.0,
                );
                let v = inv_proj * ndc;
                -v.z / v.w
            }));
            checkpoint().await;
        }
        let eroded = erode3(mask, res).await;
        let interior = own_colour_pixels(mask, &eroded);
        checkpoint().await;
        let mut texels: Vec<Vec3> = Vec::with_capacity(res * res);
        for band in rgb.chunks(3 * BAND_ROWS * res) {
            let decode = |c: &[f32]| Vec3::new(c[0], c[1], c[2]).map(crate::render::colour::decode_srgb_fast);
            texels.extend(band.chunks_exact(3).map(decode));
            checkpoint().await;
        }
        let mut inside = texels.clone();
        extend_from_interior(&mut inside, mask, &eroded, res, reach(res)).await;
        let mask = extend_from_interior(&mut texels, mask, &interior, res, reach(res)).await;
        let texels = prefilter(&texels, res, PREFILTER).await;
        let photo = Texture { width: res, height: res, texels };
        let photo_inside = Texture { width: res, height: res, texels: inside };
        Self { res, view: world_to_camera, view_proj, photo, photo_inside, mask, depth }
    }

    /// The photo's linear colour at posed point `p` with unit normal `n`, and its weight in
    /// [0, 1] (0: hidden, outside the person, or grazing).
    pub fn sample(&self, p: Vec3, n: Vec3) -> (Vec3, f32) {
        self.locate(p, n).map_or((Vec3::ZERO, 0.0), |(uv, w)| (self.photo.sample(uv), w))
    }

    /// Where posed point `p` with unit normal `n` falls on the photo (texture coordinates, v up)
    /// and the photo's weight there; `None` where it is 0.
    fn locate(&self, p: Vec3, n: Vec3) -> Option<(Vec2, f32)> {
        let pv = self.view.transform_point3(p);
        if pv.z >= 0.0 {
            return None;
        }
        let to_cam = (-pv).normalize_or_zero();
        let nv = self.view.transform_vector3(n).normalize_or_zero();
        let cos = nv.dot(to_cam);
        let facing = ((cos - GRAZING) / (FACING - GRAZING)).clamp(0.0, 1.0);
        let facing = facing * facing * (3.0 - 2.0 * facing);
        if facing <= 0.0 {
            return None;
        }
        let c = self.view_proj * p.extend(1.0);
        let ndc = Vec2::new(c.x / c.w, c.y / c.w);
        let r = self.res as f32;
        let px = Vec2::new((ndc.x + 1.0) * 0.5 * r, (1.0 - ndc.y) * 0.5 * r);
        if px.x < 0.0 || px.y < 0.0 || px.x >= r || px.y >= r {
            return None;
        }
        let k = px.y as usize * self.res + px.x as usize;
        // Visible: not behind the avatar's nearest surface at this pixel.
        if -pv.z > self.depth[k] + DEPTH_TOLERANCE {
            return None;
        }
        let w = facing * self.mask[k].clamp(0.0, 1.0);
        if w <= 0.0 {
            return None;
        }
        // The texture lookup's v points up from the image's bottom row.
        Some((Vec2::new(px.x / r, 1.0 - px.y / r), w))
    }

    /// Blend the photo into `colors` (linear) at posed `points` with `normals`; `canonical`
    /// (the same points in the canonical Da-pose, one per colour) carries the photo's colour
    /// shift to the parts it does not see ([`colour_shift`]). With `canonical` of another length
    /// than `colors` the hidden side keeps its generated colours.
    pub fn blend(&self, canonical: &[Vec3], points: &[Vec3], normals: &[Vec3], colors: &mut [Vec3]) {
        crate::util::cooperative::run_blocking(self.blend_async(canonical, points, normals, colors))
    }

    /// [`Self::blend`] in slices ([`crate::util::cooperative`]): the samples in chunks, then each
    /// of the colour shift's grids.
    pub async fn blend_async(&self, canonical: &[Vec3], points: &[Vec3], normals: &[Vec3], colors: &mut [Vec3]) {
        let mut located: Vec<Option<(Vec2, f32)>> = Vec::with_capacity(points.len());
        for (p, n) in points.chunks(SLICE).zip(normals.chunks(SLICE)) {
            located.extend(p.iter().zip(n).map(|(p, n)| self.locate(*p, *n)));
            checkpoint().await;
        }
        let samples = lookups(&located, &self.photo).await;
        let shift = if canonical.len() == colors.len() {
            let inside = lookups(&located, &self.photo_inside).await;
            colour_shift_async(canonical, &inside, colors).await
        } else {
            vec![Vec3::ZERO; colors.len()]
        };
        for ((c, (photo, w)), d) in colors.iter_mut().zip(samples).zip(shift) {
            *c = (*c + d).clamp(Vec3::ZERO, Vec3::ONE).lerp(photo, w);
        }
    }
}

/// Points per slice of [`PhotoProjection::blend_async`]'s loops.
const SLICE: usize = 4096;

/// The colours of `t` at the photo positions `located` (zero weight where `None`), a
/// checkpoint every [`SLICE`] points.
async fn lookups(located: &[Option<(Vec2, f32)>], t: &Texture) -> Vec<(Vec3, f32)> {
    let mut out = Vec::with_capacity(located.len());
    for chunk in located.chunks(SLICE) {
        out.extend(chunk.iter().map(|l| l.map_or((Vec3::ZERO, 0.0), |(uv, w)| (t.sample(uv), w))));
        checkpoint().await;
    }
    out
}

/// Widths (Gaussian σ, metres) of the colour shift's two levels: the fine one keeps garment
/// borders (a waist, a hem) where the photo saw them; the coarse one reaches what only the
/// far side of the body covers in the front view (a side photo's hidden half).
pub const SHIFT_FINE: f32 = 0.04;
pub const SHIFT_COARSE: f32 = 0.16;
/// How far (linear RGB) a seen point's shift may lie from the mean around it before it counts
/// less in the colour shift (a Gaussian weight of this σ).
pub const SHIFT_OUTLIER: f32 = 0.25;

/// The photo's colour shift carried to the surface it does not see: per point, the mean of
/// `photo − generated` over the points the photo does see (weighted by their photo weight) near
/// it in the canonical pose's front view (x, y: the Da-pose faces +z, so a point's front and back
/// fall together, and the back of a dress takes the shift of its front), at two widths, each
/// faded out where the photo saw less than a fifth of the points around. Additive in linear
/// RGB: the generated texture's own variation stays, its tone follows the photo's. Robust: a
/// second round weighs each seen point down by how far its shift lies from the first round's
/// mean around it (σ [`SHIFT_OUTLIER`]), so that background inside the detector's mask does not
/// tint the hidden side.
pub fn colour_shift(canonical: &[Vec3], samples: &[(Vec3, f32)], colors: &[Vec3]) -> Vec<Vec3> {
    crate::util::cooperative::run_blocking(colour_shift_async(canonical, samples, colors))
}

/// [`colour_shift`] in slices: one per grid and per pass over the points.
pub async fn colour_shift_async(canonical: &[Vec3], samples: &[(Vec3, f32)], colors: &[Vec3]) -> Vec<Vec3> {
    let fine = ShiftGrid::new(canonical, samples, colors, SHIFT_FINE);
    checkpoint().await;
    let coarse = ShiftGrid::new(canonical, samples, colors, SHIFT_COARSE);
    checkpoint().await;
    let mut reweighted: Vec<(Vec3, f32)> = Vec::with_capacity(samples.len());
    for ((p, s), g) in canonical.chunks(SLICE).zip(samples.chunks(SLICE)).zip(colors.chunks(SLICE)) {
        reweighted.extend(p.iter().zip(s).zip(g).map(|((p, (photo, w)), g)| {
            let ((f, fs), (c, cs)) = (fine.at(*p), coarse.at(*p));
            let mean = if fs > 0.05 {
                f / fs
            } else if cs > 0.05 {
                c / cs
            } else {
                return (*photo, *w);
            };
            let d = (*photo - *g - mean).length_squared();
            (*photo, w * (-d / (2.0 * SHIFT_OUTLIER * SHIFT_OUTLIER)).exp())
        }));
        checkpoint().await;
    }
    let fine = ShiftGrid::new(canonical, &reweighted, colors, SHIFT_FINE);
    checkpoint().await;
    let coarse = ShiftGrid::new(canonical, &reweighted, colors, SHIFT_COARSE);
    checkpoint().await;
    let mut shift = Vec::with_capacity(canonical.len());
    for p in canonical.chunks(SLICE) {
        shift.extend(p.iter().map(|p| {
            let (f, fs) = fine.at(*p);
            let (c, _) = coarse.at(*p);
            f + (1.0 - fs) * c
        }));
        checkpoint().await;
    }
    shift
}

/// One level of [`colour_shift`]: a grid over the canonical x, y with cells of σ/2, holding the
/// shift times its strength, and the strength.
struct ShiftGrid {
    origin: Vec2,
    cell: f32,
    w: usize,
    h: usize,
    /// Shift × strength per cell, and the strength in [0, 1].
    shift: Vec<Vec3>,
    strength: Vec<f32>,
}

impl ShiftGrid {
    /// At most this many cells a side (a surface spread wider takes coarser cells).
    const MAX_SIDE: usize = 512;

    fn new(canonical: &[Vec3], samples: &[(Vec3, f32)], colors: &[Vec3], sigma: f32) -> Self {
        let (mut lo, mut hi) = (Vec2::splat(f32::INFINITY), Vec2::splat(f32::NEG_INFINITY));
        for p in canonical.iter().filter(|p| p.is_finite()) {
            lo = lo.min(p.truncate());
            hi = hi.max(p.truncate());
        }
        if lo.x > hi.x {
            return Self { origin: Vec2::ZERO, cell: 1.0, w: 1, h: 1, shift: vec![Vec3::ZERO], strength: vec![0.0] };
        }
        let extent = (hi - lo).max_element();
        let cell = (sigma / 2.0).max(extent / (Self::MAX_SIDE - 1) as f32).max(1e-6);
        let (w, h) = (((hi.x - lo.x) / cell) as usize + 1, ((hi.y - lo.y) / cell) as usize + 1);
        let index = |p: Vec3| {
            let q = (p.truncate() - lo) / cell;
            (q.y.round() as usize).min(h - 1) * w + (q.x.round() as usize).min(w - 1)
        };
        // Splat: the weighted shift, the photo's weight, and how many points.
        let (mut acc, mut seen, mut count) = (vec![Vec3::ZERO; w * h], vec![0.0f32; w * h], vec![0.0f32; w * h]);
        for ((p, (photo, wt)), c) in canonical.iter().zip(samples).zip(colors) {
            if !p.is_finite() {
                continue;
            }
            let k = index(*p);
            count[k] += 1.0;
            if *wt > 0.0 {
                acc[k] += *wt * (*photo - *c);
                seen[k] += *wt;
            }
        }
        let radius = (3.0 * sigma / cell).ceil() as i64;
        let kernel: Vec<f32> = (-radius..=radius).map(|i| (-0.5 * (i as f32 * cell / sigma).powi(2)).exp()).collect();
        let acc = blur(&acc, w, h, &kernel);
        let seen = blur(&seen, w, h, &kernel);
        let count = blur(&count, w, h, &kernel);
        let mut shift = vec![Vec3::ZERO; w * h];
        let mut strength = vec![0.0f32; w * h];
        for k in 0..w * h {
            if seen[k] > 1e-6 && count[k] > 1e-6 {
                let t = (seen[k] / count[k] / 0.2).clamp(0.0, 1.0);
                strength[k] = t * t * (3.0 - 2.0 * t);
                shift[k] = acc[k] / seen[k] * strength[k];
            }
        }
        Self { origin: lo, cell, w, h, shift, strength }
    }

    /// Bilinear lookup at `p`'s x, y: (shift × strength, strength).
    fn at(&self, p: Vec3) -> (Vec3, f32) {
        if !p.is_finite() {
            return (Vec3::ZERO, 0.0);
        }
        let q = ((p.truncate() - self.origin) / self.cell)
            .clamp(Vec2::ZERO, Vec2::new((self.w - 1) as f32, (self.h - 1) as f32));
        let (x0, y0) = (q.x.floor() as usize, q.y.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(self.w - 1), (y0 + 1).min(self.h - 1));
        let (fx, fy) = (q.x - x0 as f32, q.y - y0 as f32);
        let mut out = (Vec3::ZERO, 0.0);
        for (x, y, wt) in
            [(x0, y0, (1.0 - fx) * (1.0 - fy)), (x1, y0, fx * (1.0 - fy)), (x0, y1, (1.0 - fx) * fy), (x1, y1, fx * fy)]
        {
            out.0 += wt * self.shift[y * self.w + x];
            out.1 += wt * self.strength[y * self.w + x];
        }
        out
    }
}

/// A separable blur of a `w × h` grid with a symmetric `kernel` (zero outside the grid).
fn blur<T>(grid: &[T], w: usize, h: usize, kernel: &[f32]) -> Vec<T>
where
    T: Copy + Default + std::ops::Add<Output = T> + std::ops::Mul<f32, Output = T>,
{
    let r = (kernel.len() / 2) as i64;
    let pass = |src: &[T], along_x: bool| -> Vec<T> {
        let mut out = vec![T::default(); w * h];
        for y in 0..h as i64 {
            for x in 0..w as i64 {
                let mut sum = T::default();
                for (i, k) in kernel.iter().enumerate() {
                    let d = i as i64 - r;
                    let (u, v) = if along_x { (x + d, y) } else { (x, y + d) };
                    if (0..w as i64).contains(&u) && (0..h as i64).contains(&v) {
                        sum = sum + src[(v * w as i64 + u) as usize] * *k;
                    }
                }
                out[(y * w as i64 + x) as usize] = sum;
            }
        }
        out
    };
    pass(&pass(grid, true), false)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::camera::OrbitCamera;
    use crate::util::cooperative::run_blocking;

    fn project(
        view: Mat4,
        proj: Mat4,
        res: usize,
        rgb: &[f32],
        mask: &[f32],
        v: &[Vec3],
        f: &[[u32; 3]],
    ) -> PhotoProjection {
        crate::util::cooperative::run_blocking(PhotoProjection::new_async(view, proj, res, rgb, mask, v, f))
    }

    /// Stripes two pixels wide, looked up bilinearly at 8×8 points per pixel and averaged (what
    /// the bake's lookups and a render at the photo's camera do), come back with their contrast
    /// when the photo is prefiltered first; a plain colour stays as it is.
    #[test]
    fn the_prefiltered_photo_comes_back_through_the_lookups_with_its_stripes() {
        let res = 32;
        let stripes: Vec<Vec3> =
            (0..res * res).map(|k| Vec3::splat(if (k % res) / 2 % 2 == 0 { 0.2 } else { 0.8 })).collect();
        let through_lookups = |texels: Vec<Vec3>| {
            let t = Texture { width: res, height: res, texels };
            let error = (0..res * res)
                .filter(|k| (4..res - 4).contains(&(k % res)) && (4..res - 4).contains(&(k / res)))
                .map(|k| {
                    let (x, y) = ((k % res) as f32, (k / res) as f32);
                    let mut sum = Vec3::ZERO;
                    for i in 0..64 {
                        let (sx, sy) = ((i % 8) as f32 + 0.5, (i / 8) as f32 + 0.5);
                        sum += t.sample(Vec2::new((x + sx / 8.0) / res as f32, 1.0 - (y + sy / 8.0) / res as f32));
                    }
                    (sum / 64.0 - stripes[k]).x.powi(2)
                })
                .sum::<f32>();
            error.sqrt()
        };
        let plain = through_lookups(stripes.clone());
        let sharpened = through_lookups(run_blocking(prefilter(&stripes, res, PREFILTER)));
        assert!(plain > 1.0, "the stripes lose contrast through plain lookups: {plain}");
        assert!(sharpened < 0.5 * plain, "prefiltered {sharpened} against plain {plain}");
        let grey = vec![Vec3::new(0.3, 0.5, 0.7); res * res];
        let kept = run_blocking(prefilter(&grey, res, PREFILTER));
        assert!(kept.iter().zip(&grey).all(|(a, b)| (*a - *b).abs().max_element() < 1e-6));
    }

    /// A unit quad facing +z at z = 0 and a second one behind it at z = −0.5.
    fn quads() -> (Vec<Vec3>, Vec<[u32; 3]>) {
        let mut v = Vec::new();
        let mut f = Vec::new();
        for z in [0.0f32, -0.5] {
            let b = v.len() as u32;
            v.extend([
                Vec3::new(-0.5, 0.5, z),
                Vec3::new(0.5, 0.5, z),
                Vec3::new(0.5, 1.5, z),
                Vec3::new(-0.5, 1.5, z),
            ]);
            f.extend([[b, b + 1, b + 2], [b, b + 2, b + 3]]);
        }
        (v, f)
    }

    #[test]
    fn the_hidden_side_takes_the_shift_of_what_the_photo_saw_in_front_of_it() {
        // A slab 0.4 m wide and 1 m tall, points every 2 cm on its front (z = +0.1) and back
        // (z = −0.1): generated grey everywhere; the photo sees the front, red on its top half,
        // blue on its bottom half. A second slab 2 m to the side is not seen at all.
        let grey = Vec3::splat(0.5);
        let (red, blue) = (Vec3::new(0.9, 0.1, 0.1), Vec3::new(0.1, 0.1, 0.9));
        let (mut canonical, mut samples) = (Vec::new(), Vec::new());
        for (x0, seen) in [(0.0f32, true), (2.0, false)] {
            for z in [0.1f32, -0.1] {
                for i in 0..20 {
                    for j in 0..50 {
                        let p = Vec3::new(x0 + i as f32 * 0.02, j as f32 * 0.02, z);
                        canonical.push(p);
                        // A 3 × 3-point patch of background (green) inside the red half.
                        let patch = (0.16..0.21).contains(&p.x) && (0.7..0.75).contains(&p.y);
                        let photo = if patch {
                            Vec3::new(0.1, 0.9, 0.1)
                        } else if p.y >= 0.5 {
                            red
                        } else {
                            blue
                        };
                        samples.push(if seen && z > 0.0 { (photo, 1.0) } else { (Vec3::ZERO, 0.0) });
                    }
                }
            }
        }
        let colors = vec![grey; canonical.len()];
        let shift = colour_shift(&canonical, &samples, &colors);
        for ((p, d), (_, w)) in canonical.iter().zip(&shift).zip(&samples) {
            let got = grey + *d;
            if p.x >= 1.0 {
                assert!(d.length() < 1e-6, "unseen slab at {p}: shift {d}");
            } else if *w == 0.0 && (p.y - 0.5).abs() > 0.1 && p.x > 0.06 && p.x < 0.32 {
                // The back, away from the red/blue border and the sides: the front's colour; the
                // green patch does not tint it (without the robust round, 0.057 off there).
                let want = if p.y >= 0.5 { red } else { blue };
                assert!((got - want).length() < 0.05, "back at {p}: {got} want {want}");
            }
        }
        // Near the border the back shifts part-way, towards the nearer colour.
        let at = |y: f32| {
            let k = canonical.iter().position(|p| (p.x - 0.2).abs() < 1e-4 && (p.y - y).abs() < 1e-4 && p.z < 0.0);
            grey + shift[k.expect("a back point there")]
        };
        let (above, below) = (at(0.52), at(0.46));
        assert!(above.x > above.z && below.z > below.x, "{above} {below}");
        assert!(shift.iter().all(|d| d.is_finite()));
    }

    #[test]
    fn erosion_is_the_three_by_three_minimum_with_zero_outside() {
        let res = 9;
        let mut rng = crate::util::rng::Rng::new(7, 0);
        let mask: Vec<f32> = (0..res * res).map(|_| rng.uniform()).collect();
        let got = run_blocking(erode3(&mask, res));
        for y in 0..res as i64 {
            for x in 0..res as i64 {
                let mut m = f32::INFINITY;
                for (u, v) in (-1..=1).flat_map(|dy| (-1..=1).map(move |dx| (x + dx, y + dy))) {
                    let inside = (0..res as i64).contains(&u) && (0..res as i64).contains(&v);
                    m = m.min(if inside { mask[(v * res as i64 + u) as usize] } else { 0.0 });
                }
                assert_eq!(got[(y * res as i64 + x) as usize], m, "({x}, {y})");
            }
        }
        // Interior pixels are not all zero (the check above is not trivially met).
        assert!(got.iter().any(|v| *v > 0.0));
    }

    #[test]
    fn the_border_and_a_few_pixels_beyond_take_the_colours_just_inside() {
        // A 16² photo: the person is the square [4, 12)², red inside, its one-pixel border
        // mixed half-way with the white background, the background white.
        let res = 16;
        let on = |x: usize, y: usize| (4..12).contains(&x) && (4..12).contains(&y);
        let edge = |x: usize, y: usize| on(x, y) && (x == 4 || x == 11 || y == 4 || y == 11);
        let mut colours = Vec::new();
        let mut mask = Vec::new();
        for y in 0..res {
            for x in 0..res {
                let (c, m) = match (on(x, y), edge(x, y)) {
                    (true, false) => (Vec3::new(1.0, 0.0, 0.0), 1.0),
                    (true, true) => (Vec3::new(1.0, 0.5, 0.5), 0.6),
                    _ => (Vec3::ONE, 0.0),
                };
                colours.push(c);
                mask.push(m);
            }
        }
        let eroded = run_blocking(erode3(&mask, res));
        let r = 2;
        let w = run_blocking(extend_from_interior(&mut colours, &mask, &eroded, res, r));
        let red = Vec3::new(1.0, 0.0, 0.0);
        for y in 0..res {
            for x in 0..res {
                let k = y * res + x;
                // Steps outside the person (Chebyshev distance to the square).
                let dx = (4i64 - x as i64).max(x as i64 - 11).max(0);
                let dy = (4i64 - y as i64).max(y as i64 - 11).max(0);
                let out = dx.max(dy) as usize;
                if out <= r {
                    assert!((colours[k] - red).length() < 1e-6, "({x}, {y}): {}", colours[k]);
                    let want = 1.0 - out as f32 / (r + 1) as f32;
                    assert!((w[k] - want).abs() < 1e-6, "({x}, {y}): weight {} want {want}", w[k]);
                } else {
                    assert_eq!(w[k], 0.0, "({x}, {y})");
                }
            }
        }
        assert_eq!((reach(32), reach(128), reach(512)), (2, 4, 16));
    }

    #[test]
    fn border_pixels_the_person_covers_keep_their_colour_mixed_ones_take_the_inside() {
        // A 16² photo: the person is the square [3, 13)², red inside, ringed by a one-pixel
        // blue band the mask covers fully (hair at the side of a head), then a ring mixed with
        // the white background (mask 0.4 and 0.6, part blue).
        let res = 16;
        let ring = |x: usize, y: usize, lo: usize, hi: usize| {
            (lo..hi).contains(&x) && (lo..hi).contains(&y) && (x == lo || x == hi - 1 || y == lo || y == hi - 1)
        };
        let (mut rgb, mut mask) = (Vec::new(), Vec::new());
        for y in 0..res {
            for x in 0..res {
                let (c, m) = if ring(x, y, 3, 13) {
                    ([0.5, 0.5, 1.0], if x == 3 { 0.6 } else { 0.4 })
                } else if ring(x, y, 4, 12) {
                    ([0.0, 0.0, 1.0], 1.0)
                } else if (5..11).contains(&x) && (5..11).contains(&y) {
                    ([1.0, 0.0, 0.0], 1.0)
                } else {
                    ([1.0, 1.0, 1.0], 0.0)
                };
                rgb.extend(c);
                mask.push(m);
            }
        }
        let cam = OrbitCamera::default();
        let p = project(cam.world_to_camera(), cam.projection_gl(1.0), res, &rgb, &mask, &[], &[]);
        let at = |x: usize, y: usize| p.photo.texels[y * res + x];
        let (red, blue) = (Vec3::new(1.0, 0.0, 0.0), Vec3::new(0.0, 0.0, 1.0));
        // The covered band keeps its blue (the 3×3 erosion alone gave it the red inside).
        for (x, y) in [(4, 4), (4, 8), (8, 4), (11, 8), (8, 11)] {
            assert!((at(x, y) - blue).length() < 1e-6, "({x}, {y}): {}", at(x, y));
        }
        assert!((at(8, 8) - red).length() < 1e-6);
        // The colour shift's copy fills the border from inside the eroded mask (on the left the
        // 0.6 ring leaves the band inside the erosion).
        for (x, y) in [(8, 4), (11, 8), (8, 11), (12, 8)] {
            let c = p.photo_inside.texels[y * res + x];
            assert!((c - red).length() < 1e-6, "({x}, {y}): {c}");
        }
        // The mixed ring, inside the mask (0.6) or not (0.4), takes the band's blue, not its own
        // pale blue.
        for (x, y) in [(3, 8), (8, 3), (12, 8)] {
            assert!((at(x, y) - blue).length() < 1e-6, "({x}, {y}): {}", at(x, y));
        }
        assert_eq!(p.mask[8 * res + 3], 1.0);
        assert!(p.mask[8 * res + 12] < 1.0 && p.mask[8 * res + 12] > 0.0);
    }

    #[test]
    fn visible_facing_points_take_the_photo_hidden_and_grazing_ones_do_not() {
        let cam = OrbitCamera { target: Vec3::new(0.0, 1.0, 0.0), ..OrbitCamera::default() };
        let res = 64;
        // Left half red, right half blue (sRGB), everyone inside the mask.
        let rgb: Vec<f32> =
            (0..res * res).flat_map(|k| if k % res < res / 2 { [1.0, 0.0, 0.0] } else { [0.0, 0.0, 1.0] }).collect();
        let mask = vec![1.0; res * res];
        let (v, f) = quads();
        let p = project(cam.world_to_camera(), cam.projection_gl(1.0), res, &rgb, &mask, &v, &f);
        let n = Vec3::Z;
        let (c, w) = p.sample(Vec3::new(-0.2, 1.0, 0.0), n);
        assert!((w - 1.0).abs() < 1e-6 && (c - Vec3::new(1.0, 0.0, 0.0)).length() < 1e-3, "{c} {w}");
        let (c, w) = p.sample(Vec3::new(0.2, 1.0, 0.0), n);
        assert!(w > 0.99 && (c - Vec3::new(0.0, 0.0, 1.0)).length() < 1e-3, "{c} {w}");
        // Behind the front quad: hidden.
        assert_eq!(p.sample(Vec3::new(0.2, 1.0, -0.5), n).1, 0.0);
        // Facing away, even just: no weight; between grazing and facing: partial.
        assert_eq!(p.sample(Vec3::new(0.2, 1.0, 0.0), -Vec3::Z).1, 0.0);
        assert_eq!(p.sample(Vec3::new(0.2, 1.0, 0.0), Vec3::new(1.0, 0.0, -0.05).normalize()).1, 0.0);
        let half = p.sample(Vec3::new(0.0, 1.0, 0.0), Vec3::new(1.0, 0.0, 0.15).normalize()).1;
        assert!(half > 0.0 && half < 1.0, "{half}");
        // Outside the person mask: no weight.
        let p = project(cam.world_to_camera(), cam.projection_gl(1.0), res, &rgb, &vec![0.0; res * res], &v, &f);
        assert_eq!(p.sample(Vec3::new(-0.2, 1.0, 0.0), n).1, 0.0);
        // Blending keeps the generated colour where the weight is 0.
        let mut cols = vec![Vec3::splat(0.5); 2];
        let p = project(cam.world_to_camera(), cam.projection_gl(1.0), res, &rgb, &mask, &v, &f);
        p.blend(&[], &[Vec3::new(-0.2, 1.0, 0.0), Vec3::new(-0.2, 1.0, -0.5)], &[n, n], &mut cols);
        assert!((cols[0] - Vec3::new(1.0, 0.0, 0.0)).length() < 1e-3 && cols[1] == Vec3::splat(0.5), "{cols:?}");
    }
}
