//! A run's settings (`run.json`): the reference code's values for a fresh run, or the
//! flags' values where given. Fixed when the run starts; `--resume` reads them back.

use std::path::Path;

use anyhow::{bail, Context, Result};
use getavatar_core::generator::network::discriminator::DiscriminatorConfig;
use getavatar_core::generator::network::GeneratorConfig;
use getavatar_core::io::dataset::Dataset;
use serde::{Deserialize, Serialize};

pub use super::args::Objective;
use super::args::TrainArgs;
use super::cfg::Scheduled;

/// Points drawn per scan and kept for training (`--scans`).
pub const SCAN_POOL_POINTS: usize = 16384;
/// Points of each drawn subject's pool used per step.
pub const SCAN_POINTS_PER_STEP: usize = 2048;
/// Face points drawn per scan and kept for the face term (`--lambda-face`).
pub const FACE_POOL_POINTS: usize = 4096;
/// Face points of each drawn subject used per step.
pub const FACE_POINTS_PER_STEP: usize = 512;

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
    /// Factor on `lr_g` for the geometry detail blocks (`GeneratorConfig::geometry_res`,
    /// parameters under `synthesis.geometry_detail.`): a grown block starts at zero output and
    /// learns its constant's detail field slowly at `lr_g` alone. Absent: 1. Editable in
    /// `run.json` like the above.
    #[serde(default = "one")]
    pub lr_geometry_detail_mul: f32,
    /// Further factor, on top of `lr_texture_mul`, for the texture detail blocks
    /// (`GeneratorConfig::texture_res`, parameters under `synthesis.texture_detail.`): a block
    /// grown into a trained generator starts at zero output, and its learned constant's texels
    /// are each reached by few points a step, so Adam's rate sets its pace (a 256² block gave
    /// nothing measurable after 200 steps at `lr_texture_mul` alone; the MODEL_CARD's git history).
    /// Absent: 1. Editable in `run.json` like the above.
    #[serde(default = "one")]
    pub lr_texture_detail_mul: f32,
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
    /// Weight of the face term (`TrainArgs::lambda_face`). Absent in older runs: 0. Editable
    /// in `run.json`.
    #[serde(default)]
    pub lambda_face: f32,
    /// Weight of the texture-swap term (`TrainArgs::lambda_texture_swap`). Absent in older
    /// runs: 0. Editable in `run.json` like the learning-rate factors.
    #[serde(default)]
    pub lambda_texture_swap: f32,
    /// The largest fraction of the way to a random w at which reconstruction terms supervise
    /// a subject (`TrainArgs::latent_spread`). Absent in older runs: 0. Editable in
    /// `run.json`.
    #[serde(default)]
    pub latent_spread: f32,
    /// The geometry branch's own spread (`TrainArgs::latent_spread_geo`), where it differs
    /// from `latent_spread`. Absent: `latent_spread`. Editable in `run.json`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub latent_spread_geo: Option<f32>,
    /// Train only the generator parameters whose checkpoint path starts with this prefix
    /// (`TrainArgs::train_only`); the others keep their weights. Absent: all. Editable in
    /// `run.json`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub train_only: Option<String>,
    /// Adam rate of the learned subject codes of a reconstruction run
    /// (`TrainArgs::lr_codes`, `subject_codes`); 0: the subjects keep their fixed latents'
    /// codes. Absent in older runs: 0. Editable in `run.json`.
    #[serde(default)]
    pub lr_codes: f32,
    /// Factor on `lr_codes` for the geometry branch's codes (0: only the texture codes
    /// learn). Absent: 1. Editable in `run.json`.
    #[serde(default = "one")]
    pub lr_codes_geo_mul: f32,
    /// The learned texture codes are W+ (one offset per texture style layer) instead of W
    /// (`TrainArgs::codes_wplus`). Absent: false. Fixed once the run has codes.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub codes_wplus: bool,
    /// Changes of these settings by step (`--cfg`'s `[[schedule]]`); the fields above are the
    /// settings before the first. Absent: none.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub schedule: Vec<Scheduled>,
}

pub(crate) fn one_view() -> usize {
    1
}

impl RunConfig {
    /// The flags that fix a run's settings and conflict with this continued run: one row per
    /// flag (the flag, the value given, the run's value, the `run.json` field to edit instead).
    /// Flags that were not given never conflict; the others must equal the run's value.
    pub fn resume_conflicts(&self, args: &TrainArgs) -> Vec<String> {
        let rc = self;
        let num = |v: f32| v.to_string();
        let objective = |o: Objective| format!("{o:?}").to_lowercase();
        let plane = |r: Option<usize>| r.map_or_else(|| "(none)".to_string(), |r| r.to_string());
        let rows: [(&str, Option<String>, String, &str); 20] = [
            ("--config", args.config.clone(), rc.generator.name.clone(), "generator"),
            ("--batch", args.batch.map(|b| b.to_string()), rc.batch.to_string(), "batch"),
            ("--seed", args.seed.map(|s| s.to_string()), rc.seed.to_string(), "seed"),
            ("--r1-gamma", args.r1_gamma.map(num), num(rc.r1_gamma), "r1_gamma"),
            ("--objective", args.objective.map(objective), objective(rc.objective), "objective"),
            ("--views", args.views.map(|v| v.to_string()), rc.views_per_subject.to_string(), "views_per_subject"),
            (
                "--scans",
                args.scans.as_ref().map(|d| d.display().to_string()),
                rc.scans.clone().unwrap_or_else(|| "(none)".into()),
                "scans",
            ),
            ("--lambda-scan", args.lambda_scan.map(num), num(rc.lambda_scan), "lambda_scan"),
            ("--lambda-face", args.lambda_face.map(num), num(rc.lambda_face), "lambda_face"),
            (
                "--lambda-reconstruction",
                args.lambda_reconstruction.map(num),
                num(rc.lambda_reconstruction),
                "lambda_reconstruction",
            ),
            (
                "--lambda-texture-swap",
                args.lambda_texture_swap.map(num),
                num(rc.lambda_texture_swap),
                "lambda_texture_swap",
            ),
            ("--latent-spread", args.latent_spread.map(num), num(rc.latent_spread), "latent_spread"),
            (
                "--latent-spread-geo",
                args.latent_spread_geo.map(num),
                rc.latent_spread_geo.map_or_else(|| "(--latent-spread)".into(), num),
                "latent_spread_geo",
            ),
            ("--lr-g", args.lr_g.map(num), num(rc.lr_g), "lr_g"),
            (
                "--train-only",
                args.train_only.clone(),
                rc.train_only.clone().unwrap_or_else(|| "(all)".into()),
                "train_only",
            ),
            ("--lr-d", args.lr_d.map(num), num(rc.lr_d), "lr_d"),
            ("--lr-codes", args.lr_codes.map(num), num(rc.lr_codes), "lr_codes"),
            ("--codes-wplus", args.codes_wplus.then(|| "true".into()), rc.codes_wplus.to_string(), "codes_wplus"),
            (
                "--texture-res",
                args.texture_res.map(|r| r.to_string()),
                plane(rc.generator.texture_res),
                "generator.texture_res",
            ),
            (
                "--geometry-res",
                args.geometry_res.map(|r| r.to_string()),
                plane(rc.generator.geometry_res),
                "generator.geometry_res",
            ),
        ];
        rows.into_iter()
            .filter_map(|(flag, given, run, field)| match given {
                Some(g) if g != run => Some(format!("{flag} {g} differs from the run's {run} (field `{field}`)")),
                _ => None,
            })
            .collect()
    }

    /// The latent spreads of the geometry and texture branches (`latent_spread_geo`, falling
    /// back to `latent_spread`, and `latent_spread`).
    pub fn latent_spreads(&self) -> (f32, f32) {
        (self.latent_spread_geo.unwrap_or(self.latent_spread), self.latent_spread)
    }

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
            lr_geometry_detail_mul: 1.0,
            lr_texture_detail_mul: 1.0,
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
            lambda_face: 0.0,
            lambda_texture_swap: 0.0,
            latent_spread: 0.0,
            latent_spread_geo: None,
            train_only: None,
            lr_codes: 0.0,
            lr_codes_geo_mul: 1.0,
            codes_wplus: false,
            schedule: Vec::new(),
        }
    }
}

pub(crate) fn one() -> f32 {
    1.0
}

pub(crate) fn discriminator_config(res: usize, g: &GeneratorConfig) -> DiscriminatorConfig {
    match g.name.as_str() {
        "paper" => DiscriminatorConfig::new(res, 32768, 512),
        "demo" => DiscriminatorConfig::new(res, 2048, 64),
        _ => DiscriminatorConfig::new(res, 512, 32),
    }
}

impl RunConfig {
    /// A fresh run's settings from the flags (defaults where not given), validated.
    pub fn from_args(a: &TrainArgs, ds: &Dataset) -> Result<Self> {
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
        let lambda_face = a.lambda_face.unwrap_or(0.0);
        if !(lambda_face >= 0.0 && lambda_face.is_finite()) {
            bail!("--lambda-face must be a finite weight ≥ 0, got {lambda_face}");
        }
        if lambda_face > 0.0 && a.scans.is_none() {
            bail!("--lambda-face weighs a term at points of the scans' faces: give the scans with --scans DIR");
        }
        if !(lambda_texture_swap >= 0.0 && lambda_texture_swap.is_finite()) {
            bail!("--lambda-texture-swap must be a finite weight ≥ 0, got {lambda_texture_swap}");
        }
        if lambda_texture_swap > 0.0 && !reconstruction_terms {
            bail!("--lambda-texture-swap applies to reconstruction terms: use it with --objective reconstruction or --lambda-reconstruction");
        }
        let check_spread = |flag: &str, s: f32| -> Result<()> {
            if !(0.0..=1.0).contains(&s) {
                bail!("{flag} is a fraction of the way to a random w, in [0, 1]; got {s}");
            }
            if s > 0.0 && !reconstruction_terms {
                bail!("{flag} applies to reconstruction terms: use it with --objective reconstruction or --lambda-reconstruction");
            }
            Ok(())
        };
        let latent_spread = a.latent_spread.unwrap_or(0.0);
        check_spread("--latent-spread", latent_spread)?;
        if let Some(s) = a.latent_spread_geo {
            check_spread("--latent-spread-geo", s)?;
        }
        let lr_codes = a.lr_codes.unwrap_or(0.0);
        if !(lr_codes >= 0.0 && lr_codes.is_finite()) {
            bail!("--lr-codes must be a finite learning rate ≥ 0, got {lr_codes}");
        }
        if lr_codes > 0.0 && objective != Objective::Reconstruction {
            bail!("--lr-codes learns the subjects' codes of the reconstruction objective: use it with --objective reconstruction");
        }
        if a.codes_wplus && lr_codes == 0.0 {
            bail!("--codes-wplus makes the learned texture codes W+: give their rate with --lr-codes");
        }
        let r1_gamma = a.r1_gamma.unwrap_or(10.0);
        if !(r1_gamma >= 0.0 && r1_gamma.is_finite()) {
            bail!("--r1-gamma must be a finite weight ≥ 0, got {r1_gamma}");
        }
        for (flag, lr) in [("--lr-g", a.lr_g), ("--lr-d", a.lr_d)] {
            if let Some(lr) = lr.filter(|lr| !(*lr > 0.0 && lr.is_finite())) {
                bail!("{flag} must be a finite learning rate > 0, got {lr}");
            }
        }
        let mut gcfg = GeneratorConfig::preset(a.config_name())
            .with_context(|| format!("unknown --config `{}`", a.config_name()))?;
        if let Some(Some(init)) = &a.resume {
            // A generator saved with finer detail planes or another tet grid (e.g. the shipped
            // demo model's) keeps them: its config where it differs from the preset only there.
            let bytes = std::fs::read(init).with_context(|| format!("reading {}", init.display()))?;
            gcfg = getavatar_core::generator::checkpoint::config_with_saved_resolutions(&bytes, &gcfg);
        }
        if let Some(res) = a.texture_res {
            gcfg.texture_res = Some(res);
            gcfg.validate().map_err(|e| anyhow::anyhow!("--texture-res {res}: {e}"))?;
        }
        if let Some(res) = a.geometry_res {
            gcfg.geometry_res = Some(res);
            gcfg.validate().map_err(|e| anyhow::anyhow!("--geometry-res {res}: {e}"))?;
        }
        let defaults =
            RunConfig::with_objective(ds, &a.data, gcfg, a.batch_size(), r1_gamma, a.seed.unwrap_or(0), objective);
        let rc = RunConfig {
            lr_g: a.lr_g.unwrap_or(defaults.lr_g),
            lr_d: a.lr_d.unwrap_or(defaults.lr_d),
            lambda_reconstruction,
            views_per_subject: views,
            scans: a.scans.as_ref().map(|d| d.display().to_string()),
            lambda_scan: if a.scans.is_some() { lambda_scan } else { 0.0 },
            lambda_face,
            lambda_texture_swap,
            latent_spread,
            latent_spread_geo: a.latent_spread_geo,
            train_only: a.train_only.clone(),
            lr_codes,
            codes_wplus: a.codes_wplus,
            schedule: match &a.cfg {
                Some(p) => super::cfg::schedule(p)?,
                None => Vec::new(),
            },
            ..defaults
        };
        // Every change applies (fields that exist, values of their types).
        if let Some(last) = rc.schedule.last() {
            rc.at_step(last.after_step).context("--cfg")?;
        }
        Ok(rc)
    }

    /// The settings once `step` steps are done: the schedule's changes up to it applied.
    pub fn at_step(&self, step: u64) -> Result<Self> {
        let mut run = serde_json::to_value(self)?;
        for e in self.schedule.iter().filter(|e| e.after_step <= step) {
            run = super::cfg::apply(run, &e.set)
                .with_context(|| format!("the schedule's change after step {}", e.after_step))?;
        }
        serde_json::from_value(run).context("run.json after the schedule's changes")
    }

    /// The settings of a run on an empty 64² dataset with normals (for tests).
    #[cfg(test)]
    pub fn for_tests(generator: GeneratorConfig, objective: Objective) -> Self {
        let ds = Dataset { root: "data".into(), entries: Vec::new(), resolution: 64, has_normals: true };
        Self::with_objective(&ds, &ds.root, generator, 4, 10.0, 0, objective)
    }

    /// Whether the schedule changes the settings once `step` steps are done.
    pub fn changes_after(&self, step: u64) -> bool {
        self.schedule.iter().any(|e| e.after_step == step)
    }

    /// A continued run's settings, read from `run_path`; flags that differ from them are
    /// refused, each named.
    pub fn continued(a: &TrainArgs, run_path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(run_path)
            .with_context(|| format!("--resume: no run to continue in {} (run.json missing)", a.out.display()))?;
        let rc = serde_json::from_str::<RunConfig>(&text).context("run.json")?;
        if let Some(p) = &a.cfg {
            if super::cfg::schedule(p)? != rc.schedule {
                bail!("--cfg {}: its schedule differs from the run's (edit it in {})", p.display(), run_path.display());
            }
        }
        let conflicts = rc.resume_conflicts(a);
        if !conflicts.is_empty() {
            bail!(
                "{}: a continued run keeps its settings (edit them in {} to change them)",
                conflicts.join("; "),
                run_path.display()
            );
        }
        Ok(rc)
    }
}
