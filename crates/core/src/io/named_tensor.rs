//! Tensors by name, as checkpoints and optimiser states store them: the record type and the
//! naming of a module's parameters, and the walk over a module's parameters by name (shared
//! by `checkpoint` and `optim`, which import nothing else from each other).

use std::collections::BTreeMap;

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::tensor::Tensor;

/// A tensor as stored: name, shape and row-major values.
pub type NamedTensor = (String, Vec<usize>, Vec<f32>);

/// Parameter name from the module path; a repeated path gets a `#k` suffix (traversal order
/// is the same when saving and loading, so names match).
pub fn unique_name(path: &[String], seen: &mut BTreeMap<String, usize>) -> String {
    let base = path.join(".");
    let k = seen.entry(base.clone()).or_insert(0);
    *k += 1;
    if *k == 1 {
        base
    } else {
        format!("{base}#{}", *k - 1)
    }
}

/// What to do with each float parameter of a module, given its name ([`unique_name`] of its
/// module path, as checkpoints store it): see [`map_named`].
pub trait MapNamed {
    fn map<const D: usize>(&mut self, name: String, param: Param<Tensor<D>>) -> Param<Tensor<D>>;
}

/// What to read from each float parameter of a module, given its name: see [`visit_named`].
pub trait VisitNamed {
    fn visit<const D: usize>(&mut self, name: String, param: &Param<Tensor<D>>);
}

/// `module` with every float parameter passed through `f` under its checkpoint name.
pub fn map_named<M: Module, F: MapNamed>(module: M, f: &mut F) -> M {
    module.map(&mut Named { path: Vec::new(), seen: BTreeMap::new(), f })
}

/// Every float parameter of `module` shown to `f` under its checkpoint name.
pub fn visit_named<M: Module, F: VisitNamed>(module: &M, f: &mut F) {
    module.visit(&mut Named { path: Vec::new(), seen: BTreeMap::new(), f })
}

/// The module path walked by burn's mapper and visitor, named as [`unique_name`] names it.
struct Named<'a, F> {
    path: Vec<String>,
    seen: BTreeMap<String, usize>,
    f: &'a mut F,
}

impl<F: MapNamed> ModuleMapper for Named<'_, F> {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.path.push(name.to_string());
    }
    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.path.pop();
    }
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let name = unique_name(&self.path, &mut self.seen);
        self.f.map(name, param)
    }
}

impl<F: VisitNamed> ModuleVisitor for Named<'_, F> {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.path.push(name.to_string());
    }
    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.path.pop();
    }
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let name = unique_name(&self.path, &mut self.seen);
        self.f.visit(name, param)
    }
}
