//! Generator geometry: DMTet on analytic shapes, template SDF, normal field, inverse skinning,
//! and "zero residual ⇒ the avatar is the posed body".

use getavatar_core::body::body_model::BodyModel;
use getavatar_core::body::pose_library::PoseLibrary;
use getavatar_core::body::skinning::{pose_body, vertex_normals};
use getavatar_core::geometry::inverse_skinning::{canonical_body, nearest_rotation};
use getavatar_core::geometry::spatial::KdTree;
use getavatar_core::geometry::template_sdf::central_difference_normal;
use getavatar_core::geometry::tet_grid::{REFERENCE_BOX_CENTER, REFERENCE_BOX_SIZE};
use getavatar_core::geometry::{marching_tets, InverseSkinning, TemplateSdf, TetGrid, TriMesh};
use glam::Vec3;

fn extract(grid: &TetGrid, f: impl Fn(Vec3) -> f32) -> TriMesh {
    let sdf: Vec<f32> = grid.vertices.iter().map(|p| f(*p)).collect();
    marching_tets(&grid.vertices, &grid.tets, &sdf, &grid.vertices)
}

fn face_normal(m: &TriMesh, f: &[u32; 3]) -> (Vec3, Vec3) {
    let [a, b, c] = f.map(|i| m.vertices[i as usize]);
    ((b - a).cross(c - a).normalize(), (a + b + c) / 3.0)
}

#[test]
fn dmtet_sphere_is_closed_outward_and_has_the_right_area() {
    let r = 0.7013;
    let grid = TetGrid::cube(40, Vec3::ZERO, 2.0);
    let m = extract(&grid, |p| p.length() - r);
    assert_eq!(m.topology_defects(), (0, 0), "sphere mesh must be a closed oriented manifold");
    let area = m.area();
    let want = 4.0 * std::f32::consts::PI * r * r;
    assert!((area / want - 1.0).abs() < 0.02, "area {area} vs {want}");
    assert!(m.volume() > 0.0);
    for f in &m.faces {
        let (n, c) = face_normal(&m, f);
        assert!(n.dot(c.normalize()) > 0.9, "inward face at {c}");
    }
    // A sphere through grid vertices (SDF exactly 0 there) still gives a closed, oriented mesh.
    let m = extract(&grid, |p| p.length() - 0.7);
    assert_eq!(m.topology_defects(), (0, 0));
    assert!((m.area() / (4.0 * std::f32::consts::PI * 0.49) - 1.0).abs() < 0.02);
    for v in &m.vertices {
        assert!((v.length() - r).abs() < 0.01, "vertex off the sphere: {}", v.length());
    }
    // Attributes are interpolated with the same weights as positions.
    for (v, a) in m.vertices.iter().zip(&m.attributes) {
        assert!((*v - *a).length() < 1e-5);
    }
}

#[test]
fn cavities_are_dropped_and_outer_surfaces_kept() {
    let grid = TetGrid::cube(40, Vec3::ZERO, 2.0);
    // A ball with a spherical pocket inside, and a small separate ball beside it.
    let shell = |p: Vec3| (p.length() - 0.5).max(0.25 - p.length());
    let small = |p: Vec3| (p - Vec3::new(0.75, 0.75, 0.0)).length() - 0.12;
    let all = extract(&grid, |p| shell(p).min(small(p)));
    let outer = extract(&grid, |p| (p.length() - 0.5).min(small(p)));
    let (ids, sizes) = all.components();
    assert_eq!(sizes.len(), 3, "outer sphere, pocket, small ball");
    assert_eq!(ids.len(), all.faces.len());
    assert_eq!(sizes.iter().sum::<usize>(), all.faces.len());
    let (kept, dropped) = all.without_cavities();
    assert_eq!(dropped, 1, "only the pocket goes");
    assert_eq!(kept.topology_defects(), (0, 0), "what is kept stays closed");
    assert_eq!((kept.faces.len(), kept.vertices.len()), (outer.faces.len(), outer.vertices.len()));
    assert!((kept.area() - outer.area()).abs() < 1e-4 * outer.area());
    assert!((kept.volume() - outer.volume()).abs() < 1e-4 * outer.volume());
    assert!(kept.vertices.iter().all(|v| v.length() > 0.4), "no pocket vertex remains");
    assert_eq!((kept.attributes.len(), kept.edges.len()), (kept.vertices.len(), kept.vertices.len()));
    for (v, a) in kept.vertices.iter().zip(&kept.attributes) {
        assert!((*v - *a).length() < 1e-5, "attributes follow their vertices");
    }
    // A mesh without pockets is returned as it is.
    let (same, none) = outer.clone().without_cavities();
    assert_eq!((none, same.faces, same.vertices), (0, outer.faces, outer.vertices));
}

#[test]
fn dmtet_box_has_flat_faces() {
    let half = Vec3::new(0.5, 0.3, 0.4);
    let box_sdf = |p: Vec3| {
        let q = p.abs() - half;
        q.max(Vec3::ZERO).length() + q.max_element().min(0.0)
    };
    let grid = TetGrid::cube(31, Vec3::new(0.013, -0.007, 0.004), 1.6);
    let h = grid.cell();
    let m = extract(&grid, box_sdf);
    assert_eq!(m.topology_defects(), (0, 0));
    let mut checked = 0;
    for f in &m.faces {
        let (n, c) = face_normal(&m, f);
        for axis in 0..3 {
            let others = [(axis + 1) % 3, (axis + 2) % 3];
            let away_from_edges = others.iter().all(|&o| c[o].abs() < half[o] - 2.0 * h);
            if (c[axis].abs() - half[axis]).abs() < h && away_from_edges {
                for &vi in f {
                    let v = m.vertices[vi as usize];
                    assert!((v[axis].abs() - half[axis]).abs() < 1e-5, "vertex {v} off the face plane");
                }
                assert!(n[axis] * c[axis].signum() > 0.9999, "face normal {n} not along axis {axis}");
                checked += 1;
            }
        }
    }
    assert!(checked > 500, "only {checked} face triangles checked");
}

#[test]
fn normal_field_matches_analytic_normals() {
    let sphere = |p: Vec3| p.length() - 0.5;
    for p in [Vec3::new(0.5, 0.0, 0.0), Vec3::new(0.1, 0.3, -0.38), Vec3::new(-0.2, -0.2, 0.41)] {
        let n = central_difference_normal(sphere, p, 1e-3);
        assert!(n.dot(p.normalize()) > 0.99999, "{n} vs {}", p.normalize());
    }
    // The template SDF of a sphere mesh gives sphere normals too.
    let grid = TetGrid::cube(40, Vec3::ZERO, 2.0);
    let m = extract(&grid, sphere);
    let t = TemplateSdf::from_mesh(&m.vertices, &m.faces, 64, Vec3::splat(-1.0), 2.0, 3);
    for p in [Vec3::new(0.5, 0.0, 0.0), Vec3::new(0.0, -0.5, 0.0), Vec3::new(0.3, 0.3, 0.3).normalize() * 0.5] {
        let n = t.normal(p, t.cell);
        assert!(n.dot(p.normalize()) > 0.995, "template normal {n} at {p}");
        assert!((t.sample(p)).abs() < t.cell, "sdf {} on the surface", t.sample(p));
    }
    // Beyond the narrow band (3 cells) the chamfer transform continues the distance: never
    // below the true distance at the surrounding grid points (up to half a cell diagonal
    // away), at most ~8 % above it.
    let slack = 3f32.sqrt() * t.cell / 2.0;
    let centre = t.sample(Vec3::ZERO);
    assert!(-centre > 0.5 - slack - 1e-3 && -centre < 0.5 * 1.09, "centre: {centre} vs −0.5");
    let far = t.sample(Vec3::new(0.95, 0.0, 0.0));
    assert!(far > 0.45 - slack - 1e-3 && far < 0.45 * 1.09, "far point: {far} vs 0.45");
    assert!(t.sample(Vec3::splat(0.9)) > 0.0);
    assert_eq!(t.sample(Vec3::splat(5.0)), 10.0, "outside the box is empty");
}

fn body() -> BodyModel {
    BodyModel::default_body().expect("body")
}

fn template(model: &BodyModel) -> TemplateSdf {
    let cano = canonical_body(model);
    let min = REFERENCE_BOX_CENTER - Vec3::splat(REFERENCE_BOX_SIZE / 2.0);
    TemplateSdf::from_mesh(&cano.vertices, &model.faces, 128, min, REFERENCE_BOX_SIZE, 3)
}

#[test]
fn body_template_sdf_has_correct_signs() {
    let model = body();
    let t = template(&model);
    let cano = canonical_body(&model);
    let j = cano.kinematics.posed_joints;
    for (k, name) in [(0, "pelvis"), (3, "spine1"), (15, "head"), (4, "left_knee"), (18, "left_elbow")] {
        assert!(t.sample(j[k]) < 0.0, "{name} joint should be inside: {}", t.sample(j[k]));
    }
    assert!(t.sample(Vec3::new(0.0, 0.6, 0.5)) > 0.0);
    // On the surface the SDF is ~0 and its gradient agrees with the mesh normal.
    let normals = vertex_normals(&cano.vertices, &model.faces);
    let mut agree = 0;
    for i in (0..cano.vertices.len()).step_by(97) {
        let p = cano.vertices[i];
        assert!(t.sample(p).abs() < 0.75 * t.cell, "vertex {i}: sdf {}", t.sample(p));
        if t.normal(p + normals[i] * 0.004, t.cell).dot(normals[i]) > 0.5 {
            agree += 1;
        }
    }
    assert!(agree as f32 > 0.85 * (cano.vertices.len() / 97) as f32, "only {agree} normals agree");
}

#[test]
fn inverse_skinning_round_trip() {
    let model = body();
    let lib = PoseLibrary::builtin();
    let cano = canonical_body(&model);
    let normals = vertex_normals(&cano.vertices, &model.faces);
    let mut betas = vec![0.0; model.num_betas];
    betas[1] = 0.8;
    betas[3] = -0.5;
    for pose in ["walking", "sitting", "arms_up"] {
        let params = lib.params(pose, &betas).expect("pose");
        let posed = pose_body(&model, &params);
        let inv = InverseSkinning::new(&model, &posed, &cano);
        // Un-warping inverts skinning exactly whenever the nearest posed vertex is the vertex
        // that skinned the point (K = 1); near joints a neighbour may be nearer, which moves
        // the point slightly. Check both: exactness, and how rare and small the exceptions are.
        let (mut worst_same, mut errors, mut same) = (0.0f32, Vec::new(), 0usize);
        for i in (0..cano.vertices.len()).step_by(13) {
            // A canonical point 2 mm outside vertex i, skinned forward with vertex i's transforms.
            let x_c = cano.vertices[i] + normals[i] * 0.002;
            let rest =
                cano.vertex_transforms[i].inverse().transform_point3(x_c) + (posed.shaped[i] - model.v_template[i]);
            let x_d = posed.vertex_transforms[i].transform_point3(rest);
            let (back, used) = inv.to_canonical(x_d);
            let err = (back - x_c).length();
            if used == i {
                same += 1;
                worst_same = worst_same.max(err);
            }
            errors.push(err);
            let n = inv.rotation(i) * normals[i];
            assert!((n.length() - 1.0).abs() < 1e-4, "rotated normal length {}", n.length());
        }
        errors.sort_by(f32::total_cmp);
        let (median, p99) = (errors[errors.len() / 2], errors[errors.len() * 99 / 100]);
        println!(
            "{pose}: same nearest vertex {same}/{}, worst exact {worst_same:.2e}, median {median:.2e}, p99 {p99:.2e}",
            errors.len()
        );
        assert!(worst_same < 1e-4, "{pose}: round trip through the same vertex is off by {worst_same} m");
        assert!(
            same as f32 > 0.95 * errors.len() as f32,
            "{pose}: nearest vertex changed for {} points",
            errors.len() - same
        );
        assert!(median < 1e-4 && p99 < 0.01, "{pose}: median {median}, p99 {p99}");
    }
}

#[test]
fn zero_residual_avatar_is_the_posed_body() {
    let model = body();
    let t = template(&model);
    let cano = canonical_body(&model);
    let lib = PoseLibrary::builtin();
    let grid = TetGrid::reference(48);
    let cell = grid.cell();
    for pose in ["Da", "standing", "walking", "one_leg"] {
        let posed = pose_body(&model, &lib.params(pose, &[]).expect("pose"));
        let inv = InverseSkinning::new(&model, &posed, &cano);
        let canon: Vec<Vec3> = grid.vertices.iter().map(|p| inv.to_canonical(*p).0).collect();
        let sdf: Vec<f32> = canon.iter().map(|p| t.sample(*p)).collect();
        let m = marching_tets(&grid.vertices, &grid.tets, &sdf, &canon);
        assert_eq!(m.topology_defects(), (0, 0), "{pose}: extracted avatar is not watertight");
        // Symmetric Hausdorff distance (vertex sets; the body is densely sampled).
        let body_tree = KdTree::new(&posed.vertices);
        let avatar_tree = KdTree::new(&m.vertices);
        let d_ab =
            m.vertices.iter().map(|v| body_tree.nearest(*v).map_or(f32::MAX, |x| x.1.sqrt())).fold(0.0, f32::max);
        // Fingers (thinner than a grid cell) cannot be resolved by any grid of this size:
        // the bound applies to the body without the hands; the hands get a looser bound.
        let fingers = |i: usize| model.weights[i][22] + model.weights[i][23] > 0.5;
        let d_ba = |keep: &dyn Fn(usize) -> bool| {
            posed
                .vertices
                .iter()
                .enumerate()
                .filter(|(i, _)| keep(*i))
                .map(|(_, v)| avatar_tree.nearest(*v).map_or(f32::MAX, |x| x.1.sqrt()))
                .fold(0.0, f32::max)
        };
        let hd = d_ab.max(d_ba(&|i| !fingers(i)));
        let hd_all = d_ab.max(d_ba(&|_| true));
        println!(
            "{pose}: {} vertices, Hausdorff {hd:.4} m ({:.2} cells) without fingers, {hd_all:.4} m with",
            m.vertices.len(),
            hd / cell
        );
        assert!(hd_all < 3.0 * cell, "{pose}: Hausdorff with fingers {hd_all} m ≥ 3 cells");
        assert!(hd < 1.5 * cell, "{pose}: Hausdorff {hd} m ≥ 1.5 cells ({cell} m)");
    }
}

/// The `demo` config's grids resolve the body: with a zero residual, the extracted avatar's
/// silhouette matches the posed body's (IoU at 256², front and side, three poses). Coarser
/// grids lose wrists, hands and feet (40 cells: IoU ≈ 0.80–0.85).
#[test]
fn demo_grid_resolves_the_posed_body() {
    use getavatar_core::generator::network::GeneratorConfig;
    use getavatar_core::render::camera::OrbitCamera;
    use getavatar_core::render::rasterize::render_views;
    let model = body();
    let cfg = GeneratorConfig::demo();
    let cano = canonical_body(&model);
    let min = REFERENCE_BOX_CENTER - Vec3::splat(REFERENCE_BOX_SIZE / 2.0);
    let t = TemplateSdf::from_mesh(&cano.vertices, &model.faces, cfg.template_res, min, REFERENCE_BOX_SIZE, 3);
    let grid = TetGrid::reference(cfg.tet_res);
    let mask = |v: &[Vec3], f: &[[u32; 3]], yaw: f32| -> Vec<bool> {
        let cam = OrbitCamera { yaw, ..Default::default() };
        let n = vertex_normals(v, f);
        let r = render_views(v, f, &n, &n, cam.projection_gl(1.0) * cam.world_to_camera(), 256, 2);
        r.mask.iter().map(|m| *m > 127).collect()
    };
    let lib = PoseLibrary::builtin();
    for pose in ["Da", "walking", "sitting", "arms_up"] {
        let posed = pose_body(&model, &lib.params(pose, &[]).expect("pose"));
        let inv = InverseSkinning::new(&model, &posed, &cano);
        let (canon, sdf): (Vec<Vec3>, Vec<f32>) =
            grid.vertices.iter().map(|p| inv.canonical_template(&t, *p)).map(|(c, s, _)| (c, s)).unzip();
        let m = marching_tets(&grid.vertices, &grid.tets, &sdf, &canon);
        // No floating fragments (K = 1 un-warping of space the pose vacated): every extracted
        // vertex lies near the posed body.
        let body_tree = KdTree::new(&posed.vertices);
        let far = m.vertices.iter().map(|v| body_tree.nearest(*v).map_or(f32::MAX, |x| x.1.sqrt())).fold(0.0, f32::max);
        println!("{pose}: farthest extracted vertex {far:.3} m from the posed body");
        assert!(far < 0.1, "{pose}: extracted surface reaches {far} m away from the body");
        for yaw in [0.0f32, std::f32::consts::FRAC_PI_2] {
            let (a, b) = (mask(&m.vertices, &m.faces, yaw), mask(&posed.vertices, &model.faces, yaw));
            let inter = a.iter().zip(&b).filter(|(x, y)| **x && **y).count();
            let union = a.iter().zip(&b).filter(|(x, y)| **x || **y).count();
            let iou = inter as f32 / union as f32;
            println!("{pose}, yaw {yaw:.2}: silhouette IoU {iou:.3}");
            assert!(iou > 0.88, "{pose}, yaw {yaw}: silhouette IoU {iou} of the zero-residual demo avatar");
        }
    }
}

/// Space a pose vacates (where the canonical arms were, in arms_up) un-warps into another body
/// part; the guard gives it the posed-space distance, and the generator's residual is not
/// evaluated there (`field_band` leaves it out), so a learned negative residual (clothing)
/// cannot turn it inside and leave floating fragments. The Da-pose vacates nothing.
#[test]
fn the_residual_is_not_evaluated_in_space_the_pose_vacated() {
    use getavatar_core::generator::network::GeneratorConfig;
    use getavatar_core::geometry::posed_grid::{field_band, BodyContext};
    // The demo grid (3.6 cm cells); vacated space near the body needs cells this fine.
    let ctx = BodyContext::new(body(), &GeneratorConfig { tet_res: 64, template_res: 128, ..GeneratorConfig::tiny() });
    let lib = PoseLibrary::builtin();
    for (pose, expect_vacated) in [("Da", false), ("arms_up", true), ("walking", true), ("sitting", true)] {
        let posed = pose_body(&ctx.model, &lib.params(pose, &[]).expect("pose"));
        let inv = InverseSkinning::new(&ctx.model, &posed, &ctx.canonical);
        let mapped: Vec<(Vec3, f32, bool)> =
            ctx.grid.vertices.iter().map(|p| inv.canonical_template(&ctx.template, *p)).collect();
        let template: Vec<f32> = mapped.iter().map(|m| m.1).collect();
        let guarded: Vec<bool> = mapped.iter().map(|m| m.2).collect();
        let vacated: Vec<usize> = (0..guarded.len()).filter(|&i| guarded[i]).collect();
        println!("{pose}: {} guarded grid vertices", vacated.len());
        assert_eq!(!vacated.is_empty(), expect_vacated, "{pose}: {} guarded vertices", vacated.len());
        // Guarded vertices are outside the posed body, by their distance to it.
        let body_tree = KdTree::new(&posed.vertices);
        for &i in &vacated {
            let d = body_tree.nearest(ctx.grid.vertices[i]).map_or(f32::MAX, |x| x.1.sqrt());
            assert!(template[i] > 0.0 && (template[i] - d).abs() < 1e-4, "{pose}: vertex {i}");
        }
        let band = field_band(&ctx, &template, &guarded);
        assert!(band.iter().all(|&i| !guarded[i as usize]), "{pose}: a guarded vertex is in the band");
        // Without the guard flags the band would include vacated vertices near the body.
        let unguarded = field_band(&ctx, &template, &[]);
        let near = unguarded.iter().filter(|&&i| guarded[i as usize]).count();
        println!("{pose}: {near} of {} band vertices guarded", unguarded.len());
        assert_eq!(unguarded.iter().any(|&i| guarded[i as usize]), expect_vacated, "{pose}");
    }
}

/// Grid vertices far from the posed body are not un-warped (`generator::far_from_body`): the
/// band where the fields are evaluated, its values, every vertex's sign and the extracted
/// surface are those of un-warping every vertex.
#[test]
fn skipping_far_grid_vertices_keeps_the_band_and_the_surface() {
    use getavatar_core::generator::network::GeneratorConfig;
    use getavatar_core::geometry::posed_grid::{far_from_body, BodyContext, PosedGrid};
    let model = body();
    let lib = PoseLibrary::builtin();
    for cfg in [GeneratorConfig::demo(), GeneratorConfig::tiny()] {
        let ctx = BodyContext::new(model.clone(), &cfg);
        let far = far_from_body(&ctx);
        for pose in ["Da", "sitting", "arms_up"] {
            let posed = pose_body(&model, &lib.params(pose, &[]).expect("pose"));
            let inv = InverseSkinning::new(&model, &posed, &ctx.canonical);
            let (fast, all) = (PosedGrid::new(&ctx, &inv), PosedGrid::with_far(&ctx, &inv, f32::INFINITY));
            assert_eq!(fast.band, all.band, "{pose}: band");
            for &i in &fast.band {
                let i = i as usize;
                assert_eq!(
                    (fast.canonical[i], fast.template[i]),
                    (all.canonical[i], all.template[i]),
                    "{pose}: vertex {i}"
                );
            }
            let skipped = fast.template.iter().filter(|&&t| t == far).count();
            assert!(skipped > fast.template.len() / 4, "{pose}: only {skipped} far vertices skipped");
            for (i, (a, b)) in fast.template.iter().zip(&all.template).enumerate() {
                assert_eq!(*a < 0.0, *b < 0.0, "{pose}: sign of vertex {i}: {a} vs {b}");
            }
            let mesh = |g: &PosedGrid| marching_tets(&ctx.grid.vertices, &ctx.grid.tets, &g.template, &g.canonical);
            let (m1, m2) = (mesh(&fast), mesh(&all));
            assert!(m1.faces.len() > 200, "{pose}: {} faces", m1.faces.len());
            assert_eq!(
                (m1.vertices, m1.faces, m1.attributes),
                (m2.vertices, m2.faces, m2.attributes),
                "{pose}: surface"
            );
        }
    }
}

/// Eq. 4's rotation: Higham's iteration (`nearest_rotation`, glam, runs in the browser) equals
/// the orthogonal polar factor U·Vᵀ of an SVD (nalgebra) on blended LBS transforms (weighted
/// means of two rotations, some scaled) and on general matrices with positive determinant.
#[test]
fn nearest_rotation_is_the_polar_factor_of_the_svd() {
    use glam::{Mat3, Quat};
    let mut rng = getavatar_core::util::rng::Rng::new(7, 3);
    let mut worst = 0.0f32;
    for case in 0..200 {
        let mut axis = || Vec3::new(rng.normal(), rng.normal(), rng.normal()).normalize_or(Vec3::Y);
        let (a1, a2) = (axis(), axis());
        let (t1, t2) = (rng.uniform() * 3.0, rng.uniform() * 3.0);
        let w = rng.uniform();
        let m = if case % 2 == 0 {
            let s = 0.8 + 0.4 * rng.uniform();
            (Mat3::from_quat(Quat::from_axis_angle(a1, t1)) * w
                + Mat3::from_quat(Quat::from_axis_angle(a2, t2)) * (1.0 - w))
                * s
        } else {
            Mat3::from_cols_array(&std::array::from_fn(|_| rng.normal()))
        };
        if m.determinant() < 0.05 {
            continue;
        }
        let r = nearest_rotation(m);
        let n = nalgebra::Matrix3::from_column_slice(&m.to_cols_array().map(f64::from));
        let svd = n.svd(true, true);
        let (u, v_t) = (svd.u.unwrap(), svd.v_t.unwrap());
        let polar = u * v_t;
        let expected = Mat3::from_cols_array(&std::array::from_fn(|i| polar.as_slice()[i] as f32));
        let err = (r - expected).to_cols_array().iter().map(|x| x.abs()).fold(0.0, f32::max);
        worst = worst.max(err);
        assert!((r.determinant() - 1.0).abs() < 1e-4, "case {case}: det {}", r.determinant());
    }
    assert!(worst < 1e-4, "largest entry difference from the SVD's polar factor: {worst}");
}
