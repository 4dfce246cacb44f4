//! What later stages derive from a body context once per burn device (the canonical grid's
//! DMTet topology as device tensors, `crate::generator::dmtet_gpu`), kept in the context so each device
//! builds it once. The context stores the values without knowing their type: geometry sits
//! below the stages that make them.

use std::any::Any;
use std::future::Future;
use std::sync::{Arc, Mutex};

use burn::tensor::Device;

/// Values kept per device, one of each type per device.
#[derive(Default)]
pub struct PerDevice(Mutex<Vec<(Device, Arc<dyn Any + Send + Sync>)>>);

impl PerDevice {
    /// The `T` kept for `device`, or `make`'s, then kept.
    pub async fn get_or_make<T: Any + Send + Sync>(&self, device: &Device, make: impl Future<Output = T>) -> Arc<T> {
        let lock = || self.0.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        let kept = lock().iter().find_map(|(d, v)| (d == device).then(|| v.clone().downcast::<T>().ok()).flatten());
        if let Some(t) = kept {
            return t;
        }
        let made = Arc::new(make.await);
        lock().push((device.clone(), made.clone()));
        made
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_device_makes_its_value_once_and_types_do_not_mix() {
        #[allow(deprecated)]
        let cpu = Device::ndarray();
        let cache = PerDevice::default();
        let a = crate::util::cooperative::run_blocking(cache.get_or_make(&cpu, async { 7u32 }));
        let b = crate::util::cooperative::run_blocking(cache.get_or_make(&cpu, async { 9u32 }));
        assert_eq!((*a, *b), (7, 7));
        let s = crate::util::cooperative::run_blocking(cache.get_or_make(&cpu, async { "x".to_string() }));
        assert_eq!(*s, "x");
    }
}
