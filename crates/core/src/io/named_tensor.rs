//! Tensors by name, as checkpoints and optimiser states store them: the record type and the
//! naming of a module's parameters (shared by `checkpoint` and `optim`, which import nothing
//! else from each other).

use std::collections::BTreeMap;

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
