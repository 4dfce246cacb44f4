//! Differentiable rendering and extraction (issue: training): every backward pass is checked
//! against finite differences of the whole forward pass (rasterisation included) on small
//! meshes, on NdArray and on Wgpu (lavapipe); silhouette gradients against the analytic area
//! change; DMTet vertex gradients against finite differences.

use getavatar_core::burn::tensor::{Device, Tensor, TensorData};
use getavatar_core::geometry::{marching_tets, TetGrid};
use getavatar_core::render::camera::OrbitCamera;
use getavatar_core::render::diff::dmtet::{surface_points, EdgeIndex};
use getavatar_core::render::diff::rasterize::{
    antialias, compose, interpolate, silhouette_pairs, silhouette_pairs_of, Coverage, MeshEdges,
};
use getavatar_core::render::rasterize::{interpolate as cpu_interpolate, rasterize};
use getavatar_core::util::rng::Rng;
use glam::{Mat4, Vec3, Vec4};

mod common;
use common::{cpu, gpu, linear_fd_error, smooth_fd_error, values, SmoothFd};

const SIZE: usize = 48;

fn tensor2(v: &[f32], n: usize, c: usize, dev: &Device) -> Tensor<2> {
    Tensor::from_data(TensorData::new(v.to_vec(), [n, c]), dev)
}

/// Two overlapping quads at different depths (occlusion, interior diagonals, silhouettes).
fn scene() -> (Vec<Vec3>, Vec<[u32; 3]>, Vec<f32>) {
    let t = OrbitCamera::default().target;
    let v = vec![
        // back quad, z = −0.2
        Vec3::new(-0.45, -0.4, -0.2),
        Vec3::new(0.35, -0.42, -0.2),
        Vec3::new(0.38, 0.3, -0.2),
        Vec3::new(-0.41, 0.33, -0.2),
        // front quad, z = +0.1, rotated a little
        Vec3::new(-0.1, -0.25, 0.1),
        Vec3::new(0.5, -0.15, 0.12),
        Vec3::new(0.42, 0.45, 0.08),
        Vec3::new(-0.18, 0.36, 0.1),
    ]
    .into_iter()
    .map(|p| p + t)
    .collect();
    let f = vec![[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]];
    // Per-vertex colour (3) + coverage (1).
    let mut rng = Rng::new(5, 5);
    let attr: Vec<f32> = (0..8).flat_map(|_| [rng.uniform(), rng.uniform(), rng.uniform(), 1.0]).collect();
    (v, f, attr)
}

fn view_proj() -> Mat4 {
    let cam = OrbitCamera { yaw: 0.3, pitch: 0.1, ..OrbitCamera::default() };
    cam.projection_gl(1.0) * cam.world_to_camera()
}

/// The full differentiable forward: world positions `[V, 3]` and attributes `[V, 4]` →
/// antialiased image `[H·W, 4]` over a white, uncovered background; then a weighted sum.
fn render_loss(pos: Tensor<2>, attr: Tensor<2>, tris: &[[u32; 3]], weights: &Tensor<2>, dev: &Device) -> Tensor<1> {
    let vp = view_proj();
    let m: Vec<f32> = vp.transpose().to_cols_array().to_vec(); // rows of vp = columns for x·Mᵀ
    let n = pos.dims()[0];
    let homo = Tensor::cat(vec![pos, Tensor::ones([n, 1], dev)], 1);
    let clip = homo.matmul(tensor2(&m, 4, 4, dev).transpose());
    let clip_cpu: Vec<Vec4> = values(clip.clone()).chunks_exact(4).map(Vec4::from_slice).collect();
    let r = rasterize(&clip_cpu, tris, SIZE, SIZE);
    let cov = Coverage::new(&r, tris);
    let px = interpolate(&cov, clip.clone(), attr, dev);
    let img = compose(&cov, px, &[1.0, 1.0, 1.0, 0.0], dev);
    let pairs = silhouette_pairs(&r, &clip_cpu, tris);
    let img = antialias(img, &pairs, clip, SIZE, SIZE, dev);
    (img * weights.clone()).sum()
}

fn grad_check(dev: &Device) {
    let (v, tris, attr) = scene();
    let pos: Vec<f32> = v.iter().flat_map(|p| p.to_array()).collect();
    let mut rng = Rng::new(9, 9);
    let w: Vec<f32> = (0..SIZE * SIZE * 4).map(|_| rng.uniform() * 2.0 - 1.0).collect();
    let ad = dev.clone().autodiff();
    let weights = tensor2(&w, SIZE * SIZE, 4, &ad);
    let p = tensor2(&pos, 8, 3, &ad).require_grad();
    let a = tensor2(&attr, 8, 4, &ad).require_grad();
    let loss = render_loss(p.clone(), a.clone(), &tris, &weights, &ad);
    let grads = loss.backward();
    let gp = values(p.grad(&grads).expect("position gradient"));
    let ga = values(a.grad(&grads).expect("attribute gradient"));

    let plain = |pos: &[f32], attr: &[f32]| -> f64 {
        let wt = tensor2(&w, SIZE * SIZE, 4, dev);
        values(render_loss(tensor2(pos, 8, 3, dev), tensor2(attr, 8, 4, dev), &tris, &wt, dev))[0] as f64
    };
    // Attributes: the image is linear in them, so central differences are exact up to rounding.
    let (err, scale) = linear_fd_error(&|a| plain(&pos, a), &attr, &ga, 1e-2);
    assert!(err / scale < 1e-3, "attribute gradients: max error {err} of {scale}");

    // Positions: per-coordinate central differences of the whole pipeline (rasterisation
    // re-run). The antialiased image is continuous except for rare visibility events near
    // triangle corners (as in nvdiffrast, an approximation); a coordinate whose finite
    // differences at two step sizes disagree has such an event inside its stencil and is not
    // a test of the gradient, so it is set aside (at most a third of them).
    let SmoothFd { stable, diff, size } = smooth_fd_error(&|p| plain(p, &attr), &pos, &gp, (1e-4, 3e-4), 0.01);
    assert!(stable.len() * 3 >= pos.len() * 2, "only {} of {} coordinates are smooth", stable.len(), pos.len());
    assert!(diff / size < 1e-2, "position gradients: relative error {} over {} coordinates", diff / size, stable.len());
    // Every vertex of a silhouette gets a gradient; occluded back-quad corners may too.
    assert!(gp.iter().all(|g| g.is_finite()));
    assert!(gp.chunks(3).skip(4).all(|g| g.iter().any(|x| x.abs() > 0.0)), "front-quad vertices");
}

#[test]
fn render_gradients_match_finite_differences_on_ndarray() {
    grad_check(&cpu());
}

#[test]
fn render_gradients_match_finite_differences_on_wgpu() {
    grad_check(&gpu());
}

#[test]
fn interpolate_matches_the_cpu_rasterizer() {
    let dev = cpu();
    let (v, tris, attr) = scene();
    let vp = view_proj();
    let clip: Vec<Vec4> = v.iter().map(|p| vp * p.extend(1.0)).collect();
    let r = rasterize(&clip, &tris, SIZE, SIZE);
    let cov = Coverage::new(&r, &tris);
    let clip_t = tensor2(&clip.iter().flat_map(|c| c.to_array()).collect::<Vec<_>>(), 8, 4, &dev);
    let got = values(interpolate(&cov, clip_t, tensor2(&attr, 8, 4, &dev), &dev));
    let colors: Vec<Vec3> = attr.chunks(4).map(|a| Vec3::new(a[0], a[1], a[2])).collect();
    let want: Vec<Vec3> = cpu_interpolate(&colors, &r, &tris).into_iter().flatten().collect();
    assert_eq!(want.len(), cov.len());
    for (k, w) in want.iter().enumerate() {
        let g = Vec3::new(got[4 * k], got[4 * k + 1], got[4 * k + 2]);
        assert!((g - *w).length() < 1e-4, "pixel {k}: {g} vs {w}");
        assert!((got[4 * k + 3] - 1.0).abs() < 1e-5);
    }
}

#[test]
fn silhouette_gradient_equals_the_area_change_of_the_mask() {
    // A camera-facing square; moving its right edge by δ pixels grows the mask by δ·height.
    let dev = cpu().autodiff();
    let cam = OrbitCamera::default();
    let t = cam.target;
    let v = [
        Vec3::new(-0.3, -0.3, 0.0),
        Vec3::new(0.31, -0.3, 0.0),
        Vec3::new(0.31, 0.32, 0.0),
        Vec3::new(-0.3, 0.32, 0.0),
    ]
    .map(|p| p + t);
    let tris = [[0, 1, 2], [0, 2, 3]];
    let vp = cam.projection_gl(1.0) * cam.world_to_camera();
    let clip: Vec<Vec4> = v.iter().map(|p| vp * p.extend(1.0)).collect();
    let clip_t = tensor2(&clip.iter().flat_map(|c| c.to_array()).collect::<Vec<_>>(), 4, 4, &dev).require_grad();
    let r = rasterize(&clip, &tris, SIZE, SIZE);
    let cov = Coverage::new(&r, &tris);
    let ones = tensor2(&[1.0; 4], 4, 1, &dev);
    let mask = compose(&cov, interpolate(&cov, clip_t.clone(), ones, &dev), &[0.0], &dev);
    let mask = antialias(mask, &silhouette_pairs(&r, &clip, &tris), clip_t.clone(), SIZE, SIZE, &dev);
    let grads = mask.sum().backward();
    let g = values(clip_t.grad(&grads).unwrap());
    // d(mask)/d(screen x) of the right edge = its height in pixels; screen x = (X/W + 1)·S/2,
    // so d/dX = d/dsx · S/(2W).
    let height_px = (clip[2].y / clip[2].w - clip[1].y / clip[1].w) * 0.5 * SIZE as f32;
    let d_dsx: f32 = [1usize, 2].iter().map(|&i| g[4 * i] * 2.0 * clip[i].w / SIZE as f32).sum();
    assert!((d_dsx / height_px - 1.0).abs() < 0.05, "d(mask area)/dx {d_dsx} vs edge height {height_px} px");
    let d_left: f32 = [0usize, 3].iter().map(|&i| g[4 * i] * 2.0 * clip[i].w / SIZE as f32).sum();
    assert!((d_left / height_px + 1.0).abs() < 0.05, "left edge {d_left}");
}

#[test]
fn mesh_edges_list_each_edge_once_with_its_triangles() {
    // A closed tetrahedron: 6 edges, each used by 2 faces; plus one dangling triangle sharing
    // the edge (0, 1), which then has 3 users, and two edges of its own with 1.
    let tris = [[0, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0], [1, 0, 4]];
    let e = MeshEdges::new(&tris);
    let got: Vec<((u32, u32), Vec<u32>)> =
        e.ends.iter().enumerate().map(|(k, &ab)| (ab, e.owners(k).to_vec())).collect();
    let want = vec![
        ((0, 1), vec![0, 1, 4]),
        ((0, 2), vec![0, 3]),
        ((0, 3), vec![1, 3]),
        ((0, 4), vec![4]),
        ((1, 2), vec![0, 2]),
        ((1, 3), vec![1, 2]),
        ((1, 4), vec![4]),
        ((2, 3), vec![2, 3]),
    ];
    assert_eq!(got, want);
    // The pairs found with the edges given beforehand are the ones found without.
    let (v, quads, _) = scene();
    let vp = view_proj();
    let clip: Vec<Vec4> = v.iter().map(|p| vp * p.extend(1.0)).collect();
    let r = rasterize(&clip, &quads, SIZE, SIZE);
    let (a, b) = (silhouette_pairs(&r, &clip, &quads), silhouette_pairs_of(&r, &clip, &quads, &MeshEdges::new(&quads)));
    assert!(!a.target.is_empty());
    assert_eq!((a.target, a.source, a.edge, a.sign), (b.target, b.source, b.edge, b.sign));
}

#[test]
fn antialias_through_the_compacted_edge_vertices_gives_the_same_mask_and_gradients() {
    // The fit poses only the silhouette edges' vertices with a gradient (`compact`): the
    // mask and the gradients of those vertices must equal antialiasing with all of them.
    let dev = cpu().autodiff();
    let (v, tris, _) = scene();
    let vp = view_proj();
    let clip: Vec<Vec4> = v.iter().map(|p| vp * p.extend(1.0)).collect();
    let flat: Vec<f32> = clip.iter().flat_map(|c| c.to_array()).collect();
    let r = rasterize(&clip, &tris, SIZE, SIZE);
    let cov = Coverage::new(&r, &tris);
    let pairs = silhouette_pairs(&r, &clip, &tris);
    let (ids, local) = pairs.compact();
    assert!(ids.len() >= 4 && ids.len() < clip.len() + 1 && ids.windows(2).all(|w| w[0] < w[1]), "{ids:?}");
    let weights = tensor2(&(0..SIZE * SIZE).map(|k| ((k * 7) % 11) as f32).collect::<Vec<_>>(), SIZE * SIZE, 1, &dev);
    let mask_of = |clip_t: Tensor<2>, p| {
        let base = compose(&cov, Tensor::<2>::ones([cov.len(), 1], &dev), &[0.0], &dev);
        antialias(base, p, clip_t, SIZE, SIZE, &dev)
    };
    let full = tensor2(&flat, clip.len(), 4, &dev).require_grad();
    let sub_rows: Vec<f32> = ids.iter().flat_map(|&i| clip[i as usize].to_array()).collect();
    let sub = tensor2(&sub_rows, ids.len(), 4, &dev).require_grad();
    let (m_full, m_sub) = (mask_of(full.clone(), &pairs), mask_of(sub.clone(), &local));
    assert_eq!(values(m_full.clone()), values(m_sub.clone()));
    let g_full = values(full.grad(&(m_full * weights.clone()).sum().backward()).unwrap());
    let g_sub = values(sub.grad(&(m_sub * weights).sum().backward()).unwrap());
    for (k, &i) in ids.iter().enumerate() {
        assert_eq!(g_sub[k * 4..k * 4 + 4], g_full[i as usize * 4..i as usize * 4 + 4], "vertex {i}");
    }
    // The vertices left out get no gradient from the mask.
    for i in (0..clip.len() as u32).filter(|i| !ids.contains(i)) {
        assert!(g_full[i as usize * 4..i as usize * 4 + 4].iter().all(|g| *g == 0.0), "vertex {i}");
    }
}

#[test]
fn dmtet_vertex_gradients_match_finite_differences() {
    let dev = cpu().autodiff();
    let grid = TetGrid::cube(6, Vec3::ZERO, 2.0);
    let n = grid.vertices.len();
    let sdf_of = |r: f32, c: Vec3| -> Vec<f32> { grid.vertices.iter().map(|p| (*p - c).length() - r).collect() };
    let (r0, c0) = (0.61f32, Vec3::new(0.05, -0.03, 0.02));
    let sdf = sdf_of(r0, c0);
    let mesh = marching_tets(&grid.vertices, &grid.tets, &sdf, &[]);
    let edges = EdgeIndex::new(&mesh);
    let pos: Vec<f32> = grid.vertices.iter().flat_map(|p| p.to_array()).collect();
    let p = tensor2(&pos, n, 3, &dev).require_grad();
    let s = Tensor::<1>::from_data(TensorData::new(sdf.clone(), [n]), &dev).require_grad();
    let pts = surface_points(&edges, p.clone(), s.clone(), &dev);
    // Forward equals the CPU extraction.
    let got = values(pts.clone());
    for (k, v) in mesh.vertices.iter().enumerate() {
        assert!((Vec3::from_slice(&got[3 * k..]) - *v).length() < 1e-5);
    }
    let mut rng = Rng::new(1, 2);
    let w: Vec<f32> = (0..mesh.vertices.len() * 3).map(|_| rng.normal()).collect();
    let wt = tensor2(&w, mesh.vertices.len(), 3, &dev);
    let grads = (pts * wt).sum().backward();
    let (gp, gs) = (values(p.grad(&grads).unwrap()), values(s.grad(&grads).unwrap()));
    // Finite differences with the same topology (edges fixed), in f64.
    let f = |pos: &[f32], sdf: &[f32]| -> f64 {
        edges.a.iter().zip(&edges.b).enumerate().fold(0.0, |acc, (k, (&a, &b))| {
            let (sa, sb) = (sdf[a as usize] as f64, sdf[b as usize] as f64);
            let t = sa / (sa - sb);
            (0..3).fold(acc, |acc, c| {
                let (xa, xb) = (pos[3 * a as usize + c] as f64, pos[3 * b as usize + c] as f64);
                acc + w[3 * k + c] as f64 * (xa + (xb - xa) * t)
            })
        })
    };
    let eps = 1e-3f32;
    let (mut worst, mut scale) = (0.0f64, 1e-9f64);
    for i in (0..n).step_by(5) {
        let (mut hi, mut lo) = (sdf.clone(), sdf.clone());
        hi[i] += eps;
        lo[i] -= eps;
        let fd = (f(&pos, &hi) - f(&pos, &lo)) / (2.0 * eps as f64);
        worst = worst.max((fd - gs[i] as f64).abs());
        scale = scale.max(fd.abs());
        let (mut hi, mut lo) = (pos.clone(), pos.clone());
        hi[3 * i] += eps;
        lo[3 * i] -= eps;
        let fd = (f(&hi, &sdf) - f(&lo, &sdf)) / (2.0 * eps as f64);
        worst = worst.max((fd - gp[3 * i] as f64).abs());
        scale = scale.max(fd.abs());
    }
    assert!(worst / scale < 1e-3, "DMTet gradients: max error {worst} of {scale}");
    // Only vertices of sign-changing edges get SDF gradients.
    let on_edge: std::collections::HashSet<u32> = edges.a.iter().chain(&edges.b).copied().collect();
    for (i, g) in gs.iter().enumerate() {
        assert_eq!(*g != 0.0, on_edge.contains(&(i as u32)) && *g != 0.0);
        if !on_edge.contains(&(i as u32)) {
            assert_eq!(*g, 0.0);
        }
    }
}

/// The silhouette gradient of a DMTet sphere with respect to a uniform SDF shift, rendered
/// through the training chain (surface points → clip → rasterize → antialias), against the
/// analytic rate of change of its projected disc: dA/dshift = −2π·r·dr/dR pixels per metre.
/// The tets are finer than the pixels, as in training; nvdiffrast's candidate set (the
/// edges of the triangle seen at the nearer pixel) finds almost none of these silhouettes.
#[test]
fn silhouette_gradients_of_sub_pixel_dmtet_triangles_match_the_projected_disc() {
    let dev = cpu().autodiff();
    let cam = OrbitCamera { yaw: 0.3, pitch: 0.1, ..OrbitCamera::default() };
    let size = 64;
    let centre = cam.target + Vec3::new(0.013, -0.021, 0.007);
    let radius = 0.3f32;
    let grid = TetGrid::cube(48, cam.target, 1.0);
    let n = grid.vertices.len();
    let sdf: Vec<f32> = grid.vertices.iter().map(|p| (*p - centre).length() - radius).collect();
    let mesh = marching_tets(&grid.vertices, &grid.tets, &sdf, &[]);
    let edges = EdgeIndex::new(&mesh);
    let pos: Vec<f32> = grid.vertices.iter().flat_map(|p| p.to_array()).collect();
    let shift = Tensor::<1>::from_data(TensorData::new(vec![0.0f32], [1]), &dev).require_grad();
    let s = Tensor::<1>::from_data(TensorData::new(sdf, [n]), &dev) + shift.clone().expand([n]);
    let verts = surface_points(&edges, tensor2(&pos, n, 3, &dev), s, &dev);
    let vp = cam.projection_gl(1.0) * cam.world_to_camera();
    let m = tensor2(&vp.transpose().to_cols_array(), 4, 4, &dev);
    let nv = mesh.vertices.len();
    let clip = Tensor::cat(vec![verts, Tensor::ones([nv, 1], &dev)], 1).matmul(m.transpose());
    let clip_v: Vec<Vec4> = values(clip.clone()).chunks_exact(4).map(Vec4::from_slice).collect();
    let r = rasterize(&clip_v, &mesh.faces, size, size);
    let cov = Coverage::new(&r, &mesh.faces);
    let cover = compose(&cov, interpolate(&cov, clip.clone(), Tensor::ones([nv, 1], &dev), &dev), &[0.0], &dev);
    let pairs = silhouette_pairs(&r, &clip_v, &mesh.faces);
    let area = antialias(cover, &pairs, clip, size, size, &dev).sum();
    let got = values(shift.grad(&area.backward()).expect("shift gradient"))[0];
    // Projected radius of a sphere at distance D: ρ = f·R / √(D² − R²), f = focal length in px.
    let f = cam.projection_gl(1.0).y_axis.y * size as f32 / 2.0;
    let d = (cam.world_to_camera() * centre.extend(1.0)).truncate().length();
    let rho = f * radius / (d * d - radius * radius).sqrt();
    let drho = f * d * d / (d * d - radius * radius).powf(1.5);
    let want = -2.0 * std::f32::consts::PI * rho * drho;
    assert!(mesh.faces.len() > 10 * cov.len(), "sub-pixel triangles: {} faces, {} pixels", mesh.faces.len(), cov.len());
    assert!((got / want - 1.0).abs() < 0.1, "d(area)/d(shift) {got} px/m, projected disc {want} (ρ = {rho:.1} px)");
}
