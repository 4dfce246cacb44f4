//! Marching tetrahedra as device work: the same surface as the CPU reference
//! [`crate::geometry::marching_tets`], extracted where the generator's fields already are, so a
//! new identity needs no read-back of the grid's fields and no per-tet loop on the host.
//!
//! The grid's topology restricted to the tets where a surface can appear
//! ([`DmtetTopology`], made once per posed grid on the host and kept on the device) goes up
//! once. Per avatar, the pass (burn tensor ops, so one code on every backend):
//! 1. gathers each vertex's SDF residual from the field band's rows (0 off the band), SDF =
//!    base (template, or outside on the box boundary) + residual;
//! 2. marks the edges whose ends differ in sign and the tets whose corners do, numbers both by
//!    a blocked prefix sum ([`inclusive_scan`]) and reads back the two counts (the one
//!    read-back);
//! 3. compacts the crossed edges by an integer scatter of their indices (parallel atomics on a
//!    GPU) and a gather, and interpolates their surface vertices (position with the DMTet
//!    offsets, canonical coordinate) at the zero, `t = s_a / (s_a − s_b)` as on the CPU;
//! 4. compacts the crossed tets likewise, looks up their triangles (nvdiffrec's table by
//!    inside-code) and orients them by the edge midpoints, from the inside corners towards
//!    the outside ones, as on the CPU.
//!
//! Vertices come in grid-edge order (the CPU numbers them by first use); triangles come in
//! the CPU's order. The caller reads the compacted rows back with whatever else it computes
//! at the vertices (the generator: normals and colours), once.

use burn::tensor::{Bool, Device, IndexingUpdateOp, Int, Tensor, TensorData};
use glam::Vec3;

use crate::generator::readback::{read_f32, ReadbackError};
use crate::geometry::dmtet::{EDGES, TRIANGLES};
use crate::geometry::id_map::{id_map_with_capacity, IdMap};
use crate::geometry::template_sdf::OUTSIDE_VALUE;
use crate::geometry::{TetGrid, TriMesh};

/// Tets looked at between two checkpoints in the browser.
const TETS_PER_SLICE: usize = 16_384;

/// Columns of [`DeviceSurface::rows`]: position (3), canonical coordinate (3), the topology's
/// edge index, and the interpolation weight t.
pub const SURFACE_COLUMNS: usize = 8;

/// The grid's topology where a surface can appear, on the host: every tet with a corner on
/// the field band, or whose fixed corner SDF values (off the band the SDF is the template's)
/// already change sign. Other tets keep one sign whatever the generator says.
#[derive(Clone, Debug)]
pub struct DmtetTopology {
    /// Grid vertex of each local vertex.
    pub vertices: Vec<u32>,
    /// Local vertices of each kept tet, in grid order.
    pub tets: Vec<[u32; 4]>,
    /// Each kept tet's edges (in [`EDGES`] order) as local edge indices.
    pub tet_edges: Vec<[u32; 6]>,
    /// Grid vertices (a, b), a < b, of each local edge: the CPU's edge key.
    pub edges: Vec<(u32, u32)>,
    /// The same edges' local vertices.
    pub local_edges: Vec<[u32; 2]>,
    /// Row of each local vertex in the band's fields, or `band_len` (a zero row) off it.
    pub band_row: Vec<u32>,
    /// SDF without the residual: the template's, or [`OUTSIDE_VALUE`] on the box boundary.
    pub base_sdf: Vec<f32>,
    /// Rows of the band's fields the pass expects (the band's length; padding rows past it
    /// are allowed and ignored).
    pub band_len: usize,
}

impl DmtetTopology {
    /// The topology of `grid` for a posed grid's `template` values (one per grid vertex),
    /// `boundary` flags and field `band` (`geometry::posed_grid::field_band`).
    pub fn new(grid: &TetGrid, boundary: &[bool], template: &[f32], band: &[u32]) -> Self {
        crate::util::cooperative::run_blocking(Self::new_async(grid, boundary, template, band))
    }

    /// [`DmtetTopology::new`] in slices with a checkpoint after each (the demo grid's 1.6 M
    /// tets are some 100 ms of work in the browser).
    pub async fn new_async(grid: &TetGrid, boundary: &[bool], template: &[f32], band: &[u32]) -> Self {
        let n = grid.vertices.len();
        let mut row = vec![u32::MAX; n];
        for (k, &i) in band.iter().enumerate() {
            row[i as usize] = k as u32;
        }
        let base_sdf: Vec<f32> = (0..n).map(|i| if boundary[i] { OUTSIDE_VALUE } else { template[i] }).collect();
        let mut local = vec![u32::MAX; n];
        let mut topo = DmtetTopology {
            vertices: Vec::new(),
            tets: Vec::new(),
            tet_edges: Vec::new(),
            edges: Vec::new(),
            local_edges: Vec::new(),
            band_row: Vec::new(),
            base_sdf: Vec::new(),
            band_len: band.len(),
        };
        let mut edge_id: IdMap<(u32, u32), u32> = id_map_with_capacity(grid.tets.len() / 4);
        crate::util::cooperative::for_chunks(&grid.tets, TETS_PER_SLICE, |chunk| {
            for tet in chunk {
                topo.add_tet(tet, &row, &base_sdf, &mut local, &mut edge_id);
            }
        })
        .await;
        topo
    }

    fn add_tet(
        &mut self,
        tet: &[u32; 4],
        row: &[u32],
        base_sdf: &[f32],
        local: &mut [u32],
        edge_id: &mut IdMap<(u32, u32), u32>,
    ) {
        let on_band = tet.iter().any(|&i| row[i as usize] != u32::MAX);
        let inside = tet.iter().filter(|&&i| base_sdf[i as usize] < 0.0).count();
        if !on_band && (inside == 0 || inside == 4) {
            return;
        }
        let l = tet.map(|i| {
            let i = i as usize;
            if local[i] == u32::MAX {
                local[i] = self.vertices.len() as u32;
                self.vertices.push(i as u32);
                self.band_row.push(if row[i] == u32::MAX { self.band_len as u32 } else { row[i] });
                self.base_sdf.push(base_sdf[i]);
            }
            local[i]
        });
        let e = EDGES.map(|[a, b]| {
            let (a, b) = if tet[a] < tet[b] { (a, b) } else { (b, a) };
            *edge_id.entry((tet[a], tet[b])).or_insert_with(|| {
                self.edges.push((tet[a], tet[b]));
                self.local_edges.push([l[a], l[b]]);
                (self.edges.len() - 1) as u32
            })
        });
        self.tets.push(l);
        self.tet_edges.push(e);
    }

    /// The topology on `device`, with the grid's (undeformed) positions and the canonical
    /// coordinate of every grid vertex (`canonical`, the posed grid's).
    pub fn upload(&self, grid: &TetGrid, canonical: &[Vec3], device: &Device) -> DeviceTopology {
        let ints = |v: Vec<i64>, shape: Vec<usize>| Tensor::<1, Int>::from_data(TensorData::new(v, shape), device);
        let (ea, eb): (Vec<i64>, Vec<i64>) = self.local_edges.iter().map(|[a, b]| (*a as i64, *b as i64)).unzip();
        let (t, e, v) = (self.tets.len(), self.edges.len(), self.vertices.len());
        let points = |f: &dyn Fn(usize) -> Vec3| {
            let flat: Vec<f32> = self.vertices.iter().flat_map(|&g| f(g as usize).to_array()).collect();
            Tensor::<2>::from_data(TensorData::new(flat, [v, 3]), device)
        };
        DeviceTopology {
            tets: ints(self.tets.iter().flatten().map(|&i| i as i64).collect(), vec![t * 4]).reshape([t, 4]),
            tet_edges: ints(self.tet_edges.iter().flatten().map(|&i| i as i64).collect(), vec![t * 6]).reshape([t, 6]),
            edge_a: ints(ea, vec![e]),
            edge_b: ints(eb, vec![e]),
            band_row: ints(self.band_row.iter().map(|&r| r as i64).collect(), vec![v]),
            base_sdf: Tensor::from_data(TensorData::new(self.base_sdf.clone(), [v]), device),
            grid_pos: points(&|g| grid.vertices[g]),
            canonical: points(&|g| canonical[g]),
            edges: self.edges.clone(),
            band_len: self.band_len,
        }
    }
}

/// [`DmtetTopology`] on a device: what the pass reads besides the fields.
#[derive(Clone, Debug)]
pub struct DeviceTopology {
    tets: Tensor<2, Int>,
    tet_edges: Tensor<2, Int>,
    edge_a: Tensor<1, Int>,
    edge_b: Tensor<1, Int>,
    band_row: Tensor<1, Int>,
    base_sdf: Tensor<1>,
    grid_pos: Tensor<2>,
    canonical: Tensor<2>,
    /// Grid vertices (a, b) of each local edge (host copy: the mesh's `edges`).
    pub edges: Vec<(u32, u32)>,
    band_len: usize,
}

impl DeviceTopology {
    pub fn device(&self) -> Device {
        self.base_sdf.device()
    }
}

/// An extracted surface still on the device.
#[derive(Clone, Debug)]
pub struct DeviceSurface {
    /// `[V', SURFACE_COLUMNS]`: one row per surface vertex, V' = the vertex count padded to
    /// [`crate::generator::fields::POINT_ALIGN`] (padding rows repeat a grid point and are ignored).
    pub rows: Tensor<2>,
    /// `[2·T, 3]` vertex indices (as floats, exact below 2²⁴), two rows per crossed tet in grid
    /// order; a tet's unused second triangle is a row of −1 ([`mesh_from_rows`] drops it).
    pub faces: Tensor<2>,
    pub vertex_count: usize,
}

impl DeviceSurface {
    /// Canonical coordinates of the (padded) vertices, `[V', 3]`.
    pub fn canonical(&self) -> Tensor<2> {
        self.rows.clone().narrow(1, 3, 3)
    }
}

/// Scan block: each element of a block sums at most this many (burn's cumsum kernel is a
/// loop per element), and the levels above work on block totals.
const SCAN_BLOCK: usize = 64;

/// Inclusive prefix sum of a 1-D integer tensor by blocks of [`SCAN_BLOCK`], recursively over
/// the block totals: O(n · block) work in a few launches per level.
pub fn inclusive_scan(x: Tensor<1, Int>) -> Tensor<1, Int> {
    #[cfg(feature = "wgpu")]
    if let Some(scan) = cube::inclusive_scan(&x) {
        return scan;
    }
    let n = x.dims()[0];
    if n <= SCAN_BLOCK {
        return x.cumsum(0);
    }
    let m = n.div_ceil(SCAN_BLOCK);
    let x = if m * SCAN_BLOCK > n {
        let device = x.device();
        Tensor::cat(vec![x, Tensor::zeros([m * SCAN_BLOCK - n], &device)], 0)
    } else {
        x
    };
    let rows = x.reshape([m, SCAN_BLOCK]).cumsum(1);
    let totals = rows.clone().narrow(1, SCAN_BLOCK - 1, 1).reshape([m]);
    let before = inclusive_scan(totals.clone()) - totals;
    (rows + before.unsqueeze_dim::<2>(1)).reshape([m * SCAN_BLOCK]).narrow(0, 0, n)
}

/// For a mask `keep` `[N]` with inclusive prefix sum `scan` (of `keep` as 0/1): the index of
/// each kept element in order, padded with 0 to `len` (≥ the kept count) — an integer scatter
/// of the indices to their ranks (parallel atomics on a GPU), then read in rank order.
fn kept_indices(keep: Tensor<1, Bool>, scan: Tensor<1, Int>, len: usize) -> Tensor<1, Int> {
    #[cfg(feature = "wgpu")]
    if let Some(kept) = cube::kept_indices(&scan, len) {
        return kept;
    }
    let device = scan.device();
    let n = scan.dims()[0];
    // Dropped elements go to a spare slot at `len` (and add 0 there).
    let rank = (scan - 1).mask_fill(keep.clone().bool_not(), len as i64);
    let index = Tensor::<1, Int>::arange(0..n as i64, &device).mask_fill(keep.bool_not(), 0);
    let slots = Tensor::<1, Int>::zeros([len + 1], &device);
    slots.scatter(0, rank, index, IndexingUpdateOp::Add).narrow(0, 0, len)
}

/// [`inclusive_scan`] and [`kept_indices`] as cubecl kernels on wgpu/WebGPU (the tensor-op
/// versions take about 20 launches per scan and 6 per compaction, and in the browser every
/// launch is host time): a scan is three launches (block totals, their running sum in one
/// unit, each block's running sum from its offset), a compaction one (each output slot finds
/// its element by a binary search of the scan). Integer results, so they equal the tensor
/// ops exactly. Other backends, and integer types other than i32, take the tensor ops.
#[cfg(feature = "wgpu")]
// Kernel code (`#[cube]`) has index loops, not iterators.
#[allow(clippy::needless_range_loop)]
mod cube {
    use burn::backend::tensor::IntTensor;
    use burn::backend::{backend_extension, Backend, DispatchDevice, TensorMetadata};
    use burn::tensor::{DType, Int, Shape, Tensor};
    use burn_cubecl::kernel::into_contiguous;
    use burn_cubecl::tensor::CubeTensor;
    use burn_cubecl::CubeBackend;
    use cubecl::prelude::*;
    use cubecl::CubeDim;

    use crate::generator::network::cube_ops::{empty_contiguous, grid};

    /// Elements each unit of a scan sums in turn.
    const BLOCK: usize = 256;

    /// The end of block `t`'s elements (the last block may be short).
    #[cube]
    fn block_end(t: usize, block: usize, n: usize) -> usize {
        let mut end = (t + 1) * block;
        if end > n {
            end = n;
        }
        end
    }

    #[cube(launch)]
    fn block_totals(x: &[i32], totals: &mut [i32], n: usize, block: usize) {
        let t = ABSOLUTE_POS;
        if t * block >= n {
            terminate!();
        }
        let end = block_end(t, block, n);
        let mut sum = 0i32;
        for i in t * block..end {
            sum += x[i];
        }
        totals[t] = sum;
    }

    /// Exclusive running sum of the block totals, in place, by one unit.
    #[cube(launch)]
    fn block_offsets(totals: &mut [i32], m: usize) {
        if ABSOLUTE_POS != 0 {
            terminate!();
        }
        let mut sum = 0i32;
        for i in 0..m {
            let v = totals[i];
            totals[i] = sum;
            sum += v;
        }
    }

    #[cube(launch)]
    fn block_scan(x: &[i32], offsets: &[i32], out: &mut [i32], n: usize, block: usize) {
        let t = ABSOLUTE_POS;
        if t * block >= n {
            terminate!();
        }
        let end = block_end(t, block, n);
        let mut sum = offsets[t];
        for i in t * block..end {
            sum += x[i];
            out[i] = sum;
        }
    }

    /// Output slot `j` holds the element whose inclusive scan value first reaches `j + 1`
    /// (the kept element of rank `j`), or 0 past the kept count.
    #[cube(launch)]
    fn kept(scan: &[i32], out: &mut [i32], n: usize, len: usize) {
        let j = ABSOLUTE_POS;
        if j >= len {
            terminate!();
        }
        let rank = (j + 1) as i32;
        let mut index = 0i32;
        if scan[n - 1] >= rank {
            let mut lo = 0usize;
            let mut hi = n - 1;
            // ⌈log₂ n⌉ ≤ 32 halvings.
            for _ in 0..32u32 {
                if lo < hi {
                    let mid = (lo + hi) / 2;
                    if scan[mid] >= rank {
                        hi = mid;
                    } else {
                        lo = mid + 1;
                    }
                }
            }
            index = lo as i32;
        }
        out[j] = index;
    }

    #[backend_extension(Cube)]
    pub trait ScanBackend: Backend {
        /// Inclusive prefix sum of a 1-D i32 tensor.
        fn inclusive_scan(x: IntTensor<Self>) -> IntTensor<Self>;
        /// See [`super::kept_indices`]; `scan` is an inclusive scan of a 0/1 mask.
        fn kept_indices(scan: IntTensor<Self>, len: usize) -> IntTensor<Self>;
    }

    fn empty_i32(like: &CubeTensor, n: usize) -> CubeTensor {
        empty_contiguous(like, Shape::new([n]), DType::I32)
    }

    impl ScanBackend for CubeBackend {
        fn inclusive_scan(x: CubeTensor) -> CubeTensor {
            let x = into_contiguous(x);
            let n = x.shape().num_elements();
            let m = n.div_ceil(BLOCK);
            let (totals, out) = (empty_i32(&x, m), empty_i32(&x, n));
            let client = x.client.clone();
            let (count, dim) = grid(&x, m.max(1));
            block_totals::launch(
                &client,
                count.clone(),
                dim,
                x.clone().into_buffer_arg(),
                totals.clone().into_buffer_arg(),
                n,
                BLOCK,
            );
            block_offsets::launch(
                &client,
                CubeCount::Static(1, 1, 1),
                CubeDim::new_single(),
                totals.clone().into_buffer_arg(),
                m,
            );
            block_scan::launch(
                &client,
                count,
                dim,
                x.into_buffer_arg(),
                totals.into_buffer_arg(),
                out.clone().into_buffer_arg(),
                n,
                BLOCK,
            );
            out
        }

        fn kept_indices(scan: CubeTensor, len: usize) -> CubeTensor {
            let scan = into_contiguous(scan);
            let n = scan.shape().num_elements();
            let out = empty_i32(&scan, len);
            let (count, dim) = grid(&scan, len.max(1));
            kept::launch(
                &scan.client.clone(),
                count,
                dim,
                scan.into_buffer_arg(),
                out.clone().into_buffer_arg(),
                n,
                len,
            );
            out
        }
    }

    /// Whether `t` is an i32 tensor of a cubecl device without autodiff (the pass's integers
    /// never are on an autodiff device).
    fn eligible(t: &Tensor<1, Int>) -> bool {
        let device = t.device();
        t.dtype() == DType::I32 && !device.is_autodiff() && matches!(device.as_dispatch(), DispatchDevice::Cube(_))
    }

    /// The kernel scan, or `None` where it does not apply.
    pub fn inclusive_scan(x: &Tensor<1, Int>) -> Option<Tensor<1, Int>> {
        (eligible(x) && x.dims()[0] > 0).then(|| {
            Tensor::from_dispatch(<burn::backend::Dispatch as ScanBackend>::inclusive_scan(x.clone().into_dispatch()))
        })
    }

    /// The kernel compaction, or `None` where it does not apply.
    pub fn kept_indices(scan: &Tensor<1, Int>, len: usize) -> Option<Tensor<1, Int>> {
        (eligible(scan) && scan.dims()[0] > 0 && len > 0).then(|| {
            Tensor::from_dispatch(<burn::backend::Dispatch as ScanBackend>::kept_indices(
                scan.clone().into_dispatch(),
                len,
            ))
        })
    }
}

fn ints(values: &[i64], device: &Device) -> Tensor<1, Int> {
    Tensor::from_data(TensorData::new(values.to_vec(), [values.len()]), device)
}

/// No surface: zero rows and faces (burn refuses to narrow to length 0, so from empty data).
fn empty_surface(device: &Device) -> DeviceSurface {
    let none = |columns: usize| Tensor::<2>::from_data(TensorData::new(Vec::<f32>::new(), [0, columns]), device);
    DeviceSurface { rows: none(SURFACE_COLUMNS), faces: none(3), vertex_count: 0 }
}

/// Extract the surface `sdf = 0` on `topo`'s device from the field band's rows
/// (`[≥ band_len, 4]`: residual, offset x, y, z; see `fields::band_rows`). One read-back: the
/// counts of crossed edges and crossed tets, after which the work runs on those only.
pub async fn extract(topo: &DeviceTopology, band: Tensor<2>) -> Result<DeviceSurface, ReadbackError> {
    let device = topo.device();
    let (v, t) = (topo.base_sdf.dims()[0], topo.tets.dims()[0]);
    if t == 0 {
        return Ok(empty_surface(&device));
    }
    // 1. SDF per local vertex: the band's rows, a zero row off it.
    let band = band.narrow(0, 0, topo.band_len);
    let rows = Tensor::cat(vec![band, Tensor::zeros([1, 4], &device)], 0);
    let f = rows.select(0, topo.band_row.clone());
    let sdf = topo.base_sdf.clone() + f.clone().narrow(1, 0, 1).reshape([v]);
    let inside = sdf.clone().lower_elem(0.0).int();

    // 2. Crossed edges (one surface vertex each) and crossed tets (one or two triangles), and
    // their counts: the one read-back.
    let (ea, eb) = (topo.edge_a.clone(), topo.edge_b.clone());
    let crossed = inside.clone().select(0, ea.clone()).not_equal(inside.clone().select(0, eb.clone()));
    let vertex_scan = inclusive_scan(crossed.clone().int());
    let corner_inside = inside.select(0, topo.tets.clone().reshape([t * 4])).reshape([t, 4]);
    let code = (corner_inside.clone() * ints(&[1, 2, 4, 8], &device).unsqueeze_dim::<2>(0)).sum_dim(1).reshape([t]);
    let cut = code.clone().greater_elem(0).bool_and(code.clone().lower_elem(15));
    let tet_scan = inclusive_scan(cut.clone().int());
    let last = |x: &Tensor<1, Int>| x.clone().narrow(0, x.dims()[0] - 1, 1);
    let totals = Tensor::cat(vec![last(&vertex_scan), last(&tet_scan)], 0).float();
    let totals = read_f32(totals).await.map_err(|err| err.context("DMTet counts"))?;
    let (vertex_count, cut_count) = (totals[0] as usize, totals[1] as usize);
    if vertex_count == 0 || cut_count == 0 {
        return Ok(empty_surface(&device));
    }

    // 3. The surface vertices, on the crossed edges only (padded; padding rows take edge 0
    // with t = 0, a finite grid point).
    let padded = vertex_count.div_ceil(crate::generator::fields::POINT_ALIGN) * crate::generator::fields::POINT_ALIGN;
    let src = kept_indices(crossed.clone(), vertex_scan.clone(), padded);
    let (ka, kb) = (ea.select(0, src.clone()), eb.select(0, src.clone()));
    let (sa, sb) = (sdf.clone().select(0, ka.clone()), sdf.select(0, kb.clone()));
    let real = crossed.select(0, src.clone());
    let w = (sa.clone() / (sa - sb)).mask_fill(real.bool_not(), 0.0).unsqueeze_dim::<2>(1);
    let pos = topo.grid_pos.clone() + f.narrow(1, 1, 3);
    let lerp = |x: &Tensor<2>| {
        let (xa, xb) = (x.clone().select(0, ka.clone()), x.clone().select(0, kb.clone()));
        xa.clone() + (xb - xa) * w.clone()
    };
    let rows = Tensor::cat(vec![lerp(&pos), lerp(&topo.canonical), src.float().unsqueeze_dim::<2>(1), w.clone()], 1);

    // 4. The crossed tets' triangles from their inside-code (nvdiffrec's table), oriented by
    // the edge midpoints; a tet's unused second triangle is a row of −1.
    let t = cut_count;
    let tet_src = kept_indices(cut, tet_scan, t);
    let tets = topo.tets.clone().select(0, tet_src.clone());
    let code = code.select(0, tet_src.clone());
    let table: Vec<i64> = TRIANGLES.iter().flatten().map(|&k| k.max(0) as i64).collect();
    let counts: Vec<i64> = TRIANGLES.iter().map(|r| r.iter().filter(|&&k| k >= 0).count() as i64 / 3).collect();
    let tri_edges = ints(&table, &device).reshape([16, 6]).select(0, code.clone());
    let tri_count = ints(&counts, &device).select(0, code);
    let tet_edges = topo.tet_edges.clone().select(0, tet_src.clone());
    let surface_vertex =
        (vertex_scan - 1).select(0, tet_edges.gather(1, tri_edges.clone()).reshape([t * 6])).reshape([t, 2, 3]);
    let p = pos.select(0, tets.reshape([t * 4])).reshape([t, 4, 3]);
    let occ = corner_inside.select(0, tet_src.clone()).float().unsqueeze_dim::<3>(2);
    let n_in = occ.clone().sum_dim(1);
    let c_in = (p.clone() * occ.clone()).sum_dim(1) / n_in.clone();
    let c_out = (p.clone() * (occ.neg() + 1.0)).sum_dim(1) / (n_in.neg() + 4.0);
    let outward = (c_out - c_in).unsqueeze_dim::<4>(1); // [T, 1, 1, 3]
    let ends = |k: usize| ints(&EDGES.map(|e| e[k] as i64), &device);
    let mids = (p.clone().select(1, ends(0)) + p.select(1, ends(1))) * 0.5;
    let m = mids.gather(1, tri_edges.unsqueeze_dim::<3>(2).repeat_dim(2, 3)).reshape([t, 2, 3, 3]);
    let corner = |k: usize| m.clone().narrow(2, k, 1);
    let (u, q) = (corner(1) - corner(0), corner(2) - corner(0));
    // u × q with the axes rolled by one and two: (u_y q_z − u_z q_y, …).
    let roll = |x: &Tensor<4>, by: i64| x.clone().select(3, ints(&[by % 3, (by + 1) % 3, (by + 2) % 3], &device));
    let normal = roll(&u, 1) * roll(&q, 2) - roll(&u, 2) * roll(&q, 1);
    let flip = (normal * outward).sum_dim(3).reshape([t, 2, 1]).lower_elem(0.0);
    let fv = |k: usize| surface_vertex.clone().narrow(2, k, 1);
    let faces = Tensor::cat(vec![fv(0), fv(1).mask_where(flip.clone(), fv(2)), fv(2).mask_where(flip, fv(1))], 2);
    let unused = tri_count.unsqueeze_dim::<2>(1).lower_equal(ints(&[0, 1], &device).unsqueeze_dim::<2>(0));
    let faces = faces.mask_fill(unused.unsqueeze_dim::<3>(2), -1).reshape([t * 2, 3]);
    Ok(DeviceSurface { rows, faces: faces.float(), vertex_count })
}

/// The mesh of a surface whose rows (`width` ≥ [`SURFACE_COLUMNS`] floats each, the surface's
/// own columns first) and faces were read back: positions, canonical coordinates as the
/// attributes, and each vertex's grid edge and weight, as [`crate::geometry::marching_tets`]
/// gives them.
pub fn mesh_from_rows(
    topo: &DeviceTopology,
    rows: &[f32],
    width: usize,
    faces: &[f32],
    vertex_count: usize,
) -> TriMesh {
    let rows = rows.chunks_exact(width).take(vertex_count);
    let mut mesh = TriMesh {
        vertices: Vec::with_capacity(vertex_count),
        faces: faces.chunks_exact(3).filter(|f| f[0] >= 0.0).map(|f| [f[0] as u32, f[1] as u32, f[2] as u32]).collect(),
        attributes: Vec::with_capacity(vertex_count),
        edges: Vec::with_capacity(vertex_count),
    };
    for r in rows {
        mesh.vertices.push(Vec3::from_slice(&r[0..3]));
        mesh.attributes.push(Vec3::from_slice(&r[3..6]));
        let (a, b) = topo.edges[r[6] as usize];
        mesh.edges.push((a, b, r[7]));
    }
    mesh
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::generator::fields::GridFields;
    use crate::generator::readback::read_f32_now;
    use crate::geometry::marching_tets;
    use crate::util::cooperative::run_blocking;
    use crate::util::rng::Rng;

    #[allow(deprecated)]
    fn cpu() -> Device {
        Device::ndarray()
    }

    #[test]
    fn blocked_scan_is_the_running_sum() {
        let mut rng = Rng::new(5, 0);
        for n in [1, 63, 64, 65, 4097, 300_000] {
            let x: Vec<i64> = (0..n).map(|_| rng.below(2) as i64).collect();
            let t = Tensor::<1, Int>::from_data(TensorData::new(x.clone(), [n]), &cpu());
            let got: Vec<i64> = inclusive_scan(t).into_data().convert::<i64>().try_to_vec::<i64>().expect("ints");
            let want: Vec<i64> = x.iter().scan(0, |s, v| Some(*s + v).inspect(|t| *s = *t)).collect();
            assert_eq!(got, want, "n = {n}");
        }
    }

    /// A sphere's SDF off centre as the "template", random residuals and offsets on the band,
    /// padding rows of garbage past it: the device pass gives the CPU reference's triangles,
    /// corner for corner (positions, canonical coordinates, grid edges and weights).
    #[test]
    fn the_device_pass_gives_the_cpu_reference_mesh() {
        let grid = TetGrid::cube(12, Vec3::ZERO, 2.0);
        let boundary = grid.boundary_flags();
        let centre = Vec3::new(0.05, -0.03, 0.02);
        let template: Vec<f32> = grid.vertices.iter().map(|p| (*p - centre).length() - 0.6).collect();
        let band: Vec<u32> =
            (0..template.len()).filter(|&i| template[i].abs() < 0.25 && !boundary[i]).map(|i| i as u32).collect();
        let mut rng = Rng::new(11, 0);
        let mut fields = GridFields::zeros(template.len());
        let mut rows = Vec::new();
        for &i in &band {
            let r = [rng.range(-0.1, 0.1), rng.range(-0.02, 0.02), rng.range(-0.02, 0.02), rng.range(-0.02, 0.02)];
            fields.residual[i as usize] = r[0];
            fields.offset[3 * i as usize..3 * i as usize + 3].copy_from_slice(&r[1..]);
            rows.extend(r);
        }
        rows.extend([9.0; 4 * 7]); // padding rows: must be ignored
        let canonical: Vec<Vec3> = grid.vertices.iter().map(|p| *p * 1.5 + Vec3::Y).collect();
        let reference =
            marching_tets(&fields.positions(&grid.vertices), &grid.tets, &fields.sdf(&template, &boundary), &canonical);
        assert!(reference.faces.len() > 500, "a real surface: {} triangles", reference.faces.len());

        let device = cpu();
        let topology = DmtetTopology::new(&grid, &boundary, &template, &band);
        assert!(topology.tets.len() < grid.tets.len(), "the far tets are left out");
        let topology = topology.upload(&grid, &canonical, &device);
        let band_rows = Tensor::<1>::from_data(TensorData::new(rows, [4 * (band.len() + 7)]), &device);
        let surface = run_blocking(extract(&topology, band_rows.reshape([band.len() + 7, 4]))).expect("extract");
        assert_eq!(surface.vertex_count, reference.vertices.len());
        assert_eq!(surface.rows.dims()[0] % crate::generator::fields::POINT_ALIGN, 0, "rows padded");
        let rows = read_f32_now(surface.rows).expect("rows");
        let faces = read_f32_now(surface.faces).expect("faces");
        let mesh = mesh_from_rows(&topology, &rows, SURFACE_COLUMNS, &faces, surface.vertex_count);
        assert_eq!(mesh.faces.len(), reference.faces.len());
        let mut worst = 0.0f32;
        for (f, g) in reference.faces.iter().zip(&mesh.faces) {
            for (&a, &b) in f.iter().zip(g) {
                let (a, b) = (a as usize, b as usize);
                worst = worst.max(reference.vertices[a].distance(mesh.vertices[b]));
                worst = worst.max(reference.attributes[a].distance(mesh.attributes[b]));
                let (ea, eb) = (reference.edges[a], mesh.edges[b]);
                assert_eq!((ea.0, ea.1), (eb.0, eb.1), "corner on another grid edge");
                worst = worst.max((ea.2 - eb.2).abs());
            }
        }
        assert!(worst < 1e-6, "corners differ by {worst}");
        assert_eq!(mesh.topology_defects(), (0, 0), "closed and consistently oriented");

        // A grid with no sign change and no band: no surface, an empty one (not a panic).
        let far = vec![1.0f32; template.len()];
        let empty = DmtetTopology::new(&grid, &boundary, &far, &[]).upload(&grid, &canonical, &device);
        let none = run_blocking(extract(&empty, Tensor::<2>::zeros([1, 4], &device))).expect("extract");
        assert_eq!((none.vertex_count, none.rows.dims(), none.faces.dims()), (0, [0, SURFACE_COLUMNS], [0, 3]));
    }
}
