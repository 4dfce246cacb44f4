//! `trainer train`'s arguments, and which of them conflict with a continued run.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

/// `trainer train --help`'s groups of flags.
const RUN: &str = "Run";
const PAPER: &str = "The paper's objective (Sec. 4.5)";
const EXTENSIONS: &str = "Extensions (not in the paper; docs/deviations.md)";

#[derive(clap::Args, Clone, Debug)]
pub struct TrainArgs {
    /// A named config (`configs/*.toml`): flags and a schedule of run.json changes.
    ///
    /// Its `[train]` table holds flags (the command line's own win) and its `[[schedule]]` the
    /// changes of run.json by step (docs/training.md).
    #[arg(help_heading = RUN, long, value_name = "FILE")]
    pub cfg: Option<PathBuf>,
    /// Dataset directory (dataset.json + images, see docs/dataset.md).
    #[arg(help_heading = RUN, long)]
    pub data: PathBuf,
    /// Generator size: tiny, demo or paper [default: tiny].
    ///
    /// Generator size: tiny, demo or paper [default: tiny]. Like every run setting below, it
    /// is fixed when a run starts: with `--resume` a value that differs from the run's is refused.
    #[arg(help_heading = RUN, long)]
    pub config: Option<String>,
    /// Run directory.
    #[arg(help_heading = RUN, long, default_value = "runs/train")]
    pub out: PathBuf,
    /// Continue the run in --out; with a file: start G from it.
    ///
    /// Continue the run in --out; with a file: start the generator from that checkpoint
    /// (transfer learning, e.g. onto a dataset without normal maps).
    #[arg(help_heading = RUN, long, num_args = 0..=1)]
    pub resume: Option<Option<PathBuf>>,
    #[command(flatten)]
    pub backend: crate::backend::BackendArg,
    /// Samples per step [default: 4].
    ///
    /// [default: 4]
    #[arg(help_heading = RUN, long)]
    pub batch: Option<usize>,
    /// Train until this many steps in total.
    #[arg(help_heading = RUN, long, default_value_t = 1000)]
    pub steps: u64,
    /// Checkpoint and sample grid every N steps.
    #[arg(help_heading = RUN, long, default_value_t = 100)]
    pub snapshot_every: u64,
    /// Seed of the run's random streams [default: 0].
    ///
    /// [default: 0]
    #[arg(help_heading = RUN, long)]
    pub seed: Option<u64>,
    /// R1 weight γ (10 for THUman2.0-like data, 20 for RenderPeople) [default: 10].
    #[arg(help_heading = PAPER, long)]
    pub r1_gamma: Option<f32>,
    /// adversarial (the paper's) or reconstruction (a warm-up) [default: adversarial].
    ///
    /// `adversarial`: the paper's objective. `reconstruction`: a warm-up that is not in the
    /// paper (fixed latents per training subject, L1 to its views); start an adversarial
    /// run from its generator with `--resume RUN/generator.safetensors` [default: adversarial].
    #[arg(help_heading = PAPER, long, value_enum)]
    pub objective: Option<Objective>,
    /// Weight of a reconstruction anchor in adversarial runs [default: 0].
    ///
    /// Adversarial runs only (not in the paper): weight of a reconstruction anchor added to
    /// G's loss, the warm-up's L1 on a batch of subject views at their fixed latents, so that
    /// an adversarial run started from a warm-up keeps its subjects while the game spreads the
    /// rest of the latent space. 0 (the default) is the paper's objective.
    #[arg(help_heading = EXTENSIONS, long)]
    pub lambda_reconstruction: Option<f32>,
    /// Views rendered per drawn subject in the reconstruction terms [default: 1].
    ///
    /// Reconstruction terms only (the warm-up, and the anchor of adversarial runs): views
    /// rendered per drawn subject, the drawn one plus others of the same subject and body pose.
    /// One surface serves all of them (triplanes, inverse skinning and DMTet are per avatar),
    /// so each step sees `batch × views` images for little more than `batch` [default: 1].
    #[arg(help_heading = EXTENSIONS, long)]
    pub views: Option<usize>,
    /// The dataset's scans, for canonical-space scan terms.
    ///
    /// Reconstruction terms only (not in the paper): the scans the dataset was prepared from
    /// (`prepare --scans`, one folder per subject with its OBJ and smpl.json). Adds
    /// canonical-space texture and SDF supervision at points drawn on each drawn subject's
    /// scan (`diff::scan_supervision`), weighted by `--lambda-scan`.
    #[arg(help_heading = EXTENSIONS, long)]
    pub scans: Option<PathBuf>,
    /// Weight of the scan terms (with `--scans`) [default: 1].
    #[arg(help_heading = EXTENSIONS, long)]
    pub lambda_scan: Option<f32>,
    /// Weight of the scans' face term [default: 0].
    ///
    /// With `--scans` (not in the paper): weight of the face term, the scan texture term at
    /// points drawn on the face alone (`FACE_POINTS_PER_STEP` of each drawn subject), where
    /// eyes, brows and mouth are too small in the renders for the image L1 to keep them.
    /// `--lambda-scan 0` leaves it alone. 0 (the default): off.
    #[arg(help_heading = EXTENSIONS, long)]
    pub lambda_face: Option<f32>,
    /// Train only the generator parameters under PREFIX.
    ///
    /// Train only the generator parameters whose checkpoint path starts with PREFIX (e.g.
    /// `synthesis.texture_detail.1.constant`, the learned constant of the second texture
    /// detail block); the others keep their weights. For a stage that teaches one part, such
    /// as the faces of the shared constant, without moving the weights every subject shares.
    #[arg(help_heading = EXTENSIONS, long, value_name = "PREFIX")]
    pub train_only: Option<String>,
    /// Weight of the texture-swap term [default: 0].
    ///
    /// Reconstruction terms only (not in the paper): weight of a texture-swap term. Each drawn
    /// subject's surface is also coloured by the texture field built from another drawn
    /// subject's geometry code with its own texture code, and that RGB is compared with the
    /// subject's views by L1 too. With fixed latent pairs alone the colours can hide in the
    /// geometry-styled backbone, and a seed's texture code then hardly changes the colours
    /// (re-texturing renders blends); this term makes them follow the texture code. 0 (the
    /// default): off.
    #[arg(help_heading = EXTENSIONS, long)]
    pub lambda_texture_swap: Option<f32>,
    /// Supervise codes up to this fraction of the way to random ones [default: 0].
    ///
    /// Reconstruction terms only (not in the paper): train the neighbourhoods of the subjects'
    /// W codes, not only the codes. Each drawn subject's w (per branch) is moved a fraction ψ,
    /// uniform in [0, this], of the way to a random w (mapped from z ~ N(0, I)) and still
    /// supervised with the subject's views. Sampling truncates seeds towards the nearest
    /// subject by ψ = 0.7, i.e. lands 70 % of the way out, where a run without this renders
    /// blends. 0 (the default): off; 0.7 matches sampling.
    #[arg(help_heading = EXTENSIONS, long)]
    pub latent_spread: Option<f32>,
    /// The geometry branch's own --latent-spread.
    ///
    /// The geometry branch's spread where it should differ from `--latent-spread` (which
    /// then applies to the texture branch alone). A wide geometry spread with a narrow
    /// texture spread trains the shapes that ψ = 1 samples reach while the colours stay
    /// close to the subjects'. Absent: `--latent-spread`.
    #[arg(help_heading = EXTENSIONS, long)]
    pub latent_spread_geo: Option<f32>,
    /// Adam rate of learned subject codes [default: 0: fixed].
    ///
    /// Reconstruction objective only (not in the paper; GLO): learn each training subject's W
    /// codes as offsets from its fixed latents' mapping, at this Adam rate, with the same L1 as
    /// the generator. The generator file's latent modes are the moved codes. A run started
    /// from a file (`--resume FILE`) whose latent modes hold as many subjects starts its
    /// offsets at those modes. `run.json`'s `lr_codes_geo_mul` scales the geometry codes'
    /// rate (0: only the texture codes learn). 0 (the default): fixed codes.
    #[arg(help_heading = EXTENSIONS, long)]
    pub lr_codes: Option<f32>,
    /// Learned texture codes in W+ (with --lr-codes).
    ///
    /// With `--lr-codes`: learn each subject's texture code in W+, one offset per texture style
    /// layer (a multi-view W+ inversion of every subject, trained beside G), instead of one W
    /// offset. The generator file's latent modes then carry the layer offsets
    /// (`latent_modes/tex_layers`).
    #[arg(help_heading = EXTENSIONS, long)]
    pub codes_wplus: bool,
    /// Adam rate of G [default: 0.002 adversarial, 0.0005 reconstruction].
    ///
    /// Adam learning rate of G (not of the paper's defaults where changed) [default: 0.002
    /// adversarial, 0.0005 reconstruction]. Below D's rate it lets the discriminators get
    /// ahead of G (a two-time-scale update).
    #[arg(help_heading = PAPER, long)]
    pub lr_g: Option<f32>,
    /// Adam learning rate of the discriminators [default: 0.002].
    #[arg(help_heading = PAPER, long)]
    pub lr_d: Option<f32>,
    /// Texture plane resolution (texture-only detail blocks).
    ///
    /// Resolution of the generator's texture planes, finer than the config's planes (not in
    /// the paper: texture-only detail blocks, `GeneratorConfig::texture_res`). A `--resume`
    /// checkpoint with coarser texture planes grows into it, rendering as before at first.
    /// Without it, a `--resume` checkpoint's own texture planes are kept.
    #[arg(help_heading = EXTENSIONS, long)]
    pub texture_res: Option<usize>,
    /// Geometry plane resolution (geometry-only detail blocks).
    ///
    /// Resolution of the generator's geometry planes, finer than the config's planes (not in
    /// the paper: geometry-only detail blocks, `GeneratorConfig::geometry_res`), so that the
    /// normal field can hold surface detail finer than the planes' texels; the mesh's tet grid
    /// is unchanged. A `--resume` checkpoint with coarser geometry planes grows into it,
    /// rendering as before at first. Without it, a `--resume` checkpoint's own geometry planes
    /// are kept.
    #[arg(help_heading = EXTENSIONS, long)]
    pub geometry_res: Option<usize>,
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
}

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
