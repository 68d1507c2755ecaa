//! Loop candidates checked before anyone trusts them: local features (ORB, OpenCV) matched between
//! the query and each candidate frame, RANSAC on the fundamental or essential matrix, and one rule
//! that orders candidates by what ran. The server (`api::service`) and `loopd eval` both go
//! through [`decide`] and [`geometric::verify`], so they give the same verified matches.
pub mod features;
pub mod geometric;
pub mod pool;
pub mod sequence;

use crate::store::query::Match;
use features::Features;
use geometric::{verify, Intrinsics, Verification, VerifyParams};
use sequence::SequenceCheck;
use serde::Serialize;

/// A loop candidate as both APIs and `loopd eval` see it: the descriptor match and, when the
/// candidate was checked, the outcome (inliers, verified, relative pose).
#[derive(Clone, Debug, Serialize)]
pub struct LoopMatch {
    #[serde(flatten)]
    pub m: Match,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub verification: Option<Verification>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sequence: Option<SequenceCheck>,
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
    /// Each candidate's trajectory up to it, oldest first, in candidate order.
    pub trails: Vec<Vec<Vec<f32>>>,
    pub places: Vec<sequence::Place>,
    pub min_margin: f32,
}

/// Candidates this close on one trajectory are one place for the uniqueness margin.
pub const SEQUENCE_WINDOW: usize = 10;

/// Checks the first `checked` candidates (best cosine first, each with its stored features, if
/// any) against the query's features, then orders all of them by [`decide`]. The server (on its
/// verification workers) and `loopd eval` both call this.
pub fn check(
    query: Option<Result<&Features, &str>>,
    candidates: Vec<(Match, Option<Features>)>,
    checked: usize,
    camera: Option<&Intrinsics>,
    params: &VerifyParams,
    seq: Option<&SequenceInputs>,
) -> Vec<LoopMatch> {
    let mut sequences = match seq {
        Some(s) => sequence::check(&s.history, &s.trails, &s.places, SEQUENCE_WINDOW, s.min_margin),
        None => Vec::new(),
    }
    .into_iter();
    let mut out: Vec<LoopMatch> = candidates
        .into_iter()
        .enumerate()
        .map(|(i, (m, features))| {
            let verification = query.filter(|_| i < checked).map(|query| match (query, features) {
                (Err(why), _) => Verification::unchecked(why.to_string()),
                (Ok(_), None) => Verification::unchecked("the candidate frame has no stored features".into()),
                (Ok(q), Some(c)) => verify(q, &c, camera, params),
            });
            LoopMatch { m, verification, sequence: sequences.next().flatten() }
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
/// so equal keys keep the search's order (earlier frame first).
pub fn decide<T: Ranked>(candidates: &mut [T]) {
    candidates.sort_by(|a, b| rank_score(b).total_cmp(&rank_score(a)));
}

/// The rule as one number, for precision-recall sweeps: geometrically verified candidates score
/// 1 + inliers (at least 9), the others their sequence margin (at most 2) when it ran, else their
/// cosine (at most 1).
pub fn rank_score<T: Ranked>(c: &T) -> f32 {
    match (c.verification(), c.sequence()) {
        (Some(v), _) if v.verified => 1.0 + v.inliers as f32 + c.cosine().clamp(-1.0, 1.0) * 1e-3,
        (_, Some(s)) => s.margin,
        _ => c.cosine(),
    }
}
