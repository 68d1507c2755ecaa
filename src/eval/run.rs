//! `loopd eval`: embed a sequence (or two traversals) through the engine, search with the
//! store's index, score against the ground truth, write the report and figures.
use super::gt::GroundTruth;
use super::metrics::{evaluate, evaluate_confidence, ConfidenceReport, QueryResult, Report};
use super::plots;
use crate::engine::{Engine, EngineConfig};
use crate::index::graph::{GraphParams, IndexKind};
use crate::index::query::{LoopQuery, VerifyOptions};
use crate::index::SessionIndex;
use crate::index::Storage;
use crate::model::network::Variant;
use crate::model::preprocess::ImageLimits;
use crate::verify::{
    self,
    confidence::{Calibration, Calibrator, Sample},
    features::{from_image_bytes, FeatureParams, Features},
    geometric::{Intrinsics, VerifyParams},
    sequence::Place,
    Checks, SequenceInputs,
};
use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;
use std::ops::Range;
use std::path::{Path, PathBuf};

use crate::files::{is_image, natural_key};

/// Image files of a folder in natural name order (only names containing `filter`, if given).
pub fn list_images(dir: &Path, filter: Option<&str>) -> Result<Vec<PathBuf>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.file_name().is_some_and(|n| is_image(&n.to_string_lossy())))
        .filter(|p| filter.is_none_or(|f| p.file_name().is_some_and(|n| n.to_string_lossy().contains(f))))
        .collect();
    files.sort_by_cached_key(|p| {
        natural_key(&p.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default())
    });
    if files.is_empty() {
        bail!("no images in {}", dir.display());
    }
    Ok(files)
}

/// Image files of a folder, restricted to a range of indices (`None`: all), with their indices.
pub fn frames_in_range(dir: &Path, filter: Option<&str>, range: Option<&Range<usize>>) -> Result<Vec<PathBuf>> {
    let all = list_images(dir, filter)?;
    let Some(r) = range else { return Ok(all) };
    if r.start >= r.end || r.end > all.len() {
        bail!("range {}..{} does not fit the {} images of {}", r.start, r.end, all.len(), dir.display());
    }
    Ok(all[r.clone()].to_vec())
}

/// Parses "A..B" (half-open frame indices).
pub fn parse_range(s: &str) -> Result<Range<usize>, String> {
    let (a, b) = s.split_once("..").ok_or_else(|| format!("bad range '{s}': expected START..END"))?;
    let (a, b): (usize, usize) = (
        a.trim().parse().map_err(|_| format!("bad range start in '{s}'"))?,
        b.trim().parse().map_err(|_| format!("bad range end in '{s}'"))?,
    );
    if a >= b {
        return Err(format!("empty range '{s}'"));
    }
    Ok(a..b)
}

/// FNV-1a: a cache key that stays the same across builds.
fn fnv(bytes: &[u8], mut h: u64) -> u64 {
    for &b in bytes {
        h = (h ^ b as u64).wrapping_mul(0x100000001b3);
    }
    h
}

fn cache_key(files: &[PathBuf], descriptor_id: &str, variant: Variant, weights: &Path) -> u64 {
    let mut h = fnv(format!("{descriptor_id}|{}|{}", variant.name(), weights.display()).as_bytes(), 0xcbf29ce484222325);
    for f in files {
        let meta = std::fs::metadata(f).ok();
        let stamp = meta.as_ref().map(|m| {
            (
                m.len(),
                m.modified()
                    .ok()
                    .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
                    .map_or(0, |d| d.as_nanos()),
            )
        });
        h = fnv(format!("{}|{stamp:?}", f.display()).as_bytes(), h);
    }
    h
}

pub struct EmbedSetup<'a> {
    pub weights: &'a Path,
    pub variant: Variant,
    pub cache_dir: Option<&'a Path>,
    pub max_batch: usize,
}

/// Each file's descriptor (or why not), in order, through the engine: up to `in_flight` files are
/// read and decoded ahead so the engine can batch them. `done` is called as each one finishes.
pub async fn embed_paths(
    engine: &Engine,
    files: &[PathBuf],
    variant: Variant,
    in_flight: usize,
    done: impl Fn() + Clone,
) -> Vec<Result<Vec<f32>>> {
    use futures::StreamExt;
    futures::stream::iter(files.iter().cloned())
        .map(|path| {
            let (engine, done) = (engine.clone(), done.clone());
            async move {
                let bytes = tokio::fs::read(&path).await.with_context(|| format!("reading {}", path.display()))?;
                let d = engine.embed_image(bytes.into(), variant).await?;
                done();
                anyhow::Ok(d)
            }
        })
        .buffered(in_flight.max(1))
        .collect()
        .await
}

/// Descriptors of `files` (rows in order) through the engine, from the cache when possible.
pub fn embed_files(engine: &Engine, files: &[PathBuf], setup: &EmbedSetup, label: &str) -> Result<Vec<Vec<f32>>> {
    let key = cache_key(files, engine.info().variant_id(setup.variant), setup.variant, setup.weights);
    let cache = setup.cache_dir.map(|d| d.join(format!("{key:016x}.f32")));
    if let Some(bytes) = cache.as_ref().and_then(|p| std::fs::read(p).ok()) {
        let values: Vec<f32> = bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        if values.len().is_multiple_of(files.len()) && !values.is_empty() {
            tracing::info!(label, frames = files.len(), "descriptors from cache");
            return Ok(values.chunks(values.len() / files.len()).map(<[f32]>::to_vec).collect());
        }
    }
    let bar = ProgressBar::new(files.len() as u64)
        .with_style(ProgressStyle::with_template("{msg} {pos}/{len} {wide_bar} {per_sec} eta {eta}").expect("template"))
        .with_message(format!("embedding {label}"));
    let rt = tokio::runtime::Runtime::new()?;
    let results = rt.block_on(embed_paths(engine, files, setup.variant, setup.max_batch * 2, || bar.inc(1)));
    let out = results
        .into_iter()
        .zip(files)
        .map(|(r, path)| r.with_context(|| path.display().to_string()))
        .collect::<Result<Vec<_>>>()?;
    bar.finish_and_clear();
    if let Some(p) = cache {
        std::fs::create_dir_all(p.parent().unwrap_or(Path::new(".")))?;
        let bytes: Vec<u8> = out.iter().flatten().flat_map(|v| v.to_le_bytes()).collect();
        // Whole or not at all: another eval sharing the folder may read it at any moment.
        let part = p.with_extension(format!("{}.part", std::process::id()));
        std::fs::write(&part, bytes)?;
        std::fs::rename(&part, &p)?;
    }
    Ok(out)
}

#[derive(Clone)]
pub struct EvalSpec<'a> {
    /// Candidates checked as the server checks them (None: descriptor ranking only).
    pub verify: Option<VerifyOptions>,
    /// The camera's intrinsics, for essential-matrix checks and relative poses.
    pub intrinsics: Option<Intrinsics>,
    pub sequence: &'a Path,
    pub query_sequence: Option<&'a Path>,
    pub gt: &'a str,
    pub camera: Option<usize>,
    pub tolerance: usize,
    pub exclude: usize,
    pub out: Option<&'a Path>,
    pub filter: Option<&'a str>,
    /// Only frames with these indices (natural name order) of each sequence; the ground truth
    /// is windowed to them (e.g. a validation range of places).
    pub range: Option<std::ops::Range<usize>>,
    /// Scores every candidate's confidence (the server's calibrator for these descriptors).
    pub calibrator: Option<std::sync::Arc<Calibrator>>,
    /// Every answered candidate's evidence and ground truth, one JSON line each (`loopd calibrate`).
    pub samples_out: Option<&'a Path>,
    /// Exact search, or the approximate index (the server's, built over every reference frame
    /// before the first query); auto means exact here.
    pub index: IndexKind,
    /// Local features as the server extracts them (`--max-features`, `--feature-bits`).
    pub features: FeatureParams,
    /// Depth images of the frames (folder, units per metre): metric loop poses.
    pub depth: Option<(&'a Path, f64)>,
    /// Ground-truth camera poses (T_world_camera per frame): each metric loop's pose error.
    pub poses: Option<&'a Path>,
}

/// A metric loop's relative pose against the ground truth's.
#[derive(Clone, Debug, Serialize)]
pub struct PoseError {
    pub query: usize,
    #[serde(rename = "match")]
    pub matched: usize,
    /// Distance between the frames, by the ground truth (metres).
    pub distance_m: f64,
    pub translation_m: f64,
    pub rotation_deg: f64,
}

/// Camera poses, one "x y z qx qy qz qw" line per frame.
fn load_poses(path: &Path) -> Result<Vec<nalgebra::Isometry3<f64>>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty() && !l.starts_with('#')) {
        let v: Vec<f64> = line
            .split_whitespace()
            .map(str::parse)
            .collect::<Result<_, _>>()
            .with_context(|| format!("{}:{}: not numbers", path.display(), n + 1))?;
        let [x, y, z, qx, qy, qz, qw] = v[..] else {
            bail!("{}:{}: {} values; x y z qx qy qz qw expected", path.display(), n + 1, v.len())
        };
        let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(qw, qx, qy, qz));
        out.push(nalgebra::Isometry3::from_parts(nalgebra::Translation3::new(x, y, z), q));
    }
    Ok(out)
}

/// Gives each frame's features the depth image with the frame's name stem in `dir`, if any.
fn attach_depths(files: &[PathBuf], features: &mut [Result<Features, String>], dir: &Path, scale: f64) -> Result<()> {
    let mut by_stem = std::collections::HashMap::new();
    for e in std::fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))? {
        let p = e?.path();
        if let Some(stem) = p.file_stem().and_then(|s| s.to_str()) {
            by_stem.insert(stem.to_string(), p.clone());
        }
    }
    let limits = ImageLimits::default();
    for (file, f) in files.iter().zip(features.iter_mut()) {
        let (Ok(f), Some(stem)) = (f, file.file_stem().and_then(|s| s.to_str())) else { continue };
        let Some(path) = by_stem.get(stem) else { continue };
        let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        let depth = crate::verify::depth::DepthImage::decode(&bytes, scale, &limits)
            .with_context(|| format!("{}", path.display()))?;
        depth.attach(f).with_context(|| format!("{}", path.display()))?;
    }
    Ok(())
}

#[derive(Serialize)]
pub struct EvalOutput {
    pub descriptor_id: String,
    pub variant: String,
    /// "none" or "geometric (K candidates, N inliers)".
    pub verify: String,
    pub sequence: String,
    pub query_sequence: Option<String>,
    pub frames: usize,
    pub query_frames: usize,
    pub tolerance: usize,
    pub exclude: usize,
    /// "exact" or "approximate".
    pub index: &'static str,
    /// Frame range used, if not all.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub range: Option<String>,
    /// Each query's best candidate after verification: [frame, score] (score as the decision rule
    /// ranks it: cosine, or 1 + inliers when verified), null when it had none.
    pub best: Vec<Option<(usize, f32)>>,
    /// Each query's best candidate's calibrated confidence (null without a calibrator).
    pub best_confidence: Vec<Option<f32>>,
    /// Whether each query's best candidate is a true loop (null: no candidate).
    pub best_correct: Vec<Option<bool>>,
    #[serde(flatten)]
    pub report: Report,
    /// The calibrator's descriptor space, when one scored the candidates.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub calibrator: Option<String>,
    /// The same protocol swept over the confidence of each query's first candidate.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub confidence: Option<ConfidenceReport>,
    /// With --poses: each query's first candidate with a metric pose, against the ground truth.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub pose_errors: Vec<PoseError>,
}

/// Runs one evaluation with an already started engine.
pub fn evaluate_sequences(engine: &Engine, spec: &EvalSpec, setup: &EmbedSetup) -> Result<EvalOutput> {
    let window = |dir: &Path| frames_in_range(dir, spec.filter, spec.range.as_ref());
    let refs = window(spec.sequence)?;
    let queries = spec.query_sequence.map(window).transpose()?;
    let ref_desc = embed_files(engine, &refs, setup, "reference")?;
    let query_desc = match &queries {
        Some(q) => Some(embed_files(engine, q, setup, "query")?),
        None => None,
    };
    let nq = queries.as_ref().map_or(refs.len(), Vec::len);
    let gt = match &spec.range {
        Some(r) => GroundTruth::load(spec.gt, spec.camera, r.start + nq.min(refs.len()))?.window(r),
        None => GroundTruth::load(spec.gt, spec.camera, nq.min(refs.len()))?,
    };
    // The store's index and search: the same code that answers robots.
    let dim = ref_desc.first().map_or(0, Vec::len);
    let mut index = SessionIndex::new(dim, Storage::F32);
    for (i, d) in ref_desc.iter().enumerate() {
        index.push(i as u64, "ref", i as f64, None, d);
    }
    if spec.index == IndexKind::Approximate {
        // Every query through the graph, however few frames its filter leaves.
        index.set_index(IndexKind::Approximate, GraphParams { exact_below: 0, exact_share: 0.0, ..Default::default() });
        index.index_all().map_err(anyhow::Error::msg)?;
    }
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    // Every query goes through `verify::check`, as the server's do: descriptor ranking alone is
    // the case with no check asked for.
    let v = spec.verify.clone().unwrap_or(VerifyOptions { geometric: false, sequence: false, ..Default::default() });
    let width = verify::search_width(&LoopQuery { k: 1, verify: v.clone(), ..Default::default() });
    // The query of frame i: its descriptor and the options of its search.
    let query_of = |i: usize, k: usize| -> Option<(&Vec<f32>, LoopQuery)> {
        match &query_desc {
            Some(qd) => Some((&qd[i], LoopQuery { k, ..Default::default() })),
            // One sequence: only earlier frames outside the exclusion window.
            None if i > spec.exclude => {
                let range = Some((0, (i - spec.exclude - 1) as u64));
                Some((&ref_desc[i], LoopQuery { k, frame_id_range: range, ..Default::default() }))
            }
            None => None,
        }
    };
    let features = |files: &[PathBuf], label: &str| -> Result<Vec<Result<Features, String>>> {
        if !v.geometric {
            return Ok(Vec::new());
        }
        let mut all = extract_all(files, label, &spec.features)?;
        if let Some((dir, scale)) = spec.depth {
            attach_depths(files, &mut all, dir, scale)?;
        }
        Ok(all)
    };
    // Ground-truth poses score metric loops of one sequence (query i is frame i).
    let poses = match (spec.poses, &queries) {
        (Some(p), None) => Some(load_poses(p)?),
        (Some(_), Some(_)) => bail!("--poses scores loops within one sequence, not with --query-sequence"),
        (None, _) => None,
    };
    let mut pose_errors = Vec::new();
    let ref_features = features(&refs, "reference features")?;
    let query_features = match &queries {
        Some(q) => Some(features(q, "query features")?),
        None => None,
    };
    let params = VerifyParams { min_inliers: v.min_inliers, ..Default::default() };
    let past = query_desc.as_ref().unwrap_or(&ref_desc);
    // Each frame's own best matches (what a robot got back for it when it was new).
    let past_top: Vec<Vec<u64>> = match v.sequence {
        true => (0..nq)
            .map(|i| match query_of(i, verify::sequence::VOTES) {
                Some((q, opts)) => index.search(q, &opts, threads).iter().map(|m| m.frame_id).collect(),
                None => Vec::new(),
            })
            .collect(),
        false => Vec::new(),
    };
    // Two traversals without sequence checks: every query has the same options, one batch.
    let batched = match (&query_desc, v.sequence) {
        (Some(qd), false) => Some(index.search_batch(qd, &LoopQuery { k: width, ..Default::default() }, threads)),
        _ => None,
    };
    let mut samples: Vec<Sample> = Vec::new();
    let mut confident: Vec<QueryResult> = Vec::new();
    let mut results: Vec<QueryResult> = Vec::with_capacity(nq);
    for i in 0..nq {
        let Some((q, opts)) = query_of(i, width) else {
            results.push(QueryResult { query: i, best: None });
            confident.push(QueryResult { query: i, best: None });
            continue;
        };
        let mut matches = match &batched {
            Some(b) => b[i].clone(),
            None => index.search(q, &opts, threads),
        };
        if v.sequence {
            // Where the query's past says it is now, beside what looks most alike now.
            let past_votes = &past_top[(i + 1).saturating_sub(v.sequence_length)..i];
            let have: Vec<u64> = matches.iter().map(|m| m.frame_id).collect();
            let ids: Vec<u64> = index.voted(past_votes).into_iter().filter(|id| !have.contains(id)).collect();
            matches.extend(index.score_frames(q, &ids, &opts));
        }
        let ids: Vec<u64> = matches.iter().map(|m| m.frame_id).collect();
        let places: Vec<Place> = ids.iter().map(|&id| Place { robot: 0, position: id as usize }).collect();
        let seq = v.sequence.then(|| {
            let l = v.sequence_length;
            let history = past[(i + 1).saturating_sub(l)..=i].to_vec();
            SequenceInputs {
                stats: index.row_stats(&history, &opts),
                history,
                trails: ids.iter().map(|&id| index.trail(id, l)).collect(),
                places: places.clone(),
                min_margin: v.min_sequence_margin,
                length: l,
            }
        });
        let qf =
            v.geometric.then(|| query_features.as_ref().unwrap_or(&ref_features)[i].as_ref().map_err(String::as_str));
        let candidates = matches
            .into_iter()
            .map(|m| {
                let f = ref_features.get(m.frame_id as usize).and_then(|f| f.clone().ok());
                (m, f)
            })
            .collect();
        let checks = Checks {
            checked: if v.geometric { v.candidates } else { 0 },
            camera: spec.intrinsics,
            params: params.clone(),
            seq,
            places,
            calibrator: spec.calibrator.clone(),
        };
        let ranked = verify::check(qf, candidates, &checks);
        for (rank, c) in ranked.iter().enumerate() {
            let truth = gt.is_match(i, c.m.frame_id as usize, spec.tolerance);
            samples.push(Sample { evidence: c.evidence, truth, best: rank == 0 });
        }
        let first = ranked.first();
        let metric = first.and_then(|c| c.verification.as_ref().filter(|v| v.verified && v.metric).map(|v| (c, v)));
        if let (Some(poses), Some((c, v))) = (&poses, metric) {
            let m = c.m.frame_id as usize;
            if let (Some(tq), Some(tm), Some(p)) = (poses.get(i), poses.get(m), v.relative_pose.as_ref()) {
                let truth = tq.inverse() * tm;
                let measured = nalgebra::Isometry3::from_parts(
                    nalgebra::Translation3::new(p.tx, p.ty, p.tz),
                    nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(p.qw, p.qx, p.qy, p.qz)),
                );
                pose_errors.push(PoseError {
                    query: i,
                    matched: m,
                    distance_m: truth.translation.vector.norm(),
                    translation_m: (truth.translation.vector - measured.translation.vector).norm(),
                    rotation_deg: (measured.inverse() * truth).rotation.angle().to_degrees(),
                });
            }
        }
        results.push(QueryResult { query: i, best: first.map(|c| (c.m.frame_id as usize, verify::rank_score(c))) });
        let conf = first.and_then(|c| c.confidence.map(|p| (c.m.frame_id as usize, p)));
        confident.push(QueryResult { query: i, best: conf });
    }
    if let Some(path) = spec.samples_out {
        let mut out = String::new();
        for s in &samples {
            out.push_str(&serde_json::to_string(s)?);
            out.push('\n');
        }
        std::fs::write(path, out).with_context(|| format!("writing {}", path.display()))?;
    }
    let confidence = spec.calibrator.as_ref().map(|c| {
        let k = c.clone();
        let scored: Vec<(f32, bool)> = samples.iter().map(|s| (k.confidence(&s.evidence), s.truth)).collect();
        evaluate_confidence(&confident, &gt, spec.tolerance, &scored, Some(c.loop_confidence))
    });
    let report = evaluate(&results, &gt, spec.tolerance);
    let best = results.iter().map(|r| r.best).collect();
    let best_confidence = confident.iter().map(|r| r.best.map(|b| b.1)).collect();
    let best_correct = results.iter().map(|r| r.best.map(|(b, _)| gt.is_match(r.query, b, spec.tolerance))).collect();
    let out = EvalOutput {
        descriptor_id: engine.info().variant_id(setup.variant).to_string(),
        variant: setup.variant.name().to_string(),
        verify: spec.verify.as_ref().map_or_else(|| "none".to_string(), describe_verify),
        sequence: spec.sequence.display().to_string(),
        query_sequence: spec.query_sequence.map(|p| p.display().to_string()),
        frames: refs.len(),
        query_frames: nq,
        tolerance: spec.tolerance,
        exclude: spec.exclude,
        index: spec.index.as_str(),
        range: spec.range.as_ref().map(|r| format!("{}..{}", r.start, r.end)),
        best,
        best_confidence,
        best_correct,
        report,
        calibrator: spec.calibrator.as_ref().map(|c| c.descriptor_id.clone()),
        confidence,
        pose_errors,
    };
    if let Some(dir) = spec.out {
        std::fs::create_dir_all(dir)?;
        std::fs::write(dir.join("report.json"), serde_json::to_vec_pretty(&out)?)?;
        let title = format!(
            "{} — R@100P {:.3}, AP {:.3}",
            out.variant, out.report.recall_at_100_precision, out.report.average_precision
        );
        plots::pr_curve(&dir.join("pr_curve.png"), &[(out.variant.clone(), out.report.pr_curve.clone())], &title)?;
        if let Some(c) = &out.confidence {
            let title = format!("reliability: ECE {:.3}", c.expected_calibration_error);
            plots::reliability(&dir.join("reliability.png"), &title, &[(out.variant.clone(), c.reliability.clone())])?;
        }
        let qd = query_desc.as_ref().unwrap_or(&ref_desc);
        // The store's SIMD dot-product kernel, one query row at a time.
        let refs: Vec<f32> = ref_desc.iter().flatten().copied().collect();
        let mut scores = vec![0f32; qd.len() * ref_desc.len()];
        for (q, row) in qd.iter().zip(scores.chunks_exact_mut(ref_desc.len())) {
            crate::index::kernels::dots_f32(q, &refs, row);
        }
        let truth: Vec<(usize, usize)> = gt.loops.iter().flat_map(|(&q, rs)| rs.iter().map(move |&r| (q, r))).collect();
        plots::similarity(&dir.join("similarity.png"), &scores, qd.len(), ref_desc.len(), &truth)?;
    }
    Ok(out)
}

/// The verification setting, for reports.
fn describe_verify(v: &VerifyOptions) -> String {
    let mut parts = Vec::new();
    if v.geometric {
        parts.push(format!("geometric ({} candidates, {} inliers)", v.candidates, v.min_inliers));
    }
    if v.sequence {
        parts.push(format!("sequence (L {}, margin {})", v.sequence_length, v.min_sequence_margin));
    }
    parts.join(" + ")
}

/// Local features of every file (or why not), extracted as the server extracts them, on all cores.
fn extract_all(files: &[PathBuf], label: &str, params: &FeatureParams) -> Result<Vec<Result<Features, String>>> {
    let bar = ProgressBar::new(files.len() as u64)
        .with_style(ProgressStyle::with_template("{msg} {pos}/{len} {wide_bar} {per_sec}").expect("template"))
        .with_message(label.to_string());
    let limits = ImageLimits::default();
    let one = |p: &PathBuf| {
        let r = std::fs::read(p)
            .map_err(|e| format!("{}: {e}", p.display()))
            .and_then(|b| from_image_bytes(&b, &limits, params).map_err(|e| e.to_string()));
        bar.inc(1);
        r
    };
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let chunk = files.len().div_ceil(threads).max(1);
    let out = std::thread::scope(|sc| {
        let parts: Vec<_> =
            files.chunks(chunk).map(|c| sc.spawn(move || c.iter().map(one).collect::<Vec<_>>())).collect();
        parts.into_iter().map(|h| h.join()).collect::<std::result::Result<Vec<_>, _>>()
    })
    .map_err(|_| anyhow::anyhow!("feature extraction thread panicked"))?;
    bar.finish_and_clear();
    Ok(out.into_iter().flatten().collect())
}

/// Loads the model, starts an engine and evaluates, with the calibrator `calibration` has for
/// the variant's descriptors.
pub fn run(
    model: impl Into<crate::model::served::Served>,
    spec: &EvalSpec,
    weights: &Path,
    variant: Variant,
    cache_dir: Option<&Path>,
    calibration: &Calibration,
) -> Result<EvalOutput> {
    let cfg = EngineConfig { max_batch: 16, warm_up: false, ..Default::default() };
    let setup = EmbedSetup { weights, variant, cache_dir, max_batch: cfg.max_batch };
    let engine = Engine::start(model, cfg, ImageLimits::default())?;
    let mut spec = spec.clone();
    spec.calibrator = calibration.resolve(engine.info().variant_id(variant))?.map(std::sync::Arc::new);
    evaluate_sequences(&engine, &spec, &setup)
}
