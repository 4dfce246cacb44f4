//! A texture atlas for an extracted avatar, and the bake of its texture field into it.
//!
//! **Layout: the body's own UVs, transferred.** The avatar is a deformation of the body
//! template (SDF = template + residual), so most of its surface lies near the body; each such
//! vertex takes the UV of its closest point on the canonical body (the open body's MakeHuman
//! layout: one chart for the body, head, hands, feet — a layout artists know). Triangles whose
//! corners fall in different body charts (the body's UV seams) are split off and mapped
//! through their centroid's body triangle. Surface that leaves the body by more than
//! [`FAR_FROM_BODY`] (skirts, loose hair) would fold onto the body's charts, so it gets its
//! own charts: triangles grouped by their dominant normal axis (box projection, so a chart does
//! not fold onto itself), connected groups projected onto that axis' plane and shelf-packed
//! into the atlas' right column and bottom strip. The body layout keeps the top-left
//! [`BODY_REGION`] of the square at uniform scale.
//!
//! Why not a general unwrapper: no well-kept unwrapping crate builds for wasm32 (xatlas is
//! C++), and the transferred layout is better for this mesh family than a generic one.
//!
//! **Bake** ([`texel_points`] + [`bake_image`]): every texel centre inside an atlas triangle
//! gets that triangle's interpolated canonical point (the generator's texture field is queried
//! there by the caller — the paper's per-pixel colour, Sec. 4.4); empty texels are then filled
//! from their filled neighbours for [`DILATE_TEXELS`] rings so mip-maps do not bleed the
//! background into the charts.

use glam::{Vec2, Vec3};

use crate::geometry::spatial::KdTree;

/// Surface further than this from the body (metres) gets its own charts.
pub const FAR_FROM_BODY: f32 = 0.03;
/// The body layout's share of the atlas side (top-left square).
pub const BODY_REGION: f32 = 0.8;
/// Rings of texels filled beyond the charts' borders.
pub const DILATE_TEXELS: usize = 8;

/// The atlas: vertices (copies of avatar vertices: seams duplicate them), their UVs (origin
/// top left, v down, as glTF), and triangles over them.
#[derive(Clone, Debug, Default)]
pub struct UvAtlas {
    /// Avatar vertex each atlas vertex copies.
    pub source: Vec<u32>,
    pub uvs: Vec<Vec2>,
    /// One per avatar triangle, in the avatar's order: `faces[t]` is triangle t's corners
    /// (same winding) as atlas vertices.
    pub faces: Vec<[u32; 3]>,
    /// Triangles mapped through the body's layout, across its seams, and in their own charts.
    pub body_faces: usize,
    pub seam_faces: usize,
    pub own_chart_faces: usize,
}

#[derive(Debug, thiserror::Error)]
pub enum AtlasError {
    #[error("the body model has no UV layout (vt/ft)")]
    NoBodyUvs,
    #[error("the mesh has no triangles")]
    Empty,
    #[error("the {0} triangles away from the body do not fit into the atlas' free region at any scale")]
    Packing(usize),
}

/// Closest point on triangle `abc` to `p`, as barycentric weights (Ericson, RTCD 5.1.5).
fn closest_barycentric(p: Vec3, a: Vec3, b: Vec3, c: Vec3) -> Vec3 {
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(ap), ac.dot(ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return Vec3::X;
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(bp), ac.dot(bp));
    if d3 >= 0.0 && d4 <= d3 {
        return Vec3::Y;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return Vec3::new(1.0 - v, v, 0.0);
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(cp), ac.dot(cp));
    if d6 >= 0.0 && d5 <= d6 {
        return Vec3::Z;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return Vec3::new(1.0 - w, 0.0, w);
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return Vec3::new(0.0, 1.0 - w, w);
    }
    let denom = 1.0 / (va + vb + vc);
    let (v, w) = (vb * denom, vc * denom);
    Vec3::new(1.0 - v - w, v, w)
}

/// Barycentric weights of `p` projected onto the plane of `abc` (not clamped).
fn plane_barycentric(p: Vec3, a: Vec3, b: Vec3, c: Vec3) -> Vec3 {
    let (v0, v1, v2) = (b - a, c - a, p - a);
    let (d00, d01, d11, d20, d21) = (v0.dot(v0), v0.dot(v1), v1.dot(v1), v2.dot(v0), v2.dot(v1));
    let den = d00 * d11 - d01 * d01;
    if den.abs() < 1e-20 {
        return Vec3::new(1.0, 0.0, 0.0);
    }
    let v = (d11 * d20 - d01 * d21) / den;
    let w = (d00 * d21 - d01 * d20) / den;
    Vec3::new(1.0 - v - w, v, w)
}

/// The canonical body with its UV layout, ready for closest-point queries.
pub struct BodyUvs<'a> {
    vertices: &'a [Vec3],
    faces: &'a [[u32; 3]],
    vt: &'a [Vec2],
    ft: &'a [[u32; 3]],
    tree: KdTree,
    /// Faces around each vertex, and each vertex's neighbours.
    vertex_faces: Vec<Vec<u32>>,
    /// UV chart of each face (connected components over shared `vt` indices).
    chart: Vec<u32>,
    /// Each face's layout scale (atlas units per metre).
    scale: Vec<f32>,
}

impl<'a> BodyUvs<'a> {
    pub fn new(
        vertices: &'a [Vec3],
        faces: &'a [[u32; 3]],
        vt: &'a [Vec2],
        ft: &'a [[u32; 3]],
    ) -> Result<Self, AtlasError> {
        if vt.is_empty() || ft.len() != faces.len() {
            return Err(AtlasError::NoBodyUvs);
        }
        let mut vertex_faces = vec![Vec::new(); vertices.len()];
        for (f, tri) in faces.iter().enumerate() {
            for &v in tri {
                vertex_faces[v as usize].push(f as u32);
            }
        }
        // Charts: union-find over UV vertices.
        let mut parent: Vec<u32> = (0..vt.len() as u32).collect();
        fn find(parent: &mut [u32], mut a: u32) -> u32 {
            while parent[a as usize] != a {
                parent[a as usize] = parent[parent[a as usize] as usize];
                a = parent[a as usize];
            }
            a
        }
        for t in ft {
            let r = find(&mut parent, t[0]);
            for &k in &t[1..] {
                let s = find(&mut parent, k);
                parent[s as usize] = r;
            }
        }
        let chart = ft.iter().map(|t| find(&mut parent, t[0])).collect();
        // Each face's layout scale, atlas units per metre (in the placed layout; charts differ:
        // the head gets more texels per metre than the legs): for spotting stretched transfers.
        let scale = faces
            .iter()
            .zip(ft)
            .map(|(f, t)| {
                let [a, b, c] = f.map(|v| vertices[v as usize]);
                let [p, q, r] = t.map(|v| vt[v as usize] * BODY_REGION);
                let a3 = (b - a).cross(c - a).length();
                let a2 = (q - p).perp_dot(r - p).abs();
                if a3 > 1e-12 {
                    (a2 / a3).sqrt()
                } else {
                    0.0
                }
            })
            .collect();
        Ok(Self { vertices, faces, vt, ft, tree: KdTree::new(vertices), vertex_faces, chart, scale })
    }

    fn corners(&self, f: usize) -> (Vec3, Vec3, Vec3) {
        let t = self.faces[f];
        (self.vertices[t[0] as usize], self.vertices[t[1] as usize], self.vertices[t[2] as usize])
    }

    fn uv_at(&self, f: usize, bary: Vec3) -> Vec2 {
        let t = self.ft[f];
        self.vt[t[0] as usize] * bary.x + self.vt[t[1] as usize] * bary.y + self.vt[t[2] as usize] * bary.z
    }

    /// The faces around the body vertex nearest `p` and its neighbours, each with the closest
    /// point's barycentric weights and distance.
    fn candidates(&self, p: Vec3) -> Vec<(usize, Vec3, f32)> {
        let Some((v, _)) = self.tree.nearest(p) else { return Vec::new() };
        let mut ring: Vec<u32> = self.vertex_faces[v].clone();
        for f in &self.vertex_faces[v] {
            for &u in &self.faces[*f as usize] {
                ring.extend_from_slice(&self.vertex_faces[u as usize]);
            }
        }
        ring.sort_unstable();
        ring.dedup();
        ring.into_iter()
            .map(|f| {
                let (a, b, c) = self.corners(f as usize);
                let bary = closest_barycentric(p, a, b, c);
                (f as usize, bary, (a * bary.x + b * bary.y + c * bary.z).distance(p))
            })
            .collect()
    }

    /// The body face nearest `p`, the closest point's barycentric weights there, and its
    /// distance.
    pub fn closest(&self, p: Vec3) -> (usize, Vec3, f32) {
        self.candidates(p).into_iter().fold((0, Vec3::X, f32::INFINITY), |best, c| if c.2 < best.2 { c } else { best })
    }

    /// The UV of `p`'s closest body point as seen from a triangle whose centre maps to `near`:
    /// where the closest point lies on a UV cut (a body vertex or edge with a UV on each
    /// side), the side nearer `near` is taken, so a triangle's corners stay on its side of the
    /// cut. Returns the face, the UV and which of the point's UVs it is (0 off cuts).
    fn uv_towards(&self, p: Vec3, near: Vec2) -> (usize, Vec2, u8) {
        let mut cands = self.candidates(p);
        cands.sort_by_key(|c| c.0);
        let Some(best) = cands.iter().min_by(|a, b| a.2.total_cmp(&b.2)).copied() else {
            return (0, Vec2::ZERO, 0);
        };
        let point = |c: &(usize, Vec3, f32)| {
            let (a, b, cc) = self.corners(c.0);
            a * c.1.x + b * c.1.y + cc * c.1.z
        };
        let at = point(&best);
        // The distinct UVs of the same closest point (in face order: deterministic).
        let mut sides: Vec<(usize, Vec2)> = Vec::new();
        for c in cands.iter().filter(|c| point(c).distance(at) < 1e-6) {
            let uv = self.uv_at(c.0, c.1);
            if !sides.iter().any(|s| s.1.distance(uv) < 1e-5) {
                sides.push((c.0, uv));
            }
        }
        sides
            .iter()
            .enumerate()
            .min_by(|a, b| a.1 .1.distance_squared(near).total_cmp(&b.1 .1.distance_squared(near)))
            .map_or((best.0, self.uv_at(best.0, best.1), 0), |(k, s)| (s.0, s.1, k as u8))
    }
}

/// The atlas of an avatar mesh (canonical vertices, triangles) from the body's layout.
pub fn transfer_body_uvs(vertices: &[Vec3], faces: &[[u32; 3]], body: &BodyUvs) -> Result<UvAtlas, AtlasError> {
    crate::util::cooperative::run_blocking(transfer_body_uvs_async(vertices, faces, body))
}

/// Closest-point queries between [`crate::util::cooperative::checkpoint`]s of the sliced transfer.
const TRANSFER_SLICE: usize = 512;

/// [`transfer_body_uvs`] in slices of [`TRANSFER_SLICE`] closest-point queries (a few
/// milliseconds each in the browser, whose UI thread runs the bake), the same result.
pub async fn transfer_body_uvs_async(
    vertices: &[Vec3],
    faces: &[[u32; 3]],
    body: &BodyUvs<'_>,
) -> Result<UvAtlas, AtlasError> {
    if faces.is_empty() {
        return Err(AtlasError::Empty);
    }
    // Body layout → top-left BODY_REGION of the square (vt has v up; glTF's v points down).
    let place = |uv: Vec2| Vec2::new(uv.x * BODY_REGION, (1.0 - uv.y) * BODY_REGION);
    let mut near: Vec<f32> = Vec::with_capacity(vertices.len());
    crate::util::cooperative::for_chunks(vertices, TRANSFER_SLICE, |c| {
        near.extend(c.iter().map(|p| body.closest(*p).2))
    })
    .await;
    let mut atlas = UvAtlas::default();
    // Shared atlas vertices: one per avatar vertex and UV (a vertex on a body UV cut has one
    // on each side).
    let mut shared: std::collections::HashMap<(u32, u8), u32> = std::collections::HashMap::new();
    let mut far = Vec::new();
    for (t, tri) in faces.iter().enumerate() {
        if t % TRANSFER_SLICE == TRANSFER_SLICE - 1 {
            crate::util::cooperative::checkpoint().await;
        }
        let idx = tri.map(|v| v as usize);
        let centroid = (vertices[idx[0]] + vertices[idx[1]] + vertices[idx[2]]) / 3.0;
        let (fc, bc, dc) = body.closest(centroid);
        if dc > FAR_FROM_BODY || idx.iter().any(|v| near[*v] > FAR_FROM_BODY) {
            far.push(t);
            // Its own chart's corners replace this placeholder (the avatar's order is kept).
            atlas.faces.push([0; 3]);
            continue;
        }
        let uv_c = body.uv_at(fc, bc);
        let corner = idx.map(|v| body.uv_towards(vertices[v], uv_c));
        let charts = corner.map(|c| body.chart[c.0]);
        let uv = corner.map(|c| place(c.1));
        let pos = idx.map(|v| vertices[v]);
        // The shared UVs must keep the triangle's shape: not folded over (the placed body
        // layout has negative signed area: v points down) and not stretched across the chart
        // (corners whose closest body points lie apart, e.g. bridging two limbs).
        let uv_area = (uv[1] - uv[0]).perp_dot(uv[2] - uv[0]);
        let area3 = (pos[1] - pos[0]).cross(pos[2] - pos[0]).length();
        let scale = corner.iter().map(|c| body.scale[c.0]).fold(body.scale[fc], f32::max);
        let stretched = uv_area.abs() > 9.0 * scale * scale * area3 + 1e-9
            || (0..3).any(|k| uv[k].distance(uv[(k + 1) % 3]) > 3.0 * scale * pos[k].distance(pos[(k + 1) % 3]) + 1e-4);
        if charts[0] == charts[1] && charts[1] == charts[2] && uv_area < 0.0 && !stretched {
            let mut out = [0u32; 3];
            for (k, v) in idx.iter().enumerate() {
                let key = (*v as u32, corner[k].2);
                out[k] = *shared.entry(key).or_insert_with(|| {
                    atlas.source.push(*v as u32);
                    atlas.uvs.push(uv[k]);
                    atlas.source.len() as u32 - 1
                });
            }
            atlas.faces.push(out);
            atlas.body_faces += 1;
        } else {
            // Across a body seam: the corners through the centroid's body face (extrapolated).
            let (a, b, c) = body.corners(fc);
            let base = atlas.source.len() as u32;
            for v in idx {
                atlas.source.push(v as u32);
                let uv = place(body.uv_at(fc, plane_barycentric(vertices[v], a, b, c)));
                // Extrapolation may leave the layout at its border: kept inside it.
                atlas.uvs.push(uv.clamp(Vec2::ZERO, Vec2::splat(BODY_REGION)));
            }
            atlas.faces.push([base, base + 1, base + 2]);
            atlas.seam_faces += 1;
        }
    }
    own_charts(vertices, faces, &far, &mut atlas)?;
    Ok(atlas)
}

/// Charts of their own for the triangles in `far`: grouped by dominant normal axis, connected
/// groups projected onto the axis plane, shelf-packed into the region outside the body layout.
fn own_charts(vertices: &[Vec3], faces: &[[u32; 3]], far: &[usize], atlas: &mut UvAtlas) -> Result<(), AtlasError> {
    if far.is_empty() {
        return Ok(());
    }
    let axis_of = |t: usize| -> usize {
        let [a, b, c] = faces[t].map(|v| vertices[v as usize]);
        let n = (b - a).cross(c - a);
        let m = n.abs();
        let k = if m.x >= m.y && m.x >= m.z {
            0
        } else if m.y >= m.z {
            1
        } else {
            2
        };
        2 * k + usize::from(n[k] < 0.0)
    };
    // Connected components (shared vertices) within one axis group.
    let mut by_vertex: std::collections::HashMap<u32, Vec<usize>> = std::collections::HashMap::new();
    for (i, &t) in far.iter().enumerate() {
        for v in faces[t] {
            by_vertex.entry(v).or_default().push(i);
        }
    }
    let axes: Vec<usize> = far.iter().map(|t| axis_of(*t)).collect();
    let mut group = vec![usize::MAX; far.len()];
    let mut charts: Vec<Vec<usize>> = Vec::new();
    for start in 0..far.len() {
        if group[start] != usize::MAX {
            continue;
        }
        let id = charts.len();
        let mut members = vec![start];
        group[start] = id;
        let mut k = 0;
        while k < members.len() {
            let i = members[k];
            k += 1;
            for v in faces[far[i]] {
                for &j in &by_vertex[&v] {
                    if group[j] == usize::MAX && axes[j] == axes[i] {
                        group[j] = id;
                        members.push(j);
                    }
                }
            }
        }
        charts.push(members);
    }
    // Project each chart onto its axis plane (metres), bounding boxes.
    let project = |p: Vec3, axis: usize| -> Vec2 {
        match axis / 2 {
            0 => Vec2::new(p.z, -p.y),
            1 => Vec2::new(p.x, p.z),
            _ => Vec2::new(p.x, -p.y),
        }
    };
    struct Chart {
        members: Vec<usize>,
        axis: usize,
        lo: Vec2,
        size: Vec2,
    }
    let mut boxes: Vec<Chart> = charts
        .into_iter()
        .map(|members| {
            let axis = axes[members[0]];
            let (mut lo, mut hi) = (Vec2::splat(f32::INFINITY), Vec2::splat(f32::NEG_INFINITY));
            for &i in &members {
                for v in faces[far[i]] {
                    let q = project(vertices[v as usize], axis);
                    lo = lo.min(q);
                    hi = hi.max(q);
                }
            }
            Chart { members, axis, lo, size: (hi - lo).max(Vec2::splat(1e-4)) }
        })
        .collect();
    boxes.sort_by(|a, b| b.size.y.total_cmp(&a.size.y));
    // The free region: a right column [R, 1] × [0, 1] and a bottom strip [0, R] × [R, 1],
    // packed as one strip of width (1 − R) + … : simplest — shelves in the column, then the strip.
    let regions = [
        (Vec2::new(BODY_REGION, 0.0), Vec2::new(1.0 - BODY_REGION, 1.0)),
        (Vec2::new(0.0, BODY_REGION), Vec2::new(BODY_REGION, 1.0 - BODY_REGION)),
    ];
    let gap = 2.0 / 1024.0;
    // Largest scale (atlas units per metre) at which every chart fits: bisection.
    let fits = |scale: f32| -> Option<Vec<Vec2>> {
        let mut at = Vec::with_capacity(boxes.len());
        let mut region = 0;
        let (mut x, mut y, mut shelf) = (0.0f32, 0.0f32, 0.0f32);
        for b in &boxes {
            let s = b.size * scale;
            loop {
                let (origin, extent) = regions.get(region)?;
                if s.x > extent.x || s.y > extent.y {
                    region += 1;
                    (x, y, shelf) = (0.0, 0.0, 0.0);
                    continue;
                }
                if x + s.x > extent.x {
                    (x, y, shelf) = (0.0, y + shelf + gap, 0.0);
                }
                if y + s.y > extent.y {
                    region += 1;
                    (x, y, shelf) = (0.0, 0.0, 0.0);
                    continue;
                }
                at.push(*origin + Vec2::new(x, y));
                x += s.x + gap;
                shelf = shelf.max(s.y);
                break;
            }
        }
        Some(at)
    };
    let (mut lo, mut hi) = (1e-3f32, 100.0f32);
    for _ in 0..30 {
        let mid = (lo * hi).sqrt();
        if fits(mid).is_some() {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    let Some(at) = fits(lo) else { return Err(AtlasError::Packing(far.len())) };
    for (b, origin) in boxes.iter().zip(at) {
        let mut local: std::collections::HashMap<u32, u32> = std::collections::HashMap::new();
        for &i in &b.members {
            let tri = faces[far[i]];
            let mut out = [0u32; 3];
            for (k, v) in tri.iter().enumerate() {
                out[k] = *local.entry(*v).or_insert_with(|| {
                    atlas.source.push(*v);
                    atlas.uvs.push(origin + (project(vertices[*v as usize], b.axis) - b.lo) * lo);
                    atlas.source.len() as u32 - 1
                });
            }
            atlas.faces[far[i]] = out;
            atlas.own_chart_faces += 1;
        }
    }
    Ok(())
}

/// The texels of a `res × res` atlas image that its triangles cover (texel centres inside a
/// triangle; the first triangle claims a texel), and each one's point interpolated from
/// `attribute` (one value per atlas vertex, e.g. canonical coordinates).
pub fn texel_points(atlas: &UvAtlas, attribute: &[Vec3], res: usize) -> (Vec<u32>, Vec<Vec3>) {
    crate::util::cooperative::run_blocking(texel_points_async(atlas, attribute, res))
}

/// Triangles of [`texel_points_async`] between two checkpoints (a 1024² atlas's whole pass was
/// a 30–60 ms task in the browser).
pub const TEXEL_SLICE: usize = 512;

/// [`texel_points`] with a [`crate::util::cooperative::checkpoint`] every [`TEXEL_SLICE`]
/// triangles: the same texels and points.
pub async fn texel_points_async(atlas: &UvAtlas, attribute: &[Vec3], res: usize) -> (Vec<u32>, Vec<Vec3>) {
    let mut owner = vec![false; res * res];
    let (mut texels, mut points) = (Vec::new(), Vec::new());
    let r = res as f32;
    for (i, tri) in atlas.faces.iter().enumerate() {
        if i % TEXEL_SLICE == TEXEL_SLICE - 1 {
            crate::util::cooperative::checkpoint().await;
        }
        let [a, b, c] = tri.map(|v| atlas.uvs[v as usize] * r);
        let [pa, pb, pc] = tri.map(|v| attribute[v as usize]);
        let area = (b - a).perp_dot(c - a);
        if area.abs() < 1e-12 {
            continue;
        }
        let lo = a.min(b).min(c).floor().max(Vec2::ZERO);
        let hi = a.max(b).max(c).ceil().min(Vec2::splat(r));
        for y in lo.y as usize..hi.y as usize {
            for x in lo.x as usize..hi.x as usize {
                let p = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
                let w0 = (b - p).perp_dot(c - p) / area;
                let w1 = (c - p).perp_dot(a - p) / area;
                let w2 = 1.0 - w0 - w1;
                if w0 < -1e-5 || w1 < -1e-5 || w2 < -1e-5 {
                    continue;
                }
                let k = y * res + x;
                if owner[k] {
                    continue;
                }
                owner[k] = true;
                texels.push(k as u32);
                points.push(pa * w0 + pb * w1 + pc * w2);
            }
        }
    }
    (texels, points)
}

/// The 8 neighbours of a texel, row by row from the top left (the order their colours are
/// summed in).
pub const NEIGHBOURS_8: [(i32, i32); 8] = [(-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1)];
/// The 4 edge neighbours of a texel: left, right, up, down.
pub const NEIGHBOURS_4: [(i32, i32); 4] = [(-1, 0), (1, 0), (0, -1), (0, 1)];

/// One ring of dilation of a `res × res` image: every empty texel with filled `neighbours`
/// (offsets) takes their mean colour and becomes filled, all from the ring's start; `false`
/// when no texel changed.
pub fn dilate_ring(rgb: &mut [Vec3], filled: &mut [bool], res: usize, neighbours: &[(i32, i32)]) -> bool {
    let mut next = Vec::new();
    for y in 0..res {
        for x in 0..res {
            if filled[y * res + x] {
                continue;
            }
            let (mut sum, mut n) = (Vec3::ZERO, 0);
            for (dx, dy) in neighbours {
                let (u, v) = (x as i32 + dx, y as i32 + dy);
                if u >= 0 && v >= 0 && (u as usize) < res && (v as usize) < res && filled[v as usize * res + u as usize]
                {
                    sum += rgb[v as usize * res + u as usize];
                    n += 1;
                }
            }
            if n > 0 {
                next.push((y * res + x, sum / n as f32));
            }
        }
    }
    for &(k, c) in &next {
        rgb[k] = c;
        filled[k] = true;
    }
    !next.is_empty()
}

/// The baked RGB image (`res × res`, 8-bit sRGB, row-major from the top left): `colors`
/// (linear RGB per covered texel of [`texel_points`]) encoded, then [`DILATE_TEXELS`] rings
/// of empty texels filled with the mean of their filled 8-neighbours.
pub fn bake_image(res: usize, texels: &[u32], colors: &[Vec3]) -> Vec<u8> {
    crate::util::cooperative::run_blocking(bake_image_async(res, texels, colors))
}

/// [`bake_image`] with a [`crate::util::cooperative::checkpoint`] after each dilation ring (a
/// 1024² ring is ≈ 50 ms in the browser) and every 64 rows of the sRGB encoding, the same
/// image.
pub async fn bake_image_async(res: usize, texels: &[u32], colors: &[Vec3]) -> Vec<u8> {
    let mut rgb = vec![Vec3::ZERO; res * res];
    let mut filled = vec![false; res * res];
    for (k, c) in texels.iter().zip(colors) {
        rgb[*k as usize] = *c;
        filled[*k as usize] = true;
    }
    for _ in 0..DILATE_TEXELS {
        if !dilate_ring(&mut rgb, &mut filled, res, &NEIGHBOURS_8) {
            break;
        }
        crate::util::cooperative::checkpoint().await;
    }
    // sRGB encoding: three `powf` per texel, ≈ 0.1 s for 1024² in the browser, in slices.
    let mut out = Vec::with_capacity(rgb.len() * 3);
    for rows in rgb.chunks(res * 64) {
        out.extend(rows.iter().flat_map(|c| {
            let s = crate::render::colour::linear_to_srgb(c.clamp(Vec3::ZERO, Vec3::ONE));
            [s.x, s.y, s.z].map(|x| (x * 255.0).round().clamp(0.0, 255.0) as u8)
        }));
        crate::util::cooperative::checkpoint().await;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::body::body_model::BodyModel;
    use crate::util::cooperative::tests::{drive, pause_always};

    /// The browser's sliced transfer and bake pause between slices and give the same atlas
    /// and image as the blocking ones, bit for bit.
    #[test]
    fn sliced_transfer_and_bake_give_the_thread_back_and_the_same_result() {
        let model = BodyModel::default_body().unwrap();
        let body = BodyUvs::new(&model.v_template, &model.faces, &model.vt, &model.ft).unwrap();
        // An "avatar": the body 2 % wider, so every query has a real distance to find.
        let avatar: Vec<Vec3> = model.v_template.iter().map(|v| Vec3::new(v.x * 1.02, v.y, v.z * 1.02)).collect();
        let reference = transfer_body_uvs(&avatar, &model.faces, &body).unwrap();
        let _pauses = pause_always();
        let (sliced, pauses) = drive(transfer_body_uvs_async(&avatar, &model.faces, &body));
        let sliced = sliced.unwrap();
        assert_eq!((&sliced.source, &sliced.faces), (&reference.source, &reference.faces));
        assert!(sliced.uvs.iter().zip(&reference.uvs).all(|(a, b)| a.to_array() == b.to_array()));
        let queries = avatar.len() / TRANSFER_SLICE + model.faces.len() / TRANSFER_SLICE;
        assert!(pauses >= queries, "{pauses} pauses for {queries} slices");

        // The texels' points: the same texels and points, a pause per slice of triangles.
        let attr: Vec<Vec3> = reference.source.iter().map(|v| avatar[*v as usize]).collect();
        let plain = texel_points(&reference, &attr, 128);
        let ((texels, points), pauses) = drive(texel_points_async(&reference, &attr, 128));
        assert!(!texels.is_empty());
        assert_eq!(texels, plain.0);
        assert!(points.iter().zip(&plain.1).all(|(a, b)| a.to_array() == b.to_array()));
        assert_eq!(pauses, reference.faces.len() / TEXEL_SLICE, "a pause per {TEXEL_SLICE} triangles");

        // Bake: a 64² image with one lit texel dilates ring by ring, one pause per ring.
        let colors = [Vec3::new(1.0, 0.5, 0.25)];
        let (image, pauses) = drive(bake_image_async(64, &[64 * 32 + 32], &colors));
        drop(_pauses);
        assert_eq!(image, bake_image(64, &[64 * 32 + 32], &colors));
        assert_eq!(pauses, DILATE_TEXELS + 1, "a pause per ring and per 64 rows");
        let lit = image.chunks_exact(3).filter(|p| p[0] == 255).count();
        assert_eq!(lit, (2 * DILATE_TEXELS + 1).pow(2), "a square of rings around the texel");
    }
}
