//! nvdiffrast's primitives on tensors: [`Coverage`] (from the CPU [`rasterize`] pass: which
//! triangle covers each pixel), [`interpolate`] (attributes at pixels through perspective-
//! correct barycentrics recomputed from clip-space positions, differentiable in both),
//! [`compose`] (pixels into an image over a background) and [`antialias`] (blends colours
//! across silhouette edges by the edge's sub-pixel position: the source of gradients of
//! masks and silhouettes with respect to vertex positions; Laine et al. 2020, Sec. 4).
//!
//! Images are `[H·W, C]` tensors, row-major from the top-left pixel.
//!
//! [`rasterize`]: crate::render::rasterize::rasterize

use burn::tensor::{Device, IndexingUpdateOp, Tensor};
use glam::{Vec2, Vec4};

use super::{index_tensor, matrix};
use crate::render::rasterize::Raster;

/// Covered pixels of a raster and their triangles' corners.
#[derive(Clone, Debug)]
pub struct Coverage {
    pub width: usize,
    pub height: usize,
    /// Pixel index (`y·W + x`) of each covered pixel.
    pub pixels: Vec<u32>,
    /// The three vertex ids of the covering triangle, per covered pixel.
    pub corners: [Vec<u32>; 3],
    /// Pixel-centre NDC coordinates `(x, y)` per covered pixel, row-major `[P, 2]`.
    pub ndc: Vec<f32>,
}

impl Coverage {
    pub fn new(r: &Raster, tris: &[[u32; 3]]) -> Self {
        let mut c = Coverage {
            width: r.width,
            height: r.height,
            pixels: Vec::new(),
            corners: [Vec::new(), Vec::new(), Vec::new()],
            ndc: Vec::new(),
        };
        for (k, &t) in r.triangle.iter().enumerate() {
            if t < 0 {
                continue;
            }
            let (x, y) = (k % r.width, k / r.width);
            c.pixels.push(k as u32);
            for (j, v) in tris[t as usize].iter().enumerate() {
                c.corners[j].push(*v);
            }
            c.ndc.push((x as f32 + 0.5) / r.width as f32 * 2.0 - 1.0);
            c.ndc.push(1.0 - (y as f32 + 0.5) / r.height as f32 * 2.0);
        }
        c
    }

    pub fn len(&self) -> usize {
        self.pixels.len()
    }

    pub fn is_empty(&self) -> bool {
        self.pixels.is_empty()
    }
}

/// Perspective-correct barycentrics `[P, 3]` of the covered pixels from clip positions
/// `clip` `[V, 4]`. With `u_k = X_k − x·W_k`, `v_k = Y_k − y·W_k` for pixel (x, y), the clip-space
/// point `Σ λ_k C_k` projects onto the pixel iff `λ ⟂ u` and `λ ⟂ v`, so `λ ∝ u × v`.
pub fn barycentrics(cov: &Coverage, clip: Tensor<2>, device: &Device) -> Tensor<2> {
    let p = cov.len();
    let ndc = matrix(cov.ndc.clone(), p, 2, device);
    let (x, y) = (ndc.clone().narrow(1, 0, 1), ndc.narrow(1, 1, 1));
    let uv = |k: usize| {
        let c = clip.clone().select(0, index_tensor(&cov.corners[k], device));
        let w = c.clone().narrow(1, 3, 1);
        (c.clone().narrow(1, 0, 1) - x.clone() * w.clone(), c.narrow(1, 1, 1) - y.clone() * w)
    };
    let ((u0, v0), (u1, v1), (u2, v2)) = (uv(0), uv(1), uv(2));
    let l0 = u1.clone() * v2.clone() - u2.clone() * v1.clone();
    let l1 = u2 * v0.clone() - u0.clone() * v2;
    let l2 = u0 * v1 - u1 * v0;
    let s = l0.clone() + l1.clone() + l2.clone();
    Tensor::cat(vec![l0, l1, l2], 1) / s
}

/// nvdiffrast's `interpolate`: per-vertex attributes `attr` `[V, C]` at the covered pixels,
/// `[P, C]`; differentiable in `attr` and in `clip` `[V, 4]`.
pub fn interpolate(cov: &Coverage, clip: Tensor<2>, attr: Tensor<2>, device: &Device) -> Tensor<2> {
    let b = barycentrics(cov, clip, device);
    let corner = |k: usize| attr.clone().select(0, index_tensor(&cov.corners[k], device)) * b.clone().narrow(1, k, 1);
    corner(0) + corner(1) + corner(2)
}

/// An image `[H·W, C]`: `values` `[P, C]` at the covered pixels over a constant `background`.
pub fn compose(cov: &Coverage, values: Tensor<2>, background: &[f32], device: &Device) -> Tensor<2> {
    let c = background.len();
    let n = cov.width * cov.height;
    let bg: Vec<f32> = (0..n).flat_map(|_| background.iter().copied()).collect();
    let base = matrix(bg, n, c, device);
    if cov.is_empty() {
        return base;
    }
    let row = matrix(background.to_vec(), 1, c, device);
    base.select_assign(0, index_tensor(&cov.pixels, device), values - row, IndexingUpdateOp::Add)
}

/// Pixel pairs straddling silhouette edges, found on the CPU (see [`antialias`]).
#[derive(Clone, Debug, Default)]
pub struct SilhouettePairs {
    /// Pixel receiving the blend.
    pub target: Vec<u32>,
    /// The other pixel of the pair (whose colour is blended in).
    pub source: Vec<u32>,
    /// Edge end points (vertex ids) of the foreground triangle.
    pub edge: [Vec<u32>; 2],
    /// Pixel centres (pixel units) of the foreground-side and the other pixel, `[K, 4]`.
    pub centres: Vec<f32>,
    /// +1 when the target is the background-side pixel, −1 when it is the foreground pixel.
    pub sign: Vec<f32>,
}

impl SilhouettePairs {
    /// The vertices the pairs' edges use (sorted, once each) and the pairs with their edge
    /// ends renumbered into that list: [`antialias`] only differentiates through those
    /// vertices, so a caller can pose just them (a fit's silhouette: ~2k of the body's 6890).
    pub fn compact(&self) -> (Vec<u32>, SilhouettePairs) {
        let mut ids: Vec<u32> = self.edge[0].iter().chain(&self.edge[1]).copied().collect();
        ids.sort_unstable();
        ids.dedup();
        let local = |v: &u32| ids.binary_search(v).map_or(0, |k| k as u32);
        let edge = [self.edge[0].iter().map(local).collect(), self.edge[1].iter().map(local).collect()];
        (ids, SilhouettePairs { edge, ..self.clone() })
    }
}

fn screen(c: Vec4, w: usize, h: usize) -> Vec2 {
    Vec2::new((c.x / c.w + 1.0) * 0.5 * w as f32, (1.0 - c.y / c.w) * 0.5 * h as f32)
}

/// The edges of a triangle mesh and the triangles using each, found once per topology (a fit's
/// body mesh keeps its faces over hundreds of steps): sorted by their end vertices, with the
/// users in one flat list (`owner[start[e]..start[e + 1]]`).
#[derive(Clone, Debug)]
pub struct MeshEdges {
    /// End points `(a, b)`, `a < b`, of each edge, sorted.
    pub ends: Vec<(u32, u32)>,
    start: Vec<u32>,
    owner: Vec<u32>,
    /// The number of vertices the faces refer to (one past the largest id).
    vertices: usize,
}

impl MeshEdges {
    pub fn new(tris: &[[u32; 3]]) -> Self {
        // Sorting packed (edge, triangle) keys: no hashing, deterministic, a few ms at 30k faces.
        let mut keys: Vec<(u64, u32)> = Vec::with_capacity(tris.len() * 3);
        let mut vertices = 0;
        for (ti, t) in tris.iter().enumerate() {
            for (i, j) in [(0, 1), (1, 2), (2, 0)] {
                let (a, b) = (t[i].min(t[j]), t[i].max(t[j]));
                keys.push(((u64::from(a) << 32) | u64::from(b), ti as u32));
                vertices = vertices.max(b as usize + 1);
            }
        }
        keys.sort_unstable();
        let mut e = MeshEdges { ends: Vec::new(), start: Vec::new(), owner: Vec::with_capacity(keys.len()), vertices };
        for (k, (key, ti)) in keys.iter().enumerate() {
            if k == 0 || keys[k - 1].0 != *key {
                e.ends.push(((key >> 32) as u32, *key as u32));
                e.start.push(e.owner.len() as u32);
            }
            e.owner.push(*ti);
        }
        e.start.push(e.owner.len() as u32);
        e
    }

    /// The triangles using edge `e` (an index into [`MeshEdges::ends`]).
    pub fn owners(&self, e: usize) -> &[u32] {
        &self.owner[self.start[e] as usize..self.start[e + 1] as usize]
    }
}

/// Items grouped by a bucket index in one flat list (compressed rows): built by counting, then
/// filling, so tens of thousands of buckets cost two allocations, not one each.
struct Buckets<T> {
    start: Vec<u32>,
    items: Vec<T>,
}

impl<T: Copy + Default> Buckets<T> {
    /// `entries` yields (bucket, item) pairs; it is called twice (count, then fill).
    fn build<I: Iterator<Item = (usize, T)>>(buckets: usize, entries: impl Fn() -> I) -> Self {
        let mut start = vec![0u32; buckets + 1];
        for (b, _) in entries() {
            start[b + 1] += 1;
        }
        for b in 0..buckets {
            start[b + 1] += start[b];
        }
        let mut fill = start.clone();
        let mut items = vec![T::default(); start[buckets] as usize];
        for (b, item) in entries() {
            items[fill[b] as usize] = item;
            fill[b] += 1;
        }
        Buckets { start, items }
    }

    fn get(&self, b: usize) -> &[T] {
        self.start.get(b + 1).map_or(&[], |&end| &self.items[self.start[b] as usize..end as usize])
    }
}

/// For each horizontally or vertically adjacent pixel pair covered by different triangles
/// (or one by none), find the silhouette edge of the nearer pixel's surface crossed by the
/// segment between the pixel centres; pairs whose segment crosses no
/// silhouette edge (e.g. an interior edge between two front-facing triangles) are skipped.
/// Where nvdiffrast's candidates (the edges at the corners of the triangle seen at the nearer
/// pixel) miss, any silhouette edge is tried, so meshes with sub-pixel triangles (DMTet at
/// the training resolution) get their silhouette gradients too.
pub fn silhouette_pairs(r: &Raster, clip: &[Vec4], tris: &[[u32; 3]]) -> SilhouettePairs {
    silhouette_pairs_of(r, clip, tris, &MeshEdges::new(tris))
}

/// [`silhouette_pairs`] with the mesh's edges found beforehand (`edges` must be
/// `MeshEdges::new(tris)`): what a loop over one topology calls each step.
pub fn silhouette_pairs_of(r: &Raster, clip: &[Vec4], tris: &[[u32; 3]], edges: &MeshEdges) -> SilhouettePairs {
    let (w, h) = (r.width, r.height);
    let mut out = SilhouettePairs::default();
    // Silhouette edges (nvdiffrast's topology test): used by one triangle, by more than two,
    // or by two that face opposite ways on screen. Each is kept with its owning triangle(s),
    // which say on which side "inside" is.
    let scr: Vec<Vec2> = clip.iter().map(|c| screen(*c, w, h)).collect();
    let facing = |t: &[u32; 3]| {
        let s = t.map(|v| scr[v as usize]);
        (s[1] - s[0]).perp_dot(s[2] - s[0])
    };
    // (a, b, owner) per silhouette edge and owner.
    let mut sil: Vec<(u32, u32, u32)> = Vec::new();
    for (e, &(a, b)) in edges.ends.iter().enumerate() {
        let owners = edges.owners(e);
        let silhouette = owners.len() != 2 || {
            let (f0, f1) = (facing(&tris[owners[0] as usize]), facing(&tris[owners[1] as usize]));
            (f0 > 0.0) != (f1 > 0.0)
        };
        if silhouette {
            sil.extend(owners.iter().map(|&o| (a, b, o)));
        }
    }
    // The silhouette edges indexed by end vertex (nvdiffrast's candidates: the edges at the
    // corners of the triangle seen at the nearer pixel) and registered in every pixel cell
    // their screen-space bounding box touches. Marching-tets meshes have triangles smaller
    // than a pixel, so the silhouette edge crossing a pixel pair rarely touches the triangle
    // seen at the nearer pixel's centre; the cell index finds it anyway.
    let by_vertex = Buckets::build(edges.vertices.max(clip.len()), || {
        sil.iter().flat_map(|&s| [(s.0 as usize, s), (s.1 as usize, s)])
    });
    let cells = |&(a, b, o): &(u32, u32, u32)| {
        let (sa, sb) = (scr[a as usize], scr[b as usize]);
        let (lo, hi) = (sa.min(sb), sa.max(sb));
        let off =
            !(lo.is_finite() && hi.is_finite()) || hi.x < 0.0 || hi.y < 0.0 || lo.x >= w as f32 || lo.y >= h as f32;
        let cell = |v: f32, n: usize| (v.max(0.0) as usize).min(n - 1);
        let (ys, xs) =
            if off { (0..0, 0..0) } else { (cell(lo.y, h)..cell(hi.y, h) + 1, cell(lo.x, w)..cell(hi.x, w) + 1) };
        ys.flat_map(move |y| xs.clone().map(move |x| (y * w + x, (a, b, o))))
    };
    let by_cell = Buckets::build(w * h, || sil.iter().flat_map(cells));
    let centre = |k: usize| Vec2::new((k % w) as f32 + 0.5, (k / w) as f32 + 0.5);
    // `horizontal`: a and b are left/right neighbours. As in nvdiffrast, an edge is handled by
    // horizontal pairs when it is closer to vertical and by vertical pairs otherwise, so each
    // edge blends once per crossing. First nvdiffrast's candidates (the line of an edge at the
    // nearer triangle's corners crossing the segment between the pixel centres, nearest to the
    // nearer pixel); where none crosses, any silhouette edge whose segment crosses it, the one
    // whose depth at the crossing is closest to the nearer pixel's (edges of surfaces hidden
    // behind it, or of an occluder whose corner is near, can cross too). Ties are broken by
    // vertex ids, not by the hash maps' order, so the pairs are deterministic.
    let mut visit = |a: usize, b: usize, horizontal: bool| {
        let (ta, tb) = (r.triangle[a], r.triangle[b]);
        if ta == tb {
            return;
        }
        let (f, o) = if ta < 0 {
            (b, a)
        } else if tb < 0 || r.depth[a] <= r.depth[b] {
            (a, b)
        } else {
            (b, a)
        };
        let tf = tris[r.triangle[f] as usize];
        let to = r.triangle[o];
        let (pf, po) = (centre(f), centre(o));
        // Where edge (i, j) of `owner` crosses the segment pf → po with pf inside: (t along the
        // segment, s along the edge).
        let crossing = |i: u32, j: u32, owner: u32| -> Option<(f32, f32)> {
            let (si, sj) = (scr[i as usize], scr[j as usize]);
            let d = sj - si;
            if (d.y.abs() >= d.x.abs()) != horizontal {
                return None;
            }
            if to >= 0 && tris[to as usize].contains(&i) && tris[to as usize].contains(&j) {
                return None; // the other pixel's triangle owns this edge too: not its silhouette
            }
            // Inside of the owner is where its third corner lies.
            let third = tris[owner as usize].into_iter().find(|&k| k != i && k != j).unwrap_or(i);
            let orient = d.perp_dot(scr[third as usize] - si).signum();
            let e = |p: Vec2| orient * d.perp_dot(p - si);
            let (ef, eo) = (e(pf), e(po));
            if !(ef >= 0.0 && eo < 0.0) {
                return None;
            }
            let t = ef / (ef - eo);
            let q = pf + (po - pf) * t;
            Some((t, (q - si).dot(d) / d.length_squared().max(1e-20)))
        };
        let mut best: Option<(f32, u32, u32)> = None;
        for v in tf {
            for &(i, j, owner) in by_vertex.get(v as usize) {
                if let Some((t, _)) = crossing(i, j, owner) {
                    if best.is_none_or(|(bt, bi, bj)| (t, i, j) < (bt, bi, bj)) {
                        best = Some((t, i, j));
                    }
                }
            }
        }
        if best.is_none() {
            // Depth (clip w) of the surface seen at the nearer pixel.
            let wf = {
                let c = tf.map(|v| clip[v as usize].w);
                let [u, v] = r.bary[f];
                c[0] * (1.0 - u - v) + c[1] * u + c[2] * v
            };
            let mut near: Option<(f32, f32, u32, u32)> = None;
            for &(i, j, owner) in by_cell.get(f).iter().chain(by_cell.get(o)) {
                let Some((t, s)) = crossing(i, j, owner) else { continue };
                if !(-1e-4..=1.0 + 1e-4).contains(&s) {
                    continue; // the crossing must lie on the edge segment itself
                }
                let (ci, cj) = (clip[i as usize].w, clip[j as usize].w);
                let dw = (ci + (cj - ci) * s.clamp(0.0, 1.0) - wf).abs();
                if near.is_none_or(|(bd, bt, bi, bj)| (dw, t, i, j) < (bd, bt, bi, bj)) {
                    near = Some((dw, t, i, j));
                }
            }
            best = near.map(|(_, t, i, j)| (t, i, j));
        }
        let Some((t, vi, vj)) = best else { return };
        let (target, source, sign) = if t > 0.5 { (o, f, 1.0) } else { (f, o, -1.0) };
        out.target.push(target as u32);
        out.source.push(source as u32);
        out.edge[0].push(vi);
        out.edge[1].push(vj);
        out.centres.extend([pf.x, pf.y, po.x, po.y]);
        out.sign.push(sign);
    };
    for y in 0..h {
        for x in 0..w {
            let k = y * w + x;
            if x + 1 < w {
                visit(k, k + 1, true);
            }
            if y + 1 < h {
                visit(k, k + w, false);
            }
        }
    }
    out
}

/// nvdiffrast's `antialias`: for each silhouette pair, the edge crosses the segment between
/// the pixel centres at `t` (0 at the foreground pixel); the pixel on the far side of the
/// segment's midpoint receives `|t − ½|` of the other pixel's colour. `t` is recomputed from
/// `clip` `[V, 4]` with tensor ops, so the blend is differentiable in vertex positions.
pub fn antialias(
    image: Tensor<2>,
    pairs: &SilhouettePairs,
    clip: Tensor<2>,
    w: usize,
    h: usize,
    device: &Device,
) -> Tensor<2> {
    let k = pairs.target.len();
    if k == 0 {
        return image;
    }
    let to_screen = |c: Tensor<2>| {
        let ww = c.clone().narrow(1, 3, 1);
        let sx = (c.clone().narrow(1, 0, 1) / ww.clone() + 1.0) * (0.5 * w as f32);
        let sy = (c.narrow(1, 1, 1) / ww * -1.0 + 1.0) * (0.5 * h as f32);
        (sx, sy)
    };
    let (ax, ay) = to_screen(clip.clone().select(0, index_tensor(&pairs.edge[0], device)));
    let (bx, by) = to_screen(clip.select(0, index_tensor(&pairs.edge[1], device)));
    let centres = matrix(pairs.centres.clone(), k, 4, device);
    let col = |i: usize| centres.clone().narrow(1, i, 1);
    let edge = |px: Tensor<2>, py: Tensor<2>| {
        (bx.clone() - ax.clone()) * (py - ay.clone()) - (by.clone() - ay.clone()) * (px - ax.clone())
    };
    let (ef, eo) = (edge(col(0), col(1)), edge(col(2), col(3)));
    let t = ef.clone() / (ef - eo);
    let sign = matrix(pairs.sign.clone(), k, 1, device);
    let alpha = (t - 0.5) * sign;
    let (ti, si) = (index_tensor(&pairs.target, device), index_tensor(&pairs.source, device));
    let delta = (image.clone().select(0, si) - image.clone().select(0, ti.clone())) * alpha;
    image.select_assign(0, ti, delta, IndexingUpdateOp::Add)
}
