//! Views of one image for training: random resized crop, small rotation and perspective,
//! colour jitter, blur and grey-scale, on RGB 0-255 tensors (before normalisation).
use rand::{rngs::StdRng, Rng};
use tch::{Kind, Tensor};

#[derive(Clone, Copy, Debug, serde::Serialize, serde::Deserialize)]
pub struct Strength {
    /// Smallest kept side fraction of a random resized crop.
    pub min_scale: f64,
    pub max_rotation_deg: f64,
    /// Largest perspective term (normalised image coordinates).
    pub perspective: f64,
    /// Brightness, contrast and saturation factors vary by +- this.
    pub jitter: f64,
    pub blur_probability: f64,
    pub grey_probability: f64,
}

impl Strength {
    /// For unlabelled images, whose only positives are their views (SimCLR-like, milder crops:
    /// a place must stay recognisable).
    pub const STRONG: Strength = Strength {
        min_scale: 0.6,
        max_rotation_deg: 10.0,
        perspective: 0.15,
        jitter: 0.4,
        blur_probability: 0.3,
        grey_probability: 0.2,
    };
    /// For labelled views (real positives already differ).
    pub const LIGHT: Strength = Strength {
        min_scale: 0.85,
        max_rotation_deg: 3.0,
        perspective: 0.05,
        jitter: 0.15,
        blur_probability: 0.1,
        grey_probability: 0.05,
    };
}

/// One augmented view of `rgb` ([3, H, W], 0-255), same size.
pub fn view(rgb: &Tensor, s: &Strength, rng: &mut StdRng) -> Tensor {
    let (_, h, w) = rgb.size3().expect("[3, H, W] image");
    let x = rgb.unsqueeze(0);
    // Geometry: a homography from output to input coordinates in [-1, 1]: crop scale and shift,
    // rotation, perspective terms; sampled with bilinear interpolation, borders replicated.
    let scale = rng.random_range(s.min_scale..=1.0);
    let (tx, ty) = ((1.0 - scale) * rng.random_range(-1.0..=1.0), (1.0 - scale) * rng.random_range(-1.0..=1.0));
    let a = rng.random_range(-s.max_rotation_deg..=s.max_rotation_deg).to_radians();
    let (px, py) = (rng.random_range(-s.perspective..=s.perspective), rng.random_range(-s.perspective..=s.perspective));
    let hm = [scale * a.cos(), -scale * a.sin(), tx, scale * a.sin(), scale * a.cos(), ty, px, py, 1.0];
    let hm = Tensor::from_slice(&hm.map(|v| v as f32)).reshape([3, 3]);
    let ys = Tensor::linspace(-1.0, 1.0, h, (Kind::Float, tch::Device::Cpu));
    let xs = Tensor::linspace(-1.0, 1.0, w, (Kind::Float, tch::Device::Cpu));
    let gy = ys.unsqueeze(1).expand([h, w], false);
    let gx = xs.unsqueeze(0).expand([h, w], false);
    let ones = Tensor::ones([h, w], (Kind::Float, tch::Device::Cpu));
    let pts = Tensor::stack(&[gx, gy, ones], 2).reshape([h * w, 3]).matmul(&hm.tr());
    let xy = pts.narrow(1, 0, 2) / pts.narrow(1, 2, 1).clamp_min(1e-3);
    let grid = xy.reshape([1, h, w, 2]);
    let mut y = x.grid_sampler(&grid, 0, 1, true);
    // Colour: brightness, contrast (around the mean), saturation (around the grey image).
    let j = s.jitter;
    let grey = |t: &Tensor| {
        let wts = Tensor::from_slice(&[0.299f32, 0.587, 0.114]).reshape([1, 3, 1, 1]);
        (t * wts).sum_dim_intlist([1i64].as_slice(), true, None)
    };
    y *= rng.random_range(1.0 - j..=1.0 + j);
    let mean = y.mean(Kind::Float);
    y = (&y - &mean) * rng.random_range(1.0 - j..=1.0 + j) + &mean;
    let g = grey(&y);
    y = &g + (&y - &g) * rng.random_range(1.0 - j..=1.0 + j);
    if rng.random_bool(s.blur_probability) {
        let sigma = rng.random_range(0.3..1.5f64);
        let k: Vec<f32> = (-2..=2).map(|i: i32| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp() as f32).collect();
        let sum: f32 = k.iter().sum();
        let k = Tensor::from_slice(&k.iter().map(|v| v / sum).collect::<Vec<_>>());
        let kx = k.reshape([1, 1, 1, 5]).repeat([3, 1, 1, 1]);
        let ky = k.reshape([1, 1, 5, 1]).repeat([3, 1, 1, 1]);
        y = y.replication_pad2d([2, 2, 0, 0]).conv2d(&kx, None::<Tensor>, [1, 1], [0, 0], [1, 1], 3);
        y = y.replication_pad2d([0, 0, 2, 2]).conv2d(&ky, None::<Tensor>, [1, 1], [0, 0], [1, 1], 3);
    }
    if rng.random_bool(s.grey_probability) {
        y = grey(&y).expand([1, 3, h, w], false);
    }
    y.clamp(0.0, 255.0).squeeze_dim(0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn views_keep_the_size_differ_and_repeat_with_the_seed() {
        let img = Tensor::rand([3, 32, 64], (Kind::Float, tch::Device::Cpu)) * 255.0;
        let a = view(&img, &Strength::STRONG, &mut StdRng::seed_from_u64(1));
        let b = view(&img, &Strength::STRONG, &mut StdRng::seed_from_u64(1));
        let c = view(&img, &Strength::STRONG, &mut StdRng::seed_from_u64(2));
        assert_eq!(a.size(), vec![3, 32, 64]);
        assert!(a.equal(&b));
        assert!(f64::try_from((&a - &c).abs().mean(Kind::Float)).unwrap() > 1.0);
        let (lo, hi) = (f64::try_from(a.min()).unwrap(), f64::try_from(a.max()).unwrap());
        assert!(lo >= 0.0 && hi <= 255.0);
    }
}
