//! `loopd eval --server`: the protocol run against a live server's session over gRPC (the one
//! client of `crate::client`, with the tenant's key and TLS), so the numbers come from the very
//! engine and index that serve the robots.
//!
//! The session's frames must be one sequence with frame ids 0..n-1 in order (what the offline
//! sequence job and a single robot with server-assigned ids produce); ground-truth indices refer
//! to that order.
use super::gt::GroundTruth;
use super::metrics::{evaluate, evaluate_confidence, ConfidenceReport, QueryResult, Report};
use crate::client::Grpc;
use crate::pb;
use anyhow::{bail, Context, Result};

pub async fn evaluate_session(
    client: &mut Grpc,
    session: &str,
    gt: &str,
    camera: Option<usize>,
    tolerance: usize,
    exclude: usize,
) -> Result<(usize, Report, Option<ConfidenceReport>)> {
    let info = client.get_session(pb::GetSessionRequest { id: session.into() }).await?.into_inner();
    let n = info.frames as usize;
    if n == 0 {
        bail!("session '{session}' has no frames");
    }
    let gt = GroundTruth::load(gt, camera, n)?;
    let bar = indicatif::ProgressBar::new(n as u64);
    let mut results = Vec::with_capacity(n);
    // The server's calibrated confidence of each first candidate, when it gives one.
    let mut confident = Vec::with_capacity(n);
    let mut scored = Vec::new();
    // Each answer scored by the decision rule the server ranked them by, as `eval` scores its own.
    let ranked = |m: &pb::Match| {
        let verified = m.verification.as_ref().filter(|v| v.verified).map(|v| v.inliers as usize);
        crate::verify::rank_value(m.score, verified, m.sequence.as_ref().map(|s| s.margin))
    };
    for i in 0..n {
        bar.inc(1);
        if i <= exclude {
            results.push(QueryResult { query: i, best: None });
            confident.push(QueryResult { query: i, best: None });
            continue;
        }
        let options = pb::QueryOptions {
            k: Some(1),
            frame_id_from: Some(0),
            frame_id_to: Some((i - exclude - 1) as u64),
            scope: pb::Scope::All as i32,
            ..Default::default()
        };
        let req = pb::QueryRequest {
            session_id: session.into(),
            content: Some(pb::query_request::Content::FrameId(i as u64)),
            options: Some(options),
            ..Default::default()
        };
        let m = client
            .query(req)
            .await
            .with_context(|| format!("querying frame {i} (frame ids must be 0..{n})"))?
            .into_inner()
            .matches;
        results.push(QueryResult { query: i, best: m.first().map(|m| (m.frame_id as usize, ranked(m))) });
        let first = m.first().and_then(|m| m.confidence.map(|c| (m.frame_id as usize, c)));
        if let Some((frame, c)) = first {
            scored.push((c, gt.is_match(i, frame, tolerance)));
        }
        confident.push(QueryResult { query: i, best: first });
    }
    bar.finish_and_clear();
    let confidence = (!scored.is_empty()).then(|| evaluate_confidence(&confident, &gt, tolerance, &scored, None));
    Ok((n, evaluate(&results, &gt, tolerance), confidence))
}
