//! The body template SDF (paper Sec. 4.2: SDF(x_c) = template(x_c) + residual(x_c)): the
//! signed distance to the canonical body surface, precomputed once on a regular grid and
//! sampled trilinearly. Negative inside; points outside the grid's box are empty (+10, as in
//! the reference code).
//!
//! - Distance: exact point–triangle distance within a narrow band of `band` cells around the
//!   surface; beyond it, a chamfer distance transform (26-neighbourhood, two passes) seeded by
//!   the band, which over-estimates the true distance by at most ~8 %.
//! - Sign: inside/outside from ray-crossing parity along x, y and z (for a closed manifold
//!   surface this equals the winding number), majority of the three votes, so a ray grazing
//!   an edge or vertex cannot flip a sign.

use glam::Vec3;

use crate::util::cooperative::{checkpoint, run_blocking};

/// Faces between two checkpoints (a few milliseconds of work in wasm).
const FACES_PER_SLICE: usize = 256;

/// Value of points outside the grid box (empty space).
pub const OUTSIDE_VALUE: f32 = 10.0;

#[derive(Clone, Debug)]
pub struct TemplateSdf {
    /// Samples per side (grid points, not cells).
    pub res: usize,
    pub min: Vec3,
    /// Grid spacing, metres.
    pub cell: f32,
    /// `res³` values, x fastest.
    pub values: Vec<f32>,
}

/// Closest point on triangle (a, b, c) to p (Ericson, Real-Time Collision Detection 5.1.5).
pub fn closest_point_on_triangle(p: Vec3, a: Vec3, b: Vec3, c: Vec3) -> Vec3 {
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(ap), ac.dot(ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(bp), ac.dot(bp));
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return a + ab * (d1 / (d1 - d3));
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(cp), ac.dot(cp));
    if d6 >= 0.0 && d5 <= d6 {
        return c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return a + ac * (d2 / (d2 - d6));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    }
    let denom = 1.0 / (va + vb + vc);
    a + ab * (vb * denom) + ac * (vc * denom)
}

impl TemplateSdf {
    /// Build from a closed, outward-oriented triangle mesh on a `res³` grid spanning the cube
    /// with minimum corner `min` and edge `size`.
    pub fn from_mesh(vertices: &[Vec3], faces: &[[u32; 3]], res: usize, min: Vec3, size: f32, band: usize) -> Self {
        run_blocking(Self::from_mesh_async(vertices, faces, res, min, size, band))
    }

    /// [`TemplateSdf::from_mesh`] in slices, with a [`checkpoint`] after each (a 128³ grid is a
    /// second of work in the browser).
    pub async fn from_mesh_async(
        vertices: &[Vec3],
        faces: &[[u32; 3]],
        res: usize,
        min: Vec3,
        size: f32,
        band: usize,
    ) -> Self {
        let res = res.max(2);
        let cell = size / (res - 1) as f32;
        let n = res;
        let limit = band.max(1) as f32 * cell;
        let mut dist = vec![limit; n * n * n];
        let at = BandGrid { n, min, cell, band };
        // The three axes' inside votes need no distances: natively they start first, a thread
        // each, and run beside the distances and the chamfer sweeps.
        #[cfg(not(target_arch = "wasm32"))]
        let voting: Vec<std::thread::JoinHandle<Vec<bool>>> = (0..3)
            .map(|axis| {
                let (vertices, faces) = (vertices.to_vec(), faces.to_vec());
                std::thread::spawn(move || run_blocking(parity_inside(&vertices, &faces, n, min, cell, axis)))
            })
            .collect();
        // Natively, threads take slabs of z-slices, each over every face; in the browser, slices
        // of the faces with a checkpoint after each. A slot keeps the least distance over the
        // faces in either order, so both give the same values.
        #[cfg(not(target_arch = "wasm32"))]
        {
            let threads = std::thread::available_parallelism().map(|t| t.get()).unwrap_or(1).clamp(1, 16);
            let slab = n.div_ceil(threads).max(1);
            std::thread::scope(|sc| {
                for (s, part) in dist.chunks_mut(n * n * slab).enumerate() {
                    let k0 = s * slab;
                    sc.spawn(move || at.exact_distances(vertices, faces, k0, part));
                }
            });
        }
        #[cfg(target_arch = "wasm32")]
        for part in faces.chunks(FACES_PER_SLICE) {
            at.exact_distances(vertices, part, 0, &mut dist);
            checkpoint().await;
        }
        chamfer_fill(&mut dist, n, cell, limit).await;
        #[cfg(not(target_arch = "wasm32"))]
        let votes: Vec<Vec<bool>> =
            voting.into_iter().map(|h| h.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic))).collect();
        #[cfg(target_arch = "wasm32")]
        let mut votes = Vec::with_capacity(3);
        #[cfg(target_arch = "wasm32")]
        for axis in 0..3 {
            votes.push(parity_inside(vertices, faces, n, min, cell, axis).await);
        }
        let values = (0..n * n * n)
            .map(|q| {
                let inside = votes.iter().filter(|v| v[q]).count() >= 2;
                if inside {
                    -dist[q]
                } else {
                    dist[q]
                }
            })
            .collect();
        Self { res: n, min, cell, values }
    }

    /// Trilinear sample; `OUTSIDE_VALUE` outside the box.
    pub fn sample(&self, p: Vec3) -> f32 {
        let g = (p - self.min) / self.cell;
        let m = (self.res - 1) as f32;
        if !(g.x >= 0.0 && g.y >= 0.0 && g.z >= 0.0 && g.x <= m && g.y <= m && g.z <= m) {
            return OUTSIDE_VALUE;
        }
        let i0 = g.floor().min(Vec3::splat(m - 1.0));
        let t = g - i0;
        let (i, j, k) = (i0.x as usize, i0.y as usize, i0.z as usize);
        let n = self.res;
        let v = |di: usize, dj: usize, dk: usize| self.values[(i + di) + n * ((j + dj) + n * (k + dk))];
        let x00 = v(0, 0, 0) + (v(1, 0, 0) - v(0, 0, 0)) * t.x;
        let x10 = v(0, 1, 0) + (v(1, 1, 0) - v(0, 1, 0)) * t.x;
        let x01 = v(0, 0, 1) + (v(1, 0, 1) - v(0, 0, 1)) * t.x;
        let x11 = v(0, 1, 1) + (v(1, 1, 1) - v(0, 1, 1)) * t.x;
        let y0 = x00 + (x10 - x00) * t.y;
        let y1 = x01 + (x11 - x01) * t.y;
        y0 + (y1 - y0) * t.z
    }

    /// ∇SDF by central differences with step `h` (first-order quantities only, as the
    /// normal field of paper eq. 4 needs), normalised; zero where the gradient vanishes.
    pub fn normal(&self, p: Vec3, h: f32) -> Vec3 {
        central_difference_normal(|q| self.sample(q), p, h)
    }
}

/// The grid [`TemplateSdf::from_mesh_async`] fills: `n` samples per side from `min`, `cell`
/// apart, exact distances within `band` cells of the surface.
#[derive(Clone, Copy)]
struct BandGrid {
    n: usize,
    min: Vec3,
    cell: f32,
    band: usize,
}

impl BandGrid {
    /// Lower the slots of `part` (whole z-slices from `k0`) to each face's exact distance
    /// within the band of that face.
    fn exact_distances(self, vertices: &[Vec3], faces: &[[u32; 3]], k0: usize, part: &mut [f32]) {
        let BandGrid { n, min, cell, band } = self;
        let k1 = k0 + part.len() / (n * n);
        if k1 == k0 {
            return;
        }
        let to_grid = |p: Vec3| (p - min) / cell;
        for f in faces {
            let [a, b, c] = f.map(|i| vertices[i as usize]);
            // The distance to the triangle's plane bounds the distance to the triangle from
            // below: a grid point whose plane distance already exceeds its slot (less a
            // rounding margin) cannot be improved and skips the closest-point search.
            let normal = (b - a).cross(c - a).normalize_or_zero();
            let margin = 1e-4 * cell;
            let lo = (to_grid(a.min(b).min(c)) - Vec3::splat(band as f32)).floor().max(Vec3::ZERO);
            let hi = (to_grid(a.max(b).max(c)) + Vec3::splat(band as f32)).ceil().min(Vec3::splat((n - 1) as f32));
            let (klo, khi) = ((lo.z as usize).max(k0), (hi.z as usize).min(k1 - 1));
            if lo.x > hi.x || lo.y > hi.y || lo.z > hi.z || klo > khi {
                continue;
            }
            for k in klo..=khi {
                for j in lo.y as usize..=hi.y as usize {
                    for i in lo.x as usize..=hi.x as usize {
                        let p = min + Vec3::new(i as f32, j as f32, k as f32) * cell;
                        let slot = &mut part[i + n * (j + n * (k - k0))];
                        if (p - a).dot(normal).abs() - margin > *slot {
                            continue;
                        }
                        let d = closest_point_on_triangle(p, a, b, c).distance(p);
                        if d < *slot {
                            *slot = d;
                        }
                    }
                }
            }
        }
    }
}

/// Extend distances beyond the narrow band (values ≥ `limit`) with a two-pass 3-D chamfer
/// transform: forward and backward raster sweeps over half of the 26-neighbourhood each
/// (a checkpoint after every slice of the grid).
async fn chamfer_fill(dist: &mut [f32], n: usize, cell: f32, limit: f32) {
    for d in dist.iter_mut() {
        if *d >= limit {
            *d = f32::INFINITY;
        }
    }
    let mut fwd = Vec::new();
    for dk in -1i64..=0 {
        for dj in -1i64..=1 {
            for di in -1i64..=1 {
                let before = dk < 0 || (dk == 0 && (dj < 0 || (dj == 0 && di < 0)));
                if before {
                    fwd.push((di, dj, dk, cell * ((di * di + dj * dj + dk * dk) as f32).sqrt()));
                }
            }
        }
    }
    let bwd: Vec<_> = fwd.iter().map(|&(a, b, c, w)| (-a, -b, -c, w)).collect();
    // Slice by slice along z: forward in raster order, backward in reverse.
    for k in 0..n {
        sweep_slice(dist, n, k, &fwd, true);
        checkpoint().await;
    }
    for k in (0..n).rev() {
        sweep_slice(dist, n, k, &bwd, false);
        checkpoint().await;
    }
    for d in dist.iter_mut() {
        if !d.is_finite() {
            *d = limit;
        }
    }
}

/// One chamfer pass over the z-slice `k`: every voxel takes the least of itself and its
/// `offs` neighbours plus their weights, in raster order (`forward`) or its reverse. Interior
/// voxels skip the bounds checks; the values are those of a checked pass.
fn sweep_slice(dist: &mut [f32], n: usize, k: usize, offs: &[(i64, i64, i64, f32)], forward: bool) {
    let n_i = n as i64;
    let linear: Vec<(i64, f32)> = offs.iter().map(|&(di, dj, dk, w)| (di + n_i * (dj + n_i * dk), w)).collect();
    let k_inside = k >= 1 && k + 1 < n;
    let mut visit = |i: usize, j: usize| {
        let q = i + n * (j + n * k);
        let mut best = dist[q];
        if k_inside && i >= 1 && i + 1 < n && j >= 1 && j + 1 < n {
            for &(delta, w) in &linear {
                let v = dist[(q as i64 + delta) as usize] + w;
                if v < best {
                    best = v;
                }
            }
        } else {
            let (i, j, k) = (i as i64, j as i64, k as i64);
            for &(di, dj, dk, w) in offs {
                let (a, b, c) = (i + di, j + dj, k + dk);
                if a < 0 || b < 0 || c < 0 || a >= n_i || b >= n_i || c >= n_i {
                    continue;
                }
                let v = dist[(a + n_i * (b + n_i * c)) as usize] + w;
                if v < best {
                    best = v;
                }
            }
        }
        dist[q] = best;
    };
    if forward {
        for j in 0..n {
            for i in 0..n {
                visit(i, j);
            }
        }
    } else {
        for j in (0..n).rev() {
            for i in (0..n).rev() {
                visit(i, j);
            }
        }
    }
}

/// Normalised central-difference gradient of a scalar field.
pub fn central_difference_normal(f: impl Fn(Vec3) -> f32, p: Vec3, h: f32) -> Vec3 {
    let g = Vec3::new(
        f(p + Vec3::X * h) - f(p - Vec3::X * h),
        f(p + Vec3::Y * h) - f(p - Vec3::Y * h),
        f(p + Vec3::Z * h) - f(p - Vec3::Z * h),
    );
    g.normalize_or_zero()
}

/// Inside flags of all grid points from the parity of surface crossings along rays parallel
/// to `axis`, cast from below each grid line (checkpoints between slices of the work).
async fn parity_inside(
    vertices: &[Vec3],
    faces: &[[u32; 3]],
    n: usize,
    min: Vec3,
    cell: f32,
    axis: usize,
) -> Vec<bool> {
    let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
    // Crossing coordinates (along `axis`) per grid line (iu, iv).
    let mut hits: Vec<Vec<f32>> = vec![Vec::new(); n * n];
    for (fi, f) in faces.iter().enumerate() {
        if fi % FACES_PER_SLICE == FACES_PER_SLICE - 1 {
            checkpoint().await;
        }
        let p = f.map(|i| vertices[i as usize]);
        let pu = p.map(|q| (q[u] - min[u]) / cell);
        let pv = p.map(|q| (q[v] - min[v]) / cell);
        let (u0, u1) =
            (pu.iter().cloned().fold(f32::INFINITY, f32::min), pu.iter().cloned().fold(f32::NEG_INFINITY, f32::max));
        let (v0, v1) =
            (pv.iter().cloned().fold(f32::INFINITY, f32::min), pv.iter().cloned().fold(f32::NEG_INFINITY, f32::max));
        let (iu0, iu1) = (u0.ceil().max(0.0) as i64, u1.floor().min((n - 1) as f32) as i64);
        let (iv0, iv1) = (v0.ceil().max(0.0) as i64, v1.floor().min((n - 1) as f32) as i64);
        for iu in iu0..=iu1 {
            for iv in iv0..=iv1 {
                let (x, y) = (iu as f32, iv as f32);
                // Barycentrics of (x, y) in the projected triangle, with a tie-breaking rule
                // (top-left) so a line through a shared edge counts once.
                let e = |a: usize, b: usize| (pu[b] - pu[a]) * (y - pv[a]) - (pv[b] - pv[a]) * (x - pu[a]);
                let (w0, w1, w2) = (e(1, 2), e(2, 0), e(0, 1));
                let area = w0 + w1 + w2;
                if area == 0.0 {
                    continue;
                }
                let s = area.signum();
                let owns = |w: f32, a: usize, b: usize| {
                    let w = w * s;
                    if w != 0.0 {
                        return w > 0.0;
                    }
                    // On the edge a→b: accept for one orientation of the edge only.
                    let (du, dv) = ((pu[b] - pu[a]) * s, (pv[b] - pv[a]) * s);
                    dv < 0.0 || (dv == 0.0 && du > 0.0)
                };
                if owns(w0, 1, 2) && owns(w1, 2, 0) && owns(w2, 0, 1) {
                    let t = (w0 * p[0][axis] + w1 * p[1][axis] + w2 * p[2][axis]) / area;
                    hits[iu as usize + n * iv as usize].push((t - min[axis]) / cell);
                }
            }
        }
    }
    let mut inside = vec![false; n * n * n];
    for iu in 0..n {
        checkpoint().await;
        for iv in 0..n {
            let h = &mut hits[iu + n * iv];
            h.sort_by(f32::total_cmp);
            let mut crossed = 0;
            for ia in 0..n {
                while crossed < h.len() && h[crossed] < ia as f32 {
                    crossed += 1;
                }
                let mut c = [0usize; 3];
                c[axis] = ia;
                c[u] = iu;
                c[v] = iv;
                inside[c[0] + n * (c[1] + n * c[2])] = crossed % 2 == 1;
            }
        }
    }
    inside
}

#[cfg(all(test, feature = "embedded-body"))]
mod tests {
    use super::*;
    use crate::body::body_model::BodyModel;
    use crate::geometry::inverse_skinning::canonical_body;
    use crate::geometry::tet_grid::{REFERENCE_BOX_CENTER, REFERENCE_BOX_SIZE};
    use crate::util::cooperative::tests::{drive, pause_always};
    use crate::util::cooperative::uninstall;

    /// The interior shortcut of [`sweep_slice`] gives every voxel the bits a bounds-checked
    /// pass gives it, forward and backward, on a grid of random distances and gaps.
    #[test]
    fn a_chamfer_pass_with_the_interior_shortcut_equals_the_checked_pass() {
        let n = 7;
        let mut rng = crate::util::rng::Rng::new(5, 1);
        let start: Vec<f32> =
            (0..n * n * n).map(|_| if rng.uniform() < 0.3 { f32::INFINITY } else { rng.uniform() * 3.0 }).collect();
        let offs: Vec<(i64, i64, i64, f32)> = (-1i64..=0)
            .flat_map(|dk| (-1i64..=1).flat_map(move |dj| (-1i64..=1).map(move |di| (di, dj, dk))))
            .filter(|&(di, dj, dk)| dk < 0 || (dk == 0 && (dj < 0 || (dj == 0 && di < 0))))
            .map(|(di, dj, dk)| (di, dj, dk, 0.1 * ((di * di + dj * dj + dk * dk) as f32).sqrt()))
            .collect();
        let bwd: Vec<_> = offs.iter().map(|&(a, b, c, w)| (-a, -b, -c, w)).collect();
        let checked = |dist: &mut [f32], offs: &[(i64, i64, i64, f32)], order: Vec<usize>| {
            let m = n as i64;
            for q in order {
                let (i, j, k) = ((q % n) as i64, ((q / n) % n) as i64, (q / (n * n)) as i64);
                let mut best = dist[q];
                for &(di, dj, dk, w) in offs {
                    let (a, b, c) = (i + di, j + dj, k + dk);
                    if (0..m).contains(&a) && (0..m).contains(&b) && (0..m).contains(&c) {
                        best = best.min(dist[(a + m * (b + m * c)) as usize] + w);
                    }
                }
                dist[q] = best;
            }
        };
        let (mut fast, mut slow) = (start.clone(), start);
        for k in 0..n {
            sweep_slice(&mut fast, n, k, &offs, true);
            checked(&mut slow, &offs, (k * n * n..(k + 1) * n * n).collect());
        }
        for k in (0..n).rev() {
            sweep_slice(&mut fast, n, k, &bwd, false);
            checked(&mut slow, &bwd, (k * n * n..(k + 1) * n * n).rev().collect());
        }
        assert!(fast.iter().all(|v| v.is_finite()));
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&fast), bits(&slow));
    }

    #[test]
    fn sliced_template_sdf_gives_the_thread_back_and_the_same_values() {
        let model = BodyModel::default_body().expect("body");
        let cano = canonical_body(&model);
        let min = REFERENCE_BOX_CENTER - Vec3::splat(REFERENCE_BOX_SIZE / 2.0);
        let build = || TemplateSdf::from_mesh_async(&cano.vertices, &model.faces, 64, min, REFERENCE_BOX_SIZE, 3);
        let reference = TemplateSdf::from_mesh(&cano.vertices, &model.faces, 64, min, REFERENCE_BOX_SIZE, 3);
        // A host that takes the thread back at every checkpoint (the browser's hook decides by
        // time; pausing always is the strictest case).
        let _pauses = pause_always();
        let (sliced, pauses) = drive(build());
        // The synchronous form ignores the hook (nothing could resume it).
        let blocking = TemplateSdf::from_mesh(&cano.vertices, &model.faces, 64, min, REFERENCE_BOX_SIZE, 3);
        uninstall();
        assert_eq!(sliced.values, reference.values);
        assert_eq!(blocking.values, reference.values);
        // The chamfer sweeps slice by slice (2 × 64). The band's distances and the parity
        // votes run on threads of their own natively; in the browser they pause too (faces in
        // slices of 256, four passes over them).
        assert!(pauses >= 2 * 64, "{pauses} pauses");
    }
}
