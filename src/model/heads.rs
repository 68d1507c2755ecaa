//! Trained heads: a small safetensors file with the attention/fusion tensors (and, when trained,
//! layer4 or a whitening) loaded on top of a backbone weight file by `--heads FILE`.
use super::weights::WeightFile;
use anyhow::{bail, Result};
use std::collections::{HashMap, HashSet};
use std::path::Path;
use tch::{nn::VarStore, Device, Kind, Tensor};

pub const HEADS_FORMAT: &str = "loopd-heads/1";
/// Metadata keys of a heads file.
pub const META_BACKBONE_SHA256: &str = "backbone_sha256";
pub const META_POOLING: &str = "pooling";
/// Names of the whitening tensors: mean [D] and projection [d, D].
pub const WHITEN_MEAN: &str = "whiten.mean";
pub const WHITEN_PROJ: &str = "whiten.proj";

/// PCA whitening of the unit pooled descriptor: centre, project (rows scaled by the inverse
/// square root of their eigenvalue, possibly fewer than D), renormalise.
pub struct Whitening {
    pub mean: Tensor,
    pub proj: Tensor,
}

impl Whitening {
    pub fn dim(&self) -> i64 {
        self.proj.size()[0]
    }

    /// `x`: [N, D] unit rows (f32, on the whitening's device) -> [N, d] unit rows.
    pub fn apply(&self, x: &Tensor) -> Tensor {
        super::network::l2_normalize(&(x - &self.mean).matmul(&self.proj.tr()))
    }

    pub fn to_device(&self, device: Device) -> Self {
        Self { mean: self.mean.to_device(device), proj: self.proj.to_device(device) }
    }
}

/// What a heads file put into a model.
pub struct LoadedHeads {
    pub sha256: String,
    pub metadata: HashMap<String, String>,
    pub tensors: usize,
    pub whitening: Option<Whitening>,
}

/// Checks a heads file against the model's var store and backbone, then copies its tensors in.
/// Nothing is copied unless every tensor fits: a wrong file leaves the model as it was.
pub fn load_into(vs: &VarStore, path: &Path, backbone_sha256: &str) -> Result<LoadedHeads> {
    let file = WeightFile::read(path)?;
    let meta = |k: &str| file.metadata.get(k).map(String::as_str);
    if meta(super::weights::META_FORMAT) != Some(HEADS_FORMAT) {
        bail!(
            "{} is not a loopd heads file (format {:?}, expected {HEADS_FORMAT}); full weight files go to --weights",
            path.display(),
            meta(super::weights::META_FORMAT).unwrap_or("missing")
        );
    }
    match meta(META_BACKBONE_SHA256) {
        Some(h) if h == backbone_sha256 => {}
        other => bail!(
            "{} was trained on backbone {} but the loaded weights are {backbone_sha256}",
            path.display(),
            other.unwrap_or("(not stated)")
        ),
    }
    let vars = vs.variables();
    let mut names = HashSet::new();
    let (mut mean, mut proj) = (None, None);
    let mut copies = Vec::new();
    for (name, t) in &file.tensors {
        names.insert(name.as_str());
        match name.as_str() {
            WHITEN_MEAN => mean = Some(t.to_kind(Kind::Float)),
            WHITEN_PROJ => proj = Some(t.to_kind(Kind::Float)),
            _ => match vars.get(name) {
                Some(v) if v.size() == t.size() => copies.push((v.shallow_clone(), t)),
                Some(v) => {
                    bail!(
                        "{}: tensor {name} has shape {:?}, the model expects {:?}",
                        path.display(),
                        t.size(),
                        v.size()
                    )
                }
                None => bail!("{}: tensor {name} is not a parameter of this network", path.display()),
            },
        }
    }
    let whitening = match (mean, proj) {
        (None, None) => None,
        (Some(mean), Some(proj)) => {
            let dims = (mean.size(), proj.size());
            if dims.0.len() != 1 || dims.1.len() != 2 || dims.1[1] != dims.0[0] || dims.1[0] < 1 {
                bail!("{}: whitening shapes {:?} and {:?} do not fit ([D] and [d, D])", path.display(), dims.0, dims.1);
            }
            Some(Whitening { mean, proj })
        }
        _ => bail!("{}: whitening needs both {WHITEN_MEAN} and {WHITEN_PROJ}", path.display()),
    };
    // Attention and fusion come all together or not at all (a whitening-only file has none).
    let is_head = |k: &&String| super::network::HEAD_PREFIXES.iter().any(|p| k.starts_with(p));
    let heads: Vec<&String> = vars.keys().filter(is_head).collect();
    let present = heads.iter().filter(|k| names.contains(k.as_str())).count();
    if present != 0 && present != heads.len() {
        bail!(
            "{}: has {present} of the {} attention/fusion tensors; expected all or none",
            path.display(),
            heads.len()
        );
    }
    let tensors = copies.len();
    tch::no_grad(|| {
        for (mut var, t) in copies {
            var.copy_(&t.to_kind(var.kind()).to_device(var.device()));
        }
    });
    Ok(LoadedHeads { sha256: file.sha256, metadata: file.metadata, tensors, whitening })
}

/// Writes a heads file: the named tensors, the whitening if any, and metadata.
pub fn write(
    path: &Path,
    tensors: Vec<(String, Tensor)>,
    whitening: Option<&Whitening>,
    backbone_sha256: &str,
    mut metadata: HashMap<String, String>,
) -> Result<()> {
    let mut all = tensors;
    if let Some(w) = whitening {
        all.push((WHITEN_MEAN.into(), w.mean.shallow_clone()));
        all.push((WHITEN_PROJ.into(), w.proj.shallow_clone()));
    }
    metadata.insert(super::weights::META_FORMAT.into(), HEADS_FORMAT.into());
    metadata.insert(META_BACKBONE_SHA256.into(), backbone_sha256.into());
    WeightFile::write(path, &all, metadata)
}
