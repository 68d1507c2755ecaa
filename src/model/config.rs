//! What a network is built from: backbone layout, the paper's additions, input size.
use serde::{Deserialize, Serialize};

/// Which of the paper's additions run in a forward pass (the ablation switches).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Variant {
    pub attention: bool,
    pub fusion: bool,
}

impl Variant {
    pub const FULL: Variant = Variant { attention: true, fusion: true };
    pub const BACKBONE: Variant = Variant { attention: false, fusion: false };
    pub const ALL: [Variant; 4] = [
        Variant { attention: true, fusion: true },
        Variant { attention: true, fusion: false },
        Variant { attention: false, fusion: true },
        Variant { attention: false, fusion: false },
    ];

    pub fn name(&self) -> &'static str {
        match (self.attention, self.fusion) {
            (true, true) => "attention+fusion",
            (true, false) => "attention",
            (false, true) => "fusion",
            (false, false) => "backbone",
        }
    }
}

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

/// How the final feature map becomes the descriptor (before L2 normalisation).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Pooling {
    /// Global average pooling (the paper).
    Gap,
    /// Global average pooling, then the signed square root of each value ("power
    /// normalisation"): a few bursty channels no longer dominate the cosine.
    GapSqrt,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelConfig {
    pub stride_layout: StrideLayout,
    pub pooling: Pooling,
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
            pooling: Pooling::Gap,
            channel_reduction: 16,
            preprocess: Preprocess::default(),
        }
    }
}

impl ModelConfig {
    /// Names the descriptor space: everything that changes a descriptor is in it (weights and
    /// heads by the hash of the file holding them, variant, input size, resize, normalisation,
    /// pooling). Sessions refuse descriptors computed under another id.
    pub fn descriptor_id(&self, variant: Variant, weights_sha256: &str, heads_sha256: Option<&str>) -> String {
        let heads = heads_sha256.map_or(String::new(), |h| format!("-h{}", &h[..h.len().min(12)]));
        format!(
            "{}-{}-{}-w{}{heads}",
            self.legacy_descriptor_id(variant),
            match self.preprocess.normalization {
                Normalization::Caffe => "caffe",
                Normalization::Torch => "torch",
            },
            match self.pooling {
                Pooling::Gap => "gap",
                Pooling::GapSqrt => "gap-sqrt",
            },
            &weights_sha256[..weights_sha256.len().min(12)]
        )
    }

    /// The id sessions were created with before weight hashes were part of it (loopd 0.1,
    /// ImageNet weights, identity heads): such sessions stay usable by the same configuration.
    pub fn legacy_descriptor_id(&self, variant: Variant) -> String {
        format!(
            "resnet50-{}{}{}-{}x{}-{}",
            match self.stride_layout {
                StrideLayout::V1 => "v1",
                StrideLayout::V15 => "v1.5",
            },
            if variant.attention { "+att" } else { "" },
            if variant.fusion { "+fus" } else { "" },
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

#[cfg(test)]
mod tests {
    use super::*;

    /// Every setting that changes a descriptor changes the id; nothing else does.
    #[test]
    fn every_descriptor_setting_changes_the_id() {
        let base = ModelConfig::default();
        let id = |c: &ModelConfig, v: Variant, w: &str| c.descriptor_id(v, w, None);
        let reference = id(&base, Variant::FULL, "aaaaaaaaaaaaaaaa");
        let mut variants = vec![
            id(&base, Variant::FULL, "bbbbbbbbbbbbbbbb"),
            base.descriptor_id(Variant::FULL, "aaaaaaaaaaaaaaaa", Some("cccccccccccccccc")),
            base.descriptor_id(Variant::FULL, "aaaaaaaaaaaaaaaa", Some("dddddddddddddddd")),
            id(&base, Variant::BACKBONE, "aaaaaaaaaaaaaaaa"),
            id(&base, Variant { attention: true, fusion: false }, "aaaaaaaaaaaaaaaa"),
            id(&base, Variant { attention: false, fusion: true }, "aaaaaaaaaaaaaaaa"),
        ];
        let changed = [
            ModelConfig { stride_layout: StrideLayout::V15, ..base.clone() },
            ModelConfig { pooling: Pooling::GapSqrt, ..base.clone() },
            ModelConfig { preprocess: Preprocess { width: 112, ..base.preprocess.clone() }, ..base.clone() },
            ModelConfig { preprocess: Preprocess { height: 112, ..base.preprocess.clone() }, ..base.clone() },
            ModelConfig {
                preprocess: Preprocess { resize: ResizeMode::Keep, ..base.preprocess.clone() },
                ..base.clone()
            },
            ModelConfig {
                preprocess: Preprocess { normalization: Normalization::Torch, ..base.preprocess.clone() },
                ..base.clone()
            },
        ];
        variants.extend(changed.iter().map(|c| id(c, Variant::FULL, "aaaaaaaaaaaaaaaa")));
        for (i, v) in variants.iter().enumerate() {
            assert_ne!(v, &reference, "change {i} kept the id");
        }
        let distinct: std::collections::HashSet<_> = variants.iter().collect();
        assert_eq!(distinct.len(), variants.len());
        assert_eq!(reference, id(&base.clone(), Variant::FULL, "aaaaaaaaaaaaaaaa"), "the id is stable");
    }
}
