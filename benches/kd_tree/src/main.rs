//! The extraction's hot loop, measured: nearest posed body vertex of every tet-grid vertex
//! (SMPL-guided inverse skinning, paper eq. 2), with this crate's k-d tree (`spatial::KdTree`,
//! as the generator calls it) against `kiddo`'s immutable k-d tree, the ecosystem's standard.
//! Prints one table of times and ratios measured in this run; every variant's distances are
//! checked against the others (the same nearest distance for every query).
//!
//! `cargo run --release --manifest-path benches/kd_tree/Cargo.toml` (its own workspace and
//! lock file; the core without burn: about two minutes cold). `GETAVATAR_BENCH_RES=48,64,96`
//! picks the grid sizes.

use std::time::Instant;

use getavatar_core::body::body_model::BodyModel;
use getavatar_core::geometry::posed_grid::far_from_body;
use getavatar_core::geometry::BodyContext;
use getavatar_core::body::pose_library::PoseLibrary;
use getavatar_core::body::skinning::pose_body;
use getavatar_core::geometry::spatial::KdTree;
use glam::Vec3;
use kiddo::immutable::float::kdtree::ImmutableKdTree;
use kiddo::SquaredEuclidean;

/// Best of `repeats` runs of `f`, seconds, and its last result.
fn best_of<T>(repeats: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut best = f64::INFINITY;
    let mut out = None;
    for _ in 0..repeats.max(1) {
        let t = Instant::now();
        let v = f();
        best = best.min(t.elapsed().as_secs_f64());
        out = Some(v);
    }
    match out {
        Some(v) => (best, v),
        None => unreachable!("at least one repeat runs"),
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let resolutions: Vec<usize> = std::env::var("GETAVATAR_BENCH_RES")
        .unwrap_or_else(|_| "64,96".into())
        .split(',')
        .map(|s| s.trim().parse())
        .collect::<Result<_, _>>()?;
    let model = BodyModel::default_body()?;
    let params = PoseLibrary::builtin().params("walking", &[])?;
    let posed = pose_body(&model, &params);
    let points = &posed.vertices;
    let t_ours = Instant::now();
    let ours = KdTree::new(points);
    let build_ours = t_ours.elapsed().as_secs_f64();
    let flat: Vec<[f32; 3]> = points.iter().map(|p| p.to_array()).collect();
    let t_kiddo = Instant::now();
    let kiddo: ImmutableKdTree<f32, u32, 3, 32> = ImmutableKdTree::new_from_slice(&flat);
    let build_kiddo = t_kiddo.elapsed().as_secs_f64();
    println!(
        "{} posed body vertices (walking); build: spatial::KdTree {:.2} ms, kiddo {:.2} ms",
        points.len(),
        build_ours * 1e3,
        build_kiddo * 1e3
    );
    println!(
        "{:>5} {:>9} | {:>26} | {:>14} {:>14} {:>14} | {:>10}",
        "grid", "queries", "variant", "ms", "ns/query", "× kiddo time", "agree"
    );
    for res in resolutions {
        let ctx = BodyContext::with_resolution(model.clone(), 32, res);
        let far = far_from_body(&ctx);
        let queries: &[Vec3] = &ctx.grid.vertices;
        let n = queries.len();
        let (t_k, k) = best_of(3, || {
            queries.iter().map(|q| kiddo.nearest_one::<SquaredEuclidean>(&q.to_array()).distance).collect::<Vec<f32>>()
        });
        let (t_plain, plain) =
            best_of(3, || queries.iter().map(|&q| ours.nearest(q).map_or(f32::NAN, |n| n.1)).collect::<Vec<f32>>());
        let (t_hint, hinted) = best_of(3, || {
            let mut hint = None;
            queries
                .iter()
                .map(|&q| {
                    let r = match hint {
                        Some(h) => ours.nearest_from(q, h),
                        None => ours.nearest(q),
                    };
                    hint = r.map(|r| r.0);
                    r.map_or(f32::NAN, |r| r.1)
                })
                .collect::<Vec<f32>>()
        });
        let (t_within, within) = best_of(3, || {
            let mut hint = None;
            queries
                .iter()
                .map(|&q| {
                    let r = ours.nearest_within(q, far, hint);
                    hint = r.map(|r| r.0).or(hint);
                    r.map(|r| r.1)
                })
                .collect::<Vec<Option<f32>>>()
        });
        // Every variant finds the same nearest distance (the bounded one: where one is within `far`).
        let same = |a: f32, b: f32| (a - b).abs() <= 1e-6 * a.max(1e-6);
        let agree_plain = k.iter().zip(&plain).all(|(&a, &b)| same(a, b));
        let agree_hint = k.iter().zip(&hinted).all(|(&a, &b)| same(a, b));
        let agree_within = k.iter().zip(&within).all(|(&a, b)| match b {
            Some(b) => same(a, *b),
            None => a >= far * far * (1.0 - 1e-6),
        });
        let row = |name: &str, t: f64, agree: Option<bool>| {
            println!(
                "{:>5} {:>9} | {:>26} | {:>14.1} {:>14.0} {:>14.2} | {:>10}",
                format!("{res}³"),
                n,
                name,
                t * 1e3,
                t * 1e9 / n as f64,
                t / t_k,
                agree.map_or("reference", |a| if a { "yes" } else { "NO" })
            )
        };
        row("kiddo nearest_one", t_k, None);
        row("KdTree::nearest", t_plain, Some(agree_plain));
        row("KdTree::nearest_from", t_hint, Some(agree_hint));
        row(&format!("KdTree::nearest_within {far:.2}"), t_within, Some(agree_within));
        if !(agree_plain && agree_hint && agree_within) {
            return Err("the k-d trees disagree on a nearest distance".into());
        }
    }
    Ok(())
}
