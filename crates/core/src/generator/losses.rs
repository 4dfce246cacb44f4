//! The paper's training objective (Sec. 4.5) as functions of tensors:
//! non-saturating adversarial losses, R1 on real images (estimated by finite differences:
//! burn has no double backward, see [`r1_penalty`]), the eikonal loss on surface points and
//! the SDF cross-entropy over sign-changing tet edges (nvdiffrec's regulariser).

use burn::tensor::activation::{sigmoid, softplus};
use burn::tensor::{Device, Tensor, TensorData};

use crate::util::rng::Rng;

/// Generator loss `softplus(−D(fake))`, mean over the batch.
pub fn generator_loss(fake_logits: Tensor<2>) -> Tensor<1> {
    softplus(fake_logits.neg(), 1.0).mean()
}

/// Discriminator loss `softplus(D(fake)) + softplus(−D(real))`, mean over the batch.
pub fn discriminator_loss(fake_logits: Tensor<2>, real_logits: Tensor<2>) -> Tensor<1> {
    softplus(fake_logits, 1.0).mean() + softplus(real_logits.neg(), 1.0).mean()
}

/// Random unit directions shaped like a batch `[B, C, H, W]`: one per sample, uniform on the
/// sphere of the sample's C·H·W numbers.
fn unit_directions(rng: &mut Rng, dims: [usize; 4], device: &Device) -> Tensor<4> {
    let [b, c, h, w] = dims;
    let n = c * h * w;
    let mut v = rng.normals(b * n);
    for s in v.chunks_mut(n) {
        let norm = s.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-12);
        s.iter_mut().for_each(|x| *x /= norm);
    }
    Tensor::from_data(TensorData::new(v, dims), device)
}

/// R1 penalty `‖∇ₓ D(x)‖²` per sample `[B]`, estimated without double backward: for random unit
/// directions u (uniform on the sphere of the sample's `n` numbers), `E[(u·∇D)²] = ‖∇D‖²/n`,
/// and `u·∇D ≈ (D(x+εu) − D(x−εu)) / 2ε`; averaged over `k` directions. Unbiased up to O(ε²);
/// its gradient with respect to D's parameters flows through the D evaluations (first order
/// only), so it trains D like R1. Relative standard deviation ≈ √(2/k); used lazily (every 16
/// D steps), the noise averages out. `d` maps images `[B, C, H, W]` to logits `[B, 1]`.
pub fn r1_penalty(
    d: impl Fn(Tensor<4>) -> Tensor<2>,
    x: Tensor<4>,
    k: usize,
    eps: f32,
    rng: &mut Rng,
    device: &Device,
) -> Tensor<1> {
    let dims = x.dims();
    let n = (dims[1] * dims[2] * dims[3]) as f32;
    let squared_derivative = |rng: &mut Rng| {
        let u = unit_directions(rng, dims, device) * eps;
        let diff = (d(x.clone() + u.clone()) - d(x.clone() - u)) * (1.0 / (2.0 * eps));
        diff.powf_scalar(2.0).reshape([dims[0]])
    };
    let mut acc = squared_derivative(rng);
    for _ in 1..k {
        acc = acc + squared_derivative(rng);
    }
    acc * (n / k.max(1) as f32)
}

/// Eikonal loss `mean (‖∇SDF‖ − 1)²` from gradients `[N, 3]`.
pub fn eikonal_loss(grad: Tensor<2>) -> Tensor<1> {
    let norm = (grad.powf_scalar(2.0).sum_dim(1) + 1e-12).sqrt();
    (norm - 1.0).powf_scalar(2.0).mean()
}

/// SDF cross-entropy over sign-changing edges (nvdiffrec): for edge (a, b) with SDF values
/// `sa`, `sb` `[E]`, `BCE(sigmoid(sa), sb > 0) + BCE(sigmoid(sb), sa > 0)`, mean. Discourages
/// floaters and spurious sign changes.
pub fn sdf_cross_entropy(sa: Tensor<1>, sb: Tensor<1>) -> Tensor<1> {
    let ta = sa.clone().greater_elem(0.0).float();
    let tb = sb.clone().greater_elem(0.0).float();
    bce_with_logits(sa, tb) + bce_with_logits(sb, ta)
}

/// Binary cross-entropy of logits against targets in {0, 1}, mean (numerically stable form).
pub fn bce_with_logits(logits: Tensor<1>, target: Tensor<1>) -> Tensor<1> {
    // max(x, 0) − x·t + log(1 + e^{−|x|}) = softplus(x) − x·t
    (softplus(logits.clone(), 1.0) - logits * target).mean()
}

/// σ(x), re-exported for callers that turn logits into probabilities.
pub fn probability(logits: Tensor<2>) -> Tensor<2> {
    sigmoid(logits)
}
