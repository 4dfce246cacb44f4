//! Snapshots: the sample grid (RGB | normal | mask of G_ema at fixed seeds and the data's
//! first labels) and, for reconstruction runs, its L1 against the data.

use anyhow::Result;
use getavatar_core::burn::tensor::{Device, Tensor};
use getavatar_core::generator::pipeline::BodyContext;
use getavatar_core::generator::readback::read_f32_now;
use getavatar_core::io::dataset::{encode_png, Dataset, Label};
use getavatar_core::render::camera::View;
use getavatar_core::render::diff::avatar::{render_avatars, PosedGridCache};
use getavatar_core::util::rng::Rng;
use serde::{Deserialize, Serialize};

use super::reconstruction::subject_latents;
use super::run_config::{Objective, RunConfig};
use super::scan_pools::subject_of_entries;
use super::state::State;
use super::step::{latents, load_reals, scalar};
use super::subject_codes::{subject_ws, with_layer_offsets};

/// L1 (in [0, 1] units, mean over pixels and channels) between G_ema's renders of the
/// sample grid's subjects and the data's views of them: a fixed yardstick of how far a
/// reconstruction run has fitted its subjects, comparable across snapshots of one dataset.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct GridL1 {
    pub step: u64,
    pub rgb: f32,
    pub normal: Option<f32>,
    pub mask: f32,
}

/// RGB | normal | mask rows of G_ema at fixed seeds and the first labels of the dataset: the
/// snapshot's sample grid (PNG) and, for reconstruction runs, its [`GridL1`] against the data.
pub(crate) fn sample_grid(
    st: &State,
    ds: &Dataset,
    ctx: &BodyContext,
    grids: &PosedGridCache,
    rc: &RunConfig,
    plain: &Device,
) -> Result<(Vec<u8>, Option<GridL1>)> {
    let n = 4.min(ds.len());
    let shown: Vec<usize> = (0..n).map(|i| i * ds.len() / n).collect();
    let labels: Vec<Label> = shown.iter().map(|&i| ds.entries[i].1.clone()).collect();
    let styles = if rc.objective == Objective::Reconstruction {
        // The subjects of the shown views (at their learned codes, where the run learns
        // them), to compare with the data.
        let subjects = subject_of_entries(ds);
        let shown_subjects: Vec<usize> = shown.iter().map(|&i| subjects[i]).collect();
        let (zg, zt) = subject_latents(rc, &shown_subjects, plain);
        let offsets = st.codes_ema.as_ref().map(|c| c.values_of(&shown_subjects, plain)).transpose()?;
        let tex_offsets = offsets.as_ref().map(|(_, t)| t.clone());
        let (wg, wt) = subject_ws(&st.g_ema, zg, zt, offsets);
        with_layer_offsets(st.g_ema.styles_from_w(wg, wt), tex_offsets)
    } else {
        let mut rng = Rng::new(12345, 1);
        let (zg, zt) =
            (latents(&mut rng, n, rc.generator.z_dim, plain), latents(&mut rng, n, rc.generator.z_dim, plain));
        st.g_ema.styles(zg, zt, 1.0)
    };
    let views: Vec<View> = labels.iter().map(Label::view).collect();
    let f = render_avatars(&st.g_ema, ctx, &styles, &views, rc.resolution, grids, plain)?;
    let fit = if rc.objective == Objective::Reconstruction {
        let (rgb, nrm, msk, _) = load_reals(ds, &shown, plain)?;
        // Images are in [-1, 1]: half the mean absolute difference is in [0, 1] units.
        let l1 = |a: Tensor<4>, b: Tensor<4>| -> Result<f32> { Ok(scalar((a - b).abs().mean())? / 2.0) };
        Some(GridL1 {
            step: st.step,
            rgb: l1(f.rgb.clone(), rgb)?,
            normal: if rc.use_normals { Some(l1(f.normal.clone(), nrm)?) } else { None },
            mask: l1(f.mask.clone(), msk)?,
        })
    } else {
        None
    };
    let r = rc.resolution;
    let imgs = [f.rgb, f.normal, f.mask.repeat_dim(1, 3)];
    let vals: Vec<Vec<f32>> = imgs.into_iter().map(read_f32_now).collect::<Result<_, _>>()?;
    let (w, h) = (n * r, 3 * r);
    let mut px = vec![0u8; w * h * 3];
    for (row, v) in vals.iter().enumerate() {
        for s in 0..n {
            for y in 0..r {
                for x in 0..r {
                    for c in 0..3 {
                        let val = v[((s * 3 + c) * r + y) * r + x];
                        px[((row * r + y) * w + s * r + x) * 3 + c] = ((val + 1.0) * 127.5).clamp(0.0, 255.0) as u8;
                    }
                }
            }
        }
    }
    Ok((encode_png(w, h, 3, &px)?, fit))
}
