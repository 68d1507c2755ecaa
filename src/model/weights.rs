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
    /// SHA-256 (hex) of the file's content: tensors (name, dtype, shape, bytes, in name order)
    /// and metadata (in key order). Part of the descriptor id of what it computes. Not the file's
    /// bytes: safetensors writes metadata in hash-map order, so two imports of the same weights
    /// differ byte-wise but not in content.
    pub sha256: String,
    /// SHA-256 of the file's bytes: how loopd 0.2 named weights in descriptor ids (sessions made
    /// then stay usable by the same weights).
    pub file_sha256: String,
}

impl WeightFile {
    pub fn read(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).with_context(|| format!("reading weights {}", path.display()))?;
        let st = SafeTensors::deserialize(&bytes)
            .with_context(|| format!("{} is not a safetensors file", path.display()))?;
        let (_, meta) = SafeTensors::read_metadata(&bytes)?;
        let mut tensors = Vec::with_capacity(st.len());
        let mut views = st.tensors();
        views.sort_by(|a, b| a.0.cmp(&b.0));
        let mut hash = sha2::Sha256::new();
        for (name, view) in &views {
            hash.update((name.len() as u64).to_le_bytes());
            hash.update(name.as_bytes());
            hash.update(format!("{:?}{:?}", view.dtype(), view.shape()).as_bytes());
            hash.update((view.data().len() as u64).to_le_bytes());
            hash.update(view.data());
        }
        let metadata: BTreeMap<String, String> = meta.metadata().clone().unwrap_or_default().into_iter().collect();
        for (k, v) in &metadata {
            hash.update(format!("{}:{k}={}:{v};", k.len(), v.len()).as_bytes());
        }
        for (name, view) in views {
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
        let sha256 = hex(&hash.finalize());
        let file_sha256 = hex(&sha2::Sha256::digest(&bytes));
        Ok(Self { metadata: metadata.into_iter().collect(), tensors, sha256, file_sha256 })
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

/// Lower-case hex of a digest.
pub(crate) fn hex(d: &[u8]) -> String {
    d.iter().map(|b| format!("{b:02x}")).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The id hash follows content, not bytes: metadata is written in hash-map order, so two
    /// writes of one content may differ byte-wise, yet they name the same weights.
    #[test]
    fn the_hash_names_the_content_not_the_bytes() {
        let dir = tempfile::tempdir().unwrap();
        let t = vec![
            ("a".to_string(), Tensor::from_slice(&[1.0f32, 2.0])),
            ("b".to_string(), Tensor::from_slice(&[3.0f32])),
        ];
        let meta: HashMap<String, String> = (0..8).map(|i| (format!("key{i}"), format!("value{i}"))).collect();
        let mut hashes = HashSet::new();
        for i in 0..4 {
            let p = dir.path().join(format!("{i}.safetensors"));
            // A fresh map each time: its iteration order (hence the header bytes) varies.
            WeightFile::write(&p, &t, meta.clone().into_iter().collect()).unwrap();
            hashes.insert(WeightFile::read(&p).unwrap().sha256);
        }
        assert_eq!(hashes.len(), 1);
        let p = dir.path().join("other.safetensors");
        let changed = vec![
            ("a".to_string(), Tensor::from_slice(&[1.0f32, 2.0])),
            ("b".to_string(), Tensor::from_slice(&[3.5f32])),
        ];
        WeightFile::write(&p, &changed, meta.clone()).unwrap();
        assert!(!hashes.contains(&WeightFile::read(&p).unwrap().sha256), "a changed value keeps the hash");
        let mut meta2 = meta;
        meta2.insert("key0".into(), "other".into());
        WeightFile::write(&p, &t, meta2).unwrap();
        assert!(!hashes.contains(&WeightFile::read(&p).unwrap().sha256), "changed metadata keeps the hash");
    }
}
