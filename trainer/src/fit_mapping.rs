//! `trainer fit-mapping`: the texture mapping network refitted so that seeds' texture codes
//! lie near the training subjects' texture codes, each within a spread of one, instead of
//! between them (not in the paper).
//!
//! Why: a reconstruction-trained generator has been supervised at its subjects' codes (and a
//! little around them), while its mapping network spreads w_tex over the space between them:
//! the median seed lies as far from its nearest subject's code as the subjects lie from each
//! other. There the texture field renders the average of the neighbours: soft, desaturated
//! blends, even after multi-modal truncation (which keeps ψ of the way from the nearest
//! subject). Refitting only the texture mapping so that its codes lie within `--spread` of a
//! subject's code, with every subject near some of them, gives each seed one subject's kind
//! of colouring, varied by the spread, on its own shape. The geometry mapping, the synthesis,
//! the decoders and the subjects' codes are untouched: the subjects render as before, the
//! seeds' shapes (and every mask and normal figure) are the same, and only seeds' colours
//! change.
//!
//! The objective is a one-sided shell plus a cover term, in units of the codes' median
//! nearest-neighbour distance: each code's distance to its nearest subject's code beyond the
//! spread, squared, plus each subject's squared distance to its nearest code of the batch.
//! z ~ N(0, I) as the seeds draw it. Seconds to a minute of a 4-layer MLP on a CPU, so it is
//! not resumable; the file is written once, atomically. w_avg becomes the new codes' mean.

use std::collections::BTreeMap;
use std::io::Write as _;
use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use getavatar_core::burn::tensor::{Device, Tensor, TensorData};
use getavatar_core::generator::checkpoint::save_generator_with_modes;
use getavatar_core::generator::network::mapping::nearest_mode;
use getavatar_core::generator::optim::{trainable_where, Adam};
use getavatar_core::generator::pipeline::Generator;
use getavatar_core::generator::readback::read_f32_now;
use getavatar_core::util::rng::Rng;

use crate::atomic::write_atomic;

#[derive(clap::Args, Debug)]
pub struct FitMappingArgs {
    #[command(flatten)]
    pub model: crate::model_io::GeneratorArgs,
    /// Output folder: `generator.safetensors` and `metrics.jsonl`.
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, default_value_t = 6000)]
    pub steps: usize,
    /// Codes per step.
    #[arg(long, default_value_t = 256)]
    pub batch: usize,
    /// How far a code may lie from its nearest subject's code without cost, as a fraction of
    /// the subjects' codes' median nearest-neighbour distance in W: 0 pulls every seed onto
    /// a subject's colours, 0.5 allows half the way to that subject's nearest neighbour.
    #[arg(long, default_value_t = 0.3)]
    pub spread: f32,
    /// Adam's rate on the mapping's effective weights (the stored ones move by this over the
    /// layers' learning-rate multiplier), after a linear warm-up over the first 50 steps.
    #[arg(long, default_value_t = 0.03)]
    pub lr: f32,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// Codes drawn for the before/after figures.
const PROBE: usize = 2048;

pub fn fit_mapping(a: &FitMappingArgs) -> Result<()> {
    if a.steps == 0 || a.batch < 2 {
        bail!("--steps must be at least 1 and --batch at least 2");
    }
    if !(a.spread >= 0.0 && a.spread.is_finite() && a.lr > 0.0 && a.lr.is_finite()) {
        bail!("--spread must be a finite fraction ≥ 0 and --lr a finite rate > 0");
    }
    #[allow(deprecated)]
    let plain = Device::ndarray();
    let ad = plain.clone().autodiff();
    let (cfg, g, modes) = a.model.load(&ad)?;
    let Some(modes) = modes else {
        bail!("fit-mapping needs a checkpoint with latent modes (its training subjects' codes); this one has none");
    };
    let k = modes.count();
    if k < 2 {
        bail!("fit-mapping needs at least 2 subjects' codes; the checkpoint has {k}");
    }
    let source_meta = crate::fit_codes::source_metadata(&a.model)?;
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let w_dim = cfg.w_dim;
    let codes = read_f32_now(modes.tex.clone())?;
    let nn = median_nearest_distance(&codes, w_dim);
    if !(nn > 0.0 && nn.is_finite()) {
        bail!("the checkpoint's texture codes coincide (median nearest-neighbour distance {nn})");
    }
    let radius = a.spread * nn;
    let centres = modes.tex.clone().detach();
    let z_dim = cfg.z_dim;
    let draw_z =
        |rng: &mut Rng, n: usize| Tensor::<2>::from_data(TensorData::new(rng.normals(n * z_dim), [n, z_dim]), &ad);

    let mut rng = Rng::new(a.seed, 0x3a99);
    let probe_z = draw_z(&mut rng, PROBE);
    let before = probe(&g, &probe_z, &centres, nn)?;
    let lr_mul = g.mapping_tex.layers.first().map_or(1.0, |l| l.lr_mul);
    let mut g = trainable_where(g, &|n: &str| n.starts_with("mapping_tex.layers."));
    let mut adam = Adam::new(0.9, 0.99, 1e-8);
    let mut log = std::fs::File::create(a.out.join("metrics.jsonl"))?;
    let bar = crate::progress::bar(a.steps as u64, "steps");
    for step in 1..=a.steps {
        let x = g.mapping_tex.forward(draw_z(&mut rng, a.batch));
        let loss = shell_chamfer(x, &centres, radius, nn);
        let grads = loss.backward();
        let warm = (step as f32 / 50.0).min(1.0);
        g = adam.step(a.lr * warm / lr_mul, g, &grads);
        let v = read_f32_now(loss)?[0];
        if !v.is_finite() {
            bail!("step {step}: non-finite loss; nothing was written");
        }
        writeln!(log, "{}", serde_json::json!({ "step": step, "loss": v }))?;
        bar.set_position(step as u64);
        bar.set_message(format!("loss {v:.4}"));
    }
    bar.finish_and_clear();
    let after = probe(&g, &probe_z, &centres, nn)?;
    // w_avg: the new codes' mean (ordinary truncation, `--mean-truncation`, pulls towards it).
    g.mapping_tex.w_avg =
        getavatar_core::burn::module::Param::from_tensor(after.mean.clone().reshape([w_dim])).set_require_grad(false);
    let mut extra: BTreeMap<String, String> = source_meta;
    extra.insert("fit_mapping_steps".into(), a.steps.to_string());
    extra.insert("fit_mapping_spread".into(), a.spread.to_string());
    let bytes = save_generator_with_modes(&g, &cfg, Some(&modes), &extra)?;
    let path = a.out.join("generator.safetensors");
    write_atomic(&path, &bytes)?;
    println!("texture codes w_tex = mapping(z) of {PROBE} draws, against the {k} subjects' codes (median nearest-neighbour distance {nn:.3}):");
    println!("|  | distance to the nearest subject's code / that median | codes within half of it | subjects nearest to some code |");
    println!("|---|---|---|---|");
    for (name, p) in [("before", &before), ("after", &after)] {
        println!(
            "| {name} | {:.2} (median) | {:.0} % | {} of {k} |",
            p.median_distance,
            100.0 * p.within_half,
            p.covered
        );
    }
    println!("wrote {}", path.display());
    Ok(())
}

/// Figures of the mapping's codes for `z`: the median distance of a code to its nearest
/// subject's (in units of `nn`), how many subjects are the nearest of some code, and the share
/// of codes within half of `nn` of a subject's; and the codes' mean, `[1, w_dim]`.
struct Probe {
    median_distance: f32,
    covered: usize,
    within_half: f32,
    mean: Tensor<2>,
}

fn probe(g: &Generator, z: &Tensor<2>, centres: &Tensor<2>, nn: f32) -> Result<Probe> {
    let w = g.mapping_tex.forward(z.clone()).detach();
    let near = nearest_mode(&w, centres);
    let c = centres.clone().select(0, near.clone());
    let d = read_f32_now((w.clone() - c).powf_scalar(2.0).sum_dim(1).sqrt().reshape([z.dims()[0]]))?;
    let near: Vec<i64> = near
        .into_data()
        .convert::<i64>()
        .try_to_vec::<i64>()
        .map_err(|e| anyhow::anyhow!("reading the nearest subjects: {e:?}"))?;
    let covered = near.iter().collect::<std::collections::BTreeSet<_>>().len();
    let within_half = d.iter().filter(|&&v| v < 0.5 * nn).count() as f32 / d.len() as f32;
    Ok(Probe { median_distance: median(d) / nn, covered, within_half, mean: w.mean_dim(0) })
}

/// The fit's objective, in units of `nn`²: each code's distance to its nearest subject's code
/// beyond `radius` (squared), plus each subject's code's squared distance to its nearest code
/// of the batch (so that every subject keeps some draws).
fn shell_chamfer(x: Tensor<2>, centres: &Tensor<2>, radius: f32, nn: f32) -> Tensor<1> {
    let xx = x.clone().powf_scalar(2.0).sum_dim(1);
    let cc = centres.clone().powf_scalar(2.0).sum_dim(1).transpose();
    let d2 = (xx + cc - x.matmul(centres.clone().transpose()) * 2.0).clamp_min(1e-12);
    let [b, k] = d2.dims();
    let near = d2.clone().min_dim(1).reshape([b]).sqrt();
    let pull = (near - radius).clamp_min(0.0).powf_scalar(2.0).mean();
    let cover = d2.min_dim(0).reshape([k]).mean();
    (pull + cover) / (nn * nn)
}

/// The median over the rows of `codes` (`[K, w]`, row-major) of the distance to the nearest
/// other row.
fn median_nearest_distance(codes: &[f32], w: usize) -> f32 {
    let rows: Vec<&[f32]> = codes.chunks_exact(w).collect();
    let d: Vec<f32> = rows
        .iter()
        .enumerate()
        .map(|(i, a)| {
            rows.iter()
                .enumerate()
                .filter(|&(j, _)| j != i)
                .map(|(_, b)| a.iter().zip(*b).map(|(p, q)| (p - q) * (p - q)).sum::<f32>().sqrt())
                .fold(f32::INFINITY, f32::min)
        })
        .collect();
    median(d)
}

fn median(mut v: Vec<f32>) -> f32 {
    v.sort_by(f32::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f32::NAN)
}
