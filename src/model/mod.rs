//! The descriptor model: network definition, weights, preprocessing.
pub mod attention;
pub mod backbone;
pub mod config;
pub mod device;
pub mod fusion;
pub mod heads;
pub mod labels;
pub mod network;
pub mod preprocess;
pub mod script;
pub mod served;
pub mod tfjs;
pub mod weights;

use anyhow::{bail, Result};
use config::{ModelConfig, Normalization, StrideLayout};
use device::DType;
use network::{Network, Variant};
use std::path::Path;
use tch::{nn::VarStore, Device, Tensor};
use weights::{LoadReport, WeightFile};

/// A network on its device with its weights: the one object that runs forward passes.
/// Not `Sync` (tch tensors); the engine gives it to a single thread.
pub struct Model {
    pub config: ModelConfig,
    pub device: Device,
    pub dtype: DType,
    /// SHA-256 (hex) of the weight file loaded; "none" for a model built without one.
    pub weights_sha256: String,
    /// SHA-256 of the weight file's bytes (the weights' name in loopd 0.2's descriptor ids).
    pub weights_file_sha256: String,
    /// SHA-256 (hex) of the heads file loaded on top (`--heads`), if any.
    pub heads_sha256: Option<String>,
    /// Learned whitening from the heads file, applied after pooling.
    whitening: Option<heads::Whitening>,
    /// The weight file and configuration it was loaded with (before any heads): what a
    /// `builtin` model folder builds its own network from ([`Model::sibling`]).
    pub origin: Option<(std::path::PathBuf, ModelConfig)>,
    vs: VarStore,
    net: Network,
}

impl Model {
    /// A model with the var store's default initialisation (heads at identity).
    pub fn new(config: ModelConfig, device: Device, dtype: DType) -> Result<Self> {
        dtype.check(device)?;
        let vs = VarStore::new(Device::Cpu);
        let net = Network::new(&vs.root(), &config);
        Ok(Self {
            config,
            device,
            dtype,
            weights_sha256: "none".into(),
            weights_file_sha256: "none".into(),
            heads_sha256: None,
            whitening: None,
            origin: None,
            vs,
            net,
        })
    }

    /// Loads a loopd weight file; its metadata fixes the stride layout and normalisation.
    pub fn load(path: &Path, mut config: ModelConfig, device: Device, dtype: DType) -> Result<(Self, LoadReport)> {
        let file = WeightFile::read(path)?;
        if let Some(layout) = file.metadata.get(weights::META_STRIDE_LAYOUT) {
            config.stride_layout = serde_json::from_value::<StrideLayout>(layout.as_str().into())?;
        }
        if let Some(norm) = file.metadata.get(weights::META_NORMALIZATION) {
            config.preprocess.normalization = serde_json::from_value::<Normalization>(norm.as_str().into())?;
        }
        let mut model = Self::new(config.clone(), Device::Cpu, DType::F32)?;
        model.origin = Some((path.to_path_buf(), config));
        let report = weights::load_into(&model.vs, &file)?;
        model.weights_sha256 = file.sha256.clone();
        model.weights_file_sha256 = file.file_sha256.clone();
        model.to(device, dtype)?;
        Ok((model, report))
    }

    /// Loads a heads file (`loopd train`'s output) on top of the backbone. Its pooling setting,
    /// if it states one, replaces the configured one (its whitening was fitted after it).
    /// Names the same descriptor space had in earlier releases, for sessions made then: the id
    /// before weight hashes (loopd 0.1, average pooling) and the id with the weight file's byte
    /// hash (0.2). Only without heads: heads did not exist then.
    pub fn earlier_descriptor_ids(&self) -> Vec<String> {
        if self.heads_sha256.is_some() {
            return Vec::new();
        }
        let mut ids = vec![self.config.descriptor_id(Variant::FULL, &self.weights_file_sha256, None)];
        if self.config.pooling == config::Pooling::Gap {
            ids.push(self.config.legacy_descriptor_id(Variant::FULL));
        }
        ids
    }

    pub fn load_heads(&mut self, path: &Path) -> Result<heads::LoadedHeads> {
        let mut loaded = heads::load_into(&self.vs, path, &self.weights_sha256)?;
        if let Some(p) = loaded.metadata.get(heads::META_POOLING) {
            let pooling = serde_json::from_value::<config::Pooling>(p.as_str().into())?;
            if pooling != self.config.pooling {
                tracing::warn!(heads = %path.display(), ?pooling, "pooling set by the heads file");
            }
            self.set_pooling(pooling);
        }
        self.whitening = loaded.whitening.take().map(|w| w.to_device(self.device));
        self.heads_sha256 = Some(loaded.sha256.clone());
        Ok(loaded)
    }

    /// Another network on the same weights, configuration, device and precision as this one,
    /// with `heads` on top (None: the identity heads, the plain backbone); this model's own heads
    /// are not carried over. Needs a model loaded from a weight file ([`Model::load`]).
    pub fn sibling(&self, heads: Option<&Path>) -> Result<Self> {
        let Some((weights, config)) = &self.origin else {
            bail!("this network was not loaded from a weight file: no other network can share its weights")
        };
        let (mut model, _) = Self::load(weights, config.clone(), self.device, self.dtype)?;
        if let Some(h) = heads {
            model.load_heads(h).map_err(|e| e.context(format!("loading heads {}", h.display())))?;
        }
        Ok(model)
    }

    pub fn set_pooling(&mut self, pooling: config::Pooling) {
        self.config.pooling = pooling;
        self.net.pooling = pooling;
    }

    /// Replaces the whitening (None: plain pooled descriptors).
    pub fn set_whitening(&mut self, w: Option<heads::Whitening>) {
        self.whitening = w.map(|w| w.to_device(self.device));
    }

    pub fn whitening(&self) -> Option<&heads::Whitening> {
        self.whitening.as_ref()
    }

    /// Length of the descriptors this model computes.
    pub fn dim(&self) -> i64 {
        self.whitening.as_ref().map_or(network::DESCRIPTOR_DIM, heads::Whitening::dim)
    }

    pub fn to(&mut self, device: Device, dtype: DType) -> Result<()> {
        dtype.check(device)?;
        self.whitening = self.whitening.take().map(|w| w.to_device(device));
        self.vs.set_device(device);
        self.vs.set_kind(dtype.kind());
        self.device = device;
        self.dtype = dtype;
        Ok(())
    }

    /// The descriptor space this model's `variant` computes (see `ModelConfig::descriptor_id`).
    pub fn descriptor_id(&self, variant: Variant) -> String {
        self.config.descriptor_id(variant, &self.weights_sha256, self.heads_sha256.as_deref())
    }

    pub fn var_store(&self) -> &VarStore {
        &self.vs
    }

    /// Pooled unit descriptors of a batch with autograd on (training; no whitening).
    pub fn forward_train(&self, x: &Tensor, v: Variant) -> Tensor {
        self.net.descriptor(&channels_last(x), v)
    }

    /// Sets every attention/fusion parameter to seeded random values (tests, benchmarks): the
    /// same seed gives the same network in every run.
    pub fn randomize(&self, seed: i64, heads_only: bool) {
        use rand::Rng;
        self.draw_sorted(seed as u64, |rng, name, t| {
            let head = network::HEAD_PREFIXES.iter().any(|p| name.starts_with(p));
            if heads_only && !head {
                return None;
            }
            let n = t.numel();
            Some(if name.ends_with("running_var") {
                (0..n).map(|_| rng.random::<f32>() + 0.5).collect()
            } else {
                // Normals: batch-norm scales near 1 (near 0, as the other 1-d values, every
                // residual branch is silenced and the output hardly depends on the input),
                // other 1-d values near 0, weights scaled by their fan-in.
                let (mean, sd) = match (t.dim(), name.ends_with(".weight")) {
                    (1, true) => (1.0, 0.1),
                    (1, false) => (0.0, 0.1),
                    _ => (0.0, (1.0 / fan_in(&t.size()) as f32).sqrt()),
                };
                (0..n).map(|_| mean + sd * rng.sample::<f32, _>(rand_distr::StandardNormal)).collect()
            })
        });
    }

    /// Draws the heads' starting values for training from `seed`, as the layers' own
    /// initialisers draw them (tch's defaults: Kaiming uniform weights, bound sqrt(6 / fan-in);
    /// a linear layer's bias uniform within 1 / sqrt(its inputs); zero-initialised parameters,
    /// the last layers and the convolutions' biases, stay zero). The initialisers draw from
    /// libtorch's global generator, which every thread of the process shares: a model loaded on
    /// another thread between a `manual_seed` and the heads' draws gave the same seed other heads
    /// (CI's run of `train::the_same_seed_…`, docs/ci.md "Stop 68").
    pub fn seed_heads(&self, seed: u64) {
        use rand::Rng;
        let sizes: std::collections::HashMap<String, Vec<i64>> =
            self.vs.variables().into_iter().map(|(n, t)| (n, t.size())).collect();
        self.draw_sorted(seed, |rng, name, t| {
            let head = network::HEAD_PREFIXES.iter().any(|p| name.starts_with(p));
            if !head || t.abs().max().double_value(&[]) == 0.0 {
                return None;
            }
            let size = t.size();
            let bound = if size.len() >= 2 {
                (6.0 / fan_in(&size)).sqrt()
            } else {
                // A drawn 1-d parameter is a linear layer's bias: its weight's inputs.
                let weight = name.strip_suffix("bias").map(|p| format!("{p}weight"));
                match weight.and_then(|w| sizes.get(&w)) {
                    Some(w) if w.len() == 2 => 1.0 / (w[1] as f64).sqrt(),
                    _ => return None,
                }
            };
            Some((0..t.numel()).map(|_| rng.random_range(-bound..bound) as f32).collect())
        });
    }

    /// Sets parameters to values drawn from a generator of their own, seeded with `seed`, in the
    /// order of the parameters' names: libtorch's global generator is shared by every thread of a
    /// process (tests running beside each other draw from it too), and the variable store's map
    /// has no fixed order. `draw` gives a parameter's values, or None to leave it as it is.
    fn draw_sorted(&self, seed: u64, mut draw: impl FnMut(&mut rand::rngs::StdRng, &str, &Tensor) -> Option<Vec<f32>>) {
        use rand::SeedableRng;
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let mut vars: Vec<(String, Tensor)> = self.vs.variables().into_iter().collect();
        vars.sort_by(|a, b| a.0.cmp(&b.0));
        tch::no_grad(|| {
            for (name, mut t) in vars {
                if let Some(values) = draw(&mut rng, &name, &t) {
                    t.copy_(&Tensor::from_slice(&values).reshape(t.size()));
                }
            }
        });
    }

    fn batch(&self, inputs: &[Tensor]) -> Result<Tensor> {
        Ok(channels_last(&stack(inputs, self.device, self.dtype.kind())?))
    }

    /// Unit descriptors, [N, 2048] f32 on the CPU, for same-size preprocessed inputs.
    pub fn descriptors(&self, inputs: &[Tensor], v: Variant) -> Result<Tensor> {
        let x = self.batch(inputs)?;
        let d = tch::no_grad(|| self.net.descriptor(&x, v));
        // Renormalise in f32: half-precision norms are off by ~1e-3.
        let d = network::l2_normalize(&d.to_kind(tch::Kind::Float));
        let d = match &self.whitening {
            Some(w) => tch::no_grad(|| w.apply(&d)),
            None => d,
        };
        Ok(d.to_device(Device::Cpu))
    }

    /// ImageNet probabilities, [N, 1000] f32 on the CPU.
    pub fn class_probabilities(&self, inputs: &[Tensor]) -> Result<Tensor> {
        let x = self.batch(inputs)?;
        Ok(tch::no_grad(|| self.net.class_probabilities(&x)).to_kind(tch::Kind::Float).to_device(Device::Cpu))
    }
}

/// Same-size preprocessed inputs ([3, H, W]) as one batch [N, 3, H, W] on `device` in `kind`.
pub(crate) fn stack(inputs: &[Tensor], device: Device, kind: tch::Kind) -> Result<Tensor> {
    if inputs.is_empty() {
        bail!("empty batch");
    }
    let shape = inputs[0].size();
    if inputs.iter().any(|t| t.size() != shape) {
        bail!("inputs of one batch must share a size");
    }
    Ok(Tensor::stack(inputs, 0).to_device(device).to_kind(kind))
}

/// A weight's inputs per output (its size past the first dimension; 1 for a 1-d parameter): the
/// fan-in both seeded draws scale by.
fn fan_in(size: &[i64]) -> f64 {
    size.iter().skip(1).product::<i64>().max(1) as f64
}

/// Rows of a [N, D] CPU float tensor.
pub fn rows(t: &Tensor) -> Result<Vec<Vec<f32>>> {
    let t = t.to_kind(tch::Kind::Float).contiguous();
    Ok(Vec::<Vec<f32>>::try_from(t)?)
}

/// The same NCHW tensor stored NHWC. Convolutions, depthwise ones above all, and pooling
/// run several times faster in this layout on CPU (oneDNN) and on tensor-core GPUs;
/// libtorch keeps the layout through the network. tch has no memory-format call, hence the permutes.
fn channels_last(x: &Tensor) -> Tensor {
    x.permute([0, 2, 3, 1]).contiguous().permute([0, 3, 1, 2])
}
