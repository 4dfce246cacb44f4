//! `trainer variety`: how different a generator's avatars are from one another, against how
//! different its training subjects are (the model card's variety figure).
//!
//! Every avatar is rendered in the canonical pose (Da-pose) from the front at `res`², and
//! two renders are compared by their pixel L1: the mean absolute difference over the RGB
//! channels (on white) and the mask, all in [0, 1]. The seeds' pairwise distances (ψ as
//! given, 0.7 by default) are set against the training subjects' (a checkpoint's latent
//! modes, each subject with its own codes). A generator that renders blends of a few
//! subjects has seeds much closer to one another than its subjects are; the target is a
//! median at least half the subjects'. Contact sheets of both go next to the figures.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use getavatar_core::body::pose_library::PoseLibrary;
use getavatar_core::generator::pipeline::{generate_avatar, Styles};
use getavatar_core::io::dataset::encode_png;
use serde::Serialize;

use crate::model_io::{load_body, render_avatar, seed_styles, GeneratorArgs};

#[derive(clap::Args, Debug)]
pub struct VarietyArgs {
    #[command(flatten)]
    pub backend: crate::backend::BackendArg,
    #[command(flatten)]
    pub model: GeneratorArgs,
    /// Seeds to render (seed pairs `seed + 2k`, `seed + 2k + 1` for geometry and texture).
    #[arg(long, default_value_t = 64)]
    pub count: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Truncation ψ of the seeds (towards the checkpoint's latent modes where it has them).
    #[arg(long, default_value_t = 0.7)]
    pub psi: f32,
    /// Render size in pixels (square).
    #[arg(long, default_value_t = 128)]
    pub res: usize,
    /// Body model .npz in the SMPL layout (default: the embedded open body).
    #[arg(long)]
    pub body: Option<PathBuf>,
    /// Output folder: `variety.json`, `seeds.png` and `subjects.png` (contact sheets), and
    /// each render in `seeds/` and `subjects/` (`NNN.png`).
    #[arg(long, default_value = "variety")]
    pub out: PathBuf,
}

/// Quartiles of a distance distribution.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Spread {
    pub pairs: usize,
    pub min: f32,
    pub q1: f32,
    pub median: f32,
    pub q3: f32,
    pub max: f32,
}

#[derive(Debug, Serialize)]
pub struct VarietyReport {
    pub resolution: usize,
    pub psi: f32,
    pub seeds: Spread,
    /// `None` for a checkpoint without latent modes (no training subjects to compare with).
    pub subjects: Option<Spread>,
    /// Median of the seeds over the median of the subjects (target ≥ 0.5).
    pub ratio: Option<f32>,
    pub seed_distances: Vec<f32>,
    pub subject_distances: Vec<f32>,
}

/// A render as the compared values: RGB in [0, 1] (on white), then the mask.
struct Render {
    rgb: Vec<u8>,
    mask: Vec<u8>,
}

/// Pixel L1 of two renders: the mean absolute difference over RGB and mask channels, [0, 1].
fn distance(a: &Render, b: &Render) -> f32 {
    let sum = |x: &[u8], y: &[u8]| x.iter().zip(y).map(|(p, q)| p.abs_diff(*q) as u64).sum::<u64>();
    let total = sum(&a.rgb, &b.rgb) + sum(&a.mask, &b.mask);
    total as f32 / (255.0 * (a.rgb.len() + a.mask.len()).max(1) as f32)
}

/// All pairwise distances (i < j).
fn pairwise(renders: &[Render]) -> Vec<f32> {
    let mut d = Vec::with_capacity(renders.len() * renders.len().saturating_sub(1) / 2);
    for i in 0..renders.len() {
        for j in i + 1..renders.len() {
            d.push(distance(&renders[i], &renders[j]));
        }
    }
    d
}

/// Quartiles by linear interpolation between order statistics; `None` for no values.
fn spread(values: &[f32]) -> Option<Spread> {
    let mut v: Vec<f32> = values.to_vec();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f32::total_cmp);
    let q = |f: f32| {
        let x = f * (v.len() - 1) as f32;
        let (lo, hi) = (x.floor() as usize, x.ceil() as usize);
        v[lo] + (v[hi] - v[lo]) * (x - lo as f32)
    };
    Some(Spread { pairs: v.len(), min: v[0], q1: q(0.25), median: q(0.5), q3: q(0.75), max: v[v.len() - 1] })
}

/// Renders side by side, `cols` to a row, as one RGB PNG.
fn contact_sheet(renders: &[Render], res: usize, cols: usize) -> Result<Vec<u8>> {
    let cols = cols.clamp(1, renders.len().max(1));
    let rows = renders.len().div_ceil(cols).max(1);
    let (w, h) = (cols * res, rows * res);
    let mut buf = vec![255u8; w * h * 3];
    for (k, r) in renders.iter().enumerate() {
        let (ox, oy) = ((k % cols) * res, (k / cols) * res);
        for y in 0..res {
            let dst = ((oy + y) * w + ox) * 3;
            buf[dst..dst + res * 3].copy_from_slice(&r.rgb[y * res * 3..(y + 1) * res * 3]);
        }
    }
    Ok(encode_png(w, h, 3, &buf)?)
}

/// Each render as its own PNG `dir/NNN.png` (for detectors: `tools/mediapipe_fixtures.mjs
/// --front` checks that each front render shows a person facing the camera).
fn write_each(dir: &std::path::Path, renders: &[Render], res: usize) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    for (k, r) in renders.iter().enumerate() {
        crate::atomic::write_atomic(&dir.join(format!("{k:03}.png")), &encode_png(res, res, 3, &r.rgb)?)?;
    }
    Ok(())
}

pub fn variety(a: &VarietyArgs) -> Result<VarietyReport> {
    if a.count < 2 {
        bail!("--count must be at least 2 (distances are between pairs)");
    }
    if !(16..=1024).contains(&a.res) {
        bail!("--res must be between 16 and 1024 (got {})", a.res);
    }
    if !a.psi.is_finite() {
        bail!("--psi must be a number");
    }
    let device = a.backend.device()?;
    let (cfg, g, modes) = a.model.load(&device)?;
    let ctx = crate::model_io::body_context(load_body(&a.body)?, &cfg);
    let params = PoseLibrary::builtin().params("Da", &[]).context("the built-in Da-pose")?;
    let render = |styles: &Styles| -> Result<Render> {
        let avatar = generate_avatar(&g, &ctx, styles, &params, &device)?;
        let v = render_avatar(&g, styles, &avatar, 0.0, a.res, &device)?;
        Ok(Render { rgb: v.rgb, mask: v.mask })
    };
    let subjects = modes.as_ref().map_or(0, |m| m.count());
    let bar = crate::progress::bar((a.count + subjects) as u64, "avatars");
    let mut seeds = Vec::with_capacity(a.count);
    for k in 0..a.count as u64 {
        let pair = (a.seed + 2 * k, a.seed + 2 * k + 1);
        seeds.push(render(&seed_styles(&g, &cfg, &modes, pair, Some(a.psi), false, &device))?);
        bar.inc(1);
    }
    let mut own = Vec::with_capacity(subjects);
    if let Some(m) = &modes {
        for k in 0..subjects {
            own.push(render(&g.subject_styles(m, k, k).context("a latent mode inside the checkpoint's count")?)?);
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    crate::atomic::write_atomic(&a.out.join("seeds.png"), &contact_sheet(&seeds, a.res, 8)?)?;
    write_each(&a.out.join("seeds"), &seeds, a.res)?;
    if !own.is_empty() {
        crate::atomic::write_atomic(&a.out.join("subjects.png"), &contact_sheet(&own, a.res, 8)?)?;
        write_each(&a.out.join("subjects"), &own, a.res)?;
    }
    let (seed_distances, subject_distances) = (pairwise(&seeds), pairwise(&own));
    let seeds_spread = spread(&seed_distances).context("no seed pairs")?;
    let subjects_spread = spread(&subject_distances);
    let ratio = subjects_spread.as_ref().map(|s| seeds_spread.median / s.median.max(1e-9));
    Ok(VarietyReport {
        resolution: a.res,
        psi: a.psi,
        seeds: seeds_spread,
        subjects: subjects_spread,
        ratio,
        seed_distances,
        subject_distances,
    })
}

pub fn run(a: &VarietyArgs) -> Result<()> {
    let r = variety(a)?;
    let line = |name: &str, s: &Spread| {
        println!(
            "{name}: {} pairs, pixel L1 min {:.4} q1 {:.4} median {:.4} q3 {:.4} max {:.4}",
            s.pairs, s.min, s.q1, s.median, s.q3, s.max
        )
    };
    line(&format!("{} seeds at ψ {}", a.count, a.psi), &r.seeds);
    match (&r.subjects, r.ratio) {
        (Some(s), Some(ratio)) => {
            line("training subjects (own codes)", s);
            println!(
                "median ratio seeds / subjects {ratio:.3} (target ≥ 0.5: {})",
                if ratio >= 0.5 { "met" } else { "not met" }
            );
        }
        _ => println!("the checkpoint carries no latent modes: no training subjects to compare with"),
    }
    let json = a.out.join("variety.json");
    crate::atomic::write_atomic(&json, serde_json::to_string_pretty(&r)?.as_bytes())?;
    println!("wrote {}, seeds.png{}", json.display(), if r.subjects.is_some() { ", subjects.png" } else { "" });
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flat(rgb: u8, mask: u8, n: usize) -> Render {
        Render { rgb: vec![rgb; n * 3], mask: vec![mask; n] }
    }

    /// White background vs a black, covered image: every channel differs fully.
    #[test]
    fn distance_is_the_mean_channel_difference() {
        let (white, black) = (flat(255, 0, 16), flat(0, 255, 16));
        assert_eq!(distance(&white, &white), 0.0);
        assert!((distance(&white, &black) - 1.0).abs() < 1e-6);
        // Half the pixels' RGB differ by 51/255 = 0.2, masks equal: 0.2 · ½ · ¾ = 0.075.
        let mut half = flat(255, 0, 16);
        for v in &mut half.rgb[..24] {
            *v = 204;
        }
        assert!((distance(&white, &half) - 0.075).abs() < 1e-6, "{}", distance(&white, &half));
    }

    #[test]
    fn quartiles_interpolate_between_order_statistics() {
        let s = spread(&[4.0, 1.0, 3.0, 2.0, 5.0]).unwrap();
        assert_eq!((s.pairs, s.min, s.q1, s.median, s.q3, s.max), (5, 1.0, 2.0, 3.0, 4.0, 5.0));
        let s = spread(&[1.0, 2.0]).unwrap();
        assert_eq!((s.q1, s.median, s.q3), (1.25, 1.5, 1.75));
        assert!(spread(&[]).is_none());
        let renders = [flat(0, 0, 4), flat(255, 0, 4), flat(255, 255, 4)];
        assert_eq!(pairwise(&renders), vec![0.75, 1.0, 0.25]);
    }
}
