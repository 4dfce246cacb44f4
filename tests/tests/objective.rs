//! The adversarial objective's parts: the conditional residual discriminator, the
//! non-saturating losses with Adam steps, the finite-difference R1 estimator against the exact
//! input gradient, and the geometry regularisers.

use getavatar_core::burn::module::Module;
use getavatar_core::burn::tensor::{Device, Tensor, TensorData};
use getavatar_core::generator::losses::{discriminator_loss, eikonal_loss, r1_penalty, sdf_cross_entropy};
use getavatar_core::generator::network::discriminator::{minibatch_std, Discriminator, DiscriminatorConfig};
use getavatar_core::generator::optim::Adam;
use getavatar_core::util::rng::Rng;

mod common;
use common::{assert_close, cpu, values};

fn randn4(rng: &mut Rng, dims: [usize; 4], dev: &Device) -> Tensor<4> {
    Tensor::from_data(TensorData::new(rng.normals(dims.iter().product()), dims), dev)
}

fn cameras(rng: &mut Rng, b: usize, dev: &Device) -> Tensor<2> {
    Tensor::from_data(TensorData::new(rng.normals(b * 16), [b, 16]), dev)
}

#[test]
fn discriminator_shapes_conditioning_and_minibatch_std() {
    let dev = cpu();
    let cfg = DiscriminatorConfig::new(32, 256, 32);
    let d = Discriminator::new(&cfg, 3, 1, &dev);
    let mut rng = Rng::new(1, 1);
    let x = randn4(&mut rng, [4, 3, 32, 32], &dev);
    let c = cameras(&mut rng, 4, &dev);
    let y = d.forward(x.clone(), c.clone());
    assert_eq!(y.dims(), [4, 1]);
    let a = values(y);
    assert_eq!(a, values(d.forward(x.clone(), c)), "deterministic");
    let b = values(d.forward(x, cameras(&mut rng, 4, &dev)));
    assert!(a.iter().zip(&b).any(|(p, q)| (p - q).abs() > 1e-4), "the camera conditions the output");
    // Minibatch std: identical samples in a group have zero std; the extra channel says so.
    let same = Tensor::<4>::ones([4, 2, 4, 4], &dev);
    let s = values(minibatch_std(same, 4).narrow(1, 2, 1));
    assert!(s.iter().all(|v| v.abs() < 1e-3), "{s:?}");
    // Known std: samples 0 and 1 differ by 2 in every entry → population std 1 (group of 2).
    let x = Tensor::<4>::from_data(TensorData::new(vec![-1.0f32, -1.0, 1.0, 1.0], [2, 1, 1, 2]), &dev);
    let s = values(minibatch_std(x, 4).narrow(1, 1, 1));
    assert!(s.iter().all(|v| (v - 1.0).abs() < 1e-3), "{s:?}");
}

#[test]
fn one_adam_step_lowers_the_discriminator_loss_on_a_fixed_batch() {
    let dev = cpu().autodiff();
    let cfg = DiscriminatorConfig::new(16, 128, 16);
    let mut d = Discriminator::new(&cfg, 1, 2, &dev);
    let mut rng = Rng::new(3, 3);
    let real = randn4(&mut rng, [4, 1, 16, 16], &dev).tanh();
    let fake = randn4(&mut rng, [4, 1, 16, 16], &dev) * 0.3;
    let c = cameras(&mut rng, 4, &dev);
    let loss =
        |d: &Discriminator| discriminator_loss(d.forward(fake.clone(), c.clone()), d.forward(real.clone(), c.clone()));
    let mut adam = Adam::new(0.0, 0.99, 1e-8);
    let before = loss(&d);
    let l0 = values(before.clone())[0];
    let grads = before.backward();
    d = adam.step(0.002, d, &grads);
    let l1 = values(loss(&d))[0];
    assert!(l1 < l0 - 1e-4, "D loss {l0} → {l1}");
    assert_eq!(adam.moments.len(), d.num_params_tensors(), "one moment pair per parameter tensor");
    // Ten more steps keep lowering it.
    for _ in 0..10 {
        let grads = loss(&d).backward();
        d = adam.step(0.002, d, &grads);
    }
    let l2 = values(loss(&d))[0];
    assert!(l2 < l1, "{l1} → {l2}");
}

trait CountTensors {
    fn num_params_tensors(&self) -> usize;
}

impl<M: Module> CountTensors for M {
    fn num_params_tensors(&self) -> usize {
        struct C(usize);
        impl getavatar_core::burn::module::ModuleVisitor for C {
            fn visit_float<const D: usize>(&mut self, _p: &getavatar_core::burn::module::Param<Tensor<D>>) {
                self.0 += 1;
            }
        }
        let mut c = C(0);
        self.visit(&mut c);
        c.0
    }
}

#[test]
fn r1_estimator_matches_the_exact_input_gradient_norm() {
    let dev = cpu().autodiff();
    let cfg = DiscriminatorConfig::new(8, 64, 8);
    let d = Discriminator::new(&cfg, 1, 4, &dev);
    let mut rng = Rng::new(5, 5);
    let x = randn4(&mut rng, [2, 1, 8, 8], &dev);
    let c = cameras(&mut rng, 2, &dev);
    // Exact ‖∇ₓD_s‖² of each sample's logit w.r.t. the whole batch input (minibatch-std couples
    // the samples a little; the estimator perturbs all samples at once, so it estimates the
    // same quantity).
    let mut exact = Vec::new();
    for s in 0..2 {
        let xi = x.clone().detach().require_grad();
        let out = d.forward(xi.clone(), c.clone()).narrow(0, s, 1).sum();
        let g = values(xi.grad(&out.backward()).unwrap());
        exact.push(g.iter().map(|v| v * v).sum::<f32>());
    }
    // The estimator averages directional derivatives over random unit directions.
    let est = values(r1_penalty(|img| d.forward(img, c.clone()), x.clone().detach(), 2000, 1e-2, &mut rng, &dev));
    let total_exact: f32 = exact.iter().sum();
    let total_est: f32 = est.iter().sum();
    assert!(
        (total_est / total_exact - 1.0).abs() < 0.06,
        "R1 estimate {total_est} vs exact {total_exact} (per sample {est:?} vs {exact:?})"
    );
    // Its gradient reaches the discriminator's parameters (it regularises D).
    let r1 = r1_penalty(|img| d.forward(img, c.clone()), x.detach(), 2, 1e-2, &mut rng, &dev).mean();
    let grads = r1.backward();
    let w = d.blocks[0].conv0.weight.val();
    assert!(values(w.grad(&grads).expect("R1 reaches D")).iter().any(|v| v.abs() > 0.0));
}

#[test]
fn eikonal_and_cross_entropy_values() {
    let dev = cpu();
    // Unit gradients → 0; gradients of length 2 → 1.
    let g = Tensor::<2>::from_data(TensorData::new(vec![1.0f32, 0.0, 0.0, 0.0, 2.0, 0.0], [2, 3]), &dev);
    assert!((values(eikonal_loss(g))[0] - 0.5).abs() < 1e-5);
    // Edge (−1, +1): BCE(σ(−1), 1) + BCE(σ(1), 0) = 2·softplus(1).
    let sa = Tensor::<1>::from_data(TensorData::new(vec![-1.0f32], [1]), &dev);
    let sb = Tensor::<1>::from_data(TensorData::new(vec![1.0f32], [1]), &dev);
    let want = 2.0 * (1.0f32 + 1f32.exp()).ln();
    assert!((values(sdf_cross_entropy(sa, sb))[0] - want).abs() < 1e-5);
}

/// The networks' one convolution (im2col + matmul on NdArray, also in bands of rows) equals
/// burn's `conv2d` (grouped for per-sample weights), values and gradients.
#[test]
fn conv2d_same_matches_burn_conv2d() {
    use getavatar_core::burn::tensor::module::conv2d;
    use getavatar_core::burn::tensor::ops::ConvOptions;
    use getavatar_core::generator::network::layers::{conv2d_im2col, conv2d_same};
    let dev = cpu().autodiff();
    let mut rng = Rng::new(5, 5);
    for &(b, c, o, k, r, shared) in
        &[(3usize, 5usize, 4usize, 3usize, 8usize, true), (3, 5, 4, 3, 7, false), (2, 3, 6, 1, 5, true)]
    {
        let x = randn4(&mut rng, [b, c, r, r], &dev).require_grad();
        let wb = if shared { 1 } else { b };
        let w: Tensor<5> =
            Tensor::from_data(TensorData::new(rng.normals(wb * o * c * k * k), [wb, o, c, k, k]), &dev).require_grad();
        let opts = |g| ConvOptions::new([1, 1], [k / 2, k / 2], [1, 1], g);
        let reference = if shared {
            conv2d(x.clone(), w.clone().reshape([o, c, k, k]), None, opts(1))
        } else {
            conv2d(x.clone().reshape([1, b * c, r, r]), w.clone().reshape([b * o, c, k, k]), None, opts(b))
                .reshape([b, o, r, r])
        };
        let ours = conv2d_same(x.clone(), w.clone());
        assert_eq!(ours.dims(), [b, o, r, r]);
        let weights = randn4(&mut rng, [b, o, r, r], &dev);
        let grads = |y: Tensor<4>| {
            let g = (y * weights.clone()).sum().backward();
            (values(x.grad(&g).expect("x grad")), values(w.grad(&g).expect("w grad")))
        };
        let close = |ours: &[f32], want: &[f32], what: &str| assert_close(ours, want, 1e-5, what);
        close(&values(ours.clone()), &values(reference.clone()), "values");
        let reference_values = reference.clone().detach();
        let (gx0, gw0) = grads(reference);
        let (gx1, gw1) = grads(ours);
        close(&gx1, &gx0, "∂x");
        close(&gw1, &gw0, "∂w");
        // In bands of output rows (GPU backends bound the column matrix's size): 1 row, 3
        // rows (a short last band), all rows.
        let row_bytes = 4 * b * c * k * k * r;
        for rows in [1, 3, r] {
            let banded = conv2d_im2col(x.clone(), w.clone(), rows * row_bytes + row_bytes / 2);
            close(&values(banded.clone()), &values(reference_values.clone()), &format!("values, bands of {rows} rows"));
            let (gx2, gw2) = grads(banded);
            close(&gx2, &gx0, &format!("∂x, bands of {rows} rows"));
            close(&gw2, &gw0, &format!("∂w, bands of {rows} rows"));
        }
    }
}

/// NdArray's 2×2 average pooling (one operation with its own backward, the discriminators'
/// downsampling) equals burn's `avg_pool2d`, values and gradients, odd sizes included.
#[test]
fn ndarray_avg_pool2x2_matches_burn_avg_pool2d() {
    use getavatar_core::burn::tensor::module::avg_pool2d;
    use getavatar_core::burn::tensor::ops::AvgPoolOptions;
    use getavatar_core::generator::network::ndarray_ops::avg_pool2x2;
    let dev = cpu().autodiff();
    let mut rng = Rng::new(6, 6);
    for shape in [[2usize, 3usize, 8usize, 6usize], [1, 2, 5, 7]] {
        let x = randn4(&mut rng, shape, &dev).require_grad();
        let reference = avg_pool2d(x.clone(), AvgPoolOptions::new([2, 2]));
        let ours = avg_pool2x2(x.clone());
        assert_eq!(ours.dims(), reference.dims());
        assert_close(&values(ours.clone()), &values(reference.clone()), 1e-6, "values");
        let weights = randn4(&mut rng, reference.dims(), &dev);
        let grad = |y: Tensor<4>| values(x.grad(&(y * weights.clone()).sum().backward()).expect("x grad"));
        assert_close(&grad(ours), &grad(reference), 1e-6, "∂x");
    }
}

/// The bias and activation after each convolution (on NdArray one operation with its own
/// backward) equal the bias add and `lrelu_gain` as tensor ops, values and both gradients.
#[test]
fn ndarray_bias_lrelu_matches_the_tensor_ops() {
    use getavatar_core::generator::network::layers::{bias_lrelu, lrelu_gain};
    let dev = cpu().autodiff();
    let mut rng = Rng::new(7, 7);
    let x = randn4(&mut rng, [2, 3, 5, 4], &dev).require_grad();
    let bias: Tensor<1> = Tensor::from_data(TensorData::new(rng.normals(3), [3]), &dev).require_grad();
    let ours = bias_lrelu(x.clone(), bias.clone(), true);
    let reference = lrelu_gain(x.clone() + bias.clone().reshape([1, 3, 1, 1]));
    assert_close(&values(ours.clone()), &values(reference.clone()), 1e-6, "values");
    let weights = randn4(&mut rng, [2, 3, 5, 4], &dev);
    let grads = |y: Tensor<4>| {
        let g = (y * weights.clone()).sum().backward();
        (values(x.grad(&g).expect("x grad")), values(bias.grad(&g).expect("bias grad")))
    };
    let ((gx0, gb0), (gx1, gb1)) = (grads(reference), grads(ours));
    assert_close(&gx1, &gx0, 1e-6, "∂x");
    assert_close(&gb1, &gb0, 1e-5, "∂bias");
    // Both slopes are exercised.
    let v = values(x.clone() + bias.clone().reshape([1, 3, 1, 1]));
    assert!(v.iter().any(|t| *t > 0.0) && v.iter().any(|t| *t < 0.0));
}

/// Every float parameter of `m` by checkpoint path.
fn named_params<M: Module>(m: &M) -> std::collections::BTreeMap<String, Vec<f32>> {
    getavatar_core::generator::checkpoint::collect_params(m)
        .unwrap()
        .into_iter()
        .map(|(name, _, v)| (name, v))
        .collect()
}

#[test]
fn the_texture_branch_learns_at_its_own_rate() {
    use getavatar_core::burn::module::{ModuleVisitor, Param};
    use getavatar_core::generator::network::GeneratorConfig;
    use getavatar_core::generator::pipeline::{is_texture_param, Generator};
    let dev = cpu().autodiff();
    let cfg = GeneratorConfig::preset("tiny").expect("tiny preset");
    let g = Generator::new(&cfg, 0, &dev);
    // A loss that reaches every trainable parameter, with non-zero gradients also where a
    // weight starts at 0 or 1 (biases): Σ (w − 0.37)².
    struct Sq(Option<Tensor<1>>);
    impl ModuleVisitor for Sq {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            let s = (p.val() - 0.37).powf_scalar(2.0).sum();
            self.0 = Some(match self.0.take() {
                Some(t) => t + s,
                None => s,
            });
        }
    }
    let before = named_params(&g);
    let step = |factor: f32| {
        let mut sq = Sq(None);
        g.visit(&mut sq);
        let grads = sq.0.expect("parameters").backward();
        let mut adam = Adam::new(0.9, 0.99, 1e-8);
        named_params(&adam.step_scaled(1e-3, g.clone(), &grads, &|n| if is_texture_param(n) { factor } else { 1.0 }))
    };
    let (plain, scaled) = (step(1.0), step(4.0));
    let mut branches = [0usize; 4];
    for (name, b) in &before {
        let moved = |after: &Vec<f32>| after.iter().zip(b).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        let (dp, ds) = (moved(&plain[name]), moved(&scaled[name]));
        if name.ends_with("w_avg") {
            assert!(dp == 0.0 && ds == 0.0, "{name} is tracked, not trained");
            continue;
        }
        assert!(dp > 5e-4, "{name} moved only {dp}");
        let want = if is_texture_param(name) { 4.0 } else { 1.0 };
        assert!((ds / dp - want).abs() < 1e-2 * want, "{name}: moved {ds} vs {dp}, want ×{want}");
        for (k, p) in ["mapping_tex.", ".to_texture.", "decoders.texture.", "decoders.to_rgb."].iter().enumerate() {
            branches[k] += name.contains(p) as usize;
        }
    }
    assert!(branches.iter().all(|&n| n > 0), "every texture part was seen: {branches:?}");
    // The geometry side is outside the branch.
    for n in
        ["mapping_geo.layers.0.weight", "synthesis.blocks.0.convs.0.weight", "synthesis.blocks.1.to_geometry.weight"]
    {
        assert!(before.contains_key(n) && !is_texture_param(n), "{n}");
    }
    assert!(before.contains_key("decoders.sdf.out.weight") && !is_texture_param("decoders.offset.out.weight"));
}
