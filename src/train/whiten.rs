//! PCA whitening of unit descriptors (Jégou & Chum 2012; Radenović et al. 2018): fitted on
//! training frames, it decorrelates the descriptor and flattens the bursty directions.
use crate::model::heads::Whitening;
use anyhow::{bail, Result};
use tch::{Kind, Tensor};

/// Fits on `x` ([N, D] unit rows). `dim`: rows kept (largest variance first; None: all that the
/// data supports, at most N - 1). `shrink`: added to every eigenvalue as a fraction of their
/// mean, so that near-empty directions are not blown up into noise.
pub fn fit(x: &Tensor, dim: Option<i64>, shrink: f64) -> Result<Whitening> {
    let (n, d) = x.size2()?;
    if n < 2 {
        bail!("whitening needs at least 2 frames, got {n}");
    }
    // By default as many as the data supports, rounded down to whole 8-lane SIMD blocks (the
    // store's search kernels run on multiples of 8).
    let keep = match dim {
        Some(k) => k.min(d).min(n - 1),
        None => {
            let k = d.min(n - 1);
            if k >= 8 {
                k - k % 8
            } else {
                k
            }
        }
    };
    if keep < 1 {
        bail!("whitening dimension must be at least 1");
    }
    let x = x.to_kind(Kind::Double);
    let mean = x.mean_dim([0i64].as_slice(), false, None);
    let xc = &x - &mean;
    let cov = xc.tr().matmul(&xc) / (n - 1) as f64;
    let (values, vectors) = cov.linalg_eigh("L"); // ascending
    let values = values.flip([0]).narrow(0, 0, keep).clamp_min(0.0);
    let vectors = vectors.flip([1]).narrow(1, 0, keep);
    let eps = shrink * f64::try_from(values.mean(Kind::Double))?.max(1e-12);
    let scale = (values + eps).rsqrt();
    let proj = vectors.tr() * scale.unsqueeze(1);
    Ok(Whitening { mean: mean.to_kind(Kind::Float), proj: proj.to_kind(Kind::Float) })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Whitened training data has (close to) identity covariance before the final L2.
    #[test]
    fn whitened_training_data_is_decorrelated() {
        tch::manual_seed(3);
        let mix = Tensor::randn([8, 8], (Kind::Float, tch::Device::Cpu));
        let x = Tensor::randn([4000, 8], (Kind::Float, tch::Device::Cpu)).matmul(&mix);
        let w = fit(&x, None, 0.0).unwrap();
        let y = (&x - &w.mean).matmul(&w.proj.tr());
        let cov = y.tr().matmul(&y) / 3999.0;
        let off = (&cov - Tensor::eye(8, (Kind::Float, tch::Device::Cpu))).abs().max();
        assert!(f64::try_from(off).unwrap() < 1e-3, "{cov}");
        let w4 = fit(&x, Some(4), 0.1).unwrap();
        assert_eq!(w4.proj.size(), vec![4, 8]);
        assert_eq!(w4.apply(&x).size(), vec![4000, 4]);
    }
}
