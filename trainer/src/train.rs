//! `trainer train`: the paper's adversarial training (Sec. 4.5) on a prepared dataset.
//!
//! Per step: a D phase (non-saturating loss of the three discriminators — RGB, normal map,
//! mask — on real images and detached fakes; every `r1_every` steps the finite-difference R1
//! penalty on reals, scaled for lazy regularisation) and a G phase (non-saturating G loss
//! through the differentiable renderer + λ_eik·eikonal + λ_ce·SDF cross-entropy), Adam
//! β = (0, 0.99), w_avg tracking and an EMA of G. Fakes use body poses and cameras drawn from
//! the dataset's labels.
//!
//! `RUN/` holds `run.json` (the run's settings), `state.safetensors` (G, G_ema, the three Ds,
//! Adam moments, step and RNG state: resume continues bit-identically on the same backend),
//! `generator.safetensors` (G_ema alone, what `trainer sample` and the app load),
//! `metrics.jsonl` and `samples_<step>.png` grids (RGB | normal | mask at fixed seeds and
//! poses). Every file is written to a temporary name and renamed, so a kill at any moment
//! leaves the previous checkpoint intact.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use getavatar_core::body_model::BodyModel;
use getavatar_core::burn::tensor::{Device, Gradients, Tensor, TensorData};
use getavatar_core::camera::{to_row_major, View};
use getavatar_core::checkpoint::{
    collect_params, load_generator, load_params, parse_safetensors, save_generator_with_modes, write_safetensors,
};
use getavatar_core::dataset::{encode_png, Dataset, Label};
use getavatar_core::diff::avatar::{render_avatar_views_retextured, render_avatars, FakeViews, PosedGridCache};
use getavatar_core::diff::scan_supervision::{scan_losses, CanonicalSamples};
use getavatar_core::generator::{
    is_geometry_head_param, is_texture_param, BodyContext, Generator, LatentModes, ModePairing, Styles,
};
use getavatar_core::losses::{discriminator_loss, generator_loss, r1_penalty};
use getavatar_core::network::discriminator::{Discriminator, DiscriminatorConfig};
use getavatar_core::network::GeneratorConfig;
use getavatar_core::optim::{ema_update, Adam};
use getavatar_core::readback::read_f32_now;
use getavatar_core::rng::Rng;
use serde::{Deserialize, Serialize};

const STATE_FORMAT: &str = "getavatar-train-state/1";

#[derive(clap::Args, Debug)]
pub struct TrainArgs {
    /// Dataset directory (dataset.json + images, see docs/dataset.md).
    #[arg(long)]
    pub data: PathBuf,
    /// Generator size: tiny, demo or paper [default: tiny]. Like every run setting below, it
    /// is fixed when a run starts: with `--resume` a value that differs from the run's is refused.
    #[arg(long)]
    pub config: Option<String>,
    /// Run directory.
    #[arg(long, default_value = "runs/train")]
    pub out: PathBuf,
    /// Continue the run in --out; with a file: start the generator from that checkpoint
    /// (transfer learning, e.g. onto a dataset without normal maps).
    #[arg(long, num_args = 0..=1)]
    pub resume: Option<Option<PathBuf>>,
    /// ndarray (CPU) or wgpu (GPU via Vulkan/Metal/DX12).
    #[arg(long, default_value = "ndarray")]
    pub backend: String,
    /// [default: 4]
    #[arg(long)]
    pub batch: Option<usize>,
    /// Train until this many steps in total.
    #[arg(long, default_value_t = 1000)]
    pub steps: u64,
    /// Checkpoint and sample grid every N steps.
    #[arg(long, default_value_t = 100)]
    pub snapshot_every: u64,
    /// [default: 0]
    #[arg(long)]
    pub seed: Option<u64>,
    /// R1 weight γ (10 for THUman2.0-like data, 20 for RenderPeople) [default: 10].
    #[arg(long)]
    pub r1_gamma: Option<f32>,
    /// `adversarial`: the paper's objective. `reconstruction`: a warm-up that is not in the
    /// paper (fixed latents per training subject, L1 to its views); start an adversarial
    /// run from its generator with `--resume RUN/generator.safetensors` [default: adversarial].
    #[arg(long, value_enum)]
    pub objective: Option<Objective>,
    /// Adversarial runs only (not in the paper): weight of a reconstruction anchor added to
    /// G's loss, the warm-up's L1 on a batch of subject views at their fixed latents, so that
    /// an adversarial run started from a warm-up keeps its subjects while the game spreads the
    /// rest of the latent space. 0 (the default) is the paper's objective.
    #[arg(long)]
    pub lambda_reconstruction: Option<f32>,
    /// Reconstruction terms only (the warm-up, and the anchor of adversarial runs): views
    /// rendered per drawn subject, the drawn one plus others of the same subject and body pose.
    /// One surface serves all of them (triplanes, inverse skinning and DMTet are per avatar),
    /// so each step sees `batch × views` images for little more than `batch` [default: 1].
    #[arg(long)]
    pub views: Option<usize>,
    /// Reconstruction terms only (not in the paper): the scans the dataset was prepared from
    /// (`prepare --scans`, one folder per subject with its OBJ and smpl.json). Adds
    /// canonical-space texture and SDF supervision at points drawn on each drawn subject's
    /// scan (`diff::scan_supervision`), weighted by `--lambda-scan`.
    #[arg(long)]
    pub scans: Option<PathBuf>,
    /// Weight of the scan terms (with `--scans`) [default: 1].
    #[arg(long)]
    pub lambda_scan: Option<f32>,
    /// Reconstruction terms only (not in the paper): weight of a texture-swap term. Each drawn
    /// subject's surface is also coloured by the texture field built from another drawn
    /// subject's geometry code with its own texture code, and that RGB is compared with the
    /// subject's views by L1 too. With fixed latent pairs alone the colours can hide in the
    /// geometry-styled backbone, and a seed's texture code then hardly changes the colours
    /// (re-texturing renders blends); this term makes them follow the texture code. 0 (the
    /// default): off.
    #[arg(long)]
    pub lambda_texture_swap: Option<f32>,
}

impl TrainArgs {
    /// `--config`, or its default.
    pub fn config_name(&self) -> &str {
        self.config.as_deref().unwrap_or("tiny")
    }

    /// `--batch`, or its default.
    pub fn batch_size(&self) -> usize {
        self.batch.unwrap_or(4)
    }

    /// The flags that fix a run's settings and conflict with a continued run `rc`: one row per
    /// flag (the flag, the value given, the run's value, the `run.json` field to edit instead).
    /// Flags that were not given never conflict; the others must equal the run's value.
    pub fn resume_conflicts(&self, rc: &RunConfig) -> Vec<String> {
        let num = |v: f32| v.to_string();
        let objective = |o: Objective| format!("{o:?}").to_lowercase();
        let rows: [(&str, Option<String>, String, &str); 10] = [
            ("--config", self.config.clone(), rc.generator.name.clone(), "generator"),
            ("--batch", self.batch.map(|b| b.to_string()), rc.batch.to_string(), "batch"),
            ("--seed", self.seed.map(|s| s.to_string()), rc.seed.to_string(), "seed"),
            ("--r1-gamma", self.r1_gamma.map(num), num(rc.r1_gamma), "r1_gamma"),
            ("--objective", self.objective.map(objective), objective(rc.objective), "objective"),
            ("--views", self.views.map(|v| v.to_string()), rc.views_per_subject.to_string(), "views_per_subject"),
            (
                "--scans",
                self.scans.as_ref().map(|d| d.display().to_string()),
                rc.scans.clone().unwrap_or_else(|| "(none)".into()),
                "scans",
            ),
            ("--lambda-scan", self.lambda_scan.map(num), num(rc.lambda_scan), "lambda_scan"),
            (
                "--lambda-reconstruction",
                self.lambda_reconstruction.map(num),
                num(rc.lambda_reconstruction),
                "lambda_reconstruction",
            ),
            (
                "--lambda-texture-swap",
                self.lambda_texture_swap.map(num),
                num(rc.lambda_texture_swap),
                "lambda_texture_swap",
            ),
        ];
        rows.into_iter()
            .filter_map(|(flag, given, run, field)| match given {
                Some(g) if g != run => Some(format!("{flag} {g} differs from the run's {run} (field `{field}`)")),
                _ => None,
            })
            .collect()
    }
}

/// Points drawn per scan and kept for training (`--scans`).
pub const SCAN_POOL_POINTS: usize = 16384;
/// Points of each drawn subject's pool used per step.
pub const SCAN_POINTS_PER_STEP: usize = 2048;

/// What a run optimises.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Objective {
    /// The paper's objective (Sec. 4.5): three discriminators, R1, eikonal, SDF cross-entropy.
    #[default]
    Adversarial,
    /// A warm-up that is not in the paper: every training subject gets a fixed latent pair
    /// (z_geo, z_tex) and G learns to reproduce that subject's views (L1 on RGB, normal map and
    /// mask, plus the eikonal and cross-entropy terms). Dense per-pixel gradients teach garment
    /// colours and shapes in far fewer steps than the adversarial game; an adversarial run
    /// started from it (`--resume GENERATOR`) then spreads the latent space. Adam β₁ = 0.9 and
    /// lr 0.0005 (a quarter of the adversarial rate) except the texture branch (0.002).
    Reconstruction,
}

/// Settings of a run (written once to `run.json`, read back on resume).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct RunConfig {
    pub generator: GeneratorConfig,
    pub discriminator: DiscriminatorConfig,
    pub data: String,
    pub resolution: usize,
    pub use_normals: bool,
    pub batch: usize,
    pub lr_g: f32,
    /// Factor on `lr_g` for the generator's texture branch (`generator::is_texture_param`).
    /// Absent in runs written before it existed: 1. It may be edited in `run.json` between
    /// sessions; `--resume` reads it back.
    #[serde(default = "one")]
    pub lr_texture_mul: f32,
    /// Factor on `lr_g` for the SDF-residual and DMTet-offset decoders
    /// (`generator::is_geometry_head_param`). Absent in older runs: 1. Editable in `run.json` like the above.
    #[serde(default = "one")]
    pub lr_geometry_head_mul: f32,
    pub lr_d: f32,
    pub r1_gamma: f32,
    pub r1_every: u64,
    pub r1_directions: usize,
    pub lambda_eikonal: f32,
    pub lambda_cross_entropy: f32,
    pub ema_kimg: f32,
    pub seed: u64,
    /// Absent in runs written before it existed: adversarial.
    #[serde(default)]
    pub objective: Objective,
    /// Weight of the reconstruction anchor in adversarial G steps (`TrainArgs::lambda_reconstruction`).
    /// Absent in older runs: 0. Editable in `run.json` like the learning-rate factors.
    #[serde(default)]
    pub lambda_reconstruction: f32,
    /// Views per subject in the reconstruction terms (`TrainArgs::views`). Absent in older
    /// runs: 1. Editable in `run.json` like the learning-rate factors.
    #[serde(default = "one_view")]
    pub views_per_subject: usize,
    /// Scans of the subjects for the canonical-space scan terms (`TrainArgs::scans`); absent:
    /// none. Editable in `run.json` like the learning-rate factors.
    #[serde(default)]
    pub scans: Option<String>,
    /// Weight of the scan terms. Absent in older runs: 0.
    #[serde(default)]
    pub lambda_scan: f32,
    /// Weight of the texture-swap term (`TrainArgs::lambda_texture_swap`). Absent in older
    /// runs: 0. Editable in `run.json` like the learning-rate factors.
    #[serde(default)]
    pub lambda_texture_swap: f32,
}

fn one_view() -> usize {
    1
}

impl RunConfig {
    /// The settings of a fresh run on `ds` (the reference code's values, see
    /// `../shared/reference/paper-code-facts.md`; EMA half-life scaled to the batch).
    pub fn new(ds: &Dataset, data: &Path, generator: GeneratorConfig, batch: usize, r1_gamma: f32, seed: u64) -> Self {
        Self::with_objective(ds, data, generator, batch, r1_gamma, seed, Objective::Adversarial)
    }

    pub fn with_objective(
        ds: &Dataset,
        data: &Path,
        generator: GeneratorConfig,
        batch: usize,
        r1_gamma: f32,
        seed: u64,
        objective: Objective,
    ) -> Self {
        Self {
            discriminator: discriminator_config(ds.resolution, &generator),
            generator,
            data: data.display().to_string(),
            resolution: ds.resolution,
            use_normals: ds.has_normals,
            batch,
            // The reconstruction warm-up's dense L1 gradients overshoot at the adversarial rate
            // (the SDF residual inflated and collapsed whole avatars within 100 steps at 0.002).
            lr_g: match objective {
                Objective::Adversarial => 0.002,
                Objective::Reconstruction => 0.0005,
            },
            // Colours only reach the RGB image, so the texture branch cannot inflate or collapse
            // the surface: it learns at the adversarial rate in the warm-up.
            lr_texture_mul: match objective {
                Objective::Adversarial => 1.0,
                Objective::Reconstruction => 4.0,
            },
            // With silhouette gradients reaching the SDF, the adversarial game at the full rate
            // moves the surface by centimetres per step while D is still near chance, and
            // small avatars vanish within a few steps; the heads that place the surface learn
            // at a tenth of the rate there.
            lr_geometry_head_mul: match objective {
                Objective::Adversarial => 0.1,
                Objective::Reconstruction => 1.0,
            },
            lr_d: 0.002,
            r1_gamma,
            r1_every: 16,
            r1_directions: 4,
            lambda_eikonal: 0.001,
            lambda_cross_entropy: 0.01,
            ema_kimg: 10.0f32.min(batch as f32 * 10.0 / 32.0),
            seed,
            objective,
            lambda_reconstruction: 0.0,
            views_per_subject: 1,
            scans: None,
            lambda_scan: 0.0,
            lambda_texture_swap: 0.0,
        }
    }
}

/// Everything that changes during training.
pub struct State {
    pub g: Generator,
    pub g_ema: Generator,
    /// RGB, normal, mask.
    pub d: Vec<Discriminator>,
    pub adam_g: Adam,
    pub adam_d: Vec<Adam>,
    pub step: u64,
    pub rng: Rng,
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
    /// The texture-swap RGB L1 (`lambda_texture_swap > 0`); absent otherwise.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub texture_swap: Option<f32>,
    pub seconds: f64,
}

/// The value of a one-element tensor.
fn scalar(t: Tensor<1>) -> Result<f32> {
    read_f32_now(t)?.first().copied().ok_or_else(|| anyhow!("an empty tensor where a scalar was expected"))
}

pub fn device_for(backend: &str) -> Result<Device> {
    Ok(match backend {
        #[allow(deprecated)]
        "ndarray" => Device::ndarray(),
        "wgpu" => Device::wgpu_options().init().map_err(|e| anyhow!("no wgpu adapter: {e:?}"))?,
        other => bail!("unknown --backend `{other}` (ndarray, wgpu)"),
    })
}

fn discriminator_config(res: usize, g: &GeneratorConfig) -> DiscriminatorConfig {
    match g.name.as_str() {
        "paper" => DiscriminatorConfig::new(res, 32768, 512),
        "demo" => DiscriminatorConfig::new(res, 2048, 64),
        _ => DiscriminatorConfig::new(res, 512, 32),
    }
}

/// G's optimiser: the paper's Adam β = (0, 0.99) for the adversarial game; β₁ = 0.9 (momentum)
/// for the reconstruction warm-up, whose L1 gradients are noisy per batch but not adversarial.
fn generator_adam(rc: &RunConfig) -> Adam {
    match rc.objective {
        Objective::Adversarial => Adam::new(0.0, 0.99, 1e-8),
        Objective::Reconstruction => Adam::new(0.9, 0.99, 1e-8),
    }
}

impl State {
    pub fn new(rc: &RunConfig, ad: &Device, plain: &Device) -> Self {
        let seed = rc.seed;
        Self {
            g: Generator::new(&rc.generator, seed, ad),
            g_ema: Generator::new(&rc.generator, seed, plain),
            d: [3usize, 3, 1]
                .iter()
                .enumerate()
                .map(|(k, &c)| Discriminator::new(&rc.discriminator, c, seed + 100 + k as u64, ad))
                .collect(),
            adam_g: generator_adam(rc),
            adam_d: (0..3).map(|_| Adam::new(0.0, 0.99, 1e-8)).collect(),
            step: 0,
            rng: Rng::new(seed, 0x7a1e),
        }
    }

    fn save(&self, rc: &RunConfig) -> Result<Vec<u8>> {
        let mut tensors = Vec::new();
        let mut put = |prefix: &str, v: Vec<(String, Vec<usize>, Vec<f32>)>| {
            tensors.extend(v.into_iter().map(|(n, s, d)| (format!("{prefix}{n}"), s, d)));
        };
        put("g/", collect_params(&self.g)?);
        put("g_ema/", collect_params(&self.g_ema)?);
        for (k, d) in self.d.iter().enumerate() {
            put(&format!("d{k}/"), collect_params(d)?);
        }
        let adams: Vec<(String, &Adam)> = std::iter::once(("adam_g/".to_string(), &self.adam_g))
            .chain(self.adam_d.iter().enumerate().map(|(k, a)| (format!("adam_d{k}/"), a)))
            .collect();
        let mut meta = BTreeMap::new();
        for (prefix, a) in &adams {
            for (name, (m, v)) in &a.moments {
                let vals = |t: &Tensor<1>| read_f32_now(t.clone()).map_err(|e| e.context(format!("{prefix}{name}")));
                let (mv, vv) = (vals(m)?, vals(v)?);
                tensors.push((format!("{prefix}{name}/m"), vec![mv.len()], mv));
                tensors.push((format!("{prefix}{name}/v"), vec![vv.len()], vv));
            }
            meta.insert(format!("{prefix}step"), a.step.to_string());
        }
        let (s, inc) = self.rng.state();
        meta.insert("format".into(), STATE_FORMAT.into());
        meta.insert("step".into(), self.step.to_string());
        meta.insert("rng_state".into(), s.to_string());
        meta.insert("rng_inc".into(), inc.to_string());
        meta.insert("run".into(), serde_json::to_string(rc)?);
        Ok(write_safetensors(&meta, &tensors)?)
    }

    fn load(bytes: &[u8], rc: &RunConfig, ad: &Device, plain: &Device) -> Result<Self> {
        let st = parse_safetensors(bytes)?;
        if st.metadata.get("format").map(String::as_str) != Some(STATE_FORMAT) {
            bail!("not a training state (format {:?})", st.metadata.get("format"));
        }
        let num = |k: &str| -> Result<u64> {
            st.metadata.get(k).and_then(|v| v.parse().ok()).ok_or_else(|| anyhow!("state metadata lacks `{k}`"))
        };
        let mut s = State::new(rc, ad, plain);
        s.g = load_params(s.g, &st.tensors, "g/", ad)?;
        s.g_ema = load_params(s.g_ema, &st.tensors, "g_ema/", plain)?;
        s.d =
            s.d.into_iter()
                .enumerate()
                .map(|(k, d)| load_params(d, &st.tensors, &format!("d{k}/"), ad))
                .collect::<Result<_, _>>()?;
        let inner = ad.clone().without_autodiff();
        let load_adam = |prefix: &str| -> Result<Adam> {
            let mut a = if prefix == "adam_g/" { generator_adam(rc) } else { Adam::new(0.0, 0.99, 1e-8) };
            a.step = num(&format!("{prefix}step"))?;
            for (k, (shape, vals)) in &st.tensors {
                if let Some(rest) = k.strip_prefix(prefix).and_then(|r| r.strip_suffix("/m")) {
                    let v = st
                        .tensors
                        .get(&format!("{prefix}{rest}/v"))
                        .ok_or_else(|| anyhow!("state lacks {prefix}{rest}/v"))?;
                    let t = |d: &Vec<f32>| Tensor::<1>::from_data(TensorData::new(d.clone(), [shape[0]]), &inner);
                    a.moments.insert(rest.to_string(), (t(vals), t(&v.1)));
                }
            }
            Ok(a)
        };
        s.adam_g = load_adam("adam_g/")?;
        s.adam_d = (0..3).map(|k| load_adam(&format!("adam_d{k}/"))).collect::<Result<_>>()?;
        s.step = num("step")?;
        s.rng = Rng::from_state(num("rng_state")?, num("rng_inc")?);
        Ok(s)
    }
}

/// Real images as discriminator inputs: `[B, C, R, R]` in [−1, 1] (RGB, normal, mask) and cameras.
fn load_reals(ds: &Dataset, idx: &[usize], dev: &Device) -> Result<(Tensor<4>, Tensor<4>, Tensor<4>, Tensor<2>)> {
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

fn cameras(labels: &[Label], dev: &Device) -> Tensor<2> {
    let v: Vec<f32> = labels.iter().flat_map(|l| to_row_major(l.world_to_camera)).collect();
    Tensor::from_data(TensorData::new(v, [labels.len(), 16]), dev)
}

fn latents(rng: &mut Rng, b: usize, dim: usize, dev: &Device) -> Tensor<2> {
    Tensor::from_data(TensorData::new(rng.normals(b * dim), [b, dim]), dev)
}

/// One training step (D phase, lazy R1, G phase, w_avg, EMA).
pub fn train_step(
    mut st: State,
    ds: &Dataset,
    ctx: &BodyContext,
    grids: &PosedGridCache,
    scans: &[CanonicalSamples],
    rc: &RunConfig,
    ad: &Device,
) -> Result<(State, Metrics)> {
    if rc.objective == Objective::Reconstruction {
        return reconstruction_step(st, ds, ctx, grids, scans, rc, ad);
    }
    let t0 = std::time::Instant::now();
    let b = rc.batch;
    let real_idx: Vec<usize> = (0..b).map(|_| st.rng.below(ds.len())).collect();
    let fake_labels: Vec<Label> = (0..b).map(|_| ds.entries[st.rng.below(ds.len())].1.clone()).collect();
    let zg = latents(&mut st.rng, b, rc.generator.z_dim, ad);
    let zt = latents(&mut st.rng, b, rc.generator.z_dim, ad);
    let (real_rgb, real_nrm, real_msk, c_real) = load_reals(ds, &real_idx, ad)?;
    let c_fake = cameras(&fake_labels, ad);
    let res = rc.resolution;
    let active: Vec<usize> = if rc.use_normals { vec![0, 1, 2] } else { vec![0, 2] };

    // One render per step: the D phase sees it detached, the G phase through the renderer
    // (D's update does not change G, so re-rendering would give the same images).
    let styles = st.g.styles(zg.clone(), zt.clone(), 1.0);
    let prof = std::env::var_os("GETAVATAR_PROFILE").is_some();
    let lap = |what: &str| {
        if prof {
            eprintln!("{:>8.3} s  {what}", t0.elapsed().as_secs_f64());
        }
    };
    lap("reals loaded");
    let fake_views: Vec<View> = fake_labels.iter().map(Label::view).collect();
    let fakes = render_avatars(&st.g, ctx, &styles, &fake_views, res, grids, ad)?;
    lap("fakes rendered");
    let fake_imgs = [fakes.rgb.clone().detach(), fakes.normal.clone().detach(), fakes.mask.clone().detach()];
    let reals = [real_rgb, real_nrm, real_msk];
    let mut loss_d: Option<Tensor<1>> = None;
    let add = |acc: &mut Option<Tensor<1>>, t: Tensor<1>| {
        *acc = Some(match acc.take() {
            None => t,
            Some(a) => a + t,
        })
    };
    for &k in &active {
        let lf = st.d[k].forward(fake_imgs[k].clone(), c_fake.clone());
        let lr = st.d[k].forward(reals[k].clone(), c_real.clone());
        add(&mut loss_d, discriminator_loss(lf, lr));
    }
    let loss_d = loss_d.expect("active discriminators");
    let mut metrics = Metrics { loss_d: scalar(loss_d.clone())?, ..Metrics::default() };
    let mut total_d = loss_d;
    if st.step % rc.r1_every == 0 {
        let mut r1_sum: Option<Tensor<1>> = None;
        for &k in &active {
            let d = &st.d[k];
            let c = c_real.clone();
            let r1 = r1_penalty(|x| d.forward(x, c.clone()), reals[k].clone(), rc.r1_directions, 1e-2, &mut st.rng, ad);
            add(&mut r1_sum, r1.mean());
        }
        let r1 = r1_sum.expect("active");
        metrics.r1 = Some(scalar(r1.clone())?);
        total_d = total_d + r1 * (rc.r1_gamma / 2.0 * rc.r1_every as f32);
    }
    lap("D losses");
    let grads = total_d.backward();
    lap("D backward");
    let ratio = rc.r1_every as f32 / (rc.r1_every as f32 + 1.0);
    st.d =
        st.d.into_iter()
            .enumerate()
            .map(|(k, d)| if active.contains(&k) { st.adam_d[k].step(rc.lr_d * ratio, d, &grads) } else { d })
            .collect();
    lap("D step");

    // G phase: the same fakes against the updated discriminators.
    let imgs = [fakes.rgb, fakes.normal, fakes.mask];
    let mut loss_g: Option<Tensor<1>> = None;
    for &k in &active {
        add(&mut loss_g, generator_loss(st.d[k].forward(imgs[k].clone(), c_fake.clone())));
    }
    let loss_g = loss_g.expect("active");
    metrics.loss_g = scalar(loss_g.clone())?;
    metrics.eikonal = scalar(fakes.eikonal.clone())?;
    metrics.cross_entropy = scalar(fakes.cross_entropy.clone())?;
    metrics.triangles = fakes.triangles.iter().sum::<usize>() as f32 / b as f32;
    let mut total_g = loss_g + fakes.eikonal * rc.lambda_eikonal + fakes.cross_entropy * rc.lambda_cross_entropy;
    if rc.lambda_reconstruction > 0.0 {
        // The anchor: the subjects' views at their fixed latents, with their own eikonal and
        // cross-entropy terms (a second surface is extracted).
        let r = subject_reconstruction(&st.g, &mut st.rng, ds, ctx, grids, scans, rc, ad)?;
        metrics.reconstruction = Some(r.l1);
        (metrics.scan_texture, metrics.scan_sdf) = (r.scan.map(|s| s.0), r.scan.map(|s| s.1));
        total_g = total_g
            + (r.loss + r.fakes.eikonal * rc.lambda_eikonal + r.fakes.cross_entropy * rc.lambda_cross_entropy)
                * rc.lambda_reconstruction;
    }
    lap("G losses");
    let grads = total_g.backward();
    lap("G backward");
    // w_avg tracking and the EMA of G.
    let g = track_w_avg(generator_update(&mut st.adam_g, rc, st.g, &grads), zg, zt, rc.generator.w_avg_beta);
    let beta = 0.5f32.powf(b as f32 / (rc.ema_kimg * 1000.0).max(1e-8));
    st.g_ema = ema_update(st.g_ema, &g, beta);
    st.g = g;
    lap("G step, w_avg, EMA");
    st.step += 1;
    metrics.step = st.step;
    metrics.kimg = st.step as f64 * b as f64 / 1000.0;
    metrics.seconds = t0.elapsed().as_secs_f64();
    Ok((st, metrics))
}

/// One Adam step of G at `lr_g`, the texture branch at `lr_g · lr_texture_mul` and the
/// geometry heads at `lr_g · lr_geometry_head_mul`.
fn generator_update(adam: &mut Adam, rc: &RunConfig, g: Generator, grads: &Gradients) -> Generator {
    let (tex, geo) = (rc.lr_texture_mul, rc.lr_geometry_head_mul);
    adam.step_scaled(rc.lr_g, g, grads, &|name| {
        if is_texture_param(name) {
            tex
        } else if is_geometry_head_param(name) {
            geo
        } else {
            1.0
        }
    })
}

fn one() -> f32 {
    1.0
}

/// Track both mapping networks' w_avg (decay `beta`) on this step's latents.
fn track_w_avg(mut g: Generator, zg: Tensor<2>, zt: Tensor<2>, beta: f32) -> Generator {
    let wg = g.mapping_geo.forward(zg.detach());
    g.mapping_geo = g.mapping_geo.track_w_avg(wg, beta);
    let wt = g.mapping_tex.forward(zt.detach());
    g.mapping_tex = g.mapping_tex.track_w_avg(wt, beta);
    g
}

/// Subject of every dataset entry (the folder part of its image path) as an index into the
/// sorted subject names.
fn subject_of_entries(ds: &Dataset) -> Vec<usize> {
    let names: std::collections::BTreeSet<&str> = ds.entries.iter().map(|(p, _)| subject_name(p)).collect();
    let names: Vec<&str> = names.into_iter().collect();
    ds.entries.iter().map(|(p, _)| names.binary_search(&subject_name(p)).unwrap_or(0)).collect()
}

/// The subject (folder) of a dataset entry `subject/view.png`; "" for a top-level file.
fn subject_name(entry: &str) -> &str {
    entry.rsplit_once('/').map_or("", |(d, _)| d)
}

/// The fixed latent pair (z_geo, z_tex) `[B, z_dim]` of each subject for the reconstruction
/// objective (a function of the run seed and the subject index only).
fn subject_latents(rc: &RunConfig, subjects: &[usize], dev: &Device) -> (Tensor<2>, Tensor<2>) {
    let z = rc.generator.z_dim;
    let draw = |stream: u64| -> Vec<f32> {
        subjects.iter().flat_map(|&s| Rng::new(rc.seed.wrapping_add(stream), s as u64).normals(z)).collect()
    };
    let t = |v: Vec<f32>| Tensor::from_data(TensorData::new(v, [subjects.len(), z]), dev);
    (t(draw(0x9e0)), t(draw(0x7e8)))
}

/// The W codes of the training subjects' fixed latents under `g`, saved with the generator of
/// reconstruction and anchored runs as the modes of multi-modal truncation; None for the
/// paper's objective, whose latents have no subjects.
fn subject_modes(g: &Generator, ds: &Dataset, rc: &RunConfig, dev: &Device) -> Option<LatentModes> {
    if rc.objective == Objective::Adversarial && rc.lambda_reconstruction == 0.0 {
        return None;
    }
    let n = subject_of_entries(ds).into_iter().max()? + 1;
    let (zg, zt) = subject_latents(rc, &(0..n).collect::<Vec<_>>(), dev);
    // With the texture-swap term the colours follow the texture code, so each branch may
    // go to its own nearest subject (one subject's geometry, another's colours).
    let pairing = if rc.lambda_texture_swap > 0.0 { ModePairing::Branch } else { ModePairing::Subject };
    Some(LatentModes { geo: g.mapping_geo.forward(zg), tex: g.mapping_tex.forward(zt), pairing })
}

/// The warm-up's reconstruction term: G renders `rc.batch` random views of the dataset (drawn
/// from `rng`), each at its subject's fixed latents and the view's camera and body pose, plus
/// `rc.views_per_subject − 1` further views of the same avatar, and is compared with the real
/// images by L1 (RGB + mask, + normal map where the data has them).
/// With `scans` (one per subject) and `rc.lambda_scan > 0`, adds the weighted scan terms at
/// `SCAN_POINTS_PER_STEP` points of each drawn subject's scan. With
/// `rc.lambda_texture_swap > 0` (and more than one subject in the batch), adds the weighted
/// texture-swap term: the same surfaces coloured by the texture field of (the next drawn
/// subject's w_geo, this subject's w_tex), L1 against this subject's RGB views.
fn subject_reconstruction(
    g: &Generator,
    rng: &mut Rng,
    ds: &Dataset,
    ctx: &BodyContext,
    grids: &PosedGridCache,
    scans: &[CanonicalSamples],
    rc: &RunConfig,
    ad: &Device,
) -> Result<SubjectReconstruction> {
    let idx: Vec<usize> = (0..rc.batch).map(|_| rng.below(ds.len())).collect();
    let subjects = subject_of_entries(ds);
    // Each drawn view, then further views of its subject under the same body pose and shape
    // (drawn with replacement; none are drawn with one view per subject, keeping older runs'
    // random streams).
    let body = |i: usize| {
        let l = &ds.entries[i].1;
        (l.global_orient, l.body_pose, l.betas)
    };
    let groups: Vec<Vec<usize>> = idx
        .iter()
        .map(|&i| {
            let mut group = vec![i];
            if rc.views_per_subject > 1 {
                let others: Vec<usize> =
                    (0..ds.len()).filter(|&j| j != i && subjects[j] == subjects[i] && body(j) == body(i)).collect();
                if !others.is_empty() {
                    group.extend((1..rc.views_per_subject).map(|_| others[rng.below(others.len())]));
                }
            }
            group
        })
        .collect();
    let views: Vec<Vec<View>> = groups.iter().map(|g| g.iter().map(|&i| ds.entries[i].1.view()).collect()).collect();
    let (zg, zt) = subject_latents(rc, &idx.iter().map(|&i| subjects[i]).collect::<Vec<_>>(), ad);
    let (real_rgb, real_nrm, real_msk, _) = load_reals(ds, &groups.concat(), ad)?;
    let styles = g.styles(zg.clone(), zt.clone(), 1.0);
    let b = styles.geo.dims()[0];
    let swap = (rc.lambda_texture_swap > 0.0 && b > 1).then(|| Styles {
        geo: Tensor::cat(vec![styles.geo.clone().narrow(0, 1, b - 1), styles.geo.clone().narrow(0, 0, 1)], 0),
        tex: styles.tex.clone(),
    });
    let fakes = render_avatar_views_retextured(g, ctx, &styles, swap.as_ref(), &views, rc.resolution, grids, ad)?;
    let l1 = |a: Tensor<4>, b: Tensor<4>| (a - b).abs().mean();
    let mut texture_swap = None;
    let mut swap_loss = None;
    if let Some(rgb) = fakes.rgb_retextured.clone() {
        let t = l1(rgb, real_rgb.clone());
        texture_swap = Some(scalar(t.clone())?);
        swap_loss = Some(t * rc.lambda_texture_swap);
    }
    let mut loss = l1(fakes.rgb.clone(), real_rgb) + l1(fakes.mask.clone(), real_msk);
    if rc.use_normals {
        loss = loss + l1(fakes.normal.clone(), real_nrm);
    }
    let l1 = scalar(loss.clone())?;
    if let Some(t) = swap_loss {
        loss = loss + t;
    }
    let mut scan = None;
    if rc.lambda_scan > 0.0 && !scans.is_empty() {
        let batch: Vec<(&CanonicalSamples, Vec<usize>)> = idx
            .iter()
            .map(|&i| {
                let s = &scans[subjects[i].min(scans.len() - 1)];
                (s, (0..SCAN_POINTS_PER_STEP).map(|_| rng.below(s.len().max(1))).collect())
            })
            .collect();
        let terms = scan_losses(g, ctx, &styles, &batch, ad);
        scan = Some((scalar(terms.texture.clone())?, scalar(terms.sdf.clone())?));
        loss = loss + (terms.texture + terms.sdf) * rc.lambda_scan;
    }
    Ok(SubjectReconstruction { loss, l1, scan, texture_swap, fakes, zg, zt })
}

/// The reconstruction terms of one step ([`subject_reconstruction`]).
struct SubjectReconstruction {
    /// Image L1 plus the weighted scan terms.
    loss: Tensor<1>,
    /// The image L1 alone.
    l1: f32,
    /// Scan texture and SDF terms (unweighted), where used.
    scan: Option<(f32, f32)>,
    /// The texture-swap L1 (unweighted), where used.
    texture_swap: Option<f32>,
    /// The renders (for the eikonal and cross-entropy terms).
    fakes: FakeViews,
    zg: Tensor<2>,
    zt: Tensor<2>,
}

/// One step of the reconstruction warm-up (`Objective::Reconstruction`): the subject
/// reconstruction L1 plus the eikonal and SDF cross-entropy terms; then w_avg tracking and an
/// EMA with StyleGAN2-ADA's ramp-up (half-life at most 5 % of the images seen so far).
fn reconstruction_step(
    mut st: State,
    ds: &Dataset,
    ctx: &BodyContext,
    grids: &PosedGridCache,
    scans: &[CanonicalSamples],
    rc: &RunConfig,
    ad: &Device,
) -> Result<(State, Metrics)> {
    let t0 = std::time::Instant::now();
    let b = rc.batch;
    let SubjectReconstruction { loss, l1, scan, texture_swap, fakes, zg, zt } =
        subject_reconstruction(&st.g, &mut st.rng, ds, ctx, grids, scans, rc, ad)?;
    let metrics = Metrics {
        loss_g: scalar(loss.clone())?,
        reconstruction: Some(l1),
        scan_texture: scan.map(|s| s.0),
        scan_sdf: scan.map(|s| s.1),
        texture_swap,
        eikonal: scalar(fakes.eikonal.clone())?,
        cross_entropy: scalar(fakes.cross_entropy.clone())?,
        triangles: fakes.triangles.iter().sum::<usize>() as f32 / fakes.triangles.len().max(1) as f32,
        ..Metrics::default()
    };
    let total = loss + fakes.eikonal * rc.lambda_eikonal + fakes.cross_entropy * rc.lambda_cross_entropy;
    let grads = total.backward();
    let g = track_w_avg(generator_update(&mut st.adam_g, rc, st.g, &grads), zg, zt, rc.generator.w_avg_beta);
    let seen_kimg = (st.step + 1) as f32 * b as f32 / 1000.0;
    let half_life = rc.ema_kimg.min(0.05 * seen_kimg);
    st.g_ema = ema_update(st.g_ema, &g, 0.5f32.powf(b as f32 / (half_life * 1000.0).max(1e-8)));
    st.g = g;
    st.step += 1;
    let (step, seconds) = (st.step, t0.elapsed().as_secs_f64());
    Ok((st, Metrics { step, kimg: step as f64 * b as f64 / 1000.0, seconds, ..metrics }))
}

/// The scan samples of every dataset subject (index = `subject_of_entries`), in canonical
/// space under the body fit of the subject's views: `SCAN_POOL_POINTS` points per scan, drawn
/// deterministically from (seed, subject name). A subject without a scan under `dir` is an
/// error.
fn canonical_scan_samples(dir: &Path, ds: &Dataset, ctx: &BodyContext, seed: u64) -> Result<Vec<CanonicalSamples>> {
    let found: BTreeMap<String, PathBuf> = crate::prepare::find_subjects(dir)?.into_iter().collect();
    let subjects = subject_of_entries(ds);
    let n = subjects.iter().copied().max().map_or(0, |m| m + 1);
    // Each subject's name and the body fit of its first view.
    let mut first: Vec<Option<(String, Label)>> = vec![None; n];
    for ((path, label), &s) in ds.entries.iter().zip(&subjects) {
        if first[s].is_none() {
            first[s] = Some((subject_name(path).to_string(), label.clone()));
        }
    }
    let bar = crate::progress::bar(n as u64, "scans");
    bar.set_message(format!("scan samples from {}", dir.display()));
    let load = |(name, label): &(String, Label)| -> Result<CanonicalSamples> {
        let obj = found.get(name).ok_or_else(|| anyhow!("no scan of subject `{name}` under {}", dir.display()))?;
        let scan = crate::prepare::load_scan(obj)?;
        let smpl = crate::prepare::load_smpl(name, obj, None)?;
        let prepared = getavatar_core::scan::RenderableScan::new(&scan, &smpl);
        let mut rng = Rng::new(seed, getavatar_core::rng::hash_str(name));
        let surface = getavatar_core::scan::sample_surface(&scan, &prepared, SCAN_POOL_POINTS, &mut rng);
        if surface.is_empty() {
            bail!("the scan of subject `{name}` has no surface area");
        }
        bar.inc(1);
        Ok(CanonicalSamples::from_surface(&surface, ctx, &label.body_params()))
    };
    let todo: Vec<&(String, Label)> = first.iter().flatten().collect();
    let out: Vec<CanonicalSamples> = {
        use rayon::prelude::*;
        todo.par_iter().map(|x| load(x)).collect::<Result<_>>()?
    };
    bar.finish_and_clear();
    println!("scan terms: {} points from each of {} scans under {}", SCAN_POOL_POINTS, out.len(), dir.display());
    Ok(out)
}

use crate::atomic::write_atomic;

/// L1 (in [0, 1] units, mean over pixels and channels) between G_ema's renders of the
/// sample grid's subjects and the data's views of them: a fixed yardstick of how far a
/// reconstruction run has fitted its subjects, comparable across snapshots of one dataset.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct GridL1 {
    pub step: u64,
    pub rgb: f32,
    pub normal: Option<f32>,
    pub mask: f32,
}

/// RGB | normal | mask rows of G_ema at fixed seeds and the first labels of the dataset: the
/// snapshot's sample grid (PNG) and, for reconstruction runs, its [`GridL1`] against the data.
fn sample_grid(
    st: &State,
    ds: &Dataset,
    ctx: &BodyContext,
    grids: &PosedGridCache,
    rc: &RunConfig,
    plain: &Device,
) -> Result<(Vec<u8>, Option<GridL1>)> {
    let n = 4.min(ds.len());
    let shown: Vec<usize> = (0..n).map(|i| i * ds.len() / n).collect();
    let labels: Vec<Label> = shown.iter().map(|&i| ds.entries[i].1.clone()).collect();
    let (zg, zt) = if rc.objective == Objective::Reconstruction {
        // The subjects of the shown views, to compare with the data.
        let subjects = subject_of_entries(ds);
        subject_latents(rc, &(0..n).map(|i| subjects[i * ds.len() / n]).collect::<Vec<_>>(), plain)
    } else {
        let mut rng = Rng::new(12345, 1);
        (latents(&mut rng, n, rc.generator.z_dim, plain), latents(&mut rng, n, rc.generator.z_dim, plain))
    };
    let views: Vec<View> = labels.iter().map(Label::view).collect();
    let f = render_avatars(&st.g_ema, ctx, &st.g_ema.styles(zg, zt, 1.0), &views, rc.resolution, grids, plain)?;
    let fit = if rc.objective == Objective::Reconstruction {
        let (rgb, nrm, msk, _) = load_reals(ds, &shown, plain)?;
        // Images are in [-1, 1]: half the mean absolute difference is in [0, 1] units.
        let l1 = |a: Tensor<4>, b: Tensor<4>| -> Result<f32> { Ok(scalar((a - b).abs().mean())? / 2.0) };
        Some(GridL1 {
            step: st.step,
            rgb: l1(f.rgb.clone(), rgb)?,
            normal: if rc.use_normals { Some(l1(f.normal.clone(), nrm)?) } else { None },
            mask: l1(f.mask.clone(), msk)?,
        })
    } else {
        None
    };
    let r = rc.resolution;
    let imgs = [f.rgb, f.normal, f.mask.repeat_dim(1, 3)];
    let vals: Vec<Vec<f32>> = imgs.into_iter().map(read_f32_now).collect::<Result<_, _>>()?;
    let (w, h) = (n * r, 3 * r);
    let mut px = vec![0u8; w * h * 3];
    for (row, v) in vals.iter().enumerate() {
        for s in 0..n {
            for y in 0..r {
                for x in 0..r {
                    for c in 0..3 {
                        let val = v[((s * 3 + c) * r + y) * r + x];
                        px[((row * r + y) * w + s * r + x) * 3 + c] = ((val + 1.0) * 127.5).clamp(0.0, 255.0) as u8;
                    }
                }
            }
        }
    }
    Ok((encode_png(w, h, 3, &px)?, fit))
}

pub fn train(a: &TrainArgs) -> Result<()> {
    let ds = Dataset::open(&a.data).with_context(|| format!("opening dataset {}", a.data.display()))?;
    if !ds.resolution.is_power_of_two() || ds.resolution < 16 {
        bail!("dataset resolution {} must be a power of two ≥ 16", ds.resolution);
    }
    let base = device_for(&a.backend)?;
    let (ad, plain) = (base.clone().autodiff(), base);
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let run_path = a.out.join("run.json");
    let state_path = a.out.join("state.safetensors");
    let continuing = matches!(a.resume, Some(None));
    let rc = if continuing {
        let text = std::fs::read_to_string(&run_path)
            .with_context(|| format!("--resume: no run to continue in {} (run.json missing)", a.out.display()))?;
        let rc = serde_json::from_str::<RunConfig>(&text).context("run.json")?;
        let conflicts = a.resume_conflicts(&rc);
        if !conflicts.is_empty() {
            bail!(
                "{}: a continued run keeps its settings (edit them in {} to change them)",
                conflicts.join("; "),
                run_path.display()
            );
        }
        rc
    } else {
        if state_path.exists() {
            bail!(
                "{} already holds a training run: pass --resume to continue it, or choose another --out",
                a.out.display()
            );
        }
        let objective = a.objective.unwrap_or_default();
        let lambda_reconstruction = a.lambda_reconstruction.unwrap_or(0.0);
        let lambda_texture_swap = a.lambda_texture_swap.unwrap_or(0.0);
        let lambda_scan = a.lambda_scan.unwrap_or(1.0);
        let views = a.views.unwrap_or(1);
        let reconstruction_terms = objective == Objective::Reconstruction || lambda_reconstruction > 0.0;
        if lambda_reconstruction != 0.0 && objective != Objective::Adversarial {
            bail!("--lambda-reconstruction weighs an anchor of adversarial runs; the reconstruction objective is that term alone");
        }
        if !(lambda_reconstruction >= 0.0 && lambda_reconstruction.is_finite()) {
            bail!("--lambda-reconstruction must be a finite weight ≥ 0, got {lambda_reconstruction}");
        }
        if views == 0 {
            bail!("--views must be at least 1");
        }
        if views > 1 && !reconstruction_terms {
            bail!("--views applies to reconstruction terms: use it with --objective reconstruction or --lambda-reconstruction");
        }
        if a.scans.is_some() && !reconstruction_terms {
            bail!("--scans applies to reconstruction terms: use it with --objective reconstruction or --lambda-reconstruction");
        }
        if !(lambda_scan >= 0.0 && lambda_scan.is_finite()) {
            bail!("--lambda-scan must be a finite weight ≥ 0, got {lambda_scan}");
        }
        if !(lambda_texture_swap >= 0.0 && lambda_texture_swap.is_finite()) {
            bail!("--lambda-texture-swap must be a finite weight ≥ 0, got {lambda_texture_swap}");
        }
        if lambda_texture_swap > 0.0 && !reconstruction_terms {
            bail!("--lambda-texture-swap applies to reconstruction terms: use it with --objective reconstruction or --lambda-reconstruction");
        }
        let r1_gamma = a.r1_gamma.unwrap_or(10.0);
        if !(r1_gamma >= 0.0 && r1_gamma.is_finite()) {
            bail!("--r1-gamma must be a finite weight ≥ 0, got {r1_gamma}");
        }
        let gcfg = GeneratorConfig::preset(a.config_name())
            .with_context(|| format!("unknown --config `{}`", a.config_name()))?;
        let rc = RunConfig {
            lambda_reconstruction,
            views_per_subject: views,
            scans: a.scans.as_ref().map(|d| d.display().to_string()),
            lambda_scan: if a.scans.is_some() { lambda_scan } else { 0.0 },
            lambda_texture_swap,
            ..RunConfig::with_objective(&ds, &a.data, gcfg, a.batch_size(), r1_gamma, a.seed.unwrap_or(0), objective)
        };
        write_atomic(&run_path, serde_json::to_string_pretty(&rc)?.as_bytes())?;
        rc
    };
    if rc.resolution != ds.resolution {
        bail!("the run was trained at {}², the dataset has {}² images", rc.resolution, ds.resolution);
    }
    let rc = RunConfig { use_normals: rc.use_normals && ds.has_normals, ..rc };
    let mut st = if continuing && state_path.exists() {
        let bytes = std::fs::read(&state_path)?;
        State::load(&bytes, &rc, &ad, &plain).with_context(|| format!("loading {}", state_path.display()))?
    } else {
        let mut st = State::new(&rc, &ad, &plain);
        if let Some(Some(init)) = &a.resume {
            // Transfer learning (paper Sec. 5.3): start G from a trained generator.
            let bytes = std::fs::read(init).with_context(|| format!("reading {}", init.display()))?;
            st.g = load_generator(&bytes, &rc.generator, &ad)?;
            st.g_ema = load_generator(&bytes, &rc.generator, &plain)?;
            println!("initialised the generator from {}", init.display());
        }
        st
    };
    if !rc.use_normals {
        println!("the dataset has no normal maps: the normal discriminator is off");
    }
    let model = BodyModel::default_body()?;
    let ctx = BodyContext::new(model, &rc.generator);
    let grids = PosedGridCache::default();
    let scans = match &rc.scans {
        Some(dir) if rc.lambda_scan > 0.0 => canonical_scan_samples(Path::new(dir), &ds, &ctx, rc.seed)?,
        _ => Vec::new(),
    };
    let bar = crate::progress::bar(a.steps, "steps");
    bar.set_position(st.step.min(a.steps));
    let mut log = std::fs::OpenOptions::new().create(true).append(true).open(a.out.join("metrics.jsonl"))?;
    let t0 = std::time::Instant::now();
    let start = st.step;
    let mut last = Metrics::default();
    let snapshot = |st: &State, step: u64| -> Result<()> {
        let mut extra = BTreeMap::new();
        extra.insert("kimg".to_string(), format!("{:.3}", step as f64 * rc.batch as f64 / 1000.0));
        extra.insert("step".to_string(), step.to_string());
        let modes = subject_modes(&st.g_ema, &ds, &rc, &plain);
        let g_bytes = save_generator_with_modes(&st.g_ema, &rc.generator, modes.as_ref(), &extra)?;
        write_atomic(&a.out.join("generator.safetensors"), &g_bytes)?;
        write_atomic(&state_path, &st.save(&rc)?)?;
        let (png, fit) = sample_grid(st, &ds, &ctx, &grids, &rc, &plain)?;
        write_atomic(&a.out.join(format!("samples_{step:06}.png")), &png)?;
        if let Some(fit) = fit {
            // One line per snapshot; a resumed run appends (rows of steps done twice after
            // a crash appear twice, the later one counts).
            let mut f = std::fs::OpenOptions::new().create(true).append(true).open(a.out.join("grid_l1.jsonl"))?;
            writeln!(f, "{}", serde_json::to_string(&fit)?)?;
        }
        write_atomic(&a.out.join("losses.png"), &loss_plot(&a.out.join("metrics.jsonl"))?)
    };
    while st.step < a.steps {
        let (next, m) = train_step(st, &ds, &ctx, &grids, &scans, &rc, &ad)?;
        st = next;
        writeln!(log, "{}", serde_json::to_string(&m)?)?;
        bar.set_position(st.step);
        let rec = m.reconstruction.map(|r| format!(" rec {r:.4}")).unwrap_or_default();
        bar.set_message(format!(
            "kimg {:.3} G {:.3} D {:.3} eik {:.3} ce {:.3}{rec}",
            m.kimg, m.loss_g, m.loss_d, m.eikonal, m.cross_entropy
        ));
        if !(m.loss_g.is_finite() && m.loss_d.is_finite()) {
            bail!("step {}: non-finite loss (G {}, D {}); the last checkpoint is intact", m.step, m.loss_g, m.loss_d);
        }
        if st.step % a.snapshot_every == 0 || st.step == a.steps {
            snapshot(&st, st.step)?;
        }
        last = m;
    }
    bar.finish_and_clear();
    let dt = t0.elapsed().as_secs_f64();
    let done = st.step - start;
    println!(
        "trained {done} steps ({:.3} kimg total) in {:.1} s ({:.2} s/step, {:.1} s/kimg) on {}; last losses G {:.4} D {:.4}; checkpoint {}",
        st.step as f64 * rc.batch as f64 / 1000.0,
        dt,
        dt / done.max(1) as f64,
        dt / (done.max(1) as f64 * rc.batch as f64 / 1000.0),
        a.backend,
        last.loss_g,
        last.loss_d,
        state_path.display()
    );
    Ok(())
}

/// Timings of a few training steps of a fresh run (the training benchmark's measurement).
#[derive(Debug, Serialize, Deserialize)]
pub struct StepTimings {
    /// First step: R1, inverse-skinning cache fill, kernel compilation.
    pub first_step_s: f64,
    /// Mean of the following plain steps (no R1).
    pub step_s: f64,
    /// One step with the lazy R1 penalty, after warm-up.
    pub r1_step_s: f64,
}

/// Run `steps` plain steps (after one warm-up step) and one R1 step of a fresh run of `config`
/// on `ds` with `backend`.
pub fn time_steps(data: &Path, config: &str, backend: &str, batch: usize, steps: usize) -> Result<StepTimings> {
    let ds = Dataset::open(data).with_context(|| format!("opening dataset {}", data.display()))?;
    let gcfg = GeneratorConfig::preset(config).with_context(|| format!("unknown config `{config}`"))?;
    let rc = RunConfig::new(&ds, data, gcfg, batch, 10.0, 0);
    let base = device_for(backend)?;
    let (ad, plain) = (base.clone().autodiff(), base);
    let ctx = BodyContext::new(BodyModel::default_body()?, &rc.generator);
    let grids = PosedGridCache::default();
    let scans = Vec::new();
    let mut st = State::new(&rc, &ad, &plain);
    let (next, first) = train_step(st, &ds, &ctx, &grids, &scans, &rc, &ad)?;
    st = next;
    let mut plain_s = Vec::new();
    for _ in 0..steps.max(1) {
        let (next, m) = train_step(st, &ds, &ctx, &grids, &scans, &rc, &ad)?;
        st = next;
        plain_s.push(m.seconds);
    }
    st.step = rc.r1_every * (st.step / rc.r1_every + 1);
    let (_, r1) = train_step(st, &ds, &ctx, &grids, &scans, &rc, &ad)?;
    Ok(StepTimings {
        first_step_s: first.seconds,
        step_s: plain_s.iter().sum::<f64>() / plain_s.len() as f64,
        r1_step_s: r1.seconds,
    })
}

/// `losses.png` from a run's `metrics.jsonl`: G loss, D loss, eikonal, SDF cross-entropy
/// (top to bottom; raw faint, 20-step moving average bold).
pub fn loss_plot(metrics: &Path) -> Result<Vec<u8>> {
    // A step logged twice (a run killed after logging, before its checkpoint) keeps the
    // later row: the one the resumed run continued from. A torn last line (a kill while
    // appending) is skipped.
    let mut by_step = BTreeMap::new();
    let text = std::fs::read_to_string(metrics).with_context(|| format!("reading {}", metrics.display()))?;
    for v in text.lines().filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok()) {
        let row = crate::plot::SERIES.map(|(k, _)| v.get(k).and_then(|x| x.as_f64()).map_or(f32::NAN, |x| x as f32));
        by_step.insert(v.get("step").and_then(|s| s.as_u64()).unwrap_or(0), row);
    }
    let rows: Vec<[f32; 4]> = by_step.into_values().collect();
    let (w, panel) = (640, 120);
    Ok(encode_png(w, panel * crate::plot::SERIES.len(), 3, &crate::plot::loss_curves(&rows, w, panel, 20))?)
}
