//! 3D scans as dataset users have them (paper Sec. 5: THUman2.0 / RenderPeople): a Wavefront
//! OBJ with UVs, its MTL material(s) and texture image(s), plus the fitted body parameters
//! (`smpl.json`). Parsing works on text and decoded pixels (no file access here); the CLI
//! reads the files. [`render_scan`] renders a scan with the data protocol's camera into the
//! dataset's RGB / normal / mask images.
//!
//! Scan frame: a scan's vertices are `scale · (body(θ, β) + transl)` (`smpl.json`); rendering
//! maps them back to the body frame `x / scale − transl`, where the generator lives.

use glam::{Vec2, Vec3};
use serde::{Deserialize, Serialize};

use crate::body::skinning::BodyParams;
use crate::render::camera::OrbitCamera;
use crate::render::rasterize::{render_views_textured, RenderedViews, Texture};

/// Errors of the scan readers; messages carry the line number or field.
#[derive(Debug, thiserror::Error)]
pub enum ScanError {
    #[error("OBJ line {line}: {msg}")]
    Obj { line: usize, msg: String },
    #[error("OBJ: {0}")]
    ObjMesh(String),
    #[error("MTL line {line}: {msg}")]
    Mtl { line: usize, msg: String },
    #[error("smpl.json: {0}")]
    Smpl(String),
}

/// One triangle corner: indices into positions, UVs and normals.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Corner {
    pub v: u32,
    pub vt: Option<u32>,
    pub vn: Option<u32>,
}

/// A triangle with its material (index into [`ObjMesh::materials`]) and group (index into
/// [`ObjMesh::groups`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ObjFace {
    pub corners: [Corner; 3],
    pub material: u32,
    pub group: u32,
}

/// A triangulated OBJ mesh.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ObjMesh {
    pub positions: Vec<Vec3>,
    pub uvs: Vec<Vec2>,
    pub normals: Vec<Vec3>,
    pub faces: Vec<ObjFace>,
    /// Material names in order of first `usemtl` (index 0 = "" when faces precede any `usemtl`).
    pub materials: Vec<String>,
    /// `mtllib` file names, as written.
    pub mtllibs: Vec<String>,
    /// Group names (`g`) in order of first use; faces before any `g` are in "default".
    pub groups: Vec<String>,
}

impl ObjMesh {
    /// The triangles of group `name`.
    pub fn group_faces<'a>(&'a self, name: &str) -> impl Iterator<Item = &'a ObjFace> + 'a {
        let index = self.groups.iter().position(|g| g == name).map(|i| i as u32);
        self.faces.iter().filter(move |f| Some(f.group) == index)
    }
}

fn parse_floats<const N: usize>(it: &mut std::str::SplitWhitespace, line: usize) -> Result<[f32; N], ScanError> {
    let mut out = [0.0f32; N];
    for (k, o) in out.iter_mut().enumerate() {
        let tok = it.next().ok_or_else(|| ScanError::Obj { line, msg: format!("expected {N} numbers, got {k}") })?;
        *o = tok.parse().map_err(|_| ScanError::Obj { line, msg: format!("`{tok}` is not a number") })?;
        if !o.is_finite() {
            return Err(ScanError::Obj { line, msg: format!("`{tok}` is not finite") });
        }
    }
    Ok(out)
}

/// Parse OBJ text: `v` (extra vertex-colour numbers ignored), `vt`, `vn`, `f` (polygons are
/// fan-triangulated; negative indices count from the end), `usemtl`, `mtllib`, `g` (the first
/// name). Indices are validated.
pub fn parse_obj(text: &str) -> Result<ObjMesh, ScanError> {
    let mut m = ObjMesh::default();
    let mut current: Option<u32> = None;
    let mut group: Option<u32> = None;
    for (ln, raw) in text.lines().enumerate() {
        let line = ln + 1;
        let l = raw.split('#').next().unwrap_or("").trim();
        let mut it = l.split_whitespace();
        match it.next() {
            Some("v") => m.positions.push(Vec3::from_array(parse_floats::<3>(&mut it, line)?)),
            Some("vt") => m.uvs.push(Vec2::from_array(parse_floats::<2>(&mut it, line)?)),
            Some("vn") => m.normals.push(Vec3::from_array(parse_floats::<3>(&mut it, line)?)),
            Some("usemtl") => {
                let name = it.collect::<Vec<_>>().join(" ");
                let idx = match m.materials.iter().position(|n| *n == name) {
                    Some(i) => i,
                    None => {
                        m.materials.push(name);
                        m.materials.len() - 1
                    }
                };
                current = Some(idx as u32);
            }
            Some("mtllib") => m.mtllibs.push(it.collect::<Vec<_>>().join(" ")),
            Some("g") => group = Some(group_index(&mut m.groups, it.next().unwrap_or("default"))),
            Some("f") => {
                let material = match current {
                    Some(c) => c,
                    None => {
                        if m.materials.is_empty() {
                            m.materials.push(String::new());
                        }
                        let c = m.materials.iter().position(|n| n.is_empty()).unwrap_or_else(|| {
                            m.materials.push(String::new());
                            m.materials.len() - 1
                        }) as u32;
                        current = Some(c);
                        c
                    }
                };
                let corners: Vec<Corner> = it.map(|tok| parse_corner(tok, &m, line)).collect::<Result<_, _>>()?;
                if corners.len() < 3 {
                    return Err(ScanError::Obj { line, msg: format!("face with {} corners", corners.len()) });
                }
                let group = *group.get_or_insert_with(|| group_index(&mut m.groups, "default"));
                for k in 1..corners.len() - 1 {
                    m.faces.push(ObjFace { corners: [corners[0], corners[k], corners[k + 1]], material, group });
                }
            }
            _ => {} // o, g, s, l, p and unknown statements carry nothing we render
        }
    }
    if m.faces.is_empty() {
        return Err(ScanError::ObjMesh("no faces".into()));
    }
    Ok(m)
}

/// Index of group `name`, added when new.
fn group_index(groups: &mut Vec<String>, name: &str) -> u32 {
    match groups.iter().position(|g| g == name) {
        Some(i) => i as u32,
        None => {
            groups.push(name.to_string());
            (groups.len() - 1) as u32
        }
    }
}

fn parse_corner(tok: &str, m: &ObjMesh, line: usize) -> Result<Corner, ScanError> {
    let mut parts = tok.split('/');
    let idx = |s: Option<&str>, n: usize, what: &str| -> Result<Option<u32>, ScanError> {
        match s {
            None | Some("") => Ok(None),
            Some(s) => {
                let i: i64 = s
                    .parse()
                    .map_err(|_| ScanError::Obj { line, msg: format!("bad {what} index `{s}` in `{tok}`") })?;
                let r = if i > 0 { i - 1 } else { n as i64 + i };
                if i == 0 || r < 0 || r >= n as i64 {
                    return Err(ScanError::Obj { line, msg: format!("{what} index {i} out of range (1..={n})") });
                }
                Ok(Some(r as u32))
            }
        }
    };
    let v = idx(parts.next(), m.positions.len(), "vertex")?
        .ok_or_else(|| ScanError::Obj { line, msg: format!("corner `{tok}` has no vertex index") })?;
    let vt = idx(parts.next(), m.uvs.len(), "texture")?;
    let vn = idx(parts.next(), m.normals.len(), "normal")?;
    Ok(Corner { v, vt, vn })
}

/// Write an OBJ (one `g` per group run where there is more than one group, one `usemtl` per
/// material run, `v/vt/vn` corners when present).
pub fn write_obj(m: &ObjMesh) -> String {
    use std::fmt::Write;
    let mut s = String::from("# GETAvatar scan\n");
    for lib in &m.mtllibs {
        let _ = writeln!(s, "mtllib {lib}");
    }
    for p in &m.positions {
        let _ = writeln!(s, "v {:.6} {:.6} {:.6}", p.x, p.y, p.z);
    }
    for t in &m.uvs {
        let _ = writeln!(s, "vt {:.6} {:.6}", t.x, t.y);
    }
    for n in &m.normals {
        let _ = writeln!(s, "vn {:.5} {:.5} {:.5}", n.x, n.y, n.z);
    }
    let mut current = u32::MAX;
    let mut group = u32::MAX;
    for f in &m.faces {
        if m.groups.len() > 1 && f.group != group {
            group = f.group;
            if let Some(name) = m.groups.get(group as usize) {
                let _ = writeln!(s, "g {name}");
            }
        }
        if f.material != current {
            current = f.material;
            if let Some(name) = m.materials.get(current as usize).filter(|n| !n.is_empty()) {
                let _ = writeln!(s, "usemtl {name}");
            }
        }
        s.push('f');
        for c in f.corners {
            let _ = match (c.vt, c.vn) {
                (None, None) => write!(s, " {}", c.v + 1),
                (Some(t), None) => write!(s, " {}/{}", c.v + 1, t + 1),
                (None, Some(n)) => write!(s, " {}//{}", c.v + 1, n + 1),
                (Some(t), Some(n)) => write!(s, " {}/{}/{}", c.v + 1, t + 1, n + 1),
            };
        }
        s.push('\n');
    }
    s
}

/// A material of an MTL file: diffuse colour and diffuse texture.
#[derive(Clone, Debug, PartialEq)]
pub struct Material {
    pub name: String,
    /// `Kd`, linear RGB (default 0.8 grey).
    pub kd: Vec3,
    /// `map_Kd` file name as written (options before the name are skipped).
    pub map_kd: Option<String>,
}

/// Parse MTL text (`newmtl`, `Kd`, `map_Kd`).
pub fn parse_mtl(text: &str) -> Result<Vec<Material>, ScanError> {
    let mut out: Vec<Material> = Vec::new();
    for (ln, raw) in text.lines().enumerate() {
        let line = ln + 1;
        let l = raw.split('#').next().unwrap_or("").trim();
        let mut it = l.split_whitespace();
        let Some(key) = it.next() else { continue };
        let rest: Vec<&str> = it.collect();
        match key {
            "newmtl" => {
                out.push(Material { name: rest.join(" "), kd: Vec3::splat(0.8), map_kd: None });
            }
            "Kd" | "map_Kd" => {
                let m =
                    out.last_mut().ok_or_else(|| ScanError::Mtl { line, msg: format!("`{key}` before `newmtl`") })?;
                if key == "Kd" {
                    let v: Vec<f32> = rest.iter().take(3).filter_map(|t| t.parse().ok()).collect();
                    if v.len() != 3 {
                        return Err(ScanError::Mtl { line, msg: "Kd needs three numbers".into() });
                    }
                    m.kd = Vec3::new(v[0], v[1], v[2]);
                } else {
                    // The file name is the last token(s) after any `-option value` pairs.
                    let name =
                        rest.last().ok_or_else(|| ScanError::Mtl { line, msg: "map_Kd without a file".into() })?;
                    m.map_kd = Some(name.to_string());
                }
            }
            _ => {}
        }
    }
    Ok(out)
}

/// Write an MTL file with one textured material.
pub fn write_mtl(name: &str, texture_file: &str) -> String {
    format!("newmtl {name}\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nillum 1\nmap_Kd {texture_file}\n")
}

/// Fitted body parameters of a scan (`<id>/smpl.json`): SMPL's 72-number pose split as
/// `global_orient` (3) + `body_pose` (69), `betas` (≤ the model's count, usually 10),
/// `transl` (metres) and `scale`; scan vertices = `scale · (body + transl)`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SmplParams {
    pub global_orient: Vec<f32>,
    pub body_pose: Vec<f32>,
    pub betas: Vec<f32>,
    #[serde(default)]
    pub transl: Vec<f32>,
    #[serde(default = "one")]
    pub scale: f32,
}

fn one() -> f32 {
    1.0
}

impl SmplParams {
    /// Parse and validate (`global_orient` 3, `body_pose` 69, `transl` 3 or absent, finite
    /// numbers, positive scale).
    pub fn from_json(text: &str) -> Result<Self, ScanError> {
        let p: SmplParams = serde_json::from_str(text).map_err(|e| ScanError::Smpl(e.to_string()))?;
        let check = |name: &str, v: &[f32], want: &[usize]| {
            if !want.contains(&v.len()) {
                return Err(ScanError::Smpl(format!("`{name}` has {} numbers, expected {want:?}", v.len())));
            }
            if v.iter().any(|x| !x.is_finite()) {
                return Err(ScanError::Smpl(format!("`{name}` has a non-finite number")));
            }
            Ok(())
        };
        check("global_orient", &p.global_orient, &[3])?;
        check("body_pose", &p.body_pose, &[69])?;
        check("transl", &p.transl, &[0, 3])?;
        if p.betas.len() > 300 || p.betas.iter().any(|x| !x.is_finite()) {
            return Err(ScanError::Smpl("`betas` must be at most 300 finite numbers".into()));
        }
        if !(p.scale.is_finite() && p.scale > 0.0) {
            return Err(ScanError::Smpl(format!("`scale` must be positive, got {}", p.scale)));
        }
        Ok(p)
    }

    pub fn to_json(&self) -> Result<String, ScanError> {
        serde_json::to_string_pretty(self).map_err(|e| ScanError::Smpl(e.to_string()))
    }

    pub fn from_body(params: &BodyParams, scale: f32) -> Self {
        let theta = params.theta();
        Self {
            global_orient: theta[..3].to_vec(),
            body_pose: theta[3..].to_vec(),
            betas: params.betas.clone(),
            transl: params.transl.to_array().to_vec(),
            scale,
        }
    }

    /// The body parameters (translation included).
    pub fn body_params(&self) -> BodyParams {
        let mut p = BodyParams::from_split(&self.global_orient, &self.body_pose, &self.betas);
        p.transl = self.translation();
        p
    }

    pub fn translation(&self) -> Vec3 {
        if self.transl.len() == 3 {
            Vec3::new(self.transl[0], self.transl[1], self.transl[2])
        } else {
            Vec3::ZERO
        }
    }

    /// Map a scan-frame point to the body frame: `x / scale − transl`.
    pub fn scan_to_body(&self, x: Vec3) -> Vec3 {
        x / self.scale - self.translation()
    }
}

/// A loaded scan: mesh, decoded textures and colours per material.
#[derive(Clone, Debug)]
pub struct Scan {
    pub mesh: ObjMesh,
    /// Per material of `mesh.materials`: its texture, if any.
    pub textures: Vec<Option<Texture>>,
    /// Per material: its diffuse colour, linear RGB, used where there is no texture (a texture
    /// replaces `Kd`, as Blender's OBJ importer does).
    pub colors: Vec<Vec3>,
}

/// Per-corner normals: the OBJ's `vn` where given, otherwise area-weighted smooth normals that
/// keep creases sharper than 60° (faces meeting at a larger angle do not share normals, so a
/// box stays flat-shaded while a sphere is smooth).
pub fn corner_normals(mesh: &ObjMesh) -> Vec<[Vec3; 3]> {
    let face_n: Vec<Vec3> = mesh
        .faces
        .iter()
        .map(|f| {
            let [a, b, c] = f.corners.map(|c| mesh.positions[c.v as usize]);
            (b - a).cross(c - a)
        })
        .collect();
    // Faces incident to each position (CSR).
    let nv = mesh.positions.len();
    let mut start = vec![0usize; nv + 1];
    for f in &mesh.faces {
        for c in f.corners {
            start[c.v as usize + 1] += 1;
        }
    }
    for i in 0..nv {
        start[i + 1] += start[i];
    }
    let mut fill = start.clone();
    let mut inc = vec![0u32; start[nv]];
    for (fi, f) in mesh.faces.iter().enumerate() {
        for c in f.corners {
            inc[fill[c.v as usize]] = fi as u32;
            fill[c.v as usize] += 1;
        }
    }
    let cos_crease = 60f32.to_radians().cos();
    mesh.faces
        .iter()
        .enumerate()
        .map(|(fi, f)| {
            let own = face_n[fi].normalize_or_zero();
            f.corners.map(|c| {
                if let Some(n) = c.vn.and_then(|i| mesh.normals.get(i as usize)) {
                    return n.normalize_or_zero();
                }
                let mut sum = Vec3::ZERO;
                for &g in &inc[start[c.v as usize]..start[c.v as usize + 1]] {
                    let n = face_n[g as usize];
                    if n.normalize_or_zero().dot(own) >= cos_crease {
                        sum += n;
                    }
                }
                let s = sum.normalize_or_zero();
                if s == Vec3::ZERO {
                    own
                } else {
                    s
                }
            })
        })
        .collect()
}

/// Vertical extent `(min_y, max_y)` of the scan in the body frame.
pub fn body_frame_y_range(mesh: &ObjMesh, smpl: &SmplParams) -> (f32, f32) {
    let used = mesh.faces.iter().flat_map(|f| f.corners.map(|c| c.v));
    used.fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), v| {
        let y = smpl.scan_to_body(mesh.positions[v as usize]).y;
        (lo.min(y), hi.max(y))
    })
}

/// A scan prepared for rendering: unwelded triangles (three vertices per face) in the body
/// frame with per-corner normals and `(u, v, material)` attributes.
#[derive(Clone, Debug)]
pub struct RenderableScan {
    pub vertices: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    pub attributes: Vec<Vec3>,
    pub triangles: Vec<[u32; 3]>,
}

impl RenderableScan {
    pub fn new(scan: &Scan, smpl: &SmplParams) -> Self {
        let m = &scan.mesh;
        let normals = corner_normals(m);
        let n = m.faces.len() * 3;
        let mut out = Self {
            vertices: Vec::with_capacity(n),
            normals: Vec::with_capacity(n),
            attributes: Vec::with_capacity(n),
            triangles: Vec::with_capacity(m.faces.len()),
        };
        for (f, fnorm) in m.faces.iter().zip(&normals) {
            let base = out.vertices.len() as u32;
            for (c, nrm) in f.corners.iter().zip(fnorm) {
                out.vertices.push(smpl.scan_to_body(m.positions[c.v as usize]));
                out.normals.push(*nrm);
                let uv = c.vt.map(|t| m.uvs[t as usize]).unwrap_or(Vec2::ZERO);
                out.attributes.push(Vec3::new(uv.x, uv.y, f.material as f32));
            }
            out.triangles.push([base, base + 1, base + 2]);
        }
        out
    }

    /// Vertical extent of the rendered geometry.
    pub fn y_range(&self) -> (f32, f32) {
        self.vertices.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), v| (lo.min(v.y), hi.max(v.y)))
    }
}

/// Render a scan through `camera` at `size`² with `ss`×`ss` supersampling: unlit albedo from
/// the textures (bilinear, in linear light) on white, world-space normals, coverage mask.
pub fn render_scan(
    scan: &Scan,
    prepared: &RenderableScan,
    camera: &OrbitCamera,
    size: usize,
    ss: usize,
) -> RenderedViews {
    let vp = camera.projection_gl(1.0) * camera.world_to_camera();
    let albedo = |attrs: &[Vec3]| Ok::<_, std::convert::Infallible>(attrs.iter().map(|a| scan.albedo(*a)).collect());
    render_views_textured(
        &prepared.vertices,
        &prepared.triangles,
        &prepared.normals,
        &prepared.attributes,
        vp,
        size,
        ss,
        albedo,
    )
    .unwrap_or_else(|never| match never {})
}

impl Scan {
    /// Linear albedo at a [`RenderableScan`] attribute `(u, v, material)`: the material's
    /// texture (bilinear) or, without one, its diffuse colour.
    pub fn albedo(&self, a: Vec3) -> Vec3 {
        let mat = (a.z.round().max(0.0) as usize).min(self.colors.len().saturating_sub(1));
        match self.textures.get(mat).and_then(|t| t.as_ref()) {
            Some(t) => t.sample(Vec2::new(a.x, a.y)),
            None => self.colors.get(mat).copied().unwrap_or(Vec3::splat(0.8)),
        }
    }
}

/// A point on a scan's surface in the body frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceSample {
    pub position: Vec3,
    /// Unit normal (interpolated corner normals).
    pub normal: Vec3,
    /// Linear albedo ([`Scan::albedo`]).
    pub color: Vec3,
}

/// `n` points drawn uniformly by area over the surface of `prepared` (triangle by its area,
/// then a uniform point in it), with their normals and albedo. Empty for a surface of zero
/// area.
pub fn sample_surface(
    scan: &Scan,
    prepared: &RenderableScan,
    n: usize,
    rng: &mut crate::util::rng::Rng,
) -> Vec<SurfaceSample> {
    sample_surface_where(scan, prepared, n, rng, |_| true)
}

/// [`sample_surface`] over the triangles whose centroid (body frame) passes `keep`: uniform by
/// area over that part of the surface. Empty where it has no area.
pub fn sample_surface_where(
    scan: &Scan,
    prepared: &RenderableScan,
    n: usize,
    rng: &mut crate::util::rng::Rng,
    keep: impl Fn(Vec3) -> bool,
) -> Vec<SurfaceSample> {
    let v = &prepared.vertices;
    let mut cumulative = Vec::with_capacity(prepared.triangles.len());
    let mut total = 0.0f64;
    for t in &prepared.triangles {
        let [a, b, c] = t.map(|i| v[i as usize]);
        if keep((a + b + c) / 3.0) {
            total += 0.5 * (b - a).cross(c - a).length() as f64;
        }
        cumulative.push(total);
    }
    // Also catches NaN areas.
    if total.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
        return Vec::new();
    }
    (0..n)
        .map(|_| {
            let x = rng.uniform() as f64 * total;
            // The first triangle whose cumulative area exceeds x: one with area (x < total).
            let k = cumulative.partition_point(|&c| c <= x).min(cumulative.len() - 1);
            let t = prepared.triangles[k].map(|i| i as usize);
            // Uniform barycentrics: (1 − √r₁, √r₁ (1 − r₂), √r₁ r₂).
            let (r1, r2) = (rng.uniform().sqrt(), rng.uniform());
            let w = [1.0 - r1, r1 * (1.0 - r2), r1 * r2];
            let mix = |a: &[Vec3]| w[0] * a[t[0]] + w[1] * a[t[1]] + w[2] * a[t[2]];
            SurfaceSample {
                position: mix(v),
                normal: mix(&prepared.normals).normalize_or_zero(),
                color: scan.albedo(mix(&prepared.attributes).with_z(prepared.attributes[t[0]].z)),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn obj_round_trip_with_polygons_negative_indices_and_materials() {
        let text = "mtllib a.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n\
                    usemtl skin\nf 1/1 2/2 3/3 4/4\nusemtl cloth\nf -4/-4 -2/-2 -1/-1\n";
        let m = parse_obj(text).unwrap();
        assert_eq!(m.faces.len(), 3);
        assert_eq!(m.materials, vec!["skin", "cloth"]);
        assert_eq!(m.faces[2].material, 1);
        assert_eq!(m.faces[2].corners.map(|c| c.v), [0, 2, 3]);
        assert_eq!(m.faces[1].corners[2].vt, Some(3));
        let again = parse_obj(&write_obj(&m)).unwrap();
        assert_eq!(again.faces, m.faces);
        assert_eq!(again.mtllibs, vec!["a.mtl"]);
    }

    #[test]
    fn obj_groups_keep_their_faces_through_a_round_trip() {
        let text =
            "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\ng body\nf 1 2 3 4\ng helper\nf 2 3 4\ng body\nf 4 1 2\n";
        let m = parse_obj(text).unwrap();
        assert_eq!(m.groups, vec!["default", "body", "helper"]);
        assert_eq!(m.faces.iter().map(|f| f.group).collect::<Vec<_>>(), [0, 1, 1, 2, 1]);
        let body: Vec<[u32; 3]> = m.group_faces("body").map(|f| f.corners.map(|c| c.v)).collect();
        assert_eq!(body, [[0, 1, 2], [0, 2, 3], [3, 0, 1]]);
        assert_eq!(m.group_faces("missing").count(), 0);
        let again = parse_obj(&write_obj(&m)).unwrap();
        assert_eq!((again.faces, again.groups), (m.faces, m.groups));
    }

    #[test]
    fn malformed_obj_and_mtl_errors_name_the_line() {
        let e = parse_obj("v 0 0 0\nv 1 0\n").unwrap_err().to_string();
        assert!(e.contains("line 2") && e.contains("expected 3"), "{e}");
        let e = parse_obj("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n").unwrap_err().to_string();
        assert!(e.contains("line 4") && e.contains("out of range"), "{e}");
        let e = parse_obj("v 0 0 nan\n").unwrap_err().to_string();
        assert!(e.contains("not finite"), "{e}");
        assert!(parse_obj("v 0 0 0\n").unwrap_err().to_string().contains("no faces"));
        let e = parse_mtl("Kd 1 1 1\n").unwrap_err().to_string();
        assert!(e.contains("line 1") && e.contains("before `newmtl`"), "{e}");
        let m = parse_mtl("newmtl a\nKd 0.5 0.25 1\nmap_Kd -bm 1 tex.png\n").unwrap();
        assert_eq!(m[0].map_kd.as_deref(), Some("tex.png"));
        assert_eq!(m[0].kd, Vec3::new(0.5, 0.25, 1.0));
    }

    #[test]
    fn smpl_json_validation_and_frames() {
        let mut p = SmplParams::from_body(&BodyParams::default(), 2.0);
        p.transl = vec![0.0, 1.0, 0.0];
        let q = SmplParams::from_json(&p.to_json().unwrap()).unwrap();
        assert_eq!(q, p);
        assert_eq!(q.scan_to_body(Vec3::new(2.0, 4.0, 0.0)), Vec3::new(1.0, 1.0, 0.0));
        p.body_pose.pop();
        let e = SmplParams::from_json(&p.to_json().unwrap()).unwrap_err().to_string();
        assert!(e.contains("`body_pose` has 68 numbers"), "{e}");
    }

    #[test]
    fn surface_samples_are_uniform_by_area_with_normals_and_albedo() {
        // Two triangles in the z = 0 plane, areas 3 : 1, red and blue diffuse materials.
        let text = "v 0 0 0\nv 3 0 0\nv 0 2 0\nv 3 2 0\nv 4 2 0\nusemtl red\nf 1 2 3\nusemtl blue\nf 2 5 4\n";
        let mesh = parse_obj(text).unwrap();
        let scan = Scan { mesh, textures: vec![None, None], colors: vec![Vec3::X, Vec3::Z] };
        let smpl = SmplParams::from_body(&BodyParams::default(), 1.0);
        let prepared = RenderableScan::new(&scan, &smpl);
        let n = 4000;
        let s = sample_surface(&scan, &prepared, n, &mut crate::util::rng::Rng::new(7, 0));
        assert_eq!(s.len(), n);
        let red = s.iter().filter(|p| p.color == Vec3::X).count() as f32 / n as f32;
        assert!((red - 0.75).abs() < 0.03, "red share {red}");
        assert!(s.iter().all(|p| p.color == Vec3::X || p.color == Vec3::Z));
        for p in &s {
            assert!(p.position.z == 0.0 && (p.normal - Vec3::Z).length() < 1e-5, "{p:?}");
            // Inside its triangle: red below the diagonal x/3 + y/2 = 1, blue in x ∈ [3, 4].
            if p.color == Vec3::X {
                assert!(p.position.x / 3.0 + p.position.y / 2.0 <= 1.0 + 1e-5 && p.position.min_element() >= 0.0);
            } else {
                assert!(p.position.x >= 3.0 - 1e-5 && p.position.y >= 2.0 * (p.position.x - 3.0) - 1e-4);
            }
        }
        // Uniform within the red triangle: its centroid is (1, 2/3).
        let reds: Vec<Vec3> = s.iter().filter(|p| p.color == Vec3::X).map(|p| p.position).collect();
        let c = reds.iter().copied().sum::<Vec3>() / reds.len() as f32;
        assert!((c - Vec3::new(1.0, 2.0 / 3.0, 0.0)).length() < 0.05, "{c}");
        let flat = parse_obj("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n").unwrap();
        let scan = Scan { mesh: flat, textures: vec![None], colors: vec![Vec3::ONE] };
        assert!(sample_surface(&scan, &RenderableScan::new(&scan, &smpl), 5, &mut crate::util::rng::Rng::new(1, 0))
            .is_empty());
    }

    #[test]
    fn surface_samples_where_keep_only_the_chosen_triangles() {
        // Three triangles in the z = 0 plane: red (area 3), blue (area 1), green (area 2)
        // beyond x = 4. Keeping centroids with x > 3 draws blue : green = 1 : 2, never red.
        let text = "v 0 0 0\nv 3 0 0\nv 0 2 0\nv 3 2 0\nv 4 2 0\nv 4 0 0\nv 6 0 0\n\
                    usemtl red\nf 1 2 3\nusemtl blue\nf 2 5 4\nusemtl green\nf 6 7 5\n";
        let mesh = parse_obj(text).unwrap();
        let scan = Scan { mesh, textures: vec![None, None, None], colors: vec![Vec3::X, Vec3::Z, Vec3::Y] };
        let prepared = RenderableScan::new(&scan, &SmplParams::from_body(&BodyParams::default(), 1.0));
        let n = 3000;
        let s = sample_surface_where(&scan, &prepared, n, &mut crate::util::rng::Rng::new(3, 0), |c| c.x > 3.0);
        assert_eq!(s.len(), n);
        assert!(s.iter().all(|p| p.color != Vec3::X && p.position.x >= 3.0 - 1e-5), "a red point was drawn");
        let green = s.iter().filter(|p| p.color == Vec3::Y).count() as f32 / n as f32;
        assert!((green - 2.0 / 3.0).abs() < 0.03, "green share {green}");
        // Nothing kept: no points.
        assert!(
            sample_surface_where(&scan, &prepared, 5, &mut crate::util::rng::Rng::new(3, 0), |c| c.x > 9.0).is_empty()
        );
    }

    #[test]
    fn crease_normals_split_a_cube_and_smooth_a_fan() {
        // Two faces at 90° share an edge: normals stay per face.
        let text = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 1 0 -1\nf 1 2 3\nf 2 4 3\n";
        let m = parse_obj(text).unwrap();
        let n = corner_normals(&m);
        assert!((n[0][1] - Vec3::Z).length() < 1e-6 && (n[1][0] - Vec3::X).length() < 1e-6, "{n:?}");
        // Nearly coplanar faces (10°) share a smooth normal.
        let text = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 2 0 -0.176\nf 1 2 3\nf 2 4 3\n";
        let n = corner_normals(&parse_obj(text).unwrap());
        assert!((n[0][1] - n[1][0]).length() < 1e-6);
    }
}
