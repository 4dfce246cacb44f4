//! The avatar's outline moved onto the photo's person (beyond the paper, with the photo's
//! projection): a generated avatar's silhouette at the photo's camera lies a pixel or two off
//! the person's (thinner arms, a narrower hem), and every such pixel shows background where
//! the photo shows the person. Each vertex on the avatar's outer silhouette (its normal across
//! the line of sight, nothing of the avatar just outside it in the image) is moved across the
//! line of sight to the person mask's border when that lies within [`reach`] pixels; the moves
//! are spread over the mesh by screened smoothing, so the surface near the outline follows and
//! the parts facing the camera stay where they are. No optimisation: two rasterisations (the
//! avatar's, and the fitted body's parts) and a walk along each outline vertex's image normal.
//!
//! Beyond [`reach`] a walk may go on to [`reach_within_part`] when the fitted body, rasterised
//! at the photo's camera with its coarse parts ([`OutlineParts`]), shows no other part along
//! it: a hem wider than the guess's trouser legs is claimed, an arm beside the back is not (a
//! vertex whose walk meets another part is held where it is).
//!
//! Where the photo's projection is applied (`trainer invert`, `trainer export --inverted`, the
//! app's result and a reopened file) the outline is snapped first, from the same photo
//! ([`SourcePhoto`]), so every later bake of a saved reconstruction gives the same mesh.

use glam::{Vec2, Vec3};

use crate::body::body_model::NUM_JOINTS;
use crate::body::skinning::vertex_normals;
use crate::reconstruction::photo_projection::SourcePhoto;
use crate::render::camera::OrbitCamera;
use crate::render::rasterize::rasterize;
use crate::util::cooperative::checkpoint;

/// How far (pixels) an outline vertex may move whatever lies in the way: 3 at the 128² crop the
/// reconstruction uses, in proportion at other sizes (2.3 % of the crop; about 4 cm on a person
/// filling it). Longer walks, unchecked, raise humps where the photo's person has a limb the
/// avatar has elsewhere; [`reach_within_part`] goes further where the body shows none.
pub fn reach(res: usize) -> f32 {
    3.0 * res as f32 / 128.0
}

/// How far (pixels) an outline vertex may move when the walk crosses none of the fitted body's
/// other parts ([`OutlineParts`]): 6 at the 128² crop (about 8 cm), in proportion at other
/// sizes. Longer walks score a little higher still but tear a long skirt's hem in other poses
/// (docs/benchmarks.md, "The outline moved onto the person").
pub fn reach_within_part(res: usize) -> f32 {
    6.0 * res as f32 / 128.0
}

/// The coarse part of the torso with the head ([`joint_part`]; each arm and each leg is its own).
pub const TORSO: u8 = 0;
/// No part: where the body is absent.
pub const NO_PART: u8 = u8::MAX;

/// The coarse part of SMPL joint `j` (SMPL order): the torso and head 0, the left and right
/// arm (shoulder to hand) 1 and 2, the left and right leg (hip to foot) 3 and 4.
pub fn joint_part(j: usize) -> u8 {
    match j {
        16 | 18 | 20 | 22 => 1,
        17 | 19 | 21 | 23 => 2,
        1 | 4 | 7 | 10 => 3,
        2 | 5 | 8 | 11 => 4,
        _ => TORSO,
    }
}

/// Each body vertex's coarse part: that of its heaviest skinning joint.
pub fn body_vertex_parts(weights: &[[f32; NUM_JOINTS]]) -> Vec<u8> {
    weights
        .iter()
        .map(|w| joint_part(w.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).map_or(0, |(j, _)| j)))
        .collect()
}

/// The fitted body's parts for [`silhouette_offsets`]: each surface vertex's part, and the part
/// the posed body shows at each pixel of the photo's crop.
#[derive(Clone, Debug)]
pub struct OutlineParts {
    pub vertex: Vec<u8>,
    pub pixel: Vec<u8>,
}

impl OutlineParts {
    /// The body (`body` posed as the photo shows it, `body_faces`, `body_parts` per body vertex)
    /// rasterised at the photo's camera; `vertex` is each surface vertex's part.
    pub fn new(
        vertex: Vec<u8>,
        body: &[Vec3],
        body_faces: &[[u32; 3]],
        body_parts: &[u8],
        photo: &SourcePhoto,
    ) -> Self {
        let res = photo.res;
        let view_proj = OrbitCamera::default().projection_gl(1.0) * photo.view.world_to_camera;
        let clip: Vec<_> = body.iter().map(|v| view_proj * v.extend(1.0)).collect();
        let raster = rasterize(&clip, body_faces, res, res);
        let pixel = raster
            .triangle
            .iter()
            .zip(&raster.bary)
            .map(|(&t, b)| {
                let Some(f) = usize::try_from(t).ok().and_then(|t| body_faces.get(t)) else { return NO_PART };
                // The part of the triangle's vertex nearest the pixel.
                let k = if 1.0 - b[0] - b[1] >= b[0].max(b[1]) {
                    0
                } else if b[0] >= b[1] {
                    1
                } else {
                    2
                };
                body_parts.get(f[k] as usize).copied().unwrap_or(NO_PART)
            })
            .collect();
        Self { vertex, pixel }
    }
}

/// `|cos θ|` (the normal against the direction to the camera) up to which a vertex moves fully,
/// and from which it does not move at all.
const EDGE_FULL: f32 = 0.2;
const EDGE_NONE: f32 = 0.4;
/// Screened smoothing: the pull between neighbours, the pull of every vertex towards staying,
/// and the passes.
const SMOOTH: f32 = 0.5;
const STAY: f32 = 0.05;
const PASSES: usize = 30;
/// The walk along an outline vertex's image normal, pixels per sample.
const WALK_STEP: f32 = 0.25;

/// What [`silhouette_offsets`] did: vertices on the outer silhouette that found the person's
/// border within reach, those held in place because another part lay in the way, and the
/// largest move (metres).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SnapReport {
    pub outline_vertices: usize,
    pub held_vertices: usize,
    pub max_move_m: f32,
}

/// The moves (metres, world frame) that bring the outer silhouette of the surface (`posed`,
/// `faces`, posed as the photo shows it) onto the photo's person mask at its camera; with the
/// fitted body's `parts`, up to [`reach_within_part`] where the walk crosses no other part.
pub fn silhouette_offsets(
    posed: &[Vec3],
    faces: &[[u32; 3]],
    photo: &SourcePhoto,
    parts: Option<&OutlineParts>,
) -> (Vec<Vec3>, SnapReport) {
    crate::util::cooperative::run_blocking(silhouette_offsets_async(posed, faces, photo, parts))
}

/// [`silhouette_offsets`] in slices ([`crate::util::cooperative`]), for the browser's UI
/// thread: the rasterisation, the walk, then every ten smoothing passes.
pub async fn silhouette_offsets_async(
    posed: &[Vec3],
    faces: &[[u32; 3]],
    photo: &SourcePhoto,
    parts: Option<&OutlineParts>,
) -> (Vec<Vec3>, SnapReport) {
    let n = posed.len();
    let res = photo.res;
    if n == 0 || res == 0 || photo.mask.len() != res * res {
        return (vec![Vec3::ZERO; n], SnapReport::default());
    }
    let parts = parts.filter(|p| p.vertex.len() == n && p.pixel.len() == res * res);
    let view = photo.view.world_to_camera;
    let view_proj = OrbitCamera::default().projection_gl(1.0) * view;
    let clip: Vec<_> = posed.iter().map(|v| view_proj * v.extend(1.0)).collect();
    let raster = rasterize(&clip, faces, res, res);
    checkpoint().await;
    let rf = res as f32;
    let inside = |p: Vec2| p.x >= 0.0 && p.y >= 0.0 && p.x < rf && p.y < rf;
    let covered = |p: Vec2| inside(p) && raster.triangle[p.y as usize * res + p.x as usize] >= 0;
    let person = |p: Vec2| person_at(&photo.mask, res, p) >= 0.5;
    let to_px = |p: Vec3| {
        let c = view_proj * p.extend(1.0);
        (c.w > 1e-6).then(|| Vec2::new((c.x / c.w + 1.0) * 0.5 * rf, (1.0 - c.y / c.w) * 0.5 * rf))
    };
    let camera_to_world = view.inverse();
    let normals = vertex_normals(posed, faces);
    let near = reach(res);
    let far = if parts.is_some() { reach_within_part(res).max(near) } else { near };
    let part_at = |p: Vec2| {
        if inside(p) {
            parts.map_or(NO_PART, |q| q.pixel[p.y as usize * res + p.x as usize])
        } else {
            NO_PART
        }
    };
    let mut target = vec![Vec3::ZERO; n];
    let mut weight = vec![0.0f32; n];
    let mut report = SnapReport::default();
    for i in 0..n {
        let pv = view.transform_point3(posed[i]);
        let to_cam = (-pv).normalize_or_zero();
        let nv = view.transform_vector3(normals[i]).normalize_or_zero();
        let cos = nv.dot(to_cam);
        if cos.abs() >= EDGE_NONE {
            continue;
        }
        // The normal's part across the line of sight, and its direction in the image.
        let across = camera_to_world.transform_vector3((nv - to_cam * cos).normalize_or_zero());
        let (Some(a), Some(b)) = (to_px(posed[i]), to_px(posed[i] + across * 0.01)) else { continue };
        let px_per_m = (b - a).length() / 0.01;
        if !px_per_m.is_finite() || px_per_m <= 1e-3 || !inside(a) {
            continue;
        }
        let u = (b - a).normalize();
        // The outer silhouette only: an edge with the avatar just outside it (an arm in front
        // of the torso) is not the outline the person mask shows.
        if covered(a + u * 1.5) {
            continue;
        }
        let own = parts.map_or(NO_PART, |q| q.vertex[i]);
        let foreign = |p: Vec2| {
            let q = part_at(p);
            q != NO_PART && q != own
        };
        let w = 1.0 - ((cos.abs() - EDGE_FULL) / (EDGE_NONE - EDGE_FULL)).clamp(0.0, 1.0);
        match border_along(a, u, near, far, &person, &foreign) {
            Walk::Border(t) => {
                target[i] = across * (t / px_per_m);
                weight[i] = w;
                report.outline_vertices += 1;
            }
            // Held in place, so its neighbours' moves do not carry it onto the other part.
            Walk::Blocked => {
                weight[i] = w;
                report.held_vertices += 1;
            }
            Walk::Nothing => {}
        }
    }
    checkpoint().await;
    let moves = smooth_moves(n, faces, &target, &weight).await;
    report.max_move_m = moves.iter().map(|d| d.length()).fold(0.0, f32::max);
    (moves, report)
}

/// What a walk along an outline vertex's image normal found.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Walk {
    /// The person mask's border at this signed distance (pixels): positive outwards when the
    /// vertex lies on the person, negative when it lies off it.
    Border(f32),
    /// Another part of the body lies in the way beyond the plain reach: the vertex stays.
    Blocked,
    /// No border within reach.
    Nothing,
}

/// The walk from `a` along `u` to the person mask's border: found within `near`, or within
/// `far` when no sample before it is `foreign` (another part's).
fn border_along(
    a: Vec2,
    u: Vec2,
    near: f32,
    far: f32,
    person: &impl Fn(Vec2) -> bool,
    foreign: &impl Fn(Vec2) -> bool,
) -> Walk {
    let on = person(a);
    let dir = if on { u } else { -u };
    let mut crossed = false;
    let mut s = WALK_STEP;
    while s <= far + 1e-4 {
        let p = a + dir * s;
        if person(p) != on {
            let t = s - 0.5 * WALK_STEP;
            return if t <= near + 1e-4 || !crossed { Walk::Border(if on { t } else { -t }) } else { Walk::Blocked };
        }
        crossed |= foreign(p);
        if crossed && s > near {
            return Walk::Blocked;
        }
        s += WALK_STEP;
    }
    Walk::Nothing
}

/// The person mask at pixel position `p` (bilinear, 0 outside the crop).
fn person_at(mask: &[f32], res: usize, p: Vec2) -> f32 {
    let (fx, fy) = (p.x - 0.5, p.y - 0.5);
    let (x0, y0) = (fx.floor(), fy.floor());
    let (tx, ty) = (fx - x0, fy - y0);
    let at = |x: f32, y: f32| {
        if x < 0.0 || y < 0.0 || x >= res as f32 || y >= res as f32 {
            0.0
        } else {
            mask[y as usize * res + x as usize]
        }
    };
    let top = at(x0, y0) * (1.0 - tx) + at(x0 + 1.0, y0) * tx;
    let bottom = at(x0, y0 + 1.0) * (1.0 - tx) + at(x0 + 1.0, y0 + 1.0) * tx;
    top * (1.0 - ty) + bottom * ty
}

/// Screened smoothing of the outline's moves over the mesh's edges: each vertex pulled
/// towards its own target by its weight, towards its neighbours and, weakly, towards staying.
async fn smooth_moves(n: usize, faces: &[[u32; 3]], target: &[Vec3], weight: &[f32]) -> Vec<Vec3> {
    let mut neighbours: Vec<Vec<u32>> = vec![Vec::new(); n];
    for f in faces {
        for k in 0..3 {
            let (a, b) = (f[k] as usize, f[(k + 1) % 3] as usize);
            if a < n && b < n && !neighbours[a].contains(&(b as u32)) {
                neighbours[a].push(b as u32);
                neighbours[b].push(a as u32);
            }
        }
    }
    let mut d: Vec<Vec3> = target.iter().zip(weight).map(|(t, w)| *t * *w).collect();
    for pass in 0..PASSES {
        if pass % 10 == 9 {
            checkpoint().await;
        }
        d = (0..n)
            .map(|i| {
                let sum: Vec3 = neighbours[i].iter().map(|&j| d[j as usize]).sum();
                (target[i] * weight[i] + sum * SMOOTH) / (weight[i] + STAY + SMOOTH * neighbours[i].len() as f32)
            })
            .collect();
    }
    d
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::body::skinning::BodyParams;
    use crate::render::camera::View;
    use glam::Mat4;

    /// A UV sphere of radius `r` around the origin.
    fn sphere(r: f32, rings: usize, segments: usize) -> (Vec<Vec3>, Vec<[u32; 3]>) {
        let mut v = vec![Vec3::new(0.0, r, 0.0)];
        for i in 1..rings {
            let th = std::f32::consts::PI * i as f32 / rings as f32;
            for j in 0..segments {
                let ph = std::f32::consts::TAU * j as f32 / segments as f32;
                v.push(Vec3::new(r * th.sin() * ph.cos(), r * th.cos(), r * th.sin() * ph.sin()));
            }
        }
        v.push(Vec3::new(0.0, -r, 0.0));
        let last = v.len() as u32 - 1;
        let at = |i: usize, j: usize| (1 + (i - 1) * segments + j % segments) as u32;
        let mut f = Vec::new();
        for j in 0..segments {
            f.push([0, at(1, j + 1), at(1, j)]);
            f.push([last, at(rings - 1, j), at(rings - 1, j + 1)]);
        }
        for i in 1..rings - 1 {
            for j in 0..segments {
                f.push([at(i, j), at(i, j + 1), at(i + 1, j)]);
                f.push([at(i, j + 1), at(i + 1, j + 1), at(i + 1, j)]);
            }
        }
        (v, f)
    }

    /// A photo of a disc of `radius_px` pixels at the crop's centre, seen by a camera 2.5 m
    /// in front of the origin.
    fn disc_photo(res: usize, radius_px: f32) -> SourcePhoto {
        let c = res as f32 / 2.0;
        let mask = (0..res * res)
            .map(|k| {
                let (x, y) = ((k % res) as f32 + 0.5 - c, (k / res) as f32 + 0.5 - c);
                if (x * x + y * y).sqrt() <= radius_px {
                    1.0
                } else {
                    0.0
                }
            })
            .collect();
        let world_to_camera = Mat4::look_at_rh(Vec3::new(0.0, 0.0, 2.5), Vec3::ZERO, Vec3::Y);
        SourcePhoto {
            view: View { world_to_camera, body: BodyParams::default() },
            res,
            rgb: vec![0.5; res * res * 3],
            mask,
        }
    }

    /// The radius (pixels) of the surface's silhouette at the photo's camera: from its area.
    fn silhouette_radius(v: &[Vec3], f: &[[u32; 3]], photo: &SourcePhoto) -> f32 {
        let vp = OrbitCamera::default().projection_gl(1.0) * photo.view.world_to_camera;
        let clip: Vec<_> = v.iter().map(|p| vp * p.extend(1.0)).collect();
        let r = rasterize(&clip, f, photo.res, photo.res);
        let area = r.triangle.iter().filter(|&&t| t >= 0).count() as f32;
        (area / std::f32::consts::PI).sqrt()
    }

    #[test]
    fn a_sphere_thinner_than_the_person_grows_to_the_outline_and_keeps_its_front() {
        let (v, f) = sphere(0.3, 48, 96);
        let res = 128;
        let probe = disc_photo(res, 10.0);
        let r0 = silhouette_radius(&v, &f, &probe);
        // The person is 2 pixels wider all round than the sphere's outline.
        let photo = disc_photo(res, r0 + 2.0);
        let (moves, report) = silhouette_offsets(&v, &f, &photo, None);
        assert!(report.outline_vertices > 50, "{report:?}");
        let moved: Vec<Vec3> = v.iter().zip(&moves).map(|(p, d)| *p + *d).collect();
        let r1 = silhouette_radius(&moved, &f, &photo);
        assert!((r1 - (r0 + 2.0)).abs() < 0.6, "outline radius {r0:.2} → {r1:.2}, the person's {:.2}", r0 + 2.0);
        // The point facing the camera stays; the outline moves outwards, across the line of sight.
        let front = v.iter().enumerate().max_by(|a, b| a.1.z.total_cmp(&b.1.z)).unwrap().0;
        assert!(moves[front].length() < 1e-3, "front moved {:?}", moves[front]);
        let side = v.iter().enumerate().max_by(|a, b| a.1.x.total_cmp(&b.1.x)).unwrap().0;
        assert!(moves[side].x > 0.005 && moves[side].z.abs() < 0.3 * moves[side].x, "side move {:?}", moves[side]);
        // 2 px at 2.5 m through the reference camera: a few centimetres, not the reach.
        assert!(report.max_move_m < 0.05, "{report:?}");
    }

    #[test]
    fn a_sphere_wider_than_the_person_shrinks_and_a_far_outline_is_left_alone() {
        let (v, f) = sphere(0.3, 48, 96);
        let res = 128;
        let r0 = silhouette_radius(&v, &f, &disc_photo(res, 10.0));
        let photo = disc_photo(res, r0 - 2.0);
        let (moves, _) = silhouette_offsets(&v, &f, &photo, None);
        let moved: Vec<Vec3> = v.iter().zip(&moves).map(|(p, d)| *p + *d).collect();
        let r1 = silhouette_radius(&moved, &f, &photo);
        assert!((r1 - (r0 - 2.0)).abs() < 0.6, "outline radius {r0:.2} → {r1:.2}, the person's {:.2}", r0 - 2.0);
        // A person narrower than the reach allows: nothing found within it, nothing moves.
        let (moves, report) = silhouette_offsets(&v, &f, &disc_photo(res, r0 - reach(res) - 3.0), None);
        assert_eq!(report.outline_vertices, 0);
        assert!(moves.iter().all(|d| d.length() < 1e-6));
    }

    /// The leftmost and rightmost covered pixel centres of the crop's middle row.
    fn middle_row_extent(v: &[Vec3], f: &[[u32; 3]], photo: &SourcePhoto) -> (f32, f32) {
        let vp = OrbitCamera::default().projection_gl(1.0) * photo.view.world_to_camera;
        let clip: Vec<_> = v.iter().map(|p| vp * p.extend(1.0)).collect();
        let r = rasterize(&clip, f, photo.res, photo.res);
        let row = photo.res / 2;
        let xs: Vec<f32> =
            (0..photo.res).filter(|&x| r.triangle[row * photo.res + x] >= 0).map(|x| x as f32 + 0.5).collect();
        (xs[0], xs[xs.len() - 1])
    }

    #[test]
    fn the_longer_reach_claims_the_person_only_where_the_body_shows_no_other_part() {
        let (v, f) = sphere(0.3, 48, 96);
        let res = 128;
        let c = res as f32 / 2.0;
        let r0 = silhouette_radius(&v, &f, &disc_photo(res, 10.0));
        // The person is 4.5 px wider all round: beyond the plain reach, within the part's.
        let gap = 4.5;
        assert!(gap > reach(res) + 1.0 && gap < reach_within_part(res) - 1.0);
        let photo = disc_photo(res, r0 + gap);
        let (plain, report) = silhouette_offsets(&v, &f, &photo, None);
        assert_eq!(report.outline_vertices, 0, "{report:?}");
        assert!(plain.iter().all(|d| d.length() < 1e-6));
        // The body shows another part (an arm, say) right of the sphere, nothing on its left.
        let pixel = (0..res * res).map(|k| if (k % res) as f32 + 0.5 - c > r0 + 1.0 { 1 } else { NO_PART }).collect();
        let parts = OutlineParts { vertex: vec![TORSO; v.len()], pixel };
        let (moves, report) = silhouette_offsets(&v, &f, &photo, Some(&parts));
        assert!(report.outline_vertices > 20, "{report:?}");
        let moved: Vec<Vec3> = v.iter().zip(&moves).map(|(p, d)| *p + *d).collect();
        let (left0, right0) = middle_row_extent(&v, &f, &photo);
        let (left1, right1) = middle_row_extent(&moved, &f, &photo);
        let disc_left = c - r0 - gap;
        assert!((left1 - disc_left).abs() <= 1.5, "left edge {left0} → {left1}, the person's {disc_left}");
        assert!((right1 - right0).abs() <= 1.0, "right edge {right0} → {right1}: claimed the other part");
        // The same walk with the sphere's own part there claims both sides.
        let same = OutlineParts { vertex: vec![1; v.len()], pixel: parts.pixel.clone() };
        let (moves, _) = silhouette_offsets(&v, &f, &photo, Some(&same));
        let moved: Vec<Vec3> = v.iter().zip(&moves).map(|(p, d)| *p + *d).collect();
        let (_, right2) = middle_row_extent(&moved, &f, &photo);
        assert!((right2 - (c + r0 + gap)).abs() <= 1.5, "right edge {right0} → {right2}");
    }

    #[test]
    fn a_body_vertex_takes_its_heaviest_joints_part() {
        let mut w = [[0.0f32; NUM_JOINTS]; 3];
        w[0][18] = 0.7; // left elbow
        w[0][16] = 0.3;
        w[1][5] = 0.6; // right knee
        w[1][2] = 0.4;
        w[2][3] = 0.5; // spine1
        w[2][1] = 0.4;
        w[2][2] = 0.1;
        assert_eq!(body_vertex_parts(&w), vec![1, 4, TORSO]);
    }
}
