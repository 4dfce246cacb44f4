//! Single-image reconstruction (`inversion`): inverting a render of a known avatar of the tiny
//! generator recovers it; gradients reach both branches' codes; pivotal tuning changes the
//! weights and lowers the loss, and leaves the caller's generator as it was.

use getavatar_core::body::body_model::BodyModel;
use getavatar_core::body::pose_library::PoseLibrary;
use getavatar_core::generator::checkpoint::collect_params;
use getavatar_core::generator::network::GeneratorConfig;
use getavatar_core::generator::pipeline::{is_texture_param, seed_latents, BodyContext, Generator, Styles};
use getavatar_core::generator::readback::block_on_ready;
use getavatar_core::reconstruction::inversion::{
    choose_start_async, lr_schedule, render_images, start_candidates, InversionError, InversionOptions,
    InversionTarget, Inverter, Phase, COLLAPSED_IOU, MIN_WARMUP_STEPS,
};
use getavatar_core::render::camera::{OrbitCamera, View};
use getavatar_core::render::diff::avatar::{render_avatars, PosedGridCache};

mod common;
use common::{cpu, values};

const RES: usize = 64;

fn setup() -> (GeneratorConfig, BodyContext, InversionTarget, Styles) {
    let dev = cpu();
    let cfg = GeneratorConfig::tiny();
    let ctx = BodyContext::new(BodyModel::default_body().unwrap(), &cfg);
    let g = Generator::new(&cfg, 0, &dev);
    let (zg, zt) = seed_latents(&cfg, 11, 12, &dev);
    let truth = g.styles(zg, zt, 1.0);
    let body = PoseLibrary::builtin().params("walking", &[]).unwrap();
    let cam = OrbitCamera { yaw: 0.4, pitch: 0.05, ..OrbitCamera::default() };
    let view = View { world_to_camera: cam.world_to_camera(), body };
    let f =
        render_avatars(&g, &ctx, &truth, std::slice::from_ref(&view), RES, &PosedGridCache::default(), &dev).unwrap();
    let (rgb, mask) = render_images(&f).unwrap();
    (cfg, ctx, InversionTarget { view, res: RES, rgb, mask }, truth)
}

fn l1(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).sum::<f32>() / a.len() as f32
}

#[test]
fn inverting_a_known_render_recovers_it_and_pti_refines_it() {
    let (cfg, ctx, target, _truth) = setup();
    let dev = cpu().autodiff();
    let g = Generator::new(&cfg, 0, &dev);
    let before = collect_params(&g).unwrap();
    // Start at the generator's mean codes (the untrained generator's w_avg is 0).
    let cands = start_candidates(&g, None);
    assert_eq!(cands.len(), 1);
    let start = cands[0].styles.clone();
    let opts =
        InversionOptions { steps: 80, pti_steps: 60, lr: 0.03, locality_every: 2, ..InversionOptions::default() };
    let mut inv = Inverter::new(g.clone(), &ctx, None, target.clone(), &start, opts, &dev).unwrap();

    let mut latent = Vec::new();
    let mut pivotal = Vec::new();
    let s0 = inv.styles();
    while let Some(r) = inv.step().unwrap() {
        if latent.len() == 1 && r.phase == Phase::Latent {
            // After one step both branches' codes moved: gradients reached w_geo and w_tex.
            let s1 = inv.styles();
            let moved = |a: &getavatar_core::burn::tensor::Tensor<3>, b: &getavatar_core::burn::tensor::Tensor<3>| {
                values((a.clone() - b.clone()).abs().sum())[0]
            };
            assert!(moved(&s1.geo, &s0.geo) > 0.0, "w_geo did not move");
            assert!(moved(&s1.tex, &s0.tex) > 0.0, "w_tex did not move");
        }
        match r.phase {
            Phase::Latent => latent.push(r.terms),
            Phase::Pivotal => pivotal.push(r.terms),
            Phase::Done => unreachable!(),
        }
    }
    assert_eq!((latent.len(), pivotal.len()), (80, 60));
    let total: Vec<f32> = latent.iter().map(|t| t.total).collect();
    eprintln!("W+ losses: {total:?}");
    eprintln!("PTI losses: {:?}", pivotal.iter().map(|t| t.total).collect::<Vec<_>>());
    // The loss falls monotonically over the first steps (the warm-up's small steps).
    for k in 1..5 {
        assert!(total[k] < total[k - 1], "step {k}: {} ≥ {}", total[k], total[k - 1]);
    }
    let (first, last) = (&latent[0], latent.last().unwrap());
    assert!(last.rgb_l1 < 0.5 * first.rgb_l1, "RGB L1 {} → {}", first.rgb_l1, last.rgb_l1);
    // PTI: the locality term ran on even steps, and the loss improved.
    assert!(pivotal[0].locality.is_some() && pivotal[1].locality.is_none());
    // The image loss at the pivot jumps from step to step (the tiny generator's surface gains
    // and loses triangles as its weights move), so compare the mean of the last 20 steps with
    // the first: 60 steps lower it by ≈ 17 % (a single last step against the first was within
    // that noise).
    let image: Vec<f32> = pivotal.iter().map(|t| t.rgb_l1 + t.rgb_mse).collect();
    let tail = image[image.len() - 20..].iter().sum::<f32>() / 20.0;
    assert!(
        tail < 0.95 * image[0],
        "PTI did not lower the image loss: {} → mean {tail} over the last 20 steps",
        image[0]
    );

    // The result at the photo's camera: mask IoU ≥ 0.95 and colours close to the target's.
    let f = inv.render().unwrap();
    let (rgb, mask) = render_images(&f).unwrap();
    let iou = getavatar_core::reconstruction::inversion::mask_iou(&mask, &target.mask);
    let start_f =
        render_avatars(&g, &ctx, &start, std::slice::from_ref(&target.view), RES, &PosedGridCache::default(), &dev)
            .unwrap();
    let (rgb0, _) = render_images(&start_f).unwrap();
    eprintln!("IoU {iou}, RGB L1 start {} → end {}", l1(&rgb0, &target.rgb), l1(&rgb, &target.rgb));
    assert!(iou >= 0.95, "mask IoU {iou}");
    assert!(l1(&rgb, &target.rgb) < 0.5 * l1(&rgb0, &target.rgb));

    // PTI tuned the inverter's generator (synthesis/decoders, not mapping) and left the
    // caller's untouched (what a cancelled reconstruction keeps).
    let after = collect_params(inv.generator()).unwrap();
    let unchanged = collect_params(&g).unwrap();
    let diff = |a: &[getavatar_core::generator::checkpoint::NamedTensor],
                b: &[getavatar_core::generator::checkpoint::NamedTensor],
                pre: &str| {
        a.iter()
            .zip(b)
            .filter(|(x, _)| x.0.starts_with(pre))
            .map(|(x, y)| x.2.iter().zip(&y.2).map(|(p, q)| (p - q).abs()).sum::<f32>())
            .sum::<f32>()
    };
    assert!(diff(&after, &before, "synthesis.") > 0.0, "PTI left the synthesis weights as they were");
    assert!(diff(&after, &before, "decoders.") > 0.0);
    assert_eq!(diff(&after, &before, "mapping_"), 0.0, "PTI changed the mapping networks");
    assert_eq!(diff(&unchanged, &before, ""), 0.0, "the caller's generator changed");
}

/// A W+ run that diverges (here a learning rate far too large for these codes) ends on the
/// codes of its lowest loss, not on where it was thrown; a settled run keeps its last codes.
#[test]
fn a_diverged_w_plus_run_ends_on_its_best_codes() {
    let (cfg, ctx, target, _truth) = setup();
    let g = Generator::new(&cfg, 0, &cpu().autodiff());
    let start = start_candidates(&g, None)[0].styles.clone();
    let run = |lr: f32, steps: usize| {
        let opts =
            InversionOptions { steps, pti_steps: 0, lr, warmup: 0.0, rampdown: 0.0, ..InversionOptions::default() };
        run_inversion(&g, &ctx, &target, &start, opts, &codes)
    };
    let (seen, end) = run(4.0, 4);
    assert_diverged_and_ended_on_its_best(&seen, &end);
    // A settled run (small steps): its last codes are the update after the last step, not a
    // code it rendered.
    let (seen, end) = run(0.01, 3);
    assert!(seen.iter().all(|s| s.state != end), "a settled run keeps its last update");
}

/// PTI that diverges (a rate far too large for these colours) ends on the weights of its lowest
/// image loss, not where it was thrown; a settled run keeps its last update.
#[test]
fn a_diverged_pti_run_ends_on_its_best_weights() {
    let (cfg, ctx, target, _truth) = setup();
    let g = Generator::new(&cfg, 0, &cpu().autodiff());
    let start = start_candidates(&g, None)[0].styles.clone();
    let run = |lr: f32, texture: f32, steps: usize| {
        let opts = InversionOptions {
            steps: 0,
            pti_steps: steps,
            pti_lr: lr,
            pti_texture_lr_mul: texture,
            locality_every: 0,
            ..InversionOptions::default()
        };
        run_inversion(&g, &ctx, &target, &start, opts, &weights)
    };
    // The texture branch at 3e-2 throws the colours off while the outline holds (a collapse of
    // the outline restarts instead, `COLLAPSED_IOU`): the tiny generator's losses go 0.188,
    // 0.345, 0.176, 0.193 at mask IoUs 0.968–0.989.
    let (seen, end) = run(1e-4, 300.0, 4);
    assert_diverged_and_ended_on_its_best(&seen, &end);
    let (seen, end) = run(1e-5, 1.0, 3);
    assert!(seen.iter().all(|s| s.state != end), "a settled run keeps its last update");
}

/// PTI whose mask IoU collapses (a rate far too large for these weights) goes back to the
/// weights of its lowest image loss at the step that shows it (making no update there), and
/// goes on at half the rate, warmed up again; a settled run never restarts.
#[test]
fn a_collapsing_pti_run_restarts_from_its_best_weights_at_half_the_rate() {
    let (cfg, ctx, target, _truth) = setup();
    let g = Generator::new(&cfg, 0, &cpu().autodiff());
    let start = start_candidates(&g, None)[0].styles.clone();
    let steps = 12;
    let run = |lr: f32| {
        let opts = InversionOptions {
            steps: 0,
            pti_steps: steps,
            pti_lr: lr,
            locality_every: 0,
            ..InversionOptions::default()
        };
        run_inversion(&g, &ctx, &target, &start, opts, &weights).0
    };
    // At 0.01 the tiny generator's first update takes the mask IoU from 0.968 to 0.342.
    assert_restarted_once(&run(0.01), 0.01, steps);
    assert!(run(1e-5).iter().all(|s| s.lr > 0.0 && !s.restarted), "a settled run restarted");
}

/// A W+ run whose mask IoU collapses goes back to the codes of its lowest loss the same way
/// (`COLLAPSED_IOU`), at half the rate, warmed up again; a settled run never restarts.
#[test]
fn a_collapsing_w_plus_run_restarts_from_its_best_codes_at_half_the_rate() {
    let (cfg, ctx, target, _truth) = setup();
    let g = Generator::new(&cfg, 0, &cpu().autodiff());
    let start = start_candidates(&g, None)[0].styles.clone();
    let steps = 12;
    let run = |lr: f32| {
        let opts =
            InversionOptions { steps, pti_steps: 0, lr, warmup: 0.0, rampdown: 0.0, ..InversionOptions::default() };
        run_inversion(&g, &ctx, &target, &start, opts, &codes).0
    };
    // At a rate of 2 the tiny generator's first update takes the mask IoU from 0.968 to 0.716.
    assert_restarted_once(&run(2.0), 2.0, steps);
    assert!(run(0.01).iter().all(|s| s.lr > 0.0 && !s.restarted), "a settled run restarted");
}

/// One step of a run: its render's mask IoU, its loss, its rate and the state it started from.
struct Seen {
    iou: f32,
    loss: f32,
    lr: f32,
    restarted: bool,
    state: Vec<f32>,
}

/// Every step of an inversion of `target` from `start` with `opts` (a `Seen` each, its state
/// read by `state` before the step), and the state after the last.
fn run_inversion(
    g: &Generator,
    ctx: &BodyContext,
    target: &InversionTarget,
    start: &Styles,
    opts: InversionOptions,
    state: &dyn Fn(&Inverter) -> Vec<f32>,
) -> (Vec<Seen>, Vec<f32>) {
    let mut inv = Inverter::new(g.clone(), ctx, None, target.clone(), start, opts, &cpu().autodiff()).unwrap();
    let mut seen = Vec::new();
    loop {
        let before = state(&inv);
        let Some(r) = inv.step().unwrap() else { break };
        seen.push(Seen { iou: r.terms.mask_iou, loss: r.terms.total, lr: r.lr, restarted: r.restarted, state: before });
    }
    let end = state(&inv);
    (seen, end)
}

/// The W+ codes of the geometry branch, and the generator's weights.
fn codes(inv: &Inverter) -> Vec<f32> {
    values(inv.styles().geo.reshape([-1]))
}
fn weights(inv: &Inverter) -> Vec<f32> {
    collect_params(inv.generator()).unwrap().into_iter().flat_map(|t| t.2).collect()
}

/// The last loss of `seen` lies more than 5 % above its lowest (the run diverged), and the
/// run ended (`end`) on the state of that lowest loss.
fn assert_diverged_and_ended_on_its_best(seen: &[Seen], end: &[f32]) {
    let best = seen.iter().min_by(|a, b| a.loss.total_cmp(&b.loss)).unwrap();
    let last = seen.last().unwrap().loss;
    let losses: Vec<f32> = seen.iter().map(|s| s.loss).collect();
    assert!(last > 1.05 * best.loss, "the run did not diverge: losses {losses:?}");
    assert!(end == best.state, "a diverged run ends on the state of its lowest loss {}", best.loss);
}

/// The first step of `seen` whose mask IoU lies `COLLAPSED_IOU` below the highest before it
/// made no update, the next starts from the state of the lowest loss before it (and renders
/// as it did), at half the constant rate `lr` warmed up again.
fn assert_restarted_once(seen: &[Seen], lr: f32, steps: usize) {
    let ious: Vec<f32> = seen.iter().map(|s| s.iou).collect();
    let collapsed = |k: usize| ious[k] < ious[..k].iter().copied().fold(0.0, f32::max) - COLLAPSED_IOU;
    let k = (1..steps - 1).find(|k| collapsed(*k)).unwrap_or_else(|| panic!("no collapse: mask IoUs {ious:?}"));
    assert_eq!(seen[k].lr, 0.0, "the collapsed step {k} made an update");
    assert!(seen[k].restarted && seen.iter().take(k).all(|s| !s.restarted), "only step {k} reports a restart");
    let best = (0..k).min_by(|a, b| seen[*a].loss.total_cmp(&seen[*b].loss)).unwrap();
    assert!(
        seen[k + 1].state == seen[best].state,
        "step {k}'s restart is not from the state of the lowest loss (step {best})"
    );
    assert_eq!(seen[k + 1].iou, seen[best].iou, "the restored state renders as it did");
    let rate = lr_schedule(lr, k + 1, steps, 0.0, 0.0) * 0.5 / MIN_WARMUP_STEPS;
    assert!((seen[k + 1].lr - rate).abs() < 1e-9, "after the restart the rate is {} not {rate}", seen[k + 1].lr);
}

/// PTI's texture factor scales the texture branch's rate alone: Adam's first step moves every
/// coordinate with a gradient by about the rate, so after one step at `lr` the texture
/// weights move by up to `factor · lr` and the rest by up to `lr`; the mapping networks stay.
#[test]
fn pti_tunes_the_texture_branch_at_its_own_rate() {
    let (cfg, ctx, target, _truth) = setup();
    let dev = cpu().autodiff();
    let g = Generator::new(&cfg, 0, &dev);
    let start = start_candidates(&g, None)[0].styles.clone();
    let lr = 1e-4;
    // Largest move per group (texture branch, mapping networks, the rest) after one PTI step.
    let moves = |factor: f32| -> [f32; 3] {
        let opts = InversionOptions {
            steps: 0,
            pti_steps: 2,
            pti_lr: lr,
            pti_texture_lr_mul: factor,
            locality_every: 0,
            ..InversionOptions::default()
        };
        let mut inv = Inverter::new(g.clone(), &ctx, None, target.clone(), &start, opts, &dev).unwrap();
        inv.step().unwrap().unwrap();
        let before = collect_params(&g).unwrap();
        let after = collect_params(inv.generator()).unwrap();
        let mut m = [0.0f32; 3];
        for (a, b) in before.iter().zip(&after) {
            assert_eq!(a.0, b.0);
            let group = if a.0.starts_with("mapping_") {
                1
            } else if is_texture_param(&a.0) {
                0
            } else {
                2
            };
            let d = a.2.iter().zip(&b.2).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
            m[group] = m[group].max(d);
        }
        m
    };
    let [tex, mapping, rest] = moves(4.0);
    assert_eq!(mapping, 0.0, "the mapping networks are not tuned");
    assert!((rest - lr).abs() < 0.2 * lr, "the rest moves by the rate: {rest}");
    assert!((tex - 4.0 * lr).abs() < 0.8 * lr, "the texture branch moves by 4× the rate: {tex}");
    let [tex, _, rest] = moves(0.0);
    assert_eq!(tex, 0.0, "a factor of 0 holds the texture branch");
    assert!((rest - lr).abs() < 0.2 * lr, "{rest}");
}

#[test]
fn the_start_is_the_candidate_that_explains_the_image() {
    let (cfg, ctx, target, truth) = setup();
    let dev = cpu();
    let g = Generator::new(&cfg, 0, &dev);
    let mut cands = start_candidates(&g, None);
    let (zg, zt) = seed_latents(&cfg, 3, 4, &dev);
    cands.push(getavatar_core::reconstruction::inversion::StartCandidate {
        name: "other".into(),
        styles: g.styles(zg, zt, 1.0),
    });
    cands.push(getavatar_core::reconstruction::inversion::StartCandidate { name: "truth".into(), styles: truth });
    let (best, losses) = block_on_ready(choose_start_async(&g, &ctx, &target, &cands, &dev)).unwrap();
    assert_eq!(cands[best].name, "truth", "losses {losses:?}");
    assert!(losses[best] < 1e-3, "{losses:?}");
}

#[test]
fn bad_targets_are_refused_with_reasons() {
    let (cfg, ctx, target, truth) = setup();
    let dev = cpu().autodiff();
    let g = Generator::new(&cfg, 0, &dev);
    let run = |t: InversionTarget| {
        Inverter::new(g.clone(), &ctx, None, t, &truth, InversionOptions::default(), &dev).err().map(|e| e.to_string())
    };
    let mut t = target.clone();
    t.mask = vec![0.0; RES * RES];
    assert!(matches!(
        Inverter::new(g.clone(), &ctx, None, t, &truth, InversionOptions::default(), &dev),
        Err(InversionError::EmptyMask)
    ));
    let mut t = target.clone();
    t.rgb.pop();
    assert!(run(t).unwrap().contains("rgb has 12287 values"));
    let mut t = target.clone();
    t.rgb[5] = f32::NAN;
    assert!(run(t).unwrap().contains("not finite"));
    let mut t = target.clone();
    t.res = 8;
    assert!(run(t).unwrap().contains("at least 16"));
}

/// The shipped demo model (its config, generator and file) and encoder file, with a body context.
struct Shipped {
    cfg: GeneratorConfig,
    g: Generator,
    model_bytes: Vec<u8>,
    encoder_bytes: Vec<u8>,
    ctx: BodyContext,
}

fn shipped() -> Shipped {
    use getavatar_core::generator::checkpoint::{config_with_saved_resolutions, load_generator};
    let root = concat!(env!("CARGO_MANIFEST_DIR"), "/../assets/models/");
    let model_bytes = std::fs::read(format!("{root}demo.safetensors")).unwrap();
    let cfg = config_with_saved_resolutions(&model_bytes, &GeneratorConfig::demo());
    let g = load_generator(&model_bytes, &cfg, &cpu()).unwrap();
    let encoder_bytes = std::fs::read(format!("{root}encoder.safetensors")).unwrap();
    let ctx = BodyContext::new(BodyModel::default_body().unwrap(), &cfg);
    Shipped { cfg, g, model_bytes, encoder_bytes, ctx }
}

/// The shipped encoder on renders of known codes of the shipped demo model (codes and
/// bodies it never saw: other seeds than `train-encoder` draws, a library pose, a fixed
/// camera): its guess is nearer the true codes than w_avg and its avatar's silhouette
/// matches the render better.
#[test]
fn the_shipped_encoder_guesses_known_codes_better_than_w_avg() {
    use getavatar_core::generator::checkpoint::load_latent_modes;
    use getavatar_core::reconstruction::encoder::load_encoder;
    use getavatar_core::reconstruction::inversion::{encoder_start, mask_iou, masked_psnr};
    let Shipped { cfg, g, model_bytes, encoder_bytes, ctx } = shipped();
    let dev = cpu();
    let modes = load_latent_modes(&model_bytes, &dev).unwrap();
    let enc = load_encoder(&encoder_bytes, &dev).unwrap();
    let grids = PosedGridCache::default();
    let res = 128;
    let avg = start_candidates(&g, None).remove(0).styles;
    let (mut d_enc, mut d_avg, mut iou_enc, mut iou_avg, mut psnr_enc, mut psnr_avg) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    let cases = [(101, "walking", 0.3), (102, "arms_up", -0.5), (103, "standing", 0.0)];
    for (seed, pose, yaw) in cases {
        let (zg, zt) = seed_latents(&cfg, seed, seed + 1000, &dev);
        let truth = g.styles_with(zg, zt, 0.8, modes.as_ref());
        let body = PoseLibrary::builtin().params(pose, &[]).unwrap();
        let cam = OrbitCamera { yaw, pitch: 0.05, ..OrbitCamera::default() };
        let view = View { world_to_camera: cam.world_to_camera(), body };
        let render = |s: &Styles| {
            let f = render_avatars(&g, &ctx, s, std::slice::from_ref(&view), res, &grids, &dev).unwrap();
            render_images(&f).unwrap()
        };
        let (rgb, mask) = render(&truth);
        let target = InversionTarget { view: view.clone(), res, rgb, mask: mask.clone() };
        let guess = encoder_start(&enc, &g, &ctx.model, &target, &dev).unwrap();
        let dist = |s: &Styles| {
            let d = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f32>();
            let (tg, tt) = (values(truth.geo.clone()), values(truth.tex.clone()));
            let n = (tg.len() + tt.len()) as f32;
            (d(&values(s.geo.clone()), &tg) + d(&values(s.tex.clone()), &tt)) / n
        };
        // w_avg's styles are [1, n, w] like the guess's.
        d_enc += dist(&guess);
        d_avg += dist(&avg);
        let ((ge, me), (ga, ma)) = (render(&guess), render(&avg));
        iou_enc += mask_iou(&me, &mask);
        iou_avg += mask_iou(&ma, &mask);
        psnr_enc += masked_psnr(&ge, &target.rgb, &mask);
        psnr_avg += masked_psnr(&ga, &target.rgb, &mask);
    }
    let n = cases.len() as f32;
    let (d_enc, d_avg, iou_enc, iou_avg, psnr_enc, psnr_avg) =
        (d_enc / n, d_avg / n, iou_enc / n, iou_avg / n, psnr_enc / n, psnr_avg / n);
    eprintln!(
        "code MSE {d_enc:.4} (w_avg {d_avg:.4}); mask IoU {iou_enc:.3} (w_avg {iou_avg:.3}); \
         masked PSNR {psnr_enc:.2} dB (w_avg {psnr_avg:.2})"
    );
    // Much of a code's spread changes little in the image (the model was trained on 64
    // subjects' codes): the code distance drops a little; the colours are nearer too.
    assert!(d_enc < 0.98 * d_avg, "code MSE {d_enc} vs w_avg's {d_avg}");
    assert!(iou_enc >= iou_avg - 0.005 && iou_enc >= 0.9, "mask IoU {iou_enc} vs w_avg's {iou_avg}");
    assert!(psnr_enc > psnr_avg + 0.3, "masked PSNR {psnr_enc} vs w_avg's {psnr_avg}");
}

/// The shipped encoder file's garment codes (`reconstruction::garment_codes`): a render whose
/// geometry is one of them (a dress, the texture the guess's) gets that code's geometry, and
/// a render of the guess itself keeps the guess's.
#[test]
fn a_render_of_a_garment_code_gets_that_code_and_the_guess_keeps_its_own() {
    use getavatar_core::burn::tensor::{Tensor, TensorData};
    use getavatar_core::generator::checkpoint::parse_safetensors;
    use getavatar_core::reconstruction::encoder::load_encoder;
    use getavatar_core::reconstruction::garment_codes::{choose_garment_async, GarmentCodes};
    use getavatar_core::reconstruction::inversion::encoder_start;
    let Shipped { g, encoder_bytes, ctx, .. } = shipped();
    let dev = cpu();
    let enc = load_encoder(&encoder_bytes, &dev).unwrap();
    let all =
        GarmentCodes::from_safetensors(&parse_safetensors(&encoder_bytes).unwrap()).expect("shipped garment codes");
    all.check(&g).unwrap();
    // Three codes keep the test short; the photo is drawn by the second.
    let codes = GarmentCodes { codes: all.codes[..3].to_vec() };
    let res = 128;
    let body = PoseLibrary::builtin().params("walking", &[]).unwrap();
    let cam = OrbitCamera { yaw: 0.3, pitch: 0.05, ..OrbitCamera::default() };
    let view = View { world_to_camera: cam.world_to_camera(), body };
    let render = |s: &Styles| {
        let f =
            render_avatars(&g, &ctx, s, std::slice::from_ref(&view), res, &PosedGridCache::default(), &dev).unwrap();
        let (rgb, mask) = render_images(&f).unwrap();
        InversionTarget { view: view.clone(), res, rgb, mask }
    };
    let avg = start_candidates(&g, None).remove(0).styles;
    let (name, shape, v) = &codes.codes[1];
    let geo = Tensor::<3>::from_data(TensorData::new(v.clone(), [shape[0], shape[1], shape[2]]), &dev);
    let target = render(&Styles { geo, tex: avg.tex.clone() });
    let guess = encoder_start(&enc, &g, &ctx.model, &target, &dev).unwrap();
    let choice = block_on_ready(choose_garment_async(&g, &ctx, &target, &guess, None, &codes, &dev)).unwrap();
    let figures: Vec<String> =
        choice.candidates.iter().map(|c| format!("{} {:.3} / {:?}", c.name, c.mask_iou, c.loss)).collect();
    eprintln!("the code's render: {}", figures.join(", "));
    assert_eq!(choice.chosen.as_ref(), Some(name), "{figures:?}");
    let (guess_c, chosen_c) = (&choice.candidates[0], &choice.candidates[2]);
    assert!(chosen_c.mask_iou > guess_c.mask_iou + 0.02 && chosen_c.mask_iou > 0.9, "{figures:?}");
    // A render of the guess itself: no code explains it better.
    let target = render(&guess);
    let choice = block_on_ready(choose_garment_async(&g, &ctx, &target, &guess, None, &codes, &dev)).unwrap();
    let figures: Vec<String> =
        choice.candidates.iter().map(|c| format!("{} {:.3} / {:?}", c.name, c.mask_iou, c.loss)).collect();
    eprintln!("the guess's render: {}", figures.join(", "));
    assert_eq!(choice.chosen, None, "{figures:?}");
    assert!(choice.candidates[0].mask_iou > 0.9, "{figures:?}");
}
