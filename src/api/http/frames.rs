//! HTTP routes of frames and queries: add a frame, read one back, query, and add-and-query (one
//! round trip per keyframe).
use super::doc::{
    BadRequest, Binary, Conflict, FrameForm, NotFound, Overloaded, RawFrameFields, TooLarge, Unauthorized, Unavailable,
};
use super::form::{content, frame_input, read_fields, FrameFields};
use super::state::{parse_u64, AppState, FrameView};
use crate::api::error::ApiError;
use crate::api::service::QueryTarget;
use crate::auth::Caller;
use crate::verify::LoopMatch;
use axum::extract::{Path, Request, State};
use axum::http::StatusCode;
use axum::{Extension, Json};
use serde::Serialize;
use std::sync::Arc;

#[derive(Serialize, utoipa::ToSchema)]
pub struct AddFrameResponse {
    frame_id: u64,
}

/// Add a frame; acknowledged once durable
#[utoipa::path(
    post, path = "/v1/sessions/{id}/frames", tag = "frames",
    params(("id" = String, Path), RawFrameFields),
    request_body(content(
        (FrameFields = "application/json"), (FrameForm = "multipart/form-data"), (Binary = "application/octet-stream"),
    )),
    responses(
        (status = 201, description = "Stored.", body = AddFrameResponse),
        (status = 400, response = BadRequest), (status = 401, response = Unauthorized),
        (status = 404, response = NotFound), (status = 409, response = Conflict),
        (status = 413, response = TooLarge), (status = 429, response = Overloaded),
        (status = 503, response = Unavailable),
    )
)]
pub async fn add_frame(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
    req: Request,
) -> Result<(StatusCode, Json<AddFrameResponse>), ApiError> {
    let (f, _) = frame_input(read_fields(req).await?)?;
    Ok((StatusCode::CREATED, Json(AddFrameResponse { frame_id: s.service.scoped(caller).add_frame(&id, f).await? })))
}

/// A stored frame's record
#[utoipa::path(
    get, path = "/v1/sessions/{id}/frames/{frame_id}", tag = "frames",
    params(("id" = String, Path), ("frame_id" = u64, Path)),
    responses(
        (status = 200, description = "The frame.", body = FrameView),
        (status = 400, response = BadRequest), (status = 401, response = Unauthorized),
        (status = 404, response = NotFound), (status = 503, response = Unavailable),
    )
)]
pub async fn get_frame(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path((id, frame_id)): Path<(String, String)>,
) -> Result<Json<FrameView>, ApiError> {
    let frame_id = parse_u64("frame_id", &frame_id)?;
    Ok(Json(FrameView::new(frame_id, s.service.scoped(caller).frame(&id, frame_id).await?)))
}

/// Ranked matches, best first.
#[derive(Serialize, utoipa::ToSchema)]
pub struct QueryResponse {
    matches: Vec<LoopMatch>,
}

/// Loop candidates for an image, a descriptor or a stored frame (stores nothing)
///
/// A cluster node (serve --cluster) that could not read the session's version from the database
/// (no writable primary) answers from its own index and sets `X-Loopd-Stale: 1` (gRPC:
/// loopd-stale metadata): the frames acknowledged last may be missing.
#[utoipa::path(
    post, path = "/v1/sessions/{id}/query", tag = "frames",
    params(("id" = String, Path), RawFrameFields),
    request_body(content(
        (FrameFields = "application/json"), (FrameForm = "multipart/form-data"), (Binary = "application/octet-stream"),
    )),
    responses(
        (status = 200, description = "Ranked matches, best first.", body = QueryResponse,
         headers(("X-Loopd-Stale" = String, description = "1: answered from this node's index alone"))),
        (status = 400, response = BadRequest), (status = 401, response = Unauthorized),
        (status = 404, response = NotFound), (status = 409, response = Conflict),
        (status = 413, response = TooLarge), (status = 429, response = Overloaded),
        (status = 503, response = Unavailable),
    )
)]
pub async fn query(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
    req: Request,
) -> Result<Json<QueryResponse>, ApiError> {
    let mut f = read_fields(req).await?;
    let target = match f.frame_id {
        Some(frame) if f.image.is_none() && f.descriptor.is_none() => QueryTarget::Frame(frame),
        _ => QueryTarget::Content(content(&mut f)?),
    };
    let opts = f.options.unwrap_or_default();
    Ok(Json(QueryResponse {
        matches: s.service.scoped(caller).query(&id, f.robot_id, f.timestamp, target, &opts).await?,
    }))
}

/// The new frame's id and its loop candidates.
#[derive(Serialize, utoipa::ToSchema)]
pub struct AddAndQueryResponse {
    frame_id: u64,
    matches: Vec<LoopMatch>,
}

/// Query with a new frame, then store it (one round trip per keyframe)
#[utoipa::path(
    post, path = "/v1/sessions/{id}/add_and_query", tag = "frames",
    params(("id" = String, Path), RawFrameFields),
    request_body(content(
        (FrameFields = "application/json"), (FrameForm = "multipart/form-data"), (Binary = "application/octet-stream"),
    )),
    responses(
        (status = 200, description = "The new frame's id and its loop candidates.", body = AddAndQueryResponse),
        (status = 400, response = BadRequest), (status = 401, response = Unauthorized),
        (status = 404, response = NotFound), (status = 409, response = Conflict),
        (status = 413, response = TooLarge), (status = 429, response = Overloaded),
        (status = 503, response = Unavailable),
    )
)]
pub async fn add_and_query(
    State(s): State<Arc<AppState>>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
    req: Request,
) -> Result<Json<AddAndQueryResponse>, ApiError> {
    let (f, opts) = frame_input(read_fields(req).await?)?;
    let (frame_id, matches) = s.service.scoped(caller).add_and_query(&id, f, &opts).await?;
    Ok(Json(AddAndQueryResponse { frame_id, matches }))
}
