//! One model code on two backends: the generator gives the same fields and meshes on NdArray
//! (CPU) and on Wgpu (natively: Vulkan, on CI Mesa's lavapipe software rasteriser).

use getavatar_core::body::body_model::BodyModel;
use getavatar_core::body::pose_library::PoseLibrary;
use getavatar_core::burn::tensor::{Device, Tensor, TensorData};
use getavatar_core::generator::network::GeneratorConfig;
use getavatar_core::generator::pipeline::{generate_avatar, seed_latents, BodyContext, Generator};
use getavatar_core::geometry::spatial::KdTree;

mod common;
use common::{assert_close, values};
use getavatar_core::util::profile;

#[test]
fn ndarray_and_wgpu_give_the_same_fields_and_meshes() {
    #[allow(deprecated)]
    let cpu = Device::ndarray();
    let gpu = common::gpu();
    let cfg = GeneratorConfig::tiny();
    let model = BodyModel::default_body().expect("body");
    let (gc, gg) = (Generator::new(&cfg, 0, &cpu), Generator::new(&cfg, 0, &gpu));

    // Fields at body points near the surface.
    let pts = body_points(&model, 7);
    let (a, b) = (fields(&gc, &cfg, (3, 4), &pts, &cpu), fields(&gg, &cfg, (3, 4), &pts, &gpu));
    assert_fields_close(&a, &b, 1e-4, "NdArray and Wgpu");

    // Whole avatars: same mesh within float noise.
    let ctx = BodyContext::new(model, &cfg);
    let params = PoseLibrary::builtin().params("walking", &[]).expect("pose");
    let avatar = |g: &Generator, dev: &Device| {
        let (zg, zt) = seed_latents(&cfg, 3, 4, dev);
        generate_avatar(g, &ctx, &g.styles(zg, zt, 0.7), &params, dev).expect("generation reads back")
    };
    let (ma, mb) = (avatar(&gc, &cpu), avatar(&gg, &gpu));
    assert_eq!(ma.mesh.faces.len(), mb.mesh.faces.len(), "different triangle counts");
    let tb = KdTree::new(&mb.mesh.vertices);
    let d = ma.mesh.vertices.iter().map(|v| tb.nearest(*v).map_or(f32::MAX, |x| x.1.sqrt())).fold(0.0, f32::max);
    println!("mesh: {} vertices, max vertex distance {d:.2e} m", ma.mesh.vertices.len());
    assert!(d < 1e-4, "meshes differ by {d} m");
}

/// Every `step`-th vertex of the body template (points near the surface), flattened.
fn body_points(model: &BodyModel, step: usize) -> Vec<f32> {
    model.v_template.iter().step_by(step).flat_map(|v| v.to_array()).collect()
}

/// The names of [`fields`]' outputs.
const FIELDS: [&str; 5] = ["geometry planes", "texture planes", "sdf residual", "offsets", "colours"];

/// A generator's triplanes, and its SDF residual, offsets and colours at `pts`, for one seed
/// pair at ψ 0.7 on `dev`.
fn fields(g: &Generator, cfg: &GeneratorConfig, seeds: (u64, u64), pts: &[f32], dev: &Device) -> [Vec<f32>; 5] {
    let n = pts.len() / 3;
    let (zg, zt) = seed_latents(cfg, seeds.0, seeds.1, dev);
    let s = g.styles(zg, zt, 0.7);
    let planes = g.triplanes(&s);
    let p = Tensor::<3>::from_data(TensorData::new(pts.to_vec(), [1, n, 3]), dev);
    let (r, o) = g.geometry_fields(&planes, &s, p.clone());
    let c = g.texture_field(&planes, &s, p);
    [values(planes.geometry), values(planes.texture), values(r), values(o), values(c)]
}

/// Each of [`fields`]' outputs within `rel` of its scale (plus 1e-7).
fn assert_fields_close(a: &[Vec<f32>; 5], b: &[Vec<f32>; 5], rel: f32, what: &str) {
    for ((name, x), y) in FIELDS.iter().zip(a).zip(b) {
        let scale = y.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-6);
        let diff = x.iter().zip(y).fold(0.0f32, |m, (p, q)| m.max((p - q).abs()));
        println!("{name}: max |Δ| {diff:.3e} (scale {scale:.3e})");
        assert!(diff <= rel * scale + 1e-7, "{name}: {what} differ by {diff} (scale {scale})");
    }
}

fn clock_ms() -> f64 {
    static T0: std::sync::OnceLock<std::time::Instant> = std::sync::OnceLock::new();
    T0.get_or_init(std::time::Instant::now).elapsed().as_secs_f64() * 1e3
}

/// A profiled stage counts the GPU kernels it launched (cubecl's launch observer);
/// a stage that launched nothing counts none, unless another test's launches overlap it.
#[test]
fn profiled_stages_count_gpu_dispatches() {
    let gpu = common::gpu();
    profile::start(clock_ms);
    profile::stage("matmuls");
    let mut x = Tensor::<2>::from_data(TensorData::new((0..64 * 64).map(|i| (i % 7) as f32).collect(), [64, 64]), &gpu);
    for _ in 0..3 {
        // Read back each product, so the three are separate launches, not one fused graph.
        x = x.clone().matmul(x) / 64.0;
        let _ = values(x.clone());
    }
    let p = profile::finish().expect("recording");
    let d = p.stages[0].dispatches;
    println!("{}", p.table());
    assert!(d >= 3, "three read-back matmuls launched {d} GPU kernels");
    assert_eq!(p.dispatches(), d);
}

/// Marching tetrahedra as GPU work (`dmtet_gpu`, on lavapipe here) gives the CPU
/// reference's mesh from the same fields: the same triangles in the same order, each corner
/// within 1e-5 m, on the canonical grid of a generator's band. And a new identity on the GPU
/// then reads back twice: the surface's counts, then its rows with their normals and colours.
#[test]
fn marching_tets_on_the_gpu_gives_the_cpu_mesh() {
    use getavatar_core::generator::dmtet_gpu::{extract, mesh_from_rows, DmtetTopology, SURFACE_COLUMNS};
    use getavatar_core::generator::fields::{aligned_points, band_fields, band_rows, points_tensor};
    use getavatar_core::generator::readback::{block_on_ready, read_f32_now};
    use getavatar_core::generator::rigging::generate_rigged_async;
    use getavatar_core::geometry::marching_tets;
    use getavatar_core::util::cooperative::run_blocking;

    let gpu = common::gpu();
    let cfg = GeneratorConfig::tiny();
    let ctx = BodyContext::new(BodyModel::default_body().expect("body"), &cfg);
    let g = Generator::new(&cfg, 0, &gpu);
    let (zg, zt) = seed_latents(&cfg, 5, 6, &gpu);
    let s = g.styles(zg, zt, 0.7);
    let planes = g.triplanes(&s);
    let grid = run_blocking(ctx.canonical_grid_async(ctx.canonical_inverse()));
    let band_points: Vec<_> = grid.band.iter().map(|&i| grid.canonical[i as usize]).collect();
    let points = points_tensor(&aligned_points(&band_points), &gpu);

    let fields =
        block_on_ready(band_fields(&g, &planes.geometry, &s, points.clone(), &grid.band, grid.canonical.len()))
            .expect("fields read back");
    let reference = marching_tets(
        &fields.positions(&ctx.grid.vertices),
        &ctx.grid.tets,
        &fields.sdf(&grid.template, &ctx.boundary),
        &grid.canonical,
    );
    let topology = DmtetTopology::new(&ctx.grid, &ctx.boundary, &grid.template, &grid.band).upload(
        &ctx.grid,
        &grid.canonical,
        &gpu,
    );
    let surface =
        block_on_ready(extract(&topology, band_rows(&g, &planes.geometry, &s, points))).expect("counts read back");
    assert_eq!(surface.vertex_count, reference.vertices.len());
    let rows = read_f32_now(surface.rows).expect("rows");
    let faces = read_f32_now(surface.faces).expect("faces");
    let mesh = mesh_from_rows(&topology, &rows, SURFACE_COLUMNS, &faces, surface.vertex_count);
    let worst = reference.faces.iter().zip(&mesh.faces).fold(0.0f32, |w, (f, h)| {
        f.iter().zip(h).fold(w, |w, (&a, &b)| w.max(reference.vertices[a as usize].distance(mesh.vertices[b as usize])))
    });
    println!("{} triangles, corners within {worst:.2e} m", mesh.faces.len());
    assert_eq!(mesh.faces.len(), reference.faces.len());
    assert!(reference.faces.len() > 500);
    assert!(worst < 1e-5, "GPU and CPU corners differ by {worst} m");

    profile::start(clock_ms);
    let rigged = block_on_ready(generate_rigged_async(&g, &ctx, &s, &gpu)).expect("generation reads back");
    let stages = profile::finish().expect("recorded");
    let per_stage: Vec<(&str, u32)> = stages.stages.iter().map(|s| (s.stage.as_str(), s.readbacks)).collect();
    println!("{}", stages.table());
    assert_eq!(
        per_stage,
        [
            ("synthesis", 0),
            ("posed grid", 0),
            ("grid decode", 0),
            ("DMTet", 1),
            ("normals & colours", 1),
            ("rigging", 0)
        ]
    );
    let canonical = &rigged.canonical;
    assert!(canonical.mesh.vertices.len() > 500);
    assert_eq!(canonical.mesh.topology_defects(), (0, 0));
    assert!(canonical.normals.iter().all(|n| (n.length() - 1.0).abs() < 1e-4));
    assert_eq!(canonical.colors.len(), canonical.mesh.vertices.len());

    // The same identity by the CPU reference on NdArray: each vertex's normal (the template's
    // gradient added on the host) and colour agree at its nearest vertex there.
    #[allow(deprecated)]
    let cpu = Device::ndarray();
    let gc = Generator::new(&cfg, 0, &cpu);
    let (zg, zt) = seed_latents(&cfg, 5, 6, &cpu);
    let reference = block_on_ready(generate_rigged_async(&gc, &ctx, &gc.styles(zg, zt, 0.7), &cpu)).expect("cpu");
    let reference = &reference.canonical;
    assert_eq!(reference.mesh.faces.len(), canonical.mesh.faces.len());
    let tree = KdTree::new(&reference.mesh.vertices);
    let (mut far, mut normal, mut colour) = (0.0f32, 0.0f32, 0.0f32);
    for ((v, n), c) in canonical.mesh.vertices.iter().zip(&canonical.normals).zip(&canonical.colors) {
        let (i, d2) = tree.nearest(*v).expect("a vertex");
        far = far.max(d2.sqrt());
        normal = normal.max(1.0 - n.dot(reference.normals[i]));
        colour = colour.max((*c - reference.colors[i]).abs().max_element());
    }
    println!("vs NdArray: vertices within {far:.2e} m, normals 1 − cos ≤ {normal:.2e}, colours within {colour:.2e}");
    assert!(far < 1e-4 && normal < 1e-4 && colour < 1e-4, "{far} {normal} {colour}");
}

/// A large convolution on a GPU backend goes through im2col + matmul
/// (`GPU_IM2COL_MIN_MACS`; burn's direct kernel was 83 % of the paper config's generation on an
/// H200). At that size, on lavapipe, it gives burn's `conv2d` (the direct kernel) within float
/// noise, values and gradients, for a shared and a per-sample weight.
#[test]
fn a_large_gpu_convolution_through_im2col_matches_burn_conv2d() {
    use getavatar_core::burn::tensor::module::conv2d;
    use getavatar_core::burn::tensor::ops::ConvOptions;
    use getavatar_core::generator::network::layers::{conv2d_im2col, conv2d_same, GPU_IM2COL_MIN_MACS};
    use getavatar_core::util::rng::Rng;
    let dev = common::gpu().autodiff();
    let mut rng = Rng::new(8, 1);
    let (c, o, k, r) = (128usize, 128usize, 3usize, 64usize);
    for b in [1usize, 2] {
        assert!(b * o * c * k * k * r * r >= GPU_IM2COL_MIN_MACS, "the case must take the im2col path");
        let x: Tensor<4> =
            Tensor::from_data(TensorData::new(rng.normals(b * c * r * r), [b, c, r, r]), &dev).require_grad();
        let w: Tensor<5> =
            Tensor::from_data(TensorData::new(rng.normals(b * o * c * k * k), [b, o, c, k, k]), &dev).require_grad();
        let opts = |g| ConvOptions::new([1, 1], [k / 2, k / 2], [1, 1], g);
        let reference = conv2d(x.clone().reshape([1, b * c, r, r]), w.clone().reshape([b * o, c, k, k]), None, opts(b))
            .reshape([b, o, r, r]);
        let ours = conv2d_same(x.clone(), w.clone());
        let weights: Tensor<4> = Tensor::from_data(TensorData::new(rng.normals(b * o * r * r), [b, o, r, r]), &dev);
        let grads = |y: Tensor<4>| {
            let g = (y * weights.clone()).sum().backward();
            (values(x.grad(&g).expect("x grad")), values(w.grad(&g).expect("w grad")))
        };
        let close =
            |ours: &[f32], want: &[f32], what: &str| assert_close(ours, want, 1e-5, &format!("{what} (batch {b})"));
        close(&values(ours.clone()), &values(reference.clone()), "values");
        // In bands of rows, as the paper config's 256² layers go (here 4 bands of 16 rows).
        let banded = conv2d_im2col(x.clone(), w.clone(), 4 * b * c * k * k * r * 16);
        close(&values(banded), &values(reference.clone()), "values in bands");
        let (gx0, gw0) = grads(reference);
        let (gx1, gw1) = grads(ours);
        close(&gx1, &gx0, "∂x");
        close(&gw1, &gw0, "∂w");
    }
}

/// Generation's element-wise chains run as single kernels on wgpu
/// (`network::cube_ops`): the style affines and mapping layers, weight modulation, bias + leaky
/// ReLU, and the synthesis's upsampling with its skip sum. They apply to untracked tensors of a
/// cubecl device only (also of an autodiff one), and a tiny generator's triplanes, fields and
/// colours through them equal those through the tensor ops (the same generator with its
/// parameters tracked, on wgpu too) within float noise.
#[test]
fn fused_generation_kernels_match_the_tensor_ops() {
    use getavatar_core::generator::network::cube_ops;
    let gpu = common::gpu();
    #[allow(deprecated)]
    let cpu = Device::ndarray();
    let t2 = |dev: &Device| Tensor::<2>::from_data(TensorData::new(vec![0.5f32, -1.0, 2.0, 0.25], [2, 2]), dev);
    let b1 = |dev: &Device| Tensor::<1>::from_data(TensorData::new(vec![0.1f32, -0.2], [2]), dev);
    let fc = |x: &Tensor<2>, w: &Tensor<2>, b: &Tensor<1>| cube_ops::fully_connected(x, w, b, 0.5, 1.0, true);
    // Routing: plain and untracked-autodiff wgpu tensors take the kernels; tracked or CPU ones do not.
    let y = fc(&t2(&gpu), &t2(&gpu), &b1(&gpu)).expect("wgpu tensors take the kernel");
    // x·Wᵀ·0.5 + b, then leaky ReLU × √2: row 0 = [0.5·(0.25+1) + 0.1, 0.5·(1−0.25) − 0.2] = [0.725, 0.175].
    assert_close(&values(y)[..2], &[0.725 * std::f32::consts::SQRT_2, 0.175 * std::f32::consts::SQRT_2], 1e-6, "fc");
    let ad = gpu.clone().autodiff();
    let y = fc(&t2(&ad), &t2(&ad), &b1(&ad)).expect("untracked autodiff tensors take the kernel");
    assert!(y.is_autodiff(), "the result goes back to the autodiff device");
    assert!(fc(&t2(&ad).require_grad(), &t2(&ad), &b1(&ad)).is_none(), "tracked tensors keep the tensor ops");
    assert!(fc(&t2(&cpu), &t2(&cpu), &b1(&cpu)).is_none(), "NdArray tensors keep the tensor ops");
    let empty = Tensor::<2>::from_data(TensorData::new(Vec::<f32>::new(), [0, 2]), &gpu); // a decoder on no points
    assert!(cube_ops::bias_lrelu(&empty, &b1(&gpu), 1, true).is_none(), "empty tensors keep the tensor ops");

    // A whole generator: fused (plain wgpu) against tensor ops (tracked parameters).
    let cfg = GeneratorConfig::tiny();
    let (fused, plain) = (Generator::new(&cfg, 0, &gpu), Generator::new(&cfg, 0, &ad));
    let model = BodyModel::default_body().expect("body");
    let pts = body_points(&model, 11);
    let (a, b) = (fields(&fused, &cfg, (5, 6), &pts, &gpu), fields(&plain, &cfg, (5, 6), &pts, &ad));
    assert_fields_close(&a, &b, 1e-5, "fused kernels and tensor ops");
}

/// DMTet's prefix sum as cubecl kernels on wgpu (`dmtet_gpu::inclusive_scan`,
/// three launches) is the running sum, at block edges and past them; the compaction built on
/// it is covered by `marching_tets_on_the_gpu_gives_the_cpu_mesh`.
#[test]
fn the_gpu_prefix_sum_is_the_running_sum() {
    use getavatar_core::burn::tensor::Int;
    use getavatar_core::generator::dmtet_gpu::inclusive_scan;
    use getavatar_core::util::rng::Rng;
    let gpu = common::gpu();
    let mut rng = Rng::new(6, 0);
    for n in [1usize, 255, 256, 257, 513, 300_000] {
        let x: Vec<i64> = (0..n).map(|_| rng.below(2) as i64).collect();
        let t = Tensor::<1, Int>::from_data(TensorData::new(x.clone(), [n]), &gpu);
        let got: Vec<i64> = inclusive_scan(t).into_data().convert::<i64>().try_to_vec::<i64>().expect("ints");
        let want: Vec<i64> = x.iter().scan(0, |s, v| Some(*s + v).inspect(|t| *s = *t)).collect();
        assert_eq!(got, want, "n = {n}");
    }
}
