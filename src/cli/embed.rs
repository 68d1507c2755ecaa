use super::{images, ModelArgs, VariantArgs};
use crate::model::rows;
use anyhow::Result;
use clap::Args;
use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Args)]
pub struct EmbedArgs {
    #[command(flatten)]
    pub model: ModelArgs,
    #[command(flatten)]
    pub variant: VariantArgs,
    /// JSON lines: {"path": ..., "descriptor": [...]} per image.
    #[arg(long)]
    pub json: bool,
    /// Images per forward pass.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=256))]
    pub batch_size: u32,
    #[arg(required = true)]
    pub images: Vec<PathBuf>,
}

pub fn run(a: EmbedArgs) -> Result<ExitCode> {
    let model = a.model.load()?;
    let variant = a.variant.variant();
    let mut failed = false;
    let mut ok = Vec::new();
    for path in &a.images {
        match images::load(path, &model.config.preprocess) {
            Ok(t) => ok.push((path.clone(), t)),
            Err(e) => {
                eprintln!("{}: {e:#}", path.display());
                failed = true;
            }
        }
    }
    let mut out = std::io::stdout().lock();
    for run in images::same_size_runs(&ok, a.batch_size as usize) {
        let inputs: Vec<_> = ok[run.clone()].iter().map(|(_, t)| t.shallow_clone()).collect();
        let descs = rows(&model.descriptors(&inputs, variant)?)?;
        for ((path, _), d) in ok[run].iter().zip(descs) {
            if a.json {
                writeln!(out, "{}", serde_json::json!({ "path": path.display().to_string(), "descriptor": d }))?;
            } else {
                let head: Vec<String> = d.iter().take(4).map(|v| format!("{v:.5}")).collect();
                writeln!(out, "{}\t{}-d [{}, ...]", path.display(), d.len(), head.join(", "))?;
            }
        }
    }
    Ok(if failed { ExitCode::FAILURE } else { ExitCode::SUCCESS })
}
