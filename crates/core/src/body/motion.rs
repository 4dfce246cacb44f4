//! Motion clips: sequences of body poses θ (24 joint rotations, axis-angle, SMPL layout) and
//! root translations at a fixed frame rate, played by re-posing (paper eq. 1) and exported
//! as glTF animations ([`crate::export::gltf_export`]).
//!
//! Sources:
//! - built-in clips ([`BUILTIN_CLIPS`]: `walk`, `turn`, `wave`), keyframed poses interpolated
//!   by SQUAD (Shoemake's spherical cubic: C¹ through the keys, no gimbal), looping where the
//!   clip loops;
//! - SMPL/AMASS `.npz` files ([`Motion::from_amass_npz`]): `poses` N×72 (SMPL) or N×156
//!   (SMPL-H: the first 66 numbers are the 22 body joints; SMPL's two hand joints are set to
//!   zero), `trans` N×3, `mocap_framerate` (or `mocap_frame_rate`), resampled to
//!   [`MOTION_FPS`]. AMASS is z-up; the root is turned into this project's y-up world
//!   (docs/conventions.md) and the clip starts at the body's rest position. The file's `betas` are not
//!   applied: a motion plays on the avatar's own body.
//!
//! Limits: at most [`MAX_FRAMES`] frames after resampling (5 minutes; longer files are cut
//! there, and the clip says so in its notes). NaN/∞, wrong shapes, missing arrays or a frame
//! rate outside (0, 1000] fps are errors that name the array.

use glam::{Quat, Vec3};

use crate::body::body_model::NUM_JOINTS;
use crate::body::skinning::{axis_angle_to_quat as quat, quat_to_axis_angle as to_axis_angle, BodyParams};
use crate::io::npz::{read_npz_arrays, NpyArray, NpzError};

/// Frame rate of every clip, frames per second.
pub const MOTION_FPS: f32 = 30.0;
/// Most frames a clip keeps (5 minutes at [`MOTION_FPS`]).
pub const MAX_FRAMES: usize = 9000;
/// Names of the built-in clips.
pub const BUILTIN_CLIPS: [&str; 3] = ["walk", "turn", "wave"];

/// A clip: one pose and root translation per frame at [`MOTION_FPS`].
#[derive(Clone, Debug, PartialEq)]
pub struct Motion {
    pub name: String,
    /// Per frame, each joint's local rotation (axis-angle, radians).
    pub poses: Vec<[Vec3; NUM_JOINTS]>,
    /// Per frame, the root translation (metres, y-up world).
    pub trans: Vec<Vec3>,
    /// Whether the last frame leads back into the first.
    pub looping: bool,
    /// What was changed on loading (cut, resampled, hands zeroed, …), for the user.
    pub notes: Vec<String>,
}

#[derive(Debug, thiserror::Error)]
pub enum MotionError {
    #[error("{0}")]
    Npz(#[from] NpzError),
    #[error("the motion file has no `{0}` array (an SMPL/AMASS .npz has `poses`, `trans` and `mocap_framerate`)")]
    Missing(&'static str),
    #[error("`{key}` has shape {shape:?}, expected {expected}")]
    Shape { key: &'static str, shape: Vec<usize>, expected: String },
    #[error("`{key}` holds a non-finite number (NaN or ∞) at frame {frame}")]
    NonFinite { key: &'static str, frame: usize },
    #[error("the frame rate {0} fps is not in (0, 1000]")]
    FrameRate(f64),
    #[error("the motion has no frames")]
    Empty,
    #[error("unknown motion clip `{0}`; built-in clips: walk, turn, wave")]
    UnknownClip(String),
}

impl Motion {
    /// Number of frames.
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    /// Length in seconds (the last frame's time; a looping clip's last frame leads back into
    /// the first after one more frame interval).
    pub fn duration(&self) -> f32 {
        self.poses.len().saturating_sub(1) as f32 / MOTION_FPS
    }

    /// Frame `k`'s body parameters with shape `betas`.
    pub fn params(&self, k: usize, betas: &[f32]) -> BodyParams {
        let k = k.min(self.poses.len().saturating_sub(1));
        BodyParams { pose: self.poses[k], betas: betas.to_vec(), transl: self.trans[k] }
    }

    /// The pose at time `t` seconds (looping clips wrap, others hold their ends), joint
    /// rotations interpolated by slerp between frames.
    pub fn sample(&self, t: f32, betas: &[f32]) -> BodyParams {
        let n = self.poses.len();
        if n == 0 {
            return BodyParams { betas: betas.to_vec(), ..BodyParams::default() };
        }
        let span = if self.looping { n as f32 } else { (n - 1) as f32 };
        let mut f = t.max(0.0) * MOTION_FPS;
        f = if self.looping { f.rem_euclid(span.max(1.0)) } else { f.min(span) };
        let (i, a) = (f.floor() as usize % n, f.fract());
        let j = if self.looping { (i + 1) % n } else { (i + 1).min(n - 1) };
        let mut pose = [Vec3::ZERO; NUM_JOINTS];
        for (k, p) in pose.iter_mut().enumerate() {
            *p = to_axis_angle(quat(self.poses[i][k]).slerp(quat(self.poses[j][k]), a));
        }
        BodyParams { pose, betas: betas.to_vec(), transl: self.trans[i].lerp(self.trans[j], a) }
    }

    /// A built-in clip by name ([`BUILTIN_CLIPS`]).
    pub fn builtin(name: &str) -> Result<Motion, MotionError> {
        let (keys, period, looping) = match name {
            "walk" => (walk_keys(), 1.1, true),
            "turn" => (turn_keys(), 4.0, false),
            "wave" => (wave_keys(), 1.6, true),
            other => return Err(MotionError::UnknownClip(other.to_string())),
        };
        Ok(from_keys(name, &keys, period, looping))
    }

    /// An SMPL/AMASS motion file (see the module docs for what it must hold).
    pub fn from_amass_npz(bytes: &[u8], name: &str) -> Result<Motion, MotionError> {
        let keys = ["poses", "trans", "mocap_framerate", "mocap_frame_rate", "betas"];
        let arrays = read_npz_arrays(bytes, Some(&keys))?;
        let poses = arrays.get("poses").ok_or(MotionError::Missing("poses"))?;
        let width = match poses.shape.as_slice() {
            [_, w @ (72 | 156)] => *w,
            _ => {
                return Err(MotionError::Shape {
                    key: "poses",
                    shape: poses.shape.clone(),
                    expected: "N×72 (SMPL) or N×156 (SMPL-H)".into(),
                })
            }
        };
        let n = poses.shape[0];
        if n == 0 {
            return Err(MotionError::Empty);
        }
        let trans = arrays.get("trans").ok_or(MotionError::Missing("trans"))?;
        if trans.shape != [n, 3] {
            return Err(MotionError::Shape { key: "trans", shape: trans.shape.clone(), expected: format!("{n}×3") });
        }
        let rate = arrays
            .get("mocap_framerate")
            .or_else(|| arrays.get("mocap_frame_rate"))
            .ok_or(MotionError::Missing("mocap_framerate"))?;
        let fps = scalar(rate).ok_or_else(|| MotionError::Shape {
            key: "mocap_framerate",
            shape: rate.shape.clone(),
            expected: "one number".into(),
        })?;
        if !(fps > 0.0 && fps <= 1000.0) {
            return Err(MotionError::FrameRate(fps));
        }
        let p = poses.to_f64();
        let t = trans.to_f64();
        let mut notes = Vec::new();
        let mut src_poses = Vec::with_capacity(n);
        let mut src_trans = Vec::with_capacity(n);
        // z-up → y-up: a turn of −90° about x.
        let up = Quat::from_rotation_x(-std::f32::consts::FRAC_PI_2);
        for f in 0..n {
            let row = &p[f * width..(f + 1) * width];
            if row.iter().any(|x| !x.is_finite()) {
                return Err(MotionError::NonFinite { key: "poses", frame: f });
            }
            let tr = &t[f * 3..f * 3 + 3];
            if tr.iter().any(|x| !x.is_finite()) {
                return Err(MotionError::NonFinite { key: "trans", frame: f });
            }
            let mut pose = [Vec3::ZERO; NUM_JOINTS];
            let joints = if width == 72 { NUM_JOINTS } else { 22 };
            for (j, pj) in pose.iter_mut().enumerate().take(joints) {
                *pj = Vec3::new(row[3 * j] as f32, row[3 * j + 1] as f32, row[3 * j + 2] as f32);
            }
            pose[0] = to_axis_angle(up * quat(pose[0]));
            src_poses.push(pose);
            src_trans.push(up * Vec3::new(tr[0] as f32, tr[1] as f32, tr[2] as f32));
        }
        if width == 156 {
            notes.push("SMPL-H file: the 22 body joints are used, SMPL's hand joints are left straight".into());
        }
        if arrays.contains_key("betas") {
            notes.push("the file's body shape (betas) is not applied: the motion plays on the avatar's body".into());
        }
        // Start where the body stands at rest (AMASS places people anywhere in its room, and
        // SMPL's root turns about the origin, not the pelvis: the constant that the z-up → y-up
        // turn adds to the pelvis drops out with the first frame's translation).
        let start = src_trans[0];
        for tr in &mut src_trans {
            *tr -= start;
        }
        let (mut poses, mut trans) = resample(&src_poses, &src_trans, fps as f32, MOTION_FPS);
        if (fps as f32 - MOTION_FPS).abs() > 1e-3 {
            notes.push(format!("resampled from {fps} fps to {MOTION_FPS} fps ({n} → {} frames)", poses.len()));
        }
        if poses.len() > MAX_FRAMES {
            notes.push(format!(
                "cut to the first {MAX_FRAMES} frames ({} s) of {}",
                MAX_FRAMES as f32 / MOTION_FPS,
                poses.len()
            ));
            poses.truncate(MAX_FRAMES);
            trans.truncate(MAX_FRAMES);
        }
        Ok(Motion { name: name.to_string(), poses, trans, looping: false, notes })
    }
}

impl Motion {
    /// The clip as an SMPL/AMASS `.npz` that [`Motion::from_amass_npz`] reads back: `poses`
    /// N×72 and `trans` N×3 (z-up, as AMASS), `mocap_framerate` ([`MOTION_FPS`]), and `betas`
    /// when given (the body the motion was fitted on; players use their own).
    pub fn to_amass_npz(&self, betas: Option<&[f32]>) -> Result<Vec<u8>, MotionError> {
        if self.poses.is_empty() {
            return Err(MotionError::Empty);
        }
        // y-up → z-up: a turn of +90° about x (the reader turns back by −90°).
        let down = Quat::from_rotation_x(std::f32::consts::FRAC_PI_2);
        let mut poses = Vec::with_capacity(self.len() * 72);
        let mut trans = Vec::with_capacity(self.len() * 3);
        for (p, t) in self.poses.iter().zip(&self.trans) {
            for (j, r) in p.iter().enumerate() {
                let r = if j == 0 { to_axis_angle(down * quat(*r)) } else { *r };
                poses.extend(r.to_array().map(f64::from));
            }
            trans.extend((down * *t).to_array().map(f64::from));
        }
        let mut arrays = std::collections::BTreeMap::new();
        arrays.insert("poses".to_string(), NpyArray::f64(vec![self.len(), 72], poses));
        arrays.insert("trans".to_string(), NpyArray::f64(vec![self.len(), 3], trans));
        arrays.insert("mocap_framerate".to_string(), NpyArray::f64(vec![], vec![f64::from(MOTION_FPS)]));
        if let Some(b) = betas {
            arrays.insert("betas".to_string(), NpyArray::f32(vec![b.len()], b.to_vec()));
        }
        Ok(crate::io::npz::write_npz(&arrays)?)
    }
}

/// A 0-d or one-element array's number.
fn scalar(a: &NpyArray) -> Option<f64> {
    (a.len() == 1).then(|| a.to_f64()[0])
}

/// Resample poses (slerp) and translations (lerp) from `src_fps` to `dst_fps`, first frame
/// kept, last frame not passed.
pub(crate) fn resample(
    poses: &[[Vec3; NUM_JOINTS]],
    trans: &[Vec3],
    src_fps: f32,
    dst_fps: f32,
) -> (Vec<[Vec3; NUM_JOINTS]>, Vec<Vec3>) {
    let n = poses.len();
    if (src_fps - dst_fps).abs() <= 1e-3 || n == 1 {
        return (poses.to_vec(), trans.to_vec());
    }
    let duration = (n - 1) as f64 / src_fps as f64;
    // Only the frames that will be kept are interpolated (a 100 k-frame file stays cheap).
    let m = ((duration * dst_fps as f64).floor() as usize + 1).min(MAX_FRAMES + 1);
    let mut out_p = Vec::with_capacity(m);
    let mut out_t = Vec::with_capacity(m);
    for k in 0..m {
        let f = (k as f64 / dst_fps as f64 * src_fps as f64).min((n - 1) as f64);
        let i = f.floor() as usize;
        let j = (i + 1).min(n - 1);
        let a = (f - i as f64) as f32;
        let mut pose = [Vec3::ZERO; NUM_JOINTS];
        for (q, p) in pose.iter_mut().enumerate() {
            *p = to_axis_angle(quat(poses[i][q]).slerp(quat(poses[j][q]), a));
        }
        out_p.push(pose);
        out_t.push(trans[i].lerp(trans[j], a));
    }
    (out_p, out_t)
}

/// A keyframe: time as a fraction of the clip's period, joint rotations (joints not named
/// are at rest) and the root's translation.
struct Key {
    at: f32,
    joints: Vec<(usize, Quat)>,
    trans: Vec3,
}

fn rot(turns: &[(char, f32)]) -> Quat {
    // Applied in order: the first turn acts first (rightmost in the product).
    turns.iter().fold(Quat::IDENTITY, |q, (axis, a)| {
        let r = match axis {
            'x' => Quat::from_rotation_x(*a),
            'y' => Quat::from_rotation_y(*a),
            _ => Quat::from_rotation_z(*a),
        };
        r * q
    })
}

/// Arms down by the sides, slightly bent, as in a relaxed stand.
fn arms_down(left_swing: f32, right_swing: f32) -> Vec<(usize, Quat)> {
    vec![
        (16, rot(&[('z', -1.25), ('x', left_swing)])),
        (17, rot(&[('z', 1.25), ('x', right_swing)])),
        (18, rot(&[('y', -0.25)])),
        (19, rot(&[('y', 0.25)])),
    ]
}

fn walk_keys() -> Vec<Key> {
    // One stride pair: left foot forward at 0, passing at ¼, right forward at ½, passing at ¾.
    // Arms swing against the legs; the pelvis is lowest at the contacts.
    let stride = |l_hip: f32, r_hip: f32, l_knee: f32, r_knee: f32, l_ank: f32, r_ank: f32, y: f32, twist: f32| Key {
        at: 0.0,
        joints: {
            let mut j = vec![
                (1, rot(&[('x', l_hip)])),
                (2, rot(&[('x', r_hip)])),
                (4, rot(&[('x', l_knee)])),
                (5, rot(&[('x', r_knee)])),
                (7, rot(&[('x', l_ank)])),
                (8, rot(&[('x', r_ank)])),
                (3, rot(&[('y', twist)])),
                (9, rot(&[('y', -twist)])),
            ];
            j.extend(arms_down(-0.8 * r_hip.clamp(-0.5, 0.5), -0.8 * l_hip.clamp(-0.5, 0.5)));
            j
        },
        trans: Vec3::new(0.0, y, 0.0),
    };
    let mut keys = vec![
        stride(-0.45, 0.3, 0.1, 0.25, 0.1, -0.2, -0.02, 0.08),
        stride(0.0, -0.2, 0.25, 1.0, 0.0, 0.3, 0.0, 0.0),
        stride(0.3, -0.45, 0.25, 0.1, -0.2, 0.1, -0.02, -0.08),
        stride(-0.2, 0.0, 1.0, 0.25, 0.3, 0.0, 0.0, 0.0),
    ];
    for (k, key) in keys.iter_mut().enumerate() {
        key.at = k as f32 / 4.0;
    }
    keys
}

fn turn_keys() -> Vec<Key> {
    // A full turn on the spot in four quarter steps.
    (0..=4)
        .map(|k| {
            let mut joints = arms_down(0.0, 0.0);
            joints.push((0, Quat::from_rotation_y(k as f32 * std::f32::consts::FRAC_PI_2)));
            Key { at: k as f32 / 4.0, joints, trans: Vec3::ZERO }
        })
        .collect()
}

fn wave_keys() -> Vec<Key> {
    // The right arm raised, the forearm swinging side to side; the left arm down.
    let key = |at: f32, swing: f32| {
        let mut joints = arms_down(0.0, 0.0);
        joints.retain(|(j, _)| *j != 17 && *j != 19);
        joints.push((17, rot(&[('z', -1.0)])));
        joints.push((19, rot(&[('z', -0.6 + swing)])));
        joints.push((21, rot(&[('z', 0.5 * swing)])));
        Key { at, joints, trans: Vec3::ZERO }
    };
    vec![key(0.0, 0.45), key(0.5, -0.45)]
}

/// Sample keys at [`MOTION_FPS`] over `period` seconds with SQUAD per joint; translations by
/// Catmull–Rom. Looping clips wrap (the frame at `period` is the first again and is not
/// repeated); others end on their last key.
fn from_keys(name: &str, keys: &[Key], period: f32, looping: bool) -> Motion {
    let nk = keys.len();
    let mut table = vec![[Quat::IDENTITY; NUM_JOINTS]; nk];
    for (k, key) in keys.iter().enumerate() {
        for (j, q) in &key.joints {
            table[k][*j] = q.normalize();
        }
    }
    // Same hemisphere as the previous key, so slerps take the short way.
    for k in 1..nk {
        let prev = table[k - 1];
        for (q, p) in table[k].iter_mut().zip(prev) {
            if q.dot(p) < 0.0 {
                *q = -*q;
            }
        }
    }
    let at = |k: isize| -> (usize, f32) {
        // Key index (wrapped or clamped) and its time offset in periods.
        if looping {
            let n = nk as isize;
            (k.rem_euclid(n) as usize, k.div_euclid(n) as f32)
        } else {
            (k.clamp(0, nk as isize - 1) as usize, 0.0)
        }
    };
    let q_at = |k: isize, j: usize, near: Quat| {
        let q = table[at(k).0][j];
        if q.dot(near) < 0.0 {
            -q
        } else {
            q
        }
    };
    let frames =
        if looping { (period * MOTION_FPS).round() as usize } else { (period * MOTION_FPS).round() as usize + 1 };
    let times: Vec<f32> = keys.iter().map(|k| k.at).collect();
    let mut poses = Vec::with_capacity(frames);
    let mut trans = Vec::with_capacity(frames);
    for f in 0..frames {
        let u = f as f32 / MOTION_FPS / period; // fraction of the period
                                                // Segment [k, k+1] holding u.
        let mut k = times.iter().rposition(|t| *t <= u + 1e-6).unwrap_or(0);
        if !looping && k == nk - 1 {
            k = nk.saturating_sub(2);
        }
        let t0 = times[k];
        let t1 = if k + 1 < nk { times[k + 1] } else { 1.0 + times[0] };
        let s = if t1 > t0 { ((u - t0) / (t1 - t0)).clamp(0.0, 1.0) } else { 0.0 };
        let ki = k as isize;
        let mut pose = [Vec3::ZERO; NUM_JOINTS];
        for (j, p) in pose.iter_mut().enumerate() {
            let q1 = table[k][j];
            let q2 = q_at(ki + 1, j, q1);
            let q0 = q_at(ki - 1, j, q1);
            let q3 = q_at(ki + 2, j, q2);
            *p = to_axis_angle(squad(q0, q1, q2, q3, s));
        }
        let tr = |k: isize| keys[at(k).0].trans;
        trans.push(catmull_rom(tr(ki - 1), tr(ki), tr(ki + 1), tr(ki + 2), s));
        poses.push(pose);
    }
    Motion { name: name.to_string(), poses, trans, looping, notes: Vec::new() }
}

fn quat_log(q: Quat) -> Vec3 {
    let v = Vec3::new(q.x, q.y, q.z);
    let s = v.length();
    if s < 1e-9 {
        Vec3::ZERO
    } else {
        v / s * s.atan2(q.w)
    }
}

fn quat_exp(v: Vec3) -> Quat {
    let a = v.length();
    if a < 1e-9 {
        Quat::IDENTITY
    } else {
        let s = a.sin() / a;
        Quat::from_xyzw(v.x * s, v.y * s, v.z * s, a.cos())
    }
}

/// Shoemake's inner control point of `q1` between neighbours `q0` and `q2`.
fn squad_control(q0: Quat, q1: Quat, q2: Quat) -> Quat {
    let inv = q1.conjugate();
    let l = (quat_log(inv * q2) + quat_log(inv * q0)) * -0.25;
    (q1 * quat_exp(l)).normalize()
}

/// SQUAD between `q1` and `q2` at `s ∈ [0, 1]` with neighbours `q0`, `q3`: C¹ through keys.
fn squad(q0: Quat, q1: Quat, q2: Quat, q3: Quat, s: f32) -> Quat {
    let a = squad_control(q0, q1, q2);
    let b = squad_control(q1, q2, q3);
    q1.slerp(q2, s).slerp(a.slerp(b, s), 2.0 * s * (1.0 - s)).normalize()
}

fn catmull_rom(p0: Vec3, p1: Vec3, p2: Vec3, p3: Vec3, s: f32) -> Vec3 {
    let (s2, s3) = (s * s, s * s * s);
    0.5 * ((2.0 * p1)
        + (p2 - p0) * s
        + (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3) * s2
        + (3.0 * p1 - p0 - 3.0 * p2 + p3) * s3)
}
