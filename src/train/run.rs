//! `loopd train`: the heads (and optionally layer4) on a frozen ImageNet backbone, P x K batches,
//! multi-similarity loss, AdamW with warm-up and cosine decay, validation through `loopd eval`'s
//! code every epoch, early stopping, checkpoints, curves; then optional PCA whitening.
use super::augment::{self, Strength};
pub use super::checkpoint::State;
use super::checkpoint::{is_trained, plot, save_state, write_heads};
use super::data::TrainSet;
use super::loss::multi_similarity;
use super::sampler::epoch_batches;
pub use super::spec::{Recipe, TrainSpec, ValSet, WhitenSpec};
use super::validate::{fit_whitening, keeps_r_at_100p, load_model, log_validation, selection_score};
pub use super::validate::{validate, ValScore};
use crate::model::config::ModelConfig;
use crate::model::network::Variant;
use crate::model::preprocess::{decode, normalize, resized_rgb, ImageLimits};
use crate::model::script::check_name;
use crate::model::served::{BuiltinManifest, BUILTIN_KIND};
use crate::model::Model;
use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rand::{rngs::StdRng, SeedableRng};
use std::path::{Path, PathBuf};
use std::time::Instant;
use tch::{nn::OptimizerConfig, Tensor};

/// What `train` produced.
pub struct Outcome {
    pub heads: PathBuf,
    pub state: State,
    /// Validation of the final file (with whitening, if fitted).
    pub final_validation: Vec<ValScore>,
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
    // Under autocast the network runs in half precision; the loss takes f32 descriptors.
    let d =
        crate::model::device::autocast(r.autocast, || model.forward_train(x, Variant::FULL)).to_kind(tch::Kind::Float);
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
    let name = model_name(spec)?;
    std::fs::create_dir_all(&spec.out)?;
    let ckpt = spec.out.join("checkpoint.safetensors");
    let best = spec.out.join("best.safetensors");
    let final_path = spec.out.join(HEADS_FILE);

    // The heads' random starting values (all but their zeroed last layers) come from the seed,
    // through a generator of their own: libtorch's global one is shared with every other thread.
    let mut model = load_model(spec, &spec.config, spec.init_heads.as_deref())?;
    if spec.init_heads.is_none() {
        model.seed_heads(r.seed);
    }
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
    // The folder is a model a server serves (`serve --models`) beside its default network.
    let scores: Vec<String> = final_validation
        .iter()
        .map(|v| {
            format!(
                "{} R@100P {:.3} recall@1 {:.3} AP {:.3}",
                v.set, v.recall_at_100_precision, v.recall_at_1, v.average_precision
            )
        })
        .collect();
    BuiltinManifest {
        name,
        kind: BUILTIN_KIND.into(),
        heads: Some(HEADS_FILE.into()),
        license: String::new(),
        source: format!(
            "loopd train on {}: best epoch {} of {}, {} steps; validation: {}",
            spec.set.sources.join("; "),
            st.best_epoch,
            st.epochs_done,
            st.step,
            if scores.is_empty() { "none".into() } else { scores.join(", ") }
        ),
    }
    .write(&spec.out)?;
    Ok(Outcome { heads: final_path, state: st, final_validation })
}

/// The heads file `train` writes into its output folder.
pub const HEADS_FILE: &str = "heads.safetensors";

/// The name the output folder is served under: `spec.name`, or the folder's own name.
fn model_name(spec: &TrainSpec) -> Result<String> {
    let name = match &spec.name {
        Some(n) => n.clone(),
        None => spec.out.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default(),
    };
    check_name(&name).with_context(|| {
        format!("the trained model's name (--name, default the --out folder's name {})", spec.out.display())
    })?;
    Ok(name)
}
