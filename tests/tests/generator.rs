//! Generator inference end to end on NdArray (tiny config): determinism, texture/geometry
//! separation, watertight output, the normal field, and zero residual ⇒ the posed body.

use getavatar_core::body::body_model::BodyModel;
use getavatar_core::body::pose_library::PoseLibrary;
use getavatar_core::body::skinning::{pose_body, vertex_normals};
use getavatar_core::burn::module::Param;
use getavatar_core::burn::tensor::{Device, Tensor};
use getavatar_core::generator::network::GeneratorConfig;
use getavatar_core::generator::pipeline::{generate_avatar, seed_latents, Avatar, BodyContext, Generator};
use getavatar_core::generator::readback::block_on_ready;
use getavatar_core::generator::rigging::generate_rigged_async;
use getavatar_core::geometry::spatial::KdTree;
use glam::Vec3;

#[allow(deprecated)]
fn device() -> Device {
    Device::ndarray()
}

fn generate(g: &Generator, ctx: &BodyContext, cfg: &GeneratorConfig, seeds: (u64, u64), pose: &str) -> Avatar {
    let dev = device();
    let (zg, zt) = seed_latents(cfg, seeds.0, seeds.1, &dev);
    let s = g.styles(zg, zt, 0.7);
    let params = PoseLibrary::builtin().params(pose, &[]).expect("pose");
    generate_avatar(g, ctx, &s, &params, &dev).expect("generation reads back")
}

/// The checkpoint names of `g`'s parameters that start with `prefix`.
fn param_names_under(g: &Generator, prefix: &str) -> Vec<String> {
    let all = getavatar_core::generator::checkpoint::collect_params(g).expect("parameters read back");
    all.into_iter().map(|(n, _, _)| n).filter(|n| n.starts_with(prefix)).collect()
}

/// The tiny generator (weights of seed 0) on the default body, on the test device, and the
/// styles of latent seeds `seeds` at ψ = 0.7.
fn tiny_identity(seeds: (u64, u64)) -> (BodyContext, Device, Generator, getavatar_core::generator::pipeline::Styles) {
    identity(&GeneratorConfig::tiny(), seeds)
}

/// [`tiny_identity`] of another generator config.
fn identity(
    cfg: &GeneratorConfig,
    seeds: (u64, u64),
) -> (BodyContext, Device, Generator, getavatar_core::generator::pipeline::Styles) {
    let ctx = BodyContext::new(BodyModel::default_body().expect("body"), cfg);
    let dev = device();
    let g = Generator::new(cfg, 0, &dev);
    let (zg, zt) = seed_latents(cfg, seeds.0, seeds.1, &dev);
    let s = g.styles(zg, zt, 0.7);
    (ctx, dev, g, s)
}

#[test]
fn texture_seed_changes_colours_not_geometry_and_generation_is_deterministic() {
    let cfg = GeneratorConfig::tiny();
    let ctx = BodyContext::new(BodyModel::default_body().expect("body"), &cfg);
    let g = Generator::new(&cfg, 0, &device());
    let a = generate(&g, &ctx, &cfg, (1, 2), "standing");
    let b = generate(&g, &ctx, &cfg, (1, 3), "standing");
    let a2 = generate(&g, &ctx, &cfg, (1, 2), "standing");
    assert!(a.mesh.vertices.len() > 500, "{} vertices", a.mesh.vertices.len());
    assert_eq!(a.mesh.vertices, a2.mesh.vertices);
    assert_eq!(a.colors, a2.colors);
    assert_eq!(a.mesh.vertices, b.mesh.vertices, "texture seed must not change geometry");
    assert_eq!(a.mesh.faces, b.mesh.faces);
    let diff: f32 =
        a.colors.iter().zip(&b.colors).map(|(x, y)| (*x - *y).abs().element_sum()).sum::<f32>() / a.colors.len() as f32;
    assert!(diff > 0.01, "texture seed changed colours by only {diff}");
    let c = generate(&g, &ctx, &cfg, (5, 2), "standing");
    assert_ne!(a.mesh.vertices, c.mesh.vertices, "geometry seed must change geometry");
    for col in &a.colors {
        assert!(col.min_element() >= 0.0 && col.max_element() <= 1.0);
    }
}

#[test]
fn untrained_avatar_is_watertight_body_shaped_with_a_consistent_normal_field() {
    // A grid fine enough (5.7 cm) to keep limbs.
    let cfg = GeneratorConfig { tet_res: 40, template_res: 96, ..GeneratorConfig::tiny() };
    let model = BodyModel::default_body().expect("body");
    let posed = pose_body(&model, &PoseLibrary::builtin().params("walking", &[]).expect("pose"));
    let ctx = BodyContext::new(model, &cfg);
    let g = Generator::new(&cfg, 0, &device());
    let a = generate(&g, &ctx, &cfg, (7, 8), "walking");
    assert_eq!(a.mesh.topology_defects(), (0, 0));
    let bbox = |v: &[Vec3]| v.iter().fold((Vec3::MAX, Vec3::MIN), |(l, h), p| (l.min(*p), h.max(*p)));
    let (al, ah) = bbox(&a.mesh.vertices);
    let (bl, bh) = bbox(&posed.vertices);
    let cell = ctx.grid.cell();
    assert!(
        (al - bl).abs().max_element() < 2.0 * cell && (ah - bh).abs().max_element() < 2.0 * cell,
        "avatar bbox {al}..{ah} vs body {bl}..{bh}"
    );
    // The normal field (∇SDF rotated by skinning) agrees with the extracted surface.
    let geo = vertex_normals(&a.mesh.vertices, &a.mesh.faces);
    let mean_dot = a.normals.iter().zip(&geo).map(|(n, m)| n.dot(*m)).sum::<f32>() / geo.len() as f32;
    assert!(mean_dot > 0.75, "normal field vs mesh normals: mean cosine {mean_dot}");
    assert!(a.normals.iter().all(|n| (n.length() - 1.0).abs() < 1e-3));
}

#[test]
fn zero_residual_generator_reproduces_the_posed_body() {
    let cfg = GeneratorConfig { tet_res: 40, template_res: 128, ..GeneratorConfig::tiny() };
    let model = BodyModel::default_body().expect("body");
    let ctx = BodyContext::new(model.clone(), &cfg);
    let dev = device();
    let mut g = Generator::new(&cfg, 0, &dev);
    for d in [&mut g.decoders.sdf, &mut g.decoders.offset] {
        d.out.weight = Param::from_tensor(d.out.weight.val() * 0.0);
        d.out.bias = Param::from_tensor(Tensor::zeros(d.out.bias.dims(), &dev));
    }
    for pose in ["Da", "sitting"] {
        let a = generate(&g, &ctx, &cfg, (3, 4), pose);
        let posed = pose_body(&model, &PoseLibrary::builtin().params(pose, &[]).expect("pose"));
        let body = KdTree::new(&posed.vertices);
        let avatar = KdTree::new(&a.mesh.vertices);
        // Hands (palms ~2.5 cm, fingers ~1.5 cm thick) are thinner than a cell of this grid
        // (5.7 cm) and cannot be resolved; the bound applies to the rest of the body.
        let d_ab =
            a.mesh.vertices.iter().map(|v| body.nearest(*v).map_or(f32::MAX, |x| x.1.sqrt())).fold(0.0, f32::max);
        let d_ba = posed
            .vertices
            .iter()
            .enumerate()
            .filter(|(i, _)| model.weights[*i][20..24].iter().sum::<f32>() < 0.5)
            .map(|(_, v)| avatar.nearest(*v).map_or(f32::MAX, |x| x.1.sqrt()))
            .fold(0.0, f32::max);
        let cell = ctx.grid.cell();
        let worst =
            a.mesh.vertices.iter().max_by(|p, q| {
                body.nearest(**p).map_or(0.0, |x| x.1).total_cmp(&body.nearest(**q).map_or(0.0, |x| x.1))
            });
        println!(
            "{pose}: Hausdorff {:.4} m = {:.2} cells (avatar→body {d_ab:.4} at {worst:?}, body→avatar {d_ba:.4})",
            d_ab.max(d_ba),
            d_ab.max(d_ba) / cell
        );
        assert!(d_ab.max(d_ba) < 1.5 * cell, "{pose}: Hausdorff {} ≥ 1.5 cells", d_ab.max(d_ba));
    }
}

#[test]
fn config_presets_are_valid() {
    for name in ["paper", "demo", "tiny"] {
        let c = GeneratorConfig::preset(name).expect("preset");
        c.validate().expect("valid");
        assert_eq!(*c.block_resolutions().last().expect("blocks"), c.plane_res);
    }
    let bad = GeneratorConfig { plane_res: 48, ..GeneratorConfig::tiny() };
    assert!(bad.validate().unwrap_err().contains("plane_res"));
    assert!(GeneratorConfig::preset("huge").is_none());
}

#[test]
fn fast_repose_path_matches_the_exact_path() {
    let cfg = GeneratorConfig { tet_res: 40, template_res: 96, ..GeneratorConfig::tiny() };
    let (ctx, dev, g, s) = identity(&cfg, (11, 12));
    let model = &ctx.model;
    let rigged = block_on_ready(generate_rigged_async(&g, &ctx, &s, &dev)).expect("generation reads back");
    // Re-posing to the canonical pose is the identity.
    let cano = pose_body(model, &PoseLibrary::builtin().params("Da", &[]).expect("pose"));
    let (v, n) = rigged.repose(&ctx, &cano);
    for (a, b) in v.iter().zip(&rigged.canonical.mesh.vertices) {
        assert!((*a - *b).length() < 1e-4);
    }
    assert!(n.iter().all(|x| (x.length() - 1.0).abs() < 1e-3));
    // In another pose, the LBS-reposed avatar is close to the exact posed-space extraction.
    let params = PoseLibrary::builtin().params("standing", &[]).expect("pose");
    let posed = pose_body(model, &params);
    let (v, _) = rigged.repose(&ctx, &posed);
    let exact = generate_avatar(&g, &ctx, &s, &params, &dev).expect("generation reads back");
    let (ta, tb) = (KdTree::new(&v), KdTree::new(&exact.mesh.vertices));
    let d1 = v.iter().map(|p| tb.nearest(*p).map_or(f32::MAX, |x| x.1.sqrt())).fold(0.0, f32::max);
    let d2 = exact.mesh.vertices.iter().map(|p| ta.nearest(*p).map_or(f32::MAX, |x| x.1.sqrt())).fold(0.0, f32::max);
    let cell = ctx.grid.cell();
    println!("fast vs exact: Hausdorff {:.4} m = {:.2} cells", d1.max(d2), d1.max(d2) / cell);
    assert!(d1.max(d2) < 2.0 * cell, "fast and exact paths differ by {} m", d1.max(d2));

    // A bind pose kept ahead is the one computed on demand, at its shape only.
    let (betas, other) = ([1.0, -0.5, 0.3], [0.0, 2.0]);
    let mut kept = rigged.clone();
    block_on_ready(kept.keep_bind_pose_async(&ctx, &betas));
    let rest = |b: &[f32]| {
        let p = getavatar_core::body::skinning::BodyParams { betas: b.to_vec(), ..Default::default() };
        rigged.repose(&ctx, &pose_body(model, &p))
    };
    assert_eq!(kept.bind_pose(&ctx, &betas), rest(&betas));
    assert_eq!(kept.bind_pose(&ctx, &other), rest(&other));
    assert_ne!(rest(&betas).0, rest(&other).0, "the shapes differ, so the check can fail");
}

/// A new identity is generated in the canonical pose with the inverse skinning and grid kept
/// in the `BodyContext` and no rotation of the normal field (host time). The general
/// path, taken here by moving the body 1 µm, gives the same mesh, normals and colours.
#[test]
fn the_canonical_shortcut_matches_the_general_path() {
    let (ctx, dev, g, s) = tiny_identity((5, 6));
    let params = PoseLibrary::builtin().params("Da", &[]).expect("pose");
    let fast = generate_avatar(&g, &ctx, &s, &params, &dev).expect("generation reads back");
    let moved = getavatar_core::body::skinning::BodyParams { transl: Vec3::new(0.0, 1e-6, 0.0), ..params };
    let general = generate_avatar(&g, &ctx, &s, &moved, &dev).expect("generation reads back");
    assert!(!fast.mesh.vertices.is_empty());
    assert_eq!(
        (fast.mesh.vertices.len(), fast.mesh.faces.len()),
        (general.mesh.vertices.len(), general.mesh.faces.len())
    );
    let worst = |a: &[Vec3], b: &[Vec3], shift: Vec3| {
        a.iter().zip(b).map(|(x, y)| (*x + shift - *y).length()).fold(0.0, f32::max)
    };
    let dv = worst(&fast.mesh.vertices, &general.mesh.vertices, moved.transl);
    let dn = worst(&fast.normals, &general.normals, Vec3::ZERO);
    let dc = worst(&fast.colors, &general.colors, Vec3::ZERO);
    // The 1 µm move changes the SDF a little where it is nearly flat along an edge: 0.05 mm.
    assert!(dv < 1e-4 && dn < 1e-3 && dc < 1e-4, "vertices {dv}, normals {dn}, colours {dc}");
    // What the shortcut assumes: the canonical body's own inverse skinning rotates nothing.
    let inv = ctx.canonical_inverse();
    let worst_rotation = (0..ctx.model.v_template.len())
        .map(|i| (inv.rotation(i) - glam::Mat3::IDENTITY).to_cols_array().iter().fold(0.0f32, |m, x| m.max(x.abs())))
        .fold(0.0, f32::max);
    assert!(worst_rotation < 1e-5, "{worst_rotation}");
}

/// A new identity (canonical generation and rigging) reads back from the device
/// twice: the geometry fields of the grid's band, then the mesh vertices' normals and colours
/// together. The stage profile counts every read-back (`readback::read_f32`).
#[test]
fn a_new_identity_reads_back_from_the_device_twice() {
    use getavatar_core::util::profile;
    let (ctx, dev, g, s) = tiny_identity((1, 2));
    static T0: std::sync::OnceLock<std::time::Instant> = std::sync::OnceLock::new();
    profile::start(|| T0.get_or_init(std::time::Instant::now).elapsed().as_secs_f64() * 1000.0);
    let rigged = block_on_ready(generate_rigged_async(&g, &ctx, &s, &dev)).expect("generation reads back");
    let stages = profile::finish().expect("recorded");
    let names: Vec<&str> = stages.stages.iter().map(|s| s.stage.as_str()).collect();
    assert_eq!(names, ["synthesis", "posed grid", "grid decode", "DMTet", "normals & colours", "rigging"]);
    let per_stage: Vec<u32> = stages.stages.iter().map(|s| s.readbacks).collect();
    assert_eq!(per_stage, [0, 0, 1, 0, 1, 0], "{stages:?}");
    assert!(rigged.canonical.mesh.vertices.len() > 500);
    // The folded read-back gives each vertex its own colour and normal.
    let colors = block_on_ready(getavatar_core::generator::pipeline::recolor_async(
        &g,
        &g.triplanes(&s),
        &s,
        &rigged.canonical.mesh.attributes,
        &dev,
    ))
    .expect("colours read back");
    assert_eq!(colors, rigged.canonical.colors);
    assert!(rigged.canonical.normals.iter().all(|n| (n.length() - 1.0).abs() < 1e-4));
}

/// The geometry alone (the garment codes' outline check), with its vertices' fields added
/// after, is the avatar a whole generation gives: the same mesh, normals and colours, and no
/// field of the vertices is read back before they are asked for.
#[test]
fn the_geometry_first_and_its_fields_after_are_the_whole_generation() {
    use getavatar_core::generator::pipeline::canonical_geometry_async;
    use getavatar_core::util::profile;
    let (ctx, dev, g, s) = tiny_identity((3, 4));
    let whole = block_on_ready(generate_rigged_async(&g, &ctx, &s, &dev)).expect("generation reads back");
    static T0: std::sync::OnceLock<std::time::Instant> = std::sync::OnceLock::new();
    profile::start(|| T0.get_or_init(std::time::Instant::now).elapsed().as_secs_f64() * 1000.0);
    let geometry = block_on_ready(canonical_geometry_async(&g, &ctx, &s, &dev)).expect("geometry reads back");
    let stages = profile::finish().expect("recorded");
    let names: Vec<&str> = stages.stages.iter().map(|s| s.stage.as_str()).collect();
    assert_eq!(names, ["synthesis", "posed grid", "grid decode", "DMTet"], "{stages:?}");
    assert_eq!(stages.stages.iter().map(|s| s.readbacks).sum::<u32>(), 1, "{stages:?}");
    assert_eq!(geometry.mesh.vertices, whole.canonical.mesh.vertices);
    assert_eq!(geometry.mesh.faces, whole.canonical.mesh.faces);
    assert_eq!(geometry.mesh.attributes, whole.canonical.mesh.attributes);
    let (normals, colors) = block_on_ready(geometry.vertex_fields_async(&g, &ctx, &s, &dev)).expect("fields read back");
    assert_eq!(normals, whole.canonical.normals);
    assert_eq!(colors, whole.canonical.colors);
    // The geometry planes alone, with texture and geometry detail blocks, are the whole
    // synthesis's geometry planes.
    let cfg = GeneratorConfig { texture_res: Some(32), ..GeneratorConfig::tiny() };
    let cfg = GeneratorConfig { geometry_res: Some(2 * cfg.plane_res), ..cfg };
    let g = Generator::new(&cfg, 7, &dev);
    let (zg, zt) = seed_latents(&cfg, 1, 2, &dev);
    let s = g.styles(zg, zt, 0.7);
    let vec = |t: Tensor<4>| t.into_data().try_to_vec::<f32>().expect("f32");
    let alone = block_on_ready(g.geometry_planes_async(&s));
    assert_eq!(alone.dims(), [1, 3 * cfg.plane_channels, 2 * cfg.plane_res, 2 * cfg.plane_res]);
    assert_eq!(vec(alone), vec(g.triplanes(&s).geometry));
}

/// A rigged avatar as flat arrays (the browser worker hands its result to the page so) comes
/// back the same, re-poses the same, and broken arrays are refused with the reason.
#[test]
fn a_rigged_avatar_round_trips_through_flat_arrays_and_broken_ones_are_refused() {
    use getavatar_core::body::skinning::{pose_body, BodyParams};
    use getavatar_core::generator::rigging::{RiggedArraysError, RiggedAvatar};
    let (ctx, dev, g, s) = tiny_identity((3, 4));
    let rigged = block_on_ready(generate_rigged_async(&g, &ctx, &s, &dev)).expect("generation reads back");
    let arrays = rigged.to_arrays();
    let n = rigged.canonical.mesh.vertices.len();
    assert_eq!((arrays.positions.len(), arrays.faces.len()), (3 * n, 3 * rigged.canonical.mesh.faces.len()));
    let back = RiggedAvatar::from_arrays(arrays.clone(), &ctx).expect("valid arrays");
    assert_eq!(back.canonical.mesh.vertices, rigged.canonical.mesh.vertices);
    assert_eq!(back.canonical.mesh.faces, rigged.canonical.mesh.faces);
    assert_eq!(back.canonical.mesh.attributes, rigged.canonical.mesh.attributes);
    assert_eq!(back.canonical.mesh.edges, rigged.canonical.mesh.edges);
    assert_eq!(
        (&back.canonical.normals, &back.canonical.colors),
        (&rigged.canonical.normals, &rigged.canonical.colors)
    );
    assert_eq!(back.body_vertex, rigged.body_vertex);
    let mut params = BodyParams::default();
    params.pose[16] = glam::Vec3::new(0.0, 0.0, -1.0);
    let posed = pose_body(&ctx.model, &params);
    assert_eq!(back.repose(&ctx, &posed), rigged.repose(&ctx, &posed));

    let nb = ctx.model.num_vertices();
    let broken = |f: &dyn Fn(&mut getavatar_core::generator::rigging::RiggedArrays)| {
        let mut a = arrays.clone();
        f(&mut a);
        RiggedAvatar::from_arrays(a, &ctx).err()
    };
    assert_eq!(broken(&|a| a.faces[4] = n as u32), Some(RiggedArraysError::Face(n as u32, n)));
    assert_eq!(broken(&|a| a.body_vertex[0] = nb as u32), Some(RiggedArraysError::BodyVertex(nb as u32, nb)));
    assert_eq!(
        broken(&|a| {
            a.colors.pop();
        }),
        Some(RiggedArraysError::Length("colors", 3 * n - 1, 3 * n))
    );
    assert_eq!(broken(&|a| a.normals[7] = f32::NAN), Some(RiggedArraysError::NonFinite("normals")));
    assert_eq!(
        broken(&|a| {
            a.body_vertex.pop();
        }),
        Some(RiggedArraysError::Length("body_vertex", n - 1, n))
    );
    assert_eq!(
        broken(&|a| {
            a.edge_t.pop();
        }),
        Some(RiggedArraysError::Length("edge_t", n - 1, n))
    );
    assert_eq!(broken(&|a| a.faces.clear()), Some(RiggedArraysError::Empty));
    assert!(broken(&|a| {
        a.faces.pop();
    })
    .is_some());
    // Without edges and attributes (a mesh that has none) the arrays are still an avatar.
    let bare = broken(&|a| {
        a.edge_a.clear();
        a.edge_b.clear();
        a.edge_t.clear();
        a.attributes.clear();
    });
    assert_eq!(bare, None);
}

#[test]
fn checkpoints_round_trip_and_reject_other_configs() {
    use getavatar_core::generator::checkpoint::{load_generator, parse_safetensors, save_generator};
    let cfg = GeneratorConfig::tiny();
    let dev = device();
    let g = Generator::new(&cfg, 42, &dev);
    let mut extra = std::collections::BTreeMap::new();
    extra.insert("kimg".to_string(), "1.5".to_string());
    let bytes = save_generator(&g, &cfg, &extra).unwrap();
    let st = parse_safetensors(&bytes).expect("parses");
    assert_eq!(st.metadata.get("kimg").map(String::as_str), Some("1.5"));
    assert!(
        st.tensors.keys().any(|k| k.contains("synthesis")),
        "names: {:?}",
        st.tensors.keys().take(5).collect::<Vec<_>>()
    );
    let back = load_generator(&bytes, &cfg, &dev).expect("loads");
    // Same weights ⇒ same triplanes.
    let (zg, zt) = seed_latents(&cfg, 1, 2, &dev);
    let (a, b) = (g.triplanes(&g.styles(zg.clone(), zt.clone(), 0.7)), back.triplanes(&back.styles(zg, zt, 0.7)));
    let (va, vb) = (
        a.geometry.into_data().try_to_vec::<f32>().expect("f32"),
        b.geometry.into_data().try_to_vec::<f32>().expect("f32"),
    );
    assert_eq!(va, vb);
    // Another config is refused with a message naming the differing fields.
    let e = load_generator(&bytes, &GeneratorConfig::demo(), &dev).expect_err("mismatch").to_string();
    assert!(e.contains("tiny") && e.contains("demo") && e.contains("z_dim"), "{e}");
    // Corrupt files are errors.
    assert!(load_generator(&bytes[..bytes.len() / 2], &cfg, &dev).is_err());
    assert!(load_generator(b"junk", &cfg, &dev).is_err());
}

/// Multi-modal truncation: each w moves towards its nearest mode by 1 − ψ, the texture code
/// towards the mode of the subject chosen by the geometry code; the modes travel in the
/// checkpoint and old checkpoints have none.
#[test]
fn latent_modes_truncate_towards_the_nearest_mode_and_round_trip() {
    use getavatar_core::burn::tensor::TensorData;
    use getavatar_core::generator::checkpoint::{
        load_generator, load_generator_and_modes, load_latent_modes, save_generator, save_generator_with_modes,
    };
    use getavatar_core::generator::network::mapping::{truncate_toward_modes, truncate_toward_subject};
    use getavatar_core::generator::pipeline::{LatentModes, ModePairing};
    let dev = device();
    let t2 = |v: Vec<f32>, r: usize| Tensor::<2>::from_data(TensorData::new(v, [r, 2]), &dev);
    let vals = |t: Tensor<2>| t.into_data().try_to_vec::<f32>().expect("f32");
    // Modes at (0, 0), (10, 0), (0, 10); w near the second, then the third.
    let modes = t2(vec![0.0, 0.0, 10.0, 0.0, 0.0, 10.0], 3);
    let w = t2(vec![8.0, 2.0, 1.0, 7.0], 2);
    let got = vals(truncate_toward_modes(w.clone(), &modes, 0.5));
    let want = [9.0, 1.0, 0.5, 8.5];
    assert!(got.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-5), "{got:?}");
    assert_eq!(vals(truncate_toward_modes(w.clone(), &modes, 1.0)), vals(w));
    // Generation pairs the branches: the subject is the one whose geometry mode is nearest
    // to w_geo, and w_tex moves towards *that* subject's texture mode, even where another
    // texture mode is nearer (which would pair codes of two subjects).
    let (geo_modes, tex_modes) = (t2(vec![0.0, 0.0, 10.0, 0.0], 2), t2(vec![0.0, 0.0, 10.0, 0.0], 2));
    let (wg, wt) = (t2(vec![9.0, 1.0], 1), t2(vec![1.0, 1.0], 1));
    let pair = |psi: f32| {
        let (g, t) = truncate_toward_subject(wg.clone(), wt.clone(), &geo_modes, &tex_modes, psi);
        (vals(g), vals(t))
    };
    assert_eq!(pair(0.0), (vec![10.0, 0.0], vec![10.0, 0.0]));
    let (g, t) = pair(0.5);
    let close = |a: &[f32], b: [f32; 2]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-5);
    assert!(close(&g, [9.5, 0.5]) && close(&t, [5.5, 0.5]), "{g:?} {t:?}");
    assert_eq!(pair(1.0), (vals(wg.clone()), vals(wt.clone())));

    let cfg = GeneratorConfig::tiny();
    let g = Generator::new(&cfg, 7, &dev);
    let extra = std::collections::BTreeMap::new();
    let plain = save_generator(&g, &cfg, &extra).unwrap();
    assert!(load_latent_modes(&plain, &dev).expect("parses").is_none());
    let (zg, zt) = seed_latents(&cfg, 3, 4, &dev);
    let m = LatentModes {
        geo: g.mapping_geo.forward(zg.clone()),
        tex: g.mapping_tex.forward(zt.clone()),
        tex_layers: None,
        pairing: ModePairing::Subject,
    };
    let bytes = save_generator_with_modes(&g, &cfg, Some(&m), &extra).unwrap();
    let back = load_generator(&bytes, &cfg, &dev).expect("a checkpoint with modes loads");
    let m2 = load_latent_modes(&bytes, &dev).expect("parses").expect("modes present");
    assert_eq!(m2.count(), 1);
    assert_eq!(vals(m2.geo.clone()), vals(m.geo.clone()));
    // A latent that is itself a mode is a fixed point of any ψ; another is not.
    let at = |z: Tensor<2>, psi: f32| {
        vals(back.styles_with(z, zt.clone(), psi, Some(&m2)).geo.narrow(1, 0, 1).reshape([1, cfg.w_dim]))
    };
    let (a, b) = (at(zg.clone(), 0.0), at(zg, 1.0));
    assert!(a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-4));
    let (zo, _) = seed_latents(&cfg, 99, 4, &dev);
    let (c, d) = (at(zo.clone(), 0.0), at(zo, 1.0));
    assert!(c.iter().zip(&a).all(|(x, y)| (x - y).abs() < 1e-4), "ψ = 0 is the nearest (only) mode");
    assert!(c.iter().zip(&d).any(|(x, y)| (x - y).abs() > 1e-3));
    // Modes of another width than w_dim are refused.
    let narrow =
        LatentModes { geo: m.geo.clone(), tex: m.tex.clone().narrow(1, 0, 1), tex_layers: None, pairing: m.pairing };
    let bad = save_generator_with_modes(&g, &cfg, Some(&narrow), &extra).unwrap();
    assert!(load_latent_modes(&bad, &dev).is_err());

    // Pairing: subject 0 = codes of seeds (1, 3), subject 1 = (2, 4). Geometry seed 1 with
    // texture seed 4 at ψ = 0: `subject` gives subject 0's texture code, `branch` keeps the
    // texture code's own subject (1). The pairing travels in the checkpoint; an unknown value
    // is refused.
    let (z1, z3) = seed_latents(&cfg, 1, 3, &dev);
    let (z2, z4) = seed_latents(&cfg, 2, 4, &dev);
    let w = |m: &getavatar_core::generator::network::mapping::MappingNetwork, a: &Tensor<2>, b: &Tensor<2>| {
        m.forward(Tensor::cat(vec![a.clone(), b.clone()], 0))
    };
    let two = LatentModes {
        geo: w(&g.mapping_geo, &z1, &z2),
        tex: w(&g.mapping_tex, &z3, &z4),
        tex_layers: None,
        pairing: ModePairing::Branch,
    };
    let bytes = save_generator_with_modes(&g, &cfg, Some(&two), &extra).unwrap();
    let loaded = load_latent_modes(&bytes, &dev).expect("parses").expect("modes present");
    assert_eq!(loaded.pairing, ModePairing::Branch);
    let tex_at = |m: &LatentModes| {
        vals(g.styles_with(z1.clone(), z4.clone(), 0.0, Some(m)).tex.narrow(1, 0, 1).reshape([1, cfg.w_dim]))
    };
    let row = |t: &Tensor<2>, k: usize| vals(t.clone().narrow(0, k, 1));
    let near = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-4);
    assert!(near(&tex_at(&loaded), &row(&two.tex, 1)), "branch: the texture code's own subject");
    let subject = LatentModes { pairing: ModePairing::Subject, ..two.clone() };
    assert!(near(&tex_at(&subject), &row(&two.tex, 0)), "subject: the geometry code's subject");
    let mut patched = bytes.clone();
    let at = patched.windows(8).position(|x| x == b"\"branch\"").expect("pairing in the header");
    patched[at + 1..at + 7].copy_from_slice(b"braNch");
    let err = load_latent_modes(&patched, &dev).expect_err("unknown pairing").to_string();
    assert!(err.contains("latent_modes/pairing"), "{err}");

    // Per-layer texture modes (W+ subject codes): they travel in the file; a subject's styles
    // and ψ = 0 add its layer offsets to its W code on each layer, ψ = ½ half of them, ψ = 1
    // none; a file whose layer count is not the generator's is refused.
    let nt = g.num_ws().1;
    let offsets: Vec<f32> = (0..2 * nt * cfg.w_dim).map(|i| ((i % 7) as f32 - 3.0) * 0.1).collect();
    let layered = LatentModes {
        tex_layers: Some(Tensor::from_data(TensorData::new(offsets.clone(), [2, nt, cfg.w_dim]), &dev)),
        ..two.clone()
    };
    let bytes = save_generator_with_modes(&g, &cfg, Some(&layered), &extra).unwrap();
    let (_, loaded) = load_generator_and_modes(&bytes, &cfg, &dev).expect("a file with layer offsets loads");
    let loaded = loaded.expect("modes present");
    assert_eq!(vals(loaded.tex_layers.clone().expect("layers travel").reshape([1, 2 * nt * cfg.w_dim])), offsets);
    let t1 = row(&two.tex, 1);
    let expect = |scale: f32| -> Vec<f32> {
        (0..nt * cfg.w_dim).map(|i| t1[i % cfg.w_dim] + scale * offsets[nt * cfg.w_dim + i]).collect()
    };
    let own = g.subject_styles(&loaded, 0, 1).expect("in range");
    assert!(near(&vals(own.tex.reshape([1, nt * cfg.w_dim])), &expect(1.0)), "subject 1's texture, layer by layer");
    let at_psi =
        |psi: f32| vals(g.styles_with(z1.clone(), z4.clone(), psi, Some(&loaded)).tex.reshape([1, nt * cfg.w_dim]));
    assert!(near(&at_psi(0.0), &expect(1.0)), "ψ = 0: the mode's W+ code");
    let w4 = vals(g.mapping_tex.forward(z4.clone()));
    let half: Vec<f32> = (0..nt * cfg.w_dim)
        .map(|i| 0.5 * (t1[i % cfg.w_dim] + w4[i % cfg.w_dim]) + 0.5 * offsets[nt * cfg.w_dim + i])
        .collect();
    assert!(near(&at_psi(0.5), &half), "ψ = ½: half way, half the offsets");
    let plain_w: Vec<f32> = (0..nt * cfg.w_dim).map(|i| w4[i % cfg.w_dim]).collect();
    assert!(near(&at_psi(1.0), &plain_w), "ψ = 1: the seed's own code");
    assert!(g.subject_styles(&loaded, 0, 2).is_none(), "out of range");
    let short = LatentModes { tex_layers: layered.tex_layers.clone().map(|t| t.narrow(1, 0, nt - 1)), ..two.clone() };
    let bytes = save_generator_with_modes(&g, &cfg, Some(&short), &extra).unwrap();
    let Err(err) = load_generator_and_modes(&bytes, &cfg, &dev) else { panic!("wrong layer count refused") };
    let err = err.to_string();
    assert!(err.contains("latent_modes/tex_layers"), "{err}");
}

type Fingerprint = (usize, usize, [f64; 3]);

/// What identifies a generated mesh: vertex and triangle counts, and Σ (x + 2y + 3z) over its
/// positions, normals and colours (clamped to [0, 1] as the .glb stores them), in f64.
fn fingerprint(a: &Avatar) -> Fingerprint {
    let sum =
        |v: &mut dyn Iterator<Item = Vec3>| v.map(|p| p.x as f64 + 2.0 * p.y as f64 + 3.0 * p.z as f64).sum::<f64>();
    let colors = &mut a.colors.iter().map(|c| c.clamp(Vec3::ZERO, Vec3::ONE));
    let (positions, normals) = (&mut a.mesh.vertices.iter().copied(), &mut a.normals.iter().copied());
    (a.mesh.vertices.len(), a.mesh.faces.len(), [sum(positions), sum(normals), sum(colors)])
}

/// The shipped demo checkpoint loads and generates, through the library, the avatars its CLI
/// exported: the figures were measured on the .glb of `trainer sample --config demo
/// --seed-geo 1 --seed-tex 2 --pose walking|arms_up` (default ψ: 0, the nearest training
/// subject) when the file was shipped (v3.3, a release build: v3's
/// geometry, so the position and normal sums are v3's; v3.1's fitted texture codes and
/// texture branch; v3.2's refitted texture mapping, which picks another subject's colours for
/// texture seed 2; v3.3's face plane, which colours the face alone), summing the glTF's POSITION, NORMAL and COLOR_0 accessors
/// (`tools/glb_fingerprint.py` prints the figures). (The 16-subject file before it was checked the same way against commit
/// e02b26a, to pin a refactor.)
#[test]
fn shipped_demo_model_generates_the_avatars_its_cli_exported() {
    use getavatar_core::generator::checkpoint::{config_with_saved_resolutions, load_generator, load_latent_modes};
    use getavatar_core::generator::pipeline::default_psi;
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../assets/models/demo.safetensors");
    let bytes = std::fs::read(path).unwrap();
    let dev = device();
    // The shipped file is the demo config with 128² texture and geometry planes, extracted
    // on a 96³ tet grid (v3 to v3.3) with a 64² face plane (v3.3), and its latent modes
    // carry W+ texture codes.
    let cfg = config_with_saved_resolutions(&bytes, &GeneratorConfig::demo());
    assert_eq!((cfg.texture_res, cfg.geometry_res, cfg.tet_res), (Some(128), Some(128), 96));
    assert_eq!(cfg.face.as_ref().map(|f| f.res), Some(64));
    let g = load_generator(&bytes, &cfg, &dev).unwrap();
    let modes = load_latent_modes(&bytes, &dev).unwrap();
    assert_eq!(modes.as_ref().and_then(|m| m.tex_layers.as_ref()).map(|t| t.dims()), Some([64, g.num_ws().1, 128]));
    let ctx = BodyContext::new(BodyModel::default_body().unwrap(), &cfg);
    let expected: [(&str, Fingerprint); 2] = [
        ("walking", (14576, 29144, [-5271.214605034233, -250.93387932197948, 29333.571582364035])),
        ("arms_up", (14892, 29780, [-3468.108474515305, 435.5633037153639, 28746.391369986115])),
    ];
    for (pose, want) in expected {
        let (zg, zt) = seed_latents(&cfg, 1, 2, &dev);
        let styles = g.styles_with(zg, zt, default_psi(modes.as_ref()), modes.as_ref());
        let params = PoseLibrary::builtin().params(pose, &[]).unwrap();
        let got = fingerprint(&generate_avatar(&g, &ctx, &styles, &params, &dev).unwrap());
        assert_eq!((got.0, got.1), (want.0, want.1), "{pose}: vertex and triangle counts {got:?}");
        // Sums over all vertices of positions, normals and colours. The release CLI and
        // this debug test may round differently (for the file before this one, positions
        // differed by ≈ 2e-5 m and colours by ≈ 5e-4 in sums over 6,224 vertices once
        // NdArray's convolution became one operation): float rounding, not another avatar.
        for ((k, (a, b)), tol) in got.2.iter().zip(want.2).enumerate().zip([1e-4, 1e-3, 2e-3]) {
            assert!((a - b).abs() < tol, "{pose}: sum {k} is {a}, was {b} ({got:?})");
        }
    }
}

/// Geometry detail blocks (`geometry_res`): finer geometry planes, the same texture planes;
/// a checkpoint without them grows into the finer config with the same SDF residual up to
/// the planes' 2× upsampling (the new to-geometry layer starts at zero); their weights are
/// not the texture branch's, and they take w_geo styles of their own.
#[test]
fn geometry_detail_blocks_refine_the_geometry_planes_and_grow_from_a_saved_generator() {
    use getavatar_core::generator::checkpoint::{
        config_with_saved_resolutions, load_generator_growing, save_generator,
    };
    use getavatar_core::generator::pipeline::is_texture_param;
    let dev = device();
    let cfg = GeneratorConfig { texture_res: Some(32), ..GeneratorConfig::tiny() };
    let fine = GeneratorConfig { geometry_res: Some(2 * cfg.plane_res), ..cfg.clone() };
    assert!(fine.validate().is_ok());
    let e = GeneratorConfig { geometry_res: Some(3 * cfg.plane_res), ..cfg.clone() }.validate().unwrap_err();
    assert!(e.contains("geometry_res"), "{e}");
    let coarse = Generator::new(&cfg, 3, &dev);
    let bytes = save_generator(&coarse, &cfg, &Default::default()).unwrap();
    let grown = load_generator_growing(&bytes, &fine, 5, &dev).expect("grows");
    assert_eq!(grown.num_ws().0, coarse.num_ws().0 + 2, "a detail conv and a to-geometry layer");
    assert_eq!(grown.num_ws().1, coarse.num_ws().1);
    let (zg, zt) = seed_latents(&cfg, 1, 2, &dev);
    let (sa, sb) = (coarse.styles(zg.clone(), zt.clone(), 0.7), grown.styles(zg, zt, 0.7));
    let (a, b) = (coarse.triplanes(&sa), grown.triplanes(&sb));
    let r = cfg.plane_res;
    assert_eq!(b.geometry.dims(), [1, 3 * cfg.plane_channels, 2 * r, 2 * r]);
    let vec = |t: Tensor<4>| t.into_data().try_to_vec::<f32>().expect("f32");
    assert_eq!(vec(a.texture.clone()), vec(b.texture.clone()), "the texture planes are untouched");
    let (ga, gb) = (vec(a.geometry.clone()), vec(b.geometry.clone()));
    let at = |c: usize, y: usize, x: usize| ga[(c * r + y) * r + x];
    let (c, i, j) = (2, 5, 3);
    let want = 0.5625 * at(c, i, j) + 0.1875 * (at(c, i - 1, j) + at(c, i, j - 1)) + 0.0625 * at(c, i - 1, j - 1);
    let got = gb[(c * 2 * r + 2 * i) * 2 * r + 2 * j];
    assert!((got - want).abs() < 1e-5, "{got} vs {want}");
    // The SDF residual at canonical points: the same field, up to the planes' resampling.
    let pts: Vec<f32> = (0..64).flat_map(|k| [0.3 * ((k as f32) * 0.7).sin(), -0.9 + 0.03 * k as f32, 0.1]).collect();
    let pts = Tensor::<3>::from_data(getavatar_core::burn::tensor::TensorData::new(pts, [1, 64, 3]), &dev);
    let flat = |t: Tensor<2>| t.into_data().try_to_vec::<f32>().expect("f32");
    let (ra, rb) = (flat(coarse.sdf_residual(&a, &sa, pts.clone())), flat(grown.sdf_residual(&b, &sb, pts)));
    let scale = ra.iter().map(|v| v.abs()).fold(0f32, f32::max);
    let diff = ra.iter().zip(&rb).map(|(x, y)| (x - y).abs()).fold(0f32, f32::max);
    assert!(scale > 0.0 && diff < 0.5 * scale, "residual moved by {diff} (scale {scale})");
    let names = param_names_under(&grown, "synthesis.geometry_detail.");
    assert!(names.len() >= 4 && names.iter().all(|n| !is_texture_param(n)), "{names:?}");
    let grown_bytes = save_generator(&grown, &fine, &Default::default()).unwrap();
    assert_eq!(config_with_saved_resolutions(&grown_bytes, &GeneratorConfig::tiny()), fine);
    let back = GeneratorConfig { geometry_res: None, ..fine.clone() };
    assert!(load_generator_growing(&grown_bytes, &back, 5, &dev).is_err(), "geometry planes cannot shrink");
}

/// Texture detail blocks (`texture_res`): finer texture planes, the same geometry planes; a
/// checkpoint without them grows into the finer config rendering the same planes up to the
/// 2× upsampling (the new to-texture layer starts at zero), and their weights count as the
/// texture branch.
#[test]
fn texture_detail_blocks_refine_the_texture_planes_and_grow_from_a_saved_generator() {
    use getavatar_core::generator::checkpoint::{load_generator, load_generator_growing, save_generator};
    use getavatar_core::generator::pipeline::is_texture_param;
    let dev = device();
    let cfg = GeneratorConfig::tiny();
    let fine = GeneratorConfig { texture_res: Some(2 * cfg.plane_res), ..cfg.clone() };
    assert!(fine.validate().is_ok());
    for bad in [3 * cfg.plane_res, cfg.plane_res / 2, 32 * cfg.plane_res] {
        let e = GeneratorConfig { texture_res: Some(bad), ..cfg.clone() }.validate().unwrap_err();
        assert!(e.contains("texture_res"), "{e}");
    }
    let coarse = Generator::new(&cfg, 3, &dev);
    let bytes = save_generator(&coarse, &cfg, &Default::default()).unwrap();
    // The plain loader refuses the other config; the growing one takes it.
    assert!(load_generator(&bytes, &fine, &dev).is_err());
    let grown = load_generator_growing(&bytes, &fine, 5, &dev).expect("grows");
    let other = GeneratorConfig { z_dim: 8, ..fine.clone() };
    assert!(load_generator_growing(&bytes, &other, 5, &dev).is_err(), "only the texture planes may differ");
    let (zg, zt) = seed_latents(&cfg, 1, 2, &dev);
    let a = coarse.triplanes(&coarse.styles(zg.clone(), zt.clone(), 0.7));
    let b = grown.triplanes(&grown.styles(zg, zt, 0.7));
    let r = cfg.plane_res;
    assert_eq!(a.texture.dims(), [1, 3 * cfg.plane_channels, r, r]);
    assert_eq!(b.texture.dims(), [1, 3 * cfg.plane_channels, 2 * r, 2 * r]);
    let vec = |t: Tensor<4>| t.into_data().try_to_vec::<f32>().expect("f32");
    assert_eq!(vec(a.geometry), vec(b.geometry), "the geometry planes are untouched");
    // Texel (2i, 2j) of the grown planes is ¾·¾ of texel (i, j) plus its up-left neighbours'
    // shares (half-pixel bilinear): check an interior texel against that formula.
    let (ta, tb) = (vec(a.texture), vec(b.texture));
    let at = |c: usize, y: usize, x: usize| ta[(c * r + y) * r + x];
    let (c, i, j) = (1, 3, 4);
    let want = 0.5625 * at(c, i, j) + 0.1875 * (at(c, i - 1, j) + at(c, i, j - 1)) + 0.0625 * at(c, i - 1, j - 1);
    let got = tb[(c * 2 * r + 2 * i) * 2 * r + 2 * j];
    assert!((got - want).abs() < 1e-5, "{got} vs {want}");
    // The detail block's weights are the texture branch's (its own learning rate).
    let names = param_names_under(&grown, "synthesis.texture_detail.");
    assert!(names.len() >= 4, "{names:?}");
    assert!(names.iter().all(|n| is_texture_param(n)), "{names:?}");
    // A file with finer texture planes names its own config for the preset it grew from
    // (the app and the CLI load the shipped file that way), and for no other.
    use getavatar_core::generator::checkpoint::config_with_saved_resolutions;
    let grown_bytes = save_generator(&grown, &fine, &Default::default()).unwrap();
    assert_eq!(config_with_saved_resolutions(&grown_bytes, &cfg), fine);
    assert_eq!(config_with_saved_resolutions(&grown_bytes, &GeneratorConfig::demo()), GeneratorConfig::demo());
    assert_eq!(config_with_saved_resolutions(b"junk", &cfg), cfg);
    // A file claiming absurd texture planes is not adopted, and cannot size a model.
    let huge = GeneratorConfig { texture_res: Some(1 << 20), ..cfg.clone() };
    let meta = [
        ("format".to_string(), getavatar_core::generator::checkpoint::FORMAT.to_string()),
        ("config".to_string(), serde_json::to_string(&huge).unwrap()),
    ]
    .into_iter()
    .collect();
    let params = getavatar_core::generator::checkpoint::collect_params(&grown).unwrap();
    let forged = getavatar_core::generator::checkpoint::write_safetensors(&meta, &params).unwrap();
    assert_eq!(config_with_saved_resolutions(&forged, &cfg), cfg);
    let e = load_generator(&forged, &huge, &dev).expect_err("refused").to_string();
    assert!(e.contains("texture_res"), "{e}");
    assert!(load_generator_growing(&bytes, &huge, 5, &dev).is_err());
    assert!(load_generator(&grown_bytes, &config_with_saved_resolutions(&grown_bytes, &cfg), &dev).is_ok());
    // Generation with the grown generator runs on the finer planes.
    let ctx = BodyContext::new(BodyModel::default_body().expect("body"), &fine);
    let av = generate(&grown, &ctx, &fine, (1, 2), "standing");
    assert!(av.colors.iter().all(|c| c.min_element() >= 0.0 && c.max_element() <= 1.0));
}

/// The tet grid (`tet_res`) is no weight's: the same seed draws the same weights on any grid,
/// a file saved with a finer grid names its config for the preset it came from (the app and
/// the CLI extract the shipped file on its own grid) and loads either way, the DMTet offsets
/// stay within a quarter of the grid's cell, and the finer grid gives more triangles over the
/// same body. A file claiming an absurd grid is not adopted and cannot size a model.
#[test]
fn a_checkpoint_brings_its_tet_grid_and_no_weight_depends_on_it() {
    use getavatar_core::generator::checkpoint::{
        collect_params, config_with_saved_resolutions, load_generator, load_generator_growing, save_generator,
        write_safetensors, FORMAT,
    };
    use getavatar_core::geometry::tet_grid::REFERENCE_BOX_SIZE;
    let dev = device();
    let cfg = GeneratorConfig::tiny();
    let finer = GeneratorConfig { tet_res: cfg.tet_res * 3 / 2, ..cfg.clone() };
    let (g, gf) = (Generator::new(&cfg, 3, &dev), Generator::new(&finer, 3, &dev));
    let (pa, pf) = (collect_params(&g).unwrap(), collect_params(&gf).unwrap());
    assert_eq!(pa, pf, "the grid changes no weight");
    let bytes = save_generator(&gf, &finer, &Default::default()).unwrap();
    assert_eq!(config_with_saved_resolutions(&bytes, &cfg), finer);
    let loaded = load_generator(&bytes, &finer, &dev).expect("loads on its own grid");
    assert_eq!(loaded.decoders.tet_res, finer.tet_res);
    let coarse = load_generator_growing(&bytes, &cfg, 5, &dev).expect("loads on the preset's grid");
    assert_eq!(coarse.decoders.tet_res, cfg.tet_res);
    assert_eq!(collect_params(&coarse).unwrap(), pf);
    // Offsets: bounded by a quarter of each grid's cell, so smaller on the finer grid.
    let pts: Vec<f32> = (0..64).flat_map(|k| [0.3 * ((k as f32) * 0.7).sin(), -0.9 + 0.03 * k as f32, 0.1]).collect();
    let pts = Tensor::<3>::from_data(getavatar_core::burn::tensor::TensorData::new(pts, [1, 64, 3]), &dev);
    let (zg, zt) = seed_latents(&cfg, 1, 2, &dev);
    let s = loaded.styles(zg, zt, 0.7);
    let planes = loaded.triplanes(&s);
    let max_offset = |g: &Generator| {
        let (_, o) = g.geometry_fields(&planes, &s, pts.clone());
        o.into_data().try_to_vec::<f32>().expect("f32").iter().fold(0f32, |m, v| m.max(v.abs()))
    };
    let (of, oc) = (max_offset(&loaded), max_offset(&coarse));
    let cell = |n: usize| REFERENCE_BOX_SIZE / n as f32;
    assert!(of > 0.0 && of <= cell(finer.tet_res) / 4.0 + 1e-6, "{of}");
    assert!((of / oc - cfg.tet_res as f32 / finer.tet_res as f32).abs() < 1e-3, "{of} vs {oc}");
    // The same avatar on both grids: the same extent, more triangles on the finer one.
    let avatar = |g: &Generator, c: &GeneratorConfig| {
        let ctx = BodyContext::new(BodyModel::default_body().expect("body"), c);
        generate(g, &ctx, c, (1, 2), "standing")
    };
    let (af, ac) = (avatar(&loaded, &finer), avatar(&coarse, &cfg));
    let extent = |a: &Avatar| {
        let v = &a.mesh.vertices;
        let lo = v.iter().fold(Vec3::splat(f32::INFINITY), |m, p| m.min(*p));
        let hi = v.iter().fold(Vec3::splat(f32::NEG_INFINITY), |m, p| m.max(*p));
        (lo, hi)
    };
    let ((lf, hf), (lc, hc)) = (extent(&af), extent(&ac));
    assert!(
        (lf - lc).abs().max_element() < 1.5 * cell(cfg.tet_res)
            && (hf - hc).abs().max_element() < 1.5 * cell(cfg.tet_res),
        "{lf}..{hf} vs {lc}..{hc}"
    );
    let (tf, tc) = (af.mesh.faces.len(), ac.mesh.faces.len());
    assert!(tf as f32 > 1.5 * tc as f32, "{tf} triangles on the finer grid, {tc} on the coarser");
    // A forged file asking for a huge grid.
    let huge = GeneratorConfig { tet_res: 1 << 16, ..cfg.clone() };
    let meta =
        [("format".to_string(), FORMAT.to_string()), ("config".to_string(), serde_json::to_string(&huge).unwrap())]
            .into_iter()
            .collect();
    let forged = write_safetensors(&meta, &pf).unwrap();
    assert_eq!(config_with_saved_resolutions(&forged, &cfg), cfg);
    let e = load_generator(&forged, &huge, &dev).expect_err("refused").to_string();
    assert!(e.contains("tet_res"), "{e}");
}

/// W+ texture modes follow a checkpoint that grows texture detail blocks
/// (`Generator::grown_modes`, `trainer fit-codes --texture-res`): the new block's two style
/// layers, between the file's detail blocks and the 3 decoder layers, get zero offsets; every
/// other layer of every subject keeps its own. Too many layers is refused.
#[test]
fn texture_modes_grow_with_the_texture_detail_blocks() {
    use getavatar_core::burn::tensor::TensorData;
    use getavatar_core::generator::checkpoint::{load_generator_growing, save_generator};
    use getavatar_core::generator::pipeline::{LatentModes, ModePairing};
    let dev = device();
    let cfg = GeneratorConfig { texture_res: Some(2 * GeneratorConfig::tiny().plane_res), ..GeneratorConfig::tiny() };
    let fine = GeneratorConfig { texture_res: Some(4 * cfg.plane_res), ..cfg.clone() };
    let coarse = Generator::new(&cfg, 3, &dev);
    let grown = load_generator_growing(&save_generator(&coarse, &cfg, &Default::default()).unwrap(), &fine, 5, &dev)
        .expect("grows");
    let (nt, w) = (coarse.num_ws().1, cfg.w_dim);
    assert_eq!(grown.num_ws().1, nt + 2, "a detail conv and a to-texture layer");
    let k = 2;
    let offsets: Vec<f32> = (0..k * nt * w).map(|i| 1.0 + i as f32).collect();
    let codes = |d: usize| Tensor::from_data(TensorData::new(vec![0.5; k * d], [k, d]), &dev);
    let modes = LatentModes {
        geo: codes(w),
        tex: codes(w),
        tex_layers: Some(Tensor::from_data(TensorData::new(offsets.clone(), [k, nt, w]), &dev)),
        pairing: ModePairing::Branch,
    };
    let g = grown.grown_modes(modes.clone()).expect("grows");
    let layers = g.tex_layers.clone().expect("kept").into_data().try_to_vec::<f32>().unwrap();
    assert_eq!(layers.len(), k * (nt + 2) * w);
    let old = |s: usize, l: usize| &offsets[(s * nt + l) * w..(s * nt + l + 1) * w];
    let new = |s: usize, l: usize| &layers[(s * (nt + 2) + l) * w..(s * (nt + 2) + l + 1) * w];
    for s in 0..k {
        for l in 0..nt - 3 {
            assert_eq!(new(s, l), old(s, l), "subject {s}, backbone/detail layer {l}");
        }
        for l in nt - 3..nt - 1 {
            assert!(new(s, l).iter().all(|&v| v == 0.0), "subject {s}: new layer {l} starts at zero");
        }
        for l in nt - 3..nt {
            assert_eq!(new(s, l + 2), old(s, l), "subject {s}: decoder layer {l} moves by 2");
        }
    }
    // Already the generator's count: unchanged; more than it has: refused.
    assert_eq!(coarse.grown_modes(modes.clone()).unwrap().tex_layers.unwrap().dims(), [k, nt, w]);
    let too_many = LatentModes { tex_layers: g.tex_layers.clone(), ..modes };
    assert!(coarse.grown_modes(too_many).unwrap_err().contains("layers"));
}

/// The face plane (`GeneratorConfig::face`): a checkpoint without one grows into it rendering
/// the same colours everywhere (its constant starts at zero); once it holds features, colours
/// change on the face and nowhere else (not behind it, not beside it), fading at the window's
/// edge; its weights are the texture branch's, and the file round-trips with its window.
#[test]
fn the_face_plane_colours_the_face_alone_and_grows_from_a_saved_generator() {
    use getavatar_core::burn::tensor::TensorData;
    use getavatar_core::generator::checkpoint::{
        config_with_saved_resolutions, load_generator, load_generator_growing, save_generator,
    };
    use getavatar_core::generator::network::config::FacePlaneConfig;
    use getavatar_core::generator::network::face_plane::face_window;
    use getavatar_core::generator::pipeline::{is_face_param, is_texture_param};
    let dev = device();
    let cfg = GeneratorConfig::tiny();
    let body = BodyModel::default_body().expect("body");
    let window = face_window(&body, 16).expect("the body has a face");
    let [cx, cy, front] = window.center;
    // The nose tip lies on the canonical head: at the midline, well above the root (the pelvis).
    assert!(cx.abs() < 0.01 && cy > 0.3 && front > 0.05, "{window:?}");
    let with_face = GeneratorConfig { face: Some(window.clone()), ..cfg.clone() };
    assert!(with_face.validate().is_ok());
    for bad in [
        FacePlaneConfig { res: 2, ..window.clone() },
        FacePlaneConfig { half_size: [0.0, 0.1], ..window.clone() },
        FacePlaneConfig { depth: f32::NAN, ..window.clone() },
    ] {
        let e = GeneratorConfig { face: Some(bad), ..cfg.clone() }.validate().unwrap_err();
        assert!(e.contains("face"), "{e}");
    }
    let plain = Generator::new(&cfg, 3, &dev);
    let bytes = save_generator(&plain, &cfg, &Default::default()).unwrap();
    assert!(load_generator(&bytes, &with_face, &dev).is_err(), "the plain loader wants the file's config");
    let mut grown = load_generator_growing(&bytes, &with_face, 5, &dev).expect("grows");
    assert_eq!(grown.num_ws(), plain.num_ws(), "the face plane takes the texture decoder's first style");
    // Points: on the face (nose tip, an eye), 20 cm behind the nose (the back of the head's
    // depth), beside the window, and half-way into its edge fade.
    let [hx, _] = window.half_size;
    let pts = [
        [cx, cy, front],
        [cx + 0.032, cy + 0.03, front - 0.02],
        [cx, cy, front - 0.2],
        [cx + 1.2 * hx, cy, front],
        [cx + 0.875 * hx, cy, front],
    ];
    let flat: Vec<f32> = pts.iter().flatten().copied().collect();
    let pts = Tensor::<3>::from_data(TensorData::new(flat, [1, 5, 3]), &dev);
    let (zg, zt) = seed_latents(&cfg, 1, 2, &dev);
    let colours = |g: &Generator| {
        let s = g.styles(zg.clone(), zt.clone(), 0.7);
        let planes = g.triplanes(&s);
        g.texture_field(&planes, &s, pts.clone()).into_data().try_to_vec::<f32>().expect("f32")
    };
    let before = colours(&plain);
    assert_eq!(colours(&grown), before, "a grown face plane renders what the file rendered");
    // A constant feature over the whole plane.
    let face = grown.face.as_mut().expect("a face plane");
    let dims = face.constant.dims();
    face.constant = Param::from_tensor(Tensor::ones(dims, &dev) * 3.0);
    let after = colours(&grown);
    let moved = |i: usize| (0..3).map(|c| (after[3 * i + c] - before[3 * i + c]).abs()).sum::<f32>();
    assert!(moved(0) > 1e-3 && moved(1) > 1e-3, "the face's colours change: {} {}", moved(0), moved(1));
    assert_eq!(moved(2), 0.0, "behind the face");
    assert_eq!(moved(3), 0.0, "beside the window");
    assert!(moved(4) > 0.0 && moved(4) < moved(0), "the edge fades: {} of {}", moved(4), moved(0));
    let names: Vec<String> =
        getavatar_core::generator::checkpoint::collect_params(&grown).unwrap().into_iter().map(|(n, _, _)| n).collect();
    let faces: Vec<&String> = names.iter().filter(|n| is_face_param(n)).collect();
    assert!(faces.len() >= 3 && faces.iter().all(|n| is_texture_param(n)), "{faces:?}");
    // The file keeps the window: loaders take it from there, and it cannot be dropped.
    let saved = save_generator(&grown, &with_face, &Default::default()).unwrap();
    assert_eq!(config_with_saved_resolutions(&saved, &cfg), with_face);
    let back = load_generator(&saved, &with_face, &dev).expect("loads");
    assert_eq!(colours(&back), after);
    assert!(load_generator_growing(&saved, &cfg, 5, &dev).is_err(), "the face plane cannot be dropped");
    let moved_window = GeneratorConfig { face: Some(FacePlaneConfig { res: 32, ..window }), ..cfg };
    assert!(load_generator_growing(&saved, &moved_window, 5, &dev).is_err(), "nor changed");
}
