//! FID and KID from Inception pool3 features ([`crate::inception`]).
//!
//! - FID (Heusel et al.): ‖μ₁ − μ₂‖² + tr Σ₁ + tr Σ₂ − 2 tr (Σ₁Σ₂)^½ with unbiased
//!   covariances (as numpy's `np.cov`). tr (Σ₁Σ₂)^½ is computed as tr (Σ₁^½ Σ₂ Σ₁^½)^½, both
//!   symmetric PSD, from symmetric eigendecompositions (no complex `sqrtm`). With fewer samples
//!   than feature dimensions the same value comes from the n₁×n₂ cross-Gram matrix:
//!   tr (Σ₁Σ₂)^½ = ‖X₁ᶜ X₂ᶜᵀ‖_* / √((n₁−1)(n₂−1)) (nuclear norm of the centred features),
//!   which is what [`fid`] uses then (exact, and much cheaper than 2048² eigenproblems).
//! - KID (Bińkowski et al.): the unbiased MMD² with the cubic polynomial kernel
//!   k(x, y) = (xᵀy/d + 1)³, averaged over random subsets, exactly as StyleGAN2-ADA's
//!   `kernel_inception_distance` (100 subsets of at most 1000 samples by default).

use anyhow::{bail, Result};
use getavatar_core::util::rng::Rng;
use nalgebra::{DMatrix, DVector, SymmetricEigen};

/// Mean and unbiased covariance of a feature set.
pub struct FeatureStats {
    pub mean: DVector<f64>,
    pub cov: DMatrix<f64>,
}

/// Features as an n×d matrix; all rows must have one length.
fn matrix(f: &[Vec<f32>]) -> Result<DMatrix<f64>> {
    let d = f.first().map(|r| r.len()).unwrap_or(0);
    if d == 0 || f.iter().any(|r| r.len() != d) {
        bail!("features must be non-empty rows of one length");
    }
    if f.iter().flatten().any(|v| !v.is_finite()) {
        bail!("features contain NaN or infinity");
    }
    Ok(DMatrix::from_fn(f.len(), d, |i, j| f[i][j] as f64))
}

fn centred(x: &DMatrix<f64>) -> (DVector<f64>, DMatrix<f64>) {
    let mean = DVector::from_fn(x.ncols(), |j, _| x.column(j).mean());
    let mut c = x.clone();
    for mut row in c.row_iter_mut() {
        row -= mean.transpose();
    }
    (mean, c)
}

impl FeatureStats {
    pub fn from_features(f: &[Vec<f32>]) -> Result<Self> {
        if f.len() < 2 {
            bail!("FID needs at least 2 feature vectors per set (got {})", f.len());
        }
        let (mean, c) = centred(&matrix(f)?);
        let cov = c.transpose() * &c / (f.len() - 1) as f64;
        Ok(Self { mean, cov })
    }
}

/// Σ √max(λ, 0) over the eigenvalues of a symmetric matrix.
fn trace_sqrt_psd(m: &DMatrix<f64>) -> f64 {
    let sym = (m + m.transpose()) * 0.5;
    sym.symmetric_eigenvalues().iter().map(|l| l.max(0.0).sqrt()).sum()
}

/// FID between two Gaussians given by their statistics.
pub fn frechet_distance(a: &FeatureStats, b: &FeatureStats) -> Result<f64> {
    if a.mean.len() != b.mean.len() {
        bail!("feature dimensions differ ({} vs {})", a.mean.len(), b.mean.len());
    }
    let e = SymmetricEigen::new((&a.cov + a.cov.transpose()) * 0.5);
    let root = DVector::from_iterator(e.eigenvalues.len(), e.eigenvalues.iter().map(|l| l.max(0.0).sqrt()));
    let sqrt_a = &e.eigenvectors * DMatrix::from_diagonal(&root) * e.eigenvectors.transpose();
    let cross = trace_sqrt_psd(&(&sqrt_a * &b.cov * &sqrt_a));
    let dm = (&a.mean - &b.mean).norm_squared();
    Ok(dm + a.cov.trace() + b.cov.trace() - 2.0 * cross)
}

/// FID between two feature sets (the cross-Gram route when samples < dimensions).
pub fn fid(a: &[Vec<f32>], b: &[Vec<f32>]) -> Result<f64> {
    let (xa, xb) = (matrix(a)?, matrix(b)?);
    if xa.ncols() != xb.ncols() {
        bail!("feature dimensions differ ({} vs {})", xa.ncols(), xb.ncols());
    }
    if a.len() < 2 || b.len() < 2 {
        bail!("FID needs at least 2 feature vectors per set (got {} and {})", a.len(), b.len());
    }
    if a.len().max(b.len()) >= xa.ncols() {
        return frechet_distance(&FeatureStats::from_features(a)?, &FeatureStats::from_features(b)?);
    }
    let ((ma, ca), (mb, cb)) = (centred(&xa), centred(&xb));
    let (na, nb) = ((a.len() - 1) as f64, (b.len() - 1) as f64);
    let g = &ca * cb.transpose();
    // ‖G‖_* = Σ √eig(G Gᵀ).
    let nuclear = trace_sqrt_psd(&(&g * g.transpose()));
    let dm = (ma - mb).norm_squared();
    Ok(dm + ca.norm_squared() / na + cb.norm_squared() / nb - 2.0 * nuclear / (na * nb).sqrt())
}

/// KID (unbiased MMD², cubic polynomial kernel) over `subsets` random subsets of
/// min(|real|, |fake|, `max_subset`) samples each, drawn without replacement.
pub fn kid(real: &[Vec<f32>], fake: &[Vec<f32>], subsets: usize, max_subset: usize, seed: u64) -> Result<f64> {
    let (xr, xf) = (matrix(real)?, matrix(fake)?);
    if xr.ncols() != xf.ncols() {
        bail!("feature dimensions differ ({} vs {})", xr.ncols(), xf.ncols());
    }
    let m = real.len().min(fake.len()).min(max_subset);
    if m < 2 || subsets == 0 {
        bail!("KID needs at least 2 samples per set and one subset");
    }
    let d = xr.ncols() as f64;
    let mut rng = Rng::new(seed, 0x4b1d);
    let mut pick = |x: &DMatrix<f64>| -> DMatrix<f64> {
        let mut idx: Vec<usize> = (0..x.nrows()).collect();
        for i in 0..m {
            let j = i + rng.below(idx.len() - i);
            idx.swap(i, j);
        }
        x.select_rows(&idx[..m])
    };
    let kernel = |p: &DMatrix<f64>, q: &DMatrix<f64>| (p * q.transpose()).map(|v| (v / d + 1.0).powi(3));
    let mut t = 0.0;
    for _ in 0..subsets {
        let x = pick(&xf);
        let y = pick(&xr);
        let a = kernel(&x, &x) + kernel(&y, &y);
        let b = kernel(&x, &y);
        t += (a.sum() - a.trace()) / (m - 1) as f64 - b.sum() * 2.0 / m as f64;
    }
    Ok(t / subsets as f64 / m as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gaussian(n: usize, d: usize, mean: f32, sigma: f32, seed: u64) -> Vec<Vec<f32>> {
        let mut r = Rng::new(seed, 7);
        (0..n).map(|_| (0..d).map(|_| mean + sigma * r.normal()).collect()).collect()
    }

    #[test]
    fn fid_of_two_by_two_gaussians_matches_the_closed_form() {
        // Non-commuting covariances: for 2×2, tr (Σ₁Σ₂)^½ = √(tr Σ₁Σ₂ + 2√(det Σ₁ det Σ₂)).
        let s1 = DMatrix::from_row_slice(2, 2, &[2.0, 0.6, 0.6, 1.0]);
        let s2 = DMatrix::from_row_slice(2, 2, &[0.5, -0.3, -0.3, 1.5]);
        let a = FeatureStats { mean: DVector::from_vec(vec![1.0, 2.0]), cov: s1.clone() };
        let b = FeatureStats { mean: DVector::from_vec(vec![0.0, 4.0]), cov: s2.clone() };
        let cross = ((&s1 * &s2).trace() + 2.0 * (s1.determinant() * s2.determinant()).sqrt()).sqrt();
        let want = 5.0 + s1.trace() + s2.trace() - 2.0 * cross;
        let got = frechet_distance(&a, &b).unwrap();
        assert!((got - want).abs() < 1e-9, "{got} vs {want}");
        assert!(frechet_distance(&a, &a).unwrap().abs() < 1e-9);
    }

    #[test]
    fn fid_of_sampled_gaussians_approaches_the_analytic_value() {
        // N(0, I) vs N(0.5, 1.5² I) in 4-D: FID = 4·0.25 + 4·(1 − 1.5)² = 2.
        let a = gaussian(20000, 4, 0.0, 1.0, 1);
        let b = gaussian(20000, 4, 0.5, 1.5, 2);
        let got = fid(&a, &b).unwrap();
        assert!((got - 2.0).abs() < 0.05, "{got}");
    }

    #[test]
    fn the_gram_route_equals_the_covariance_route() {
        let a = gaussian(5, 9, 0.0, 1.0, 3);
        let b = gaussian(7, 9, 0.3, 0.8, 4);
        let gram = fid(&a, &b).unwrap();
        let cov =
            frechet_distance(&FeatureStats::from_features(&a).unwrap(), &FeatureStats::from_features(&b).unwrap())
                .unwrap();
        // Rank-deficient covariances: √ of ~1e-16 eigenvalues adds ~1e-8 of round-off.
        assert!((gram - cov).abs() < 1e-6 * cov.abs().max(1.0), "{gram} vs {cov}");
        assert!(fid(&a, &a).unwrap().abs() < 1e-6);
    }

    #[test]
    fn kid_matches_a_hand_computed_example() {
        // x = {0, 1}, y = {2, 3} (d = 1), k(a, b) = (ab + 1)³: off-diagonal Σk_xx = 2, Σk_yy = 686,
        // Σk_xy = 1 + 1 + 27 + 64 = 93 → ((2 + 686)/1 − 2·93/2)/2 = 297.5.
        let got = kid(&[vec![2.0], vec![3.0]], &[vec![0.0], vec![1.0]], 3, 1000, 0).unwrap();
        assert!((got - 297.5).abs() < 1e-9, "{got}");
    }

    #[test]
    fn kid_is_near_zero_for_one_distribution_and_positive_for_two() {
        let a = gaussian(400, 8, 0.0, 1.0, 5);
        let b = gaussian(400, 8, 0.0, 1.0, 6);
        let c = gaussian(400, 8, 1.0, 1.0, 7);
        let same = kid(&a, &b, 20, 200, 0).unwrap();
        let diff = kid(&a, &c, 20, 200, 0).unwrap();
        assert!(same.abs() < 0.05 && diff > 0.5, "same {same}, shifted {diff}");
    }

    #[test]
    fn bad_inputs_are_errors() {
        assert!(fid(&[vec![1.0, 2.0]], &[vec![1.0, 2.0], vec![0.0, 1.0]]).is_err());
        assert!(fid(&[vec![1.0, 2.0], vec![1.0]], &[vec![1.0, 2.0], vec![0.0, 1.0]]).is_err());
        assert!(kid(&[vec![f32::NAN], vec![1.0]], &[vec![0.0], vec![1.0]], 1, 10, 0).is_err());
    }
}
