//! HTTP routes of kept loops: a paged, filtered listing and a client's verdict.
use super::state::{json_error, parse_u64, AppState};
use crate::api::error::ApiError;
use crate::api::wire::cursor;
use crate::auth::Caller;
use crate::store::loops::{LoopFilter, LoopRecord, Transform};
use axum::extract::rejection::{JsonRejection, QueryRejection};
use axum::extract::{Path, Query, State};
use axum::{Extension, Json};
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// Loops per page unless `limit` says otherwise.
const DEFAULT_PAGE: usize = 100;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LoopParams {
    robot: Option<String>,
    min_score: Option<f32>,
    min_confidence: Option<f32>,
    verified: Option<bool>,
    time_from: Option<f64>,
    time_to: Option<f64>,
    /// `QUERY-MATCH`: the `next` of the previous page.
    after: Option<String>,
    limit: Option<usize>,
}

#[derive(Serialize)]
pub struct LoopPage {
    loops: Vec<LoopRecord>,
    /// Where the next page starts (`after=`), or null on the last page.
    next: Option<String>,
}

pub async fn list_loops(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
    params: Result<Query<LoopParams>, QueryRejection>,
) -> Result<Json<LoopPage>, ApiError> {
    let Query(p) = params.map_err(|e| ApiError::InvalidArgument(e.body_text()))?;
    let filter = LoopFilter {
        robot: p.robot,
        min_score: p.min_score,
        min_confidence: p.min_confidence,
        verified: p.verified,
        time_from: p.time_from,
        time_to: p.time_to,
        after: p.after.as_deref().map(cursor).transpose()?,
        limit: p.limit.unwrap_or(DEFAULT_PAGE),
    };
    let (loops, next) = s.service.scoped(caller).loops(&id, &filter).await?;
    Ok(Json(LoopPage { loops, next: next.map(|(q, m)| format!("{q}-{m}")) }))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VerdictBody {
    accepted: bool,
    relative_pose: Option<Transform>,
    covariance: Option<Vec<f64>>,
}

pub async fn set_verdict(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path((id, query, matched)): Path<(String, String, String)>,
    body: Result<Json<VerdictBody>, JsonRejection>,
) -> Result<Json<LoopRecord>, ApiError> {
    let pair = (parse_u64("query_frame", &query)?, parse_u64("match_frame", &matched)?);
    let Json(v) = body.map_err(json_error)?;
    let scoped = s.service.scoped(caller);
    Ok(Json(scoped.set_verdict(&id, pair, v.accepted, v.relative_pose, v.covariance).await?))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExportParams {
    odometry_sigma_m: Option<f64>,
    odometry_sigma_rad: Option<f64>,
    loop_sigma_m: Option<f64>,
    loop_sigma_rad: Option<f64>,
}

/// The session's loop graph as a tar (frames.csv, loops.csv, graph.g2o, one TUM file per robot).
pub async fn export(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
    params: Result<Query<ExportParams>, QueryRejection>,
) -> Result<impl axum::response::IntoResponse, ApiError> {
    let Query(p) = params.map_err(|e| ApiError::InvalidArgument(e.body_text()))?;
    let d = crate::export::Noise::default();
    let sigma = |name: &str, v: Option<f64>, default: f64| match v {
        None => Ok(default),
        Some(x) if x.is_finite() && x > 0.0 && x <= 1e6 => Ok(x),
        Some(x) => Err(ApiError::InvalidArgument(format!("{name} must be in (0, 1e6], got {x}"))),
    };
    let noise = crate::export::Noise {
        odometry_m: sigma("odometry_sigma_m", p.odometry_sigma_m, d.odometry_m)?,
        odometry_rad: sigma("odometry_sigma_rad", p.odometry_sigma_rad, d.odometry_rad)?,
        loop_m: sigma("loop_sigma_m", p.loop_sigma_m, d.loop_m)?,
        loop_rad: sigma("loop_sigma_rad", p.loop_sigma_rad, d.loop_rad)?,
    };
    let snapshot = s.service.scoped(caller).snapshot(&id).await?;
    // Building the tar walks every frame: off the request threads.
    let tar = tokio::task::spawn_blocking(move || crate::export::tar(&snapshot, noise))
        .await
        .map_err(|e| ApiError::Internal(format!("export worker failed: {e}")))?
        .map_err(|e| ApiError::Internal(format!("building the export: {e}")))?;
    let name = format!("attachment; filename=\"{}.tar\"", crate::export::file_name(&id));
    Ok((
        [
            (axum::http::header::CONTENT_TYPE, "application/x-tar".to_string()),
            (axum::http::header::CONTENT_DISPOSITION, name),
        ],
        tar,
    ))
}
