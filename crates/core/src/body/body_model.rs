//! The parametric body model in the SMPL layout (paper Sec. 3, "SMPL").
//!
//! A [`BodyModel`] holds exactly the arrays of an official SMPL `.npz` file: `v_template (V,3)`,
//! `f (F,3)`, `weights (V,24)`, `J_regressor (24,V)`, `kintree_table (2,24)`,
//! `shapedirs (V,3,B)`, `posedirs (V,3,207)` and optionally `vt (T,2)` / `ft (F,3)` UVs.
//! The project ships an open equivalent built from CC0 MakeHuman assets
//! (`assets/body/getavatar_body.npz`, see its README); a licensed `SMPL_NEUTRAL.npz` loads
//! the same way.
//!
//! Conventions (docs/conventions.md): metres, y up, the body faces +z, its left side is +x,
//! rest pose = SMPL's T-pose with world-aligned joint frames.

use std::collections::BTreeMap;

use glam::{Vec2, Vec3};

use crate::io::npz::{self, NpyArray, NpzError};

/// Number of joints of the SMPL kinematic tree.
pub const NUM_JOINTS: usize = 24;
/// Pose-corrective feature size: 23 joints × 9 rotation-matrix entries.
pub const NUM_POSE_FEATURES: usize = (NUM_JOINTS - 1) * 9;

/// SMPL joint names in SMPL order.
pub const JOINT_NAMES: [&str; NUM_JOINTS] = [
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hand",
    "right_hand",
];

/// SMPL parents (`-1` for the root).
pub const SMPL_PARENTS: [i32; NUM_JOINTS] =
    [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21];

/// Index of a joint by its SMPL name.
pub fn joint_index(name: &str) -> Option<usize> {
    JOINT_NAMES.iter().position(|n| *n == name)
}

/// Errors when loading or validating a body model. Messages name the offending key.
#[derive(Debug, thiserror::Error)]
pub enum BodyModelError {
    #[error(transparent)]
    Npz(#[from] NpzError),
    #[error("body model key `{key}`: {msg}")]
    Invalid { key: &'static str, msg: String },
}

fn invalid(key: &'static str, msg: impl Into<String>) -> BodyModelError {
    BodyModelError::Invalid { key, msg: msg.into() }
}

/// A body model in the SMPL layout. All arrays are flattened row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct BodyModel {
    /// Rest-pose template vertices, metres.
    pub v_template: Vec<Vec3>,
    /// Triangles (indices into `v_template`), counter-clockwise seen from outside.
    pub faces: Vec<[u32; 3]>,
    /// Skin weights, `V × 24`, rows sum to 1.
    pub weights: Vec<[f32; NUM_JOINTS]>,
    /// Joint regressor, `24 × V` row-major.
    pub j_regressor: Vec<f32>,
    /// Parent of each joint (`-1` for the root).
    pub parents: [i32; NUM_JOINTS],
    /// Shape blend shapes, `V × 3 × B` row-major.
    pub shapedirs: Vec<f32>,
    /// Number of shape components B.
    pub num_betas: usize,
    /// Pose-corrective blend shapes, `V × 3 × 207` row-major; empty when the model has none
    /// (a file's all-zero `posedirs` load as empty: no pose pays for scanning or adding them).
    pub posedirs: Vec<f32>,
    /// Texture coordinates (optional; empty when absent).
    pub vt: Vec<Vec2>,
    /// UV triangles (indices into `vt`, same count as `faces` when present).
    pub ft: Vec<[u32; 3]>,
    /// Human-readable names of the shape components, when the file carries them
    /// (`shape_names`, one name per line, UTF-8 bytes). Not part of SMPL; optional.
    pub shape_names: Vec<String>,
}

/// The open default body, embedded in the binary (see `assets/body/README.md`).
#[cfg(feature = "embedded-body")]
pub const DEFAULT_BODY_NPZ: &[u8] =
    include_bytes!(concat!(env!("CARGO_MANIFEST_DIR"), "/../../assets/body/getavatar_body.npz"));

impl BodyModel {
    /// The embedded open default body.
    #[cfg(feature = "embedded-body")]
    pub fn default_body() -> Result<Self, BodyModelError> {
        Self::from_npz_bytes(DEFAULT_BODY_NPZ)
    }

    pub fn num_vertices(&self) -> usize {
        self.v_template.len()
    }

    /// Load from the bytes of an SMPL-layout `.npz`.
    pub fn from_npz_bytes(bytes: &[u8]) -> Result<Self, BodyModelError> {
        let arrays = npz::read_npz(bytes)?;
        Self::from_arrays(&arrays)
    }

    /// Build from parsed arrays, validating every key and shape.
    pub fn from_arrays(a: &BTreeMap<String, NpyArray>) -> Result<Self, BodyModelError> {
        let get =
            |key: &'static str| a.get(key).ok_or_else(|| BodyModelError::from(NpzError::Missing(key.to_string())));
        let shape_is = |key: &'static str, arr: &NpyArray, want: &[Option<usize>]| -> Result<(), BodyModelError> {
            let ok =
                arr.shape.len() == want.len() && arr.shape.iter().zip(want).all(|(s, w)| w.is_none_or(|w| *s == w));
            if ok {
                Ok(())
            } else {
                let want_s: Vec<String> = want.iter().map(|w| w.map_or("_".to_string(), |w| w.to_string())).collect();
                Err(invalid(key, format!("shape {:?}, expected ({})", arr.shape, want_s.join(", "))))
            }
        };

        let vt_arr = get("v_template")?;
        shape_is("v_template", vt_arr, &[None, Some(3)])?;
        let nv = vt_arr.shape[0];
        if nv == 0 {
            return Err(invalid("v_template", "no vertices"));
        }
        let v = vt_arr.to_f32();
        if v.iter().any(|x| !x.is_finite()) {
            return Err(invalid("v_template", "non-finite coordinates"));
        }
        let v_template: Vec<Vec3> = v.chunks_exact(3).map(Vec3::from_slice).collect();

        let f_arr = get("f")?;
        shape_is("f", f_arr, &[None, Some(3)])?;
        let faces = to_triangles("f", f_arr, nv)?;

        let w_arr = get("weights")?;
        shape_is("weights", w_arr, &[Some(nv), Some(NUM_JOINTS)])?;
        let w = w_arr.to_f32();
        let weights: Vec<[f32; NUM_JOINTS]> = w
            .chunks_exact(NUM_JOINTS)
            .map(|c| {
                let mut r = [0.0; NUM_JOINTS];
                r.copy_from_slice(c);
                r
            })
            .collect();
        if weights.iter().any(|r| r.iter().any(|x| !x.is_finite())) {
            return Err(invalid("weights", "non-finite skin weights"));
        }

        let j_arr = get("J_regressor")?;
        shape_is("J_regressor", j_arr, &[Some(NUM_JOINTS), Some(nv)])?;
        let j_regressor = j_arr.to_f32();

        let k_arr = get("kintree_table")?;
        shape_is("kintree_table", k_arr, &[Some(2), Some(NUM_JOINTS)])?;
        let k = k_arr.to_i64("kintree_table")?;
        let mut parents = [-1i32; NUM_JOINTS];
        for j in 0..NUM_JOINTS {
            let id = k[NUM_JOINTS + j];
            if id != j as i64 {
                return Err(invalid(
                    "kintree_table",
                    format!("row 1 must list joints 0..23 in order; column {j} has {id}"),
                ));
            }
            let p = k[j];
            parents[j] = if j == 0 {
                -1
            } else if (0..j as i64).contains(&p) {
                p as i32
            } else {
                return Err(invalid(
                    "kintree_table",
                    format!("joint {j} has parent {p}; parents must precede their children"),
                ));
            };
        }

        let s_arr = get("shapedirs")?;
        shape_is("shapedirs", s_arr, &[Some(nv), Some(3), None])?;
        let num_betas = s_arr.shape[2];
        let shapedirs = s_arr.to_f32();

        let posedirs = match a.get("posedirs") {
            Some(p) => {
                shape_is("posedirs", p, &[Some(nv), Some(3), Some(NUM_POSE_FEATURES)])?;
                if p.is_all_zero() {
                    Vec::new()
                } else {
                    p.to_f32()
                }
            }
            None => return Err(NpzError::Missing("posedirs".into()).into()),
        };

        let (vt, ft) = match (a.get("vt"), a.get("ft")) {
            (Some(vt), Some(ft)) => {
                shape_is("vt", vt, &[None, Some(2)])?;
                shape_is("ft", ft, &[Some(faces.len()), Some(3)])?;
                let uv: Vec<Vec2> = vt.to_f32().chunks_exact(2).map(Vec2::from_slice).collect();
                let ft = to_triangles("ft", ft, uv.len())?;
                (uv, ft)
            }
            (None, None) => (Vec::new(), Vec::new()),
            (Some(_), None) => return Err(invalid("ft", "`vt` is present but `ft` is missing")),
            (None, Some(_)) => return Err(invalid("vt", "`ft` is present but `vt` is missing")),
        };

        let shape_names = match a.get("shape_names") {
            Some(n) => {
                let bytes: Vec<u8> = n.to_i64("shape_names")?.into_iter().map(|b| b as u8).collect();
                String::from_utf8_lossy(&bytes).lines().map(str::to_string).collect()
            }
            None => Vec::new(),
        };

        Ok(Self {
            v_template,
            faces,
            weights,
            j_regressor,
            parents,
            shapedirs,
            num_betas,
            posedirs,
            vt,
            ft,
            shape_names,
        })
    }

    /// The arrays of the SMPL layout (inverse of [`BodyModel::from_arrays`]).
    pub fn to_arrays(&self) -> BTreeMap<String, NpyArray> {
        let nv = self.num_vertices();
        let mut m = BTreeMap::new();
        m.insert(
            "v_template".into(),
            NpyArray::f32(vec![nv, 3], self.v_template.iter().flat_map(|v| v.to_array()).collect()),
        );
        m.insert("f".into(), NpyArray::u32(vec![self.faces.len(), 3], self.faces.iter().flatten().copied().collect()));
        m.insert(
            "weights".into(),
            NpyArray::f32(vec![nv, NUM_JOINTS], self.weights.iter().flatten().copied().collect()),
        );
        m.insert("J_regressor".into(), NpyArray::f32(vec![NUM_JOINTS, nv], self.j_regressor.clone()));
        // SMPL stores the root's parent as uint32::MAX.
        let mut k: Vec<i64> = self.parents.iter().map(|&p| if p < 0 { 4294967295 } else { p as i64 }).collect();
        k.extend(0..NUM_JOINTS as i64);
        m.insert("kintree_table".into(), NpyArray::i64(vec![2, NUM_JOINTS], k));
        m.insert("shapedirs".into(), NpyArray::f32(vec![nv, 3, self.num_betas], self.shapedirs.clone()));
        let posedirs =
            if self.has_pose_correctives() { self.posedirs.clone() } else { vec![0.0; nv * 3 * NUM_POSE_FEATURES] };
        m.insert("posedirs".into(), NpyArray::f32(vec![nv, 3, NUM_POSE_FEATURES], posedirs));
        if !self.vt.is_empty() {
            m.insert(
                "vt".into(),
                NpyArray::f32(vec![self.vt.len(), 2], self.vt.iter().flat_map(|v| v.to_array()).collect()),
            );
            m.insert("ft".into(), NpyArray::u32(vec![self.ft.len(), 3], self.ft.iter().flatten().copied().collect()));
        }
        if !self.shape_names.is_empty() {
            let bytes: Vec<i64> = self.shape_names.join("\n").bytes().map(i64::from).collect();
            m.insert(
                "shape_names".into(),
                NpyArray { shape: vec![bytes.len()], data: npz::NpyData::Int(bytes, npz::DType::U8) },
            );
        }
        m
    }

    /// Serialise as a compressed SMPL-layout `.npz`.
    pub fn to_npz_bytes(&self) -> Result<Vec<u8>, BodyModelError> {
        Ok(npz::write_npz(&self.to_arrays())?)
    }

    /// Template with shape blend shapes applied: `v_template + shapedirs · β`.
    /// Extra β entries beyond the model's components are ignored; missing ones are zero.
    pub fn shaped_vertices(&self, betas: &[f32]) -> Vec<Vec3> {
        let nb = self.num_betas.min(betas.len());
        let mut out = self.v_template.clone();
        if nb == 0 || betas[..nb].iter().all(|b| *b == 0.0) {
            return out;
        }
        for (i, v) in out.iter_mut().enumerate() {
            let mut d = [0.0f32; 3];
            for (c, dc) in d.iter_mut().enumerate() {
                let row = &self.shapedirs[(i * 3 + c) * self.num_betas..][..nb];
                *dc = row.iter().zip(betas).map(|(s, b)| s * b).sum();
            }
            *v += Vec3::from_array(d);
        }
        out
    }

    /// Rest joint locations regressed from (shaped) vertices: `J_regressor · v`.
    pub fn regress_joints(&self, vertices: &[Vec3]) -> [Vec3; NUM_JOINTS] {
        let nv = vertices.len();
        let mut j = [Vec3::ZERO; NUM_JOINTS];
        for (k, jk) in j.iter_mut().enumerate() {
            let row = &self.j_regressor[k * nv..(k + 1) * nv];
            *jk = row.iter().zip(vertices).filter(|(w, _)| **w != 0.0).fold(Vec3::ZERO, |acc, (w, v)| acc + *w * *v);
        }
        j
    }

    /// Whether any pose-corrective blend shape is non-zero.
    pub fn has_pose_correctives(&self) -> bool {
        !self.posedirs.is_empty()
    }
}

fn to_triangles(key: &'static str, arr: &NpyArray, n: usize) -> Result<Vec<[u32; 3]>, BodyModelError> {
    let idx = arr.to_i64(key)?;
    if let Some(bad) = idx.iter().find(|&&i| i < 0 || i as usize >= n) {
        return Err(invalid(key, format!("index {bad} out of range 0..{n}")));
    }
    Ok(idx.chunks_exact(3).map(|c| [c[0] as u32, c[1] as u32, c[2] as u32]).collect())
}
