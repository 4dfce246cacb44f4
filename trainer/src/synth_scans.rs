//! `trainer synth-scans`: procedural textured, clothed human scans on the open body model, so
//! the project has data it can make itself (THUman2.0 / RenderPeople cannot be downloaded).
//!
//! A scan = the posed body plus garment layers with real geometry: each garment is an
//! offset surface of a body region (shirt / jacket / tank top, trousers / shorts, hair,
//! shoes) subdivided once and displaced outwards by its thickness plus folds and wrinkles
//! (periodic folds along limbs, bunching at elbows and knees, drape noise on the torso), or
//! a flared tube (skirt / dress) with vertical folds. Everything is built in the rest pose
//! and posed by linear blend skinning with the body's weights, so garments follow the pose.
//! Colours are baked into one texture atlas through UVs (the body's UV layout, one atlas
//! tile per layer): skin tones with eyes, brows and lips, and fabrics with stripes, checks,
//! dots, denim or solid colour, evaluated on the 3D rest surface so patterns run continuously
//! across UV seams.
//!
//! Output per scan, exactly as a scan dataset user has it: `<id>/mesh.obj`,
//! `<id>/material.mtl`, `<id>/texture.png`, `<id>/outfit.json` (the garments drawn: upper,
//! lower, hair; the labels a garment-aware experiment selects by), `<id>/smpl.json` (written
//! last; a folder with it is complete and skipped on re-runs). Deterministic for a given `--seed` and id, whatever
//! `--threads` is.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use rayon::prelude::*;

use anyhow::{bail, Context, Result};
use getavatar_core::body::body_model::{BodyModel, NUM_JOINTS};
use getavatar_core::body::pose_library::PoseLibrary;
use getavatar_core::body::skinning::{blend_transform, forward_kinematics, vertex_normals, BodyParams};
use getavatar_core::export::uv_atlas;
use getavatar_core::io::dataset::encode_png;
use getavatar_core::io::scan::{write_mtl, write_obj, Corner, ObjFace, ObjMesh, SmplParams};
use getavatar_core::util::rng::{hash_str, Rng};
use glam::{Vec2, Vec3};

/// Poses drawn for scans (from the built-in library), with random variation added.
pub const SCAN_POSES: [&str; 6] = ["standing", "walking", "sitting", "one_leg", "arms_up", "A"];
/// Betas written per scan (the dataset label's count); further components stay zero.
const SCAN_BETAS: usize = 10;

pub struct SynthArgs {
    pub out: PathBuf,
    pub count: usize,
    pub seed: u64,
    pub threads: usize,
    pub texture_size: usize,
    /// Every scan in this pose (θ of a library pose or of `body_fit::synthetic`'s unseen
    /// test poses) instead of a drawn library pose.
    pub pose: Option<String>,
}

/// θ of a pose by name: a library pose or one of the body fit's unseen test poses.
pub fn named_pose(name: &str) -> Result<[Vec3; NUM_JOINTS]> {
    if let Some((_, p)) =
        getavatar_core::body::body_fit::synthetic::unseen_poses().into_iter().find(|(n, _)| *n == name)
    {
        return Ok(p.pose);
    }
    let lib = PoseLibrary::builtin();
    lib.pose(name).map_err(|e| {
        let unseen: Vec<&str> =
            getavatar_core::body::body_fit::synthetic::unseen_poses().iter().map(|(n, _)| *n).collect();
        anyhow::anyhow!("--pose: {e}; the unseen test poses are {}", unseen.join(", "))
    })
}

pub fn synth_scans(a: &SynthArgs) -> Result<()> {
    if a.count == 0 {
        bail!("--count must be at least 1");
    }
    if !(64..=8192).contains(&a.texture_size) || !a.texture_size.is_power_of_two() {
        bail!("--texture-size must be a power of two in 64..=8192 (got {})", a.texture_size);
    }
    let pose = a.pose.as_deref().map(named_pose).transpose()?;
    let model = BodyModel::default_body()?;
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let bar = crate::progress::bar(a.count as u64, "scans");
    let skipped = AtomicUsize::new(0);
    let t0 = std::time::Instant::now();
    let pool = rayon::ThreadPoolBuilder::new().num_threads(a.threads.max(1)).build()?;
    let errors: Vec<String> = pool.install(|| {
        (0..a.count)
            .into_par_iter()
            .filter_map(|i| {
                let id = format!("{i:04}");
                let dir = a.out.join(&id);
                let result = if dir.join("smpl.json").is_file() {
                    skipped.fetch_add(1, Ordering::Relaxed);
                    Ok(())
                } else {
                    write_scan(&model, a.seed, &id, a.texture_size, pose.as_ref(), &dir)
                };
                bar.inc(1);
                result.err().map(|e| format!("{id}: {e:#}"))
            })
            .collect()
    });
    bar.finish_and_clear();
    let made = a.count - errors.len() - skipped.load(Ordering::Relaxed);
    let dt = t0.elapsed().as_secs_f64();
    println!(
        "wrote {made} scans to {} ({} already there), {:.2} s, {:.2} scans/s",
        a.out.display(),
        skipped.load(Ordering::Relaxed),
        dt,
        made as f64 / dt.max(1e-9)
    );
    if !errors.is_empty() {
        bail!("{} scans failed:\n{}", errors.len(), errors.join("\n"));
    }
    Ok(())
}

/// Build scan `id` and write its four files (smpl.json last, each via a temporary name).
fn write_scan(
    model: &BodyModel,
    seed: u64,
    id: &str,
    texture_size: usize,
    pose: Option<&[Vec3; NUM_JOINTS]>,
    dir: &Path,
) -> Result<()> {
    let scan = make_scan(model, seed, id, texture_size, pose)?;
    std::fs::create_dir_all(dir)?;
    let put = |name: &str, bytes: &[u8]| -> Result<()> { crate::atomic::write_atomic(&dir.join(name), bytes) };
    put("mesh.obj", write_obj(&scan.mesh).as_bytes())?;
    put("material.mtl", write_mtl("material0", "texture.png").as_bytes())?;
    put("texture.png", &encode_png(scan.texture_size, scan.texture_size, 3, &scan.texture)?)?;
    put("outfit.json", serde_json::to_string_pretty(&scan.outfit)?.as_bytes())?;
    put("smpl.json", scan.smpl.to_json()?.as_bytes())?;
    Ok(())
}

/// A generated scan in memory.
pub struct SynthScan {
    pub mesh: ObjMesh,
    /// sRGB RGB texels, `texture_size²·3`, row 0 at the top.
    pub texture: Vec<u8>,
    pub texture_size: usize,
    pub smpl: SmplParams,
    pub outfit: Outfit,
}

/// The garments a scan was drawn with (`outfit.json`).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Outfit {
    upper: Upper,
    lower: Lower,
    hair: Hair,
}

// ---------------------------------------------------------------------------------------
// Outfits and fabrics

#[derive(Clone, Copy, Debug, PartialEq)]
enum Pattern {
    Solid,
    Stripes,
    Checks,
    Dots,
    Denim,
}

#[derive(Clone, Copy, Debug)]
struct Fabric {
    base: Vec3,
    accent: Vec3,
    pattern: Pattern,
    /// Pattern period, metres.
    period: f32,
    phase: f32,
}

const SKIN: [[u8; 3]; 6] =
    [[255, 219, 182], [241, 194, 150], [224, 172, 125], [198, 134, 86], [141, 85, 46], [92, 58, 40]];
const HAIR: [[u8; 3]; 6] = [[28, 24, 22], [58, 38, 28], [102, 70, 44], [196, 164, 108], [138, 62, 32], [150, 150, 150]];
const CLOTH: [[u8; 3]; 16] = [
    [32, 42, 82],
    [236, 236, 230],
    [30, 30, 32],
    [172, 32, 42],
    [42, 102, 62],
    [212, 170, 52],
    [128, 128, 130],
    [122, 172, 222],
    [202, 182, 150],
    [112, 30, 52],
    [62, 82, 122],
    [232, 152, 172],
    [112, 112, 62],
    [222, 112, 42],
    [92, 62, 142],
    [60, 150, 150],
];

fn srgb(c: [u8; 3]) -> Vec3 {
    Vec3::new(c[0] as f32, c[1] as f32, c[2] as f32) / 255.0
}

fn pick<T: Copy>(rng: &mut Rng, xs: &[T]) -> T {
    xs[rng.below(xs.len())]
}

fn random_fabric(rng: &mut Rng, allow_denim: bool) -> Fabric {
    let base = srgb(pick(rng, &CLOTH));
    let mut accent = srgb(pick(rng, &CLOTH));
    if (accent - base).length() < 0.3 {
        accent = Vec3::ONE - base * 0.8;
    }
    let patterns: &[Pattern] = if allow_denim {
        &[Pattern::Solid, Pattern::Solid, Pattern::Denim, Pattern::Denim, Pattern::Checks, Pattern::Stripes]
    } else {
        &[Pattern::Solid, Pattern::Solid, Pattern::Stripes, Pattern::Stripes, Pattern::Checks, Pattern::Dots]
    };
    let pattern = pick(rng, patterns);
    let base =
        if pattern == Pattern::Denim { srgb(pick(rng, &[[52, 72, 118], [38, 50, 84], [92, 120, 160]])) } else { base };
    Fabric { base, accent, pattern, period: rng.range(0.025, 0.09), phase: rng.range(0.0, 1.0) }
}

/// Value noise in [−1, 1] on a unit lattice, smooth (C¹) trilinear interpolation.
fn noise(p: Vec3) -> f32 {
    let i = p.floor();
    let f = p - i;
    let s = f * f * (Vec3::splat(3.0) - 2.0 * f);
    let h = |dx: f32, dy: f32, dz: f32| {
        let (x, y, z) = ((i.x + dx) as i32, (i.y + dy) as i32, (i.z + dz) as i32);
        let mut n = (x as u32).wrapping_mul(0x8da6b343)
            ^ (y as u32).wrapping_mul(0xd8163841)
            ^ (z as u32).wrapping_mul(0xcb1ab31f);
        n ^= n >> 13;
        n = n.wrapping_mul(0x5bd1e995);
        n ^= n >> 15;
        (n & 0xffff) as f32 / 32767.5 - 1.0
    };
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let x00 = lerp(h(0., 0., 0.), h(1., 0., 0.), s.x);
    let x10 = lerp(h(0., 1., 0.), h(1., 1., 0.), s.x);
    let x01 = lerp(h(0., 0., 1.), h(1., 0., 1.), s.x);
    let x11 = lerp(h(0., 1., 1.), h(1., 1., 1.), s.x);
    lerp(lerp(x00, x10, s.y), lerp(x01, x11, s.y), s.z)
}

fn fabric_color(f: &Fabric, p: Vec3) -> Vec3 {
    let tau = std::f32::consts::TAU;
    let soft = |x: f32| (x * 6.0).clamp(-1.0, 1.0) * 0.5 + 0.5; // antialiased square wave
    let c = match f.pattern {
        Pattern::Solid => f.base,
        Pattern::Stripes => f.base.lerp(f.accent, soft((tau * (p.y / f.period + f.phase)).sin())),
        Pattern::Checks => {
            let a = soft((tau * (p.y / f.period + f.phase)).sin());
            let b = soft((tau * ((p.x + 0.7 * p.z) / f.period)).sin());
            f.base.lerp(f.accent, 0.5 * (a + b))
        }
        Pattern::Dots => {
            let q = p / (f.period * 0.8) + Vec3::splat(f.phase);
            let d = (q - q.round()).length();
            f.base.lerp(f.accent, ((0.3 - d) * 20.0).clamp(0.0, 1.0))
        }
        Pattern::Denim => {
            let twill = (tau * (p.y + p.x + p.z) / 0.004).sin() * 0.04;
            f.base * (1.0 + twill + 0.12 * noise(p * 60.0))
        }
    };
    // Weave and soiling: small multiplicative noise.
    (c * (1.0 + 0.05 * noise(p * 150.0) + 0.04 * noise(p * 9.0))).clamp(Vec3::ZERO, Vec3::ONE)
}

#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
enum Upper {
    TShirt,
    LongSleeve,
    Tank,
    Jacket,
}

#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
enum Lower {
    Trousers,
    Shorts,
    Skirt,
    Dress,
}

#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
enum Hair {
    Short,
    Long,
    Bald,
}

/// Body landmarks in the rest pose (after shape), metres.
struct Landmarks {
    joints: [Vec3; NUM_JOINTS],
    head_top: f32,
    nose: Vec3,
    /// Hip half-width and half-depth at the widest hip section.
    hip_radii: Vec2,
}

fn landmarks(model: &BodyModel, rest: &[Vec3]) -> Landmarks {
    let joints = model.regress_joints(rest);
    let head: Vec<Vec3> = rest.iter().zip(&model.weights).filter(|(_, w)| w[15] > 0.5).map(|(v, _)| *v).collect();
    let head_top = head.iter().map(|v| v.y).fold(f32::NEG_INFINITY, f32::max);
    let nose = head.iter().copied().fold(Vec3::splat(-9.0), |a, v| if v.z > a.z { v } else { a });
    let hy = joints[1].y;
    let mut r = Vec2::ZERO;
    for (v, w) in rest.iter().zip(&model.weights) {
        let arm: f32 = [16, 17, 18, 19, 20, 21, 22, 23].iter().map(|&j| w[j]).sum();
        if arm < 0.1 && (v.y - hy).abs() < 0.06 {
            r = r.max(Vec2::new(v.x.abs(), (v.z - joints[0].z).abs()));
        }
    }
    Landmarks { joints, head_top, nose, hip_radii: r }
}

// ---------------------------------------------------------------------------------------
// Geometry: layers in the rest pose

/// A surface layer in the rest pose with per-vertex skin weights and atlas UVs.
#[derive(Default)]
struct Layer {
    rest: Vec<Vec3>,
    weights: Vec<[f32; NUM_JOINTS]>,
    /// UV within the layer's atlas tile, [0, 1]².
    uv: Vec<Vec2>,
    faces: Vec<[u32; 3]>,
    /// Rest position on the underlying surface (before the offset): where patterns are evaluated.
    surface: Vec<Vec3>,
    tile: usize,
}

/// Faces of the body (with their UV corners) whose three vertices satisfy `keep`, as a layer
/// keyed on (vertex, uv) pairs; `surface` holds the body position, `rest` is filled later.
fn body_region(model: &BodyModel, rest: &[Vec3], keep: &dyn Fn(usize) -> bool, tile: usize) -> Layer {
    let mut layer = Layer { tile, ..Layer::default() };
    let mut map: HashMap<(u32, u32), u32> = HashMap::new();
    let has_uv = model.ft.len() == model.faces.len();
    for (fi, f) in model.faces.iter().enumerate() {
        if !f.iter().all(|&v| keep(v as usize)) {
            continue;
        }
        let ft = if has_uv { model.ft[fi] } else { *f };
        let mut tri = [0u32; 3];
        for k in 0..3 {
            let key = (f[k], ft[k]);
            tri[k] = *map.entry(key).or_insert_with(|| {
                let v = f[k] as usize;
                layer.surface.push(rest[v]);
                layer.weights.push(model.weights[v]);
                layer.uv.push(if has_uv { model.vt[ft[k] as usize] } else { Vec2::ZERO });
                (layer.surface.len() - 1) as u32
            });
        }
        layer.faces.push(tri);
    }
    layer
}

/// One 1→4 midpoint subdivision (positions, weights and UVs interpolated).
fn subdivide(l: &Layer) -> Layer {
    let mut out = Layer {
        surface: l.surface.clone(),
        weights: l.weights.clone(),
        uv: l.uv.clone(),
        tile: l.tile,
        ..Layer::default()
    };
    let mut mid: HashMap<(u32, u32), u32> = HashMap::new();
    let mut midpoint = |a: u32, b: u32, out: &mut Layer| -> u32 {
        let key = (a.min(b), a.max(b));
        *mid.entry(key).or_insert_with(|| {
            let (a, b) = (a as usize, b as usize);
            out.surface.push((out.surface[a] + out.surface[b]) * 0.5);
            let mut w = [0.0; NUM_JOINTS];
            for (j, wj) in w.iter_mut().enumerate() {
                *wj = 0.5 * (out.weights[a][j] + out.weights[b][j]);
            }
            out.weights.push(w);
            out.uv.push((out.uv[a] + out.uv[b]) * 0.5);
            (out.surface.len() - 1) as u32
        })
    };
    for &[a, b, c] in &l.faces {
        let ab = midpoint(a, b, &mut out);
        let bc = midpoint(b, c, &mut out);
        let ca = midpoint(c, a, &mut out);
        out.faces.extend([[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]);
    }
    out
}

/// Displace a layer's surface along its normals by `offset(surface point, normal)`.
fn inflate(mut l: Layer, offset: &dyn Fn(Vec3, Vec3) -> f32) -> Layer {
    let normals = vertex_normals(&l.surface, &l.faces);
    // Seam copies (same position, different UV) must move identically: average their normals.
    let mut by_pos: HashMap<[u32; 3], Vec3> = HashMap::new();
    for (p, n) in l.surface.iter().zip(&normals) {
        *by_pos.entry(p.to_array().map(f32::to_bits)).or_default() += *n;
    }
    l.rest = l
        .surface
        .iter()
        .map(|p| {
            let n = by_pos[&p.to_array().map(f32::to_bits)].normalize_or_zero();
            *p + n * offset(*p, n)
        })
        .collect();
    l
}

fn smoothstep(e0: f32, e1: f32, x: f32) -> f32 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Folds of a garment: periodic ridges across a limb (`along` = position along it, metres)
/// with irregular phase, stronger near a bending joint, plus low-frequency drape noise.
fn folds(p: Vec3, along: f32, amp: f32, wavelength: f32, joint_boost: f32) -> f32 {
    let tau = std::f32::consts::TAU;
    let warp = 1.5 * noise(p * 12.0);
    let ridge = 0.5 + 0.5 * (tau * along / wavelength + warp).sin();
    let drape = 0.5 + 0.5 * noise(p * 25.0 + Vec3::splat(7.0));
    amp * (ridge * (0.6 + joint_boost) + 0.4 * drape)
}

/// A flared tube (skirt) from `y_top` down to `y_bottom` around the hips, rest pose.
fn skirt(lm: &Landmarks, y_top: f32, y_bottom: f32, flare: f32, rng: &mut Rng, tile: usize) -> Layer {
    let (na, nh) = (96usize, 28usize);
    let mut l = Layer { tile, ..Layer::default() };
    let folds_n = 7 + rng.below(6);
    let phase = rng.range(0.0, std::f32::consts::TAU);
    let c = Vec3::new(0.0, 0.0, lm.joints[0].z + 0.01);
    let r0 = lm.hip_radii + Vec2::splat(0.02);
    for i in 0..=nh {
        let t = i as f32 / nh as f32;
        let y = y_top + (y_bottom - y_top) * t;
        // Waist → hips (wider) → flare at the hem.
        let hips = smoothstep(0.0, 0.25, t);
        let scale = 0.92 + 0.08 * hips + flare * t * t;
        for k in 0..=na {
            let phi = k as f32 / na as f32 * std::f32::consts::TAU;
            let fold = 1.0
                + 0.07 * t * (folds_n as f32 * phi + phase).sin()
                + 0.02 * noise(Vec3::new(phi * 3.0, y * 10.0, 0.0));
            let (s, co) = phi.sin_cos();
            let p = c + Vec3::new(s * r0.x * scale * fold, y, co * r0.y * scale * fold);
            l.rest.push(p);
            l.surface.push(p);
            // Skin: the pelvis at the waist, blending to the thigh on each side at the hem.
            let mut w = [0.0; NUM_JOINTS];
            let side = (s * 1.5).clamp(-1.0, 1.0) * 0.5 + 0.5; // 1 = left (+x)
            let down = smoothstep(0.1, 1.0, t) * 0.8;
            w[0] = 1.0 - down;
            w[1] = down * side;
            w[2] = down * (1.0 - side);
            l.weights.push(w);
            l.uv.push(Vec2::new(k as f32 / na as f32, 1.0 - t));
        }
    }
    let row = na as u32 + 1;
    for i in 0..nh as u32 {
        for k in 0..na as u32 {
            let (a, b, c2, d) = (i * row + k, i * row + k + 1, (i + 1) * row + k, (i + 1) * row + k + 1);
            // Outward (CCW seen from outside): phi increases towards +x from +z.
            l.faces.push([a, c2, b]);
            l.faces.push([b, c2, d]);
        }
    }
    l
}

// ---------------------------------------------------------------------------------------
// The scan

/// A scan's body: β (adults, heights ≈ 1.5–1.95 m) and a library pose with variation, drawn
/// from `rng` (the `encoder` training data draws its bodies the same way).
pub fn draw_body(model: &BodyModel, rng: &mut Rng) -> Result<BodyParams> {
    // Shape: 10 components; age is kept adult (β_age ≥ −0.3).
    // Components of the open body: 0 gender, 1 weight, 2 muscle, 3 height, 4 proportions,
    // 5 age, 6 hip width, 7 shoulder width, 8 leg length, 9 torso length. The length
    // components combine multiplicatively, so they vary less (heights stay ≈ 1.5–1.95 m).
    let mut betas: Vec<f32> = (0..SCAN_BETAS.min(model.num_betas))
        .map(|k| {
            let (sigma, lim) = if matches!(k, 3 | 8 | 9) { (0.2, 0.45) } else { (0.4, 1.0) };
            (rng.normal() * sigma).clamp(-lim, lim)
        })
        .collect();
    if betas.len() > 5 {
        betas[5] = betas[5].max(-0.3); // adults
    }
    // Pose: a library pose plus variation.
    let lib = PoseLibrary::builtin();
    let pose_name = pick(rng, &SCAN_POSES);
    let mut params: BodyParams = lib.params(pose_name, &betas)?;
    for (k, r) in params.pose.iter_mut().enumerate().skip(1) {
        let sigma = match k {
            16..=19 => 0.12, // shoulders, elbows
            22 | 23 => 0.0,
            _ => 0.05,
        };
        *r += Vec3::new(rng.normal(), rng.normal(), rng.normal()) * sigma;
    }
    if pose_name == "arms_up" {
        // Raised, but not straight up: keep the hands inside the generator's box (y ≤ 0.96 m).
        let k = rng.range(0.45, 0.75);
        params.pose[16] *= k;
        params.pose[17] *= k;
    }
    params.pose[0] = Vec3::new(rng.normal() * 0.03, rng.normal() * 0.25, rng.normal() * 0.03);

    Ok(params)
}

/// Build scan `id` of the dataset with `seed` (deterministic); in pose θ = `pose` when given,
/// else in a drawn library pose with variation.
pub fn make_scan(
    model: &BodyModel,
    seed: u64,
    id: &str,
    texture_size: usize,
    pose: Option<&[Vec3; NUM_JOINTS]>,
) -> Result<SynthScan> {
    let mut rng = Rng::new(seed, hash_str(id));
    let mut params = draw_body(model, &mut rng)?;
    let betas = params.betas.clone();
    let rest = model.shaped_vertices(&betas);
    let lm = landmarks(model, &rest);
    let j = lm.joints;

    if let Some(p) = pose {
        params.pose = *p;
    }

    // Outfit.
    let upper = pick(&mut rng, &[Upper::TShirt, Upper::TShirt, Upper::LongSleeve, Upper::Tank, Upper::Jacket]);
    let lower = pick(&mut rng, &[Lower::Trousers, Lower::Trousers, Lower::Shorts, Lower::Skirt, Lower::Dress]);
    let hair = pick(&mut rng, &[Hair::Short, Hair::Short, Hair::Long, Hair::Long, Hair::Bald]);
    let upper_fabric = random_fabric(&mut rng, false);
    let lower_fabric = if lower == Lower::Dress { upper_fabric } else { random_fabric(&mut rng, true) };
    let skin = srgb(pick(&mut rng, &SKIN)) * rng.range(0.95, 1.03);
    let hair_color = srgb(pick(&mut rng, &HAIR));
    let shoe_color = srgb(pick(&mut rng, &[[25, 25, 28], [235, 235, 235], [96, 60, 36], [160, 30, 40], [40, 60, 110]]));
    let sole_color = if rng.chance(0.5) { Vec3::splat(0.93) } else { Vec3::splat(0.12) };

    // Region coordinates in the rest (T) pose.
    let w = &model.weights;
    let wsum = |v: usize, js: &[usize]| js.iter().map(|&k| w[v][k]).sum::<f32>();
    const ARM: [usize; 8] = [16, 17, 18, 19, 20, 21, 22, 23];
    const LEG: [usize; 8] = [1, 2, 4, 5, 7, 8, 10, 11];
    let shoulder_x = j[16].x.abs();
    let arm_len = j[20].x.abs() - shoulder_x;
    let arm_t = |v: usize| (rest[v].x.abs() - shoulder_x) / arm_len; // 0 shoulder … 1 wrist
    let leg_len = j[1].y - j[7].y;
    let leg_t = |v: usize| (j[1].y - rest[v].y) / leg_len; // 0 hip … 1 ankle
    let is_arm = |v: usize| wsum(v, &ARM) > 0.5;
    let is_head = |v: usize| w[v][15] + w[v][12] > 0.5 && rest[v].y > j[12].y - 0.02;

    let sleeve = match upper {
        Upper::TShirt => rng.range(0.25, 0.4),
        Upper::LongSleeve | Upper::Jacket => rng.range(0.9, 0.97),
        Upper::Tank => -0.15,
    };
    let neck_y = j[12].y - rng.range(0.02, 0.06);
    let hem_y = j[0].y - rng.range(0.0, 0.1);
    let waist_y = j[0].y + rng.range(0.02, 0.08);
    let leg_end = match lower {
        Lower::Trousers => rng.range(0.9, 0.97),
        Lower::Shorts => rng.range(0.3, 0.5),
        _ => 0.0,
    };

    let shirt_keep = |v: usize| {
        let p = rest[v];
        if is_arm(v) {
            return arm_t(v) < sleeve;
        }
        if is_head(v) || wsum(v, &LEG) > 0.6 {
            return false;
        }
        // Neckline: lower in front.
        let neck = neck_y - if p.z > j[12].z { 0.04 } else { 0.0 };
        p.y < neck && p.y > hem_y
    };
    let trouser_keep = |v: usize| {
        let p = rest[v];
        !is_arm(v) && p.y < waist_y && (p.y >= j[1].y || leg_t(v) < leg_end)
    };
    let hair_keep = |v: usize| {
        let p = rest[v];
        let back = smoothstep(lm.nose.z - 0.1, lm.nose.z - 0.2, p.z); // 0 front … 1 back
        let hairline = lm.head_top - 0.075 - 0.09 * back;
        match hair {
            Hair::Bald => false,
            Hair::Short => is_head(v) && p.y > hairline,
            Hair::Long => {
                (is_head(v) && p.y > hairline)
                    || (!is_arm(v) && p.z < j[12].z - 0.02 && p.y > j[9].y && p.y < j[15].y && (p.x.abs() < 0.12))
            }
        }
    };
    let shoe_keep = |v: usize| rest[v].y < j[7].y + 0.035 && wsum(v, &LEG) > 0.5;

    let tile_skin = 0;
    let (tile_upper, tile_lower, tile_misc) = (1, 2, 3);
    let mut layers: Vec<(Layer, Paint)> = Vec::new();
    // The body itself: every face, no offset.
    let mut body = body_region(model, &rest, &|_| true, tile_skin);
    body.rest = body.surface.clone();
    layers.push((body, Paint::Skin));

    let wrinkle_amp = rng.range(0.002, 0.006);
    if lower != Lower::Skirt && lower != Lower::Dress {
        let l = subdivide(&body_region(model, &rest, &trouser_keep, tile_lower));
        let knee_y = j[4].y;
        let l = inflate(l, &|p, _| {
            let boost = (-((p.y - knee_y) / 0.08).powi(2)).exp();
            0.007 + folds(p, p.y, wrinkle_amp, 0.045, boost)
        });
        layers.push((l, Paint::Fabric(lower_fabric)));
    }
    {
        let thick = if upper == Upper::Jacket { 0.02 } else { 0.011 };
        let l = subdivide(&body_region(model, &rest, &shirt_keep, tile_upper));
        let elbow_x = j[18].x.abs();
        let l = inflate(l, &|p, _| {
            if p.x.abs() > shoulder_x {
                let boost = (-((p.x.abs() - elbow_x) / 0.06).powi(2)).exp();
                thick + folds(p, p.x.abs(), wrinkle_amp, 0.04, boost)
            } else {
                // Torso: diagonal drape folds, looser towards the hem.
                let loose = smoothstep(j[9].y, hem_y, p.y);
                thick + folds(p, p.y + 0.4 * p.x.abs(), wrinkle_amp * (0.5 + loose), 0.07, 0.0) + 0.01 * loose
            }
        });
        layers.push((l, Paint::Fabric(upper_fabric)));
    }
    if matches!(lower, Lower::Skirt | Lower::Dress) {
        let len = rng.range(0.35, 0.8);
        let bottom = j[1].y - len * leg_len;
        let top = if lower == Lower::Dress { hem_y + 0.05 } else { waist_y };
        layers.push((skirt(&lm, top, bottom, rng.range(0.1, 0.6), &mut rng, tile_lower), Paint::Fabric(lower_fabric)));
    }
    if hair != Hair::Bald {
        let l = subdivide(&body_region(model, &rest, &hair_keep, tile_misc));
        let volume = rng.range(0.008, 0.025);
        let l = inflate(l, &|p, _| {
            let strands = 0.5 + 0.5 * (std::f32::consts::TAU * (p.x * 90.0 + 3.0 * noise(p * 8.0))).sin();
            volume + 0.003 * strands + 0.006 * (0.5 + 0.5 * noise(p * 15.0))
        });
        layers.push((l, Paint::Hair(hair_color)));
    }
    {
        let l = subdivide(&body_region(model, &rest, &shoe_keep, tile_misc));
        let l = inflate(l, &|_, n| 0.008 + 0.015 * smoothstep(-0.5, -0.9, n.y));
        layers.push((l, Paint::Shoe { upper: shoe_color, sole: sole_color, sole_y: j[10].y - 0.03 }));
    }

    // Pose everything with the body's skinning transforms.
    let mut fk_params = params.clone();
    fk_params.transl = Vec3::ZERO;
    let kin = forward_kinematics(&model.parents, &j, &fk_params);
    let scale = rng.range(0.95, 1.05);
    let transl = Vec3::new(rng.normal() * 0.05, rng.normal() * 0.02, rng.normal() * 0.05);

    let tex = bake_texture(&layers, texture_size, &Face { lm: &lm, skin, brow: hair_color * 0.7 });
    let mut mesh = ObjMesh {
        materials: vec!["material0".into()],
        mtllibs: vec!["material.mtl".into()],
        groups: vec!["default".into()],
        ..ObjMesh::default()
    };
    for (l, _) in &layers {
        let base = mesh.positions.len() as u32;
        for ((p, wv), uv) in l.rest.iter().zip(&l.weights).zip(&l.uv) {
            let posed = blend_transform(wv, &kin.skinning).transform_point3(*p);
            mesh.positions.push(scale * (posed + transl));
            mesh.uvs.push(atlas_uv(l.tile, *uv));
        }
        for f in &l.faces {
            let corners = f.map(|i| Corner { v: base + i, vt: Some(base + i), vn: None });
            mesh.faces.push(ObjFace { corners, material: 0, group: 0 });
        }
    }
    params.transl = transl;
    let smpl = SmplParams::from_body(&params, scale);
    Ok(SynthScan { mesh, texture: tex, texture_size, smpl, outfit: Outfit { upper, lower, hair } })
}

/// Atlas UV of a tile-local UV: 2×2 tiles with a 1 % gutter.
fn atlas_uv(tile: usize, uv: Vec2) -> Vec2 {
    let origin = Vec2::new((tile % 2) as f32 * 0.5, (tile / 2) as f32 * 0.5);
    origin + Vec2::splat(0.005) + uv.clamp(Vec2::ZERO, Vec2::ONE) * 0.49
}

enum Paint {
    Skin,
    Fabric(Fabric),
    Hair(Vec3),
    Shoe { upper: Vec3, sole: Vec3, sole_y: f32 },
}

struct Face<'a> {
    lm: &'a Landmarks,
    skin: Vec3,
    brow: Vec3,
}

fn skin_color(f: &Face, p: Vec3) -> Vec3 {
    let mut c = f.skin * (1.0 + 0.03 * noise(p * 40.0));
    let nose = f.lm.nose;
    if p.z > nose.z - 0.07 && (p.y - nose.y).abs() < 0.12 {
        for side in [-1.0f32, 1.0] {
            let eye = Vec3::new(nose.x + side * 0.033, nose.y + 0.035, 0.0);
            let d = Vec2::new((p.x - eye.x) / 0.013, (p.y - eye.y) / 0.007).length();
            if d < 1.0 {
                c = if d < 0.45 { Vec3::new(0.08, 0.06, 0.05) } else { Vec3::splat(0.92) };
            }
            let brow = Vec2::new((p.x - eye.x) / 0.02, (p.y - eye.y - 0.02) / 0.004).length();
            if brow < 1.0 {
                c = f.brow;
            }
        }
        let mouth = Vec2::new((p.x - nose.x) / 0.022, (p.y - nose.y + 0.045) / 0.0055).length();
        if mouth < 1.0 {
            c = f.skin * Vec3::new(0.85, 0.55, 0.55);
        }
    }
    c
}

/// Rasterise every layer's UV triangles into the atlas, colouring each texel by its layer's
/// paint at the interpolated rest-surface point; then dilate into the gutters.
fn bake_texture(layers: &[(Layer, Paint)], size: usize, face: &Face) -> Vec<u8> {
    let mut img = vec![Vec3::ZERO; size * size];
    let mut filled = vec![false; size * size];
    for (l, paint) in layers {
        for f in &l.faces {
            let uv = f.map(|i| atlas_uv(l.tile, l.uv[i as usize]) * size as f32);
            // Texture rows go down: y_img = (1 − v)·size.
            let s = uv.map(|t| Vec2::new(t.x, size as f32 - t.y));
            let area = (s[1] - s[0]).perp_dot(s[2] - s[0]);
            if area.abs() < 1e-12 {
                continue;
            }
            let lo = s[0].min(s[1]).min(s[2]).floor().max(Vec2::ZERO);
            let hi = s[0].max(s[1]).max(s[2]).ceil().min(Vec2::splat(size as f32 - 1.0));
            for y in lo.y as usize..=hi.y as usize {
                for x in lo.x as usize..=hi.x as usize {
                    let p = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
                    let b0 = (s[1] - p).perp_dot(s[2] - p) / area;
                    let b1 = (s[2] - p).perp_dot(s[0] - p) / area;
                    let b2 = 1.0 - b0 - b1;
                    // Slightly conservative so thin triangles still cover their texels.
                    if b0 < -0.02 || b1 < -0.02 || b2 < -0.02 {
                        continue;
                    }
                    let [a, b, c] = f.map(|i| l.surface[i as usize]);
                    let pt = a * b0 + b * b1 + c * b2;
                    let col = match paint {
                        Paint::Skin => skin_color(face, pt),
                        Paint::Fabric(fab) => fabric_color(fab, pt),
                        Paint::Hair(h) => {
                            *h * (1.0
                                + 0.25 * (std::f32::consts::TAU * (pt.x * 120.0 + 4.0 * noise(pt * 10.0))).sin() * 0.5
                                + 0.1 * noise(pt * 60.0))
                        }
                        Paint::Shoe { upper, sole, sole_y } => {
                            if pt.y < *sole_y {
                                *sole
                            } else {
                                *upper * (1.0 + 0.05 * noise(pt * 80.0))
                            }
                        }
                    };
                    img[y * size + x] = col.clamp(Vec3::ZERO, Vec3::ONE);
                    filled[y * size + x] = true;
                }
            }
        }
    }
    // Dilate 4 texels so bilinear lookups near island borders never see the background.
    for _ in 0..4 {
        uv_atlas::dilate_ring(&mut img, &mut filled, size, &uv_atlas::NEIGHBOURS_4);
    }
    img.iter().flat_map(|c| c.to_array().map(|x| (x * 255.0).round() as u8)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scans_are_deterministic_textured_and_clothed() {
        let model = BodyModel::default_body().unwrap();
        let a = make_scan(&model, 3, "0001", 128, None).unwrap();
        let b = make_scan(&model, 3, "0001", 128, None).unwrap();
        assert_eq!(a.mesh.positions, b.mesh.positions);
        assert_eq!(a.texture, b.texture);
        let c = make_scan(&model, 3, "0002", 128, None).unwrap();
        assert_ne!(a.mesh.positions.len() + a.texture.len(), 0);
        assert_ne!(a.texture, c.texture, "different ids differ");
        // Garments add geometry on top of the body.
        assert!(a.mesh.faces.len() > model.faces.len() * 2, "{} faces", a.mesh.faces.len());
        assert!(a.mesh.uvs.iter().all(|t| (0.0..=1.0).contains(&t.x) && (0.0..=1.0).contains(&t.y)));
        assert_eq!(a.smpl.body_pose.len(), 69);
        assert_eq!(a.smpl.betas.len(), 10);
        // The scan sits where its smpl.json says: the body-frame height matches a human.
        let ys: Vec<f32> = a.mesh.positions.iter().map(|p| a.smpl.scan_to_body(*p).y).collect();
        let h = ys.iter().cloned().fold(f32::MIN, f32::max) - ys.iter().cloned().fold(f32::MAX, f32::min);
        assert!((1.0..2.3).contains(&h), "height {h}");
    }

    #[test]
    fn outfit_json_names_the_garments_drawn() {
        let model = BodyModel::default_body().unwrap();
        let dir = std::env::temp_dir().join(format!("getavatar-outfit-{}", std::process::id()));
        let mut lowers = std::collections::BTreeSet::new();
        for i in 0..24 {
            let id = format!("{i:04}");
            let scan = make_scan(&model, 3, &id, 64, None).unwrap();
            let json = serde_json::to_value(scan.outfit).unwrap();
            lowers.insert(json["lower"].as_str().unwrap().to_string());
            if i == 0 {
                write_scan(&model, 3, &id, 64, None, &dir.join(&id)).unwrap();
                let text = std::fs::read_to_string(dir.join(&id).join("outfit.json")).unwrap();
                let v: serde_json::Value = serde_json::from_str(&text).unwrap();
                assert_eq!(v, json, "outfit.json is the scan's outfit");
                for (key, kinds) in [
                    ("upper", &["t_shirt", "long_sleeve", "tank", "jacket"][..]),
                    ("lower", &["trousers", "shorts", "skirt", "dress"][..]),
                    ("hair", &["short", "long", "bald"][..]),
                ] {
                    assert!(kinds.contains(&v[key].as_str().unwrap()), "{key}: {}", v[key]);
                }
            }
        }
        let _ = std::fs::remove_dir_all(&dir);
        let all: Vec<&str> = lowers.iter().map(|s| s.as_str()).collect();
        assert_eq!(all, ["dress", "shorts", "skirt", "trousers"], "24 scans draw every kind of lower garment");
    }
}
