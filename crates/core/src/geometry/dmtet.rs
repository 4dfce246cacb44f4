//! Marching tetrahedra (DMTet, paper Sec. 4.3; Shen et al. 2021): extract the zero level set of
//! an SDF given on the vertices of a tetrahedral grid as a triangle mesh.
//!
//! Inside is `sdf < 0`. A surface vertex sits on every grid edge whose end points differ in
//! sign, at the zero of the linear interpolant: `p = (a·s_b − b·s_a) / (s_b − s_a)`; the same
//! weights carry per-vertex attributes (e.g. canonical coordinates). Vertices on shared edges
//! are shared, so a conforming grid gives a watertight mesh. Each triangle is oriented from
//! the tet's inside corners to its outside corners, i.e. faces point outwards
//! (counter-clockwise seen from outside).

use glam::Vec3;

use crate::geometry::id_map::{id_map_with_capacity, IdMap};

/// An extracted mesh with one attribute vector per vertex.
#[derive(Clone, Debug, Default)]
pub struct TriMesh {
    pub vertices: Vec<Vec3>,
    pub faces: Vec<[u32; 3]>,
    /// Interpolated attribute per vertex (empty when none was given).
    pub attributes: Vec<Vec3>,
    /// Grid edge (a, b) and interpolation weight t of each vertex: v = (1−t)·a + t·b.
    pub edges: Vec<(u32, u32, f32)>,
}

// For each 4-bit inside-code, up to two triangles given as edge indices (nvdiffrec's table,
// re-oriented below). Edge e joins tet corners EDGES[e].
pub(crate) const EDGES: [[usize; 2]; 6] = [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]];
pub(crate) const TRIANGLES: [[i8; 6]; 16] = [
    [-1, -1, -1, -1, -1, -1],
    [1, 0, 2, -1, -1, -1],
    [4, 0, 3, -1, -1, -1],
    [1, 4, 2, 1, 3, 4],
    [3, 1, 5, -1, -1, -1],
    [2, 3, 0, 2, 5, 3],
    [1, 4, 0, 1, 5, 4],
    [4, 2, 5, -1, -1, -1],
    [4, 5, 2, -1, -1, -1],
    [4, 1, 0, 4, 5, 1],
    [3, 2, 0, 3, 5, 2],
    [1, 3, 5, -1, -1, -1],
    [4, 1, 2, 4, 3, 1],
    [3, 0, 4, -1, -1, -1],
    [2, 0, 1, -1, -1, -1],
    [-1, -1, -1, -1, -1, -1],
];

/// Extract the surface `sdf = 0` from a tet grid with (possibly deformed) vertex `positions`.
/// `attributes` is either empty or has one entry per grid vertex.
pub fn marching_tets(positions: &[Vec3], tets: &[[u32; 4]], sdf: &[f32], attributes: &[Vec3]) -> TriMesh {
    let inside = |i: u32| sdf[i as usize] < 0.0;
    let mut mesh = TriMesh::default();
    // About one surface vertex per 20 tets on the demo grid.
    let mut edge_vertex: IdMap<(u32, u32), u32> = id_map_with_capacity(tets.len() / 16);
    for tet in tets {
        let code = (0..4).fold(0usize, |c, k| c | ((inside(tet[k]) as usize) << k));
        if code == 0 || code == 15 {
            continue;
        }
        let mut vid = [u32::MAX; 6];
        for (e, [a, b]) in EDGES.iter().enumerate() {
            let (va, vb) = (tet[*a], tet[*b]);
            if inside(va) == inside(vb) {
                continue;
            }
            let key = (va.min(vb), va.max(vb));
            vid[e] = *edge_vertex.entry(key).or_insert_with(|| {
                let (sa, sb) = (sdf[key.0 as usize], sdf[key.1 as usize]);
                let t = sa / (sa - sb);
                let (pa, pb) = (positions[key.0 as usize], positions[key.1 as usize]);
                mesh.vertices.push(pa + (pb - pa) * t);
                if !attributes.is_empty() {
                    let (aa, ab) = (attributes[key.0 as usize], attributes[key.1 as usize]);
                    mesh.attributes.push(aa + (ab - aa) * t);
                }
                mesh.edges.push((key.0, key.1, t));
                (mesh.vertices.len() - 1) as u32
            });
        }
        // Orientation: a triangle must face from the tet's inside corners towards its outside
        // corners. Decided on the edge MIDPOINTS, which never degenerate (the interpolated
        // vertices can coincide when the SDF vanishes at a grid vertex), and the surface
        // triangle is a continuous deformation of the midpoint triangle that keeps separating
        // the same corners, so the orientation carries over.
        let p = tet.map(|i| positions[i as usize]);
        let (mut cin, mut cout, mut nin) = (Vec3::ZERO, Vec3::ZERO, 0.0f32);
        for k in 0..4 {
            if inside(tet[k]) {
                cin += p[k];
                nin += 1.0;
            } else {
                cout += p[k];
            }
        }
        let outward = cout / (4.0 - nin) - cin / nin;
        let mid = |e: usize| (p[EDGES[e][0]] + p[EDGES[e][1]]) * 0.5;
        let row = TRIANGLES[code];
        for t in 0..2 {
            if row[3 * t] < 0 {
                break;
            }
            let e = [row[3 * t] as usize, row[3 * t + 1] as usize, row[3 * t + 2] as usize];
            let mut f = e.map(|k| vid[k]);
            let [a, b, c] = e.map(mid);
            if (b - a).cross(c - a).dot(outward) < 0.0 {
                f.swap(1, 2);
            }
            mesh.faces.push(f);
        }
    }
    mesh
}

impl TriMesh {
    /// Total surface area.
    pub fn area(&self) -> f32 {
        self.faces
            .iter()
            .map(|f| {
                let [a, b, c] = f.map(|i| self.vertices[i as usize]);
                (b - a).cross(c - a).length() / 2.0
            })
            .sum()
    }

    /// Signed enclosed volume (positive for outward-facing closed meshes).
    pub fn volume(&self) -> f32 {
        self.faces
            .iter()
            .map(|f| {
                let [a, b, c] = f.map(|i| self.vertices[i as usize]);
                a.dot(b.cross(c)) / 6.0
            })
            .sum()
    }

    /// Connected components (faces sharing a vertex): each face's component id, and each
    /// component's face count, ids in order of first appearance.
    pub fn components(&self) -> (Vec<u32>, Vec<usize>) {
        let mut parent: Vec<u32> = (0..self.vertices.len() as u32).collect();
        fn root(parent: &mut [u32], mut i: u32) -> u32 {
            while parent[i as usize] != i {
                parent[i as usize] = parent[parent[i as usize] as usize];
                i = parent[i as usize];
            }
            i
        }
        for f in &self.faces {
            let r0 = root(&mut parent, f[0]);
            for &v in &f[1..] {
                let r = root(&mut parent, v);
                if r != r0 {
                    parent[r as usize] = r0;
                }
            }
        }
        let mut id_of_root: IdMap<u32, u32> = IdMap::default();
        let mut sizes = Vec::new();
        let ids = self
            .faces
            .iter()
            .map(|f| {
                let r = root(&mut parent, f[0]);
                let id = *id_of_root.entry(r).or_insert_with(|| {
                    sizes.push(0);
                    (sizes.len() - 1) as u32
                });
                sizes[id as usize] += 1;
                id
            })
            .collect();
        (ids, sizes)
    }

    /// This mesh without its cavities: components with negative signed volume, i.e. closed
    /// surfaces facing inwards, which bound empty pockets inside the solid and cannot be seen
    /// from outside. Everything else (also small detached pieces, which at grid resolution are
    /// often fingertips or toes) keeps its order, attributes and edges. Returns the mesh and
    /// how many components it dropped.
    pub fn without_cavities(self) -> (TriMesh, usize) {
        let (mesh, dropped, _) = self.without_cavities_mapped();
        (mesh, dropped)
    }

    /// [`TriMesh::without_cavities`], also giving each kept vertex's index in `self` (`None`
    /// when nothing was dropped: the vertices are unchanged), so per-vertex data computed
    /// before follows the mesh.
    pub fn without_cavities_mapped(self) -> (TriMesh, usize, Option<Vec<u32>>) {
        let (ids, sizes) = self.components();
        let mut volume = vec![0.0f64; sizes.len()];
        for (f, id) in self.faces.iter().zip(&ids) {
            let [a, b, c] = f.map(|i| self.vertices[i as usize].as_dvec3());
            volume[*id as usize] += a.dot(b.cross(c)) / 6.0;
        }
        let keep: Vec<bool> = volume.iter().map(|v| *v >= 0.0).collect();
        let dropped = keep.iter().filter(|k| !**k).count();
        if dropped == 0 {
            return (self, 0, None);
        }
        let mut remap = vec![u32::MAX; self.vertices.len()];
        let mut out = TriMesh::default();
        let mut kept = Vec::new();
        for (f, id) in self.faces.iter().zip(&ids) {
            if !keep[*id as usize] {
                continue;
            }
            let g = f.map(|v| {
                if remap[v as usize] == u32::MAX {
                    remap[v as usize] = out.vertices.len() as u32;
                    kept.push(v);
                    out.vertices.push(self.vertices[v as usize]);
                    if !self.attributes.is_empty() {
                        out.attributes.push(self.attributes[v as usize]);
                    }
                    if !self.edges.is_empty() {
                        out.edges.push(self.edges[v as usize]);
                    }
                }
                remap[v as usize]
            });
            out.faces.push(g);
        }
        (out, dropped, Some(kept))
    }

    /// Number of boundary or non-manifold edges, and of edges used twice in the same
    /// direction (inconsistent orientation). Both are zero for a closed, oriented manifold.
    pub fn topology_defects(&self) -> (usize, usize) {
        let mut directed: IdMap<(u32, u32), u32> = IdMap::default();
        for f in &self.faces {
            for k in 0..3 {
                *directed.entry((f[k], f[(k + 1) % 3])).or_default() += 1;
            }
        }
        let mut open = 0;
        let mut flipped = 0;
        for (&(a, b), &n) in &directed {
            if n > 1 {
                flipped += 1;
            }
            if directed.get(&(b, a)) != Some(&1) {
                open += 1;
            }
        }
        (open, flipped)
    }
}
