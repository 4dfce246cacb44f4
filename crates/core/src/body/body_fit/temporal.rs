//! A video's per-frame body fits as one motion: frames where the person was lost filled in,
//! the joint rotations and the root smoothed over time without lag, and the yardsticks of a
//! motion against its truth (acceleration error, lag at a sharp turn).
//!
//! The smoothing is a centred Gaussian over frames (the whole clip is known before it is
//! smoothed, so no causal filter and none of its lag is needed): joint rotations as unit
//! quaternions on one hemisphere, averaged and normalised, the root translation averaged.
//! At the clip's ends the window's weights are renormalised over the frames that exist.

use glam::{Quat, Vec3};

use crate::body::body_model::NUM_JOINTS;
use crate::body::skinning::{axis_angle_to_quat, quat_to_axis_angle};

/// One frame of a motion: joint rotations (axis-angle; `[0]` the root) and root translation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseFrame {
    pub pose: [Vec3; NUM_JOINTS],
    pub trans: Vec3,
}

/// Fill the frames without a pose (`None`: the person was lost) by slerping the joint
/// rotations and lerping the root between the nearest frames on either side; before the
/// first and after the last seen frame, the nearest seen frame is held. `None` when no frame
/// has a pose.
pub fn fill_lost(frames: &[Option<PoseFrame>]) -> Option<Vec<PoseFrame>> {
    let seen: Vec<usize> = (0..frames.len()).filter(|&k| frames[k].is_some()).collect();
    let (&first, &last) = (seen.first()?, seen.last()?);
    let mut out = Vec::with_capacity(frames.len());
    let mut next_seen = 0usize;
    for k in 0..frames.len() {
        if let Some(f) = frames[k] {
            out.push(f);
            continue;
        }
        if k < first {
            out.push(frames[first]?);
            continue;
        }
        if k > last {
            out.push(frames[last]?);
            continue;
        }
        while seen[next_seen] < k {
            next_seen += 1;
        }
        let (a, b) = (seen[next_seen - 1], seen[next_seen]);
        let t = (k - a) as f32 / (b - a) as f32;
        out.push(blend(&frames[a]?, &frames[b]?, t));
    }
    Some(out)
}

/// `a` to `b` at `t` in 0..1 (slerp per joint, lerp of the root).
fn blend(a: &PoseFrame, b: &PoseFrame, t: f32) -> PoseFrame {
    let mut pose = [Vec3::ZERO; NUM_JOINTS];
    for (j, p) in pose.iter_mut().enumerate() {
        *p = quat_to_axis_angle(axis_angle_to_quat(a.pose[j]).slerp(axis_angle_to_quat(b.pose[j]), t));
    }
    PoseFrame { pose, trans: a.trans.lerp(b.trans, t) }
}

/// Centred Gaussian smoothing with standard deviation `sigma` frames (0 returns the frames
/// unchanged); the window reaches 3σ either side.
pub fn smooth(frames: &[PoseFrame], sigma: f32) -> Vec<PoseFrame> {
    if sigma <= 0.0 || frames.len() < 3 {
        return frames.to_vec();
    }
    let reach = (3.0 * sigma).ceil() as isize;
    let weights: Vec<f32> = (-reach..=reach).map(|d| (-(d * d) as f32 / (2.0 * sigma * sigma)).exp()).collect();
    // Each joint's quaternions on one hemisphere, frame to frame, so averages do not cancel.
    let mut quats: Vec<[Quat; NUM_JOINTS]> = Vec::with_capacity(frames.len());
    for (k, f) in frames.iter().enumerate() {
        let mut q = [Quat::IDENTITY; NUM_JOINTS];
        for j in 0..NUM_JOINTS {
            let mut x = axis_angle_to_quat(f.pose[j]);
            if k > 0 && quats[k - 1][j].dot(x) < 0.0 {
                x = -x;
            }
            q[j] = x;
        }
        quats.push(q);
    }
    let n = frames.len() as isize;
    (0..n)
        .map(|k| {
            let mut acc = [glam::Vec4::ZERO; NUM_JOINTS];
            let (mut trans, mut total) = (Vec3::ZERO, 0.0f32);
            for (i, d) in (-reach..=reach).enumerate() {
                let m = k + d;
                if !(0..n).contains(&m) {
                    continue;
                }
                let w = weights[i];
                total += w;
                trans += frames[m as usize].trans * w;
                for (a, q) in acc.iter_mut().zip(&quats[m as usize]) {
                    *a += glam::Vec4::from(*q) * w;
                }
            }
            let mut pose = [Vec3::ZERO; NUM_JOINTS];
            for (p, a) in pose.iter_mut().zip(acc) {
                *p = quat_to_axis_angle(Quat::from_vec4(a / total).normalize());
            }
            PoseFrame { pose, trans: trans / total }
        })
        .collect()
}

/// Mean acceleration error of joint tracks against the truth's, metres per frame²: per
/// interior frame and joint, ‖(x₊ − 2x + x₋) − (y₊ − 2y + y₋)‖ (the video-pose literature's
/// "Accel"; both tracks in the same frame and scale).
pub fn acceleration_error(tracks: &[Vec<Vec3>], truth: &[Vec<Vec3>]) -> f32 {
    let accel = |t: &[Vec<Vec3>], k: usize, j: usize| t[k + 1][j] - 2.0 * t[k][j] + t[k - 1][j];
    let (mut sum, mut count) = (0.0f32, 0usize);
    for k in 1..tracks.len().min(truth.len()).saturating_sub(1) {
        for j in 0..tracks[k].len().min(truth[k].len()) {
            sum += (accel(tracks, k, j) - accel(truth, k, j)).length();
            count += 1;
        }
    }
    if count == 0 {
        0.0
    } else {
        sum / count as f32
    }
}

/// Frames by which `signal` trails `truth` through a sharp change (a turn): the time at which
/// each first crosses the middle of `truth`'s range (interpolated between frames), positive
/// when `signal` is late. `None` when either never crosses it.
pub fn lag_at_half_change(signal: &[f32], truth: &[f32]) -> Option<f32> {
    let lo = truth.iter().copied().fold(f32::INFINITY, f32::min);
    let hi = truth.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let level = (lo + hi) / 2.0;
    let rising = truth.first()? < truth.last()?;
    let crossing = |s: &[f32]| {
        (0..s.len().saturating_sub(1)).find_map(|k| {
            let (a, b) = if rising { (s[k], s[k + 1]) } else { (-s[k], -s[k + 1]) };
            let l = if rising { level } else { -level };
            (a < l && b >= l).then(|| k as f32 + (l - a) / (b - a))
        })
    };
    Some(crossing(signal)? - crossing(truth)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(yaw: f32, x: f32) -> PoseFrame {
        let mut pose = [Vec3::ZERO; NUM_JOINTS];
        pose[0] = Vec3::new(0.0, yaw, 0.0);
        pose[18] = Vec3::new(0.0, -yaw / 2.0, 0.0);
        PoseFrame { pose, trans: Vec3::new(x, 0.0, 0.0) }
    }

    #[test]
    fn lost_frames_are_interpolated_between_their_neighbours_and_held_at_the_ends() {
        let frames = vec![None, Some(frame(0.0, 0.0)), None, None, Some(frame(0.9, 0.3)), None];
        let out = fill_lost(&frames).unwrap();
        assert_eq!(out.len(), 6);
        assert_eq!(out[0], frame(0.0, 0.0));
        assert!((out[2].pose[0].y - 0.3).abs() < 1e-5 && (out[2].trans.x - 0.1).abs() < 1e-6, "{:?}", out[2].pose[0]);
        assert!((out[3].pose[18].y + 0.3).abs() < 1e-5, "{:?}", out[3].pose[18]);
        assert_eq!(out[5], frame(0.9, 0.3));
        assert!(fill_lost(&[None, None]).is_none());
    }

    #[test]
    fn smoothing_removes_jitter_keeps_a_ramp_and_does_not_lag_a_sharp_turn() {
        // A turn of 90° over 4 frames in the middle of a 40-frame clip, with ±0.05 rad
        // alternating jitter on top.
        let truth: Vec<f32> =
            (0..40).map(|k| std::f32::consts::FRAC_PI_2 * ((k as f32 - 18.0) / 4.0).clamp(0.0, 1.0)).collect();
        let noisy: Vec<PoseFrame> = truth
            .iter()
            .enumerate()
            .map(|(k, y)| frame(y + if k % 2 == 0 { 0.05 } else { -0.05 }, 0.01 * k as f32))
            .collect();
        let out = smooth(&noisy, 1.0);
        let yaw: Vec<f32> = out.iter().map(|f| f.pose[0].y).collect();
        // Jitter away from the turn: from 0.05 to below 0.01.
        for k in (3..14).chain(27..37) {
            assert!((yaw[k] - truth[k]).abs() < 0.01, "frame {k}: {} vs {}", yaw[k], truth[k]);
        }
        let lag = lag_at_half_change(&yaw, &truth).unwrap();
        assert!(lag.abs() < 0.1, "lag {lag} frames: {yaw:?}");
        // A linear root track is kept; at the ends, whose windows are one-sided, within half
        // a frame's step.
        for (k, f) in out.iter().enumerate() {
            let tolerance = if (3..37).contains(&k) { 1e-4 } else { 6e-3 };
            assert!((f.trans.x - 0.01 * k as f32).abs() < tolerance, "frame {k}: {}", f.trans.x);
        }
        // The hemisphere of a quaternion track does not matter: a joint near ±π stays there.
        let flips: Vec<PoseFrame> = (0..10).map(|k| frame(3.1 + 0.01 * (k % 2) as f32, 0.0)).collect();
        for f in smooth(&flips, 1.5) {
            assert!(
                axis_angle_to_quat(f.pose[0]).angle_between(Quat::from_rotation_y(3.105)) < 0.01,
                "{:?}",
                f.pose[0]
            );
        }
        assert_eq!(smooth(&noisy, 0.0), noisy);
    }

    #[test]
    fn acceleration_error_is_zero_for_a_shifted_copy_and_counts_a_spike() {
        let truth: Vec<Vec<Vec3>> = (0..10).map(|k| vec![Vec3::new(0.1 * k as f32, 0.0, 0.0)]).collect();
        let shifted: Vec<Vec<Vec3>> = truth.iter().map(|t| vec![t[0] + Vec3::Y]).collect();
        assert!(acceleration_error(&shifted, &truth) < 1e-6);
        let mut spike = truth.clone();
        spike[5][0].y += 0.08;
        // Frames 4, 5 and 6 see 0.08, 0.16 and 0.08 of 8 interior frames.
        assert!((acceleration_error(&spike, &truth) - 0.04).abs() < 1e-6);
        assert_eq!(lag_at_half_change(&[0.0, 0.0, 0.0, 1.0, 1.0], &[0.0, 1.0, 1.0, 1.0, 1.0]), Some(2.0));
        assert_eq!(lag_at_half_change(&[0.0; 5], &[0.0, 1.0, 1.0, 1.0, 1.0]), None);
    }
}
