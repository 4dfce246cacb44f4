//! Garment codes: W+ geometry codes that draw what the model's training subjects' codes do
//! not, a dress or a skirt, for the photo encoder's guess to borrow.
//!
//! The demo model draws a skirt as two wide trouser legs at its subjects' codes, and so does
//! the encoder, whose geometry is a softmax over them plus a residual. A person's own W+
//! inversion does draw the dress, and its geometry code draws a dress on other people too.
//! So the encoder file carries the geometry codes of W+ inversions of training people in
//! dresses and skirts (`trainer garment-codes`), and after the encoder's guess
//! [`choose_garment_async`] weighs each of them (with the guess's texture codes) against the
//! guess at the photo's camera. No gradient step: each candidate is one generation in the
//! canonical pose, rigged, re-posed to the photo's body and rasterised on the CPU; a code's
//! outline is judged first, on its geometry alone, and only a code whose outline qualifies
//! gets its texture planes, its normal and texture fields and a loss.
//!
//! **Rule** ([`garment_rule`]). A code replaces the guess's geometry when its render covers at
//! least as much of the person mask, overlaps it nearly as well (mask IoU at most
//! [`IOU_SLACK`] lower) and explains the photo better (lower [`image_loss`]); among those, the
//! lowest loss. A guess whose mask IoU is [`WEIGH_BELOW_IOU`] or more keeps its geometry
//! unweighed. The rule, the threshold and which codes ship were chosen on 32 validation
//! people (`synth-scans --seed 3`), never on the benchmark's (docs/benchmarks.md, "Garment
//! codes after the guess").
//!
//! **File**: tensors `garments/<name>`, `[1, n_geo, w_dim]` each, in the encoder's
//! safetensors file beside its weights (an encoder file without them has no garment codes).

use burn::tensor::{Device, Tensor, TensorData};
use glam::Vec3;

use crate::body::skinning::pose_body;
use crate::generator::checkpoint::SafeTensors;
use crate::generator::pipeline::{canonical_geometry_async, Avatar, BodyContext, Generator, Styles};
use crate::generator::rigging::{generate_rigged_async, RiggedAvatar};
use crate::reconstruction::inversion::{image_loss, mask_iou, InversionError, InversionTarget};
use crate::render::camera::OrbitCamera;
use crate::render::rasterize::render_views;

/// The tensor-name prefix of the garment codes in an encoder file.
pub const GARMENT_PREFIX: &str = "garments/";

/// Named W+ geometry codes (`[1, n_geo, w_dim]` each).
#[derive(Clone, Debug)]
pub struct GarmentCodes {
    pub codes: Vec<(String, Vec<usize>, Vec<f32>)>,
}

/// Why garment codes cannot be used with a generator.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum GarmentCodesError {
    #[error("the garment code `{name}` has shape {shape:?}; this model's geometry codes are [1, {n}, {w}]")]
    Shape { name: String, shape: Vec<usize>, n: usize, w: usize },
    #[error("the garment code `{0}` holds a value that is not finite")]
    NotFinite(String),
}

impl GarmentCodes {
    /// The codes an (already parsed) encoder file carries; None when it has none.
    pub fn from_safetensors(st: &SafeTensors) -> Option<Self> {
        let codes: Vec<_> = st
            .tensors
            .iter()
            .filter_map(|(k, (shape, v))| {
                k.strip_prefix(GARMENT_PREFIX).map(|name| (name.to_string(), shape.clone(), v.clone()))
            })
            .collect();
        (!codes.is_empty()).then_some(Self { codes })
    }

    /// Each code's shape must be the generator's geometry W+ (`[1, n_geo, w_dim]`), its values finite.
    pub fn check(&self, g: &Generator) -> Result<(), GarmentCodesError> {
        let (n, w) = (g.num_ws().0, g.mapping_geo.w_avg_tensor().dims()[1]);
        for (name, shape, v) in &self.codes {
            if shape != &[1, n, w] || v.len() != n * w {
                return Err(GarmentCodesError::Shape { name: name.clone(), shape: shape.clone(), n, w });
            }
            if v.iter().any(|x| !x.is_finite()) {
                return Err(GarmentCodesError::NotFinite(name.clone()));
            }
        }
        Ok(())
    }

    pub fn len(&self) -> usize {
        self.codes.len()
    }

    pub fn is_empty(&self) -> bool {
        self.codes.is_empty()
    }
}

/// One candidate's figures at the photo's camera.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GarmentCandidate {
    /// "guess" for the encoder's own geometry, else the code's name.
    pub name: String,
    pub mask_iou: f32,
    /// The fraction of the person mask the render covers.
    pub coverage: f32,
    /// The [`image_loss`] of its render; None for a code whose outline does not qualify
    /// ([`outline_qualifies`]): its colours are never computed.
    pub loss: Option<f32>,
}

/// The choice: the styles (the guess's, or a code's geometry with the guess's texture), the
/// chosen avatar rigged, and every candidate's figures (the guess first).
pub struct GarmentChoice {
    pub styles: Styles,
    /// The chosen code's name; None when the guess's own geometry stays.
    pub chosen: Option<String>,
    pub rigged: RiggedAvatar,
    pub candidates: Vec<GarmentCandidate>,
}

/// A guess whose outline overlaps the person this well (mask IoU) keeps its geometry without
/// weighing the codes: on the 32 validation people none at 0.92 or above changed.
pub const WEIGH_BELOW_IOU: f32 = 0.92;

/// How much lower a code's mask IoU may be than the guess's (it must cover as much). On the
/// 32 validation people 0.02 and 0.03 chose alike, and one person better than 0.01 did.
pub const IOU_SLACK: f32 = 0.02;

/// Whether candidate `c`'s outline may replace the guess's: it covers at least as much of the
/// person and its mask IoU is at most [`IOU_SLACK`] lower.
pub fn outline_qualifies(guess: &GarmentCandidate, c: &GarmentCandidate) -> bool {
    c.coverage >= guess.coverage && c.mask_iou >= guess.mask_iou - IOU_SLACK
}

/// The index [`choose_garment_async`]'s rule picks among `candidates` (the guess first): the
/// lowest loss among the guess and the codes whose outline qualifies.
pub fn garment_rule(candidates: &[GarmentCandidate]) -> usize {
    let Some(guess) = candidates.first() else { return 0 };
    let mut best = 0;
    for (k, c) in candidates.iter().enumerate().skip(1) {
        let lower = match (c.loss, candidates[best].loss) {
            (Some(l), Some(b)) => l < b,
            (Some(_), None) => true,
            (None, _) => false,
        };
        if lower && outline_qualifies(guess, c) {
            best = k;
        }
    }
    best
}

/// Weigh the guess against the guess with each garment code's geometry at `target`'s camera
/// and body ([`garment_rule`]; none when the guess's mask IoU is [`WEIGH_BELOW_IOU`] or
/// more). Renders without gradients; the avatars are generated on `device`, rasterised on the
/// CPU. A code's outline is judged on its geometry alone ([`canonical_geometry_async`]); only
/// a code whose outline qualifies gets its normal and texture fields and a loss.
/// `guess_rigged`: the guess's avatar (`generate_rigged_async` of `guess`) where the caller has
/// it already (it is generated here otherwise).
pub async fn choose_garment_async(
    g: &Generator,
    ctx: &BodyContext,
    target: &InversionTarget,
    guess: &Styles,
    guess_rigged: Option<RiggedAvatar>,
    codes: &GarmentCodes,
    device: &Device,
) -> Result<GarmentChoice, InversionError> {
    target.validate()?;
    let rigged = match guess_rigged {
        Some(rigged) => rigged,
        None => generate_rigged_async(g, ctx, guess, device).await?,
    };
    let (rgb, mask) = render_rigged(&rigged, ctx, target, WEIGH_SS);
    let mut candidates = vec![GarmentCandidate {
        name: "guess".to_string(),
        mask_iou: mask_iou(&mask, &target.mask),
        coverage: coverage(&mask, &target.mask),
        loss: Some(image_loss(target, &rgb, &mask)),
    }];
    let mut best = (guess.clone(), None, rigged);
    if candidates[0].mask_iou >= WEIGH_BELOW_IOU {
        let (styles, chosen, rigged) = best;
        return Ok(GarmentChoice { styles, chosen, rigged, candidates });
    }
    for (name, shape, v) in &codes.codes {
        crate::util::cooperative::checkpoint().await;
        let geo = Tensor::<3>::from_data(TensorData::new(v.clone(), [shape[0], shape[1], shape[2]]), device);
        let styles = Styles { geo, tex: guess.tex.clone() };
        let geometry = canonical_geometry_async(g, ctx, &styles, device).await?;
        // Rigging and the outline need the geometry alone.
        let n = geometry.mesh.vertices.len();
        let outline = Avatar { mesh: geometry.mesh.clone(), normals: vec![Vec3::Z; n], colors: vec![Vec3::ZERO; n] };
        let mut rigged = RiggedAvatar::new(outline, ctx);
        let mask = render_rigged(&rigged, ctx, target, WEIGH_SS).1;
        let mut c = GarmentCandidate {
            name: name.clone(),
            mask_iou: mask_iou(&mask, &target.mask),
            coverage: coverage(&mask, &target.mask),
            loss: None,
        };
        if outline_qualifies(&candidates[0], &c) {
            (rigged.canonical.normals, rigged.canonical.colors) =
                geometry.vertex_fields_async(g, ctx, &styles, device).await?;
            let (rgb, mask) = render_rigged(&rigged, ctx, target, WEIGH_SS);
            c.loss = Some(image_loss(target, &rgb, &mask));
        }
        candidates.push(c);
        if garment_rule(&candidates) == candidates.len() - 1 {
            best = (styles, Some(name.clone()), rigged);
        }
    }
    let (styles, chosen, rigged) = best;
    Ok(GarmentChoice { styles, chosen, rigged, candidates })
}

/// The fraction of the person (`person` ≥ ½) that `mask` (≥ ½) covers; 1 without a person.
pub fn coverage(mask: &[f32], person: &[f32]) -> f32 {
    let (mut hit, mut n) = (0usize, 0usize);
    for (m, p) in mask.iter().zip(person) {
        if *p >= 0.5 {
            n += 1;
            hit += (*m >= 0.5) as usize;
        }
    }
    if n == 0 {
        1.0
    } else {
        hit as f32 / n as f32
    }
}

/// Samples per pixel and axis of the renders the garment codes are weighed on: the rule and its
/// thresholds ([`WEIGH_BELOW_IOU`], [`outline_qualifies`]) were chosen on these. With 2×2 a
/// pixel that two samples cover reads as covered, so an outline reads a quarter pixel wider
/// than with the 8×8 that `trainer invert`'s figures use.
pub const WEIGH_SS: usize = 2;

/// A rigged avatar re-posed to `target`'s body and rasterised at its camera (`ss`×`ss` samples
/// per pixel, vertex colours): sRGB HWC in [0, 1] and the coverage in [0, 1].
pub fn render_rigged(
    rigged: &RiggedAvatar,
    ctx: &BodyContext,
    target: &InversionTarget,
    ss: usize,
) -> (Vec<f32>, Vec<f32>) {
    let (pos, nrm) = rigged.repose(ctx, &pose_body(&ctx.model, &target.view.body));
    let vp = OrbitCamera::default().projection_gl(1.0) * target.view.world_to_camera;
    let v = render_views(&pos, &rigged.canonical.mesh.faces, &nrm, &rigged.canonical.colors, vp, target.res, ss);
    (v.rgb.iter().map(|c| *c as f32 / 255.0).collect(), v.mask.iter().map(|m| *m as f32 / 255.0).collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

    fn cand(name: &str, mask_iou: f32, coverage: f32, loss: f32) -> GarmentCandidate {
        GarmentCandidate { name: name.into(), mask_iou, coverage, loss: Some(loss) }
    }

    #[test]
    fn the_rule_takes_the_lowest_loss_that_covers_the_person_as_well() {
        // b: the lowest loss but its outline 0.05 worse; e: lower still but covering less;
        // c and d cover as much with outlines within the slack, d the lower loss.
        let c = [
            cand("guess", 0.90, 0.95, 0.20),
            cand("b", 0.85, 0.97, 0.10),
            cand("c", 0.91, 0.96, 0.18),
            cand("d", 0.895, 0.95, 0.15),
            cand("e", 0.92, 0.94, 0.12),
        ];
        assert_eq!(garment_rule(&c), 3);
        // An outline 0.015 below the guess's is within the slack; one 0.025 below is not.
        let near = [cand("guess", 0.90, 0.95, 0.20), cand("n", 0.885, 0.96, 0.15), cand("f", 0.875, 0.99, 0.10)];
        assert_eq!(garment_rule(&near), 1);
        // A code whose outline did not qualify has no loss and never wins.
        let unweighed = GarmentCandidate { name: "u".into(), mask_iou: 0.95, coverage: 0.99, loss: None };
        assert_eq!(garment_rule(&[cand("guess", 0.90, 0.95, 0.20), unweighed.clone()]), 0);
        assert_eq!(garment_rule(&[cand("guess", 0.90, 0.95, 0.20), unweighed, cand("c", 0.91, 0.96, 0.18)]), 2);
        // Nothing explains the photo better: the guess stays.
        assert_eq!(garment_rule(&[cand("guess", 0.9, 0.9, 0.1), cand("b", 0.95, 0.95, 0.12)]), 0);
        assert_eq!(garment_rule(&[cand("guess", 0.9, 0.9, 0.1)]), 0);
        assert_eq!(garment_rule(&[]), 0);
    }

    #[test]
    fn codes_are_read_by_prefix_and_checked_against_the_generator() {
        #[allow(deprecated)] // burn 0.22 marks NdArray deprecated in favour of flex; the project's CPU backend.
        let dev = Device::ndarray();
        let g = Generator::new(&crate::generator::network::GeneratorConfig::tiny(), 0, &dev);
        let (n, w) = (g.num_ws().0, g.mapping_geo.w_avg_tensor().dims()[1]);
        let mut st = SafeTensors { metadata: BTreeMap::new(), tensors: BTreeMap::new() };
        st.tensors.insert("enc/head.weight".into(), (vec![2], vec![0.0; 2]));
        assert!(GarmentCodes::from_safetensors(&st).is_none());
        st.tensors.insert(format!("{GARMENT_PREFIX}dress"), (vec![1, n, w], vec![0.5; n * w]));
        let codes = GarmentCodes::from_safetensors(&st).unwrap();
        assert_eq!(codes.len(), 1);
        assert_eq!(codes.codes[0].0, "dress");
        assert_eq!(codes.check(&g), Ok(()));
        st.tensors.insert(format!("{GARMENT_PREFIX}short"), (vec![1, n - 1, w], vec![0.5; (n - 1) * w]));
        let err = GarmentCodes::from_safetensors(&st).unwrap().check(&g).unwrap_err();
        assert_eq!(err, GarmentCodesError::Shape { name: "short".into(), shape: vec![1, n - 1, w], n, w });
        st.tensors.remove(&format!("{GARMENT_PREFIX}short"));
        st.tensors.insert(format!("{GARMENT_PREFIX}nan"), (vec![1, n, w], vec![f32::NAN; n * w]));
        let err = GarmentCodes::from_safetensors(&st).unwrap().check(&g).unwrap_err();
        assert!(err.to_string().contains("`nan`"), "{err}");
    }
}
