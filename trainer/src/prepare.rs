//! `trainer prepare`: render scans into a training dataset in the reference code's layout
//! (docs/dataset.md) with the paper's camera protocol (radius 2.3, fov 49.13°, azimuth
//! uniform, elevation ~ N(0, 0.1) rad, looking at the subject's vertical centre, white
//! background).
//!
//! Input: one folder per subject holding an OBJ (any name; THUman2.0's `0000/0000.obj` +
//! `material0.mtl` + `material0.jpeg` works unchanged), its MTL and textures, and the body
//! fit as `smpl.json` in the folder or `<--smpl-dir>/<subject>.json`. Subjects render in
//! parallel; each finished subject leaves `<out>/<subject>/labels.part.json` (written last,
//! atomically), so re-running skips it. A broken subject is reported by name and the rest
//! of the run goes on; `dataset.json` is (re)built from all finished subjects at the end.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use rayon::prelude::*;

use anyhow::{bail, Context, Result};
use getavatar_core::io::dataset::{encode_views, labels_to_json, parse_labels, Label, LABELS_FILE};
use getavatar_core::io::dataset::{find_scans, load_body_fit, load_scan};
use getavatar_core::io::scan::{render_scan, RenderableScan};
use getavatar_core::render::camera::sample_data_camera;
use getavatar_core::util::rng::{hash_str, Rng};

/// Per-subject labels file of a finished subject (merged into dataset.json).
const PART_FILE: &str = "labels.part.json";

pub struct PrepareArgs {
    pub scans: PathBuf,
    pub out: PathBuf,
    pub views: usize,
    pub res: usize,
    /// Supersampling factor per axis (antialiasing).
    pub ss: usize,
    pub seed: u64,
    pub threads: usize,
    pub smpl_dir: Option<PathBuf>,
    /// Render only the first N subjects (sorted by name).
    pub limit: Option<usize>,
}

use crate::atomic::write_atomic;

/// The cameras of a subject: deterministic in (seed, subject name), so a resumed run and a
/// fresh run agree.
pub fn subject_cameras(seed: u64, subject: &str, views: usize, centre_y: f32) -> Vec<getavatar_core::OrbitCamera> {
    let mut rng = Rng::new(seed, hash_str(subject));
    (0..views).map(|_| sample_data_camera(&mut rng, centre_y)).collect()
}

/// Render one subject into `out/<subject>/`; returns its labels.
pub fn prepare_subject(subject: &str, obj: &Path, a: &PrepareArgs, on_view: &dyn Fn()) -> Result<Vec<(String, Label)>> {
    let scan = load_scan(obj)?;
    let smpl = load_body_fit(subject, obj, a.smpl_dir.as_deref())?;
    let prepared = RenderableScan::new(&scan, &smpl);
    let (lo, hi) = prepared.y_range();
    let cams = subject_cameras(a.seed, subject, a.views, 0.5 * (lo + hi));
    let dir = a.out.join(subject);
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut body = smpl.body_params();
    body.transl = glam::Vec3::ZERO; // labels live in the body frame
    let digits = (a.views.max(2) - 1).to_string().len().max(3);
    let mut labels = Vec::with_capacity(a.views);
    for (k, cam) in cams.iter().enumerate() {
        let views = render_scan(&scan, &prepared, cam, a.res, a.ss);
        let (rgba, normal) = encode_views(&views)?;
        let name = format!("{k:0digits$}");
        write_atomic(&dir.join(format!("{name}.png")), &rgba)?;
        write_atomic(&dir.join(format!("{name}_normal.png")), &normal)?;
        labels.push((format!("{subject}/{name}.png"), Label::new(cam.world_to_camera(), &body)));
        on_view();
    }
    write_atomic(&dir.join(PART_FILE), labels_to_json(&labels).as_bytes())?;
    Ok(labels)
}

pub fn prepare(a: &PrepareArgs) -> Result<()> {
    if a.views == 0 || !(16..=4096).contains(&a.res) || !(1..=8).contains(&a.ss) {
        bail!("need --views ≥ 1, --res in 16..=4096 and --ss in 1..=8 (got {}, {}, {})", a.views, a.res, a.ss);
    }
    let mut subjects = find_scans(&a.scans)?;
    if subjects.is_empty() {
        bail!("no subject folders with an .obj under {}", a.scans.display());
    }
    if let Some(n) = a.limit {
        subjects.truncate(n);
    }
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let todo: Vec<&(String, PathBuf)> =
        subjects.iter().filter(|(s, _)| !a.out.join(s).join(PART_FILE).is_file()).collect();
    let done_before = subjects.len() - todo.len();
    let bar = crate::progress::bar((todo.len() * a.views) as u64, "views");
    let rendered = AtomicUsize::new(0);
    let t0 = std::time::Instant::now();
    let pool = rayon::ThreadPoolBuilder::new().num_threads(a.threads.max(1)).build()?;
    let errors: Vec<String> = pool.install(|| {
        todo.par_iter()
            .filter_map(|(subject, obj)| {
                let on_view = || {
                    bar.inc(1);
                    rendered.fetch_add(1, Ordering::Relaxed);
                };
                let e = prepare_subject(subject, obj, a, &on_view).err()?;
                bar.println(format!("skipping subject {subject}: {e:#}"));
                Some(format!("{subject}: {e:#}"))
            })
            .collect()
    });
    bar.finish_and_clear();
    let dt = t0.elapsed().as_secs_f64();

    // Merge every finished subject's labels (this run's and earlier runs').
    let mut all = Vec::new();
    for (subject, _) in &subjects {
        let part = a.out.join(subject).join(PART_FILE);
        if part.is_file() {
            let text = std::fs::read_to_string(&part)?;
            all.extend(parse_labels(&part, &text)?);
        }
    }
    all.sort_by(|x, y| x.0.cmp(&y.0));
    write_atomic(&a.out.join(LABELS_FILE), labels_to_json(&all).as_bytes())?;
    let views = rendered.load(Ordering::Relaxed);
    println!(
        "rendered {} subjects ({} views at {}², {}× supersampling) in {:.1} s: {:.2} views/s, {:.3} subjects/s; {} subjects were already done; {} has {} labels",
        todo.len() - errors.len(),
        views,
        a.res,
        a.ss,
        dt,
        views as f64 / dt.max(1e-9),
        (todo.len() - errors.len()) as f64 / dt.max(1e-9),
        done_before,
        a.out.join(LABELS_FILE).display(),
        all.len()
    );
    if !errors.is_empty() {
        bail!("{} of {} subjects failed:\n  {}", errors.len(), subjects.len(), errors.join("\n  "));
    }
    Ok(())
}
