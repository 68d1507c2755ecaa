//! What a training run leaves: the heads file (trained tensors and provenance), the resumable
//! state, and the loss and validation curves.
use super::spec::TrainSpec;
use super::validate::ValScore;
use crate::eval::plots;
use crate::model::config::ModelConfig;
use crate::model::heads::{self, Whitening};
use crate::model::network::HEAD_PREFIXES;
use crate::model::weights::WeightFile;
use crate::model::Model;
use anyhow::Result;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::Path;
use tch::{Device, Tensor};

/// Everything a resumed run needs, saved after each epoch beside `checkpoint.safetensors`.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct State {
    pub epochs_done: usize,
    pub step: usize,
    /// (step, loss) of every step.
    pub losses: Vec<(usize, f64)>,
    /// Per epoch (0 = before training): each set's scores.
    pub validation: Vec<Vec<ValScore>>,
    pub best_epoch: usize,
    pub best_score: f64,
    pub seconds: f64,
    pub images: usize,
}

pub fn is_trained(name: &str, layer4: bool) -> bool {
    HEAD_PREFIXES.iter().any(|p| name.starts_with(p)) || (layer4 && name.starts_with("layer4."))
}

/// The trained tensors of a model (what a heads file holds), sorted by name.
pub fn trained_tensors(model: &Model, layer4: bool) -> Vec<(String, Tensor)> {
    let mut v: Vec<(String, Tensor)> = model
        .var_store()
        .variables()
        .into_iter()
        .filter(|(n, _)| is_trained(n, layer4))
        .map(|(n, t)| (n, t.detach().to_device(Device::Cpu)))
        .collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}

pub fn write_heads(
    spec: &TrainSpec,
    path: &Path,
    model: &Model,
    w: Option<&Whitening>,
    extra: &[(&str, String)],
) -> Result<()> {
    let mut meta = HashMap::new();
    meta.insert(
        heads::META_POOLING.into(),
        serde_json::to_value(spec.config.pooling)?.as_str().unwrap_or("gap").into(),
    );
    meta.insert("datasets".into(), spec.set.sources.join("; "));
    meta.insert("recipe".into(), serde_json::to_string(&spec.recipe)?);
    let size = |c: &ModelConfig| format!("{}x{}", c.preprocess.width, c.preprocess.height);
    meta.insert("train_input_size".into(), size(&spec.config));
    meta.insert("validation_input_size".into(), size(&spec.val_config));
    for (k, v) in extra {
        meta.insert((*k).into(), v.clone());
    }
    // Provenance of heads this run started from (their data, recipe, steps), if any.
    if let Some(init) = &spec.init_heads {
        let mut m = WeightFile::read(init)?.metadata;
        m.remove(heads::META_BACKBONE_SHA256);
        meta.insert("init_heads".into(), serde_json::to_string(&m)?);
    }
    heads::write(path, trained_tensors(model, spec.recipe.train_layer4), w, &model.weights_sha256, meta)
}

pub fn plot(out: &Path, st: &State) -> Result<()> {
    let raw: Vec<(f64, f64)> = st.losses.iter().map(|&(s, l)| (s as f64, l)).collect();
    // A running mean over 20 steps shows the trend under the batch-to-batch noise.
    let smooth: Vec<(f64, f64)> = raw
        .iter()
        .enumerate()
        .map(|(i, &(s, _))| {
            let w = &raw[i.saturating_sub(19)..=i];
            (s, w.iter().map(|p| p.1).sum::<f64>() / w.len() as f64)
        })
        .collect();
    plots::lines(
        &out.join("loss.png"),
        "training loss (multi-similarity)",
        ("step", "loss"),
        &[("loss".into(), raw), ("mean of 20".into(), smooth)],
    )?;
    let mut series = Vec::new();
    let names: Vec<String> =
        st.validation.first().map(|v| v.iter().map(|s| s.set.clone()).collect()).unwrap_or_default();
    for (i, name) in names.iter().enumerate() {
        let pick = |f: fn(&ValScore) -> f64| -> Vec<(f64, f64)> {
            st.validation.iter().enumerate().filter_map(|(e, v)| v.get(i).map(|s| (e as f64, f(s)))).collect()
        };
        series.push((format!("{name} recall@1"), pick(|s| s.recall_at_1)));
        series.push((format!("{name} AP"), pick(|s| s.average_precision)));
        series.push((format!("{name} R@100P"), pick(|s| s.recall_at_100_precision)));
    }
    plots::lines(&out.join("validation.png"), "validation (epoch 0 = before training)", ("epoch", "score"), &series)
}

pub fn save_state(out: &Path, st: &State) -> Result<()> {
    let tmp = out.join("state.json.partial");
    std::fs::write(&tmp, serde_json::to_vec_pretty(st)?)?;
    std::fs::rename(&tmp, out.join("state.json"))?;
    Ok(())
}
