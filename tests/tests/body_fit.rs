//! Photo → body: the differentiable body model against the CPU reference (values and
//! finite-difference gradients), and the fit's synthetic round trip: bodies in poses that
//! are neither in the pose library nor drawn by `synth-scans` (squat, lunge, kick, twisted
//! torso, crossed arms), photographed by known cameras, detected with noise, fitted:
//! PA-MPJPE over the 24 joints ≤ 60 mm and the fitted body's silhouette IoU against the
//! true body's ≥ 0.9, in the photo, through the fit's reported camera and framing.

use std::sync::Arc;

use getavatar_core::body::body_fit::fit::{BodyFit, BodyFitter, FitInput, FitOptions};
use getavatar_core::body::body_fit::landmarks::SegmentationMask;
use getavatar_core::body::body_fit::metrics::{body_mask, mask_iou, pa_mpjpe};
use getavatar_core::body::body_fit::synthetic::{detect, unseen_poses, UNSEEN_POSE_CAMERAS};
use getavatar_core::body::skinning::{axis_angle_to_matrix, pose_body};
use getavatar_core::burn::tensor::{Device, Tensor, TensorData};
use getavatar_core::generator::readback::block_on_ready;
use getavatar_core::render::camera::reference_fov_y;
use getavatar_core::render::diff::body_model::{rodrigues, Skeleton, VertexSet};
use getavatar_core::util::rng::Rng;
use getavatar_core::{BodyModel, BodyParams, NUM_JOINTS};
use glam::Vec3;

mod common;
use common::{central_difference, cpu, values};

fn theta_tensor(p: &BodyParams, dev: &getavatar_core::burn::tensor::Device) -> Tensor<2> {
    Tensor::from_data(TensorData::new(p.theta().to_vec(), [NUM_JOINTS, 3]), dev)
}

fn random_params(rng: &mut Rng, scale: f32, betas: usize) -> BodyParams {
    let mut p = BodyParams::default();
    for r in p.pose.iter_mut() {
        *r = Vec3::new(rng.normal(), rng.normal(), rng.normal()) * scale;
    }
    p.betas = (0..betas).map(|_| rng.normal()).collect();
    p
}

#[test]
fn rodrigues_matches_glam_and_is_smooth_at_zero() {
    let dev = cpu();
    let rs = [Vec3::ZERO, Vec3::new(0.3, -0.2, 0.9), Vec3::new(0.0, 3.0, 0.0), Vec3::new(1e-5, 0.0, -2e-5)];
    let flat: Vec<f32> = rs.iter().flat_map(|r| r.to_array()).collect();
    let m = values(rodrigues(Tensor::from_data(TensorData::new(flat, [4, 3]), &dev)));
    for (k, r) in rs.iter().enumerate() {
        let want = axis_angle_to_matrix(*r);
        for i in 0..3 {
            for j in 0..3 {
                // Row-major rows i, columns j; glam's col(j)[i].
                let got = m[k * 9 + i * 3 + j];
                assert!((got - want.col(j)[i]).abs() < 1e-5, "{r}: ({i},{j}) {got} vs {}", want.col(j)[i]);
            }
        }
    }
    // d R / d r at 0 is [dr]×: the (0, 1) entry is −r_z.
    let ad = dev.autodiff();
    let r = Tensor::<2>::from_data(TensorData::new(vec![0.0f32; 3], [1, 3]), &ad).require_grad();
    let entry01 = rodrigues(r.clone()).reshape([9]).narrow(0, 1, 1).sum();
    let g = values(r.grad(&entry01.backward()).expect("gradient"));
    assert!((g[2] + 1.0).abs() < 1e-4 && g[0].abs() < 1e-4 && g[1].abs() < 1e-4, "{g:?}");
}

#[test]
fn the_differentiable_body_poses_like_the_reference() {
    let model = BodyModel::default_body().unwrap();
    let dev = cpu();
    let skel = Skeleton::new(&model, 12, &dev);
    let all = VertexSet::all(&model, &skel, &dev);
    let mut rng = Rng::new(5, 1);
    for _ in 0..3 {
        let p = random_params(&mut rng, 0.5, 12);
        let betas = Tensor::<2>::from_data(TensorData::new(p.betas.clone(), [1, 12]), &dev);
        let posed = skel.forward(theta_tensor(&p, &dev), &betas);
        let want = pose_body(&model, &p);
        let j = values(posed.joints.clone());
        for (k, w) in want.kinematics.posed_joints.iter().enumerate() {
            let got = Vec3::from_slice(&j[k * 3..]);
            assert!((got - *w).length() < 2e-5, "joint {k}: {got} vs {w}");
        }
        let v = values(all.pose(&posed, &betas, &skel));
        let worst = want
            .vertices
            .iter()
            .enumerate()
            .map(|(i, w)| (Vec3::from_slice(&v[i * 3..]) - *w).length())
            .fold(0.0f32, f32::max);
        assert!(worst < 5e-5, "worst vertex {worst} m");
        // A selection of the set poses its vertices exactly as the whole set does.
        let ids = [6889u32, 0, 3500, 17, 3500];
        let sub = values(all.select(&ids).pose(&posed, &betas, &skel));
        for (k, &i) in ids.iter().enumerate() {
            assert_eq!(sub[k * 3..k * 3 + 3], v[i as usize * 3..i as usize * 3 + 3], "vertex {i}");
        }
    }
}

#[test]
fn body_gradients_match_finite_differences() {
    let model = BodyModel::default_body().unwrap();
    let ad = cpu().autodiff();
    let skel = Skeleton::new(&model, 4, &ad);
    let ids = [0u32, 5000, 9000, 13000];
    let verts = VertexSet::new(&model, &ids, &skel, &ad);
    let mut rng = Rng::new(9, 2);
    let p = random_params(&mut rng, 0.4, 4);
    // A fixed random linear read-out of joints and vertices.
    let wj: Vec<f32> = rng.normals(NUM_JOINTS * 3);
    let wv: Vec<f32> = rng.normals(ids.len() * 3);
    let f = |theta: Tensor<2>, betas: Tensor<2>| {
        let dev = theta.device();
        let posed = skel.forward(theta, &betas);
        let v = verts.pose(&posed, &betas, &skel);
        let a = Tensor::<2>::from_data(TensorData::new(wj.clone(), [NUM_JOINTS, 3]), &dev);
        let b = Tensor::<2>::from_data(TensorData::new(wv.clone(), [ids.len(), 3]), &dev);
        (posed.joints * a).sum() + (v * b).sum()
    };
    let theta = theta_tensor(&p, &ad).require_grad();
    let betas = Tensor::<2>::from_data(TensorData::new(p.betas.clone(), [1, 4]), &ad).require_grad();
    let grads = f(theta.clone(), betas.clone()).backward();
    let (gt, gb) = (values(theta.grad(&grads).unwrap()), values(betas.grad(&grads).unwrap()));
    let x: Vec<f32> = p.theta().iter().copied().chain(p.betas.iter().copied()).collect();
    let eval = |x: &[f32]| {
        let t = Tensor::<2>::from_data(TensorData::new(x[..72].to_vec(), [NUM_JOINTS, 3]), &ad);
        let b = Tensor::<2>::from_data(TensorData::new(x[72..].to_vec(), [1, 4]), &ad);
        values(f(t, b))[0] as f64
    };
    let mut worst = 0.0f64;
    for i in (0..x.len()).step_by(5).chain(72..76) {
        let fd = central_difference(&eval, &x, i, 1e-3);
        let g = if i < 72 { gt[i] } else { gb[i - 72] } as f64;
        worst = worst.max((fd - g).abs() / (1.0 + fd.abs()));
    }
    assert!(worst < 5e-3, "worst relative gradient error {worst}");
}

/// The fitted body's mask in the photo: the fit's camera on its crop, the crop placed in the
/// photo by the framing (a 2D similarity of clip space).
fn fitted_mask_in_photo(model: &BodyModel, fit: &BodyFit, size: usize) -> Vec<f32> {
    let posed = pose_body(model, &fit.body_params());
    body_mask(&posed.vertices, &model.faces, fit.photo_view_proj(), size)
}

/// The default body, the CPU autodiff device and the detector-noise stream of `seed`.
fn fit_setup(seed: u64) -> (Arc<BodyModel>, Device, Rng) {
    (Arc::new(BodyModel::default_body().unwrap()), cpu().autodiff(), Rng::new(seed, 1))
}

#[test]
fn synthetic_round_trip_recovers_unseen_poses() {
    let (model, dev, mut rng) = fit_setup(20);
    let size = 512;
    let mut report = Vec::new();
    for ((name, truth), cam) in unseen_poses().into_iter().zip(UNSEEN_POSE_CAMERAS.map(|c| c.camera())) {
        let det = detect(&model, &truth, cam.world_to_camera(), size, 2.0, 0.02, &mut rng).unwrap();
        let opts = FitOptions::default();
        let mask = SegmentationMask { width: size, height: size, data: det.mask.clone() };
        let input = FitInput::from_detection(&det.result, size, size, Some(&mask), &model, &opts).unwrap();
        let mut fitter = BodyFitter::new(model.clone(), input, opts, &dev).unwrap();
        let fit = block_on_ready(async {
            fitter.run().await?;
            fitter.finish().await
        })
        .unwrap();
        let fitted = pose_body(&model, &fit.body_params()).kinematics.posed_joints;
        let true_joints = pose_body(&model, &truth).kinematics.posed_joints;
        let err = pa_mpjpe(&fitted, &true_joints);
        let iou = mask_iou(&fitted_mask_in_photo(&model, &fit, size), &det.mask);
        report.push(format!(
            "{name}: PA-MPJPE {:.1} mm, IoU {iou:.3} (fit's own {:.3}), {:.2} px mean",
            err * 1000.0,
            fit.residuals.mask_iou.unwrap_or(f32::NAN),
            fit.residuals.mean_px
        ));
        eprintln!("{}", report.last().unwrap());
        assert!(err <= 0.060 && iou >= 0.9, "{}", report.join("\n"));
        // The keypoints it reports: within 2 % of the body's height of the detections.
        assert!(fit.residuals.relative_to_height < 0.02, "{}", report.join("\n"));
        assert!((fit.fov_y - reference_fov_y()).abs() < 1e-6);
    }
}

/// A re-fit from the user's corrected pose (`BodyFitter::start_from`) starts from that pose:
/// with the torso stage only (which leaves the limbs as they start), the re-fit from the true
/// limbs ends on them while the first fit keeps the detector-based start's error, and the
/// stages run again from the first.
#[test]
fn refit_starts_from_the_corrected_pose() {
    let (model, dev, mut rng) = fit_setup(21);
    let size = 256;
    let (name, truth) = unseen_poses().into_iter().find(|(n, _)| *n == "arms_crossed").unwrap();
    let cam = UNSEEN_POSE_CAMERAS[4].camera();
    let det = detect(&model, &truth, cam.world_to_camera(), size, 2.0, 0.02, &mut rng).unwrap();
    let opts = FitOptions { iterations: [20, 0, 0], ..FitOptions::default() };
    let input = FitInput::from_detection(&det.result, size, size, None, &model, &opts).unwrap();
    let mut fitter = BodyFitter::new(model.clone(), input, opts, &dev).unwrap();
    let true_joints = pose_body(&model, &truth).kinematics.posed_joints;
    let error = |fitter: &mut BodyFitter| {
        let fit = block_on_ready(async {
            fitter.run().await?;
            fitter.finish().await
        })
        .unwrap();
        let fitted = pose_body(&model, &fit.body_params()).kinematics.posed_joints;
        (pa_mpjpe(&fitted, &true_joints), fit)
    };
    let (first, _) = error(&mut fitter);
    let mut corrected = truth.clone();
    corrected.pose[0] = Vec3::ZERO; // the user corrects limbs, not the turn towards the camera
    fitter.start_from(&corrected);
    let (second, fit) = error(&mut fitter);
    eprintln!("{name}: short fit {:.1} mm, re-fit from the true limbs {:.1} mm", first * 1000.0, second * 1000.0);
    assert!(second < 0.005 && second < 0.5 * first, "first {first}, re-fit {second}");
    assert!(fit.residuals.stage_loss[0].is_some());
}

/// The fit refined on a clothed outline (`body_fit::refit`): a person 4 cm wider than the bare
/// body all round (the body's surface pushed out along its normals, standing in for clothes),
/// fitted first with the bare body, which the silhouette stage stretches towards the clothes,
/// then refined with that outline: the outline posed by the refined fit covers the person
/// better than posed by the first fit, the body's shape comes back in towards the truth, and
/// the pose stays where the landmarks put it.
#[test]
fn a_fit_refined_on_the_clothed_outline_covers_the_clothed_person() {
    use getavatar_core::body::body_fit::refit::{refit_on_outline, OutlineMesh, RefitOptions};
    use getavatar_core::body::skinning::vertex_normals;
    let (model, dev, mut rng) = fit_setup(22);
    let size = 256;
    let (name, truth) = unseen_poses().into_iter().find(|(n, _)| *n == "lunge").unwrap();
    let cam = UNSEEN_POSE_CAMERAS[1].camera();
    let rest = pose_body(&model, &BodyParams::default());
    let normals = vertex_normals(&rest.vertices, &model.faces);
    let outline = OutlineMesh {
        rest: rest.vertices.iter().zip(&normals).map(|(v, n)| *v + *n * 0.04).collect(),
        body_vertex: (0..rest.vertices.len() as u32).collect(),
        faces: model.faces.clone(),
    };
    // The outline posed as the body of `params` (each point follows its body vertex).
    let posed_outline = |params: &BodyParams| -> Vec<Vec3> {
        let posed = pose_body(&model, params);
        (0..outline.rest.len())
            .map(|i| {
                let shape = posed.shaped[i] - model.v_template[i];
                posed.vertex_transforms[i].transform_point3(outline.rest[i] + shape)
            })
            .collect()
    };
    let det = detect(&model, &truth, cam.world_to_camera(), size, 2.0, 0.02, &mut rng).unwrap();
    let proj = glam::Mat4::perspective_rh_gl(reference_fov_y(), 1.0, 0.1, 100.0) * cam.world_to_camera();
    let person = body_mask(&posed_outline(&truth), &outline.faces, proj, size);
    let opts = FitOptions::default();
    let mask = SegmentationMask { width: size, height: size, data: person.clone() };
    let input = FitInput::from_detection(&det.result, size, size, Some(&mask), &model, &opts).unwrap();
    let mut fitter = BodyFitter::new(model.clone(), input, opts.clone(), &dev).unwrap();
    let fit = block_on_ready(async {
        fitter.run().await?;
        fitter.finish().await
    })
    .unwrap();
    let crop = fit.framing.resample_mask(&person, size, size, opts.silhouette_size);
    let refined = block_on_ready(refit_on_outline(
        model.clone(),
        &fit,
        &crop,
        opts.silhouette_size,
        &outline,
        &RefitOptions::default(),
        &dev,
    ))
    .unwrap();
    let cover = |f: &BodyFit| {
        mask_iou(&body_mask(&posed_outline(&f.body_params()), &outline.faces, f.photo_view_proj(), size), &person)
    };
    let true_joints = pose_body(&model, &truth).kinematics.posed_joints;
    let error = |f: &BodyFit| pa_mpjpe(&pose_body(&model, &f.body_params()).kinematics.posed_joints, &true_joints);
    let beta = |f: &BodyFit| f.betas.iter().zip(&truth.betas).map(|(a, b)| (a - b).powi(2)).sum::<f32>().sqrt();
    eprintln!(
        "{name}, 4 cm of clothes: the outline's IoU {:.3} → {:.3}, β off by {:.2} → {:.2}, PA-MPJPE {:.1} → {:.1} mm",
        cover(&fit),
        cover(&refined),
        beta(&fit),
        beta(&refined),
        error(&fit) * 1000.0,
        error(&refined) * 1000.0
    );
    assert!(cover(&refined) > cover(&fit) + 0.02 && cover(&refined) > 0.9);
    assert!(beta(&refined) < beta(&fit));
    assert!(error(&refined) < error(&fit) + 0.005);
    // The refined fit keeps what the first was fitted to.
    assert_eq!((refined.framing, &refined.missing), (fit.framing, &fit.missing));
}
