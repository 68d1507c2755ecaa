//! HTTP routes of the loop inspector: the page and its two assets (served without a key: they
//! hold no data), a session's frames, a frame's thumbnail and the similarity matrix.
use super::doc::{BadRequest, NotFound, Overloaded, Unauthorized, Unavailable};
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

/// The loop inspector page (static; it asks for a key and reads the session through the routes here)
#[utoipa::path(
    get, path = "/v1/sessions/{id}/inspect", tag = "inspector", security(()),
    params(("id" = String, Path)),
    responses((status = 200, description = "The page.", body = String, content_type = "text/html"))
)]
pub async fn page() -> impl IntoResponse {
    asset("text/html; charset=utf-8", crate::inspect::PAGE)
}

/// The inspector page's script
#[utoipa::path(
    get, path = "/v1/inspector/app.js", tag = "inspector", security(()),
    responses((status = 200, description = "The script.", body = String, content_type = "text/javascript"))
)]
pub async fn script() -> impl IntoResponse {
    asset("text/javascript; charset=utf-8", crate::inspect::SCRIPT)
}

/// The inspector page's style
#[utoipa::path(
    get, path = "/v1/inspector/app.css", tag = "inspector", security(()),
    responses((status = 200, description = "The style.", body = String, content_type = "text/css"))
)]
pub async fn style() -> impl IntoResponse {
    asset("text/css; charset=utf-8", crate::inspect::STYLE)
}

#[derive(Deserialize, utoipa::IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct FrameParams {
    /// The `next` of the previous page.
    after: Option<u64>,
    /// Frames per page (default 1000).
    #[param(minimum = 1, maximum = 10000)]
    limit: Option<usize>,
}

/// One page of a session's frames.
#[derive(Serialize, utoipa::ToSchema)]
pub struct FramePage {
    frames: Vec<FrameView>,
    /// Where the next page starts (`after=`), or null on the last page.
    next: Option<u64>,
}

/// The session's frames in id order, paged
#[utoipa::path(
    get, path = "/v1/sessions/{id}/frames", tag = "frames",
    params(("id" = String, Path), FrameParams),
    responses(
        (status = 200, description = "One page.", body = FramePage),
        (status = 400, response = BadRequest), (status = 401, response = Unauthorized),
        (status = 404, response = NotFound), (status = 503, response = Unavailable),
    )
)]
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

/// A frame's thumbnail (sessions created with `thumbnails`; at most 160 px on the long side)
#[utoipa::path(
    get, path = "/v1/sessions/{id}/frames/{frame_id}/thumbnail", tag = "inspector",
    params(("id" = String, Path), ("frame_id" = u64, Path)),
    responses(
        (status = 200, description = "The JPEG.", body = super::doc::Binary, content_type = "image/jpeg"),
        (status = 400, response = BadRequest), (status = 401, response = Unauthorized),
        (status = 404, response = NotFound), (status = 503, response = Unavailable),
    )
)]
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

#[derive(Deserialize, utoipa::IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct SimilarityParams {
    /// Frames the matrix spans (default 256).
    #[param(minimum = 1, maximum = 1024)]
    size: Option<usize>,
}

/// Cosine similarity of up to `size` frames taken evenly along the frame ids (the inspector's matrix)
#[utoipa::path(
    get, path = "/v1/sessions/{id}/similarity", tag = "inspector",
    params(("id" = String, Path), SimilarityParams),
    responses(
        (status = 200, description = "The matrix.", body = Similarity),
        (status = 400, response = BadRequest), (status = 401, response = Unauthorized),
        (status = 404, response = NotFound), (status = 429, response = Overloaded),
        (status = 503, response = Unavailable),
    )
)]
pub async fn similarity(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
    params: Result<Query<SimilarityParams>, QueryRejection>,
) -> Result<Json<Similarity>, ApiError> {
    let Query(p) = params.map_err(|e| ApiError::InvalidArgument(e.body_text()))?;
    Ok(Json(s.service.scoped(caller).similarity(&id, p.size.unwrap_or(DEFAULT_SIMILARITY)).await?))
}
