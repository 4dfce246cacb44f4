//! The tetrahedral grid of DMTet, generated in code: a cube of `res³` cells, each split into
//! six tetrahedra along its main diagonal (Kuhn/Freudenthal subdivision). Neighbouring cubes
//! share faces exactly, so marching tetrahedra yields watertight meshes.
//!
//! Size: `(res+1)³` vertices, `6·res³` tets. `res = 45` gives 97,336 vertices and 546,750 tets,
//! close to the reference code's grid (98,653 / 532,314, called "res 90" there).

use glam::Vec3;

/// Box of the reference code's posed space: y ∈ [−1.33, 0.96] (2.29 m cube), centre y = −0.185.
pub const REFERENCE_BOX_CENTER: Vec3 = Vec3::new(0.0, -0.185, 0.0);
/// Edge length of the reference box, metres.
pub const REFERENCE_BOX_SIZE: f32 = 2.29;

#[derive(Clone, Debug)]
pub struct TetGrid {
    /// Cells per side.
    pub res: usize,
    /// Minimum corner of the box, metres.
    pub min: Vec3,
    /// Box edge length, metres.
    pub size: f32,
    pub vertices: Vec<Vec3>,
    pub tets: Vec<[u32; 4]>,
}

impl TetGrid {
    /// A `res³`-cell grid filling the cube with centre `center` and edge `size`.
    pub fn cube(res: usize, center: Vec3, size: f32) -> Self {
        let res = res.max(1);
        let n = res + 1;
        let min = center - Vec3::splat(size / 2.0);
        let h = size / res as f32;
        let mut vertices = Vec::with_capacity(n * n * n);
        for k in 0..n {
            for j in 0..n {
                for i in 0..n {
                    vertices.push(min + Vec3::new(i as f32, j as f32, k as f32) * h);
                }
            }
        }
        let id = |i: usize, j: usize, k: usize| (i + n * (j + n * k)) as u32;
        // The six monotone paths from corner 000 to 111, one per axis permutation.
        const PERMS: [[usize; 3]; 6] = [[0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]];
        let mut tets = Vec::with_capacity(6 * res * res * res);
        for k in 0..res {
            for j in 0..res {
                for i in 0..res {
                    for p in PERMS {
                        let mut c = [i, j, k];
                        let mut t = [id(i, j, k), 0, 0, 0];
                        for (s, axis) in p.iter().enumerate() {
                            c[*axis] += 1;
                            t[s + 1] = id(c[0], c[1], c[2]);
                        }
                        tets.push(t);
                    }
                }
            }
        }
        Self { res, min, size, vertices, tets }
    }

    /// The reference posed-space box at `res` cells per side.
    pub fn reference(res: usize) -> Self {
        Self::cube(res, REFERENCE_BOX_CENTER, REFERENCE_BOX_SIZE)
    }

    /// `true` for vertices on the faces of the box.
    pub fn boundary_flags(&self) -> Vec<bool> {
        let n = self.res + 1;
        (0..n * n * n)
            .map(|q| {
                let (i, j, k) = (q % n, (q / n) % n, q / (n * n));
                [i, j, k].iter().any(|&c| c == 0 || c == self.res)
            })
            .collect()
    }

    /// Cell edge length, metres.
    pub fn cell(&self) -> f32 {
        self.size / self.res as f32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tets_fill_the_cube_without_overlap() {
        let g = TetGrid::cube(3, Vec3::ZERO, 2.0);
        assert_eq!(g.vertices.len(), 64);
        assert_eq!(g.tets.len(), 6 * 27);
        let vol: f32 = g
            .tets
            .iter()
            .map(|t| {
                let [a, b, c, d] = t.map(|i| g.vertices[i as usize]);
                ((b - a).cross(c - a).dot(d - a) / 6.0).abs()
            })
            .sum();
        assert!((vol - 8.0).abs() < 1e-4, "total volume {vol}");
        let counts = (TetGrid::reference(45).vertices.len(), 6 * 45usize.pow(3));
        assert_eq!(counts, (97_336, 546_750));
    }
}
