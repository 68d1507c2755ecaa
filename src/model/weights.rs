//! Our weight format: safetensors with torchvision-style names and a few metadata keys.
use super::network::HEAD_PREFIXES;
use anyhow::{bail, Context, Result};
use safetensors::{tensor::TensorView, Dtype, SafeTensors};
use sha2::Digest;
use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::Path;
use tch::{nn::VarStore, Kind, Tensor};

/// Metadata keys written by `loopd weights import` and read back at load.
pub const META_FORMAT: &str = "format";
pub const META_STRIDE_LAYOUT: &str = "stride_layout";
pub const META_NORMALIZATION: &str = "normalization";
pub const FORMAT_NAME: &str = "loopd-weights/1";

pub struct WeightFile {
    pub metadata: HashMap<String, String>,
    pub tensors: Vec<(String, Tensor)>,
    /// SHA-256 of the file's bytes (hex): part of the descriptor id of what it computes.
    pub sha256: String,
}

impl WeightFile {
    pub fn read(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).with_context(|| format!("reading weights {}", path.display()))?;
        let st = SafeTensors::deserialize(&bytes)
            .with_context(|| format!("{} is not a safetensors file", path.display()))?;
        let (_, meta) = SafeTensors::read_metadata(&bytes)?;
        let mut tensors = Vec::with_capacity(st.len());
        for (name, view) in st.tensors() {
            let kind = match view.dtype() {
                Dtype::F32 => Kind::Float,
                Dtype::F16 => Kind::Half,
                Dtype::BF16 => Kind::BFloat16,
                d => bail!("tensor {name}: unsupported dtype {d:?}"),
            };
            let shape: Vec<i64> = view.shape().iter().map(|&d| d as i64).collect();
            let t = Tensor::from_data_size(view.data(), &shape, kind).to_kind(Kind::Float);
            tensors.push((name, t));
        }
        let sha256 = sha2::Sha256::digest(&bytes).iter().map(|b| format!("{b:02x}")).collect();
        Ok(Self { metadata: meta.metadata().clone().unwrap_or_default(), tensors, sha256 })
    }

    /// Writes f32 tensors (sorted by name) and the metadata.
    pub fn write(path: &Path, tensors: &[(String, Tensor)], metadata: HashMap<String, String>) -> Result<()> {
        let mut owned: BTreeMap<&str, (Vec<usize>, Vec<u8>)> = BTreeMap::new();
        for (name, t) in tensors {
            let t = t.to_kind(Kind::Float).to_device(tch::Device::Cpu).contiguous();
            let shape: Vec<usize> = t.size().iter().map(|&d| d as usize).collect();
            let values = Vec::<f32>::try_from(t.flatten(0, -1))?;
            let bytes = values.iter().flat_map(|v| v.to_le_bytes()).collect();
            if owned.insert(name, (shape, bytes)).is_some() {
                bail!("duplicate tensor name {name}");
            }
        }
        let views = owned
            .iter()
            .map(|(name, (shape, bytes))| Ok((*name, TensorView::new(Dtype::F32, shape.clone(), bytes)?)))
            .collect::<Result<Vec<_>>>()?;
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir)?;
        }
        let tmp = path.with_extension("safetensors.partial");
        safetensors::serialize_to_file(views, Some(metadata), &tmp)?;
        std::fs::rename(&tmp, path)?; // never leave a half-written weight file under the real name
        Ok(())
    }
}

/// What a load filled in.
#[derive(Debug)]
pub struct LoadReport {
    pub backbone_tensors: usize,
    /// Attention/fusion came from the file (trained) rather than their identity start.
    pub heads_from_file: bool,
}

fn is_head(name: &str) -> bool {
    HEAD_PREFIXES.iter().any(|p| name.starts_with(p))
}

/// Copies every file tensor into the var store. Unknown names, wrong shapes or any
/// missing backbone tensor are errors; the heads may be absent only all together.
pub fn load_into(vs: &VarStore, file: &WeightFile) -> Result<LoadReport> {
    let mut vars = vs.variables();
    let mut seen = HashSet::new();
    tch::no_grad(|| -> Result<()> {
        for (name, t) in &file.tensors {
            let Some(var) = vars.get_mut(name) else { bail!("weight file has unknown tensor {name}") };
            if var.size() != t.size() {
                bail!("tensor {name}: file has shape {:?}, model expects {:?}", t.size(), var.size());
            }
            var.copy_(t);
            seen.insert(name.as_str());
        }
        Ok(())
    })?;
    let missing: Vec<&String> = vars.keys().filter(|k| !seen.contains(k.as_str())).collect();
    let missing_backbone: Vec<&&String> = missing.iter().filter(|k| !is_head(k)).collect();
    if !missing_backbone.is_empty() {
        bail!("weight file lacks {} backbone tensors, e.g. {}", missing_backbone.len(), missing_backbone[0]);
    }
    let heads_total = vars.keys().filter(|k| is_head(k)).count();
    let heads_missing = missing.len();
    if heads_missing != 0 && heads_missing != heads_total {
        bail!(
            "weight file has {} of {heads_total} attention/fusion tensors; expected all or none",
            heads_total - heads_missing
        );
    }
    Ok(LoadReport { backbone_tensors: seen.len() - (heads_total - heads_missing), heads_from_file: heads_missing == 0 })
}

/// All parameters of a var store under their names (for writing a full weight file).
pub fn named_tensors(vs: &VarStore) -> Vec<(String, Tensor)> {
    let mut v: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}
