//! `trainer train-discriminator`: the RGB discriminator of a frozen, shipped generator, trained
//! against the generator's training data (the paper's D phase alone: non-saturating loss on
//! real images and the generator's fakes at data labels, lazy finite-difference R1). The
//! inversion's perceptual term uses its multi-scale features (`Discriminator::features`, as
//! Deep Generative Prior's `DiscriminatorLoss` does in place of VGG, which cannot be
//! downloaded here). A checkpoint without a trained discriminator (the reconstruction warm-up
//! trains none) gets one this way.
//!
//! OUT/discriminator.safetensors holds the discriminator (`d0/…`, metadata `discriminator` =
//! its config, `step`), written atomically every `--snapshot-every` steps; a rerun with the
//! same OUT resumes from it (Adam's moments start afresh). OUT/metrics.jsonl logs each step.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::PathBuf;

use anyhow::{Context, Result};
use getavatar_core::burn::tensor::Device;
use getavatar_core::generator::checkpoint::{collect_params, load_params, parse_safetensors, write_safetensors};
use getavatar_core::generator::losses::{discriminator_loss, r1_penalty};
use getavatar_core::generator::network::discriminator::{Discriminator, DiscriminatorConfig};
use getavatar_core::generator::optim::Adam;
use getavatar_core::generator::readback::read_f32_now;
use getavatar_core::io::dataset::{Dataset, Label};
use getavatar_core::render::camera::View;
use getavatar_core::render::diff::avatar::{render_avatars, PosedGridCache};
use getavatar_core::util::rng::Rng;

use crate::atomic::write_atomic;
use crate::model_io::{load_body, GeneratorArgs};

#[derive(clap::Args, Debug)]
pub struct TrainDiscriminatorArgs {
    #[command(flatten)]
    pub model: GeneratorArgs,
    /// The generator's training data (a prepared dataset).
    #[arg(long)]
    pub data: PathBuf,
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, default_value_t = 500)]
    pub steps: u64,
    #[arg(long, default_value_t = 4)]
    pub batch: usize,
    #[arg(long, default_value_t = 50)]
    pub snapshot_every: u64,
    /// Adam learning rate (the paper's D rate).
    #[arg(long, default_value_t = 0.002)]
    pub lr: f32,
    /// R1 weight γ (lazy, every 16 steps).
    #[arg(long, default_value_t = 1.0)]
    pub r1_gamma: f32,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Body model .npz in the SMPL layout (default: the embedded open body).
    #[arg(long)]
    pub body: Option<PathBuf>,
}

const FILE: &str = "discriminator.safetensors";
const R1_EVERY: u64 = 16;

pub fn train_discriminator(a: &TrainDiscriminatorArgs) -> Result<()> {
    anyhow::ensure!(a.batch >= 1 && a.snapshot_every >= 1, "--batch and --snapshot-every must be at least 1");
    let ds = Dataset::open(&a.data)?;
    anyhow::ensure!(
        ds.resolution.is_power_of_two() && ds.resolution >= 8,
        "the data's resolution {} is not a power of two ≥ 8",
        ds.resolution
    );
    #[allow(deprecated)]
    let plain = Device::ndarray();
    let ad = plain.clone().autodiff();
    let (cfg, g, _) = a.model.load(&plain)?;
    let ctx = crate::model_io::body_context(load_body(&a.body)?, &cfg);
    let dcfg: DiscriminatorConfig = crate::train::discriminator_config(ds.resolution, &cfg);
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let path = a.out.join(FILE);
    let (mut d, mut step) = (Discriminator::new(&dcfg, 3, a.seed + 100, &ad), 0u64);
    if path.is_file() {
        let bytes = std::fs::read(&path)?;
        let st = parse_safetensors(&bytes).with_context(|| format!("{} is unreadable", path.display()))?;
        d = load_params(d, &st.tensors, "d0/", &ad).with_context(|| format!("resuming from {}", path.display()))?;
        step = st.metadata.get("step").and_then(|s| s.parse().ok()).unwrap_or(0);
        eprintln!("resuming from {} at step {step}", path.display());
    }
    let mut adam = Adam::new(0.0, 0.99, 1e-8);
    let mut rng = Rng::new(a.seed, 0xd15c + step);
    let grids = PosedGridCache::default();
    let mut log = std::fs::OpenOptions::new().create(true).append(true).open(a.out.join("metrics.jsonl"))?;
    let bar = crate::progress::bar(a.steps, "steps");
    bar.set_position(step.min(a.steps));
    let save = |d: &Discriminator, step: u64| -> Result<()> {
        let mut meta = BTreeMap::new();
        meta.insert("format".into(), "getavatar-discriminator/1".into());
        meta.insert("discriminator".into(), serde_json::to_string(&dcfg)?);
        meta.insert("step".into(), step.to_string());
        meta.insert("generator".into(), cfg.name.clone());
        let tensors: Vec<_> = collect_params(d)?.into_iter().map(|(n, s, v)| (format!("d0/{n}"), s, v)).collect();
        write_atomic(&path, &write_safetensors(&meta, &tensors)?)
    };
    while step < a.steps {
        let t0 = std::time::Instant::now();
        let b = a.batch;
        let real_idx: Vec<usize> = (0..b).map(|_| rng.below(ds.len())).collect();
        let fake_labels: Vec<Label> = (0..b).map(|_| ds.entries[rng.below(ds.len())].1.clone()).collect();
        let z = |rng: &mut Rng| {
            getavatar_core::burn::tensor::Tensor::<2>::from_data(
                getavatar_core::burn::tensor::TensorData::new(rng.normals(b * cfg.z_dim), [b, cfg.z_dim]),
                &plain,
            )
        };
        let (zg, zt) = (z(&mut rng), z(&mut rng));
        let styles = g.styles(zg, zt, 1.0);
        let views: Vec<View> = fake_labels.iter().map(Label::view).collect();
        let fakes = render_avatars(&g, &ctx, &styles, &views, ds.resolution, &grids, &plain)?;
        let fake = getavatar_core::burn::tensor::Tensor::<4>::from_data(fakes.rgb.into_data(), &ad);
        let (real, _, _, c_real) = crate::train::load_reals(&ds, &real_idx, &ad)?;
        let c_fake = crate::train::cameras(&fake_labels, &ad);
        let loss = discriminator_loss(d.forward(fake, c_fake), d.forward(real.clone(), c_real.clone()));
        let loss_v = read_f32_now(loss.clone())?[0];
        let mut total = loss;
        let mut r1_v = None;
        if step % R1_EVERY == 0 {
            let r1 = r1_penalty(|x| d.forward(x, c_real.clone()), real, 4, 1e-2, &mut rng, &ad).mean();
            r1_v = Some(read_f32_now(r1.clone())?[0]);
            total = total + r1 * (a.r1_gamma / 2.0 * R1_EVERY as f32);
        }
        let grads = total.backward();
        let ratio = R1_EVERY as f32 / (R1_EVERY as f32 + 1.0);
        d = adam.step(a.lr * ratio, d, &grads);
        step += 1;
        writeln!(
            log,
            "{}",
            serde_json::json!({"step": step, "loss_d": loss_v, "r1": r1_v, "seconds": t0.elapsed().as_secs_f64()})
        )?;
        bar.set_position(step);
        bar.set_message(format!("loss_D {loss_v:.3}"));
        if step % a.snapshot_every == 0 || step == a.steps {
            save(&d, step)?;
        }
    }
    bar.finish_and_clear();
    println!("wrote {} (step {step})", path.display());
    Ok(())
}
