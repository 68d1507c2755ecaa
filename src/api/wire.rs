//! What the transports and the clients read alike, below both transports (neither imports the
//! other): the loop cursor, and a sequence job's limits and status as the HTTP API writes them
//! and `loopd ingest` reads them back.
use super::error::ApiError;
use serde::{Deserialize, Serialize};

/// Most frames one job may hold (bounded memory); the body size limit applies as well.
pub const MAX_JOB_FRAMES: usize = 100_000;

/// Most bytes of a decompressed ROS 1 bag chunk (rosbag records 768 KiB chunks).
pub const MAX_BAG_CHUNK_BYTES: usize = 256 << 20;

/// A loop a sequence job found: the frame and its best candidate, by place in the sequence, name
/// and frame id.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
pub struct LoopClosure {
    pub query_index: usize,
    pub query_name: String,
    pub query_frame_id: u64,
    pub match_index: usize,
    pub match_name: String,
    pub match_frame_id: u64,
    /// Cosine similarity of the descriptors.
    pub score: f32,
    /// The calibrated confidence (absent without a calibrator for the session's descriptors).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub confidence: Option<f32>,
    /// Geometric verification passed, with these inliers.
    #[serde(default)]
    pub verified: bool,
    #[serde(default)]
    pub inliers: u32,
    /// The sequence check's margin, when it ran.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sequence_margin: Option<f32>,
}

/// Jobs are kept and answer after a restart; one that was running when the server stopped is
/// `interrupted`.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum JobState {
    Running,
    Done,
    Failed,
    /// The server stopped while the job ran: its first `done` frames are in the session and its
    /// loops so far are kept; the images are not, so a client restarts it by sending them again.
    Interrupted,
}

/// A sequence job's progress and the loops found so far.
#[derive(Clone, Debug, Serialize, Deserialize, utoipa::ToSchema)]
pub struct JobStatus {
    pub job_id: String,
    pub session_id: String,
    pub state: JobState,
    pub total: usize,
    pub done: usize,
    pub loops: Vec<LoopClosure>,
    /// Frames that could not be used (bad image), by name.
    pub errors: Vec<String>,
}

/// A loop listing's cursor (`after=`, gRPC's `after`): QUERY-MATCH frame ids of the last loop of
/// the previous page.
pub fn cursor(s: &str) -> Result<(u64, u64), ApiError> {
    s.split_once('-')
        .and_then(|(q, m)| Some((q.parse().ok()?, m.parse().ok()?)))
        .ok_or_else(|| ApiError::InvalidArgument(format!("after must be QUERY-MATCH frame ids, got '{s}'")))
}
