//! Validation during training: each validation set evaluated through `loopd eval`'s code, the
//! model-selection score and the shipping rule; and the whitening fit on frames embedded the same
//! way.
use super::spec::{TrainSpec, WhitenSpec};
use super::whiten;
use crate::engine::{Engine, EngineConfig};
use crate::eval::run::{embed_files, evaluate_sequences, EmbedSetup, EvalSpec};
use crate::model::config::ModelConfig;
use crate::model::device::DType;
use crate::model::heads::Whitening;
use crate::model::network::Variant;
use crate::model::preprocess::ImageLimits;
use crate::model::Model;
use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use tch::Tensor;

/// One validation of one set.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ValScore {
    pub set: String,
    pub recall_at_100_precision: f64,
    pub recall_at_1: f64,
    pub average_precision: f64,
}

/// The model-selection score: mean recall@1 over the validation sets (AP breaks ties), among
/// the epochs that pass [`keeps_r_at_100p`].
pub fn selection_score(v: &[ValScore]) -> f64 {
    let n = v.len().max(1) as f64;
    v.iter().map(|s| s.recall_at_1 + 1e-3 * s.average_precision).sum::<f64>() / n
}

/// The shipping rule's first part: no validation set loses recall at 100% precision against the
/// heads training started from (epoch 0). A better ranking within queries must not cost the
/// scores' meaning across queries (docs/training.md).
pub fn keeps_r_at_100p(v: &[ValScore], start: &[ValScore]) -> bool {
    v.iter().zip(start).all(|(a, b)| a.recall_at_100_precision + 1e-9 >= b.recall_at_100_precision)
}

pub fn load_model(spec: &TrainSpec, config: &ModelConfig, heads: Option<&Path>) -> Result<Model> {
    let (mut model, _) = Model::load(&spec.weights, config.clone(), spec.device, DType::F32)
        .with_context(|| format!("loading weights {}", spec.weights.display()))?;
    if let Some(h) = heads {
        model.load_heads(h).with_context(|| format!("loading heads {}", h.display()))?;
    }
    Ok(model)
}

/// An engine for `loopd eval`'s embedding code (validation, whitening frames), with its setup.
pub fn embedding_engine(spec: &TrainSpec, model: Model) -> Result<(Engine, EmbedSetup<'_>)> {
    let cfg = EngineConfig { max_batch: 16, warm_up: false, ..Default::default() };
    let setup = EmbedSetup {
        weights: &spec.weights,
        variant: Variant::FULL,
        cache_dir: spec.cache_dir.as_deref(),
        max_batch: cfg.max_batch,
    };
    Ok((Engine::start(model, cfg, ImageLimits::default())?, setup))
}

/// Validates a heads file on every validation set through `loopd eval`'s code.
pub fn validate(spec: &TrainSpec, heads: Option<&Path>) -> Result<Vec<ValScore>> {
    if spec.val.is_empty() {
        return Ok(Vec::new());
    }
    let (engine, setup) = embedding_engine(spec, load_model(spec, &spec.val_config, heads)?)?;
    spec.val
        .iter()
        .map(|v| {
            let es = EvalSpec {
                verify: None,
                intrinsics: None,
                sequence: &v.sequence,
                query_sequence: v.query_sequence.as_deref(),
                gt: &v.gt,
                camera: None,
                tolerance: v.tolerance,
                exclude: v.exclude,
                out: None,
                filter: v.filter.as_deref(),
                range: v.range.clone(),
                calibrator: None,
                samples_out: None,
                index: Default::default(),
                features: Default::default(),
                depth: None,
                poses: None,
            };
            let r =
                evaluate_sequences(&engine, &es, &setup).with_context(|| format!("validation set {}", v.name))?.report;
            Ok(ValScore {
                set: v.name.clone(),
                recall_at_100_precision: r.recall_at_100_precision,
                recall_at_1: r.recall_at_1,
                average_precision: r.average_precision,
            })
        })
        .collect()
}

pub fn log_validation(epoch: usize, v: &[ValScore]) {
    for s in v {
        tracing::info!(
            epoch,
            set = %s.set,
            r100p = s.recall_at_100_precision,
            recall1 = s.recall_at_1,
            ap = s.average_precision,
            "validation"
        );
    }
}

/// Embeds up to `w.frames` training frames with the given heads (through the engine, as `loopd
/// eval` does) and fits the whitening on them.
pub fn fit_whitening(spec: &TrainSpec, heads_path: &Path, w: &WhitenSpec) -> Result<Whitening> {
    let mut model = load_model(spec, &spec.val_config, Some(heads_path))?;
    model.set_whitening(None);
    let n = spec.set.samples.len();
    let step = n.div_ceil(w.frames.max(1)).max(1);
    let files: Vec<PathBuf> = spec.set.samples.iter().step_by(step).map(|s| s.path.clone()).collect();
    let (engine, setup) = embedding_engine(spec, model)?;
    let rows = embed_files(&engine, &files, &setup, "whitening frames")?;
    let flat: Vec<f32> = rows.iter().flatten().copied().collect();
    let dim = rows.first().map_or(0, Vec::len) as i64;
    let x = Tensor::from_slice(&flat).reshape([rows.len() as i64, dim]);
    tracing::info!(frames = rows.len(), dim = ?w.dim, "fitting whitening");
    whiten::fit(&x, w.dim, w.shrink)
}
