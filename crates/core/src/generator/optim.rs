//! Adam (Kingma & Ba) over a burn module's float parameters, with its state kept by parameter
//! path so it can be checkpointed and restored exactly (resume continues bit-identically).
//! The paper's settings: β = (0, 0.99), ε = 1e-8, learning rates scaled for lazy
//! regularisation by the caller.

use std::collections::BTreeMap;

use burn::module::{Module, Param};
use burn::tensor::{Device, Gradients, Tensor, TensorData};

#[cfg(not(target_arch = "wasm32"))]
use crate::generator::readback::{read_f32_now, ReadbackError};
#[cfg(not(target_arch = "wasm32"))]
use crate::io::named_tensor::NamedTensor;
use crate::io::named_tensor::{map_named, visit_named, MapNamed, VisitNamed};

/// Adam hyper-parameters and per-parameter moments (flattened, on the parameters' device).
#[derive(Clone, Debug)]
pub struct Adam {
    pub beta1: f32,
    pub beta2: f32,
    pub eps: f32,
    /// Steps taken.
    pub step: u64,
    /// First and second moments by parameter path.
    pub moments: BTreeMap<String, (Tensor<1>, Tensor<1>)>,
}

impl Adam {
    pub fn new(beta1: f32, beta2: f32, eps: f32) -> Self {
        Self { beta1, beta2, eps, step: 0, moments: BTreeMap::new() }
    }

    /// The moments as flat named tensors `{prefix}{path}/m` and `…/v`, for a checkpoint (the
    /// step goes in the caller's metadata). Native only (it blocks on the read-backs).
    #[cfg(not(target_arch = "wasm32"))]
    pub fn moment_tensors(&self, prefix: &str) -> Result<Vec<NamedTensor>, ReadbackError> {
        let mut out = Vec::new();
        for (name, (m, v)) in &self.moments {
            for (suffix, t) in [("m", m), ("v", v)] {
                let what = format!("{prefix}{name}/{suffix}");
                let vals = read_f32_now(t.clone()).map_err(|e| e.context(what.clone()))?;
                out.push((what, vec![vals.len()], vals));
            }
        }
        Ok(out)
    }

    /// This optimiser with the moments [`Adam::moment_tensors`] wrote under `prefix` in
    /// `tensors`, on `device` (without autodiff). Err names a first moment without its second.
    pub fn with_moments(
        mut self,
        tensors: &BTreeMap<String, (Vec<usize>, Vec<f32>)>,
        prefix: &str,
        device: &Device,
    ) -> Result<Self, String> {
        for (k, (shape, m)) in tensors {
            if let Some(name) = k.strip_prefix(prefix).and_then(|r| r.strip_suffix("/m")) {
                let (_, v) =
                    tensors.get(&format!("{prefix}{name}/v")).ok_or_else(|| format!("lacks {prefix}{name}/v"))?;
                let t = |d: &Vec<f32>| Tensor::<1>::from_data(TensorData::new(d.clone(), [shape[0]]), device);
                self.moments.insert(name.to_string(), (t(m), t(v)));
            }
        }
        Ok(self)
    }

    /// One update of `module` (an autodiff module whose loss produced `grads`) with learning
    /// rate `lr`. Parameters without a gradient are left unchanged.
    pub fn step<M: Module>(&mut self, lr: f32, module: M, grads: &Gradients) -> M {
        self.step_scaled(lr, module, grads, &|_| 1.0)
    }

    /// [`Adam::step`] with a per-parameter learning-rate factor: the parameter at path `name`
    /// (as in checkpoints, e.g. `decoders.texture.out.weight`) is updated with
    /// `lr · lr_factor(name)`. The moments do not depend on the factor.
    pub fn step_scaled<M: Module>(
        &mut self,
        lr: f32,
        module: M,
        grads: &Gradients,
        lr_factor: &dyn Fn(&str) -> f32,
    ) -> M {
        self.step += 1;
        map_named(module, &mut AdamMapper { adam: self, lr, lr_factor, grads })
    }
}

struct AdamMapper<'a> {
    adam: &'a mut Adam,
    lr: f32,
    lr_factor: &'a dyn Fn(&str) -> f32,
    grads: &'a Gradients,
}

impl MapNamed for AdamMapper<'_> {
    fn map<const D: usize>(&mut self, name: String, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let (id, tensor, mapper) = param.consume();
        let Some(g) = tensor.grad(self.grads) else {
            return Param::from_mapped_value(id, tensor, mapper);
        };
        let dims = tensor.dims();
        let n: usize = dims.iter().product();
        let g: Tensor<1> = g.reshape([n]);
        let a = &mut *self.adam;
        let (m, v) = match a.moments.remove(&name) {
            Some(mv) => mv,
            None => (g.zeros_like(), g.zeros_like()),
        };
        let m = m * a.beta1 + g.clone() * (1.0 - a.beta1);
        let v = v * a.beta2 + g.powf_scalar(2.0) * (1.0 - a.beta2);
        let t = a.step as i32;
        let c1 = 1.0 - a.beta1.powi(t);
        let c2 = 1.0 - a.beta2.powi(t);
        let lr = self.lr * (self.lr_factor)(&name);
        let update = (m.clone() / c1) / ((v.clone() / c2).sqrt() + a.eps) * lr;
        a.moments.insert(name, (m, v));
        let inner = tensor.inner();
        let new = inner - update.reshape(dims);
        Param::from_mapped_value(id, Tensor::from_inner(new).require_grad(), mapper)
    }
}

/// `module` with only the parameters whose path `keep` accepts (as in checkpoints, e.g.
/// `decoders.texture.out.weight`) tracked for gradients: a backward pass then computes no
/// gradient for the others, nor through the layers that only they feed.
pub fn trainable_where<M: Module>(module: M, keep: &dyn Fn(&str) -> bool) -> M {
    struct Mark<'a>(&'a dyn Fn(&str) -> bool);
    impl MapNamed for Mark<'_> {
        fn map<const D: usize>(&mut self, name: String, p: Param<Tensor<D>>) -> Param<Tensor<D>> {
            p.set_require_grad((self.0)(&name))
        }
    }
    map_named(module, &mut Mark(keep))
}

/// Exponential moving average of a model's parameters (the paper's "EMA of the generator"):
/// `ema ← β·ema + (1 − β)·model`, matched by parameter path. `ema` may live on the model's
/// device without autodiff.
pub fn ema_update<M: Module>(ema: M, model: &M, beta: f32) -> M {
    struct Get(BTreeMap<String, Tensor<1>>);
    impl VisitNamed for Get {
        fn visit<const D: usize>(&mut self, name: String, p: &Param<Tensor<D>>) {
            let t = p.val().inner();
            let n: usize = t.dims().iter().product();
            self.0.insert(name, t.reshape([n]));
        }
    }
    struct Set {
        src: BTreeMap<String, Tensor<1>>,
        beta: f32,
    }
    impl MapNamed for Set {
        fn map<const D: usize>(&mut self, name: String, p: Param<Tensor<D>>) -> Param<Tensor<D>> {
            let Some(src) = self.src.remove(&name) else { return p };
            let beta = self.beta;
            p.map(|t| {
                let dims = t.dims();
                t.clone() * beta + src.reshape(dims) * (1.0 - beta)
            })
        }
    }
    let mut get = Get(BTreeMap::new());
    visit_named(model, &mut get);
    map_named(ema, &mut Set { src: get.0, beta })
}
