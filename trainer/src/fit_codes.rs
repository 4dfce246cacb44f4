//! `trainer fit-codes`: W+ texture codes for every training subject of a checkpoint, fitted to
//! all of the subject's data views with the generator frozen (not in the paper: its Sec. 5.4
//! latent inversion, made multi-view and run for every training subject at once). The
//! result is the same generator with per-layer texture offsets in its latent modes
//! (`latent_modes/tex_layers`), which `eval --subject-codes`, `sample --subject`, truncation
//! and the app use.
//!
//! Why: a W+ inversion of one data view with the shipped generator frozen draws the stripes
//! that the subject's own W code renders as a smear (`assets/models/codes_vs_network.png`),
//! and W+ codes learned beside G in training (`train --codes-wplus`) are drawn too rarely
//! (a subject every 16 steps at batch 4 of 64) to get there.
//!
//! How it stays cheap: with the geometry frozen, each view's covered pixels see fixed
//! canonical surface points, and a covered pixel's RGB is the texture field there
//! ([`PixelSurface`]). So the views are rendered once, the points of the pixels inside the
//! data's silhouette are pooled per subject with the data's colours (`surfaces.safetensors`),
//! and a step is the texture branch and the texture field at points drawn from the pools: no
//! DMTet, normal field or rasterisation. The L1 is the scan texture term's
//! ([`texture_loss`]), i.e. the RGB L1 of those pixels. Resumable from `--out`.

use std::collections::BTreeMap;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use getavatar_core::burn;
use getavatar_core::burn::module::{Module, Param};
use getavatar_core::burn::tensor::{Device, Int, Tensor, TensorData};
use getavatar_core::checkpoint::{parse_safetensors, save_generator_with_modes, write_safetensors, NamedTensor};
use getavatar_core::colour::decode_srgb;
use getavatar_core::dataset::Dataset;
use getavatar_core::diff::avatar::{render_avatar_views, PixelSurface, PosedGridCache};
use getavatar_core::diff::scan_supervision::{texture_loss, CanonicalSamples};
use getavatar_core::generator::{BodyContext, Generator, LatentModes, Styles};
use getavatar_core::optim::Adam;
use getavatar_core::readback::read_f32_now;
use getavatar_core::rng::Rng;
use glam::Vec3;

use crate::atomic::write_atomic;

#[derive(clap::Args, Debug)]
pub struct FitCodesArgs {
    /// The prepared dataset the checkpoint was trained on (its subjects are the latent modes'
    /// rows; a dataset of its first subjects fits those alone).
    #[arg(long)]
    pub data: PathBuf,
    #[command(flatten)]
    pub model: crate::sample::GeneratorArgs,
    /// Output folder: `generator.safetensors` (the checkpoint with the fitted codes),
    /// `state.safetensors` and `surfaces.safetensors` (to resume), `metrics.jsonl`, `compare.png`.
    #[arg(long)]
    pub out: PathBuf,
    /// Adam steps in all (a resumed fit continues to this count).
    #[arg(long, default_value_t = 1000)]
    pub steps: usize,
    /// Subjects per step.
    #[arg(long, default_value_t = 8)]
    pub batch: usize,
    /// Surface points per subject per step.
    #[arg(long, default_value_t = 4096)]
    pub points: usize,
    /// Points pooled per subject from its views' pixels.
    #[arg(long, default_value_t = 65536)]
    pub pool: usize,
    /// Adam's rate, after a linear warm-up over the first 20 steps (no ramp-down: a fit
    /// resumed to more steps goes on as one run would).
    #[arg(long, default_value_t = 0.02)]
    pub lr: f32,
    /// Weight of the offsets' mean square (keeps them near the subject's W code, which is
    /// where truncation with ψ > 0 starts from).
    #[arg(long, default_value_t = 0.0)]
    pub lambda_reg: f32,
    /// Write the generator and the state every N steps.
    #[arg(long, default_value_t = 50)]
    pub snapshot_every: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// The fitted per-layer texture offsets, `[modes, layers · w_dim]`.
#[derive(Module, Debug)]
struct TexCodes {
    tex: Param<Tensor<2>>,
}

const STATE_FORMAT: &str = "getavatar-fit-codes-1";
/// Steps of the linear learning-rate warm-up (Adam's first steps move every coordinate by
/// about the rate, whatever its gradient).
const WARMUP_STEPS: f32 = 20.0;

pub fn fit_codes(a: &FitCodesArgs) -> Result<()> {
    if a.batch == 0 || a.points == 0 || a.pool == 0 || a.steps == 0 || a.snapshot_every == 0 {
        bail!("--batch, --points, --pool, --steps and --snapshot-every must be at least 1");
    }
    if !(a.lr > 0.0 && a.lr.is_finite() && a.lambda_reg >= 0.0 && a.lambda_reg.is_finite()) {
        bail!("--lr must be a finite rate > 0 and --lambda-reg a finite weight ≥ 0");
    }
    let ds = Dataset::open(&a.data).with_context(|| format!("opening dataset {}", a.data.display()))?;
    #[allow(deprecated)]
    let plain = Device::ndarray();
    let ad = plain.clone().autodiff();
    let (cfg, g, modes) = a.model.load(&plain)?;
    let Some(modes) = modes else {
        bail!("fit-codes needs a checkpoint with latent modes (a reconstruction or anchored run's); this one has none");
    };
    let subject_of = crate::train::subject_of_entries(&ds);
    let n = subject_of.iter().max().map_or(0, |s| s + 1);
    if n == 0 || n > modes.count() {
        bail!(
            "{} holds {n} subjects, the checkpoint has codes for {}: use the checkpoint's training data (or its first subjects)",
            a.data.display(),
            modes.count()
        );
    }
    let (_, nt) = g.num_ws();
    let w_dim = cfg.w_dim;
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;

    let pools = surface_pools(a, &ds, &subject_of, n, &g, &cfg, &modes, &plain)?;
    if let Some(s) = pools.iter().position(|p| p.points.is_empty()) {
        bail!("subject {s}: no pixel of its views is inside both the render and the data's silhouette");
    }

    // The codes start at the file's layer offsets (none: zero, the W codes).
    let k = modes.count();
    let init = match &modes.tex_layers {
        Some(t) => read_f32_now(t.clone())?,
        None => vec![0.0; k * nt * w_dim],
    };
    let state_path = a.out.join("state.safetensors");
    let (mut codes, mut adam, mut step, mut rng) = if state_path.exists() {
        let (c, adam, step, rng) = load_state(&state_path, k, nt * w_dim, &ad)?;
        println!("resuming the fit at step {step} from {}", state_path.display());
        (c, adam, step, rng)
    } else {
        let c = TexCodes { tex: Param::from_tensor(Tensor::from_data(TensorData::new(init, [k, nt * w_dim]), &ad)) };
        (c, Adam::new(0.9, 0.999, 1e-8), 0usize, Rng::new(a.seed, 0xf17c))
    };

    let (_, g_ad, _) = a.model.load(&ad)?;
    let g_ad = g_ad.no_grad();
    let ws = |m: &Tensor<2>, rows: &[usize], dev: &Device| {
        let idx: Vec<i64> = rows.iter().map(|&r| r as i64).collect();
        let idx = Tensor::<1, Int>::from_data(TensorData::new(idx, [rows.len()]), dev);
        m.clone().to_device(dev).select(0, idx)
    };
    let mut log = std::fs::OpenOptions::new().create(true).append(true).open(a.out.join("metrics.jsonl"))?;
    let bar = crate::progress::bar(a.steps as u64, "steps");
    bar.set_position(step as u64);
    let snapshot = |codes: &TexCodes, adam: &Adam, step: usize, rng: &Rng| -> Result<()> {
        write_atomic(&state_path, &save_state(codes, adam, step, rng)?)?;
        let layers = read_f32_now(codes.tex.val().detach())?;
        let fitted = LatentModes {
            tex_layers: Some(Tensor::from_data(TensorData::new(layers, [k, nt, w_dim]), &plain)),
            ..modes.clone()
        };
        let mut extra = BTreeMap::new();
        extra.insert("fit_codes_steps".to_string(), step.to_string());
        extra.insert("fit_codes_data".to_string(), a.data.display().to_string());
        write_atomic(&a.out.join("generator.safetensors"), &save_generator_with_modes(&g, &cfg, Some(&fitted), &extra)?)
    };
    while step < a.steps {
        // Each subject equally often: the steps walk through a shuffled order of them.
        let drawn: Vec<usize> = (0..a.batch.min(n))
            .map(|i| order(n, a.seed, (step * a.batch.min(n) + i) / n)[(step * a.batch.min(n) + i) % n])
            .collect();
        let batch: Vec<(&CanonicalSamples, Vec<usize>)> = drawn
            .iter()
            .map(|&s| (&pools[s], (0..a.points).map(|_| rng.below(pools[s].points.len())).collect()))
            .collect();
        let offsets = codes.tex.val().select(
            0,
            Tensor::<1, Int>::from_data(TensorData::new(drawn.iter().map(|&s| s as i64).collect(), [drawn.len()]), &ad),
        );
        let b = drawn.len();
        let base = g_ad.styles_from_w(ws(&modes.geo, &drawn, &ad), ws(&modes.tex, &drawn, &ad));
        let styles = Styles { geo: base.geo, tex: base.tex + offsets.clone().reshape([b, nt, w_dim]) };
        let planes = g_ad.triplanes(&styles);
        let l1 = texture_loss(&g_ad, &planes, &styles, &batch, &ad);
        let reg = offsets.powf_scalar(2.0).mean();
        let loss = l1.clone() + reg.clone() * a.lambda_reg;
        let grads = loss.backward();
        let lr = a.lr * ((step + 1) as f32 / WARMUP_STEPS).min(1.0);
        codes = adam.step(lr, codes, &grads);
        step += 1;
        let (l1, reg) = (read_f32_now(l1)?[0], read_f32_now(reg)?[0]);
        if !l1.is_finite() {
            bail!("step {step}: non-finite loss; the last snapshot is intact");
        }
        writeln!(log, "{}", serde_json::json!({ "step": step, "l1": l1, "reg": reg, "lr": lr, "subjects": drawn }))?;
        bar.set_position(step as u64);
        bar.set_message(format!("L1 {l1:.4} reg {reg:.4}"));
        if step % a.snapshot_every == 0 || step == a.steps {
            snapshot(&codes, &adam, step, &rng)?;
        }
    }
    bar.finish_and_clear();
    compare_png(&a.out, &ds, &subject_of, n, &g, &cfg, &modes, &plain)?;
    println!(
        "fitted the texture codes of {n} subjects in {step} steps; checkpoint {}",
        a.out.join("generator.safetensors").display()
    );
    Ok(())
}

/// A shuffled order of `0..n`, the `epoch`-th one of `seed`.
fn order(n: usize, seed: u64, epoch: usize) -> Vec<usize> {
    let mut rng = Rng::new(seed ^ 0x0de5, epoch as u64);
    let mut v: Vec<usize> = (0..n).collect();
    for i in (1..n).rev() {
        v.swap(i, rng.below(i + 1));
    }
    v
}

/// Each subject's pool: the canonical points of the pixels its views' renders cover and the
/// data's silhouette covers fully, with the data's colours (linear); at most `--pool` of them,
/// drawn evenly over its views. Computed once and kept in `surfaces.safetensors`.
#[allow(clippy::too_many_arguments)]
fn surface_pools(
    a: &FitCodesArgs,
    ds: &Dataset,
    subject_of: &[usize],
    n: usize,
    g: &Generator,
    cfg: &getavatar_core::network::GeneratorConfig,
    modes: &LatentModes,
    plain: &Device,
) -> Result<Vec<CanonicalSamples>> {
    let path = a.out.join("surfaces.safetensors");
    if path.exists() {
        let st = parse_safetensors(&std::fs::read(&path)?).with_context(|| format!("reading {}", path.display()))?;
        let pools: Vec<CanonicalSamples> = (0..n)
            .map(|s| -> Result<CanonicalSamples> {
                let get = |what: &str| {
                    st.tensors.get(&format!("{s}/{what}")).map(|(_, v)| v.clone()).with_context(|| {
                        format!("{} lacks subject {s}'s {what}: delete it to compute it again", path.display())
                    })
                };
                let v3 = |v: Vec<f32>| v.chunks_exact(3).map(Vec3::from_slice).collect::<Vec<_>>();
                Ok(CanonicalSamples { points: v3(get("points")?), normals: Vec::new(), colors: v3(get("colors")?) })
            })
            .collect::<Result<_>>()?;
        println!("the subjects' surface points from {}", path.display());
        return Ok(pools);
    }
    let ctx = BodyContext::new(crate::sample::load_body(&None)?, cfg);
    let grids = PosedGridCache::default();
    let res = ds.resolution;
    let bar = crate::progress::bar(n as u64, "subjects' views rendered");
    let mut rng = Rng::new(a.seed, 0x5ec7);
    let mut pools = Vec::with_capacity(n);
    let mut tensors: Vec<NamedTensor> = Vec::new();
    for s in 0..n {
        let entries: Vec<usize> = (0..ds.len()).filter(|&i| subject_of[i] == s).collect();
        let styles = g.subject_styles(modes, s, s).context("a subject inside the checkpoint's count (checked)")?;
        let views = vec![entries.iter().map(|&i| ds.entries[i].1.view()).collect::<Vec<_>>()];
        let f = render_avatar_views(g, &ctx, &styles, &views, res, &grids, plain)?;
        let mut per_view: Vec<(Vec<Vec3>, Vec<Vec3>)> = Vec::new();
        for (surface, &i) in f.surfaces.iter().zip(&entries) {
            let Some(PixelSurface { pixels, canonical }) = surface else { continue };
            let sample = ds.load(i)?;
            let pts = read_f32_now(canonical.clone())?;
            let (mut p, mut c) = (Vec::new(), Vec::new());
            for (k, &px) in pixels.iter().enumerate() {
                let px = px as usize;
                if sample.mask[px] < 0.999 {
                    continue;
                }
                p.push(Vec3::from_slice(&pts[3 * k..3 * k + 3]));
                c.push(Vec3::from_array([0, 1, 2].map(|ch| decode_srgb(sample.rgb[3 * px + ch]))));
            }
            per_view.push((p, c));
        }
        // At most `pool` points, the same share from each view.
        let total: usize = per_view.iter().map(|v| v.0.len()).sum();
        let mut pool = CanonicalSamples::default();
        for (p, c) in per_view {
            if total <= a.pool {
                pool.points.extend(p);
                pool.colors.extend(c);
                continue;
            }
            for _ in 0..p.len() * a.pool / total {
                let j = rng.below(p.len());
                pool.points.push(p[j]);
                pool.colors.push(c[j]);
            }
        }
        let flat = |v: &[Vec3]| v.iter().flat_map(|x| x.to_array()).collect::<Vec<f32>>();
        tensors.push((format!("{s}/points"), vec![pool.points.len(), 3], flat(&pool.points)));
        tensors.push((format!("{s}/colors"), vec![pool.colors.len(), 3], flat(&pool.colors)));
        pools.push(pool);
        bar.inc(1);
    }
    bar.finish_and_clear();
    let mut meta = BTreeMap::new();
    meta.insert("format".to_string(), "getavatar-fit-codes-surfaces-1".to_string());
    write_atomic(&path, &write_safetensors(&meta, &tensors)?)?;
    Ok(pools)
}

fn save_state(codes: &TexCodes, adam: &Adam, step: usize, rng: &Rng) -> Result<Vec<u8>> {
    let mut tensors: Vec<NamedTensor> = Vec::new();
    let c = read_f32_now(codes.tex.val().detach())?;
    tensors.push(("codes".into(), codes.tex.dims().to_vec(), c));
    for (name, (m, v)) in &adam.moments {
        for (suffix, t) in [("m", m), ("v", v)] {
            let vals = read_f32_now(t.clone())?;
            tensors.push((format!("adam/{name}/{suffix}"), vec![vals.len()], vals));
        }
    }
    let (s, inc) = rng.state();
    let mut meta = BTreeMap::new();
    meta.insert("format".to_string(), STATE_FORMAT.to_string());
    meta.insert("step".to_string(), step.to_string());
    meta.insert("adam_step".to_string(), adam.step.to_string());
    meta.insert("rng_state".to_string(), s.to_string());
    meta.insert("rng_inc".to_string(), inc.to_string());
    Ok(write_safetensors(&meta, &tensors)?)
}

fn load_state(path: &Path, k: usize, width: usize, ad: &Device) -> Result<(TexCodes, Adam, usize, Rng)> {
    let st = parse_safetensors(&std::fs::read(path)?).with_context(|| format!("reading {}", path.display()))?;
    if st.metadata.get("format").map(String::as_str) != Some(STATE_FORMAT) {
        bail!("{} is not a fit-codes state", path.display());
    }
    let num = |key: &str| -> Result<u64> {
        st.metadata.get(key).and_then(|v| v.parse().ok()).with_context(|| format!("{} lacks `{key}`", path.display()))
    };
    let (shape, vals) = st.tensors.get("codes").with_context(|| format!("{} lacks the codes", path.display()))?;
    if shape[..] != [k, width] {
        bail!("{}: codes of shape {shape:?}, the checkpoint needs [{k}, {width}]", path.display());
    }
    let codes = TexCodes { tex: Param::from_tensor(Tensor::from_data(TensorData::new(vals.clone(), [k, width]), ad)) };
    let mut adam = Adam::new(0.9, 0.999, 1e-8);
    adam.step = num("adam_step")?;
    let inner = ad.clone().without_autodiff();
    for (name, (s, m)) in &st.tensors {
        if let Some(p) = name.strip_prefix("adam/").and_then(|r| r.strip_suffix("/m")) {
            let (_, v) = st
                .tensors
                .get(&format!("adam/{p}/v"))
                .with_context(|| format!("{} lacks adam/{p}/v", path.display()))?;
            let t = |d: &Vec<f32>| Tensor::<1>::from_data(TensorData::new(d.clone(), [s[0]]), &inner);
            adam.moments.insert(p.to_string(), (t(m), t(v)));
        }
    }
    Ok((codes, adam, num("step")? as usize, Rng::from_state(num("rng_state")?, num("rng_inc")?)))
}

/// `compare.png`: for the first view of up to 4 subjects, data | the file's own codes | the
/// fitted codes.
#[allow(clippy::too_many_arguments)]
fn compare_png(
    out: &Path,
    ds: &Dataset,
    subject_of: &[usize],
    n: usize,
    g: &Generator,
    cfg: &getavatar_core::network::GeneratorConfig,
    before: &LatentModes,
    plain: &Device,
) -> Result<()> {
    let bytes = std::fs::read(out.join("generator.safetensors"))?;
    let (_, after) = getavatar_core::checkpoint::load_generator_and_modes(&bytes, cfg, plain)?;
    let after = after.context("the fitted file has latent modes")?;
    let ctx = BodyContext::new(crate::sample::load_body(&None)?, cfg);
    let grids = PosedGridCache::default();
    let r = ds.resolution;
    let shown: Vec<usize> = (0..4.min(n)).map(|k| k * n / 4.min(n)).collect();
    let (w, h) = (3 * r, shown.len() * r);
    let mut px = vec![255u8; w * h * 3];
    for (row, &s) in shown.iter().enumerate() {
        let i = (0..ds.len()).find(|&i| subject_of[i] == s).context("every subject has a view")?;
        let data = ds.load(i)?;
        let view = ds.entries[i].1.view();
        let mut cols: Vec<Vec<f32>> = vec![data.rgb.iter().map(|v| v * 2.0 - 1.0).collect()];
        for m in [before, &after] {
            let styles = g.subject_styles(m, s, s).context("a subject inside the count")?;
            let f = getavatar_core::diff::avatar::render_avatars(
                g,
                &ctx,
                &styles,
                std::slice::from_ref(&view),
                r,
                &grids,
                plain,
            )?;
            let chw = read_f32_now(f.rgb)?;
            cols.push((0..r * r * 3).map(|k| chw[(k % 3) * r * r + k / 3]).collect());
        }
        for (col, img) in cols.iter().enumerate() {
            for y in 0..r {
                for x in 0..r {
                    for c in 0..3 {
                        let v = img[(y * r + x) * 3 + c];
                        px[((row * r + y) * w + col * r + x) * 3 + c] = ((v + 1.0) * 127.5).clamp(0.0, 255.0) as u8;
                    }
                }
            }
        }
    }
    write_atomic(&out.join("compare.png"), &getavatar_core::dataset::encode_png(w, h, 3, &px)?)
}
