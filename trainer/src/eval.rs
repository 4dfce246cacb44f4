//! `trainer eval`: how well a generator follows the requested pose and matches the data, on
//! the labels of a (held-out) dataset.
//!
//! For `--count` labels spread evenly over the dataset, one avatar per label (latents from
//! `--seed` + index) is rendered under the label's camera and body pose at the dataset's
//! resolution (the training renderer, `diff::avatar::render_avatars`), and compared with:
//! - the posed body's silhouette (the label's θ, β through the body model, rasterised with
//!   the same camera, 2×2 supersampled): mask IoU, the pose-controllability figure of the
//!   paper. The data's own masks against the posed body are reported beside it (clothes
//!   and hair make even real scans differ from the naked body);
//! - the data's normal map at the label: mean angular error (degrees) over pixels covered in
//!   both (world-space normals, so this measures body-level orientation, not identity);
//! - with `--inception` (pt_inception-2015-12-05 as safetensors, see `crate::inception`):
//!   FID and KID between the generated RGB images and the data's RGB images of the same
//!   labels (both in [0, 1], resized to 299² as pytorch-fid does). With the few dozen
//!   images a CPU eval affords, FID is strongly biased upwards; compare runs at equal
//!   `--count` only. Without the weights file it says so and reports null.
//!
//! With `--subject-codes` each label is rendered at its own training subject's codes (the
//! checkpoint's latent modes) instead of seeds, and the RGB / normal / mask L1 against the
//! data is reported too: how closely the checkpoint reproduces its subjects, on any grid of
//! their views (on the training data, `--count 4` is the run's `grid_l1.jsonl` figure).
//!
//! The JSON report (`--out`) lists every label's two IoUs (`per_label`), and `--images DIR`
//! writes one PNG per label (generated RGB | generated mask against the posed body | data),
//! so a low mean can be traced to the labels and shapes that cause it.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use getavatar_core::body::body_model::BodyModel;
use getavatar_core::body::skinning::{pose_body, vertex_normals};
use getavatar_core::generator::pipeline::seed_latents;
use getavatar_core::generator::pipeline::LatentModes;
use getavatar_core::generator::readback::read_f32_now;
use getavatar_core::io::dataset::{encode_png, Dataset, Label, Sample};
use getavatar_core::render::camera::OrbitCamera;
use getavatar_core::render::diff::avatar::{render_avatars, PosedGridCache};
use getavatar_core::render::rasterize::render_views;
use serde::Serialize;

use crate::inception::ImageChw;

#[derive(clap::Args, Debug)]
pub struct EvalArgs {
    #[command(flatten)]
    pub backend: crate::backend::BackendArg,
    /// Dataset directory whose labels (camera, θ, β) and images are used.
    #[arg(long)]
    pub data: PathBuf,
    #[command(flatten)]
    pub model: crate::model_io::GeneratorArgs,
    /// Labels to evaluate (spread evenly over the dataset).
    #[arg(long, default_value_t = 32)]
    pub count: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Truncation ψ (1 = none).
    #[arg(long, default_value_t = 1.0)]
    pub psi: f32,
    /// Truncate towards w_avg even where the checkpoint carries latent modes (by default
    /// ψ pulls the latents towards the training subjects: both towards the subject whose
    /// geometry mode is nearest, or each to its own nearest, as the checkpoint's pairing says).
    #[arg(long)]
    pub mean_truncation: bool,
    /// Comparison resolution (labels are resolution-free; default: the dataset's). At
    /// 64² a limb is two pixels wide and IoU mostly measures boundary rounding.
    #[arg(long)]
    pub res: Option<usize>,
    /// Inception weights (pt_inception-2015-12-05 converted to safetensors by
    /// tools/inception_weights.py) for FID/KID; without it they are not computed.
    #[arg(long)]
    pub inception: Option<PathBuf>,
    /// Write the figures as JSON here.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Also write one PNG per label here (`NN.png`: generated RGB | generated mask against
    /// the posed body, white both, red generated only, blue body only | the data's image |
    /// with normal maps, the angle between the normals, white 0° to red 45°), to see where
    /// the IoU and the normal error are lost.
    #[arg(long)]
    pub images: Option<PathBuf>,
    /// Render each label with its own training subject's codes (the checkpoint's latent
    /// modes) instead of seeds, and also report the RGB / normal / mask L1 against the data:
    /// how closely a reconstruction-trained checkpoint reproduces its subjects. The dataset's
    /// subject folders, in sorted order, are subjects 0, 1, … as in training, so the dataset
    /// must hold the run's training subjects or the first of them prepared alike (e.g. the
    /// first 16 of `synth-scans --count 64`, which are bit-identical to `--count 16`). On the
    /// training data at its resolution, `--count 4` gives the snapshot grid's `grid_l1.jsonl`
    /// figure.
    #[arg(long, conflicts_with_all = ["psi", "seed", "mean_truncation"])]
    pub subject_codes: bool,
    /// Render at N× the comparison resolution per axis and box-filter down to it, as
    /// `trainer prepare --ss N` makes the data (its default is 2). With 1 (the default) each
    /// pixel is one point sample of the fields, so fine colour detail aliases where the data
    /// averages it: at 64² the scans themselves, rendered with one sample per pixel, differ
    /// from their 2×2-supersampled views by an RGB L1 of 0.0085 (MODEL_CARD, Evaluation).
    #[arg(long, default_value_t = 1)]
    pub supersample: usize,
}

#[derive(Debug, Serialize)]
pub struct EvalReport {
    pub labels: usize,
    pub resolution: usize,
    /// Samples per pixel and axis of the generated images (`--supersample`).
    pub supersample: usize,
    /// Generated mask vs posed body silhouette.
    pub mask_iou_mean: f32,
    pub mask_iou_min: f32,
    /// The data's masks (nearest-upsampled to `resolution`) vs the posed body silhouette
    /// (reference level).
    pub data_mask_iou_mean: f32,
    /// Mean angle between generated and data normals where both cover the pixel (degrees).
    pub normal_error_deg: Option<f32>,
    /// Where that angle comes from: its median, and the mean over the pixels at least
    /// [`EDGE_BAND`] px inside both silhouettes (away from where a shifted outline meets
    /// grazing normals), with the share of the compared pixels that are there.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub normal_error_breakdown: Option<NormalErrorBreakdown>,
    pub fid: Option<f32>,
    pub kid: Option<f32>,
    /// With `--subject-codes`: the L1 between the renders and the data's images.
    pub reconstruction_l1: Option<ReconstructionL1>,
    /// The same figures per label, in evaluation order (seeds `seed + 2k`, `seed + 2k + 1`,
    /// or with `--subject-codes` the label's subject).
    pub per_label: Vec<LabelFigures>,
}

/// Pixels this close to either silhouette's outline (Chebyshev distance) count as edge.
pub const EDGE_BAND: usize = 2;

/// The normal error split by where it arises (`EvalReport::normal_error_breakdown`).
#[derive(Debug, Serialize, Clone, Copy, PartialEq)]
pub struct NormalErrorBreakdown {
    pub median_deg: f32,
    /// Mean over pixels at least `EDGE_BAND` px inside both silhouettes.
    pub interior_deg: f32,
    /// Share of the compared pixels that are interior.
    pub interior_share: f32,
    /// Mean over the other (edge) pixels.
    pub edge_deg: f32,
}

/// Which pixels of a `res`² image lie at least `band` px (Chebyshev) inside the mask.
fn interior(mask: &[bool], res: usize, band: usize) -> Vec<bool> {
    let b = band as isize;
    (0..res * res)
        .map(|p| {
            let (y, x) = ((p / res) as isize, (p % res) as isize);
            (-b..=b).all(|dy| {
                (-b..=b).all(|dx| {
                    let (yy, xx) = (y + dy, x + dx);
                    (0..res as isize).contains(&yy)
                        && (0..res as isize).contains(&xx)
                        && mask[yy as usize * res + xx as usize]
                })
            })
        })
        .collect()
}

/// The breakdown of per-pixel angles (degrees) with their interior flags; None for none.
fn breakdown(angles: &mut [(f32, bool)]) -> Option<NormalErrorBreakdown> {
    if angles.is_empty() {
        return None;
    }
    let mean = |it: &mut dyn Iterator<Item = f32>| -> (f32, usize) {
        let (s, n) = it.fold((0f64, 0usize), |(s, n), a| (s + a as f64, n + 1));
        ((s / n.max(1) as f64) as f32, n)
    };
    let (interior_deg, ni) = mean(&mut angles.iter().filter(|a| a.1).map(|a| a.0));
    let (edge_deg, _) = mean(&mut angles.iter().filter(|a| !a.1).map(|a| a.0));
    let mid = angles.len() / 2;
    angles.select_nth_unstable_by(mid, |a, b| a.0.total_cmp(&b.0));
    Some(NormalErrorBreakdown {
        median_deg: angles[mid].0,
        interior_deg,
        interior_share: ni as f32 / angles.len() as f32,
        edge_deg,
    })
}

/// Mean absolute difference in [0, 1] units (images in [0, 1], normals' components halved),
/// over pixels, channels and labels; the units of the training snapshots' `grid_l1.jsonl`.
#[derive(Debug, Serialize, Clone, Copy, PartialEq)]
pub struct ReconstructionL1 {
    pub rgb: f32,
    /// None when the dataset has no normal maps.
    pub normal: Option<f32>,
    pub mask: f32,
}

/// One evaluated label: which dataset image, and both IoUs against the posed body.
#[derive(Debug, Serialize)]
pub struct LabelFigures {
    pub image: String,
    pub mask_iou: f32,
    pub data_mask_iou: f32,
    /// With `--subject-codes`: the training subject rendered, and its RGB L1 ([0, 1] units).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub subject: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rgb_l1: Option<f32>,
}

/// Box-filter a channel-major image `[channels, hi, hi]` by `factor` per axis (`hi` a
/// multiple of it): each output pixel is the mean of its `factor`² samples, the average that
/// `rasterize::render_views` takes over its supersamples.
fn box_filter(image: Vec<f32>, channels: usize, hi: usize, factor: usize) -> Vec<f32> {
    if factor == 1 {
        return image;
    }
    let lo = hi / factor;
    let scale = 1.0 / (factor * factor) as f32;
    let mut out = vec![0f32; channels * lo * lo];
    for c in 0..channels {
        for y in 0..lo {
            for x in 0..lo {
                let mut sum = 0f32;
                for sy in 0..factor {
                    let row = c * hi * hi + (y * factor + sy) * hi + x * factor;
                    sum += image[row..row + factor].iter().sum::<f32>();
                }
                out[c * lo * lo + y * lo + x] = sum * scale;
            }
        }
    }
    out
}

fn iou(a: &[bool], b: &[bool]) -> f32 {
    let i = a.iter().zip(b).filter(|(x, y)| **x && **y).count();
    let u = a.iter().zip(b).filter(|(x, y)| **x || **y).count();
    if u == 0 {
        1.0
    } else {
        i as f32 / u as f32
    }
}

/// The posed body's silhouette under `label` at `res`².
pub fn body_silhouette(model: &BodyModel, label: &Label, res: usize) -> Vec<bool> {
    let posed = pose_body(model, &label.body_params());
    let vp = OrbitCamera::default().projection_gl(1.0) * label.world_to_camera;
    let n = vertex_normals(&posed.vertices, &model.faces);
    let r = render_views(&posed.vertices, &model.faces, &n, &n, vp, res, 2);
    r.mask.iter().map(|m| *m > 127).collect()
}

pub fn evaluate(a: &EvalArgs) -> Result<EvalReport> {
    let ds = Dataset::open(&a.data).with_context(|| format!("opening dataset {}", a.data.display()))?;
    if a.count == 0 {
        bail!("--count must be at least 1");
    }
    if !a.psi.is_finite() {
        bail!("--psi must be a number");
    }
    let dev = a.backend.device()?;
    // Load the Inception weights first: a bad file fails before minutes of rendering.
    let inception = match &a.inception {
        Some(p) => Some(crate::inception::Inception::load(p, &dev)?),
        None => None,
    };
    let (cfg, g, modes) = a.model.load(&dev)?;
    let subjects = eval_subjects(a, &ds, modes.as_ref())?;
    let modes = crate::model_io::truncation_modes(&modes, a.mean_truncation);
    let model = BodyModel::default_body()?;
    let ctx = crate::model_io::body_context(model.clone(), &cfg);
    let grids = PosedGridCache::default();
    let res = a.res.unwrap_or(ds.resolution);
    if !(16..=1024).contains(&res) {
        bail!("--res must be between 16 and 1024 (got {res})");
    }
    let ss = a.supersample;
    if !(1..=4).contains(&ss) {
        bail!("--supersample must be between 1 and 4 (got {ss})");
    }
    let hi = res * ss;
    if hi > 2048 {
        bail!("--res × --supersample must be at most 2048 (got {res} × {ss})");
    }
    let dres = ds.resolution;
    // Nearest sampling of a dataset image at comparison pixel p.
    let src = |p: usize| ((p / res) * dres / res) * dres + (p % res) * dres / res;
    let count = a.count.min(ds.len());
    if let Some(dir) = &a.images {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let bar = crate::progress::bar(count as u64, "labels");
    let (mut ious, mut data_ious, mut per_label) = (Vec::new(), Vec::new(), Vec::new());
    let (mut angle_sum, mut angle_n) = (0f64, 0usize);
    let mut angles: Vec<(f32, bool)> = Vec::new();
    let (mut fake_rgb, mut real_rgb) = (Vec::new(), Vec::new());
    let mut rec_sums: Vec<(f64, Option<f64>, f64)> = Vec::new();
    for k in 0..count {
        let idx = k * ds.len() / count;
        let sample = ds.load(idx)?;
        let label = sample.label.clone();
        let subject = subjects.as_ref().map(|s| s[idx]);
        let styles = match (subject, modes) {
            (Some(s), Some(m)) => {
                g.subject_styles(m, s, s).context("a subject inside the checkpoint's count (checked above)")?
            }
            _ => {
                let (zg, zt) = seed_latents(&cfg, a.seed + 2 * k as u64, a.seed + 2 * k as u64 + 1, &dev);
                g.styles_with(zg, zt, a.psi, modes)
            }
        };
        let f = render_avatars(&g, &ctx, &styles, &[label.view()], hi, &grids, &dev)?;
        let mask: Vec<f32> = box_filter(read_f32_now(f.mask.clone())?, 1, hi, ss);
        let fake: Vec<bool> = mask.iter().map(|m| *m > 0.0).collect();
        // The render's RGB, read back once for whichever of FID, the strips and the
        // reconstruction L1 asks for it.
        let rgb: Vec<f32> = if inception.is_some() || a.images.is_some() || subject.is_some() {
            box_filter(read_f32_now(f.rgb.clone())?, 3, hi, ss)
        } else {
            Vec::new()
        };
        if inception.is_some() {
            fake_rgb.push(ImageChw {
                data: rgb.iter().map(|v| ((v + 1.0) * 0.5).clamp(0.0, 1.0)).collect(),
                height: res,
                width: res,
            });
            real_rgb.push(ImageChw::from_interleaved(&sample.rgb, dres, dres));
        }
        let body = body_silhouette(&model, &label, res);
        ious.push(iou(&fake, &body));
        let real: Vec<bool> = (0..res * res).map(|p| sample.mask[src(p)] > 0.5).collect();
        data_ious.push(iou(&real, &body));
        let fnrm: Option<Vec<f32>> = match &sample.normal {
            Some(_) => Some(box_filter(read_f32_now(f.normal.clone())?, 3, hi, ss)),
            None => None,
        };
        let rgb_l1 = match subject {
            Some(_) => {
                let r = reconstruction_l1(&sample, &rgb, &mask, fnrm.as_deref(), res, &src);
                rec_sums.push(r);
                Some(r.0 as f32)
            }
            None => None,
        };
        per_label.push(LabelFigures {
            image: sample.name.clone(),
            mask_iou: ious[k],
            data_mask_iou: data_ious[k],
            subject,
            rgb_l1,
        });
        let pixel_angle: Vec<Option<f32>> = match (&sample.normal, &fnrm) {
            (Some(rn), Some(fnrm)) => normal_angles(rn, fnrm, &fake, &real, res, &src)
                .into_iter()
                .map(|a| {
                    a.map(|(angle, inside)| {
                        angle_sum += angle as f64;
                        angle_n += 1;
                        angles.push((angle, inside));
                        angle
                    })
                })
                .collect(),
            _ => vec![None; res * res],
        };
        if let Some(dir) = &a.images {
            let views = StripViews { rgb: &rgb, fake: &fake, body: &body, real: &real, pixel_angle: &pixel_angle };
            write_label_strip(&dir.join(format!("{k:02}.png")), &sample, &views, fnrm.is_some(), res, &src)?;
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len().max(1) as f32;
    let (fid, kid) = fid_kid(inception.as_ref(), &fake_rgb, &real_rgb, a.seed)?;
    Ok(EvalReport {
        labels: count,
        resolution: res,
        supersample: ss,
        mask_iou_mean: mean(&ious),
        mask_iou_min: ious.iter().copied().fold(f32::INFINITY, f32::min),
        data_mask_iou_mean: mean(&data_ious),
        normal_error_deg: (angle_n > 0).then(|| (angle_sum / angle_n as f64) as f32),
        normal_error_breakdown: breakdown(&mut angles),
        fid,
        kid,
        reconstruction_l1: (!rec_sums.is_empty()).then(|| {
            let n = rec_sums.len() as f64;
            let normals: Option<Vec<f64>> = rec_sums.iter().map(|r| r.1).collect();
            ReconstructionL1 {
                rgb: (rec_sums.iter().map(|r| r.0).sum::<f64>() / n) as f32,
                normal: normals.map(|v| (v.iter().sum::<f64>() / n) as f32),
                mask: (rec_sums.iter().map(|r| r.2).sum::<f64>() / n) as f32,
            }
        }),
        per_label,
    })
}

/// With `--subject-codes`, each dataset entry's subject (checked against the checkpoint's
/// latent modes); else None.
fn eval_subjects(a: &EvalArgs, ds: &Dataset, modes: Option<&LatentModes>) -> Result<Option<Vec<usize>>> {
    if !a.subject_codes {
        return Ok(None);
    }
    {
        let Some(m) = modes else {
            bail!("--subject-codes needs a checkpoint with latent modes (a reconstruction or anchored run's); this one has none");
        };
        let subjects = crate::train::subject_of_entries(ds);
        let n = subjects.iter().max().map_or(0, |s| s + 1);
        if n > m.count() {
            bail!(
                "--subject-codes: {} holds {n} subjects but the checkpoint has codes for {}; use the run's training data (or its first subjects)",
                a.data.display(),
                m.count()
            );
        }
        Ok(Some(subjects))
    }
}

/// Mean L1 of the render against the data image (RGB, normal where both have them, mask),
/// each scaled to [0, 1]: renders are in [-1, 1] (mask too), the data in [0, 1]; normals are
/// unit vectors in both, so their difference is halved like the others'.
fn reconstruction_l1(
    sample: &Sample,
    rgb: &[f32],
    mask: &[f32],
    fnrm: Option<&[f32]>,
    res: usize,
    src: &dyn Fn(usize) -> usize,
) -> (f64, Option<f64>, f64) {
    let n = (res * res) as f64;
    let chw_l1 = |fake: &[f32], real: &dyn Fn(usize, usize) -> f32, ch: usize, to01: bool| -> f64 {
        let mut sum = 0f64;
        for c in 0..ch {
            for p in 0..res * res {
                let v = fake[c * res * res + p];
                let v = if to01 { v * 0.5 + 0.5 } else { v };
                sum += (v - real(c, src(p))).abs() as f64;
            }
        }
        let d = sum / (n * ch as f64);
        if to01 {
            d
        } else {
            d / 2.0
        }
    };
    let rgb = chw_l1(rgb, &|c, q| sample.rgb[3 * q + c], 3, true);
    let msk = chw_l1(mask, &|_, q| sample.mask[q], 1, true);
    let nrm = match (fnrm, &sample.normal) {
        (Some(fnrm), Some(rn)) => Some(chw_l1(fnrm, &|c, q| rn[3 * q + c], 3, false)),
        _ => None,
    };
    (rgb, nrm, msk)
}

/// Per pixel covered by both the render and the data, the angle between their normals in
/// degrees and whether the pixel is inside both silhouettes by [`EDGE_BAND`] pixels.
fn normal_angles(
    rn: &[f32],
    fnrm: &[f32],
    fake: &[bool],
    real: &[bool],
    res: usize,
    src: &dyn Fn(usize) -> usize,
) -> Vec<Option<(f32, bool)>> {
    let both: Vec<bool> = fake.iter().zip(real).map(|(f, r)| *f && *r).collect();
    let inside = interior(&both, res, EDGE_BAND);
    (0..res * res)
        .map(|p| {
            if !(fake[p] && real[p]) {
                return None;
            }
            let a3 = [fnrm[p], fnrm[res * res + p], fnrm[2 * res * res + p]];
            let q = src(p);
            let b3 = [rn[3 * q], rn[3 * q + 1], rn[3 * q + 2]];
            let dot: f32 = a3.iter().zip(&b3).map(|(x, y)| x * y).sum();
            let la = a3.iter().map(|x| x * x).sum::<f32>().sqrt();
            let lb = b3.iter().map(|x| x * x).sum::<f32>().sqrt();
            (la > 1e-3 && lb > 1e-3).then(|| ((dot / (la * lb)).clamp(-1.0, 1.0).acos().to_degrees(), inside[p]))
        })
        .collect()
}

/// FID and KID of the renders against the data images, with the Inception network given.
fn fid_kid(
    inception: Option<&crate::inception::Inception>,
    fake_rgb: &[ImageChw],
    real_rgb: &[ImageChw],
    seed: u64,
) -> Result<(Option<f32>, Option<f32>)> {
    match inception {
        Some(net) => {
            println!("FID/KID: Inception features of {} generated and {} data images…", fake_rgb.len(), real_rgb.len());
            let ff = net.features(fake_rgb, 4)?;
            let fr = net.features(real_rgb, 4)?;
            let fid = crate::fid::fid(&fr, &ff)?;
            let kid = crate::fid::kid(&fr, &ff, 100, 1000, seed)?;
            Ok((Some(fid as f32), Some(kid as f32)))
        }
        None => {
            println!(
            "FID/KID: not computed (pass --inception with the pt_inception-2015-12-05 weights as safetensors; tools/inception_weights.py converts the .pth)"
        );
            Ok((None, None))
        }
    }
}

/// The render and its figures at one label, for the PNG strip.
struct StripViews<'a> {
    /// The render's RGB, `[3, res, res]` in [-1, 1].
    rgb: &'a [f32],
    fake: &'a [bool],
    body: &'a [bool],
    real: &'a [bool],
    pixel_angle: &'a [Option<f32>],
}

/// One label's strip: render | render vs body silhouette | data (| normal angle heat map).
fn write_label_strip(
    path: &std::path::Path,
    sample: &Sample,
    v: &StripViews,
    with_normals: bool,
    res: usize,
    src: &dyn Fn(usize) -> usize,
) -> Result<()> {
    let fake_rgb: Vec<f32> = (0..res * res * 3).map(|i| v.rgb[(i % 3) * res * res + i / 3] * 0.5 + 0.5).collect();
    let real_rgb: Vec<f32> = (0..res * res * 3)
        .map(|i| {
            let q = src(i / 3);
            let m = sample.mask[q];
            sample.rgb[3 * q + i % 3] * m + (1.0 - m)
        })
        .collect();
    let overlay: Vec<f32> = (0..res * res * 3)
        .map(|i| match (v.fake[i / 3], v.body[i / 3], i % 3) {
            (true, true, _) => 1.0,
            (true, false, c) => [0.9, 0.1, 0.1][c],
            (false, true, c) => [0.1, 0.3, 0.9][c],
            (false, false, _) => 0.0,
        })
        .collect();
    // With normal maps, a fourth panel: the angle between the normals per pixel
    // (white 0°, red from 45°; grey where only one image covers the pixel).
    let heat: Vec<f32> = (0..res * res * 3)
        .map(|i| match (v.pixel_angle[i / 3], v.fake[i / 3] || v.real[i / 3]) {
            (Some(a), _) => {
                let t = (a / 45.0).clamp(0.0, 1.0);
                [1.0 - 0.2 * t, 1.0 - t, 1.0 - t][i % 3]
            }
            (None, true) => 0.6,
            (None, false) => 0.0,
        })
        .collect();
    let mut panels: Vec<&[f32]> = vec![&fake_rgb, &overlay, &real_rgb];
    if with_normals {
        panels.push(&heat);
    }
    write_strip(path, &panels, res)
}

/// Interleaved RGB images in [0, 1] (`res²·3` each) side by side as one PNG.
fn write_strip(path: &std::path::Path, images: &[&[f32]], res: usize) -> Result<()> {
    let w = res * images.len();
    let mut buf = vec![0u8; w * res * 3];
    for (j, im) in images.iter().enumerate() {
        for y in 0..res {
            for x in 0..res {
                for c in 0..3 {
                    buf[(y * w + j * res + x) * 3 + c] =
                        (im[(y * res + x) * 3 + c].clamp(0.0, 1.0) * 255.0).round() as u8;
                }
            }
        }
    }
    crate::atomic::write_atomic(path, &encode_png(w, res, 3, &buf)?)
}

pub fn eval(a: &EvalArgs) -> Result<()> {
    let r = evaluate(a)?;
    println!(
        "{} labels at {}²{}: mask IoU vs posed body {:.3} (min {:.3}; the data's own masks: {:.3}); normal error {}",
        r.labels,
        r.resolution,
        if r.supersample > 1 { format!(" ({0}×{0} samples per pixel)", r.supersample) } else { String::new() },
        r.mask_iou_mean,
        r.mask_iou_min,
        r.data_mask_iou_mean,
        r.normal_error_deg.map(|d| format!("{d:.1}°")).unwrap_or_else(|| "n/a (no normal maps)".into())
    );
    if let Some(b) = &r.normal_error_breakdown {
        println!(
            "normal error: median {:.1}°; {:.0} % of the compared pixels lie ≥ {EDGE_BAND} px inside both silhouettes, {:.1}° there, {:.1}° nearer the outlines",
            b.median_deg,
            100.0 * b.interior_share,
            b.interior_deg,
            b.edge_deg
        );
    }
    if let Some(l1) = &r.reconstruction_l1 {
        println!(
            "reconstruction L1 against the data ([0, 1] units, each label at its subject's codes): RGB {:.4}, normal {}, mask {:.4}",
            l1.rgb,
            l1.normal.map(|v| format!("{v:.4}")).unwrap_or_else(|| "n/a (no normal maps)".into()),
            l1.mask
        );
    }
    if let (Some(fid), Some(kid)) = (r.fid, r.kid) {
        println!("FID {fid:.2}, KID {kid:.4} ({} images per set)", r.labels);
    }
    if let Some(out) = &a.out {
        crate::atomic::write_atomic(out, serde_json::to_string_pretty(&r)?.as_bytes())?;
        println!("wrote {}", out.display());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_filter_averages_each_block_per_channel() {
        // Two channels of a 4×4 image (values 0..32) filtered by 2: each output pixel is the
        // mean of its 2×2 block, channel by channel.
        let image: Vec<f32> = (0..32).map(|v| v as f32).collect();
        let out = box_filter(image.clone(), 2, 4, 2);
        assert_eq!(out, vec![2.5, 4.5, 10.5, 12.5, 18.5, 20.5, 26.5, 28.5]);
        // Filtering by 4 gives each channel's mean; by 1 the image itself.
        assert_eq!(box_filter(image.clone(), 2, 4, 4), vec![7.5, 23.5]);
        assert_eq!(box_filter(image.clone(), 2, 4, 1), image);
    }

    #[test]
    fn interior_keeps_pixels_the_band_away_from_the_outline_and_the_border() {
        // A 7×7 square in a 9×9 image: with band 2 only its 3×3 centre is interior.
        let res = 9;
        let mask: Vec<bool> =
            (0..res * res).map(|p| (1..8).contains(&(p / res)) && (1..8).contains(&(p % res))).collect();
        let inside = interior(&mask, res, 2);
        let got: Vec<usize> = (0..res * res).filter(|&p| inside[p]).collect();
        assert_eq!(got, vec![30, 31, 32, 39, 40, 41, 48, 49, 50]);
        // The image border counts as outside.
        assert!(!interior(&[true; 25], 5, 1)[0] && interior(&[true; 25], 5, 1)[12]);
    }

    #[test]
    fn breakdown_splits_the_mean_and_finds_the_median() {
        let mut a = vec![(10.0, true), (20.0, true), (60.0, false), (2.0, true), (90.0, false)];
        let b = breakdown(&mut a).unwrap();
        assert_eq!(b.median_deg, 20.0);
        assert!((b.interior_deg - 32.0 / 3.0).abs() < 1e-5 && (b.edge_deg - 75.0).abs() < 1e-5);
        assert!((b.interior_share - 0.6).abs() < 1e-6);
        assert_eq!(breakdown(&mut []), None);
    }
}
