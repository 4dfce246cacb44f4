//! What both objectives' steps share: the step's metrics, real images as tensors, latents,
//! G's Adam update with per-branch rates, and w_avg tracking.

use anyhow::{anyhow, Result};
use getavatar_core::burn::tensor::{Device, Gradients, Tensor, TensorData};
use getavatar_core::generator::optim::Adam;
use getavatar_core::generator::pipeline::{is_geometry_head_param, is_texture_param, Generator};
use getavatar_core::generator::readback::read_f32_now;
use getavatar_core::io::dataset::{Dataset, Label};
use getavatar_core::render::camera::to_row_major;
use getavatar_core::util::rng::Rng;
use serde::Serialize;

use getavatar_core::generator::pipeline::BodyContext;
use getavatar_core::render::diff::avatar::PosedGridCache;

use super::run_config::RunConfig;
use super::scan_pools::ScanPools;

/// What every training step reads: the data, the body, the inverse-skinning cache, the scan
/// samples (empty without `--scans`), the run's settings and the autodiff device.
#[derive(Clone, Copy)]
pub struct StepInputs<'a> {
    pub ds: &'a Dataset,
    pub ctx: &'a BodyContext,
    pub grids: &'a PosedGridCache,
    pub scans: &'a ScanPools,
    pub rc: &'a RunConfig,
    pub ad: &'a Device,
}

/// Losses of one step.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Metrics {
    pub step: u64,
    pub kimg: f64,
    pub loss_g: f32,
    pub loss_d: f32,
    pub r1: Option<f32>,
    pub eikonal: f32,
    pub cross_entropy: f32,
    pub triangles: f32,
    /// The reconstruction L1 (RGB + mask + normal) of the warm-up, or of the anchor of an
    /// adversarial run with `lambda_reconstruction > 0`; absent otherwise.
    pub reconstruction: Option<f32>,
    /// The scan terms (`--scans`): texture L1 and SDF L1; absent without scans.
    pub scan_texture: Option<f32>,
    pub scan_sdf: Option<f32>,
    /// The face term (`--lambda-face`): texture L1 at face points; absent without it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub face_texture: Option<f32>,
    /// The texture-swap RGB L1 (`lambda_texture_swap > 0`); absent otherwise.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub texture_swap: Option<f32>,
    pub seconds: f64,
}

/// The value of a one-element tensor.
pub(crate) fn scalar(t: Tensor<1>) -> Result<f32> {
    read_f32_now(t)?.first().copied().ok_or_else(|| anyhow!("an empty tensor where a scalar was expected"))
}

/// Real images as discriminator inputs: `[B, C, R, R]` in [−1, 1] (RGB, normal, mask) and cameras.
pub(crate) fn load_reals(
    ds: &Dataset,
    idx: &[usize],
    dev: &Device,
) -> Result<(Tensor<4>, Tensor<4>, Tensor<4>, Tensor<2>)> {
    let r = ds.resolution;
    let (mut rgb, mut nrm, mut msk, mut cam) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for &i in idx {
        let s = ds.load(i)?;
        // HWC → CHW.
        for c in 0..3 {
            rgb.extend((0..r * r).map(|k| s.rgb[3 * k + c] * 2.0 - 1.0));
        }
        let n = s.normal.unwrap_or_else(|| vec![0.0; r * r * 3]);
        for c in 0..3 {
            nrm.extend((0..r * r).map(|k| n[3 * k + c]));
        }
        msk.extend(s.mask.iter().map(|m| m * 2.0 - 1.0));
        cam.extend_from_slice(&to_row_major(s.label.world_to_camera));
    }
    let b = idx.len();
    let t4 = |v: Vec<f32>, c: usize| Tensor::<4>::from_data(TensorData::new(v, [b, c, r, r]), dev);
    Ok((t4(rgb, 3), t4(nrm, 3), t4(msk, 1), Tensor::from_data(TensorData::new(cam, [b, 16]), dev)))
}

pub(crate) fn cameras(labels: &[Label], dev: &Device) -> Tensor<2> {
    let v: Vec<f32> = labels.iter().flat_map(|l| to_row_major(l.world_to_camera)).collect();
    Tensor::from_data(TensorData::new(v, [labels.len(), 16]), dev)
}

pub(crate) fn latents(rng: &mut Rng, b: usize, dim: usize, dev: &Device) -> Tensor<2> {
    Tensor::from_data(TensorData::new(rng.normals(b * dim), [b, dim]), dev)
}

/// One Adam step of G, each parameter at `lr_g` times its [`lr_factor`].
pub(crate) fn generator_update(adam: &mut Adam, rc: &RunConfig, g: Generator, grads: &Gradients) -> Generator {
    adam.step_scaled(rc.lr_g, g, grads, &|name| lr_factor(rc, name))
}

/// The factor on `lr_g` of the G parameter at checkpoint path `name`: the texture branch at
/// `lr_texture_mul` (its detail blocks at `lr_texture_mul · lr_texture_detail_mul`), the
/// geometry heads at `lr_geometry_head_mul`, the geometry detail blocks at
/// `lr_geometry_detail_mul`, the rest at 1; with `train_only`, parameters outside it at 0.
pub(crate) fn lr_factor(rc: &RunConfig, name: &str) -> f32 {
    if rc.train_only.as_deref().is_some_and(|p| !name.starts_with(p)) {
        0.0
    } else if name.starts_with("synthesis.texture_detail.") {
        rc.lr_texture_mul * rc.lr_texture_detail_mul
    } else if is_texture_param(name) {
        rc.lr_texture_mul
    } else if is_geometry_head_param(name) {
        rc.lr_geometry_head_mul
    } else if name.starts_with("synthesis.geometry_detail.") {
        rc.lr_geometry_detail_mul
    } else {
        1.0
    }
}

/// Track both mapping networks' w_avg (decay `beta`) on this step's latents.
pub(crate) fn track_w_avg(mut g: Generator, zg: Tensor<2>, zt: Tensor<2>, beta: f32) -> Generator {
    let wg = g.mapping_geo.forward(zg.detach());
    g.mapping_geo = g.mapping_geo.track_w_avg(wg, beta);
    let wt = g.mapping_tex.forward(zt.detach());
    g.mapping_tex = g.mapping_tex.track_w_avg(wt, beta);
    g
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::train::run_config::Objective;

    #[test]
    fn each_parameter_group_learns_at_its_own_factor() {
        let tiny = getavatar_core::generator::network::GeneratorConfig::tiny();
        let mut rc = RunConfig::for_tests(tiny, Objective::Reconstruction);
        (rc.lr_texture_mul, rc.lr_texture_detail_mul) = (8.0, 3.0);
        (rc.lr_geometry_head_mul, rc.lr_geometry_detail_mul) = (0.25, 4.0);
        let cases = [
            ("synthesis.texture_detail.1.constant", 24.0),
            ("synthesis.texture_detail.0.to_texture.weight", 24.0),
            ("synthesis.blocks.2.to_texture.weight", 8.0),
            ("decoders.texture.0.weight", 8.0),
            ("mapping_tex.layers.0.weight", 8.0),
            ("decoders.sdf.0.weight", 0.25),
            ("synthesis.geometry_detail.0.constant", 4.0),
            ("synthesis.blocks.2.convs.0.weight", 1.0),
        ];
        for (name, want) in cases {
            assert_eq!(lr_factor(&rc, name), want, "{name}");
        }
        rc.train_only = Some("synthesis.texture_detail.".into());
        assert_eq!(lr_factor(&rc, "synthesis.texture_detail.1.constant"), 24.0);
        assert_eq!(lr_factor(&rc, "decoders.texture.0.weight"), 0.0);
    }
}
