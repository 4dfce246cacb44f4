//! The paper's adversarial objective (Sec. 4.5): per step a D phase (non-saturating loss of
//! the three discriminators on reals and detached fakes, lazy finite-difference R1) and a
//! G phase (non-saturating G loss through the differentiable renderer + eikonal + SDF
//! cross-entropy), then w_avg tracking and the EMA of G.

use anyhow::Result;
use getavatar_core::burn::module::Module;
use getavatar_core::burn::tensor::Tensor;
use getavatar_core::generator::losses::{discriminator_loss, generator_loss, r1_penalty};
use getavatar_core::generator::optim::ema_update;
use getavatar_core::io::dataset::Label;
use getavatar_core::render::camera::View;
use getavatar_core::render::diff::avatar::render_avatars;

use super::reconstruction::subject_reconstruction;
use super::state::State;
use super::step::{cameras, generator_update, latents, load_reals, scalar, track_w_avg, Metrics, StepInputs};

/// One step of the paper's objective (D phase, lazy R1, G phase, w_avg, EMA), with the
/// reconstruction anchor where `rc.lambda_reconstruction > 0`.
pub(crate) fn adversarial_step(mut st: State, inputs: &StepInputs) -> Result<(State, Metrics)> {
    let StepInputs { ds, ctx, grids, rc, ad, .. } = *inputs;
    let t0 = std::time::Instant::now();
    let b = rc.batch;
    let real_idx: Vec<usize> = (0..b).map(|_| st.rng.below(ds.len())).collect();
    let fake_labels: Vec<Label> = (0..b).map(|_| ds.entries[st.rng.below(ds.len())].1.clone()).collect();
    let zg = latents(&mut st.rng, b, rc.generator.z_dim, ad);
    let zt = latents(&mut st.rng, b, rc.generator.z_dim, ad);
    let (real_rgb, real_nrm, real_msk, c_real) = load_reals(ds, &real_idx, ad)?;
    let c_fake = cameras(&fake_labels, ad);
    let res = rc.resolution;

    // One render per step: the D phase sees it detached, the G phase through the renderer
    // (D's update does not change G, so re-rendering would give the same images).
    let styles = st.g.styles(zg.clone(), zt.clone(), 1.0);
    let prof = std::env::var_os("GETAVATAR_PROFILE").is_some();
    let lap = |what: &str| {
        if prof {
            eprintln!("{:>8.3} s  {what}", t0.elapsed().as_secs_f64());
        }
    };
    lap("reals loaded");
    let fake_views: Vec<View> = fake_labels.iter().map(Label::view).collect();
    let fakes = render_avatars(&st.g, ctx, &styles, &fake_views, res, grids, ad)?;
    lap("fakes rendered");
    let fake_imgs = [fakes.rgb.clone().detach(), fakes.normal.clone().detach(), fakes.mask.clone().detach()];
    let reals = [real_rgb, real_nrm, real_msk];
    let loss_d = sum_active(rc.use_normals, |k| {
        let lf = st.d[k].forward(fake_imgs[k].clone(), c_fake.clone());
        let lr = st.d[k].forward(reals[k].clone(), c_real.clone());
        discriminator_loss(lf, lr)
    });
    let mut metrics = Metrics { loss_d: scalar(loss_d.clone())?, ..Metrics::default() };
    let mut total_d = loss_d;
    if st.step % rc.r1_every == 0 {
        let (d, rng) = (&st.d, &mut st.rng);
        let r1 = sum_active(rc.use_normals, |k| {
            let c = c_real.clone();
            r1_penalty(|x| d[k].forward(x, c.clone()), reals[k].clone(), rc.r1_directions, 1e-2, rng, ad).mean()
        });
        metrics.r1 = Some(scalar(r1.clone())?);
        total_d = total_d + r1 * (rc.r1_gamma / 2.0 * rc.r1_every as f32);
    }
    lap("D losses");
    let grads = total_d.backward();
    lap("D backward");
    let ratio = rc.r1_every as f32 / (rc.r1_every as f32 + 1.0);
    st.d =
        st.d.into_iter()
            .enumerate()
            .map(|(k, d)| if k != 1 || rc.use_normals { st.adam_d[k].step(rc.lr_d * ratio, d, &grads) } else { d })
            .collect();
    lap("D step");

    // G phase: the same fakes against the updated discriminators, their parameters untracked:
    // the gradient flows through them to the images, and the weight gradients G's update
    // never reads (a second matmul per layer) are not computed.
    let imgs = [fakes.rgb, fakes.normal, fakes.mask];
    let frozen: Vec<_> = st.d.iter().map(|d| d.clone().no_grad()).collect();
    let loss_g = sum_active(rc.use_normals, |k| generator_loss(frozen[k].forward(imgs[k].clone(), c_fake.clone())));
    metrics.loss_g = scalar(loss_g.clone())?;
    metrics.eikonal = scalar(fakes.eikonal.clone())?;
    metrics.cross_entropy = scalar(fakes.cross_entropy.clone())?;
    metrics.triangles = fakes.triangles.iter().sum::<usize>() as f32 / b as f32;
    let mut total_g = loss_g + fakes.eikonal * rc.lambda_eikonal + fakes.cross_entropy * rc.lambda_cross_entropy;
    if rc.lambda_reconstruction > 0.0 {
        // The anchor: the subjects' views at their fixed latents, with their own eikonal and
        // cross-entropy terms (a second surface is extracted).
        let r = subject_reconstruction(&st.g, None, &mut st.rng, inputs)?;
        metrics.reconstruction = Some(r.l1);
        (metrics.scan_texture, metrics.scan_sdf) = (r.scan.map(|s| s.0), r.scan.map(|s| s.1));
        metrics.face_texture = r.face;
        total_g = total_g
            + (r.loss + r.fakes.eikonal * rc.lambda_eikonal + r.fakes.cross_entropy * rc.lambda_cross_entropy)
                * rc.lambda_reconstruction;
    }
    lap("G losses");
    let grads = total_g.backward();
    lap("G backward");
    // w_avg tracking and the EMA of G.
    let g = track_w_avg(generator_update(&mut st.adam_g, rc, st.g, &grads), zg, zt, rc.generator.w_avg_beta);
    let beta = 0.5f32.powf(b as f32 / (rc.ema_kimg * 1000.0).max(1e-8));
    st.g_ema = ema_update(st.g_ema, &g, beta);
    st.g = g;
    lap("G step, w_avg, EMA");
    st.step += 1;
    metrics.step = st.step;
    metrics.kimg = st.step as f64 * b as f64 / 1000.0;
    metrics.seconds = t0.elapsed().as_secs_f64();
    Ok((st, metrics))
}

/// `term(0) [+ term(1)] + term(2)`: a loss summed over the active discriminators (RGB, the
/// normal map's where the data has normal maps, mask), in that order.
fn sum_active(use_normals: bool, mut term: impl FnMut(usize) -> Tensor<1>) -> Tensor<1> {
    let mut sum = term(0);
    if use_normals {
        sum = sum + term(1);
    }
    sum + term(2)
}
