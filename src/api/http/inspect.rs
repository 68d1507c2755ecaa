//! HTTP routes of the loop inspector: the page and its two assets (served without a key: they
//! hold no data), a session's frames, a frame's thumbnail and the similarity matrix.
use super::state::{parse_u64, AppState, FrameView};
use crate::api::error::ApiError;
use crate::auth::Caller;
use crate::inspect::similarity::Similarity;
use axum::extract::rejection::QueryRejection;
use axum::extract::{Path, Query, State};
use axum::http::header;
use axum::response::IntoResponse;
use axum::{Extension, Json};
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// Frames per page unless `limit` says otherwise.
const DEFAULT_FRAMES: usize = 1000;
/// Frames a similarity matrix spans unless `size` says otherwise.
const DEFAULT_SIMILARITY: usize = 256;

/// The page may only load its own script and style and talk to this server; nothing can frame
/// it (a key typed into it must not leak to another origin).
const POLICY: &str = "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' blob:; \
                      connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'";

/// Whether a path is one of the inspector's static files (no key needed).
pub fn is_static(path: &str) -> bool {
    let page = path
        .strip_prefix("/v1/sessions/")
        .and_then(|rest| rest.strip_suffix("/inspect"))
        .is_some_and(|id| !id.is_empty() && !id.contains('/'));
    page || path == "/v1/inspector/app.js" || path == "/v1/inspector/app.css"
}

fn asset(content_type: &'static str, body: &'static str) -> impl IntoResponse {
    (
        [
            (header::CONTENT_TYPE, content_type),
            (header::CONTENT_SECURITY_POLICY, POLICY),
            (header::X_CONTENT_TYPE_OPTIONS, "nosniff"),
            (header::REFERRER_POLICY, "no-referrer"),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        body,
    )
}

pub async fn page() -> impl IntoResponse {
    asset("text/html; charset=utf-8", crate::inspect::PAGE)
}

pub async fn script() -> impl IntoResponse {
    asset("text/javascript; charset=utf-8", crate::inspect::SCRIPT)
}

pub async fn style() -> impl IntoResponse {
    asset("text/css; charset=utf-8", crate::inspect::STYLE)
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FrameParams {
    /// The `next` of the previous page.
    after: Option<u64>,
    limit: Option<usize>,
}

#[derive(Serialize)]
pub struct FramePage {
    frames: Vec<FrameView>,
    /// Where the next page starts (`after=`), or null on the last page.
    next: Option<u64>,
}

pub async fn list_frames(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
    params: Result<Query<FrameParams>, QueryRejection>,
) -> Result<Json<FramePage>, ApiError> {
    let Query(p) = params.map_err(|e| ApiError::InvalidArgument(e.body_text()))?;
    let (frames, next) = s.service.scoped(caller).frames(&id, p.after, p.limit.unwrap_or(DEFAULT_FRAMES)).await?;
    Ok(Json(FramePage { frames: frames.into_iter().map(|(id, h)| FrameView::new(id, h)).collect(), next }))
}

pub async fn thumbnail(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path((id, frame_id)): Path<(String, String)>,
) -> Result<impl IntoResponse, ApiError> {
    let frame_id = parse_u64("frame_id", &frame_id)?;
    let jpeg = s.service.scoped(caller).thumbnail(&id, frame_id).await?;
    // A frame id names one picture for the session's life: a browser may keep it a while.
    Ok(([(header::CONTENT_TYPE, "image/jpeg"), (header::CACHE_CONTROL, "private, max-age=3600")], jpeg))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimilarityParams {
    size: Option<usize>,
}

pub async fn similarity(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
    params: Result<Query<SimilarityParams>, QueryRejection>,
) -> Result<Json<Similarity>, ApiError> {
    let Query(p) = params.map_err(|e| ApiError::InvalidArgument(e.body_text()))?;
    Ok(Json(s.service.scoped(caller).similarity(&id, p.size.unwrap_or(DEFAULT_SIMILARITY)).await?))
}
