//! Shallow-deep fusion: layer1 max-pooled to layer4's grid, 1x1 conv to 2048 channels, added.
use tch::{nn, Tensor};

pub struct Fusion {
    conv: nn::Conv2D,
}

impl Fusion {
    pub fn new(p: &nn::Path, shallow: i64, deep: i64) -> Self {
        // Zero start: the sum equals layer4 until training moves it.
        let cfg = nn::ConvConfig { ws_init: nn::Init::Const(0.), bs_init: nn::Init::Const(0.), ..Default::default() };
        Self { conv: nn::conv2d(p / "conv", shallow, deep, 1, cfg) }
    }

    pub fn forward(&self, shallow: &Tensor, deep: &Tensor) -> Tensor {
        let (_, _, h, w) = deep.size4().expect("4-d feature map");
        // Adaptive max pooling is exactly 8x8/8 at 224 (56 -> 7) and still lines up at other sizes.
        let (pooled, _) = shallow.adaptive_max_pool2d([h, w]);
        deep + pooled.apply(&self.conv)
    }
}
