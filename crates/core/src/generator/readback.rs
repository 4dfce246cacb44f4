//! Reading tensors back from the device: the one place where a failed read-back (a lost GPU
//! device, a dtype that cannot become f32) turns into an error value with its cause, never an
//! empty vector that a later index would turn into a panic (which aborts the browser app) or
//! a checkpoint that cannot be loaded.
//!
//! Browsers cannot block, so [`read_f32`] awaits the GPU on wasm32; natively it reads
//! synchronously and [`read_f32_now`] is its blocking twin.

use std::fmt::Display;

use burn::tensor::{Tensor, TensorData};

/// A tensor could not be read back to the host.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("reading {what} back from the device failed: {cause}")]
pub struct ReadbackError {
    /// What was being read (`[3, 64, 64] tensor`, a parameter name, …).
    pub what: String,
    /// The backend's message.
    pub cause: String,
}

impl ReadbackError {
    /// The same error, naming what was read (e.g. the checkpoint parameter).
    pub fn context(self, what: impl Into<String>) -> Self {
        Self { what: what.into(), ..self }
    }
}

/// The values of a device read (`tensor.try_into_data()` or `into_data_async().await`) as
/// f32, converted from any float dtype; `shape` names the tensor in the error.
pub fn f32_values<E: Display>(data: Result<TensorData, E>, shape: &[usize]) -> Result<Vec<f32>, ReadbackError> {
    let what = || format!("a {shape:?} tensor");
    let data = data.map_err(|e| ReadbackError { what: what(), cause: e.to_string() })?;
    data.try_into_vec_as::<f32>().map_err(|e| ReadbackError { what: what(), cause: e.to_string() })
}

/// A tensor's values, row-major, on any platform (awaits the GPU in the browser).
pub async fn read_f32<const D: usize>(t: Tensor<D>) -> Result<Vec<f32>, ReadbackError> {
    let shape = t.dims();
    let since = crate::util::profile::now();
    #[cfg(target_arch = "wasm32")]
    let data = t.into_data_async().await;
    #[cfg(not(target_arch = "wasm32"))]
    let data = t.try_into_data();
    crate::util::profile::readback_done(since);
    f32_values(data, &shape)
}

/// A tensor's values, row-major, read synchronously. Native only (browsers cannot block).
#[cfg(not(target_arch = "wasm32"))]
pub fn read_f32_now<const D: usize>(t: Tensor<D>) -> Result<Vec<f32>, ReadbackError> {
    let shape = t.dims();
    let since = crate::util::profile::now();
    let data = t.try_into_data();
    crate::util::profile::readback_done(since);
    f32_values(data, &shape)
}

/// Run a future whose awaits all complete immediately (native read-backs are synchronous), so
/// the `async` pipelines that the browser awaits run natively without an executor.
#[cfg(not(target_arch = "wasm32"))]
pub fn block_on_ready<F: std::future::Future>(fut: F) -> F::Output {
    // Checkpoints do not pause in here (`cooperative`): nothing would resume them.
    let _scope = crate::util::cooperative::BlockingScope::enter();
    let mut fut = std::pin::pin!(fut);
    let mut cx = std::task::Context::from_waker(std::task::Waker::noop());
    loop {
        if let std::task::Poll::Ready(v) = fut.as_mut().poll(&mut cx) {
            return v;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::Device;

    #[test]
    fn a_failed_or_unconvertible_read_is_an_error_naming_the_tensor() {
        // A device error (e.g. a lost GPU) keeps its cause.
        let lost: Result<TensorData, &str> = Err("device lost");
        let e = f32_values(lost, &[2, 3]).unwrap_err();
        assert_eq!(e.cause, "device lost");
        assert!(e.to_string().contains("[2, 3]"), "{e}");
        // Floats of another width are converted.
        let f64s: Result<TensorData, &str> = Ok(TensorData::new(vec![1.5f64, -2.0], [2]));
        assert_eq!(f32_values(f64s, &[2]).unwrap(), vec![1.5, -2.0]);
        assert_eq!(e.clone().context("decoders.sdf.out.weight").what, "decoders.sdf.out.weight");
    }

    #[cfg(feature = "generator")]
    #[test]
    fn tensors_read_back_row_major() {
        #[allow(deprecated)]
        let dev = Device::ndarray();
        let t = Tensor::<2>::from_data(TensorData::new(vec![1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0], [2, 3]), &dev);
        assert_eq!(read_f32_now(t.clone().transpose()).unwrap(), vec![1.0, 4.0, 2.0, 5.0, 3.0, 6.0]);
        assert_eq!(block_on_ready(read_f32(t)).unwrap(), vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
    }
}
