//! What a server serves: the built-in network (`Model`) or a TorchScript model (`ScriptModel`),
//! each under a name, behind one face for the engine (inputs, forward pass, descriptor ids).
use super::config::Preprocess;
use super::device::device_name;
use super::network::Variant;
use super::preprocess::{decode, to_input, ImageError, ImageLimits};
use super::script::{check_name, Input, ScriptModel, MANIFEST};
use super::Model;
use anyhow::{bail, Context, Result};
use image::RgbImage;
use serde::{Deserialize, Serialize};
use std::path::Path;
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
    /// The license and source a `builtin` model folder states (None: the built-in network's own).
    pub notes: Option<(String, String)>,
}

impl Served {
    /// The built-in network under `name`.
    pub fn builtin(name: &str, m: Model) -> Self {
        Self { name: name.into(), net: Net::Builtin(Box::new(m)), notes: None }
    }
}

impl From<Model> for Served {
    fn from(m: Model) -> Self {
        Self::builtin(BUILTIN_NAME, m)
    }
}

impl From<ScriptModel> for Served {
    fn from(m: ScriptModel) -> Self {
        Self { name: m.manifest.name.clone(), net: Net::Script(Box::new(m)), notes: None }
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
            Net::Builtin(_) if self.notes.is_some() => {
                let (license, source) = self.notes.clone().unwrap_or_default();
                About { kind: "builtin", license, source }
            }
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

/// `model.json` of a folder that serves the built-in network (`"kind": "builtin"`): the
/// server's weights, input size, pooling, device and precision, with the folder's heads file
/// (`loopd train`'s output, which writes this manifest) or none (the plain backbone, which sessions
/// made with `--heads none` or before heads were shipped hold). A folder without `kind` (or with
/// `"kind": "torchscript"`) is a TorchScript model ([`super::script::Manifest`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BuiltinManifest {
    /// The model's name in the server.
    pub name: String,
    /// Always "builtin".
    pub kind: String,
    /// The heads file, a name inside the folder; absent: the plain backbone.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub heads: Option<String>,
    #[serde(default)]
    pub license: String,
    #[serde(default)]
    pub source: String,
}

/// The kind a `builtin` manifest states.
pub const BUILTIN_KIND: &str = "builtin";

impl BuiltinManifest {
    fn check(&self) -> Result<()> {
        check_name(&self.name)?;
        if let Some(h) = &self.heads {
            if h.is_empty() || Path::new(h).components().count() != 1 {
                bail!("heads {h:?}: a file name inside the model folder");
            }
        }
        Ok(())
    }

    /// Writes `dir/model.json`.
    pub fn write(&self, dir: &Path) -> Result<()> {
        self.check()?;
        let path = dir.join(MANIFEST);
        std::fs::write(&path, serde_json::to_string_pretty(self)? + "\n")
            .with_context(|| format!("writing {}", path.display()))
    }
}

/// What a model folder holds, by its manifest's `kind`.
pub enum Folder {
    Script,
    Builtin(BuiltinManifest),
}

impl Folder {
    /// Reads `dir/model.json`'s kind (a `builtin` manifest whole and checked).
    pub fn read(dir: &Path) -> Result<Self> {
        let path = dir.join(MANIFEST);
        let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
        let v: serde_json::Value =
            serde_json::from_str(&text).with_context(|| format!("{}: not a model manifest", path.display()))?;
        match v.get("kind").map(|k| k.as_str()) {
            None | Some(Some(super::script::SCRIPT_KIND)) => Ok(Self::Script),
            Some(Some(BUILTIN_KIND)) => {
                let m: BuiltinManifest =
                    serde_json::from_value(v).with_context(|| format!("{}: not a model manifest", path.display()))?;
                m.check().with_context(|| format!("{}", path.display()))?;
                Ok(Self::Builtin(m))
            }
            Some(_) => bail!(
                "{}: kind {}: \"{}\" (a TorchScript file, the default) or \"{BUILTIN_KIND}\" (the built-in network, \
                 with the folder's heads or none)",
                path.display(),
                v["kind"],
                super::script::SCRIPT_KIND
            ),
        }
    }
}

/// The model in folder `dir`: a TorchScript model onto `device`, or the built-in network on
/// `base`'s weights and configuration with the folder's heads (a `builtin` manifest; `base`: the
/// server's default network, or what a command's model flags load).
pub fn load_folder(dir: &Path, device: Device, base: Option<&Model>) -> Result<Served> {
    match Folder::read(dir)? {
        Folder::Script => Ok(ScriptModel::load(dir, device)?.into()),
        Folder::Builtin(m) => {
            let Some(base) = base else {
                bail!(
                    "{}: a builtin model folder runs on the built-in network's weights, and none are loaded here",
                    dir.display()
                )
            };
            let heads = m.heads.as_ref().map(|h| dir.join(h));
            let model = base.sibling(heads.as_deref())?;
            let name = m.name.clone();
            let (license, source) = (m.license, m.source);
            let source = if source.is_empty() {
                match &heads {
                    Some(h) => format!("the built-in network with the heads {}", h.display()),
                    None => "the built-in network with the identity heads (the plain backbone)".into(),
                }
            } else {
                source
            };
            Ok(Served { name, net: Net::Builtin(Box::new(model)), notes: Some((license, source)) })
        }
    }
}

/// The models of a model repository (`serve --models DIR`): each subfolder of `dir` one model
/// ([`load_folder`]: a TorchScript model onto `device`, or the built-in network on `base`), by
/// folder name order.
pub fn load_dir(dir: &std::path::Path, device: Device, base: Option<&Model>) -> Result<Vec<Served>> {
    let mut folders: Vec<std::path::PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading the model folder {}", dir.display()))?
        .map(|e| e.map(|e| e.path()))
        .collect::<std::io::Result<_>>()
        .with_context(|| format!("reading the model folder {}", dir.display()))?;
    folders.retain(|p| p.is_dir());
    folders.sort();
    folders.iter().map(|f| load_folder(f, device, base).with_context(|| format!("model {}", f.display()))).collect()
}
