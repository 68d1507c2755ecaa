//! HTTP routes of kept loops: a paged, filtered listing and a client's verdict.
use super::doc::{BadRequest, NotFound, Unauthorized, Unavailable};
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

#[derive(Deserialize, utoipa::IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct LoopParams {
    /// Loops with this robot on either side.
    robot: Option<String>,
    min_score: Option<f32>,
    /// Loops answered with at least this calibrated confidence.
    min_confidence: Option<f32>,
    verified: Option<bool>,
    /// The query frame's time, from.
    time_from: Option<f64>,
    /// The query frame's time, to.
    time_to: Option<f64>,
    /// `QUERY-MATCH`: the `next` of the previous page.
    #[param(pattern = "^[0-9]+-[0-9]+$")]
    after: Option<String>,
    /// Loops per page (default 100).
    #[param(minimum = 1, maximum = 1000)]
    limit: Option<usize>,
}

/// One page of kept loops.
#[derive(Serialize, utoipa::ToSchema)]
pub struct LoopPage {
    loops: Vec<LoopRecord>,
    /// Where the next page starts (`after=`), or null on the last page.
    next: Option<String>,
}

/// Kept loop candidates (every candidate answered for a stored frame), in frame order, paged
#[utoipa::path(
    get, path = "/v1/sessions/{id}/loops", tag = "loops",
    params(("id" = String, Path), LoopParams),
    responses(
        (status = 200, description = "One page.", body = LoopPage),
        (status = 400, response = BadRequest), (status = 401, response = Unauthorized),
        (status = 404, response = NotFound), (status = 503, response = Unavailable),
    )
)]
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

/// A client's verdict on a kept loop, optionally with its own registration.
#[derive(Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct VerdictBody {
    accepted: bool,
    relative_pose: Option<Transform>,
    /// 6x6 row-major covariance of the relative pose (x y z, then rotation).
    #[schema(min_items = 36, max_items = 36)]
    covariance: Option<Vec<f64>>,
}

/// A client's verdict on a kept loop (accept or reject), optionally with its own relative pose and covariance
#[utoipa::path(
    post, path = "/v1/sessions/{id}/loops/{query_frame}/{match_frame}/verdict", tag = "loops",
    params(("id" = String, Path), ("query_frame" = u64, Path), ("match_frame" = u64, Path)),
    request_body = VerdictBody,
    responses(
        (status = 200, description = "The loop with its verdict.", body = LoopRecord),
        (status = 400, response = BadRequest), (status = 401, response = Unauthorized),
        (status = 404, response = NotFound), (status = 503, response = Unavailable),
    )
)]
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

#[derive(Deserialize, utoipa::IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct ExportParams {
    /// Default 0.1.
    #[param(exclusive_minimum = 0, maximum = 1000000)]
    odometry_sigma_m: Option<f64>,
    /// Default 0.01.
    #[param(exclusive_minimum = 0, maximum = 1000000)]
    odometry_sigma_rad: Option<f64>,
    /// For accepted loops given without a covariance (default 0.2).
    #[param(exclusive_minimum = 0, maximum = 1000000)]
    loop_sigma_m: Option<f64>,
    /// Default 0.02.
    #[param(exclusive_minimum = 0, maximum = 1000000)]
    loop_sigma_rad: Option<f64>,
    /// Only loops a client accepted with a relative pose become edges (default false: verified
    /// metric loops no client rejected too).
    accepted_only: Option<bool>,
}

/// The session's loop graph as a tar: frames.csv, loops.csv, graph.g2o (g2o SE3:QUAT), trajectories/<robot>.tum
#[utoipa::path(
    get, path = "/v1/sessions/{id}/export", tag = "loops",
    params(("id" = String, Path), ExportParams),
    responses(
        (status = 200, description = "The tar.", body = super::doc::Binary, content_type = "application/x-tar"),
        (status = 400, response = BadRequest), (status = 401, response = Unauthorized),
        (status = 404, response = NotFound), (status = 503, response = Unavailable),
    )
)]
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
        accepted_only: p.accepted_only.unwrap_or(false),
    };
    let snapshot = s.service.scoped(caller).snapshot(&id).await?;
    // Building the tar walks every frame: off the request threads.
    let (tar, counts) = tokio::task::spawn_blocking(move || crate::export::tar(&snapshot, noise))
        .await
        .map_err(|e| ApiError::Internal(format!("export worker failed: {e}")))?
        .map_err(|e| ApiError::Internal(format!("building the export: {e}")))?;
    let name = format!("attachment; filename=\"{}.tar\"", crate::export::file_name(&id));
    Ok((
        [
            (axum::http::header::CONTENT_TYPE, "application/x-tar".to_string()),
            (axum::http::header::CONTENT_DISPOSITION, name),
            (axum::http::HeaderName::from_static("x-loopd-loop-edges"), counts.edges.to_string()),
            (axum::http::HeaderName::from_static("x-loopd-loops-left-out"), counts.summary()),
        ],
        tar,
    ))
}
