//! Helpers shared by the test crates of `tests/tests/` (each file is its own crate and uses
//! what it needs, hence `allow(dead_code)`).

use getavatar_core::burn::tensor::{Device, Tensor};

/// NdArray on the CPU.
#[allow(dead_code, deprecated)]
pub fn cpu() -> Device {
    Device::ndarray()
}

/// Wgpu on the machine's adapter (lavapipe in CI).
#[allow(dead_code)]
pub fn gpu() -> Device {
    Device::wgpu_options().init().expect("no wgpu adapter: CI uses Debian's mesa-vulkan-drivers (lavapipe)")
}

/// A float tensor's values, row-major.
#[allow(dead_code)]
pub fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_to_vec::<f32>().expect("f32")
}
