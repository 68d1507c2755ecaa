use super::ModelArgs;
use crate::eval::run::parse_range;
use crate::model::device::parse_device;
use crate::train::data::{TrainSet, TraversalSource};
use crate::train::loss::MsParams;
use crate::train::run::{train, Recipe, TrainSpec, ValSet, WhitenSpec};
use anyhow::{bail, Context, Result};
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Args)]
pub struct TrainArgs {
    /// Backbone weights, device, input size, pooling; --heads: heads to start from.
    #[command(flatten)]
    pub model: ModelArgs,
    /// Reference traversal (or one sequence with loop ground truth).
    #[arg(long)]
    pub sequence: Option<PathBuf>,
    /// A second traversal of the same route, matched to --sequence by --gt.
    #[arg(long, requires = "sequence")]
    pub query_sequence: Option<PathBuf>,
    /// Ground truth of --sequence: "aligned", a .mat or a .csv (as `loopd eval` reads it).
    #[arg(long, default_value = "aligned")]
    pub gt: String,
    /// Frames this close on the route are the same place (never negatives of each other).
    #[arg(long, default_value_t = 2)]
    pub tolerance: usize,
    /// Training frames START..END of the sequences (the rest is left for validation).
    #[arg(long, value_parser = parse_range)]
    pub range: Option<std::ops::Range<usize>>,
    /// Places CSV: image path (first column, relative to the CSV) and place columns.
    #[arg(long)]
    pub places: Option<PathBuf>,
    /// Columns of --places whose values together name a place.
    #[arg(long, value_delimiter = ',', default_value = "place")]
    pub place_columns: Vec<String>,
    /// Unlabelled image folders: each image is a place, its views are augmentations.
    #[arg(long)]
    pub images: Vec<PathBuf>,
    /// Validation set (repeatable), never trained on:
    /// "name=N,sequence=DIR[,query=DIR][,gt=aligned|FILE][,tolerance=T][,exclude=E][,range=A..B][,filter=S]".
    #[arg(long)]
    pub val: Vec<String>,
    /// Input size for validation and the whitening fit (default: --input-size): train small,
    /// select at the size the heads will serve at.
    #[arg(long, value_parser = crate::model::config::parse_input_size)]
    pub val_input_size: Option<(u32, u32)>,
    /// Output folder: heads.safetensors, checkpoint, state.json, loss.png, validation.png, and
    /// model.json (the folder is a model `serve --models` serves).
    #[arg(long)]
    pub out: PathBuf,
    /// The model's name when --out is served as a model folder (`serve --models`: train writes
    /// its model.json); default: --out's folder name.
    #[arg(long)]
    pub name: Option<String>,
    #[arg(long, default_value_t = 8)]
    pub epochs: usize,
    /// Places per batch (P).
    #[arg(long, default_value_t = 8)]
    pub batch_places: usize,
    /// Views per place (K).
    #[arg(long, default_value_t = 2)]
    pub views: usize,
    #[arg(long, default_value_t = 1e-3)]
    pub lr: f64,
    #[arg(long, default_value_t = 1e-4)]
    pub weight_decay: f64,
    #[arg(long, default_value_t = 50)]
    pub warmup_steps: usize,
    /// Largest global gradient norm.
    #[arg(long, default_value_t = 1.0)]
    pub clip_norm: f64,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Cap on steps per epoch (default: every place once).
    #[arg(long)]
    pub steps_per_epoch: Option<usize>,
    /// Stop after this many epochs without a better validation score (0: never).
    #[arg(long, default_value_t = 2)]
    pub patience: usize,
    /// Also train this part of the backbone.
    #[arg(long, value_enum, default_value = "none")]
    pub train_backbone: TrainBackbone,
    /// Light augmentation of labelled views as well (unlabelled ones are always augmented).
    #[arg(long)]
    pub augment: bool,
    /// Mixed precision of the training forward pass: f16 or bf16 autocast (CUDA only; matrix
    /// products and convolutions in half precision, the loss and the weights in f32). f32: none.
    #[arg(long, value_enum, default_value = "f32")]
    pub autocast: crate::model::device::DType,
    /// Multi-similarity margin (lambda).
    #[arg(long, default_value_t = 0.5)]
    pub margin: f64,
    /// Fit PCA whitening on the training frames after training (stored in the heads file).
    #[arg(long)]
    pub whiten: bool,
    /// Whitened descriptor length (default: all dimensions the frames support).
    #[arg(long)]
    pub whiten_dim: Option<i64>,
    /// Most training frames embedded for the whitening.
    #[arg(long, default_value_t = 4000)]
    pub whiten_frames: usize,
    /// Eigenvalue regularisation, as a fraction of the mean eigenvalue.
    #[arg(long, default_value_t = 0.1)]
    pub whiten_shrink: f64,
    /// Descriptor cache for validation and whitening frames (shared with `loopd eval`).
    #[arg(long, default_value = ".loopd-cache")]
    pub cache_dir: PathBuf,
    /// Continue from --out's checkpoint and state.json.
    #[arg(long)]
    pub resume: bool,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum TrainBackbone {
    None,
    Layer4,
}

/// Parses one --val specification.
pub fn parse_val(s: &str) -> Result<ValSet> {
    let mut v = ValSet {
        name: String::new(),
        sequence: PathBuf::new(),
        query_sequence: None,
        gt: "aligned".into(),
        tolerance: 0,
        exclude: 0,
        range: None,
        filter: None,
    };
    for part in s.split(',') {
        let (k, val) = part.split_once('=').with_context(|| format!("--val '{s}': '{part}' is not key=value"))?;
        match k.trim() {
            "name" => v.name = val.into(),
            "sequence" => v.sequence = val.into(),
            "query" => v.query_sequence = Some(val.into()),
            "gt" => v.gt = val.into(),
            "tolerance" => v.tolerance = val.parse().context("--val tolerance")?,
            "exclude" => v.exclude = val.parse().context("--val exclude")?,
            "range" => v.range = Some(parse_range(val).map_err(anyhow::Error::msg)?),
            "filter" => v.filter = Some(val.into()),
            other => bail!("--val '{s}': unknown key '{other}'"),
        }
    }
    if v.sequence.as_os_str().is_empty() {
        bail!("--val '{s}': sequence= is required");
    }
    if v.name.is_empty() {
        v.name = v.sequence.display().to_string();
    }
    Ok(v)
}

pub fn run(a: TrainArgs) -> Result<ExitCode> {
    let mut set = TrainSet::default();
    if let Some(seq) = &a.sequence {
        set.add_traversal(&TraversalSource {
            sequence: seq.clone(),
            query_sequence: a.query_sequence.clone(),
            gt: a.gt.clone(),
            camera: None,
            tolerance: a.tolerance,
            range: a.range.clone(),
            filter: None,
        })?;
    }
    if let Some(p) = &a.places {
        set.add_places_csv(p, &a.place_columns)?;
    }
    for dir in &a.images {
        set.add_unlabelled(dir)?;
    }
    if a.whiten_dim.is_some_and(|d| d < 8 || d % 8 != 0) {
        bail!("--whiten-dim must be a positive multiple of 8 (the search kernels' lane width)");
    }
    let device = parse_device(&a.model.device)?;
    a.autocast.check(device).context("--autocast")?;
    let val = a.val.iter().map(|s| parse_val(s)).collect::<Result<Vec<_>>>()?;
    for v in &val {
        if !v.sequence.is_dir() {
            bail!("validation set {}: {} is not a folder", v.name, v.sequence.display());
        }
    }
    for s in &set.sources {
        eprintln!("training data: {s}");
    }
    let spec = TrainSpec {
        weights: a.model.weights.clone(),
        init_heads: a.model.heads_path(),
        config: a.model.config(),
        val_config: {
            let mut c = a.model.config();
            if let Some((w, h)) = a.val_input_size {
                (c.preprocess.width, c.preprocess.height) = (w, h);
            }
            c
        },
        device,
        set,
        val,
        out: a.out.clone(),
        name: a.name.clone(),
        recipe: Recipe {
            epochs: a.epochs,
            places_per_batch: a.batch_places,
            views: a.views,
            lr: a.lr,
            weight_decay: a.weight_decay,
            warmup_steps: a.warmup_steps,
            clip_norm: a.clip_norm,
            seed: a.seed,
            steps_per_epoch: a.steps_per_epoch,
            patience: a.patience,
            train_layer4: a.train_backbone == TrainBackbone::Layer4,
            augment_labelled: a.augment,
            loss: MsParams { lambda: a.margin, ..Default::default() },
            autocast: a.autocast,
        },
        whiten: a.whiten.then_some(WhitenSpec { dim: a.whiten_dim, frames: a.whiten_frames, shrink: a.whiten_shrink }),
        resume: a.resume,
        cache_dir: Some(a.cache_dir.clone()),
    };
    let out = train(&spec)?;
    println!("heads: {}", out.heads.display());
    println!(
        "steps {}  best epoch {}  {:.0} s  {} images",
        out.state.step, out.state.best_epoch, out.state.seconds, out.state.images
    );
    for (e, v) in out.state.validation.iter().enumerate() {
        for s in v {
            println!(
                "epoch {e} {:<12} R@100P {:.3}  recall@1 {:.3}  AP {:.3}",
                s.set, s.recall_at_100_precision, s.recall_at_1, s.average_precision
            );
        }
    }
    for s in &out.final_validation {
        println!(
            "final   {:<12} R@100P {:.3}  recall@1 {:.3}  AP {:.3}",
            s.set, s.recall_at_100_precision, s.recall_at_1, s.average_precision
        );
    }
    Ok(ExitCode::SUCCESS)
}
