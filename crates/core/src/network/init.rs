//! Deterministic parameter initialisation: a seeded PCG32 stream and Box–Muller normals,
//! generated on the CPU and uploaded, so all backends start from identical weights.

use burn::tensor::{Device, Tensor, TensorData};

/// PCG32 (O'Neill), small and reproducible everywhere (including wasm32).
#[derive(Clone, Debug)]
pub struct Rng {
    state: u64,
    inc: u64,
}

impl Rng {
    pub fn new(seed: u64, stream: u64) -> Self {
        let mut r = Self { state: 0, inc: (stream << 1) | 1 };
        r.next_u32();
        r.state = r.state.wrapping_add(seed);
        r.next_u32();
        r
    }

    pub fn next_u32(&mut self) -> u32 {
        let old = self.state;
        self.state = old.wrapping_mul(6364136223846793005).wrapping_add(self.inc);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        let rot = (old >> 59) as u32;
        xorshifted.rotate_right(rot)
    }

    /// Uniform in (0, 1).
    pub fn uniform(&mut self) -> f32 {
        ((self.next_u32() >> 8) as f32 + 0.5) / (1u32 << 24) as f32
    }

    /// Standard normal.
    pub fn normal(&mut self) -> f32 {
        let (u1, u2) = (self.uniform(), self.uniform());
        (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
    }

    pub fn normals(&mut self, n: usize) -> Vec<f32> {
        (0..n).map(|_| self.normal()).collect()
    }
}

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
