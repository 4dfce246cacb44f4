//! Loss curves as a PNG (no plotting dependency): one panel per series, raw values faint,
//! a moving average bold, horizontal grid lines at round values. `trainer train` writes
//! `RUN/losses.png` with every snapshot; the legend is fixed (see [`loss_curves`]).

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{Context, Result};
use getavatar_core::io::dataset::encode_png;

/// Series drawn by [`loss_curves`], top to bottom, with their colours.
pub const SERIES: [(&str, [u8; 3]); 4] = [
    ("loss_g", [200, 40, 40]),
    ("loss_d", [40, 80, 200]),
    ("eikonal", [40, 150, 60]),
    ("cross_entropy", [150, 90, 20]),
];

/// A `width`×(`panel`·4) RGB image of the series in `rows` (each row: one value per series,
/// NaN = missing), smoothed over `window` steps.
pub fn loss_curves(rows: &[[f32; 4]], width: usize, panel: usize, window: usize) -> Vec<u8> {
    let h = panel * SERIES.len();
    let mut px = vec![255u8; width * h * 3];
    let mut put = |x: usize, y: usize, c: [u8; 3], alpha: f32| {
        if x < width && y < h {
            let i = (y * width + x) * 3;
            for k in 0..3 {
                px[i + k] = (px[i + k] as f32 * (1.0 - alpha) + c[k] as f32 * alpha) as u8;
            }
        }
    };
    for (s, (_, colour)) in SERIES.iter().enumerate() {
        let vals: Vec<f32> = rows.iter().map(|r| r[s]).collect();
        let finite: Vec<f32> = vals.iter().copied().filter(|v| v.is_finite()).collect();
        let top = s * panel;
        // Panel frame.
        for x in 0..width {
            put(x, top, [0, 0, 0], 1.0);
        }
        if finite.len() < 2 {
            continue;
        }
        let lo = finite.iter().copied().fold(f32::INFINITY, f32::min);
        let hi = finite.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        let span = (hi - lo).max(1e-6);
        let (y0, y1) = (top as f32 + 4.0, (top + panel) as f32 - 4.0);
        let to_y = |v: f32| y1 - (v - lo) / span * (y1 - y0);
        // Grid lines at multiples of a round step.
        let step = 10f32.powf(span.log10().floor());
        let mut g = (lo / step).ceil() * step;
        while g <= hi {
            let y = to_y(g) as usize;
            for x in (0..width).step_by(3) {
                put(x, y, [160, 160, 160], 1.0);
            }
            g += step;
        }
        let n = vals.len();
        let to_x = |i: usize| i as f32 / (n - 1).max(1) as f32 * (width - 1) as f32;
        let smooth: Vec<f32> = (0..n)
            .map(|i| {
                let w = &vals[i.saturating_sub(window.max(1) - 1)..=i];
                let f: Vec<f32> = w.iter().copied().filter(|v| v.is_finite()).collect();
                if f.is_empty() {
                    f32::NAN
                } else {
                    f.iter().sum::<f32>() / f.len() as f32
                }
            })
            .collect();
        for (series, alpha, thick) in [(&vals, 0.25f32, 0usize), (&smooth, 1.0, 1)] {
            for i in 1..n {
                let (a, b) = (series[i - 1], series[i]);
                if !(a.is_finite() && b.is_finite()) {
                    continue;
                }
                let (xa, xb, ya, yb) = (to_x(i - 1), to_x(i), to_y(a), to_y(b));
                let steps = ((xb - xa).abs().max((yb - ya).abs()).ceil() as usize).max(1);
                for k in 0..=steps {
                    let t = k as f32 / steps as f32;
                    let (x, y) = (xa + (xb - xa) * t, ya + (yb - ya) * t);
                    for d in 0..=thick {
                        put(x as usize, y as usize + d, *colour, alpha);
                    }
                }
            }
        }
    }
    px
}

/// `losses.png` from a run's `metrics.jsonl`: G loss, D loss, eikonal, SDF cross-entropy
/// (top to bottom; raw faint, 20-step moving average bold).
pub fn loss_plot(metrics: &Path) -> Result<Vec<u8>> {
    // A step logged twice (a run killed after logging, before its checkpoint) keeps the
    // later row: the one the resumed run continued from. A torn last line (a kill while
    // appending) is skipped.
    let mut by_step = BTreeMap::new();
    let text = std::fs::read_to_string(metrics).with_context(|| format!("reading {}", metrics.display()))?;
    for v in text.lines().filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok()) {
        let row = SERIES.map(|(k, _)| v.get(k).and_then(|x| x.as_f64()).map_or(f32::NAN, |x| x as f32));
        by_step.insert(v.get("step").and_then(|s| s.as_u64()).unwrap_or(0), row);
    }
    let rows: Vec<[f32; 4]> = by_step.into_values().collect();
    let (w, panel) = (640, 120);
    Ok(encode_png(w, panel * SERIES.len(), 3, &loss_curves(&rows, w, panel, 20))?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_rising_series_is_drawn_from_bottom_left_to_top_right() {
        let rows: Vec<[f32; 4]> = (0..50).map(|i| [i as f32, 1.0, f32::NAN, 0.5]).collect();
        let (w, p) = (100, 40);
        let px = loss_curves(&rows, w, p, 1);
        let at = |x: usize, y: usize| [px[(y * w + x) * 3], px[(y * w + x) * 3 + 1], px[(y * w + x) * 3 + 2]];
        let red = SERIES[0].1;
        // Smoothed (window 1) line: bottom of panel 0 at the left, top at the right.
        assert_eq!(at(0, p - 4), red);
        assert_eq!(at(w - 1, 4), red);
        assert_ne!(at(0, 4), red);
        // A series without values leaves its panel blank (white) below the frame.
        assert_eq!(at(w / 2, 2 * p + p / 2), [255, 255, 255]);
    }
}
