//! Rasterisation, modelled on nvdiffrast's primitives (Laine et al. 2020):
//! [`rasterize`] (per-pixel triangle id and perspective-correct barycentrics),
//! [`interpolate`] (attributes at pixels) and [`texture`] (bilinear image lookups at
//! interpolated UVs). This is the CPU reference implementation used by
//! the CLI and tests; the app draws with wgpu.
//!
//! Conventions: clip-space positions (x, y, z, w) as produced by an OpenGL projection;
//! pixel (0, 0) is the top-left, pixel centres at +0.5; depth test on z/w, nearest wins;
//! triangles with a vertex at w ≤ 0 are dropped (no near-plane clipping).

use crate::render::colour::{decode_srgb, linear_to_srgb};
use glam::{Vec2, Vec3, Vec4};

/// Output of [`rasterize`]: per pixel, row-major from the top-left.
#[derive(Clone, Debug)]
pub struct Raster {
    pub width: usize,
    pub height: usize,
    /// Triangle index per pixel, `-1` where no triangle covers the pixel centre.
    pub triangle: Vec<i32>,
    /// Perspective-correct barycentrics (u, v) of vertices 1 and 2 (vertex 0 has 1 − u − v).
    pub bary: Vec<[f32; 2]>,
    /// z/w (NDC depth, −1 near … 1 far).
    pub depth: Vec<f32>,
}

/// Rasterise triangles `tris` with clip-space vertex positions `clip` into a `width`×`height` image.
pub fn rasterize(clip: &[Vec4], tris: &[[u32; 3]], width: usize, height: usize) -> Raster {
    crate::util::cooperative::run_blocking(rasterize_async(clip, tris, width, height))
}

/// Triangles rasterised between two checkpoints of [`rasterize_async`].
const TRIANGLES_PER_SLICE: usize = 4096;
/// Pixels of the raster's buffers filled between two checkpoints of [`rasterize_async`].
const PIXELS_PER_SLICE: usize = 1 << 16;

/// [`rasterize`] with a checkpoint ([`crate::util::cooperative`]) every
/// [`TRIANGLES_PER_SLICE`] triangles, for large images on the browser's UI thread.
pub async fn rasterize_async(clip: &[Vec4], tris: &[[u32; 3]], width: usize, height: usize) -> Raster {
    let n = width * height;
    let mut r = Raster {
        width,
        height,
        triangle: Vec::with_capacity(n),
        bary: Vec::with_capacity(n),
        depth: Vec::with_capacity(n),
    };
    // The buffers are filled in slices too: the first touch of fresh memory is what costs in
    // the browser (a 512² raster's three buffers took 20–30 ms at once there).
    for start in (0..n).step_by(PIXELS_PER_SLICE) {
        let m = PIXELS_PER_SLICE.min(n - start);
        r.triangle.extend(std::iter::repeat_n(-1, m));
        r.bary.extend(std::iter::repeat_n([0.0; 2], m));
        r.depth.extend(std::iter::repeat_n(f32::INFINITY, m));
        crate::util::cooperative::checkpoint().await;
    }
    for (t, tri) in tris.iter().enumerate() {
        if t % TRIANGLES_PER_SLICE == TRIANGLES_PER_SLICE - 1 {
            crate::util::cooperative::checkpoint().await;
        }
        let c = tri.map(|i| clip[i as usize]);
        if c.iter().any(|v| v.w <= 1e-6) {
            continue;
        }
        // Screen positions (pixels) and NDC depth.
        let s = c.map(|v| {
            Vec3::new((v.x / v.w + 1.0) * 0.5 * width as f32, (1.0 - v.y / v.w) * 0.5 * height as f32, v.z / v.w)
        });
        let area = (s[1].x - s[0].x) * (s[2].y - s[0].y) - (s[1].y - s[0].y) * (s[2].x - s[0].x);
        if area.abs() < 1e-12 {
            continue;
        }
        let x0 = s.iter().map(|p| p.x).fold(f32::INFINITY, f32::min).floor().max(0.0) as usize;
        let x1 = (s.iter().map(|p| p.x).fold(f32::NEG_INFINITY, f32::max).ceil() as i64).min(width as i64 - 1);
        let y0 = s.iter().map(|p| p.y).fold(f32::INFINITY, f32::min).floor().max(0.0) as usize;
        let y1 = (s.iter().map(|p| p.y).fold(f32::NEG_INFINITY, f32::max).ceil() as i64).min(height as i64 - 1);
        if x1 < 0 || y1 < 0 {
            continue;
        }
        let inv_w = c.map(|v| 1.0 / v.w);
        for py in y0..=y1 as usize {
            for px in x0..=x1 as usize {
                let (x, y) = (px as f32 + 0.5, py as f32 + 0.5);
                let e = |a: usize, b: usize| (s[b].x - s[a].x) * (y - s[a].y) - (s[b].y - s[a].y) * (x - s[a].x);
                let (w0, w1, w2) = (e(1, 2) / area, e(2, 0) / area, e(0, 1) / area);
                if w0 < 0.0 || w1 < 0.0 || w2 < 0.0 {
                    continue;
                }
                let z = w0 * s[0].z + w1 * s[1].z + w2 * s[2].z;
                let k = py * width + px;
                if z < r.depth[k] {
                    let (p0, p1, p2) = (w0 * inv_w[0], w1 * inv_w[1], w2 * inv_w[2]);
                    let sum = p0 + p1 + p2;
                    r.depth[k] = z;
                    r.triangle[k] = t as i32;
                    r.bary[k] = [p1 / sum, p2 / sum];
                }
            }
        }
    }
    r
}

/// Interpolate per-vertex attributes at every covered pixel (`None` on background).
pub fn interpolate(attr: &[Vec3], raster: &Raster, tris: &[[u32; 3]]) -> Vec<Option<Vec3>> {
    raster
        .triangle
        .iter()
        .zip(&raster.bary)
        .map(|(&t, &[u, v])| {
            (t >= 0).then(|| {
                let [a, b, c] = tris[t as usize].map(|i| attr[i as usize]);
                a * (1.0 - u - v) + b * u + c * v
            })
        })
        .collect()
}

/// An RGB image for [`texture`] lookups, linear-light texels, row 0 at the top.
#[derive(Clone, Debug, PartialEq)]
pub struct Texture {
    pub width: usize,
    pub height: usize,
    /// Linear RGB, row-major from the top row.
    pub texels: Vec<Vec3>,
}

impl Texture {
    /// From 8-bit sRGB-encoded RGB or RGBA pixels (`channels` 3 or 4; alpha ignored).
    pub fn from_srgb8(width: usize, height: usize, channels: usize, pixels: &[u8]) -> Option<Self> {
        if width == 0 || height == 0 || !(3..=4).contains(&channels) || pixels.len() != width * height * channels {
            return None;
        }
        let lut: Vec<f32> = (0..256).map(|i| decode_srgb(i as f32 / 255.0)).collect();
        let texels = pixels
            .chunks_exact(channels)
            .map(|p| Vec3::new(lut[p[0] as usize], lut[p[1] as usize], lut[p[2] as usize]));
        Some(Self { width, height, texels: texels.collect() })
    }

    /// Bilinear lookup at `uv` with OBJ's convention (u right, v up, (0, 0) = bottom-left
    /// corner of the image), wrapping (repeat) outside [0, 1].
    pub fn sample(&self, uv: Vec2) -> Vec3 {
        let x = uv.x * self.width as f32 - 0.5;
        let y = (1.0 - uv.y) * self.height as f32 - 0.5;
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let at = |ix: f32, iy: f32| {
            let i = (ix as i64).rem_euclid(self.width as i64) as usize;
            let j = (iy as i64).rem_euclid(self.height as i64) as usize;
            self.texels[j * self.width + i]
        };
        let top = at(x0, y0).lerp(at(x0 + 1.0, y0), fx);
        let bottom = at(x0, y0 + 1.0).lerp(at(x0 + 1.0, y0 + 1.0), fx);
        top.lerp(bottom, fy)
    }
}

/// nvdiffrast's `texture`: bilinear lookups of `tex` at per-pixel `uv` (`None` stays `None`).
pub fn texture(tex: &Texture, uv: &[Option<Vec2>]) -> Vec<Option<Vec3>> {
    uv.iter().map(|p| p.map(|p| tex.sample(p))).collect()
}

/// RGB / normal / mask images of a mesh, 8-bit, row-major RGB (mask: one channel).
#[derive(Clone, Debug)]
pub struct RenderedViews {
    pub size: usize,
    /// Colours on a white background (the data's convention).
    pub rgb: Vec<u8>,
    /// World-space normals encoded (n+1)/2; background = zero vector (128).
    pub normal: Vec<u8>,
    /// Coverage 0..255 (antialiased by supersampling).
    pub mask: Vec<u8>,
}

/// Render RGB, normal and mask views at `size`² with `ss`×`ss` supersampling, colours
/// interpolated from the vertices. `view_proj` maps world to OpenGL clip space.
pub fn render_views(
    vertices: &[Vec3],
    tris: &[[u32; 3]],
    normals: &[Vec3],
    colors: &[Vec3],
    view_proj: glam::Mat4,
    size: usize,
    ss: usize,
) -> RenderedViews {
    let hi = size * ss.max(1);
    let clip: Vec<Vec4> = vertices.iter().map(|v| view_proj * v.extend(1.0)).collect();
    let r = rasterize(&clip, tris, hi, hi);
    let c = interpolate(colors, &r, tris);
    composite(&r, &interpolate(normals, &r, tris), &c, size, ss.max(1))
}

/// Like [`render_views`], but each pixel's colour comes from `texture`, called once with the
/// interpolated `canonical` coordinates of all covered (super)samples — the paper's Sec. 4.4:
/// the texture field is queried at the canonical coordinate of every pixel. An error of
/// `texture` (e.g. a failed GPU read-back) is returned as it is.
#[allow(clippy::too_many_arguments)]
pub fn render_views_textured<E>(
    vertices: &[Vec3],
    tris: &[[u32; 3]],
    normals: &[Vec3],
    canonical: &[Vec3],
    view_proj: glam::Mat4,
    size: usize,
    ss: usize,
    texture: impl FnOnce(&[Vec3]) -> Result<Vec<Vec3>, E>,
) -> Result<RenderedViews, E> {
    let hi = size * ss.max(1);
    let clip: Vec<Vec4> = vertices.iter().map(|v| view_proj * v.extend(1.0)).collect();
    let r = rasterize(&clip, tris, hi, hi);
    let canon = interpolate(canonical, &r, tris);
    let covered: Vec<usize> = (0..canon.len()).filter(|&k| canon[k].is_some()).collect();
    let points: Vec<Vec3> = covered.iter().filter_map(|&k| canon[k]).collect();
    let colors = texture(&points)?;
    let mut c = vec![None; canon.len()];
    for (&k, col) in covered.iter().zip(colors) {
        c[k] = Some(col);
    }
    Ok(composite(&r, &interpolate(normals, &r, tris), &c, size, ss.max(1)))
}

/// Average `ss`×`ss` samples into the three 8-bit images.
fn composite(r: &Raster, n: &[Option<Vec3>], c: &[Option<Vec3>], size: usize, ss: usize) -> RenderedViews {
    let hi = r.width;
    let mut out = RenderedViews {
        size,
        rgb: vec![0; size * size * 3],
        normal: vec![0; size * size * 3],
        mask: vec![0; size * size],
    };
    let enc = |x: f32| (x.clamp(0.0, 1.0) * 255.0).round() as u8;
    for y in 0..size {
        for x in 0..size {
            let (mut rgb, mut nrm, mut cov) = (Vec3::ZERO, Vec3::ZERO, 0.0f32);
            for sy in 0..ss {
                for sx in 0..ss {
                    let k = (y * ss + sy) * hi + x * ss + sx;
                    match (c[k], n[k]) {
                        (Some(col), Some(nn)) => {
                            rgb += linear_to_srgb(col);
                            nrm += nn.normalize_or_zero() * 0.5 + Vec3::splat(0.5);
                            cov += 1.0;
                        }
                        _ => {
                            rgb += Vec3::ONE;
                            nrm += Vec3::splat(0.5);
                        }
                    }
                }
            }
            let s = (ss * ss) as f32;
            let (rgb, nrm) = (rgb / s, nrm / s);
            let k = y * size + x;
            out.rgb[3 * k..3 * k + 3].copy_from_slice(&rgb.to_array().map(enc));
            out.normal[3 * k..3 * k + 3].copy_from_slice(&nrm.to_array().map(enc));
            out.mask[k] = enc(cov / s);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::camera::OrbitCamera;

    /// The sliced raster gives the host a checkpoint per slice of its buffers and of its
    /// triangles, and the same image as [`rasterize`].
    #[test]
    fn the_sliced_raster_offers_a_checkpoint_per_slice_and_draws_the_same_image() {
        use std::cell::Cell;
        use std::future::Future;
        use std::rc::Rc;
        // A 100×100 grid of quads (20,000 triangles) over the middle of the NDC square.
        let n = 100usize;
        let clip: Vec<Vec4> = (0..=n)
            .flat_map(|j| {
                (0..=n).map(move |i| Vec4::new(i as f32 / n as f32 - 0.5, j as f32 / n as f32 - 0.5, 0.5, 1.0))
            })
            .collect();
        let at = |i: usize, j: usize| (j * (n + 1) + i) as u32;
        let tris: Vec<[u32; 3]> = (0..n)
            .flat_map(|j| {
                (0..n).flat_map(move |i| {
                    [[at(i, j), at(i + 1, j), at(i + 1, j + 1)], [at(i, j), at(i + 1, j + 1), at(i, j + 1)]]
                })
            })
            .collect();
        let calls = Rc::new(Cell::new(0usize));
        let c = calls.clone();
        crate::util::cooperative::install(Rc::new(move || {
            c.set(c.get() + 1);
            None
        }));
        let mut fut = std::pin::pin!(rasterize_async(&clip, &tris, 512, 512));
        let mut cx = std::task::Context::from_waker(std::task::Waker::noop());
        let std::task::Poll::Ready(sliced) = fut.as_mut().poll(&mut cx) else { panic!("a checkpoint without a pause") };
        crate::util::cooperative::uninstall();
        let want = 512 * 512 / PIXELS_PER_SLICE + tris.len() / TRIANGLES_PER_SLICE;
        assert_eq!(calls.get(), want, "checkpoints: {} (4 buffer slices + 4 triangle slices)", calls.get());
        let whole = rasterize(&clip, &tris, 512, 512);
        assert_eq!(sliced.triangle, whole.triangle);
        assert_eq!(sliced.depth, whole.depth);
        assert!(sliced.triangle.iter().filter(|t| **t >= 0).count() > 512 * 512 / 5, "the grid covers a quarter");
    }

    #[test]
    fn a_square_covers_its_projected_pixels_with_correct_attributes() {
        // Unit square in the z = 0 plane seen by the default camera, moved to the target.
        let cam = OrbitCamera::default();
        let t = cam.target;
        let v = [
            Vec3::new(-0.5, -0.5, 0.0),
            Vec3::new(0.5, -0.5, 0.0),
            Vec3::new(0.5, 0.5, 0.0),
            Vec3::new(-0.5, 0.5, 0.0),
        ]
        .map(|p| p + t);
        let tris = [[0, 1, 2], [0, 2, 3]];
        let vp = cam.projection_gl(1.0) * cam.world_to_camera();
        let clip: Vec<Vec4> = v.iter().map(|p| vp * p.extend(1.0)).collect();
        let size = 200;
        let r = rasterize(&clip, &tris, size, size);
        // Half-width in pixels: 0.5 / (2.3·tan(fov/2)) · size/2.
        let half = 0.5 / (2.3 * (cam.fov_y / 2.0).tan()) * size as f32 / 2.0;
        let covered = r.triangle.iter().filter(|t| **t >= 0).count() as f32;
        let want = (2.0 * half).powi(2);
        assert!((covered / want - 1.0).abs() < 0.03, "covered {covered} vs {want}");
        // Attribute = world position: linear in the plane, exact at pixel centres.
        let pos = interpolate(&v, &r, &tris);
        let k = 100 * size + 100; // pixel centre (100.5, 100.5) → just right/below the centre
        let p = pos[k].expect("centre covered");
        let px = 0.5 / half * 0.5; // world metres per pixel · half a pixel
        assert!((p.x - t.x - px).abs() < 1e-3 && (p.y - t.y + px).abs() < 1e-3, "{p}");
        assert!(pos[0].is_none());

        // Per-pixel texturing: the texture callback sees exactly the covered pixels, at their
        // interpolated canonical coordinates; a field equal to the vertex colours' linear
        // interpolant reproduces per-vertex colouring bit for bit.
        let colors = v.map(|p| (p - t + Vec3::splat(0.5)).clamp(Vec3::ZERO, Vec3::ONE));
        let normals = [Vec3::Z; 4];
        let a = render_views(&v, &tris, &normals, &colors, vp, size, 1);
        let mut seen = 0;
        let b = render_views_textured(&v, &tris, &normals, &v, vp, size, 1, |pts| {
            seen = pts.len();
            Ok::<_, std::convert::Infallible>(
                pts.iter().map(|p| (*p - t + Vec3::splat(0.5)).clamp(Vec3::ZERO, Vec3::ONE)).collect(),
            )
        })
        .unwrap_or_else(|never| match never {});
        assert_eq!(seen as f32, covered);
        let max_diff = a.rgb.iter().zip(&b.rgb).map(|(x, y)| (*x as i32 - *y as i32).abs()).max().unwrap_or(0);
        assert!(max_diff <= 1, "per-pixel vs per-vertex colours differ by {max_diff}");
        assert_eq!(&a.rgb[..3], &[255, 255, 255], "white background");
        assert_eq!(a.mask, b.mask);
    }

    #[test]
    fn texture_lookup_is_bilinear_with_obj_orientation() {
        // 2×2 sRGB image: top row black, white; bottom row red, green.
        let px = [0, 0, 0, 255, 255, 255, 255, 0, 0, 0, 255, 0];
        let t = Texture::from_srgb8(2, 2, 3, &px).unwrap();
        // Texel centres: (0.25, 0.75) = top-left (black), (0.25, 0.25) = bottom-left (red).
        assert!((t.sample(Vec2::new(0.25, 0.75)) - Vec3::ZERO).length() < 1e-6);
        assert!((t.sample(Vec2::new(0.25, 0.25)) - Vec3::X).length() < 1e-6);
        assert!((t.sample(Vec2::new(0.75, 0.25)) - Vec3::Y).length() < 1e-6);
        // Halfway between the bottom texels: linear average of red and green.
        assert!((t.sample(Vec2::new(0.5, 0.25)) - Vec3::new(0.5, 0.5, 0.0)).length() < 1e-6);
        // Repeat wrapping.
        assert_eq!(t.sample(Vec2::new(1.25, 0.75)), t.sample(Vec2::new(0.25, 0.75)));
        assert!(Texture::from_srgb8(2, 2, 3, &px[..6]).is_none());
        let r = texture(&t, &[None, Some(Vec2::new(0.75, 0.75))]);
        assert!(r[0].is_none() && (r[1].unwrap() - Vec3::ONE).length() < 1e-6);
        assert!((decode_srgb(linear_to_srgb(Vec3::splat(0.3)).x) - 0.3).abs() < 1e-5);
    }
}
