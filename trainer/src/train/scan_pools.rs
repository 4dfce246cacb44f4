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
