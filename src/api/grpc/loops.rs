//! The gRPC side of kept loops (ListLoops, SetLoopVerdict); the Loopd service delegates here.
use crate::api::error::ApiError;
use crate::api::service::LoopService;
use crate::api::wire::cursor;
use crate::auth::Caller;
use crate::pb;
use crate::store::loops::{LoopFilter, LoopRecord, Transform};

pub fn loop_to_pb(l: LoopRecord) -> pb::Loop {
    pb::Loop {
        query_frame: l.query_frame,
        match_frame: l.match_frame,
        query_robot: l.query_robot,
        match_robot: l.match_robot,
        query_time: l.query_time,
        match_time: l.match_time,
        score: l.score,
        rank: l.rank,
        confidence: l.confidence,
        checked: l.checked,
        verified: l.verified,
        inliers: l.inliers,
        relative_pose: l.relative_pose.map(pb::RelativePose::from),
        metric: l.metric,
        covariance: l.covariance.unwrap_or_default(),
        found: l.found,
        inlier_matches: l
            .inlier_matches
            .iter()
            .map(|m| pb::InlierMatch { query_x: m[0], query_y: m[1], match_x: m[2], match_y: m[3] })
            .collect(),
        verdict: l.verdict.map(|v| pb::LoopVerdict {
            accepted: v.accepted,
            relative_pose: v.relative_pose.map(pb::RelativePose::from),
            covariance: v.covariance.unwrap_or_default(),
            at: v.at,
        }),
    }
}

pub async fn list(
    service: &LoopService,
    caller: Caller,
    r: pb::ListLoopsRequest,
) -> Result<pb::ListLoopsResponse, ApiError> {
    let filter = LoopFilter {
        robot: Some(r.robot_id).filter(|s| !s.is_empty()),
        min_score: r.min_score,
        min_confidence: r.min_confidence,
        verified: r.verified,
        time_from: r.time_from,
        time_to: r.time_to,
        after: Some(r.after).filter(|s| !s.is_empty()).as_deref().map(cursor).transpose()?,
        limit: if r.limit == 0 { 100 } else { r.limit as usize },
    };
    let (loops, next) = service.scoped(caller).loops(&r.session_id, &filter).await?;
    Ok(pb::ListLoopsResponse {
        loops: loops.into_iter().map(loop_to_pb).collect(),
        next: next.map(|(q, m)| format!("{q}-{m}")).unwrap_or_default(),
    })
}

pub async fn set_verdict(
    service: &LoopService,
    caller: Caller,
    r: pb::SetLoopVerdictRequest,
) -> Result<pb::Loop, ApiError> {
    let pose = r.relative_pose.map(Transform::from);
    let covariance = Some(r.covariance).filter(|c| !c.is_empty());
    let pair = (r.query_frame, r.match_frame);
    let record = service.scoped(caller).set_verdict(&r.session_id, pair, r.accepted, pose, covariance).await?;
    Ok(loop_to_pb(record))
}
