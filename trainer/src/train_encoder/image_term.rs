//! The encoder's image term (`train-encoder --image-data`): its guess for a scan photo rendered
//! through the differentiable renderer at the photo's camera and at another view of the same
//! subject, compared with the scan's own renders as the inversion compares them.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{bail, Context, Result};
use getavatar_core::body::body_model::BodyModel;
use getavatar_core::burn::tensor::{Device, Tensor, TensorData};
use getavatar_core::generator::pipeline::{BodyContext, Generator};
use getavatar_core::generator::readback::read_f32_now;
use getavatar_core::io::dataset::Dataset;
use getavatar_core::reconstruction::encoder::{resample, BodyMaps, Encoder, EncoderImage, EncoderInput};
use getavatar_core::reconstruction::inversion::{mask_iou, masked_psnr};
use getavatar_core::render::camera::View;
use getavatar_core::render::diff::avatar::{render_avatar_views, FakeViews, PosedGridCache};
use getavatar_core::util::rng::Rng;
use glam::Vec3;

use super::pairs::{perturbed_body, perturbed_camera};
use super::{augment, HELD_SUBJECTS, IMAGE_RES};

/// A `prepare` dataset of scans as photos for the encoder, with the generator (on the
/// autodiff device, its weights without gradients) that renders the encoder's guesses.
pub struct ScanPhotos {
    ds: Dataset,
    g: Generator,
    model: BodyModel,
    /// Entry indices per subject: the training subjects and the held-out ones.
    train: Vec<Vec<usize>>,
    held: Vec<Vec<usize>>,
    grids: PosedGridCache,
}

/// One scan photo: the encoder's input and the images its guess must match.
pub struct ScanPhoto {
    pub input: EncoderInput,
    /// The photo's view and another view of the same subject (true bodies and cameras).
    pub views: [View; 2],
    /// Their renders at [`IMAGE_RES`]²: RGB `[2, 3, R, R]` in [−1, 1] and mask `[2, 1, R, R]`.
    pub rgb: Vec<f32>,
    pub mask: Vec<f32>,
}

/// The held-out photos' figures: the image loss, and mask IoU / masked PSNR of the guess at
/// the photo's camera and at the other view.
#[derive(Clone, Copy, Debug, Default)]
pub struct ImageFigures {
    pub loss: f64,
    pub iou: f64,
    pub psnr: f64,
    pub iou_other: f64,
    pub psnr_other: f64,
}

/// Weight of the silhouette's MSE in the image term. It is a mean over every pixel, where the
/// RGB terms are means over the person: at weight 1 (the inversion's) it was a tenth of the
/// term, and the held-out mask IoU did not move in 200 steps while the PSNR rose 1.7 dB.
pub const SILHOUETTE_WEIGHT: f32 = 10.0;

/// The image term of `enc`'s guesses for `photos`, rendered by `g` at each photo's two views
/// (masked RGB L1 + MSE in [0, 1] units, and the silhouette's MSE weighted by
/// [`SILHOUETTE_WEIGHT`]), and the renders.
pub fn image_loss(
    g: &Generator,
    grids: &PosedGridCache,
    enc: &Encoder,
    ctx: &BodyContext,
    photos: &[ScanPhoto],
    ad: &Device,
) -> Result<(Tensor<1>, FakeViews)> {
    let refs: Vec<&EncoderInput> = photos.iter().map(|p| &p.input).collect();
    let styles = enc.styles(g, &refs, ad)?;
    let views: Vec<Vec<View>> = photos.iter().map(|p| p.views.to_vec()).collect();
    let f = render_avatar_views(g, ctx, &styles, &views, IMAGE_RES, grids, ad)?;
    let (n, r) = (2 * photos.len(), IMAGE_RES);
    let rgb: Vec<f32> = photos.iter().flat_map(|p| p.rgb.iter().copied()).collect();
    let mask: Vec<f32> = photos.iter().flat_map(|p| p.mask.iter().copied()).collect();
    let msum = mask.iter().sum::<f32>().max(1.0);
    let rgb = Tensor::<4>::from_data(TensorData::new(rgb, [n, 3, r, r]), ad);
    let m = Tensor::<4>::from_data(TensorData::new(mask, [n, 1, r, r]), ad);
    let d = (f.rgb.clone() - rgb) * 0.5;
    let l1 = (d.clone().abs() * m.clone()).sum() / (3.0 * msum);
    let mse = (d.powf_scalar(2.0) * m.clone()).sum() / (3.0 * msum);
    let sil = ((f.mask.clone() + 1.0) * 0.5 - m).powf_scalar(2.0).mean();
    Ok((l1 + mse + sil * SILHOUETTE_WEIGHT, f))
}

impl ScanPhotos {
    pub fn open(root: &Path, g: Generator, model: BodyModel) -> Result<Self> {
        let ds = Dataset::open(root).with_context(|| format!("--image-data {}", root.display()))?;
        let mut by: BTreeMap<&str, Vec<usize>> = BTreeMap::new();
        for (i, (name, _)) in ds.entries.iter().enumerate() {
            by.entry(name.split('/').next().unwrap_or(name)).or_default().push(i);
        }
        let subjects: Vec<Vec<usize>> = by.into_values().filter(|v| v.len() >= 2).collect();
        if subjects.len() < 2 {
            bail!(
                "--image-data {}: {} subjects with two views or more; the image term needs at least 2 \
                 (one is held out)",
                root.display(),
                subjects.len()
            );
        }
        let held_n = HELD_SUBJECTS.min(subjects.len() / 4).max(1);
        let (train, held) = subjects.split_at(subjects.len() - held_n);
        eprintln!(
            "image term: {} training and {} held-out subjects of {} ({} views at {}²)",
            train.len(),
            held.len(),
            root.display(),
            ds.len(),
            ds.resolution
        );
        // One posed grid per subject (each scan has one pose): computed once, then reused.
        let grids = PosedGridCache::new(subjects.len());
        Ok(Self { ds, g, model, train: train.to_vec(), held: held.to_vec(), grids })
    }

    /// A training photo: a random subject's random view, over a backdrop made with `other`
    /// (a render at `res`²), the body the encoder sees perturbed like a fit's.
    pub fn draw(&self, res: usize, other: &[f32], rng: &mut Rng) -> Result<ScanPhoto> {
        let subject = &self.train[rng.below(self.train.len())];
        let a = rng.below(subject.len());
        let b = (a + 1 + rng.below(subject.len() - 1)) % subject.len();
        self.photo(subject[a], subject[b], res, Some((other, rng)))
    }

    /// The held-out photos: per held-out subject, its first view as the photo and the one
    /// half-way round as the other view; on white, the true body.
    pub fn held_out(&self, res: usize) -> Result<Vec<ScanPhoto>> {
        self.held.iter().map(|s| self.photo(s[0], s[s.len() / 2], res, None)).collect()
    }

    fn photo(&self, i: usize, j: usize, res: usize, augmentation: Option<(&[f32], &mut Rng)>) -> Result<ScanPhoto> {
        let (a, b) = (self.ds.load(i)?, self.ds.load(j)?);
        let src = self.ds.resolution;
        let (va, vb) = (a.label.view(), b.label.view());
        let rgb = resample(&a.rgb, src, 3, res);
        let mask = resample(&a.mask, src, 1, res);
        let input = match augmentation {
            Some((other, rng)) => {
                let m = va.world_to_camera;
                // The point on the camera's axis at the body's depth: what a fit's camera turns about.
                let center = m.inverse().transform_point3(Vec3::new(0.0, 0.0, m.w_axis.z));
                let fit =
                    View { world_to_camera: perturbed_camera(m, center, rng), body: perturbed_body(&va.body, rng) };
                augment(&rgb, &mask, &BodyMaps::render(&self.model, &fit, res), res, other, rng)
            }
            None => EncoderImage::from_parts(&rgb, &mask, &BodyMaps::render(&self.model, &va, res), res).patchify(),
        };
        let n = IMAGE_RES * IMAGE_RES;
        let (mut trgb, mut tmask) = (Vec::with_capacity(6 * n), Vec::with_capacity(2 * n));
        for s in [&a, &b] {
            let c = resample(&s.rgb, src, 3, IMAGE_RES);
            trgb.extend((0..3).flat_map(|ch| (0..n).map(move |k| (ch, k))).map(|(ch, k)| 2.0 * c[3 * k + ch] - 1.0));
            tmask.extend(resample(&s.mask, src, 1, IMAGE_RES));
        }
        Ok(ScanPhoto { input, views: [va, vb], rgb: trgb, mask: tmask })
    }

    /// The image term of `enc`'s guesses for `photos` ([`image_loss`]) and the renders.
    pub fn loss(
        &self,
        enc: &Encoder,
        ctx: &BodyContext,
        photos: &[ScanPhoto],
        ad: &Device,
    ) -> Result<(Tensor<1>, FakeViews)> {
        image_loss(&self.g, &self.grids, enc, ctx, photos, ad)
    }

    /// [`ScanPhotos::loss`] and the mask IoU and masked PSNR on `photos` (no gradients).
    pub fn figures(&self, enc: &Encoder, ctx: &BodyContext, photos: &[ScanPhoto], ad: &Device) -> Result<ImageFigures> {
        let mut out = ImageFigures::default();
        let n = IMAGE_RES * IMAGE_RES;
        for chunk in photos.chunks(2) {
            let (loss, f) = self.loss(enc, ctx, chunk, ad)?;
            out.loss += read_f32_now(loss.detach())?[0] as f64 * chunk.len() as f64;
            let rgb = read_f32_now(f.rgb.detach())?;
            let mask = read_f32_now(f.mask.detach())?;
            for (k, p) in chunk.iter().enumerate() {
                for v in 0..2 {
                    let img = 2 * k + v;
                    let hwc = |x: &[f32]| -> Vec<f32> {
                        (0..n).flat_map(|q| (0..3).map(move |c| ((x[c * n + q] + 1.0) * 0.5).clamp(0.0, 1.0))).collect()
                    };
                    let out_rgb = hwc(&rgb[img * 3 * n..(img + 1) * 3 * n]);
                    let out_mask: Vec<f32> =
                        mask[img * n..(img + 1) * n].iter().map(|m| ((m + 1.0) * 0.5).clamp(0.0, 1.0)).collect();
                    let t_rgb = hwc(&p.rgb[v * 3 * n..(v + 1) * 3 * n]);
                    let t_mask = &p.mask[v * n..(v + 1) * n];
                    let (iou, psnr) =
                        (mask_iou(&out_mask, t_mask) as f64, masked_psnr(&out_rgb, &t_rgb, t_mask) as f64);
                    if v == 0 {
                        out.iou += iou;
                        out.psnr += psnr;
                    } else {
                        out.iou_other += iou;
                        out.psnr_other += psnr;
                    }
                }
            }
        }
        let k = photos.len().max(1) as f64;
        Ok(ImageFigures {
            loss: out.loss / k,
            iou: out.iou / k,
            psnr: out.psnr / k,
            iou_other: out.iou_other / k,
            psnr_other: out.psnr_other / k,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use getavatar_core::body::skinning::BodyParams;
    use getavatar_core::burn::module::Module;
    use getavatar_core::generator::network::GeneratorConfig;
    use getavatar_core::reconstruction::encoder::EncoderConfig;
    use getavatar_core::render::camera::OrbitCamera;

    /// The term is the inversion's: nothing where the targets are the guess's own renders;
    /// every colour 0.2 lighter adds L1 0.2 + MSE 0.04; and its gradient reaches the encoder.
    #[test]
    fn the_image_term_is_zero_on_the_guess_itself_and_measures_a_colour_shift() {
        #[allow(deprecated)]
        let ad = Device::ndarray().autodiff();
        let gcfg = GeneratorConfig::preset("tiny").unwrap();
        let g = Generator::new(&gcfg, 1, &ad).no_grad();
        let model = crate::model_io::load_body(&None).unwrap();
        let ctx = BodyContext::new(model.clone(), &gcfg);
        let ecfg = EncoderConfig {
            res: 32,
            channels: vec![8, 8],
            hidden: 6,
            ..EncoderConfig::for_generator(g.num_ws(), gcfg.w_dim)
        };
        let enc = Encoder::new(&ecfg, 2, &ad);
        let body = BodyParams::from_split(&[0.0; 3], &[0.0; 69], &[0.0; 10]);
        let cam = |yaw: f32| OrbitCamera { yaw, ..OrbitCamera::default() }.world_to_camera();
        let views = [View { world_to_camera: cam(0.0), body: body.clone() }, View { world_to_camera: cam(1.5), body }];
        let input = EncoderImage::from_parts(
            &vec![0.5; 3 * 32 * 32],
            &vec![1.0; 32 * 32],
            &BodyMaps::render(&model, &views[0], 32),
            32,
        )
        .patchify();
        let n = IMAGE_RES * IMAGE_RES;
        let photo = |rgb: Vec<f32>, mask: Vec<f32>| ScanPhoto { input: input.clone(), views: views.clone(), rgb, mask };
        let grids = PosedGridCache::new(2);
        let loss = |p: &ScanPhoto| image_loss(&g, &grids, &enc, &ctx, std::slice::from_ref(p), &ad).unwrap();
        let (_, f) = loss(&photo(vec![0.0; 6 * n], vec![0.0; 2 * n]));
        let rgb = read_f32_now(f.rgb.detach()).unwrap();
        let mask: Vec<f32> = read_f32_now(f.mask.detach()).unwrap().iter().map(|m| (m + 1.0) * 0.5).collect();
        assert!(mask.iter().sum::<f32>() > 20.0, "the tiny generator drew no surface");
        let (own, _) = loss(&photo(rgb.clone(), mask.clone()));
        let own = read_f32_now(own).unwrap()[0];
        assert!(own.abs() < 1e-6, "{own}");
        let lighter: Vec<f32> = rgb.iter().map(|v| v - 0.4).collect(); // 0.2 in [0, 1] units
        let (shifted, _) = loss(&photo(lighter, mask));
        let grads = shifted.clone().backward();
        let shifted = read_f32_now(shifted.detach()).unwrap()[0];
        assert!((shifted - 0.24).abs() < 1e-4, "{shifted}");
        let reached = enc.out.weight.val().grad(&grads).map(|t| read_f32_now(t.abs().sum()).unwrap()[0]);
        assert!(reached.is_some_and(|s| s > 0.0), "no gradient reached the encoder: {reached:?}");
    }
}
