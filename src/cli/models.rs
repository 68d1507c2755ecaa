use crate::model::device::parse_device;
use crate::model::preprocess::{decode, ImageLimits};
use crate::model::script::ScriptModel;
use anyhow::{bail, Context, Result};
use clap::Subcommand;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;
use tch::Tensor;

#[derive(Subcommand)]
pub enum ModelsCommand {
    /// Loads a model folder (model.json + TorchScript file), runs it on real images and checks
    /// what comes out (shape, finite, unit after normalisation, unit before it when the
    /// manifest says so); prints its descriptor id. Exits non-zero on the first failure.
    Check {
        /// The model folder.
        dir: PathBuf,
        /// Images to run it on (at least one).
        #[arg(long = "image", required = true)]
        images: Vec<PathBuf>,
        #[arg(long, env = "LOOPD_DEVICE", default_value = "cpu")]
        device: String,
        /// Writes, per image, `<stem>.safetensors` here: the resized RGB ("rgb", 0-255), the
        /// model's input ("input") and the unit descriptor ("descriptor"), for a comparison
        /// with PyTorch on the same pixels.
        #[arg(long)]
        save: Option<PathBuf>,
    },
}

pub fn run(c: ModelsCommand) -> Result<ExitCode> {
    match c {
        ModelsCommand::Check { dir, images, device, save } => check(dir, images, &device, save),
    }
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
