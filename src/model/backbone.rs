//! ResNet50 in tch, with torchvision parameter names so one safetensors file fits both.
use super::config::StrideLayout;
use tch::{nn, Tensor};

/// Batch-norm epsilon of the stored statistics. Keras' 1e-3 is folded into the
/// running variance at import, so every weight file uses torchvision's 1e-5.
pub const BN_EPS: f64 = 1e-5;

fn conv(p: nn::Path, i: i64, o: i64, k: i64, stride: i64, padding: i64) -> nn::Conv2D {
    let cfg = nn::ConvConfig { stride, padding, bias: false, ..Default::default() };
    nn::conv2d(p, i, o, k, cfg)
}

fn bn(p: nn::Path, c: i64) -> nn::BatchNorm {
    nn::batch_norm2d(p, c, nn::BatchNormConfig { eps: BN_EPS, ..Default::default() })
}

struct Bottleneck {
    conv1: nn::Conv2D,
    bn1: nn::BatchNorm,
    conv2: nn::Conv2D,
    bn2: nn::BatchNorm,
    conv3: nn::Conv2D,
    bn3: nn::BatchNorm,
    downsample: Option<(nn::Conv2D, nn::BatchNorm)>,
}

impl Bottleneck {
    fn new(p: &nn::Path, inp: i64, width: i64, stride: i64, layout: StrideLayout) -> Self {
        let out = width * 4;
        let (s1, s3) = match layout {
            StrideLayout::V1 => (stride, 1),
            StrideLayout::V15 => (1, stride),
        };
        let downsample = (stride != 1 || inp != out)
            .then(|| (conv(p / "downsample" / 0, inp, out, 1, stride, 0), bn(p / "downsample" / 1, out)));
        Self {
            conv1: conv(p / "conv1", inp, width, 1, s1, 0),
            bn1: bn(p / "bn1", width),
            conv2: conv(p / "conv2", width, width, 3, s3, 1),
            bn2: bn(p / "bn2", width),
            conv3: conv(p / "conv3", width, out, 1, 1, 0),
            bn3: bn(p / "bn3", out),
            downsample,
        }
    }

    fn forward(&self, x: &Tensor) -> Tensor {
        let y = x.apply(&self.conv1).apply_t(&self.bn1, false).relu();
        let y = y.apply(&self.conv2).apply_t(&self.bn2, false).relu();
        let y = y.apply(&self.conv3).apply_t(&self.bn3, false);
        let shortcut = match &self.downsample {
            Some((c, b)) => x.apply(c).apply_t(b, false),
            None => x.shallow_clone(),
        };
        (y + shortcut).relu()
    }
}

pub struct Backbone {
    conv1: nn::Conv2D,
    bn1: nn::BatchNorm,
    stages: Vec<Vec<Bottleneck>>,
    fc: nn::Linear,
}

/// Output channels of layer1..layer4.
pub const STAGE_CHANNELS: [i64; 4] = [256, 512, 1024, 2048];
const STAGE_BLOCKS: [usize; 4] = [3, 4, 6, 3];
const STAGE_WIDTHS: [i64; 4] = [64, 128, 256, 512];

impl Backbone {
    pub fn new(p: &nn::Path, layout: StrideLayout) -> Self {
        let mut inp = 64;
        let mut stages = Vec::with_capacity(4);
        for (i, (&blocks, &width)) in STAGE_BLOCKS.iter().zip(&STAGE_WIDTHS).enumerate() {
            let sp = p / format!("layer{}", i + 1);
            let stride = if i == 0 { 1 } else { 2 };
            let mut stage = Vec::with_capacity(blocks);
            for b in 0..blocks {
                stage.push(Bottleneck::new(&(&sp / b), inp, width, if b == 0 { stride } else { 1 }, layout));
                inp = width * 4;
            }
            stages.push(stage);
        }
        Self {
            conv1: conv(p / "conv1", 3, 64, 7, 2, 3),
            bn1: bn(p / "bn1", 64),
            stages,
            fc: nn::linear(p / "fc", 2048, 1000, Default::default()),
        }
    }

    /// conv1, bn, relu, 3x3/2 max pool: 224 -> 56.
    pub fn stem(&self, x: &Tensor) -> Tensor {
        // Inputs to the pool are >= 0 (after ReLU), so torch's -inf padding equals Keras' zero padding.
        x.apply(&self.conv1).apply_t(&self.bn1, false).relu().max_pool2d([3, 3], [2, 2], [1, 1], [1, 1], false)
    }

    /// Stage `i` (0-based: layer1..layer4).
    pub fn stage(&self, i: usize, x: &Tensor) -> Tensor {
        self.stages[i].iter().fold(x.shallow_clone(), |y, block| block.forward(&y))
    }

    /// ImageNet logits from a pooled 2048-d feature.
    pub fn logits(&self, pooled: &Tensor) -> Tensor {
        pooled.apply_t(&self.fc, false)
    }
}
