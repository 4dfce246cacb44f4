//! The training subjects' scans in canonical space, for the scan and face terms (not in the
//! paper): each subject's surface and face samples, drawn once per run.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Result};
use getavatar_core::generator::pipeline::BodyContext;
use getavatar_core::io::dataset::{find_scans, load_body_fit, load_scan, Dataset, Label};
use getavatar_core::render::diff::scan_supervision::{CanonicalSamples, FaceRegion};
use getavatar_core::util::rng::Rng;

use super::run_config::{FACE_POOL_POINTS, SCAN_POOL_POINTS};

/// Subject of every dataset entry (the folder part of its image path) as an index into the
/// sorted subject names.
pub(crate) fn subject_of_entries(ds: &Dataset) -> Vec<usize> {
    let names: std::collections::BTreeSet<&str> = ds.entries.iter().map(|(p, _)| subject_name(p)).collect();
    let names: Vec<&str> = names.into_iter().collect();
    ds.entries.iter().map(|(p, _)| names.binary_search(&subject_name(p)).unwrap_or(0)).collect()
}

/// The subject (folder) of a dataset entry `subject/view.png`; "" for a top-level file.
pub(crate) fn subject_name(entry: &str) -> &str {
    entry.rsplit_once('/').map_or("", |(d, _)| d)
}

/// The scan samples of every dataset subject (index = `subject_of_entries`), in canonical
/// space: the scan terms' surface pool and the face term's face pool, each empty where its
/// term is off.
#[derive(Default)]
pub struct ScanPools {
    pub surface: Vec<CanonicalSamples>,
    pub face: Vec<CanonicalSamples>,
}

/// The scan pools of the dataset's subjects under the body fit of each subject's views:
/// with `surface`, `SCAN_POOL_POINTS` points per scan; with `face`, `FACE_POOL_POINTS` on
/// its face ([`FaceRegion`]); drawn deterministically from (seed, subject name). A subject
/// without a scan under `dir`, or without a face where one is asked, is an error.
pub(crate) fn canonical_scan_samples(
    dir: &Path,
    ds: &Dataset,
    ctx: &BodyContext,
    seed: u64,
    (surface, face): (bool, bool),
) -> Result<ScanPools> {
    let region = face
        .then(|| FaceRegion::of(ctx))
        .transpose()
        .map_err(|e| anyhow!("the face term needs a face on the body model: {e}"))?;
    let found: BTreeMap<String, PathBuf> = find_scans(dir)?.into_iter().collect();
    let subjects = subject_of_entries(ds);
    let n = subjects.iter().copied().max().map_or(0, |m| m + 1);
    // Each subject's name and the body fit of its first view.
    let mut first: Vec<Option<(String, Label)>> = vec![None; n];
    for ((path, label), &s) in ds.entries.iter().zip(&subjects) {
        if first[s].is_none() {
            first[s] = Some((subject_name(path).to_string(), label.clone()));
        }
    }
    let bar = crate::progress::bar(n as u64, "scans");
    bar.set_message(format!("scan samples from {}", dir.display()));
    let load = |(name, label): &(String, Label)| -> Result<(CanonicalSamples, CanonicalSamples)> {
        let obj = found.get(name).ok_or_else(|| anyhow!("no scan of subject `{name}` under {}", dir.display()))?;
        let scan = load_scan(obj)?;
        let smpl = load_body_fit(name, obj, None)?;
        let prepared = getavatar_core::io::scan::RenderableScan::new(&scan, &smpl);
        let mut pools = (CanonicalSamples::default(), CanonicalSamples::default());
        if surface {
            let mut rng = Rng::new(seed, getavatar_core::util::rng::hash_str(name));
            let points = getavatar_core::io::scan::sample_surface(&scan, &prepared, SCAN_POOL_POINTS, &mut rng);
            if points.is_empty() {
                bail!("the scan of subject `{name}` has no surface area");
            }
            pools.0 = CanonicalSamples::from_surface(&points, ctx, &label.body_params());
        }
        if let Some(region) = &region {
            // Its own stream, so that the surface pool stays what runs without it drew.
            let mut rng = Rng::new(seed ^ FACE_STREAM, getavatar_core::util::rng::hash_str(name));
            let params = label.body_params();
            pools.1 = CanonicalSamples::face_of(&scan, &prepared, ctx, &params, region, FACE_POOL_POINTS, &mut rng);
            if pools.1.is_empty() {
                bail!("the scan of subject `{name}` has no surface on the face (covered, or not a person facing +z in its body fit's frame): train without --lambda-face");
            }
        }
        bar.inc(1);
        Ok(pools)
    };
    let todo: Vec<&(String, Label)> = first.iter().flatten().collect();
    let out: Vec<(CanonicalSamples, CanonicalSamples)> = {
        use rayon::prelude::*;
        todo.par_iter().map(|x| load(x)).collect::<Result<_>>()?
    };
    bar.finish_and_clear();
    let (surface_pool, face_pool): (Vec<_>, Vec<_>) = out.into_iter().unzip();
    let pools = ScanPools {
        surface: if surface { surface_pool } else { Vec::new() },
        face: if face { face_pool } else { Vec::new() },
    };
    if surface {
        println!(
            "scan terms: {SCAN_POOL_POINTS} points from each of {} scans under {}",
            pools.surface.len(),
            dir.display()
        );
    }
    if face {
        println!(
            "face term: {FACE_POOL_POINTS} face points from each of {} scans under {}",
            pools.face.len(),
            dir.display()
        );
    }
    Ok(pools)
}

/// Seed offset of the face pools' random stream.
const FACE_STREAM: u64 = 0xface;

#[cfg(test)]
mod tests {
    use super::*;
    use getavatar_core::generator::network::GeneratorConfig;

    /// The face pool of a synthetic scan holds its face: eye whites on both sides of the
    /// nose, dark pupils, and nothing far from the canonical face.
    #[test]
    fn face_pools_hold_the_synthetic_scans_eyes() {
        use getavatar_core::io::scan::{sample_surface, RenderableScan};
        let dir = tempfile::tempdir().unwrap();
        let args = crate::synth_scans::SynthArgs {
            out: dir.path().into(),
            count: 1,
            seed: 0,
            threads: 1,
            texture_size: 1024,
            pose: None,
        };
        crate::synth_scans::synth_scans(&args).unwrap();
        let (name, obj) = find_scans(dir.path()).unwrap().into_iter().next().unwrap();
        let (scan, smpl) = (load_scan(&obj).unwrap(), load_body_fit(&name, &obj, None).unwrap());
        let prepared = RenderableScan::new(&scan, &smpl);
        let model = getavatar_core::body::body_model::BodyModel::default_body().unwrap();
        let ctx = BodyContext::new(model, &GeneratorConfig::tiny());
        let region = FaceRegion::of(&ctx).unwrap();
        // The body frame has the fit's translation taken out (`SmplParams::scan_to_body`), and
        // the dataset's labels, which the training carries points with, have none.
        let params = getavatar_core::body::skinning::BodyParams { transl: glam::Vec3::ZERO, ..smpl.body_params() };
        let n = 4096;
        let face = CanonicalSamples::face_of(&scan, &prepared, &ctx, &params, &region, n, &mut Rng::new(0, 1));
        assert_eq!(face.len(), n);
        // Points lie in triangles whose centroid is in the region: within a triangle's size.
        for p in &face.points {
            let d = *p - region.nose;
            assert!(d.x.abs() < 0.09 && d.y > -0.09 && d.y < 0.1 && d.z > -0.085, "{d} from the nose");
        }
        // The scans' eye white is a grey 0.92 (linear); the pupils are 0.05–0.08.
        let white = |c: &glam::Vec3| c.min_element() > 0.8 && c.max_element() - c.min_element() < 0.05;
        let sides: Vec<f32> =
            face.points.iter().zip(&face.colors).filter(|(_, c)| white(c)).map(|(p, _)| p.x).collect();
        let (left, right) = (sides.iter().filter(|&&x| x > region.nose.x).count(), sides.len());
        let right = right - left;
        assert!(left >= n / 400 && right >= n / 400, "eye-white points: {left} left, {right} right of {n}");
        let dark = face.colors.iter().filter(|c| c.max_element() < 0.1).count();
        assert!(dark >= n / 1000, "{dark} pupil points of {n}");
        // Drawn uniformly over the whole scan, few points land on the face at all.
        let all =
            CanonicalSamples::from_surface(&sample_surface(&scan, &prepared, n, &mut Rng::new(0, 2)), &ctx, &params);
        let on_face = all.points.iter().filter(|p| region.contains(**p)).count();
        assert!(on_face * 20 < n, "{on_face} of {n} uniform points on the face");
    }
}
