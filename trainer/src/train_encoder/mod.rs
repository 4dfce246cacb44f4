//! `trainer train-encoder`: the photo encoder (`getavatar_core::reconstruction::encoder`) trained on the
//! generator's own renders (E3DGE / GOAE's recipe; no outside data).
//!
//! **Pairs** (`OUT/pairs/shard_NNNN.{bin,safetensors}`, 64 per shard, deterministic in
//! `--seed` and the shard's number, so an interrupted run renders only the missing shards;
//! below 128 pairs, two shards of half each):
//! z of both branches, ψ uniform in [0, 1] towards the checkpoint's latent modes (so every
//! training subject and the blends between them occur); a body drawn as `synth-scans` draws
//! one (β, a library pose with variation); a data-protocol camera (`prepare`'s) with its
//! distance and aim jittered as photo framings vary. The avatar's RGB and mask are rendered
//! there; the body the encoder is shown is a **perturbed fit**: θ, β and the camera jittered by
//! about the errors `fit-pose` makes on MediaPipe detections (docs/benchmarks.md), so the
//! encoder tolerates a fit that is a few pixels off. `.bin` holds the 11 u8 images of each
//! pair (render RGB, mask, the perturbed body's normals, canonical coordinates, silhouette);
//! `.safetensors` the true W+ codes and views. The last shard is held out. `--render-part K/N`
//! renders only the shards whose number is K modulo N and stops, so that N processes (on a
//! GPU machine: `tools/gpu_bench.sh`, part `encoder`) render one set of pairs together.
//!
//! **Training**: code regression (mean squared error of the W+ offsets from w_avg), Adam.
//! With `--image-data DIR` (a `prepare` dataset of scans, e.g. `synth-scans --seed 5` then
//! `prepare --views 8 --res 256`) each step adds an **image term** through the differentiable
//! renderer: the encoder's guess for [`IMAGE_BATCH`] scan photos (over a random background,
//! the body perturbed as for the pairs) is rendered at [`IMAGE_RES`]² at the photo's true camera
//! and at another view of the same subject, and compared with the scan's renders as the
//! inversion compares (masked RGB L1 + MSE, the silhouette weighted up: `image_term`),
//! weighted by `--image-weight`. The last [`HELD_SUBJECTS`] subjects are held out; with image
//! data the kept encoder is the one with the lowest held-out image loss (the people it will
//! see are scans, not samples).
//! With latent modes in the checkpoint the encoder's dictionaries start at the training
//! subjects' codes (one per subject and branch), which the samples are truncated towards.
//! `--init FILE` starts a new run from an encoder's weights instead (training the shipped one
//! further on new pairs) and logs their held-out error as step 0.
//! Each step composes the renders over a random background (solid, noise, or a blurred other
//! render) and erodes or dilates the person mask by up to 2 px before the input is built, as a
//! detector's mask is off at the silhouette. `OUT/state.safetensors` (weights, Adam's moments,
//! the step and the random state) is written atomically every `--snapshot-every` steps and a
//! rerun resumes from it bit-identically; `OUT/encoder.safetensors` is the encoder alone,
//! `OUT/encoder_best.safetensors` the one with the lowest held-out code error (with image
//! data: image loss) so far (its `step`, `held_out_mse` and `held_out_image` in the metadata:
//! the one to ship, as longer runs overfit), `OUT/log.jsonl` the held-out code error against
//! w_avg's and the held-out image figures, `OUT/snapshots/step_NNNNNN.png`
//! held-out rows of input | the encoder's avatar | the truth.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use getavatar_core::burn::module::Module;
use getavatar_core::burn::tensor::{Device, Tensor, TensorData};
use getavatar_core::generator::checkpoint::{collect_params, parse_safetensors, write_safetensors, NamedTensor};
use getavatar_core::generator::optim::Adam;
use getavatar_core::generator::pipeline::{BodyContext, Generator, LatentModes, Styles};
use getavatar_core::generator::readback::read_f32_now;
use getavatar_core::reconstruction::encoder::{
    batch_tensor, load_encoder, save_encoder, BodyMaps, Encoder, EncoderConfig, EncoderImage, EncoderInput,
    ENCODER_FORMAT,
};
use getavatar_core::reconstruction::inversion::render_images;
use getavatar_core::render::diff::avatar::{render_avatars, PosedGridCache};
use getavatar_core::util::rng::Rng;

use crate::atomic::{write_atomic, write_atomic_keeping_previous};
use crate::model_io::{load_body, GeneratorArgs};

pub mod garments;
mod image_term;
mod pairs;
use image_term::ScanPhotos;
use pairs::{read_shard, render_pairs, shard_path, shard_size, Shard};

#[derive(clap::Args, Debug)]
pub struct TrainEncoderArgs {
    #[command(flatten)]
    pub model: GeneratorArgs,
    /// Pairs rendered from the generator (rounded up to shards of 64, or two halves below 128
    /// pairs; the last shard is held out).
    #[arg(long, default_value_t = 1024)]
    pub pairs: usize,
    /// Training steps (the total: a rerun with more continues).
    #[arg(long, default_value_t = 3000)]
    pub steps: u64,
    #[arg(long, default_value_t = 8)]
    pub batch: usize,
    /// Adam's learning rate (equalised-learning-rate weights).
    #[arg(long, default_value_t = 0.002)]
    pub lr: f32,
    /// Steps between checkpoints, held-out figures and snapshot grids.
    #[arg(long, default_value_t = 100)]
    pub snapshot_every: u64,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[command(flatten)]
    pub backend: crate::backend::BackendArg,
    /// Body model .npz in the SMPL layout (default: the embedded open body).
    #[arg(long)]
    pub body: Option<PathBuf>,
    /// Start a new run from this encoder's weights (e.g. the shipped one, to train it further
    /// on new pairs) instead of from scratch; its held-out error is logged as step 0.
    #[arg(long)]
    pub init: Option<PathBuf>,
    /// `K/N`: render only the shards whose number is K modulo N, then stop without training,
    /// so that N processes (or machines) render one set of pairs together; the shards are
    /// the ones a single process would render.
    #[arg(long, value_parser = parse_part)]
    pub render_part: Option<(usize, usize)>,
    /// A `prepare` dataset of scan renders for the image term (module docs); its last
    /// subjects are held out and choose the kept encoder.
    #[arg(long)]
    pub image_data: Option<PathBuf>,
    /// Weight of the image term against the code error.
    #[arg(long, default_value_t = 1.0)]
    pub image_weight: f32,
    #[arg(long)]
    pub out: PathBuf,
}

fn parse_part(s: &str) -> Result<(usize, usize), String> {
    let (k, n) = s.split_once('/').ok_or_else(|| format!("`{s}` is not K/N"))?;
    let (k, n): (usize, usize) = (
        k.trim().parse().map_err(|e| format!("K in `{s}`: {e}"))?,
        n.trim().parse().map_err(|e| format!("N in `{s}`: {e}"))?,
    );
    if n == 0 || k >= n {
        return Err(format!("`{s}`: need 0 <= K < N"));
    }
    Ok((k, n))
}

const STATE: &str = "state.safetensors";
/// Scan photos per step in the image term, each rendered at two views.
pub const IMAGE_BATCH: usize = 4;
/// The image term's render side, pixels.
pub const IMAGE_RES: usize = 64;
/// Subjects of `--image-data` held out (fewer when it has few: a quarter).
pub const HELD_SUBJECTS: usize = 8;

pub fn train_encoder(a: &TrainEncoderArgs) -> Result<()> {
    if a.batch == 0 || a.snapshot_every == 0 || a.pairs < 4 {
        bail!("--batch and --snapshot-every must be at least 1 and --pairs at least 4");
    }
    if !(a.image_weight.is_finite() && a.image_weight >= 0.0) {
        bail!("--image-weight must be a number ≥ 0 (got {})", a.image_weight);
    }
    let device = a.backend.device()?;
    let ad = device.clone().autodiff();
    let (cfg, g, modes) = a.model.load(&device)?;
    let model = load_body(&a.body)?;
    let ctx = crate::model_io::body_context(model.clone(), &cfg);
    // One dictionary code per training subject (where the checkpoint has latent modes).
    let atoms = modes.as_ref().map_or(0, |m| m.count());
    let ecfg = EncoderConfig { atoms, ..EncoderConfig::for_generator(g.num_ws(), cfg.w_dim) };
    std::fs::create_dir_all(a.out.join("pairs")).with_context(|| format!("creating {}", a.out.display()))?;
    let shards = a.pairs.div_ceil(shard_size(a.pairs));
    render_pairs(a, &g, modes.as_ref(), &ctx, &model, ecfg.res, shards, &device)?;
    if let Some((k, n)) = a.render_part {
        println!("rendered the shards {k} mod {n} of {shards} in {}", a.out.join("pairs").display());
        return Ok(());
    }
    let data: Vec<Shard> =
        (0..shards).map(|s| read_shard(&shard_path(&a.out, s), g.num_ws(), cfg.w_dim)).collect::<Result<_>>()?;
    let (train, held) = data.split_at(shards - 1);
    let dictionary = modes.as_ref().map(|m| subject_offsets(&g, m)).transpose()?;
    let scans = match &a.image_data {
        Some(p) => {
            let (_, g_ad, _) = a.model.load(&ad)?;
            Some(ScanPhotos::open(p, g_ad.no_grad(), model)?)
        }
        None => None,
    };
    train_loop(a, &g, &ctx, &ecfg, dictionary, train, &held[0], scans.as_ref(), &ad)
}

/// The training subjects' codes as offsets from w_avg, `[subjects, n·w_dim]` per branch: the
/// encoder's dictionaries at the start.
fn subject_offsets(g: &Generator, m: &LatentModes) -> Result<(Tensor<2>, Tensor<2>)> {
    let (ng, nt) = g.num_ws();
    let (mut geo, mut tex) = (Vec::new(), Vec::new());
    for k in 0..m.count() {
        let s = g.subject_styles(m, k, k).with_context(|| format!("subject {k} of the latent modes"))?;
        let off = |t: Tensor<3>, avg: Tensor<2>, n: usize| {
            let w = avg.dims()[1];
            (t - avg.unsqueeze_dim::<3>(1)).reshape([1, n * w])
        };
        geo.push(off(s.geo, g.mapping_geo.w_avg_tensor(), ng));
        tex.push(off(s.tex, g.mapping_tex.w_avg_tensor(), nt));
    }
    Ok((Tensor::cat(geo, 0), Tensor::cat(tex, 0)))
}

/// Pair `i` of `shard` as the encoder sees it in training (see [`augment`]).
fn augmented_input(shard: &Shard, i: usize, other: &[f32], rng: &mut Rng) -> EncoderInput {
    let (rgb, mask, maps) = shard.pair(i);
    augment(&rgb, &mask, &maps, shard.res, other, rng)
}

/// A render (`res`², HWC RGB and mask) with its body maps as the encoder sees it in training:
/// over a random background, with its mask eroded or dilated (`rng` draws both; `other` is
/// another render for a blurred backdrop).
fn augment(rgb: &[f32], mask: &[f32], maps: &BodyMaps, res: usize, other: &[f32], rng: &mut Rng) -> EncoderInput {
    let bg = background(res, other, rng);
    let shown: Vec<f32> = (0..res * res * 3).map(|k| rgb[k] * mask[k / 3] + bg[k] * (1.0 - mask[k / 3])).collect();
    let r = rng.below(5) as i32 - 2; // −2 … 2 px
    let m = morph(mask, res, r);
    EncoderImage::from_parts(&shown, &m, maps, res).patchify()
}

/// A backdrop: a solid colour, coloured noise, or `other` blurred and tinted.
fn background(res: usize, other: &[f32], rng: &mut Rng) -> Vec<f32> {
    let c = [rng.uniform(), rng.uniform(), rng.uniform()];
    match rng.below(3) {
        0 => (0..res * res * 3).map(|k| c[k % 3]).collect(),
        1 => (0..res * res * 3).map(|k| (c[k % 3] + 0.25 * rng.normal()).clamp(0.0, 1.0)).collect(),
        _ => {
            let small = getavatar_core::reconstruction::encoder::resample(other, res, 3, res / 8);
            let big = getavatar_core::reconstruction::encoder::resample(&small, res / 8, 3, res);
            big.iter().enumerate().map(|(k, v)| 0.6 * v + 0.4 * c[k % 3]).collect()
        }
    }
}

/// The mask dilated (r > 0) or eroded (r < 0) by |r| pixels (max / min over a square).
fn morph(mask: &[f32], res: usize, r: i32) -> Vec<f32> {
    if r == 0 {
        return mask.to_vec();
    }
    let k = r.unsigned_abs() as i64;
    let mut out = vec![0.0; mask.len()];
    for y in 0..res as i64 {
        for x in 0..res as i64 {
            let mut v: f32 = if r > 0 { 0.0 } else { 1.0 };
            for yy in (y - k).max(0)..=(y + k).min(res as i64 - 1) {
                for xx in (x - k).max(0)..=(x + k).min(res as i64 - 1) {
                    let m = mask[(yy * res as i64 + xx) as usize];
                    v = if r > 0 { v.max(m) } else { v.min(m) };
                }
            }
            out[(y * res as i64 + x) as usize] = v;
        }
    }
    out
}

/// The encoder's training state on disk: weights, Adam's moments, step and random state.
fn save_state(path: &Path, enc: &Encoder, adam: &Adam, step: u64, rng: &Rng, ecfg: &EncoderConfig) -> Result<()> {
    let mut tensors: Vec<NamedTensor> =
        collect_params(enc)?.into_iter().map(|(n, s, v)| (format!("enc/{n}"), s, v)).collect();
    tensors.extend(adam.moment_tensors("adam/")?);
    let mut meta = BTreeMap::new();
    meta.insert("format".into(), ENCODER_FORMAT.into());
    meta.insert("encoder".into(), serde_json::to_string(ecfg)?);
    meta.insert("step".into(), step.to_string());
    meta.insert("adam_step".into(), adam.step.to_string());
    let (s, inc) = rng.state();
    meta.insert("rng".into(), format!("{s} {inc}"));
    let prev = path.with_extension("previous.safetensors");
    write_atomic_keeping_previous(path, &prev, &write_safetensors(&meta, &tensors)?)
}

fn load_state(path: &Path, ad: &Device) -> Result<(Encoder, Adam, u64, Rng)> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    let enc = load_encoder(&bytes, ad).with_context(|| format!("the encoder in {}", path.display()))?;
    let st = parse_safetensors(&bytes)?;
    let num = |k: &str| -> Result<u64> {
        st.metadata.get(k).and_then(|v| v.parse().ok()).with_context(|| format!("{} lacks `{k}`", path.display()))
    };
    let mut adam = Adam::new(0.9, 0.99, 1e-8)
        .with_moments(&st.tensors, "adam/", &ad.clone().inner())
        .map_err(anyhow::Error::msg)?;
    adam.step = num("adam_step")?;
    let rng = st
        .metadata
        .get("rng")
        .and_then(|r| {
            let mut it = r.split(' ').map(|x| x.parse::<u64>().ok());
            Some(Rng::from_state(it.next()??, it.next()??))
        })
        .with_context(|| format!("{} lacks the random state", path.display()))?;
    Ok((enc, adam, num("step")?, rng))
}

/// Where a run starts: its saved state (a resumed run), the weights of `--init`, or a new
/// encoder with the subjects' dictionaries.
fn starting_state(
    a: &TrainEncoderArgs,
    ecfg: &EncoderConfig,
    dictionary: Option<(Tensor<2>, Tensor<2>)>,
    state: &Path,
    ad: &Device,
) -> Result<(Encoder, Adam, u64, Rng)> {
    Ok(if state.is_file() {
        let s = load_state(state, ad)?;
        eprintln!("resuming from {} at step {}", state.display(), s.2);
        s
    } else if let Some(init) = &a.init {
        let bytes = std::fs::read(init).with_context(|| format!("reading {}", init.display()))?;
        let st = parse_safetensors(&bytes).with_context(|| format!("{} is not an encoder", init.display()))?;
        let text = st.metadata.get("encoder").with_context(|| format!("{} has no encoder config", init.display()))?;
        let theirs: EncoderConfig =
            serde_json::from_str(text).with_context(|| format!("the encoder config in {}", init.display()))?;
        if &theirs != ecfg {
            bail!("{} is an encoder of another size ({theirs:?}) than this generator's ({ecfg:?})", init.display());
        }
        let enc = load_encoder(&bytes, ad).with_context(|| format!("the encoder in {}", init.display()))?;
        eprintln!("starting from the weights of {}", init.display());
        (enc, Adam::new(0.9, 0.99, 1e-8), 0, Rng::new(a.seed, 0xe2c0))
    } else {
        let mut enc = Encoder::new(ecfg, a.seed, ad);
        if let Some((geo, tex)) = dictionary {
            let on = |t: Tensor<2>| Tensor::<2>::from_data(t.into_data(), ad);
            enc = enc.with_dictionary(on(geo), on(tex))?;
        }
        (enc, Adam::new(0.9, 0.99, 1e-8), 0, Rng::new(a.seed, 0xe2c0))
    })
}

#[allow(clippy::too_many_arguments)]
fn train_loop(
    a: &TrainEncoderArgs,
    g: &Generator,
    ctx: &BodyContext,
    ecfg: &EncoderConfig,
    dictionary: Option<(Tensor<2>, Tensor<2>)>,
    train: &[Shard],
    held: &Shard,
    scans: Option<&ScanPhotos>,
    ad: &Device,
) -> Result<()> {
    let state = a.out.join(STATE);
    let (mut enc, mut adam, mut step, mut rng) = starting_state(a, ecfg, dictionary, &state, ad)?;
    enc.check(g)?;
    let (ng, nt) = g.num_ws();
    let w = ecfg.w_dim;
    let avg = |t: Tensor<2>| -> Result<Vec<f32>> { Ok(read_f32_now(t)?) };
    let (avg_g, avg_t) = (avg(g.mapping_geo.w_avg_tensor())?, avg(g.mapping_tex.w_avg_tensor())?);
    let offsets = |shard: &Shard, i: usize| -> Vec<f32> {
        let (cg, ct) = shard.codes(i, ng, nt, w);
        let og = cg.iter().enumerate().map(|(k, v)| v - avg_g[k % w]);
        let ot = ct.iter().enumerate().map(|(k, v)| v - avg_t[k % w]);
        og.chain(ot).collect()
    };
    let n_train: usize = train.iter().map(|s| s.count).sum();
    let locate = |mut i: usize| -> (usize, usize) {
        for (s, sh) in train.iter().enumerate() {
            if i < sh.count {
                return (s, i);
            }
            i -= sh.count;
        }
        unreachable!("index within the training pairs")
    };
    let held_photos = scans.map(|s| s.held_out(ecfg.res)).transpose()?;
    // What chooses the kept encoder: the held-out image loss with scans, else the code error.
    let key = if scans.is_some() { "held_out_image" } else { "held_out_mse" };
    let image_figures = |enc: &Encoder| -> Result<Option<image_term::ImageFigures>> {
        match (scans, &held_photos) {
            (Some(s), Some(p)) => Ok(Some(s.figures(enc, ctx, p, ad)?)),
            _ => Ok(None),
        }
    };
    let mut best = best_logged(&a.out.join("log.jsonl"), step, key)?;
    let mut log = std::fs::OpenOptions::new().create(true).append(true).open(a.out.join("log.jsonl"))?;
    if step == 0 && a.init.is_some() && best.is_infinite() {
        // The starting weights' figure, so that the run shows what training further gained.
        let (val, val_avg) = held_out_error(&enc, held, &offsets, ad)?;
        let img = image_figures(&enc)?;
        let mut line = serde_json::json!({"step": 0, "held_out_mse": val, "held_out_mse_w_avg": val_avg});
        add_image_figures(&mut line, img.as_ref());
        writeln!(log, "{line}")?;
        eprintln!(
            "step 0 (the --init weights): held-out code MSE {val:.4} (w_avg {val_avg:.4}){}",
            describe(img.as_ref())
        );
        best = img.map_or(val, |f| f.loss);
        let mut extra = BTreeMap::new();
        extra.insert("step".into(), "0".into());
        extra.insert("held_out_mse".into(), val.to_string());
        if let Some(f) = img {
            extra.insert("held_out_image".into(), f.loss.to_string());
        }
        write_atomic(&a.out.join("encoder_best.safetensors"), &save_encoder(&collect_params(&enc)?, ecfg, &extra)?)?;
    }
    let bar = crate::progress::bar(a.steps, "steps");
    bar.set_position(step.min(a.steps));
    let (mut loss_sum, mut loss_n, mut image_sum) = (0.0f64, 0usize, 0.0f64);
    let mut t0 = std::time::Instant::now();
    while step < a.steps {
        let mut inputs = Vec::with_capacity(a.batch);
        let mut targets = Vec::with_capacity(a.batch * (ng + nt) * w);
        for _ in 0..a.batch {
            let (s, i) = locate(rng.below(n_train));
            let (os, oi) = locate(rng.below(n_train));
            let other = train[os].pair(oi).0;
            inputs.push(augmented_input(&train[s], i, &other, &mut rng));
            targets.extend(offsets(&train[s], i));
        }
        let refs: Vec<&EncoderInput> = inputs.iter().collect();
        let x = batch_tensor(&refs, ad)?;
        let (pg, pt) = enc.forward(x);
        let b = a.batch;
        let pred = Tensor::cat(vec![pg.reshape([b, ng * w]), pt.reshape([b, nt * w])], 1);
        let target = Tensor::<2>::from_data(TensorData::new(targets, [b, (ng + nt) * w]), ad);
        let mut loss = (pred - target).powf_scalar(2.0).mean();
        let mut parts = vec![loss.clone()];
        if let Some(sc) = scans {
            // Each photo's backdrop is made from a random pair's render, as for the pairs.
            let draw = |rng: &mut Rng| sc.draw(ecfg.res, &train_pair(&locate, train, rng.below(n_train)), rng);
            let photos = (0..IMAGE_BATCH).map(|_| draw(&mut rng)).collect::<Result<Vec<_>>>()?;
            let (image, _) = sc.loss(&enc, ctx, &photos, ad)?;
            loss = loss + image.clone() * a.image_weight;
            parts.push(image);
        }
        let values = read_f32_now(Tensor::cat(parts.into_iter().map(|t| t.detach()).collect(), 0))?;
        let lv = values[0];
        let iv = values.get(1).copied().unwrap_or(0.0);
        if !lv.is_finite() || !iv.is_finite() {
            bail!("the loss became {lv} (code) / {iv} (image) at step {}", step + 1);
        }
        image_sum += iv as f64;
        let grads = loss.backward();
        enc = adam.step(a.lr, enc, &grads);
        step += 1;
        loss_sum += lv as f64;
        loss_n += 1;
        bar.set_position(step);
        let image_part = scans.map_or(String::new(), |_| format!(" image {iv:.4}"));
        bar.set_message(format!("code MSE {lv:.4}{image_part}"));
        if step % a.snapshot_every == 0 || step == a.steps {
            let (val, val_avg) = held_out_error(&enc, held, &offsets, ad)?;
            let img = image_figures(&enc)?;
            snapshot(a, g, ctx, &enc, held, step, ad)?;
            save_state(&state, &enc, &adam, step, &rng, ecfg)?;
            let mut extra = BTreeMap::new();
            extra.insert("step".into(), step.to_string());
            extra.insert("held_out_mse".into(), val.to_string());
            if let Some(f) = img {
                extra.insert("held_out_image".into(), f.loss.to_string());
            }
            let file = save_encoder(&collect_params(&enc)?, ecfg, &extra)?;
            write_atomic(&a.out.join("encoder.safetensors"), &file)?;
            let score = img.map_or(val, |f| f.loss);
            if score < best {
                best = score;
                write_atomic(&a.out.join("encoder_best.safetensors"), &file)?;
            }
            let mut line = serde_json::json!({
                "step": step, "train_mse": loss_sum / loss_n.max(1) as f64,
                "held_out_mse": val, "held_out_mse_w_avg": val_avg,
                "seconds_per_step": t0.elapsed().as_secs_f64() / loss_n.max(1) as f64,
            });
            if scans.is_some() {
                line["train_image"] = (image_sum / loss_n.max(1) as f64).into();
            }
            add_image_figures(&mut line, img.as_ref());
            writeln!(log, "{line}")?;
            bar.println(format!(
                "step {step}: held-out code MSE {val:.4} (w_avg {val_avg:.4}){}",
                describe(img.as_ref())
            ));
            (loss_sum, loss_n, image_sum, t0) = (0.0, 0, 0.0, std::time::Instant::now());
        }
    }
    bar.finish_and_clear();
    println!("wrote {} (step {step})", a.out.join("encoder.safetensors").display());
    Ok(())
}

/// Training pair `i` (counted over all training shards; `locate` finds its shard)'s render.
fn train_pair(locate: &dyn Fn(usize) -> (usize, usize), train: &[Shard], i: usize) -> Vec<f32> {
    let (s, k) = locate(i);
    train[s].pair(k).0
}

/// Mean squared code error of the encoder and of w_avg (zero offsets) on the held-out pairs,
/// as the app sees them (white backdrop, the detector's mask = the render's).
fn held_out_error(
    enc: &Encoder,
    held: &Shard,
    offsets: &dyn Fn(&Shard, usize) -> Vec<f32>,
    ad: &Device,
) -> Result<(f64, f64)> {
    let (mut se, mut se0, mut n) = (0.0f64, 0.0f64, 0usize);
    let all: Vec<usize> = (0..held.count).collect();
    for chunk in all.chunks(16) {
        let inputs: Vec<EncoderInput> = chunk.iter().map(|&i| clean_input(held, i)).collect();
        let refs: Vec<&EncoderInput> = inputs.iter().collect();
        let (pg, pt) = enc.forward(batch_tensor(&refs, ad)?);
        let b = chunk.len();
        let (pg, pt) = (read_f32_now(pg.detach())?, read_f32_now(pt.detach())?);
        let (lg, lt) = (pg.len() / b, pt.len() / b);
        for (j, &i) in chunk.iter().enumerate() {
            let t = offsets(held, i);
            let p = pg[j * lg..(j + 1) * lg].iter().chain(&pt[j * lt..(j + 1) * lt]);
            for (pv, tv) in p.zip(&t) {
                se += ((pv - tv) as f64).powi(2);
                se0 += (*tv as f64).powi(2);
            }
            n += t.len();
        }
    }
    Ok((se / n.max(1) as f64, se0 / n.max(1) as f64))
}

/// Pair `i` as a photo's input: on white, with the render's own mask.
fn clean_input(shard: &Shard, i: usize) -> EncoderInput {
    let (rgb, mask, maps) = shard.pair(i);
    EncoderImage::from_parts(&rgb, &mask, &maps, shard.res).patchify()
}

/// The held-out image figures in a log line (`held_out_image`, `held_out_iou`, …).
fn add_image_figures(line: &mut serde_json::Value, f: Option<&image_term::ImageFigures>) {
    if let Some(f) = f {
        line["held_out_image"] = f.loss.into();
        line["held_out_iou"] = f.iou.into();
        line["held_out_psnr"] = f.psnr.into();
        line["held_out_iou_other_view"] = f.iou_other.into();
        line["held_out_psnr_other_view"] = f.psnr_other.into();
    }
}

fn describe(f: Option<&image_term::ImageFigures>) -> String {
    f.map_or(String::new(), |f| {
        format!(
            "; held-out scans: image loss {:.4}, IoU {:.3} / PSNR {:.2} dB (other view {:.3} / {:.2})",
            f.loss, f.iou, f.psnr, f.iou_other, f.psnr_other
        )
    })
}

/// The lowest held-out figure `key` that `log` records up to `step` (a resumed run's earlier
/// snapshots; infinity without any).
fn best_logged(log: &Path, step: u64, key: &str) -> Result<f64> {
    let text = match std::fs::read_to_string(log) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(f64::INFINITY),
        Err(e) => return Err(e).with_context(|| format!("reading {}", log.display())),
    };
    let mut best = f64::INFINITY;
    for (i, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
        let v: serde_json::Value =
            serde_json::from_str(line).with_context(|| format!("{} line {}", log.display(), i + 1))?;
        let at = v["step"].as_u64().unwrap_or(u64::MAX);
        if let Some(e) = v[key].as_f64().filter(|_| at <= step) {
            best = best.min(e);
        }
    }
    Ok(best)
}

/// `OUT/snapshots/step_NNNNNN.png`: rows of held-out pairs, input (on white) | the encoder's
/// avatar at the true view | the truth.
fn snapshot(
    a: &TrainEncoderArgs,
    g: &Generator,
    ctx: &BodyContext,
    enc: &Encoder,
    held: &Shard,
    step: u64,
    ad: &Device,
) -> Result<()> {
    let res = held.res;
    let rows = held.count.min(4);
    let grids = PosedGridCache::new(2);
    let mut img = vec![255u8; rows * res * 3 * res * 3];
    for i in 0..rows {
        let input = clean_input(held, i);
        let (og, ot) = enc.forward(batch_tensor(&[&input], ad)?);
        let dev = g.mapping_geo.w_avg_tensor().device();
        let on = |t: Tensor<3>| Tensor::<3>::from_data(t.detach().into_data(), &dev);
        let w = |t: Tensor<2>| t.unsqueeze_dim::<3>(1);
        let styles =
            Styles { geo: on(og) + w(g.mapping_geo.w_avg_tensor()), tex: on(ot) + w(g.mapping_tex.w_avg_tensor()) };
        let f = render_avatars(g, ctx, &styles, std::slice::from_ref(&held.views[i]), res, &grids, &dev)?;
        let (out, out_mask) = render_images(&f)?;
        let (rgb, mask, _) = held.pair(i);
        let on_white = |c: &[f32], m: &[f32], k: usize, ch: usize| c[3 * k + ch] * m[k] + 1.0 - m[k];
        for y in 0..res {
            for x in 0..res {
                let k = y * res + x;
                for ch in 0..3 {
                    let cells = [on_white(&rgb, &mask, k, ch), on_white(&out, &out_mask, k, ch), rgb[3 * k + ch]];
                    for (col, v) in cells.iter().enumerate() {
                        let o = ((i * res + y) * 3 * res + col * res + x) * 3 + ch;
                        img[o] = (v.clamp(0.0, 1.0) * 255.0).round() as u8;
                    }
                }
            }
        }
    }
    let png = getavatar_core::io::dataset::encode_png(3 * res, rows * res, 3, &img)?;
    write_atomic(&a.out.join("snapshots").join(format!("step_{step:06}.png")), &png)
}
