//! Deterministic parameter initialisation: a seeded PCG32 stream and Box–Muller normals,
//! generated on the CPU and uploaded, so all backends start from identical weights.

use std::cell::Cell;

use burn::tensor::{Device, Tensor, TensorData};

pub use crate::util::rng::Rng;

thread_local! {
    /// Inside [`placeholder_weights`].
    static PLACEHOLDER: Cell<bool> = const { Cell::new(false) };
}

/// Build a module whose every weight is replaced at once by a load (`checkpoint`'s loaders,
/// which fail on any weight the file lacks): inside `f`, [`randn`] gives zeros without drawing.
/// A generator's 6 M draws held the browser's UI thread for 70 ms per load.
pub fn placeholder_weights<T>(f: impl FnOnce() -> T) -> T {
    let was = PLACEHOLDER.with(|p| p.replace(true));
    let out = f();
    PLACEHOLDER.with(|p| p.set(was));
    out
}

/// A tensor of `shape` filled with N(0, 1)·`scale` from `rng` (zeros, and `rng` untouched,
/// inside [`placeholder_weights`]).
pub fn randn<const D: usize>(rng: &mut Rng, shape: [usize; D], scale: f32, device: &Device) -> Tensor<D> {
    if PLACEHOLDER.with(Cell::get) {
        return Tensor::zeros(shape, device);
    }
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn placeholder_weights_are_zeros_only_inside() {
        #[allow(deprecated)]
        let dev = Device::ndarray();
        let values = |t: Tensor<2>| t.into_data().try_to_vec::<f32>().unwrap();
        let mut rng = Rng::new(1, 2);
        let zeros = placeholder_weights(|| values(randn(&mut rng, [3, 4], 1.0, &dev)));
        assert_eq!(zeros, vec![0.0; 12]);
        // The stream was not advanced, and outside the weights are drawn again.
        assert_eq!(rng, Rng::new(1, 2));
        let drawn = values(randn(&mut rng, [3, 4], 1.0, &dev));
        assert!(drawn.iter().all(|v| v.is_finite()) && drawn.iter().any(|v| *v != 0.0));
    }
}
