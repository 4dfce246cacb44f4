//! `trainer bench`: timings of the generator stages, measured in one run, printed as a table
//! with ratios (no assertions: performance claims live here, not in tests).

use std::time::Instant;

use anyhow::{Context, Result};
use getavatar_core::body_model::BodyModel;
use getavatar_core::burn::tensor::Device;
use getavatar_core::camera::OrbitCamera;
use getavatar_core::generator::{
    block_on_ready, generate_avatar, generate_rigged_async, seed_latents, BodyContext, Generator,
};
use getavatar_core::network::GeneratorConfig;
use getavatar_core::pose_library::PoseLibrary;
use getavatar_core::rasterize::render_views;
use getavatar_core::skinning::pose_body;

fn secs<T>(f: impl FnOnce() -> T) -> (T, f64) {
    let t = Instant::now();
    let v = f();
    (v, t.elapsed().as_secs_f64())
}

pub fn bench(configs: &[String], repeats: usize) -> Result<()> {
    #[allow(deprecated)]
    let device = Device::ndarray();
    let model = BodyModel::default_body()?;
    let lib = PoseLibrary::builtin();
    let poses = ["standing", "walking", "sitting", "arms_up"];
    println!(
        "backend: NdArray (CPU), {} threads available",
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    println!(
        "{:<6} {:>10} {:>10} {:>10} {:>10} {:>10} {:>12} {:>12} {:>8}",
        "config", "setup s", "gen s", "extract s", "r512 s", "r1024 s", "exact/pose s", "fast/pose s", "ratio"
    );
    for name in configs {
        let cfg = GeneratorConfig::preset(name).with_context(|| format!("unknown config `{name}`"))?;
        let ((ctx, g), setup) = secs(|| (BodyContext::new(model.clone(), &cfg), Generator::new(&cfg, 0, &device)));
        let (zg, zt) = seed_latents(&cfg, 1, 2, &device);
        let s = g.styles(zg, zt, 0.7);
        // Network only: styles → triplanes, read back to force execution.
        let (_, gen) = secs(|| {
            let p = g.triplanes(&s);
            let _ = p.geometry.into_data();
        });
        let params: Vec<_> = poses.iter().map(|p| lib.params(p, &[])).collect::<Result<_, _>>()?;
        let (avatar, exact_total) = secs(|| {
            let mut last = None;
            for _ in 0..repeats {
                for p in &params {
                    last = Some(generate_avatar(&g, &ctx, &s, p, &device));
                }
            }
            last
        });
        let exact = exact_total / (repeats * params.len()) as f64;
        let avatar = avatar.context("no avatar")?;
        let extract = (exact - gen).max(0.0);
        let cam = OrbitCamera::default();
        let vp = cam.projection_gl(1.0) * cam.world_to_camera();
        let m = &avatar.mesh;
        let (_, r512) = secs(|| render_views(&m.vertices, &m.faces, &avatar.normals, &avatar.colors, vp, 512, 1));
        let (_, r1024) = secs(|| render_views(&m.vertices, &m.faces, &avatar.normals, &avatar.colors, vp, 1024, 1));
        let rigged = block_on_ready(generate_rigged_async(&g, &ctx, &s, &device));
        let (_, fast_total) = secs(|| {
            for _ in 0..repeats {
                for p in &params {
                    let posed = pose_body(&model, p);
                    let _ = rigged.repose(&ctx, &posed);
                }
            }
        });
        let fast = fast_total / (repeats * params.len()) as f64;
        println!(
            "{:<6} {:>10.3} {:>10.3} {:>10.3} {:>10.3} {:>10.3} {:>12.3} {:>12.4} {:>7.0}×",
            name,
            setup,
            gen,
            extract,
            r512,
            r1024,
            exact,
            fast,
            exact / fast.max(1e-9)
        );
    }
    println!("gen = mapping + triplane synthesis; extract = exact per-pose path minus gen (inverse skinning, decoders, DMTet, normal field, colours);");
    println!("r512/r1024 = CPU reference rasteriser (RGB+normal+mask); ratio = exact per-frame path / fast re-pose path (LBS of the rigged canonical avatar).");
    Ok(())
}
