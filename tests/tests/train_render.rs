//! Rendering generated avatars for training: images follow the posed body and camera of the
//! label, and each loss term's gradient reaches exactly the parameters it should.

use getavatar_core::body::body_model::BodyModel;
use getavatar_core::body::pose_library::PoseLibrary;
use getavatar_core::body::skinning::{pose_body, vertex_normals};
use getavatar_core::burn::module::{Module, ModuleVisitor, Param};
use getavatar_core::burn::tensor::{Gradients, Tensor, TensorData};
use getavatar_core::generator::network::GeneratorConfig;
use getavatar_core::generator::pipeline::{recolor_async, seed_latents, BodyContext, Generator};
use getavatar_core::generator::readback::block_on_ready;
use getavatar_core::io::dataset::Label;
use getavatar_core::render::camera::OrbitCamera;
use getavatar_core::render::diff::avatar::{render_avatars, PosedGridCache};
use getavatar_core::render::rasterize::{render_views, render_views_textured};
use glam::Vec3;

mod common;
use common::{cpu, values};

/// Shift of the colour head's bias that makes the untrained tiny generator's colours dark
/// (linear ≈ 0.02, sRGB ≈ 40/255).
const DARK_SHIFT: f32 = 4.0;

/// The renderer's views of dataset labels.
fn views(labels: &[Label]) -> Vec<getavatar_core::render::camera::View> {
    labels.iter().map(Label::view).collect()
}

/// Sum of |gradient| over the parameters under module path `prefix`.
fn grad_mass<M: Module>(m: &M, grads: &Gradients, prefix: &str) -> f32 {
    struct V<'a> {
        path: Vec<String>,
        grads: &'a Gradients,
        prefix: &'a str,
        sum: f32,
    }
    impl ModuleVisitor for V<'_> {
        fn enter_module(&mut self, name: &str, _: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _: &str, _: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            if self.path.join(".").starts_with(self.prefix) {
                if let Some(g) = p.val().grad(self.grads) {
                    self.sum += values(g.abs().sum())[0];
                }
            }
        }
    }
    let mut v = V { path: Vec::new(), grads, prefix, sum: 0.0 };
    m.visit(&mut v);
    v.sum
}

#[test]
fn fakes_follow_the_label_and_gradients_reach_the_right_networks() {
    let dev = cpu().autodiff();
    let cfg = GeneratorConfig::tiny();
    let model = BodyModel::default_body().unwrap();
    let ctx = BodyContext::new(model.clone(), &cfg);
    let g = Generator::new(&cfg, 0, &dev);
    let (zg, zt) = seed_latents(&cfg, 1, 2, &dev);
    let lib = PoseLibrary::builtin();
    let params = lib.params("walking", &[]).unwrap();
    let cam = OrbitCamera { yaw: 0.5, pitch: 0.05, ..OrbitCamera::default() };
    let label = Label::new(cam.world_to_camera(), &params);
    let res = 64;
    let render_with = |g: &Generator| {
        render_avatars(
            g,
            &ctx,
            &g.styles(zg.clone(), zt.clone(), 1.0),
            &[label.view()],
            res,
            &PosedGridCache::default(),
            &dev,
        )
        .unwrap()
    };
    let render = || render_with(&g);
    let fakes = render();
    assert_eq!(fakes.rgb.dims(), [1, 3, res, res]);
    assert_eq!(fakes.mask.dims(), [1, 1, res, res]);
    assert!(fakes.triangles[0] > 100);

    // The untrained generator's surface is the template body: its mask matches the posed body
    // rendered through the label's camera.
    let mask: Vec<f32> = values(fakes.mask.clone()).iter().map(|m| (m + 1.0) / 2.0).collect();
    let posed = pose_body(&model, &params);
    let vp = cam.projection_gl(1.0) * cam.world_to_camera();
    let nrm = vertex_normals(&posed.vertices, &model.faces);
    let body = render_views(&posed.vertices, &model.faces, &nrm, &nrm, vp, res, 2);
    let (mut inter, mut union) = (0.0, 0.0);
    for (a, b) in mask.iter().zip(&body.mask) {
        let (a, b) = (*a > 0.5, *b > 127);
        inter += (a && b) as u8 as f32;
        union += (a || b) as u8 as f32;
    }
    // The same avatar as the app's (non-differentiable) generation path, rendered on the CPU.
    let plain = cpu();
    let g2 = Generator::new(&cfg, 0, &plain);
    let (a, b) = seed_latents(&cfg, 1, 2, &plain);
    let styles2 = g2.styles(a, b, 1.0);
    let av = getavatar_core::generator::pipeline::generate_avatar(&g2, &ctx, &styles2, &params, &plain).unwrap();
    let gen = render_views(&av.mesh.vertices, &av.mesh.faces, &av.normals, &av.normals, vp, res, 2);
    let iou = |x: &[bool], y: &[bool]| {
        let i = x.iter().zip(y).filter(|(a, b)| **a && **b).count() as f32;
        i / x.iter().zip(y).filter(|(a, b)| **a || **b).count() as f32
    };
    let fake_px: Vec<bool> = mask.iter().map(|m| *m > 0.5).collect();
    let gen_px: Vec<bool> = gen.mask.iter().map(|m| *m > 127).collect();
    // (At 64² a third of the figure's pixels are on its boundary, where 2×2 supersampling and
    // the antialias pass round differently.)
    assert!(iou(&fake_px, &gen_px) > 0.9, "differentiable vs app path: mask IoU {}", iou(&fake_px, &gen_px));
    // Colour: the training image is what `trainer sample` and the app show. Both encode the
    // linear texture field with the one sRGB curve (`colour`); where both cover a pixel fully
    // (interior, away from the boundary's different rounding) they agree. A second curve (γ
    // 1/2.2) differs by 6–8/255 in the darks and little in the lights, so dark and light
    // pixels are compared separately, by their mean signed difference (the encoding's bias;
    // sampling positions differ within a pixel, which averages out), with the colour head's
    // bias shifted so that the untrained generator also paints dark colours.
    let rgb_train = values(fakes.rgb.clone());
    let compare = |shift: f32, rgb_train: &[f32], mask: &[f32]| -> ((f32, usize), (f32, usize), f32) {
        let mut g2 = Generator::new(&cfg, 0, &plain);
        g2.decoders.to_rgb.bias = g2.decoders.to_rgb.bias.clone().map(|b| b - shift);
        let styles2 = g2.styles(seed_latents(&cfg, 1, 2, &plain).0, seed_latents(&cfg, 1, 2, &plain).1, 1.0);
        let av = getavatar_core::generator::pipeline::generate_avatar(&g2, &ctx, &styles2, &params, &plain).unwrap();
        let planes = g2.triplanes(&styles2);
        let shown = render_views_textured(
            &av.mesh.vertices,
            &av.mesh.faces,
            &av.normals,
            &av.mesh.attributes,
            vp,
            res,
            2,
            |p| block_on_ready(recolor_async(&g2, &planes, &styles2, p, &plain)),
        )
        .unwrap();
        let (mut dark, mut light, mut abs, mut n) = ((0.0f32, 0usize), (0.0f32, 0usize), 0.0f32, 0usize);
        for k in 0..res * res {
            if mask[k] > 0.999 && shown.mask[k] == 255 {
                for c in 0..3 {
                    let (t, s) = ((rgb_train[c * res * res + k] + 1.0) / 2.0, shown.rgb[3 * k + c] as f32 / 255.0);
                    let bucket = if s < 0.3 { &mut dark } else { &mut light };
                    bucket.0 += t - s;
                    bucket.1 += 1;
                    abs += (t - s).abs();
                    n += 1;
                }
            }
        }
        ((dark.0 / dark.1.max(1) as f32, dark.1), (light.0 / light.1.max(1) as f32, light.1), abs / n.max(1) as f32)
    };
    let (_, (light_bias, light_n), mean_abs) = compare(0.0, &rgb_train, &mask);
    assert!(light_n > 300, "{light_n} light interior channels");
    assert!(mean_abs < 0.03, "training vs shown colour: mean |Δ| {mean_abs}");
    assert!(light_bias.abs() < 1.0 / 255.0, "light colours: training − shown {:.2}/255", light_bias * 255.0);
    // The same surface with dark colours: only the colour head's bias differs.
    let dark_fakes = {
        let mut gd = Generator::new(&cfg, 0, &dev);
        gd.decoders.to_rgb.bias = gd.decoders.to_rgb.bias.clone().map(|b| b - DARK_SHIFT);
        render_with(&gd)
    };
    let ((dark_bias, dark_n), _, _) = compare(DARK_SHIFT, &values(dark_fakes.rgb), &mask);
    assert!(dark_n > 300, "{dark_n} dark interior channels");
    assert!(dark_bias.abs() < 1.0 / 255.0, "dark colours: training − shown {:.2}/255", dark_bias * 255.0);
    // Against the posed body: the tiny config's 9.5 cm cells lose thin limbs, so only roughly.
    assert!(inter / union > 0.5, "mask IoU vs posed body {}", inter / union);
    // Normals: unit length on the avatar, zero on the background.
    let n = values(fakes.normal.clone());
    let k_in = mask.iter().position(|m| *m > 0.99).unwrap();
    let len = (0..3).map(|c| n[c * res * res + k_in].powi(2)).sum::<f32>().sqrt();
    assert!((len - 1.0).abs() < 1e-3, "{len}");
    assert!((0..3).all(|c| n[c * res * res].abs() < 1e-6));

    // Mask loss → geometry networks only; RGB loss → texture networks too.
    let grads = render().mask.mean().backward();
    assert!(grad_mass(&g, &grads, "mapping_geo") > 0.0, "mask reaches the geometry mapping");
    assert!(grad_mass(&g, &grads, "decoders.sdf") > 0.0 || grad_mass(&g, &grads, "decoders") > 0.0);
    assert_eq!(grad_mass(&g, &grads, "mapping_tex"), 0.0, "the mask does not depend on texture");
    let grads = render().rgb.mean().backward();
    assert!(grad_mass(&g, &grads, "mapping_tex") > 0.0, "RGB reaches the texture mapping");
    let f = render();
    let grads = (f.eikonal + f.cross_entropy).backward();
    assert!(grad_mass(&g, &grads, "mapping_geo") > 0.0);
    assert_eq!(grad_mass(&g, &grads, "mapping_tex"), 0.0, "regularisers are geometry-only");
    let _ = Vec3::ZERO;
}

/// One Adam step of G against frozen discriminators (RGB, normal, mask) lowers the
/// non-saturating G loss on the same latents and labels.
#[test]
fn one_generator_step_lowers_the_generator_loss_against_a_frozen_discriminator() {
    use getavatar_core::generator::losses::generator_loss;
    use getavatar_core::generator::network::discriminator::{Discriminator, DiscriminatorConfig};
    use getavatar_core::generator::optim::Adam;
    let dev = cpu().autodiff();
    let cfg = GeneratorConfig::tiny();
    let ctx = BodyContext::new(BodyModel::default_body().unwrap(), &cfg);
    let res = 32;
    let dcfg = DiscriminatorConfig::new(res, 512, 32);
    let ds: Vec<Discriminator> = [3usize, 3, 1]
        .iter()
        .enumerate()
        .map(|(k, &c)| Discriminator::new(&dcfg, c, 40 + k as u64, &dev).no_grad())
        .collect();
    let lib = PoseLibrary::builtin();
    let labels: Vec<Label> = ["walking", "T"]
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let params = lib.params(p, &[]).unwrap();
            let cam = OrbitCamera { yaw: 0.7 * i as f32, ..OrbitCamera::default() };
            Label::new(cam.world_to_camera(), &params)
        })
        .collect();
    let cams: Vec<f32> =
        labels.iter().flat_map(|l| getavatar_core::render::camera::to_row_major(l.world_to_camera)).collect();
    let c = Tensor::<2>::from_data(getavatar_core::burn::tensor::TensorData::new(cams, [2, 16]), &dev);
    let (zg, zt) = seed_latents(&cfg, 3, 4, &dev);
    let (zg, zt) = (zg.repeat_dim(0, 2), zt.repeat_dim(0, 2));
    let grids = PosedGridCache::default();
    let loss = |g: &Generator| {
        let f = render_avatars(g, &ctx, &g.styles(zg.clone(), zt.clone(), 1.0), &views(&labels), res, &grids, &dev)
            .unwrap();
        let imgs = [f.rgb, f.normal, f.mask];
        imgs.into_iter().zip(&ds).map(|(x, d)| generator_loss(d.forward(x, c.clone()))).reduce(|a, b| a + b).unwrap()
    };
    let g = Generator::new(&cfg, 0, &dev);
    let before = loss(&g);
    let grads = before.clone().backward();
    let before = values(before)[0];
    let mut adam = Adam::new(0.0, 0.99, 1e-8);
    let g = adam.step(0.002, g, &grads);
    let after = values(loss(&g))[0];
    assert!(after < before - 1e-4, "G loss {before} → {after} after one step");
}

/// The mask L1 of a generated avatar against its own silhouette grown by one pixel: its
/// gradient on the SDF-residual bias (a uniform SDF shift) says "inflate" and agrees with
/// finite differences of the whole render. The tet grid is finer than the pixels, as in the
/// demo config; before the silhouette search looked beyond the nearer triangle's corners this
/// gradient was a few per cent of the true one and could have the wrong sign.
#[test]
fn mask_loss_gradient_on_the_sdf_matches_finite_differences_at_sub_pixel_tets() {
    let dev = cpu().autodiff();
    let cfg = GeneratorConfig { tet_res: 64, template_res: 96, ..GeneratorConfig::tiny() };
    let ctx = BodyContext::new(BodyModel::default_body().unwrap(), &cfg);
    let g = Generator::new(&cfg, 0, &dev);
    let (zg, zt) = seed_latents(&cfg, 1, 2, &dev);
    let params = PoseLibrary::builtin().params("walking", &[]).unwrap();
    let cam = OrbitCamera { yaw: 0.5, pitch: 0.05, ..OrbitCamera::default() };
    let label = Label::new(cam.world_to_camera(), &params);
    let (res, grids) = (64, PosedGridCache::default());
    let mask = |g: &Generator| {
        render_avatars(g, &ctx, &g.styles(zg.clone(), zt.clone(), 1.0), &[label.view()], res, &grids, &dev)
            .unwrap()
            .mask
    };
    // Target: the avatar's own silhouette dilated by one pixel, in the mask's [−1, 1] encoding.
    let m0: Vec<bool> = values(mask(&g)).iter().map(|v| *v > 0.0).collect();
    let target: Vec<f32> = (0..res * res)
        .map(|k| {
            let (x, y) = ((k % res) as i32, (k / res) as i32);
            let hit = [(0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)].iter().any(|(dx, dy)| {
                let (u, v) = (x + dx, y + dy);
                (0..res as i32).contains(&u) && (0..res as i32).contains(&v) && m0[v as usize * res + u as usize]
            });
            if hit {
                1.0
            } else {
                -1.0
            }
        })
        .collect();
    let target = Tensor::<4>::from_data(TensorData::new(target, [1, 1, res, res]), &dev);
    let loss = |g: &Generator| (mask(g) - target.clone()).abs().mean();
    let grads = loss(&g).backward();
    let analytic = values(g.decoders.sdf.out.bias.val().grad(&grads).expect("bias gradient").sum())[0];
    let shifted = |d: f32| {
        let mut h = g.clone();
        let b: Vec<f32> = values(h.decoders.sdf.out.bias.val()).iter().map(|v| v + d).collect();
        let n = b.len();
        h.decoders.sdf.out.bias = Param::from_tensor(Tensor::from_data(TensorData::new(b, [n]), &dev));
        values(loss(&h))[0]
    };
    let eps = 1e-3;
    let fd = (shifted(eps) - shifted(-eps)) / (2.0 * eps);
    assert!(fd > 0.0, "finite differences: growing the surface lowers the loss ({fd})");
    assert!(
        analytic > 0.0 && (analytic / fd - 1.0).abs() < 0.2,
        "d(mask L1)/d(SDF shift): analytic {analytic}, finite differences {fd}"
    );
}

/// Several views of one avatar (one surface, rasterised per camera) give the same images,
/// regularisers and parameter gradients as rendering each view as its own avatar.
#[test]
fn views_of_one_avatar_equal_separate_renders() {
    use getavatar_core::render::diff::avatar::render_avatar_views;
    let dev = cpu().autodiff();
    let cfg = GeneratorConfig::tiny();
    let ctx = BodyContext::new(BodyModel::default_body().unwrap(), &cfg);
    let g = Generator::new(&cfg, 0, &dev);
    let params = PoseLibrary::builtin().params("walking", &[]).unwrap();
    let labels: Vec<Label> = [0.0f32, 1.9, -2.6]
        .iter()
        .map(|&yaw| Label::new(OrbitCamera { yaw, pitch: 0.1, ..OrbitCamera::default() }.world_to_camera(), &params))
        .collect();
    let (res, grids) = (32, PosedGridCache::default());
    let (zg, zt) = seed_latents(&cfg, 5, 6, &dev);
    let one =
        render_avatar_views(&g, &ctx, &g.styles(zg.clone(), zt.clone(), 1.0), &[views(&labels)], res, &grids, &dev)
            .unwrap();
    let (zg3, zt3) = (zg.repeat_dim(0, 3), zt.repeat_dim(0, 3));
    let sep = render_avatars(&g, &ctx, &g.styles(zg3, zt3, 1.0), &views(&labels), res, &grids, &dev).unwrap();
    assert_eq!(one.rgb.dims(), [3, 3, res, res]);
    assert_eq!(one.triangles, sep.triangles);
    let close = |a: Vec<f32>, b: Vec<f32>, what: &str| {
        let err = a.iter().zip(&b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max);
        assert!(err < 1e-5, "{what}: max difference {err}");
    };
    close(values(one.rgb.clone()), values(sep.rgb.clone()), "rgb");
    close(values(one.normal.clone()), values(sep.normal.clone()), "normal");
    close(values(one.mask.clone()), values(sep.mask.clone()), "mask");
    close(values(one.eikonal.clone()), values(sep.eikonal.clone()), "eikonal");
    close(values(one.cross_entropy.clone()), values(sep.cross_entropy.clone()), "cross-entropy");
    // The views differ (three cameras), and the gradients agree.
    assert!(values(one.mask.clone().narrow(0, 0, 1) - one.mask.clone().narrow(0, 1, 1)).iter().any(|d| d.abs() > 1.0));
    let loss =
        |f: getavatar_core::render::diff::avatar::FakeViews| f.rgb.mean() + f.mask.mean() + f.normal.mean() + f.eikonal;
    let (ga, gb) = (loss(one).backward(), loss(sep).backward());
    for prefix in ["mapping_geo", "mapping_tex", "synthesis", "decoders"] {
        let (a, b) = (grad_mass(&g, &ga, prefix), grad_mass(&g, &gb, prefix));
        assert!(a > 0.0 && (a / b - 1.0).abs() < 1e-3, "{prefix}: gradient mass {a} vs {b}");
    }
}

/// What `trainer fit-codes` rests on: a rendered view's covered pixels are the texture field
/// at the canonical points `FakeViews::surfaces` gives (sRGB-encoded, no shading), and every
/// other pixel is the white background, so with the geometry fixed the RGB term needs only
/// those points.
#[test]
fn rgb_pixels_are_the_texture_field_at_the_views_surface_points() {
    use getavatar_core::render::colour::encode_srgb_tensor;
    use getavatar_core::render::diff::avatar::render_avatar_views;
    let dev = cpu();
    let cfg = GeneratorConfig::tiny();
    let ctx = BodyContext::new(BodyModel::default_body().unwrap(), &cfg);
    let g = Generator::new(&cfg, 0, &dev);
    let params = PoseLibrary::builtin().params("walking", &[]).unwrap();
    let labels: Vec<Label> = [0.4f32, 2.8]
        .iter()
        .map(|&yaw| Label::new(OrbitCamera { yaw, pitch: 0.1, ..OrbitCamera::default() }.world_to_camera(), &params))
        .collect();
    let res = 32;
    let (zg, zt) = seed_latents(&cfg, 5, 6, &dev);
    let s = g.styles(zg, zt, 1.0);
    let f = render_avatar_views(&g, &ctx, &s, &[views(&labels)], res, &PosedGridCache::default(), &dev).unwrap();
    assert_eq!(f.surfaces.len(), 2, "one per view");
    let rgb = values(f.rgb.clone());
    let planes = g.triplanes(&s);
    for (v, surface) in f.surfaces.iter().enumerate() {
        let surface = surface.as_ref().expect("the avatar covers pixels");
        let p = surface.pixels.len();
        assert!(p > 50, "view {v}: {p} pixels");
        let c =
            values(encode_srgb_tensor(g.texture_field(&planes, &s, surface.canonical.clone().unsqueeze_dim::<3>(0))));
        let mut covered = vec![false; res * res];
        for (k, &px) in surface.pixels.iter().enumerate() {
            covered[px as usize] = true;
            for ch in 0..3 {
                let want = c[3 * k + ch] * 2.0 - 1.0;
                let got = rgb[((v * 3 + ch) * res * res) + px as usize];
                assert!((got - want).abs() < 1e-5, "view {v} pixel {px} channel {ch}: {got} vs {want}");
            }
        }
        let background = (0..res * res).filter(|&px| !covered[px]).collect::<Vec<_>>();
        assert!(!background.is_empty());
        for px in background {
            assert!((0..3).all(|ch| rgb[((v * 3 + ch) * res * res) + px] == 1.0), "view {v} pixel {px} is white");
        }
    }
}

/// The texture-swap term's renders (not in the paper): the surface of one code coloured by the
/// texture field of other styles. With the same styles they equal the plain RGB; with another
/// geometry code in the texture styles only covered pixels change, and the term's gradient
/// reaches the texture path (mapping networks, synthesis, colour decoders) but not the heads
/// that place the surface.
#[test]
fn retextured_views_keep_the_surface_and_train_only_the_colours() {
    use getavatar_core::generator::pipeline::Styles;
    use getavatar_core::render::diff::avatar::render_avatar_views_async;
    let dev = cpu().autodiff();
    let cfg = GeneratorConfig::tiny();
    let ctx = BodyContext::new(BodyModel::default_body().unwrap(), &cfg);
    let g = Generator::new(&cfg, 0, &dev);
    let params = PoseLibrary::builtin().params("walking", &[]).unwrap();
    let labels: Vec<Label> = [0.4f32, 2.1]
        .iter()
        .map(|&yaw| Label::new(OrbitCamera { yaw, pitch: 0.1, ..OrbitCamera::default() }.world_to_camera(), &params))
        .collect();
    let (res, grids) = (32, PosedGridCache::default());
    let (zg, zt) = seed_latents(&cfg, 5, 6, &dev);
    let (zg2, _) = seed_latents(&cfg, 7, 8, &dev);
    let own = g.styles(zg.clone(), zt.clone(), 1.0);
    let same =
        block_on_ready(render_avatar_views_async(&g, &ctx, &own, Some(&own), &[views(&labels)], res, &grids, &dev))
            .unwrap();
    let rgb = values(same.rgb.clone());
    let max_diff = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max);
    assert!(max_diff(&rgb, &values(same.rgb_retextured.clone().unwrap())) < 1e-6);
    // The render hands out the avatar's own triplanes (the scan and face terms reuse them).
    let planes = g.triplanes(&own);
    assert_eq!(same.planes.texture.dims(), planes.texture.dims());
    assert!(max_diff(&values(same.planes.texture.clone()), &values(planes.texture)) < 1e-6);
    assert!(max_diff(&values(same.planes.geometry.clone()), &values(planes.geometry)) < 1e-6);
    let swapped = Styles { geo: g.styles(zg2, zt.clone(), 1.0).geo, tex: own.tex.clone() };
    let f =
        block_on_ready(render_avatar_views_async(&g, &ctx, &own, Some(&swapped), &[views(&labels)], res, &grids, &dev))
            .unwrap();
    let re = values(f.rgb_retextured.clone().unwrap());
    assert_eq!(re.len(), rgb.len());
    let (mask, n) = (values(f.mask.clone()), res * res);
    let (mut changed, mut covered) = (0, 0);
    for (i, (a, b)) in rgb.iter().zip(&re).enumerate() {
        let (view, pix) = (i / (3 * n), i % n);
        if mask[view * n + pix] > 0.99 {
            covered += 1;
            changed += ((a - b).abs() > 1e-3) as usize;
        } else if mask[view * n + pix] < -0.99 {
            assert_eq!((*a, *b), (1.0, 1.0), "background stays white in both");
        }
    }
    assert!(covered > 100 && changed * 2 > covered, "{changed} of {covered} covered values changed");
    let grads = f.rgb_retextured.unwrap().mean().backward();
    for prefix in ["mapping_geo", "mapping_tex", "synthesis", "decoders.texture", "decoders.to_rgb"] {
        assert!(grad_mass(&g, &grads, prefix) > 0.0, "{prefix}: no gradient");
    }
    for prefix in ["decoders.sdf", "decoders.offset"] {
        assert_eq!(grad_mass(&g, &grads, prefix), 0.0, "{prefix}: the swap term must not move the surface");
    }
}

/// The scan terms (not in the paper): surface points of a posed scan land on the canonical
/// surface, and each term trains exactly its branch.
#[test]
fn scan_terms_map_to_canonical_space_and_train_their_branch() {
    use getavatar_core::generator::optim::Adam;
    use getavatar_core::io::scan::SurfaceSample;
    use getavatar_core::render::diff::scan_supervision::{scan_losses, CanonicalSamples};
    let dev = cpu().autodiff();
    let cfg = GeneratorConfig::tiny();
    let model = BodyModel::default_body().unwrap();
    let ctx = BodyContext::new(model.clone(), &cfg);

    // A "scan" that is the posed body itself: its vertices go back to the canonical body's
    // (each is its own nearest body vertex), its normals to the canonical normals.
    let params = PoseLibrary::builtin().params("walking", &[]).unwrap();
    let posed = pose_body(&model, &params);
    let pn = vertex_normals(&posed.vertices, &model.faces);
    let red = Vec3::new(0.8, 0.1, 0.1);
    let surface: Vec<SurfaceSample> =
        posed.vertices.iter().zip(&pn).map(|(p, n)| SurfaceSample { position: *p, normal: *n, color: red }).collect();
    let canon = CanonicalSamples::from_surface(&surface, &ctx, &params);
    assert_eq!(canon.len(), surface.len());
    let err = canon.points.iter().zip(&ctx.canonical.vertices).map(|(a, b)| (*a - *b).length()).fold(0.0, f32::max);
    assert!(err < 1e-4, "canonical positions off by {err} m");
    let cn = vertex_normals(&ctx.canonical.vertices, &model.faces);
    let mut dots: Vec<f32> = canon.normals.iter().zip(&cn).map(|(a, b)| a.dot(*b)).collect();
    dots.sort_by(f32::total_cmp);
    assert!(dots[dots.len() / 10] > 0.95, "10th percentile of normal agreement {}", dots[dots.len() / 10]);

    // Gradients: texture term → texture branch, not the SDF head (the shared backbone, styled
    // by w_geo, feeds both); SDF term → geometry only.
    let mut g = Generator::new(&cfg, 0, &dev);
    let (zg, zt) = seed_latents(&cfg, 3, 4, &dev);
    let picks: Vec<usize> = (0..canon.len()).step_by(7).collect();
    let losses = |g: &Generator| {
        let styles = g.styles(zg.clone(), zt.clone(), 1.0);
        scan_losses(g, &ctx, &g.triplanes(&styles), &styles, &[(&canon, picks.clone())], &dev)
    };
    let grads = losses(&g).texture.backward();
    assert!(grad_mass(&g, &grads, "mapping_tex") > 0.0);
    assert_eq!(grad_mass(&g, &grads, "decoders.sdf"), 0.0, "colour does not depend on the SDF head");
    let grads = losses(&g).sdf.backward();
    assert!(grad_mass(&g, &grads, "mapping_geo") > 0.0 && grad_mass(&g, &grads, "decoders.sdf") > 0.0);
    assert_eq!(grad_mass(&g, &grads, "mapping_tex"), 0.0, "the SDF does not depend on texture");

    // On the template surface the SDF target is the template's own value up to the residual:
    // the untrained generator's term is the residual's size, well under a centimetre.
    let first = losses(&g);
    let (tex0, sdf0) = (values(first.texture)[0], values(first.sdf)[0]);
    assert!(sdf0 * getavatar_core::render::diff::scan_supervision::SDF_UNIT < 0.02, "SDF error {sdf0}");
    // A few Adam steps on the texture term pull the colour to the scan's red.
    let mut adam = Adam::new(0.9, 0.99, 1e-8);
    for _ in 0..15 {
        let grads = losses(&g).texture.backward();
        g = adam.step(0.01, g, &grads);
    }
    let tex1 = values(losses(&g).texture)[0];
    assert!(tex1 < 0.5 * tex0, "texture L1 {tex0} → {tex1}");
}
