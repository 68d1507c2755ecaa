use super::{ModelArgs, VariantArgs};
use crate::eval::run::{run as run_eval, EvalSpec};
use crate::index::graph::IndexKind;
use crate::index::query::VerifyOptions;
use crate::model::served::{load_folder, Folder, Served};
use crate::verify::features::{parse_descriptor_bits, FeatureParams, DEFAULT_DESCRIPTOR_BITS};
use crate::verify::geometric::Intrinsics;
use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Args)]
pub struct EvalArgs {
    #[command(flatten)]
    pub model: ModelArgs,
    /// A model folder, as `loopd serve --models` serves each (docs/models.md: a TorchScript
    /// model, or the built-in network on --weights with the folder's heads): its descriptors are
    /// evaluated instead of --heads', through the same engine the server runs it on.
    #[arg(long = "model", conflicts_with = "server")]
    pub script_model: Option<PathBuf>,
    /// Ordered image sequence (files in natural name order); the reference traversal when
    /// --query-sequence is given.
    #[arg(long, required_unless_present = "server")]
    pub sequence: Option<PathBuf>,
    /// Evaluate a live server's session instead (gRPC address, e.g. 127.0.0.1:50051); its frame
    /// ids must be 0..n-1 in sequence order.
    #[arg(long, requires = "session")]
    pub server: Option<String>,
    #[arg(long)]
    pub session: Option<String>,
    /// With --server: a file holding the tenant's key (else LOOPD_KEY; none on a server without
    /// keys).
    #[arg(long, env = "LOOPD_KEY_FILE")]
    pub key_file: Option<PathBuf>,
    /// With --server: its TLS (an https:// address needs --ca).
    #[command(flatten)]
    pub tls: crate::client::TlsArgs,
    /// A second traversal whose frames are matched against --sequence.
    #[arg(long)]
    pub query_sequence: Option<PathBuf>,
    /// Ground truth: a MATLAB v5 .mat matrix, a CSV (query,ref pairs or query,"ref ref ..."), or
    /// "aligned" (query i matches reference i, within --tolerance).
    #[arg(long)]
    pub gt: String,
    /// For interleaved stereo ground truth (New College): 0 = left, 1 = right camera.
    #[arg(long)]
    pub camera: Option<usize>,
    /// A match within this many frames of a true one counts as true.
    #[arg(long, default_value_t = 0)]
    pub tolerance: usize,
    /// One sequence: frames this close to the query are never candidates.
    #[arg(long, default_value_t = 0)]
    pub exclude: usize,
    /// How reference frames are searched: exact, or approximate (the server's approximate index,
    /// every query through its graph).
    #[arg(long, default_value = "exact", value_parser = ["exact", "approximate"])]
    pub index: String,
    #[command(flatten)]
    pub variant: VariantArgs,
    /// Print the report as JSON on stdout.
    #[arg(long)]
    pub json: bool,
    /// Folder for report.json, pr_curve.png and similarity.png.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Only images whose file name contains this (e.g. "left_" for one camera of a stereo folder).
    #[arg(long)]
    pub filter: Option<String>,
    /// Check each query's best candidates as the server does: none, geometric (ORB + RANSAC),
    /// sequence (the frames before query and candidate), or all.
    #[arg(long, value_enum, default_value = "none")]
    pub verify: VerifyMode,
    /// Candidates checked per query (K).
    #[arg(long, default_value_t = 5)]
    pub verify_candidates: usize,
    /// Inliers for a verified loop.
    #[arg(long, default_value_t = 30)]
    pub min_inliers: usize,
    /// ORB features extracted per frame (as the server's `--max-features`).
    #[arg(long, default_value_t = FeatureParams::default().max_features)]
    pub max_features: usize,
    /// ORB descriptor bits kept per keypoint (as the server's `--feature-bits`).
    #[arg(long, default_value_t = DEFAULT_DESCRIPTOR_BITS, value_parser = parse_descriptor_bits)]
    pub feature_bits: usize,
    /// Frames compared along the trajectories in sequence verification (L).
    #[arg(long, default_value_t = 40)]
    pub sequence_length: usize,
    /// Margin over candidates elsewhere for a sequence-verified loop.
    #[arg(long, default_value_t = 1.0)]
    pub min_sequence_margin: f32,
    /// Camera intrinsics "fx,fy,cx,cy" or "fx,fy,cx,cy,k1,k2,p1,p2,k3": essential-matrix checks.
    #[arg(long, value_parser = parse_intrinsics)]
    pub intrinsics: Option<Intrinsics>,
    /// Only frames START..END (indices in natural name order) of each sequence, ground truth
    /// windowed to them (e.g. Nordland's validation places 2000..2400).
    #[arg(long, value_parser = crate::eval::run::parse_range)]
    pub range: Option<std::ops::Range<usize>>,
    /// Descriptor cache (a rerun with other search settings does not embed again).
    #[arg(long, default_value = ".loopd-cache")]
    pub cache_dir: PathBuf,
    /// Write every answered candidate's evidence (what its confidence is computed from) and its
    /// ground truth here, one JSON line each: the input of `loopd calibrate` (training sets only).
    #[arg(long)]
    pub samples_out: Option<PathBuf>,
    /// Depth images registered to the frames (the file with a frame's name stem, e.g.
    /// depth/3.pgm for color/3.png; 16-bit in --depth-scale units per metre, or float TIFF in
    /// metres): verified loops get metric poses, scored against --poses.
    #[arg(long)]
    pub depth: Option<PathBuf>,
    /// Units per metre of 16-bit depth images.
    #[arg(long, default_value_t = crate::verify::depth::DEFAULT_DEPTH_SCALE)]
    pub depth_scale: f64,
    /// Ground-truth camera poses, one line per frame in natural name order, "x y z qx qy qz qw"
    /// (T_world_camera; '#' lines skipped): each metric loop's pose error (one sequence only).
    #[arg(long)]
    pub poses: Option<PathBuf>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum VerifyMode {
    None,
    Geometric,
    Sequence,
    All,
}

fn parse_intrinsics(s: &str) -> Result<Intrinsics, String> {
    let v: Vec<f64> =
        s.split(',').map(|x| x.trim().parse::<f64>()).collect::<Result<_, _>>().map_err(|e| e.to_string())?;
    let k = match v[..] {
        [fx, fy, cx, cy] => Intrinsics { fx, fy, cx, cy, dist: None },
        [fx, fy, cx, cy, k1, k2, p1, p2, k3] => Intrinsics { fx, fy, cx, cy, dist: Some([k1, k2, p1, p2, k3]) },
        _ => return Err(format!("expected 4 or 9 numbers, got {}", v.len())),
    };
    k.validate().map_err(|e| e.to_string())?;
    Ok(k)
}

pub fn run(a: EvalArgs) -> Result<ExitCode> {
    if let (Some(server), Some(session)) = (&a.server, &a.session) {
        let rt = tokio::runtime::Runtime::new()?;
        let key = crate::client::tenant_key(a.key_file.as_deref())?;
        let (frames, report, confidence) = rt.block_on(async {
            let mut client = crate::client::grpc(server, key, &a.tls).await?;
            crate::eval::remote::evaluate_session(&mut client, session, &a.gt, a.camera, a.tolerance, a.exclude).await
        })?;
        let mut out = serde_json::to_value(&report)?;
        for (k, v) in [
            ("server", serde_json::json!(server)),
            ("session", session.as_str().into()),
            ("frames", frames.into()),
            ("exclude", a.exclude.into()),
            ("confidence", serde_json::to_value(&confidence)?),
        ] {
            out[k] = v;
        }
        println!("{}", if a.json { out.to_string() } else { serde_json::to_string_pretty(&out)? });
        return Ok(ExitCode::SUCCESS);
    }
    let Some(sequence) = a.sequence.as_deref() else { anyhow::bail!("--sequence or --server is required") };
    let (model, weights): (Served, &std::path::Path) = match &a.script_model {
        Some(dir) => {
            let device = crate::model::device::parse_device(&a.model.device)?;
            // A `builtin` folder runs on --weights (its own heads instead of --heads).
            let base = match Folder::read(dir).with_context(|| format!("model {}", dir.display()))? {
                Folder::Builtin(_) => Some(a.model.load()?),
                Folder::Script => None,
            };
            let model = load_folder(dir, device, base.as_ref()).with_context(|| format!("model {}", dir.display()))?;
            (model, if base.is_some() { &a.model.weights } else { dir })
        }
        None => (a.model.load()?.into(), &a.model.weights),
    };
    let verify = (a.verify != VerifyMode::None).then_some(VerifyOptions {
        geometric: matches!(a.verify, VerifyMode::Geometric | VerifyMode::All),
        candidates: a.verify_candidates,
        min_inliers: a.min_inliers,
        sequence: matches!(a.verify, VerifyMode::Sequence | VerifyMode::All),
        sequence_length: a.sequence_length,
        min_sequence_margin: a.min_sequence_margin,
    });
    if let Some(v) = &verify {
        let q = crate::index::query::LoopQuery { verify: v.clone(), ..Default::default() };
        q.validate()?;
    }
    let spec = EvalSpec {
        verify,
        intrinsics: a.intrinsics,
        sequence,
        query_sequence: a.query_sequence.as_deref(),
        gt: &a.gt,
        camera: a.camera,
        tolerance: a.tolerance,
        exclude: a.exclude,
        out: a.out.as_deref(),
        filter: a.filter.as_deref(),
        range: a.range.clone(),
        calibrator: None,
        samples_out: a.samples_out.as_deref(),
        index: IndexKind::parse(&a.index).map_err(anyhow::Error::msg)?,
        features: FeatureParams { max_features: a.max_features, descriptor_bits: a.feature_bits, ..Default::default() },
        depth: a.depth.as_deref().map(|d| (d, a.depth_scale)),
        poses: a.poses.as_deref(),
    };
    spec.features.validate()?;
    let variant = a.variant.variant();
    let out = run_eval(model, &spec, weights, variant, Some(&a.cache_dir), &a.model.calibration())?;
    if a.json {
        println!("{}", serde_json::to_string(&out)?);
    } else {
        let r = &out.report;
        println!("{} ({}), {} queries, {} with a loop", out.variant, out.descriptor_id, r.queries, r.positives);
        println!("verification: {}", out.verify);
        println!(
            "recall@100%precision {:.4} (threshold {:?})",
            r.recall_at_100_precision, r.threshold_at_100_precision
        );
        println!("recall@1 {:.4}   average precision {:.4}", r.recall_at_1, r.average_precision);
        if let Some(c) = &out.confidence {
            println!(
                "by confidence: recall@100%precision {:.4} (threshold {:?}), recall@99%precision {:.4}, \
                 first wrong answer at {:?}, ECE {:.4}",
                c.recall_at_100_precision,
                c.threshold_at_100_precision,
                c.recall_at_99_precision,
                c.first_false_confidence,
                c.expected_calibration_error
            );
            if let Some((t, p, r)) = c.at_loop_confidence {
                println!("at the loop confidence {t:.2}: precision {p:.4}, recall {r:.4}");
            }
        }
    }
    Ok(ExitCode::SUCCESS)
}
