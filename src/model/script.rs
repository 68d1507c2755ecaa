//! Models brought by their users: a TorchScript file (`torch.jit.save`) and a manifest
//! (`model.json`) saying how images go in and what comes out (docs/models.md). Loaded with
//! libtorch's `CModule`; the rest of loopd sees unit descriptors and a descriptor id, as it
//! does of the built-in network.
use super::config::{Preprocess, ResizeMode};
use super::preprocess::resized_rgb;
use super::weights::hex;
use anyhow::{bail, Context, Result};
use image::RgbImage;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};
use tch::{Device, Kind, Tensor};

/// The manifest's file name in a model folder.
pub const MANIFEST: &str = "model.json";

/// The `kind` of a TorchScript model folder's manifest (the default).
pub const SCRIPT_KIND: &str = "torchscript";

/// Largest input side a manifest may ask for (pixels).
const MAX_SIDE: u32 = 4096;
/// Largest descriptor a model may output.
const MAX_DIM: usize = 65_536;

/// Channel order the model expects.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Channels {
    Rgb,
    Bgr,
}

/// How an image becomes the model's input: resized to `width` x `height` (or to fit inside it,
/// `keep`), in `channels` order, each value `(pixel * scale - mean[c]) / std[c]` (pixel 0-255).
/// The defaults are torchvision's ImageNet ones.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Input {
    pub width: u32,
    pub height: u32,
    #[serde(default = "stretch")]
    pub resize: ResizeMode,
    #[serde(default = "rgb")]
    pub channels: Channels,
    #[serde(default = "div255")]
    pub scale: f32,
    #[serde(default = "imagenet_mean")]
    pub mean: [f32; 3],
    #[serde(default = "imagenet_std")]
    pub std: [f32; 3],
}

fn stretch() -> ResizeMode {
    ResizeMode::Stretch
}
fn rgb() -> Channels {
    Channels::Rgb
}
fn div255() -> f32 {
    1.0 / 255.0
}
fn imagenet_mean() -> [f32; 3] {
    [0.485, 0.456, 0.406]
}
fn imagenet_std() -> [f32; 3] {
    [0.229, 0.224, 0.225]
}

/// `model.json`: what loopd needs to run a TorchScript model, and what a user needs to know of it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    /// The model's name in the server (sessions name it): letters, digits, `-`, `_`, `.`.
    pub name: String,
    /// "torchscript" when given (the default kind of a model folder; `served::Folder`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub kind: Option<String>,
    /// The TorchScript file, relative to the folder.
    #[serde(default = "model_pt")]
    pub file: String,
    pub input: Input,
    /// Values per descriptor the model outputs ([N, output_dim]).
    pub output_dim: usize,
    /// Whether the model's output is already L2-normalised (loopd normalises either way; a
    /// normalised model whose output is not unit is refused by `loopd models check`).
    #[serde(default)]
    pub normalized: bool,
    /// Its license, as text (shown by `GET /v1/models` and `loopd models check`).
    #[serde(default)]
    pub license: String,
    /// Where it comes from (paper, repository, training data), as text.
    #[serde(default)]
    pub source: String,
}

fn model_pt() -> String {
    "model.pt".into()
}

impl Manifest {
    /// Reads and checks `dir/model.json`.
    pub fn read(dir: &Path) -> Result<Self> {
        let path = dir.join(MANIFEST);
        let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
        let m: Manifest =
            serde_json::from_str(&text).with_context(|| format!("{}: not a model manifest", path.display()))?;
        m.check().with_context(|| format!("{}", path.display()))?;
        Ok(m)
    }

    fn check(&self) -> Result<()> {
        check_name(&self.name)?;
        if let Some(k) = self.kind.as_deref().filter(|k| *k != SCRIPT_KIND) {
            bail!("kind {k:?}: a TorchScript model's manifest says \"{SCRIPT_KIND}\" or nothing");
        }
        let i = &self.input;
        if !(32..=MAX_SIDE).contains(&i.width) || !(32..=MAX_SIDE).contains(&i.height) {
            bail!("input {}x{}: each side must be 32 to {MAX_SIDE} pixels", i.width, i.height);
        }
        if !i.scale.is_finite() || i.scale <= 0.0 {
            bail!("input scale {}: must be a positive number", i.scale);
        }
        if i.mean.iter().any(|m| !m.is_finite()) || i.std.iter().any(|s| !s.is_finite() || *s <= 0.0) {
            bail!("input mean {:?} / std {:?}: finite, std positive", i.mean, i.std);
        }
        if !(1..=MAX_DIM).contains(&self.output_dim) {
            bail!("output_dim {}: must be 1 to {MAX_DIM}", self.output_dim);
        }
        if self.file.is_empty() || Path::new(&self.file).components().count() != 1 {
            bail!("file {:?}: a file name inside the model folder", self.file);
        }
        Ok(())
    }
}

/// A model's name in a server: 1 to 64 letters, digits, `-`, `_` or `.`.
pub fn check_name(name: &str) -> Result<()> {
    let ok =
        !name.is_empty() && name.len() <= 64 && name.chars().all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c));
    if !ok {
        bail!("model name {name:?}: 1 to 64 letters, digits, '-', '_' or '.'");
    }
    Ok(())
}

impl Input {
    /// The built-in model's resizing of the same size (its normalisation is not used).
    fn preprocess(&self) -> Preprocess {
        Preprocess { width: self.width, height: self.height, resize: self.resize, ..Default::default() }
    }

    /// The model's input for an image ([3, H, W] f32): resized as the built-in model resizes,
    /// then in this channel order, scale, mean and std.
    pub fn to_input(&self, img: &RgbImage) -> Tensor {
        self.normalize(&self.resized(img))
    }

    /// The image resized for the model, RGB 0-255 ([3, H, W] f32), before normalisation.
    pub fn resized(&self, img: &RgbImage) -> Tensor {
        resized_rgb(img, &self.preprocess())
    }

    /// This normalisation of a resized RGB 0-255 [3, H, W] tensor.
    pub fn normalize(&self, rgb: &Tensor) -> Tensor {
        let x = if self.channels == Channels::Bgr { rgb.flip([0]) } else { rgb.shallow_clone() };
        let column = |v: [f32; 3]| Tensor::from_slice(&v).reshape([3, 1, 1]);
        (x * f64::from(self.scale) - column(self.mean)) / column(self.std)
    }
}

/// A TorchScript descriptor model on its device. Not `Sync` (tch); one thread runs it.
pub struct ScriptModel {
    pub manifest: Manifest,
    pub dir: PathBuf,
    /// SHA-256 (hex) of the TorchScript file.
    pub sha256: String,
    pub device: Device,
    module: tch::CModule,
}

impl ScriptModel {
    /// Loads the model in `dir` (manifest and TorchScript file) onto `device`.
    pub fn load(dir: &Path, device: Device) -> Result<Self> {
        let manifest = Manifest::read(dir)?;
        let file = dir.join(&manifest.file);
        let bytes = std::fs::read(&file).with_context(|| format!("reading {}", file.display()))?;
        let sha256 = hex(&Sha256::digest(&bytes));
        let mut module = tch::CModule::load_on_device(&file, device)
            .with_context(|| format!("{}: not a TorchScript file libtorch can load", file.display()))?;
        module.set_eval();
        Ok(Self { manifest, dir: dir.to_path_buf(), sha256, device, module })
    }

    /// The descriptor space this model computes: its name, the file's hash and the manifest's
    /// input (a different resize or normalisation is a different space).
    pub fn descriptor_id(&self) -> String {
        let input = serde_json::to_string(&self.manifest.input).unwrap_or_default();
        let h = hex(&Sha256::digest(format!("{}|{input}|{}", self.sha256, self.manifest.output_dim)));
        format!("script-{}-{}", self.manifest.name, &h[..12])
    }

    pub fn dim(&self) -> usize {
        self.manifest.output_dim
    }

    /// The model's input for an image ([3, H, W] f32): see [`Input::to_input`].
    pub fn to_input(&self, img: &RgbImage) -> Tensor {
        self.manifest.input.to_input(img)
    }

    /// The image resized for the model, RGB 0-255 ([3, H, W] f32), before normalisation.
    pub fn resized(&self, img: &RgbImage) -> Tensor {
        self.manifest.input.resized(img)
    }

    /// The manifest's normalisation of a resized RGB 0-255 [3, H, W] tensor.
    pub fn normalize(&self, rgb: &Tensor) -> Tensor {
        self.manifest.input.normalize(rgb)
    }

    /// Raw model output for a batch of same-size inputs, [N, output_dim] f32 on the CPU, checked
    /// against the manifest (shape, finite values).
    pub fn forward(&self, inputs: &[Tensor]) -> Result<Tensor> {
        let x = super::stack(inputs, self.device, Kind::Float)?;
        let out = tch::no_grad(|| self.module.forward_ts(&[x]))
            .with_context(|| format!("model {}: forward pass failed", self.manifest.name))?;
        let out = out.to_kind(Kind::Float).to_device(Device::Cpu);
        let want = [inputs.len() as i64, self.manifest.output_dim as i64];
        if out.size() != want {
            bail!(
                "model {} returned a tensor of shape {:?}; its manifest says [N, {}] (output_dim)",
                self.manifest.name,
                out.size(),
                self.manifest.output_dim
            );
        }
        if !bool::try_from(out.isfinite().all())? {
            bail!("model {} returned values that are not finite (NaN or infinite)", self.manifest.name);
        }
        Ok(out)
    }

    /// Unit descriptors ([N, output_dim] f32 on the CPU).
    pub fn descriptors(&self, inputs: &[Tensor]) -> Result<Tensor> {
        self.unit(&self.forward(inputs)?)
    }

    /// [`ScriptModel::forward`]'s output as unit descriptors (each row L2-normalised).
    pub fn unit(&self, out: &Tensor) -> Result<Tensor> {
        let norm = out.norm_scalaropt_dim(2.0, [1i64].as_slice(), true);
        if !bool::try_from(norm.gt(1e-12).all())? {
            bail!("model {} returned an all-zero descriptor", self.manifest.name);
        }
        Ok(out / norm)
    }
}
