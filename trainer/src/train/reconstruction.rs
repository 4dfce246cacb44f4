//! The reconstruction terms (not in the paper): the warm-up objective (fixed latents per
//! training subject, L1 to its views), the anchor of adversarial runs, the texture-swap and
//! canonical-space scan terms, and the subjects' latent modes saved with the generator.

use anyhow::{bail, Result};
use getavatar_core::burn::tensor::{Device, Tensor, TensorData};
use getavatar_core::generator::optim::ema_update;
use getavatar_core::generator::pipeline::{Generator, LatentModes, ModePairing, Styles};
use getavatar_core::generator::readback::block_on_ready;
use getavatar_core::io::dataset::Dataset;
use getavatar_core::render::camera::View;
use getavatar_core::render::diff::avatar::{render_avatar_views_async, FakeViews};
use getavatar_core::render::diff::scan_supervision::{scan_losses, texture_loss, CanonicalSamples};
use getavatar_core::util::rng::Rng;

use super::run_config::{Objective, RunConfig, FACE_POINTS_PER_STEP, SCAN_POINTS_PER_STEP};
use super::scan_pools::subject_of_entries;
use super::state::State;
use super::step::{generator_update, load_reals, scalar, track_w_avg, Metrics, StepInputs};
use super::subject_codes::{layer_modes, subject_ws, with_layer_offsets, SubjectCodes};

/// The fixed latent pair (z_geo, z_tex) `[B, z_dim]` of each subject for the reconstruction
/// objective (a function of the run seed and the subject index only).
pub(crate) fn subject_latents(rc: &RunConfig, subjects: &[usize], dev: &Device) -> (Tensor<2>, Tensor<2>) {
    let z = rc.generator.z_dim;
    let draw = |stream: u64| -> Vec<f32> {
        subjects.iter().flat_map(|&s| Rng::new(rc.seed.wrapping_add(stream), s as u64).normals(z)).collect()
    };
    let t = |v: Vec<f32>| Tensor::from_data(TensorData::new(v, [subjects.len(), z]), dev);
    (t(draw(0x9e0)), t(draw(0x7e8)))
}

/// The W codes of the training subjects' fixed latents under `g`, saved with the generator of
/// reconstruction and anchored runs as the modes of multi-modal truncation; None for the
/// paper's objective, whose latents have no subjects.
/// With learned `codes` (`subject_codes`), the modes are the moved codes.
pub(crate) fn subject_modes(
    g: &Generator,
    codes: Option<&SubjectCodes>,
    ds: &Dataset,
    rc: &RunConfig,
    dev: &Device,
) -> Result<Option<LatentModes>> {
    if rc.objective == Objective::Adversarial && rc.lambda_reconstruction == 0.0 {
        return Ok(None);
    }
    let Some(n) = subject_of_entries(ds).into_iter().max().map(|m| m + 1) else { return Ok(None) };
    let (zg, zt) = subject_latents(rc, &(0..n).collect::<Vec<_>>(), dev);
    let offsets = codes.map(|c| c.values_on(dev)).transpose()?;
    if let Some((o, _)) = &offsets {
        if o.dims()[0] != n {
            bail!("the run learns codes for {} subjects, the dataset has {n}", o.dims()[0]);
        }
    }
    let tex_layers = offsets.as_ref().and_then(|(_, t)| layer_modes(t, rc.generator.w_dim));
    let (geo, tex) = subject_ws(g, zg, zt, offsets);
    // With the texture-swap term the colours follow the texture code, so each branch may
    // go to its own nearest subject (one subject's geometry, another's colours).
    let pairing = if rc.lambda_texture_swap > 0.0 { ModePairing::Branch } else { ModePairing::Subject };
    Ok(Some(LatentModes { geo, tex, tex_layers, pairing }))
}

/// The warm-up's reconstruction term: G renders `rc.batch` random views of the dataset (drawn
/// from `rng`), each at its subject's fixed latents and the view's camera and body pose, plus
/// `rc.views_per_subject − 1` further views of the same avatar, and is compared with the real
/// images by L1 (RGB + mask, + normal map where the data has them).
/// With `scans` (one per subject) and `rc.lambda_scan > 0`, adds the weighted scan terms at
/// `SCAN_POINTS_PER_STEP` points of each drawn subject's scan, and with `rc.lambda_face > 0`
/// the weighted face term at `FACE_POINTS_PER_STEP` of its face points. With
/// `rc.lambda_texture_swap > 0` (and more than one subject in the batch), adds the weighted
/// texture-swap term: the same surfaces coloured by the texture field of (the next drawn
/// subject's w_geo, this subject's w_tex), L1 against this subject's RGB views. With
/// a latent spread (`rc.latent_spreads()`), the subjects' codes are moved towards random ones
/// first ([`spread_styles`]). With `codes`, each subject's codes are moved by its learned
/// offsets (`subject_codes`) before anything else.
pub(crate) fn subject_reconstruction<'a>(
    g: &Generator,
    codes: Option<&SubjectCodes>,
    rng: &mut Rng,
    inputs: &StepInputs<'a>,
) -> Result<SubjectReconstruction> {
    let StepInputs { ds, ctx, grids, scans, rc, ad } = *inputs;
    let idx: Vec<usize> = (0..rc.batch).map(|_| rng.below(ds.len())).collect();
    let subjects = subject_of_entries(ds);
    // Each drawn view, then further views of its subject under the same body pose and shape
    // (drawn with replacement; none are drawn with one view per subject, keeping older runs'
    // random streams).
    let body = |i: usize| {
        let l = &ds.entries[i].1;
        (l.global_orient, l.body_pose, l.betas)
    };
    let groups: Vec<Vec<usize>> = idx
        .iter()
        .map(|&i| {
            let mut group = vec![i];
            if rc.views_per_subject > 1 {
                let others: Vec<usize> =
                    (0..ds.len()).filter(|&j| j != i && subjects[j] == subjects[i] && body(j) == body(i)).collect();
                if !others.is_empty() {
                    group.extend((1..rc.views_per_subject).map(|_| others[rng.below(others.len())]));
                }
            }
            group
        })
        .collect();
    let views: Vec<Vec<View>> = groups.iter().map(|g| g.iter().map(|&i| ds.entries[i].1.view()).collect()).collect();
    let drawn: Vec<usize> = idx.iter().map(|&i| subjects[i]).collect();
    if let Some(c) = codes {
        if let Some(s) = drawn.iter().find(|&&s| s >= c.count()) {
            bail!(
                "subject {s} has no learned code (the run learns {}): the dataset has more subjects than the run",
                c.count()
            );
        }
    }
    let (zg, zt) = subject_latents(rc, &drawn, ad);
    let (real_rgb, real_nrm, real_msk, _) = load_reals(ds, &groups.concat(), ad)?;
    let (spread_geo, spread_tex) = rc.latent_spreads();
    let offsets = codes.map(|c| c.select(&drawn));
    let tex_offsets = offsets.as_ref().map(|(_, t)| t.clone());
    let (wg, wt) = subject_ws(g, zg.clone(), zt.clone(), offsets);
    let styles = if spread_geo > 0.0 || spread_tex > 0.0 {
        spread_styles(g, wg, wt, [spread_geo, spread_tex], rng)
    } else {
        g.styles_from_w(wg, wt)
    };
    let styles = with_layer_offsets(styles, tex_offsets);
    let b = styles.geo.dims()[0];
    let swap = (rc.lambda_texture_swap > 0.0 && b > 1).then(|| Styles {
        geo: Tensor::cat(vec![styles.geo.clone().narrow(0, 1, b - 1), styles.geo.clone().narrow(0, 0, 1)], 0),
        tex: styles.tex.clone(),
    });
    let fakes =
        block_on_ready(render_avatar_views_async(g, ctx, &styles, swap.as_ref(), &views, rc.resolution, grids, ad))?;
    let l1 = |a: Tensor<4>, b: Tensor<4>| (a - b).abs().mean();
    let mut texture_swap = None;
    let mut swap_loss = None;
    if let Some(rgb) = fakes.rgb_retextured.clone() {
        let t = l1(rgb, real_rgb.clone());
        texture_swap = Some(scalar(t.clone())?);
        swap_loss = Some(t * rc.lambda_texture_swap);
    }
    let mut loss = l1(fakes.rgb.clone(), real_rgb) + l1(fakes.mask.clone(), real_msk);
    if rc.use_normals {
        loss = loss + l1(fakes.normal.clone(), real_nrm);
    }
    let l1 = scalar(loss.clone())?;
    if let Some(t) = swap_loss {
        loss = loss + t;
    }
    let (mut scan, mut face) = (None, None);
    let use_surface = rc.lambda_scan > 0.0 && !scans.surface.is_empty();
    let use_face = rc.lambda_face > 0.0 && !scans.face.is_empty();
    if use_surface || use_face {
        let planes = &fakes.planes;
        // `per_step` points of each drawn subject's pool, drawn with replacement.
        let mut draw = |pools: &'a [CanonicalSamples], per_step: usize| -> Vec<(&'a CanonicalSamples, Vec<usize>)> {
            idx.iter()
                .map(|&i| {
                    let s = &pools[subjects[i].min(pools.len() - 1)];
                    (s, (0..per_step).map(|_| rng.below(s.len().max(1))).collect())
                })
                .collect()
        };
        if use_surface {
            let terms = scan_losses(g, ctx, planes, &styles, &draw(&scans.surface, SCAN_POINTS_PER_STEP), ad);
            scan = Some((scalar(terms.texture.clone())?, scalar(terms.sdf.clone())?));
            loss = loss + (terms.texture + terms.sdf) * rc.lambda_scan;
        }
        if use_face {
            let term = texture_loss(g, planes, &styles, &draw(&scans.face, FACE_POINTS_PER_STEP), ad);
            face = Some(scalar(term.clone())?);
            loss = loss + term * rc.lambda_face;
        }
    }
    Ok(SubjectReconstruction { loss, l1, scan, face, texture_swap, fakes, zg, zt })
}

/// `w + ψ·(w_random − w)` per row: `w` `[B, w_dim]`, `w_random` likewise, `psi` `[B]`.
pub(crate) fn toward(w: Tensor<2>, w_random: Tensor<2>, psi: &[f32]) -> Tensor<2> {
    let psi = Tensor::<2>::from_data(TensorData::new(psi.to_vec(), [psi.len(), 1]), &w.device());
    w.clone() + (w_random - w) * psi
}

/// The styles of the subjects' W codes `wg`, `wt` (`[B, w_dim]`) with each branch's w moved
/// towards a random w ([`toward`]; ψ uniform in [0, `spread`] per subject and branch; the
/// random w mapped from z ~ N(0, I) by the same mapping network, without gradient): the
/// neighbourhoods that multi-modal truncation samples from (`--latent-spread`). `spreads` is
/// [geometry, texture]; the random draws do not depend on it.
pub(crate) fn spread_styles(g: &Generator, wg: Tensor<2>, wt: Tensor<2>, spreads: [f32; 2], rng: &mut Rng) -> Styles {
    let b = wg.dims()[0];
    let mut branch =
        |mapping: &getavatar_core::generator::network::mapping::MappingNetwork, w: Tensor<2>, spread: f32| {
            let z = mapping.z_dim();
            let random: Vec<f32> = rng.normals(b * z);
            let w_random = mapping.forward(Tensor::from_data(TensorData::new(random, [b, z]), &w.device())).detach();
            let psi: Vec<f32> = (0..b).map(|_| rng.uniform() * spread).collect();
            toward(w, w_random, &psi)
        };
    let (w_geo, w_tex) = (branch(&g.mapping_geo, wg, spreads[0]), branch(&g.mapping_tex, wt, spreads[1]));
    g.styles_from_w(w_geo, w_tex)
}

/// The reconstruction terms of one step ([`subject_reconstruction`]).
pub(crate) struct SubjectReconstruction {
    /// Image L1 plus the weighted scan terms.
    pub(crate) loss: Tensor<1>,
    /// The image L1 alone.
    pub(crate) l1: f32,
    /// Scan texture and SDF terms (unweighted), where used.
    pub(crate) scan: Option<(f32, f32)>,
    /// The face term (unweighted), where used.
    pub(crate) face: Option<f32>,
    /// The texture-swap L1 (unweighted), where used.
    pub(crate) texture_swap: Option<f32>,
    /// The renders (for the eikonal and cross-entropy terms).
    pub(crate) fakes: FakeViews,
    pub(crate) zg: Tensor<2>,
    pub(crate) zt: Tensor<2>,
}

/// One step of the reconstruction warm-up (`Objective::Reconstruction`): the subject
/// reconstruction L1 plus the eikonal and SDF cross-entropy terms; then w_avg tracking and an
/// EMA with StyleGAN2-ADA's ramp-up (half-life at most 5 % of the images seen so far).
pub(crate) fn reconstruction_step(mut st: State, inputs: &StepInputs) -> Result<(State, Metrics)> {
    let rc = inputs.rc;
    let t0 = std::time::Instant::now();
    let b = rc.batch;
    let SubjectReconstruction { loss, l1, scan, face, texture_swap, fakes, zg, zt } =
        subject_reconstruction(&st.g, st.codes.as_ref(), &mut st.rng, inputs)?;
    let metrics = Metrics {
        loss_g: scalar(loss.clone())?,
        reconstruction: Some(l1),
        scan_texture: scan.map(|s| s.0),
        scan_sdf: scan.map(|s| s.1),
        face_texture: face,
        texture_swap,
        eikonal: scalar(fakes.eikonal.clone())?,
        cross_entropy: scalar(fakes.cross_entropy.clone())?,
        triangles: fakes.triangles.iter().sum::<usize>() as f32 / fakes.triangles.len().max(1) as f32,
        ..Metrics::default()
    };
    let total = loss + fakes.eikonal * rc.lambda_eikonal + fakes.cross_entropy * rc.lambda_cross_entropy;
    let grads = total.backward();
    let g = track_w_avg(generator_update(&mut st.adam_g, rc, st.g, &grads), zg, zt, rc.generator.w_avg_beta);
    let geo_mul = rc.lr_codes_geo_mul;
    st.codes = st.codes.map(|c| {
        st.adam_codes.step_scaled(rc.lr_codes, c, &grads, &|name| if name.starts_with("geo") { geo_mul } else { 1.0 })
    });
    let seen_kimg = (st.step + 1) as f32 * b as f32 / 1000.0;
    let half_life = rc.ema_kimg.min(0.05 * seen_kimg);
    let beta = 0.5f32.powf(b as f32 / (half_life * 1000.0).max(1e-8));
    st.g_ema = ema_update(st.g_ema, &g, beta);
    if let (Some(ema), Some(codes)) = (st.codes_ema.take(), &st.codes) {
        st.codes_ema = Some(ema_update(ema, codes, beta));
    }
    st.g = g;
    st.step += 1;
    let (step, seconds) = (st.step, t0.elapsed().as_secs_f64());
    Ok((st, Metrics { step, kimg: step as f64 * b as f64 / 1000.0, seconds, ..metrics }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use getavatar_core::generator::network::GeneratorConfig;

    fn values(t: Tensor<2>) -> Vec<f32> {
        t.into_data().try_to_vec::<f32>().expect("f32")
    }

    #[test]
    fn toward_moves_each_row_its_own_fraction_of_the_way() {
        #[allow(deprecated)]
        let dev = Device::ndarray();
        let t = |v: Vec<f32>| Tensor::<2>::from_data(TensorData::new(v, [3, 2]), &dev);
        let w = t(vec![1.0, 2.0, 1.0, 2.0, 1.0, 2.0]);
        let r = t(vec![3.0, -2.0, 3.0, -2.0, 3.0, -2.0]);
        let got = values(toward(w, r, &[0.0, 0.7, 1.0]));
        let want = [1.0, 2.0, 2.4, -0.8, 3.0, -2.0];
        assert!(got.iter().zip(want).all(|(g, w)| (g - w).abs() < 1e-6), "{got:?}");
    }

    /// Spread 0 is the subjects' own styles; a spread moves each subject's w by at most that
    /// fraction of its distance to some random w, so never further than `spread` × the
    /// largest distance between mapped codes, and not at all when ψ is drawn as 0.
    #[test]
    fn spread_styles_stay_near_the_subjects_codes() {
        #[allow(deprecated)]
        let dev = Device::ndarray();
        let cfg = GeneratorConfig::tiny();
        let g = Generator::new(&cfg, 0, &dev);
        let z = |seed: u64| {
            Tensor::<2>::from_data(TensorData::new(Rng::new(seed, 0).normals(4 * cfg.z_dim), [4, cfg.z_dim]), &dev)
        };
        let (zg, zt) = (z(1), z(2));
        let own = g.styles(zg.clone(), zt.clone(), 1.0);
        let (wg, wt) = (g.mapping_geo.forward(zg), g.mapping_tex.forward(zt));
        let same = spread_styles(&g, wg.clone(), wt.clone(), [0.0, 0.0], &mut Rng::new(3, 0));
        assert_eq!(values(own.geo.clone().reshape([4, -1])), values(same.geo.reshape([4, -1])));
        assert_eq!(values(own.tex.clone().reshape([4, -1])), values(same.tex.reshape([4, -1])));

        let moved = spread_styles(&g, wg.clone(), wt.clone(), [0.7, 0.7], &mut Rng::new(3, 0));
        let max_shift = |a: &Tensor<3>, b: &Tensor<3>| {
            let (a, b) = (values(a.clone().reshape([4, -1])), values(b.clone().reshape([4, -1])));
            a.iter().zip(&b).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max)
        };
        let shift = max_shift(&own.geo, &moved.geo);
        assert!(shift > 0.0, "a spread moves the codes");
        // w of this untrained tiny mapping has entries of order 1: 0.7 of the way to another
        // mapped code moves an entry by well under 10.
        assert!(shift < 10.0, "moved by {shift}");

        // Per branch: a geometry spread alone leaves the texture styles at the subjects' own,
        // and moves the geometry exactly as the same draws did above (the draws do not
        // depend on the spreads).
        let geo_only = spread_styles(&g, wg, wt, [0.7, 0.0], &mut Rng::new(3, 0));
        assert_eq!(values(own.tex.clone().reshape([4, -1])), values(geo_only.tex.reshape([4, -1])));
        assert_eq!(values(moved.geo.reshape([4, -1])), values(geo_only.geo.reshape([4, -1])));
    }
}
