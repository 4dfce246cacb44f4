//! Helpers shared by the test crates of `tests/tests/` (each file is its own crate and uses
//! what it needs, hence `allow(dead_code)`).

use getavatar_core::burn::tensor::{Device, Tensor};

/// NdArray on the CPU.
#[allow(dead_code, deprecated)]
pub fn cpu() -> Device {
    Device::ndarray()
}

/// Wgpu on the machine's adapter (lavapipe in CI), opened once per test binary (a second
/// `init` of the same runtime is an error).
#[allow(dead_code)]
pub fn gpu() -> Device {
    static GPU: std::sync::OnceLock<Device> = std::sync::OnceLock::new();
    GPU.get_or_init(|| {
        Device::wgpu_options().init().expect("no wgpu adapter: CI uses Debian's mesa-vulkan-drivers (lavapipe)")
    })
    .clone()
}

/// A float tensor's values, row-major.
#[allow(dead_code)]
pub fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_to_vec::<f32>().expect("f32")
}

/// `ours` equals `want` within `rel` × max(1, max |want|), element by element.
#[allow(dead_code)]
pub fn assert_close(ours: &[f32], want: &[f32], rel: f32, what: &str) {
    assert_eq!(ours.len(), want.len(), "{what}: lengths");
    let scale = want.iter().map(|v| v.abs()).fold(1.0f32, f32::max);
    let err = ours.iter().zip(want).map(|(p, q)| (p - q).abs()).fold(0.0f32, f32::max);
    assert!(err < rel * scale, "{what}: max error {err} (scale {scale})");
}

/// Central difference of `f` at `x` along coordinate `i` with step `eps`.
#[allow(dead_code)]
pub fn central_difference(f: &dyn Fn(&[f32]) -> f64, x: &[f32], i: usize, eps: f32) -> f64 {
    let (mut hi, mut lo) = (x.to_vec(), x.to_vec());
    hi[i] += eps;
    lo[i] -= eps;
    (f(&hi) - f(&lo)) / (2.0 * eps as f64)
}

/// For `f` linear in `x` (central differences exact up to rounding): the largest
/// |finite difference − `grad`| over all coordinates, and the largest |finite difference|.
#[allow(dead_code)]
pub fn linear_fd_error(f: &dyn Fn(&[f32]) -> f64, x: &[f32], grad: &[f32], eps: f32) -> (f64, f64) {
    (0..x.len()).fold((0.0f64, 0.0f64), |(err, scale), i| {
        let fd = central_difference(f, x, i, eps);
        (err.max((fd - grad[i] as f64).abs()), scale.max(fd.abs()))
    })
}

/// Finite differences of a piecewise-smooth `f` against `grad`.
#[allow(dead_code)]
pub struct SmoothFd {
    /// Coordinates whose differences at the two step sizes agree (no kink inside the stencil).
    pub stable: Vec<usize>,
    /// ‖fd − grad‖ over the stable coordinates (larger step).
    pub diff: f64,
    /// ‖fd‖ over the stable coordinates.
    pub size: f64,
}

/// Central differences at steps `eps.0` and `eps.1`; a coordinate is stable where they differ
/// by less than `tol` × the largest |difference| (at `eps.1`).
#[allow(dead_code)]
pub fn smooth_fd_error(f: &dyn Fn(&[f32]) -> f64, x: &[f32], grad: &[f32], eps: (f32, f32), tol: f64) -> SmoothFd {
    let fds: Vec<(f64, f64)> =
        (0..x.len()).map(|i| (central_difference(f, x, i, eps.0), central_difference(f, x, i, eps.1))).collect();
    let norm = fds.iter().map(|f| f.1.abs()).fold(0.0, f64::max);
    let stable: Vec<usize> = (0..x.len()).filter(|&i| (fds[i].0 - fds[i].1).abs() < tol * norm).collect();
    let diff = stable.iter().map(|&i| (fds[i].1 - grad[i] as f64).powi(2)).sum::<f64>().sqrt();
    let size = stable.iter().map(|&i| fds[i].1.powi(2)).sum::<f64>().sqrt();
    SmoothFd { stable, diff, size }
}
