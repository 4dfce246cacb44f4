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
use getavatar_core::generator::checkpoint::{
    collect_params, load_params, parse_safetensors, save_generator_with_modes, write_safetensors, NamedTensor,
};
use getavatar_core::generator::optim::{trainable_where, Adam};
use getavatar_core::generator::pipeline::{is_face_param, is_texture_param, Generator, LatentModes, Styles};
use getavatar_core::generator::readback::read_f32_now;
use getavatar_core::io::dataset::Dataset;
use getavatar_core::render::colour::decode_srgb;
use getavatar_core::render::diff::avatar::{render_avatar_views, PixelSurface, PosedGridCache};
use getavatar_core::render::diff::scan_supervision::{texture_loss, CanonicalSamples};
use getavatar_core::util::rng::Rng;
use glam::Vec3;

use crate::atomic::write_atomic;

#[derive(clap::Args, Debug)]
pub struct FitCodesArgs {
    /// The fit's device (the views are rendered once on the CPU either way).
    #[command(flatten)]
    pub backend: crate::backend::BackendArg,
    /// The prepared dataset the checkpoint was trained on (its subjects are the latent modes'
    /// rows; a dataset of its first subjects fits those alone).
    #[arg(long)]
    pub data: PathBuf,
    #[command(flatten)]
    pub model: crate::model_io::GeneratorArgs,
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
    /// Adam's rate for the codes, after a linear warm-up over the first 20 steps (no
    /// ramp-down: a fit resumed to more steps goes on as one run would); 0 keeps the file's
    /// codes (with `--lr-texture`: fit the generator alone).
    #[arg(long, default_value_t = 0.02)]
    pub lr: f32,
    /// Adam rate of the generator's texture branch (`generator::is_texture_param`: to-texture
    /// layers, texture detail blocks, texture decoder) on the same L1, beside the codes;
    /// 0 (the default): the generator stays frozen. The geometry never changes.
    #[arg(long, default_value_t = 0.0)]
    pub lr_texture: f32,
    /// Weight of the offsets' mean square (keeps them near the subject's W code, which is
    /// where truncation with ψ > 0 starts from).
    #[arg(long, default_value_t = 0.0)]
    pub lambda_reg: f32,
    /// Weight of the texture-swap term (as `train --lambda-texture-swap`): each drawn subject's
    /// points coloured again by the texture field built from the next drawn subject's
    /// geometry styles and its own texture styles, L1 against its own colours, so that its
    /// colours stay its own on other shapes (the app's re-texturing, `pairing: branch`).
    /// 0: off.
    #[arg(long, default_value_t = 0.5)]
    pub lambda_texture_swap: f32,
    /// The training scans (`synth-scans`' folder): with `--lambda-face`, each subject's face
    /// points are drawn from its scan (as `train --lambda-face`).
    #[arg(long)]
    pub scans: Option<PathBuf>,
    /// Weight of the face term (not in the paper; as `train --lambda-face`): the same L1 at
    /// `--face-points` points per drawn subject from a pool on its scan's face
    /// (`FaceRegion`), where the views' pixels put about 1 % of the points and an eye is a
    /// pixel or two. Needs `--scans`; 0 (the default): off.
    #[arg(long, default_value_t = 0.0)]
    pub lambda_face: f32,
    /// Face points per drawn subject per step.
    #[arg(long, default_value_t = crate::train::FACE_POINTS_PER_STEP)]
    pub face_points: usize,
    /// Texture planes finer than the checkpoint's (not in the paper; as `train --texture-res`):
    /// the file grows a texture detail block, rendering as before at first, which learns with
    /// the texture branch (`--lr-texture`). Give it again to resume such a fit.
    #[arg(long)]
    pub texture_res: Option<usize>,
    /// A face plane of N² texels (not in the paper; `GeneratorConfig::face`) over the canonical
    /// body's face, grown onto a checkpoint without one (rendering as before at first) and
    /// learning with the texture branch (`--lr-texture`). Give it again to resume such a fit.
    #[arg(long)]
    pub face_res: Option<usize>,
    /// Of the generator, train the face plane alone (with `--lr-texture`): everything away
    /// from the face renders as the checkpoint did.
    #[arg(long)]
    pub face_only: bool,
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
const SURFACES_FORMAT: &str = "getavatar-fit-codes-surfaces-1";
/// Steps of the linear learning-rate warm-up (Adam's first steps move every coordinate by
/// about the rate, whatever its gradient).
const WARMUP_STEPS: f32 = 20.0;

pub fn fit_codes(a: &FitCodesArgs) -> Result<()> {
    check_args(a)?;
    let ds = Dataset::open(&a.data).with_context(|| format!("opening dataset {}", a.data.display()))?;
    #[allow(deprecated)]
    let plain = Device::ndarray();
    let ad = a.backend.device()?.autodiff();
    let (cfg, g, modes) = load_grown(a, &plain)?;
    if a.face_only && cfg.face.is_none() {
        bail!("--face-only trains the face plane, and this checkpoint has none: give --face-res N to grow one");
    }
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
    let faces = match (&a.scans, a.lambda_face > 0.0) {
        (Some(dir), true) => {
            let ctx = crate::model_io::body_context(crate::model_io::load_body(&None)?, &cfg);
            crate::train::canonical_scan_samples(dir, &ds, &ctx, a.seed, (false, true))?.face
        }
        _ => Vec::new(),
    };

    // The codes start at the file's layer offsets (none: zero, the W codes).
    let k = modes.count();
    let init = match &modes.tex_layers {
        Some(t) => read_f32_now(t.clone())?,
        None => vec![0.0; k * nt * w_dim],
    };
    let state_path = a.out.join("state.safetensors");
    let source_meta = source_metadata(&a.model)?;
    let (_, g_ad, _) = load_grown(a, &ad)?;
    // Only the texture branch is tracked where it learns; nothing of G otherwise.
    let trainable = |g: Generator| {
        if a.face_only {
            trainable_where(g, &is_face_param)
        } else if a.lr_texture > 0.0 {
            trainable_where(g, &is_texture_param)
        } else {
            g.no_grad()
        }
    };
    let mut fit = if state_path.exists() {
        let fit = FitState::load(&state_path, k, nt * w_dim, g_ad, &ad)?;
        println!("resuming the fit at step {} from {}", fit.step, state_path.display());
        fit
    } else {
        let c = TexCodes { tex: Param::from_tensor(Tensor::from_data(TensorData::new(init, [k, nt * w_dim]), &ad)) };
        FitState {
            codes: c,
            adam: Adam::new(0.9, 0.999, 1e-8),
            g: g_ad,
            adam_g: Adam::new(0.9, 0.99, 1e-8),
            step: 0,
            rng: Rng::new(a.seed, 0xf17c),
        }
    };
    fit.g = trainable(fit.g);
    // The subjects' W codes on the fit's device, once.
    let (modes_geo, modes_tex) = (modes.geo.clone().to_device(&ad), modes.tex.clone().to_device(&ad));
    let mut log = std::fs::OpenOptions::new().create(true).append(true).open(a.out.join("metrics.jsonl"))?;
    let bar = crate::progress::bar(a.steps as u64, "steps");
    bar.set_position(fit.step as u64);
    let snapshot = |fit: &FitState| -> Result<()> {
        write_atomic(&state_path, &fit.save(a.lr_texture > 0.0)?)?;
        let layers = read_f32_now(fit.codes.tex.val().detach())?;
        let fitted = LatentModes {
            tex_layers: Some(Tensor::from_data(TensorData::new(layers, [k, nt, w_dim]), &plain)),
            ..modes.clone()
        };
        let mut extra = source_meta.clone();
        extra.insert("fit_codes_steps".to_string(), fit.step.to_string());
        extra.insert("fit_codes_data".to_string(), a.data.display().to_string());
        let bytes = save_generator_with_modes(&fit.g, &cfg, Some(&fitted), &extra)?;
        write_atomic(&a.out.join("generator.safetensors"), &bytes)
    };
    while fit.step < a.steps {
        let (next, figures) = fit_step(a, fit, &pools, &faces, &modes_geo, &modes_tex, (n, nt, w_dim), &ad)?;
        fit = next;
        let StepFigures { l1, reg, swap, face, drawn, warm } = figures;
        let step = fit.step;
        if !l1.is_finite() {
            bail!("step {step}: non-finite loss; the last snapshot is intact");
        }
        let lr = a.lr * warm;
        writeln!(
            log,
            "{}",
            serde_json::json!({ "step": step, "l1": l1, "swap": swap, "face": face, "reg": reg, "lr": lr, "subjects": drawn })
        )?;
        bar.set_position(step as u64);
        bar.set_message(format!("L1 {l1:.4} reg {reg:.4}"));
        if step % a.snapshot_every == 0 || step == a.steps {
            snapshot(&fit)?;
        }
    }
    bar.finish_and_clear();
    compare_png(&a.out, &ds, &subject_of, n, &g, &cfg, &modes, &plain)?;
    let step = fit.step;
    println!(
        "fitted the texture codes of {n} subjects in {step} steps; checkpoint {}",
        a.out.join("generator.safetensors").display()
    );
    Ok(())
}

/// The flags' values checked before any work.
fn check_args(a: &FitCodesArgs) -> Result<()> {
    if a.batch == 0 || a.points == 0 || a.pool == 0 || a.steps == 0 || a.snapshot_every == 0 {
        bail!("--batch, --points, --pool, --steps and --snapshot-every must be at least 1");
    }
    let finite_at_least = |x: f32, low: f32| x >= low && x.is_finite();
    if !(finite_at_least(a.lr, 0.0)
        && (a.lr > 0.0 || a.lr_texture > 0.0)
        && finite_at_least(a.lambda_reg, 0.0)
        && finite_at_least(a.lr_texture, 0.0)
        && finite_at_least(a.lambda_texture_swap, 0.0)
        && finite_at_least(a.lambda_face, 0.0))
    {
        bail!("--lr and --lr-texture must be finite rates ≥ 0, not both 0; --lambda-reg, --lambda-texture-swap and --lambda-face finite weights ≥ 0");
    }
    if (a.face_only || a.face_res.is_some()) && a.lr_texture <= 0.0 {
        bail!("--face-res and --face-only need --lr-texture > 0 (the rate the face plane learns at)");
    }
    if a.lambda_face > 0.0 && (a.scans.is_none() || a.face_points == 0) {
        bail!("--lambda-face needs --scans (the training scans) and --face-points ≥ 1");
    }
    Ok(())
}

/// One step's figures: L1, the offsets' regulariser, the swap and face terms where on, the
/// subjects drawn and the warm-up factor of the rates.
struct StepFigures {
    l1: f32,
    reg: f32,
    swap: Option<f32>,
    face: Option<f32>,
    drawn: Vec<usize>,
    warm: f32,
}

/// One step of the fit: draw subjects and points, the texture L1 (+ swap, face, regulariser),
/// Adam on the codes (and the texture branch or face plane where it learns).
#[allow(clippy::too_many_arguments)]
fn fit_step(
    a: &FitCodesArgs,
    mut fit: FitState,
    pools: &[CanonicalSamples],
    faces: &[CanonicalSamples],
    modes_geo: &Tensor<2>,
    modes_tex: &Tensor<2>,
    (n, nt, w_dim): (usize, usize, usize),
    ad: &Device,
) -> Result<(FitState, StepFigures)> {
    let step = fit.step;
    // Each subject equally often: the steps walk through a shuffled order of them.
    let per = a.batch.min(n);
    let drawn: Vec<usize> = (0..per).map(|i| order(n, a.seed, (step * per + i) / n)[(step * per + i) % n]).collect();
    let rng = &mut fit.rng;
    let batch: Vec<(&CanonicalSamples, Vec<usize>)> =
        drawn.iter().map(|&s| (&pools[s], (0..a.points).map(|_| rng.below(pools[s].points.len())).collect())).collect();
    let idx: Vec<i64> = drawn.iter().map(|&s| s as i64).collect();
    let idx = Tensor::<1, Int>::from_data(TensorData::new(idx, [per]), ad);
    let offsets = fit.codes.tex.val().select(0, idx.clone());
    let base = fit.g.styles_from_w(modes_geo.clone().select(0, idx.clone()), modes_tex.clone().select(0, idx));
    let styles = Styles { geo: base.geo, tex: base.tex + offsets.clone().reshape([per, nt, w_dim]) };
    let planes = fit.g.triplanes(&styles);
    let l1 = texture_loss(&fit.g, &planes, &styles, &batch, ad);
    let reg = offsets.powf_scalar(2.0).mean();
    let mut loss = l1.clone() + reg.clone() * a.lambda_reg;
    let swap = (a.lambda_texture_swap > 0.0 && per > 1).then(|| {
        // The next drawn subject's geometry styles under each subject's texture styles.
        let geo = Tensor::cat(vec![styles.geo.clone().narrow(0, 1, per - 1), styles.geo.clone().narrow(0, 0, 1)], 0);
        let swapped = Styles { geo, tex: styles.tex.clone() };
        texture_loss(&fit.g, &fit.g.triplanes(&swapped), &swapped, &batch, ad)
    });
    if let Some(t) = &swap {
        loss = loss + t.clone() * a.lambda_texture_swap;
    }
    let face = (!faces.is_empty()).then(|| {
        let rng = &mut fit.rng;
        let batch: Vec<(&CanonicalSamples, Vec<usize>)> = drawn
            .iter()
            .map(|&s| (&faces[s], (0..a.face_points).map(|_| rng.below(faces[s].points.len())).collect()))
            .collect();
        texture_loss(&fit.g, &planes, &styles, &batch, ad)
    });
    if let Some(t) = &face {
        loss = loss + t.clone() * a.lambda_face;
    }
    let grads = loss.backward();
    let warm = ((step + 1) as f32 / WARMUP_STEPS).min(1.0);
    if a.lr > 0.0 {
        fit.codes = fit.adam.step(a.lr * warm, fit.codes, &grads);
    }
    if a.lr_texture > 0.0 {
        fit.g = fit.adam_g.step(a.lr_texture * warm, fit.g, &grads);
    }
    fit.step += 1;
    let (l1, reg) = (read_f32_now(l1)?[0], read_f32_now(reg)?[0]);
    let swap = swap.map(|t| read_f32_now(t).map(|v| v[0])).transpose()?;
    let face = face.map(|t| read_f32_now(t).map(|v| v[0])).transpose()?;
    Ok((fit, StepFigures { l1, reg, swap, face, drawn, warm }))
}

/// The metadata of the file `model` loads (its training step, kimg, earlier fits' records)
/// that a file derived from it carries over; none for random weights.
pub(crate) fn source_metadata(model: &crate::model_io::GeneratorArgs) -> Result<BTreeMap<String, String>> {
    let source = match (&model.checkpoint, model.random) {
        (Some(p), _) => Some(p.clone()),
        (None, false) => crate::model_io::shipped_model(&model.config()?),
        (None, true) => None,
    };
    let mut meta = BTreeMap::new();
    if let Some(p) = &source {
        let st = parse_safetensors(&std::fs::read(p).with_context(|| format!("reading {}", p.display()))?)?;
        meta.extend(
            st.metadata
                .into_iter()
                .filter(|(k, _)| !matches!(k.as_str(), "format" | "config") && !k.starts_with("latent_modes/")),
        );
    }
    Ok(meta)
}

/// The checkpoint as `--model` loads it, grown to `--texture-res` where that is finer than
/// its texture planes (the new detail block's output layer starts at zero) and by a face
/// plane with `--face-res` where it has none (its constant starts at zero).
fn load_grown(
    a: &FitCodesArgs,
    device: &Device,
) -> Result<(getavatar_core::generator::network::GeneratorConfig, Generator, Option<LatentModes>)> {
    let (cfg, g, modes) = a.model.load(device)?;
    if a.texture_res.is_some() && a.lr_texture <= 0.0 {
        bail!("--texture-res grows a texture detail block that only --lr-texture trains: give a rate > 0");
    }
    let mut grown = cfg.clone();
    if let Some(res) = a.texture_res {
        grown.texture_res = Some(res);
    }
    if let Some(res) = a.face_res {
        grown.face = Some(match &cfg.face {
            Some(f) if f.res == res => f.clone(),
            Some(f) => bail!("the checkpoint has a {}² face plane; --face-res {res} differs", f.res),
            None => {
                let model = crate::model_io::load_body(&None)?;
                getavatar_core::generator::network::face_plane::face_window(&model, res)
                    .map_err(|e| anyhow::anyhow!("--face-res needs a face on the body model: {e}"))?
            }
        });
    }
    if grown.texture_plane_res() == cfg.texture_plane_res() && grown.face == cfg.face {
        return Ok((cfg, g, modes));
    }
    let path = match (&a.model.checkpoint, a.model.random) {
        (Some(p), _) => p.clone(),
        (None, false) => {
            crate::model_io::shipped_model(&cfg).context("no shipped model for this config: give --checkpoint")?
        }
        (None, true) => bail!("--texture-res and --face-res grow a checkpoint: give --checkpoint"),
    };
    grown.validate().map_err(|e| anyhow::anyhow!("--texture-res / --face-res: {e}"))?;
    let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
    let g = getavatar_core::generator::checkpoint::load_generator_growing(&bytes, &grown, 0, device).with_context(
        || {
            format!(
                "growing {} to {}² texture planes and face plane {:?}",
                path.display(),
                grown.texture_plane_res(),
                grown.face
            )
        },
    )?;
    let modes = modes.map(|m| g.grown_modes(m)).transpose().map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    Ok((grown, g, modes))
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
    cfg: &getavatar_core::generator::network::GeneratorConfig,
    modes: &LatentModes,
    plain: &Device,
) -> Result<Vec<CanonicalSamples>> {
    let path = a.out.join("surfaces.safetensors");
    if path.exists() {
        let st = parse_safetensors(&std::fs::read(&path)?).with_context(|| format!("reading {}", path.display()))?;
        // The pools belong to one dataset's subjects at one resolution (and to the geometry of
        // the checkpoint they were rendered with, which a texture fit never changes).
        let meta = |k: &str| st.metadata.get(k).map(String::as_str);
        let want = (n.to_string(), ds.resolution.to_string());
        if meta("format") != Some(SURFACES_FORMAT)
            || meta("subjects") != Some(want.0.as_str())
            || meta("resolution") != Some(want.1.as_str())
        {
            bail!(
                "{} holds the surfaces of another fit ({:?} subjects at {:?}², this data {n} at {}²): delete it to render them again",
                path.display(),
                meta("subjects"),
                meta("resolution"),
                ds.resolution
            );
        }
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
    let ctx = crate::model_io::body_context(crate::model_io::load_body(&None)?, cfg);
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
    meta.insert("format".to_string(), SURFACES_FORMAT.to_string());
    meta.insert("subjects".to_string(), n.to_string());
    meta.insert("resolution".to_string(), res.to_string());
    write_atomic(&path, &write_safetensors(&meta, &tensors)?)?;
    Ok(pools)
}

/// What a fit resumes from: the codes, G (its texture branch learns with `--lr-texture`),
/// both optimisers, the step and the point draws' generator.
struct FitState {
    codes: TexCodes,
    adam: Adam,
    g: Generator,
    adam_g: Adam,
    step: usize,
    rng: Rng,
}

impl FitState {
    /// The state's bytes; G and its optimiser only where it learns (`with_g`).
    fn save(&self, with_g: bool) -> Result<Vec<u8>> {
        let mut tensors: Vec<NamedTensor> = Vec::new();
        let c = read_f32_now(self.codes.tex.val().detach())?;
        tensors.push(("codes".into(), self.codes.tex.dims().to_vec(), c));
        let mut meta = BTreeMap::new();
        let mut adams = vec![("adam", &self.adam)];
        if with_g {
            tensors.extend(collect_params(&self.g)?.into_iter().map(|(n, s, v)| (format!("g/{n}"), s, v)));
            adams.push(("adam_g", &self.adam_g));
        }
        for (prefix, adam) in adams {
            tensors.extend(adam.moment_tensors(&format!("{prefix}/"))?);
            meta.insert(format!("{prefix}_step"), adam.step.to_string());
        }
        let (s, inc) = self.rng.state();
        meta.insert("format".to_string(), STATE_FORMAT.to_string());
        meta.insert("step".to_string(), self.step.to_string());
        meta.insert("rng_state".to_string(), s.to_string());
        meta.insert("rng_inc".to_string(), inc.to_string());
        Ok(write_safetensors(&meta, &tensors)?)
    }

    /// The state at `path`: codes of `[k, width]`, and G's weights over `g` where it holds them.
    fn load(path: &Path, k: usize, width: usize, g: Generator, ad: &Device) -> Result<Self> {
        let st = parse_safetensors(&std::fs::read(path)?).with_context(|| format!("reading {}", path.display()))?;
        if st.metadata.get("format").map(String::as_str) != Some(STATE_FORMAT) {
            bail!("{} is not a fit-codes state", path.display());
        }
        let num = |key: &str| -> Result<u64> {
            st.metadata
                .get(key)
                .and_then(|v| v.parse().ok())
                .with_context(|| format!("{} lacks `{key}`", path.display()))
        };
        let (shape, vals) = st.tensors.get("codes").with_context(|| format!("{} lacks the codes", path.display()))?;
        if shape[..] != [k, width] {
            bail!("{}: codes of shape {shape:?}, the checkpoint needs [{k}, {width}]", path.display());
        }
        let codes =
            TexCodes { tex: Param::from_tensor(Tensor::from_data(TensorData::new(vals.clone(), [k, width]), ad)) };
        let inner = ad.clone().without_autodiff();
        let load_adam = |prefix: &str, adam: Adam| -> Result<Adam> {
            let mut adam = adam
                .with_moments(&st.tensors, &format!("{prefix}/"), &inner)
                .map_err(|e| anyhow::anyhow!("{} {e}", path.display()))?;
            adam.step = num(&format!("{prefix}_step"))?;
            Ok(adam)
        };
        let with_g = st.metadata.contains_key("adam_g_step");
        let g = if with_g { load_params(g, &st.tensors, "g/", ad)? } else { g };
        Ok(Self {
            codes,
            adam: load_adam("adam", Adam::new(0.9, 0.999, 1e-8))?,
            g,
            adam_g: if with_g { load_adam("adam_g", Adam::new(0.9, 0.99, 1e-8))? } else { Adam::new(0.9, 0.99, 1e-8) },
            step: num("step")? as usize,
            rng: Rng::from_state(num("rng_state")?, num("rng_inc")?),
        })
    }
}

/// `compare.png`: for the first view of up to 4 subjects, data | the input file at its own
/// codes | the fitted file.
#[allow(clippy::too_many_arguments)]
fn compare_png(
    out: &Path,
    ds: &Dataset,
    subject_of: &[usize],
    n: usize,
    g: &Generator,
    cfg: &getavatar_core::generator::network::GeneratorConfig,
    before: &LatentModes,
    plain: &Device,
) -> Result<()> {
    let bytes = std::fs::read(out.join("generator.safetensors"))?;
    let (g_after, after) = getavatar_core::generator::checkpoint::load_generator_and_modes(&bytes, cfg, plain)?;
    let after = after.context("the fitted file has latent modes")?;
    let ctx = crate::model_io::body_context(crate::model_io::load_body(&None)?, cfg);
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
        for (g, m) in [(g, before), (&g_after, &after)] {
            let styles = g.subject_styles(m, s, s).context("a subject inside the count")?;
            let f = getavatar_core::render::diff::avatar::render_avatars(
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
    write_atomic(&out.join("compare.png"), &getavatar_core::io::dataset::encode_png(w, h, 3, &px)?)
}
