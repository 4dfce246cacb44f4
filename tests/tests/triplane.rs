//! Triplane lookup (paper Sec. 4.1): the row-table sampler (autodiff devices) agrees with the
//! backends' `grid_sample_2d` (inference) inside, at the border and outside the box, and is
//! exact on a linear plane; its gradients with respect to the planes and the points match
//! finite differences (of the native path) on NdArray and on Wgpu (lavapipe). On NdArray the
//! lookup is its own operation (tracked or not), checked against the row table and
//! `grid_sample_2d`.

use getavatar_core::burn::tensor::{Device, Tensor, TensorData};
use getavatar_core::generator::network::triplane::{sample_triplanes, sample_triplanes_native, sample_triplanes_rows};
use getavatar_core::geometry::tet_grid::{REFERENCE_BOX_CENTER, REFERENCE_BOX_SIZE};
use getavatar_core::util::rng::Rng;

mod common;
use common::{cpu, gpu, linear_fd_error, smooth_fd_error, values, SmoothFd};

const B: usize = 2;
const C: usize = 3;
const R: usize = 5;

fn planes(v: &[f32], dev: &Device) -> Tensor<4> {
    Tensor::from_data(TensorData::new(v.to_vec(), [B, 3 * C, R, R]), dev)
}

fn points(v: &[f32], n: usize, dev: &Device) -> Tensor<3> {
    Tensor::from_data(TensorData::new(v.to_vec(), [B, n, 3]), dev)
}

/// Random planes, and canonical points: mostly inside the box, some within a texel of its
/// faces (partly zero-padded) and some far outside (all zeros).
fn scene(n: usize) -> (Vec<f32>, Vec<f32>) {
    let mut rng = Rng::new(3, 4);
    let p: Vec<f32> = (0..B * 3 * C * R * R).map(|_| rng.uniform() * 2.0 - 1.0).collect();
    let c = REFERENCE_BOX_CENTER.to_array();
    let mut q = Vec::new();
    for i in 0..B * n {
        let reach = match i % 4 {
            0 => 1.1,  // across the border
            1 => 3.0,  // mostly far outside
            _ => 0.95, // inside
        };
        for ck in c {
            q.push(ck + 0.5 * REFERENCE_BOX_SIZE * reach * (rng.uniform() * 2.0 - 1.0));
        }
    }
    (p, q)
}

#[test]
fn triplane_lookup_matches_grid_sample_inside_at_the_border_and_outside() {
    let dev = cpu();
    let n = 64;
    let (p, q) = scene(n);
    let got = values(sample_triplanes_rows(planes(&p, &dev), points(&q, n, &dev)));
    let want = values(sample_triplanes_native(planes(&p, &dev), points(&q, n, &dev)));
    let err = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
    assert!(err < 1e-5, "max difference {err}");
    // Constants on an autodiff device take the untracked lookup of the inner backend: on
    // NdArray the lookup's own forward pass (over the CPU cores), the same values as on the
    // plain device and as `grid_sample_2d` up to float rounding.
    let ad = dev.clone().autodiff();
    let (pa, qa) = (planes(&p, &ad), points(&q, n, &ad));
    assert!(pa.is_autodiff() && !pa.is_tracked());
    let untracked = values(sample_triplanes(pa, qa));
    assert_eq!(untracked, values(sample_triplanes(planes(&p, &dev), points(&q, n, &dev))));
    let err = untracked.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
    assert!(err < 1e-5, "untracked: max difference {err}");
    // The scene exercises all three cases: zeros (far outside), partial borders, interiors.
    let zero_rows = want.chunks(C).filter(|f| f.iter().all(|x| *x == 0.0)).count();
    assert!(zero_rows > 0 && zero_rows < B * n / 2, "{zero_rows} all-zero points");
    // A linear plane is reproduced exactly at interior points (bilinear is exact on it).
    let mut lin = vec![0f32; B * 3 * C * R * R];
    for (i, x) in lin.iter_mut().enumerate() {
        let (y, xx) = ((i / R) % R, i % R);
        *x = if (i / (R * R)) % (3 * C) == 0 { 0.5 * xx as f32 + 0.25 * y as f32 } else { 0.0 };
    }
    let c = REFERENCE_BOX_CENTER.to_array();
    let texel = REFERENCE_BOX_SIZE / R as f32;
    // (x, y) = centre + (0.3, −0.7) texels: plane 0 reads 0.5·(2 + 0.3) + 0.25·(2 − 0.7).
    let one: Vec<f32> = (0..B).flat_map(|_| [c[0] + 0.3 * texel, c[1] - 0.7 * texel, c[2]]).collect();
    let f = values(sample_triplanes_rows(planes(&lin, &dev), points(&one, 1, &dev)));
    let want0 = 0.5 * 2.3 + 0.25 * 1.3;
    assert!((f[0] - want0).abs() < 1e-5, "{} vs {want0}", f[0]);
}

fn grad_check(dev: &Device) {
    let n = 24;
    let (p, q) = scene(n);
    let mut rng = Rng::new(5, 6);
    let w: Vec<f32> = (0..B * n * C).map(|_| rng.uniform() * 2.0 - 1.0).collect();
    let loss = |pl: Tensor<4>, pt: Tensor<3>, d: &Device| {
        let wt = Tensor::<3>::from_data(TensorData::new(w.clone(), [B, n, C]), d);
        (sample_triplanes(pl, pt) * wt).sum()
    };
    let ad = dev.clone().autodiff();
    let (pl, pt) = (planes(&p, &ad).require_grad(), points(&q, n, &ad).require_grad());
    let grads = loss(pl.clone(), pt.clone(), &ad).backward();
    let gp = values(pl.grad(&grads).expect("plane gradient"));
    let gq = values(pt.grad(&grads).expect("point gradient"));
    let plain = |p: &[f32], q: &[f32]| values(loss(planes(p, dev), points(q, n, dev), dev))[0] as f64;

    // Planes: the lookup is linear in them, so central differences are exact up to rounding.
    let (err, scale) = linear_fd_error(&|p| plain(p, &q), &p, &gp, 0.05);
    assert!(scale > 0.1 && err / scale < 1e-3, "plane gradients: max error {err} of {scale}");

    // Points: piecewise bilinear; steps well inside a texel (texel = 0.46 m at R = 5) keep
    // almost every stencil within one cell. A coordinate whose two step sizes disagree
    // straddles a texel line and is set aside (a few at most).
    let SmoothFd { stable, diff, size } = smooth_fd_error(&|q| plain(&p, q), &q, &gq, (1e-3, 3e-3), 1e-3);
    assert!(stable.len() * 10 >= q.len() * 9, "only {} of {} coordinates are smooth", stable.len(), q.len());
    assert!(
        size > 0.1 && diff / size < 1e-2,
        "point gradients: relative error {} over {} coordinates",
        diff / size,
        stable.len()
    );
}

/// On NdArray the tracked lookup is one operation with its own backward pass
/// (`ndarray_ops::triplane_bilinear`); the row-table sampler is what other backends use. Both
/// give the same values and the same gradients for the planes and the points.
#[test]
fn the_cpu_lookup_operation_equals_the_row_table_sampler_and_so_do_its_gradients() {
    let ad = cpu().autodiff();
    let n = 64;
    let (p, q) = scene(n);
    let mut rng = Rng::new(7, 8);
    let w: Vec<f32> = (0..B * n * C).map(|_| rng.uniform() * 2.0 - 1.0).collect();
    let run = |op: bool| {
        let (pl, pt) = (planes(&p, &ad).require_grad(), points(&q, n, &ad).require_grad());
        let y =
            if op { sample_triplanes(pl.clone(), pt.clone()) } else { sample_triplanes_rows(pl.clone(), pt.clone()) };
        let wt = Tensor::<3>::from_data(TensorData::new(w.clone(), [B, n, C]), &ad);
        let grads = (y.clone() * wt).sum().backward();
        (values(y), values(pl.grad(&grads).expect("plane gradient")), values(pt.grad(&grads).expect("point gradient")))
    };
    let (op, rows) = (run(true), run(false));
    for (what, a, b) in [("values", &op.0, &rows.0), ("∂planes", &op.1, &rows.1), ("∂points", &op.2, &rows.2)] {
        assert_eq!(a.len(), b.len(), "{what}");
        let scale = b.iter().fold(0f32, |m, v| m.max(v.abs()));
        let err = a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0f32, f32::max);
        assert!(scale > 0.1 && err <= 1e-5 * scale, "{what}: max difference {err} of {scale}");
    }
}

#[test]
fn triplane_gradients_match_finite_differences_on_ndarray() {
    grad_check(&cpu());
}

#[test]
fn triplane_gradients_match_finite_differences_on_wgpu() {
    grad_check(&gpu());
}
