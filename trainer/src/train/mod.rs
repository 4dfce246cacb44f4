//! `trainer train`: the paper's adversarial training (Sec. 4.5) on a prepared dataset.
//!
//! Per step (`adversarial`): a D phase (non-saturating loss of the three discriminators — RGB, normal map,
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
//! leaves the previous checkpoint intact. Each snapshot keeps the checkpoint before it as
//! `state.prev.safetensors`; a resume whose latest checkpoint is unreadable (corrupt, cut
//! short, missing) says so and continues from that one.
//!
//! Modules, along StyleGAN's training loop: `args` (the CLI), `run_config` (`run.json`),
//! `state` (`state.safetensors`), `step` (what both objectives share), `adversarial` (the
//! paper's step), `reconstruction` (the warm-up, anchor and scan terms), `subject_codes`
//! (the reconstruction's learned per-subject codes), `snapshots` (sample grids).

mod adversarial;
mod args;
pub mod cfg;
mod reconstruction;
mod run_config;
mod scan_pools;
mod snapshots;
mod state;
mod step;
mod subject_codes;

use std::collections::BTreeMap;
use std::io::Write;
use std::path::Path;

use anyhow::{bail, Context, Result};
use getavatar_core::body::body_model::BodyModel;
use getavatar_core::burn::tensor::Device;
use getavatar_core::generator::checkpoint::{load_generator_growing, save_generator_with_modes};
use getavatar_core::io::dataset::Dataset;
use getavatar_core::render::diff::avatar::PosedGridCache;

pub use args::TrainArgs;
pub(crate) use run_config::discriminator_config;
pub use run_config::{Objective, RunConfig};
pub use state::State;
pub(crate) use step::{cameras, load_reals};
pub use step::{Metrics, StepInputs};

use crate::atomic::{write_atomic, write_atomic_keeping_previous};
use reconstruction::{reconstruction_step, subject_modes};
pub(crate) use run_config::FACE_POINTS_PER_STEP;
pub(crate) use scan_pools::canonical_scan_samples;
pub(crate) use scan_pools::subject_of_entries;
pub use scan_pools::ScanPools;
use snapshots::sample_grid;
use subject_codes::SubjectCodes;

/// One training step of the run's objective.
pub fn train_step(st: State, inputs: &StepInputs) -> Result<(State, Metrics)> {
    match inputs.rc.objective {
        Objective::Adversarial => adversarial::adversarial_step(st, inputs),
        Objective::Reconstruction => reconstruction_step(st, inputs),
    }
}

/// The learned subject codes a run with `lr_codes` > 0 starts from: the offsets that reach
/// the latent modes of the generator file it started from (`init`, where they hold the
/// dataset's number of subjects: a checkpoint trained with learned codes goes on from its
/// codes), else zero (every subject at its fixed latents' code).
fn initial_codes(st: &State, rc: &RunConfig, ds: &Dataset, init: Option<&Path>, ad: &Device) -> Result<SubjectCodes> {
    let n = subject_of_entries(ds).into_iter().max().map_or(0, |m| m + 1);
    let w_dim = rc.generator.w_dim;
    let layers = if rc.codes_wplus { st.g.num_ws().1 } else { 1 };
    if let Some(path) = init {
        let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        let plain = ad.clone().without_autodiff();
        if let Some(modes) = getavatar_core::generator::checkpoint::load_latent_modes(&bytes, &plain)? {
            let fixed = subject_modes(&st.g_ema, None, ds, rc, &plain)?
                .context("a reconstruction run's subjects have modes")?;
            if let Some(codes) = SubjectCodes::reaching(&modes, &fixed, layers, ad)? {
                println!("learning the {n} subjects' codes from the latent modes of {}", path.display());
                return Ok(codes);
            }
            println!(
                "{} holds {} latent modes, the dataset {n} subjects: the learned codes start at the fixed ones",
                path.display(),
                modes.count()
            );
        }
    }
    println!("learning the {n} subjects' codes, starting at their fixed latents' codes");
    Ok(SubjectCodes::zeros(n, w_dim, layers, ad))
}

/// The run's state: the latest checkpoint (or the previous one where the latest does not load)
/// of a continued run; else a new state, its generator taken from `--resume FILE` if given.
fn start_state(
    a: &TrainArgs,
    rc: &RunConfig,
    continuing: bool,
    (state_path, prev_path): (&Path, &Path),
    ad: &Device,
    plain: &Device,
) -> Result<State> {
    Ok(if continuing && (state_path.exists() || prev_path.exists()) {
        let load = |p: &Path| -> Result<State> {
            let bytes = std::fs::read(p).with_context(|| format!("reading {}", p.display()))?;
            // The settings at the checkpoint's step (the schedule's changes so far).
            let rc = rc.at_step(State::step_of(&bytes).with_context(|| format!("loading {}", p.display()))?)?;
            State::load(&bytes, &rc, ad, plain).with_context(|| format!("loading {}", p.display()))
        };
        match load(state_path) {
            Ok(st) => st,
            Err(latest) if prev_path.exists() => {
                let st = load(prev_path).map_err(|prev| {
                    anyhow::anyhow!("neither checkpoint loads: {latest:#}; the previous one: {prev:#}")
                })?;
                eprintln!(
                    "the latest checkpoint cannot be used ({latest:#}); resuming from the previous one, {} (step {})",
                    prev_path.display(),
                    st.step
                );
                st
            }
            Err(e) => return Err(e),
        }
    } else {
        let mut st = State::new(rc, ad, plain);
        if let Some(Some(init)) = &a.resume {
            // Transfer learning (paper Sec. 5.3): start G from a trained generator.
            let bytes = std::fs::read(init).with_context(|| format!("reading {}", init.display()))?;
            // A generator saved with coarser texture planes grows into the run's config.
            st.g = load_generator_growing(&bytes, &rc.generator, rc.seed, ad)?;
            st.g_ema = load_generator_growing(&bytes, &rc.generator, rc.seed, plain)?;
            println!("initialised the generator from {}", init.display());
        }
        st
    })
}

/// `--train-only PREFIX`: how many of the generator's parameters it trains (none: an error).
fn report_train_only(st: &State, prefix: &str) -> Result<()> {
    let names: Vec<String> = getavatar_core::generator::checkpoint::collect_params(&st.g_ema)?
        .into_iter()
        .map(|(name, _, _)| name)
        .collect();
    let trained = names.iter().filter(|n| n.starts_with(prefix)).count();
    if trained == 0 {
        bail!(
            "--train-only {prefix}: no generator parameter's path starts with it (they start with {})",
            names
                .iter()
                .filter_map(|n| n.split('.').next())
                .collect::<std::collections::BTreeSet<_>>()
                .into_iter()
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    println!("training {trained} of the generator's {} parameters (--train-only {prefix})", names.len());
    Ok(())
}

pub fn train(a: &TrainArgs) -> Result<()> {
    let ds = Dataset::open(&a.data).with_context(|| format!("opening dataset {}", a.data.display()))?;
    if !ds.resolution.is_power_of_two() || ds.resolution < 16 {
        bail!("dataset resolution {} must be a power of two ≥ 16", ds.resolution);
    }
    let base = a.backend.device()?;
    let (ad, plain) = (base.clone().autodiff(), base);
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let run_path = a.out.join("run.json");
    let state_path = a.out.join("state.safetensors");
    let continuing = matches!(a.resume, Some(None));
    let rc = if continuing {
        RunConfig::continued(a, &run_path)?
    } else {
        if state_path.exists() {
            bail!(
                "{} already holds a training run: pass --resume to continue it, or choose another --out",
                a.out.display()
            );
        }
        let rc = RunConfig::from_args(a, &ds)?;
        write_atomic(&run_path, serde_json::to_string_pretty(&rc)?.as_bytes())?;
        rc
    };
    if rc.resolution != ds.resolution {
        bail!("the run was trained at {}², the dataset has {}² images", rc.resolution, ds.resolution);
    }
    let rc = RunConfig { use_normals: rc.use_normals && ds.has_normals, ..rc };
    let prev_path = a.out.join("state.prev.safetensors");
    let mut st = start_state(a, &rc, continuing, (&state_path, &prev_path), &ad, &plain)?;
    // The schedule's changes so far (`--cfg`): a continued run takes up the settings of its step.
    let rc = rc.at_step(st.step)?;
    if let Some(c) = &st.codes {
        if (c.tex_layers() > 1) != rc.codes_wplus {
            bail!(
                "the state's texture codes are {} but run.json says codes_wplus {}: set it back",
                if c.tex_layers() > 1 { "W+" } else { "W" },
                rc.codes_wplus
            );
        }
    }
    if rc.lr_codes > 0.0 && st.codes.is_none() {
        let codes = initial_codes(&st, &rc, &ds, a.resume.as_ref().and_then(|r| r.as_deref()), &ad)?;
        st.codes_ema = Some(codes.copy_to(&plain)?);
        st.codes = Some(codes);
    }
    if !rc.use_normals {
        println!("the dataset has no normal maps: the normal discriminator is off");
    }
    if let Some(prefix) = &rc.train_only {
        report_train_only(&st, prefix)?;
    }
    let model = BodyModel::default_body()?;
    let ctx = crate::model_io::body_context(model, &rc.generator);
    let grids = PosedGridCache::default();
    let scans = match &rc.scans {
        Some(dir) if rc.lambda_scan > 0.0 || rc.lambda_face > 0.0 => {
            canonical_scan_samples(Path::new(dir), &ds, &ctx, rc.seed, (rc.lambda_scan > 0.0, rc.lambda_face > 0.0))?
        }
        _ => ScanPools::default(),
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
        let modes = subject_modes(&st.g_ema, st.codes_ema.as_ref(), &ds, &rc, &plain)?;
        let g_bytes = save_generator_with_modes(&st.g_ema, &rc.generator, modes.as_ref(), &extra)?;
        write_atomic(&a.out.join("generator.safetensors"), &g_bytes)?;
        // The new checkpoint is written, then the last one becomes the previous one (resume
        // falls back to it when the latest is unreadable or missing).
        write_atomic_keeping_previous(&state_path, &prev_path, &st.save(&rc)?)?;
        let (png, fit) = sample_grid(st, &ds, &ctx, &grids, &rc, &plain)?;
        write_atomic(&a.out.join(format!("samples_{step:06}.png")), &png)?;
        if let Some(fit) = fit {
            // One line per snapshot; a resumed run appends (rows of steps done twice after
            // a crash appear twice, the later one counts).
            let mut f = std::fs::OpenOptions::new().create(true).append(true).open(a.out.join("grid_l1.jsonl"))?;
            writeln!(f, "{}", serde_json::to_string(&fit)?)?;
        }
        write_atomic(&a.out.join("losses.png"), &crate::plot::loss_plot(&a.out.join("metrics.jsonl"))?)
    };
    while st.step < a.steps {
        if st.step > start && rc.changes_after(st.step) {
            // The schedule changes the settings here: checkpoint (unless just done) and continue
            // as `--resume` would, with the changed settings.
            if st.step % a.snapshot_every != 0 {
                snapshot(&st, st.step)?;
            }
            bar.finish_and_clear();
            println!("after step {}: the schedule changes the run's settings ({})", st.step, run_path.display());
            return train(&TrainArgs { resume: Some(None), ..a.clone() });
        }
        let inputs = StepInputs { ds: &ds, ctx: &ctx, grids: &grids, scans: &scans, rc: &rc, ad: &ad };
        let (next, m) = train_step(st, &inputs)?;
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
        a.backend.backend,
        last.loss_g,
        last.loss_d,
        state_path.display()
    );
    Ok(())
}
