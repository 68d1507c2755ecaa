//! Loop candidates checked before anyone trusts them: local features (ORB, OpenCV) matched between
//! the query and each candidate frame, RANSAC on the fundamental or essential matrix, and one rule
//! that orders candidates by what ran. The server (`api::service`) and `loopd eval` both go
//! through [`decide`] and [`geometric::verify`], so they give the same verified matches.
pub mod features;
pub mod geometric;
pub mod pool;

use crate::store::query::Match;
use features::Features;
use geometric::{verify, Intrinsics, Verification, VerifyParams};
use serde::Serialize;

/// A loop candidate as both APIs and `loopd eval` see it: the descriptor match and, when the
/// candidate was checked, the outcome (inliers, verified, relative pose).
#[derive(Clone, Debug, Serialize)]
pub struct LoopMatch {
    #[serde(flatten)]
    pub m: Match,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub verification: Option<Verification>,
}

impl Ranked for LoopMatch {
    fn cosine(&self) -> f32 {
        self.m.score
    }
    fn verification(&self) -> Option<&Verification> {
        self.verification.as_ref()
    }
}

/// Checks the first `checked` candidates (best cosine first, each with its stored features, if
/// any) against the query's features, then orders all of them by [`decide`]. The server (on its
/// verification workers) and `loopd eval` both call this.
pub fn check(
    query: Result<&Features, &str>,
    candidates: Vec<(Match, Option<Features>)>,
    checked: usize,
    camera: Option<&Intrinsics>,
    params: &VerifyParams,
) -> Vec<LoopMatch> {
    let mut out: Vec<LoopMatch> = candidates
        .into_iter()
        .enumerate()
        .map(|(i, (m, features))| {
            let verification = (i < checked).then(|| match (query, features) {
                (Err(why), _) => Verification::unchecked(why.to_string()),
                (Ok(_), None) => Verification::unchecked("the candidate frame has no stored features".into()),
                (Ok(q), Some(c)) => verify(q, &c, camera, params),
            });
            LoopMatch { m, verification }
        })
        .collect();
    decide(&mut out);
    out
}

/// A candidate as verification sees it: its cosine score and, if it was checked, the outcome.
pub trait Ranked {
    fn cosine(&self) -> f32;
    fn verification(&self) -> Option<&Verification>;
}

/// The one decision rule: a verified candidate outranks every unverified one; verified ones rank
/// by inliers, then cosine; the rest keep their cosine order. Stable, so equal keys keep the
/// search's order (earlier frame first).
pub fn decide<T: Ranked>(candidates: &mut [T]) {
    candidates.sort_by(|a, b| rank_score(b).total_cmp(&rank_score(a)));
}

/// The rule as one number, for precision-recall sweeps: unverified candidates score their cosine
/// (at most 1), verified ones 1 + inliers.
pub fn rank_score<T: Ranked>(c: &T) -> f32 {
    match c.verification() {
        Some(v) if v.verified => 1.0 + v.inliers as f32 + c.cosine().clamp(-1.0, 1.0) * 1e-3,
        _ => c.cosine(),
    }
}
