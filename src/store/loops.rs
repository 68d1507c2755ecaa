//! Loop candidates kept per session: each candidate loopd answered for a stored
//! frame, with its verification outcome and a client's verdict, so a SLAM back end can fetch the
//! session's loop graph later. Keyed by (query frame, match frame), big-endian: listed in frame
//! order; a pair answered again is updated, its verdict kept.
use super::{Session, Store, StoreError};
use serde::{Deserialize, Serialize};

/// Most loops one listing returns.
pub const MAX_LOOPS_PER_PAGE: usize = 1000;

/// A rigid transform: the match camera's pose in the query camera's frame (unit quaternion,
/// translation).
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
#[schema(as = RelativePose)]
pub struct Transform {
    pub qx: f64,
    pub qy: f64,
    pub qz: f64,
    pub qw: f64,
    pub tx: f64,
    pub ty: f64,
    pub tz: f64,
}

/// A client's judgement of a loop, optionally with its own registration.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
pub struct Verdict {
    pub accepted: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub relative_pose: Option<Transform>,
    /// 6x6 row-major covariance of the relative pose (x y z, then rotation), if given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub covariance: Option<Vec<f64>>,
    /// Unix seconds it was recorded.
    pub at: f64,
}

/// A kept loop candidate: the pair, what was found when it was answered, and a client's verdict.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
#[schema(as = Loop)]
pub struct LoopRecord {
    pub query_frame: u64,
    pub match_frame: u64,
    pub query_robot: String,
    pub match_robot: String,
    pub query_time: f64,
    pub match_time: f64,
    /// Cosine similarity of the descriptors.
    pub score: f32,
    /// Place among the candidates answered (0: first).
    pub rank: u32,
    /// Its calibrated confidence when it was answered (none without a calibrator).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub confidence: Option<f32>,
    /// Geometric verification ran on this candidate.
    pub checked: bool,
    pub verified: bool,
    pub inliers: u32,
    /// From verification, with a camera (monocular: |t| = 1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub relative_pose: Option<Transform>,
    /// The relative pose is metric (depth at one of the frames): `graph.g2o` makes it a loop
    /// edge without a client's verdict.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub metric: bool,
    /// A metric pose's 6x6 row-major covariance (x y z, then the rotation vector).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<Vec<f64>>, min_items = 36, max_items = 36)]
    pub covariance: Option<Vec<f64>>,
    /// Up to 100 inlier matches (query x, y, match x, y as fractions of each image's size).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    #[schema(value_type = Vec<Vec<f32>>, max_items = 100)]
    pub inlier_matches: Vec<[f32; 4]>,
    /// Unix seconds it was (last) answered.
    pub found: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub verdict: Option<Verdict>,
}

/// One page of a listing, and where the next starts (None: the last page).
pub type Page = (Vec<LoopRecord>, Option<(u64, u64)>);

/// Which loops a listing returns; every field set narrows it.
#[derive(Clone, Debug, Default)]
pub struct LoopFilter {
    /// Loops with this robot on either side.
    pub robot: Option<String>,
    pub min_score: Option<f32>,
    /// Loops answered with at least this confidence (those without one are left out).
    pub min_confidence: Option<f32>,
    pub verified: Option<bool>,
    /// The query frame's time in [time_from, time_to].
    pub time_from: Option<f64>,
    pub time_to: Option<f64>,
    /// Start after this (query frame, match frame): the `next` of the previous page.
    pub after: Option<(u64, u64)>,
    pub limit: usize,
}

impl LoopFilter {
    fn keeps(&self, l: &LoopRecord) -> bool {
        self.robot.as_ref().is_none_or(|r| *r == l.query_robot || *r == l.match_robot)
            && self.min_score.is_none_or(|s| l.score >= s)
            && self.min_confidence.is_none_or(|c| l.confidence.is_some_and(|x| x >= c))
            && self.verified.is_none_or(|v| v == l.verified)
            && self.time_from.is_none_or(|t| l.query_time >= t)
            && self.time_to.is_none_or(|t| l.query_time <= t)
    }
}

fn loop_key(query: u64, matched: u64) -> [u8; 16] {
    let mut k = [0u8; 16];
    k[..8].copy_from_slice(&query.to_be_bytes());
    k[8..].copy_from_slice(&matched.to_be_bytes());
    k
}

fn key_loop(k: &[u8]) -> Option<(u64, u64)> {
    let k: [u8; 16] = k.try_into().ok()?;
    Some((u64::from_be_bytes(k[..8].try_into().ok()?), u64::from_be_bytes(k[8..].try_into().ok()?)))
}

fn decode(v: &[u8]) -> Result<LoopRecord, StoreError> {
    serde_json::from_slice(v).map_err(|e| StoreError::Storage(format!("bad loop record: {e}")))
}

/// The loops answered for a batch of frames being added, each with the position of its query
/// frame in the batch: the store sets its `query_frame` to that frame's id once ids are given
/// (by sled here, in the log's transaction in a cluster), so both backends take the same shape.
pub type KeptLoops = Vec<(usize, LoopRecord)>;

/// `loops` with their query frame's id from `ids` (the batch's ids, in order).
pub(super) fn with_ids(loops: KeptLoops, ids: &[u64]) -> Vec<LoopRecord> {
    loops
        .into_iter()
        .filter_map(|(i, mut l)| {
            l.query_frame = *ids.get(i)?;
            Some(l)
        })
        .collect()
}

impl Store {
    /// This node's copy of the loops updated (a pair answered again keeps its verdict); not
    /// yet durable.
    pub(super) fn keep_loops_here(&self, s: &Session, loops: Vec<LoopRecord>) -> Result<(), StoreError> {
        let trees = s.trees()?;
        for mut l in loops {
            let key = loop_key(l.query_frame, l.match_frame);
            if let Some(old) = self.note(trees.loops.get(key))? {
                l.verdict = decode(&old).ok().and_then(|o| o.verdict);
            }
            let value = serde_json::to_vec(&l).map_err(|e| StoreError::Storage(e.to_string()))?;
            self.note(trees.loops.insert(key, value))?;
        }
        Ok(())
    }

    /// The verdict on this node's copy of the loop; not yet durable.
    pub(super) fn set_verdict_here(
        &self,
        s: &Session,
        query: u64,
        matched: u64,
        verdict: Verdict,
    ) -> Result<LoopRecord, StoreError> {
        let trees = s.trees()?;
        let key = loop_key(query, matched);
        let old = self.note(trees.loops.get(key))?.ok_or_else(|| {
            StoreError::LoopNotFound(format!("no loop {query} -> {matched} in session '{}'", s.meta.id))
        })?;
        let mut record = decode(&old)?;
        record.verdict = Some(verdict);
        let value = serde_json::to_vec(&record).map_err(|e| StoreError::Storage(e.to_string()))?;
        self.note(trees.loops.insert(key, value))?;
        Ok(record)
    }
}

impl Session {
    /// Inserts loop records of frames being added (not yet durable: their flush makes them so).
    pub(super) fn write_loops(&self, loops: &[LoopRecord]) -> Result<(), StoreError> {
        if loops.is_empty() {
            return Ok(());
        }
        let trees = self.trees()?;
        for l in loops {
            let value = serde_json::to_vec(l).map_err(|e| StoreError::Storage(e.to_string()))?;
            trees.loops.insert(loop_key(l.query_frame, l.match_frame), value)?;
        }
        Ok(())
    }

    /// This node's kept loops become exactly `records` (a cluster's, from its log).
    pub(super) fn replace_loops(&self, records: &[LoopRecord]) -> Result<(), StoreError> {
        let trees = self.trees()?;
        let mut batch = sled::Batch::default();
        for key in trees.loops.iter().keys() {
            batch.remove(key?);
        }
        for l in records {
            let value = serde_json::to_vec(l).map_err(|e| StoreError::Storage(e.to_string()))?;
            batch.insert(&loop_key(l.query_frame, l.match_frame)[..], value);
        }
        Ok(trees.loops.apply_batch(batch)?)
    }

    /// One page of kept loops in (query, match) order, and where the next page starts.
    pub fn loops(&self, f: &LoopFilter) -> Result<Page, StoreError> {
        let trees = self.trees()?;
        let limit = f.limit.clamp(1, MAX_LOOPS_PER_PAGE);
        let range = match f.after {
            Some((q, m)) => trees.loops.range(loop_key(q, m)..),
            None => trees.loops.iter(),
        };
        let mut page: Vec<LoopRecord> = Vec::new();
        for entry in range {
            let (k, v) = entry?;
            let pair = key_loop(&k).ok_or_else(|| StoreError::Storage("bad loop key".into()))?;
            if Some(pair) == f.after {
                continue;
            }
            let l = decode(&v)?;
            if !f.keeps(&l) {
                continue;
            }
            if page.len() == limit {
                let next = (page[limit - 1].query_frame, page[limit - 1].match_frame);
                return Ok((page, Some(next)));
            }
            page.push(l);
        }
        Ok((page, None))
    }

    /// Every searchable frame's header, in frame id order (exports).
    pub fn headers(&self) -> Result<Vec<(u64, super::record::FrameHeader)>, StoreError> {
        Ok(self.headers_page(None, usize::MAX)?.0)
    }

    /// Up to `limit` searchable frames' headers after frame `after`, in frame id order, and the
    /// last id when more may follow (the next page's `after`).
    #[allow(clippy::type_complexity)]
    pub fn headers_page(
        &self,
        after: Option<u64>,
        limit: usize,
    ) -> Result<(Vec<(u64, super::record::FrameHeader)>, Option<u64>), StoreError> {
        use super::record::{decode_frame, frame_key, key_frame};
        let trees = self.trees()?;
        let index = self.index.read();
        let mut out = Vec::new();
        let range = match after {
            Some(a) => trees.frames.range(frame_key(a)..),
            None => trees.frames.iter(),
        };
        for entry in range {
            let (k, v) = entry?;
            let id = key_frame(&k).ok_or_else(|| StoreError::Storage("bad frame key".into()))?;
            if Some(id) == after || !index.contains(id) {
                continue;
            }
            if out.len() == limit {
                let last = out.last().map(|(id, _)| *id);
                return Ok((out, last));
            }
            out.push((id, decode_frame(&v).map_err(StoreError::Storage)?.0));
        }
        Ok((out, None))
    }

    /// Every searchable frame id, ascending.
    pub fn frame_ids(&self) -> Vec<u64> {
        self.index.read().frame_ids()
    }

    /// Every kept loop (exports).
    pub fn all_loops(&self) -> Result<Vec<LoopRecord>, StoreError> {
        let trees = self.trees()?;
        trees.loops.iter().values().map(|v| decode(&v?)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_sort_by_query_then_match() {
        let (a, b, c) = (loop_key(1, 9), loop_key(2, 0), loop_key(2, 1));
        assert!(a < b && b < c);
        assert_eq!(key_loop(&c), Some((2, 1)));
        assert_eq!(key_loop(&[0u8; 3]), None);
    }

    /// Both backends take loops by their query frame's position in the batch; sled names them
    /// by the ids it gave, as the log does in its transaction.
    #[test]
    fn kept_loops_get_their_query_frame_s_id_by_position() {
        let record = |m: u64| LoopRecord {
            query_frame: 0,
            match_frame: m,
            query_robot: "r".into(),
            match_robot: "r".into(),
            query_time: 0.0,
            match_time: 0.0,
            score: 0.9,
            rank: 0,
            confidence: None,
            checked: false,
            verified: false,
            inliers: 0,
            relative_pose: None,
            metric: false,
            covariance: None,
            inlier_matches: Vec::new(),
            found: 0.0,
            verdict: None,
        };
        let named = with_ids(vec![(0, record(3)), (2, record(4)), (5, record(9))], &[70, 71, 72]);
        let pairs: Vec<(u64, u64)> = named.iter().map(|l| (l.query_frame, l.match_frame)).collect();
        // Position 5 names no frame of a 3-frame batch: dropped, never given another's id.
        assert_eq!(pairs, [(70, 3), (72, 4)]);
    }
}
