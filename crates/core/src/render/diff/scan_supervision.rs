//! Canonical-space supervision from the training scans — **not in the paper**, a term of the
//! reconstruction warm-up (`trainer train --scans`). The paper learns texture and geometry
//! from rendered images only; on a 2-core CPU at 64² those give a few thousand pixels per
//! subject and step, and garment textures stay blurred. The scans themselves say more: points
//! drawn on a scan's surface ([`crate::io::scan::sample_surface`]) are carried to canonical space
//! by the generator's own SMPL-guided inverse skinning under the scan's body fit (the mapping
//! its renders use, paper eq. 2), and there
//!
//! - the texture field must give the scan's albedo (L1, in the sRGB-encoded space the image loss
//!   compares in), and
//! - the SDF (template + residual) must be 0 on the surface and ±δ at ±δ along the normal
//!   (L1, in units of [`SDF_UNIT`]).
//!
//! Both are dense, per-point and cheap (no extraction or rasterisation).
//!
//! The **face term** (`trainer train --lambda-face`) is the texture term at points drawn on
//! the face alone ([`FaceRegion`]). A face is about 0.5 % of a clothed body's surface, and its
//! features (eyes 2.6 cm wide, brows, mouth) are 1–2 px in the training renders, where a
//! centimetre of the generated head's geometry moves them between views and L1 averages them
//! out. In canonical space they sit at the same place on every view, and on every subject.

use burn::tensor::{Device, Tensor, TensorData};
use glam::Vec3;

use crate::body::body_model::BodyModel;
use crate::body::body_surface::{nose_on, SurfaceError};
use crate::body::skinning::{pose_body, BodyParams, PosedBody};
use crate::generator::network::synthesis::Triplanes;
use crate::generator::pipeline::{BodyContext, Generator, Styles};
use crate::geometry::InverseSkinning;
use crate::io::scan::{sample_surface_where, RenderableScan, Scan, SurfaceSample};
use crate::render::colour::{encode_srgb, encode_srgb_tensor};

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
        Self::carried(samples, &Self::inverse(ctx, params))
    }

    /// `n` points of `scan`'s face ([`FaceRegion`]), uniform by area, in canonical space: the
    /// triangles whose centroid the body fit `params` carries into `face`. Empty where the
    /// scan has no surface there (a hood, a helmet, a scan that is not of a person).
    pub fn face_of(
        scan: &Scan,
        prepared: &RenderableScan,
        ctx: &BodyContext,
        params: &BodyParams,
        face: &FaceRegion,
        n: usize,
        rng: &mut crate::util::rng::Rng,
    ) -> Self {
        let inv = Self::inverse(ctx, params);
        let samples = sample_surface_where(scan, prepared, n, rng, |c| face.contains(inv.to_canonical(c).0));
        Self::carried(&samples, &inv)
    }

    fn inverse(ctx: &BodyContext, params: &BodyParams) -> InverseSkinning {
        InverseSkinning::new(&ctx.model, &pose_body(&ctx.model, params), &ctx.canonical)
    }

    fn carried(samples: &[SurfaceSample], inv: &InverseSkinning) -> Self {
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

/// The front of the head in canonical space: within 7.5 cm of the canonical body's nose
/// (`body_surface`: the most forward midline vertex of the head) across, from 7.5 cm
/// below it to 8.5 cm above, and in front of a plane 7 cm behind it. That holds the eyes
/// (3.3 cm either side, 3.5 cm up), brows and mouth of the synthetic scans and the skin
/// around them, not the ears or the back of the head.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FaceRegion {
    pub nose: Vec3,
}

impl FaceRegion {
    /// The region of the canonical body of `ctx`; an error for a body that is not a person in
    /// the SMPL layout.
    pub fn of(ctx: &BodyContext) -> Result<Self, SurfaceError> {
        Self::of_body(&ctx.model, &ctx.canonical)
    }

    /// The region of `model`, whose canonical body (`inverse_skinning::canonical_body`) is
    /// `canonical`.
    pub fn of_body(model: &BodyModel, canonical: &PosedBody) -> Result<Self, SurfaceError> {
        Ok(Self { nose: nose_on(model, canonical)? })
    }

    pub fn contains(&self, p: Vec3) -> bool {
        let d = p - self.nose;
        d.x.abs() < 0.075 && (-0.075..0.085).contains(&d.y) && d.z > -0.07
    }
}

/// The two terms, each a mean over the batch's points.
pub struct ScanLosses {
    /// L1 between texture field and albedo, both sRGB-encoded ([`crate::render::colour`]).
    pub texture: Tensor<1>,
    /// L1 between SDF and its target on and off the surface, in units of [`SDF_UNIT`].
    pub sdf: Tensor<1>,
}

/// The points of avatar b of a batch: the samples of its subject and which of them to use
/// (the same count for every b).
pub type ScanBatch<'a> = [(&'a CanonicalSamples, Vec<usize>)];

/// The scan terms of avatar b of `styles` (batch B, its `planes`) against `batch[b]`.
pub fn scan_losses(
    g: &Generator,
    ctx: &BodyContext,
    planes: &Triplanes,
    styles: &Styles,
    batch: &ScanBatch,
    device: &Device,
) -> ScanLosses {
    let (b, m) = batch_shape(batch);
    let texture = texture_loss(g, planes, styles, batch, device);

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
    let residual = g.sdf_residual(planes, styles, batch_points(probes, b, 3 * m, device));
    let target = Tensor::<2>::from_data(TensorData::new(target, [b, 3 * m]), device);
    let sdf = (residual - target).abs().mean() / SDF_UNIT;
    ScanLosses { texture, sdf }
}

/// The texture term alone: L1 between the texture field of avatar b of `styles` (its
/// `planes`) at `batch[b]`'s points and their albedo, both sRGB-encoded, a mean over the
/// batch's points. The face term is this at face points ([`CanonicalSamples::face_of`]).
pub fn texture_loss(
    g: &Generator,
    planes: &Triplanes,
    styles: &Styles,
    batch: &ScanBatch,
    device: &Device,
) -> Tensor<1> {
    let (b, m) = batch_shape(batch);
    let pts: Vec<f32> = batch.iter().flat_map(|(s, idx)| idx.iter().flat_map(|&i| s.points[i].to_array())).collect();
    let want: Vec<f32> =
        batch.iter().flat_map(|(s, idx)| idx.iter().flat_map(|&i| s.colors[i].to_array().map(encode_srgb))).collect();
    let color = encode_srgb_tensor(g.texture_field(planes, styles, batch_points(pts, b, m, device)));
    (color - batch_points(want, b, m, device)).abs().mean()
}

fn batch_shape(batch: &ScanBatch) -> (usize, usize) {
    let m = batch.first().map_or(0, |x| x.1.len());
    assert!(batch.iter().all(|x| x.1.len() == m), "scan terms: the same number of points per avatar");
    (batch.len(), m)
}

fn batch_points(v: Vec<f32>, b: usize, n: usize, device: &Device) -> Tensor<3> {
    Tensor::<3>::from_data(TensorData::new(v, [b, n, 3]), device)
}
