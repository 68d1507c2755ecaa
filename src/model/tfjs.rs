//! Reads a Keras ResNet50 saved as a TF.js layers model (model.json + float32 shards)
//! and renames it to torchvision-style tensors, folding conv biases and Keras' BN epsilon
//! into the batch-norm statistics so the result is a plain bias-free ResNet.
use super::backbone::BN_EPS;
use super::config::{Normalization, StrideLayout};
use super::weights::{FORMAT_NAME, META_FORMAT, META_NORMALIZATION, META_STRIDE_LAYOUT};
use anyhow::{bail, Context, Result};
use serde::Deserialize;
use serde_json::Value;
use std::collections::{HashMap, HashSet};
use std::path::Path;
use tch::Tensor;

#[derive(Deserialize)]
struct ModelJson {
    #[serde(rename = "modelTopology")]
    topology: Value,
    #[serde(rename = "weightsManifest")]
    manifest: Vec<Group>,
    #[serde(rename = "generatedBy", default)]
    generated_by: String,
}

#[derive(Deserialize)]
struct Group {
    paths: Vec<String>,
    weights: Vec<Entry>,
}

#[derive(Deserialize)]
struct Entry {
    name: String,
    shape: Vec<usize>,
    dtype: String,
    #[serde(default)]
    quantization: Option<Value>,
}

pub struct Imported {
    /// torchvision-style name -> tensor.
    pub tensors: Vec<(String, Tensor)>,
    pub metadata: HashMap<String, String>,
    /// Keras weight arrays read from the shards (every one of them is consumed).
    pub keras_arrays: usize,
    pub shard_bytes: usize,
}

/// Keras weight arrays by name, each consumed at most once.
struct Arrays {
    arrays: HashMap<String, (Vec<usize>, Vec<f32>)>,
    used: HashSet<String>,
}

impl Arrays {
    fn take(&mut self, name: &str) -> Result<Tensor> {
        let (shape, data) = self.arrays.get(name).with_context(|| format!("model.json has no weight {name}"))?;
        if !self.used.insert(name.to_string()) {
            bail!("weight {name} used twice");
        }
        let shape: Vec<i64> = shape.iter().map(|&d| d as i64).collect();
        Ok(Tensor::from_slice(data).reshape(&shape))
    }

    fn has(&self, name: &str) -> bool {
        self.arrays.contains_key(name)
    }
}

fn read_arrays(dir: &Path, model: &ModelJson) -> Result<(Arrays, usize)> {
    let mut arrays = HashMap::new();
    let mut total = 0;
    for group in &model.manifest {
        let mut bytes = Vec::new();
        for p in &group.paths {
            let path = dir.join(p);
            bytes.extend(std::fs::read(&path).with_context(|| format!("reading shard {}", path.display()))?);
        }
        let mut offset = 0usize;
        for e in &group.weights {
            if e.dtype != "float32" || e.quantization.is_some() {
                bail!("weight {}: only unquantised float32 is supported (got {})", e.name, e.dtype);
            }
            let n: usize = e.shape.iter().product();
            let end = offset + 4 * n;
            let chunk = bytes.get(offset..end).with_context(|| format!("shards end before weight {}", e.name))?;
            let data = chunk.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
            arrays.insert(e.name.clone(), (e.shape.clone(), data));
            offset = end;
        }
        if offset != bytes.len() {
            bail!("shards hold {} bytes but the manifest describes {offset}", bytes.len());
        }
        total += bytes.len();
    }
    Ok((Arrays { arrays, used: HashSet::new() }, total))
}

/// Layer name -> Keras layer config.
fn layer_configs(topology: &Value) -> HashMap<String, Value> {
    let layers = topology.pointer("/model_config/config/layers").and_then(Value::as_array);
    layers
        .into_iter()
        .flatten()
        .filter_map(|l| Some((l.get("name")?.as_str()?.to_string(), l.get("config")?.clone())))
        .collect()
}

fn strides(cfg: &HashMap<String, Value>, layer: &str) -> Option<Vec<i64>> {
    cfg.get(layer)?.get("strides")?.as_array()?.iter().map(Value::as_i64).collect()
}

/// One Keras conv + batch norm pair, written as a bias-free conv and a BN with eps = BN_EPS.
fn conv_bn(
    a: &mut Arrays,
    cfg: &HashMap<String, Value>,
    keras: (&str, &str),
    torch: (&str, &str),
    out: &mut Vec<(String, Tensor)>,
) -> Result<()> {
    let (conv, bn) = keras;
    // Keras kernels are [kh, kw, in, out]; torch wants [out, in, kh, kw].
    out.push((format!("{}.weight", torch.0), a.take(&format!("{conv}/kernel"))?.permute([3, 2, 0, 1]).contiguous()));
    let mean = a.take(&format!("{bn}/moving_mean"))?;
    let var = a.take(&format!("{bn}/moving_variance"))?;
    let c = mean.size()[0];
    // bn(conv(x) + b) == bn'(conv(x)) with mean' = mean - b.
    let mean = if a.has(&format!("{conv}/bias")) { mean - a.take(&format!("{conv}/bias"))? } else { mean };
    let eps = cfg.get(bn).and_then(|c| c.get("epsilon")).and_then(Value::as_f64).unwrap_or(1e-3);
    // (var + eps) stays the same denominator when the runtime eps is BN_EPS.
    let var = var + (eps - BN_EPS);
    let gamma = if a.has(&format!("{bn}/gamma")) {
        a.take(&format!("{bn}/gamma"))?
    } else {
        Tensor::ones([c], tch::kind::FLOAT_CPU)
    };
    let beta = if a.has(&format!("{bn}/beta")) {
        a.take(&format!("{bn}/beta"))?
    } else {
        Tensor::zeros([c], tch::kind::FLOAT_CPU)
    };
    out.push((format!("{}.weight", torch.1), gamma));
    out.push((format!("{}.bias", torch.1), beta));
    out.push((format!("{}.running_mean", torch.1), mean));
    out.push((format!("{}.running_var", torch.1), var));
    Ok(())
}

pub fn import(dir: &Path) -> Result<Imported> {
    let json_path = dir.join("model.json");
    let text = std::fs::read_to_string(&json_path).with_context(|| format!("reading {}", json_path.display()))?;
    let model: ModelJson = serde_json::from_str(&text).with_context(|| format!("parsing {}", json_path.display()))?;
    let (mut a, shard_bytes) = read_arrays(dir, &model)?;
    let cfg = layer_configs(&model.topology);

    let layout = match (strides(&cfg, "res3a_branch2a").as_deref(), strides(&cfg, "res3a_branch2b").as_deref()) {
        (Some([2, 2]), _) => StrideLayout::V1,
        (_, Some([2, 2])) => StrideLayout::V15,
        _ => bail!("cannot tell the stride layout from res3a_branch2a/2b in model.json"),
    };

    let mut out = Vec::new();
    conv_bn(&mut a, &cfg, ("conv1", "bn_conv1"), ("conv1", "bn1"), &mut out)?;
    for (s, blocks) in [3usize, 4, 6, 3].iter().enumerate() {
        let stage = s + 2; // Keras numbers stages 2..5
        for b in 0..*blocks {
            let letter = (b'a' + b as u8) as char;
            for (i, branch) in ["2a", "2b", "2c"].iter().enumerate() {
                let keras = (format!("res{stage}{letter}_branch{branch}"), format!("bn{stage}{letter}_branch{branch}"));
                let torch = (format!("layer{}.{b}.conv{}", s + 1, i + 1), format!("layer{}.{b}.bn{}", s + 1, i + 1));
                conv_bn(&mut a, &cfg, (&keras.0, &keras.1), (&torch.0, &torch.1), &mut out)?;
            }
            if b == 0 {
                let keras = (format!("res{stage}a_branch1"), format!("bn{stage}a_branch1"));
                let torch = (format!("layer{}.0.downsample.0", s + 1), format!("layer{}.0.downsample.1", s + 1));
                conv_bn(&mut a, &cfg, (&keras.0, &keras.1), (&torch.0, &torch.1), &mut out)?;
            }
        }
    }
    out.push(("fc.weight".into(), a.take("fc1000/kernel")?.transpose(0, 1).contiguous()));
    out.push(("fc.bias".into(), a.take("fc1000/bias")?));

    let unused: Vec<&String> = a.arrays.keys().filter(|k| !a.used.contains(*k)).collect();
    if !unused.is_empty() {
        bail!("{} weights in model.json were not mapped, e.g. {}", unused.len(), unused[0]);
    }

    let mut metadata = HashMap::new();
    metadata.insert(META_FORMAT.to_string(), FORMAT_NAME.to_string());
    metadata.insert(META_STRIDE_LAYOUT.to_string(), serde_json::to_value(layout)?.as_str().unwrap_or("v1").to_string());
    let norm =
        if model.generated_by.to_lowercase().contains("keras") { Normalization::Caffe } else { Normalization::Torch };
    metadata
        .insert(META_NORMALIZATION.to_string(), serde_json::to_value(norm)?.as_str().unwrap_or("caffe").to_string());
    metadata.insert("source".to_string(), format!("TF.js layers model ({})", model.generated_by));
    Ok(Imported { tensors: out, metadata, keras_arrays: a.used.len(), shard_bytes })
}
