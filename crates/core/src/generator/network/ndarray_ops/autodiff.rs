//! The backward passes of [`super`]'s operations under burn's autodiff: each a single
//! operation on the tape whose adjoint is the matching `*_backward` kernel.

use super::*;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::Autodiff;

/// The gradients of a two-input operation (the convolution, the triplane lookup) from its
/// inputs' shapes and values and its output's gradient, each only when asked.
type PairAdjoint =
    fn((&[usize], &[f32]), (&[usize], &[f32]), &[f32], bool, bool) -> (Option<Vec<f32>>, Option<Vec<f32>>);

/// The backward pass of a two-input operation that keeps both inputs for it.
#[derive(Debug)]
struct PairBackward(PairAdjoint);

impl Backward<NdArray, 2> for PairBackward {
    /// The forward pass's inputs (NdArray's arrays are reference-counted: no copy).
    type State = (FloatTensor<NdArray>, FloatTensor<NdArray>);

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
        let [node_a, node_b] = ops.parents;
        let dy = grads.consume::<NdArray>(&ops.node);
        let (a, b) = ops.state;
        let ((sa, va), (sb, vb), (_, dy)) = (values(&a), values(&b), values(&dy));
        let (da, db) = (self.0)((&sa, &va), (&sb, &vb), &dy, node_a.is_some(), node_b.is_some());
        if let (Some(node), Some(da)) = (node_a, da) {
            grads.register::<NdArray>(node.id, tensor(da, sa));
        }
        if let (Some(node), Some(db)) = (node_b, db) {
            grads.register::<NdArray>(node.id, tensor(db, sb));
        }
    }
}

/// A two-input operation (`forward` on NdArray) under autodiff, with its `adjoint`.
fn pair<C: CheckpointStrategy>(
    a: FloatTensor<Autodiff<NdArray, C>>,
    b: FloatTensor<Autodiff<NdArray, C>>,
    forward: fn(FloatTensor<NdArray>, FloatTensor<NdArray>) -> FloatTensor<NdArray>,
    adjoint: PairAdjoint,
) -> FloatTensor<Autodiff<NdArray, C>> {
    let (a, a_node) = a.into_parts();
    let (b, b_node) = b.into_parts();
    match PairBackward(adjoint).prepare::<C>([a_node, b_node]).compute_bound().stateful() {
        OpsKind::Tracked(prep) => {
            let y = forward(a.clone(), b.clone());
            prep.finish((a, b), y)
        }
        OpsKind::UnTracked(prep) => prep.finish(forward(a, b)),
    }
}

fn conv_adjoint(
    (xs, x): (&[usize], &[f32]),
    (ws, w): (&[usize], &[f32]),
    dy: &[f32],
    want_x: bool,
    want_w: bool,
) -> (Option<Vec<f32>>, Option<Vec<f32>>) {
    backward(&ConvDims::of(xs, ws), x, w, dy, want_x, want_w)
}

fn triplane_adjoint(
    (ps, p): (&[usize], &[f32]),
    (ts, t): (&[usize], &[f32]),
    dy: &[f32],
    want_p: bool,
    want_t: bool,
) -> (Option<Vec<f32>>, Option<Vec<f32>>) {
    triplane_backward(&TriplaneDims::of(ps, ts), p, t, dy, want_p, want_t)
}

/// The backward pass of a linear operation of one `[B, C, H, W]` input that works plane by
/// plane (the pooling, the upsampling): its adjoint `(planes, H, W, dy) → dx`.
#[derive(Debug)]
struct PlanewiseBackward(fn(usize, usize, usize, &[f32]) -> Vec<f32>);

impl Backward<NdArray, 1> for PlanewiseBackward {
    /// The input's shape.
    type State = Vec<usize>;

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
        let [node] = ops.parents;
        let dy = grads.consume::<NdArray>(&ops.node);
        if let Some(node) = node {
            let (_, dy) = values(&dy);
            let (p, h, w) = planes(&ops.state);
            grads.register::<NdArray>(node.id, tensor((self.0)(p, h, w, &dy), ops.state));
        }
    }
}

/// A plane-wise operation (`forward` on NdArray) under autodiff, with its `adjoint`.
fn planewise<C: CheckpointStrategy>(
    x: FloatTensor<Autodiff<NdArray, C>>,
    forward: fn(FloatTensor<NdArray>) -> FloatTensor<NdArray>,
    adjoint: fn(usize, usize, usize, &[f32]) -> Vec<f32>,
) -> FloatTensor<Autodiff<NdArray, C>> {
    let (x, node) = x.into_parts();
    match PlanewiseBackward(adjoint).prepare::<C>([node]).compute_bound().stateful() {
        OpsKind::Tracked(prep) => {
            let shape = x.shape().to_vec();
            prep.finish(shape, forward(x))
        }
        OpsKind::UnTracked(prep) => prep.finish(forward(x)),
    }
}

#[derive(Debug)]
struct BiasLreluBackward;

impl Backward<NdArray, 2> for BiasLreluBackward {
    /// The forward pass's output (its sign is the activation's slope).
    type State = FloatTensor<NdArray>;

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
        let [node_x, node_b] = ops.parents;
        let dy = grads.consume::<NdArray>(&ops.node);
        let ((shape, y), (_, dy)) = (values(&ops.state), values(&dy));
        let (c, plane) = (shape[1], shape[2..].iter().product());
        let (dx, db) = bias_lrelu_backward(c, plane, &y, &dy);
        if let Some(node) = node_x {
            grads.register::<NdArray>(node.id, tensor(dx, shape));
        }
        if let Some(node) = node_b {
            grads.register::<NdArray>(node.id, tensor(db, vec![c]));
        }
    }
}

impl<C: CheckpointStrategy> NdArrayOpsBackend for Autodiff<NdArray, C> {
    fn conv2d_same(x: FloatTensor<Self>, weight: FloatTensor<Self>) -> FloatTensor<Self> {
        pair::<C>(x, weight, NdArray::conv2d_same, conv_adjoint)
    }

    fn avg_pool2x2(x: FloatTensor<Self>) -> FloatTensor<Self> {
        planewise::<C>(x, NdArray::avg_pool2x2, pool_backward)
    }

    fn bias_lrelu(x: FloatTensor<Self>, bias: FloatTensor<Self>) -> FloatTensor<Self> {
        let (x, x_node) = x.into_parts();
        let (b, b_node) = bias.into_parts();
        match BiasLreluBackward.prepare::<C>([x_node, b_node]).compute_bound().stateful() {
            OpsKind::Tracked(prep) => {
                let y = NdArray::bias_lrelu(x, b);
                prep.finish(y.clone(), y)
            }
            OpsKind::UnTracked(prep) => prep.finish(NdArray::bias_lrelu(x, b)),
        }
    }

    fn upsample2(x: FloatTensor<Self>) -> FloatTensor<Self> {
        planewise::<C>(x, NdArray::upsample2, upsample2_backward)
    }

    fn triplane_bilinear(planes: FloatTensor<Self>, texels: FloatTensor<Self>) -> FloatTensor<Self> {
        pair::<C>(planes, texels, NdArray::triplane_bilinear, triplane_adjoint)
    }
}
