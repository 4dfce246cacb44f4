//! Canonical-space supervision from the training scans — **not in the paper**, a term of the
//! reconstruction warm-up (`trainer train --scans`). The paper learns texture and geometry
//! from rendered images only; on a 2-core CPU at 64² those give a few thousand pixels per
//! subject and step, and garment textures stay blurred. The scans themselves say more: points
//! drawn on a scan's surface ([`crate::scan::sample_surface`]) are carried to canonical space
//! by the generator's own SMPL-guided inverse skinning under the scan's body fit (the mapping
//! its renders use, paper eq. 2), and there
//!
//! - the texture field must give the scan's albedo (L1, in the sRGB-encoded space the image loss
//!   compares in), and
//! - the SDF (template + residual) must be 0 on the surface and ±δ at ±δ along the normal
//!   (L1, in units of [`SDF_UNIT`]).
//!
//! Both are dense, per-point and cheap (no extraction or rasterisation).

use burn::tensor::{Device, Tensor, TensorData};
use glam::Vec3;

use crate::colour::{encode_srgb, encode_srgb_tensor};
use crate::generator::{BodyContext, Generator, Styles};
use crate::geometry::InverseSkinning;
use crate::scan::SurfaceSample;
use crate::skinning::{pose_body, BodyParams};

/// Offset δ (metres) of the off-surface SDF probes along the normal.
pub const SDF_PROBE_OFFSET: f32 = 0.01;
/// SDF errors are measured in units of this length (metres).
pub const SDF_UNIT: f32 = 0.05;

/// Surface points of one scan in canonical space.
#[derive(Clone, Debug, Default)]
pub struct CanonicalSamples {
    pub points: Vec<Vec3>,
    /// Unit normals, rotated to canonical space.
    pub normals: Vec<Vec3>,
    /// Linear albedo.
    pub colors: Vec<Vec3>,
}

impl CanonicalSamples {
    /// Carry body-frame `samples` of a scan whose body fit is `params` to canonical space
    /// (nearest posed body vertex's transform; normals by its rotation's inverse).
    pub fn from_surface(samples: &[SurfaceSample], ctx: &BodyContext, params: &BodyParams) -> Self {
        let posed = pose_body(&ctx.model, params);
        let inv = InverseSkinning::new(&ctx.model, &posed, &ctx.canonical);
        let mut out = Self::default();
        for s in samples {
            let (c, i) = inv.to_canonical(s.position);
            out.points.push(c);
            out.normals.push((inv.rotation(i).transpose() * s.normal).normalize_or_zero());
            out.colors.push(s.color);
        }
        out
    }

    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }
}

/// The two terms, each a mean over the batch's points.
pub struct ScanLosses {
    /// L1 between texture field and albedo, both sRGB-encoded ([`crate::colour`]).
    pub texture: Tensor<1>,
    /// L1 between SDF and its target on and off the surface, in units of [`SDF_UNIT`].
    pub sdf: Tensor<1>,
}

/// The scan terms of avatar b of `styles` (batch B) against `batch[b]`: the samples of its
/// subject and which of them to use (the same count for every b).
pub fn scan_losses(
    g: &Generator,
    ctx: &BodyContext,
    styles: &Styles,
    batch: &[(&CanonicalSamples, Vec<usize>)],
    device: &Device,
) -> ScanLosses {
    let b = batch.len();
    let m = batch.first().map_or(0, |x| x.1.len());
    assert!(batch.iter().all(|x| x.1.len() == m), "scan_losses: the same number of points per avatar");
    let planes = g.triplanes(styles);
    let t3 = |v: Vec<f32>, n: usize| Tensor::<3>::from_data(TensorData::new(v, [b, n, 3]), device);

    // Texture at the surface points.
    let pts: Vec<f32> = batch.iter().flat_map(|(s, idx)| idx.iter().flat_map(|&i| s.points[i].to_array())).collect();
    let want: Vec<f32> =
        batch.iter().flat_map(|(s, idx)| idx.iter().flat_map(|&i| s.colors[i].to_array().map(encode_srgb))).collect();
    let color = encode_srgb_tensor(g.texture_field(&planes, styles, t3(pts, m)));
    let texture = (color - t3(want, m)).abs().mean();

    // SDF at p, p + δn, p − δn: targets 0, +δ, −δ. The template part is a constant.
    let d = SDF_PROBE_OFFSET;
    let (mut probes, mut target) = (Vec::with_capacity(b * m * 9), Vec::with_capacity(b * m * 3));
    for (s, idx) in batch {
        for &i in idx {
            for k in [0.0f32, 1.0, -1.0] {
                let p = s.points[i] + s.normals[i] * (k * d);
                probes.extend(p.to_array());
                target.push(k * d - ctx.template.sample(p));
            }
        }
    }
    let residual = g.sdf_residual(&planes, styles, t3(probes, 3 * m));
    let target = Tensor::<2>::from_data(TensorData::new(target, [b, 3 * m]), device);
    let sdf = (residual - target).abs().mean() / SDF_UNIT;
    ScanLosses { texture, sdf }
}
