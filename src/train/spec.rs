//! What a training run is given: the backbone and the heads it starts from, the network
//! configurations, the training and validation sets, the recipe and the whitening to fit.
use super::data::TrainSet;
use super::loss::MsParams;
use crate::model::config::ModelConfig;
use serde::{Deserialize, Serialize};
use std::ops::Range;
use std::path::PathBuf;
use tch::Device;

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Recipe {
    pub epochs: usize,
    pub places_per_batch: usize,
    pub views: usize,
    pub lr: f64,
    pub weight_decay: f64,
    pub warmup_steps: usize,
    pub clip_norm: f64,
    pub seed: u64,
    pub steps_per_epoch: Option<usize>,
    /// Epochs without a better validation score before stopping.
    pub patience: usize,
    pub train_layer4: bool,
    /// Light augmentation of labelled views too.
    pub augment_labelled: bool,
    pub loss: MsParams,
    /// Mixed precision of the training forward pass on CUDA (`--autocast`); F32: none.
    #[serde(default = "no_autocast")]
    pub autocast: crate::model::device::DType,
}

#[derive(Clone, Debug)]
pub struct WhitenSpec {
    pub dim: Option<i64>,
    /// At most this many training frames (evenly spaced) are embedded to fit it.
    pub frames: usize,
    pub shrink: f64,
}

pub struct TrainSpec {
    pub weights: PathBuf,
    pub init_heads: Option<PathBuf>,
    /// Network configuration while training (input size: cost per step).
    pub config: ModelConfig,
    /// Configuration for validation and the whitening fit (the size the heads will serve at).
    pub val_config: ModelConfig,
    pub device: Device,
    pub set: TrainSet,
    pub val: Vec<ValSet>,
    pub out: PathBuf,
    /// The trained model's name when `out` is served as a model folder (`serve --models`; its
    /// `model.json`); None: the folder's name.
    pub name: Option<String>,
    pub recipe: Recipe,
    pub whiten: Option<WhitenSpec>,
    pub resume: bool,
    /// Descriptor cache shared with `loopd eval` (keys include the heads' hash).
    pub cache_dir: Option<PathBuf>,
}

/// A validation set: evaluated with `loopd eval`'s code, never trained on.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ValSet {
    pub name: String,
    pub sequence: PathBuf,
    pub query_sequence: Option<PathBuf>,
    pub gt: String,
    pub tolerance: usize,
    pub exclude: usize,
    pub range: Option<Range<usize>>,
    pub filter: Option<String>,
}

fn no_autocast() -> crate::model::device::DType {
    crate::model::device::DType::F32
}
