//! The training pairs of `train-encoder`: avatars rendered from the generator with their true
//! codes and views, and the perturbed fit the encoder is shown (module docs of `train_encoder`).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use getavatar_core::body::body_model::BodyModel;
use getavatar_core::body::skinning::{pose_body, BodyParams};
use getavatar_core::burn::tensor::{Device, Tensor, TensorData};
use getavatar_core::generator::checkpoint::{parse_safetensors, write_safetensors, NamedTensor};
use getavatar_core::generator::pipeline::{BodyContext, Generator, LatentModes, Styles};
use getavatar_core::generator::readback::read_f32_now;
use getavatar_core::reconstruction::encoder::BodyMaps;
use getavatar_core::reconstruction::inversion::render_images;
use getavatar_core::render::camera::{from_row_major, sample_data_camera, to_row_major, View};
use getavatar_core::render::diff::avatar::{render_avatars, PosedGridCache};
use getavatar_core::util::rng::Rng;
use getavatar_core::NUM_JOINTS;
use glam::{Mat4, Vec3};

use super::TrainEncoderArgs;
use crate::atomic::write_atomic;

pub(super) const SHARD: usize = 64;

/// Pairs per shard: 64, or half the pairs for small runs (tests), so one shard is held out.
pub(super) fn shard_size(pairs: usize) -> usize {
    if pairs >= 2 * SHARD {
        SHARD
    } else {
        pairs / 2
    }
}
/// Pairs drawn with one body (different codes and cameras).
pub(super) const PER_BODY: usize = 4;
/// u8 images per pair: render RGB (3), mask (1), body normals (3), canonical (3), silhouette (1).
pub(super) const PLANES: usize = 11;

/// One shard of pairs in memory.
pub(super) struct Shard {
    pub(super) res: usize,
    pub(super) count: usize,
    /// `[count, res, res, PLANES]` u8.
    pub(super) images: Vec<u8>,
    /// W+ codes `[count, n, w_dim]` per branch, flattened.
    pub(super) geo: Vec<f32>,
    pub(super) tex: Vec<f32>,
    pub(super) views: Vec<View>,
}

pub(super) fn shard_path(out: &Path, s: usize) -> PathBuf {
    out.join("pairs").join(format!("shard_{s:04}"))
}

/// Render the shards that are not on disk yet.
#[allow(clippy::too_many_arguments)]
pub(super) fn render_pairs(
    a: &TrainEncoderArgs,
    g: &Generator,
    modes: Option<&LatentModes>,
    ctx: &BodyContext,
    model: &BodyModel,
    res: usize,
    shards: usize,
    dev: &Device,
) -> Result<()> {
    let mine = |s: &usize| a.render_part.is_none_or(|(k, n)| s % n == k);
    let todo: Vec<usize> =
        (0..shards).filter(mine).filter(|s| !shard_path(&a.out, *s).with_extension("safetensors").is_file()).collect();
    if todo.is_empty() {
        return Ok(());
    }
    let size = shard_size(a.pairs);
    let bar = crate::progress::bar((todo.len() * size) as u64, "pairs");
    let grids = PosedGridCache::new(4);
    for s in todo {
        let mut rng = Rng::new(a.seed, 0xe2c0_0000 + s as u64);
        let (mut images, mut geo, mut tex, mut views) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        let mut body = crate::synth_scans::draw_body(model, &mut rng)?;
        while views.len() < size {
            // A body serves PER_BODY pairs in a row (its posed grid is cached).
            if views.len() % PER_BODY == 0 && !views.is_empty() {
                body = crate::synth_scans::draw_body(model, &mut rng)?;
            }
            let Some((img, styles, view)) = draw_pair(g, modes, ctx, model, &body, &mut rng, res, &grids, dev)? else {
                continue; // an empty surface: draw again
            };
            images.extend(img);
            geo.extend(read_f32_now(styles.geo)?);
            tex.extend(read_f32_now(styles.tex)?);
            views.push(view);
            bar.inc(1);
        }
        let p = shard_path(&a.out, s);
        write_atomic(&p.with_extension("bin"), &images)?;
        // The codes last: a shard counts as rendered once they are on disk.
        write_atomic(&p.with_extension("safetensors"), &shard_codes(&views, &geo, &tex, g.num_ws(), res)?)?;
    }
    bar.finish_and_clear();
    Ok(())
}

/// One pair: the images (`res²·PLANES` u8, HWC), the true styles and the true view. None when
/// the avatar's surface is empty there.
#[allow(clippy::too_many_arguments)]
pub(super) fn draw_pair(
    g: &Generator,
    modes: Option<&LatentModes>,
    ctx: &BodyContext,
    model: &BodyModel,
    body: &BodyParams,
    rng: &mut Rng,
    res: usize,
    grids: &PosedGridCache,
    dev: &Device,
) -> Result<Option<(Vec<u8>, Styles, View)>> {
    let z_dim = g.mapping_geo.z_dim();
    let z = |rng: &mut Rng| Tensor::<2>::from_data(TensorData::new(rng.normals(z_dim), [1, z_dim]), dev);
    let (zg, zt) = (z(rng), z(rng));
    let psi = rng.uniform();
    let styles = g.styles_with(zg, zt, psi, modes);
    let styles = Styles { geo: styles.geo.detach(), tex: styles.tex.detach() };
    let posed = pose_body(model, body);
    let (lo, hi) = posed.vertices.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(l, h), v| (l.min(v.y), h.max(v.y)));
    let mut cam = sample_data_camera(rng, 0.5 * (lo + hi));
    // Photo framings: the torso-based crop lands a little nearer or farther and off-centre.
    cam.radius *= rng.range(0.93, 1.07);
    cam.target += Vec3::new(rng.range(-0.04, 0.04), rng.range(-0.04, 0.04), 0.0);
    let view = View { world_to_camera: cam.world_to_camera(), body: body.clone() };
    let f = render_avatars(g, ctx, &styles, std::slice::from_ref(&view), res, grids, dev)?;
    if f.triangles.first().copied().unwrap_or(0) == 0 {
        return Ok(None);
    }
    let (rgb, mask) = render_images(&f)?;
    // The perturbed fit the encoder is shown.
    let fit = perturbed_body(body, rng);
    let mut fcam = cam;
    fcam.yaw += rng.normal() * 0.02;
    fcam.pitch += rng.normal() * 0.015;
    fcam.radius *= 1.0 + rng.normal() * 0.02;
    fcam.target += jitter(rng, 0.01);
    let maps = BodyMaps::render(model, &View { world_to_camera: fcam.world_to_camera(), body: fit }, res);
    let q = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
    let mut img = Vec::with_capacity(res * res * PLANES);
    for k in 0..res * res {
        img.extend((0..3).map(|c| q(rgb[3 * k + c])));
        img.push(q(mask[k]));
        img.extend((0..3).map(|c| q(0.5 * maps.normal[3 * k + c] + 0.5)));
        img.extend((0..3).map(|c| q(0.5 * maps.canonical[3 * k + c] + 0.5)));
        img.push(q(maps.mask[k]));
    }
    Ok(Some((img, styles, view)))
}

/// `body` jittered by about the errors `fit-pose` makes on MediaPipe's detections.
pub(super) fn perturbed_body(body: &BodyParams, rng: &mut Rng) -> BodyParams {
    let mut fit = body.clone();
    fit.pose[0] += jitter(rng, 0.03);
    for r in fit.pose.iter_mut().skip(1) {
        *r += jitter(rng, 0.04);
    }
    for b in fit.betas.iter_mut() {
        *b += rng.normal() * 0.15;
    }
    fit
}

/// A camera (world → camera) jittered as [`draw_pair`] jitters the fitted one: turned about
/// `center` by about 0.02 rad of yaw and 0.015 of pitch, 2 % nearer or farther, aimed 1 cm off.
pub(super) fn perturbed_camera(m: Mat4, center: Vec3, rng: &mut Rng) -> Mat4 {
    let turn = Mat4::from_translation(center)
        * Mat4::from_rotation_y(rng.normal() * 0.02)
        * Mat4::from_rotation_x(rng.normal() * 0.015)
        * Mat4::from_translation(-center);
    let mut out = m * turn;
    let scale = 1.0 + rng.normal() * 0.02;
    out.w_axis.x += rng.normal() * 0.01;
    out.w_axis.y += rng.normal() * 0.01;
    out.w_axis.z *= scale;
    out
}

pub(super) fn jitter(rng: &mut Rng, sigma: f32) -> Vec3 {
    Vec3::new(rng.normal(), rng.normal(), rng.normal()) * sigma
}

pub(super) fn shard_codes(
    views: &[View],
    geo: &[f32],
    tex: &[f32],
    (ng, nt): (usize, usize),
    res: usize,
) -> Result<Vec<u8>> {
    let n = views.len();
    let w = geo.len() / (n * ng);
    let nb = views.iter().map(|v| v.body.betas.len()).max().unwrap_or(0);
    let mut cams = Vec::new();
    let mut pose = Vec::new();
    let mut betas = Vec::new();
    let mut transl = Vec::new();
    for v in views {
        cams.extend(to_row_major(v.world_to_camera));
        pose.extend(v.body.pose.iter().flat_map(|p| p.to_array()));
        betas.extend((0..nb).map(|k| v.body.betas.get(k).copied().unwrap_or(0.0)));
        transl.extend(v.body.transl.to_array());
    }
    let tensors: Vec<NamedTensor> = vec![
        ("geo".into(), vec![n, ng, w], geo.to_vec()),
        ("tex".into(), vec![n, nt, w], tex.to_vec()),
        ("world_to_camera".into(), vec![n, 16], cams),
        ("pose".into(), vec![n, NUM_JOINTS * 3], pose),
        ("betas".into(), vec![n, nb], betas),
        ("transl".into(), vec![n, 3], transl),
    ];
    let mut meta = BTreeMap::new();
    meta.insert("format".into(), "getavatar-encoder-pairs/1".into());
    meta.insert("res".into(), res.to_string());
    Ok(write_safetensors(&meta, &tensors)?)
}

pub(super) fn read_shard(p: &Path, (ng, nt): (usize, usize), w: usize) -> Result<Shard> {
    let sp = p.with_extension("safetensors");
    let bytes = std::fs::read(&sp).with_context(|| format!("reading {}", sp.display()))?;
    let st = parse_safetensors(&bytes).with_context(|| format!("{} is not a pairs shard", sp.display()))?;
    let res: usize = st.metadata.get("res").and_then(|r| r.parse().ok()).context("the shard has no `res`")?;
    let get = |k: &str| st.tensors.get(k).with_context(|| format!("{} lacks `{k}`", sp.display()));
    let (gs, geo) = get("geo")?;
    let (_, tex) = get("tex")?;
    let n = gs[0];
    if geo.len() != n * ng * w || tex.len() != n * nt * w {
        bail!("{}: codes for another generator ({:?}); delete the pairs to render them again", sp.display(), gs);
    }
    let (_, cams) = get("world_to_camera")?;
    let (_, pose) = get("pose")?;
    let (bs, betas) = get("betas")?;
    let (_, transl) = get("transl")?;
    let nb = bs.get(1).copied().unwrap_or(0);
    if cams.len() != 16 * n || pose.len() != n * NUM_JOINTS * 3 || betas.len() != n * nb || transl.len() != 3 * n {
        bail!("{}: cameras or bodies for another number of pairs than {n}", sp.display());
    }
    let views = (0..n)
        .map(|i| {
            let mut m = [0.0f32; 16];
            m.copy_from_slice(&cams[16 * i..16 * i + 16]);
            let mut p = [Vec3::ZERO; NUM_JOINTS];
            for (j, r) in p.iter_mut().enumerate() {
                *r = Vec3::from_slice(&pose[(i * NUM_JOINTS + j) * 3..]);
            }
            let body = BodyParams {
                pose: p,
                betas: betas[i * nb..(i + 1) * nb].to_vec(),
                transl: Vec3::from_slice(&transl[3 * i..]),
            };
            View { world_to_camera: from_row_major(&m), body }
        })
        .collect();
    let bp = p.with_extension("bin");
    let images = std::fs::read(&bp).with_context(|| format!("reading {}", bp.display()))?;
    if images.len() != n * res * res * PLANES {
        bail!("{}: {} bytes, {n} pairs at {res}² need {}", bp.display(), images.len(), n * res * res * PLANES);
    }
    Ok(Shard { res, count: n, images, geo: geo.clone(), tex: tex.clone(), views })
}

impl Shard {
    /// Pair `i`'s render (RGB HWC, mask) in [0, 1] and its body maps.
    pub(super) fn pair(&self, i: usize) -> (Vec<f32>, Vec<f32>, BodyMaps) {
        let n = self.res * self.res;
        let px = &self.images[i * n * PLANES..(i + 1) * n * PLANES];
        let f = |v: u8| v as f32 / 255.0;
        let (mut rgb, mut mask) = (Vec::with_capacity(3 * n), Vec::with_capacity(n));
        let mut maps =
            BodyMaps { normal: Vec::with_capacity(3 * n), canonical: Vec::with_capacity(3 * n), mask: Vec::new() };
        for p in px.chunks_exact(PLANES) {
            rgb.extend(p[..3].iter().map(|v| f(*v)));
            mask.push(f(p[3]));
            maps.normal.extend(p[4..7].iter().map(|v| 2.0 * f(*v) - 1.0));
            maps.canonical.extend(p[7..10].iter().map(|v| 2.0 * f(*v) - 1.0));
            maps.mask.push(f(p[10]));
        }
        (rgb, mask, maps)
    }

    pub(super) fn codes(&self, i: usize, ng: usize, nt: usize, w: usize) -> (&[f32], &[f32]) {
        (&self.geo[i * ng * w..(i + 1) * ng * w], &self.tex[i * nt * w..(i + 1) * nt * w])
    }
}
