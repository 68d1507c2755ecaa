use super::{images, ModelArgs};
use crate::model::labels;
use anyhow::Result;
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Args)]
pub struct ClassifyArgs {
    #[command(flatten)]
    pub model: ModelArgs,
    /// ImageNet labels (labels.json of the weights package).
    #[arg(long, env = "LOOPD_LABELS", default_value = "weights/imagenet-labels.json")]
    pub labels: PathBuf,
    /// How many classes to print per image.
    #[arg(long, default_value_t = 5)]
    pub top: i64,
    #[arg(required = true)]
    pub images: Vec<PathBuf>,
}

/// Prints, per image, `top` lines `label<TAB>probability`, best first; with several
/// images each block starts with `==> path <==`.
pub fn run(a: ClassifyArgs) -> Result<ExitCode> {
    let labels = labels::load(&a.labels)?;
    let model = a.model.load()?;
    let mut failed = false;
    for path in &a.images {
        let input = match images::load(path, &model.config.preprocess) {
            Ok(t) => t,
            Err(e) => {
                eprintln!("{}: {e:#}", path.display());
                failed = true;
                continue;
            }
        };
        let probs = model.class_probabilities(&[input])?.squeeze_dim(0);
        let (values, indices) = probs.topk(a.top.clamp(1, 1000), 0, true, true);
        if a.images.len() > 1 {
            println!("==> {} <==", path.display());
        }
        for (p, i) in Vec::<f32>::try_from(&values)?.iter().zip(Vec::<i64>::try_from(&indices)?) {
            println!("{}\t{p:.4}", labels.get(i as usize).map(String::as_str).unwrap_or("?"));
        }
    }
    Ok(if failed { ExitCode::FAILURE } else { ExitCode::SUCCESS })
}
