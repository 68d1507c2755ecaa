//! The paper's multiscale channel attention and spatial attention (one pair per stage).
//!
//! Both end in `2 * sigmoid(last layer)` whose last layer starts at zero, so a fresh
//! module multiplies by exactly 1.0: an untrained network is the plain backbone.
use tch::{nn, Tensor};

/// Kernel sizes of the channel attention's branches (paper: 3x3, 5x5, 7x7).
pub const BRANCH_KERNELS: [i64; 3] = [3, 5, 7];

fn zero_init() -> (nn::Init, nn::Init) {
    (nn::Init::Const(0.), nn::Init::Const(0.))
}

/// Group convolution module: 2x2/2 max and average pooling, each channel's two maps
/// side by side, then a 3x3 group conv with two inputs per group (paper eq. 1).
struct Gcm {
    conv: nn::Conv2D,
}

impl Gcm {
    fn new(p: nn::Path, c: i64) -> Self {
        let cfg = nn::ConvConfig { padding: 1, groups: c, ..Default::default() };
        Self { conv: nn::conv2d(p, 2 * c, c, 3, cfg) }
    }

    fn forward(&self, x: &Tensor) -> Tensor {
        // ceil_mode keeps a 1-pixel map alive at small inputs instead of failing.
        let mx = x.max_pool2d([2, 2], [2, 2], [0, 0], [1, 1], true);
        let av = x.avg_pool2d([2, 2], [2, 2], [0, 0], true, false, None::<i64>);
        // The group conv over interleaved [max_c, avg_c] pairs equals two depthwise convs
        // summed; that skips materialising the 2C-channel stack (a large copy on CPU).
        let c = mx.size()[1];
        let w = &self.conv.ws;
        let depthwise = |input: &Tensor, tap: i64, bias: Option<&Tensor>| {
            input.conv2d(&w.narrow(1, tap, 1), bias, [1, 1], [1, 1], [1, 1], c)
        };
        depthwise(&mx, 0, self.conv.bs.as_ref()) + depthwise(&av, 1, None)
    }
}

/// One scale: a depthwise kxk conv, two GCMs, global average pooling, sigmoid.
struct Branch {
    conv: nn::Conv2D,
    gcm: [Gcm; 2],
}

impl Branch {
    fn forward(&self, x: &Tensor) -> Tensor {
        let y = x.apply(&self.conv);
        let y = self.gcm[1].forward(&self.gcm[0].forward(&y));
        y.mean_dim([2i64, 3].as_slice(), false, None).sigmoid()
    }
}

pub struct ChannelAttention {
    branches: Vec<Branch>,
    fc1: nn::Linear,
    fc2: nn::Linear,
}

impl ChannelAttention {
    pub fn new(p: &nn::Path, c: i64, reduction: i64) -> Self {
        let branches = BRANCH_KERNELS
            .iter()
            .map(|&k| {
                let bp = p / format!("branch{k}");
                // Depthwise: a dense CxC 7x7 conv would cost more than the backbone.
                let cfg = nn::ConvConfig { padding: k / 2, groups: c, ..Default::default() };
                Branch {
                    conv: nn::conv2d(&bp / "conv", c, c, k, cfg),
                    gcm: [Gcm::new(&bp / "gcm1", c), Gcm::new(&bp / "gcm2", c)],
                }
            })
            .collect();
        let hidden = (c / reduction.max(1)).max(8);
        let (ws, bs) = zero_init();
        Self {
            branches,
            fc1: nn::linear(p / "fc1", 3 * c, hidden, Default::default()),
            fc2: nn::linear(p / "fc2", hidden, c, nn::LinearConfig { ws_init: ws, bs_init: Some(bs), bias: true }),
        }
    }

    pub fn forward(&self, x: &Tensor) -> Tensor {
        let maps: Vec<Tensor> = self.branches.iter().map(|b| b.forward(x)).collect();
        let weights = Tensor::cat(&maps, 1).apply(&self.fc1).relu().apply(&self.fc2).sigmoid() * 2.0;
        let (n, c) = weights.size2().expect("[N, C] channel weights");
        x * weights.reshape([n, c, 1, 1])
    }
}

/// CBAM-style spatial attention: channel max and mean maps, 3x3 conv, 1x1 conv, sigmoid (eq. 4).
pub struct SpatialAttention {
    conv1: nn::Conv2D,
    conv2: nn::Conv2D,
}

impl SpatialAttention {
    pub fn new(p: &nn::Path) -> Self {
        let (ws, bs) = zero_init();
        Self {
            conv1: nn::conv2d(p / "conv1", 2, 1, 3, nn::ConvConfig { padding: 1, ..Default::default() }),
            conv2: nn::conv2d(p / "conv2", 1, 1, 1, nn::ConvConfig { ws_init: ws, bs_init: bs, ..Default::default() }),
        }
    }

    pub fn forward(&self, u: &Tensor) -> Tensor {
        let mx = u.amax([1i64].as_slice(), true);
        let av = u.mean_dim([1i64].as_slice(), true, None);
        let m = Tensor::cat(&[mx, av], 1).apply(&self.conv1).apply(&self.conv2).sigmoid() * 2.0;
        u * m
    }
}

/// Channel attention then spatial attention, applied to one stage's output.
pub struct StageAttention {
    channel: ChannelAttention,
    spatial: SpatialAttention,
}

impl StageAttention {
    pub fn new(p: &nn::Path, c: i64, reduction: i64) -> Self {
        Self {
            channel: ChannelAttention::new(&(p / "channel"), c, reduction),
            spatial: SpatialAttention::new(&(p / "spatial")),
        }
    }

    pub fn forward(&self, x: &Tensor) -> Tensor {
        self.spatial.forward(&self.channel.forward(x))
    }
}
