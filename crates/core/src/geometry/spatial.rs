//! Spatial acceleration: a static 3-D k-d tree for nearest-neighbour queries (used by
//! SMPL-guided inverse skinning to find the nearest posed body vertex, paper Sec. 4.2).

use glam::Vec3;

const LEAF: usize = 8;

/// A balanced k-d tree over a fixed point set. Queries return indices into the input.
#[derive(Clone, Debug)]
pub struct KdTree {
    points: Vec<Vec3>,
    /// Permutation of point indices, partitioned recursively.
    order: Vec<u32>,
    nodes: Vec<Node>,
}

#[derive(Clone, Copy, Debug)]
enum Node {
    Leaf { start: u32, end: u32 },
    Split { axis: u8, value: f32, left: u32, right: u32 },
}

impl KdTree {
    /// Build over `points` (any count, including zero).
    pub fn new(points: &[Vec3]) -> Self {
        let mut t = Self { points: points.to_vec(), order: (0..points.len() as u32).collect(), nodes: Vec::new() };
        if !points.is_empty() {
            t.build(0, points.len());
        }
        t
    }

    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The points, in the order given to [`KdTree::new`].
    pub fn points(&self) -> &[Vec3] {
        &self.points
    }

    fn build(&mut self, start: usize, end: usize) -> u32 {
        let id = self.nodes.len() as u32;
        if end - start <= LEAF {
            self.nodes.push(Node::Leaf { start: start as u32, end: end as u32 });
            return id;
        }
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        for &i in &self.order[start..end] {
            lo = lo.min(self.points[i as usize]);
            hi = hi.max(self.points[i as usize]);
        }
        let ext = hi - lo;
        let axis = if ext.x >= ext.y && ext.x >= ext.z {
            0
        } else if ext.y >= ext.z {
            1
        } else {
            2
        };
        let mid = (start + end) / 2;
        let pts = &self.points;
        self.order[start..end]
            .select_nth_unstable_by(mid - start, |&a, &b| pts[a as usize][axis].total_cmp(&pts[b as usize][axis]));
        let value = self.points[self.order[mid] as usize][axis];
        self.nodes.push(Node::Leaf { start: 0, end: 0 }); // placeholder
        let left = self.build(start, mid);
        let right = self.build(mid, end);
        self.nodes[id as usize] = Node::Split { axis: axis as u8, value, left, right };
        id
    }

    /// Index and squared distance of the point nearest to `q`; `None` for an empty tree. Ties
    /// go to the lower index.
    pub fn nearest(&self, q: Vec3) -> Option<(usize, f32)> {
        if self.nodes.is_empty() {
            return None;
        }
        let mut best = (usize::MAX, f32::INFINITY);
        self.search(0, q, Vec3::ZERO, &mut best);
        Some(best)
    }

    /// [`KdTree::nearest`] (the same result) starting from the bound given by point `hint`,
    /// e.g. the answer for a neighbouring query: for coherent query sequences (grid vertices
    /// in raster order) most of the tree is then pruned at once.
    pub fn nearest_from(&self, q: Vec3, hint: usize) -> Option<(usize, f32)> {
        let Some(p) = self.points.get(hint) else { return self.nearest(q) };
        let mut best = (hint, p.distance_squared(q));
        self.search(0, q, Vec3::ZERO, &mut best);
        Some(best)
    }

    /// [`KdTree::nearest_from`] restricted to points closer than `radius`: None when there is
    /// none. Far queries prune almost the whole tree, so they cost a few node visits instead of
    /// a search over every leaf as close as the nearest point.
    pub fn nearest_within(&self, q: Vec3, radius: f32, hint: Option<usize>) -> Option<(usize, f32)> {
        if self.nodes.is_empty() {
            return None;
        }
        let r2 = radius * radius;
        let mut best = (usize::MAX, r2);
        if let Some((h, p)) = hint.and_then(|h| self.points.get(h).map(|p| (h, p))) {
            let d = p.distance_squared(q);
            if d < r2 {
                best = (h, d);
            }
        }
        self.search(0, q, Vec3::ZERO, &mut best);
        (best.0 != usize::MAX && best.1 < r2).then_some(best)
    }

    /// Depth-first search with Arya and Mount's incremental distance: `off` holds, per axis,
    /// the distance from `q` to the node's cell (0 where `q` lies within its extent), so
    /// `|off|²` bounds the distance to every point below from beneath. A far child is skipped
    /// when that bound, not only the distance to its splitting plane, exceeds the best so far;
    /// queries far from the points (most tet-grid vertices around a body) then visit few
    /// leaves. The bound is computed with the same operations as the point distances, so
    /// rounding never makes it exceed a distance it bounds: the result is the exact nearest.
    fn search(&self, node: u32, q: Vec3, mut off: Vec3, best: &mut (usize, f32)) {
        match self.nodes[node as usize] {
            Node::Leaf { start, end } => {
                for &i in &self.order[start as usize..end as usize] {
                    let d = self.points[i as usize].distance_squared(q);
                    if d < best.1 || (d == best.1 && (i as usize) < best.0) {
                        *best = (i as usize, d);
                    }
                }
            }
            Node::Split { axis, value, left, right } => {
                let a = axis as usize;
                let diff = q[a] - value;
                let (near, far) = if diff < 0.0 { (left, right) } else { (right, left) };
                self.search(near, q, off, best);
                off[a] = diff;
                if off.length_squared() <= best.1 {
                    self.search(far, q, off, best);
                }
            }
        }
    }
}

/// A regular lattice of points (`TetGrid::cube`'s vertices): `n` per side from `min`, `h`
/// apart, x fastest, each point `(xs[i], ys[j], zs[k])`.
#[derive(Clone, Debug)]
pub struct Lattice {
    pub n: usize,
    pub min: Vec3,
    pub h: f32,
    xs: Vec<f32>,
    ys: Vec<f32>,
    zs: Vec<f32>,
}

impl Lattice {
    /// The lattice whose points are `positions` (`n`³ of them, x fastest, about `min + (i, j,
    /// k)·h`), its coordinates read from them; None when they are not such a lattice (each
    /// coordinate depending on its own index alone).
    pub fn of(positions: &[Vec3], n: usize, min: Vec3, h: f32) -> Option<Self> {
        if n == 0 || positions.len() != n * n * n || h.is_nan() || h <= 0.0 {
            return None;
        }
        let xs: Vec<f32> = positions[..n].iter().map(|p| p.x).collect();
        let ys: Vec<f32> = (0..n).map(|j| positions[j * n].y).collect();
        let zs: Vec<f32> = (0..n).map(|k| positions[k * n * n].z).collect();
        let separable = positions.iter().enumerate().all(|(q, p)| {
            let (i, j, k) = (q % n, (q / n) % n, q / (n * n));
            p.x == xs[i] && p.y == ys[j] && p.z == zs[k]
        });
        let near = |c: &[f32], m: f32| c.iter().enumerate().all(|(i, v)| (v - (m + i as f32 * h)).abs() <= 0.25 * h);
        (separable && near(&xs, min.x) && near(&ys, min.y) && near(&zs, min.z)).then_some(Self {
            n,
            min,
            h,
            xs,
            ys,
            zs,
        })
    }
}

/// "No point within the radius" in [`scatter_nearest`]'s index slots.
pub const NONE_WITHIN: u32 = u32::MAX;

/// [`KdTree::nearest_within`] for every point of a lattice at once, the other way round: each
/// of `points` (numbered from `first`, in increasing order over the calls) lowers the slots of
/// the lattice points closer than `radius` to it. `index` and `dist2` hold the slots of the
/// lattice's z-slices from `k0` (n² each), initialised to [`NONE_WITHIN`] and `radius²`. The
/// squared distances are the tree's (`distance_squared` between the same two points, summed
/// in the same order) and a slot keeps the lower index among equal distances, so the answers
/// are the tree's; for a lattice that the radius covers in a few dozen cells this is an order
/// of magnitude less work than a search per lattice point. Candidate rows and ranges are
/// widened by a cell, so rounding never leaves out a point the exact test would take.
pub fn scatter_nearest(
    lattice: &Lattice,
    points: &[Vec3],
    first: usize,
    radius: f32,
    k0: usize,
    index: &mut [u32],
    dist2: &mut [f32],
) {
    let (n, min, h) = (lattice.n, lattice.min, lattice.h);
    let plane = n * n;
    let k1 = k0 + index.len().min(dist2.len()) / plane.max(1);
    if n == 0 || k1 <= k0 {
        return;
    }
    let r2 = radius * radius;
    let last = (n - 1) as f32;
    let at = |v: f32| v.clamp(0.0, last) as usize;
    let reach = radius / h + 1.0;
    for (local, p) in points.iter().enumerate() {
        let i_pt = (first + local) as u32;
        let g = (*p - min) / h;
        if g.z + reach < k0 as f32 || g.z - reach > (k1 - 1) as f32 || g.y + reach < 0.0 || g.y - reach > last {
            continue;
        }
        let (klo, khi) = (at((g.z - reach).floor()).max(k0), at((g.z + reach).ceil()).min(k1 - 1));
        let (jlo, jhi) = (at((g.y - reach).floor()), at((g.y + reach).ceil()));
        for k in klo..=khi {
            let dz = p.z - lattice.zs[k];
            let dz_low = ((k as f32 - g.z).abs() - 1.0).max(0.0) * h;
            for j in jlo..=jhi {
                let dy_low = ((j as f32 - g.y).abs() - 1.0).max(0.0) * h;
                let rest = r2 - dz_low * dz_low - dy_low * dy_low;
                if rest < 0.0 {
                    continue;
                }
                let half = rest.sqrt() / h + 1.0;
                if g.x + half < 0.0 || g.x - half > last {
                    continue;
                }
                let (ilo, ihi) = (at((g.x - half).floor()), at((g.x + half).ceil()));
                let dy = p.y - lattice.ys[j];
                let (dy2, dz2) = (dy * dy, dz * dz);
                let row = j * n + (k - k0) * plane;
                let (idx, d2s) = (&mut index[row + ilo..=row + ihi], &mut dist2[row + ilo..=row + ihi]);
                // (dx² + dy²) + dz²: `Vec3::length_squared`'s order.
                for ((slot_i, slot_d), x) in idx.iter_mut().zip(d2s.iter_mut()).zip(&lattice.xs[ilo..=ihi]) {
                    let dx = p.x - x;
                    let d = dx * dx + dy2 + dz2;
                    let lower = d < *slot_d;
                    *slot_d = if lower { d } else { *slot_d };
                    *slot_i = if lower { i_pt } else { *slot_i };
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Values in [−0.5, 0.5) from a linear congruential sequence started at `seed`.
    fn uniform(seed: u32) -> impl FnMut() -> f32 {
        let mut s = seed;
        move || {
            s = s.wrapping_mul(1664525).wrapping_add(1013904223);
            (s >> 8) as f32 / (1u32 << 24) as f32 - 0.5
        }
    }

    #[test]
    fn nearest_matches_brute_force() {
        let mut r = uniform(7);
        let pts: Vec<Vec3> = (0..2000).map(|_| Vec3::new(r(), r() * 3.0, r() * 0.1)).collect();
        let tree = KdTree::new(&pts);
        for _ in 0..500 {
            let q = Vec3::new(r(), r(), r()) * 2.0;
            let (i, d) = tree.nearest(q).expect("non-empty");
            let (bi, bd) = pts
                .iter()
                .enumerate()
                .map(|(k, p)| (k, p.distance_squared(q)))
                .min_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)))
                .expect("points");
            assert_eq!(d, bd);
            assert_eq!(pts[i].distance_squared(q), pts[bi].distance_squared(q));
        }
        // Queries far outside the points (where the cell bound prunes most), and ties.
        for k in 0..300 {
            let q = Vec3::new(r(), r(), r()) * 40.0 + Vec3::X * (k % 3) as f32 * 5.0;
            let (i, d) = tree.nearest(q).expect("non-empty");
            let bd = pts.iter().map(|p| p.distance_squared(q)).min_by(f32::total_cmp).expect("points");
            assert_eq!(d, bd, "query {q}");
            assert_eq!(pts[i].distance_squared(q), bd);
        }
        // A hint (good, bad or out of range) never changes the answer.
        for k in 0..300 {
            let q = Vec3::new(r(), r(), r()) * 3.0;
            let want = tree.nearest(q);
            for hint in [k, (k * 7919) % 2000, 5000] {
                assert_eq!(tree.nearest_from(q, hint), want, "query {q} hint {hint}");
            }
        }
        // Within a radius: the nearest point where it is closer than the radius, else none.
        for k in 0..600 {
            let q = Vec3::new(r(), r(), r()) * 3.0;
            let want = tree.nearest(q).expect("non-empty");
            for radius in [0.05f32, 0.2, 1.0] {
                let got = tree.nearest_within(q, radius, [None, Some(k % 2000), Some(9999)][k % 3]);
                assert_eq!(got, (want.1 < radius * radius).then_some(want), "query {q} radius {radius}");
            }
        }
        assert!(KdTree::new(&[]).nearest_within(Vec3::ZERO, 1.0, None).is_none());
        // Ties go to the lowest index, also across leaves.
        let dup: Vec<Vec3> = (0..100).map(|k| if k % 7 == 3 { Vec3::X } else { Vec3::splat(k as f32) }).collect();
        let dup_tree = KdTree::new(&dup);
        assert_eq!(dup_tree.nearest(Vec3::new(1.1, 0.0, 0.0)).map(|(i, _)| i), Some(3));
        assert_eq!(dup_tree.nearest_from(Vec3::new(1.1, 0.0, 0.0), 94).map(|(i, _)| i), Some(3));
        assert!(KdTree::new(&[]).nearest(Vec3::ZERO).is_none());
    }

    /// The lattice scatter gives the tree's answers (index, squared distance, or none within
    /// the radius) at every lattice point, with the lattice split into slabs and the points
    /// into batches as the callers split them, points straddling and outside the box, and
    /// duplicates (ties go to the lower index).
    #[test]
    fn the_lattice_scatter_finds_what_the_tree_finds() {
        let mut r = uniform(11);
        let mut pts: Vec<Vec3> = (0..400).map(|_| Vec3::new(r() * 2.4, r() * 2.4, r() * 0.6)).collect();
        pts.extend_from_within(..20);
        let grid = crate::geometry::tet_grid::TetGrid::cube(23, Vec3::new(0.05, 0.0, 0.0), 2.0);
        let n = grid.res + 1;
        let lattice = Lattice::of(&grid.vertices, n, grid.min, grid.cell()).expect("a lattice");
        let mut moved = grid.vertices.clone();
        moved[n + 2].x += 1e-3;
        assert!(Lattice::of(&moved, n, grid.min, grid.cell()).is_none(), "not separable");
        let tree = KdTree::new(&pts);
        for radius in [0.07f32, 0.2, 0.5] {
            let mut index = vec![NONE_WITHIN; n * n * n];
            let mut dist2 = vec![radius * radius; n * n * n];
            for (slab, (idx, d2)) in index.chunks_mut(n * n * 5).zip(dist2.chunks_mut(n * n * 5)).enumerate() {
                for (b, batch) in pts.chunks(64).enumerate() {
                    scatter_nearest(&lattice, batch, b * 64, radius, slab * 5, idx, d2);
                }
            }
            let slots: Vec<(u32, f32)> = index.into_iter().zip(dist2).collect();
            let (mut found, mut none) = (0, 0);
            for (q, slot) in grid.vertices.iter().zip(&slots) {
                let want = tree.nearest_within(*q, radius, None);
                let got = (slot.0 != NONE_WITHIN).then_some((slot.0 as usize, slot.1));
                assert_eq!(got, want, "radius {radius} at {q}");
                if got.is_some() {
                    found += 1
                } else {
                    none += 1
                }
            }
            assert!(found > 100 && none > 100, "radius {radius}: {found} found, {none} none");
        }
    }
}
