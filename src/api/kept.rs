//! What is kept of the candidates answered for a stored frame: one loop record each, in answer
//! order (both the service and the listings in `loops.rs` build on these).
use crate::store::loops::LoopRecord;
use crate::verify::LoopMatch;

pub fn now() -> f64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default().as_secs_f64()
}

/// The stored frame a query was answered for.
pub struct QueryFrame<'a> {
    pub id: u64,
    pub robot: &'a str,
    pub time: f64,
}

/// The records of the candidates answered for a stored frame, in answer order.
pub fn loop_records(q: QueryFrame<'_>, matches: &[LoopMatch]) -> Vec<LoopRecord> {
    let found = now();
    matches
        .iter()
        .enumerate()
        .map(|(rank, m)| {
            let v = m.verification.as_ref();
            LoopRecord {
                query_frame: q.id,
                match_frame: m.m.frame_id,
                query_robot: q.robot.to_string(),
                match_robot: m.m.robot_id.clone(),
                query_time: q.time,
                match_time: m.m.timestamp,
                score: m.m.score,
                rank: rank as u32,
                confidence: m.confidence,
                checked: v.is_some(),
                verified: v.is_some_and(|v| v.verified),
                inliers: v.map_or(0, |v| v.inliers as u32),
                relative_pose: v.and_then(|v| v.relative_pose.as_ref()).copied(),
                metric: v.is_some_and(|v| v.metric),
                covariance: v.and_then(|v| v.covariance.clone()),
                inlier_matches: v.map_or_else(Vec::new, |v| v.inlier_matches.clone()),
                found,
                verdict: None,
            }
        })
        .collect()
}
