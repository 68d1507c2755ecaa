//! `loopd train`: the heads (and optionally layer4) on a frozen ImageNet backbone, P x K batches,
//! multi-similarity loss, AdamW with warm-up and cosine decay, validation through `loopd eval`'s
//! code every epoch, early stopping, checkpoints, curves; then optional PCA whitening.
use super::augment::{self, Strength};
use super::data::TrainSet;
use super::loss::{multi_similarity, MsParams};
use super::sampler::epoch_batches;
use super::whiten;
use crate::engine::{Engine, EngineConfig};
use crate::eval::plots;
use crate::eval::run::{embed_files, evaluate_sequences, EmbedSetup, EvalSpec};
use crate::model::config::ModelConfig;
use crate::model::device::DType;
use crate::model::heads::{self, Whitening};
use crate::model::network::{Variant, HEAD_PREFIXES};
use crate::model::preprocess::{decode, normalize, resized_rgb, ImageLimits};
use crate::model::weights::WeightFile;
use crate::model::Model;
use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rand::{rngs::StdRng, SeedableRng};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::time::Instant;
use tch::{nn::OptimizerConfig, Device, Tensor};

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
    pub recipe: Recipe,
    pub whiten: Option<WhitenSpec>,
    pub resume: bool,
    /// Descriptor cache shared with `loopd eval` (keys include the heads' hash).
    pub cache_dir: Option<PathBuf>,
}

/// One validation of one set.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ValScore {
    pub set: String,
    pub recall_at_100_precision: f64,
    pub recall_at_1: f64,
    pub average_precision: f64,
}

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

/// What `train` produced.
pub struct Outcome {
    pub heads: PathBuf,
    pub state: State,
    /// Validation of the final file (with whitening, if fitted).
    pub final_validation: Vec<ValScore>,
}

/// The model-selection score: mean recall@1 over the validation sets (AP breaks ties), among
/// the epochs that pass [`keeps_r_at_100p`].
fn selection_score(v: &[ValScore]) -> f64 {
    let n = v.len().max(1) as f64;
    v.iter().map(|s| s.recall_at_1 + 1e-3 * s.average_precision).sum::<f64>() / n
}

/// The shipping rule's first part: no validation set loses recall at 100% precision against the
/// heads training started from (epoch 0). A better ranking within queries must not cost the
/// scores' meaning across queries (docs/training.md).
fn keeps_r_at_100p(v: &[ValScore], start: &[ValScore]) -> bool {
    v.iter().zip(start).all(|(a, b)| a.recall_at_100_precision + 1e-9 >= b.recall_at_100_precision)
}

fn is_trained(name: &str, layer4: bool) -> bool {
    HEAD_PREFIXES.iter().any(|p| name.starts_with(p)) || (layer4 && name.starts_with("layer4."))
}

/// The trained tensors of a model (what a heads file holds), sorted by name.
fn trained_tensors(model: &Model, layer4: bool) -> Vec<(String, Tensor)> {
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

fn load_model(spec: &TrainSpec, config: &ModelConfig, heads: Option<&Path>) -> Result<Model> {
    let (mut model, _) = Model::load(&spec.weights, config.clone(), spec.device, DType::F32)
        .with_context(|| format!("loading weights {}", spec.weights.display()))?;
    if let Some(h) = heads {
        model.load_heads(h).with_context(|| format!("loading heads {}", h.display()))?;
    }
    Ok(model)
}

/// An engine for `loopd eval`'s embedding code (validation, whitening frames), with its setup.
fn embedding_engine(spec: &TrainSpec, model: Model) -> Result<(Engine, EmbedSetup<'_>)> {
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

/// Reads, decodes and resizes one training image (RGB 0-255 tensor).
fn load_rgb(path: &Path, cfg: &ModelConfig) -> Result<Tensor> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    let img = decode(&bytes, &ImageLimits::default()).with_context(|| format!("decoding {}", path.display()))?;
    Ok(resized_rgb(&img, &cfg.preprocess))
}

/// Checks every training image before the first step: a bad file fails the run now.
fn check_images(set: &TrainSet) -> Result<()> {
    let limits = ImageLimits::default();
    for s in &set.samples {
        let bytes = std::fs::read(&s.path).with_context(|| format!("reading {}", s.path.display()))?;
        crate::model::preprocess::decode(&bytes, &limits).with_context(|| format!("decoding {}", s.path.display()))?;
    }
    Ok(())
}

/// Freezes all but the trained tensors (their gradients are never computed or stepped) and
/// builds AdamW over the rest; returns the optimizer and the trained tensors.
pub fn optimizer(model: &Model, r: &Recipe) -> Result<(tch::nn::Optimizer, Vec<Tensor>)> {
    let mut params = Vec::new();
    for (name, t) in model.var_store().variables() {
        let trained = is_trained(&name, r.train_layer4);
        let _ = t.set_requires_grad(trained);
        if trained {
            params.push(t);
        }
    }
    let opt = tch::nn::AdamW { wd: r.weight_decay, ..Default::default() }.build(model.var_store(), r.lr)?;
    Ok((opt, params))
}

/// One optimisation step on a prepared batch (normalised inputs, loss masks): forward with
/// autograd, multi-similarity loss, backward, gradient clipping, AdamW at `lr`. Returns the loss;
/// the clipped gradients stay in the tensors until the next step.
#[allow(clippy::too_many_arguments)]
pub fn step(
    model: &Model,
    opt: &mut tch::nn::Optimizer,
    params: &[Tensor],
    x: &Tensor,
    pos: &Tensor,
    neg: &Tensor,
    r: &Recipe,
    lr: f64,
) -> Result<f64> {
    opt.set_lr(lr);
    opt.zero_grad();
    let d = model.forward_train(x, Variant::FULL);
    let loss = multi_similarity(&d, pos, neg, &r.loss);
    loss.backward();
    clip_gradients(params, r.clip_norm);
    opt.step();
    Ok(f64::try_from(&loss)?)
}

fn lr_at(step: usize, total: usize, r: &Recipe) -> f64 {
    if step < r.warmup_steps {
        return r.lr * (step + 1) as f64 / r.warmup_steps as f64;
    }
    let t = (step - r.warmup_steps) as f64 / (total.saturating_sub(r.warmup_steps)).max(1) as f64;
    r.lr * 0.5 * (1.0 + (std::f64::consts::PI * t.min(1.0)).cos())
}

/// Scales gradients so their global L2 norm is at most `max`; returns the norm before.
fn clip_gradients(params: &[Tensor], max: f64) -> f64 {
    tch::no_grad(|| {
        let grads: Vec<Tensor> = params.iter().map(Tensor::grad).filter(Tensor::defined).collect();
        let total: f64 = grads.iter().map(|g| f64::try_from(g.square().sum(tch::Kind::Double)).unwrap_or(0.0)).sum();
        let norm = total.sqrt();
        if norm > max && max > 0.0 {
            for mut g in grads {
                let _ = g.g_mul_scalar_(max / (norm + 1e-6));
            }
        }
        norm
    })
}

fn write_heads(
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

fn plot(out: &Path, st: &State) -> Result<()> {
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

fn save_state(out: &Path, st: &State) -> Result<()> {
    let tmp = out.join("state.json.partial");
    std::fs::write(&tmp, serde_json::to_vec_pretty(st)?)?;
    std::fs::rename(&tmp, out.join("state.json"))?;
    Ok(())
}

/// Trains; writes `heads.safetensors` (best validation epoch, whitened if asked), the checkpoint,
/// `state.json`, `loss.png` and `validation.png` into `spec.out`.
pub fn train(spec: &TrainSpec) -> Result<Outcome> {
    let r = &spec.recipe;
    if spec.set.places.is_empty() {
        bail!("no training places (give --sequence, --places or --images)");
    }
    if r.places_per_batch < 2 || r.views < 2 {
        bail!("a batch needs at least 2 places and 2 views per place");
    }
    check_images(&spec.set)?;
    std::fs::create_dir_all(&spec.out)?;
    let ckpt = spec.out.join("checkpoint.safetensors");
    let best = spec.out.join("best.safetensors");
    let final_path = spec.out.join("heads.safetensors");

    // The heads' random starting values (all but their zeroed last layers) come from the seed.
    tch::manual_seed(r.seed as i64);
    let mut model = load_model(spec, &spec.config, spec.init_heads.as_deref())?;
    model.set_whitening(None); // trained underneath; refitted after if asked
    let mut st = State::default();
    if spec.resume && spec.out.join("state.json").is_file() && ckpt.is_file() {
        st = serde_json::from_slice(&std::fs::read(spec.out.join("state.json"))?)?;
        model.load_heads(&ckpt).context("resuming from checkpoint.safetensors")?;
        model.set_whitening(None);
        tracing::info!(epochs_done = st.epochs_done, step = st.step, "resumed");
    }
    let (mut opt, params) = optimizer(&model, r)?;
    if st.validation.is_empty() {
        let baseline = if let Some(h) = &spec.init_heads { validate(spec, Some(h))? } else { validate(spec, None)? };
        log_validation(0, &baseline);
        st.best_score = selection_score(&baseline);
        st.validation.push(baseline);
        write_heads(spec, &best, &model, None, &[])?;
    }
    let mut rng = StdRng::seed_from_u64(r.seed);
    let steps_in = |epoch: usize| {
        let n =
            epoch_batches(&spec.set, r.places_per_batch, r.views, r.seed, epoch, &mut StdRng::seed_from_u64(0)).len();
        r.steps_per_epoch.map_or(n, |s| s.min(n))
    };
    let per_epoch = steps_in(0);
    let total = per_epoch * r.epochs;
    tch::manual_seed(r.seed as i64);
    let started = Instant::now();
    for epoch in st.epochs_done..r.epochs {
        if r.patience > 0 && st.epochs_done >= st.best_epoch + r.patience {
            tracing::info!(epoch, best = st.best_epoch, "early stop: no better validation for {} epochs", r.patience);
            break;
        }
        let mut batches = epoch_batches(&spec.set, r.places_per_batch, r.views, r.seed, epoch, &mut rng);
        batches.truncate(per_epoch);
        let bar = ProgressBar::new(batches.len() as u64).with_style(
            ProgressStyle::with_template("epoch {prefix} {pos}/{len} {wide_bar} {msg} eta {eta}").expect("template"),
        );
        bar.set_prefix(format!("{}/{}", epoch + 1, r.epochs));
        let t0 = Instant::now();
        let mut images = 0usize;
        for b in &batches {
            let views = b
                .samples
                .iter()
                .zip(&b.augment)
                .map(|(&i, &aug)| {
                    let rgb = load_rgb(&spec.set.samples[i].path, &spec.config)?;
                    let rgb = match (aug, r.augment_labelled) {
                        (true, _) => augment::view(&rgb, &Strength::STRONG, &mut rng),
                        (false, true) => augment::view(&rgb, &Strength::LIGHT, &mut rng),
                        (false, false) => rgb,
                    };
                    Ok(normalize(&rgb, spec.config.preprocess.normalization))
                })
                .collect::<Result<Vec<_>>>()?;
            let x = Tensor::stack(&views, 0).to_device(spec.device);
            let (pos, neg) = (b.pos.to_device(spec.device), b.neg.to_device(spec.device));
            let l = step(&model, &mut opt, &params, &x, &pos, &neg, r, lr_at(st.step, total, r))?;
            if !l.is_finite() {
                bail!("loss is {l} at step {}: lower --lr", st.step);
            }
            st.losses.push((st.step, l));
            st.step += 1;
            images += views.len();
            let rate = images as f64 / t0.elapsed().as_secs_f64().max(1e-9);
            bar.set_message(format!("loss {l:.4} {rate:.1} img/s"));
            bar.inc(1);
        }
        bar.finish_and_clear();
        st.images += images;
        st.seconds += t0.elapsed().as_secs_f64();
        write_heads(spec, &ckpt, &model, None, &[])?;
        let v = validate(spec, Some(&ckpt))?;
        log_validation(epoch + 1, &v);
        let score = selection_score(&v);
        st.epochs_done = epoch + 1;
        let eligible = st.validation.first().is_none_or(|start| keeps_r_at_100p(&v, start));
        if !eligible {
            tracing::warn!(epoch = epoch + 1, "a validation set lost R@100P against epoch 0: not selectable");
        }
        if eligible && score > st.best_score {
            st.best_score = score;
            st.best_epoch = epoch + 1;
            let extra = [
                ("steps", st.step.to_string()),
                ("best_epoch", st.best_epoch.to_string()),
                ("seed", r.seed.to_string()),
                ("validation", serde_json::to_string(&v)?),
            ];
            write_heads(spec, &best, &model, None, &extra)?;
        }
        st.validation.push(v);
        save_state(&spec.out, &st)?;
        plot(&spec.out, &st)?;
    }
    tracing::info!(seconds = started.elapsed().as_secs_f64(), best_epoch = st.best_epoch, "training done");
    // The best epoch's heads (epoch 0: the starting heads), whitened if asked.
    let mut best_model = load_model(spec, &spec.config, Some(&best))?;
    best_model.set_whitening(None);
    let whitening = match &spec.whiten {
        Some(w) => Some(fit_whitening(spec, &best, w)?),
        None => None,
    };
    let best_val = st.validation.get(st.best_epoch).cloned().unwrap_or_default();
    let extra = |val: &[ValScore]| -> Result<Vec<(&'static str, String)>> {
        Ok(vec![
            ("steps", st.step.to_string()),
            ("best_epoch", st.best_epoch.to_string()),
            ("seed", r.seed.to_string()),
            ("validation", serde_json::to_string(val)?),
        ])
    };
    write_heads(spec, &final_path, &best_model, whitening.as_ref(), &extra(&best_val)?)?;
    let final_validation = if whitening.is_some() {
        let v = validate(spec, Some(&final_path))?;
        log_validation(st.best_epoch, &v);
        // Rewritten with its own numbers (same tensors, so the same descriptors).
        write_heads(spec, &final_path, &best_model, whitening.as_ref(), &extra(&v)?)?;
        v
    } else {
        best_val
    };
    save_state(&spec.out, &st)?;
    plot(&spec.out, &st)?;
    Ok(Outcome { heads: final_path, state: st, final_validation })
}

fn log_validation(epoch: usize, v: &[ValScore]) {
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
fn fit_whitening(spec: &TrainSpec, heads_path: &Path, w: &WhitenSpec) -> Result<Whitening> {
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
