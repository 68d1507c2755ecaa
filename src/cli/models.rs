use crate::model::device::parse_device;
use crate::model::preprocess::{decode, ImageLimits};
use crate::model::script::ScriptModel;
use crate::model::served::{load_folder, Folder};
use anyhow::{bail, Context, Result};
use clap::Subcommand;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;
use tch::Tensor;

#[derive(Subcommand)]
pub enum ModelsCommand {
    /// Loads a model folder (model.json + TorchScript file, or a `builtin` folder's heads), runs
    /// it on real images and checks what comes out (shape, finite, unit after normalisation, unit
    /// before it when the manifest says so); prints its descriptor id. Exits non-zero on the
    /// first failure.
    Check {
        /// The model folder.
        dir: PathBuf,
        /// Images to run it on (at least one).
        #[arg(long = "image", required = true)]
        images: Vec<PathBuf>,
        /// The built-in network's flags (--weights, --device, --input-size, ...): a `builtin`
        /// folder runs on them with its own heads; a TorchScript model takes --device only.
        #[command(flatten)]
        model: super::ModelArgs,
        /// Writes, per image, `<stem>.safetensors` here: the resized RGB ("rgb", 0-255), the
        /// model's input ("input") and the unit descriptor ("descriptor"), for a comparison
        /// with PyTorch on the same pixels.
        #[arg(long)]
        save: Option<PathBuf>,
    },
}

pub fn run(c: ModelsCommand) -> Result<ExitCode> {
    match c {
        ModelsCommand::Check { dir, images, model, save } => match Folder::read(&dir)? {
            Folder::Script => check(dir, images, &model.device, save),
            Folder::Builtin(_) if save.is_some() => {
                bail!("--save compares a TorchScript model with PyTorch; {} is a builtin folder", dir.display())
            }
            Folder::Builtin(_) => check_builtin(&dir, &images, &model),
        },
    }
}

/// A `builtin` folder: the built-in network on --weights with the folder's heads, run on each
/// image (unit, finite descriptors of the heads' length).
fn check_builtin(dir: &std::path::Path, images: &[PathBuf], args: &super::ModelArgs) -> Result<ExitCode> {
    let base = args.load()?;
    let served = load_folder(dir, base.device, Some(&base))?;
    let about = served.about();
    println!("model        {} (the built-in network)", served.name);
    println!("weights      {}", args.weights.display());
    println!("output       {} values", served.dim());
    println!("license      {}", if about.license.is_empty() { "(not stated)" } else { &about.license });
    println!("source       {}", about.source);
    println!("\n| image | size | ms |\n|---|--:|--:|");
    let input = served.input();
    for path in images {
        let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        let img = decode(&bytes, &ImageLimits::default()).with_context(|| format!("{}", path.display()))?;
        let t = Instant::now();
        let d = served.descriptors(&[input.to_input(&img)], crate::model::network::Variant::FULL)?;
        let ms = t.elapsed().as_secs_f64() * 1e3;
        if d.size() != [1, served.dim() as i64] || !bool::try_from(d.isfinite().all())? {
            bail!("{}: the descriptor has shape {:?} or values that are not finite", path.display(), d.size());
        }
        let unit = f64::try_from(d.norm())?;
        if (unit - 1.0).abs() > 1e-4 {
            bail!("{}: the descriptor has norm {unit}", path.display());
        }
        println!("| {} | {}x{} | {ms:.1} |", path.display(), img.width(), img.height());
    }
    println!("\ndescriptor id {}", served.descriptor_id(crate::model::network::Variant::FULL));
    Ok(ExitCode::SUCCESS)
}

fn check(dir: PathBuf, images: Vec<PathBuf>, device: &str, save: Option<PathBuf>) -> Result<ExitCode> {
    let model = ScriptModel::load(&dir, parse_device(device)?)?;
    let m = &model.manifest;
    println!("model        {}", m.name);
    println!("file         {} (sha256 {})", dir.join(&m.file).display(), model.sha256);
    let lower = |v: &dyn std::fmt::Debug| format!("{v:?}").to_lowercase();
    println!(
        "input        {}x{}, {}, {}",
        m.input.width,
        m.input.height,
        lower(&m.input.resize),
        lower(&m.input.channels)
    );
    println!("output       {} values, normalised by the model: {}", m.output_dim, m.normalized);
    println!("license      {}", if m.license.is_empty() { "(not stated)" } else { &m.license });
    println!("source       {}", if m.source.is_empty() { "(not stated)" } else { &m.source });
    if let Some(s) = &save {
        std::fs::create_dir_all(s).with_context(|| format!("creating {}", s.display()))?;
    }
    println!("\n| image | size | input | norm as output | ms |\n|---|--:|--:|--:|--:|");
    for path in &images {
        let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        let img = decode(&bytes, &ImageLimits::default()).with_context(|| format!("{}", path.display()))?;
        let rgb = model.resized(&img);
        let input = model.normalize(&rgb);
        let t = Instant::now();
        let raw = model.forward(std::slice::from_ref(&input)).with_context(|| format!("{}", path.display()))?;
        let ms = t.elapsed().as_secs_f64() * 1e3;
        let norm = f64::try_from(raw.norm())?;
        if m.normalized && (norm - 1.0).abs() > 1e-3 {
            bail!("{}: the manifest says the output is normalised, but its norm is {norm:.6}", path.display());
        }
        let d = model.unit(&raw)?;
        let unit = f64::try_from(d.norm())?;
        if (unit - 1.0).abs() > 1e-4 {
            bail!("{}: the normalised descriptor has norm {unit}", path.display());
        }
        let size = input.size();
        println!(
            "| {} | {}x{} | {}x{} | {norm:.4} | {ms:.1} |",
            path.display(),
            img.width(),
            img.height(),
            size[2],
            size[1]
        );
        if let Some(s) = &save {
            let stem = path.file_stem().map_or_else(|| "image".into(), |s| s.to_string_lossy().into_owned());
            let out = s.join(format!("{stem}.safetensors"));
            let saved = [
                ("rgb", rgb.contiguous()),
                ("input", input.contiguous()),
                ("descriptor", d.squeeze_dim(0).contiguous()),
            ];
            Tensor::write_safetensors(&saved, &out).with_context(|| format!("writing {}", out.display()))?;
        }
    }
    println!("\ndescriptor id {}", model.descriptor_id());
    Ok(ExitCode::SUCCESS)
}
