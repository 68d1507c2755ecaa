//! The descriptor network: backbone, per-stage attention, fusion, pooled unit descriptor.
use super::attention::StageAttention;
use super::backbone::{Backbone, STAGE_CHANNELS};
pub use super::config::Variant;
use super::config::{ModelConfig, Pooling};
use super::fusion::Fusion;
use tch::{nn, Tensor};

pub const DESCRIPTOR_DIM: i64 = 2048;

/// All parameters always exist, whatever the variant, so one weight file serves every ablation.
pub struct Network {
    pub(crate) pooling: Pooling,
    backbone: Backbone,
    attention: Vec<StageAttention>,
    fusion: Fusion,
}

/// Parameter name prefixes of the paper's additions (absent from ImageNet weight files).
pub const HEAD_PREFIXES: [&str; 2] = ["attention.", "fusion."];

impl Network {
    pub fn new(root: &nn::Path, cfg: &ModelConfig) -> Self {
        let att = root / "attention";
        Self {
            pooling: cfg.pooling,
            backbone: Backbone::new(root, cfg.stride_layout),
            attention: STAGE_CHANNELS
                .iter()
                .enumerate()
                .map(|(i, &c)| StageAttention::new(&(&att / i), c, cfg.channel_reduction))
                .collect(),
            fusion: Fusion::new(&(root / "fusion"), STAGE_CHANNELS[0], STAGE_CHANNELS[3]),
        }
    }

    /// The final feature map ([N, 2048, h, w]) before pooling.
    pub fn feature_map(&self, x: &Tensor, v: Variant) -> Tensor {
        let mut y = self.backbone.stem(x);
        let mut shallow = None;
        for i in 0..4 {
            y = self.backbone.stage(i, &y);
            if v.attention {
                y = self.attention[i].forward(&y);
            }
            if i == 0 && v.fusion {
                shallow = Some(y.shallow_clone());
            }
        }
        match shallow {
            Some(s) => self.fusion.forward(&s, &y),
            None => y,
        }
    }

    /// Global average pooling (and, with `Pooling::GapSqrt`, the signed square root) and L2
    /// normalisation: [N, 2048] unit rows (cosine = dot).
    pub fn descriptor(&self, x: &Tensor, v: Variant) -> Tensor {
        let pooled = self.feature_map(x, v).mean_dim([2i64, 3].as_slice(), false, None);
        match self.pooling {
            Pooling::Gap => l2_normalize(&pooled),
            Pooling::GapSqrt => l2_normalize(&(pooled.sign() * pooled.abs().sqrt())),
        }
    }

    /// ImageNet class probabilities of the plain backbone ([N, 1000]).
    pub fn class_probabilities(&self, x: &Tensor) -> Tensor {
        let pooled = self.feature_map(x, Variant::BACKBONE).mean_dim([2i64, 3].as_slice(), false, None);
        self.backbone.logits(&pooled).softmax(-1, None)
    }
}

pub fn l2_normalize(x: &Tensor) -> Tensor {
    let norm = x.norm_scalaropt_dim(2, [1i64].as_slice(), true).clamp_min(1e-12);
    x / norm
}
