//! Loop query options and results.
use serde::{Deserialize, Serialize};

/// Which robots' frames a query may match.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Scope {
    /// Every robot, the querying one included.
    #[default]
    All,
    /// Only the querying robot's own frames (single-robot loop closure).
    SameRobot,
    /// Only other robots' frames (inter-robot loop closure / map merging).
    OtherRobots,
}

/// "Where have we been that looks like this?" Every field has a safe default.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(default)]
pub struct LoopQuery {
    /// Most matches returned.
    pub k: usize,
    /// Matches scoring below this cosine similarity are not returned.
    pub min_score: f32,
    /// Candidates whose calibrated confidence is below this are not returned (0: every one;
    /// above 0 it needs a calibrator for the session's descriptors).
    pub min_confidence: f32,
    /// Robot asking; the exclusion window and the scope refer to it.
    pub robot_id: Option<String>,
    /// Skip the querying robot's own last N frames (neighbours always look alike).
    pub exclude_last_frames: usize,
    /// Skip the querying robot's own frames newer than `at_time - exclude_last_seconds`.
    pub exclude_last_seconds: f64,
    /// The query's own time (defaults to the robot's newest frame time) for the seconds window.
    pub at_time: Option<f64>,
    pub scope: Scope,
    /// Optional inclusive ranges.
    #[schema(value_type = Option<Vec<f64>>, min_items = 2, max_items = 2)]
    pub time_range: Option<(f64, f64)>,
    #[schema(value_type = Option<Vec<u64>>, min_items = 2, max_items = 2)]
    pub frame_id_range: Option<(u64, u64)>,
    /// A frame never returned (the stored frame a query is made from); not a client option.
    #[serde(skip)]
    pub exclude_frame: Option<u64>,
    /// How candidates are checked before they are returned (the store itself only ranks by
    /// cosine; the service runs the checks).
    pub verify: VerifyOptions,
}

/// Candidate checks a query asks for.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(default)]
pub struct VerifyOptions {
    /// Check the best candidates with local features and RANSAC.
    pub geometric: bool,
    /// How many of the best descriptor matches are checked (K).
    pub candidates: usize,
    /// Geometric inliers needed for a verified loop.
    pub min_inliers: usize,
    /// Score candidates by the frames that led up to them (sequence verification).
    pub sequence: bool,
    /// Frames compared along the trajectories (L).
    pub sequence_length: usize,
    /// Margin over candidates elsewhere on the map for a sequence-verified loop.
    pub min_sequence_margin: f32,
}

/// Longest trajectory stretch sequence verification compares.
pub const MAX_SEQUENCE_LENGTH: usize = 200;

/// Most candidates one query may have checked (each costs a few milliseconds of CPU).
pub const MAX_CANDIDATES: usize = 50;

impl Default for VerifyOptions {
    fn default() -> Self {
        // docs/verification.md: true desk and EuRoC loops have 91+ inliers at 1,000 features,
        // non-loops at most 15.
        Self {
            geometric: true,
            candidates: 5,
            min_inliers: 30,
            sequence: false,
            // Chosen on Nordland's training places (docs/verification.md): 40 frames, a margin of
            // 1 z unit over the best candidate elsewhere.
            sequence_length: 40,
            min_sequence_margin: 1.0,
        }
    }
}

impl Default for LoopQuery {
    fn default() -> Self {
        Self {
            k: 5,
            min_score: -1.0,
            min_confidence: 0.0,
            robot_id: None,
            exclude_last_frames: 0,
            exclude_last_seconds: 0.0,
            at_time: None,
            scope: Scope::All,
            time_range: None,
            frame_id_range: None,
            exclude_frame: None,
            verify: VerifyOptions::default(),
        }
    }
}

/// Why a query's options cannot be searched: a bad argument of the client's.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct InvalidQuery(pub String);

impl LoopQuery {
    /// The one place a query's options are checked; every search path calls it.
    pub fn validate(&self) -> Result<(), InvalidQuery> {
        if !(1..=MAX_K).contains(&self.k) {
            return Err(InvalidQuery(format!("k = {} is out of range 1..={MAX_K}", self.k)));
        }
        if !self.min_score.is_finite() {
            return Err(InvalidQuery("min_score must be a finite number".into()));
        }
        if !(0.0..=1.0).contains(&self.min_confidence) {
            return Err(InvalidQuery(format!("min_confidence = {} is out of range 0..=1", self.min_confidence)));
        }
        if !self.exclude_last_seconds.is_finite() || self.exclude_last_seconds < 0.0 {
            return Err(InvalidQuery("exclude_last_seconds must be a finite number >= 0".into()));
        }
        if self.at_time.is_some_and(|t| !t.is_finite()) {
            return Err(InvalidQuery("the query time must be a finite number".into()));
        }
        if let Some((a, b)) = self.time_range {
            if a.is_nan() || b.is_nan() || a > b {
                return Err(InvalidQuery(format!("time range {a}..{b} is not an ordered pair of numbers")));
            }
        }
        if let Some((a, b)) = self.frame_id_range {
            if a > b {
                return Err(InvalidQuery(format!("frame id range {a}..{b} is empty (from > to)")));
            }
        }
        let v = &self.verify;
        if !(1..=MAX_CANDIDATES).contains(&v.candidates) {
            return Err(InvalidQuery(format!(
                "verify_candidates = {} is out of range 1..={MAX_CANDIDATES}",
                v.candidates
            )));
        }
        if !(8..=10_000).contains(&v.min_inliers) {
            return Err(InvalidQuery(format!("min_inliers = {} is out of range 8..=10000", v.min_inliers)));
        }
        if !(1..=MAX_SEQUENCE_LENGTH).contains(&v.sequence_length) {
            return Err(InvalidQuery(format!(
                "sequence_length = {} is out of range 1..={MAX_SEQUENCE_LENGTH}",
                v.sequence_length
            )));
        }
        if !v.min_sequence_margin.is_finite() {
            return Err(InvalidQuery("min_sequence_margin must be a finite number".into()));
        }
        Ok(())
    }
}

/// A 6-DoF pose: position and unit quaternion (x, y, z, qx, qy, qz, qw).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Pose {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub qx: f64,
    pub qy: f64,
    pub qz: f64,
    pub qw: f64,
}

/// A stored frame found by descriptor: its id, cosine similarity to the query, robot, time and
/// pose.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Match {
    pub frame_id: u64,
    pub score: f32,
    pub robot_id: String,
    pub timestamp: f64,
    pub pose: Option<Pose>,
}

pub const MAX_K: usize = 1000;
