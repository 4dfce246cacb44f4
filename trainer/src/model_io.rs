//! What the trainer's commands share: the shipped model files, the generator arguments and
//! loading (a checkpoint, the shipped model or a random one), the body model, seed styles,
//! the body context (kept on disk between commands), an avatar's rendered views, PNG writing
//! and reconstruction files.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use getavatar_core::body::body_model::BodyModel;
use getavatar_core::burn::tensor::Device;
use getavatar_core::generator::checkpoint::{
    config_with_saved_resolutions, load_generator_and_modes, load_inverted, InvertedAvatar,
};
use getavatar_core::generator::network::GeneratorConfig;
use getavatar_core::generator::pipeline::recolor_async;
use getavatar_core::generator::pipeline::BodyContext;
use getavatar_core::generator::pipeline::{default_psi, seed_latents, Avatar, Generator, LatentModes, Styles};
use getavatar_core::generator::readback::block_on_ready;
use getavatar_core::geometry::context_cache::{build, file_name, from_bytes, to_bytes};
use getavatar_core::io::dataset::encode_png;
use getavatar_core::render::camera::OrbitCamera;
use getavatar_core::render::rasterize::{render_views_textured, RenderedViews};

pub fn write_png(path: &Path, data: &[u8], size: usize, channels: usize) -> Result<()> {
    let png = encode_png(size, size, channels, data).with_context(|| format!("encoding {}", path.display()))?;
    crate::atomic::write_atomic(path, &png)
}

/// Where the shipped demo model lives (see `assets/models/MODEL_CARD.md`).
pub const SHIPPED_DEMO_MODEL: &str = "assets/models/demo.safetensors";
/// Where its RGB discriminator lives (the inversion's perceptual term).
pub const SHIPPED_DEMO_DISCRIMINATOR: &str = "assets/models/demo_d_rgb.safetensors";

/// Where its photo encoder lives (the reconstruction's first guess).
pub const SHIPPED_DEMO_ENCODER: &str = "assets/models/encoder.safetensors";

/// The shipped demo model, if this is the `demo` config and the file is there (looked up in
/// the working directory, then in the source tree this binary was built from).
pub fn shipped_model(cfg: &GeneratorConfig) -> Option<PathBuf> {
    shipped_file(cfg, SHIPPED_DEMO_MODEL)
}

/// The shipped demo model's RGB discriminator, found like [`shipped_model`].
pub fn shipped_discriminator(cfg: &GeneratorConfig) -> Option<PathBuf> {
    shipped_file(cfg, SHIPPED_DEMO_DISCRIMINATOR)
}

/// The shipped demo model's photo encoder, found like [`shipped_model`].
pub fn shipped_encoder(cfg: &GeneratorConfig) -> Option<PathBuf> {
    shipped_file(cfg, SHIPPED_DEMO_ENCODER)
}

fn shipped_file(cfg: &GeneratorConfig, rel: &str) -> Option<PathBuf> {
    if cfg.name != "demo" {
        return None;
    }
    [PathBuf::from(rel), Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(rel)].into_iter().find(|p| p.is_file())
}

/// The seeds of a generated avatar's two latents (`sample`, `export`).
#[derive(clap::Args, Debug)]
pub struct SeedArgs {
    /// Seed of the geometry latent z_geo.
    #[arg(long, default_value_t = 0)]
    pub seed_geo: u64,
    /// Seed of the texture latent z_tex.
    #[arg(long, default_value_t = 0)]
    pub seed_tex: u64,
}

impl SeedArgs {
    /// (geometry, texture).
    pub fn pair(&self) -> (u64, u64) {
        (self.seed_geo, self.seed_tex)
    }
}

/// Which generator a command runs: `--config`, `--checkpoint`, `--random-weights` (shared by
/// `sample` and `eval`).
#[derive(clap::Args, Debug)]
pub struct GeneratorArgs {
    /// Generator size: paper, demo or tiny.
    #[arg(long, default_value = "demo")]
    pub config: String,
    /// Trained generator (`generator.safetensors`; default: the shipped demo model for
    /// `--config demo`, random weights otherwise).
    #[arg(long)]
    pub checkpoint: Option<PathBuf>,
    /// Use deterministic random weights even where a trained model ships.
    #[arg(long = "random-weights", conflicts_with = "checkpoint")]
    pub random: bool,
    /// Extract the surface on an N³ tet grid instead of the model's own (`tet_res` of its
    /// config; no weight depends on it). Finer grids resolve narrow gaps and grazing
    /// outlines at the cost of time and memory.
    #[arg(long = "tet-res", value_name = "N")]
    pub tet_res: Option<usize>,
}

impl GeneratorArgs {
    /// The config preset, the generator (see [`generator_or_random`]) and its latent modes.
    /// A checkpoint's config replaces the preset where the two differ only in resolutions
    /// (a generator grown with `trainer train --texture-res`, a finer tet grid).
    /// `--tet-res` replaces the loaded config's tet grid.
    pub fn load(&self, device: &Device) -> Result<(GeneratorConfig, Generator, Option<LatentModes>)> {
        let (mut cfg, mut g, modes) =
            generator_or_random(self.checkpoint.as_deref(), self.random, &self.config()?, device)?;
        if let Some(n) = self.tet_res {
            cfg.tet_res = n;
            cfg.validate().map_err(|e| anyhow::anyhow!("--tet-res {n}: {e}"))?;
            g.decoders.tet_res = n;
        }
        Ok((cfg, g, modes))
    }
}

impl GeneratorArgs {
    /// The config preset alone.
    pub fn config(&self) -> Result<GeneratorConfig> {
        GeneratorConfig::preset(&self.config)
            .with_context(|| format!("unknown --config `{}` (paper, demo, tiny)", self.config))
    }
}

/// An inverted avatar: `trainer invert`'s output directory or its `inverted.safetensors`, with
/// the config it loads under (`cfg`, or the file's where it differs only in resolutions,
/// as [`generator_or_random`]).
pub fn load_inverted_file(
    path: &Path,
    cfg: &GeneratorConfig,
    device: &Device,
) -> Result<(GeneratorConfig, InvertedAvatar)> {
    let file = if path.is_dir() { path.join("inverted.safetensors") } else { path.to_path_buf() };
    let bytes = std::fs::read(&file).with_context(|| format!("reading {}", file.display()))?;
    let cfg = config_with_saved_resolutions(&bytes, cfg);
    let inv = load_inverted(&bytes, &cfg, device)
        .with_context(|| format!("loading the inverted avatar {}", file.display()))?;
    Ok((cfg, inv))
}

/// The generator in `checkpoint` and the latent modes it carries (if any); without one, the
/// shipped model of `cfg` (the trained demo model; an error where it ships but is not found)
/// unless `random` is set; otherwise (saying so) the deterministic random weights (seed 0) of
/// `cfg`. The config returned is `cfg`, or
/// the checkpoint's where it is `cfg` with other detail planes or tet grid
/// ([`config_with_saved_resolutions`]).
pub fn generator_or_random(
    checkpoint: Option<&Path>,
    random: bool,
    cfg: &GeneratorConfig,
    device: &Device,
) -> Result<(GeneratorConfig, Generator, Option<LatentModes>)> {
    let shipped = if random { None } else { shipped_model(cfg) };
    Ok(match checkpoint.map(Path::to_path_buf).or(shipped) {
        Some(p) => {
            if checkpoint.is_none() {
                eprintln!("using the shipped demo model {}", p.display());
            }
            let bytes = std::fs::read(&p).with_context(|| format!("reading checkpoint {}", p.display()))?;
            let loading = || format!("loading checkpoint {}", p.display());
            let cfg = config_with_saved_resolutions(&bytes, cfg);
            let (g, modes) = load_generator_and_modes(&bytes, &cfg, device).with_context(loading)?;
            (cfg, g, modes)
        }
        None if !random && cfg.name == "demo" => bail!(
            "the shipped demo model was not found: neither ./{SHIPPED_DEMO_MODEL} nor {} exists (a trainer \
             built from another checkout?); give --checkpoint FILE, or --random-weights for untrained weights",
            Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(SHIPPED_DEMO_MODEL).display()
        ),
        None => {
            eprintln!(
                "no trained checkpoint: using deterministic random weights (seed 0) of the `{}` config",
                cfg.name
            );
            (cfg.clone(), Generator::new(cfg, 0, device), None)
        }
    })
}

/// The body model in `path` (SMPL-layout .npz), or the embedded open body.
pub fn load_body(path: &Option<PathBuf>) -> Result<BodyModel> {
    Ok(match path {
        Some(p) => BodyModel::from_npz_bytes(&std::fs::read(p).with_context(|| format!("reading {}", p.display()))?)
            .with_context(|| format!("loading the body model {}", p.display()))?,
        None => BodyModel::default_body()?,
    })
}

/// The folder of the body-context files: `$GETAVATAR_CACHE/body_context` (set empty: none),
/// else `$XDG_CACHE_HOME/getavatar/body_context`, else `~/.cache/getavatar/body_context`.
fn body_context_dir() -> Option<PathBuf> {
    let base = match std::env::var_os("GETAVATAR_CACHE") {
        Some(dir) if dir.is_empty() => return None,
        Some(dir) => PathBuf::from(dir),
        None => match std::env::var_os("XDG_CACHE_HOME").filter(|d| !d.is_empty()) {
            Some(dir) => PathBuf::from(dir).join("getavatar"),
            None => PathBuf::from(std::env::var_os("HOME").filter(|d| !d.is_empty())?).join(".cache/getavatar"),
        },
    };
    Some(base.join("body_context"))
}

/// The body context of `model` at `cfg`'s resolutions with its canonical grid made: read from
/// the cache folder ([`body_context_dir`]) when an earlier command kept it there (0.03 s
/// against 0.45 s of building on 2 cores, `trainer bench generator`), otherwise built and kept.
/// A file that cannot be used or kept costs only the build, with a line saying why.
pub fn body_context(model: BodyModel, cfg: &GeneratorConfig) -> BodyContext {
    let Some(dir) = body_context_dir() else {
        return build(model, cfg.template_res, cfg.tet_res);
    };
    let (ctx, used) = body_context_in(model, cfg.template_res, cfg.tet_res, &dir);
    if let KeptContext::Built { why, kept } = used {
        if let Some(why) = why {
            eprintln!("the kept body context was not used ({why}): built it again");
        }
        match kept {
            Ok(path) => eprintln!("kept the body context for the next commands in {}", path.display()),
            Err(e) => eprintln!("could not keep the body context for the next commands: {e:#}"),
        }
    }
    ctx
}

/// What [`body_context_in`] did with the folder's file.
#[derive(Debug)]
enum KeptContext {
    Read,
    /// Built, there being no file or `why` it could not be used; then written to the file, or
    /// the error that kept it from being written.
    Built {
        why: Option<String>,
        kept: Result<PathBuf>,
    },
}

/// [`body_context`] with the file in `dir` (`context_cache::file_name`), written atomically.
fn body_context_in(model: BodyModel, template_res: usize, tet_res: usize, dir: &Path) -> (BodyContext, KeptContext) {
    let path = dir.join(file_name(&model, template_res, tet_res));
    let why = match std::fs::read(&path) {
        Ok(bytes) => match from_bytes(model.clone(), &bytes, template_res, tet_res) {
            Ok(ctx) => return (ctx, KeptContext::Read),
            Err(why) => Some(format!("{}: {why}", path.display())),
        },
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
        Err(e) => Some(format!("reading {}: {e}", path.display())),
    };
    let ctx = build(model, template_res, tet_res);
    let kept =
        to_bytes(&ctx).map_err(anyhow::Error::msg).and_then(|b| crate::atomic::write_atomic(&path, &b)).map(|()| path);
    (ctx, KeptContext::Built { why, kept })
}

/// The styles of the seeds' latents, truncated by ψ (`None`: the model's default) towards
/// the checkpoint's latent modes (w_avg where it has none or `mean_truncation`).
pub fn seed_styles(
    g: &Generator,
    cfg: &GeneratorConfig,
    modes: &Option<LatentModes>,
    (seed_geo, seed_tex): (u64, u64),
    psi: Option<f32>,
    mean_truncation: bool,
    device: &Device,
) -> Styles {
    let (zg, zt) = seed_latents(cfg, seed_geo, seed_tex, device);
    let modes = truncation_modes(modes, mean_truncation);
    g.styles_with(zg, zt, psi.unwrap_or_else(|| default_psi(modes)), modes)
}

/// The modes to truncate towards: the checkpoint's unless `mean_truncation` (then w_avg).
pub fn truncation_modes(modes: &Option<LatentModes>, mean_truncation: bool) -> Option<&LatentModes> {
    modes.as_ref().filter(|_| !mean_truncation)
}

/// RGB, normal and mask views of a generated avatar from the reference orbit camera at
/// `yaw` (radians, 0 = front), `res`²; RGB is the texture field queried at every pixel's
/// canonical coordinate (paper Sec. 4.4).
pub fn render_avatar(
    g: &Generator,
    styles: &Styles,
    avatar: &Avatar,
    yaw: f32,
    res: usize,
    device: &Device,
) -> Result<RenderedViews> {
    if avatar.mesh.faces.is_empty() {
        bail!("the generator produced an empty surface");
    }
    let cam = OrbitCamera { yaw, ..OrbitCamera::default() };
    let vp = cam.projection_gl(1.0) * cam.world_to_camera();
    let planes = g.triplanes(styles);
    let m = &avatar.mesh;
    Ok(render_views_textured(&m.vertices, &m.faces, &avatar.normals, &m.attributes, vp, res, 2, |pts| {
        block_on_ready(recolor_async(g, &planes, styles, pts, device))
    })?)
}

/// A reconstruction's outline moved onto its photo's person
/// ([`getavatar_core::reconstruction::silhouette_snap`]), as `trainer invert` and `trainer
/// export --inverted` do before projecting the photo; says how far.
pub fn snap_to_photo(
    rigged: &mut getavatar_core::generator::rigging::RiggedAvatar,
    ctx: &getavatar_core::geometry::BodyContext,
    photo: &getavatar_core::reconstruction::photo_projection::SourcePhoto,
) {
    let t = std::time::Instant::now();
    let body = getavatar_core::body::skinning::pose_body(&ctx.model, &photo.view.body);
    let report = rigged.snap_to_photo(ctx, &body, photo);
    eprintln!(
        "the outline moved onto the photo's person: {} outline vertices ({} held by another part in the way), at most {:.1} cm ({:.0} ms)",
        report.outline_vertices,
        report.held_vertices,
        report.max_move_m * 100.0,
        t.elapsed().as_secs_f64() * 1e3
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The canonical grids' bits, equal or not.
    fn grid_bits(c: &BodyContext) -> Option<Vec<u32>> {
        c.canonical_grid_made().map(|g| {
            let points = g.canonical.iter().flat_map(|p| p.to_array()).chain(g.template.iter().copied());
            points.map(f32::to_bits).chain(g.band.iter().copied()).collect()
        })
    }

    #[test]
    fn a_kept_context_is_read_back_and_a_damaged_file_is_rebuilt_and_replaced() {
        let dir = tempfile::tempdir().expect("a folder");
        let body = BodyModel::default_body().expect("the embedded body");
        let (built, used) = body_context_in(body.clone(), 24, 12, dir.path());
        let path = match used {
            KeptContext::Built { why: None, kept: Ok(p) } => p,
            other => panic!("expected a first build, got {other:?}"),
        };
        let (read, used) = body_context_in(body.clone(), 24, 12, dir.path());
        assert!(matches!(used, KeptContext::Read), "{used:?}");
        assert!(grid_bits(&read).is_some() && grid_bits(&read) == grid_bits(&built));
        let mut bytes = std::fs::read(&path).expect("the file");
        let mid = bytes.len() / 2;
        bytes[mid] ^= 0x10;
        std::fs::write(&path, &bytes).expect("write");
        let (rebuilt, used) = body_context_in(body.clone(), 24, 12, dir.path());
        match used {
            KeptContext::Built { why: Some(why), kept: Ok(_) } => assert!(why.contains("checksum"), "{why}"),
            other => panic!("expected a rebuild, got {other:?}"),
        }
        assert!(grid_bits(&rebuilt) == grid_bits(&built));
        let (_, used) = body_context_in(body, 24, 12, dir.path());
        assert!(matches!(used, KeptContext::Read), "replaced: {used:?}");
    }

    #[test]
    fn threads_keeping_the_same_context_at_once_leave_one_whole_file() {
        let dir = tempfile::tempdir().expect("a folder");
        let body = BodyModel::default_body().expect("the embedded body");
        let built: Vec<BodyContext> = std::thread::scope(|sc| {
            let handles: Vec<_> =
                (0..4).map(|_| sc.spawn(|| body_context_in(body.clone(), 16, 8, dir.path()).0)).collect();
            handles.into_iter().map(|h| h.join().expect("no panic")).collect()
        });
        let (read, used) = body_context_in(body, 16, 8, dir.path());
        assert!(matches!(used, KeptContext::Read), "{used:?}");
        for ctx in &built {
            assert!(grid_bits(ctx) == grid_bits(&read));
        }
        let left: Vec<_> =
            std::fs::read_dir(dir.path()).expect("the folder").map(|e| e.expect("an entry").file_name()).collect();
        assert_eq!(left.len(), 1, "no temporary file left: {left:?}");
    }

    #[test]
    fn an_unwritable_folder_still_gives_the_context() {
        let dir = tempfile::tempdir().expect("a folder");
        let file = dir.path().join("a file");
        std::fs::write(&file, b"not a folder").expect("write");
        let body = BodyModel::default_body().expect("the embedded body");
        let (ctx, used) = body_context_in(body, 16, 8, &file.join("sub"));
        assert!(matches!(used, KeptContext::Built { kept: Err(_), .. }), "{used:?}");
        assert!(ctx.canonical_grid_made().is_some());
    }
}
