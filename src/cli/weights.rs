use crate::model::config::ModelConfig;
use crate::model::tfjs;
use crate::model::weights::{load_into, WeightFile};
use crate::model::Model;
use anyhow::{Context, Result};
use clap::Subcommand;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Subcommand)]
pub enum WeightsCommand {
    /// Convert a Keras ResNet50 in TF.js form (model.json + shards) to a loopd safetensors file.
    Import {
        /// Folder holding model.json and its shards.
        #[arg(long)]
        tfjs: PathBuf,
        #[arg(long)]
        out: PathBuf,
    },
    /// Content hash (what descriptor ids and heads files name), tensor count and metadata of a
    /// weight or heads file, as JSON.
    Info { file: PathBuf },
}

pub fn run(c: WeightsCommand) -> Result<ExitCode> {
    match c {
        WeightsCommand::Info { file } => {
            let f = WeightFile::read(&file)?;
            let params: i64 = f.tensors.iter().map(|(_, t)| t.numel() as i64).sum();
            let meta: std::collections::BTreeMap<_, _> = f.metadata.iter().collect();
            let info = serde_json::json!({
                "file": file.display().to_string(),
                "sha256": f.sha256,
                "tensors": f.tensors.len(),
                "parameters": params,
                "metadata": meta,
            });
            println!("{}", serde_json::to_string_pretty(&info)?);
            Ok(ExitCode::SUCCESS)
        }
        WeightsCommand::Import { tfjs: dir, out } => {
            let imported = tfjs::import(&dir).with_context(|| format!("importing {}", dir.display()))?;
            // Prove the result fits the network exactly before writing it.
            let model = Model::new(ModelConfig::default(), tch::Device::Cpu, crate::model::device::DType::F32)?;
            let file = WeightFile {
                metadata: imported.metadata.clone(),
                tensors: imported.tensors,
                sha256: String::new(),
                file_sha256: String::new(),
            };
            let report = load_into(model.var_store(), &file)?;
            WeightFile::write(&out, &file.tensors, file.metadata)?;
            eprintln!(
                "imported {} Keras arrays ({} bytes of shards) into {} tensors -> {}",
                imported.keras_arrays,
                imported.shard_bytes,
                report.backbone_tensors,
                out.display()
            );
            Ok(ExitCode::SUCCESS)
        }
    }
}
