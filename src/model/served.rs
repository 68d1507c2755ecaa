//! What a server serves: the built-in network (`Model`) or a TorchScript model (`ScriptModel`),
//! each under a name, behind one face for the engine (inputs, forward pass, descriptor ids).
use super::config::Preprocess;
use super::device::device_name;
use super::network::Variant;
use super::preprocess::{decode, to_input, ImageError, ImageLimits};
use super::script::{Input, ScriptModel};
use super::Model;
use anyhow::{bail, Result};
use image::RgbImage;
use tch::{Device, Tensor};

/// The built-in network's name in a server that serves several models (`--model-name`).
pub const BUILTIN_NAME: &str = "loopd";

/// The network a served model runs.
pub enum Net {
    Builtin(Box<Model>),
    Script(Box<ScriptModel>),
}

/// A model under its name in the server.
pub struct Served {
    pub name: String,
    pub net: Net,
}

impl From<Model> for Served {
    fn from(m: Model) -> Self {
        Self { name: BUILTIN_NAME.into(), net: Net::Builtin(Box::new(m)) }
    }
}

impl From<ScriptModel> for Served {
    fn from(m: ScriptModel) -> Self {
        Self { name: m.manifest.name.clone(), net: Net::Script(Box::new(m)) }
    }
}

/// How an image becomes a model's input.
#[derive(Clone, Debug)]
pub enum InputSpec {
    Builtin(Preprocess),
    Script(Input),
}

impl InputSpec {
    /// The preprocessed input ([3, H, W] f32) of a decoded image.
    pub fn to_input(&self, img: &RgbImage) -> Tensor {
        match self {
            Self::Builtin(p) => to_input(img, p),
            Self::Script(i) => i.to_input(img),
        }
    }

    /// Decodes and preprocesses an encoded image (a decoding worker's job).
    pub fn prepare(&self, bytes: &[u8], limits: &ImageLimits) -> Result<Tensor, ImageError> {
        Ok(self.to_input(&decode(bytes, limits)?))
    }

    /// The input size (width, height) a stretched image takes; a zero input of it warms up.
    pub fn size(&self) -> (u32, u32) {
        match self {
            Self::Builtin(p) => (p.width, p.height),
            Self::Script(i) => (i.width, i.height),
        }
    }
}

/// What a served model is, for `GET /v1/models` and the logs.
#[derive(Clone, Debug)]
pub struct About {
    /// "builtin" or "torchscript".
    pub kind: &'static str,
    pub license: String,
    pub source: String,
}

impl Served {
    pub fn device(&self) -> Device {
        match &self.net {
            Net::Builtin(m) => m.device,
            Net::Script(m) => m.device,
        }
    }

    pub fn device_name(&self) -> String {
        device_name(self.device())
    }

    /// The element type its forward pass runs in.
    pub fn dtype(&self) -> String {
        match &self.net {
            Net::Builtin(m) => format!("{:?}", m.dtype).to_lowercase(),
            Net::Script(_) => "f32".into(),
        }
    }

    pub fn dim(&self) -> usize {
        match &self.net {
            Net::Builtin(m) => m.dim() as usize,
            Net::Script(m) => m.dim(),
        }
    }

    pub fn input(&self) -> InputSpec {
        match &self.net {
            Net::Builtin(m) => InputSpec::Builtin(m.config.preprocess.clone()),
            Net::Script(m) => InputSpec::Script(m.manifest.input.clone()),
        }
    }

    /// The variants it computes: the built-in network's ablations, a TorchScript model's whole
    /// output only.
    pub fn variants(&self) -> Vec<Variant> {
        match &self.net {
            Net::Builtin(_) => Variant::ALL.to_vec(),
            Net::Script(_) => vec![Variant::FULL],
        }
    }

    /// The descriptor space of `variant` (one of [`Served::variants`]).
    pub fn descriptor_id(&self, variant: Variant) -> String {
        match &self.net {
            Net::Builtin(m) => m.descriptor_id(variant),
            Net::Script(m) => m.descriptor_id(),
        }
    }

    /// Ids earlier releases gave the same descriptor space (sessions created then stay usable).
    pub fn earlier_descriptor_ids(&self) -> Vec<String> {
        match &self.net {
            Net::Builtin(m) => m.earlier_descriptor_ids(),
            Net::Script(_) => Vec::new(),
        }
    }

    pub fn about(&self) -> About {
        match &self.net {
            Net::Builtin(m) => About {
                kind: "builtin",
                license: "loopd's network (docs/model.md); weights as shipped".into(),
                source: format!(
                    "ResNet50 with attention and fusion (Hu et al.), weights {}{}",
                    &m.weights_sha256[..m.weights_sha256.len().min(12)],
                    m.heads_sha256.as_deref().map_or(String::new(), |h| format!(", heads {}", &h[..h.len().min(12)]))
                ),
            },
            Net::Script(m) => {
                About { kind: "torchscript", license: m.manifest.license.clone(), source: m.manifest.source.clone() }
            }
        }
    }

    /// Unit descriptors, [N, dim] f32 on the CPU, of same-size preprocessed inputs.
    pub fn descriptors(&self, inputs: &[Tensor], variant: Variant) -> Result<Tensor> {
        match &self.net {
            Net::Builtin(m) => m.descriptors(inputs, variant),
            Net::Script(m) if variant == Variant::FULL => m.descriptors(inputs),
            Net::Script(_) => {
                bail!("model {} computes its whole output only (no {} variant)", self.name, variant.name())
            }
        }
    }
}

/// The TorchScript models of a model repository (`serve --models DIR`): each subfolder of `dir`
/// one model (its `model.json` and TorchScript file), loaded onto `device`, by folder name order.
pub fn load_dir(dir: &std::path::Path, device: Device) -> Result<Vec<Served>> {
    use anyhow::Context;
    let mut folders: Vec<std::path::PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading the model folder {}", dir.display()))?
        .map(|e| e.map(|e| e.path()))
        .collect::<std::io::Result<_>>()
        .with_context(|| format!("reading the model folder {}", dir.display()))?;
    folders.retain(|p| p.is_dir());
    folders.sort();
    folders
        .iter()
        .map(|f| ScriptModel::load(f, device).map(Served::from).with_context(|| format!("model {}", f.display())))
        .collect()
}
