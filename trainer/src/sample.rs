//! `trainer sample`: generate one avatar and write RGB / normal / mask PNGs and a .glb of the
//! posed, vertex-coloured mesh.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use getavatar_core::body::pose_library::PoseLibrary;
use getavatar_core::export::gltf_export::{write_glb, ExportMesh};
use getavatar_core::generator::pipeline::generate_avatar;

use crate::model_io::{load_body, load_inverted_file, render_avatar, seed_styles, write_png, GeneratorArgs};

#[derive(clap::Args, Debug)]
pub struct SampleArgs {
    #[command(flatten)]
    pub backend: crate::backend::BackendArg,
    #[command(flatten)]
    pub model: GeneratorArgs,
    #[command(flatten)]
    pub seeds: crate::model_io::SeedArgs,
    /// Truncation ψ (1 = none; default: 0 for a checkpoint with latent modes, i.e. its training
    /// subjects, else 0.7).
    #[arg(long)]
    pub psi: Option<f32>,
    /// Truncate towards w_avg even where the checkpoint carries latent modes (by default
    /// ψ pulls the latents towards the training subjects: both towards the subject whose
    /// geometry mode is nearest, or each to its own nearest, as the checkpoint's pairing says).
    #[arg(long)]
    pub mean_truncation: bool,
    /// A training subject's own codes instead of seeds: `K` (its geometry and texture) or
    /// `K,M` (subject K's geometry with subject M's colours), for checkpoints that carry
    /// latent modes (reconstruction and anchored runs); ψ and the seeds are then unused.
    #[arg(long, value_name = "K[,M]")]
    pub subject: Option<String>,
    /// An inverted avatar (`trainer invert`'s output directory, or its
    /// `inverted.safetensors`): its tuned generator and codes; seeds, ψ and --checkpoint are
    /// then unused.
    #[arg(long, value_name = "DIR", conflicts_with_all = ["subject", "checkpoint"])]
    pub inverted: Option<PathBuf>,
    /// Named pose (T, A, Da, standing, walking, sitting, one_leg, arms_up).
    #[arg(long, default_value = "standing")]
    pub pose: String,
    /// Camera azimuth, degrees (0 = front).
    #[arg(long = "yaw", value_name = "DEG", default_value_t = 0.0, allow_negative_numbers = true)]
    pub yaw_deg: f32,
    /// Image size in pixels (square).
    #[arg(long, default_value_t = 512)]
    pub res: usize,
    /// Body model .npz in the SMPL layout (default: the embedded open body).
    #[arg(long)]
    pub body: Option<PathBuf>,
    #[arg(long, default_value = "samples")]
    pub out: PathBuf,
}

/// `K` or `K,M` of `--subject`.
fn parse_subject(spec: &str) -> Result<(usize, usize)> {
    let num = |t: &str| {
        t.trim().parse::<usize>().with_context(|| format!("--subject {spec}: expected K or K,M with subject indices"))
    };
    match spec.split_once(',') {
        Some((k, m)) => Ok((num(k)?, num(m)?)),
        None => num(spec).map(|k| (k, k)),
    }
}

pub fn sample(a: &SampleArgs) -> Result<()> {
    if !(16..=4096).contains(&a.res) {
        bail!("--res must be between 16 and 4096 (got {})", a.res);
    }
    if a.psi.is_some_and(|p| !p.is_finite()) {
        bail!("--psi must be a number");
    }
    let lib = PoseLibrary::builtin();
    let params = lib.params(&a.pose, &[]).with_context(|| {
        format!("unknown pose `{}`; available: {}", a.pose, lib.names().collect::<Vec<_>>().join(", "))
    })?;
    let model = load_body(&a.body)?;
    let device = a.backend.device()?;
    // An inverted avatar brings its own (tuned) generator and codes.
    let (cfg, g, modes, inverted) = match &a.inverted {
        Some(p) => {
            let (cfg, inv) = load_inverted_file(p, &a.model.config()?, &device)?;
            (cfg, inv.generator, None, Some(inv.styles))
        }
        None => {
            let (cfg, g, modes) = a.model.load(&device)?;
            (cfg, g, modes, None)
        }
    };
    let t0 = std::time::Instant::now();
    let ctx = crate::model_io::body_context(model, &cfg);
    let styles = match (&a.subject, inverted) {
        (_, Some(s)) => s,
        (Some(spec), None) => {
            let (k, m) = parse_subject(spec)?;
            let Some(modes) = &modes else {
                bail!("--subject needs a checkpoint with latent modes (a reconstruction or anchored run's); this one has none");
            };
            g.subject_styles(modes, k, m).with_context(|| {
                format!("--subject {spec}: the checkpoint has {} subjects (0…{})", modes.count(), modes.count() - 1)
            })?
        }
        (None, None) => seed_styles(&g, &cfg, &modes, a.seeds.pair(), a.psi, a.mean_truncation, &device),
    };
    let t1 = std::time::Instant::now();
    let avatar = generate_avatar(&g, &ctx, &styles, &params, &device)?;
    let t2 = std::time::Instant::now();
    let views = render_avatar(&g, &styles, &avatar, a.yaw_deg.to_radians(), a.res, &device)?;
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    write_png(&a.out.join("rgb.png"), &views.rgb, a.res, 3)?;
    write_png(&a.out.join("normal.png"), &views.normal, a.res, 3)?;
    write_png(&a.out.join("mask.png"), &views.mask, a.res, 1)?;
    let glb = write_glb(&ExportMesh {
        positions: avatar.mesh.vertices.clone(),
        normals: avatar.normals.clone(),
        colors: avatar.colors.clone(),
        uvs: Vec::new(),
        indices: avatar.mesh.faces.clone(),
        name: format!("getavatar_{}_{}_{}", a.seeds.seed_geo, a.seeds.seed_tex, a.pose),
    })?;
    crate::atomic::write_atomic(&a.out.join("avatar.glb"), &glb)?;
    println!(
        "wrote {}/{{rgb,normal,mask}}.png and avatar.glb: {} vertices, {} triangles; setup {:.2} s, generation {:.2} s, render {:.2} s",
        a.out.display(),
        avatar.mesh.vertices.len(),
        avatar.mesh.faces.len(),
        (t1 - t0).as_secs_f32(),
        (t2 - t1).as_secs_f32(),
        t2.elapsed().as_secs_f32()
    );
    Ok(())
}
