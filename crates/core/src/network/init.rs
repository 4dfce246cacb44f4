//! Deterministic parameter initialisation: a seeded PCG32 stream and Box–Muller normals,
//! generated on the CPU and uploaded, so all backends start from identical weights.

use burn::tensor::{Device, Tensor, TensorData};

pub use crate::rng::Rng;

/// A tensor of `shape` filled with N(0, 1)·`scale` from `rng`.
pub fn randn<const D: usize>(rng: &mut Rng, shape: [usize; D], scale: f32, device: &Device) -> Tensor<D> {
    let n = shape.iter().product();
    let v: Vec<f32> = rng.normals(n).into_iter().map(|x| x * scale).collect();
    Tensor::from_data(TensorData::new(v, shape), device)
}

/// A tensor of `shape` filled with `value`.
pub fn full<const D: usize>(shape: [usize; D], value: f32, device: &Device) -> Tensor<D> {
    let n = shape.iter().product();
    Tensor::from_data(TensorData::new(vec![value; n], shape), device)
}

/// The latent z of a seed (StyleGAN's convention: one normal vector per seed).
pub fn latent(seed: u64, dim: usize) -> Vec<f32> {
    Rng::new(seed, 0x5eed).normals(dim)
}
