//! How well a fitted body matches the truth: MPJPE after Procrustes alignment (PA-MPJPE,
//! the standard 3D pose error: the fitted joints are scaled, rotated and translated onto the
//! true ones before the mean joint distance is taken, so the camera's depth ambiguity and a
//! global turn do not count); masks and their IoU; PCK between two detections.

use glam::{DMat4, DQuat, DVec4, Mat3, Mat4, Vec3, Vec4};

use super::landmarks::VISIBLE;

/// The similarity transform (scale `s`, rotation `r`, translation `t`) minimising
/// Σ‖s·r·aᵢ + t − bᵢ‖². The rotation is Horn's closed form (the unit quaternion of the largest
/// eigenvalue of a symmetric 4×4 matrix built from the cross-covariance), so it is always a
/// proper rotation, also for mirrored point sets; the eigenvector comes from repeated squaring
/// of the shifted matrix, in f64.
pub fn procrustes(a: &[Vec3], b: &[Vec3]) -> (f32, Mat3, Vec3) {
    let n = a.len().min(b.len()).max(1) as f32;
    let ca = a.iter().take(b.len()).copied().sum::<Vec3>() / n;
    let cb = b.iter().take(a.len()).copied().sum::<Vec3>() / n;
    let centred: Vec<(Vec3, Vec3)> = a.iter().zip(b).map(|(p, q)| (*p - ca, *q - cb)).collect();
    // S[i][j] = Σ pᵢ qⱼ.
    let mut m = [[0.0f64; 3]; 3];
    for (p, q) in &centred {
        let (p, q) = (p.as_dvec3().to_array(), q.as_dvec3().to_array());
        for (i, row) in m.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v += p[i] * q[j];
            }
        }
    }
    let [[sxx, sxy, sxz], [syx, syy, syz], [szx, szy, szz]] = m;
    let horn = DMat4::from_cols(
        DVec4::new(sxx + syy + szz, syz - szy, szx - sxz, sxy - syx),
        DVec4::new(syz - szy, sxx - syy - szz, sxy + syx, szx + sxz),
        DVec4::new(szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy),
        DVec4::new(sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz),
    );
    // Shifted to be positive semi-definite (every eigenvalue + ‖N‖ ≥ 0), then squared until
    // the largest eigenvalue's direction dominates every column.
    let shift = horn.to_cols_array().iter().map(|v| v * v).sum::<f64>().sqrt();
    let mut power = horn + DMat4::from_diagonal(DVec4::splat(shift.max(1e-300)));
    for _ in 0..40 {
        power = power * power;
        let norm = power.to_cols_array().iter().fold(0.0f64, |acc, v| acc.max(v.abs()));
        if !(norm > 0.0 && norm.is_finite()) {
            break;
        }
        power *= 1.0 / norm;
    }
    let col = [power.x_axis, power.y_axis, power.z_axis, power.w_axis]
        .into_iter()
        .max_by(|u, v| u.length_squared().total_cmp(&v.length_squared()))
        .unwrap_or(DVec4::X);
    // (w, x, y, z) → glam's (x, y, z, w).
    let q = DQuat::from_xyzw(col.y, col.z, col.w, col.x);
    let r = if q.length_squared() > 0.0 { Mat3::from_quat(q.normalize().as_quat()) } else { Mat3::IDENTITY };
    // Optimal scale: Σ qᵢ·(r pᵢ) / Σ‖pᵢ‖².
    let var_a: f32 = centred.iter().map(|(p, _)| p.length_squared()).sum();
    let cov: f32 = centred.iter().map(|(p, q)| q.dot(r * *p)).sum();
    let s = if var_a > 0.0 { cov / var_a } else { 1.0 };
    (s, r, cb - s * (r * ca))
}

/// Mean distance between `fitted` and `truth` joints after [`procrustes`] alignment, in the
/// joints' units (metres here).
pub fn pa_mpjpe(fitted: &[Vec3], truth: &[Vec3]) -> f32 {
    let (s, r, t) = procrustes(fitted, truth);
    let n = fitted.len().min(truth.len()).max(1) as f32;
    fitted.iter().zip(truth).map(|(p, q)| (s * (r * *p) + t - *q).length()).sum::<f32>() / n
}

/// A mesh's mask at `size`² through `view_proj` (CPU rasteriser), 0 or 1 per pixel.
pub fn body_mask(vertices: &[Vec3], faces: &[[u32; 3]], view_proj: Mat4, size: usize) -> Vec<f32> {
    body_mask_rect(vertices, faces, view_proj, size, size)
}

/// A mesh's mask at `width × height` through `view_proj` (CPU rasteriser), 0 or 1 per
/// pixel, row-major from the top left (e.g. the fitted body over a photo through
/// `BodyFit::photo_view_proj`).
pub fn body_mask_rect(vertices: &[Vec3], faces: &[[u32; 3]], view_proj: Mat4, width: usize, height: usize) -> Vec<f32> {
    let clip: Vec<Vec4> = vertices.iter().map(|v| view_proj * v.extend(1.0)).collect();
    let r = crate::render::rasterize::rasterize(&clip, faces, width, height);
    r.triangle.iter().map(|t| if *t >= 0 { 1.0 } else { 0.0 }).collect()
}

/// Intersection over union of two masks thresholded at ½ (1 for two empty masks).
pub fn mask_iou(a: &[f32], b: &[f32]) -> f32 {
    let (mut inter, mut union) = (0usize, 0usize);
    for (x, y) in a.iter().zip(b) {
        let (x, y) = (*x >= 0.5, *y >= 0.5);
        inter += (x && y) as usize;
        union += (x || y) as usize;
    }
    if union == 0 {
        1.0
    } else {
        inter as f32 / union as f32
    }
}

/// PCK, the paper's pose metric (Sec. 4.1): the share of the reference detection's seen
/// landmarks (visibility ≥ ½) that the test detection puts within `threshold` × the reference
/// person's size (the long side of the box around its seen landmarks); a landmark the test did
/// not see counts as wrong, and without a test detection every landmark does. Points are in
/// one image's pixels. Returns (share, landmarks compared, distance threshold in pixels), or
/// None when the reference saw fewer than two landmarks.
pub fn pck(
    reference: &[([f32; 2], f32)],
    test: Option<&[([f32; 2], f32)]>,
    threshold: f32,
) -> Option<(f32, usize, f32)> {
    let seen: Vec<(usize, [f32; 2])> =
        reference.iter().enumerate().filter(|(_, (_, v))| *v >= VISIBLE).map(|(i, (p, _))| (i, *p)).collect();
    if seen.len() < 2 {
        return None;
    }
    let (lo, hi) = seen.iter().fold(([f32::MAX; 2], [f32::MIN; 2]), |(lo, hi), (_, p)| {
        ([lo[0].min(p[0]), lo[1].min(p[1])], [hi[0].max(p[0]), hi[1].max(p[1])])
    });
    let limit = threshold * (hi[0] - lo[0]).max(hi[1] - lo[1]);
    let correct = seen
        .iter()
        .filter(|(i, p)| {
            test.and_then(|t| t.get(*i))
                .is_some_and(|(q, v)| *v >= VISIBLE && (q[0] - p[0]).hypot(q[1] - p[1]) <= limit)
        })
        .count();
    Some((correct as f32 / seen.len() as f32, seen.len(), limit))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::body::body_model::BodyModel;
    use crate::body::pose_library::PoseLibrary;
    use crate::body::skinning::pose_body;
    use crate::util::rng::Rng;
    use glam::Quat;

    fn joints(pose: &str) -> Vec<Vec3> {
        let model = BodyModel::default_body().unwrap();
        pose_body(&model, &PoseLibrary::builtin().params(pose, &[]).unwrap()).kinematics.posed_joints.to_vec()
    }

    #[test]
    fn a_similarity_transform_costs_nothing_and_noise_costs_its_size() {
        let truth = joints("walking");
        let q = Quat::from_axis_angle(Vec3::new(0.3, 1.0, -0.2).normalize(), 2.4);
        let moved: Vec<Vec3> = truth.iter().map(|p| 1.7 * (q * *p) + Vec3::new(0.4, -1.0, 2.3)).collect();
        let (s, r, _) = procrustes(&moved, &truth);
        assert!((s - 1.0 / 1.7).abs() < 1e-4, "scale {s}");
        assert!((r * (q * Vec3::X) - Vec3::X).length() < 1e-4, "the rotation undoes q");
        assert!(pa_mpjpe(&moved, &truth) < 1e-4, "{}", pa_mpjpe(&moved, &truth));
        // Independent 2 cm noise per coordinate: the error is about its expected norm (≈ 3.2 cm),
        // a little less as the alignment absorbs part of it.
        let mut rng = Rng::new(5, 1);
        let noisy: Vec<Vec3> =
            moved.iter().map(|p| *p + 1.7 * 0.02 * Vec3::new(rng.normal(), rng.normal(), rng.normal())).collect();
        let e = pa_mpjpe(&noisy, &truth);
        assert!((0.015..0.035).contains(&e), "{e}");
        // A different pose is not aligned away.
        assert!(pa_mpjpe(&joints("sitting"), &truth) > 0.05);
    }

    #[test]
    fn pck_counts_the_seen_landmarks_within_a_tenth_of_the_persons_size() {
        // A person 200 px tall: the threshold is 20 px.
        let reference: Vec<([f32; 2], f32)> =
            (0..5).map(|i| ([100.0, 100.0 + 50.0 * i as f32], 0.9)).chain([([0.0, 0.0], 0.1)]).collect();
        let (share, n, limit) = pck(&reference, Some(&reference), 0.1).unwrap();
        assert_eq!((share, n, limit), (1.0, 5, 20.0), "the hidden landmark is not compared");
        let mut test = reference.clone();
        test[0].0[0] += 19.0; // within
        test[1].0[1] += 21.0; // outside
        test[2].1 = 0.2; // not seen by the test: wrong
        assert_eq!(pck(&reference, Some(&test), 0.1).unwrap().0, 3.0 / 5.0, "0, 3 and 4 are correct");
        assert_eq!(pck(&reference, None, 0.1).unwrap().0, 0.0, "no detection: nothing correct");
        assert!(pck(&reference[..1], Some(&test), 0.1).is_none());
    }

    #[test]
    fn a_mirrored_body_is_not_aligned_by_a_reflection() {
        let truth = joints("walking");
        let mirrored: Vec<Vec3> = truth.iter().map(|p| Vec3::new(-p.x, p.y, p.z)).collect();
        let (_, r, _) = procrustes(&mirrored, &truth);
        assert!((r.determinant() - 1.0).abs() < 1e-4, "a proper rotation, det {}", r.determinant());
        assert!(pa_mpjpe(&mirrored, &truth) > 0.01, "left and right differ");
    }
}
