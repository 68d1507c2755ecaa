//! Loop candidates checked before anyone trusts them: local features (ORB, OpenCV) matched between
//! the query and each candidate frame, RANSAC on the fundamental or essential matrix, and one rule
//! that orders candidates by what ran, and one calibrated confidence per candidate
//! ([`confidence`]). The server (`api::service`) and `loopd eval` both go through [`check`], so
//! they give the same verified matches and the same confidences.
pub mod confidence;
pub mod depth;
pub mod error;
pub mod features;
pub mod geometric;
mod matching;
pub mod pool;
pub mod sequence;
pub mod stereo;

use crate::index::query::Match;
use confidence::{Calibrator, Evidence};
pub use error::VerifyError;
use features::Features;
use geometric::{verify, Intrinsics, Verification, VerifyParams};
use sequence::SequenceCheck;
use serde::Serialize;

/// A loop candidate as both APIs and `loopd eval` see it: the descriptor match and, when the
/// candidate was checked, the outcome (inliers, verified, relative pose).
#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct LoopMatch {
    #[serde(flatten)]
    pub m: Match,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub verification: Option<Verification>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sequence: Option<SequenceCheck>,
    /// P(true loop) from the calibrator of the session's descriptor space (none without one).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub confidence: Option<f32>,
    /// What the confidence was computed from (kept for `loopd eval --samples-out`).
    #[serde(skip)]
    pub evidence: Evidence,
}

impl Ranked for LoopMatch {
    fn cosine(&self) -> f32 {
        self.m.score
    }
    fn verification(&self) -> Option<&Verification> {
        self.verification.as_ref()
    }
    fn sequence(&self) -> Option<&SequenceCheck> {
        self.sequence.as_ref()
    }
}

/// What sequence verification compares (see [`sequence::check`]).
pub struct SequenceInputs {
    /// The query's past, oldest first, the query last.
    pub history: Vec<Vec<f32>>,
    /// Each history frame's (mean, std) of similarities to the map ([`sequence::ROW_SAMPLE`]
    /// of its frames), in history order.
    pub stats: Vec<(f32, f32)>,
    /// Each candidate's trajectory up to it, oldest first, in candidate order.
    pub trails: Vec<Vec<Vec<f32>>>,
    pub places: Vec<sequence::Place>,
    pub min_margin: f32,
    /// The frames asked for (L); a young trajectory compares fewer.
    pub length: usize,
}

/// How a query's candidates are checked and scored, besides the candidates themselves.
pub struct Checks {
    /// The first `checked` candidates are verified geometrically (with the query's features).
    pub checked: usize,
    pub camera: Option<Intrinsics>,
    pub params: VerifyParams,
    pub seq: Option<SequenceInputs>,
    /// Each candidate's place (robot, position on its trajectory): for the margin over the best
    /// candidate elsewhere.
    pub places: Vec<sequence::Place>,
    pub calibrator: Option<std::sync::Arc<Calibrator>>,
}

impl Checks {
    /// No check, only the confidence: a query that asks for neither verification.
    pub fn none(places: Vec<sequence::Place>, calibrator: Option<std::sync::Arc<Calibrator>>) -> Self {
        Self { checked: 0, camera: None, params: VerifyParams::default(), seq: None, places, calibrator }
    }
}

/// Candidates this close on one trajectory are one place for the uniqueness margin.
pub const SEQUENCE_WINDOW: usize = 10;

/// Candidates fetched for the confidence's margin over the best candidate elsewhere, at least.
pub const MARGIN_POOL: usize = 10;

/// How many candidates a query fetches by descriptor before its checks: what it returns, its
/// votes, the margin's pool, the candidates it checks and the sequence pool (server and eval).
pub fn search_width(q: &crate::index::query::LoopQuery) -> usize {
    let v = &q.verify;
    let widths = [
        q.k,
        sequence::VOTES,
        MARGIN_POOL,
        if v.geometric { v.candidates } else { 0 },
        if v.sequence { sequence::POOL } else { 0 },
    ];
    widths.into_iter().max().unwrap_or(q.k).min(crate::index::query::MAX_K)
}

/// Checks the first `checked` candidates (best cosine first, each with its stored features, if
/// any) against the query's features, scores every one by sequence when asked, gives each its
/// confidence, then orders all of them by [`decide`]. The server (on its verification workers)
/// and `loopd eval` both call this.
pub fn check(
    query: Option<Result<&Features, &str>>,
    candidates: Vec<(Match, Option<Features>)>,
    c: &Checks,
) -> Vec<LoopMatch> {
    let mut sequences = match &c.seq {
        Some(s) => sequence::check(&s.history, &s.stats, &s.trails, &s.places, SEQUENCE_WINDOW, s.min_margin),
        None => Vec::new(),
    }
    .into_iter();
    let cosines: Vec<f32> = candidates.iter().map(|(m, _)| m.score).collect();
    let place = |i: usize| c.places.get(i).copied();
    let margins = confidence::cosine_margins(&cosines, |i, j| match (place(i), place(j)) {
        (Some(a), Some(b)) => a.robot == b.robot && a.position.abs_diff(b.position) <= SEQUENCE_WINDOW,
        _ => false,
    });
    let asked = c.seq.as_ref().map_or(1, |s| s.length.max(1));
    let mut out: Vec<LoopMatch> = candidates
        .into_iter()
        .enumerate()
        .map(|(i, (m, features))| {
            let mut ran = false;
            let verification = query.filter(|_| i < c.checked).map(|query| match (query, features) {
                (Err(why), _) => Verification::unchecked(why.to_string()),
                (Ok(_), None) => Verification::unchecked("the candidate frame has no stored features".into()),
                (Ok(q), Some(f)) => {
                    ran = true;
                    verify(q, &f, c.camera.as_ref(), &c.params)
                }
            });
            let sequence = sequences.next().flatten();
            let evidence = Evidence {
                cosine: m.score,
                margin: margins[i],
                geometric: verification.as_ref().filter(|_| ran).map(|v| (v.inliers as u32, v.inlier_ratio)),
                sequence: sequence.as_ref().map(|s| (s.margin, s.length as f32 / asked as f32)),
            };
            let confidence = c.calibrator.as_ref().map(|k| k.confidence(&evidence));
            LoopMatch { m, verification, sequence, confidence, evidence }
        })
        .collect();
    decide(&mut out);
    out
}

/// A candidate as verification sees it: its cosine score and, if it was checked, the outcome.
pub trait Ranked {
    fn cosine(&self) -> f32;
    fn verification(&self) -> Option<&Verification>;
    fn sequence(&self) -> Option<&SequenceCheck>;
}

/// The one decision rule: a geometrically verified candidate outranks every other; those rank by
/// inliers, then cosine. The rest rank by their sequence margin when sequence verification ran
/// (sequence-verified ones, above the margin threshold, therefore first), else by cosine. Stable,
/// so equal keys keep the search's order (earlier frame first). The confidence says how far to
/// trust the first candidate; it does not reorder them (a query without checks keeps the
/// descriptor ranking).
pub fn decide<T: Ranked>(candidates: &mut [T]) {
    candidates.sort_by(|a, b| rank_score(b).total_cmp(&rank_score(a)));
}

/// The rule as one number, for precision-recall sweeps: geometrically verified candidates score
/// 1 + inliers (at least 9), the others their sequence margin (at most 2) when it ran, else their
/// cosine (at most 1).
pub fn rank_score<T: Ranked>(c: &T) -> f32 {
    let verified = c.verification().filter(|v| v.verified).map(|v| v.inliers);
    rank_value(c.cosine(), verified, c.sequence().map(|s| s.margin))
}

/// [`rank_score`] from an answer's parts (what a client reads back from the server): its cosine,
/// its inliers if geometrically verified, its sequence margin if sequence verification ran.
pub fn rank_value(cosine: f32, verified_inliers: Option<usize>, sequence_margin: Option<f32>) -> f32 {
    match (verified_inliers, sequence_margin) {
        (Some(inliers), _) => 1.0 + inliers as f32 + cosine.clamp(-1.0, 1.0) * 1e-3,
        (_, Some(margin)) => margin,
        _ => cosine,
    }
}
