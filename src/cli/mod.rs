//! Command-line interface: one file per subcommand.
mod calibrate;
mod classify;
mod embed;
mod eval;
mod export;
mod images;
mod ingest;
mod models;
mod ros2;
mod serve;
mod tenant;
mod train;
mod weights;

use crate::model::config::{parse_input_size, ModelConfig, Pooling, ResizeMode};
use crate::model::device::{parse_device, DType};
use crate::model::Model;
use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "loopd",
    version,
    about = "Loop-closure detection service: attention ResNet50 descriptors and map sessions"
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand)]
pub enum Command {
    /// Run the server (gRPC and HTTP) on a local data directory.
    Serve(serve::ServeArgs),
    /// Weight file tools.
    #[command(subcommand)]
    Weights(weights::WeightsCommand),
    /// Descriptor models brought as TorchScript (docs/models.md).
    #[command(subcommand)]
    Models(models::ModelsCommand),
    /// Top-5 ImageNet classes of each image (checks weights and preprocessing).
    Classify(classify::ClassifyArgs),
    /// The loop-closure descriptor of each image.
    Embed(embed::EmbedArgs),
    /// Recall at 100% precision, PR curve and similarity matrix on a sequence with ground truth.
    Eval(eval::EvalArgs),
    /// Fit the calibrated loop confidence of a model on training candidates (`eval --samples-out`).
    Calibrate(calibrate::CalibrateArgs),
    /// Train the attention/fusion heads (and whitening) on real data; writes a heads file.
    Train(train::TrainArgs),
    /// Tenants and their API keys, through a running server (admin key).
    Tenant(tenant::TenantArgs),
    /// A session's loop graph (frames.csv, loops.csv, graph.g2o, TUM trajectories) as a tar,
    /// through a running server.
    Export(export::ExportArgs),
    /// A ROS bag (MCAP, rosbag2 folder, ROS 1) as a sequence job on a running server; without
    /// --session, the bag's topics.
    Ingest(ingest::IngestArgs),
    /// A ROS 2 node between a fleet's camera topics and a server: keyframes in, loop closures
    /// out (loopd_msgs/LoopClosure, visualization_msgs/MarkerArray; docs/ros2.md).
    Ros2(ros2::Ros2Args),
    /// The HTTP API's OpenAPI document (YAML), generated from the routes this build serves:
    /// `loopd openapi > openapi.yaml`.
    Openapi,
}

/// The heads shipped in the repository (trained on the real data here, see docs/training.md).
pub const DEFAULT_HEADS: &str = "models/heads.safetensors";

/// Options shared by every command that runs the network.
#[derive(Args, Clone, Debug)]
pub struct ModelArgs {
    /// loopd weight file (safetensors), as written by `loopd weights import`.
    #[arg(long, env = "LOOPD_WEIGHTS", default_value = "weights/resnet50-imagenet.safetensors")]
    pub weights: PathBuf,
    /// Trained heads (attention, fusion, whitening) from `loopd train`, loaded on top of --weights;
    /// part of the descriptor id. Default: the shipped heads (docs/training.md); "none": the
    /// identity heads (the plain backbone, and sessions made before heads were shipped).
    #[arg(long, env = "LOOPD_HEADS", default_value = DEFAULT_HEADS)]
    pub heads: String,
    /// auto, cpu, cuda or cuda:N.
    #[arg(long, env = "LOOPD_DEVICE", default_value = "auto")]
    pub device: String,
    /// Precision; f16 and bf16 need CUDA.
    #[arg(long, env = "LOOPD_DTYPE", value_enum, default_value = "f32")]
    pub dtype: DType,
    /// Network input size: N or WxH.
    #[arg(long, env = "LOOPD_INPUT_SIZE", default_value = "224", value_parser = parse_input_size)]
    pub input_size: (u32, u32),
    /// How the feature map becomes the descriptor: gap (average) or gap-sqrt (average, then the
    /// signed square root).
    #[arg(long, env = "LOOPD_POOLING", value_enum, default_value = "gap")]
    pub pooling: Pooling,
    /// stretch to the input size, or keep the aspect ratio inside it.
    #[arg(long, env = "LOOPD_RESIZE", value_enum, default_value = "stretch")]
    pub resize: ResizeMode,
    /// The calibrated loop confidence (a file of `loopd calibrate`: one calibrator per descriptor
    /// space; docs/evaluation.md). A file given here must hold one for this model; the shipped one
    /// covers the shipped heads and the plain backbone at 224. "none": answers carry no confidence.
    #[arg(long, env = "LOOPD_CALIBRATION", default_value = crate::verify::confidence::SHIPPED)]
    pub calibration: String,
}

impl ModelArgs {
    pub fn config(&self) -> ModelConfig {
        let mut cfg = ModelConfig::default();
        cfg.preprocess.width = self.input_size.0;
        cfg.preprocess.height = self.input_size.1;
        cfg.preprocess.resize = self.resize;
        cfg.pooling = self.pooling;
        cfg
    }

    pub fn load(&self) -> Result<Model> {
        let device = parse_device(&self.device)?;
        let (model, report) = Model::load(&self.weights, self.config(), device, self.dtype).with_context(|| {
            format!("loading weights {} (run scripts/dev setup to import them)", self.weights.display())
        })?;
        let mut model = model;
        if let Some(path) = self.heads_path() {
            let h = model.load_heads(&path).with_context(|| format!("loading heads {}", path.display()))?;
            tracing::info!(heads = %path.display(), tensors = h.tensors, whitening = model.dim(), "heads loaded");
        }
        tracing::debug!(?report, device = ?model.device, "model loaded");
        Ok(model)
    }

    pub fn calibration(&self) -> crate::verify::confidence::Calibration {
        crate::verify::confidence::Calibration::parse(&self.calibration)
    }

    /// The heads file to load, if any.
    pub fn heads_path(&self) -> Option<PathBuf> {
        (self.heads != "none" && !self.heads.is_empty()).then(|| PathBuf::from(&self.heads))
    }
}

/// The paper's ablation switches, for commands that compute descriptors.
#[derive(Args, Clone, Copy, Debug)]
pub struct VariantArgs {
    /// Leave out the attention modules.
    #[arg(long)]
    pub no_attention: bool,
    /// Leave out the layer1 -> layer4 fusion.
    #[arg(long)]
    pub no_fusion: bool,
}

impl VariantArgs {
    pub fn variant(&self) -> crate::model::network::Variant {
        crate::model::network::Variant { attention: !self.no_attention, fusion: !self.no_fusion }
    }
}

pub fn run(cli: Cli) -> Result<ExitCode> {
    match cli.command {
        Command::Serve(a) => serve::run(a),
        Command::Weights(c) => weights::run(c),
        Command::Models(c) => models::run(c),
        Command::Classify(a) => classify::run(a),
        Command::Embed(a) => embed::run(a),
        Command::Eval(a) => eval::run(a),
        Command::Calibrate(a) => calibrate::run(a),
        Command::Train(a) => train::run(a),
        Command::Tenant(a) => tenant::run(a),
        Command::Export(a) => export::run(a),
        Command::Ingest(a) => ingest::run(a),
        Command::Ros2(a) => ros2::run(a),
        Command::Openapi => {
            print!("{}", crate::api::http::doc::yaml().map_err(anyhow::Error::msg)?);
            Ok(ExitCode::SUCCESS)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::Cli;
    use clap::{CommandFactory, Parser};

    /// clap checks its definitions only in debug builds: every subcommand's arguments (the
    /// client's TLS and key arguments flattened into several) are checked here in release too.
    #[test]
    fn every_subcommand_s_arguments_are_well_formed() {
        Cli::command().debug_assert();
        let eval = Cli::try_parse_from([
            "loopd",
            "eval",
            "--server",
            "https://localhost:50051",
            "--session",
            "s",
            "--gt",
            "gt.csv",
            "--ca",
            "ca.pem",
            "--key-file",
            "key",
        ]);
        assert!(eval.is_ok(), "{:?}", eval.err());
        let half = Cli::try_parse_from(["loopd", "export", "s", "--client-cert", "c.pem"]);
        assert!(half.is_err(), "a client certificate without its key must be refused");
    }
}
