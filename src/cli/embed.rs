use super::{ModelArgs, VariantArgs};
use crate::engine::{Engine, EngineConfig};
use crate::eval::run::embed_paths;
use crate::model::preprocess::ImageLimits;
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
    /// Most images per forward pass.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=256))]
    pub batch_size: u32,
    #[arg(required = true)]
    pub images: Vec<PathBuf>,
}

/// Through the same engine as the server (decode workers, dynamic batching), so the CLI and the
/// server cannot drift apart; a bad file is reported and the rest still embedded.
pub fn run(a: EmbedArgs) -> Result<ExitCode> {
    let model = a.model.load()?;
    let variant = a.variant.variant();
    let cfg = EngineConfig { max_batch: a.batch_size as usize, warm_up: false, ..Default::default() };
    let engine = Engine::start(model, cfg, ImageLimits::default())?;
    let rt = tokio::runtime::Runtime::new()?;
    let results = rt.block_on(embed_paths(&engine, &a.images, variant, 2 * a.batch_size as usize, || {}));
    let mut failed = false;
    let mut out = std::io::stdout().lock();
    for (path, r) in a.images.iter().zip(results) {
        match r {
            Ok(d) if a.json => {
                writeln!(out, "{}", serde_json::json!({ "path": path.display().to_string(), "descriptor": d }))?
            }
            Ok(d) => {
                let head: Vec<String> = d.iter().take(4).map(|v| format!("{v:.5}")).collect();
                writeln!(out, "{}\t{}-d [{}, ...]", path.display(), d.len(), head.join(", "))?;
            }
            Err(e) => {
                eprintln!("{}: {e:#}", path.display());
                failed = true;
            }
        }
    }
    Ok(if failed { ExitCode::FAILURE } else { ExitCode::SUCCESS })
}
