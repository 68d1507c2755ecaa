//! What a network is built from: backbone layout, the paper's additions, input size.
use serde::{Deserialize, Serialize};

/// Where a stage's stride-2 sits in its first bottleneck block.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum StrideLayout {
    /// ResNet v1 (Keras/Caffe weights): stride on the first 1x1 conv.
    V1,
    /// ResNet v1.5 (torchvision weights): stride on the 3x3 conv.
    V15,
}

/// How an image becomes the network's input size.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum ResizeMode {
    /// Resize to exactly width x height (aspect ratio not kept). Batches always stack.
    Stretch,
    /// Scale to fit inside width x height, keeping the aspect ratio (no padding).
    Keep,
}

/// Input normalisation matching the weights' training.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Normalization {
    /// Keras "caffe": BGR, 0-255, minus the ImageNet mean.
    Caffe,
    /// torchvision: RGB, 0-1, minus mean, divided by std.
    Torch,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelConfig {
    pub stride_layout: StrideLayout,
    /// Multiscale channel + spatial attention after each stage.
    pub attention: bool,
    /// layer1 -> layer4 fusion.
    pub fusion: bool,
    /// Hidden width of the channel attention's fully connected layer is C / reduction.
    pub channel_reduction: i64,
    pub preprocess: Preprocess,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Preprocess {
    pub width: u32,
    pub height: u32,
    pub resize: ResizeMode,
    pub normalization: Normalization,
}

impl Default for Preprocess {
    fn default() -> Self {
        Self { width: 224, height: 224, resize: ResizeMode::Stretch, normalization: Normalization::Caffe }
    }
}

impl Default for ModelConfig {
    fn default() -> Self {
        Self {
            stride_layout: StrideLayout::V1,
            attention: true,
            fusion: true,
            channel_reduction: 16,
            preprocess: Preprocess::default(),
        }
    }
}

impl ModelConfig {
    /// A short id that names the descriptor space: sessions refuse descriptors of another.
    pub fn descriptor_id(&self) -> String {
        format!(
            "resnet50-{}{}{}-{}x{}-{}",
            match self.stride_layout {
                StrideLayout::V1 => "v1",
                StrideLayout::V15 => "v1.5",
            },
            if self.attention { "+att" } else { "" },
            if self.fusion { "+fus" } else { "" },
            self.preprocess.width,
            self.preprocess.height,
            match self.preprocess.resize {
                ResizeMode::Stretch => "stretch",
                ResizeMode::Keep => "keep",
            }
        )
    }
}

/// Parses "224" or "320x240" (width x height).
pub fn parse_input_size(s: &str) -> Result<(u32, u32), String> {
    let parse = |v: &str| -> Result<u32, String> {
        let n: u32 = v.trim().parse().map_err(|_| format!("bad input size '{s}': expected N or WxH"))?;
        if !(32..=4096).contains(&n) {
            return Err(format!("input size {n} out of range 32..=4096"));
        }
        Ok(n)
    };
    match s.split_once(['x', 'X']) {
        Some((w, h)) => Ok((parse(w)?, parse(h)?)),
        None => {
            let n = parse(s)?;
            Ok((n, n))
        }
    }
}
