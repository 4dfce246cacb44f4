//! `trainer export`: an avatar (or the bare body) as an animatable .glb — bound in the rest
//! pose, 24 SMPL joints (or humanoid-named, `--skeleton humanoid`), showing the chosen pose,
//! with motion clips as glTF animations — or, with `--static`, the posed mesh alone; as a
//! VRM 1.0 avatar (`--format vrm`); or motion clips as VRM animations (`--format vrma`).
//! The app's downloads use the same core code (`RiggedAvatar::animated_glb` / `vrm`,
//! `skin_export`).

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use getavatar_core::body::body_fit::fit::BodyFit;
use getavatar_core::body::body_model::BodyModel;
use getavatar_core::body::humanoid::{SkeletonNames, HUMANOID_BONES};
use getavatar_core::body::motion::{Motion, BUILTIN_CLIPS};
use getavatar_core::body::pose_library::PoseLibrary;
use getavatar_core::body::skinning::{forward_kinematics, pose_body, vertex_normals, BodyParams};
use getavatar_core::burn::tensor::Device;
use getavatar_core::export::gltf_export::{write_glb, ExportMesh};
use getavatar_core::export::skin_export::{animated_body_glb, body_vrm, motion_vrma, vrm_frame};
use getavatar_core::export::vrm_export::{AvatarOrigin, VrmMeta};
use getavatar_core::generator::checkpoint::InvertedAvatar;
use getavatar_core::generator::network::GeneratorConfig;
use getavatar_core::generator::pipeline::BodyContext;
use getavatar_core::generator::pipeline::{Generator, Styles};
use getavatar_core::generator::readback::block_on_ready;
use getavatar_core::generator::rigging::{generate_rigged_async, BakedTexture, RiggedAvatar};
use getavatar_core::reconstruction::photo_projection::SourcePhoto;

use crate::model_io::{load_body, load_inverted_file, seed_styles, snap_to_photo, GeneratorArgs};

#[derive(clap::Args, Debug)]
pub struct ExportArgs {
    #[command(flatten)]
    pub seeds: crate::model_io::SeedArgs,
    /// Truncation ψ (default: the model's, as `sample`).
    #[arg(long)]
    pub psi: Option<f32>,
    #[command(flatten)]
    pub model: GeneratorArgs,
    #[command(flatten)]
    pub backend: crate::backend::BackendArg,
    /// The pose the file shows (a library pose; the animations start from their own).
    /// Default: `standing`; with `--inverted`, the pose of the photo it was made from.
    #[arg(long)]
    pub pose: Option<String>,
    /// Pose and shape from a body fit (`fit.json` of `fit-pose` or the app's "Download fit")
    /// instead of `--pose`.
    #[arg(long, conflicts_with = "pose")]
    pub fit: Option<PathBuf>,
    /// A motion clip: a built-in name (walk, turn, wave) or an SMPL/AMASS .npz file;
    /// repeat for several. Each becomes one glTF animation.
    #[arg(long = "motion", value_name = "CLIP|FILE")]
    pub motions: Vec<String>,
    /// The bare body instead of a generated avatar.
    #[arg(long)]
    pub body_only: bool,
    /// An inverted avatar (`trainer invert`'s output directory or its
    /// `inverted.safetensors`): its tuned generator and codes (the seeds, ψ and --checkpoint
    /// are then unused), its body shape, and its texture with the photo's colours projected
    /// again (where the file keeps the photo).
    #[arg(long, value_name = "DIR", conflicts_with_all = ["checkpoint", "body_only", "random"])]
    pub inverted: Option<PathBuf>,
    /// With --inverted: the generated texture and outline alone, without the photo's colours
    /// and without the outline moved onto the photo's person.
    #[arg(long, requires = "inverted")]
    pub no_projection: bool,
    /// A static mesh in the pose shown (no skin, no animations).
    #[arg(long, conflicts_with = "motions")]
    pub r#static: bool,
    /// Side of the baked base-colour texture (the body's UV layout transferred to the avatar;
    /// 0: vertex colours, no texture).
    #[arg(long, default_value_t = 1024)]
    pub texture_res: usize,
    /// Also write OBJ + MTL + PNG beside the .glb (the mesh in the pose shown, textured).
    #[arg(long)]
    pub obj: bool,
    /// Body model .npz in the SMPL layout (default: the embedded open body).
    #[arg(long)]
    pub body: Option<PathBuf>,
    /// The file: `glb` (glTF 2.0), `vrm` (a VRM 1.0 avatar in its rest T-pose, soles at
    /// y = 0, humanoid bones; no animations) or `vrma` (each --motion as a VRM animation:
    /// one file, or with several `<stem>_<motion>.vrma` beside --out).
    #[arg(long, value_enum, default_value_t = Format::Glb)]
    pub format: Format,
    /// The skeleton's node names: `smpl` (pelvis, left_hip, …) or `humanoid` (Hips,
    /// LeftUpLeg, …, which retargeting tools map by name).
    #[arg(long, value_parser = SkeletonNames::parse, default_value = "smpl")]
    pub skeleton: SkeletonNames,
    #[arg(long, default_value = "avatar.glb")]
    pub out: PathBuf,
    /// Also write, for checking other tools against the project's skinning, the vertex
    /// positions the project's LBS gives at the first, a middle and the last frame of each
    /// motion: `{"clips": [{"name", "frames": [{"frame", "time", "positions": [x, y, z, …]}]}]}`;
    /// for `vrm` the rest joints (`{"offset": [x, y, z], "joints": {"hips": [x, y, z], …}}`:
    /// VRM's frame, the body moved by `offset`), for `vrma` the joints per frame (`"joints"`
    /// in place of `"positions"`, and the skeleton's `"offset"`).
    #[arg(long, value_name = "FILE")]
    pub frames_json: Option<PathBuf>,
}

/// `trainer export --format`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    Glb,
    Vrm,
    Vrma,
}

/// The avatar a file holds, in words.
fn what_avatar(a: &ExportArgs) -> String {
    match &a.inverted {
        Some(p) => format!("inverted avatar {}", p.display()),
        None => format!("avatar {}/{}", a.seeds.seed_geo, a.seeds.seed_tex),
    }
}

/// Frames checked by `--frames-json`.
fn check_frames(m: &Motion) -> Vec<usize> {
    let mut f = vec![0, m.len() / 3, m.len() - 1];
    f.dedup();
    f
}

fn frames_json(
    motions: &[Motion],
    positions: impl Fn(&BodyParams) -> serde_json::Value,
    key: &str,
    betas: &[f32],
) -> serde_json::Value {
    let clips: Vec<serde_json::Value> = motions
        .iter()
        .map(|m| {
            let frames: Vec<serde_json::Value> = check_frames(m)
                .into_iter()
                .map(|k| {
                    serde_json::json!({ "frame": k, "time": k as f32 / getavatar_core::body::motion::MOTION_FPS, key: positions(&m.params(k, betas)) })
                })
                .collect();
            serde_json::json!({ "name": m.name, "frames": frames })
        })
        .collect();
    serde_json::json!({ "clips": clips })
}

/// Vertex positions as one flat JSON array.
fn flat(points: &[glam::Vec3]) -> serde_json::Value {
    points.iter().flat_map(|v| v.to_array()).collect()
}

/// The body's joints at `params`, moved by `offset` (VRM's frame), keyed by VRM bone.
fn vrm_joints(model: &BodyModel, params: &BodyParams, offset: glam::Vec3) -> serde_json::Value {
    let rest = model.regress_joints(&model.shaped_vertices(&params.betas));
    let posed = forward_kinematics(&model.parents, &rest, params).posed_joints;
    let bones: serde_json::Map<String, serde_json::Value> = HUMANOID_BONES
        .iter()
        .zip(posed)
        .filter_map(|(b, p)| b.vrm.map(|v| (v.to_string(), serde_json::json!((p + offset).to_array()))))
        .collect();
    serde_json::Value::Object(bones)
}

/// `--frames-json` of a .vrm: the rest joints in VRM's frame and the frame's offset.
fn vrm_rest_json(model: &BodyModel, betas: &[f32], offset: glam::Vec3) -> serde_json::Value {
    let rest = BodyParams { betas: betas.to_vec(), ..BodyParams::default() };
    serde_json::json!({ "offset": offset.to_array(), "joints": vrm_joints(model, &rest, offset) })
}

/// `--format vrma`: each motion as a VRM animation on the skeleton of the body at
/// `params.betas`; no avatar is generated.
fn export_vrma(a: &ExportArgs, model: &BodyModel, params: &BodyParams, motions: &[Motion]) -> Result<()> {
    if motions.is_empty() {
        bail!("--format vrma needs at least one --motion");
    }
    let frame = vrm_frame(model, &params.betas)?;
    let stem = a.out.file_stem().map_or_else(|| "motion".into(), |s| s.to_string_lossy().into_owned());
    for m in motions {
        let path =
            if motions.len() == 1 { a.out.clone() } else { a.out.with_file_name(format!("{stem}_{}.vrma", m.name)) };
        let bytes = motion_vrma(model, &params.betas, m, a.skeleton)?;
        crate::atomic::write_atomic(&path, &bytes)?;
        println!(
            "wrote {} ({:.2} MB): VRM animation `{}`, {} frames, {:.1} s",
            path.display(),
            bytes.len() as f64 / 1e6,
            m.name,
            m.len(),
            m.duration()
        );
    }
    if let Some(path) = &a.frames_json {
        let mut json = frames_json(motions, |p| vrm_joints(model, p, frame.offset), "joints", &params.betas);
        json["offset"] = serde_json::json!(frame.offset.to_array());
        crate::atomic::write_atomic(path, json.to_string().as_bytes())?;
    }
    Ok(())
}

/// A clip by name or file.
pub fn load_motion(spec: &str) -> Result<Motion> {
    if BUILTIN_CLIPS.contains(&spec) {
        return Ok(Motion::builtin(spec)?);
    }
    let path = PathBuf::from(spec);
    if !path.exists() {
        bail!("--motion {spec}: neither a built-in clip ({}) nor a file", BUILTIN_CLIPS.join(", "));
    }
    let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
    let name = path.file_stem().map_or_else(|| spec.to_string(), |s| s.to_string_lossy().into_owned());
    let m = Motion::from_amass_npz(&bytes, &name).with_context(|| format!("motion file {}", path.display()))?;
    for note in &m.notes {
        eprintln!("{}: {note}", path.display());
    }
    Ok(m)
}

pub fn export(a: &ExportArgs) -> Result<()> {
    let t0 = std::time::Instant::now();
    if a.texture_res != 0 && !(64..=4096).contains(&a.texture_res) {
        bail!("--texture-res {} (64…4096, or 0 for vertex colours)", a.texture_res);
    }
    let model = load_body(&a.body)?;
    if a.r#static && a.frames_json.is_some() {
        bail!("--frames-json needs a skinned export (not --static)");
    }
    let device = a.backend.device()?;
    // An inverted avatar: its generator, codes, and the photo it was made from.
    let inverted = match &a.inverted {
        Some(p) => {
            let (cfg, inv) = load_inverted_file(p, &a.model.config()?, &device)?;
            Some((inv, cfg))
        }
        None => None,
    };
    let photo = inverted.as_ref().and_then(|(inv, _)| inv.photo.clone());
    let params = export_params(a, &model, photo.as_ref())?;
    let motions = a.motions.iter().map(|m| load_motion(m)).collect::<Result<Vec<_>>>()?;
    if a.format == Format::Vrma {
        return export_vrma(a, &model, &params, &motions);
    }
    let vrm = vrm_meta(a, &motions)?;
    let stem = a.out.file_stem().map_or_else(|| "avatar".into(), |s| s.to_string_lossy().into_owned());
    let job = Job { a, params: &params, motions: &motions, vrm: vrm.as_ref(), stem };
    let Exported { glb, what, expected } = if a.body_only {
        export_body(&job, &model)?
    } else {
        export_avatar(&job, model, inverted, photo.as_ref(), &device)?
    };
    crate::atomic::write_atomic(&a.out, &glb)?;
    if let (Some(path), Some(json)) = (&a.frames_json, expected) {
        crate::atomic::write_atomic(path, json.to_string().as_bytes())?;
    }
    let clips: Vec<String> =
        motions.iter().map(|m| format!("{} ({} frames, {:.1} s)", m.name, m.len(), m.duration())).collect();
    println!(
        "wrote {} ({:.1} MB): {what}; {}; {:.2} s",
        a.out.display(),
        glb.len() as f64 / 1e6,
        if a.r#static {
            "no skin".to_string()
        } else if vrm.is_some() {
            format!("rest T-pose, soles at y = 0, {:?} node names", a.skeleton)
        } else if clips.is_empty() {
            "skinned, no animations".into()
        } else {
            format!("skinned, animations: {}", clips.join(", "))
        },
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}

/// The pose and shape shown: `--fit`'s, the photo's, or a named pose (with the photo's shape).
fn export_params(a: &ExportArgs, model: &BodyModel, photo: Option<&SourcePhoto>) -> Result<BodyParams> {
    Ok(match (&a.fit, &a.pose, photo) {
        (Some(f), _, _) => {
            let text = std::fs::read_to_string(f).with_context(|| format!("reading {}", f.display()))?;
            let fit = BodyFit::from_json(&text)
                .map_err(|e| anyhow::anyhow!("{} is not a usable fit.json: {e}", f.display()))?;
            let mut p = fit.body_params();
            p.betas.truncate(model.num_betas);
            p
        }
        // The photo's pose and shape.
        (None, None, Some(photo)) => photo.view.body.clone(),
        (None, pose, _) => {
            let pose = pose.as_deref().unwrap_or("standing");
            let lib = PoseLibrary::builtin();
            let mut p = lib.params(pose, &[]).with_context(|| {
                format!("unknown pose `{pose}`; available: {}", lib.names().collect::<Vec<_>>().join(", "))
            })?;
            // An inverted avatar keeps the body shape of its photo.
            if let Some(photo) = &photo {
                p.betas = photo.view.body.betas.clone();
            }
            p
        }
    })
}

/// With `--format vrm`, the avatar's VRM meta (refusing what a .vrm cannot hold).
fn vrm_meta(a: &ExportArgs, motions: &[Motion]) -> Result<Option<VrmMeta>> {
    Ok(match a.format {
        Format::Vrma | Format::Glb => None,
        Format::Vrm if !motions.is_empty() => {
            bail!("a .vrm holds no animations (VRM keeps them in .vrma files): export the motions with --format vrma")
        }
        Format::Vrm if a.r#static || a.pose.is_some() => {
            bail!("a .vrm shows its rest T-pose: --static and --pose do not apply (--fit gives the body shape)")
        }
        Format::Vrm => {
            let origin = if a.body_only {
                AvatarOrigin::Body
            } else if a.inverted.is_some() {
                AvatarOrigin::Photo
            } else {
                AvatarOrigin::Generated
            };
            let name = a.out.file_stem().map_or_else(|| "avatar".into(), |s| s.to_string_lossy().into_owned());
            Some(VrmMeta { name, origin })
        }
    })
}

/// One export's settings, shared by the body's and the avatar's.
struct Job<'a> {
    a: &'a ExportArgs,
    params: &'a BodyParams,
    motions: &'a [Motion],
    vrm: Option<&'a VrmMeta>,
    stem: String,
}

/// The file's bytes, what it holds in words, and with `--frames-json` the expected figures.
struct Exported {
    glb: Vec<u8>,
    what: String,
    expected: Option<serde_json::Value>,
}

/// `--body-only`: the body as .vrm, static .glb or animated .glb.
fn export_body(job: &Job, model: &BodyModel) -> Result<Exported> {
    let Job { a, params, motions, vrm, stem } = job;
    let mut expected: Option<serde_json::Value> = None;
    let (glb, what) = if let Some(meta) = vrm {
        if a.frames_json.is_some() {
            expected = Some(vrm_rest_json(model, &params.betas, vrm_frame(model, &params.betas)?.offset));
        }
        (
            body_vrm(model, &params.betas, meta, a.skeleton)?,
            format!("the body as VRM 1.0, {} vertices", model.num_vertices()),
        )
    } else if a.r#static {
        let posed = pose_body(model, params);
        let mesh = ExportMesh {
            normals: vertex_normals(&posed.vertices, &model.faces),
            positions: posed.vertices,
            indices: model.faces.clone(),
            name: stem.clone(),
            ..Default::default()
        };
        (write_glb(&mesh)?, format!("the body, static, {} vertices", model.num_vertices()))
    } else {
        if a.frames_json.is_some() {
            expected = Some(frames_json(motions, |p| flat(&pose_body(model, p).vertices), "positions", &params.betas));
        }
        (
            animated_body_glb(model, params, motions, stem, a.skeleton)?,
            format!("the body, {} vertices", model.num_vertices()),
        )
    };
    Ok(Exported { glb, what, expected })
}

/// The generated or inverted avatar as .vrm, static .glb or animated .glb (and `--obj`).
fn export_avatar(
    job: &Job,
    model: BodyModel,
    inverted: Option<(InvertedAvatar, GeneratorConfig)>,
    photo: Option<&SourcePhoto>,
    device: &Device,
) -> Result<Exported> {
    let Job { a, params, motions, vrm, stem } = job;
    let mut expected: Option<serde_json::Value> = None;
    let (cfg, g, styles) = match inverted {
        Some((inv, cfg)) => (cfg, inv.generator, inv.styles),
        None => {
            let (cfg, g, modes) = a.model.load(device)?;
            if a.psi.is_some_and(|p| !p.is_finite()) {
                bail!("--psi must be a number");
            }
            let styles = seed_styles(&g, &cfg, &modes, a.seeds.pair(), a.psi, false, device);
            (cfg, g, styles)
        }
    };
    let ctx = crate::model_io::body_context(model, &cfg);
    let mut rigged = block_on_ready(generate_rigged_async(&g, &ctx, &styles, device))?;
    if rigged.canonical.mesh.faces.is_empty() {
        bail!("the generator produced an empty surface");
    }
    if let (Some(p), false) = (photo, a.no_projection) {
        snap_to_photo(&mut rigged, &ctx, p);
    }
    let n = rigged.canonical.mesh.vertices.len();
    let texture = bake_texture(a, &rigged, &g, &styles, &ctx, photo, device)?;
    if a.obj {
        let (positions, normals) = rigged.repose(&ctx, &pose_body(&ctx.model, params));
        write_obj_files(&a.out, &positions, &normals, &rigged, texture.as_ref())?;
    }
    let order: Vec<u32> = match &texture {
        Some(t) => t.atlas.source.clone(),
        None => (0..n as u32).collect(),
    };
    let (glb, what) = if let Some(meta) = vrm {
        if a.frames_json.is_some() {
            let offset = rigged.vrm_frame(&ctx, &params.betas)?.offset;
            expected = Some(vrm_rest_json(&ctx.model, &params.betas, offset));
        }
        (
            rigged.vrm(&ctx, &params.betas, texture.as_ref(), meta, a.skeleton)?,
            format!("{} as VRM 1.0, {n} vertices", what_avatar(a)),
        )
    } else if a.r#static {
        (rigged.posed_glb(&ctx, params, texture.as_ref(), stem)?, format!("{}, static, {n} vertices", what_avatar(a)))
    } else {
        if a.frames_json.is_some() {
            let at = |p: &BodyParams| {
                let v = rigged.repose(&ctx, &pose_body(&ctx.model, p)).0;
                flat(&order.iter().map(|i| v[*i as usize]).collect::<Vec<_>>())
            };
            expected = Some(frames_json(motions, at, "positions", &params.betas));
        }
        (
            rigged.animated_glb(&ctx, params, motions, texture.as_ref(), stem, a.skeleton)?,
            format!("{}, {n} vertices", what_avatar(a)),
        )
    };
    Ok(Exported { glb, what, expected })
}

/// The avatar's texture baked at `--texture-res` (None: 0, vertex colours), with the photo's
/// colours projected where it has one (unless `--no-projection`).
fn bake_texture(
    a: &ExportArgs,
    rigged: &RiggedAvatar,
    g: &Generator,
    styles: &Styles,
    ctx: &BodyContext,
    photo: Option<&SourcePhoto>,
    device: &Device,
) -> Result<Option<BakedTexture>> {
    let n = rigged.canonical.mesh.vertices.len();
    let tb = std::time::Instant::now();
    let texture = if a.texture_res > 0 {
        let planes = g.triplanes(styles);
        let projection = match (&photo, a.no_projection) {
            (Some(p), false) => Some((rigged.photo_projection(ctx, p), &p.view.body)),
            _ => None,
        };
        let bake = rigged.bake_texture_photo_async(
            g,
            &planes,
            styles,
            ctx,
            a.texture_res,
            projection.as_ref().map(|(p, b)| (p, *b)),
            device,
        );
        let t = block_on_ready(bake).context("baking the texture")?;
        if projection.is_some() {
            eprintln!("the photo's colours projected onto the texture (--no-projection leaves them off)");
        }
        eprintln!(
            "texture {r}²: {} atlas vertices ({} avatar vertices), triangles {} on the body's layout, {} across its seams, {} in their own charts; {:.0} % of the texels covered; {:.2} s",
            t.atlas.source.len(),
            n,
            t.atlas.body_faces,
            t.atlas.seam_faces,
            t.atlas.own_chart_faces,
            100.0 * t.covered as f64 / (t.res * t.res) as f64,
            tb.elapsed().as_secs_f64(),
            r = t.res
        );
        Some(t)
    } else {
        None
    };
    Ok(texture)
}

/// OBJ + MTL + PNG beside `out` (same stem): the avatar in the pose shown, with the baked
/// texture (OBJ's v points up: v = 1 − glTF's v), or without UVs when there is none.
fn write_obj_files(
    out: &std::path::Path,
    positions: &[glam::Vec3],
    normals: &[glam::Vec3],
    rigged: &getavatar_core::generator::rigging::RiggedAvatar,
    texture: Option<&getavatar_core::generator::rigging::BakedTexture>,
) -> Result<()> {
    use getavatar_core::io::scan::{write_mtl, write_obj, Corner, ObjFace, ObjMesh};
    let stem = out.file_stem().map_or_else(|| "avatar".into(), |s| s.to_string_lossy().into_owned());
    let dir = out.parent().unwrap_or(std::path::Path::new("."));
    let (source, uvs, faces): (Vec<u32>, Vec<glam::Vec2>, Vec<[u32; 3]>) = match texture {
        Some(t) => (
            t.atlas.source.clone(),
            t.atlas.uvs.iter().map(|u| glam::Vec2::new(u.x, 1.0 - u.y)).collect(),
            t.atlas.faces.clone(),
        ),
        None => ((0..positions.len() as u32).collect(), Vec::new(), rigged.canonical.mesh.faces.clone()),
    };
    let mut m = ObjMesh {
        positions: source.iter().map(|v| positions[*v as usize]).collect(),
        normals: source.iter().map(|v| normals[*v as usize]).collect(),
        uvs,
        materials: vec!["avatar".into()],
        groups: vec!["avatar".into()],
        ..Default::default()
    };
    let textured = texture.is_some();
    m.faces = faces
        .iter()
        .map(|f| ObjFace {
            corners: f.map(|v| Corner { v, vt: textured.then_some(v), vn: Some(v) }),
            material: 0,
            group: 0,
        })
        .collect();
    if let Some(t) = texture {
        m.mtllibs = vec![format!("{stem}.mtl")];
        crate::atomic::write_atomic(&dir.join(format!("{stem}.png")), &t.png)?;
        crate::atomic::write_atomic(
            &dir.join(format!("{stem}.mtl")),
            write_mtl("avatar", &format!("{stem}.png")).as_bytes(),
        )?;
    }
    crate::atomic::write_atomic(&dir.join(format!("{stem}.obj")), write_obj(&m).as_bytes())?;
    eprintln!("wrote {}/{stem}.obj{}", dir.display(), if textured { " + .mtl + .png" } else { "" });
    Ok(())
}

#[derive(clap::Args, Debug)]
pub struct BenchExportArgs {
    #[command(flatten)]
    pub backend: crate::backend::BackendArg,
    /// Generator configs to time (demo uses the shipped model; others random weights).
    #[arg(long, default_value = "demo", value_delimiter = ',')]
    pub configs: Vec<String>,
    /// Texture sides to bake.
    #[arg(long, default_value = "1024,2048", value_delimiter = ',')]
    pub texture_res: Vec<usize>,
    #[arg(long, default_value_t = 1)]
    pub seed_geo: u64,
    #[arg(long, default_value_t = 3)]
    pub seed_tex: u64,
}

/// `bench export`: the export's stages timed one by one (atlas, texel points, texture-field
/// queries, image + dilation, PNG, glTF writing) and the file sizes, per config and texture
/// side, on `--backend`.
pub fn bench_export(a: &BenchExportArgs) -> Result<()> {
    use getavatar_core::export::uv_atlas::{bake_image, texel_points};
    use getavatar_core::generator::pipeline::recolor_async;
    use getavatar_core::generator::rigging::encode_rgb_png;
    let device = a.backend.device()?;
    let walk = Motion::builtin("walk")?;
    let params = PoseLibrary::builtin().params("standing", &[])?;
    println!("| config | texture | vertices (atlas) | atlas s | texels s | field queries s | image s | PNG s | glb write s | total s | animated .glb MB |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    for config in &a.configs {
        let gen = GeneratorArgs { config: config.clone(), checkpoint: None, random: config != "demo", tet_res: None };
        let (cfg, g, modes) = gen.load(&device)?;
        let ctx = BodyContext::new(BodyModel::default_body()?, &cfg);
        let styles = seed_styles(&g, &cfg, &modes, (a.seed_geo, a.seed_tex), None, false, &device);
        let rigged = block_on_ready(generate_rigged_async(&g, &ctx, &styles, &device))?;
        let planes = g.triplanes(&styles);
        for &res in &a.texture_res {
            let t = std::time::Instant::now();
            let atlas = rigged.atlas(&ctx)?;
            let t_atlas = t.elapsed().as_secs_f64();
            let t = std::time::Instant::now();
            let canon: Vec<glam::Vec3> =
                atlas.source.iter().map(|v| rigged.canonical.mesh.attributes[*v as usize]).collect();
            let (texels, points) = texel_points(&atlas, &canon, res);
            let t_texels = t.elapsed().as_secs_f64();
            let t = std::time::Instant::now();
            let mut colors = Vec::with_capacity(points.len());
            for chunk in points.chunks(65_536) {
                colors.extend(block_on_ready(recolor_async(&g, &planes, &styles, chunk, &device))?);
            }
            let t_query = t.elapsed().as_secs_f64();
            let t = std::time::Instant::now();
            let rgb = bake_image(res, &texels, &colors);
            let t_image = t.elapsed().as_secs_f64();
            let t = std::time::Instant::now();
            let png = encode_rgb_png(&rgb, res, res).map_err(anyhow::Error::msg)?;
            let t_png = t.elapsed().as_secs_f64();
            let baked =
                getavatar_core::generator::rigging::BakedTexture { atlas, res, rgb, png, covered: texels.len() };
            let t = std::time::Instant::now();
            let glb = rigged.animated_glb(
                &ctx,
                &params,
                std::slice::from_ref(&walk),
                Some(&baked),
                "bench",
                SkeletonNames::Smpl,
            )?;
            let t_write = t.elapsed().as_secs_f64();
            let total = t_atlas + t_texels + t_query + t_image + t_png + t_write;
            println!(
                "| {config} | {res}² | {} ({}) | {t_atlas:.2} | {t_texels:.2} | {t_query:.2} | {t_image:.2} | {t_png:.2} | {t_write:.3} | {total:.2} | {:.2} |",
                rigged.canonical.mesh.vertices.len(),
                baked.atlas.source.len(),
                glb.len() as f64 / 1e6
            );
        }
    }
    Ok(())
}
